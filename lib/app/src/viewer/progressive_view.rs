//! Raw LAS/LAZ in `mortar view`: the progressive renderer of paper 000, no preprocessing.
//!
//! The window opens at once; loader threads decode the files in parallel and hand over pieces as
//! they are ready (§3.2); every frame takes the pieces that arrived into the shuffled buffer
//! (the incremental shuffle of eq. 1-2), then draws Reproject, Fill with the adaptive budget of
//! §3.4.1 and Prepare ([`ProgressiveRenderer::frame`]). Frames are drawn back to back while the
//! image is not final (points still loading, or fewer frames than slots over budget since the
//! camera last moved), and on input only once it is.
//!
//! Colours: each point carries one 64-bit payload, the raw attribute its colour mode needs
//! ([`Payload`]), turned into colours for the visible points only. Switching to a mode that
//! needs another attribute is streamed batch by batch (§3.5): new loaders read the attribute
//! again and replace the payloads piece by piece while frames go on, the points already switched
//! drawn in the new mode and the others in the old one until every piece has arrived.
//!
//! On the GPU ([`GpuProgressive`], the window's GPU path) the points are inserted with their
//! colour (computed from the payload when the piece arrives) and the image is resolved on the
//! GPU and presented without a read-back. The colour rules are then fixed by the first piece
//! that arrives: the 8/16-bit RGB decision and the scalar modes' range (`--range`, else the 1st
//! to 99th percentile of that piece's values) instead of the visible points' of each frame. A
//! colour switch is streamed there too: loaders read the new mode's attribute again and each
//! piece's new colours are written into the shuffled buffer by slot
//! ([`GpuProgressive::recolor`], the scatter pass writing colours only); points not switched yet
//! keep their colour.

use super::content::{Content, GpuDrawn};
use crate::draw::raw::{
    load_pieces, payload_colors, payload_for, payload_range, point_count, ColorStats, LoadedPiece,
    Payload,
};
use crate::draw::ColorChoice;
use anyhow::{anyhow, bail, Result};
use mortar_core::render::framing::{IntBox, ViewBox};
use mortar_core::render::progressive::ProgressiveFrame;
use mortar_core::render::progressive::{
    AdaptiveBudget, FillBudget, FrameStats, ProgressiveRenderer,
};
use mortar_core::render::resolve::{resolve, ColorMode, ResolveOptions};
use mortar_core::render::{Aabb, Camera, RasterOptions};
use mortar_io::dataset::Dataset;
use mortar_render::{
    wgpu, AtomicPath, GpuContext, GpuError, GpuProgressive, GpuRasterizer, ProgressiveOptions,
};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, TryRecvError};
use std::sync::Arc;
use std::thread::JoinHandle;

/// Loader threads delivering pieces of the dataset with one kind of payload.
struct Loader {
    /// Pieces read before the window opened (every piece, where the framing rule needs the
    /// points' box), handed over first.
    pending: Vec<LoadedPiece>,
    rx: Receiver<mortar_io::Result<LoadedPiece>>,
    cancel: Arc<AtomicBool>,
    thread: Option<JoinHandle<mortar_io::Result<()>>>,
    /// All pieces were delivered (the channel closed).
    finished: bool,
}

impl Loader {
    fn start(ds: &Arc<Dataset>, payload: Payload, threads: usize) -> Loader {
        let (tx, rx) = sync_channel(4 * threads.max(1));
        let cancel = Arc::new(AtomicBool::new(false));
        let (ds, c) = (ds.clone(), cancel.clone());
        let thread = std::thread::Builder::new()
            .name("mortar-view-load".into())
            .spawn(move || {
                load_pieces(&ds, payload, threads, &c, move |piece| tx.send(piece).is_ok())
            })
            .ok();
        Loader { pending: Vec::new(), rx, cancel, thread, finished: false }
    }

    /// Waits for every piece (kept for [`arrived`](Self::arrived)).
    fn preload(&mut self) -> Result<()> {
        while !self.finished {
            match self.rx.recv() {
                Ok(p) => self.pending.push(p?),
                Err(_) => {
                    self.finished = true;
                    if let Some(t) = self.thread.take() {
                        t.join().map_err(|_| anyhow!("a loader thread panicked"))??;
                    }
                }
            }
        }
        Ok(())
    }

