//! Colouring and drawing the selected nodes of a store ([`mortar_io::store::StoreLod`], paper
//! 004 §6) with either rasterizer: every sample is a real source point with its record (leaf
//! points, and the point each voxel stands for), so every colour mode works under LOD: the
//! source's RGB (the payload's colour), elevation from the exact decoded height, and intensity,
//! classification, return number and GPS time from the record's attributes, with scalar modes
//! mapped over a given range or that of all the points ([`color_range`], over the leaves: the
//! rule of every renderer, so LOD and `--no-lod` colour alike), the same in `mortar render` and
//! the window. `auto` is RGB where the source has colours, else intensity. Hole filling and
//! eye-dome lighting work as for batch files: they read only the keys.

use super::color::{attribute_value, percentile_range, scalar_colors, ColorChoice};
use super::settings::{RenderSettings, Rendered};
use mortar_core::grid::Grid;
use mortar_core::octree::{LodTree, NodeId};
use mortar_core::render::framebuffer::{key_index, EMPTY_KEY};
use mortar_core::render::resolve::{resolve, ColorMode};
use mortar_core::render::{rasterize, Camera, Framebuffer, RasterStats};
use mortar_io::error::{Error, RenderError, Result};
use mortar_io::store::{LodBatches, Store, StoreLod};
use rayon::prelude::*;
use std::time::Instant;

/// What an LOD render colours samples by.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LodColor {
    /// The payload's RGBA8 colour: the source's RGB (or, without RGB, the intensity grey baked
    /// at build time).
    Stored,
    /// Height, from the exact decoded position.
    Elevation,
    /// An attribute mode (intensity, classification, return number, GPS time) from the samples'
    /// records.
    Attribute(ColorMode),
}

/// Whether the store's payload colours are the source's RGB: its format has RGB and the root's
/// samples (real points spread over the whole cloud) are not all black.
fn rgb_in_use(store: &Store) -> bool {
    let Some(rgb) = store.layout.attribute("rgb") else { return false };
    if store.entries.is_empty() || store.entries[0].count == 0 {
        return true;
    }
    let d = store.node(0);
    let al = d.header.attr_len as usize;
    let off = rgb.offset - 12;
    (0..d.header.count as usize)
        .any(|i| d.attributes[i * al + off..i * al + off + 6].iter().any(|&b| b != 0))
}

impl LodColor {
    /// The colour source of `choice` for `store`, or an error naming the store for modes its
    /// point format cannot show. `auto` is RGB where the source has colours, else intensity.
    pub fn of(store: &Store, choice: ColorChoice) -> Result<LodColor> {
        match choice {
            ColorChoice::Auto if rgb_in_use(store) => Ok(LodColor::Stored),
            ColorChoice::Auto if store.layout.attribute("intensity").is_some() => {
                Ok(LodColor::Attribute(ColorMode::Intensity))
            }
            ColorChoice::Auto | ColorChoice::Stored => Ok(LodColor::Stored),
            ColorChoice::Mode(ColorMode::Elevation) => Ok(LodColor::Elevation),
            ColorChoice::Mode(ColorMode::Rgb) if rgb_in_use(store) => Ok(LodColor::Stored),
            ColorChoice::Mode(ColorMode::Rgb) => Err(Error::Render {
                path: store.path.clone(),
                error: RenderError::NoColour {
                    format: store.layout.format,
                    has_rgb: store.layout.has_rgb(),
                },
            }),
            ColorChoice::Mode(m) if store.layout.attribute(m.attribute()).is_some() => {
                Ok(LodColor::Attribute(m))
            }
            ColorChoice::Mode(m) => Err(Error::Render {
                path: store.path.clone(),
                error: RenderError::MissingAttribute {
                    mode: m.name(),
                    attribute: m.attribute(),
                    format: store.layout.format,
                    not_kept: false,
                },
            }),
        }
    }

    /// The name reported for it.
    pub fn name(self) -> &'static str {
        match self {
            LodColor::Stored => "stored",
            LodColor::Elevation => "elevation",
            LodColor::Attribute(m) => m.name(),
        }
    }

    /// Whether it maps a scalar over a range (elevation, intensity, GPS time).
    pub fn uses_range(self) -> bool {
        matches!(
            self,
            LodColor::Elevation | LodColor::Attribute(ColorMode::Intensity | ColorMode::GpsTime)
        )
    }
}

/// The value of sample `index` of `batches` in `color`: a colour, or for scalar modes the
/// value's `f64` bits (`None` outside the selection).
fn sample_value(
    store: &Store,
    grid: &Grid,
    batches: &LodBatches<'_>,
    color: LodColor,
    index: u32,
) -> Option<u64> {
    match color {
        LodColor::Stored => batches.color(index).map(u64::from),
        LodColor::Elevation => {
            batches.position(index).map(|p| grid.world(2, p[2] as i64).to_bits())
        }
        LodColor::Attribute(m) => {
            let f = store.layout.attribute(m.attribute()).expect("checked by LodColor::of");
            let at = f.offset - 12;
            batches
                .attributes(index)
                .map(|a| attribute_value(m, store.layout.family(), &a[at..at + f.width]))
        }
    }
}

