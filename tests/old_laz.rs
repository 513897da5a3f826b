//! LAZ files of LASzip's pointwise compressor (compressor 1: LASzip 1.x, early LAStools; one
//! arithmetic stream, no chunk table) and LAZ files whose chunks are larger than one piece are
//! read by every command, point for point as their uncompressed twins; truncated and lying
//! ones are refused cleanly (issue 26, item 1: they were refused as "truncated").

mod common;
use common::*;
use std::path::{Path, PathBuf};
use std::time::Duration;

const POINTWISE: &str = "PDAL/test/data/apps/simple-laszip-compressor-version-1.2r0.laz";
const TWIN: &str = "PDAL/test/data/apps/simple.las";

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `mortar sort IN -o OUT` (LAS), the bytes of OUT.
fn sorted(input: &Path, out: &Path) -> Vec<u8> {
    run_ok(mortar().args(["sort", s(input), "-o", s(out)]));
    std::fs::read(out).unwrap()
}

/// The file at `src` with `patch` applied, in `dir`.
fn patched(src: &Path, dir: &Path, name: &str, patch: impl Fn(&mut Vec<u8>)) -> PathBuf {
    let mut b = std::fs::read(src).unwrap();
    patch(&mut b);
    let p = dir.join(name);
    std::fs::write(&p, b).unwrap();
    p
}

fn offset_to_points(b: &[u8]) -> usize {
    u32::from_le_bytes(b[96..100].try_into().unwrap()) as usize
}

/// Where the LASzip VLR's data begins (the first VLR of the fixture).
fn laszip_vlr_data(b: &[u8]) -> usize {
    let header = u16::from_le_bytes(b[94..96].try_into().unwrap()) as usize;
    assert_eq!(
        u16::from_le_bytes(b[header + 18..header + 20].try_into().unwrap()),
        22204,
        "the fixture's first VLR is LASzip's"
    );
    header + 54
}

#[test]
fn pointwise_laz_reads_as_its_uncompressed_twin_in_every_command() {
    let Some(data) = shared_data() else { return };
    let pw = data.join(POINTWISE);
    let dir = tempdir("pointwise");
    // the compressor really is 1, and the first 8 bytes of the point data are no offset
    let b = std::fs::read(&pw).unwrap();
    let v = laszip_vlr_data(&b);
    assert_eq!(u16::from_le_bytes(b[v..v + 2].try_into().unwrap()), 1);
    let want = sorted(&data.join(TWIN), &dir.join("twin.las"));
    assert_eq!(
        sorted(&pw, &dir.join("pw.las")),
        want,
        "the pointwise file sorts to its twin's bytes"
    );
    // a chunk size of u32::MAX in the VLR (laz-rs takes it for variable-size chunks and panics)
    let max = patched(&pw, &dir, "chunk-max.laz", |b| {
        b[v + 12..v + 16].copy_from_slice(&u32::MAX.to_le_bytes())
    });
    assert_eq!(sorted(&max, &dir.join("max.las")), want);
    let j: serde_json::Value = serde_json::from_slice(
        &run_ok(mortar().args(["info", "--json", "--stats", s(&pw)])).stdout,
    )
    .unwrap();
    assert_eq!(j[0]["point_count"].as_u64(), Some(1065), "{j}");
    assert_eq!(j[0]["stats"]["point_count"].as_u64(), Some(1065), "{j}");
    // the other commands: batch, store, exports, render; every record back from batch and store
    let mbat = dir.join("pw.mbat");
    run_ok(mortar().args(["batch", s(&pw), "-o", s(&mbat)]));
    assert_eq!(sorted(&mbat, &dir.join("from-mbat.las")), want);
    let store = dir.join("store");
    run_ok(mortar().args(["build", s(&pw), "-o", s(&store), "--leaf-capacity", "200"]));
    assert_eq!(sorted(&store, &dir.join("from-store.las")), want);
    run_ok(mortar().args(["export", s(&pw), "-o", s(&dir.join("pw.copc.laz"))]));
    run_ok(mortar().args(["render", s(&pw), "-o", s(&dir.join("pw.png")), "--backend", "cpu"]));
    // and someone else's reader reads the LAZ mortar writes from it
    let laz = dir.join("pw-sorted.laz");
    run_ok(mortar().args(["sort", s(&pw), "-o", s(&laz)]));
    if let Some(py) = laspy_python() {
        let o = run_ok(std::process::Command::new(py).args(["-c", "import laspy,sys; f=laspy.read(sys.argv[1]); print(len(f.points), int(f.header.point_count))", s(&laz)]));
        assert_eq!(String::from_utf8_lossy(&o.stdout).trim(), "1065 1065");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

fn expect_refusal(args: &[&str], file: &Path, says: &str) {
    let mut c = mortar();
    c.args(args);
    let o = run_limited(c, Duration::from_secs(30));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{args:?}: {err}");
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(err.contains(&*file.file_name().unwrap().to_string_lossy()), "{err}");
    assert!(err.contains(says), "{args:?} should say {says:?}: {err}");
}

#[test]
fn truncated_and_lying_pointwise_files_are_refused_cleanly() {
    let Some(data) = shared_data() else { return };
    let pw = data.join(POINTWISE);
    let dir = tempdir("pointwise-bad");
    let b = std::fs::read(&pw).unwrap();
    let start = offset_to_points(&b);
    let cut = patched(&pw, &dir, "cut.laz", |b| b.truncate(start + (b.len() - start) / 2));
    let more =
        patched(&pw, &dir, "more.laz", |b| b[107..111].copy_from_slice(&1200u32.to_le_bytes()));
    let huge = patched(&pw, &dir, "huge.laz", |b| {
        b[107..111].copy_from_slice(&4_000_000_000u32.to_le_bytes())
    });
    let out = dir.join("out.las");
    expect_refusal(&["sort", s(&cut), "-o", s(&out)], &cut, "ends early");
    expect_refusal(&["sort", s(&more), "-o", s(&out)], &more, "ends early");
    expect_refusal(&["info", "--stats", s(&huge)], &huge, "implausible");
    assert!(!out.exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn one_laz_chunk_of_more_than_a_piece_reads_as_its_las_twin() {
    let dir = tempdir("big-chunk");
    let (las, laz) = (dir.join("twin.las"), dir.join("one-chunk.laz"));
    run_ok(gen().args(["--points", "1100000", "--seed", "5", "-o", s(&las)]));
    run_ok(gen().args([
        "--points",
        "1100000",
        "--seed",
        "5",
        "--laz-chunk",
        "1100000",
        "-o",
        s(&laz),
    ]));
    let want = sorted(&las, &dir.join("a.las"));
    assert_eq!(sorted(&laz, &dir.join("b.las")), want);
    let store = dir.join("store");
    run_ok(mortar().args(["build", s(&laz), "-o", s(&store)]));
    assert_eq!(sorted(&store, &dir.join("c.las")), want);
    std::fs::remove_dir_all(&dir).unwrap();
}
