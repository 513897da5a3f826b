//! `mortar view`: a window on one of three kinds of content ([`Content`]): a batch file (every
//! point; other non-LAS inputs are batched on the fly as `mortar render` does), an octree store
//! ([`store::StoreView`]: LOD selection per frame, nodes uploaded on first selection) or raw
//! LAS/LAZ ([`progressive::ProgressiveView`]: the progressive renderer of paper 000, the window
//! open at once and points appearing as they are decoded); and the window of `mortar build
//! --preview`, which reads the growing store's commits. Each frame is drawn by the GPU
//! rasterizer (paper 003 §3.2-3.3: clear, draw, resolve in compute shaders) and put on the
//! window's surface by one render pass, without the image leaving the GPU; where no hardware GPU
//! can present to the window (or with `--backend cpu`) the CPU reference rasterizer draws and
//! the image is uploaded to the window as a plain pixel buffer (softbuffer).
//!
//! Frames are drawn on input (orbit, pan, zoom, keys, resizes) and when the content changes
//! (points decoded, a new commit of the previewed store). `--screenshot out.png --frames N`
//! draws N frames in the real window, writes what the last one put on the surface and exits
//! (tests run it under Xvfb).

pub mod content;
pub mod progressive;
pub mod store;

pub use content::{group_digits, BatchContent, Content, GpuDrawn};

use crate::cli as common;
use crate::render::{
    build_camera, encode_png, parse_color, parse_color_choice, parse_range, write_atomic,
    AtomicsArg, CameraArgs, PrecisionArg,
};
use crate::viewer::progressive::ProgressiveView;
use crate::viewer::store::StoreView;
use anyhow::{anyhow, bail, Context as _, Result};
use mortar_core::layout::RecordLayout;
use mortar_core::render::resolve::ResolveOptions;
use mortar_core::render::{Aabb, Orbit, RasterOptions};
use mortar_io::inputs::InputKind;
use mortar_io::render_input::{self, ColorChoice};
use mortar_io::store::{BuildProgress, BuildReport};
use mortar_render::{
    AtomicPath, GpuContext, GpuError, GpuOptions, GpuRasterizer, Overlay, Presented, WindowSurface,
};
use std::num::NonZeroU32;
use std::path::PathBuf;
use std::sync::mpsc::{Receiver, TryRecvError};
use std::sync::Arc;
use std::time::Instant;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, KeyEvent, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop, EventLoopProxy};
use winit::keyboard::{Key, NamedKey};
use winit::window::{Window, WindowId};

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
    /// Fill empty pixels from their nearest neighbour where at least N of the 8 neighbours hold a
    /// point (--hole-fill alone: N = 3).
    #[arg(long, value_name = "N", num_args = 0..=1, default_missing_value = "3", value_parser = clap::value_parser!(u32).range(1..=8))]
    pub hole_fill: Option<u32>,
    /// Eye-dome lighting (shading from depth differences), with an optional strength.
    #[arg(long, value_name = "STRENGTH", num_args = 0..=1, default_missing_value = "1.0")]
    pub edl: Option<f32>,
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
    pub lod: crate::render::LodArgs,
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
    /// The preview's hole filling (as `mortar view --hole-fill [N]`).
    #[arg(long, value_name = "N", num_args = 0..=1, default_missing_value = "3", value_parser = clap::value_parser!(u32).range(1..=8), requires = "preview")]
    pub preview_hole_fill: Option<u32>,
    /// The preview's eye-dome lighting (as `mortar view --edl [STRENGTH]`).
    #[arg(long, value_name = "STRENGTH", num_args = 0..=1, default_missing_value = "1.0", requires = "preview")]
    pub preview_edl: Option<f32>,
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
            hole_fill: self.preview_hole_fill,
            edl: self.preview_edl,
            screenshot: self.preview_screenshot.clone(),
            frames: 1,
            json: false,
            no_status: false,
            sort: common::SortArgs::default(),
            lod: crate::render::LodArgs::default(),
            no_progressive: false,
        }
    }
}