/// The colours of node `id`'s samples of `lod` in `color`, scalar modes over `range` (or the 1st
/// to 99th percentile of the node's own values): what a viewer uploads with the node.
pub fn node_colors(
    lod: &StoreLod,
    id: NodeId,
    color: LodColor,
    range: Option<[f64; 2]>,
) -> Result<Vec<u32>> {
    let b = lod.batches(&[id])?;
    let v: Vec<u64> = (0..b.samples as u32)
        .map(|i| sample_value(lod.store(), &lod.grid(), &b, color, i).unwrap_or(0))
        .collect();
    Ok(match color {
        LodColor::Stored
        | LodColor::Attribute(ColorMode::Classification | ColorMode::ReturnNumber) => {
            v.into_iter().map(|c| c as u32).collect()
        }
        LodColor::Elevation => scalar_colors(ColorMode::Elevation, &v, range).0,
        LodColor::Attribute(m) => scalar_colors(m, &v, range).0,
    })
}

/// The range scalar colour mode `color` maps over when none is given: the 1st to 99th
/// percentile of the values of every point of the store (the samples of the nodes without
/// children: the leaves, which hold every point, and in a commit of a build under way the
/// frontier whose levels below are not written yet), the one colour-range rule of every
/// renderer, so that LOD, `--no-lod` and the raw file colour alike. Reads every leaf once.
/// `None` for the other modes.
pub fn color_range(lod: &StoreLod, color: LodColor) -> Option<[f64; 2]> {
    if !color.uses_range() || lod.store().entries.is_empty() {
        return None;
    }
    let index = lod.index();
    let leaves: Vec<NodeId> = (0..index.node_count() as u32)
        .map(NodeId)
        .filter(|&id| index.children(id).is_none())
        .collect();
    let mut v = Vec::with_capacity(index.point_count() as usize);
    let (store, grid) = (lod.store(), lod.grid());
    for group in leaves.chunks(4096) {
        let b = lod.batches(group).ok()?;
        v.par_extend(
            (0..b.samples as u32)
                .into_par_iter()
                .filter_map(|i| sample_value(store, &grid, &b, color, i)),
        );
    }
    Some(percentile_range(&v))
}

/// Rasterizes `batches` (from [`StoreLod::batches`]) with the CPU rasterizer for `camera` and
/// resolves the image ([`resolve_keys`]).
pub fn render(
    lod: &StoreLod,
    batches: &LodBatches<'_>,
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<Rendered> {
    LodColor::of(lod.store(), settings.color)?;
    let fb = Framebuffer::new(camera.width, camera.height);
    let t0 = Instant::now();
    let stats =
        rasterize(&fb, &batches.refs, &lod.grid(), camera, &settings.raster).map_err(|error| {
            Error::Render { path: lod.path().to_path_buf(), error: RenderError::Raster { error } }
        })?;
    let raster_seconds = t0.elapsed().as_secs_f64();
    resolve_keys(lod, batches, fb.into_keys(), stats, raster_seconds, camera, settings)
}

/// Resolves a visibility buffer of `batches`' samples (drawn by either rasterizer with `stats`
/// in `raster_seconds`) into the image: stored colours or elevation (over `settings.range`, or
/// the range of all points, [`color_range`], that the store's window uses too), then hole
/// filling and eye-dome lighting as asked.
pub fn resolve_keys(
    lod: &StoreLod,
    batches: &LodBatches<'_>,
    keys: Vec<u64>,
    stats: RasterStats,
    raster_seconds: f64,
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<Rendered> {
    let color = LodColor::of(lod.store(), settings.color)?;
    let t1 = Instant::now();
    if keys.par_iter().any(|&k| k != EMPTY_KEY && key_index(k) as u64 >= batches.samples) {
        return Err(Error::Render {
            path: lod.path().to_path_buf(),
            error: RenderError::StrayIndex { beyond: "the selected samples" },
        });
    }
    let bg = settings.resolve.background;
    // The visible samples, their values, then their colours.
    let mut idx: Vec<u32> =
        keys.par_iter().filter(|&&k| k != EMPTY_KEY).map(|&k| key_index(k)).collect();
    idx.par_sort_unstable();
    idx.dedup();
    let values: Vec<u64> = idx
        .par_iter()
        .map(|&i| sample_value(lod.store(), &lod.grid(), batches, color, i).unwrap_or(0))
        .collect();
    // Scalar modes over the range of all the store's points, as its window and `--no-lod` map them.
    let range = settings.range.or_else(|| color_range(lod, color));
    let (colors, color_range) = match color {
        LodColor::Stored
        | LodColor::Attribute(ColorMode::Classification | ColorMode::ReturnNumber) => {
            (values.iter().map(|&c| c as u32).collect::<Vec<u32>>(), None)
        }
        LodColor::Elevation => {
            let (c, r) = scalar_colors(ColorMode::Elevation, &values, range);
            (c, Some(r))
        }
        LodColor::Attribute(m) => {
            let (c, r) = scalar_colors(m, &values, range);
            (c, Some(r))
        }
    };
    let color_of = |i: u32| idx.binary_search(&i).map_or(bg, |k| colors[k]);
    let rgba = resolve(&keys, camera.width, camera.height, color_of, &settings.resolve);
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
        color_range,
    })
}
