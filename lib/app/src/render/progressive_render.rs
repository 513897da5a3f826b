//! `mortar render <las|laz> --progressive N`: the progressive renderer of paper 000, headless, on
//! the CPU (`mortar_core::render::progressive`) or the GPU (`mortar_render::progressive`;
//! `--backend gpu`, or `auto` on a hardware GPU with 64-bit atomics). The inputs are decoded in
//! parallel on loader threads while frames are drawn; every frame takes the points decoded so far
//! into the shuffled buffer (incremental shuffle, eq. 1-2), then runs Reproject, Fill (`--budget`
//! slots, or the adaptive budget of §3.4.1 with `--budget auto`, timed by GPU timestamps where the
//! GPU has them) and Prepare with a still camera. The last frame's keys are resolved on the host
//! like `mortar render`'s images (same colour rules, hole filling, eye-dome lighting; both
//! backends leave the same keys) and written as PNG; `--json` prints every frame's statistics and
//! when the image converged.
//!
//! The interactive window (`mortar view` on raw LAS/LAZ) draws progressively too:
//! [`crate::viewer::progressive_view`].

use super::args::{Args, Backend, ProgressiveArgs};
use super::output::{build_camera, camera_json, encode_png, gpu_context, write_atomic};
use crate::cli as common;
use crate::draw::raw::{
    load_pieces, payload_colors, payload_for, payload_range, point_count, resolve_choice,
    ColorStats, LoadedPiece,
};
use crate::draw::ColorChoice;
use anyhow::{anyhow, bail, Result};
use mortar_core::metrics::median;
use mortar_core::render::framing::{IntBox, ViewBox};
use mortar_core::render::progressive::{
    AdaptiveBudget, FillBudget, FrameStats, ProgressiveFrame, ProgressiveRenderer, Shuffle,
};
use mortar_core::render::resolve::{resolve, ColorMode, EyeDome, HoleFill, ResolveOptions};
use mortar_core::render::{Camera, RasterOptions};
use mortar_io::inputs::InputKind;
use mortar_render::{
    AtomicPath, GpuContext, GpuProgressive, GpuProgressiveFrame, ProgressiveOptions,
};
use std::sync::atomic::AtomicBool;
use std::sync::mpsc::{sync_channel, Receiver, TryRecvError};
use std::time::Instant;

/// Default fill budget (the paper's basic fixed budget).
const DEFAULT_BUDGET: u64 = 1_000_000;

/// How many frames to draw.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Frames {
    Count(u64),
    Converge,
}

fn parse_frames(s: &str) -> Result<Frames> {
    if s == "converge" {
        return Ok(Frames::Converge);
    }
    match s.parse::<u64>() {
        Ok(0) => bail!("--progressive 0: draw at least one frame (or --progressive converge)"),
        Ok(n) => Ok(Frames::Count(n)),
        Err(_) => bail!("--progressive '{s}': expected a number of frames or 'converge'"),
    }
}

fn parse_budget(p: &ProgressiveArgs) -> Result<FillBudget> {
    let auto = p.budget.as_deref() == Some("auto");
    if !auto && p.probe.is_some() {
        bail!("--probe applies to --budget auto");
    }
    if !auto && !p.pace && p.target_ms.is_some() {
        bail!("--target-ms applies to --budget auto and --pace");
    }
    if let Some(t) = p.target_ms {
        if !(t.is_finite() && t > 0.0) {
            bail!("--target-ms {t}: must be a positive number of milliseconds");
        }
    }
    if auto {
        let mut a = AdaptiveBudget::default();
        if let Some(t) = p.target_ms {
            a.target_ms = t;
        }
        if let Some(n) = p.probe {
            if n == 0 {
                bail!("--probe 0: the adaptive budget needs at least one point to time");
            }
            a.probe_points = n;
        }
        return Ok(FillBudget::Adaptive(a));
    }
    match p.budget.as_deref().map(str::parse::<u64>) {
        None => Ok(FillBudget::Fixed(DEFAULT_BUDGET)),
        Some(Ok(0)) => bail!("--budget 0: the Fill pass must draw at least one point per frame, or the image never converges"),
        Some(Ok(n)) => Ok(FillBudget::Fixed(n)),
        Some(Err(_)) => bail!("--budget '{}': expected a number of points or 'auto'", p.budget.as_deref().unwrap_or_default()),
    }
}

