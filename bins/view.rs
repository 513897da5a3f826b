//! `mortar view`: a window showing a batch file (or LAS/LAZ or an octree store, batched on the fly
//! into a temporary batch file as `mortar render` does). Each frame is drawn by the GPU rasterizer
//! (paper 003 §3.2-3.3: clear, draw, resolve in compute shaders) and put on the window's surface
//! by one render pass, without the image leaving the GPU; where no hardware GPU can present to
//! the window (or with `--backend cpu`) the CPU reference rasterizer draws and the image is
//! uploaded to the window as a plain pixel buffer (softbuffer), which needs no GPU at all.
//!
//! Frames are drawn on input only (orbit, pan, zoom, keys, resizes). `--screenshot out.png
//! --frames N` draws N frames in the real window, writes what the last one put on the surface
//! and exits (tests run it under Xvfb).

use crate::common;
use crate::render::{build_camera, encode_png, parse_color, parse_color_choice, parse_range, write_atomic, AtomicsArg, CameraArgs, PrecisionArg};
use crate::view_progressive::ProgressiveView;
use crate::view_store::{StoreGpu, StoreView};
use mortar_core::layout::RecordLayout;
use anyhow::{anyhow, bail, Context as _, Result};
use mortar_core::render::resolve::{resolve, ColorMode, ResolveOptions};
use mortar_core::render::{rasterize, Aabb, BatchRef, Camera, Framebuffer, Projection, RasterOptions};
use mortar_io::batchfile::BatchFile;
use mortar_io::render_input::{self, ColorChoice};
use mortar_render::{AtomicPath, GpuContext, GpuError, GpuOptions, GpuRasterizer, GpuScene, Overlay, Presented, SceneOptions, WindowSurface};
use std::num::NonZeroU32;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::Instant;
use mortar_io::store::{BuildProgress, BuildReport};
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, KeyEvent, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop, EventLoopProxy};
use winit::keyboard::{Key, NamedKey};
use winit::window::{Window, WindowId};

/// Seconds of uploading per frame while a batch file streams onto the GPU.
const UPLOAD_SLICE_SECONDS: f64 = 0.1;

/// Which rasterizer draws the window's frames.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ViewBackend {
    /// The GPU rasterizer on a hardware GPU that can present to the window, else the CPU one.
    Auto,
    /// The GPU rasterizer on any adapter that can present to the window, software ones included.
    Gpu,
    /// The CPU rasterizer; frames are uploaded to the window as pixels (no GPU needed).
    Cpu,
}

/// Arguments of `mortar view`.
#[derive(clap::Args)]
pub struct Args {
    /// A batch file, an octree store (every point, no LOD yet), or LAS/LAZ files, directories,
    /// glob patterns or - (batched on the fly into a temporary batch file, as `mortar batch`
    /// would).
    #[arg(required = true)]
    pub inputs: Vec<String>,
    /// Initial window width in pixels.
    #[arg(long, default_value_t = 1280)]
    pub width: u32,
    /// Initial window height in pixels.
    #[arg(long, default_value_t = 720)]
    pub height: u32,
    #[command(flatten)]
    pub camera: CameraArgs,
    /// Initial colour mode (C cycles through the modes the file has): auto, stored, rgb,
    /// intensity, classification, elevation, return-number, gps-time.
    #[arg(long, default_value = "auto", value_parser = parse_color_choice)]
    pub color: ColorChoice,
    /// Range lo,hi of intensity, elevation and gps-time colours (default: 1st to 99th percentile
    /// of all the points).
    #[arg(long, value_parser = parse_range, allow_hyphen_values = true)]
    pub range: Option<[f64; 2]>,
    /// Coordinate precision: adaptive (paper 003's 500 px rule) or 10, 20, 30 bits for every batch.
    #[arg(long, value_enum, default_value = "adaptive")]
    pub precision: PrecisionArg,
    /// Rasterizer: auto (a hardware GPU if one can present to the window, else cpu), gpu (any
    /// adapter, software included) or cpu.
    #[arg(long, value_enum, default_value = "auto")]
    pub backend: ViewBackend,
    /// Atomics of the GPU rasterizer: auto, 64 or 32 (the two-pass fallback).
    #[arg(long, value_enum, default_value = "auto")]
    pub atomics: AtomicsArg,
    /// Background colour: black, white, grey, #rrggbb.
    #[arg(long, default_value = "black", value_parser = parse_color)]
    pub background: u32,
    /// Write what the window shows after --frames frames to this PNG and exit.
    #[arg(long, value_name = "PNG")]
    pub screenshot: Option<PathBuf>,
    /// Frames to draw before the screenshot (each a full draw, resolve and present).
    #[arg(long, value_name = "N", requires = "screenshot", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    pub frames: u32,
    /// With --screenshot: print statistics (backend, adapter, frame times) as JSON on stdout.
    #[arg(long, requires = "screenshot")]
    pub json: bool,
    /// No status line in the window (the title still shows it).
    #[arg(long)]
    pub no_status: bool,
    #[command(flatten)]
    pub sort: common::SortArgs,
    #[command(flatten)]
    pub lod: crate::render_lod::LodArgs,
    /// Raw LAS/LAZ: batch the points into a temporary batch file first and draw every point each
    /// frame, instead of the progressive renderer (paper 000) that shows them as they load.
    #[arg(long)]
    pub no_progressive: bool,
}

/// The preview options of `mortar build`.
#[derive(clap::Args, Clone, Debug)]
pub struct PreviewArgs {
    /// Show the store in a window while it is built (orbit/pan/zoom with the mouse, F fits, C
    /// cycles colours; the status line shows the build's progress). The store is committed at
    /// least every second for it; the build never waits for the window.
    #[arg(long)]
    pub preview: bool,
    /// The preview's rasterizer: auto, gpu or cpu (as `mortar view --backend`).
    #[arg(long, value_enum, default_value = "auto", requires = "preview")]
    pub preview_backend: ViewBackend,
    /// Preview window width and height in pixels.
    #[arg(long, value_name = "WxH", default_value = "1280x720", value_parser = parse_size_wxh, requires = "preview")]
    pub preview_size: (u32, u32),
    /// With --preview: once the build is done and its last commit shown, write what the window
    /// shows to this PNG and close the window (for tests and scripted runs).
    #[arg(long, value_name = "PNG", requires = "preview")]
    pub preview_screenshot: Option<PathBuf>,
    /// With --preview: draw the preview off screen, without a window, at most 60 frames per
    /// second from the fixed camera, and report the frames in --json (for benchmarks, and for
    /// servers with a GPU but no display).
    #[arg(long, requires = "preview", conflicts_with = "preview_screenshot")]
    pub preview_offscreen: bool,
}

fn parse_size_wxh(s: &str) -> std::result::Result<(u32, u32), String> {
    let bad = || format!("'{s}' is not WIDTHxHEIGHT");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    Ok((w.trim().parse().map_err(|_| bad())?, h.trim().parse().map_err(|_| bad())?))
}

