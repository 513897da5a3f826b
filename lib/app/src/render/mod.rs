//! `mortar render`: one view of a batch file (or of LAS/LAZ batched on the fly) drawn by the CPU
//! reference rasterizer or the wgpu compute rasterizer (paper 003 §3.2-3.4) to a PNG. Both leave
//! the same visibility buffer; the colours are chosen from the visible points alone. The CPU
//! path resolves on the host; the GPU path reads the keys back only to choose the colours, and
//! hole filling, colours and eye-dome lighting run on the GPU (the same image, byte for byte).

pub mod lod;
pub mod progressive;

use crate::cli as common;
use anyhow::{anyhow, bail, Context, Result};
use mortar_core::grid::Grid;
use mortar_core::quantize::Precision;
use mortar_core::render::framing::{IntBox, ViewBox};
use mortar_core::render::resolve::{EyeDome, HoleFill, ResolveOptions};
use mortar_core::render::BatchRef;
use mortar_core::render::{Aabb, Camera, PrecisionMode, Projection, RasterOptions, ViewPreset};
use mortar_io::batchfile::{AttributeSelection, BatchFile};
use mortar_io::cleanup::TempPath;
use mortar_io::inputs::InputKind;
use mortar_io::render_input::{self, ColorChoice, RenderSettings, RenderSource, Rendered};
use mortar_render::{
    AtomicPath, GpuContext, GpuError, GpuFrame, GpuOptions, GpuRasterizer, GpuScene, SceneOptions,
};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

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

/// Prints a render's `--json` statistics: on stdout, or on stderr where the PNG goes to stdout.
pub(crate) fn print_json(a: &Args, j: &serde_json::Value) -> Result<()> {
    let text = serde_json::to_string_pretty(j)?;
    if a.output.as_os_str() == "-" {
        eprintln!("{text}");
    } else {
        println!("{text}");
    }
    Ok(())
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
    /// Image width in pixels.
    #[arg(long, default_value_t = 1280)]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 720)]
    pub height: u32,
    #[command(flatten)]
    pub camera: CameraArgs,
    /// Colour mode: auto (RGB if the points have colours, else intensity), stored (the batch
    /// file's render colour), rgb, intensity, classification, elevation, return-number, gps-time.
    #[arg(long, default_value = "auto", value_parser = parse_color_choice)]
    pub color: ColorChoice,
    /// Range lo,hi of intensity, elevation and gps-time colours (default: 1st to 99th percentile
    /// of the visible points).
    #[arg(long, value_parser = parse_range, allow_hyphen_values = true)]
    pub range: Option<[f64; 2]>,
    /// Coordinate precision: adaptive (paper 003's 500 px rule) or 10, 20, 30 bits for every batch.
    #[arg(long, value_enum, default_value = "adaptive")]
    pub precision: PrecisionArg,
    /// Draw every batch, also those outside the view (same image, slower).
    #[arg(long)]
    pub no_cull: bool,
    /// Rasterizer: cpu, gpu (any adapter, software included) or auto (a hardware GPU if there is
    /// one, else cpu).
    #[arg(long, value_enum, default_value = "auto")]
    pub backend: Backend,
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
    /// Print statistics as JSON on stdout (on stderr when the PNG goes to stdout).
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub sort: common::SortArgs,
    #[command(flatten)]
    pub lod: crate::render::lod::LodArgs,
    #[command(flatten)]
    pub progressive: crate::render::progressive::ProgressiveArgs,
}

