//! The CPU reference rasterizer (paper 003 §3.2-3.3): one task per batch, frustum culling of whole
//! batches, adaptive precision, and per point a projection, an early depth test and an atomic
//! minimum on the 64-bit depth|index key.
//!
//! The GPU rasterizer (wgpu, `atomicMin` on `atomic<u64>`) follows the same steps with the same
//! per-batch record ([`BatchProjection`]) and must produce the same keys; this module is the
//! reference it is tested against. Batches run in parallel on rayon; the image does not depend on
//! their order or on thread scheduling because the smallest key wins in every pixel.
//!
//! Per point only the words the batch's precision needs are read, the decode is integer work
//! ([`crate::quantize::join_words`] and a shift), and the transform is f32: no f64, no allocation,
//! no dynamic dispatch. As in §3.4, the word arrays are read as linear streams (struct of arrays,
//! one loop per batch) and the early depth test keeps most points away from the atomic.

use super::camera::{BatchProjection, Camera};
use super::error::RasterError;
use super::framebuffer::Framebuffer;
use super::math::Aabb;
use super::plan::{BatchPlan, Planner, RasterOptions};
use crate::grid::Grid;
use crate::quantize::{BatchGrid, Precision};
use rayon::prelude::*;

/// One batch to draw: its quantization frame, world bounds and packed coordinate words.
#[derive(Clone, Copy, Debug)]
pub struct BatchRef<'a> {
    /// The batch's quantization frame (integer min and bits per axis).
    pub grid: BatchGrid,
    /// Smallest world coordinate of the batch's points.
    pub bounds_min: [f64; 3],
    /// Largest world coordinate of the batch's points.
    pub bounds_max: [f64; 3],
    /// Coarse, medium and fine words, one per point each; all three of the same length.
    pub words: [&'a [u32]; 3],
    /// Global index of the batch's first point (the index written to the framebuffer).
    pub first_index: u32,
}

impl BatchRef<'_> {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.words[0].len()
    }

    /// Whether the batch has no points.
    pub fn is_empty(&self) -> bool {
        self.words[0].is_empty()
    }

    /// The world bounds as a box.
    pub fn bounds(&self) -> Aabb {
        Aabb::new(self.bounds_min, self.bounds_max)
    }
}

/// What a rasterization did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct RasterStats {
    /// Batches looked at.
    pub batches: u64,
    /// Batches skipped by frustum culling.
    pub batches_culled: u64,
    /// Batches whose points were projected.
    pub batches_drawn: u64,
    /// Points projected, by the number of words loaded: `[10 bits, 20 bits, 30 bits]`.
    pub points_by_precision: [u64; 3],
    /// Points that landed in the viewport and depth range and were depth-tested.
    pub points_drawn: u64,
}

impl RasterStats {
    /// Points projected at any precision.
    pub fn points_projected(&self) -> u64 {
        self.points_by_precision.iter().sum()
    }

    /// The sum of two statistics.
    pub fn merge(mut self, o: RasterStats) -> RasterStats {
        self.batches += o.batches;
        self.batches_culled += o.batches_culled;
        self.batches_drawn += o.batches_drawn;
        for i in 0..3 {
            self.points_by_precision[i] += o.points_by_precision[i];
        }
        self.points_drawn += o.points_drawn;
        self
    }
}

/// Viewport and depth range as the CPU per-point loop reads them (the same f32 values the GPU
/// passes read from [`FrameUniforms`](super::gpu::FrameUniforms); this struct has no WGSL mirror).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RasterUniforms {
    /// Viewport width in pixels.
    pub width: u32,
    /// Viewport height in pixels.
    pub height: u32,
    /// Near plane (view depth), f32.
    pub near: f32,
    /// Far plane (view depth), f32.
    pub far: f32,
}

const _: () = assert!(std::mem::size_of::<RasterUniforms>() == 16);

impl RasterUniforms {
    /// The uniforms of a camera.
    pub fn new(camera: &Camera) -> RasterUniforms {
        RasterUniforms {
            width: camera.width,
            height: camera.height,
            near: camera.near as f32,
            far: camera.far as f32,
        }
    }
}

