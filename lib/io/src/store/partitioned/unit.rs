//! A unit of the partitioned engine (a node whose points fit the budget for one): what each of
//! its points costs in memory, and its points read back from every run and sorted as the sorted
//! engine sorts.

use crate::error::{Error, Result};
use crate::sort;
use crate::store::engine::{grid_of, histogram, sort_records, Sorted, BUCKET_BITS};
use crate::store::runs::Run;
use mortar_core::octree::{Cube, NodeKey};
use rayon::prelude::*;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

/// Bytes per point of a unit held in memory: the entry read back (record + 8), the sorted copy
/// (record + 8), and the sort's keys and scratch (32).
pub(crate) fn unit_bytes_per_point(rl: u64) -> u64 {
    2 * (rl + 8) + 32
}

/// The points of the partition cells `cells` (those of node `key`, `count` of them) read back
/// from every run and sorted as the sorted engine sorts: a unit's points, ready for
/// [`build_subtree`]. `dir` names the place in errors.
///
/// [`build_subtree`]: mortar_core::octree::build_subtree
pub(crate) fn read_unit(
    runs: &[Run],
    root: Cube,
    key: NodeKey,
    cells: std::ops::Range<usize>,
    count: u64,
    rl: usize,
    dir: &Path,
) -> Result<Sorted> {
    let n = count as usize;
    let mut records = sort::zeroed_huge::<u8>(n * rl);
    let mut arrival = sort::zeroed_huge::<u64>(n);
    // Each run's share, read in parallel straight into place (runs in input order).
    let mut parts: Vec<(&Run, &mut [u8], &mut [u64])> = Vec::with_capacity(runs.len());
    {
        let (mut rr, mut ar): (&mut [u8], &mut [u64]) = (&mut records, &mut arrival);
        for run in runs {
            let m = (run.starts[cells.end] - run.starts[cells.start]) as usize;
            if m > ar.len() {
                return Err(Error::Internal {
                    path: dir.to_path_buf(),
                    what: "the run files hold more points than counted",
                });
            }
            let (x, y) = std::mem::take(&mut rr).split_at_mut(m * rl);
            let (u, v) = std::mem::take(&mut ar).split_at_mut(m);
            parts.push((run, x, u));
            rr = y;
            ar = v;
        }
        if !ar.is_empty() {
            return Err(Error::Internal {
                path: dir.to_path_buf(),
                what: "the run files hold fewer points than counted",
            });
        }
    }
    let cs = cells.start;
    parts.into_par_iter().try_for_each(|(run, recs, arr)| -> Result<()> {
        if arr.is_empty() {
            return Ok(());
        }
        let total = *run.starts.last().expect("a run has an end");
        let first = run.starts[cs];
        let mut f = std::fs::File::open(&run.path).map_err(|e| Error::io(&run.path, e))?;
        f.seek(SeekFrom::Start(first * rl as u64)).map_err(|e| Error::io(&run.path, e))?;
        f.read_exact(recs).map_err(|e| Error::io(&run.path, e))?;
        f.seek(SeekFrom::Start(total * rl as u64 + first * 8))
            .map_err(|e| Error::io(&run.path, e))?;
        f.read_exact(bytemuck::cast_slice_mut(arr)).map_err(|e| Error::io(&run.path, e))
    })?;
    // Sorted as the sorted engine sorts (buckets below the unit's own prefix): local order
    // is input order, so ties come out the same.
    let g = grid_of(root);
    let high = 3 * (root.size_log2 as u32).min(mortar_core::morton::BITS_PER_AXIS);
    let unit_level = key.level as u32;
    let shift = high.saturating_sub(3 * unit_level.min(high / 3)).saturating_sub(BUCKET_BITS);
    let sorted: Sorted = if n == 0 {
        Sorted { records: Vec::new(), arrival: Vec::new(), rl }
    } else {
        // Slabs of the unit, so that the histograms and the scatter run on every thread.
        const SLAB: usize = 1 << 16;
        let slabs: Vec<&[u8]> = records.chunks(SLAB * rl).collect();
        let hist: Vec<Vec<u32>> = slabs.par_iter().map(|s| histogram(s, rl, &g, shift)).collect();
        sort_records(&slabs, &hist, rl, &g, shift, &crate::progress::Progress::new(), |p, i| {
            arrival[p * SLAB + i]
        })
    };
    Ok(sorted)
}
