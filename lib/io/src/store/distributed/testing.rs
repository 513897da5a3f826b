//! What the distributed build's unit tests share: scratch directories, a plan of a few jobs and
//! parts written as a job leaves them (with payloads that need not decode).

use super::part::{PartFile, ENTRIES_FILE, PART_FILE};
use super::plan::{Plan, PlanJob, PLAN_FORMAT};
use crate::store::format::{NodeEntry, LEAF, NODES_FILE, SOURCE_FILE};
use std::path::{Path, PathBuf};

/// A fresh directory under the system's temporary directory.
pub(super) fn scratch(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("mortar-dist-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A plan of `jobs` jobs (id `id`, not its checksum: the merge compares ids and plans).
pub(super) fn plan_of(jobs: usize, id: &str) -> Plan {
    Plan {
        format: PLAN_FORMAT.into(),
        id: id.into(),
        scanned: false,
        root_min: [0; 3],
        root_size_log2: 10,
        cell_depth: 1,
        leaf_capacity: 100,
        max_level: 20,
        points: 0,
        inputs: Vec::new(),
        jobs: (0..jobs as u32)
            .map(|j| PlanJob { nodes: vec![[1, j, 0, 0]], inputs: Vec::new(), estimated_points: 0 })
            .collect(),
        warnings: Vec::new(),
    }
}

/// The description of a part of job `job` of `plan` with `entries` entries over `nodes_len`
/// bytes of payloads.
pub(super) fn part_file(plan: &Plan, job: usize, entries: u64, nodes_len: u64) -> PartFile {
    PartFile {
        format: "mortar-part/1".into(),
        plan: plan.clone(),
        job,
        nodes: Vec::new(),
        entries,
        nodes_len,
        record_len: 26,
        points: 0,
        min: [0; 3],
        max: [0; 3],
        max_rgb: 0,
        max_intensity: 0,
        rgb_offset: None,
    }
}

/// Two entries over 100 bytes of payloads (60 and 40).
pub(super) fn two_entries() -> Vec<NodeEntry> {
    let e = |i: u32, offset: u64, length: u64| NodeEntry {
        level: 2,
        kind: LEAF,
        index: [i, 0, 0],
        segment: 0,
        count: 1,
        offset,
        length,
    };
    vec![e(0, 0, 60), e(1, 60, 40)]
}

/// Writes the part `file` with `entries`, `nodes_len` bytes of payloads and `source` as its
/// `source.las` into the directory `dir`.
pub(super) fn write_part(dir: &Path, file: &PartFile, entries: &[NodeEntry], source: &[u8]) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(dir.join(PART_FILE), serde_json::to_vec_pretty(file).unwrap()).unwrap();
    std::fs::write(dir.join(ENTRIES_FILE), bytemuck::cast_slice::<NodeEntry, u8>(entries)).unwrap();
    std::fs::write(dir.join(NODES_FILE), vec![7u8; file.nodes_len as usize]).unwrap();
    std::fs::write(dir.join(SOURCE_FILE), source).unwrap();
}