/// The frame period of `--pace`, ms.
fn frame_period(p: &ProgressiveArgs) -> Option<f64> {
    p.pace.then(|| p.target_ms.unwrap_or(AdaptiveBudget::default().target_ms))
}

/// The `--backend` value, for messages.
fn backend_name(b: Backend) -> &'static str {
    match b {
        Backend::Cpu => "cpu",
        Backend::Gpu => "gpu",
        Backend::Auto => "auto",
    }
}

/// Milliseconds since `t`.
fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The progressive renderer a loop drives, on either backend: [`ProgressiveRenderer`] (CPU) or
/// [`GpuProgressive`] on its context ([`OnGpu`]). Both hold the same shuffle and convergence
/// state; the loop of `render --progressive` sees only this trait.
pub trait ProgressiveEngine {
    /// Points inserted so far.
    fn loaded(&self) -> u64;
    /// Points the buffer holds when full.
    fn capacity(&self) -> u64;
    /// The shuffle that maps arrival numbers to slots.
    fn shuffle(&self) -> &Shuffle;
    /// Inserts a decoded piece (positions and payloads).
    fn insert(&mut self, piece: &LoadedPiece) -> std::result::Result<(), String>;
    /// One frame: reproject, fill within `budget`, prepare; the GPU's own account where there is one.
    fn frame(
        &mut self,
        camera: &Camera,
        options: &RasterOptions,
        budget: &FillBudget,
    ) -> std::result::Result<(FrameStats, Option<GpuProgressiveFrame>), String>;
    /// The last frame's keys and its visible slots (sorted).
    fn keys_and_visible(&self) -> Result<(Vec<u64>, Vec<u32>)>;
    /// The payload in `slot`, once loaded.
    fn payload(&self, slot: u32) -> Option<u64>;
    /// The payloads of every point loaded.
    fn loaded_payloads(&self) -> Vec<u64>;
    /// The quantization frame (which grows for points outside it).
    fn frame_state(&self) -> ProgressiveFrame;
    /// How often the frame grew.
    fn growths(&self) -> u32;
    /// Pixels of the last frame whose winner ties in depth with another point (`None` before
    /// every point arrived).
    fn depth_ties(&mut self) -> Result<Option<u64>>;
    /// The backend for `--json` (`null` for the CPU).
    fn backend_json(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
}

impl ProgressiveEngine for ProgressiveRenderer {
    fn loaded(&self) -> u64 {
        ProgressiveRenderer::loaded(self)
    }

    fn capacity(&self) -> u64 {
        ProgressiveRenderer::capacity(self)
    }

    fn shuffle(&self) -> &Shuffle {
        ProgressiveRenderer::shuffle(self)
    }

    fn insert(&mut self, piece: &LoadedPiece) -> std::result::Result<(), String> {
        ProgressiveRenderer::insert(self, piece.first, &piece.xyz, &piece.payload)
            .map_err(|e| e.to_string())
    }

    fn frame(
        &mut self,
        camera: &Camera,
        options: &RasterOptions,
        budget: &FillBudget,
    ) -> std::result::Result<(FrameStats, Option<GpuProgressiveFrame>), String> {
        ProgressiveRenderer::frame(self, camera, options, budget)
            .map(|s| (s, None))
            .map_err(|e| e.to_string())
    }

    fn keys_and_visible(&self) -> Result<(Vec<u64>, Vec<u32>)> {
        let mut v = self.visible();
        v.sort_unstable();
        Ok((self.keys(), v))
    }

    fn payload(&self, slot: u32) -> Option<u64> {
        ProgressiveRenderer::payload(self, slot)
    }

    fn loaded_payloads(&self) -> Vec<u64> {
        ProgressiveRenderer::loaded_payloads(self)
    }

    fn frame_state(&self) -> ProgressiveFrame {
        *ProgressiveRenderer::frame_state(self)
    }

    fn growths(&self) -> u32 {
        ProgressiveRenderer::growths(self)
    }

