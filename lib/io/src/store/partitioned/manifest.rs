//! The manifest of a resumable partitioned build: what pass 1 found (the root, the run files
//! with their checksums, the cells' counts and the points' statistics), kept in `.partition/`
//! inside the store so that `--resume` skips pass 1 when it and every run check out.

use super::checksum::checksum;
use super::partition::Partition;
use crate::error::{Error, Result};
use crate::sort::PieceStats;
use crate::store::runs::Run;
use mortar_core::octree::Cube;
use rayon::prelude::*;
use std::path::Path;

/// The directory inside the store that holds the partition until the build ends.
pub(crate) const STATE_DIR: &str = ".partition";
const MANIFEST: &str = "manifest.json";
const TABLES: &str = "tables.bin";

/// Whether the store `dir` holds the state a partitioned build can resume from.
pub(crate) fn has_state(dir: &Path) -> bool {
    dir.join(STATE_DIR).join(MANIFEST).is_file()
}

/// Writes the manifest (the tables first, then the JSON by rename) once the runs are synced.
pub(super) fn write_manifest(state: &Path, p: &Partition) -> Result<()> {
    let tp = state.join(TABLES);
    let mut t: Vec<u64> = p.hist.clone();
    for r in &p.runs {
        t.extend_from_slice(&r.starts);
    }
    let tables = bytemuck::cast_slice::<u64, u8>(&t);
    std::fs::write(&tp, tables).map_err(|e| Error::io(&tp, e))?;
    let j = serde_json::json!({
        "root_min": p.root.min,
        "root_size_log2": p.root.size_log2,
        "cells": p.hist.len(),
        "runs": p.runs.iter().map(|r| r.path.file_name().map(|n| n.to_string_lossy().to_string())).collect::<Vec<_>>(),
        "run_checksums": p.runs.iter().map(|r| r.hash).collect::<Vec<_>>(),
        "tables_checksum": checksum(tables),
        "checksum": manifest_sum(p, checksum(tables)),
        "count": p.all.count,
        "min": p.all.min,
        "max": p.all.max,
        "max_rgb": p.all.max_rgb,
        "max_intensity": p.all.max_intensity,
        "warnings": p.warnings,
    });
    let mp = state.join(MANIFEST);
    let tmp = state.join(format!("{MANIFEST}.tmp"));
    std::fs::write(&tmp, serde_json::to_vec_pretty(&j).unwrap_or_default())
        .map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, &mp).map_err(|e| Error::io(&mp, e))?;
    Ok(())
}

/// A checksum of what the manifest says (its JSON is checked field by field against it).
fn manifest_sum(p: &Partition, tables: u64) -> u64 {
    let names: Vec<String> = p
        .runs
        .iter()
        .map(|r| r.path.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default())
        .collect();
    let hashes: Vec<u64> = p.runs.iter().map(|r| r.hash).collect();
    let a = &p.all;
    let text = format!(
        "{:?} {} {} {names:?} {hashes:?} {} {:?} {:?} {} {} {tables} {:?}",
        p.root.min,
        p.root.size_log2,
        p.hist.len(),
        a.count,
        a.min,
        a.max,
        a.max_rgb,
        a.max_intensity,
        p.warnings
    );
    checksum(text.as_bytes())
}

