//! The bounds the inputs' headers declare, on the merged grid, and the warning for points
//! outside them: where every engine (and a distributed job) places the octree's root from.

use crate::dataset::{Dataset, RecordSource};
use crate::error::BoundsError;

/// The integer bounds the inputs' headers declare (one unit of margin), on the merged grid, with
/// a warning for each input whose header bounds are not usable; `None` when no header is.
pub(crate) fn header_bounds(
    ds: &Dataset,
    warnings: &mut Vec<String>,
) -> Option<([i32; 3], [i32; 3])> {
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    for src in &ds.inputs {
        if src.point_count() == 0 {
            continue;
        }
        // A store standing for its inputs: their box, as its build placed the root by it (on
        // the same grid: `--append` refuses another).
        if let Some(declared) = src.declared_box() {
            if let Some((l, h)) = declared {
                for a in 0..3 {
                    lo[a] = lo[a].min(l[a]);
                    hi[a] = hi[a].max(h[a]);
                }
            }
            continue;
        }
        match header_box(ds, src.as_ref()) {
            Ok((l, h)) => {
                for a in 0..3 {
                    lo[a] = lo[a].min(l[a]);
                    hi[a] = hi[a].max(h[a]);
                }
            }
            Err(why) => warnings.push(format!(
                "{}: {why}; the octree is placed from the points",
                src.path().display()
            )),
        }
    }
    (lo[0] <= hi[0]).then_some((lo, hi))
}

/// The integer box the header of `src` declares (one unit of margin), on the merged grid, or
/// why it is not usable.
pub(crate) fn header_box(
    ds: &Dataset,
    src: &dyn RecordSource,
) -> std::result::Result<([i32; 3], [i32; 3]), BoundsError> {
    let h = src.header();
    if src.point_count() > 1 && (0..3).all(|a| h.min[a] == 0.0 && h.max[a] == 0.0) {
        return Err(BoundsError::AllZero);
    }
    if let Some(a) =
        (0..3).find(|&a| !(h.min[a].is_finite() && h.max[a].is_finite()) || h.min[a] > h.max[a])
    {
        return Err(BoundsError::Unusable {
            axis: ['x', 'y', 'z'][a],
            min: h.min[a],
            max: h.max[a],
        });
    }
    let c = |v: i64| v.clamp(i32::MIN as i64, i32::MAX as i64) as i32;
    Ok((
        [0, 1, 2].map(|a| c(ds.grid.to_int(a, h.min[a]).saturating_sub(1))),
        [0, 1, 2].map(|a| c(ds.grid.to_int(a, h.max[a]).saturating_add(1))),
    ))
}

/// A warning when the points of `src` (`st`, on the merged grid) reach outside the bounds its
/// header declares, with both ranges in world coordinates on the file's grid.
pub(crate) fn bounds_warning(
    ds: &Dataset,
    src: &dyn RecordSource,
    st: &crate::sort::PieceStats,
) -> Option<String> {
    let h = src.header();
    if st.count == 0
        || (0..3).any(|a| !(h.min[a].is_finite() && h.max[a].is_finite()) || h.min[a] > h.max[a])
    {
        return None;
    }
    let g = &ds.grid;
    let outside = (0..3).any(|a| {
        (st.min[a] as i64) < g.to_int(a, h.min[a]) - 1
            || (st.max[a] as i64) > g.to_int(a, h.max[a]) + 1
    });
    if !outside {
        return None;
    }
    let digits = |a: usize| (-h.scale[a].log10()).ceil().clamp(0.0, 12.0) as usize;
    let range = |a: usize, lo: f64, hi: f64| {
        format!("{} [{:.*}, {:.*}]", ['x', 'y', 'z'][a], digits(a), lo, digits(a), hi)
    };
    let real: Vec<String> = (0..3)
        .map(|a| range(a, g.world(a, st.min[a] as i64), g.world(a, st.max[a] as i64)))
        .collect();
    let declared: Vec<String> = (0..3).map(|a| range(a, h.min[a], h.max[a])).collect();
    Some(format!(
        "{}: its points reach {}, outside the bounds its header declares ({}); the octree's root holds them (`mortar sort` writes the file with true bounds)",
        src.path().display(),
        real.join(", "),
        declared.join(", ")
    ))
}