    fn depth_ties(&mut self) -> Result<Option<u64>> {
        Ok(ProgressiveRenderer::depth_ties(self)?)
    }
}

/// The GPU progressive renderer with the context it runs on.
pub struct OnGpu<'a> {
    pub ctx: &'a GpuContext,
    pub r: GpuProgressive,
}

impl ProgressiveEngine for OnGpu<'_> {
    fn loaded(&self) -> u64 {
        self.r.loaded()
    }

    fn capacity(&self) -> u64 {
        self.r.capacity()
    }

    fn shuffle(&self) -> &Shuffle {
        self.r.shuffle()
    }

    fn insert(&mut self, piece: &LoadedPiece) -> std::result::Result<(), String> {
        self.r
            .insert(self.ctx, piece.first, &piece.xyz, None, Some(&piece.payload))
            .map_err(|e| e.to_string())
    }

    fn frame(
        &mut self,
        camera: &Camera,
        options: &RasterOptions,
        budget: &FillBudget,
    ) -> std::result::Result<(FrameStats, Option<GpuProgressiveFrame>), String> {
        self.r
            .frame(self.ctx, camera, options, budget, None)
            .map(|f| (f.stats, Some(f)))
            .map_err(|e| format!("GPU: {e}"))
    }

    fn keys_and_visible(&self) -> Result<(Vec<u64>, Vec<u32>)> {
        Ok((self.r.read_keys(self.ctx)?, self.r.read_visible(self.ctx)?))
    }

    fn payload(&self, slot: u32) -> Option<u64> {
        self.r.payload(slot)
    }

    fn loaded_payloads(&self) -> Vec<u64> {
        self.r.loaded_payloads()
    }

    fn frame_state(&self) -> ProgressiveFrame {
        *self.r.frame_state()
    }

    fn growths(&self) -> u32 {
        self.r.growths()
    }

    fn depth_ties(&mut self) -> Result<Option<u64>> {
        self.r.depth_ties(self.ctx).map_err(|e| anyhow!("GPU: {e}"))
    }

    fn backend_json(&self) -> serde_json::Value {
        let (ctx, r) = (self.ctx, &self.r);
        let ad = ctx.adapter();
        serde_json::json!({
            "adapter": ad.name,
            "api": ad.backend,
            "device_type": ad.device_type,
            "driver": ad.driver,
            "atomics": ctx.atomic_path().name(),
            "chunks": r.chunk_count(),
            "gpu_bytes": r.gpu_bytes(),
            // How pass times and the adaptive budget were measured: "gpu-timestamps" or "host-clock".
            "timing": r.timing().name(),
            "timestamps": r.timing() == mortar_render::BudgetTiming::GpuTimestamps,
        })
    }
}

/// One frame with what happened before it.
struct FrameRecord {
    stats: FrameStats,
    /// The GPU renderer's account of the frame (timing source, GPU pass times).
    gpu: Option<GpuProgressiveFrame>,
    /// Time taking the decoded pieces into the shuffled buffer, ms.
    distribute_ms: f64,
    /// End of the frame, ms since the start.
    at_ms: f64,
}

/// What the render loop produced.
struct Outcome {
    /// The camera every frame was drawn with.
    camera: Camera,
    frames: Vec<FrameRecord>,
    colors: ColorStats,
    /// When every point was in the buffer, ms since the start.
    loaded_ms: Option<f64>,
    /// When the first frame began, ms since the start.
    first_frame_ms: f64,
    decode_seconds: f64,
}

/// Takes a decoded piece into the renderer.
fn take(
    r: &mut dyn ProgressiveEngine,
    piece: mortar_io::Result<LoadedPiece>,
    colors: &mut ColorStats,
    decode_seconds: &mut f64,
    label: &str,
) -> Result<()> {
    let piece = piece?;
    colors.add(&piece);
    *decode_seconds += piece.seconds;
    r.insert(&piece).map_err(|e| anyhow!("{label}: {e}"))
}

