//! Helpers shared by the render tests of mortar-core and mortar-render (not a stable API): a
//! seeded generator and synthetic batched scenes.

/// A small deterministic generator (SplitMix64).
pub struct Rng(pub u64);

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
pub struct Scene {
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
        Scene::quantized(grid, points, batches, (lo, hi))
    }

    /// One batch per group of points, in the order given (no sort): scenes whose batches have a
    /// chosen shape (each group must fit a 30-bit frame).
    pub fn from_groups(grid: Grid, groups: Vec<Vec<[i32; 3]>>) -> Scene {
        let mut points = Vec::new();
        let mut batches = Vec::new();
        let (mut lo, mut hi) = ([i64::MAX; 3], [i64::MIN; 3]);
        for g in groups {
            let (min, max) = crate::batching::int_bounds(&g);
            for a in 0..3 {
                lo[a] = lo[a].min(min[a] as i64);
                hi[a] = hi[a].max(max[a] as i64);
            }
            let grid =
                crate::quantize::BatchGrid::for_bounds(min, max).expect("a group fits 30 bits");
            batches.push(PlannedBatch { range: points.len()..points.len() + g.len(), grid, max });
            points.extend(g);
        }
        Scene::quantized(grid, points, batches, (lo, hi))
    }

    /// Words, bounds and colours of points already batched.
    fn quantized(
        grid: Grid,
        points: Vec<[i32; 3]>,
        batches: Vec<PlannedBatch>,
        (lo, hi): ([i64; 3], [i64; 3]),
    ) -> Scene {
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
        Scene {
            grid,
            points,
            batches,
            words,
            bounds: Aabb::new(world(lo), world(hi)),
            batch_bounds,
            colors,
        }
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

use super::camera::Camera;
use super::plan::{BatchPlan, Planner, RasterOptions};
use super::precision::PrecisionMode;
use crate::quantize::join_words;

/// Per-point comparison of the f32 batch projection with the f64 reference, over a scene.
#[derive(Debug, Default)]
pub struct ProjectionCheck {
    /// Points whose reference pixel lies in the viewport (and depth range).
    pub on_screen: usize,
    /// Of those, points the f32 projection puts in another pixel (or drops).
    pub other_pixel: usize,
    /// Points left out of the pixel comparison because their reference position lies within 1e-6 px
    /// of a pixel edge: integer-grid data seen by a framed camera puts some points exactly on an
    /// edge, where the f64 reference's own rounding decides the side.
    pub on_edge: usize,
    /// Largest distance (pixels, per axis) between the f32 and f64 projections of a decoded point.
    pub worst_f32_px: f64,
    /// Largest distance (pixels, per axis) between a point decoded at the chosen precision and the
    /// exact point, both projected in f64, over batches drawn at less than full precision.
    pub worst_decode_px: f64,
    /// Points projected at each precision.
    pub by_precision: [usize; 3],
}

impl Scene {
    /// World position of a local position (relative to the grid offset).
    pub fn world(&self, local: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| self.grid.offset[a] + local[a])
    }

    /// Compares, for every point, the rasterizer's f32 projection with the f64 reference.
    pub fn check_projection(&self, cam: &Camera, mode: PrecisionMode) -> ProjectionCheck {
        let mut c = ProjectionCheck::default();
        let (w, h) = (cam.width as f64, cam.height as f64);
        let near = cam.near as f32;
        let far = cam.far as f32;
        // The rasterizer's own plan (precision and projection, in f32 as the GPU makes it).
        let planner =
            Planner::new(cam, &self.grid, &RasterOptions { precision: mode, cull: false })
                .expect("a valid camera");
        for (b, bounds) in self.batches.iter().zip(&self.batch_bounds) {
            let BatchPlan::Draw { precision, projection: bp } =
                planner.plan(&b.grid, bounds, b.range.len())
            else {
                continue;
            };
            c.by_precision[precision.words() - 1] += b.range.len();
            for i in b.range.clone() {
                let words = [self.words[0][i], self.words[1][i], self.words[2][i]];
                let rel = b.grid.decode_relative(words, precision);
                let decoded = [0, 1, 2].map(|a| {
                    self.grid.offset[a] + self.grid.scale[a] * (b.grid.min[a] as f64 + rel[a])
                });
                let exact = [0, 1, 2].map(|a| self.grid.world(a, self.points[i][a] as i64));
                let Some(r) = cam.project(decoded) else { continue };
                if let Some(e) = cam.project(exact) {
                    if precision.bits() < 30 {
                        c.worst_decode_px =
                            c.worst_decode_px.max((r.x - e.x).abs()).max((r.y - e.y).abs());
                    }
                }
                if !(r.x >= 0.0 && r.x < w && r.y >= 0.0 && r.y < h) {
                    continue;
                }
                let edge = |v: f64| (v - v.round()).abs() < 1e-6;
                if edge(r.x) || edge(r.y) {
                    c.on_edge += 1;
                    continue;
                }
                c.on_screen += 1;
                let [x, y, d, wc] = bp.transform(bp.local(join_words(words, precision)));
                let (fx, fy) = (
                    (x / wc) as f64 + bp.pixel_origin[0] as f64,
                    (y / wc) as f64 + bp.pixel_origin[1] as f64,
                );
                c.worst_f32_px = c.worst_f32_px.max((fx - r.x).abs()).max((fy - r.y).abs());
                let same =
                    d >= near && d <= far && fx.floor() == r.x.floor() && fy.floor() == r.y.floor();
                if !same {
                    c.other_pixel += 1;
                }
            }
        }
        c
    }

    /// Cameras that see the scene: every preset in perspective and orthographic at 1920x1080,
    /// and two close-ups from 2 m above the terrain (local terrain coordinates of [`Scene::terrain`]).
    pub fn cameras(&self) -> Vec<Camera> {
        use super::camera::{Projection, ViewPreset};
        let mut cams = Vec::new();
        for preset in ViewPreset::ALL {
            cams.push(Camera::frame_perspective(&self.bounds, preset, 0.8, 1920, 1080).unwrap());
            cams.push(Camera::frame_orthographic(&self.bounds, preset, 1920, 1080).unwrap());
        }
        for (eye, target) in
            [([60.0, 40.0, 32.0], [110.0, 90.0, 15.0]), ([150.0, 20.0, 30.0], [140.0, 60.0, 22.0])]
        {
            cams.push(Camera {
                eye: self.world(eye),
                target: self.world(target),
                up: [0.0, 0.0, 1.0],
                projection: Projection::Perspective { fov_y: 0.9 },
                near: 0.05,
                far: 1e4,
                width: 2560,
                height: 1440,
            });
        }
        cams
    }
}