/// Opens the inputs: a single batch file as it is, anything else batched into a temporary file,
/// with every attribute, or (`colour` given) only what drawing in that colour reads, so that
/// layered LAZ skips the rest. Also returns the box framed views frame, by the one framing rule
/// of every renderer ([`mortar_core::render::framing`]): for LAS/LAZ the headers' box unless the
/// first piece lies farther than its extent outside it, else (and for a batch file, whose
/// header records it) the points' box.
pub fn open_source(
    inputs: &[String],
    sort: &common::SortArgs,
    colour: Option<ColorChoice>,
) -> Result<(RenderSource, Aabb)> {
    if let [one] = inputs {
        let p = Path::new(one);
        if InputKind::of(p) == InputKind::BatchFile {
            let source = RenderSource::open_batch_file(p)?;
            let bounds = render_input::file_bounds(&source.file);
            return Ok((source, bounds));
        }
    }
    let mut ds = common::open_dataset(inputs, &sort.crs)?;
    common::print_warnings(&ds.warnings);
    let view = mortar_io::framing::view_box(&ds)?;
    let attributes = match colour {
        Some(c) => {
            let keep = c.attributes(&ds.layout);
            ds.decode_only(&keep);
            AttributeSelection::Only(keep.iter().map(|n| n.to_string()).collect())
        }
        None => AttributeSelection::All,
    };
    let source = RenderSource::batch_dataset(&ds, &sort.options(), &attributes)?;
    let points = render_input::file_bounds(&source.file);
    let label = source.name.display().to_string();
    let bounds = match view {
        ViewBox::Header(h) => {
            if let Some(p) = IntBox::from_world(&ds.grid, points.min, points.max) {
                warn_outside_header(&label, &h, &p, &ds.grid);
            }
            h.world(&ds.grid)
        }
        ViewBox::Points => {
            common::warn(&format!("{label}: the header's bounds do not hold the first points; framing the points' own box"));
            points
        }
    };
    Ok((source, bounds))
}

/// Warns when points lie outside the headers' box `header` (the box every renderer frames): they
/// are drawn, but framed views and the window's F key show the header's box.
pub(crate) fn warn_outside_header(label: &str, header: &IntBox, points: &IntBox, grid: &Grid) {
    if header.contains(&points.min) && header.contains(&points.max) {
        return;
    }
    let (h, p) = (header.world(grid), points.world(grid));
    common::warn(&format!(
        "{label}: points lie outside the header's bounds (points {:?}..{:?}, header {:?}..{:?}); they are drawn, but framed views show the header's box (`mortar sort` writes the true bounds)",
        p.min, p.max, h.min, h.max
    ));
}

/// The camera the arguments ask for, framing `bounds` where a view is asked for.
pub fn build_camera(a: &CameraArgs, bounds: &Aabb, width: u32, height: u32) -> Result<Camera> {
    if !(a.fov > 0.0 && a.fov < 180.0) {
        bail!("--fov {}: must be between 0 and 180 degrees", a.fov);
    }
    let fov = a.fov.to_radians();
    let cam = match (a.eye, a.target) {
        (Some(eye), Some(target)) => Camera::look_at(
            eye,
            target,
            a.up,
            Projection::Perspective { fov_y: fov },
            bounds,
            width,
            height,
        )?,
        _ => match a.view.unwrap_or(ViewArg::Iso) {
            ViewArg::Closeup => Camera::close_up(bounds, fov, width, height)?,
            ViewArg::Inside => Camera::inside(bounds, fov, width, height)?,
            v => {
                let preset = match v {
                    ViewArg::Top => ViewPreset::Top,
                    ViewArg::Front => ViewPreset::Front,
                    ViewArg::Side => ViewPreset::Side,
                    _ => ViewPreset::Iso,
                };
                if a.ortho {
                    return Ok(Camera::frame_orthographic(bounds, preset, width, height)?);
                }
                Camera::frame_perspective(bounds, preset, fov, width, height)?
            }
        },
    };
    if !a.ortho {
        return Ok(cam);
    }
    // Orthographic with the perspective view's visible height at the target's distance.
    let d: f64 = (0..3).map(|i| (cam.target[i] - cam.eye[i]).powi(2)).sum::<f64>().sqrt();
    let height_world = 2.0 * d * (0.5 * fov).tan();
    Ok(Camera::look_at(
        cam.eye,
        cam.target,
        cam.up,
        Projection::Orthographic { height: height_world },
        bounds,
        width,
        height,
    )?)
}

/// PNG bytes of an RGBA8 image (packed `r | g << 8 | b << 16 | a << 24`, row-major).
pub fn encode_png(width: u32, height: u32, rgba: &[u32]) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(png::ColorType::Rgba);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header()?;
        let bytes: Vec<u8> = rgba.iter().flat_map(|c| c.to_le_bytes()).collect();
        w.write_image_data(&bytes)?;
        w.finish()?;
    }
    Ok(out)
}

