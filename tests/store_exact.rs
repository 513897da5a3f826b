//! Issue 12, items 1 and 2: `sort store/` gives the bytes of `sort input` after merges, Morton
//! shifts, shuffled input and splits, at every thread count; and a build takes inputs whose
//! headers declare narrower bounds than their points (the octree grows a new root above the old
//! one) with a warning, still exact.

mod common;

use common::*;
use std::path::{Path, PathBuf};

fn sample() -> PathBuf {
    root().join("data-samples/autzen_trim.laz")
}

/// The sample as uncompressed LAS (sorted), for byte surgery.
fn sample_las(dir: &Path) -> PathBuf {
    let p = dir.join("sample.las");
    run_ok(mortar().arg("sort").arg(sample()).arg("-o").arg(&p));
    p
}

fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

fn set_f64(b: &mut [u8], at: usize, v: f64) {
    b[at..at + 8].copy_from_slice(&v.to_le_bytes());
}

/// A copy of a LAS file moved by `dx` metres in x: only the header's offset and bounds change.
fn moved_copy(src: &Path, dst: &Path, dx: f64) {
    let mut b = std::fs::read(src).unwrap();
    // X offset at 155, max X at 179, min X at 187.
    for at in [155, 179, 187] {
        let v = f64_at(&b, at);
        set_f64(&mut b, at, v + dx);
    }
    std::fs::write(dst, &b).unwrap();
}

/// A copy of a LAS file with its records in a seeded random order.
fn shuffled_copy(src: &Path, dst: &Path, seed: u64) {
    let b = std::fs::read(src).unwrap();
    let start = u32::from_le_bytes(b[96..100].try_into().unwrap()) as usize;
    let rl = u16::from_le_bytes(b[105..107].try_into().unwrap()) as usize;
    let n = u32::from_le_bytes(b[107..111].try_into().unwrap()) as usize;
    let mut idx: Vec<usize> = (0..n).collect();
    let mut s = seed | 1;
    for i in (1..n).rev() {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        idx.swap(i, (s % (i as u64 + 1)) as usize);
    }
    let mut out = b[..start].to_vec();
    for i in idx {
        out.extend_from_slice(&b[start + i * rl..start + (i + 1) * rl]);
    }
    out.extend_from_slice(&b[start + n * rl..]);
    std::fs::write(dst, &out).unwrap();
}

/// Builds `inputs` with `extra` arguments and asserts that sorting the store gives the bytes of
/// sorting the inputs. Returns the build's JSON report and stderr.
fn assert_exact(inputs: &[&Path], extra: &[&str], dir: &Path) -> (serde_json::Value, String) {
    let store = dir.join("store");
    let _ = std::fs::remove_dir_all(&store);
    let mut c = mortar();
    c.arg("build").args(inputs).arg("-o").arg(&store).arg("--json").args(extra);
    let o = run_ok(&mut c);
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).expect("JSON");
    run_ok(mortar().arg("sort").arg(&store).arg("-o").arg(dir.join("a.las")));
    run_ok(mortar().arg("sort").args(inputs).arg("-o").arg(dir.join("b.las")));
    let a = std::fs::read(dir.join("a.las")).unwrap();
    let b = std::fs::read(dir.join("b.las")).unwrap();
    assert!(a.len() == b.len(), "{inputs:?} {extra:?}: sizes differ ({} vs {})", a.len(), b.len());
    if let Some(at) = a.iter().zip(&b).position(|(x, y)| x != y) {
        panic!("{inputs:?} {extra:?}: sorting the store differs from sorting the input at byte {at} of {}", a.len());
    }
    (j, String::from_utf8_lossy(&o.stderr).into_owned())
}

