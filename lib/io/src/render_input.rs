//! Drawing batch files with the CPU reference rasterizer of [`mortar_core::render`] (paper 003
//! §3.2-3.3): the adapter from a [`BatchFile`] to the rasterizer's [`BatchRef`]s, LAS/LAZ inputs
//! batched on the fly into a temporary batch file ([`RenderSource`]), and the colours of the
//! visibility-buffer resolve ([`colors_for_keys`]): only the points that won a pixel are looked
//! up, batch by batch, in the colour mode asked for (scalar modes over the range of all the
//! points, [`color_range`]) (§3.3: "transform the point indices to vertex
//! colors in a post-processing step").
//!
//! Uncompressed batch files are used in place: the rasterizer reads the memory map, so the pages of
//! a word array a batch does not need (its medium and fine words at 10-bit precision, every word of
//! a culled batch) are never read from disk. zstd files are decompressed (the three word sections
//! of every batch) before drawing.

use crate::batchfile::{AttributeSelection, BatchFile, BatchSink, BatchView, Compression};
use crate::cleanup::TempPath;
use crate::dataset::Dataset;
use crate::error::{Error, RenderError, Result};
use crate::sort::{sort, SortOptions};
use mortar_core::layout::Family;
use mortar_core::render::framebuffer::{key_index, EMPTY_KEY};
use mortar_core::render::resolve::{
    classification_color, elevation_color, gps_time_color, intensity_color, resolve,
    return_number_color, ColorMode, ResolveOptions,
};
use mortar_core::render::{
    rasterize, Aabb, BatchRef, Camera, Framebuffer, RasterOptions, RasterStats,
};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Sections of a batch holding the coarse, medium and fine words.
const WORD_SECTIONS: [usize; 3] = [0, 1, 2];
/// Section of the stored RGBA8 render colour.
const COLOR_SECTION: usize = 3;
/// Section of the first kept attribute.
const FIRST_ATTRIBUTE_SECTION: usize = 4;

/// A batch file to draw: opened as given, or made from LAS/LAZ inputs in a temporary directory
/// that is removed when this is dropped (and on Ctrl-C, through [`crate::cleanup`]).
#[derive(Debug)]
pub struct RenderSource {
    /// The batch file.
    pub file: BatchFile,
    /// What the user gave: the batch file's path, or the LAS/LAZ inputs.
    pub name: PathBuf,
    // Dropped after `file` (declaration order): the map is closed before the directory goes.
    temp: Option<TempPath>,
}

impl RenderSource {
    /// Opens an existing batch file.
    pub fn open_batch_file(path: &Path) -> Result<RenderSource> {
        Ok(RenderSource { file: BatchFile::open(path)?, name: path.to_path_buf(), temp: None })
    }

    /// Morton-sorts and batches `ds` exactly as `mortar batch --attributes ...` does (no
    /// compression) into a temporary batch file under `opts.tmp_dir`, and opens it.
    pub fn batch_dataset(
        ds: &Dataset,
        opts: &SortOptions,
        attributes: &AttributeSelection,
    ) -> Result<RenderSource> {
        let names: Vec<String> = ds.inputs.iter().map(|i| i.path().display().to_string()).collect();
        let dir =
            TempPath::dir_in(&opts.tmp_dir, "render").map_err(|e| Error::io(&opts.tmp_dir, e))?;
        let path = dir.path().join("input.mbat");
        let attributes = attributes.resolve(&ds.layout)?;
        let template = ds.source_meta();
        let mut sink = BatchSink::new(&path, template, attributes, Compression::None);
        sort(ds, opts, &mut sink)?;
        sink.finish()?;
        Ok(RenderSource {
            file: BatchFile::open(&path)?,
            name: PathBuf::from(names.join(" ")),
            temp: Some(dir),
        })
    }

    /// `e` with the temporary batch file's path replaced by the inputs' names, so that messages
    /// name what the user gave.
    pub fn own_error(&self, e: Error) -> Error {
        e.renamed(&self.file.path, &self.name)
    }

    /// Whether the batch file is a temporary one made from LAS/LAZ.
    pub fn is_temporary(&self) -> bool {
        self.temp.is_some()
    }
}

/// World bounds of every point of the file.
pub fn file_bounds(file: &BatchFile) -> Aabb {
    let (a, b) = (file.meta.world_min, file.meta.world_max);
    Aabb::new([0, 1, 2].map(|i| a[i].min(b[i])), [0, 1, 2].map(|i| a[i].max(b[i])))
}