impl Args {
    /// The resolve's choices: background, hole filling, eye-dome lighting.
    pub fn resolve_options(&self) -> ResolveOptions {
        crate::render::resolve_options(self.background, self.hole_fill, self.edl)
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
        [one] if !a.lod.no_lod && InputKind::of(std::path::Path::new(one)) == InputKind::Store => {
            Some(PathBuf::from(one))
        }
        _ => None,
    };
    if store.is_none() && (a.lod.lod_threshold.is_some() || a.lod.point_budget.is_some()) {
        bail!("--lod-threshold and --point-budget apply to a single octree store (made by mortar build), not to {}", a.inputs.join(" "));
    }
    if let Some(dir) = store {
        let mut view = StoreView::open(&dir, a.lod.options(true)?, a.range)?;
        view.show_mode(a.color)?;
        let label = dir.display().to_string();
        return show(&a, event_loop, Box::new(view), label, None).map(drop);
    }
    if !a.no_progressive {
        let paths = mortar_io::inputs::expand(&a.inputs)?;
        let raw = !paths.is_empty() && paths.iter().all(|p| InputKind::of(p) == InputKind::Las);
        if raw {
            let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
            let view = ProgressiveView::open(&paths, a.color, a.range, threads)?;
            let label = paths.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" ");
            return show(&a, event_loop, Box::new(view), label, None).map(drop);
        }
    }
    let (source, bounds) = crate::render::open_source(&a.inputs, &a.sort, None)?;
    let file = &source.file;
    let own = |e| source.own_error(e);
    let label = source.name.display().to_string();
    if file.header.point_count == 0 {
        bail!("{label}: no points to draw");
    }
    render_input::check_color(file, a.color.resolved(file)).map_err(own)?;
    let views = render_input::load_words(file).map_err(own)?;
    let refs = render_input::batch_refs(file, &views).map_err(own)?;
    let content =
        BatchContent::new(label.clone(), file, &refs, bounds, a.color, a.range).map_err(own)?;
    show(&a, event_loop, Box::new(content), label, None).map(drop)
}

/// `mortar build --preview`: shows the store `dir` as `build` grows it. `build` runs on its own
/// thread and reports progress through the callback it is given, which never blocks (an
/// unbounded channel and a wake-up event): the builder never waits for the window. The window
/// reloads the store at each new commit and draws it with LOD, uploading only new nodes. If the
/// window is closed first, the build goes on without it and this waits for it; with
/// `--screenshot` the window closes itself once the last commit was shown. Returns the build's
/// report and the frames' statistics.
pub fn run_preview<F>(
    a: &Args,
    dir: &std::path::Path,
    bounds: Aabb,
    layout: &RecordLayout,
    build: F,
) -> Result<(BuildReport, serde_json::Value)>
where
    F: FnOnce(&mut dyn FnMut(&BuildProgress)) -> Result<BuildReport> + Send,
{
    check_window(a)?;
    let event_loop = event_loop()?;
    let proxy: EventLoopProxy<Wake> = event_loop.create_proxy();
    let mut view = StoreView::waiting(dir, bounds, layout, a.lod.options(true)?, a.range);
    view.show_mode(a.color)?;
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
        let frames = match show(a, event_loop, Box::new(view), label, Some(BuildState::new(prx))) {
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
        let result =
            rrx.recv().map_err(|_| anyhow!("the build's thread ended without a result"))?;
        result.map(|r| (r, frames))
    })
}

/// The frame period of the off-screen preview (60 frames per second).
const OFFSCREEN_PERIOD_MS: f64 = 1000.0 / 60.0;