/// Draws frames until `frames` says stop, taking pieces from `rx` as they arrive; the camera is
/// made by `camera` once the first frame's points are in (after all of them with `preload`).
#[allow(clippy::too_many_arguments)]
fn render_loop(
    r: &mut dyn ProgressiveEngine,
    rx: Receiver<mortar_io::Result<LoadedPiece>>,
    frames: Frames,
    preload: bool,
    pace: Option<f64>,
    camera: impl FnOnce(&dyn ProgressiveEngine) -> Result<Camera>,
    options: &RasterOptions,
    budget: &FillBudget,
    start: Instant,
    label: &str,
) -> Result<Outcome> {
    let mut colors = ColorStats::default();
    let mut decode_seconds = 0.0;
    let mut open = true;
    if preload {
        for piece in rx.iter() {
            take(r, piece, &mut colors, &mut decode_seconds, label)?;
        }
        open = false;
    }
    let camera = camera(&*r)?;
    let mut out = Outcome {
        camera,
        frames: Vec::new(),
        colors,
        loaded_ms: None,
        first_frame_ms: 0.0,
        decode_seconds,
    };
    loop {
        let t = Instant::now();
        // The first frame waits for the first points, so that it shows something.
        if r.loaded() == 0 && open {
            match rx.recv() {
                Ok(piece) => take(r, piece, &mut out.colors, &mut out.decode_seconds, label)?,
                Err(_) => open = false,
            }
        }
        while open {
            match rx.try_recv() {
                Ok(piece) => take(r, piece, &mut out.colors, &mut out.decode_seconds, label)?,
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => open = false,
            }
        }
        if !open && r.loaded() < r.capacity() {
            bail!("{label}: only {} of {} points could be read", r.loaded(), r.capacity());
        }
        let distribute_ms = ms(t);
        if out.loaded_ms.is_none() && r.loaded() == r.capacity() {
            out.loaded_ms = Some(ms(start));
        }
        if out.frames.is_empty() {
            out.first_frame_ms = ms(start);
        }
        let (stats, gpu) =
            r.frame(&out.camera, options, budget).map_err(|e| anyhow!("{label}: {e}"))?;
        out.frames.push(FrameRecord { stats, gpu, distribute_ms, at_ms: ms(start) });
        let done = match frames {
            Frames::Count(n) => stats.frame >= n,
            Frames::Converge => stats.converged,
        };
        if done {
            return Ok(out);
        }
        if let Some(period) = pace {
            let left = period - ms(t);
            if left > 0.0 {
                std::thread::sleep(std::time::Duration::from_secs_f64(left * 1e-3));
            }
        }
    }
}