/// The coordinate words of every batch: borrowed from the map for uncompressed files,
/// decompressed (in parallel) for zstd files.
pub fn load_words(file: &BatchFile) -> Result<Vec<BatchView<'_>>> {
    (0..file.batch_count())
        .into_par_iter()
        .map(|i| file.batch_sections(i, &WORD_SECTIONS))
        .collect()
}

/// The rasterizer's view of the batches in `views` (from [`load_words`] on `file`). Fails when the
/// file holds more than 2^32 points (point indices are 32-bit in the framebuffer).
pub fn batch_refs<'a>(file: &BatchFile, views: &'a [BatchView<'_>]) -> Result<Vec<BatchRef<'a>>> {
    if file.header.point_count > 1u64 << 32 {
        return Err(Error::Render {
            path: file.path.clone(),
            error: RenderError::TooManyToDraw { points: file.header.point_count },
        });
    }
    Ok(views
        .iter()
        .map(|v| {
            let e = v.entry;
            BatchRef {
                grid: e.grid(),
                bounds_min: [0, 1, 2].map(|a| e.world_min[a].min(e.world_max[a])),
                bounds_max: [0, 1, 2].map(|a| e.world_min[a].max(e.world_max[a])),
                words: [v.words(0), v.words(1), v.words(2)],
                first_index: e.first_point as u32,
            }
        })
        .collect())
}

/// What the points are coloured by.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum ColorChoice {
    /// RGB when the source has colours, else intensity over the visible points' range, else the
    /// stored colour ([`resolved`](Self::resolved) says which).
    #[default]
    Auto,
    /// The batch file's stored render colour: RGB when the source has it, else a grey ramp of
    /// intensity over the dataset's whole intensity range.
    Stored,
    /// An attribute colour mode.
    Mode(ColorMode),
}

impl ColorChoice {
    /// Names accepted on the command line: `auto`, `stored` and the names of [`ColorMode`].
    pub fn names() -> Vec<&'static str> {
        let mut v = vec!["auto", "stored"];
        v.extend(ColorMode::ALL.iter().map(|m| m.name()));
        v
    }

    /// The choice of a name from [`names`](Self::names).
    pub fn from_name(name: &str) -> Option<ColorChoice> {
        match name {
            "auto" => Some(ColorChoice::Auto),
            "stored" => Some(ColorChoice::Stored),
            _ => ColorMode::from_name(name).map(ColorChoice::Mode),
        }
    }

    /// The name of the choice.
    pub fn name(self) -> &'static str {
        match self {
            ColorChoice::Auto => "auto",
            ColorChoice::Stored => "stored",
            ColorChoice::Mode(m) => m.name(),
        }
    }

    /// The choice `Auto` stands for in `file`; other choices unchanged.
    pub fn resolved(self, file: &BatchFile) -> ColorChoice {
        match self {
            ColorChoice::Auto if file.meta.color.source == "rgb" => {
                ColorChoice::Mode(ColorMode::Rgb)
            }
            ColorChoice::Auto if file.meta.attributes.iter().any(|a| a.name == "intensity") => {
                ColorChoice::Mode(ColorMode::Intensity)
            }
            ColorChoice::Auto => ColorChoice::Stored,
            c => c,
        }
    }

    /// The attributes of `layout` that drawing with this choice reads: the mode's attribute, and
    /// RGB and intensity, from which the stored colour is chosen (positions are always read).
    /// For [`Dataset::decode_only`] and the attributes of a batch file made only to be drawn.
    pub fn attributes(self, layout: &mortar_core::layout::RecordLayout) -> Vec<&'static str> {
        let mut v = vec!["rgb", "intensity"];
        if let ColorChoice::Mode(m) = self {
            v.push(m.attribute());
        }
        v.retain(|n| layout.attribute(n).is_some());
        v.dedup();
        v
    }

    /// Whether the choice maps a scalar over a range (intensity, elevation, GPS time).
    pub fn uses_range(self) -> bool {
        matches!(
            self,
            ColorChoice::Mode(ColorMode::Intensity | ColorMode::Elevation | ColorMode::GpsTime)
        )
    }
}

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

