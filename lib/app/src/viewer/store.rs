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
//! - Colours: every sample is a real source point with its record, so a store view has every
//!   colour mode its point format has (C cycles them): `auto` (RGB where the source has it, else
//!   intensity), elevation, intensity, classification, return number, GPS time. Scalar modes map
//!   over a range fixed when the store's first commit is opened (`--range`, else the 1st to 99th
//!   percentile of all its points' values, [`draw::lod::color_range`](crate::draw::lod::color_range), the rule of every renderer:
//!   `mortar render` of the store, with or without LOD, colours alike; for a store a build is
//!   still writing, the points of that first commit), so that both rasterizers colour a sample
//!   alike and a growing store's colours do not shift from frame to frame.

use super::content::{Content, GpuDrawn};
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

/// Most samples per GPU batch (a node is uploaded in slices of this size).
const SLICE: usize = 1 << 14;

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
}

/// An octree store shown in a window.
pub struct StoreView {
    path: PathBuf,
    /// The last commit, or `None` while a build has not committed yet.
    lod: Option<StoreLod>,
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
        v.lod = Some(lod);
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

    /// Opens the store's last commit if it is newer than the one shown; whether it was.
    fn reload_commit(&mut self) -> Result<bool> {
        let lod = match StoreLod::open(&self.path) {
            Ok(l) => l,
            // No commit yet.
            Err(_) if self.lod.is_none() => return Ok(false),
            Err(e) => return Err(e.into()),
        };
        if lod.store().header.commit == self.commit {
            return Ok(false);
        }
        self.commit = lod.store().header.commit;
        if self.lod.is_none() {
            self.set_ranges(&lod);
        }
        if let Some(g) = &mut self.gpu {
            let live: std::collections::HashSet<PayloadPlace> = (0..lod.node_count())
                .map(|i| lod.payload_place(mortar_core::octree::NodeId(i as u32)))
                .collect();
            let before = g.batches.len();
            let mut dropped = 0;
            g.batches.retain(|off, (_, _, n)| {
                let keep = live.contains(off);
                if !keep {
                    dropped += *n;
                }
                keep
            });
            g.garbage += dropped;
            debug_assert!(g.batches.len() <= before);
        }
        self.lod = Some(lod);
        Ok(true)
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
        self.lod.as_ref().map_or(0, StoreLod::point_count)
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

    fn busy(&self) -> bool {
        false
    }

    fn reload(&mut self) -> Result<bool> {
        self.reload_commit()
    }

    fn use_gpu(&mut self, ctx: &GpuContext) -> Result<(), GpuError> {
        let grid =
            self.lod.as_ref().map_or(Grid { scale: [1.0; 3], offset: [0.0; 3] }, StoreLod::grid);
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
        Ok((img.rgba, batches.samples))
    }

    /// The LOD selection of `camera`, drawn by the GPU rasterizer into `raster` (resolved, ready
    /// to present), uploading the selected nodes the GPU does not hold yet.
    fn draw_gpu(
        &mut self,
        ctx: &GpuContext,
        raster: &mut GpuRasterizer,
        camera: &Camera,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> Result<GpuDrawn> {
        let mode = self.mode;
        let path = self.path.display().to_string();
        let gpu = |e: GpuError| anyhow!("{path}: GPU: {e}");
        let drawn = |f: GpuFrame| GpuDrawn::of(&f);
        let g = self.gpu.as_mut().ok_or_else(|| anyhow!("{path}: GPU: not set up"))?;
        let Some(lod) = &self.lod else {
            return raster
                .draw_selected(ctx, &mut g.scene, Some(&[]), camera, options, Some(resolve))
                .map(drawn)
                .map_err(gpu);
        };
        let sel = lod.select(camera, &self.options)?;
        let samples: u64 = sel.nodes.iter().map(|&id| lod.index().samples(id)).sum();
        // A new colour mode, a new grid (the first commit) or more garbage than live samples:
        // start a new scene with what this frame needs.
        let live = g.scene.points() - g.garbage;
        if g.mode != mode
            || *g.scene.grid() != lod.grid()
            || (g.garbage > live && g.garbage > 1 << 20)
            || g.scene.points() + samples >= 1 << 32
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
            };
        }
        let color = LodColor::of(lod.store(), self.modes[mode])?;
        let range = self.ranges[mode];
        let mut ids = Vec::with_capacity(sel.nodes.len());
        let mut uploaded = 0;
        for &id in &sel.nodes {
            let off = lod.payload_place(id);
            if let Some(&(b, k, _)) = g.batches.get(&off) {
                ids.extend(b..b + k);
                continue;
            }
            let first = g.scene.points();
            let batch = lod.node_batch(id, first as u32);
            let c = draw::lod::node_colors(lod, id, color, range)?;
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
                g.scene.push(ctx, &part, Some(&c[s..e])).map_err(gpu)?;
                k += 1;
            }
            g.batches.insert(off, (b, k, n as u64));
            ids.extend(b..b + k);
            uploaded += 1;
        }
        self.selected =
            Selected { nodes: sel.nodes.len() as u64, samples, uploaded_nodes: uploaded };
        raster
            .draw_selected(ctx, &mut g.scene, Some(&ids), camera, options, Some(resolve))
            .map(drawn)
            .map_err(gpu)
    }
}
