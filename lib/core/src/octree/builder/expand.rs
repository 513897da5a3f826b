//! `expand` (paper 004 §5.1): repeated counting (every point not yet in a final leaf descends to
//! its leaf, which counts it) and splitting (a leaf over capacity becomes an inner node with 8
//! empty leaf children, its stored points spilled and counted again), until no leaf splits.
//!
//! Counting descends the points in parallel chunks (counts are added per run of equal leaves,
//! so Morton-ordered input hardly contends).

use super::node::{NodeData, Shape, NO_CHILD};
use super::{Builder, PageIn};
use crate::octree::chunks::Chunks;
use crate::octree::types::{NodeId, OctreeError, Point, MIN_INNER_SIZE_LOG2, POINT_CHUNK_MAX};
use crate::octree::voxels::VoxelState;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};

/// Points per parallel work item when counting.
pub(super) const COUNT_CHUNK: usize = 1 << 14;

/// The result of `expand`: the leaf of every point of the update and the spilled points.
pub(super) struct Expansion {
    /// Final leaf of each batch point.
    pub(super) batch_leaf: Vec<u32>,
    /// Points moved out of split leaves, in the order those leaves stored them.
    pub(super) spill: Vec<Point>,
    /// Final leaf of each spilled point.
    pub(super) spill_leaf: Vec<u32>,
    /// Level of the leaf each spilled point came from.
    pub(super) spill_origin: Vec<u8>,
    /// New points per node in this update (0 for inner nodes).
    pub(super) new_count: Vec<u64>,
    pub(super) splits: usize,
    pub(super) iterations: u32,
}

/// Adds `n` to `counts[leaf - base]` per run of equal leaves.
struct RunCounter<'a> {
    counts: &'a [AtomicU64],
    base: u32,
    leaf: u32,
    n: u64,
}

impl<'a> RunCounter<'a> {
    fn new(counts: &'a [AtomicU64], base: u32) -> Self {
        RunCounter { counts, base, leaf: 0, n: 0 }
    }

    #[inline]
    fn add(&mut self, leaf: u32) {
        if leaf == self.leaf {
            self.n += 1;
        } else {
            self.flush();
            self.leaf = leaf;
            self.n = 1;
        }
    }

    fn flush(&mut self) {
        if self.n > 0 {
            self.counts[(self.leaf - self.base) as usize].fetch_add(self.n, Ordering::Relaxed);
            self.n = 0;
        }
    }
}

/// The leaf below node `n` whose cube holds `p`.
#[inline]
fn descend(shapes: &[Shape], mut n: u32, p: [i32; 3]) -> u32 {
    loop {
        let s = &shapes[n as usize];
        if s.first_child == NO_CHILD {
            return n;
        }
        n = s.first_child + s.cube.octant_of(p) as u32;
    }
}

impl Builder {
    /// Whether a leaf may become an inner node (see "Depth bound" in the module docs).
    fn splittable(&self, s: &Shape) -> bool {
        s.cube.size_log2 >= MIN_INNER_SIZE_LOG2 && s.key.level < self.config.max_level
    }

