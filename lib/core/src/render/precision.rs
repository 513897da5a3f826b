//! Choosing how many coordinate words a batch loads (paper 003 §3.3, adaptive vertex precision):
//! a batch that projects to fewer than 500 pixels is drawn from its coarse word (10 bits per axis),
//! below 500 x 1024 pixels from coarse and medium words (20 bits), otherwise from all three.
//!
//! The paper's reasoning: 10 bits give 1024 cells across the batch, so below 500 px a cell is
//! under half a pixel and quantization opens no holes between points. mortar's batches quantize on
//! the source's integer grid with `bits` per axis ([`crate::quantize`]), so the coarse cell is
//! 1/1024 of the power-of-two box `2^bits` units wide, not of the batch's own extent; the projected
//! size is therefore measured on that quantization box ([`quantization_box`]), which keeps the
//! rule's meaning (cell < 0.5 px) for every batch. Where a batch needs no more bits than fewer
//! words already hold, the extra words are all zero and are not loaded.

use super::camera::Camera;
use super::math::Aabb;
use crate::grid::Grid;
use crate::quantize::{BatchGrid, Precision};

/// Projected size in pixels below which 10 bits per axis are used.
pub const PIXELS_10_BITS: f64 = 500.0;
/// Projected size in pixels below which 20 bits per axis are used.
pub const PIXELS_20_BITS: f64 = 500.0 * 1024.0;

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

/// The precision to draw a batch with, and the projected size (pixels) it was chosen from
/// (`None` for a fixed precision).
pub fn choose_precision(mode: PrecisionMode, camera: &Camera, grid: &Grid, batch: &BatchGrid) -> (Precision, Option<f64>) {
    let (wanted, pixels) = match mode {
        PrecisionMode::Fixed(p) => (p, None),
        PrecisionMode::Adaptive => {
            let px = camera.projected_size(&quantization_box(grid, batch));
            (precision_for_pixels(px), Some(px))
        }
    };
    (wanted.min(sufficient_precision(batch)), pixels)
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
        let (p, px) = choose_precision(PrecisionMode::Adaptive, &cam, &grid, &small);
        assert_eq!(p, Precision::Bits10);
        assert!((px.unwrap() - 327.68).abs() < 1e-6);
        // 2^16 mm = 65.5 m -> 655 px: 20 bits.
        let medium = BatchGrid { min: [10_000, 10_000, 0], bits: [16, 12, 12] };
        assert_eq!(choose_precision(PrecisionMode::Adaptive, &cam, &grid, &medium).0, Precision::Bits20);
        // 2^26 mm = 67 km -> 671,000 px: 30 bits.
        let huge = BatchGrid { min: [0, 0, 0], bits: [26, 12, 12] };
        assert_eq!(choose_precision(PrecisionMode::Adaptive, &cam, &grid, &huge).0, Precision::Bits30);
        // A batch that 10 bits hold exactly never loads more, whatever is asked.
        let exact = BatchGrid { min: [0, 0, 0], bits: [10, 10, 10] };
        assert_eq!(choose_precision(PrecisionMode::Fixed(Precision::Bits30), &cam, &grid, &exact).0, Precision::Bits10);
        assert_eq!(choose_precision(PrecisionMode::Fixed(Precision::Bits20), &cam, &grid, &huge).0, Precision::Bits20);
        // Zooming in 4x moves the small batch over the threshold.
        let mut close = cam;
        close.projection = Projection::Orthographic { height: 25.0 };
        assert_eq!(choose_precision(PrecisionMode::Adaptive, &close, &grid, &small).0, Precision::Bits20);
    }
}
