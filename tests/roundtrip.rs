//! Every readable fixture survives `sort` and `batch` round trips exactly: the same multiset of
//! records (checked with the las crate, independently of mortar's reader), Morton codes
//! non-decreasing, and `batch` then `sort` giving back the bytes `sort` gives.

mod common;
use common::*;
use mortar_core::layout::read_xyz;
use mortar_core::morton::MortonGrid;
use std::path::Path;

fn morton_sorted(bytes: &[u8], rl: usize) -> bool {
    let pts: Vec<[i32; 3]> = bytes.chunks_exact(rl).map(read_xyz).collect();
    if pts.is_empty() {
        return true;
    }
    let mut min = [i64::MAX; 3];
    let mut max = [i64::MIN; 3];
    for p in &pts {
        for a in 0..3 {
            min[a] = min[a].min(p[a] as i64);
            max[a] = max[a].max(p[a] as i64);
        }
    }
    let g = MortonGrid::for_bounds(min, max);
    pts.windows(2).all(|w| g.code(w[0].map(|v| v as i64)) <= g.code(w[1].map(|v| v as i64)))
}

fn check_fixture(f: &Path, dir: &Path, zstd: bool) -> Result<(), String> {
    let s = dir.join("s.las");
    let b = dir.join("b.mbat");
    let back = dir.join("back.las");
    let run = |args: &[&str]| -> Result<(), String> {
        let o = mortar().args(args).output().unwrap();
        if o.status.success() {
            Ok(())
        } else {
            Err(format!("{args:?}: {}", String::from_utf8_lossy(&o.stderr)))
        }
    };
    let (fs, ss, bs, backs) =
        (f.to_str().unwrap(), s.to_str().unwrap(), b.to_str().unwrap(), back.to_str().unwrap());
    run(&["-q", "sort", fs, "-o", ss])?;
    let mut batch_args = vec!["-q", "batch", fs, "-o", bs];
    if zstd {
        batch_args.extend(["--compress", "zstd"]);
    }
    run(&batch_args)?;
    run(&["sort", bs, "-o", backs])?;
    let sorted = std::fs::read(&s).unwrap();
    if std::fs::read(&back).unwrap() != sorted {
        return Err("batch -> sort differs from sort".into());
    }
    let (out, rl, oh) =
        las_records(&s).map_err(|e| format!("las crate cannot read mortar's output: {e}"))?;
    if !morton_sorted(&out, rl) {
        return Err("output is not in Morton order".into());
    }
    match las_records(f) {
        Ok((inp, irl, ih)) => {
            if irl != rl {
                return Err(format!("record length {irl} became {rl}"));
            }
            if multiset(&inp, rl) != multiset(&out, rl) {
                return Err("points differ from the input's".into());
            }
            let key = |v: &las::Vlr| (v.user_id.clone(), v.record_id, v.data.clone());
            // records that point into the input's byte layout are dropped (docs/formats.md)
            let kept = |v: &&las::Vlr| {
                v.user_id != "laszip encoded"
                    && v.user_id != "copc"
                    && !(v.user_id == "LAStools" && v.record_id == 30)
            };
            let iv: Vec<_> = ih.vlrs().iter().filter(kept).map(key).collect();
            let ov: Vec<_> = oh.vlrs().iter().map(key).collect();
            if iv != ov {
                return Err("VLRs differ".into());
            }
            if ih.evlrs().iter().filter(kept).count() != oh.evlrs().len() {
                return Err("EVLR count differs".into());
            }
        }
        Err(e) => eprintln!(
            "note: las crate cannot read {} ({e}); checked against mortar only",
            f.display()
        ),
    }
    Ok(())
}

#[test]
fn every_readable_fixture_round_trips_exactly() {
    let Some(data) = shared_data() else { return };
    let files = readable_fixtures(&data);
    assert!(files.len() > 100, "expected the shared fixtures, found {}", files.len());
    let dir = tempdir("roundtrip");
    let mut failures = Vec::new();
    for (i, f) in files.iter().enumerate() {
        if let Err(e) = check_fixture(f, &dir, i % 5 == 0) {
            failures.push(format!("{}: {e}", f.display()));
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(
        failures.is_empty(),
        "{} of {} fixtures failed:\n{}",
        failures.len(),
        files.len(),
        failures.join("\n")
    );
}

#[test]
fn laz_output_round_trips() {
    let dir = tempdir("laz");
    let sample = root().join("data-samples/autzen_trim.laz");
    let s = dir.join("s.las");
    let z = dir.join("s.laz");
    let back = dir.join("back.las");
    run_ok(mortar().args(["sort"]).arg(&sample).arg("-o").arg(&s));
    run_ok(mortar().args(["sort"]).arg(&sample).arg("-o").arg(&z));
    run_ok(mortar().args(["sort"]).arg(&z).arg("-o").arg(&back));
    assert_eq!(std::fs::read(&s).unwrap(), std::fs::read(&back).unwrap());
    let (a, rl, _) = las_records(&z).unwrap();
    let (b, _, _) = las_records(&s).unwrap();
    assert_eq!(a.len() / rl, 110_000);
    assert_eq!(a, b, "the las crate reads mortar's LAZ as the same points in the same order");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn laz_output_keeps_evlrs() {
    let Some(data) = shared_data() else { return };
    let src = data.join("laspy/tests/data/1_4_w_evlr.las");
    let dir = tempdir("evlr");
    let z = dir.join("e.laz");
    let s = dir.join("e.las");
    run_ok(mortar().arg("sort").arg(&src).arg("-o").arg(&z));
    run_ok(mortar().arg("sort").arg(&src).arg("-o").arg(&s));
    let (a, rl, ha) = las_records(&z).unwrap();
    let (b, _, hb) = las_records(&s).unwrap();
    let (_, _, hsrc) = las_records(&src).unwrap();
    assert_eq!(a, b);
    assert_eq!(a.len() / rl, 1000);
    assert_eq!(ha.evlrs().len(), hsrc.evlrs().len());
    assert_eq!(hb.evlrs().len(), hsrc.evlrs().len());
    assert_eq!(ha.evlrs()[0].data, hsrc.evlrs()[0].data);
    std::fs::remove_dir_all(&dir).unwrap();
}
