//! What a window shows, behind one trait: [`Content`]. The window (`viewer::window`) knows
//! nothing of the kind of data; each kind keeps its own CPU and GPU state and draws itself on the
//! backend it is given:
//!
//! - [`BatchContent`]: a batch file (or LAS/LAZ batched into one), every point, by the batch
//!   rasterizer; on the GPU the batches stream in a time slice per frame.
//! - [`StoreView`](super::store::StoreView): an octree store, maybe growing, drawn with the LOD
//!   selection of each frame; nodes go to the GPU as first selected.
//! - [`ProgressiveView`](super::progressive_view::ProgressiveView): raw LAS/LAZ by the progressive
//!   renderer of paper 000, loading while it draws.

use crate::draw;
use crate::draw::ColorChoice;
use anyhow::{anyhow, Result};
use mortar_core::render::resolve::{resolve, ColorMode, ResolveOptions};
use mortar_core::render::{rasterize, Aabb, BatchRef, Camera, Framebuffer, RasterOptions};
use mortar_io::batchfile::BatchFile;
use mortar_render::{wgpu, GpuContext, GpuError, GpuFrame, GpuRasterizer, GpuScene, SceneOptions};
use std::time::Instant;

/// The time slice of a frame spent uploading a batch file's batches to the GPU.
const UPLOAD_SLICE_SECONDS: f64 = 0.1;

/// What a GPU frame drew, and where its resolved image is.
#[derive(Clone, Copy, Debug, Default)]
pub struct GpuDrawn {
    pub points_drawn: u64,
    /// The GPU's drawing passes (timestamp queries), where available.
    pub draw_ms: Option<f64>,
    /// The GPU's resolve passes (hole filling, colours, eye-dome lighting).
    pub resolve_ms: Option<f64>,
    /// The image is in the content's own buffer ([`Content::image`]), not in the rasterizer.
    pub own_image: bool,
}

impl GpuDrawn {
    /// What a frame of the batch rasterizer drew (resolved in the rasterizer).
    pub fn of(f: &GpuFrame) -> GpuDrawn {
        GpuDrawn {
            points_drawn: f.stats.points_drawn,
            draw_ms: f.timings.map(|t| t.draw_ms),
            resolve_ms: f.timings.and_then(|t| t.post_ms()),
            own_image: false,
        }
    }
}

/// What a window shows: its bounds, its colour modes, new data to poll for, and a frame on the
/// CPU or the GPU backend.
pub trait Content {
    /// The box the camera frames.
    fn bounds(&self) -> Aabb;
    /// Points in the data (a store's last commit; all a progressive view will load).
    fn points(&self) -> u64;
    /// The colour modes, in the order C cycles them.
    fn modes(&self) -> &[ColorChoice];
    /// The position in [`modes`](Self::modes) of the mode shown.
    fn mode(&self) -> usize;
    /// Asks for mode `to` (with the GPU context where the GPU draws); `false` where it cannot
    /// start now (a progressive view still loading).
    fn set_mode(&mut self, to: usize, gpu: Option<&GpuContext>) -> Result<bool>;
    /// The content's parts of the status line.
    fn status(&self) -> Vec<String>;
    /// Whether more frames would change the image without new input (loading, uploading,
    /// refining).
    fn busy(&self) -> bool;
    /// Takes new data from disk (a growing store's new commit); whether there was any.
    fn reload(&mut self) -> Result<bool> {
        Ok(false)
    }
    /// Why `ctx` cannot draw this content, where it cannot (the window then draws on the CPU).
    fn gpu_unsupported(&self, _ctx: &GpuContext) -> Option<&'static str> {
        None
    }
    /// Makes the GPU state for `ctx`; called once, before the first GPU frame.
    fn use_gpu(&mut self, ctx: &GpuContext) -> Result<(), GpuError>;
    /// One frame on the CPU: the RGBA8 image of `camera` resolved with `resolve` (background,
    /// hole filling, eye-dome lighting) and the points drawn.
    fn draw_cpu(
        &mut self,
        camera: &Camera,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> Result<(Vec<u32>, u64)>;
    /// One frame on the GPU, resolved with `resolve` into `raster` (or into
    /// [`image`](Self::image) where [`GpuDrawn::own_image`]) without leaving the GPU, ready to
    /// present; the same image as [`draw_cpu`](Self::draw_cpu).
    fn draw_gpu(
        &mut self,
        ctx: &GpuContext,
        raster: &mut GpuRasterizer,
        camera: &Camera,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> Result<GpuDrawn>;
    /// What the content read, for `--json` (`lod_source` of a COPC or EPT view).
    fn report(&self) -> Option<serde_json::Value> {
        None
    }
    /// The content's own resolved image on the GPU, after [`draw_gpu`](Self::draw_gpu).
    fn image(&self) -> Option<&wgpu::Buffer> {
        None
    }
}

/// The GPU side of a batch file.
struct BatchGpu {
    scene: GpuScene,
    /// The colour mode whose colours the scene holds.
    uploaded: usize,
    /// Batches uploaded so far (frames draw those while the rest streams in).
    next: usize,
}

/// A batch file (or LAS/LAZ batched into one): every point, by the batch rasterizer.
pub struct BatchContent<'a> {
    label: String,
    file: &'a BatchFile,
    refs: &'a [BatchRef<'a>],
    /// The box framed views frame (`render::open_source`: the one framing rule).
    bounds: Aabb,
    range: Option<[f64; 2]>,
    modes: Vec<ColorChoice>,
    mode: usize,
    /// Per mode, every point's colour once computed.
    colors: Vec<Option<Vec<u32>>>,
    /// The CPU rasterizer's visibility buffer, kept from frame to frame.
    fb: Option<Framebuffer>,
    gpu: Option<BatchGpu>,
}