impl PreviewArgs {
    /// The window's options for a preview of `store` seen from `camera`.
    pub fn view_args(&self, store: &std::path::Path, camera: &CameraArgs) -> Args {
        Args {
            inputs: vec![store.display().to_string()],
            width: self.preview_size.0,
            height: self.preview_size.1,
            camera: camera.clone(),
            color: ColorChoice::Auto,
            range: None,
            precision: PrecisionArg::Adaptive,
            backend: self.preview_backend,
            atomics: AtomicsArg::Auto,
            background: 0xff00_0000,
            screenshot: self.preview_screenshot.clone(),
            frames: 1,
            json: false,
            no_status: false,
            sort: common::SortArgs::default(),
            lod: crate::render_lod::LodArgs::default(),
            no_progressive: false,
        }
    }
}

/// Checks the window options shared by `mortar view` and `mortar build --preview`.
fn check_window(a: &Args) -> Result<()> {
    if a.width == 0 || a.height == 0 || a.width > 16384 || a.height > 16384 {
        bail!("--width {} --height {}: each side must be 1 to 16384 pixels", a.width, a.height);
    }
    if !(a.camera.fov > 0.0 && a.camera.fov < 180.0) {
        bail!("--fov {}: must be between 0 and 180 degrees", a.camera.fov);
    }
    Ok(())
}

/// What wakes the event loop from another thread (the preview's build).
#[derive(Clone, Copy, Debug)]
pub enum Wake {
    /// The build reported progress (maybe a commit).
    Progress,
    /// The build ended: whether it succeeded.
    Done(bool),
}

/// The event loop, or an error that says there is no display.
fn event_loop() -> Result<EventLoop<Wake>> {
    let event_loop = EventLoop::<Wake>::with_user_event().build().map_err(|e| anyhow!("cannot open a window: {e} (no display? set DISPLAY or WAYLAND_DISPLAY, or use `mortar render`)"))?;
    event_loop.set_control_flow(ControlFlow::Wait);
    Ok(event_loop)
}

/// Opens the input and the window, then runs the event loop until the window is closed (or the
/// screenshot is written).
pub fn run(a: Args) -> Result<()> {
    check_window(&a)?;
    // The display first: no point in batching a large LAZ file for a window that cannot open.
    let event_loop = event_loop()?;
    let store = match &a.inputs[..] {
        [one] if one != "-" && !a.lod.no_lod && mortar_io::store::is_store(std::path::Path::new(one)) => Some(PathBuf::from(one)),
        _ => None,
    };
    if store.is_none() && (a.lod.lod_threshold.is_some() || a.lod.point_budget.is_some()) {
        bail!("--lod-threshold and --point-budget apply to a single octree store (made by mortar build), not to {}", a.inputs.join(" "));
    }
    if let Some(dir) = store {
        let view = StoreView::open(&dir, a.lod.options(true)?, a.range)?;
        let mode = view.mode_of(a.color)?;
        let label = dir.display().to_string();
        let modes = view.modes().to_vec();
        return show(&a, event_loop, Content::Store(Box::new(view)), modes, mode, label, None).map(drop);
    }
    if !a.no_progressive {
        let paths = mortar_io::source::expand_inputs(&a.inputs)?;
        let raw = !paths.is_empty()
            && paths.iter().all(|p| p.as_os_str() != "-" && !mortar_io::store::is_store(p) && !(p.is_file() && mortar_io::batchfile::is_batch_file(p)));
        if raw {
            let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
            let view = ProgressiveView::open(&paths, a.color, a.range, threads)?;
            let label = paths.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" ");
            let modes = view.modes.clone();
            return show(&a, event_loop, Content::Progressive(Box::new(view)), modes, 0, label, None).map(drop);
        }
    }
    let source = crate::render::open_source(&a.inputs, &a.sort, None)?;
    let file = &source.file;
    let own = |e| source.own_error(e);
    let label = source.name.display().to_string();
    if file.header.point_count == 0 {
        bail!("{label}: no points to draw");
    }
    let initial = a.color.resolved(file);
    render_input::check_color(file, initial).map_err(own)?;
    let mut modes: Vec<ColorChoice> = ColorMode::ALL.iter().map(|&m| ColorChoice::Mode(m)).filter(|&c| render_input::check_color(file, c).is_ok()).collect();
    if !modes.contains(&initial) {
        modes.insert(0, initial);
    }
    let mode = modes.iter().position(|&m| m == initial).unwrap_or(0);
    let views = render_input::load_words(file).map_err(own)?;
    let refs = render_input::batch_refs(file, &views).map_err(own)?;
    let colors = vec![None; modes.len()];
    show(&a, event_loop, Content::Batches { file, refs: &refs, colors }, modes, mode, label, None).map(drop)
}


/// `mortar build --preview`: shows the store `dir` as `build` grows it. `build` runs on its own
/// thread and reports progress through the callback it is given, which never blocks (an
/// unbounded channel and a wake-up event): the builder never waits for the window. The window
/// reloads the store at each new commit and draws it with LOD, uploading only new nodes. If the
/// window is closed first, the build goes on without it and this waits for it; with
/// `--screenshot` the window closes itself once the last commit was shown. Returns the build's
/// report and the frames' statistics.
pub fn run_preview<F>(a: &Args, dir: &std::path::Path, bounds: Aabb, layout: &RecordLayout, build: F) -> Result<(BuildReport, serde_json::Value)>
where
    F: FnOnce(&mut dyn FnMut(&BuildProgress)) -> Result<BuildReport> + Send,
{
    check_window(a)?;
    let event_loop = event_loop()?;
    let proxy: EventLoopProxy<Wake> = event_loop.create_proxy();
    let view = StoreView::waiting(dir, bounds, layout, a.lod.options(true)?, a.range);
    let mode = view.mode_of(a.color)?;
    let modes = view.modes().to_vec();
    let label = dir.display().to_string();
    let (ptx, prx) = std::sync::mpsc::channel();
    let (rtx, rrx) = std::sync::mpsc::channel();
    std::thread::scope(|scope| {
        let wake = proxy.clone();
        scope.spawn(move || {
            let mut report = |p: &BuildProgress| {
                let _ = ptx.send(*p);
                let _ = wake.send_event(Wake::Progress);
            };
            let r = build(&mut report);
            drop(ptx);
            let ok = r.is_ok();
            let _ = rtx.send(r);
            let _ = proxy.send_event(Wake::Done(ok));
        });
        let frames = match show(a, event_loop, Content::Store(Box::new(view)), modes, mode, label, Some(BuildState::new(prx))) {
            Ok(Shown { frames, build_done }) => {
                if !build_done {
                    eprintln!("mortar build: the preview was closed; the build goes on");
                }
                frames
            }
            Err(e) => {
                // The builder never waits for the window, so a failed window does not stop it.
                eprintln!("mortar build: preview: {e:#}; the build goes on without it");
                serde_json::Value::Null
            }
        };
        let result = rrx.recv().map_err(|_| anyhow!("the build's thread ended without a result"))?;
        result.map(|r| (r, frames))
    })
}