/// Checks the batches a rasterizer is given: equal word counts and 32-bit point indices.
pub fn validate_batches(batches: &[BatchRef<'_>]) -> Result<(), RasterError> {
    for (i, b) in batches.iter().enumerate() {
        let lengths = b.words.map(<[u32]>::len);
        if lengths[1] != lengths[0] || lengths[2] != lengths[0] {
            return Err(RasterError::WordCounts { batch: i, lengths });
        }
        if b.first_index as u64 + lengths[0] as u64 > 1u64 << 32 {
            return Err(RasterError::IndexOverflow {
                batch: i,
                first_index: b.first_index,
                count: lengths[0],
            });
        }
    }
    Ok(())
}

/// Draws `batches` into `fb` (which is not cleared: several calls accumulate, e.g. progressive or
/// per-file passes). `grid` is the world grid of the batches' integer coordinates.
pub fn rasterize(
    fb: &Framebuffer,
    batches: &[BatchRef<'_>],
    grid: &Grid,
    camera: &Camera,
    options: &RasterOptions,
) -> Result<RasterStats, RasterError> {
    check_view(fb, camera)?;
    validate_batches(batches)?;
    let planner = Planner::new(camera, grid, options)?;
    let uniforms = RasterUniforms::new(camera);
    let stats = batches
        .par_iter()
        .map(|b| draw_batch(fb, b, &planner, &uniforms))
        .reduce(RasterStats::default, RasterStats::merge);
    Ok(stats)
}

/// The camera is usable and matches the framebuffer's size.
fn check_view(fb: &Framebuffer, camera: &Camera) -> Result<(), RasterError> {
    camera.validate()?;
    if fb.width() != camera.width || fb.height() != camera.height {
        return Err(RasterError::Viewport {
            fb_width: fb.width(),
            fb_height: fb.height(),
            width: camera.width,
            height: camera.height,
        });
    }
    Ok(())
}

/// Culls, chooses the precision and draws one batch.
fn draw_batch<S: Sink>(
    fb: &S,
    b: &BatchRef<'_>,
    planner: &Planner,
    uniforms: &RasterUniforms,
) -> RasterStats {
    plan_and_draw(planner, &b.grid, &b.bounds(), b.len(), |precision, bp, perspective| {
        match precision {
            Precision::Bits10 => draw_points::<1, S>(fb, bp, b, uniforms, perspective),
            Precision::Bits20 => draw_points::<2, S>(fb, bp, b, uniforms, perspective),
            Precision::Bits30 => draw_points::<3, S>(fb, bp, b, uniforms, perspective),
        }
    })
}

/// The per-batch statistics around one planned draw: `draw(precision, projection, perspective)`
/// runs only for a batch that is neither empty nor culled and returns the points it drew.
fn plan_and_draw(
    planner: &Planner,
    grid: &BatchGrid,
    bounds: &Aabb,
    len: usize,
    draw: impl FnOnce(Precision, &BatchProjection, bool) -> u64,
) -> RasterStats {
    let mut stats = RasterStats { batches: 1, ..RasterStats::default() };
    let (precision, bp) = match planner.plan(grid, bounds, len) {
        BatchPlan::Empty => return stats,
        BatchPlan::Culled => {
            stats.batches_culled = 1;
            return stats;
        }
        BatchPlan::Draw { precision, projection } => (precision, projection),
    };
    stats.batches_drawn = 1;
    stats.points_by_precision[precision.words() - 1] = len as u64;
    stats.points_drawn = draw(precision, &bp, planner.camera().is_perspective());
    stats
}

/// Points gathered from anywhere into one quantization frame, each with its own global index:
/// the Reproject buffer of paper 000 §3.4, which "also stores the shuffle point index" of each
/// visible point so that the reprojected point writes the same index into the framebuffer. The
/// per-point arithmetic is that of [`BatchRef`]s (the same [`Planner`] decisions, the same
/// loop), so a point drawn from a `GatheredRef` leaves the same key as when it is drawn from a
/// `BatchRef` with the same frame, bounds and index.
#[derive(Clone, Copy, Debug)]
pub struct GatheredRef<'a> {
    /// The quantization frame the words are relative to.
    pub grid: BatchGrid,
    /// Smallest world coordinate of the frame's points (as in [`BatchRef::bounds_min`]).
    pub bounds_min: [f64; 3],
    /// Largest world coordinate of the frame's points.
    pub bounds_max: [f64; 3],
    /// Coarse, medium and fine words, one per point each.
    pub words: [&'a [u32]; 3],
    /// The global index of each point (written to the framebuffer).
    pub indices: &'a [u32],
}

impl GatheredRef<'_> {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.words[0].len()
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.words[0].is_empty()
    }

    /// The world bounds as a box.
    pub fn bounds(&self) -> Aabb {
        Aabb::new(self.bounds_min, self.bounds_max)
    }
}

/// [`rasterize`] for gathered points with explicit indices (see [`GatheredRef`]); `fb` is not
/// cleared.
pub fn rasterize_gathered(
    fb: &Framebuffer,
    batches: &[GatheredRef<'_>],
    grid: &Grid,
    camera: &Camera,
    options: &RasterOptions,
) -> Result<RasterStats, RasterError> {
    check_view(fb, camera)?;
    for (i, b) in batches.iter().enumerate() {
        let lengths = b.words.map(<[u32]>::len);
        if lengths[1] != lengths[0] || lengths[2] != lengths[0] {
            return Err(RasterError::WordCounts { batch: i, lengths });
        }
        if b.indices.len() != lengths[0] {
            return Err(RasterError::IndexCount {
                batch: i,
                points: lengths[0],
                indices: b.indices.len(),
            });
        }
    }
    let planner = Planner::new(camera, grid, options)?;
    let uniforms = RasterUniforms::new(camera);
    let stats = batches
        .par_iter()
        .map(|b| draw_gathered_batch(fb, b, &planner, &uniforms))
        .reduce(RasterStats::default, RasterStats::merge);
    Ok(stats)
}

/// [`draw_batch`] for a [`GatheredRef`].
fn draw_gathered_batch<S: Sink>(
    fb: &S,
    b: &GatheredRef<'_>,
    planner: &Planner,
    uniforms: &RasterUniforms,
) -> RasterStats {
    plan_and_draw(planner, &b.grid, &b.bounds(), b.len(), |precision, bp, perspective| {
        match precision {
            Precision::Bits10 => draw_listed::<1, S>(fb, bp, b, uniforms, perspective),
            Precision::Bits20 => draw_listed::<2, S>(fb, bp, b, uniforms, perspective),
            Precision::Bits30 => draw_listed::<3, S>(fb, bp, b, uniforms, perspective),
        }
    })
}

/// Where the per-point loop puts each drawn point's key: the framebuffer's depth test, or the
/// tie pass of [`count_depth_ties`].
trait Sink: Sync {
    /// Point key `key` landed in `pixel`.
    fn put(&self, pixel: usize, key: u64);
}

impl Sink for Framebuffer {
    #[inline(always)]
    fn put(&self, pixel: usize, key: u64) {
        self.depth_test(pixel, key);
    }
}

/// The tie pass: marks the pixels in which a point other than the winner has the winner's very
/// depth.
struct TieMarks<'a> {
    keys: &'a [u64],
    marks: Vec<std::sync::atomic::AtomicU64>,
}

impl Sink for TieMarks<'_> {
    #[inline(always)]
    fn put(&self, pixel: usize, key: u64) {
        let won = self.keys[pixel];
        if key >> 32 == won >> 32 && key != won {
            self.marks[pixel / 64]
                .fetch_or(1 << (pixel % 64), std::sync::atomic::Ordering::Relaxed);
        }
    }
}

