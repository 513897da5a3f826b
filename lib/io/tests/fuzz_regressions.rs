//! Replays the fuzz targets' findings and seeds in the normal test suite (FUZZING.md): every
//! file of `fuzz/regressions/<target>/` (an input that crashed, hung or allocated hugely before
//! its fix) and of the seed corpus `fuzz/corpus/<target>/` goes through the same function the
//! fuzz target calls, so `cargo test` on any machine fails if a fixed bug comes back.

#[path = "../../../fuzz/src/lib.rs"]
#[allow(dead_code)]
mod targets;

use std::path::PathBuf;

fn replay(target: &str, run: fn(&[u8])) {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fuzz");
    let mut n = 0;
    for dir in ["regressions", "corpus"] {
        let d = root.join(dir).join(target);
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        let mut files: Vec<PathBuf> = rd.filter_map(|e| e.ok()).map(|e| e.path()).filter(|p| p.is_file()).collect();
        files.sort();
        for f in files {
            let bytes = std::fs::read(&f).unwrap();
            // A panic names the input: the test harness prints this line with it.
            eprintln!("replaying {}", f.display());
            run(&bytes);
            n += 1;
        }
    }
    assert!(n > 0, "no inputs for fuzz target {target} under {}", root.display());
}

#[test]
fn las_header() {
    replay("las_header", targets::las_header);
}

#[test]
fn vlr_records() {
    replay("vlr_records", targets::vlr_records);
}

#[test]
fn las_input() {
    replay("las_input", targets::las_input);
}

#[test]
fn batch_file() {
    replay("batch_file", targets::batch_file);
}

#[test]
fn store() {
    replay("store", targets::store);
}

#[test]
fn lod_index() {
    replay("lod_index", targets::lod_index);
}
