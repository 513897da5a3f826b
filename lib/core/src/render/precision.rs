//! Choosing how many coordinate words a batch loads (paper 003 §3.3, adaptive vertex precision):
//! a batch that projects to fewer than 500 pixels is drawn from its coarse word (10 bits per axis),
//! below 500 x 1024 pixels from coarse and medium words (20 bits), otherwise from all three; and
//! then, since the 500 px rule alone does not bound the error on screen, with more words while the
//! decode error of the proposed precision could move a point by [`MAX_ERROR_PX`] (a quarter pixel)
//! or more ([`decode_error_px`]).
//!
//! The paper's reasoning: 10 bits give 1024 cells across the batch, so below 500 px a cell is
//! under half a pixel and quantization opens no holes between points. mortar's batches quantize on
//! the source's integer grid with `bits` per axis ([`crate::quantize`]), so the coarse cell is
//! 1/1024 of the power-of-two box `2^bits` units wide, not of the batch's own extent; the projected
//! size is therefore measured on that quantization box ([`quantization_box`]), which keeps the
//! rule's meaning (cell < 0.5 px) for every batch. Where a batch needs no more bits than fewer
//! words already hold, the extra words are all zero and are not loaded.
//!
//! A decode puts a point at the centre of its cell, so it moves by half a cell per axis: a quarter
//! pixel per axis where the box's size on screen is what the cell's is, 1/1024 of it. Two things
//! make it more: the three axes' errors add up on screen (up to 1.7x), and in perspective a cell at
//! the batch's near end projects larger than the box's average, by up to the ratio of the batch's
//! far and near depths (a batch that reaches close to the camera, or is long along the view), with
//! a depth error seen off-axis moving the point sideways (grazing views). On the real scans of
//! BENCHMARKS.md the 500 px rule's 10-bit batches moved points by up to 0.30 px (bounds up to
//! 0.62 px), and such sub-pixel shifts on batches just under 500 px were what cost PSNR (24.2 dB on
//! the PyForestScan tile's close-up against the 30-bit render); a batch seen along its length from
//! close by moves points by more than a pixel (1.8 px in the `rods` test of `raster.rs`). The bound
//! ([`crate::render::Camera::displacement_bound_px`]) is conservative, from the batch's corners as
//! projected; the budget of a quarter pixel is the paper's own (half of a half-pixel cell), now
//! held by the projected error rather than by the box's size.

use super::camera::Camera;
use super::math::Aabb;
use crate::grid::Grid;
use crate::quantize::{BatchGrid, Precision};

/// Projected size in pixels below which 10 bits per axis are used.
pub const PIXELS_10_BITS: f64 = 500.0;
/// Projected size in pixels below which 20 bits per axis are used.
pub const PIXELS_20_BITS: f64 = 500.0 * 1024.0;
/// The adaptive rule never keeps a precision whose decode error could move a point this many
/// pixels or more on screen ([`decode_error_px`]): a quarter pixel, so every point stays well
/// under a pixel from its exact position (and, on the real scans measured, within 0.25 px).
pub const MAX_ERROR_PX: f64 = 0.25;

/// How the rasterizer chooses the precision of each batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum PrecisionMode {
    /// From the batch's projected size (the 500 px rule).
    #[default]
    Adaptive,
    /// The same precision for every batch (the words beyond what a batch needs are still skipped;
    /// they are zero, so the image is the same).
    Fixed(Precision),
}

/// The precision for a batch whose quantization box projects to `pixels` pixels (NaN: 30 bits).
pub fn precision_for_pixels(pixels: f64) -> Precision {
    if pixels < PIXELS_10_BITS {
        Precision::Bits10
    } else if pixels < PIXELS_20_BITS {
        Precision::Bits20
    } else {
        Precision::Bits30
    }
}

/// The fewest words that hold every bit a batch uses: decoding with more gives the same position.
pub fn sufficient_precision(batch: &BatchGrid) -> Precision {
    match batch.bits.iter().copied().max().unwrap_or(0) {
        0..=10 => Precision::Bits10,
        11..=20 => Precision::Bits20,
        _ => Precision::Bits30,
    }
}

