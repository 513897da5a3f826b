//! Merging the integer grids of several inputs onto one.
//!
//! A LAS file stores `x = offset + scale * X` with `X: i32`. Inputs with different scale or offset
//! are merged exactly onto one grid: the finest scale on each axis, and an offset such that every
//! input's integers map to integers, `X_out = X_in * factor + shift`. When no such grid exists (a
//! scale that is not an integer multiple of the finest, an offset off the grid, or a merged extent
//! larger than `i32` can hold) [`merge`] returns an error before any point is read.

/// Scale and offset of one LAS integer grid.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    pub scale: [f64; 3],
    pub offset: [f64; 3],
}

impl Grid {
    /// World coordinate of integer coordinate `v` on axis `a`.
    #[inline]
    pub fn world(&self, a: usize, v: i64) -> f64 {
        self.offset[a] + self.scale[a] * v as f64
    }
    /// Nearest integer coordinate of world coordinate `x` on axis `a` (not clamped).
    #[inline]
    pub fn to_int(&self, a: usize, x: f64) -> i64 {
        ((x - self.offset[a]) / self.scale[a]).round() as i64
    }
}

/// How one input's integers map onto the merged grid, per axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GridMap {
    pub factor: [i64; 3],
    pub shift: [i64; 3],
}

impl GridMap {
    pub const IDENTITY: GridMap = GridMap { factor: [1; 3], shift: [0; 3] };

    pub fn is_identity(&self) -> bool {
        *self == GridMap::IDENTITY
    }

    /// The merged-grid integers of `p`, or `None` if they leave `i32` (a point outside the
    /// bounds its header declared).
    #[inline]
    pub fn apply(&self, p: [i32; 3]) -> Option<[i32; 3]> {
        let f = |a: usize| i32::try_from(p[a] as i64 * self.factor[a] + self.shift[a]).ok();
        Some([f(0)?, f(1)?, f(2)?])
    }
}

