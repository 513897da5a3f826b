//! The one framing rule of every renderer of a file: which box the framed views (`--view`, the
//! window's first view and its F key) and the clip planes are made from. The brute-force render,
//! the progressive renderer (CPU and GPU), LOD and the window all call [`view_box`], so that the
//! same file is seen from the same eye whichever renderer draws it.
//!
//! The rule: **frame the box the header declares, unless the first points of the file lie farther
//! than its extent outside it; then frame the points' own box.**
//!
//! - The header's box (the union of the inputs' headers for several files, snapped to the integer
//!   grid) is the only bound every format has before a point is decoded, and the progressive
//!   renderer must fix its camera before its first frame, which comes after the first piece is
//!   decoded and long before the last. A renderer that reads every point first (the brute force)
//!   must not use the better box it knows, or switching renderers would move the view.
//! - Headers lie, mostly by a little (a z range a few centimetres or metres short): such points
//!   are drawn (the progressive renderer's quantization frame grows to hold them) and the view
//!   stays on the header's box.
//! - Some headers are no bound at all (zeros, or not finite, or empty): the first piece of the
//!   file (one LAS piece or LAZ chunk, decoded by the progressive renderer before its first frame
//!   anyway, and cheap for the others to read) tells such a header from one that is merely a bit
//!   short: the header is taken when each of those points lies within the box grown by its
//!   largest extent on every side (the margin the progressive renderer's quantization frame
//!   starts with). When one lies farther out, or the box is unusable, the rule frames the points'
//!   box: the brute force has it after batching, the progressive renderer reads every point
//!   before its first frame (as `--preload`) and takes their box.
//!
//! A batch file or a store records the exact box of its points in its header, which holds its
//! points, so the same rule frames that box.

use super::math::Aabb;
use crate::grid::Grid;

/// A box of integer coordinates on a grid, `min..=max` per axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct IntBox {
    /// Smallest integer coordinate per axis.
    pub min: [i32; 3],
    /// Largest integer coordinate per axis.
    pub max: [i32; 3],
}

impl IntBox {
    /// The box of `points` (`None` for none).
    pub fn of(points: &[[i32; 3]]) -> Option<IntBox> {
        let first = *points.first()?;
        let mut b = IntBox { min: first, max: first };
        for p in points {
            b.add(p);
        }
        Some(b)
    }

    /// Grows the box to hold `p`.
    #[inline]
    pub fn add(&mut self, p: &[i32; 3]) {
        for a in 0..3 {
            self.min[a] = self.min[a].min(p[a]);
            self.max[a] = self.max[a].max(p[a]);
        }
    }

    /// The smallest box holding both.
    pub fn union(self, o: IntBox) -> IntBox {
        IntBox {
            min: [0, 1, 2].map(|a| self.min[a].min(o.min[a])),
            max: [0, 1, 2].map(|a| self.max[a].max(o.max[a])),
        }
    }

    /// Whether `p` lies in the box.
    #[inline]
    pub fn contains(&self, p: &[i32; 3]) -> bool {
        (0..3).all(|a| p[a] >= self.min[a] && p[a] <= self.max[a])
    }

    /// The largest extent over the axes, in grid units.
    pub fn extent(&self) -> i64 {
        (0..3).map(|a| self.max[a] as i64 - self.min[a] as i64).max().unwrap_or(0)
    }

    /// Whether `p` lies within `margin` grid units of the box on every axis.
    #[inline]
    pub fn near(&self, p: &[i32; 3], margin: i64) -> bool {
        (0..3).all(|a| {
            p[a] as i64 >= self.min[a] as i64 - margin && p[a] as i64 <= self.max[a] as i64 + margin
        })
    }

    /// The world box on `grid` (ordered on axes with a negative scale).
    pub fn world(&self, grid: &Grid) -> Aabb {
        let mut b = Aabb::EMPTY;
        for a in 0..3 {
            let (x, y) = (grid.world(a, self.min[a] as i64), grid.world(a, self.max[a] as i64));
            b.min[a] = x.min(y);
            b.max[a] = x.max(y);
        }
        b
    }