/// Writes bytes to `path` atomically (temporary file beside it, then rename), or to stdout for `-`.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    if path.as_os_str() == "-" {
        let mut out = std::io::stdout().lock();
        out.write_all(bytes)?;
        out.flush()?;
        return Ok(());
    }
    let tmp = TempPath::beside(path);
    std::fs::write(tmp.path(), bytes)
        .with_context(|| format!("{}: cannot write", path.display()))?;
    tmp.persist(path).with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}

/// The resolve's choices of `--background`, `--hole-fill [N]` and `--edl [STRENGTH]` (shared by
/// `mortar render`, `mortar view` and `build --preview`).
pub fn resolve_options(
    background: u32,
    hole_fill: Option<u32>,
    edl: Option<f32>,
) -> ResolveOptions {
    ResolveOptions {
        background,
        hole_fill: hole_fill.map(|n| HoleFill { min_neighbors: n }),
        eye_dome: edl.map(|strength| EyeDome { strength, ..EyeDome::default() }),
    }
}

/// The raster and resolve choices of the arguments.
pub(crate) fn render_settings(a: &Args) -> RenderSettings {
    RenderSettings {
        raster: RasterOptions { precision: a.precision.mode(), cull: !a.no_cull },
        color: a.color,
        range: a.range,
        resolve: resolve_options(a.background, a.hole_fill, a.edl),
    }
}

/// The GPU `--backend` asks for: none for cpu, any adapter (an error if none) for gpu, a
/// hardware GPU if there is one for auto.
pub(crate) fn gpu_context(a: &Args) -> Result<Option<GpuContext>> {
    let atomics = match a.atomics {
        AtomicsArg::Auto => None,
        AtomicsArg::U64 => Some(AtomicPath::U64),
        AtomicsArg::U32 => Some(AtomicPath::TwoPass32),
    };
    Ok(match a.backend {
        Backend::Cpu => None,
        Backend::Gpu => Some(
            GpuContext::new(&GpuOptions { atomics, allow_software: true, ..Default::default() })
                .map_err(|e| anyhow!("--backend gpu: {e}"))?,
        ),
        Backend::Auto => {
            GpuContext::new(&GpuOptions { atomics, allow_software: false, ..Default::default() })
                .ok()
        }
    })
}

pub(crate) fn camera_json(c: &Camera) -> serde_json::Value {
    let projection = match c.projection {
        Projection::Perspective { fov_y } => {
            serde_json::json!({ "perspective": { "fov_degrees": fov_y.to_degrees() } })
        }
        Projection::Orthographic { height } => {
            serde_json::json!({ "orthographic": { "height": height } })
        }
    };
    serde_json::json!({ "eye": c.eye, "target": c.target, "up": c.up, "projection": projection, "near": c.near, "far": c.far })
}