/// The frame period of the off-screen preview (60 frames per second).
const OFFSCREEN_PERIOD_MS: f64 = 1000.0 / 60.0;

/// `mortar build --preview --preview-offscreen`: the preview's frames drawn without a window,
/// paced to 60 per second, by the same store view as the window (GPU or CPU), from the fixed
/// camera of the options. Returns the build's report and the frames' statistics.
pub fn run_preview_offscreen<F>(a: &Args, dir: &std::path::Path, bounds: Aabb, layout: &RecordLayout, build: F) -> Result<(BuildReport, serde_json::Value)>
where
    F: FnOnce(&mut dyn FnMut(&BuildProgress)) -> Result<BuildReport> + Send,
{
    check_window(a)?;
    let mut view = StoreView::waiting(dir, bounds, layout, a.lod.options(true)?, a.range);
    let mode = view.mode_of(a.color)?;
    let camera = build_camera(&a.camera, &bounds, a.width, a.height)?;
    let options = RasterOptions { precision: a.precision.mode(), cull: true };
    let atomics = match a.atomics {
        AtomicsArg::Auto => None,
        AtomicsArg::U64 => Some(AtomicPath::U64),
        AtomicsArg::U32 => Some(AtomicPath::TwoPass32),
    };
    let ctx = match a.backend {
        ViewBackend::Cpu => None,
        ViewBackend::Gpu => Some(GpuContext::new(&GpuOptions { atomics, allow_software: true, ..Default::default() }).map_err(|e| anyhow!("--preview-backend gpu: {e}"))?),
        ViewBackend::Auto => GpuContext::new(&GpuOptions { atomics, allow_software: false, ..Default::default() }).ok(),
    };
    let mut gpu = match &ctx {
        Some(ctx) => Some((view.gpu(ctx, mode)?, GpuRasterizer::new(ctx, a.width, a.height)?)),
        None => None,
    };
    let (ptx, prx) = std::sync::mpsc::channel();
    let (rtx, rrx) = std::sync::mpsc::channel();
    let start = Instant::now();
    let (frames, result) = std::thread::scope(|scope| -> Result<_> {
        scope.spawn(move || {
            let r = build(&mut |p: &BuildProgress| {
                let _ = ptx.send(*p);
            });
            drop(ptx);
            let _ = rtx.send(r);
        });
        let mut state = BuildState::new(prx);
        let mut frames = Vec::new();
        let mut result = None;
        loop {
            let t = Instant::now();
            match rrx.try_recv() {
                // A failed build leaves no store to draw: its error is the command's.
                Ok(r) if r.is_err() => return Ok((frames, r)),
                Ok(r) => result = Some(r),
                Err(TryRecvError::Empty) => {}
                Err(TryRecvError::Disconnected) => return Err(anyhow!("the build's thread ended without a result")),
            }
            let committed = state.poll();
            let last = result.is_some();
            if committed || last {
                view.reload(gpu.as_mut().map(|g| &mut g.0))?;
            }
            let (drawn, gpu_ms) = match (&ctx, &mut gpu) {
                (Some(ctx), Some((sg, raster))) => {
                    let f = view.draw_gpu(ctx, sg, raster, &camera, &options, a.background, mode)?;
                    (f.stats.points_drawn, f.timings.map(|t| t.draw_ms + t.resolve_ms.unwrap_or(0.0)))
                }
                _ => {
                    view.draw_cpu(&camera, &options, a.background, mode)?;
                    (view.selected.samples, None)
                }
            };
            let frame_ms = t.elapsed().as_secs_f64() * 1e3;
            frames.push(serde_json::json!({
                "at_seconds": start.elapsed().as_secs_f64(),
                "frame_ms": frame_ms,
                "gpu_ms": gpu_ms,
                "points_drawn": drawn,
                "nodes_drawn": view.selected.nodes,
                "nodes_uploaded": view.selected.uploaded_nodes,
                "commit": view.commit(),
            }));
            if last {
                break;
            }
            let left = OFFSCREEN_PERIOD_MS - t.elapsed().as_secs_f64() * 1e3;
            if left > 0.0 {
                std::thread::sleep(std::time::Duration::from_secs_f64(left * 1e-3));
            }
        }
        Ok((frames, result.expect("the loop ends once the build's result arrived")))
    })?;
    let report = result?;
    let mut ms: Vec<f64> = frames.iter().filter_map(|f| f["frame_ms"].as_f64()).collect();
    ms.sort_by(f64::total_cmp);
    let pick = |q: f64| ms.get(((ms.len() - 1) as f64 * q).round() as usize).copied();
    let seconds = report.seconds.max(1e-9);
    let during = frames.iter().filter(|f| f["at_seconds"].as_f64().is_some_and(|t| t <= seconds)).count();
    let j = serde_json::json!({
        "offscreen": true,
        "renderer": match &ctx { Some(c) => serde_json::json!({ "backend": "gpu", "adapter": c.adapter().name }), None => serde_json::json!({ "backend": "cpu" }) },
        "width": a.width,
        "height": a.height,
        "frame_count": frames.len(),
        "frames_per_second_during_build": during as f64 / seconds,
        "frame_ms_median": pick(0.5),
        "frame_ms_p95": pick(0.95),
        "frame_ms_max": pick(1.0),
        "frames": frames,
    });
    Ok((report, j))
}

/// What a window saw.
struct Shown {
    /// Statistics of the frames drawn.
    frames: serde_json::Value,
    /// For a preview: whether the build ended while the window was open.
    build_done: bool,
}

/// Runs the window on `content` until it closes.
#[allow(clippy::too_many_arguments)]
fn show(a: &Args, event_loop: EventLoop<Wake>, content: Content<'_>, modes: Vec<ColorChoice>, mode: usize, label: String, build: Option<BuildState>) -> Result<Shown> {
    let bounds = content.bounds();
    let camera = build_camera(&a.camera, &bounds, a.width, a.height).map_err(|e| anyhow!("{label}: {e:#}"))?;
    let mut app = App {
        args: a,
        content,
        label: label.clone(),
        bounds,
        orbit: Orbit::from_camera(&camera),
        modes,
        mode,
        window: None,
        renderer: None,
        drag: Drag::default(),
        frames: Vec::new(),
        error: None,
        done: false,
        last_frame: None,
        uploading: false,
        build,
    };
    event_loop.run_app(&mut app).map_err(|e| anyhow!("{label}: window: {e}"))?;
    if let Some(e) = app.error.take() {
        return Err(e);
    }
    if a.screenshot.is_some() && !app.done {
        bail!("{label}: the window closed before {} frames were drawn", a.frames);
    }
    let backend = app.renderer.as_ref().map(Renderer::describe).unwrap_or(serde_json::Value::Null);
    let j = serde_json::json!({
        "input": label,
        "screenshot": a.screenshot,
        "points": app.content.points(),
        "color": app.modes[app.mode].name(),
        "width": app.frames.last().map(|f| f.width),
        "height": app.frames.last().map(|f| f.height),
        "renderer": backend,
        "frames": app.frames.iter().map(FrameStats::json).collect::<Vec<_>>(),
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&j)?);
    }
    Ok(Shown { frames: j, build_done: app.build.is_none_or(|b| b.done || b.failed) })
}

