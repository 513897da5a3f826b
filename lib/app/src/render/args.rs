//! The options of `mortar render`, parsed apart from what is built from them (the camera, the
//! renderer), and the parsers of their values.

use crate::cli as common;
use crate::draw::ColorChoice;
use anyhow::{bail, Result};
use mortar_core::octree::{LodOptions, DEFAULT_THRESHOLD_PX};
use mortar_core::quantize::Precision;
use mortar_core::render::resolve::{EyeDome, HoleFill, ResolveOptions};
use mortar_core::render::PrecisionMode;
use std::path::PathBuf;

/// Which rasterizer draws.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// The CPU reference rasterizer.
    Cpu,
    /// The wgpu compute rasterizer on the best adapter, software ones (a CPU Vulkan) included.
    Gpu,
    /// The GPU rasterizer on a hardware adapter if there is one, else the CPU rasterizer.
    Auto,
}

/// Which atomics the GPU rasterizer uses.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum AtomicsArg {
    /// 64-bit where the adapter has them, else 32-bit.
    Auto,
    /// One pass with 64-bit atomicMin on depth|index keys.
    #[value(name = "64")]
    U64,
    /// Two passes with 32-bit atomics (depth, then index).
    #[value(name = "32")]
    U32,
}

/// Precision of the coordinate words each batch loads.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum PrecisionArg {
    /// From each batch's size on screen (the 500 px rule).
    Adaptive,
    /// The coarse word only.
    #[value(name = "10")]
    Bits10,
    /// Coarse and medium words.
    #[value(name = "20")]
    Bits20,
    /// All three words (exact).
    #[value(name = "30")]
    Bits30,
}

impl PrecisionArg {
    /// The rasterizer's precision mode.
    pub fn mode(self) -> PrecisionMode {
        match self {
            PrecisionArg::Adaptive => PrecisionMode::Adaptive,
            PrecisionArg::Bits10 => PrecisionMode::Fixed(Precision::Bits10),
            PrecisionArg::Bits20 => PrecisionMode::Fixed(Precision::Bits20),
            PrecisionArg::Bits30 => PrecisionMode::Fixed(Precision::Bits30),
        }
    }

    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            PrecisionArg::Adaptive => "adaptive",
            PrecisionArg::Bits10 => "10",
            PrecisionArg::Bits20 => "20",
            PrecisionArg::Bits30 => "30",
        }
    }
}

/// Framed views of the data.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ViewArg {
    /// From above, north up.
    Top,
    /// From the south.
    Front,
    /// From the east.
    Side,
    /// From the south-west and above.
    Iso,
    /// Looking down at 45 degrees at the middle, about a tenth of the extent wide.
    Closeup,
    /// From inside the data: above the middle at 30 % of the height, looking north.
    Inside,
}

/// Where the camera is.
#[derive(clap::Args, Clone, Debug)]
pub struct CameraArgs {
    /// A view framing the data.
    #[arg(long, value_enum, conflicts_with = "eye")]
    pub view: Option<ViewArg>,
    /// Eye position x,y,z (world coordinates, as in the file); needs --target.
    #[arg(long, value_parser = parse_vec3, requires = "target", allow_hyphen_values = true)]
    pub eye: Option<[f64; 3]>,
    /// The point looked at, x,y,z.
    #[arg(long, value_parser = parse_vec3, requires = "eye", allow_hyphen_values = true)]
    pub target: Option<[f64; 3]>,
    /// Up direction x,y,z.
    #[arg(long, value_parser = parse_vec3, default_value = "0,0,1", allow_hyphen_values = true)]
    pub up: [f64; 3],
    /// Vertical field of view in degrees (perspective; with --ortho it sets the visible height
    /// at the target's distance).
    #[arg(long, default_value_t = 50.0)]
    pub fov: f64,
    /// Orthographic projection instead of perspective.
    #[arg(long)]
    pub ortho: bool,
}

/// `x,y,z` as three numbers.
pub fn parse_vec3(s: &str) -> std::result::Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>().map_err(|_| format!("'{s}' is not x,y,z (three numbers)")))
        .collect::<std::result::Result<_, _>>()?;
    match v[..] {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok([x, y, z]),
        _ => Err(format!("'{s}' is not x,y,z (three finite numbers)")),
    }
}