/// `mortar render --progressive`: checks the options and inputs, loads and draws, writes the PNG
/// and (with `--json`) the statistics.
pub fn run(a: &Args) -> Result<()> {
    let p = &a.progressive;
    let frames = parse_frames(p.progressive.as_deref().unwrap_or_default())?;
    let budget = parse_budget(p)?;
    if p.load_threads == Some(0) {
        bail!("--load-threads 0: at least one thread must decode the input");
    }
    let paths = mortar_io::inputs::expand(&a.inputs)?;
    for path in &paths {
        let what = match InputKind::of(path) {
            InputKind::Store => "an octree store",
            InputKind::BatchFile => "a batch file",
            InputKind::Stdin | InputKind::Las => continue,
        };
        bail!("{}: --progressive draws raw LAS/LAZ (paper 000), and this is {what}; draw it without --progressive", path.display());
    }
    let mut ds = mortar_io::inputs::open_with(&paths, &a.sort.crs.options())?;
    common::print_warnings(&ds.warnings);
    let keep = a.view.color.attributes(&ds.layout);
    ds.decode_only(&keep);
    let label = paths.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" ");
    let points = point_count(&ds);
    if points == 0 {
        bail!("{label}: no points to draw");
    }
    let first_path = ds.inputs[0].path().to_path_buf();
    let payload = payload_for(&ds.layout, a.view.color, &first_path)?;
    // The one framing rule: the headers' box, or (when the first piece lies far outside it)
    // the points' box, which needs every point before the first frame.
    let view = mortar_io::framing::view_box(&ds)?;
    let (frame, preload) = match view {
        ViewBox::Header(h) => (ProgressiveFrame::around(ds.grid, h), p.preload),
        ViewBox::Points => {
            common::warn(&format!("{label}: the header's bounds do not hold the first points; reading every point before the first frame to frame them"));
            let first = IntBox::of(&mortar_io::framing::first_points(&ds)?)
                .ok_or_else(|| anyhow!("{label}: the first piece holds no point"))?;
            (ProgressiveFrame::around(ds.grid, first), true)
        }
    };
    let frame = frame.map_err(|e| anyhow!("{label}: {e}"))?;
    let (width, height, grid) = (a.view.width, a.view.height, ds.grid);
    let make_camera = |r: &dyn ProgressiveEngine| -> Result<Camera> {
        let bounds = view.bounds(&grid, || r.frame_state().data);
        build_camera(&a.view.camera, &bounds, width, height).map_err(|e| anyhow!("{label}: {e:#}"))
    };
    // Checked before anything is loaded.
    build_camera(&a.view.camera, &frame.data.world(&grid), width, height)
        .map_err(|e| anyhow!("{label}: {e:#}"))?;
    let options = RasterOptions { precision: a.view.precision.mode(), cull: !a.no_cull };
    // `auto` takes a hardware GPU only if it has the 64-bit atomics the GPU renderer needs.
    let gpu = match gpu_context(a)? {
        Some(ctx) if a.backend == Backend::Auto && ctx.atomic_path() != AtomicPath::U64 => None,
        ctx => ctx,
    };
    let mut renderer: Box<dyn ProgressiveEngine> = match &gpu {
        None => Box::new(
            ProgressiveRenderer::with_frame(frame, points).map_err(|e| anyhow!("{label}: {e}"))?,
        ),
        Some(ctx) => {
            let options = ProgressiveOptions { payloads: true, ..ProgressiveOptions::default() };
            let r = GpuProgressive::with_frame(ctx, frame, points, options)
                .map_err(|e| anyhow!("{label}: --backend {}: {e}", backend_name(a.backend)))?;
            Box::new(OnGpu { ctx, r })
        }
    };
    let threads = p
        .load_threads
        .unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1));

    let start = Instant::now();
    let cancel = AtomicBool::new(false);
    let (tx, rx) = sync_channel::<mortar_io::Result<LoadedPiece>>(4 * threads);
    let outcome = std::thread::scope(|s| -> Result<Outcome> {
        let ds = &ds;
        let cancel = &cancel;
        let loader = s.spawn(move || {
            load_pieces(ds, payload, threads, cancel, move |piece| tx.send(piece).is_ok())
        });
        let result = render_loop(
            &mut *renderer,
            rx,
            frames,
            preload,
            frame_period(p),
            make_camera,
            &options,
            &budget,
            start,
            &label,
        );
        // The receiver is gone: the loader's next delivery fails and it stops.
        cancel.store(true, std::sync::atomic::Ordering::Relaxed);
        let loaded = loader.join().map_err(|_| anyhow!("{label}: a loader thread panicked"))?;
        let out = result?;
        loaded?;
        Ok(out)
    })?;

    // Resolve the last frame: colours of the visible points only, as `mortar render` does, scalar
    // modes over the range of every point loaded (all of them once loaded: the rule of every
    // renderer, view-independent).
    let camera = outcome.camera;
    let t = Instant::now();
    let state = renderer.frame_state();
    if let ViewBox::Header(h) = view {
        if renderer.loaded() == renderer.capacity() {
            super::output::warn_outside_header(&label, &h, &state.data, &ds.grid);
        }
    }
    let loaded_all = renderer.loaded() == renderer.capacity();
    if loaded_all
        && a.view.color == ColorChoice::Mode(ColorMode::Rgb)
        && outcome.colors.max_rgb == 0
    {
        bail!("{}: --color rgb: the points have no colour (every RGB value is zero, point format {}); try --color intensity", first_path.display(), ds.layout.format);
    }
    let (keys, slots) = renderer.keys_and_visible().map_err(|e| anyhow!("{label}: GPU: {e}"))?;
    let payloads: Vec<u64> =
        slots.iter().map(|&s| renderer.payload(s).expect("visible points are loaded")).collect();
    let range = a.view.range.or_else(|| {
        payload_range(&renderer.loaded_payloads(), a.view.color, payload, &outcome.colors, &ds.grid)
    });
    let (colors, color_range) =
        payload_colors(&payloads, a.view.color, payload, &outcome.colors, &ds.grid, range);
    let resolve_options = ResolveOptions {
        background: a.view.background,
        hole_fill: a.view.hole_fill.map(|n| HoleFill { min_neighbors: n }),
        eye_dome: a.view.edl.map(|strength| EyeDome { strength, ..EyeDome::default() }),
    };
    let bg = a.view.background;
    let color_of = |i: u32| slots.binary_search(&i).map(|k| colors[k]).unwrap_or(bg);
    let rgba = resolve(&keys, camera.width, camera.height, color_of, &resolve_options);
    let resolve_seconds = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let png = encode_png(camera.width, camera.height, &rgba)?;
    write_atomic(&a.output, &png)?;
    let png_seconds = t.elapsed().as_secs_f64();

    let last = outcome.frames.last().map(|f| f.stats).unwrap_or_default();
    if !a.json {
        if !last.converged {
            common::warn(&format!(
                "{label}: the image is not final after {} frames ({} of {} points loaded); --progressive converge draws until it is",
                last.frame,
                renderer.loaded(),
                renderer.capacity()
            ));
        }
        return Ok(());
    }
    let converged_at = outcome.frames.iter().find(|f| f.stats.converged);
    // Where the converged image may show another point than a renderer that numbers the points
    // otherwise (the batch rasterizer: Morton order): pixels whose winner ties in depth.
    let t = Instant::now();
    let depth_ties = if last.converged {
        renderer.depth_ties().map_err(|e| anyhow!("{label}: {e:#}"))?
    } else {
        None
    };
    let ties_seconds = t.elapsed().as_secs_f64();
    let gpu_json = renderer.backend_json();
    let budget_json = match budget {
        FillBudget::Fixed(b) => {
            serde_json::json!({ "fixed": b, "frames_to_converge": renderer.capacity().div_ceil(b) })
        }
        FillBudget::Adaptive(a) => {
            serde_json::json!({ "auto": { "target_ms": a.target_ms, "probe": a.probe_points, "usable": a.usable } })
        }
    };
    let filled: Vec<f64> = outcome.frames.iter().map(|f| f.stats.filled as f64).collect();
    let loaded_frames: Vec<&FrameRecord> =
        outcome.frames.iter().filter(|f| f.stats.loaded == renderer.capacity()).collect();
    let frame_json: Vec<serde_json::Value> = outcome
        .frames
        .iter()
        .map(|f| {
            let s = &f.stats;
            serde_json::json!({
                "frame": s.frame,
                "loaded": s.loaded,
                "reprojected": s.reprojected,
                "filled": s.filled,
                "fill_points": s.fill_points,
                "probe": s.probe,
                "visible": s.visible,
                "points_drawn": s.raster.points_drawn,
                "distribute_ms": f.distribute_ms,
                "reproject_ms": s.reproject_ms,
                "fill_ms": s.fill_ms,
                "prepare_ms": s.prepare_ms,
                "frame_ms": s.total_ms,
                "gpu_frame_ms": f.gpu.and_then(|g| g.gpu).map(|g| g.frame_ms),
                "at_ms": f.at_ms,
                "converged": s.converged,
            })
        })
        .collect();
    let j = serde_json::json!({
        "input": label,
        "output": a.output,
        "width": camera.width,
        "height": camera.height,
        "backend": if gpu.is_some() { "gpu" } else { "cpu" },
        "gpu": gpu_json,
        "renderer": "progressive",
        "precision": a.view.precision.name(),
        "cull": !a.no_cull,
        "color": resolve_choice(a.view.color, payload, &outcome.colors).name(),
        "color_range": color_range,
        "camera": camera_json(&camera),
        "points": renderer.capacity(),
        "loaded": renderer.loaded(),
        // The framing rule's choice: the headers' box, or the points' (read before the first frame).
        "framing": match view { ViewBox::Header(_) => "header", ViewBox::Points => "points" },
        // Times the quantization frame grew for points outside it (a header that lies).
        "frame_growths": renderer.growths(),
        "shuffle": { "prime": renderer.shuffle().prime(), "unshuffled": renderer.shuffle().unshuffled() },
        "load_threads": threads,
        "preload": p.preload,
        "pace_ms": frame_period(p),
        "budget": budget_json,
        "frames_drawn": outcome.frames.len(),
        "converged": last.converged,
        "convergence_frame": converged_at.map(|f| f.stats.frame),
        "convergence_seconds": converged_at.map(|f| f.at_ms * 1e-3),
        "convergence_render_seconds": converged_at.map(|f| (f.at_ms - outcome.first_frame_ms) * 1e-3),
        "load_seconds": outcome.loaded_ms.map(|v| v * 1e-3),
        "decode_cpu_seconds": outcome.decode_seconds,
        "first_frame_seconds": outcome.first_frame_ms * 1e-3,
        "filled_median": median(&filled),
        "filled_max": filled.iter().copied().fold(0.0, f64::max),
        "frame_ms_median": median(&outcome.frames.iter().map(|f| f.stats.total_ms).collect::<Vec<f64>>()),
        "frame_ms_max": outcome.frames.iter().map(|f| f.stats.total_ms).fold(0.0, f64::max),
        "loaded_frames": {
            "count": loaded_frames.len(),
            "filled_median": median(&loaded_frames.iter().map(|f| f.stats.filled as f64).collect::<Vec<f64>>()),
            "frame_ms_median": median(&loaded_frames.iter().map(|f| f.stats.total_ms).collect::<Vec<f64>>()),
            "reproject_ms_median": median(&loaded_frames.iter().map(|f| f.stats.reproject_ms).collect::<Vec<f64>>()),
            "fill_ms_median": median(&loaded_frames.iter().map(|f| f.stats.fill_ms).collect::<Vec<f64>>()),
            "prepare_ms_median": median(&loaded_frames.iter().map(|f| f.stats.prepare_ms).collect::<Vec<f64>>()),
        },
        "pixels_covered": last.visible,
        "depth_ties": depth_ties,
        "ties_seconds": ties_seconds,
        "resolve_seconds": resolve_seconds,
        "png_seconds": png_seconds,
        "frames": frame_json,
    });
    super::output::print_json(a, &j)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_and_budgets_parse() {
        assert_eq!(parse_frames("12").unwrap(), Frames::Count(12));
        assert_eq!(parse_frames("converge").unwrap(), Frames::Converge);
        assert!(
            parse_frames("0").is_err() && parse_frames("-3").is_err() && parse_frames("x").is_err()
        );
        let args = |b: Option<&str>| ProgressiveArgs {
            budget: b.map(String::from),
            ..ProgressiveArgs::default()
        };
        assert_eq!(parse_budget(&args(None)).unwrap(), FillBudget::Fixed(DEFAULT_BUDGET));
        assert_eq!(parse_budget(&args(Some("5000"))).unwrap(), FillBudget::Fixed(5000));
        assert!(parse_budget(&args(Some("0")))
            .unwrap_err()
            .to_string()
            .contains("at least one point"));
        assert!(parse_budget(&args(Some("lots"))).is_err());
        let auto =
            ProgressiveArgs { target_ms: Some(8.0), probe: Some(1000), ..args(Some("auto")) };
        assert_eq!(
            parse_budget(&auto).unwrap(),
            FillBudget::Adaptive(AdaptiveBudget {
                target_ms: 8.0,
                probe_points: 1000,
                ..AdaptiveBudget::default()
            })
        );
        assert!(parse_budget(&ProgressiveArgs { target_ms: Some(-1.0), ..auto.clone() }).is_err());
        assert!(
            parse_budget(&ProgressiveArgs { target_ms: Some(8.0), ..args(Some("10")) }).is_err()
        );
        // --pace takes --target-ms as its frame period, with any budget.
        let paced = ProgressiveArgs { target_ms: Some(40.0), pace: true, ..args(Some("10")) };
        assert_eq!(parse_budget(&paced).unwrap(), FillBudget::Fixed(10));
        assert_eq!(frame_period(&paced), Some(40.0));
        assert_eq!(frame_period(&args(None)), None);
        assert_eq!(frame_period(&ProgressiveArgs { pace: true, ..args(None) }), Some(16.6));
    }
}
