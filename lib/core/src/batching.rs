//! Splitting Morton-ordered points into batches (paper 003 §3.1): runs of at most 10,240
//! consecutive points with their bounding box.
//!
//! A batch whose extent needs more than 30 bits on an axis cannot be quantized exactly
//! ([`crate::quantize`]); such batches come from jumps in the Morton order (paper 003 §4.4.1 and
//! §5 suggest splitting them) and are halved until every part fits. Batches are therefore at most
//! [`BATCH_SIZE`](crate::BATCH_SIZE) points, and only the split ones are smaller.

use crate::quantize::BatchGrid;
use std::ops::Range;

/// One planned batch: a range of the ordered points and its quantization frame.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PlannedBatch {
    pub range: Range<usize>,
    pub grid: BatchGrid,
    /// Integer bounds (inclusive) of the batch.
    pub max: [i32; 3],
}

/// Integer bounds of `xyz[range]`.
pub fn int_bounds(xyz: &[[i32; 3]]) -> ([i32; 3], [i32; 3]) {
    let mut min = [i32::MAX; 3];
    let mut max = [i32::MIN; 3];
    for p in xyz {
        for a in 0..3 {
            min[a] = min[a].min(p[a]);
            max[a] = max[a].max(p[a]);
        }
    }
    (min, max)
}

/// Plans the batches of `xyz` (already in Morton order), appending to `out` with ranges offset by
/// `base`. A full batch has `batch_size` points.
pub fn plan_batches(xyz: &[[i32; 3]], batch_size: usize, base: usize, out: &mut Vec<PlannedBatch>) {
    assert!(batch_size > 0);
    let mut start = 0;
    while start < xyz.len() {
        let end = (start + batch_size).min(xyz.len());
        plan_range(xyz, start..end, base, out);
        start = end;
    }
}

fn plan_range(xyz: &[[i32; 3]], range: Range<usize>, base: usize, out: &mut Vec<PlannedBatch>) {
    let (min, max) = int_bounds(&xyz[range.clone()]);
    match BatchGrid::for_bounds(min, max) {
        Some(grid) => {
            out.push(PlannedBatch { range: range.start + base..range.end + base, grid, max })
        }
        None => {
            // A single point always fits, so the recursion ends.
            let mid = range.start + (range.end - range.start) / 2;
            plan_range(xyz, range.start..mid, base, out);
            plan_range(xyz, mid..range.end, base, out);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn full_and_last_batches() {
        let xyz: Vec<[i32; 3]> = (0..25_000).map(|i| [i, i / 2, 0]).collect();
        let mut out = Vec::new();
        plan_batches(&xyz, 10_240, 0, &mut out);
        assert_eq!(out.len(), 3);
        assert_eq!(out[0].range, 0..10_240);
        assert_eq!(out[2].range, 20_480..25_000);
        assert_eq!(out[1].grid.min, [10_240, 5_120, 0]);
    }

    #[test]
    fn oversized_batches_split_until_they_fit() {
        // Morton jump: half the points at one end of the i32 range, half at the other.
        let mut xyz: Vec<[i32; 3]> = (0..100).map(|i| [i32::MIN + i, 0, 0]).collect();
        xyz.extend((0..100).map(|i| [i32::MAX - 100 + i, 0, 0]));
        let mut out = Vec::new();
        plan_batches(&xyz, 10_240, 7, &mut out);
        assert_eq!(out.len(), 2);
        assert_eq!(out[0].range, 7..107);
        assert_eq!(out[1].range, 107..207);
        let total: usize = out.iter().map(|b| b.range.len()).sum();
        assert_eq!(total, 200);
    }
}

#[cfg(test)]
mod geo_tests {
    use super::*;
    use crate::grid::Grid;
    use crate::quantize::Precision;
    use proptest::prelude::*;

    /// A Morton-ordered-ish cloud (sorted by x) around a world origin on a grid.
    fn cloud(
        origin: [f64; 3],
        scale: f64,
        extent_m: f64,
        seed: u64,
        n: usize,
    ) -> (Grid, Vec<[i32; 3]>) {
        let grid = Grid { scale: [scale; 3], offset: origin };
        let mut s = seed | 1;
        let mut next = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut pts: Vec<[i32; 3]> = (0..n)
            .map(|_| {
                let p = [next() * extent_m, next() * extent_m, next() * extent_m * 0.1];
                p.map(|v| (v / scale).round() as i32)
            })
            .collect();
        pts.sort();
        (grid, pts)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        /// ECEF-scale (6.4e6 m, scale 0.0001) and geographic degrees (scale 1e-7): every batch
        /// decodes exactly from three words, and from one or two words within the error bound,
        /// measured in world units.
        #[test]
        fn georeferenced_batches(seed in any::<u64>(), which in 0usize..2, extent in 1.0f64..200.0) {
            let (origin, scale, ext) = if which == 0 {
                ([6.4e6, 1.2e5, 6.3e6], 1e-4, extent)
            } else {
                ([-123.07, 44.05, 0.0], 1e-7, extent * 1e-5)
            };
            let (grid, pts) = cloud(origin, scale, ext, seed, 30_000);
            let mut plan = Vec::new();
            plan_batches(&pts, crate::BATCH_SIZE, 0, &mut plan);
            prop_assert_eq!(plan.iter().map(|b| b.range.len()).sum::<usize>(), pts.len());
            for b in &plan {
                for p in &pts[b.range.clone()] {
                    let w = b.grid.encode(*p);
                    prop_assert_eq!(b.grid.decode_exact(w), *p);
                    for prec in [Precision::Bits10, Precision::Bits20] {
                        let r = b.grid.decode_relative(w, prec);
                        let bound = b.grid.error_bound(prec);
                        for a in 0..3 {
                            let world_err = ((r[a] - (p[a] as f64 - b.grid.min[a] as f64)) * grid.scale[a]).abs();
                            prop_assert!(world_err <= bound[a] * grid.scale[a] + 1e-12);
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn single_point_batches_and_extreme_coordinates() {
        for p in [[i32::MIN; 3], [i32::MAX; 3], [i32::MIN, 0, i32::MAX]] {
            let mut plan = Vec::new();
            plan_batches(&[p], crate::BATCH_SIZE, 0, &mut plan);
            assert_eq!(plan.len(), 1);
            assert_eq!(plan[0].grid.bits, [0, 0, 0]);
            assert_eq!(plan[0].grid.decode_exact(plan[0].grid.encode(p)), p);
        }
    }
}