/// The camera as the mouse moves it: a target, a distance, and the direction from the target to
/// the eye as azimuth (`yaw`, from +x towards +y) and elevation (`pitch`), with z up.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Orbit {
    target: [f64; 3],
    distance: f64,
    yaw: f64,
    pitch: f64,
}

/// The elevation stops short of the poles, where the view direction would be parallel to up.
const MAX_PITCH: f64 = 89.5 * std::f64::consts::PI / 180.0;

impl Orbit {
    fn from_camera(c: &Camera) -> Orbit {
        let d = [0, 1, 2].map(|i| c.eye[i] - c.target[i]);
        let distance = d.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-12);
        let dir = d.map(|v| v / distance);
        // Straight down (or up): the azimuth from the camera's up vector, so a top view keeps north
        // up.
        let yaw = if dir[2].abs() > 0.9999 { (-c.up[1]).atan2(-c.up[0]) } else { dir[1].atan2(dir[0]) };
        Orbit { target: c.target, distance, yaw, pitch: dir[2].clamp(-1.0, 1.0).asin().clamp(-MAX_PITCH, MAX_PITCH) }
    }

    fn eye(&self) -> [f64; 3] {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        let d = [cp * cy, cp * sy, sp];
        [0, 1, 2].map(|i| self.target[i] + self.distance * d[i])
    }

    fn camera(&self, fov_y: f64, ortho: bool, bounds: &Aabb, width: u32, height: u32) -> Result<Camera> {
        let projection = if ortho {
            Projection::Orthographic { height: 2.0 * self.distance * (0.5 * fov_y).tan() }
        } else {
            Projection::Perspective { fov_y }
        };
        Ok(Camera::look_at(self.eye(), self.target, [0.0, 0.0, 1.0], projection, bounds, width, height)?)
    }

    /// Looks at the centre of `bounds` from the current direction, from the distance at which every
    /// corner of the bounds is in view with a small margin (as `Camera::frame_perspective` does
    /// for its preset directions).
    fn fit(&mut self, bounds: &Aabb, fov_y: f64, width: u32, height: u32) {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        let forward = [-cp * cy, -cp * sy, -sp];
        // right = forward x z (the pitch stops short of the poles, so it is not zero), up = right x forward.
        let n = (forward[0] * forward[0] + forward[1] * forward[1]).sqrt().max(1e-12);
        let right = [forward[1] / n, -forward[0] / n, 0.0];
        let up = [right[1] * forward[2], -right[0] * forward[2], right[0] * forward[1] - right[1] * forward[0]];
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let ty = (0.5 * fov_y).tan() / 1.05;
        let tx = ty * width.max(1) as f64 / height.max(1) as f64;
        let c = bounds.center();
        let extent = bounds.diagonal().max(1e-9);
        let (mut dist, mut min_f) = (0.0f64, f64::INFINITY);
        for k in bounds.corners() {
            let d = [k[0] - c[0], k[1] - c[1], k[2] - c[2]];
            let (x, y, f) = (dot(right, d), dot(up, d), dot(forward, d));
            dist = dist.max(x.abs() / tx - f).max(y.abs() / ty - f);
            min_f = min_f.min(f);
        }
        self.target = c;
        self.distance = dist.max(-min_f + 0.05 * extent).max(0.5 * extent);
    }
}

/// Mouse state.
#[derive(Clone, Copy, Debug, Default)]
struct Drag {
    left: bool,
    right: bool,
    shift: bool,
    cursor: Option<(f64, f64)>,
}

/// Times and counts of one frame.
#[derive(Clone, Copy, Debug, Default)]
struct FrameStats {
    width: u32,
    height: u32,
    /// Draw, resolve and present, in milliseconds (host clock).
    frame_ms: f64,
    /// Drawing and resolving: for the GPU until it finished (host clock).
    raster_ms: f64,
    /// Putting the image on the window (for the GPU the present pass, submitted, not awaited).
    present_ms: f64,
    /// The GPU's draw pass (timestamp queries), where available.
    gpu_draw_ms: Option<f64>,
    /// The GPU's resolve pass.
    gpu_resolve_ms: Option<f64>,
    points_drawn: u64,
    /// End of the frame, ms since the command started.
    at_ms: f64,
}

impl FrameStats {
    fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "at_ms": self.at_ms,
            "frame_ms": self.frame_ms,
            "raster_ms": self.raster_ms,
            "present_ms": self.present_ms,
            "gpu_draw_ms": self.gpu_draw_ms,
            "gpu_resolve_ms": self.gpu_resolve_ms,
            "points_drawn": self.points_drawn,
        })
    }
}

/// What the window shows.
enum Content<'a> {
    /// A batch file (or LAS/LAZ batched into one): every point, by the batch rasterizer.
    Batches {
        file: &'a BatchFile,
        refs: &'a [BatchRef<'a>],
        /// Per mode, every point's colour once computed.
        colors: Vec<Option<Vec<u32>>>,
    },
    /// An octree store (maybe growing): the LOD selection of each frame.
    Store(Box<StoreView>),
    /// Raw LAS/LAZ: the progressive renderer, loading while it draws.
    Progressive(Box<ProgressiveView>),
}

impl Content<'_> {
    fn bounds(&self) -> Aabb {
        match self {
            Content::Batches { file, .. } => render_input::file_bounds(file),
            Content::Store(v) => v.bounds(),
            Content::Progressive(v) => v.bounds(),
        }
    }

    fn points(&self) -> u64 {
        match self {
            Content::Batches { file, .. } => file.header.point_count,
            Content::Store(v) => v.points(),
            Content::Progressive(v) => v.capacity(),
        }
    }
}

/// The GPU data of the content.
enum GpuData {
    Batches {
        scene: GpuScene,
        /// The colour mode whose colours the scene holds.
        uploaded: usize,
        /// Batches uploaded so far (frames draw those while the rest streams in).
        next: usize,
    },
    Store(StoreGpu),
    /// The progressive renderer's GPU buffers live in the view.
    Progressive,
}

/// The GPU renderer's parts.
struct Gpu {
    ctx: GpuContext,
    surface: WindowSurface,
    raster: GpuRasterizer,
    data: GpuData,
}

/// The preview's build, as the window sees it.
struct BuildState {
    progress: Receiver<BuildProgress>,
    latest: BuildProgress,
    start: Instant,
    /// Points and time of an earlier report, for the rate.
    rate_from: (u64, Instant),
    rate: f64,
    done: bool,
    /// Seconds the build took, once done.
    seconds: Option<f64>,
    /// The store's last commit was loaded after the build ended.
    final_loaded: bool,
    /// The build failed.
    failed: bool,
}

