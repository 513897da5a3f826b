//! The per-batch decisions of a frame, in f32 from camera-relative data, as the paper makes them
//! on the GPU (paper 003 §3.2-3.3: "at the start of each invocation, we first load the bounding
//! box of the workgroup's batch and immediately abort if it lies outside the view frustum", then
//! choose the coordinate precision): frustum culling, adaptive precision and the batch's
//! [`BatchProjection`]. This is the one definition that both the GPU's plan pass
//! (`shaders/plan.wgsl`, one thread per batch) and the CPU rasterizer ([`super::Planner`]) run,
//! operation for operation, so that the two leave the same keys; only the split of the eye into
//! an integer grid position and a fraction is made in f64, once per frame on the host
//! ([`PlanUniforms::new`]).
//!
//! Georeferenced coordinates stay exact: nothing is ever an absolute world coordinate in f32.
//! Every position is an integer grid coordinate (i32), and the one difference from the eye is
//! taken in integers, in two 16-bit halves, before it becomes f32 ([`eye_offset`]): a batch 1 m
//! from the eye has its offset to within f32 rounding of 1 m whether the scene sits at 0 or at
//! 6.4e6 m.
//!
//! - Culling: the eight corners of the points' integer bounds in view space, tested against the
//!   six planes of the frustum widened by [`CULL_MARGIN_PX`](CULL_MARGIN_PX),
//!   each corner moved by the decode error and a relative slack for f32 rounding towards the
//!   plane: a batch is culled only if all of its decoded points are outside one plane.
//! - Precision: the fewest words whose decode error moves no point more than
//!   [`MAX_ERROR_PX`](super::precision::MAX_ERROR_PX) on screen, by the bound of
//!   [`Camera::displacement_bound_px`] with the farthest-off-axis ratio taken at the nearest depth
//!   (a bound that needs no division per corner). A batch that reaches the near plane takes every
//!   word it has. This bound also implies the paper's 500 px rule (a quarter pixel of decode
//!   error is at most half a pixel per cell), so it is the only rule here.
//! - Projection: as [`Camera::batch_projection`], anchored at the eye's grid position with the
//!   pixel origin at the viewport's centre, for every batch alike: a point's local coordinate is
//!   `p - eye` in integers, so its pixel and depth are a function of the point and the camera
//!   alone, whatever batch or quantization frame holds it (the progressive renderer's one frame,
//!   the batch file's 10,240-point batches, a store's nodes). Only a batch reaching
//!   [`FAR_UNITS`] from the eye on an axis is anchored at its own point nearest to the eye, with
//!   the pixel origin where that projects.
//!
//! The WGSL twin rounds every operation on its own (`opaque` in `shaders/common/decode.wgsl`);
//! Rust never fuses, so the two agree where the GPU's add and multiply are IEEE (Vulkan requires
//! it) and its division is made correct ([`super::gpu::DIVISION_REFINED`]).

use super::camera::{BatchProjection, Camera};
use super::error::RasterError;
use super::gpu::DIVISION_REFINED;
use super::gpu::{PlanBatch, PlanUniforms};
use super::math::Aabb;
use super::precision::{PrecisionMode, MAX_ERROR_PX};
use crate::grid::Grid;
use crate::quantize::{BatchGrid, Precision, MAX_BITS};

/// Relative slack of culling, in units of (distance to the batch + batch size): covers the f32
/// rounding of the per-point depth and pixel against the planes.
pub const CULL_SLACK: f32 = 1e-5;

pub use super::camera::FAR_UNITS;

/// Pixels by which the culling frustum is wider than the viewport on each side: a batch is culled
/// only if every point of it would land at least this far outside, so f32 rounding in the
/// per-point projection can never bring a culled point on screen.
pub const CULL_MARGIN_PX: f64 = 1.0;

/// Choices of a rasterization.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct RasterOptions {
    /// How each batch's precision is chosen.
    pub precision: PrecisionMode,
    /// Whether batches outside the view frustum are skipped (the image is the same either way).
    pub cull: bool,
}

impl Default for RasterOptions {
    fn default() -> Self {
        RasterOptions { precision: PrecisionMode::Adaptive, cull: true }
    }
}