/// The pixels of `keys` (the converged or brute-force keys of drawing every point of `batches`
/// for `camera` with `options`) in which another point has exactly the winner's depth: there the
/// smaller point index decides, so a renderer that numbers the same points otherwise (the batch
/// file in Morton order, the progressive renderer by shuffled slot) may show another of them.
/// A second pass over every point; paper 000's "z-fighting" caveat, counted.
pub fn count_depth_ties(
    keys: &[u64],
    batches: &[BatchRef<'_>],
    grid: &Grid,
    camera: &Camera,
    options: &RasterOptions,
) -> Result<u64, RasterError> {
    camera.validate()?;
    if keys.len() != camera.width as usize * camera.height as usize {
        return Err(RasterError::Viewport {
            fb_width: keys.len() as u32,
            fb_height: 1,
            width: camera.width,
            height: camera.height,
        });
    }
    validate_batches(batches)?;
    let planner = Planner::new(camera, grid, options)?;
    let uniforms = RasterUniforms::new(camera);
    let marks = TieMarks {
        keys,
        marks: (0..keys.len().div_ceil(64)).map(|_| std::sync::atomic::AtomicU64::new(0)).collect(),
    };
    batches.par_iter().for_each(|b| {
        draw_batch(&marks, b, &planner, &uniforms);
    });
    Ok(marks
        .marks
        .iter()
        .map(|m| m.load(std::sync::atomic::Ordering::Relaxed).count_ones() as u64)
        .sum())
}

/// Points per block of the two-phase per-point loop.
const BLOCK: usize = 64;

/// Marks a point of a block that is not drawn.
const SKIP: u32 = u32::MAX;

/// The per-batch constants of the per-point loop, taken from the [`BatchProjection`] and the
/// uniforms.
#[derive(Clone, Copy, Debug)]
struct Kernel {
    /// Rows X, Y, D of `pixel_from_local` (W is D for perspective and 1 for orthographic).
    m: [[f32; 4]; 3],
    shift: [u32; 3],
    anchor: [i32; 3],
    near: f32,
    far: f32,
    x_lo: f32,
    x_hi: f32,
    y_lo: f32,
    y_hi: f32,
    origin: [i32; 2],
    width: i32,
}

impl Kernel {
    fn new(bp: &BatchProjection, u: &RasterUniforms) -> Kernel {
        let [ox, oy] = bp.pixel_origin;
        let m = &bp.pixel_from_local;
        Kernel {
            m: [m[0], m[1], m[2]],
            shift: bp.shift,
            anchor: bp.anchor,
            near: u.near,
            far: u.far,
            x_lo: -ox as f32,
            x_hi: (u.width as i32 - ox) as f32,
            y_lo: -oy as f32,
            y_hi: (u.height as i32 - oy) as f32,
            origin: [ox, oy],
            width: u.width as i32,
        }
    }
}

/// `floor(v)` as an i32, exact for `|v| < 1e9`; any other input (NaN included) gives some value
/// the caller rejects anyway. Truncation, minus one below zero where the value is not whole: no
/// libm call (which `f32::floor` is on baseline x86-64) and no saturating conversion (which does
/// not vectorize).
#[inline(always)]
fn floor_i32(v: f32) -> i32 {
    // `max` returns the other operand for NaN, so the clamped value is always finite (`clamp`
    // would keep the NaN, which `to_int_unchecked` must not see).
    #[allow(clippy::manual_clamp)]
    let c = v.max(-1.0e9).min(1.0e9);
    // SAFETY: `c` is finite and within i32's range.
    let t = unsafe { c.to_int_unchecked::<i32>() };
    t - ((c < t as f32) as i32)
}

/// Phase 1 of a block: decodes, projects and tests up to [`BLOCK`] points, writing each point's
/// pixel (or [`SKIP`]) and depth bits. Branch-free over the block so that it vectorizes.
#[inline(always)]
fn project_block<const WORDS: usize, const PERSPECTIVE: bool>(
    k: &Kernel,
    coarse: &[u32],
    medium: &[u32],
    fine: &[u32],
    pixels: &mut [u32; BLOCK],
    depths: &mut [u32; BLOCK],
) {
    let n = coarse.len().min(BLOCK);
    let medium = &medium[..if WORDS >= 2 { n } else { 0 }];
    let fine = &fine[..if WORDS >= 3 { n } else { 0 }];
    for i in 0..n {
        // join_words, written out per axis: bits [20, 30) from the coarse word, [10, 20) medium, [0, 10) fine.
        let c = coarse[i];
        let mut q = [(c & 0x3ff) << 20, ((c >> 10) & 0x3ff) << 20, ((c >> 20) & 0x3ff) << 20];
        if WORDS >= 2 {
            let w = medium[i];
            q = [
                q[0] | (w & 0x3ff) << 10,
                q[1] | ((w >> 10) & 0x3ff) << 10,
                q[2] | ((w >> 20) & 0x3ff) << 10,
            ];
        }
        if WORDS >= 3 {
            let w = fine[i];
            q = [q[0] | (w & 0x3ff), q[1] | ((w >> 10) & 0x3ff), q[2] | ((w >> 20) & 0x3ff)];
        }
        // BatchProjection::local and ::transform, in the same order of operations.
        let l = [
            ((q[0] >> k.shift[0]) as i32).wrapping_sub(k.anchor[0]) as f32,
            ((q[1] >> k.shift[1]) as i32).wrapping_sub(k.anchor[1]) as f32,
            ((q[2] >> k.shift[2]) as i32).wrapping_sub(k.anchor[2]) as f32,
        ];
        let row = |r: usize| k.m[r][0] * l[0] + k.m[r][1] * l[1] + k.m[r][2] * l[2] + k.m[r][3];
        let (x, y, depth) = (row(0), row(1), row(2));
        let (fx, fy) = if PERSPECTIVE { (x / depth, y / depth) } else { (x, y) };
        // Also rejects NaN. Inside [near, far], the perspective divisor (the depth) is positive.
        let inside = (depth >= k.near)
            & (depth <= k.far)
            & (fx >= k.x_lo)
            & (fx < k.x_hi)
            & (fy >= k.y_lo)
            & (fy < k.y_hi);
        let px = floor_i32(fx).wrapping_add(k.origin[0]);
        let py = floor_i32(fy).wrapping_add(k.origin[1]);
        let pixel = py.wrapping_mul(k.width).wrapping_add(px) as u32;
        pixels[i] = if inside { pixel } else { SKIP };
        depths[i] = depth.to_bits();
    }
}

/// The per-point loop over one batch, reading the first `WORDS` word arrays only. Returns the
/// points depth-tested.
///
/// Two phases per block of [`BLOCK`] points (paper 003 §3.4's prefetching, on a CPU): first every
/// point of the block is decoded and projected with no branch and no memory access besides its
/// words (so the compiler vectorizes it), then the surviving points go through the early depth
/// test and the atomic minimum one by one. The result is the same as projecting each point with
/// [`BatchProjection::local`] and [`BatchProjection::transform`] and flooring `(X / W, Y / W)`.
#[inline(always)]
fn draw_points_impl<const WORDS: usize, const PERSPECTIVE: bool, S: Sink>(
    fb: &S,
    k: &Kernel,
    b: &BatchRef<'_>,
) -> u64 {
    draw_loop::<WORDS, PERSPECTIVE, _, S>(fb, k, b.words, Consecutive(b.first_index))
}

/// Where the per-point loop takes each point's global index from.
trait PointIndices: Copy {
    /// The index of point `i` of the batch.
    fn at(self, i: usize) -> u32;
}

/// `first + i` (a [`BatchRef`]).
#[derive(Clone, Copy)]
struct Consecutive(u32);

impl PointIndices for Consecutive {
    #[inline(always)]
    fn at(self, i: usize) -> u32 {
        self.0.wrapping_add(i as u32)
    }
}

/// One index per point (a [`GatheredRef`]; the length is checked before drawing).
#[derive(Clone, Copy)]
struct Listed<'a>(&'a [u32]);

