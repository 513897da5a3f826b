//! An octree store in `mortar view` and `mortar build --preview`: each frame draws the LOD
//! selection of paper 004 §6 for the window's camera, straight from the mapped `nodes.bin`.
//!
//! - CPU: the selection's nodes are borrowed from the map and drawn by the CPU rasterizer
//!   ([`draw::lod::render`]), as `mortar render store/` does.
//! - GPU: a node is uploaded the first time a selection needs it and stays on the GPU; every frame
//!   draws the selected nodes' batches out of the one scene ([`GpuRasterizer::draw_selected`]).
//!   Uploads are keyed by the payload's offset in `nodes.bin`: the file only grows and a payload
//!   is never rewritten, so when a growing store commits again (the preview), only the nodes
//!   whose payload is new are uploaded; the replaced ones become garbage on the GPU, and the
//!   scene is rebuilt from what is selected when the garbage outweighs the live samples.
//! - Uploads are paced: a frame decodes and uploads nodes for at most [`UPLOAD_BUDGET_MS`] (and
//!   at least one node), so that a frame never waits for a whole selection (a new commit of a
//!   100 M-point build brings millions of new samples). A new commit is uploaded behind the one
//!   shown, which stays on screen until every node the new commit's selection needs is on the
//!   GPU; then the view switches to it in one frame (no holes), and opens the newest commit if
//!   more came meanwhile (a build that commits faster than its nodes upload still shows each
//!   step it can, rather than chasing its newest commit). Nodes a moved camera newly needs
//!   arrive over the next frames; meanwhile [`busy`](Content::busy) is true, so the window keeps
//!   drawing and a screenshot waits for the complete picture.
//! - Colours: every sample is a real source point with its record, so a store view has every
//!   colour mode its point format has (C cycles them): `auto` (RGB where the source has it, else
//!   intensity), elevation, intensity, classification, return number, GPS time. Scalar modes map
//!   over a range fixed when the store's first commit is opened (`--range`, else the 1st to 99th
//!   percentile of all its points' values, [`draw::lod::color_range`](crate::draw::lod::color_range), the rule of every renderer:
//!   `mortar render` of the store, with or without LOD, colours alike; for a store a build is
//!   still writing, the points of that first commit), so that both rasterizers colour a sample
//!   alike and a growing store's colours do not shift from frame to frame.

use super::content::{Content, GpuDrawn};
use super::node_loader::{threads_beside_a_build, NodeLoader};
use crate::draw;
use crate::draw::lod::LodColor;
use crate::draw::{ColorChoice, RenderSettings};
use anyhow::{anyhow, Result};
use mortar_core::grid::Grid;
use mortar_core::layout::RecordLayout;
use mortar_core::octree::{LodOptions, LodTree};
use mortar_core::render::resolve::{ColorMode, ResolveOptions};
use mortar_core::render::{Aabb, BatchRef, Camera, RasterOptions};
use mortar_io::store::{PayloadPlace, StoreLod};
use mortar_render::{GpuContext, GpuError, GpuFrame, GpuRasterizer, GpuScene, SceneOptions};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Most samples per GPU batch (a node is uploaded in slices of this size).
pub(super) const SLICE: usize = 1 << 14;

/// Time a frame may spend decoding and uploading nodes (beyond its first node): half of a
/// 60 Hz frame, leaving the rest to the draw. The environment variable
/// `MORTAR_UPLOAD_BUDGET_MS` replaces it (tests set 0: one node a frame).
pub const UPLOAD_BUDGET_MS: f64 = 8.0;

/// The upload budget in force (see [`UPLOAD_BUDGET_MS`]).
pub(super) fn upload_budget_ms() -> f64 {
    static BUDGET: std::sync::OnceLock<f64> = std::sync::OnceLock::new();
    *BUDGET.get_or_init(|| {
        std::env::var("MORTAR_UPLOAD_BUDGET_MS")
            .ok()
            .and_then(|v| v.parse::<f64>().ok())
            .filter(|v| v.is_finite() && *v >= 0.0)
            .unwrap_or(UPLOAD_BUDGET_MS)
    })
}

/// The colour modes of a store view of points in `layout`: `auto`, elevation, then the
/// attribute modes the format has.
pub fn modes_of(layout: &RecordLayout) -> Vec<ColorChoice> {
    let mut m = vec![ColorChoice::Auto, ColorChoice::Mode(ColorMode::Elevation)];
    for c in [
        ColorMode::Intensity,
        ColorMode::Classification,
        ColorMode::ReturnNumber,
        ColorMode::GpsTime,
    ] {
        if layout.attribute(c.attribute()).is_some() {
            m.push(ColorChoice::Mode(c));
        }
    }
    m
}

