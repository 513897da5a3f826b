//! The insertion phases: `insert_points` (paper 004 §5.3-5.4) scatters the points of the update
//! straight into one new chunk per leaf and the leaves append their chunks in parallel;
//! `insert_voxels` (§5.4) appends each inner node's backlog of new voxels to its chunks.

use super::expand::Expansion;
use super::Builder;
use crate::octree::types::{Point, POINT_CHUNK_MAX};
use bytemuck::Zeroable;
use rayon::prelude::*;
use std::sync::Arc;

/// Fewest points per part of the parallel scatter in `insert_points`.
const SCATTER_MIN: usize = 1 << 15;

impl Builder {
    /// §5.3-5.4: scatters the points of the update (spilled first, then the batch, each in
    /// order) straight into one new chunk per leaf and appends the chunks to their leaves.
    ///
    /// The sequence is cut into parts; each part counts its points per leaf and then writes into
    /// its own sub-slice of every leaf's chunk, so parts scatter in parallel and the order within
    /// a leaf is the sequence order.
    pub(super) fn insert_points(&mut self, exp: &Expansion, batch: &[Point]) {
        debug_assert_eq!(exp.new_count.len(), self.shapes.len());
        let total = exp.spill.len() + batch.len();
        let leaves: Vec<u32> =
            (0..exp.new_count.len() as u32).filter(|&i| exp.new_count[i as usize] > 0).collect();
        let mut compact = vec![u32::MAX; exp.new_count.len()];
        for (k, &l) in leaves.iter().enumerate() {
            compact[l as usize] = k as u32;
        }
        let parts = (rayon::current_num_threads() * 4).min(total / SCATTER_MIN).max(1);
        let bounds: Vec<usize> = (0..=parts).map(|p| p * total / parts).collect();
        let seq = |a: usize, b: usize| {
            let s = exp.spill.len();
            let spill =
                exp.spill[a.min(s)..b.min(s)].iter().zip(&exp.spill_leaf[a.min(s)..b.min(s)]);
            let batch = batch[a.max(s) - s..b.max(s) - s]
                .iter()
                .zip(&exp.batch_leaf[a.max(s) - s..b.max(s) - s]);
            spill.chain(batch).map(|(p, &l)| (p, compact[l as usize] as usize))
        };

        // Points per part and leaf.
        let counts: Vec<Vec<u32>> = (0..parts)
            .into_par_iter()
            .map(|p| {
                let mut c = vec![0u32; leaves.len()];
                for (_, k) in seq(bounds[p], bounds[p + 1]) {
                    c[k] += 1;
                }
                c
            })
            .collect();

        // One new chunk per leaf, cut into one piece per part.
        let mut fresh: Vec<Arc<[Point]>> = leaves
            .par_iter()
            .map(|&l| {
                std::iter::repeat_n(Point::zeroed(), exp.new_count[l as usize] as usize).collect()
            })
            .collect();
        let mut pieces: Vec<Vec<&mut [Point]>> =
            (0..parts).map(|_| Vec::with_capacity(leaves.len())).collect();
        for (k, chunk) in fresh.iter_mut().enumerate() {
            let mut rest = Arc::get_mut(chunk).expect("a new chunk is not shared yet");
            for (p, piece) in pieces.iter_mut().enumerate() {
                let (a, r) = std::mem::take(&mut rest).split_at_mut(counts[p][k] as usize);
                piece.push(a);
                rest = r;
            }
            debug_assert!(rest.is_empty());
        }
        pieces.into_par_iter().enumerate().for_each(|(p, mut dst)| {
            let mut cursor = vec![0u32; dst.len()];
            for (pt, k) in seq(bounds[p], bounds[p + 1]) {
                dst[k][cursor[k] as usize] = *pt;
                cursor[k] += 1;
            }
        });

        // Append in parallel.
        let mut by_node: Vec<Option<Arc<[Point]>>> = vec![None; self.data.len()];
        for (&l, chunk) in leaves.iter().zip(fresh) {
            by_node[l as usize] = Some(chunk);
        }
        self.data.par_iter_mut().zip(by_node).for_each(|(d, chunk)| {
            if let Some(chunk) = chunk {
                debug_assert!(d.voxels.is_none(), "points go to leaves only");
                d.subtree += chunk.len() as u64;
                d.points.append_chunk(chunk, POINT_CHUNK_MAX);
                d.changed = true;
            }
        });
    }

    /// §5.4: appends each inner node's new voxels (the backlog) to its chunks; in averaged mode
    /// also rebuilds the chunks whose colours changed. Returns the number of new voxels.
    pub(super) fn insert_voxels(&mut self, exp: &Expansion, batch: &[Point]) -> u64 {
        let ns = exp.spill.len();
        let point = |seq: u32| -> Point {
            let i = seq as usize;
            if i < ns {
                exp.spill[i]
            } else {
                batch[i - ns]
            }
        };
        self.data
            .par_iter_mut()
            .map(|d| match &mut d.voxels {
                Some(v) => {
                    let (new, sampled, through) = v.publish(&point);
                    d.subtree += through;
                    d.changed |= sampled > 0;
                    new
                }
                None => 0,
            })
            .sum()
    }
}