/// What a rasterizer does with one batch in one view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BatchPlan {
    /// The batch has no points.
    Empty,
    /// Frustum culling skipped it.
    Culled,
    /// Draw it at `precision` with `projection`.
    Draw {
        /// How many words per point are read.
        precision: Precision,
        /// The per-batch transform of the per-point loop.
        projection: BatchProjection,
    },
}

/// The per-view decisions about whole batches, shared by the CPU rasterizer and the GPU one so
/// that both cull the same batches, choose the same precision and project with the same
/// [`BatchProjection`] (paper 003 §3.2-3.3). The decisions are those of [`super::plan`]: made in
/// f32 from camera-relative integer offsets, as the GPU's plan pass makes them, so that the GPU
/// can plan every batch itself and still leave the CPU's keys.
#[derive(Clone, Debug)]
pub struct Planner {
    camera: Camera,
    grid: Grid,
    uniforms: PlanUniforms,
}

impl Planner {
    /// The planner of a view; fails if the camera is unusable.
    pub fn new(
        camera: &Camera,
        grid: &Grid,
        options: &RasterOptions,
    ) -> Result<Planner, RasterError> {
        camera.validate()?;
        Ok(Planner {
            camera: *camera,
            grid: *grid,
            uniforms: PlanUniforms::new(camera, grid, options, DIVISION_REFINED),
        })
    }

    /// The camera planned for.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// The f32 constants the plan is made from (the plan pass's uniforms).
    pub fn uniforms(&self) -> &PlanUniforms {
        &self.uniforms
    }

    /// Culls one batch of `len` points with quantization frame `batch` and world `bounds`, and
    /// chooses its precision and projection.
    pub fn plan(&self, batch: &BatchGrid, bounds: &Aabb, len: usize) -> BatchPlan {
        if len == 0 {
            return BatchPlan::Empty;
        }
        let count = len.min(u32::MAX as usize) as u32;
        plan_batch(&PlanBatch::new(&self.grid, batch, bounds, count, 0, 0, 0), &self.uniforms)
    }
}

/// The eye's grid units are clamped to this magnitude (a camera 2^31 units from the origin of
/// the grid is drawn as if it were here).
const EYE_LIMIT: f64 = (i32::MAX - 2) as f64;