/// What the last frame selected.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Selected {
    pub nodes: u64,
    pub samples: u64,
    /// Nodes uploaded to the GPU for this frame.
    pub uploaded_nodes: u64,
}

/// The GPU side of a store view: the scene and which payloads it holds.
struct StoreGpu {
    scene: GpuScene,
    /// Scene batches of each uploaded payload (by its place in the store: the first batch and how
    /// many), with its samples.
    batches: HashMap<PayloadPlace, (u32, u32, u64)>,
    /// Colour mode of the uploaded colours.
    mode: usize,
    /// Samples in the scene that no node of the current commit uses.
    garbage: u64,
    /// Colours the nodes in `mode` off the frame thread (made at the first frame with a commit).
    loader: Option<NodeLoader<PayloadPlace, Vec<u32>>>,
}

/// An octree store shown in a window.
pub struct StoreView {
    path: PathBuf,
    /// The last commit, or `None` while a build has not committed yet.
    lod: Option<Arc<StoreLod>>,
    commit: u64,
    options: LodOptions,
    /// The colour modes (see [`modes_of`]).
    modes: Vec<ColorChoice>,
    /// The range given with `--range`.
    given: Option<[f64; 2]>,
    /// Elevation colour range before a commit was seen (given, else the height bounds).
    range: [f64; 2],
    /// Per mode, the range of scalar modes, fixed at the first commit (see the module docs).
    ranges: Vec<Option<[f64; 2]>>,
    bounds: Aabb,
    /// The colour mode shown (a position in `modes`).
    mode: usize,
    gpu: Option<StoreGpu>,
    /// A newer commit being uploaded behind the one shown (GPU only; see the module docs).
    pending: Option<Arc<StoreLod>>,
    /// Whether a commit came while one was pending (it is opened when the pending one is shown).
    stale: bool,
    /// Whether the commit shown was not drawn whole yet (the last GPU frame left selected nodes
    /// out, or no frame drew it).
    incomplete: bool,
    pub selected: Selected,
}

impl StoreView {
    /// Opens the store `dir` (its last commit).
    pub fn open(dir: &Path, options: LodOptions, range: Option<[f64; 2]>) -> Result<StoreView> {
        let lod = StoreLod::open(dir)?;
        if lod.drawable() == 0 {
            anyhow::bail!("{}: no points to draw", dir.display());
        }
        let bounds = lod.bounds();
        let layout = lod.store().layout.clone();
        let mut v = StoreView::waiting(dir, bounds, &layout, options, range);
        v.commit = lod.store().header.commit;
        v.set_ranges(&lod);
        v.lod = Some(Arc::new(lod));
        v.incomplete = true;
        Ok(v)
    }

    /// A view of the store a build is writing into `dir` (points in `layout`), shown from its
    /// first commit on; until then frames are empty. `bounds`: the points' bounds as the inputs'
    /// headers declare them.
    pub fn waiting(
        dir: &Path,
        bounds: Aabb,
        layout: &RecordLayout,
        options: LodOptions,
        given: Option<[f64; 2]>,
    ) -> StoreView {
        let range = given.unwrap_or([bounds.min[2], bounds.max[2].max(bounds.min[2] + 1e-9)]);
        let modes = modes_of(layout);
        let ranges = vec![None; modes.len()];
        StoreView {
            path: dir.to_path_buf(),
            lod: None,
            commit: 0,
            options,
            modes,
            given,
            range,
            ranges,
            bounds,
            mode: 0,
            gpu: None,
            pending: None,
            stale: false,
            incomplete: false,
            selected: Selected::default(),
        }
    }

    /// Fixes the scalar modes' ranges from `lod` (the first commit seen).
    fn set_ranges(&mut self, lod: &StoreLod) {
        for (m, r) in self.modes.iter().zip(self.ranges.iter_mut()) {
            *r = match LodColor::of(lod.store(), *m) {
                Ok(c) if c.uses_range() => self
                    .given
                    .or_else(|| draw::lod::color_range(lod, c))
                    .or(matches!(c, LodColor::Elevation).then_some(self.range)),
                _ => None,
            };
        }
    }