/// The world box `[min, min + 2^bits]` (integer-grid units per axis) a batch's words quantize.
pub fn quantization_box(grid: &Grid, batch: &BatchGrid) -> Aabb {
    let mut b = Aabb::EMPTY;
    for a in 0..3 {
        let lo = grid.world(a, batch.min[a] as i64);
        let hi = grid.world(a, batch.min[a] as i64 + (1i64 << batch.bits[a]));
        b.min[a] = lo.min(hi);
        b.max[a] = lo.max(hi);
    }
    b
}

/// Upper bound, in pixels, of the distance on screen between a point of the batch decoded at
/// `precision` and its exact position ([`Camera::displacement_bound_px`] of the decode's error
/// bound, [`BatchGrid::error_bound`], over the points' world `bounds`); 0 where the words hold every
/// bit the batch uses.
pub fn decode_error_px(
    camera: &Camera,
    grid: &Grid,
    batch: &BatchGrid,
    bounds: &Aabb,
    precision: Precision,
) -> f64 {
    let e = batch.error_bound(precision);
    if e == [0.0; 3] {
        return 0.0;
    }
    let err = [0, 1, 2].map(|a| e[a] * grid.scale[a].abs());
    camera.displacement_bound_px(bounds, err)
}

/// The next finer precision (30 bits stays 30 bits).
fn finer(p: Precision) -> Precision {
    match p {
        Precision::Bits10 => Precision::Bits20,
        _ => Precision::Bits30,
    }
}