    /// The pieces that arrived, without waiting.
    fn arrived(&mut self) -> Result<Vec<LoadedPiece>> {
        let mut out = std::mem::take(&mut self.pending);
        while !self.finished {
            match self.rx.try_recv() {
                Ok(p) => out.push(p?),
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => {
                    self.finished = true;
                    if let Some(t) = self.thread.take() {
                        t.join().map_err(|_| anyhow!("a loader thread panicked"))??;
                    }
                }
            }
        }
        Ok(out)
    }
}

impl Drop for Loader {
    fn drop(&mut self) {
        self.cancel.store(true, Ordering::Relaxed);
        // Unblock a loader waiting to send, then let it stop.
        while self.rx.try_recv().is_ok() {}
        if let Some(t) = self.thread.take() {
            drop(std::mem::replace(&mut self.rx, sync_channel(1).1));
            let _ = t.join();
        }
    }
}

/// A colour mode switch in progress (§3.5).
struct Switch {
    loader: Loader,
    to: usize,
    payload: Payload,
    /// Per slot, whether its payload is the new one (CPU path).
    done: Vec<u64>,
    points: u64,
    /// GPU path: the new mode's colour rules, fixed by the switch's first piece until every
    /// point switched.
    rules: Option<(ColorStats, Option<[f64; 2]>)>,
    /// GPU path, scalar modes without `--range`: every point's new payload in input order (for
    /// the range of all points once every one arrived).
    values: Vec<u64>,
}

/// The GPU renderer and its colour rules.
pub struct GpuState {
    renderer: GpuProgressive,
    /// The colour decisions: fixed by the first piece while loading, then (scalar modes without
    /// `--range`) the range of all points, with every colour rewritten if it differs.
    rules: Option<(ColorStats, Option<[f64; 2]>)>,
    /// Scalar modes without `--range`: every point's payload in input order, while loading.
    values: Vec<u64>,
    loaded: u64,
}

/// The range of scalar colours over the points holding a mode's payload, recomputed as their
/// number doubles and once they are all there (CPU path).
#[derive(Clone, Copy, Debug, Default)]
struct RangeCache {
    mode: usize,
    /// Points the range was computed over.
    count: u64,
    range: Option<[f64; 2]>,
}

/// A raw LAS/LAZ shown progressively.
pub struct ProgressiveView {
    label: String,
    first_path: PathBuf,
    ds: Arc<Dataset>,
    renderer: ProgressiveRenderer,
    /// The GPU renderer, which replaces `renderer` once [`use_gpu`](Self::use_gpu) is called.
    gpu: Option<GpuState>,
    /// The quantization frame the renderers start with.
    frame: ProgressiveFrame,
    /// Points of all inputs.
    points: u64,
    /// What framed views frame: the one framing rule (`mortar_core::render::framing`).
    bounds: Aabb,
    /// The headers' box when the rule took it (for the warning about points outside it).
    header: Option<IntBox>,
    /// Scalar ranges over all points (CPU path): the shown mode's and a switch's target's.
    ranges: [RangeCache; 2],
    threads: usize,
    loader: Option<Loader>,
    /// Colour modes offered (C cycles them) and the payload each needs.
    pub modes: Vec<ColorChoice>,
    payloads: Vec<Payload>,
    /// The mode of the payloads held (of the points not yet switched, during a switch).
    mode: usize,
    switch: Option<Switch>,
    stats: ColorStats,
    range: Option<[f64; 2]>,
    budget: FillBudget,
    /// The last frame's statistics.
    pub last: FrameStats,
}

