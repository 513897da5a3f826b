//! What the partitioned engine, the dense cells and the streamed export share: run files (the
//! records of a partition grouped by cell, with their arrival numbers) and the candidates a
//! finished unit or node hands its parent.

use mortar_core::octree::{earliest_in_parent_cells, Cube, NodeKey};
use std::path::PathBuf;

/// One run file: the records of a group of pieces grouped by cell, then their arrival numbers
/// (8 bytes each, native order) in the same order, so that a range of cells is one contiguous
/// read of records and one of arrival numbers, straight into the unit's buffers.
#[derive(Clone)]
pub(crate) struct Run {
    pub(crate) path: PathBuf,
    /// Index of the first record of cell `c` (one more than the cells: the end).
    pub(crate) starts: Vec<u64>,
    /// The partitioned engine's checksum of the file (0 for a finer partition's runs).
    pub(crate) hash: u64,
}

impl Run {
    /// A run of a finer partition of a dense cell (not in the manifest: no checksum).
    pub(crate) fn new(path: PathBuf, starts: Vec<u64>) -> Run {
        Run { path, starts, hash: 0 }
    }
}

/// Points taken from a finished unit or node for its parent: positions, arrival numbers and
/// whole records.
#[derive(Default)]
pub(crate) struct Cands {
    pub pos: Vec<[i32; 3]>,
    pub arrival: Vec<u64>,
    pub records: Vec<u8>,
}

impl Cands {
    pub(crate) fn push(&mut self, pos: [i32; 3], arrival: u64, record: &[u8]) {
        self.pos.push(pos);
        self.arrival.push(arrival);
        self.records.extend_from_slice(record);
    }
    /// Which of these (a node's voxels, in Morton order) the node `key` with cube `cube` hands
    /// its parent: the earliest in each cell of the parent's grid; none for the root.
    pub(crate) fn for_parent(&self, key: NodeKey, cube: Cube) -> Vec<usize> {
        if key.level == 0 {
            return Vec::new();
        }
        earliest_in_parent_cells(cube, 0..self.pos.len(), |i| self.pos[i], |i| self.arrival[i])
    }

    /// The candidates at `idx` (records of `rl` bytes).
    pub(crate) fn pick(&self, idx: &[usize], rl: usize) -> Cands {
        let mut out = Cands::default();
        for &i in idx {
            out.push(self.pos[i], self.arrival[i], &self.records[i * rl..(i + 1) * rl]);
        }
        out
    }

    pub(crate) fn append(&mut self, o: Cands) {
        self.pos.extend(o.pos);
        self.arrival.extend(o.arrival);
        self.records.extend(o.records);
    }
}