/// The precision to draw a batch with, and the projected size (pixels) of its quantization box
/// (`None` for a fixed precision). `bounds` are the world bounds of the batch's points.
///
/// Adaptive: the 500 px rule proposes a precision, which is then raised while its decode error
/// could project to [`MAX_ERROR_PX`] or more ([`decode_error_px`]).
pub fn choose_precision(
    mode: PrecisionMode,
    camera: &Camera,
    grid: &Grid,
    batch: &BatchGrid,
    bounds: &Aabb,
) -> (Precision, Option<f64>) {
    let enough = sufficient_precision(batch);
    match mode {
        PrecisionMode::Fixed(p) => (p.min(enough), None),
        PrecisionMode::Adaptive => {
            let px = camera.projected_size(&quantization_box(grid, batch));
            let mut p = precision_for_pixels(px).min(enough);
            while p < enough && decode_error_px(camera, grid, batch, bounds, p) >= MAX_ERROR_PX {
                p = finer(p);
            }
            (p, Some(px))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera::Projection;

    #[test]
    fn thresholds() {
        assert_eq!(precision_for_pixels(0.0), Precision::Bits10);
        assert_eq!(precision_for_pixels(499.9), Precision::Bits10);
        assert_eq!(precision_for_pixels(500.0), Precision::Bits20);
        assert_eq!(precision_for_pixels(511_999.0), Precision::Bits20);
        assert_eq!(precision_for_pixels(512_000.0), Precision::Bits30);
        assert_eq!(precision_for_pixels(f64::INFINITY), Precision::Bits30);
        assert_eq!(precision_for_pixels(f64::NAN), Precision::Bits30);
    }

    #[test]
    fn sufficient_words() {
        let b = |bits: [u8; 3]| BatchGrid { min: [0; 3], bits };
        assert_eq!(sufficient_precision(&b([0, 0, 0])), Precision::Bits10);
        assert_eq!(sufficient_precision(&b([10, 3, 0])), Precision::Bits10);
        assert_eq!(sufficient_precision(&b([2, 11, 0])), Precision::Bits20);
        assert_eq!(sufficient_precision(&b([2, 20, 21])), Precision::Bits30);
    }

    #[test]
    fn batch_precision_follows_its_size_on_screen() {
        // Orthographic top view, 1000 px showing 100 m: 10 px per metre.
        let cam = Camera {
            eye: [50.0, 50.0, 100.0],
            target: [50.0, 50.0, 0.0],
            up: [0.0, 1.0, 0.0],
            projection: Projection::Orthographic { height: 100.0 },
            near: 1.0,
            far: 1000.0,
            width: 1000,
            height: 1000,
        };
        let grid = Grid { scale: [0.001; 3], offset: [0.0; 3] };
        // 2^15 mm = 32.8 m -> 328 px: 10 bits.
        let small = BatchGrid { min: [10_000, 10_000, 0], bits: [15, 15, 15] };
        let (p, px) = choose_precision(
            PrecisionMode::Adaptive,
            &cam,
            &grid,
            &small,
            &quantization_box(&grid, &small),
        );
        assert_eq!(p, Precision::Bits10);
        assert!((px.unwrap() - 327.68).abs() < 1e-6);
        // 2^16 mm = 65.5 m -> 655 px: 20 bits.
        let medium = BatchGrid { min: [10_000, 10_000, 0], bits: [16, 12, 12] };
        assert_eq!(
            choose_precision(
                PrecisionMode::Adaptive,
                &cam,
                &grid,
                &medium,
                &quantization_box(&grid, &medium)
            )
            .0,
            Precision::Bits20
        );
        // 2^26 mm = 67 km -> 671,000 px: 30 bits.
        let huge = BatchGrid { min: [0, 0, 0], bits: [26, 12, 12] };
        assert_eq!(
            choose_precision(
                PrecisionMode::Adaptive,
                &cam,
                &grid,
                &huge,
                &quantization_box(&grid, &huge)
            )
            .0,
            Precision::Bits30
        );
        // A batch that 10 bits hold exactly never loads more, whatever is asked.
        let exact = BatchGrid { min: [0, 0, 0], bits: [10, 10, 10] };
        assert_eq!(
            choose_precision(
                PrecisionMode::Fixed(Precision::Bits30),
                &cam,
                &grid,
                &exact,
                &quantization_box(&grid, &exact)
            )
            .0,
            Precision::Bits10
        );
        assert_eq!(
            choose_precision(
                PrecisionMode::Fixed(Precision::Bits20),
                &cam,
                &grid,
                &huge,
                &quantization_box(&grid, &huge)
            )
            .0,
            Precision::Bits20
        );
        // Zooming in 4x moves the small batch over the threshold.
        let mut close = cam;
        close.projection = Projection::Orthographic { height: 25.0 };
        assert_eq!(
            choose_precision(
                PrecisionMode::Adaptive,
                &close,
                &grid,
                &small,
                &quantization_box(&grid, &small)
            )
            .0,
            Precision::Bits20
        );
    }
    #[test]
    fn decode_error_bound_holds_for_displaced_points() {
        // Random boxes in front of, around and beside random cameras (perspective, also grazing
        // and very close; orthographic), random points in them and displacements at the corners of
        // the error box: every drawn displaced point stays within the bound of its exact pixel.
        use crate::render::testutil::Rng;
        let mut rng = Rng(7);
        let mut checked = 0usize;
        for case in 0..400 {
            let r = |rng: &mut Rng, s: f64| (rng.unit() - 0.5) * 2.0 * s;
            let eye = [r(&mut rng, 50.0), r(&mut rng, 50.0), r(&mut rng, 20.0)];
            let target = [
                eye[0] + r(&mut rng, 30.0),
                eye[1] + r(&mut rng, 30.0) + 0.1,
                eye[2] + r(&mut rng, 10.0),
            ];
            let projection = if case % 5 == 4 {
                Projection::Orthographic { height: 1.0 + rng.unit() * 80.0 }
            } else {
                Projection::Perspective { fov_y: 0.3 + rng.unit() * 1.5 }
            };
            let near = if case % 7 == 3 { 1e-5 } else { 0.01 + rng.unit() };
            let cam = Camera {
                eye,
                target,
                up: [0.0, 0.0, 1.0],
                projection,
                near,
                far: 1e4,
                width: 640,
                height: 480,
            };
            let lo = [r(&mut rng, 60.0), r(&mut rng, 60.0), r(&mut rng, 20.0)];
            let size = [rng.unit() * 40.0, rng.unit() * 40.0, rng.unit() * 10.0];
            let b = Aabb::new(lo, [lo[0] + size[0], lo[1] + size[1], lo[2] + size[2]]);
            let err = [rng.unit() * 0.05, rng.unit() * 0.05, rng.unit() * 0.05];
            let bound = cam.displacement_bound_px(&b, err);
            for _ in 0..200 {
                let p = [0, 1, 2].map(|a| b.min[a] + rng.unit() * size[a]);
                let Some(e) = cam.project(p) else { continue };
                let k = rng.next_u64();
                let d = [0, 1, 2].map(|a| p[a] + if k >> a & 1 == 1 { err[a] } else { -err[a] });
                let Some(q) = cam.project(d) else { continue };
                let moved = ((q.x - e.x).powi(2) + (q.y - e.y).powi(2)).sqrt();
                assert!(
                    moved <= bound * (1.0 + 1e-9) + 1e-9,
                    "case {case}: moved {moved} px, bound {bound}, {cam:?} {b:?} {err:?}"
                );
                checked += 1;
            }
        }
        assert!(checked > 20_000, "{checked}");
    }

    #[test]
    fn the_rule_raises_precision_where_the_decode_error_reaches_a_pixel() {
        // A rod 2 cm thick and 32.8 m long (1 mm grid: 15 bits along it, 10-bit cells of 32 mm),
        // seen along its length from 6 m before its near end, 3 m to the side: its box projects to
        // 489 px, under 500, but the near end is 6.5x closer than the far end, so a depth error of
        // 16 mm moves the near points by 1.5 px. The rule now loads 20 bits; so it does for the
        // same rod 1 m to the side (163 px, error 0.5 px), while 0.3 m to the side (49 px) it keeps
        // 10 bits.
        let grid = Grid { scale: [0.001; 3], offset: [0.0; 3] };
        let cam = Camera {
            eye: [0.0, -6.0, 0.0],
            target: [0.0, 10.0, 0.0],
            up: [0.0, 0.0, 1.0],
            projection: Projection::Perspective { fov_y: 50f64.to_radians() },
            near: 0.1,
            far: 1000.0,
            width: 1920,
            height: 1080,
        };
        let rod = |x: i32| BatchGrid::for_bounds([x, 0, 0], [x + 20, 32_767, 20]).unwrap();
        let bounds = |b: &BatchGrid| {
            Aabb::new(
                [0, 1, 2].map(|a| grid.world(a, b.min[a] as i64)),
                [grid.world(0, b.min[0] as i64 + 20), 32.767, 0.02],
            )
        };
        let side = rod(3000);
        let px = cam.projected_size(&quantization_box(&grid, &side));
        assert!(px > 450.0 && px < 500.0, "{px}");
        assert_eq!(
            precision_for_pixels(px),
            Precision::Bits10,
            "the 500 px rule alone takes 10 bits"
        );
        let e10 = decode_error_px(&cam, &grid, &side, &bounds(&side), Precision::Bits10);
        assert!(e10 > 1.4 && e10 < 1.8, "{e10}");
        let (p, _) = choose_precision(PrecisionMode::Adaptive, &cam, &grid, &side, &bounds(&side));
        assert_eq!(p, Precision::Bits20);
        assert!(decode_error_px(&cam, &grid, &side, &bounds(&side), p) < 0.01);
        let nearer = rod(1000);
        let e10 = decode_error_px(&cam, &grid, &nearer, &bounds(&nearer), Precision::Bits10);
        assert!(e10 > 0.4 && e10 < 0.8, "{e10}");
        assert_eq!(
            choose_precision(PrecisionMode::Adaptive, &cam, &grid, &nearer, &bounds(&nearer)).0,
            Precision::Bits20
        );
        let centre = rod(300);
        let e10 = decode_error_px(&cam, &grid, &centre, &bounds(&centre), Precision::Bits10);
        assert!(e10 > 0.05 && e10 < MAX_ERROR_PX, "{e10}");
        assert_eq!(
            choose_precision(PrecisionMode::Adaptive, &cam, &grid, &centre, &bounds(&centre)).0,
            Precision::Bits10
        );
        // Far away, the bound is the 500 px rule's quarter pixel: 10 bits stay.
        let mut far = cam;
        far.eye = [0.0, -300.0, 0.0];
        assert_eq!(
            choose_precision(PrecisionMode::Adaptive, &far, &grid, &side, &bounds(&side)).0,
            Precision::Bits10
        );
    }
}