impl BuildState {
    fn new(progress: Receiver<BuildProgress>) -> BuildState {
        let now = Instant::now();
        BuildState { progress, latest: BuildProgress::default(), start: now, rate_from: (0, now), rate: 0.0, done: false, seconds: None, final_loaded: false, failed: false }
    }

    /// Takes every report that arrived (keeping the newest); whether the commit count changed.
    fn poll(&mut self) -> bool {
        let commits = self.latest.commits;
        loop {
            match self.progress.try_recv() {
                Ok(p) => self.latest = p,
                Err(TryRecvError::Empty) => break,
                // The build's end (and whether it succeeded) comes as `Wake::Done`.
                Err(TryRecvError::Disconnected) => break,
            }
        }
        let dt = self.rate_from.1.elapsed().as_secs_f64();
        if dt >= 1.0 {
            self.rate = (self.latest.points - self.rate_from.0) as f64 / dt;
            self.rate_from = (self.latest.points, Instant::now());
        }
        self.latest.commits != commits
    }

    fn status(&self) -> String {
        let p = &self.latest;
        match self.seconds {
            Some(s) => format!("built {} points in {s:.1} s", group_digits(p.points)),
            None => format!(
                "building {} of {} ({:.0}%) {:.1} M pts/s",
                group_digits(p.points),
                group_digits(p.total),
                100.0 * p.points as f64 / p.total.max(1) as f64,
                self.rate / 1e6
            ),
        }
    }
}

/// What draws the frames.
enum Renderer {
    Gpu(Box<Gpu>),
    Cpu {
        // Dropped after `surface` (declaration order).
        surface: softbuffer::Surface<Arc<Window>, Arc<Window>>,
        _context: softbuffer::Context<Arc<Window>>,
        fb: Framebuffer,
        /// Why the CPU draws (for the status line and --json).
        why: &'static str,
    },
}

impl Renderer {
    fn short(&self) -> String {
        match self {
            Renderer::Gpu(g) => format!("gpu: {}", g.ctx.adapter().name),
            Renderer::Cpu { .. } => "cpu".to_string(),
        }
    }

    fn describe(&self) -> serde_json::Value {
        match self {
            Renderer::Gpu(g) => {
                let (ctx, surface) = (&g.ctx, &g.surface);
                let a = ctx.adapter();
                serde_json::json!({
                    "backend": "gpu",
                    "adapter": a.name,
                    "api": a.backend,
                    "device_type": a.device_type,
                    "atomics": ctx.atomic_path().name(),
                    "surface_format": format!("{:?}", surface.format()),
                    "read_back": match surface.read_back() {
                        mortar_render::ReadBack::SurfaceTexture => "surface texture",
                        mortar_render::ReadBack::ResolvedImage => "resolved image",
                    },
                })
            }
            Renderer::Cpu { why, .. } => serde_json::json!({ "backend": "cpu", "why": why, "read_back": "window pixel buffer" }),
        }
    }
}

struct App<'a> {
    args: &'a Args,
    content: Content<'a>,
    label: String,
    bounds: Aabb,
    orbit: Orbit,
    modes: Vec<ColorChoice>,
    mode: usize,
    /// The build of `mortar build --preview`.
    build: Option<BuildState>,
    window: Option<Arc<Window>>,
    renderer: Option<Renderer>,
    drag: Drag,
    frames: Vec<FrameStats>,
    error: Option<anyhow::Error>,
    /// The screenshot was written.
    done: bool,
    /// When the last frame was drawn.
    last_frame: Option<Instant>,
    /// A batch file is still being uploaded to the GPU.
    uploading: bool,
}