impl PointIndices for Listed<'_> {
    #[inline(always)]
    fn at(self, i: usize) -> u32 {
        self.0[i]
    }
}

/// The body of [`draw_points_impl`], for either source of point indices.
#[inline(always)]
fn draw_loop<const WORDS: usize, const PERSPECTIVE: bool, I: PointIndices, S: Sink>(
    fb: &S,
    k: &Kernel,
    words: [&[u32]; 3],
    idx: I,
) -> u64 {
    let n = words[0].len();
    let mut pixels = [0u32; BLOCK];
    let mut depths = [0u32; BLOCK];
    let mut drawn = 0u64;
    let mut start = 0;
    while start < n {
        let end = (start + BLOCK).min(n);
        let medium = if WORDS >= 2 { &words[1][start..end] } else { &[][..] };
        let fine = if WORDS >= 3 { &words[2][start..end] } else { &[][..] };
        project_block::<WORDS, PERSPECTIVE>(
            k,
            &words[0][start..end],
            medium,
            fine,
            &mut pixels,
            &mut depths,
        );
        for i in 0..end - start {
            let p = pixels[i];
            if p != SKIP {
                drawn += 1;
                fb.put(p as usize, ((depths[i] as u64) << 32) | idx.at(start + i) as u64);
            }
        }
        start = end;
    }
    drawn
}

/// [`draw_points_impl`] compiled for AVX2 (8 points per instruction in the projection phase).
/// Only integer and single-rounding IEEE operations are used (no fused multiply-add), so the keys
/// are bit for bit those of the baseline build.
///
/// # Safety
/// The CPU runs AVX2 (callers check [`use_avx2`] first); the body itself is safe code.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn draw_points_avx2<const WORDS: usize, const PERSPECTIVE: bool, S: Sink>(
    fb: &S,
    k: &Kernel,
    b: &BatchRef<'_>,
) -> u64 {
    draw_points_impl::<WORDS, PERSPECTIVE, S>(fb, k, b)
}

/// [`draw_loop`] over a [`GatheredRef`], compiled for AVX2 (see [`draw_points_avx2`]).
///
/// # Safety
/// The CPU runs AVX2 (callers check [`use_avx2`] first); the body itself is safe code.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn draw_listed_avx2<const WORDS: usize, const PERSPECTIVE: bool, S: Sink>(
    fb: &S,
    k: &Kernel,
    b: &GatheredRef<'_>,
) -> u64 {
    draw_loop::<WORDS, PERSPECTIVE, _, S>(fb, k, b.words, Listed(b.indices))
}

/// Whether the AVX2 build of the per-point loop can run here (checked once).
fn use_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        static AVX2: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        *AVX2.get_or_init(|| {
            std::is_x86_feature_detected!("avx2") && std::env::var_os("MORTAR_NO_AVX2").is_none()
        })
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// [`draw_points`] for a [`GatheredRef`].
#[inline(never)]
fn draw_listed<const WORDS: usize, S: Sink>(
    fb: &S,
    bp: &BatchProjection,
    b: &GatheredRef<'_>,
    u: &RasterUniforms,
    perspective: bool,
) -> u64 {
    let k = Kernel::new(bp, u);
    #[cfg(target_arch = "x86_64")]
    if use_avx2() {
        // SAFETY: the CPU supports AVX2 (checked at run time by use_avx2).
        return unsafe {
            if perspective {
                draw_listed_avx2::<WORDS, true, S>(fb, &k, b)
            } else {
                draw_listed_avx2::<WORDS, false, S>(fb, &k, b)
            }
        };
    }
    if perspective {
        draw_loop::<WORDS, true, _, S>(fb, &k, b.words, Listed(b.indices))
    } else {
        draw_loop::<WORDS, false, _, S>(fb, &k, b.words, Listed(b.indices))
    }
}

