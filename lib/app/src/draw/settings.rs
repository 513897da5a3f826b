//! How a view is drawn and coloured ([`RenderSettings`]) and what drawing it gives
//! ([`Rendered`]): shared by the batch-file and store renderers.

use super::color::ColorChoice;
use mortar_core::render::resolve::ResolveOptions;
use mortar_core::render::{RasterOptions, RasterStats};

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
