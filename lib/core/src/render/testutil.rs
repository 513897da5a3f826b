//! Helpers shared by the render tests: a seeded generator and synthetic batched scenes.

/// A small deterministic generator (SplitMix64).
pub(crate) struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

use super::math::Aabb;
use super::raster::BatchRef;
use crate::batching::{plan_batches, PlannedBatch};
use crate::grid::Grid;
use crate::morton::MortonGrid;

/// A batched point cloud in memory, as a batch file would hold it.
pub(crate) struct Scene {
    pub grid: Grid,
    /// Integer coordinates in global index order (Morton order).
    pub points: Vec<[i32; 3]>,
    pub batches: Vec<PlannedBatch>,
    /// Coarse, medium, fine words in global index order.
    pub words: [Vec<u32>; 3],
    /// World bounds of all points.
    pub bounds: Aabb,
    /// World bounds per batch.
    pub batch_bounds: Vec<Aabb>,
    /// A grey level from elevation per point, RGBA8.
    pub colors: Vec<u32>,
}

impl Scene {
    /// Sorts `points` in Morton order, splits them into batches of `batch_size` and quantizes them.
    pub fn from_points(grid: Grid, mut points: Vec<[i32; 3]>, batch_size: usize) -> Scene {
        let mut lo = [i64::MAX; 3];
        let mut hi = [i64::MIN; 3];
        for p in &points {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a] as i64);
                hi[a] = hi[a].max(p[a] as i64);
            }
        }
        let mg = MortonGrid::for_bounds(lo, hi);
        points.sort_by_key(|p| (mg.code(p.map(|v| v as i64)), *p));
        let mut batches = Vec::new();
        plan_batches(&points, batch_size, 0, &mut batches);
        let mut words = [Vec::new(), Vec::new(), Vec::new()];
        let mut batch_bounds = Vec::new();
        for b in &batches {
            for p in &points[b.range.clone()] {
                let w = b.grid.encode(*p);
                for i in 0..3 {
                    words[i].push(w[i]);
                }
            }
            let world = |v: [i32; 3]| [0, 1, 2].map(|a| grid.world(a, v[a] as i64));
            batch_bounds.push(Aabb::new(world(b.grid.min), world(b.max)));
        }
        let world = |v: [i64; 3]| [0, 1, 2].map(|a| grid.world(a, v[a]));
        let (zlo, zhi) = (lo[2], hi[2].max(lo[2] + 1));
        let colors = points
            .iter()
            .map(|p| {
                let g = ((p[2] as i64 - zlo) * 255 / (zhi - zlo)) as u32;
                g | g << 8 | g << 16 | 255 << 24
            })
            .collect();
        Scene { grid, points, batches, words, bounds: Aabb::new(world(lo), world(hi)), batch_bounds, colors }
    }

    /// `n` points of a hilly 200 m x 150 m terrain with 0.3 m of noise, placed at `grid.offset`.
    pub fn terrain(n: usize, seed: u64, grid: Grid) -> Scene {
        let mut rng = Rng(seed);
        let points = (0..n)
            .map(|_| {
                let x = rng.unit() * 200.0;
                let y = rng.unit() * 150.0;
                let z = 20.0 + 8.0 * (x / 23.0).sin() * (y / 17.0).cos() + 0.3 * rng.unit();
                let v = [x, y, z];
                [0, 1, 2].map(|a| (v[a] / grid.scale[a]).round() as i32)
            })
            .collect();
        Scene::from_points(grid, points, crate::BATCH_SIZE)
    }

    /// The batches as the rasterizer takes them.
    pub fn refs(&self) -> Vec<BatchRef<'_>> {
        self.batches
            .iter()
            .zip(&self.batch_bounds)
            .map(|(b, bb)| BatchRef {
                grid: b.grid,
                bounds_min: bb.min,
                bounds_max: bb.max,
                words: [0, 1, 2].map(|i| &self.words[i][b.range.clone()]),
                first_index: b.range.start as u32,
            })
            .collect()
    }
}
