//! The window: the winit event loop ([`Wake`] is what wakes it from another thread), orbit, pan
//! and zoom input, frames drawn by the GPU rasterizer onto the surface or by the CPU one through
//! softbuffer, the status line, the screenshot of `--screenshot`.

use super::args::*;
use super::build_state::*;
use super::content::*;
use super::overlay::*;
use crate::render::{build_camera, encode_png, write_atomic, AtomicsArg};
use anyhow::{anyhow, bail, Context as _, Result};
use mortar_core::render::{Aabb, Orbit, RasterOptions};
use mortar_render::{
    AtomicPath, GpuContext, GpuError, GpuOptions, GpuRasterizer, Overlay, Presented, WindowSurface,
};
use std::num::NonZeroU32;
use std::sync::Arc;
use std::time::Instant;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, KeyEvent, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{Key, NamedKey};
use winit::window::{Window, WindowId};

/// What wakes the event loop from another thread (the preview's build).
#[derive(Clone, Copy, Debug)]
pub enum Wake {
    /// The build reported progress (maybe a commit).
    Progress,
    /// The build ended: whether it succeeded.
    Done(bool),
}

/// The event loop, or an error that says there is no display.
pub(super) fn event_loop() -> Result<EventLoop<Wake>> {
    let event_loop = EventLoop::<Wake>::with_user_event().build().map_err(|e| anyhow!("cannot open a window: {e} (no display? set DISPLAY or WAYLAND_DISPLAY, or use `mortar render`)"))?;
    event_loop.set_control_flow(ControlFlow::Wait);
    Ok(event_loop)
}

/// What a window saw.
pub(super) struct Shown {
    /// Statistics of the frames drawn.
    pub(super) frames: serde_json::Value,
    /// For a preview: whether the build ended while the window was open.
    pub(super) build_done: bool,
}

/// Runs the window on `content` until it closes.
pub(super) fn show<'a>(
    a: &'a Args,
    event_loop: EventLoop<Wake>,
    content: Box<dyn Content + 'a>,
    label: String,
    build: Option<BuildState>,
) -> Result<Shown> {
    let bounds = content.bounds();
    let camera = build_camera(&a.view.camera, &bounds, a.view.width, a.view.height)
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
        "lod_source": app.content.report(),
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&j)?);
    }
    Ok(Shown { frames: j, build_done: app.build.is_none_or(|b| b.done || b.failed) })
}

/// Mouse state.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Drag {
    left: bool,
    right: bool,
    shift: bool,
    cursor: Option<(f64, f64)>,
}

/// Times and counts of one frame.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct FrameStats {
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
pub(super) struct Gpu {
    ctx: GpuContext,
    surface: WindowSurface,
    raster: GpuRasterizer,
}

/// What draws the frames.
pub(super) enum Renderer {
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

pub(super) struct App<'a> {
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
        self.args.view.camera.fov.to_radians()
    }

    /// Opens the window and what draws into it.
    fn open(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let attrs = Window::default_attributes()
            .with_title(format!("mortar view: {}", self.label))
            .with_inner_size(PhysicalSize::new(self.args.view.width, self.args.view.height));
        let window = Arc::new(event_loop.create_window(attrs).context("cannot open a window")?);
        self.window = Some(window.clone());
        let size = window.inner_size();
        let (w, h) = (size.width.max(1), size.height.max(1));
        let atomics = match self.args.view.atomics {
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
            .camera(self.fov(), self.args.view.camera.ortho, &self.bounds, w, h)
            .map_err(|e| anyhow!("{}: {e:#}", self.label))?;
        let options = RasterOptions { precision: self.args.view.precision.mode(), cull: true };
        let status = self.status();
        let overlay = (!self.args.no_status).then(|| status_overlay(&status, w));
        let resolve = self.args.view.resolve_options();
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
                self.args.view.camera.ortho,
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
                        // A preview's screenshot shows the finished store, whole.
                        Some(b) => b.final_loaded && !self.busy(),
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
                    Ok(_) if shooting && self.build.as_ref().is_none_or(|b| b.final_loaded) => {
                        self.redraw()
                    }
                    // Progressive frames go on until the image is final.
                    Ok(_) if self.busy() => self.redraw(),
                    Ok(_) => {}
                }
            }
            _ => {}
        }
    }
}