/// `mortar build --preview --preview-offscreen`: the preview's frames drawn without a window,
/// paced to 60 per second, by the same store view as the window (GPU or CPU), from the fixed
/// camera of the options. Returns the build's report and the frames' statistics.
pub fn run_preview_offscreen<F>(
    a: &Args,
    dir: &std::path::Path,
    bounds: Aabb,
    layout: &RecordLayout,
    build: F,
) -> Result<(BuildReport, serde_json::Value)>
where
    F: FnOnce(&mut dyn FnMut(&BuildProgress)) -> Result<BuildReport> + Send,
{
    check_window(a)?;
    let mut view = StoreView::waiting(dir, bounds, layout, a.lod.options(true)?, a.range);
    view.show_mode(a.color)?;
    let camera = build_camera(&a.camera, &bounds, a.width, a.height)?;
    let options = RasterOptions { precision: a.precision.mode(), cull: true };
    let atomics = match a.atomics {
        AtomicsArg::Auto => None,
        AtomicsArg::U64 => Some(AtomicPath::U64),
        AtomicsArg::U32 => Some(AtomicPath::TwoPass32),
    };
    let ctx = match a.backend {
        ViewBackend::Cpu => None,
        ViewBackend::Gpu => Some(
            GpuContext::new(&GpuOptions { atomics, allow_software: true, ..Default::default() })
                .map_err(|e| anyhow!("--preview-backend gpu: {e}"))?,
        ),
        ViewBackend::Auto => {
            GpuContext::new(&GpuOptions { atomics, allow_software: false, ..Default::default() })
                .ok()
        }
    };
    let mut raster = match &ctx {
        Some(ctx) => {
            view.use_gpu(ctx)?;
            Some(GpuRasterizer::new(ctx, a.width, a.height)?)
        }
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
                Err(TryRecvError::Disconnected) => {
                    return Err(anyhow!("the build's thread ended without a result"))
                }
            }
            let committed = state.poll();
            let last = result.is_some();
            if committed || last {
                view.reload()?;
            }
            let (drawn, gpu_ms) = match (&ctx, &mut raster) {
                (Some(ctx), Some(raster)) => {
                    let f = view.draw_gpu(ctx, raster, &camera, &options, &a.resolve_options())?;
                    (f.points_drawn, f.draw_ms.map(|d| d + f.resolve_ms.unwrap_or(0.0)))
                }
                _ => view
                    .draw_cpu(&camera, &options, &a.resolve_options())
                    .map(|(_, n)| (n, None))?,
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
    let ms: Vec<f64> = frames.iter().filter_map(|f| f["frame_ms"].as_f64()).collect();
    let pick = |q: f64| mortar_core::metrics::percentile(&ms, q);
    let seconds = report.seconds.max(1e-9);
    let during =
        frames.iter().filter(|f| f["at_seconds"].as_f64().is_some_and(|t| t <= seconds)).count();
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
fn show<'a>(
    a: &'a Args,
    event_loop: EventLoop<Wake>,
    content: Box<dyn Content + 'a>,
    label: String,
    build: Option<BuildState>,
) -> Result<Shown> {
    let bounds = content.bounds();
    let camera = build_camera(&a.camera, &bounds, a.width, a.height)
        .map_err(|e| anyhow!("{label}: {e:#}"))?;
    let mut app = App {
        args: a,
        content,
        label: label.clone(),
        bounds,
        orbit: Orbit::from_camera(&camera),
        window: None,
        renderer: None,
        drag: Drag::default(),
        frames: Vec::new(),
        error: None,
        done: false,
        last_frame: None,
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
        "color": app.content.modes()[app.content.mode()].name(),
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

/// The GPU renderer's parts.
struct Gpu {
    ctx: GpuContext,
    surface: WindowSurface,
    raster: GpuRasterizer,
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
        BuildState {
            progress,
            latest: BuildProgress::default(),
            start: now,
            rate_from: (0, now),
            rate: 0.0,
            done: false,
            seconds: None,
            final_loaded: false,
            failed: false,
        }
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
            Renderer::Cpu { why, .. } => {
                serde_json::json!({ "backend": "cpu", "why": why, "read_back": "window pixel buffer" })
            }
        }
    }
}

struct App<'a> {
    args: &'a Args,
    content: Box<dyn Content + 'a>,
    label: String,
    bounds: Aabb,
    orbit: Orbit,
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
}