/// The manifest of a stopped build, if it is whole and its run files are all there.
pub(super) fn read_manifest(state: &Path, rl: usize) -> Option<Partition> {
    let j: serde_json::Value =
        serde_json::from_slice(&std::fs::read(state.join(MANIFEST)).ok()?).ok()?;
    let arr3 = |v: &serde_json::Value| -> Option<[i64; 3]> {
        Some([v.get(0)?.as_i64()?, v.get(1)?.as_i64()?, v.get(2)?.as_i64()?])
    };
    let root = Cube { min: arr3(&j["root_min"])?, size_log2: j["root_size_log2"].as_u64()? as u8 };
    let cells = j["cells"].as_u64()? as usize;
    let names: Vec<String> = j["runs"]
        .as_array()?
        .iter()
        .map(|v| v.as_str().map(str::to_string))
        .collect::<Option<_>>()?;
    let hashes: Vec<u64> =
        j["run_checksums"].as_array()?.iter().map(|v| v.as_u64()).collect::<Option<_>>()?;
    if hashes.len() != names.len() {
        return None;
    }
    let t = std::fs::read(state.join(TABLES)).ok()?;
    let want =
        cells.checked_add(names.len().checked_mul(cells.checked_add(1)?)?)?.checked_mul(8)?;
    if t.len() != want
        || checksum(&t) != j["tables_checksum"].as_u64()?
        || cells == 0
        || !cells.is_power_of_two()
    {
        return None;
    }
    let t: Vec<u64> =
        t.chunks_exact(8).map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes"))).collect();
    let hist = t[..cells].to_vec();
    let mut runs = Vec::new();
    if names.iter().any(|n| !(n.starts_with("run-") && n.ends_with(".bin")) || n.contains('/')) {
        return None;
    }
    for (k, name) in names.iter().enumerate() {
        let starts = t[cells + k * (cells + 1)..cells + (k + 1) * (cells + 1)].to_vec();
        if starts[0] != 0 || starts.windows(2).any(|w| w[0] > w[1]) {
            return None;
        }
        let path = state.join(name);
        let len = std::fs::metadata(&path).ok()?.len();
        if len != *starts.last()? * (rl as u64 + 8) {
            return None;
        }
        runs.push(Run { path, starts, hash: hashes[k] });
    }
    // The cells' counts are the runs' counts summed.
    if (0..cells)
        .any(|c| runs.iter().map(|r| r.starts[c + 1] - r.starts[c]).sum::<u64>() != hist[c])
    {
        return None;
    }
    // Every run as it was written (a power loss may have kept the sizes but not the bytes).
    let whole =
        runs.par_iter().all(|r| std::fs::read(&r.path).is_ok_and(|b| checksum(&b) == r.hash));
    if !whole {
        return None;
    }
    let i32x3 =
        |v: &serde_json::Value| -> Option<[i32; 3]> { arr3(v).map(|a| a.map(|x| x as i32)) };
    let all = PieceStats {
        count: j["count"].as_u64()?,
        min: i32x3(&j["min"])?,
        max: i32x3(&j["max"])?,
        max_rgb: j["max_rgb"].as_u64()? as u16,
        max_intensity: j["max_intensity"].as_u64()? as u16,
        ..PieceStats::default()
    };
    let warnings =
        j["warnings"].as_array()?.iter().filter_map(|w| w.as_str().map(str::to_string)).collect();
    let p = Partition { root, runs, hist, all, warnings, base: [0; 3], sample: None };
    (manifest_sum(&p, j["tables_checksum"].as_u64()?) == j["checksum"].as_u64()?).then_some(p)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::partitioned::testing::{bytes, scratch};

    /// A partition of two runs over 8 cells, as pass 1 leaves it, with its run files.
    fn partition(state: &Path, rl: usize) -> Partition {
        let starts = [vec![0u64, 3, 3, 5, 9, 9, 9, 10, 12], vec![0u64, 0, 1, 1, 1, 4, 6, 6, 6]];
        let mut runs = Vec::new();
        for (k, s) in starts.iter().enumerate() {
            let path = state.join(format!("run-{k}.bin"));
            let b = bytes(*s.last().unwrap() as usize * (rl + 8), k as u64 + 1);
            std::fs::write(&path, &b).unwrap();
            runs.push(Run { path, starts: s.clone(), hash: checksum(&b) });
        }
        let hist =
            (0..8).map(|c| runs.iter().map(|r| r.starts[c + 1] - r.starts[c]).sum()).collect();
        let all = PieceStats {
            count: 18,
            min: [-5, 0, 7],
            max: [900, 1000, 70],
            max_rgb: 65535,
            max_intensity: 4000,
            ..PieceStats::default()
        };
        let root = Cube { min: [-8, -8, -8], size_log2: 11 };
        Partition {
            root,
            runs,
            hist,
            all,
            warnings: vec!["a.las: lies".into()],
            base: [0; 3],
            sample: None,
        }
    }

    #[test]
    fn a_manifest_is_read_back_as_written_and_any_damage_refuses_it() {
        let (state, rl) = (scratch("manifest"), 26);
        let p = partition(&state, rl);
        write_manifest(&state, &p).unwrap();
        let q = read_manifest(&state, rl).expect("a whole manifest is read back");
        assert_eq!((q.root, &q.hist, q.all.count, &q.warnings), (p.root, &p.hist, 18, &p.warnings));
        assert_eq!(
            (q.all.min, q.all.max, q.all.max_rgb, q.all.max_intensity),
            ([-5, 0, 7], [900, 1000, 70], 65535, 4000)
        );
        for (a, b) in q.runs.iter().zip(&p.runs) {
            assert_eq!((&a.path, &a.starts, a.hash), (&b.path, &b.starts, b.hash));
        }
        // Another record length: the run files' sizes do not match.
        assert!(read_manifest(&state, rl + 1).is_none());
        // A run file whose bytes changed but not its size (a power loss after the rename).
        let run0 = state.join("run-0.bin");
        let good = std::fs::read(&run0).unwrap();
        let mut bad = good.clone();
        bad[7] ^= 1;
        std::fs::write(&run0, &bad).unwrap();
        assert!(read_manifest(&state, rl).is_none(), "a changed run is refused");
        std::fs::write(&run0, &good).unwrap();
        // The tables cut short.
        let tables = state.join(TABLES);
        let t = std::fs::read(&tables).unwrap();
        std::fs::write(&tables, &t[..t.len() - 8]).unwrap();
        assert!(read_manifest(&state, rl).is_none(), "short tables are refused");
        std::fs::write(&tables, &t).unwrap();
        // A field of the JSON edited: the manifest's own checksum no longer matches.
        let mp = state.join(MANIFEST);
        let text = std::fs::read_to_string(&mp).unwrap();
        std::fs::write(&mp, text.replace("\"count\": 18", "\"count\": 19")).unwrap();
        assert!(read_manifest(&state, rl).is_none(), "an edited manifest is refused");
        std::fs::write(&mp, &text).unwrap();
        // A run file gone.
        std::fs::remove_file(state.join("run-1.bin")).unwrap();
        assert!(read_manifest(&state, rl).is_none(), "a missing run is refused");
        std::fs::remove_dir_all(&state).unwrap();
    }
}