impl App<'_> {
    fn fov(&self) -> f64 {
        self.args.camera.fov.to_radians()
    }

    /// A batch file's every point's colour in the current mode (computed once per mode).
    fn batch_colors(&mut self) -> Result<()> {
        if let Content::Batches { file, colors, .. } = &mut self.content {
            if colors[self.mode].is_none() {
                let (c, _range) = render_input::point_colors(file, self.modes[self.mode], self.args.range).map_err(|e| anyhow!("{}: {e}", self.label))?;
                colors[self.mode] = Some(c);
            }
        }
        Ok(())
    }

    /// Opens the window and what draws into it.
    fn open(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let attrs = Window::default_attributes().with_title(format!("mortar view: {}", self.label)).with_inner_size(PhysicalSize::new(self.args.width, self.args.height));
        let window = Arc::new(event_loop.create_window(attrs).context("cannot open a window")?);
        self.window = Some(window.clone());
        let size = window.inner_size();
        let (w, h) = (size.width.max(1), size.height.max(1));
        let atomics = match self.args.atomics {
            AtomicsArg::Auto => None,
            AtomicsArg::U64 => Some(AtomicPath::U64),
            AtomicsArg::U32 => Some(AtomicPath::TwoPass32),
        };
        let progressive = matches!(self.content, Content::Progressive(_));
        let gpu = match self.args.backend {
            ViewBackend::Cpu => Err("--backend cpu"),
            ViewBackend::Gpu => Ok(GpuContext::for_window(&GpuOptions { atomics, allow_software: true, ..Default::default() }, window.clone()).map_err(|e| anyhow!("--backend gpu: {e}"))?),
            ViewBackend::Auto => GpuContext::for_window(&GpuOptions { atomics, allow_software: false, ..Default::default() }, window.clone()).map_err(|_| "no hardware GPU can present to the window"),
        };
        // The GPU progressive renderer needs 64-bit atomics; the CPU one draws otherwise.
        let gpu = match gpu {
            Ok((ctx, _)) if progressive && ctx.atomic_path() != AtomicPath::U64 => Err("the GPU progressive renderer needs 64-bit atomics"),
            g => g,
        };
        let renderer = match gpu {
            Ok((ctx, surface)) => self.open_gpu(ctx, surface, w, h).map_err(|e| anyhow!("{}: GPU: {e}", self.label))?,
            Err(why) => {
                let context = softbuffer::Context::new(window.clone()).map_err(|e| anyhow!("cannot draw into the window: {e}"))?;
                let surface = softbuffer::Surface::new(&context, window.clone()).map_err(|e| anyhow!("cannot draw into the window: {e}"))?;
                Renderer::Cpu { surface, _context: context, fb: Framebuffer::new(w, h), why }
            }
        };
        self.renderer = Some(renderer);
        window.request_redraw();
        Ok(())
    }

    fn open_gpu(&mut self, ctx: GpuContext, surface: mortar_render::wgpu::Surface<'static>, w: u32, h: u32) -> std::result::Result<Renderer, GpuError> {
        let surface = WindowSurface::new(&ctx, surface, w, h)?;
        let raster = GpuRasterizer::new(&ctx, w, h)?;
        if let Err(e) = self.batch_colors() {
            return Err(GpuError::Colors(format!("{e:#}")));
        }
        let data = match &mut self.content {
            // Batches are uploaded by the frames, a time slice each, so that the first frame
            // comes at once whatever the file's size.
            Content::Batches { file, .. } => {
                let scene = GpuScene::new(&ctx, file.grid(), file.header.point_count, SceneOptions { colors: true, ..Default::default() })?;
                GpuData::Batches { scene, uploaded: self.mode, next: 0 }
            }
            // Nodes are uploaded as frames select them.
            Content::Store(v) => GpuData::Store(v.gpu(&ctx, self.mode)?),
            Content::Progressive(v) => {
                v.use_gpu(&ctx).map_err(|e| GpuError::Device(format!("{e:#}")))?;
                GpuData::Progressive
            }
        };
        Ok(Renderer::Gpu(Box::new(Gpu { ctx, surface, raster, data })))
    }

    /// The status line: points, the last frame's time and rate, colour mode, renderer.
    fn status(&self) -> String {
        let mut parts = Vec::new();
        if let Some(b) = &self.build {
            parts.push(b.status());
        }
        match &self.content {
            Content::Batches { file, .. } => parts.push(format!("{} points", group_digits(file.header.point_count))),
            Content::Store(v) => {
                parts.push(format!("{} points, {} nodes, commit {}", group_digits(v.points()), group_digits(v.nodes()), v.commit()));
                parts.push(format!("drawn {} nodes, {} samples", group_digits(v.selected.nodes), group_digits(v.selected.samples)));
            }
            Content::Progressive(v) => {
                parts.push(format!("{} of {} points", group_digits(v.loaded()), group_digits(v.capacity())));
                parts.push(v.status());
            }
        }
        if let Some(f) = self.frames.last() {
            parts.push(format!("{:.1} ms ({:.0} fps)", f.frame_ms, 1000.0 / f.frame_ms.max(1e-3)));
        }
        parts.push(self.modes[self.mode].name().to_string());
        parts.push(self.renderer.as_ref().map(Renderer::short).unwrap_or_default());
        parts.join(" | ")
    }

    /// Draws one frame into the window; with `read_back`, returns the pixels put on it.
    fn draw(&mut self, read_back: bool) -> Result<Option<(u32, u32, Vec<u32>)>> {
        let Some(window) = self.window.clone() else { return Ok(None) };
        let size = window.inner_size();
        let (w, h) = (size.width, size.height);
        if w == 0 || h == 0 {
            return Ok(None);
        }
        let camera = self.orbit.camera(self.fov(), self.args.camera.ortho, &self.bounds, w, h).map_err(|e| anyhow!("{}: {e:#}", self.label))?;
        let options = RasterOptions { precision: self.args.precision.mode(), cull: true };
        let status = self.status();
        let overlay = (!self.args.no_status).then(|| status_overlay(&status, w));
        let background = self.args.background;
        let mode = self.mode;
        // Colours of the current mode (computed once per mode).
        self.batch_colors()?;
        let label = self.label.clone();
        let start = Instant::now();
        let renderer = self.renderer.as_mut().ok_or_else(|| anyhow!("no renderer"))?;
        let mut stats = FrameStats { width: w, height: h, ..Default::default() };
        let pixels = match renderer {
            Renderer::Gpu(g) => {
                let Gpu { ctx, surface, raster, data } = &mut **g;
                let gpu = |e: GpuError| anyhow!("{label}: GPU: {e}");
                surface.resize(ctx, w, h).map_err(gpu)?;
                raster.resize(ctx, w, h).map_err(gpu)?;
                let frame = match (&mut self.content, data) {
                    (Content::Batches { colors, refs, .. }, GpuData::Batches { scene, uploaded, next }) => {
                        let colors = colors[mode].as_deref().expect("computed above");
                        if *uploaded != mode {
                            scene.set_colors(ctx, &colors[..scene.points() as usize]).map_err(gpu)?;
                            *uploaded = mode;
                        }
                        let t = Instant::now();
                        while *next < refs.len() && t.elapsed().as_secs_f64() < UPLOAD_SLICE_SECONDS {
                            let b = &refs[*next];
                            let first = b.first_index as usize;
                            scene.push(ctx, b, Some(&colors[first..first + b.len()])).map_err(gpu)?;
                            *next += 1;
                        }
                        self.uploading = *next < refs.len();
                        Some(if self.uploading {
                            let ids: Vec<u32> = (0..*next as u32).collect();
                            raster.draw_selected(ctx, scene, Some(&ids), &camera, &options, Some(background)).map_err(gpu)?
                        } else {
                            raster.draw(ctx, scene, &camera, &options, Some(background)).map_err(gpu)?
                        })
                    }
                    (Content::Store(v), GpuData::Store(sg)) => Some(v.draw_gpu(ctx, sg, raster, &camera, &options, background, mode)?),
                    (Content::Progressive(v), GpuData::Progressive) => {
                        // The progressive renderer resolves into its own image buffer.
                        let f = v.draw_gpu(ctx, &camera, &options, background)?;
                        stats.points_drawn = f.stats.raster.points_drawn;
                        stats.gpu_draw_ms = f.gpu.map(|t| t.reproject_ms + t.probe_ms + t.extra_fill_ms + t.prepare_ms);
                        stats.gpu_resolve_ms = f.gpu.and_then(|t| t.resolve_ms);
                        None
                    }
                    _ => bail!("{label}: the GPU holds data of another kind"),
                };
                stats.raster_ms = start.elapsed().as_secs_f64() * 1e3;
                let o = overlay.as_ref().map(|(ow, oh, px)| Overlay { width: *ow, height: *oh, rgba: px });
                let shown = match (&frame, &self.content) {
                    (None, Content::Progressive(v)) => {
                        let image = v.image_buffer().ok_or_else(|| anyhow!("{label}: GPU: no image resolved"))?;
                        surface.present_image(ctx, image, (w, h), o, read_back).map_err(gpu)?
                    }
                    _ => surface.present(ctx, raster, o, read_back).map_err(gpu)?,
                };
                if let Some(frame) = &frame {
                    stats.points_drawn = frame.stats.points_drawn;
                    stats.gpu_draw_ms = frame.timings.map(|t| t.draw_ms);
                    stats.gpu_resolve_ms = frame.timings.and_then(|t| t.resolve_ms);
                }
                match shown {
                    Presented::Shown(p) => p,
                    Presented::Skipped(_) => {
                        window.request_redraw();
                        return Ok(None);
                    }
                }
            }
            Renderer::Cpu { surface, fb, .. } => {
                let bg = background;
                let mut rgba = match &mut self.content {
                    Content::Batches { file, refs, colors } => {
                        if (fb.width(), fb.height()) != (w, h) {
                            *fb = Framebuffer::new(w, h);
                        } else {
                            fb.clear();
                        }
                        let s = rasterize(fb, refs, &file.grid(), &camera, &options).map_err(|e| anyhow!("{label}: {e}"))?;
                        stats.points_drawn = s.points_drawn;
                        let colors = colors[mode].as_deref().expect("computed above");
                        resolve(fb.keys_slice(), w, h, |i| colors.get(i as usize).copied().unwrap_or(bg), &ResolveOptions { background: bg, ..Default::default() })
                    }
                    Content::Store(v) => {
                        let rgba = v.draw_cpu(&camera, &options, bg, mode)?;
                        stats.points_drawn = v.selected.samples;
                        rgba
                    }
                    Content::Progressive(v) => {
                        let rgba = v.draw_cpu(&camera, &options, bg)?;
                        stats.points_drawn = v.last.raster.points_drawn;
                        rgba
                    }
                };
                stats.raster_ms = start.elapsed().as_secs_f64() * 1e3;
                if let Some((ow, oh, px)) = &overlay {
                    mortar_render::present::blend_overlay(&mut rgba, w, &Overlay { width: *ow, height: *oh, rgba: px });
                }
                let (nw, nh) = (NonZeroU32::new(w).expect("w > 0"), NonZeroU32::new(h).expect("h > 0"));
                surface.resize(nw, nh).map_err(|e| anyhow!("window: {e}"))?;
                let mut buf = surface.buffer_mut().map_err(|e| anyhow!("window: {e}"))?;
                for (d, c) in buf.iter_mut().zip(&rgba) {
                    let [r, g, b, _] = c.to_le_bytes();
                    *d = (r as u32) << 16 | (g as u32) << 8 | b as u32;
                }
                buf.present().map_err(|e| anyhow!("window: {e}"))?;
                read_back.then(|| rgba.iter().map(|c| c | 0xff00_0000).collect())
            }
        };
        stats.frame_ms = start.elapsed().as_secs_f64() * 1e3;
        stats.present_ms = stats.frame_ms - stats.raster_ms;
        stats.at_ms = crate::common::since_start_ms();
        self.frames.push(stats);
        self.last_frame = Some(Instant::now());
        window.set_title(&format!("mortar view: {} | {}", self.label, self.status()));
        Ok(pixels.map(|p| (w, h, p)))
    }

    fn redraw(&self) {
        if let Some(w) = &self.window {
            w.request_redraw();
        }
    }

    fn fail(&mut self, event_loop: &ActiveEventLoop, e: anyhow::Error) {
        self.error.get_or_insert(e);
        event_loop.exit();
    }

    fn on_key(&mut self, event_loop: &ActiveEventLoop, event: &KeyEvent) {
        if event.state != ElementState::Pressed {
            return;
        }
        match &event.logical_key {
            Key::Named(NamedKey::Escape) => event_loop.exit(),
            Key::Character(c) => match c.to_ascii_lowercase().as_str() {
                "q" => event_loop.exit(),
                "f" => {
                    let (w, h) = self.window.as_ref().map(|w| (w.inner_size().width, w.inner_size().height)).unwrap_or((1, 1));
                    let fov = self.fov();
                    self.orbit.fit(&self.bounds, fov, w, h);
                    self.redraw();
                }
                "c" => {
                    let next = (self.mode + 1) % self.modes.len();
                    match &mut self.content {
                        // A switch that needs another attribute is streamed (§3.5); not while
                        // the points or another switch are still loading.
                        Content::Progressive(v) => {
                            let ctx = match &self.renderer {
                                Some(Renderer::Gpu(g)) => Some(&g.ctx),
                                _ => None,
                            };
                            match v.set_mode(next, ctx) {
                                Ok(true) => self.mode = next,
                                Ok(false) => {}
                                Err(e) => return self.fail(event_loop, e),
                            }
                        }
                        _ => self.mode = next,
                    }
                    self.redraw();
                }
                _ => {}
            },
            _ => {}
        }
    }

    fn on_cursor(&mut self, x: f64, y: f64) {
        let Some((px, py)) = self.drag.cursor.replace((x, y)) else { return };
        let (dx, dy) = (x - px, y - py);
        let pan = self.drag.right || (self.drag.left && self.drag.shift);
        if pan {
            let Some(window) = &self.window else { return };
            let (w, h) = (window.inner_size().width.max(1), window.inner_size().height.max(1));
            let Ok(cam) = self.orbit.camera(self.fov(), self.args.camera.ortho, &self.bounds, w, h) else { return };
            let Some(axes) = cam.axes() else { return };
            // World units per pixel at the target's distance.
            let per_px = 2.0 * self.orbit.distance * (0.5 * self.fov()).tan() / h as f64;
            for i in 0..3 {
                self.orbit.target[i] += (-dx * axes.right[i] + dy * axes.up[i]) * per_px;
            }
            self.redraw();
        } else if self.drag.left {
            self.orbit.yaw -= dx * 0.005;
            self.orbit.pitch = (self.orbit.pitch + dy * 0.005).clamp(-MAX_PITCH, MAX_PITCH);
            self.redraw();
        }
    }

    fn on_wheel(&mut self, delta: MouseScrollDelta) {
        let lines = match delta {
            MouseScrollDelta::LineDelta(_, y) => y as f64,
            MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
        };
        let extent = self.bounds.diagonal().max(1e-9);
        self.orbit.distance = (self.orbit.distance * 0.85f64.powf(lines)).clamp(extent * 1e-6, extent * 100.0);
        self.redraw();
    }
}