impl PlanUniforms {
    /// The plan constants of a view of points on `grid`.
    pub fn new(
        camera: &Camera,
        grid: &Grid,
        options: &RasterOptions,
        division: u32,
    ) -> PlanUniforms {
        let axes = camera.axes().unwrap_or(super::camera::ViewAxes {
            right: [1.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            forward: [0.0, 0.0, 1.0],
        });
        let mut eye_int = [0i32; 3];
        let mut eye_frac = [0f32; 3];
        for a in 0..3 {
            let units = (camera.eye[a] - grid.offset[a]) / grid.scale[a];
            let units = if units.is_nan() { 0.0 } else { units.clamp(-EYE_LIMIT, EYE_LIMIT) };
            let floor = units.floor();
            eye_int[a] = floor as i32;
            // In [0, 1); f32 rounding may give 1.0, which the anchor and offsets take as it is.
            eye_frac[a] = (units - floor) as f32;
        }
        let scaled = |ax: [f64; 3]| {
            [
                (ax[0] * grid.scale[0]) as f32,
                (ax[1] * grid.scale[1]) as f32,
                (ax[2] * grid.scale[2]) as f32,
                0.0,
            ]
        };
        let (w, h) = (camera.width as f64, camera.height as f64);
        let [hx, hy] = camera.half_extent();
        let words = match options.precision {
            PrecisionMode::Adaptive => 0,
            PrecisionMode::Fixed(p) => p.words() as u32,
        };
        PlanUniforms {
            eye_int,
            perspective: camera.is_perspective() as u32,
            eye_frac,
            batches: 0,
            right: scaled(axes.right),
            up: scaled(axes.up),
            forward: scaled(axes.forward),
            scale: [
                grid.scale[0].abs() as f32,
                grid.scale[1].abs() as f32,
                grid.scale[2].abs() as f32,
                0.0,
            ],
            sx: (0.5 * w / hx) as f32,
            sy: (0.5 * h / hy) as f32,
            cx: (0.5 * w) as f32,
            cy: (0.5 * h) as f32,
            near: camera.near as f32,
            far: camera.far as f32,
            width: w as f32,
            height: h as f32,
            words,
            cull: options.cull as u32,
            division,
            zero: 0,
            margin_px: CULL_MARGIN_PX as f32,
            slack: CULL_SLACK,
            max_error_px: MAX_ERROR_PX as f32,
            _pad: 0,
        }
    }
}

impl PlanBatch {
    /// The plan pass's record of a batch of `count` points with quantization frame `batch` and
    /// world `bounds` (converted back to integer offsets, clamped into the frame; an empty box
    /// stands for the whole frame).
    pub fn new(
        grid: &Grid,
        batch: &BatchGrid,
        bounds: &Aabb,
        count: u32,
        offset: u32,
        first_index: u32,
        record: u32,
    ) -> PlanBatch {
        let mut lo = [0u32; 3];
        let mut hi = [0u32; 3];
        for a in 0..3 {
            let top = (1u64 << batch.bits[a].min(MAX_BITS as u8)) - 1;
            let unit = |w: f64| {
                let u = ((w - grid.offset[a]) / grid.scale[a]).round() - batch.min[a] as f64;
                if u.is_nan() {
                    0
                } else {
                    u.clamp(0.0, top as f64) as u32
                }
            };
            if bounds.is_empty() {
                hi[a] = top as u32;
            } else {
                let (u0, u1) = (unit(bounds.min[a]), unit(bounds.max[a]));
                lo[a] = u0.min(u1);
                hi[a] = u0.max(u1);
            }
        }
        PlanBatch {
            min: batch.min,
            record,
            lo,
            offset,
            hi,
            count,
            bits: batch.bits.map(u32::from),
            first_index,
        }
    }
}

/// `p - e` for grid coordinates, in f32: the difference is taken in two 16-bit halves so that it
/// never overflows, and rounds once (exact below 2^24 units).
#[inline]
pub fn eye_offset(p: i32, e: i32) -> f32 {
    let high = ((p >> 16) - (e >> 16)) as f32 * 65536.0;
    let low = ((p & 0xffff) - (e & 0xffff)) as f32;
    high + low
}

/// `x / d` as the GPU divides ([`super::gpu::DIVISION_REFINED`] is correctly rounded, as Rust is).
#[inline]
fn divide(x: f32, d: f32) -> f32 {
    x / d
}

/// `(a.x * v.x + a.y * v.y) + a.z * v.z`, each operation rounded on its own.
#[inline]
fn dot3(a: &[f32; 4], v: [f32; 3]) -> f32 {
    (a[0] * v[0] + a[1] * v[1]) + a[2] * v[2]
}

/// `(|a.x| e.x + |a.y| e.y) + |a.z| e.z`: how far an offset of at most `e` per axis reaches along `a`.
#[inline]
fn reach(a: &[f32; 4], e: [f32; 3]) -> f32 {
    (a[0].abs() * e[0] + a[1].abs() * e[1]) + a[2].abs() * e[2]
}

/// The decode error of `words` words per axis, in grid units: `(2^m - 1) / 2` with `m` the
/// unloaded low bits ([`BatchGrid::error_bound`]).
#[inline]
fn error_units(bits: &[u32; 3], words: u32) -> [f32; 3] {
    [0, 1, 2].map(|a| {
        let missing = bits[a].saturating_sub(words * 10);
        ((1u32 << missing) - 1) as f32 * 0.5
    })
}

/// Whether the decode error `e` (grid units) of a batch whose view-space corners span depth
/// `[zmin, ..]` and reach `xm`, `ym` off-axis moves no point by `max_error_px` or more.
#[inline]
fn error_ok(u: &PlanUniforms, e: [f32; 3], zmin: f32, xm: f32, ym: f32) -> bool {
    let ex = reach(&u.right, e);
    let ey = reach(&u.up, e);
    let ez = reach(&u.forward, e);
    if u.perspective == 0 {
        let bx = u.sx * ex;
        let by = u.sy * ey;
        return bx * bx + by * by < u.max_error_px * u.max_error_px;
    }
    // |Δpx| <= sx (Ex + Tx Ez) / D with Tx <= xm / zmin and D = zmin - Ez, multiplied through by
    // zmin D (both positive) so that no division is needed.
    let d = zmin - ez;
    if !(d > u.near) {
        return false;
    }
    let bx = u.sx * (ex * zmin + xm * ez);
    let by = u.sy * (ey * zmin + ym * ez);
    let limit = u.max_error_px * zmin * d;
    bx * bx + by * by < limit * limit
}

/// The plan of one batch (the twin of `plan_batch` in `shaders/plan.wgsl`).
pub fn plan_batch(b: &PlanBatch, u: &PlanUniforms) -> BatchPlan {
    if b.count == 0 {
        return BatchPlan::Empty;
    }
    // The eye, rounded to the nearest grid coordinate (the host keeps eye_int within ±(2^31 - 2)).
    let er = [0, 1, 2].map(|a| u.eye_int[a] + (u.eye_frac[a] >= 0.5) as i32);
    // View-space corners of the points' bounds, and how far they reach.
    let mut zmin = f32::MAX;
    let mut zmax = f32::MIN;
    let mut xm = 0f32;
    let mut ym = 0f32;
    let mut corners = [[0f32; 3]; 8];
    for (i, c) in corners.iter_mut().enumerate() {
        let rel = [0, 1, 2].map(|a| {
            let off = if i >> a & 1 == 0 { b.lo[a] } else { b.hi[a] };
            eye_offset(b.min[a].wrapping_add(off as i32), u.eye_int[a]) - u.eye_frac[a]
        });
        let v = [dot3(&u.right, rel), dot3(&u.up, rel), dot3(&u.forward, rel)];
        zmin = zmin.min(v[2]);
        zmax = zmax.max(v[2]);
        xm = xm.max(v[0].abs());
        ym = ym.max(v[1].abs());
        *c = v;
    }
    // Precision: every word the batch needs, fewer where the decode error stays small on screen.
    let needed = match b.bits.iter().copied().max().unwrap_or(0) {
        0..=10 => 1,
        11..=20 => 2,
        _ => 3,
    };
    let words = if u.words != 0 {
        u.words.min(needed)
    } else {
        let mut w = 1;
        while w < needed && !error_ok(u, error_units(&b.bits, w), zmin, xm, ym) {
            w += 1;
        }
        w
    };
    let e = error_units(&b.bits, words);
    if u.cull != 0 {
        // Each corner may move by the decode error and the slack towards a plane.
        let size = (((b.hi[0] - b.lo[0]) as f32 * u.scale[0]
            + (b.hi[1] - b.lo[1]) as f32 * u.scale[1])
            + (b.hi[2] - b.lo[2]) as f32 * u.scale[2])
            + (xm + ym + zmax.abs().max(zmin.abs()));
        let s = u.slack * size;
        let ex = reach(&u.right, e) + s;
        let ey = reach(&u.up, e) + s;
        let ez = reach(&u.forward, e) + s;
        let m = u.margin_px;
        // Planes n . (x, y, z) + d >= 0 inside; a corner is outside when even moved by (ex, ey, ez)
        // towards the plane it stays below 0.
        let planes: [[f32; 4]; 6] = if u.perspective != 0 {
            [
                [0.0, 0.0, 1.0, -u.near],
                [0.0, 0.0, -1.0, u.far],
                [u.sx, 0.0, u.cx + m, 0.0],
                [-u.sx, 0.0, (u.width + m) - u.cx, 0.0],
                [0.0, -u.sy, u.cy + m, 0.0],
                [0.0, u.sy, (u.height + m) - u.cy, 0.0],
            ]
        } else {
            [
                [0.0, 0.0, 1.0, -u.near],
                [0.0, 0.0, -1.0, u.far],
                [u.sx, 0.0, 0.0, u.cx + m],
                [-u.sx, 0.0, 0.0, (u.width + m) - u.cx],
                [0.0, -u.sy, 0.0, u.cy + m],
                [0.0, u.sy, 0.0, (u.height + m) - u.cy],
            ]
        };
        for p in &planes {
            let moved = (p[0].abs() * ex + p[1].abs() * ey) + p[2].abs() * ez;
            let outside = corners
                .iter()
                .all(|c| ((p[0] * c[0] + p[1] * c[1]) + p[2] * c[2]) + p[3] + moved < 0.0);
            if outside {
                return BatchPlan::Culled;
            }
        }
    }
    // The anchor: the eye's grid position (rounded), the same for every batch, so that a point's
    // local coordinate `p - eye` and with it its pixel and depth do not depend on which batch (or
    // quantization frame) holds it: the batch rasterizer and the progressive renderer (one frame
    // over everything) give a point the same key. The local origin adds the centre of the
    // unloaded bits. Only a batch reaching 2^30 grid units from the eye on an axis (where `p -
    // eye` could leave i32) is anchored at its own grid point nearest to the eye instead.
    let far = (0..3).any(|a| {
        let lo = eye_offset(b.min[a].wrapping_add(b.lo[a] as i32), er[a]).abs();
        let hi = eye_offset(b.min[a].wrapping_add(b.hi[a] as i32), er[a]).abs();
        lo.max(hi) >= FAR_UNITS
    });
    let mut anchor = [0i32; 3];
    let mut shift = [0u32; 3];
    let mut rel = [0f32; 3];
    for a in 0..3 {
        let base = if far {
            let lo = b.min[a].wrapping_add(b.lo[a] as i32);
            let hi = b.min[a].wrapping_add(b.hi[a] as i32);
            let an = if er[a] <= lo {
                b.lo[a]
            } else if er[a] >= hi {
                b.hi[a]
            } else {
                er[a].wrapping_sub(b.min[a]) as u32
            };
            b.min[a].wrapping_add(an as i32)
        } else {
            er[a]
        };
        anchor[a] = base.wrapping_sub(b.min[a]);
        shift[a] = MAX_BITS - b.bits[a].min(MAX_BITS);
        let missing = b.bits[a].saturating_sub(words * 10);
        let mid = ((1u32 << missing) - 1) as f32 * 0.5;
        rel[a] = (eye_offset(base, u.eye_int[a]) - u.eye_frac[a]) + mid;
    }
    let wx = dot3(&u.right, rel);
    let wy = dot3(&u.up, rel);
    let wz = dot3(&u.forward, rel);
    // The pixel origin: the viewport's centre (eye anchor: the same for every batch), or where a
    // far batch's anchor projects, clamped to the viewport.
    let (px, py) = if !far {
        (u.cx, u.cy)
    } else if u.perspective != 0 {
        if wz >= u.near {
            (divide(u.sx * wx, wz) + u.cx, u.cy - divide(u.sy * wy, wz))
        } else {
            (u.cx, u.cy)
        }
    } else {
        (u.sx * wx + u.cx, u.cy - u.sy * wy)
    };
    let ox = (px.clamp(0.0, u.width) + 0.5).floor();
    let oy = (py.clamp(0.0, u.height) + 0.5).floor();
    let (dx, dy) = (u.cx - ox, u.cy - oy);
    let f = &u.forward;
    let m = if u.perspective != 0 {
        [
            [
                u.sx * u.right[0] + dx * f[0],
                u.sx * u.right[1] + dx * f[1],
                u.sx * u.right[2] + dx * f[2],
                u.sx * wx + dx * wz,
            ],
            [
                dy * f[0] - u.sy * u.up[0],
                dy * f[1] - u.sy * u.up[1],
                dy * f[2] - u.sy * u.up[2],
                dy * wz - u.sy * wy,
            ],
            [f[0], f[1], f[2], wz],
            [f[0], f[1], f[2], wz],
        ]
    } else {
        [
            [u.sx * u.right[0], u.sx * u.right[1], u.sx * u.right[2], u.sx * wx + dx],
            [-(u.sy * u.up[0]), -(u.sy * u.up[1]), -(u.sy * u.up[2]), dy - u.sy * wy],
            [f[0], f[1], f[2], wz],
            [0.0, 0.0, 0.0, 1.0],
        ]
    };
    let precision = match words {
        1 => Precision::Bits10,
        2 => Precision::Bits20,
        _ => Precision::Bits30,
    };
    BatchPlan::Draw {
        precision,
        projection: BatchProjection {
            pixel_from_local: m,
            anchor,
            words,
            shift,
            _pad0: 0,
            pixel_origin: [ox as i32, oy as i32],
            _pad1: [0; 2],
        },
    }
}
