//! Drawing batch files with the CPU reference rasterizer of [`mortar_core::render`] (paper 003
//! §3.2-3.3) and the colours of the visibility-buffer resolve ([`colors_for_keys`]): only the
//! points that won a pixel are looked up, batch by batch, in the colour mode asked for (scalar
//! modes over the range of all the points, [`color_range`]). The batches themselves come from
//! [`mortar_io::batch_input`].

use super::color::{attribute_value, percentile_range, scalar_colors, ColorChoice};
use super::settings::{RenderSettings, Rendered};
use mortar_core::render::framebuffer::{key_index, EMPTY_KEY};
use mortar_core::render::resolve::{resolve, ColorMode};
use mortar_core::render::{rasterize, BatchRef, Camera, Framebuffer, RasterStats};
use mortar_io::batch_input::{COLOR_SECTION, FIRST_ATTRIBUTE_SECTION, WORD_SECTIONS};
use mortar_io::batchfile::BatchFile;
use mortar_io::error::{Error, RenderError, Result};
use rayon::prelude::*;
use std::time::Instant;

/// Where a colour mode's values come from in a batch file.
#[derive(Clone, Copy, Debug)]
enum Source {
    /// The stored RGBA8 section.
    Stored,
    /// Exact z from the three words.
    Elevation,
    /// Kept attribute number `index`, `width` bytes per point.
    Attribute { index: usize },
}

/// Checks that `file` has what `choice` needs, and says where it is.
fn source_of(file: &BatchFile, choice: ColorChoice) -> Result<Source> {
    let mode = match choice.resolved(file) {
        ColorChoice::Auto | ColorChoice::Stored => return Ok(Source::Stored),
        ColorChoice::Mode(ColorMode::Elevation) => return Ok(Source::Elevation),
        ColorChoice::Mode(ColorMode::Rgb) => {
            return if file.meta.color.source == "rgb" {
                Ok(Source::Stored)
            } else {
                Err(Error::Render {
                    path: file.path.clone(),
                    error: RenderError::NoColour {
                        format: file.layout.format,
                        has_rgb: file.layout.has_rgb(),
                    },
                })
            };
        }
        ColorChoice::Mode(m) => m,
    };
    let name = mode.attribute();
    if let Some(index) = file.meta.attributes.iter().position(|a| a.name == name) {
        return Ok(Source::Attribute { index });
    }
    let not_kept = file.layout.attribute(name).is_some();
    Err(Error::Render {
        path: file.path.clone(),
        error: RenderError::MissingAttribute {
            mode: mode.name(),
            attribute: name,
            format: file.layout.format,
            not_kept,
        },
    })
}

/// Checks that `file` has the attribute `choice` needs (an error naming the file otherwise).
pub fn check_color(file: &BatchFile, choice: ColorChoice) -> Result<()> {
    source_of(file, choice).map(|_| ())
}

/// The colours of the points that are visible in a framebuffer.
#[derive(Clone, Debug, Default)]
pub struct PointColors {
    indices: Vec<u32>,
    colors: Vec<u32>,
    /// The range scalar modes were mapped over (given, or 1st to 99th percentile of the visible
    /// points); `None` for the other modes.
    pub range: Option<[f64; 2]>,
}

impl PointColors {
    /// The colour of point `index`, if it was visible.
    #[inline]
    pub fn get(&self, index: u32) -> Option<u32> {
        self.indices.binary_search(&index).ok().map(|i| self.colors[i])
    }

    /// The colour of every point `0..points` in index order, `missing` for those not visible
    /// (for a resolve on the GPU, which looks colours up by index).
    pub fn dense(&self, points: usize, missing: u32) -> Vec<u32> {
        let mut out = vec![missing; points];
        for (&i, &c) in self.indices.iter().zip(&self.colors) {
            if let Some(slot) = out.get_mut(i as usize) {
                *slot = c;
            }
        }
        out
    }

    /// Number of distinct visible points.
    pub fn len(&self) -> usize {
        self.indices.len()
    }

    /// Whether no point was visible.
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }
}

