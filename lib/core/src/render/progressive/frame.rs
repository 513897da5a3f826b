//! The quantization frame of a progressive renderer's shuffled buffer ([`ProgressiveFrame`]), the
//! Distribute step's frame that the CPU and GPU renderers share, which grows when points arrive
//! outside it, and the integer box of a piece of arriving points ([`piece_box`]).

use super::error::ProgressiveError;
use crate::grid::Grid;
use crate::quantize::BatchGrid;
use crate::render::framing::IntBox;
use crate::render::math::Aabb;
use rayon::prelude::*;

/// The one quantization frame of a progressive renderer's shuffled buffer and the bounds its
/// planner sees, the same for every slot; the CPU renderer and its GPU twin hold one each and
/// grow it alike.
///
/// The paper allocates from the header before any point arrives; headers lie, so the frame is
/// the box the points are expected in (`data`: the headers' box) grown by its largest extent on
/// every side ([`around`](Self::around)), and when a point arrives outside it the frame grows
/// again ([`grown`](Self::grown): the box of everything expected and arrived, plus its extent),
/// as the octree builder grows its root: each growth more than doubles the frame, so it happens
/// a few times at most; the words already held are re-encoded in the new frame (exactly: every
/// frame holds every bit), and since a point's key depends on the point and the camera alone
/// (`plan::plan_batch`), nothing drawn moves. Refused only past 2^30 grid units on an axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProgressiveFrame {
    /// The integer grid of the points.
    pub grid: Grid,
    /// The box of the points expected (the headers') and of those that arrived.
    pub data: IntBox,
    /// Integer minimum and bits per axis of the words.
    pub quant: BatchGrid,
    /// Largest integer coordinate the frame holds per axis.
    pub max: [i32; 3],
    /// World bounds of the frame (what the planner culls and chooses precision with).
    pub bounds: Aabb,
}

impl ProgressiveFrame {
    /// The frame `min..=max` exactly, with no margin.
    pub fn exact(
        grid: Grid,
        min: [i32; 3],
        max: [i32; 3],
    ) -> Result<ProgressiveFrame, ProgressiveError> {
        if (0..3).any(|a| min[a] > max[a]) {
            return Err(ProgressiveError::Frame { min, max });
        }
        let quant = BatchGrid::for_bounds(min, max).ok_or(ProgressiveError::Frame { min, max })?;
        let b = IntBox { min, max };
        Ok(ProgressiveFrame { grid, data: b, quant, max, bounds: b.world(&grid) })
    }

    /// The frame of points expected in `data`: `data` grown by its largest extent (and one grid
    /// step) on every side, less where the frame would need more than 30 bits on an axis.
    pub fn around(grid: Grid, data: IntBox) -> Result<ProgressiveFrame, ProgressiveError> {
        let extent = data.extent();
        let room = ((1i64 << 30) - 1 - (extent + 2)).max(0) / 2;
        let margin = (extent + 1).min(room);
        let clamp = |v: i64| v.clamp(i32::MIN as i64, i32::MAX as i64) as i32;
        let min = data.min.map(|v| clamp(v as i64 - 1 - margin));
        let max = data.max.map(|v| clamp(v as i64 + 1 + margin));
        let mut f = ProgressiveFrame::exact(grid, min, max)
            .map_err(|_| ProgressiveError::Frame { min: data.min, max: data.max })?;
        f.data = data;
        Ok(f)
    }

    /// Whether the frame holds `p`.
    #[inline]
    pub fn holds(&self, p: &[i32; 3]) -> bool {
        (0..3).all(|a| p[a] >= self.quant.min[a] && p[a] <= self.max[a])
    }

    /// The frame grown to hold the points of `b` too ([`around`](Self::around) the box of
    /// everything expected and arrived), or `None` when it holds them already. Fails (the frame
    /// unchanged) when that needs more than 30 bits on an axis.
    pub fn grown(&self, b: IntBox) -> Result<Option<ProgressiveFrame>, ProgressiveError> {
        if self.holds(&b.min) && self.holds(&b.max) {
            return Ok(None);
        }
        ProgressiveFrame::around(self.grid, self.data.union(b)).map(Some)
    }

    /// The words of `words` (encoded in `from`) in this frame.
    #[inline]
    pub fn reencode(&self, from: &BatchGrid, words: [u32; 3]) -> [u32; 3] {
        self.quant.encode(from.decode_exact(words))
    }
}

/// The integer box of a piece's points (`None` for none), computed in parallel.
pub fn piece_box(xyz: &[[i32; 3]]) -> Option<IntBox> {
    xyz.par_chunks(1 << 16).filter_map(IntBox::of).reduce_with(IntBox::union)
}