impl App<'_> {
    /// Whether the content needs more frames to show its final image.
    fn busy(&self) -> bool {
        match &self.content {
            Content::Progressive(v) => v.busy(),
            _ => self.uploading,
        }
    }

    /// A preview's build reported: reloads the store at a new commit (and once more when the
    /// build ended) and redraws; otherwise redraws for the status line at most twice a second.
    fn on_build(&mut self, event: Wake) -> Result<()> {
        let Some(b) = self.build.as_mut() else { return Ok(()) };
        let committed = b.poll();
        if let Wake::Done(ok) = event {
            // A failed build leaves no store to look at: the window closes and the command
            // reports the build's error.
            if !ok {
                b.failed = true;
                return Ok(());
            }
            if !b.done {
                b.done = true;
                b.seconds = Some(b.start.elapsed().as_secs_f64());
            }
        }
        let reload = committed || (b.done && !b.final_loaded);
        if b.done {
            b.final_loaded = true;
        }
        let mut changed = false;
        if reload {
            if let Content::Store(v) = &mut self.content {
                let gpu = match self.renderer.as_mut() {
                    Some(Renderer::Gpu(g)) => match &mut g.data {
                        GpuData::Store(sg) => Some(sg),
                        GpuData::Batches { .. } | GpuData::Progressive => None,
                    },
                    _ => None,
                };
                changed = v.reload(gpu)?;
            }
        }
        let stale = self.frames.last().is_none_or(|_| self.last_frame.is_none_or(|t| t.elapsed().as_secs_f64() >= 0.5));
        if changed || reload || stale {
            self.redraw();
        }
        Ok(())
    }
}