/// `lo,hi` as two numbers.
pub(crate) fn parse_range(s: &str) -> std::result::Result<[f64; 2], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| format!("'{s}' is not lo,hi"))?;
    match v[..] {
        [lo, hi] if lo.is_finite() && hi.is_finite() && lo < hi => Ok([lo, hi]),
        _ => Err(format!("'{s}' is not lo,hi with lo < hi")),
    }
}

/// A colour: a name (black, white, grey, transparent) or #rrggbb / #rrggbbaa; RGBA8 packed.
pub fn parse_color(s: &str) -> std::result::Result<u32, String> {
    let rgba = |r: u32, g: u32, b: u32, a: u32| r | g << 8 | b << 16 | a << 24;
    match s.to_ascii_lowercase().as_str() {
        "black" => return Ok(rgba(0, 0, 0, 255)),
        "white" => return Ok(rgba(255, 255, 255, 255)),
        "grey" | "gray" => return Ok(rgba(128, 128, 128, 255)),
        "transparent" | "none" => return Ok(0),
        _ => {}
    }
    let hex = s.strip_prefix('#').unwrap_or(s);
    let bad =
        || format!("'{s}' is not a colour (black, white, grey, transparent, #rrggbb or #rrggbbaa)");
    if !(hex.len() == 6 || hex.len() == 8) || !hex.chars().all(|c| c.is_ascii_hexdigit()) {
        return Err(bad());
    }
    let byte = |i: usize| u32::from_str_radix(&hex[2 * i..2 * i + 2], 16).map_err(|_| bad());
    let a = if hex.len() == 8 { byte(3)? } else { 255 };
    Ok(rgba(byte(0)?, byte(1)?, byte(2)?, a))
}

pub(crate) fn parse_color_choice(s: &str) -> std::result::Result<ColorChoice, String> {
    ColorChoice::from_name(s).ok_or_else(|| {
        format!("'{s}' is not a colour mode (one of {})", ColorChoice::names().join(", "))
    })
}

/// The options of a view that `mortar render` and `mortar view` share, defined once: the size,
/// the camera, the colours, the precision, the atomics and the resolve.
#[derive(clap::Args, Clone, Debug)]
pub struct ViewArgs {
    /// Width in pixels (of the image; of the window when it opens).
    #[arg(long, default_value_t = 1280)]
    pub width: u32,
    /// Height in pixels (of the image; of the window when it opens).
    #[arg(long, default_value_t = 720)]
    pub height: u32,
    #[command(flatten)]
    pub camera: CameraArgs,
    /// Colour mode: auto (RGB if the points have colours, else intensity), stored (the batch
    /// file's render colour), rgb, intensity, classification, elevation, return-number, gps-time
    /// (in the window, C cycles through the modes the input has).
    #[arg(long, default_value = "auto", value_parser = parse_color_choice)]
    pub color: ColorChoice,
    /// Range lo,hi of intensity, elevation and gps-time colours (default: 1st to 99th percentile
    /// of all the points).
    #[arg(long, value_parser = parse_range, allow_hyphen_values = true)]
    pub range: Option<[f64; 2]>,
    /// Coordinate precision: adaptive (paper 003's 500 px rule) or 10, 20, 30 bits for every batch.
    #[arg(long, value_enum, default_value = "adaptive")]
    pub precision: PrecisionArg,
    /// Atomics of the GPU rasterizer: auto, 64 or 32 (the two-pass fallback).
    #[arg(long, value_enum, default_value = "auto")]
    pub atomics: AtomicsArg,
    /// Fill empty pixels from their nearest neighbour where at least N of the 8 neighbours hold a
    /// point (--hole-fill alone: N = 3, which keeps silhouettes).
    #[arg(long, value_name = "N", num_args = 0..=1, default_missing_value = "3", value_parser = clap::value_parser!(u32).range(1..=8))]
    pub hole_fill: Option<u32>,
    /// Eye-dome lighting (shading from depth differences), with an optional strength.
    #[arg(long, value_name = "STRENGTH", num_args = 0..=1, default_missing_value = "1.0")]
    pub edl: Option<f32>,
    /// Background colour: black, white, grey, transparent, #rrggbb or #rrggbbaa.
    #[arg(long, default_value = "black", value_parser = parse_color)]
    pub background: u32,
}

impl ViewArgs {
    /// The resolve's choices of `--background`, `--hole-fill [N]` and `--edl [STRENGTH]`
    /// (shared by `mortar render`, `mortar view` and `build --preview`).
    pub fn resolve_options(&self) -> ResolveOptions {
        ResolveOptions {
            background: self.background,
            hole_fill: self.hole_fill.map(|n| HoleFill { min_neighbors: n }),
            eye_dome: self.edl.map(|strength| EyeDome { strength, ..EyeDome::default() }),
        }
    }
}