impl<'a> BatchContent<'a> {
    /// The batches `refs` of `file` (named `label` in errors), first shown in colour mode
    /// `color`; the other modes are those the file's attributes serve; `bounds` what framed views
    /// frame. `range`: of the scalar modes (default: the 1st to 99th percentile of all points).
    pub fn new(
        label: String,
        file: &'a BatchFile,
        refs: &'a [BatchRef<'a>],
        bounds: Aabb,
        color: ColorChoice,
        range: Option<[f64; 2]>,
    ) -> mortar_io::Result<BatchContent<'a>> {
        let initial = color.resolved(file);
        draw::batch::check_color(file, initial)?;
        let mut modes: Vec<ColorChoice> = ColorMode::ALL
            .iter()
            .map(|&m| ColorChoice::Mode(m))
            .filter(|&c| draw::batch::check_color(file, c).is_ok())
            .collect();
        if !modes.contains(&initial) {
            modes.insert(0, initial);
        }
        let mode = modes.iter().position(|&m| m == initial).unwrap_or(0);
        let colors = vec![None; modes.len()];
        Ok(BatchContent {
            label,
            file,
            refs,
            bounds,
            range,
            modes,
            mode,
            colors,
            fb: None,
            gpu: None,
        })
    }

    /// Every point's colour in the current mode (computed once per mode).
    fn colors(&mut self) -> Result<&[u32]> {
        if self.colors[self.mode].is_none() {
            let (c, _range) =
                draw::batch::point_colors(self.file, self.modes[self.mode], self.range)
                    .map_err(|e| anyhow!("{}: {e}", self.label))?;
            self.colors[self.mode] = Some(c);
        }
        Ok(self.colors[self.mode].as_deref().unwrap_or_default())
    }
}

impl Content for BatchContent<'_> {
    fn bounds(&self) -> Aabb {
        self.bounds
    }

    fn points(&self) -> u64 {
        self.file.header.point_count
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
        vec![format!("{} points", group_digits(self.file.header.point_count))]
    }

    fn busy(&self) -> bool {
        self.gpu.as_ref().is_some_and(|g| g.next < self.refs.len())
    }

    fn use_gpu(&mut self, ctx: &GpuContext) -> Result<(), GpuError> {
        if let Err(e) = self.colors() {
            return Err(GpuError::Colors(format!("{e:#}")));
        }
        // Batches are uploaded by the frames, a time slice each, so that the first frame comes
        // at once whatever the file's size.
        let scene = GpuScene::new(
            ctx,
            self.file.grid(),
            self.file.header.point_count,
            SceneOptions { colors: true, ..Default::default() },
        )?;
        self.gpu = Some(BatchGpu { scene, uploaded: self.mode, next: 0 });
        Ok(())
    }

    fn draw_cpu(
        &mut self,
        camera: &Camera,
        options: &RasterOptions,
        resolve_options: &ResolveOptions,
    ) -> Result<(Vec<u32>, u64)> {
        self.colors()?;
        let (w, h) = (camera.width, camera.height);
        let fb = match &mut self.fb {
            Some(fb) if (fb.width(), fb.height()) == (w, h) => {
                fb.clear();
                fb
            }
            fb => fb.insert(Framebuffer::new(w, h)),
        };
        let s = rasterize(fb, self.refs, &self.file.grid(), camera, options)
            .map_err(|e| anyhow!("{}: {e}", self.label))?;
        let colors = self.colors[self.mode].as_deref().unwrap_or_default();
        let background = resolve_options.background;
        let rgba = resolve(
            fb.keys_slice(),
            w,
            h,
            |i| colors.get(i as usize).copied().unwrap_or(background),
            resolve_options,
        );
        Ok((rgba, s.points_drawn))
    }

    fn draw_gpu(
        &mut self,
        ctx: &GpuContext,
        raster: &mut GpuRasterizer,
        camera: &Camera,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> Result<GpuDrawn> {
        self.colors()?;
        let label = &self.label;
        let gpu = |e: GpuError| anyhow!("{label}: GPU: {e}");
        let g = self.gpu.as_mut().ok_or_else(|| anyhow!("{label}: GPU: not set up"))?;
        let colors = self.colors[self.mode].as_deref().unwrap_or_default();
        if g.uploaded != self.mode {
            g.scene.set_colors(ctx, &colors[..g.scene.points() as usize]).map_err(gpu)?;
            g.uploaded = self.mode;
        }
        let t = Instant::now();
        while g.next < self.refs.len() && t.elapsed().as_secs_f64() < UPLOAD_SLICE_SECONDS {
            let b = &self.refs[g.next];
            let first = b.first_index as usize;
            g.scene.push(ctx, b, Some(&colors[first..first + b.len()])).map_err(gpu)?;
            g.next += 1;
        }
        let frame = if g.next < self.refs.len() {
            let ids: Vec<u32> = (0..g.next as u32).collect();
            raster
                .draw_selected(ctx, &mut g.scene, Some(&ids), camera, options, Some(resolve))
                .map_err(gpu)?
        } else {
            raster.draw(ctx, &mut g.scene, camera, options, Some(resolve)).map_err(gpu)?
        };
        Ok(GpuDrawn::of(&frame))
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