/// One input to [`merge`]: its grid and the integer bounds its header declares.
#[derive(Clone, Copy, Debug)]
pub struct GridInput {
    pub grid: Grid,
    pub min: [i64; 3],
    pub max: [i64; 3],
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GridError {
    #[error("input {index}: scale {scale} on axis {axis} is not a positive finite number")]
    BadScale { index: usize, axis: char, scale: f64 },
    #[error("input {index}: scale {scale} on axis {axis} is not an integer multiple of the finest scale {finest}, so its points cannot be merged exactly")]
    ScaleNotMultiple { index: usize, axis: char, scale: f64, finest: f64 },
    #[error("input {index}: offset {offset} on axis {axis} does not lie on the merged grid (offset {merged_offset}, scale {scale}), so its points cannot be merged exactly")]
    OffsetOffGrid { index: usize, axis: char, offset: f64, merged_offset: f64, scale: f64 },
    #[error("the merged inputs span {extent} steps of {scale} on axis {axis}, more than a 32-bit LAS integer can hold")]
    ExtentTooLarge { axis: char, extent: f64, scale: f64 },
}

const AXES: [char; 3] = ['x', 'y', 'z'];

fn near_integer(v: f64, tol: f64) -> Option<i64> {
    let r = v.round();
    if (v - r).abs() <= tol && r.abs() < 9.0e15 {
        Some(r as i64)
    } else {
        None
    }
}

/// The merged grid and the map of each input onto it.
pub fn merge(inputs: &[GridInput]) -> Result<(Grid, Vec<GridMap>), GridError> {
    assert!(!inputs.is_empty());
    let first = inputs[0].grid;
    if inputs.iter().all(|i| i.grid == first) {
        return Ok((first, vec![GridMap::IDENTITY; inputs.len()]));
    }
    let mut grid = first;
    let mut maps = vec![GridMap::IDENTITY; inputs.len()];
    for a in 0..3 {
        for (index, i) in inputs.iter().enumerate() {
            let s = i.grid.scale[a];
            if !(s.is_finite() && s > 0.0) {
                return Err(GridError::BadScale { index, axis: AXES[a], scale: s });
            }
        }
        let finest = inputs.iter().map(|i| i.grid.scale[a]).fold(f64::INFINITY, f64::min);
        grid.scale[a] = finest;
        for (index, i) in inputs.iter().enumerate() {
            let ratio = i.grid.scale[a] / finest;
            match near_integer(ratio, 1e-9 * ratio) {
                Some(k) if k >= 1 => maps[index].factor[a] = k,
                _ => {
                    return Err(GridError::ScaleNotMultiple {
                        index,
                        axis: AXES[a],
                        scale: i.grid.scale[a],
                        finest,
                    })
                }
            }
            let d = (i.grid.offset[a] - first.offset[a]) / finest;
            match near_integer(d, 1e-6) {
                Some(d) => maps[index].shift[a] = d,
                None => {
                    return Err(GridError::OffsetOffGrid {
                        index,
                        axis: AXES[a],
                        offset: i.grid.offset[a],
                        merged_offset: first.offset[a],
                        scale: finest,
                    })
                }
            }
        }
        // Merged integer extent; re-centre the offset (by whole steps) if it leaves i32.
        let lo = inputs
            .iter()
            .zip(&maps)
            .map(|(i, m)| i.min[a] * m.factor[a] + m.shift[a])
            .min()
            .unwrap();
        let hi = inputs
            .iter()
            .zip(&maps)
            .map(|(i, m)| i.max[a] * m.factor[a] + m.shift[a])
            .max()
            .unwrap();
        if hi - lo > u32::MAX as i64 {
            return Err(GridError::ExtentTooLarge {
                axis: AXES[a],
                extent: (hi - lo) as f64,
                scale: finest,
            });
        }
        if lo < i32::MIN as i64 || hi > i32::MAX as i64 {
            let centre = lo + (hi - lo) / 2;
            grid.offset[a] = first.offset[a] + centre as f64 * finest;
            for m in maps.iter_mut() {
                m.shift[a] -= centre;
            }
        }
    }
    Ok((grid, maps))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn input(scale: f64, offset: f64, min: i64, max: i64) -> GridInput {
        GridInput {
            grid: Grid { scale: [scale; 3], offset: [offset; 3] },
            min: [min; 3],
            max: [max; 3],
        }
    }

    #[test]
    fn identical_grids_are_identity() {
        let (g, m) = merge(&[input(0.01, 5.0, 0, 10), input(0.01, 5.0, -4, 3)]).unwrap();
        assert_eq!(g.scale, [0.01; 3]);
        assert!(m.iter().all(GridMap::is_identity));
    }

    #[test]
    fn coarser_scale_and_shifted_offset_merge_exactly() {
        let (g, m) = merge(&[input(0.001, 100.0, 0, 10), input(0.01, 101.0, 0, 10)]).unwrap();
        assert_eq!(g.scale, [0.001; 3]);
        assert_eq!(m[1].factor, [10; 3]);
        assert_eq!(m[1].shift, [1000; 3]);
        let p = m[1].apply([7, 7, 7]).unwrap();
        // 101 + 0.07 == 100 + 0.001 * 1070
        assert_eq!(p, [1070; 3]);
    }

    #[test]
    fn impossible_merges_fail() {
        assert!(matches!(
            merge(&[input(0.01, 0.0, 0, 1), input(0.015, 0.0, 0, 1)]),
            Err(GridError::ScaleNotMultiple { .. })
        ));
        assert!(matches!(
            merge(&[input(0.01, 0.0, 0, 1), input(0.01, 0.005, 0, 1)]),
            Err(GridError::OffsetOffGrid { .. })
        ));
        assert!(matches!(
            merge(&[input(0.001, 0.0, i32::MIN as i64, 0), input(0.01, 0.0, 0, i32::MAX as i64)]),
            Err(GridError::ExtentTooLarge { .. })
        ));
    }

    #[test]
    fn recentres_when_merged_range_leaves_i32() {
        let a = input(0.01, 0.0, 150_000_000, 220_000_000);
        let b = input(0.001, 1.0e6, 0, 1_000_000_000);
        let (g, m) = merge(&[a, b]).unwrap();
        assert_eq!(g.scale, [0.001; 3]);
        for (i, map) in [a, b].iter().zip(&m) {
            for v in [i.min[0], i.max[0]] {
                let p = map.apply([v as i32; 3]).unwrap();
                // same world coordinate on both grids
                let w_in = i.grid.world(0, v);
                let w_out = g.world(0, p[0] as i64);
                assert!((w_in - w_out).abs() < 1e-6, "{w_in} {w_out}");
            }
        }
        assert!(g.offset[0] != 0.0);
    }
}