    /// The position in [`modes`](Self::modes) of colour mode `choice` (`stored` and `rgb` are
    /// `auto` here), or an error naming the store for modes it cannot show.
    pub fn mode_of(&self, choice: ColorChoice) -> Result<usize> {
        if let Some(lod) = &self.lod {
            LodColor::of(lod.store(), choice)?;
        }
        let want = match choice {
            ColorChoice::Stored | ColorChoice::Mode(ColorMode::Rgb) => ColorChoice::Auto,
            c => c,
        };
        self.modes.iter().position(|&m| m == want).ok_or_else(|| {
            anyhow!(
                "{}: --color {}: the store's point format has no such attribute",
                self.path.display(),
                choice.name()
            )
        })
    }

    /// Shows colour mode `choice` (see [`mode_of`](Self::mode_of)).
    pub fn show_mode(&mut self, choice: ColorChoice) -> Result<()> {
        self.mode = self.mode_of(choice)?;
        Ok(())
    }

    /// Nodes in the last commit.
    pub fn nodes(&self) -> u64 {
        self.lod.as_ref().map_or(0, |l| l.node_count() as u64)
    }

    /// The commit shown (0: none yet).
    pub fn commit(&self) -> u64 {
        self.commit
    }

    /// Opens the store's last commit if it is newer than the one shown; whether it was. Without
    /// the GPU the view switches to it at once; with the GPU it becomes the pending commit (see
    /// the module docs), and while one is pending a newer commit waits for it to be shown.
    fn reload_commit(&mut self) -> Result<bool> {
        if self.pending.is_some() {
            // The pending commit is shown first (so that a build committing faster than its
            // nodes upload still shows progress); a newer one is opened once it is.
            self.stale = true;
            return Ok(false);
        }
        self.stale = false;
        let lod = match StoreLod::open(&self.path) {
            Ok(l) => l,
            // No commit yet.
            Err(_) if self.lod.is_none() => return Ok(false),
            Err(e) => return Err(e.into()),
        };
        if lod.store().header.commit == self.commit {
            return Ok(false);
        }
        if self.lod.is_none() {
            self.set_ranges(&lod);
        }
        let lod = Arc::new(lod);
        if self.gpu.is_some() && self.lod.is_some() {
            self.pending = Some(lod);
        } else {
            self.show(lod);
        }
        Ok(true)
    }

    /// Shows commit `lod` from now on: the GPU batches of payloads it no longer has become
    /// garbage.
    fn show(&mut self, lod: Arc<StoreLod>) {
        self.commit = lod.store().header.commit;
        if let Some(g) = &mut self.gpu {
            let live: std::collections::HashSet<PayloadPlace> = (0..lod.node_count())
                .map(|i| lod.payload_place(mortar_core::octree::NodeId(i as u32)))
                .collect();
            let mut dropped = 0;
            g.batches.retain(|off, (_, _, n)| {
                let keep = live.contains(off);
                if !keep {
                    dropped += *n;
                }
                keep
            });
            g.garbage += dropped;
            if let Some(l) = &mut g.loader {
                l.retain(|p| live.contains(p));
            }
        }
        self.lod = Some(lod);
        // Not drawn whole yet.
        self.incomplete = true;
    }

    fn settings(
        &self,
        mode: usize,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> RenderSettings {
        RenderSettings {
            raster: *options,
            color: self.modes[mode],
            range: self.ranges[mode],
            resolve: *resolve,
        }
    }
}

impl Content for StoreView {
    fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// Points in the last commit.
    fn points(&self) -> u64 {
        self.lod.as_ref().map_or(0, |l| l.point_count())
    }

    fn modes(&self) -> &[ColorChoice] {
        &self.modes
    }

    fn mode(&self) -> usize {
        self.mode
    }

    fn set_mode(&mut self, to: usize, _gpu: Option<&GpuContext>) -> Result<bool> {
        self.mode = to;
        Ok(true)
    }

    fn status(&self) -> Vec<String> {
        use super::content::group_digits;
        vec![
            format!(
                "{} points, {} nodes, commit {}",
                group_digits(self.points()),
                group_digits(self.nodes()),
                self.commit()
            ),
            format!(
                "drawn {} nodes, {} samples",
                group_digits(self.selected.nodes),
                group_digits(self.selected.samples)
            ),
        ]
    }