/// Arguments of `mortar render`.
#[derive(clap::Args)]
pub struct Args {
    /// A batch file, an octree store (drawn with LOD, see --lod-threshold), or LAS/LAZ files,
    /// directories, glob patterns or - (batched on the fly into a temporary batch file, as
    /// `mortar batch` would).
    #[arg(required = true)]
    pub inputs: Vec<String>,
    /// Output PNG (- for stdout).
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub view: ViewArgs,
    /// Draw every batch, also those outside the view (same image, slower).
    #[arg(long)]
    pub no_cull: bool,
    /// Rasterizer: cpu, gpu (any adapter, software included) or auto (a hardware GPU if there is
    /// one, else cpu).
    #[arg(long, value_enum, default_value = "auto")]
    pub backend: Backend,
    /// Print statistics as JSON on stdout (on stderr when the PNG goes to stdout).
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub sort: common::SortArgs,
    #[command(flatten)]
    pub lod: LodArgs,
    #[command(flatten)]
    pub progressive: ProgressiveArgs,
}

/// The LOD options of `mortar render` (stores only).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct LodArgs {
    /// Stores: an inner node is replaced by its children while its cube is wider than PX pixels
    /// on screen (paper 004 §6; default 128, the voxel grid's edge). 0 draws every visible leaf:
    /// full detail.
    #[arg(long, value_name = "PX", allow_hyphen_values = true)]
    pub lod_threshold: Option<f64>,
    /// Stores: most points and voxels to draw; the nodes largest on screen are refined first.
    #[arg(long, value_name = "N")]
    pub point_budget: Option<u64>,
    /// Stores: draw every point through a temporary batch file instead of LOD nodes (allows the
    /// attribute colour modes: intensity, classification, return number, GPS time).
    #[arg(long, conflicts_with_all = ["lod_threshold", "point_budget"])]
    pub no_lod: bool,
}

impl LodArgs {
    /// The selection options (culling as the rasterizer's).
    pub fn options(&self, cull: bool) -> Result<LodOptions> {
        let threshold_px = self.lod_threshold.unwrap_or(DEFAULT_THRESHOLD_PX);
        if threshold_px.is_nan() || threshold_px < 0.0 {
            bail!("--lod-threshold {threshold_px}: must be 0 or more pixels");
        }
        Ok(LodOptions { threshold_px, point_budget: self.point_budget, cull })
    }
}

/// The progressive options of `mortar render` (raw LAS/LAZ only).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ProgressiveArgs {
    /// LAS/LAZ: draw progressively (paper 000) while the points load: N frames with a still
    /// camera, writing the last; `converge` draws until the image is final (every point loaded
    /// and drawn), which is the brute-force image.
    #[arg(long, value_name = "N|converge")]
    pub progressive: Option<String>,
    /// With --progressive: slots of the shuffled buffer the Fill pass draws per frame (default
    /// 1000000), or `auto` for the adaptive budget of paper 000 §3.4.1 (see --target-ms).
    #[arg(long, value_name = "POINTS|auto", requires = "progressive")]
    pub budget: Option<String>,
    /// With --budget auto: the frame time to stay within; with --pace: the frame period, in ms
    /// (default 16.6).
    #[arg(long, value_name = "MS", requires = "progressive")]
    pub target_ms: Option<f64>,
    /// With --progressive: wait out each frame to --target-ms, as a display at that rate would,
    /// so that the loader threads get the cores in between (frames are otherwise drawn back to
    /// back, which on a CPU renderer takes cores from decoding).
    #[arg(long, requires = "progressive")]
    pub pace: bool,
    /// With --budget auto: points filled first to measure the fill rate (default 100000).
    #[arg(long, value_name = "POINTS", requires = "progressive")]
    pub probe: Option<u64>,
    /// With --progressive: read every point before the first frame, so that frame k draws
    /// exactly the k-th budget of the shuffled buffer (reproducible frames for tests).
    #[arg(long, requires = "progressive")]
    pub preload: bool,
    /// With --progressive: threads decoding the input (default: one per core).
    #[arg(long, value_name = "N", requires = "progressive")]
    pub load_threads: Option<usize>,
}