impl ProgressiveView {
    /// Opens `paths` (raw LAS/LAZ) and starts loading them; `color` is the first colour mode.
    /// Where the framing rule needs the points' box (the headers' box misses the first piece),
    /// every point is read first.
    pub fn open(
        paths: &[PathBuf],
        color: ColorChoice,
        range: Option<[f64; 2]>,
        threads: usize,
    ) -> Result<ProgressiveView> {
        let ds = mortar_io::inputs::open(paths)?;
        crate::cli::print_warnings(&ds.warnings);
        let label = paths.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" ");
        let points = point_count(&ds);
        if points == 0 {
            bail!("{label}: no points to draw");
        }
        let first_path = ds.inputs[0].path().to_path_buf();
        let first = payload_for(&ds.layout, color, &first_path)?;
        let mut modes = vec![color];
        let mut payloads = vec![first];
        for m in ColorMode::ALL {
            let c = ColorChoice::Mode(m);
            if c == color {
                continue;
            }
            if let Ok(p) = payload_for(&ds.layout, c, &first_path) {
                modes.push(c);
                payloads.push(p);
            }
        }
        let view = mortar_io::framing::view_box(&ds)?;
        let grid = ds.grid;
        let ds = Arc::new(ds);
        let mut loader = Loader::start(&ds, first, threads);
        let (frame, bounds, header) = match view {
            ViewBox::Header(h) => (ProgressiveFrame::around(grid, h), h.world(&grid), Some(h)),
            ViewBox::Points => {
                crate::cli::warn(&format!("{label}: the header's bounds do not hold the first points; reading every point before the first frame to frame them"));
                loader.preload().map_err(|e| anyhow!("{label}: {e:#}"))?;
                let b = loader
                    .pending
                    .iter()
                    .filter_map(|p| mortar_core::render::progressive::piece_box(&p.xyz))
                    .reduce(IntBox::union)
                    .ok_or_else(|| anyhow!("{label}: no points could be read"))?;
                (ProgressiveFrame::around(grid, b), b.world(&grid), None)
            }
        };
        let frame = frame.map_err(|e| anyhow!("{label}: {e}"))?;
        let renderer =
            ProgressiveRenderer::with_frame(frame, points).map_err(|e| anyhow!("{label}: {e}"))?;
        Ok(ProgressiveView {
            label,
            first_path,
            ds,
            renderer,
            gpu: None,
            frame,
            points,
            bounds,
            header,
            ranges: [RangeCache::default(); 2],
            threads,
            loader: Some(loader),
            modes,
            payloads,
            mode: 0,
            switch: None,
            stats: ColorStats::default(),
            range,
            budget: FillBudget::Adaptive(AdaptiveBudget::default()),
            last: FrameStats::default(),
        })
    }

    pub fn capacity(&self) -> u64 {
        self.points
    }

    pub fn loaded(&self) -> u64 {
        match &self.gpu {
            Some(g) => g.loaded,
            None => self.renderer.loaded(),
        }
    }

    /// The colour mode shown (the one being switched to, during a switch).
    pub fn shown_mode(&self) -> usize {
        self.switch.as_ref().map_or(self.mode, |s| s.to)
    }

    fn converged(&self) -> bool {
        match &self.gpu {
            Some(g) => g.renderer.converged(),
            None => self.renderer.converged(),
        }
    }

    /// Draws with the GPU progressive renderer from now on (before the first frame). Fails
    /// (and the view stays on the CPU) where the context cannot run it (32-bit atomics).
    pub fn start_gpu(&mut self, ctx: &GpuContext) -> Result<()> {
        let renderer = GpuProgressive::with_frame(
            ctx,
            self.frame,
            self.points,
            ProgressiveOptions { colors: true, ..Default::default() },
        )
        .map_err(|e| anyhow!("{}: {e}", self.label))?;
        self.gpu = Some(GpuState { renderer, rules: None, values: Vec::new(), loaded: 0 });
        // The CPU renderer's buffers are not needed any more.
        self.renderer = ProgressiveRenderer::with_frame(self.frame, 0)
            .map_err(|e| anyhow!("{}: {e}", self.label))?;
        Ok(())
    }

    /// What the status line says of the loading and switching.
    pub fn load_status(&self) -> String {
        let mut s = if self.loaded() < self.capacity() {
            format!("loading {:.0}%", 100.0 * self.loaded() as f64 / self.capacity().max(1) as f64)
        } else if self.converged() {
            "final".to_string()
        } else {
            "refining".to_string()
        };
        if let Some(w) = &self.switch {
            s += &format!(
                ", switching colours {:.0}%",
                100.0 * w.points as f64 / self.capacity().max(1) as f64
            );
        }
        s += &format!(", budget {}", super::content::group_digits(self.last.filled));
        s
    }

    /// Asks for colour mode `to`: at once where the payloads held serve it, else streamed
    /// (§3.5) once loading is done; `false` when it cannot start now (loading or switching).
    /// On the GPU path (`ctx`), a switch starts the view over with the new mode's attribute.
    pub fn ask_mode(&mut self, to: usize, ctx: Option<&GpuContext>) -> Result<bool> {
        if to == self.shown_mode() {
            return Ok(true);
        }
        if self.switch.is_some() {
            return Ok(false);
        }
        if self.gpu.is_some() && ctx.is_some() {
            // The colours are in the GPU's shuffled buffer: stream the new ones in (the loaders
            // read the new mode's attribute again; `GpuProgressive::recolor` writes colours only).
            if self.loader.is_some() {
                return Ok(false);
            }
            self.switch = Some(Switch {
                loader: Loader::start(&self.ds, self.payloads[to], self.threads),
                to,
                payload: self.payloads[to],
                done: Vec::new(),
                points: 0,
                rules: None,
                values: Vec::new(),
            });
            return Ok(true);
        }
        Ok(self.switch_cpu(to))
    }

    fn switch_cpu(&mut self, to: usize) -> bool {
        if self.payloads[to] == self.payloads[self.mode] {
            self.mode = to;
            return true;
        }
        if self.loader.is_some() {
            return false;
        }
        let n = self.capacity() as usize;
        self.switch = Some(Switch {
            loader: Loader::start(&self.ds, self.payloads[to], self.threads),
            to,
            payload: self.payloads[to],
            done: vec![0; n.div_ceil(64)],
            points: 0,
            rules: None,
            values: Vec::new(),
        });
        true
    }

    /// Takes what the loader delivered since the last call into the GPU renderer, each point
    /// with its colour by the rules fixed at the first piece; once every point arrived, the rules
    /// of all points (the RGB depth and scalar range every renderer of the file uses), and where
    /// they differ from the first piece's every colour is written again.
    fn take_arrived_gpu(&mut self, ctx: &GpuContext) -> Result<()> {
        let n = self.points as usize;
        let grid = self.ds.grid;
        if let (Some(w), Some(g)) = (&mut self.switch, &mut self.gpu) {
            let (choice, payload) = (self.modes[w.to], w.payload);
            if w.values.is_empty() {
                w.values = vec![0; n];
            }
            for piece in w.loader.arrived().map_err(|e| anyhow!("{}: {e:#}", self.label))? {
                let (stats, range) = *w.rules.get_or_insert_with(|| {
                    let mut st = ColorStats::default();
                    st.add(&piece);
                    let (_, r) =
                        payload_colors(&piece.payload, choice, payload, &st, &grid, self.range);
                    (st, r)
                });
                let (colors, _) =
                    payload_colors(&piece.payload, choice, payload, &stats, &grid, range);
                g.renderer
                    .recolor(ctx, piece.first, &colors)
                    .map_err(|e| anyhow!("{}: GPU: {e}", self.label))?;
                let f = piece.first as usize;
                w.values[f..f + piece.payload.len()].copy_from_slice(&piece.payload);
                w.points += piece.payload.len() as u64;
            }
            if w.loader.finished {
                if w.points < self.points {
                    bail!(
                        "{}: only {} of {} points could be read again for the new colours",
                        self.label,
                        w.points,
                        self.points
                    );
                }
                g.rules = Some(
                    final_rules(
                        ctx,
                        &mut g.renderer,
                        w.rules,
                        self.stats,
                        &w.values,
                        choice,
                        payload,
                        &grid,
                        self.range,
                    )
                    .map_err(|e| anyhow!("{}: GPU: {e}", self.label))?,
                );
                self.mode = w.to;
                self.switch = None;
            }
        }
        let (Some(l), Some(g)) = (&mut self.loader, &mut self.gpu) else { return Ok(()) };
        let (choice, payload) = (self.modes[self.mode], self.payloads[self.mode]);
        if g.values.is_empty() {
            g.values = vec![0; n];
        }
        for piece in l.arrived().map_err(|e| anyhow!("{}: {e:#}", self.label))? {
            self.stats.add(&piece);
            let (stats, range) = *g.rules.get_or_insert_with(|| {
                let (_, r) =
                    payload_colors(&piece.payload, choice, payload, &self.stats, &grid, self.range);
                (self.stats, r)
            });
            let (colors, _) = payload_colors(&piece.payload, choice, payload, &stats, &grid, range);
            g.renderer
                .insert(ctx, piece.first, &piece.xyz, Some(&colors), None)
                .map_err(|e| anyhow!("{}: {e}", self.label))?;
            let f = piece.first as usize;
            g.values[f..f + piece.payload.len()].copy_from_slice(&piece.payload);
            g.loaded += piece.xyz.len() as u64;
        }
        if l.finished {
            self.loader = None;
            if g.loaded < self.points {
                bail!("{}: only {} of {} points could be read", self.label, g.loaded, self.points);
            }
            let values = std::mem::take(&mut g.values);
            g.rules = Some(
                final_rules(
                    ctx,
                    &mut g.renderer,
                    g.rules,
                    self.stats,
                    &values,
                    choice,
                    payload,
                    &grid,
                    self.range,
                )
                .map_err(|e| anyhow!("{}: GPU: {e}", self.label))?,
            );
            if let Some(h) = self.header {
                crate::render::warn_outside_header(
                    &self.label,
                    &h,
                    &g.renderer.frame_state().data,
                    &grid,
                );
            }
        }
        Ok(())
    }

    /// Draws one progressive frame with the GPU renderer, resolved on the GPU into its image
    /// buffer (for the window's present pass): the image buffer and the frame's statistics.
    pub fn frame_gpu(
        &mut self,
        ctx: &GpuContext,
        camera: &Camera,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> Result<mortar_render::GpuProgressiveFrame> {
        self.take_arrived_gpu(ctx)?;
        let g = self.gpu.as_mut().ok_or_else(|| anyhow!("the view is not on the GPU"))?;
        let f = g
            .renderer
            .frame(ctx, camera, options, &self.budget, Some(resolve))
            .map_err(|e| anyhow!("{}: GPU: {e}", self.label))?;
        self.last = f.stats;
        Ok(f)
    }

    /// The GPU renderer's resolved image (after [`frame_gpu`](Self::frame_gpu)).
    pub fn image_buffer(&self) -> Option<&mortar_render::wgpu::Buffer> {
        self.gpu.as_ref().and_then(|g| g.renderer.image_buffer())
    }

    /// Takes what the loaders delivered since the last call.
    fn take_arrived(&mut self) -> Result<()> {
        if let Some(l) = &mut self.loader {
            for piece in l.arrived().map_err(|e| anyhow!("{}: {e:#}", self.label))? {
                self.stats.add(&piece);
                self.renderer
                    .insert(piece.first, &piece.xyz, &piece.payload)
                    .map_err(|e| anyhow!("{}: {e}", self.label))?;
            }
            if l.finished {
                self.loader = None;
                if self.loaded() < self.capacity() {
                    bail!(
                        "{}: only {} of {} points could be read",
                        self.label,
                        self.loaded(),
                        self.capacity()
                    );
                }
                if let Some(h) = self.header {
                    crate::render::warn_outside_header(
                        &self.label,
                        &h,
                        &self.renderer.frame_state().data,
                        &self.ds.grid,
                    );
                }
            }
        }
        let capacity = self.capacity();
        if let Some(w) = &mut self.switch {
            for piece in w.loader.arrived().map_err(|e| anyhow!("{}: {e:#}", self.label))? {
                self.stats.add(&piece);
                self.renderer
                    .replace_payloads(piece.first, &piece.payload)
                    .map_err(|e| anyhow!("{}: {e}", self.label))?;
                let shuffle = *self.renderer.shuffle();
                for i in 0..piece.payload.len() as u64 {
                    let s = shuffle.target((piece.first + i) as u32) as usize;
                    w.done[s / 64] |= 1 << (s % 64);
                }
                w.points += piece.payload.len() as u64;
            }
            if w.loader.finished {
                if w.points < capacity {
                    bail!(
                        "{}: only {} of {capacity} points could be read again for the new colours",
                        self.label,
                        w.points
                    );
                }
                self.mode = w.to;
                self.switch = None;
                self.ranges[0] = self.ranges[1];
            }
        }
        Ok(())
    }

    /// The range of scalar colours in mode `mode` over the `held` points holding its payload
    /// (`values()` gives theirs), cached in `self.ranges[k]` and computed again when their number
    /// doubled or they are all there: `--range`, else the range of every point once all of them
    /// are in, the rule of every renderer.
    fn range_of(
        &mut self,
        k: usize,
        mode: usize,
        held: u64,
        values: impl FnOnce(&Self) -> Vec<u64>,
    ) -> Option<[f64; 2]> {
        if self.range.is_some() {
            return self.range;
        }
        let c = self.ranges[k];
        let all = self.capacity();
        let stale = c.mode != mode
            || c.count == 0
            || held >= 2 * c.count
            || (held == all && c.count != all);
        if stale && held > 0 {
            let v = values(self);
            let range = payload_range(
                &v,
                self.modes[mode],
                self.payloads_of(mode),
                &self.stats,
                &self.ds.grid,
            );
            self.ranges[k] = RangeCache { mode, count: held, range };
        }
        self.ranges[k].range
    }

    /// The payload kind of mode `mode` (a switch's target may use another than the list's).
    fn payloads_of(&self, mode: usize) -> Payload {
        self.payloads[mode]
    }

    /// Draws one progressive frame with the CPU renderer and resolves it (hole filling and
    /// eye-dome lighting as `resolve` asks, like every renderer): the RGBA8 image.
    pub fn frame_cpu(
        &mut self,
        camera: &Camera,
        options: &RasterOptions,
        resolve_options: &ResolveOptions,
    ) -> Result<Vec<u32>> {
        let background = resolve_options.background;
        self.take_arrived()?;
        self.last = self
            .renderer
            .frame(camera, options, &self.budget)
            .map_err(|e| anyhow!("{}: {e}", self.label))?;
        let keys = self.renderer.keys();
        let mut slots = self.renderer.visible();
        slots.sort_unstable();
        let colors = self.colors(&slots);
        if self.mode == 0
            && matches!(self.modes[0], ColorChoice::Mode(ColorMode::Rgb))
            && self.loader.is_none()
            && self.stats.max_rgb == 0
        {
            bail!("{}: --color rgb: the points have no colour (every RGB value is zero); try --color intensity", self.first_path.display());
        }
        let color_of = |i: u32| slots.binary_search(&i).map(|k| colors[k]).unwrap_or(background);
        Ok(resolve(&keys, camera.width, camera.height, color_of, resolve_options))
    }

    /// The colours of the visible `slots` (sorted): each in the mode its payload holds, scalar
    /// modes over the range of all points holding that mode's payload.
    fn colors(&mut self, slots: &[u32]) -> Vec<u32> {
        let grid = self.ds.grid;
        let Some((to, to_payload, switched_points)) =
            self.switch.as_ref().map(|w| (w.to, w.payload, w.points))
        else {
            let range = self
                .range_of(0, self.mode, self.renderer.loaded(), |v| v.renderer.loaded_payloads());
            let payloads: Vec<u64> = slots
                .iter()
                .map(|&s| self.renderer.payload(s).expect("visible points are loaded"))
                .collect();
            return payload_colors(
                &payloads,
                self.modes[self.mode],
                self.payloads[self.mode],
                &self.stats,
                &grid,
                range,
            )
            .0;
        };
        let switched = |w: &Switch, s: u32| w.done[s as usize / 64] >> (s % 64) & 1 == 1;
        let new_range = self.range_of(1, to, switched_points, |v| {
            let w = v.switch.as_ref().expect("a switch");
            (0..v.capacity() as u32)
                .filter(|&s| switched(w, s))
                .filter_map(|s| v.renderer.payload(s))
                .collect()
        });
        let old_range = if self.ranges[0].mode == self.mode { self.ranges[0].range } else { None }
            .or(self.range);
        let w = self.switch.as_ref().expect("a switch");
        let (new, old): (Vec<usize>, Vec<usize>) =
            (0..slots.len()).partition(|&k| switched(w, slots[k]));
        let mut out = vec![0u32; slots.len()];
        for (ks, mode, payload, range) in [
            (&new, to, to_payload, new_range),
            (&old, self.mode, self.payloads[self.mode], old_range),
        ] {
            let payloads: Vec<u64> = ks
                .iter()
                .map(|&k| self.renderer.payload(slots[k]).expect("visible points are loaded"))
                .collect();
            let c =
                payload_colors(&payloads, self.modes[mode], payload, &self.stats, &grid, range).0;
            for (&k, c) in ks.iter().zip(c) {
                out[k] = c;
            }
        }
        out
    }
}