/// Looks up the colours of the points that won a pixel in `keys` (point indices of `file`), in
/// the colour mode `choice`. Scalar modes map over `range`, or when it is `None` over
/// [`color_range`]: the 1st to 99th percentile of all the points' values, the one colour-range
/// rule of every renderer (view-independent, so that a renderer that only knows the points it
/// draws and one that draws all of them colour alike). Only the batches holding visible points
/// are read for the colours.
pub fn colors_for_keys(
    file: &BatchFile,
    keys: &[u64],
    choice: ColorChoice,
    range: Option<[f64; 2]>,
) -> Result<PointColors> {
    let choice = choice.resolved(file);
    let source = source_of(file, choice)?;
    let range = match range {
        Some(r) => Some(r),
        None => color_range(file, choice)?,
    };
    let mut indices: Vec<u32> =
        keys.par_iter().filter(|&&k| k != EMPTY_KEY).map(|&k| key_index(k)).collect();
    indices.par_sort_unstable();
    indices.dedup();
    colors_for_indices(file, indices, choice, source, range)
}

/// The range scalar colour mode `choice` maps over when none is given: the 1st to 99th
/// percentile of the values of every point of `file` (robust against outliers, independent of
/// the view); `None` for the modes without a range.
pub fn color_range(file: &BatchFile, choice: ColorChoice) -> Result<Option<[f64; 2]>> {
    let choice = choice.resolved(file);
    if !choice.uses_range() {
        return Ok(None);
    }
    let source = source_of(file, choice)?;
    if file.header.point_count > 1u64 << 32 {
        return Err(Error::Render {
            path: file.path.clone(),
            error: RenderError::TooManyToColour { points: file.header.point_count },
        });
    }
    let indices: Vec<u32> = (0..file.header.point_count).map(|i| i as u32).collect();
    Ok(Some(percentile_range(&values_for_indices(file, &indices, choice, source)?)))
}

/// The colour of every point of `file` (index order) in the mode `choice`, for renderers that
/// resolve on the GPU from per-point colours (`mortar view`). Scalar modes map over `range`, or
/// when it is `None` over the 1st to 99th percentile of all the points' values (view-independent,
/// unlike [`colors_for_keys`]). Returns the colours and the range used.
pub fn point_colors(
    file: &BatchFile,
    choice: ColorChoice,
    range: Option<[f64; 2]>,
) -> Result<(Vec<u32>, Option<[f64; 2]>)> {
    let choice = choice.resolved(file);
    let source = source_of(file, choice)?;
    if file.header.point_count > 1u64 << 32 {
        return Err(Error::Render {
            path: file.path.clone(),
            error: RenderError::TooManyToColour { points: file.header.point_count },
        });
    }
    let indices: Vec<u32> = (0..file.header.point_count).map(|i| i as u32).collect();
    let c = colors_for_indices(file, indices, choice, source, range)?;
    Ok((c.colors, c.range))
}

/// The colours of the points `indices` (sorted, distinct) of `file`.
fn colors_for_indices(
    file: &BatchFile,
    indices: Vec<u32>,
    choice: ColorChoice,
    source: Source,
    range: Option<[f64; 2]>,
) -> Result<PointColors> {
    let out = values_for_indices(file, &indices, choice, source)?;
    let mode = match choice {
        ColorChoice::Auto | ColorChoice::Stored | ColorChoice::Mode(ColorMode::Rgb) => None,
        ColorChoice::Mode(m) => Some(m),
    };
    if !choice.uses_range() {
        return Ok(PointColors {
            indices,
            colors: out.into_iter().map(|c| c as u32).collect(),
            range: None,
        });
    }
    let (colors, range) =
        scalar_colors(mode.expect("scalar modes are attribute or elevation modes"), &out, range);
    Ok(PointColors { indices, colors, range: Some(range) })
}