    /// A commit waits to be shown, or the last frame left nodes out.
    fn busy(&self) -> bool {
        self.pending.is_some() || self.stale || self.incomplete
    }

    fn reload(&mut self) -> Result<bool> {
        self.reload_commit()
    }

    fn use_gpu(&mut self, ctx: &GpuContext) -> Result<(), GpuError> {
        let grid =
            self.lod.as_ref().map_or(Grid { scale: [1.0; 3], offset: [0.0; 3] }, |l| l.grid());
        self.gpu = Some(StoreGpu {
            scene: GpuScene::new(
                ctx,
                grid,
                1 << 20,
                SceneOptions { colors: true, ..Default::default() },
            )?,
            batches: HashMap::new(),
            mode: self.mode,
            garbage: 0,
            loader: None,
        });
        Ok(())
    }

    /// The LOD selection of `camera`, drawn by the CPU rasterizer.
    fn draw_cpu(
        &mut self,
        camera: &Camera,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> Result<(Vec<u32>, u64)> {
        let Some(lod) = &self.lod else {
            return Ok((
                vec![resolve.background; camera.width as usize * camera.height as usize],
                0,
            ));
        };
        let sel = lod.select(camera, &self.options)?;
        let batches = lod.batches(&sel.nodes)?;
        let img =
            draw::lod::render(lod, &batches, camera, &self.settings(self.mode, options, resolve))?;
        self.selected =
            Selected { nodes: sel.nodes.len() as u64, samples: batches.samples, uploaded_nodes: 0 };
        self.incomplete = false;
        Ok((img.rgba, batches.samples))
    }

    /// The LOD selection of `camera`, drawn by the GPU rasterizer into `raster` (resolved, ready
    /// to present). Uploads the selected nodes the GPU does not hold yet, within the frame's
    /// upload budget: first those of a pending commit (shown once all are on the GPU), then those
    /// of the commit shown (missing ones are left out of this frame).
    fn draw_gpu(
        &mut self,
        ctx: &GpuContext,
        raster: &mut GpuRasterizer,
        camera: &Camera,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> Result<GpuDrawn> {
        let start = std::time::Instant::now();
        let mode = self.mode;
        let path = self.path.display().to_string();
        let gpu = |e: GpuError| anyhow!("{path}: GPU: {e}");
        let drawn = |f: GpuFrame| GpuDrawn::of(&f);
        if self.gpu.is_none() {
            return Err(anyhow!("{path}: GPU: not set up"));
        }
        if self.lod.is_none() {
            if let Some(p) = self.pending.take() {
                self.show(p);
            }
        }
        let Some(lod) = &self.lod else {
            let g = self.gpu.as_mut().expect("checked above");
            self.incomplete = false;
            return raster
                .draw_selected(ctx, &mut g.scene, Some(&[]), camera, options, Some(resolve))
                .map(drawn)
                .map_err(gpu);
        };
        let sel = lod.select(camera, &self.options)?;
        let samples: u64 = sel.nodes.iter().map(|&id| lod.index().samples(id)).sum();
        let upload = Upload { ctx, mode, color: self.modes[mode], range: self.ranges[mode], start };
        let g = self.gpu.as_mut().expect("checked above");
        // A new colour mode, a new grid (the first commit) or more garbage than live samples:
        // start a new scene with what this frame needs.
        let live = g.scene.points() - g.garbage;
        if g.mode != mode
            || *g.scene.grid() != lod.grid()
            || (g.garbage > live && g.garbage > 1 << 20)
            || g.scene.points() + samples >= 1 << 32
            || self.pending.as_ref().is_some_and(|p| p.grid() != *g.scene.grid())
        {
            *g = StoreGpu {
                scene: GpuScene::new(
                    ctx,
                    lod.grid(),
                    samples.max(1 << 20),
                    SceneOptions { colors: true, ..Default::default() },
                )
                .map_err(gpu)?,
                batches: HashMap::new(),
                mode,
                garbage: 0,
                loader: None,
            };
            // The pending commit's uploads went with the old scene: show it now, progressively.
            if let Some(p) = self.pending.take() {
                self.show(p);
                if self.stale {
                    self.reload_commit()?;
                }
                return self.draw_gpu(ctx, raster, camera, options, resolve);
            }
        }
        let mut uploaded = 0;
        let mut ids = Vec::with_capacity(sel.nodes.len());
        // The shown commit's missing nodes first (a moved camera), then the pending commit's.
        let shown = upload
            .nodes(g, lod, &sel.nodes, &mut ids, &mut uploaded)
            .map_err(|e| anyhow!("{path}: {e:#}"))?;
        let mut switch = false;
        if let Some(p) = &self.pending {
            let psel = p.select(camera, &self.options)?;
            let psamples: u64 = psel.nodes.iter().map(|&id| p.index().samples(id)).sum();
            if g.scene.points() + psamples >= 1 << 32 {
                // No room for both commits: the next frame starts a new scene (above).
                switch = true;
            } else {
                let mut pids = Vec::with_capacity(psel.nodes.len());
                switch = upload
                    .nodes(g, p, &psel.nodes, &mut pids, &mut uploaded)
                    .map_err(|e| anyhow!("{path}: {e:#}"))?;
                if switch {
                    ids = pids;
                    self.selected = Selected {
                        nodes: psel.nodes.len() as u64,
                        samples: psamples,
                        uploaded_nodes: uploaded,
                    };
                }
            }
        }
        if switch {
            let p = self.pending.take().expect("a pending commit");
            self.show(p);
            self.incomplete = false;
            if self.stale {
                self.reload_commit()?;
            }
        } else {
            self.incomplete = !shown;
            self.selected =
                Selected { nodes: sel.nodes.len() as u64, samples, uploaded_nodes: uploaded };
        }
        let g = self.gpu.as_mut().expect("checked above");
        raster
            .draw_selected(ctx, &mut g.scene, Some(&ids), camera, options, Some(resolve))
            .map(drawn)
            .map_err(gpu)
    }
}

/// One frame's uploads (see the module docs).
struct Upload<'a> {
    ctx: &'a GpuContext,
    mode: usize,
    color: ColorChoice,
    range: Option<[f64; 2]>,
    /// When the frame began (the budget counts from it).
    start: std::time::Instant,
}

impl Upload<'_> {
    /// Puts the scene batches of `nodes` of `lod` into `ids`, uploading those the scene lacks
    /// whose colours the loader has ready, while the frame's budget lasts (always one per frame),
    /// and asking the loader for the others; whether every node is in `ids`.
    fn nodes(
        &self,
        g: &mut StoreGpu,
        lod: &Arc<StoreLod>,
        nodes: &[mortar_core::octree::NodeId],
        ids: &mut Vec<u32>,
        uploaded: &mut u64,
    ) -> Result<bool> {
        debug_assert_eq!(g.mode, self.mode);
        let color = LodColor::of(lod.store(), self.color)?;
        let range = self.range;
        let loader = g.loader.get_or_insert_with(|| NodeLoader::new(threads_beside_a_build()));
        loader.collect()?;
        // The job that colours node `id`.
        let job = |id| {
            let lod = lod.clone();
            move || move || Ok(draw::lod::node_colors(&lod, id, color, range)?)
        };
        let mut complete = true;
        for &id in nodes {
            let off = lod.payload_place(id);
            if let Some(&(b, k, _)) = g.batches.get(&off) {
                ids.extend(b..b + k);
                continue;
            }
            if *uploaded > 0 && self.start.elapsed().as_secs_f64() * 1e3 >= upload_budget_ms() {
                // Over budget: the colours are still asked for, to be ready for a later frame.
                loader.ask(off, job(id));
                complete = false;
                continue;
            }
            let Some(c) = loader.take(off, job(id)) else {
                complete = false;
                continue;
            };
            let first = g.scene.points();
            let batch = lod.node_batch(id, first as u32);
            // A node can hold millions of samples, and the rasterizer gives one workgroup to a
            // batch: nodes go to the GPU in slices of at most SLICE samples (same frame and
            // bounds, consecutive indices), so that a large node keeps the whole GPU busy.
            let b = g.scene.batches().len() as u32;
            let n = batch.len();
            let mut k = 0u32;
            for s in (0..n.max(1)).step_by(SLICE) {
                let e = (s + SLICE).min(n);
                let part = BatchRef {
                    words: [0, 1, 2].map(|w| &batch.words[w][s..e]),
                    first_index: batch.first_index + s as u32,
                    ..batch
                };
                g.scene.push(self.ctx, &part, Some(&c[s..e])).map_err(|e| anyhow!("GPU: {e}"))?;
                k += 1;
            }
            g.batches.insert(off, (b, k, n as u64));
            ids.extend(b..b + k);
            *uploaded += 1;
        }
        Ok(complete)
    }
}