    /// The integer box of the world box `min..max` on `grid` (each end to the nearest grid
    /// coordinate), `None` where it is not finite, empty or outside the 32-bit grid: a header
    /// that declares no usable bound.
    pub fn from_world(grid: &Grid, min: [f64; 3], max: [f64; 3]) -> Option<IntBox> {
        let mut b = IntBox { min: [0; 3], max: [0; 3] };
        for a in 0..3 {
            if !(min[a].is_finite() && max[a].is_finite() && min[a] <= max[a]) {
                return None;
            }
            let (x, y) = (grid.to_int(a, min[a]), grid.to_int(a, max[a]));
            let (lo, hi) = (x.min(y), x.max(y));
            if lo < i32::MIN as i64 || hi > i32::MAX as i64 {
                return None;
            }
            b.min[a] = lo as i32;
            b.max[a] = hi as i32;
        }
        Some(b)
    }
}

/// What [`view_box`] decided.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ViewBox {
    /// Frame the header's box.
    Header(IntBox),
    /// Frame the box of all the points (the header's box is unusable or misses the first
    /// points): known only once every point was read.
    Points,
}

impl ViewBox {
    /// The world box to frame: the header's, or `points()` (the integer box of every point).
    pub fn bounds(self, grid: &Grid, points: impl FnOnce() -> IntBox) -> Aabb {
        match self {
            ViewBox::Header(b) => b.world(grid),
            ViewBox::Points => points().world(grid),
        }
    }
}

/// The framing rule (see the module documentation): the header's box `header` (`None`: no usable
/// box) if every point of `first` (the integer coordinates of the file's first piece) lies within
/// its largest extent of it, else the points' box.
pub fn view_box(header: Option<IntBox>, first: &[[i32; 3]]) -> ViewBox {
    match header {
        Some(h) if first.iter().all(|p| h.near(p, h.extent())) => ViewBox::Header(h),
        _ => ViewBox::Points,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_header_box_unless_it_misses_the_first_points() {
        let grid = Grid { scale: [0.01, 0.01, -0.001], offset: [1000.0, 0.0, 5.0] };
        let h = IntBox::from_world(&grid, [1000.0, 0.0, 4.0], [1010.0, 5.0, 6.0]).unwrap();
        assert_eq!(h, IntBox { min: [0, 0, -1000], max: [1000, 500, 1000] });
        let inside = [[0, 0, 0], [1000, 500, -1000], [7, 8, 9]];
        assert_eq!(view_box(Some(h), &inside), ViewBox::Header(h));
        // A header a little short of its points still frames (within its extent, 2000 units
        // here); only the first piece is checked.
        assert_eq!(view_box(Some(h), &[]), ViewBox::Header(h));
        assert_eq!(view_box(Some(h), &[[0, 0, 0], [3000, -2000, 3000]]), ViewBox::Header(h));
        assert_eq!(view_box(Some(h), &[[0, 0, 0], [3001, 0, 0]]), ViewBox::Points);
        assert_eq!(view_box(Some(h), &[[0, -2001, 0]]), ViewBox::Points);
        // A header of zeros (no bound written) is not a bound for points elsewhere.
        let zero = IntBox { min: [0; 3], max: [0; 3] };
        assert_eq!(view_box(Some(zero), &[[5, 0, 0]]), ViewBox::Points);
        assert_eq!(view_box(Some(zero), &[[0, 0, 0]]), ViewBox::Header(zero));
        assert_eq!(view_box(None, &inside), ViewBox::Points);
        let pts = || IntBox { min: [-5, 0, 0], max: [5, 1, 2] };
        let w = ViewBox::Points.bounds(&grid, pts);
        assert_eq!((w.min, w.max), ([999.95, 0.0, 4.998], [1000.05, 0.01, 5.0]));
        let w = ViewBox::Header(h).bounds(&grid, || unreachable!());
        assert_eq!((w.min, w.max), ([1000.0, 0.0, 4.0], [1010.0, 5.0, 6.0]));
        // Unusable headers: not finite, empty, outside the grid.
        assert_eq!(IntBox::from_world(&grid, [f64::NAN, 0.0, 0.0], [1.0; 3]), None);
        assert_eq!(IntBox::from_world(&grid, [2000.0, 0.0, 0.0], [1000.0, 1.0, 1.0]), None);
        assert_eq!(IntBox::from_world(&grid, [0.0; 3], [1e12, 1.0, 1.0]), None);
        assert_eq!(IntBox::of(&inside), Some(IntBox { min: [0, 0, -1000], max: [1000, 500, 9] }));
        assert_eq!(IntBox::of(&[]), None);
    }
}