/// The value at quantile `q` (0-1) of `v` (finite values only; reorders `v`).
pub(crate) fn quantile(v: &mut [f64], q: f64) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let k = ((v.len() - 1) as f64 * q).round() as usize;
    Some(*v.select_nth_unstable_by(k, f64::total_cmp).1)
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

/// The value of attribute colour mode `mode` from the bytes `v` of its field (as
/// [`ColorMode::attribute`] names it) in a record of `family`: the colour for classification and
/// return number, the `f64` bits of the value for intensity and GPS time.
#[inline]
pub(crate) fn attribute_value(mode: ColorMode, family: Family, v: &[u8]) -> u64 {
    match mode {
        ColorMode::Intensity => (u16::from_le_bytes([v[0], v[1]]) as f64).to_bits(),
        ColorMode::GpsTime => f64::from_le_bytes(v[..8].try_into().expect("8 bytes")).to_bits(),
        ColorMode::Classification => {
            let code = if family == Family::Legacy { v[0] & 0x1f } else { v[0] };
            classification_color(code) as u64
        }
        ColorMode::ReturnNumber => {
            let (r, n) = match family {
                Family::Legacy => (v[0] & 0x07, (v[0] >> 3) & 0x07),
                Family::Extended => (v[0] & 0x0f, v[0] >> 4),
            };
            return_number_color(r, n) as u64
        }
        ColorMode::Rgb | ColorMode::Elevation => unreachable!("not read from an attribute"),
    }
}

/// The range a scalar colour mode maps over when none is given: the 1st to 99th percentile of
/// the finite `values` (`f64` bits), robust against outliers.
pub(crate) fn percentile_range(values: &[u64]) -> [f64; 2] {
    let mut v: Vec<f64> =
        values.iter().map(|&b| f64::from_bits(b)).filter(|x| x.is_finite()).collect();
    let lo = quantile(&mut v, 0.01).unwrap_or(0.0);
    let hi = quantile(&mut v, 0.99).unwrap_or(1.0);
    [lo, hi]
}

/// Colours of scalar values (`f64` bits) in `mode` (intensity, elevation, GPS time) over
/// `range`, or when it is `None` over [`percentile_range`]; and the range used.
pub(crate) fn scalar_colors(
    mode: ColorMode,
    values: &[u64],
    range: Option<[f64; 2]>,
) -> (Vec<u32>, [f64; 2]) {
    let range = range.unwrap_or_else(|| percentile_range(values));
    let color = |v: f64| match mode {
        ColorMode::Intensity => intensity_color(v as u16, range),
        ColorMode::Elevation => elevation_color(v, range),
        _ => gps_time_color(v, range),
    };
    (values.par_iter().map(|&b| color(f64::from_bits(b))).collect(), range)
}

/// How a view is drawn and coloured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderSettings {
    /// Precision and culling.
    pub raster: RasterOptions,
    /// Colour mode.
    pub color: ColorChoice,
    /// Range of scalar colour modes (`None`: from the visible points).
    pub range: Option<[f64; 2]>,
    /// Background, hole filling, eye-dome lighting.
    pub resolve: ResolveOptions,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            raster: RasterOptions::default(),
            color: ColorChoice::Auto,
            range: None,
            resolve: ResolveOptions::default(),
        }
    }
}

/// A rendered view.
#[derive(Clone, Debug)]
pub struct Rendered {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// The visibility buffer: depth|index keys, row-major from the top-left pixel.
    pub keys: Vec<u64>,
    /// The image, RGBA8 packed as `r | g << 8 | b << 16 | a << 24`, row-major.
    pub rgba: Vec<u32>,
    /// What the rasterizer did.
    pub stats: RasterStats,
    /// Pixels holding a point (before hole filling).
    pub covered: u64,
    /// Seconds spent rasterizing (culling, projection, depth tests).
    pub raster_seconds: f64,
    /// Seconds spent resolving (colour look-up, hole filling, eye-dome lighting).
    pub resolve_seconds: f64,
    /// The range scalar colour modes used.
    pub color_range: Option<[f64; 2]>,
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

    #[test]
    fn colour_choice_names_round_trip() {
        for name in ColorChoice::names() {
            assert_eq!(ColorChoice::from_name(name).map(ColorChoice::name), Some(name));
        }
        assert_eq!(ColorChoice::from_name("height"), None);
        assert!(ColorChoice::Mode(ColorMode::GpsTime).uses_range());
        assert!(!ColorChoice::Mode(ColorMode::Classification).uses_range());
    }

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