/// The colour rules of all points for `choice`: the dataset's statistics `stats` and the range of
/// all points (`values`: every point's payload in input order), or `range`. Where they differ
/// from `provisional` (the first piece's), every point's colour is written again.
#[allow(clippy::too_many_arguments)]
fn final_rules(
    ctx: &GpuContext,
    r: &mut GpuProgressive,
    provisional: Option<(ColorStats, Option<[f64; 2]>)>,
    stats: ColorStats,
    values: &[u64],
    choice: ColorChoice,
    payload: Payload,
    grid: &mortar_core::grid::Grid,
    range: Option<[f64; 2]>,
) -> Result<(ColorStats, Option<[f64; 2]>), mortar_render::ProgressiveGpuError> {
    let rules = (stats, range.or_else(|| payload_range(values, choice, payload, &stats, grid)));
    if provisional != Some(rules) {
        let (colors, _) = payload_colors(values, choice, payload, &rules.0, grid, rules.1);
        r.recolor(ctx, 0, &colors)?;
    }
    Ok(rules)
}

impl Content for ProgressiveView {
    fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// The points the header declares, all of which are loading.
    fn points(&self) -> u64 {
        self.capacity()
    }

    fn modes(&self) -> &[ColorChoice] {
        &self.modes
    }

    fn mode(&self) -> usize {
        self.shown_mode()
    }