/// Opens the input, draws the view, writes the PNG and (with `--json`) the statistics.
pub fn run(a: Args) -> Result<()> {
    if a.width == 0 || a.height == 0 || a.width > 16384 || a.height > 16384 {
        bail!("--width {} --height {}: each side must be 1 to 16384 pixels", a.width, a.height);
    }
    // Checked again by build_camera; here so that a typo fails before LAS input is batched.
    if !(a.camera.fov > 0.0 && a.camera.fov < 180.0) {
        bail!("--fov {}: must be between 0 and 180 degrees", a.camera.fov);
    }
    if a.progressive.progressive.is_some() {
        return crate::render::progressive::run(&a);
    }
    if let Some(store) = crate::render::lod::store_input(&a)? {
        return crate::render::lod::run(&a, &store);
    }
    let start = Instant::now();
    let (source, bounds) = open_source(&a.inputs, &a.sort, Some(a.color))?;
    let batch_seconds = start.elapsed().as_secs_f64();
    let file = &source.file;
    let own = |e| source.own_error(e);
    let label = source.name.display().to_string();
    if file.header.point_count == 0 {
        bail!("{label}: no points to draw");
    }
    render_input::check_color(file, a.color).map_err(own)?;
    let camera = build_camera(&a.camera, &bounds, a.width, a.height)
        .map_err(|e| anyhow!("{label}: {e:#}"))?;
    let views = render_input::load_words(file).map_err(own)?;
    let refs = render_input::batch_refs(file, &views).map_err(own)?;
    let settings = render_settings(&a);
    let gpu = gpu_context(&a)?;
    let (r, gpu_json) = match &gpu {
        None => (
            render_input::render(file, &refs, &camera, &settings).map_err(own)?,
            serde_json::Value::Null,
        ),
        Some(ctx) => {
            let (r, j) = render_gpu(ctx, file, &refs, &camera, &settings)
                .map_err(|e| anyhow!("{label}: GPU: {e}"))?;
            (r.map_err(own)?, j)
        }
    };
    let t = Instant::now();
    let png = encode_png(r.width, r.height, &r.rgba)?;
    write_atomic(&a.output, &png)?;
    let png_seconds = t.elapsed().as_secs_f64();
    if a.json {
        let projected = r.stats.points_projected() as f64;
        let mut j = rendered_json(
            &a,
            &label,
            &r,
            &gpu_json,
            a.color.resolved(file).name(),
            &camera,
            file.header.point_count,
            png_seconds,
        );
        // Pixels whose winner ties in depth with another point (where a renderer numbering the
        // points otherwise may show another of them): a second pass over the points on the CPU,
        // on the CPU backend only.
        j["depth_ties"] = serde_json::json!(match &gpu {
            None => Some(
                mortar_core::render::count_depth_ties(
                    &r.keys,
                    &refs,
                    &file.grid(),
                    &camera,
                    &settings.raster
                )
                .map_err(|e| anyhow!("{label}: {e}"))?
            ),
            Some(_) => None,
        });
        j["batch_seconds"] =
            serde_json::json!(if source.is_temporary() { Some(batch_seconds) } else { None });
        j["gpu_points_per_second"] = serde_json::json!(gpu_json
            .get("draw_ms")
            .and_then(|v| v.as_f64())
            .map(|ms| projected / (ms * 1e-3).max(1e-12)));
        print_json(&a, &j)?;
    }
    Ok(())
}

/// The `--json` statistics every `mortar render` of batches (batch files, LAS/LAZ, stores)
/// reports; each caller adds its own.
#[allow(clippy::too_many_arguments)]
pub(crate) fn rendered_json(
    a: &Args,
    label: &str,
    r: &Rendered,
    gpu_json: &serde_json::Value,
    color: &str,
    camera: &Camera,
    points: u64,
    png_seconds: f64,
) -> serde_json::Value {
    let s = &r.stats;
    serde_json::json!({
        "input": label,
        "output": a.output,
        "width": r.width,
        "height": r.height,
        "backend": if gpu_json.is_null() { "cpu" } else { "gpu" },
        "gpu": gpu_json,
        "precision": a.precision.name(),
        "cull": !a.no_cull,
        "color": color,
        "color_range": r.color_range,
        "camera": camera_json(camera),
        "points": points,
        "batches": s.batches,
        "batches_culled": s.batches_culled,
        "batches_drawn": s.batches_drawn,
        "points_projected": s.points_projected(),
        "points_by_precision": { "10": s.points_by_precision[0], "20": s.points_by_precision[1], "30": s.points_by_precision[2] },
        "points_drawn": s.points_drawn,
        "pixels_covered": r.covered,
        "raster_seconds": r.raster_seconds,
        "resolve_seconds": r.resolve_seconds,
        "png_seconds": png_seconds,
        "points_per_second": s.points_projected() as f64 / r.raster_seconds.max(1e-9),
    })
}