impl ApplicationHandler<Wake> for App<'_> {
    fn user_event(&mut self, event_loop: &ActiveEventLoop, event: Wake) {
        if let Err(e) = self.on_build(event) {
            self.fail(event_loop, e);
        }
        if self.build.as_ref().is_some_and(|b| b.failed) {
            event_loop.exit();
        }
    }

    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.window.is_some() {
            return;
        }
        if let Err(e) = self.open(event_loop) {
            self.fail(event_loop, e);
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(_) => self.redraw(),
            WindowEvent::KeyboardInput { event, .. } => self.on_key(event_loop, &event),
            WindowEvent::ModifiersChanged(m) => self.drag.shift = m.state().shift_key(),
            WindowEvent::MouseInput { state, button, .. } => {
                let down = state == ElementState::Pressed;
                match button {
                    MouseButton::Left => self.drag.left = down,
                    MouseButton::Right => self.drag.right = down,
                    _ => {}
                }
            }
            WindowEvent::CursorMoved { position, .. } => self.on_cursor(position.x, position.y),
            WindowEvent::CursorLeft { .. } => self.drag.cursor = None,
            WindowEvent::MouseWheel { delta, .. } => self.on_wheel(delta),
            WindowEvent::RedrawRequested => {
                let shooting = self.args.screenshot.is_some();
                let last = shooting
                    && match &self.build {
                        // A preview's screenshot shows the finished store.
                        Some(b) => b.final_loaded,
                        // A progressive view's screenshot shows its final image.
                        None => self.frames.len() + 1 >= self.args.frames as usize && !self.busy(),
                    };
                match self.draw(last) {
                    Err(e) => self.fail(event_loop, e),
                    Ok(Some((w, h, pixels))) if last => {
                        let path = self.args.screenshot.clone().expect("shooting");
                        let r = encode_png(w, h, &pixels).and_then(|png| write_atomic(&path, &png));
                        match r {
                            Ok(()) => {
                                self.done = true;
                                event_loop.exit();
                            }
                            Err(e) => self.fail(event_loop, e),
                        }
                    }
                    Ok(_) if shooting && self.build.is_none() => self.redraw(),
                    // Progressive frames go on until the image is final.
                    Ok(_) if self.busy() => self.redraw(),
                    Ok(_) => {}
                }
            }
            _ => {}
        }
    }
}

/// `1234567` as `1,234,567`.
pub fn group_digits(n: u64) -> String {
    let s = n.to_string();
    let mut groups = Vec::new();
    let mut end = s.len();
    while end > 3 {
        groups.push(&s[end - 3..end]);
        end -= 3;
    }
    groups.push(&s[..end]);
    groups.reverse();
    groups.join(",")
}

/// The status line as an RGBA8 overlay (white 8x8 glyphs, doubled on wide windows, on a
/// translucent black bar) at most `max_width` pixels wide: `(width, height, pixels)`.
fn status_overlay(text: &str, max_width: u32) -> (u32, u32, Vec<u32>) {
    use font8x8::UnicodeFonts;
    let scale: u32 = if max_width >= 1600 { 2 } else { 1 };
    let pad = 3 * scale;
    let glyph = 8 * scale;
    let chars: Vec<char> = text.chars().collect();
    let width = (chars.len() as u32 * glyph + 2 * pad).min(max_width.max(1));
    let height = glyph + 2 * pad;
    let bar = 0xb000_0000u32;
    let mut px = vec![bar; width as usize * height as usize];
    for (k, ch) in chars.iter().enumerate() {
        let rows = font8x8::BASIC_FONTS.get(*ch).unwrap_or([0; 8]);
        for (gy, row) in rows.iter().enumerate() {
            for gx in 0..8u32 {
                if row & (1 << gx) == 0 {
                    continue;
                }
                for sy in 0..scale {
                    for sx in 0..scale {
                        let x = pad + k as u32 * glyph + gx * scale + sx;
                        let y = pad + gy as u32 * scale + sy;
                        if x < width {
                            px[(y * width + x) as usize] = 0xffff_ffff;
                        }
                    }
                }
            }
        }
    }
    (width, height, px)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn digits_are_grouped() {
        assert_eq!(group_digits(0), "0");
        assert_eq!(group_digits(999), "999");
        assert_eq!(group_digits(1000), "1,000");
        assert_eq!(group_digits(110_000), "110,000");
        assert_eq!(group_digits(1_234_567), "1,234,567");
    }

    #[test]
    fn orbit_round_trips_a_camera() {
        let bounds = Aabb::new([0.0, 0.0, 0.0], [100.0, 50.0, 20.0]);
        let cam = Camera::frame_perspective(&bounds, mortar_core::render::ViewPreset::Iso, 0.8, 640, 480).unwrap();
        let o = Orbit::from_camera(&cam);
        let back = o.camera(0.8, false, &bounds, 640, 480).unwrap();
        for i in 0..3 {
            assert!((back.eye[i] - cam.eye[i]).abs() < 1e-6 * o.distance, "{:?} vs {:?}", back.eye, cam.eye);
        }
        // A top view keeps north up: the eye is displaced south of the target.
        let top = Camera::frame_perspective(&bounds, mortar_core::render::ViewPreset::Top, 0.8, 640, 480).unwrap();
        let o = Orbit::from_camera(&top);
        assert!(o.eye()[1] < o.target[1] && (o.eye()[0] - o.target[0]).abs() < 1e-6 * o.distance);
        assert!(o.camera(0.8, false, &bounds, 640, 480).is_ok());
    }

    #[test]
    fn fit_shows_every_corner() {
        let bounds = Aabb::new([1000.0, 2000.0, 0.0], [1100.0, 2300.0, 40.0]);
        for (w, h) in [(640, 480), (300, 900)] {
            let mut o = Orbit { target: [0.0; 3], distance: 1.0, yaw: 0.7, pitch: 0.4 };
            o.fit(&bounds, 0.9, w, h);
            let cam = o.camera(0.9, false, &bounds, w, h).unwrap();
            let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
            for k in bounds.corners() {
                let p = cam.project(k).expect("in front of the eye");
                assert!(p.x >= 0.0 && p.x <= w as f64 && p.y >= 0.0 && p.y <= h as f64, "{k:?} at {p:?} outside {w}x{h}");
                lo = [lo[0].min(p.x), lo[1].min(p.y)];
                hi = [hi[0].max(p.x), hi[1].max(p.y)];
            }
            // Tight: the box spans most of the window in one direction.
            assert!((hi[0] - lo[0]) / w as f64 > 0.8 || (hi[1] - lo[1]) / h as f64 > 0.8, "{lo:?}..{hi:?} in {w}x{h}");
        }
    }

    #[test]
    fn status_overlay_draws_text_within_the_width() {
        let (w, h, px) = status_overlay("110,000 points | 1.0 ms", 120);
        assert_eq!((w, h), (120, 14));
        assert_eq!(px.len(), (w * h) as usize);
        let lit = px.iter().filter(|&&c| c == 0xffff_ffff).count();
        assert!(lit > 50, "{lit} text pixels");
        let (w2, _, _) = status_overlay("ab", 1000);
        assert_eq!(w2, 2 * 8 + 6);
    }
}