/// Per point of `indices` (sorted, distinct) of `file`: its colour, or in scalar modes the
/// value's `f64` bits.
fn values_for_indices(
    file: &BatchFile,
    indices: &[u32],
    choice: ColorChoice,
    source: Source,
) -> Result<Vec<u64>> {
    let entries = file.entries();
    let total = file.header.point_count;
    if indices.last().is_some_and(|&i| i as u64 >= total) {
        return Err(Error::Render {
            path: file.path.clone(),
            error: RenderError::StrayIndex { beyond: "the file's points" },
        });
    }
    // Runs of indices that fall in one batch.
    let mut groups = Vec::new();
    let mut s = 0;
    while s < indices.len() {
        let b = entries.partition_point(|e| e.first_point <= indices[s] as u64) - 1;
        let end_point = entries[b].first_point + entries[b].count as u64;
        let e = s + indices[s..].partition_point(|&i| (i as u64) < end_point);
        groups.push((b, s, e));
        s = e;
    }
    let sections: Vec<usize> = match source {
        Source::Stored => vec![COLOR_SECTION],
        Source::Elevation => WORD_SECTIONS.to_vec(),
        Source::Attribute { index } => vec![FIRST_ATTRIBUTE_SECTION + index],
    };
    let mode = match choice {
        ColorChoice::Auto | ColorChoice::Stored | ColorChoice::Mode(ColorMode::Rgb) => None,
        ColorChoice::Mode(m) => Some(m),
    };
    let family = file.layout.family();
    let grid = file.grid();
    // Per visible point: a colour, or (scalar modes) the value's f64 bits.
    let mut out = vec![0u64; indices.len()];
    let mut slices = Vec::with_capacity(groups.len());
    let mut rest = &mut out[..];
    for &(b, s, e) in &groups {
        let (head, tail) = rest.split_at_mut(e - s);
        slices.push((b, &indices[s..e], head));
        rest = tail;
    }
    slices.into_par_iter().try_for_each(|(b, idx, dst)| -> Result<()> {
        let view = file.batch_sections(b, &sections)?;
        let first = view.entry.first_point;
        let local = idx.iter().map(|&i| (i as u64 - first) as usize);
        match (source, mode) {
            (Source::Stored, _) => {
                let c = view.colors();
                for (d, k) in dst.iter_mut().zip(local) {
                    *d = c[k] as u64;
                }
            }
            (Source::Elevation, _) => {
                let g = view.entry.grid();
                let (c, m, f) = (view.words(0), view.words(1), view.words(2));
                for (d, k) in dst.iter_mut().zip(local) {
                    let z = g.decode_exact([c[k], m[k], f[k]])[2];
                    *d = grid.world(2, z as i64).to_bits();
                }
            }
            (Source::Attribute { index }, Some(mode)) => {
                let bytes = view.attribute(index);
                let width = file.meta.attributes[index].width;
                for (d, k) in dst.iter_mut().zip(local) {
                    *d = attribute_value(mode, family, &bytes[k * width..(k + 1) * width]);
                }
            }
            (Source::Attribute { .. }, None) => unreachable!("stored colours have no attribute"),
        }
        Ok(())
    })?;
    Ok(out)
}

/// Rasterizes `refs` (the batches of `file`, see [`batch_refs`]) for `camera` into a fresh
/// framebuffer and resolves the image. Deterministic: the same inputs give the same keys and
/// pixels whatever the thread count.
pub fn render(
    file: &BatchFile,
    refs: &[BatchRef<'_>],
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<Rendered> {
    check_color(file, settings.color)?;
    let fb = Framebuffer::new(camera.width, camera.height);
    let t0 = Instant::now();
    let stats = rasterize(&fb, refs, &file.grid(), camera, &settings.raster).map_err(|error| {
        Error::Render { path: file.path.clone(), error: RenderError::Raster { error } }
    })?;
    let raster_seconds = t0.elapsed().as_secs_f64();
    resolve_keys(file, fb.into_keys(), stats, raster_seconds, camera, settings)
}

/// Resolves a visibility buffer of `file`'s points (drawn by either rasterizer with `stats` in
/// `raster_seconds`) into the image: colours of the visible points in the chosen mode, then hole
/// filling and eye-dome lighting as asked.
pub fn resolve_keys(
    file: &BatchFile,
    keys: Vec<u64>,
    stats: RasterStats,
    raster_seconds: f64,
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<Rendered> {
    let t1 = Instant::now();
    let colors = colors_for_keys(file, &keys, settings.color, settings.range)?;
    let bg = settings.resolve.background;
    let rgba = resolve(
        &keys,
        camera.width,
        camera.height,
        |i| colors.get(i).unwrap_or(bg),
        &settings.resolve,
    );
    let resolve_seconds = t1.elapsed().as_secs_f64();
    let covered = keys.iter().filter(|&&k| k != EMPTY_KEY).count() as u64;
    Ok(Rendered {
        width: camera.width,
        height: camera.height,
        keys,
        rgba,
        stats,
        covered,
        raster_seconds,
        resolve_seconds,
        color_range: colors.range,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::draw::color::quantile;

    #[test]
    fn quantiles_and_lookup() {
        let mut v: Vec<f64> = (0..=100).rev().map(f64::from).collect();
        assert_eq!(quantile(&mut v, 0.01), Some(1.0));
        assert_eq!(quantile(&mut v, 0.99), Some(99.0));
        assert_eq!(quantile(&mut [], 0.5), None);
        let c = PointColors { indices: vec![3, 9, 40], colors: vec![30, 90, 400], range: None };
        assert_eq!((c.get(9), c.get(40), c.get(4)), (Some(90), Some(400), None));
        assert_eq!(c.len(), 3);
    }
}