/// Two tiles 300 km apart: the merged extent needs a Morton shift (points a few grid units apart
/// share a code), and the store's leaves split those ties apart.
#[test]
fn store_round_trip_is_exact_after_a_merge_that_needs_a_shift() {
    let dir = tempdir("exact-merge");
    let a = sample_las(&dir);
    let b = dir.join("moved.las");
    moved_copy(&a, &b, 300_000.0);
    let o = run_ok(mortar().arg("info").arg(&a).arg(&b).arg("--json"));
    let _: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    for threads in ["1", "2"] {
        let (j, _) = assert_exact(
            &[&a, &b],
            &[
                "--leaf-capacity",
                "500",
                "--batch-points",
                "20000",
                "--commit-every",
                "0",
                "--threads",
                threads,
            ],
            &dir,
        );
        assert_eq!(j["points"], 220_000);
        assert!(j["leaves"].as_u64().unwrap() > 400, "{j}");
    }
    // The other input order is another dataset, exact too.
    assert_exact(&[&b, &a], &["--leaf-capacity", "2000"], &dir);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A shuffled file: ties between duplicate positions keep input order in the leaves.
#[test]
fn store_round_trip_is_exact_on_shuffled_input() {
    let dir = tempdir("exact-shuffle");
    let a = sample_las(&dir);
    let s = dir.join("shuffled.las");
    shuffled_copy(&a, &s, 7);
    for threads in ["1", "2"] {
        assert_exact(
            &[&s],
            &[
                "--leaf-capacity",
                "300",
                "--batch-points",
                "9000",
                "--commit-every",
                "0",
                "--threads",
                threads,
            ],
            &dir,
        );
    }
    // Shuffled and moved far away: shift and shuffle together, merged with the original.
    let m = dir.join("moved-shuffled.las");
    moved_copy(&s, &m, 1_000_000.0);
    assert_exact(&[&m, &a], &["--leaf-capacity", "700", "--batch-points", "30000"], &dir);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Real tiles merged (bcts: four adjacent strips), small leaves, exact.
#[test]
fn store_round_trip_is_exact_on_merged_real_tiles() {
    let Some(data) = shared_data() else { return };
    let d = data.join("lasR/inst/extdata/bcts");
    let mut tiles: Vec<PathBuf> = std::fs::read_dir(&d)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "laz"))
        .collect();
    tiles.sort();
    assert!(tiles.len() >= 2, "bcts tiles missing");
    let dir = tempdir("exact-bcts");
    let refs: Vec<&Path> = tiles.iter().take(2).map(|p| p.as_path()).collect();
    assert_exact(&refs, &["--leaf-capacity", "20000"], &dir);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Headers that lie: the z range a few metres short (common in older files), the x range far
/// too narrow on one side, and bounds that are all zero. The build grows the octree's root (a new
/// root above the old one) instead of refusing the file, warns with the points' real range, and
/// the store gives back every record exactly.
#[test]
fn a_header_narrower_than_its_points_grows_the_root() {
    let dir = tempdir("exact-grow");
    let a = sample_las(&dir);
    type Lie = Box<dyn Fn(&mut Vec<u8>)>;
    let cases: Vec<(&str, Lie)> = vec![
        // max Z (211) lowered by 5 m, min Z (219) raised by 3 m
        (
            "z-short.las",
            Box::new(|b: &mut Vec<u8>| {
                let (hi, lo) = (f64_at(b, 211), f64_at(b, 219));
                set_f64(b, 211, hi - 5.0);
                set_f64(b, 219, lo + 3.0);
            }),
        ),
        // max X (179) := min X (187) + 1 m: every point but a few lies outside
        (
            "x-narrow.las",
            Box::new(|b: &mut Vec<u8>| {
                let lo = f64_at(b, 187);
                set_f64(b, 179, lo + 1.0);
            }),
        ),
        // min X := max X - 1 m: the root must grow downwards
        (
            "x-narrow-low.las",
            Box::new(|b: &mut Vec<u8>| {
                let hi = f64_at(b, 179);
                set_f64(b, 187, hi - 1.0);
            }),
        ),
        // all bounds zero
        (
            "zero.las",
            Box::new(|b: &mut Vec<u8>| {
                for at in (179..227).step_by(8) {
                    set_f64(b, at, 0.0);
                }
            }),
        ),
    ];
    for (name, lie) in &cases {
        let mut b = std::fs::read(&a).unwrap();
        lie(&mut b);
        let p = dir.join(name);
        std::fs::write(&p, &b).unwrap();
        // The sorted engine places the root from the points; the incremental one grows it.
        let (j, err) =
            assert_exact(&[&p], &["--leaf-capacity", "2000", "--engine", "sorted"], &dir);
        assert_eq!(j["points"], 110_000, "{name}");
        assert!(
            err.contains(name) && err.contains("outside the bounds its header declares"),
            "{name}: {err}"
        );
        let (j, err) = assert_exact(
            &[&p],
            &[
                "--leaf-capacity",
                "2000",
                "--batch-points",
                "10000",
                "--commit-every",
                "0",
                "--engine",
                "incremental",
            ],
            &dir,
        );
        assert_eq!(j["points"], 110_000, "{name}");
        assert!(
            err.contains(name)
                && err.contains("outside the bounds its header declares")
                && err.contains("root holds them"),
            "{name}: {err}"
        );
        assert!(
            j["warnings"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().contains(name)),
            "{name}: {j}"
        );
        // The warning reports the whole range of the file's points, not a partial one.
        let o = run_ok(mortar().arg("info").arg(&a).arg("--json"));
        let info: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let min_x = info[0]["header_bounds"]["min"][0].as_f64().unwrap();
        let max_x = info[0]["header_bounds"]["max"][0].as_f64().unwrap();
        assert!(
            err.contains(&format!("x [{min_x:.2}, {max_x:.2}]")),
            "{name}: {err} (x {min_x}..{max_x})"
        );
    }
    // Merged after an honest tile: the root is placed from the first file and grows when the
    // lying file's points arrive, after commits that saved the inner root's voxels (so the
    // grown root's voxels get their records back from the store).
    let moved = dir.join("moved.las");
    moved_copy(&a, &moved, 5_000.0);
    for lie in ["x-narrow-low.las", "zero.las"] {
        let lie = dir.join(lie);
        for inputs in [[&moved, &lie], [&lie, &moved]] {
            let (j, _) = assert_exact(
                &[inputs[0].as_path(), inputs[1].as_path()],
                &[
                    "--leaf-capacity",
                    "3000",
                    "--batch-points",
                    "20000",
                    "--commit-every",
                    "0",
                    "--engine",
                    "incremental",
                ],
                &dir,
            );
            assert!(j["root_growths"].as_u64().unwrap() > 0, "{inputs:?}: {j}");
            assert_eq!(j["points"], 220_000);
            let (j, _) = assert_exact(
                &[inputs[0].as_path(), inputs[1].as_path()],
                &["--leaf-capacity", "3000"],
                &dir,
            );
            assert_eq!(j["engine"], "sorted");
            assert_eq!(j["points"], 220_000);
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