    /// See [`ask_mode`](ProgressiveView::ask_mode): a switch is streamed, not while loading.
    fn set_mode(&mut self, to: usize, gpu: Option<&GpuContext>) -> Result<bool> {
        self.ask_mode(to, gpu)
    }

    fn status(&self) -> Vec<String> {
        vec![
            format!(
                "{} of {} points",
                super::content::group_digits(self.loaded()),
                super::content::group_digits(self.capacity())
            ),
            self.load_status(),
        ]
    }

    /// Points are loading, a colour switch is streaming, or the image has not converged.
    fn busy(&self) -> bool {
        self.loader.is_some() || self.switch.is_some() || !self.converged()
    }

    fn gpu_unsupported(&self, ctx: &GpuContext) -> Option<&'static str> {
        (ctx.atomic_path() != AtomicPath::U64)
            .then_some("the GPU progressive renderer needs 64-bit atomics")
    }

    fn use_gpu(&mut self, ctx: &GpuContext) -> Result<(), GpuError> {
        self.start_gpu(ctx).map_err(|e| GpuError::Device(format!("{e:#}")))
    }

    /// Resolved with hole filling and eye-dome lighting as `resolve` asks (the GPU path's bytes).
    fn draw_cpu(
        &mut self,
        camera: &Camera,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> Result<(Vec<u32>, u64)> {
        let rgba = self.frame_cpu(camera, options, resolve)?;
        Ok((rgba, self.last.raster.points_drawn))
    }

    /// Resolved on the GPU into the progressive renderer's own image buffer, with hole filling
    /// and eye-dome lighting as `resolve` asks ([`draw_cpu`](Content::draw_cpu)'s bytes).
    fn draw_gpu(
        &mut self,
        ctx: &GpuContext,
        _raster: &mut GpuRasterizer,
        camera: &Camera,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> Result<GpuDrawn> {
        let f = self.frame_gpu(ctx, camera, options, resolve)?;
        Ok(GpuDrawn {
            points_drawn: f.stats.raster.points_drawn,
            draw_ms: f.gpu.map(|t| t.reproject_ms + t.probe_ms + t.extra_fill_ms + t.prepare_ms),
            resolve_ms: f.gpu.and_then(|t| t.resolve_ms),
            own_image: true,
        })
    }

    fn image(&self) -> Option<&wgpu::Buffer> {
        self.image_buffer()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mortar_core::render::Projection;

    fn sample() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/autzen_trim.laz")
    }

    /// Frames until the image is final; the last image.
    fn settle(v: &mut ProgressiveView, camera: &Camera) -> Vec<u32> {
        for _ in 0..10_000 {
            let img = v
                .frame_cpu(
                    camera,
                    &RasterOptions::default(),
                    &ResolveOptions { background: 0xff00_0000, ..Default::default() },
                )
                .unwrap();
            if !v.busy() {
                return img;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        panic!("the progressive view never settled");
    }

    #[test]
    fn a_colour_switch_streams_in_and_ends_as_a_fresh_view_in_that_mode() {
        let mut v = ProgressiveView::open(&[sample()], ColorChoice::Auto, None, 2).unwrap();
        let b = v.bounds();
        let c = b.center();
        let d = b.diagonal();
        let camera = Camera::look_at(
            [c[0] + d, c[1] - d, c[2] + d],
            c,
            [0.0, 0.0, 1.0],
            Projection::Perspective { fov_y: 0.8 },
            &b,
            200,
            150,
        )
        .unwrap();
        let rgb = settle(&mut v, &camera);
        let k = v
            .modes
            .iter()
            .position(|&m| m == ColorChoice::Mode(ColorMode::Classification))
            .expect("the sample has classes");
        assert!(v.set_mode(k, None).unwrap());
        assert_eq!(v.mode(), k);
        assert!(v.switch.is_some(), "classification needs another attribute: streamed");
        // No second switch while one streams.
        assert!(!v.set_mode(0, None).unwrap());
        let switched = settle(&mut v, &camera);
        assert!(v.switch.is_none() && v.mode == k);
        let mut fresh = ProgressiveView::open(
            &[sample()],
            ColorChoice::Mode(ColorMode::Classification),
            None,
            2,
        )
        .unwrap();
        let expected = settle(&mut fresh, &camera);
        assert_eq!(switched, expected);
        assert!(switched.iter().zip(&rgb).filter(|(a, b)| a != b).count() > 1000);
        // Back to the first mode: its payload is not held any more, so it streams again.
        assert!(v.set_mode(0, None).unwrap());
        assert_eq!(settle(&mut v, &camera), rgb);
    }

    /// GPU frames until the image is final; the last image.
    fn settle_gpu(v: &mut ProgressiveView, ctx: &GpuContext, camera: &Camera) -> Vec<u32> {
        for _ in 0..10_000 {
            v.frame_gpu(
                ctx,
                camera,
                &RasterOptions::default(),
                &ResolveOptions { background: 0xff00_0000, ..Default::default() },
            )
            .unwrap();
            if !v.busy() {
                return v.gpu.as_ref().unwrap().renderer.read_image(ctx).unwrap();
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        panic!("the progressive view never settled on the GPU");
    }

    #[test]
    fn on_the_gpu_a_colour_switch_is_streamed_into_the_shuffled_buffer() {
        let Some(ctx) =
            mortar_render::testing::context_or_skip(mortar_render::AtomicPath::U64, None)
        else {
            return;
        };
        let open = |c: ColorChoice| {
            let mut v = ProgressiveView::open(&[sample()], c, None, 2).unwrap();
            v.start_gpu(&ctx).unwrap();
            v
        };
        let mut v = open(ColorChoice::Auto);
        let b = v.bounds();
        let (c, d) = (b.center(), b.diagonal());
        let camera = Camera::look_at(
            [c[0] - d, c[1] - d, c[2] + d],
            c,
            [0.0, 0.0, 1.0],
            Projection::Perspective { fov_y: 0.8 },
            &b,
            200,
            150,
        )
        .unwrap();
        let first = settle_gpu(&mut v, &ctx, &camera);
        let k = v
            .modes
            .iter()
            .position(|&m| m == ColorChoice::Mode(ColorMode::Classification))
            .unwrap();
        assert!(v.set_mode(k, Some(&ctx)).unwrap());
        assert!(
            v.switch.is_some() && v.loaded() == v.capacity(),
            "a switch streams colours, it does not reload the points"
        );
        let switched = settle_gpu(&mut v, &ctx, &camera);
        assert!(v.switch.is_none() && v.mode == k);
        let mut fresh = open(ColorChoice::Mode(ColorMode::Classification));
        assert_eq!(switched, settle_gpu(&mut fresh, &ctx, &camera));
        assert!(switched.iter().zip(&first).filter(|(a, b)| a != b).count() > 1000);
    }
}
