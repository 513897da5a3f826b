//! The framing rule of [`mortar_core::render::framing`] applied to raw LAS/LAZ inputs: the
//! headers' box on the merged grid and the first piece's points, from which
//! [`view_box`] decides what every renderer of these inputs frames (`mortar render` with or
//! without `--progressive`, `mortar view` with or without `--no-progressive`, CPU or GPU).

use crate::dataset::Dataset;
use crate::error::{Error, Result};
use mortar_core::layout::read_xyz;
use mortar_core::render::framing::{self, IntBox, ViewBox};

/// The union of the headers' boxes of the inputs that hold points, on the merged grid; `None`
/// when one of them is unusable (not finite, empty, outside the 32-bit grid) or no input holds
/// points.
pub fn header_box(ds: &Dataset) -> Option<IntBox> {
    let mut out: Option<IntBox> = None;
    for src in ds.inputs.iter().filter(|s| s.pieces().iter().any(|p| p.points > 0)) {
        let h = src.header();
        let b = IntBox::from_world(&ds.grid, h.min, h.max)?;
        out = Some(out.map_or(b, |o| o.union(b)));
    }
    out
}

/// The integer coordinates (merged grid) of the points of the first piece that holds any: one
/// LAS piece or LAZ chunk. (Read from the source itself, so that the dataset's progress counts
/// only the pieces a job reads; X, Y, Z are the first 12 bytes of every point format.)
pub fn first_points(ds: &Dataset) -> Result<Vec<[i32; 3]>> {
    let Some(p) = ds.pieces().into_iter().find(|p| p.piece.points > 0) else {
        return Ok(Vec::new());
    };
    let src = &ds.inputs[p.input];
    let records = src.read_piece(&p.piece)?;
    let map = ds.maps[p.input];
    records
        .chunks_exact(src.layout().record_len)
        .map(|r| {
            map.apply(read_xyz(r))
                .ok_or_else(|| Error::OutsideGrid { path: src.path().to_path_buf() })
        })
        .collect()
}

/// What every renderer of `ds` frames ([`framing::view_box`] of the headers' box and the first
/// piece's points). Reads the first piece.
pub fn view_box(ds: &Dataset) -> Result<ViewBox> {
    let header = header_box(ds);
    // A header that is no bound at all needs no piece read to be found out.
    if header.is_none() {
        return Ok(ViewBox::Points);
    }
    Ok(framing::view_box(header, &first_points(ds)?))
}