impl App<'_> {
    fn fov(&self) -> f64 {
        self.args.camera.fov.to_radians()
    }

    /// Opens the window and what draws into it.
    fn open(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let attrs = Window::default_attributes()
            .with_title(format!("mortar view: {}", self.label))
            .with_inner_size(PhysicalSize::new(self.args.width, self.args.height));
        let window = Arc::new(event_loop.create_window(attrs).context("cannot open a window")?);
        self.window = Some(window.clone());
        let size = window.inner_size();
        let (w, h) = (size.width.max(1), size.height.max(1));
        let atomics = match self.args.atomics {
            AtomicsArg::Auto => None,
            AtomicsArg::U64 => Some(AtomicPath::U64),
            AtomicsArg::U32 => Some(AtomicPath::TwoPass32),
        };
        let gpu = match self.args.backend {
            ViewBackend::Cpu => Err("--backend cpu"),
            ViewBackend::Gpu => Ok(GpuContext::for_window(
                &GpuOptions { atomics, allow_software: true, ..Default::default() },
                window.clone(),
            )
            .map_err(|e| anyhow!("--backend gpu: {e}"))?),
            ViewBackend::Auto => GpuContext::for_window(
                &GpuOptions { atomics, allow_software: false, ..Default::default() },
                window.clone(),
            )
            .map_err(|_| "no hardware GPU can present to the window"),
        };
        // Content the GPU cannot draw (the progressive renderer on 32-bit atomics) is drawn on the CPU.
        let gpu = gpu.and_then(|g| match self.content.gpu_unsupported(&g.0) {
            Some(why) => Err(why),
            None => Ok(g),
        });
        let renderer = match gpu {
            Ok((ctx, surface)) => self
                .open_gpu(ctx, surface, w, h)
                .map_err(|e| anyhow!("{}: GPU: {e}", self.label))?,
            Err(why) => {
                let context = softbuffer::Context::new(window.clone())
                    .map_err(|e| anyhow!("cannot draw into the window: {e}"))?;
                let surface = softbuffer::Surface::new(&context, window.clone())
                    .map_err(|e| anyhow!("cannot draw into the window: {e}"))?;
                Renderer::Cpu { surface, _context: context, why }
            }
        };
        self.renderer = Some(renderer);
        window.request_redraw();
        Ok(())
    }

    fn open_gpu(
        &mut self,
        ctx: GpuContext,
        surface: mortar_render::wgpu::Surface<'static>,
        w: u32,
        h: u32,
    ) -> std::result::Result<Renderer, GpuError> {
        let surface = WindowSurface::new(&ctx, surface, w, h)?;
        let raster = GpuRasterizer::new(&ctx, w, h)?;
        self.content.use_gpu(&ctx)?;
        Ok(Renderer::Gpu(Box::new(Gpu { ctx, surface, raster })))
    }

    /// The status line: points, the last frame's time and rate, colour mode, renderer.
    fn status(&self) -> String {
        let mut parts = Vec::new();
        if let Some(b) = &self.build {
            parts.push(b.status());
        }
        parts.extend(self.content.status());
        if let Some(f) = self.frames.last() {
            parts.push(format!("{:.1} ms ({:.0} fps)", f.frame_ms, 1000.0 / f.frame_ms.max(1e-3)));
        }
        parts.push(self.content.modes()[self.content.mode()].name().to_string());
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
        let camera = self
            .orbit
            .camera(self.fov(), self.args.camera.ortho, &self.bounds, w, h)
            .map_err(|e| anyhow!("{}: {e:#}", self.label))?;
        let options = RasterOptions { precision: self.args.precision.mode(), cull: true };
        let status = self.status();
        let overlay = (!self.args.no_status).then(|| status_overlay(&status, w));
        let resolve = self.args.resolve_options();
        let label = self.label.clone();
        let start = Instant::now();
        let renderer = self.renderer.as_mut().ok_or_else(|| anyhow!("no renderer"))?;
        let mut stats = FrameStats { width: w, height: h, ..Default::default() };
        let pixels = match renderer {
            Renderer::Gpu(g) => {
                let Gpu { ctx, surface, raster } = &mut **g;
                let gpu = |e: GpuError| anyhow!("{label}: GPU: {e}");
                surface.resize(ctx, w, h).map_err(gpu)?;
                raster.resize(ctx, w, h).map_err(gpu)?;
                let drawn = self.content.draw_gpu(ctx, raster, &camera, &options, &resolve)?;
                stats.raster_ms = start.elapsed().as_secs_f64() * 1e3;
                stats.points_drawn = drawn.points_drawn;
                stats.gpu_draw_ms = drawn.draw_ms;
                stats.gpu_resolve_ms = drawn.resolve_ms;
                let o = overlay.as_ref().map(|(ow, oh, px)| Overlay {
                    width: *ow,
                    height: *oh,
                    rgba: px,
                });
                let shown = if drawn.own_image {
                    let image = self
                        .content
                        .image()
                        .ok_or_else(|| anyhow!("{label}: GPU: no image resolved"))?;
                    surface.present_image(ctx, image, (w, h), o, read_back).map_err(gpu)?
                } else {
                    surface.present(ctx, raster, o, read_back).map_err(gpu)?
                };
                match shown {
                    Presented::Shown(p) => p,
                    Presented::Skipped(_) => {
                        window.request_redraw();
                        return Ok(None);
                    }
                }
            }
            Renderer::Cpu { surface, .. } => {
                let (mut rgba, drawn) = self.content.draw_cpu(&camera, &options, &resolve)?;
                stats.points_drawn = drawn;
                stats.raster_ms = start.elapsed().as_secs_f64() * 1e3;
                if let Some((ow, oh, px)) = &overlay {
                    mortar_render::present::blend_overlay(
                        &mut rgba,
                        w,
                        &Overlay { width: *ow, height: *oh, rgba: px },
                    );
                }
                let (nw, nh) =
                    (NonZeroU32::new(w).expect("w > 0"), NonZeroU32::new(h).expect("h > 0"));
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
        stats.at_ms = crate::cli::since_start_ms();
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
                    let (w, h) = self
                        .window
                        .as_ref()
                        .map(|w| (w.inner_size().width, w.inner_size().height))
                        .unwrap_or((1, 1));
                    let fov = self.fov();
                    self.orbit.fit(&self.bounds, fov, w, h);
                    self.redraw();
                }
                "c" => {
                    // A switch that needs another attribute may be streamed (§3.5), and refused
                    // while the points or another switch are still loading.
                    let next = (self.content.mode() + 1) % self.content.modes().len();
                    let ctx = match &self.renderer {
                        Some(Renderer::Gpu(g)) => Some(&g.ctx),
                        _ => None,
                    };
                    if let Err(e) = self.content.set_mode(next, ctx) {
                        return self.fail(event_loop, e);
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
            let size = window.inner_size();
            let Ok(cam) = self.orbit.camera(
                self.fov(),
                self.args.camera.ortho,
                &self.bounds,
                size.width.max(1),
                size.height.max(1),
            ) else {
                return;
            };
            if self.orbit.pan(dx, dy, self.fov(), &cam).is_some() {
                self.redraw();
            }
        } else if self.drag.left {
            self.orbit.rotate(dx, dy);
            self.redraw();
        }
    }

    fn on_wheel(&mut self, delta: MouseScrollDelta) {
        let lines = match delta {
            MouseScrollDelta::LineDelta(_, y) => y as f64,
            MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
        };
        self.orbit.zoom(lines, &self.bounds);
        self.redraw();
    }
}

impl App<'_> {
    /// Whether the content needs more frames to show its final image.
    fn busy(&self) -> bool {
        self.content.busy()
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
            changed = self.content.reload()?;
        }
        let stale = self
            .frames
            .last()
            .is_none_or(|_| self.last_frame.is_none_or(|t| t.elapsed().as_secs_f64() >= 0.5));
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