    /// §5.1: counting and splitting until no leaf splits. Fails, before changing anything, if the
    /// update would not fit 32-bit ids.
    pub(super) fn expand(
        &mut self,
        batch: &[Point],
        page_in: &PageIn<'_>,
    ) -> Result<Expansion, OctreeError> {
        let cap = self.config.leaf_capacity as u64;

        // First counting pass: every batch point descends from the root.
        let n0 = self.shapes.len();
        let mut batch_leaf = vec![0u32; batch.len()];
        let counts: Vec<AtomicU64> = (0..n0).map(|_| AtomicU64::new(0)).collect();
        {
            let shapes = &self.shapes;
            batch_leaf.par_chunks_mut(COUNT_CHUNK).zip(batch.par_chunks(COUNT_CHUNK)).for_each(
                |(leaves, pts)| {
                    let mut run = RunCounter::new(&counts, 0);
                    for (l, p) in leaves.iter_mut().zip(pts) {
                        *l = descend(shapes, 0, p.pos);
                        run.add(*l);
                    }
                    run.flush();
                },
            );
        }
        let mut new_count: Vec<u64> = counts.into_iter().map(AtomicU64::into_inner).collect();

        // Only leaves that existed before this update store points, and they receive all their
        // counts in the first pass: the spill is known now, before anything changes.
        let mut to_split = Vec::new();
        let mut spilled = 0u64;
        for (i, &n) in new_count.iter().enumerate() {
            if n == 0 {
                continue;
            }
            let stored = self.data[i].points.len() + self.data[i].paged;
            if stored + n > cap && self.splittable(&self.shapes[i]) {
                to_split.push(i as u32);
                spilled += stored;
            }
        }
        if batch.len() as u64 + spilled > u32::MAX as u64 {
            return Err(OctreeError::BatchTooLarge { points: batch.len(), spilled });
        }
        // Leaves that split need their paged-out points back first.
        let paged: Vec<u32> =
            to_split.iter().copied().filter(|&l| self.data[l as usize].paged > 0).collect();
        if !paged.is_empty() {
            let loaded: Vec<Vec<Point>> = paged
                .par_iter()
                .map(|&l| {
                    let pts = page_in(NodeId(l)).map_err(OctreeError::PageIn)?;
                    let want = self.data[l as usize].paged;
                    if pts.len() as u64 != want {
                        return Err(OctreeError::PageIn(format!(
                            "leaf {l}: {} points paged in, {want} paged out",
                            pts.len()
                        )));
                    }
                    Ok(pts)
                })
                .collect::<Result<_, _>>()?;
            for (&l, pts) in paged.iter().zip(loaded) {
                let d = &mut self.data[l as usize];
                let mut all = Chunks::default();
                all.append(&pts, POINT_CHUNK_MAX);
                for c in d.points.chunks() {
                    all.append(c, POINT_CHUNK_MAX);
                }
                d.points = all;
                d.paged = 0;
            }
        }

        let mut spill = Vec::with_capacity(spilled as usize);
        let mut spill_leaf = Vec::with_capacity(spilled as usize);
        let mut spill_origin = Vec::with_capacity(spilled as usize);
        let mut splits = 0;
        let mut iterations = 1;
        while !to_split.is_empty() {
            // Splitting.
            let first_new = self.shapes.len();
            for &leaf in &to_split {
                self.split(leaf, &mut spill, &mut spill_leaf, &mut spill_origin);
                new_count[leaf as usize] = 0;
            }
            splits += to_split.len();
            let mut split_now = vec![false; first_new];
            for &leaf in &to_split {
                split_now[leaf as usize] = true;
            }

            // Counting: points of split leaves (batch and spill) move one level down into the
            // new children, which count them.
            let total = self.shapes.len();
            let counts: Vec<AtomicU64> = (first_new..total).map(|_| AtomicU64::new(0)).collect();
            let shapes = &self.shapes;
            let step = |leaves: &mut [u32], pts: &[Point]| {
                let mut run = RunCounter::new(&counts, first_new as u32);
                for (l, p) in leaves.iter_mut().zip(pts) {
                    if split_now[*l as usize] {
                        let s = &shapes[*l as usize];
                        *l = s.first_child + s.cube.octant_of(p.pos) as u32;
                        run.add(*l);
                    }
                }
                run.flush();
            };
            batch_leaf
                .par_chunks_mut(COUNT_CHUNK)
                .zip(batch.par_chunks(COUNT_CHUNK))
                .for_each(|(l, p)| step(l, p));
            spill_leaf
                .par_chunks_mut(COUNT_CHUNK)
                .zip(spill.par_chunks(COUNT_CHUNK))
                .for_each(|(l, p)| step(l, p));
            new_count.extend(counts.into_iter().map(AtomicU64::into_inner));
            iterations += 1;

            to_split = (first_new..total)
                .filter(|&i| new_count[i] > cap && self.splittable(&self.shapes[i]))
                .map(|i| i as u32)
                .collect();
        }
        Ok(Expansion { batch_leaf, spill, spill_leaf, spill_origin, new_count, splits, iterations })
    }

    /// Turns leaf `leaf` into an inner node with 8 empty leaf children; its points go to the
    /// spill list.
    fn split(
        &mut self,
        leaf: u32,
        spill: &mut Vec<Point>,
        spill_leaf: &mut Vec<u32>,
        spill_origin: &mut Vec<u8>,
    ) {
        let s = self.shapes[leaf as usize];
        let first = u32::try_from(self.shapes.len()).expect("an octree has fewer than 2^32 nodes");
        for o in 0..8 {
            self.shapes.push(Shape {
                key: s.key.child(o),
                cube: s.cube.child(o),
                first_child: NO_CHILD,
            });
            self.data.push(NodeData { changed: true, ..NodeData::default() });
        }
        self.shapes[leaf as usize].first_child = first;
        let mode = self.config.color_mode;
        let d = &mut self.data[leaf as usize];
        for chunk in std::mem::take(&mut d.points).chunks() {
            spill.extend_from_slice(chunk);
        }
        spill_leaf.resize(spill.len(), leaf);
        spill_origin.resize(spill.len(), s.key.level);
        d.voxels = Some(Box::new(VoxelState::new(mode)));
        d.changed = true;
    }
}
