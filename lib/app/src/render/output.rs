//! What `mortar render` does with its options for any input: the camera, the source batched on
//! the fly, the PNG written atomically, the JSON report, the GPU context, and the batch-file
//! draws on the CPU and GPU.

use super::args::*;
use crate::cli as common;
use crate::draw;
use crate::draw::{ColorChoice, RenderSettings, Rendered};
use anyhow::{anyhow, bail, Context, Result};
use mortar_core::grid::Grid;
use mortar_core::render::framing::{IntBox, ViewBox};
use mortar_core::render::BatchRef;
use mortar_core::render::{Aabb, Camera, Projection, RasterOptions, ViewPreset};
use mortar_io::batch_input::{self, RenderSource};
use mortar_io::batchfile::{AttributeSelection, BatchFile};
use mortar_io::cleanup::TempPath;
use mortar_io::inputs::InputKind;
use mortar_render::{
    AtomicPath, GpuContext, GpuError, GpuFrame, GpuOptions, GpuRasterizer, GpuScene, SceneOptions,
};
use std::io::Write;
use std::path::Path;
use std::time::Instant;

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
            let bounds = batch_input::file_bounds(&source.file);
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
    let points = batch_input::file_bounds(&source.file);
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

/// The raster and resolve choices of the arguments.
pub(crate) fn render_settings(a: &Args) -> RenderSettings {
    RenderSettings {
        raster: RasterOptions { precision: a.view.precision.mode(), cull: !a.no_cull },
        color: a.view.color,
        range: a.view.range,
        resolve: a.view.resolve_options(),
    }
}

/// The GPU `--backend` asks for: none for cpu, any adapter (an error if none) for gpu, a
/// hardware GPU if there is one for auto.
pub(crate) fn gpu_context(a: &Args) -> Result<Option<GpuContext>> {
    let atomics = match a.view.atomics {
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
        "precision": a.view.precision.name(),
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

/// What one GPU draw of `mortar render` leaves: the scene and rasterizer (for a GPU resolve), the
/// frame, its keys read back and its `gpu` statistics for `--json`.
struct GpuDraw {
    scene: GpuScene,
    raster: GpuRasterizer,
    frame: GpuFrame,
    keys: Vec<u64>,
    json: serde_json::Value,
}

/// Uploads `refs` (batches on `grid` holding `points` points, indexed so that the keys' indices
/// are the points'; with room for a colour per point where `colors`, zeros until the visible
/// points' colours are known), draws one frame and reads its keys back: the one upload -> draw ->
/// read-back path of [`draw_keys_gpu`] and the batch files' GPU render.
fn draw_gpu(
    ctx: &GpuContext,
    grid: Grid,
    points: u64,
    refs: &[BatchRef<'_>],
    colors: bool,
    camera: &Camera,
    options: &RasterOptions,
) -> std::result::Result<GpuDraw, GpuError> {
    let t = Instant::now();
    let mut scene =
        GpuScene::new(ctx, grid, points, SceneOptions { colors, ..Default::default() })?;
    let zeros = if colors {
        vec![0u32; refs.iter().map(BatchRef::len).max().unwrap_or(0)]
    } else {
        Vec::new()
    };
    for b in refs {
        scene.push(ctx, b, colors.then(|| &zeros[..b.len()]))?;
    }
    scene.flush(ctx)?;
    ctx.wait()?;
    let upload_seconds = t.elapsed().as_secs_f64();
    let mut raster = GpuRasterizer::new(ctx, camera.width, camera.height)?;
    let frame = raster.draw(ctx, &mut scene, camera, options, None)?;
    let keys = raster.read_keys(ctx)?;
    let json = gpu_json(ctx, &scene, upload_seconds, &frame);
    Ok(GpuDraw { scene, raster, frame, keys, json })
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
    let d = draw_gpu(ctx, grid, points, refs, false, camera, options)?;
    Ok((d.keys, d.frame, d.json))
}

/// A batch file drawn and resolved on the GPU: the batches uploaded (with room for colours),
/// one frame drawn, its keys read back to choose the colours of the visible points as the CPU
/// path does, those colours uploaded, and the framebuffer resolved on the GPU (hole filling,
/// colours, eye-dome lighting: [`GpuRasterizer::resolve`]); only the image comes back. The outer
/// error is the GPU's, the inner one the input's.
pub(crate) fn render_gpu(
    ctx: &GpuContext,
    file: &BatchFile,
    refs: &[BatchRef<'_>],
    camera: &Camera,
    settings: &RenderSettings,
) -> std::result::Result<(mortar_io::Result<Rendered>, serde_json::Value), GpuError> {
    if let Err(e) = draw::batch::check_color(file, settings.color) {
        return Ok((Err(e), serde_json::Value::Null));
    }
    let points = file.header.point_count;
    // The colours depend on the visible points: placeholders now, the real ones after the draw.
    let GpuDraw { mut scene, mut raster, frame, keys, json: mut j } =
        draw_gpu(ctx, file.grid(), points, refs, true, camera, &settings.raster)?;
    let t = Instant::now();
    let colors = match draw::batch::colors_for_keys(file, &keys, settings.color, settings.range) {
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