/// Draws `refs` (batches on `grid` holding `points` points, indexed so that the keys' indices
/// are the points') with the GPU rasterizer: uploads them, draws one frame and reads the keys
/// back, for callers that resolve on the host exactly as their CPU path does (`mortar render`
/// of a store, whose colours come from the nodes' payloads; batch files and LAS/LAZ resolve on
/// the GPU, see `render_gpu`). Returns the keys, the frame and its `gpu` statistics for `--json`.
pub fn draw_keys_gpu(
    ctx: &GpuContext,
    grid: Grid,
    points: u64,
    refs: &[BatchRef<'_>],
    camera: &Camera,
    options: &RasterOptions,
) -> std::result::Result<(Vec<u64>, GpuFrame, serde_json::Value), GpuError> {
    let t = Instant::now();
    let mut scene = GpuScene::new(ctx, grid, points, SceneOptions::default())?;
    for b in refs {
        scene.push(ctx, b, None)?;
    }
    scene.flush(ctx)?;
    ctx.wait()?;
    let upload_seconds = t.elapsed().as_secs_f64();
    let mut raster = GpuRasterizer::new(ctx, camera.width, camera.height)?;
    let frame = raster.draw(ctx, &mut scene, camera, options, None)?;
    let keys = raster.read_keys(ctx)?;
    let j = gpu_json(ctx, &scene, upload_seconds, &frame);
    Ok((keys, frame, j))
}

/// A batch file drawn and resolved on the GPU: the batches uploaded (with room for colours),
/// one frame drawn, its keys read back to choose the colours of the visible points as the CPU
/// path does, those colours uploaded, and the framebuffer resolved on the GPU (hole filling,
/// colours, eye-dome lighting: [`GpuRasterizer::resolve`]); only the image comes back. The outer
/// error is the GPU's, the inner one the input's.
fn render_gpu(
    ctx: &GpuContext,
    file: &BatchFile,
    refs: &[BatchRef<'_>],
    camera: &Camera,
    settings: &RenderSettings,
) -> std::result::Result<(mortar_io::Result<Rendered>, serde_json::Value), GpuError> {
    if let Err(e) = render_input::check_color(file, settings.color) {
        return Ok((Err(e), serde_json::Value::Null));
    }
    let points = file.header.point_count;
    let t = Instant::now();
    let mut scene = GpuScene::new(
        ctx,
        file.grid(),
        points,
        SceneOptions { colors: true, ..Default::default() },
    )?;
    // The colours depend on the visible points: placeholders now, the real ones after the draw.
    let zeros = vec![0u32; refs.iter().map(BatchRef::len).max().unwrap_or(0)];
    for b in refs {
        scene.push(ctx, b, Some(&zeros[..b.len()]))?;
    }
    scene.flush(ctx)?;
    ctx.wait()?;
    let upload_seconds = t.elapsed().as_secs_f64();
    let mut raster = GpuRasterizer::new(ctx, camera.width, camera.height)?;
    let frame = raster.draw(ctx, &mut scene, camera, &settings.raster, None)?;
    let keys = raster.read_keys(ctx)?;
    let mut j = gpu_json(ctx, &scene, upload_seconds, &frame);
    let t = Instant::now();
    let colors = match render_input::colors_for_keys(file, &keys, settings.color, settings.range) {
        Ok(c) => c,
        Err(e) => return Ok((Err(e), j)),
    };
    let bg = settings.resolve.background;
    scene.set_colors(ctx, &colors.dense(points as usize, bg))?;
    let post = raster.resolve(ctx, &mut scene, &settings.resolve)?;
    let rgba = raster.read_image(ctx)?;
    let resolve_seconds = t.elapsed().as_secs_f64();
    j["timings"] = frame
        .timings
        .map(|t| {
            serde_json::json!({
                "clear_ms": t.clear_ms,
                "draw_ms": t.draw_ms,
                "hole_fill_ms": post.and_then(|p| p.hole_fill_ms),
                "resolve_ms": post.and_then(|p| p.resolve_ms),
                "eye_dome_ms": post.and_then(|p| p.eye_dome_ms),
            })
        })
        .into();
    let covered = keys.iter().filter(|&&k| k != mortar_core::render::EMPTY_KEY).count() as u64;
    let r = Rendered {
        width: camera.width,
        height: camera.height,
        keys,
        rgba,
        stats: frame.stats,
        covered,
        raster_seconds: frame.frame_seconds,
        resolve_seconds,
        color_range: colors.range,
    };
    Ok((Ok(r), j))
}

/// The `gpu` statistics of `--json`: the adapter, the scene and the frame.
fn gpu_json(
    ctx: &GpuContext,
    scene: &GpuScene,
    upload_seconds: f64,
    frame: &GpuFrame,
) -> serde_json::Value {
    let a = ctx.adapter();
    serde_json::json!({
        "adapter": a.name,
        "api": a.backend,
        "device_type": a.device_type,
        "driver": a.driver,
        "atomics": ctx.atomic_path().name(),
        "chunks": scene.chunk_count(),
        "gpu_bytes": scene.gpu_bytes(),
        "upload_seconds": upload_seconds,
        "plan_seconds": frame.plan_seconds,
        "frame_seconds": frame.frame_seconds,
        "draw_ms": frame.timings.map(|t| t.draw_ms),
    })
}