#[inline(never)]
fn draw_points<const WORDS: usize, S: Sink>(
    fb: &S,
    bp: &BatchProjection,
    b: &BatchRef<'_>,
    u: &RasterUniforms,
    perspective: bool,
) -> u64 {
    let k = Kernel::new(bp, u);
    #[cfg(target_arch = "x86_64")]
    if use_avx2() {
        // SAFETY: the CPU supports AVX2 (checked at run time by use_avx2).
        return unsafe {
            if perspective {
                draw_points_avx2::<WORDS, true, S>(fb, &k, b)
            } else {
                draw_points_avx2::<WORDS, false, S>(fb, &k, b)
            }
        };
    }
    if perspective {
        draw_points_impl::<WORDS, true, S>(fb, &k, b)
    } else {
        draw_points_impl::<WORDS, false, S>(fb, &k, b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera::{Projection, ViewPreset};
    use crate::render::framebuffer::{key_index, EMPTY_KEY};
    use crate::render::precision::PrecisionMode;
    use crate::render::testutil::Scene;

    fn render(scene: &Scene, camera: &Camera, options: RasterOptions) -> (Vec<u64>, RasterStats) {
        let fb = Framebuffer::new(camera.width, camera.height);
        let stats = rasterize(&fb, &scene.refs(), &scene.grid, camera, &options).unwrap();
        (fb.into_keys(), stats)
    }

    fn covered(keys: &[u64]) -> usize {
        keys.iter().filter(|&&k| k != EMPTY_KEY).count()
    }

    #[test]
    fn nearer_point_occludes_and_ties_go_to_the_smaller_index() {
        // Points on a column above (50, 50): seen from the top, the highest is nearest.
        let pts = vec![
            [5070, 5070, 100],
            [5070, 5070, 900],
            [5070, 5070, 500],
            [9030, 9030, 0],
            [9030, 9030, 0],
        ];
        let scene = Scene::from_points(Grid { scale: [0.01; 3], offset: [0.0; 3] }, pts, 2);
        let bounds = Aabb::new([0.0; 3], [100.0, 100.0, 10.0]);
        let cam = Camera::frame_orthographic(&bounds, ViewPreset::Top, 64, 64).unwrap();
        let (keys, stats) = render(&scene, &cam, RasterOptions::default());
        assert_eq!(stats.points_drawn, 5);
        assert_eq!(covered(&keys), 2);
        let winners: Vec<u32> =
            keys.iter().filter(|&&k| k != EMPTY_KEY).map(|&k| key_index(k)).collect();
        let z_of = |i: u32| scene.points[i as usize][2];
        let x_of = |i: u32| scene.points[i as usize][0];
        for w in winners {
            if x_of(w) == 5070 {
                assert_eq!(z_of(w), 900, "the highest point of the column must win");
            } else {
                // Two identical points: the smaller global index wins.
                let twins: Vec<u32> = (0..5).filter(|&i| x_of(i) == 9030).collect();
                assert_eq!(w, *twins.iter().min().unwrap());
            }
        }
    }

    #[test]
    fn deterministic_across_runs_orders_and_threads() {
        let scene = Scene::terrain(
            200_000,
            11,
            Grid { scale: [0.001; 3], offset: [500_000.0, 5_400_000.0, 0.0] },
        );
        let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 320, 240).unwrap();
        let (a, sa) = render(&scene, &cam, RasterOptions::default());
        let (b, sb) = render(&scene, &cam, RasterOptions::default());
        assert_eq!(a, b);
        assert_eq!(sa, sb);
        // Dense: points compete for pixels, so the order could matter if the result were not deterministic.
        assert!(sa.points_drawn > 2 * covered(&a) as u64);
        // Reversed batch order, and a single thread.
        let mut refs = scene.refs();
        refs.reverse();
        let fb = Framebuffer::new(320, 240);
        rasterize(&fb, &refs, &scene.grid, &cam, &RasterOptions::default()).unwrap();
        assert_eq!(fb.into_keys(), a);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let c = pool.install(|| render(&scene, &cam, RasterOptions::default()).0);
        assert_eq!(c, a);
    }

    #[test]
    fn culling_skips_batches_but_not_pixels() {
        let scene =
            Scene::terrain(300_000, 5, Grid { scale: [0.001; 3], offset: [6_400_000.0, 0.0, 0.0] });
        let c = scene.bounds.center();
        let size = scene.bounds.size();
        let mut cams = vec![
            // Close-up inside the scene, looking along the terrain.
            Camera {
                eye: [c[0] - size[0] * 0.1, c[1] - size[1] * 0.1, scene.bounds.max[2] + 2.0],
                target: [c[0] + size[0] * 0.2, c[1] + size[1] * 0.1, scene.bounds.min[2]],
                up: [0.0, 0.0, 1.0],
                projection: Projection::Perspective { fov_y: 0.7 },
                near: 0.5,
                far: 1e5,
                width: 300,
                height: 200,
            },
            // Zoomed orthographic top view of one corner.
            Camera {
                eye: [scene.bounds.min[0] + 20.0, scene.bounds.min[1] + 20.0, 500.0],
                target: [scene.bounds.min[0] + 20.0, scene.bounds.min[1] + 20.0, 0.0],
                up: [0.0, 1.0, 0.0],
                projection: Projection::Orthographic { height: 30.0 },
                near: 1.0,
                far: 1000.0,
                width: 300,
                height: 300,
            },
        ];
        cams.push(
            Camera::frame_perspective(&scene.bounds, ViewPreset::Front, 0.5, 200, 100).unwrap(),
        );
        for (i, cam) in cams.iter().enumerate() {
            let (on, s_on) =
                render(&scene, cam, RasterOptions { cull: true, ..Default::default() });
            let (off, s_off) =
                render(&scene, cam, RasterOptions { cull: false, ..Default::default() });
            assert_eq!(on, off, "camera {i}: culling changed the image");
            assert_eq!(s_on.points_drawn, s_off.points_drawn, "camera {i}");
            assert_eq!(s_off.batches_culled, 0);
            assert_eq!(s_on.batches_culled + s_on.batches_drawn, s_on.batches);
            match i {
                0 => assert!(s_on.batches_culled > 0, "camera {i}: nothing culled"),
                1 => assert!(
                    s_on.batches_culled * 2 > s_on.batches,
                    "camera {i}: culled only {} of {}",
                    s_on.batches_culled,
                    s_on.batches
                ),
                _ => {}
            }
            assert!(covered(&on) > 1000, "camera {i}: covered {}", covered(&on));
        }
    }

    /// Pixels covered in one image and empty in the other.
    fn coverage_diff(a: &[u64], b: &[u64]) -> usize {
        a.iter().zip(b).filter(|(x, y)| (**x == EMPTY_KEY) != (**y == EMPTY_KEY)).count()
    }

    #[test]
    fn adaptive_precision_matches_full_precision_in_an_overview() {
        // Dense terrain (15-60 points per pixel) at millimetre scale: batches need ~15 bits, so the
        // 10 bits the rule picks in an overview are lossy (points move by up to ~0.06 px here).
        let scene = Scene::terrain(
            1_000_000,
            21,
            Grid { scale: [0.001; 3], offset: [300_000.0, 4_000_000.0, 0.0] },
        );
        assert!(scene.batches.iter().all(|b| b.grid.bits.iter().any(|&bits| bits > 10)));
        let full_precision = RasterOptions {
            precision: PrecisionMode::Fixed(Precision::Bits30),
            ..Default::default()
        };
        for preset in [ViewPreset::Top, ViewPreset::Iso] {
            let cam = Camera::frame_perspective(&scene.bounds, preset, 0.8, 300, 225).unwrap();
            let (adaptive, sa) = render(&scene, &cam, RasterOptions::default());
            let (full, sf) = render(&scene, &cam, full_precision);
            assert_eq!(
                sa.points_by_precision,
                [1_000_000, 0, 0],
                "{preset:?}: an overview loads one word per point"
            );
            assert_eq!(
                sf.points_by_precision,
                [0, 1_000_000, 0],
                "{preset:?}: 20 bits hold every bit these batches use"
            );
            // No holes opened or closed: coverage differs only at a few silhouette pixels. (Which of
            // the ~20 points in a pixel wins does change for ~11 % of pixels: sub-pixel shifts
            // reorder points that share a pixel, at any precision short of exact.)
            let n = covered(&full);
            let diff = coverage_diff(&adaptive, &full);
            assert!(
                diff as f64 <= 5e-4 * n as f64,
                "{preset:?}: coverage differs in {diff} of {n} pixels"
            );
        }
        // Control: in a close-up the rule asks for 20 bits; forcing 10 bits there (cells of ~0.8 px)
        // changes the coverage a lot, the adaptive choice does not.
        let c = scene.world([100.0, 75.0, 20.0]);
        let cam = Camera {
            eye: [c[0], c[1], c[2] + 9.0],
            target: c,
            up: [0.0, 1.0, 0.0],
            projection: Projection::Perspective { fov_y: 0.8 },
            near: 0.1,
            far: 100.0,
            width: 300,
            height: 225,
        };
        let (adaptive, sa) = render(&scene, &cam, RasterOptions::default());
        let (full, _) = render(&scene, &cam, full_precision);
        let (coarse, _) = render(
            &scene,
            &cam,
            RasterOptions {
                precision: PrecisionMode::Fixed(Precision::Bits10),
                ..Default::default()
            },
        );
        assert!(sa.points_by_precision[1] > 0, "{sa:?}");
        let n = covered(&full);
        assert!(n > 1000, "{n}");
        assert_eq!(coverage_diff(&adaptive, &full), 0);
        let forced = coverage_diff(&coarse, &full);
        assert!(
            forced as f64 > 0.05 * n as f64,
            "forcing 10 bits changed only {forced} of {n} pixels"
        );
    }

    #[test]
    fn full_precision_matches_f64_brute_force() {
        // Every point projected in f64 from its exact world position, nearest depth wins: the
        // rasterizer at 30 bits must give the same winner in nearly every pixel (2 in 10^4).
        let scene = Scene::terrain(
            300_000,
            9,
            Grid { scale: [0.0001; 3], offset: [6_400_000.0, 6_400_000.0, 6_400_000.0] },
        );
        for preset in [ViewPreset::Top, ViewPreset::Iso] {
            let cam = Camera::frame_perspective(&scene.bounds, preset, 0.8, 640, 480).unwrap();
            let (keys, _) = render(
                &scene,
                &cam,
                RasterOptions { precision: PrecisionMode::Fixed(Precision::Bits30), cull: true },
            );
            let mut best = vec![(f64::INFINITY, u32::MAX); 640 * 480];
            for (i, p) in scene.points.iter().enumerate() {
                let world = [0, 1, 2].map(|a| scene.grid.world(a, p[a] as i64));
                if let Some(q) = cam.project(world) {
                    let (x, y) = (q.x.floor(), q.y.floor());
                    if (0.0..640.0).contains(&x) && (0.0..480.0).contains(&y) {
                        let slot = &mut best[y as usize * 640 + x as usize];
                        if (q.depth, i as u32) < *slot {
                            *slot = (q.depth, i as u32);
                        }
                    }
                }
            }
            let n = best.iter().filter(|b| b.1 != u32::MAX).count();
            let differ = keys
                .iter()
                .zip(&best)
                .filter(|(k, b)| {
                    (**k == EMPTY_KEY) != (b.1 == u32::MAX)
                        || (**k != EMPTY_KEY && key_index(**k) != b.1)
                })
                .count();
            assert!(n > 50_000, "{preset:?}: {n}");
            // Points within f32 rounding (~1e-4 px at 640 px: the projection is relative to the
            // viewport's centre, the same for every batch) of a pixel edge: 5 and 8 pixels here
            // (7 and 4 when it was relative to each batch's projected centre).
            assert!(differ as f64 <= 2e-4 * n as f64, "{preset:?}: {differ} of {n} pixels differ");
        }
    }

    fn avx2_present() -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            std::is_x86_feature_detected!("avx2")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    }

    /// One batch through the baseline or the AVX2 build of the per-point loop.
    fn draw_with(
        fb: &Framebuffer,
        k: &Kernel,
        b: &BatchRef<'_>,
        p: Precision,
        persp: bool,
        avx2: bool,
    ) -> u64 {
        #[cfg(target_arch = "x86_64")]
        if avx2 {
            assert!(avx2_present());
            // SAFETY: AVX2 is present (asserted just above).
            return unsafe {
                match (p, persp) {
                    (Precision::Bits10, true) => draw_points_avx2::<1, true, Framebuffer>(fb, k, b),
                    (Precision::Bits10, false) => {
                        draw_points_avx2::<1, false, Framebuffer>(fb, k, b)
                    }
                    (Precision::Bits20, true) => draw_points_avx2::<2, true, Framebuffer>(fb, k, b),
                    (Precision::Bits20, false) => {
                        draw_points_avx2::<2, false, Framebuffer>(fb, k, b)
                    }
                    (Precision::Bits30, true) => draw_points_avx2::<3, true, Framebuffer>(fb, k, b),
                    (Precision::Bits30, false) => {
                        draw_points_avx2::<3, false, Framebuffer>(fb, k, b)
                    }
                }
            };
        }
        assert!(!avx2, "no AVX2 build on this architecture");
        match (p, persp) {
            (Precision::Bits10, true) => draw_points_impl::<1, true, Framebuffer>(fb, k, b),
            (Precision::Bits10, false) => draw_points_impl::<1, false, Framebuffer>(fb, k, b),
            (Precision::Bits20, true) => draw_points_impl::<2, true, Framebuffer>(fb, k, b),
            (Precision::Bits20, false) => draw_points_impl::<2, false, Framebuffer>(fb, k, b),
            (Precision::Bits30, true) => draw_points_impl::<3, true, Framebuffer>(fb, k, b),
            (Precision::Bits30, false) => draw_points_impl::<3, false, Framebuffer>(fb, k, b),
        }
    }

    /// The projection the planner gives batch `b` at precision `p` (culling off).
    fn planned(grid: &Grid, cam: &Camera, b: &BatchRef<'_>, p: Precision) -> BatchProjection {
        let planner = Planner::new(
            cam,
            grid,
            &RasterOptions { precision: PrecisionMode::Fixed(p), cull: false },
        )
        .unwrap();
        match planner.plan(&b.grid, &b.bounds(), b.len()) {
            BatchPlan::Draw { projection, .. } => projection,
            other => panic!("{other:?}"),
        }
    }

    /// The reference per-point path the kernel must reproduce: `BatchProjection::local` and
    /// `::transform`, `(X / W, Y / W)` floored with `f32::floor`, one point at a time.
    fn reference_keys(scene: &Scene, cam: &Camera, precision: Precision) -> Vec<u64> {
        let u = RasterUniforms::new(cam);
        let mut keys = vec![EMPTY_KEY; (cam.width * cam.height) as usize];
        for b in scene.refs() {
            let p = precision.min(crate::render::precision::sufficient_precision(&b.grid));
            let bp = planned(&scene.grid, cam, &b, p);
            for i in 0..b.len() {
                let w = [b.words[0][i], b.words[1][i], b.words[2][i]];
                let [x, y, depth, wc] = bp.transform(bp.local(crate::quantize::join_words(w, p)));
                if !(depth >= u.near && depth <= u.far) {
                    continue;
                }
                let (fx, fy) = (
                    (x / wc).floor() as i64 + bp.pixel_origin[0] as i64,
                    (y / wc).floor() as i64 + bp.pixel_origin[1] as i64,
                );
                if fx < 0 || fy < 0 || fx >= cam.width as i64 || fy >= cam.height as i64 {
                    continue;
                }
                let slot = &mut keys[fy as usize * cam.width as usize + fx as usize];
                *slot = (*slot)
                    .min(crate::render::framebuffer::pack_key(depth, b.first_index + i as u32));
            }
        }
        keys
    }

    #[test]
    fn kernel_matches_the_per_point_reference_with_and_without_avx2() {
        let scene = Scene::terrain(
            120_000,
            3,
            Grid { scale: [0.001; 3], offset: [500_000.0, 5_400_000.0, 0.0] },
        );
        let c = scene.bounds.center();
        let mut cams = vec![
            Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 320, 200).unwrap(),
            Camera::frame_orthographic(&scene.bounds, ViewPreset::Top, 320, 200).unwrap(),
            Camera::close_up(&scene.bounds, 0.8, 320, 200).unwrap(),
            Camera::inside(&scene.bounds, 1.2, 320, 200).unwrap(),
        ];
        // A camera looking partly past the data, so that points fall on every side of the viewport.
        cams.push(Camera {
            eye: [c[0] - 30.0, c[1], c[2] + 5.0],
            target: [c[0] + 10.0, c[1] + 25.0, c[2]],
            ..cams[0]
        });
        for (ci, cam) in cams.iter().enumerate() {
            for precision in [Precision::Bits10, Precision::Bits20, Precision::Bits30] {
                let want = reference_keys(&scene, cam, precision);
                let opts =
                    RasterOptions { precision: PrecisionMode::Fixed(precision), cull: false };
                let (got, _) = render(&scene, cam, opts);
                let differ = got.iter().zip(&want).filter(|(a, b)| a != b).count();
                assert_eq!(differ, 0, "camera {ci} {precision:?}: {differ} pixels differ from the per-point reference");
                assert!(covered(&got) > 500, "camera {ci}: {}", covered(&got));
                // The baseline build of the loop and the AVX2 build write the same keys.
                let u = RasterUniforms::new(cam);
                let (base, wide) = (
                    Framebuffer::new(cam.width, cam.height),
                    Framebuffer::new(cam.width, cam.height),
                );
                for b in scene.refs() {
                    let p = precision.min(crate::render::precision::sufficient_precision(&b.grid));
                    let k = Kernel::new(&planned(&scene.grid, cam, &b, p), &u);
                    let n1 = draw_with(&base, &k, &b, p, cam.is_perspective(), false);
                    if avx2_present() {
                        assert_eq!(n1, draw_with(&wide, &k, &b, p, cam.is_perspective(), true));
                    }
                }
                assert_eq!(base.keys(), want, "camera {ci} {precision:?}: baseline loop");
                if avx2_present() {
                    assert_eq!(wide.keys(), want, "camera {ci} {precision:?}: AVX2 loop");
                }
            }
        }
    }

    #[test]
    fn floor_is_exact_where_it_matters() {
        for v in
            [-3.5f32, -3.0, -0.25, -0.0, 0.0, 0.9999999, 1.0, 1919.9999, 32767.5, -32768.0, 1.0e8]
        {
            assert_eq!(floor_i32(v), v.floor() as i32, "{v}");
        }
        // Anything else gives some value without undefined behaviour.
        let _ = (floor_i32(f32::NAN), floor_i32(f32::INFINITY), floor_i32(-1.0e30));
    }

    #[test]
    fn stats_and_errors() {
        let scene = Scene::terrain(50_000, 1, Grid { scale: [0.01; 3], offset: [0.0; 3] });
        let cam = Camera::frame_orthographic(&scene.bounds, ViewPreset::Top, 100, 100).unwrap();
        let (_, s) = render(&scene, &cam, RasterOptions::default());
        assert_eq!(s.batches, scene.batches.len() as u64);
        assert_eq!(s.points_projected(), 50_000);
        assert_eq!(s.points_drawn, 50_000, "a framed top view shows every point");
        let fb = Framebuffer::new(99, 100);
        assert!(matches!(
            rasterize(&fb, &scene.refs(), &scene.grid, &cam, &RasterOptions::default()),
            Err(RasterError::Viewport { .. })
        ));
        let fb = Framebuffer::new(100, 100);
        let mut refs = scene.refs();
        refs[1].words[2] = &refs[1].words[2][1..];
        assert!(matches!(
            rasterize(&fb, &refs, &scene.grid, &cam, &RasterOptions::default()),
            Err(RasterError::WordCounts { batch: 1, .. })
        ));
        let mut refs = scene.refs();
        refs[0].first_index = u32::MAX - 5;
        assert!(matches!(
            rasterize(&fb, &refs, &scene.grid, &cam, &RasterOptions::default()),
            Err(RasterError::IndexOverflow { batch: 0, .. })
        ));
        let mut bad = cam;
        bad.far = bad.near;
        assert!(matches!(
            rasterize(&fb, &scene.refs(), &scene.grid, &bad, &RasterOptions::default()),
            Err(RasterError::Camera(_))
        ));
    }
    /// Rods 2 cm thick and 32.8 m long seen along their length from 6 m before their near ends
    /// (think rails, fences, wires or vine rows at a grazing angle): one batch per rod, noisy colours.
    fn rods() -> (Scene, Camera, Vec<u32>) {
        let grid = Grid { scale: [0.001; 3], offset: [500_000.0, 4_000_000.0, 100.0] };
        let mut rng = crate::render::testutil::Rng(3);
        let mut groups = Vec::new();
        for x in -4..=4 {
            for z in -2..=2 {
                let rod: Vec<[i32; 3]> = (0..crate::BATCH_SIZE)
                    .map(|_| {
                        [
                            x * 1000 + (rng.unit() * 20.0) as i32,
                            (rng.unit() * 32_767.0) as i32,
                            z * 1000 + (rng.unit() * 20.0) as i32,
                        ]
                    })
                    .collect();
                groups.push(rod);
            }
        }
        let scene = Scene::from_groups(grid, groups);
        let colors =
            (0..scene.points.len()).map(|_| (rng.next_u64() as u32) | 0xff00_0000).collect();
        let cam = Camera {
            eye: scene.world([0.0, -6.0, 0.0]),
            target: scene.world([0.0, 10.0, 0.0]),
            up: [0.0, 0.0, 1.0],
            projection: Projection::Perspective { fov_y: 50f64.to_radians() },
            near: 0.1,
            far: 1000.0,
            width: 1920,
            height: 1080,
        };
        (scene, cam, colors)
    }

    /// PSNR (dB) of the RGB colours of two key images over the pixels covered in either.
    fn psnr_covered(a: &[u64], b: &[u64], colors: &[u32]) -> f64 {
        let rgb = |k: &u64| {
            if *k == EMPTY_KEY {
                0
            } else {
                colors[key_index(*k) as usize] & 0x00ff_ffff
            }
        };
        let (x, y): (Vec<u32>, Vec<u32>) =
            (a.iter().map(rgb).collect(), b.iter().map(rgb).collect());
        crate::metrics::psnr_where(&x, &y, |i| a[i] != EMPTY_KEY || b[i] != EMPTY_KEY)
    }

    #[test]
    fn adaptive_precision_bounds_the_decode_error_on_grazing_rods() {
        use crate::render::precision::{
            decode_error_px, quantization_box, sufficient_precision, MAX_ERROR_PX,
        };
        use crate::render::precision_for_pixels;
        let (scene, cam, colors) = rods();
        let refs = scene.refs();
        let (full, _) = render(
            &scene,
            &cam,
            RasterOptions { precision: PrecisionMode::Fixed(Precision::Bits30), cull: true },
        );
        let (adaptive, stats) = render(&scene, &cam, RasterOptions::default());
        // The plain 500 px rule, drawn per group of its precision (the keys it drew before).
        let rule500 = |b: &BatchRef<'_>| {
            precision_for_pixels(cam.projected_size(&quantization_box(&scene.grid, &b.grid)))
                .min(sufficient_precision(&b.grid))
        };
        let fb = Framebuffer::new(cam.width, cam.height);
        for p in [Precision::Bits10, Precision::Bits20, Precision::Bits30] {
            let group: Vec<BatchRef<'_>> =
                refs.iter().filter(|b| rule500(b) == p).copied().collect();
            rasterize(
                &fb,
                &group,
                &scene.grid,
                &cam,
                &RasterOptions { precision: PrecisionMode::Fixed(p), cull: true },
            )
            .unwrap();
        }
        let old = fb.into_keys();
        // Per drawn batch: the bound of the chosen precision is under a pixel, and so is every
        // point's measured displacement (f64 projections of the decoded and the exact position).
        let planner = Planner::new(&cam, &scene.grid, &RasterOptions::default()).unwrap();
        let (mut worst_old, mut worst_new, mut raised) = (0f64, 0f64, 0);
        for (b, bounds) in refs.iter().zip(&scene.batch_bounds) {
            let BatchPlan::Draw { precision, .. } = planner.plan(&b.grid, bounds, b.len()) else {
                continue;
            };
            let bound = decode_error_px(&cam, &scene.grid, &b.grid, bounds, precision);
            assert!(
                bound < MAX_ERROR_PX,
                "batch at {:?}: bound {bound} px at {precision:?}",
                b.grid.min
            );
            if precision != rule500(b) {
                raised += 1;
            }
            let measured = |p: Precision| {
                let world = |rel: [f64; 3]| {
                    [0, 1, 2].map(|a| {
                        scene.grid.offset[a] + scene.grid.scale[a] * (b.grid.min[a] as f64 + rel[a])
                    })
                };
                (0..b.len())
                    .filter_map(|i| {
                        let w = [b.words[0][i], b.words[1][i], b.words[2][i]];
                        let (d, e) = (
                            cam.project(world(b.grid.decode_relative(w, p)))?,
                            cam.project(world(b.grid.decode_relative(w, Precision::Bits30)))?,
                        );
                        Some(((d.x - e.x).powi(2) + (d.y - e.y).powi(2)).sqrt())
                    })
                    .fold(0f64, f64::max)
            };
            let m = measured(precision);
            assert!(
                m <= bound + 1e-9,
                "batch at {:?}: measured {m} px above the bound {bound}",
                b.grid.min
            );
            worst_new = worst_new.max(m);
            worst_old = worst_old.max(measured(rule500(b)));
        }
        let (p_old, p_new) =
            (psnr_covered(&old, &full, &colors), psnr_covered(&adaptive, &full, &colors));
        eprintln!("rods: raised {raised} batches; worst error {worst_old:.3} px -> {worst_new:.3} px; PSNR over covered pixels {p_old:.1} -> {p_new:.1} dB; {stats:?}");
        assert!(raised >= 8, "{raised}");
        assert!(worst_old > 1.3, "the 500 px rule alone moved points by {worst_old} px");
        assert!(worst_new < MAX_ERROR_PX);
        assert!(stats.points_by_precision[0] > 0, "far or small rods keep 10 bits: {stats:?}");
        assert!(p_old < PSNR_MIN_DB && p_new > PSNR_MIN_DB, "PSNR {p_old} -> {p_new} dB");
    }

    /// The adversarial rods' PSNR threshold.
    const PSNR_MIN_DB: f64 = 30.0;
}
