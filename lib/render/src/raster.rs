//! The GPU rasterizer (paper 003 §3.2-3.3 in wgpu compute shaders): per frame the host plans every
//! batch with the same [`Planner`] as the CPU reference (culling, precision, projection), uploads
//! one [`DrawRecord`] per drawn batch, and the GPU runs the passes of `shaders/`: clear, draw
//! batches (one workgroup of 128 threads per batch; 64-bit `atomicMin` or the 32-bit two-pass
//! path) and, when asked, resolve: depth-aware hole filling into a second key buffer, point index
//! to colour, eye-dome lighting of the image, as [`mortar_core::render::resolve::resolve`] does
//! on the host and equal to it byte for byte, without reading the keys back. The keys it leaves
//! are those of [`mortar_core::render::rasterize`] for the same view (see `docs/render.md` for
//! where a GPU may round differently).

use crate::buffers::{grown_size, map_read, read_image_buffer, readback};
use crate::context::{AtomicPath, GpuContext, GpuError};
use crate::pipeline::{
    batches_group, entry, storage, uniform, PassPipeline, SharedLayouts, Timestamps,
};
use crate::scene::GpuScene;
use crate::shaders::{binding, Pass};
use mortar_core::render::framebuffer::EMPTY_KEY;
use mortar_core::render::gpu::{
    plan_counter, DrawRecord, EyeDomeUniforms, FrameUniforms, HoleFillUniforms, PlanUniforms,
    ResolveUniforms,
};
use mortar_core::render::resolve::ResolveOptions;
use mortar_core::render::{BatchPlan, Camera, Planner, RasterError, RasterOptions, RasterStats};
use rayon::prelude::*;
use std::num::NonZeroU64;
use std::time::Instant;

/// GPU time of each pass of a frame, from timestamp queries, in milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GpuTimings {
    /// Clearing the framebuffer.
    pub clear_ms: f64,
    /// Drawing the batches (both steps on the 32-bit path).
    pub draw_ms: f64,
    /// Resolving indices to colours (`None` when not run).
    pub resolve_ms: Option<f64>,
    /// Planning every batch on the GPU (`None` when planned on the host).
    pub plan_ms: Option<f64>,
    /// Hole filling (`None` when not run).
    pub hole_fill_ms: Option<f64>,
    /// Eye-dome lighting (`None` when not run).
    pub eye_dome_ms: Option<f64>,
}

impl GpuTimings {
    /// The resolve's passes together: hole filling, colours, eye-dome lighting (`None` when the
    /// frame was not resolved).
    pub fn post_ms(&self) -> Option<f64> {
        self.resolve_ms
            .map(|r| r + self.hole_fill_ms.unwrap_or(0.0) + self.eye_dome_ms.unwrap_or(0.0))
    }
}

/// What one frame did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GpuFrame {
    /// Batches culled and drawn, points per precision, points drawn (counted on the GPU).
    pub stats: RasterStats,
    /// GPU pass times, where the device has timestamps.
    pub timings: Option<GpuTimings>,
    /// Host seconds spent planning the batches (culling, precision, projections).
    pub plan_seconds: f64,
    /// Host seconds from the start of the frame until the GPU finished it.
    pub frame_seconds: f64,
}

/// Variants of the 64-bit draw pass for measuring where its time goes (issue 17; the bench
/// `mortar-bench-gpu --kernels --workgroups --orders`). The renderer draws with the default,
/// which every test checks; the others are diagnostics (kernel 3 leaves no image at all).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct DrawTuning {
    /// `draw.wgsl`'s `KERNEL`: 0 the renderer (atomicLoad early test), 1 early test from a plain
    /// load of the depth word, 2 no early test, 3 no framebuffer access, 4 kernel 0 with four
    /// points' words loaded before any is projected (the paper's prefetch, §3.4).
    pub kernel: u32,
    /// Threads per workgroup (`WG`; one workgroup per batch whatever the size).
    pub workgroup: u32,
    /// Order of a chunk's draw records, i.e. of the workgroups (host planning only).
    pub order: RecordOrder,
    /// Plan every batch on the GPU (the plan pass); `false` plans on the host (as a selection
    /// always is), with the same plan.
    pub plan_on_gpu: bool,
    /// The division of the draw and plan passes instead of the context's
    /// ([`GpuContext::division`]): `Some(DIVISION_PLAIN)` on a GPU whose `/` is not correctly
    /// rounded measures what the exact division costs (its keys may then differ from the CPU's).
    pub division: Option<u32>,
}

impl Default for DrawTuning {
    fn default() -> Self {
        DrawTuning {
            kernel: 0,
            workgroup: 128,
            order: RecordOrder::Scene,
            plan_on_gpu: true,
            division: None,
        }
    }
}

/// The order in which a chunk's batches are handed to workgroups.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum RecordOrder {
    /// Scene (Morton) order: workgroups that run together draw neighbouring batches.
    Scene,
    /// Records `k, k + s, k + 2s, ...` for `k` in `0..s`: workgroups that run together draw
    /// batches `s` apart, in other places of the screen.
    Strided(u32),
}

impl RecordOrder {
    /// The permutation of `n` records.
    fn permutation(self, n: usize) -> Vec<usize> {
        match self {
            RecordOrder::Scene => (0..n).collect(),
            RecordOrder::Strided(s) => {
                let s = (s as usize).max(1);
                (0..s).flat_map(|k| (k..n).step_by(s)).collect()
            }
        }
    }
}

/// The draw pipelines of the context's atomic path.
enum DrawPasses {
    /// `draw.wgsl`.
    U64(PassPipeline),
    /// `draw_depth.wgsl`, then `draw_index.wgsl`.
    TwoPass32([PassPipeline; 2]),
}

impl DrawPasses {
    /// The draw steps in order (one compute pass each).
    fn steps(&self) -> &[PassPipeline] {
        match self {
            DrawPasses::U64(draw) => std::slice::from_ref(draw),
            DrawPasses::TwoPass32(steps) => steps,
        }
    }
}

/// The pipelines and layouts of the rasterizer: built once, whatever the viewport and the frame.
struct Passes {
    shared: SharedLayouts,
    clear: PassPipeline,
    plan: PassPipeline,
    draw: DrawPasses,
    resolve: PassPipeline,
    hole_fill: PassPipeline,
    eye_dome: PassPipeline,
}

/// The framebuffer of the atomic path.
enum Keys {
    /// 64-bit depth|index keys (`width * height * 8` bytes).
    U64(wgpu::Buffer),
    /// The 32-bit path's depths and point indices (`width * height * 4` bytes each).
    TwoPass32 { depths: wgpu::Buffer, indices: wgpu::Buffer },
}

impl Keys {
    /// Every buffer of the framebuffer (what the clear pass clears).
    fn buffers(&self) -> Vec<&wgpu::Buffer> {
        match self {
            Keys::U64(keys) => vec![keys],
            Keys::TwoPass32 { depths, indices } => vec![depths, indices],
        }
    }

    /// The framebuffer read as 32-bit words: the buffers holding the indices and the depth bits,
    /// the words per pixel and the depth word's offset (the uniforms' `key_stride`,
    /// `depth_offset`).
    fn words(&self) -> (&wgpu::Buffer, &wgpu::Buffer, u32, u32) {
        match self {
            Keys::U64(keys) => (keys, keys, 2, 1),
            Keys::TwoPass32 { depths, indices } => (indices, depths, 1, 0),
        }
    }
}

/// What the rasterizer writes anew every frame: the camera's uniforms, the drawn-point counter,
/// the draw records and the uniforms of the resolve's passes. The buffers live as long as the
/// rasterizer; the records grow when a frame needs more.
struct PerFrame {
    frame_uniforms: wgpu::Buffer,
    counters: wgpu::Buffer,
    records: wgpu::Buffer,
    /// The plan pass's constants and counters.
    plan_uniforms: wgpu::Buffer,
    plan_counters: wgpu::Buffer,
    /// One per chunk of the last resolved scene (grown, never shrunk).
    resolve_uniforms: Vec<wgpu::Buffer>,
    /// `HoleFillUniforms`.
    fill_uniforms: wgpu::Buffer,
    /// `EyeDomeUniforms`.
    eye_dome_uniforms: wgpu::Buffer,
}

/// The framebuffer of one viewport size and the bind groups that use it, made together
/// ([`GpuRasterizer::new`], [`GpuRasterizer::resize`]).
struct Target {
    width: u32,
    height: u32,
    keys: Keys,
    /// The clear pass's bind group per framebuffer buffer, with its workgroup count.
    clear_groups: Vec<(wgpu::BindGroup, u32)>,
    /// Group 0 of each draw step (frame uniforms, framebuffer, counters).
    draw_groups: Vec<wgpu::BindGroup>,
    /// The hole-filled keys (two words per pixel, index then depth: a 64-bit key's
    /// little-endian words, on both atomic paths) with the hole-fill pass's bind group (the
    /// framebuffer in, these out) and the eye-dome pass's over them; `None` where
    /// `width * height * 8` bytes exceed the device's largest binding (32-bit path only).
    filled: Option<(wgpu::Buffer, wgpu::BindGroup, wgpu::BindGroup)>,
    /// The eye-dome pass's bind group over the framebuffer (no hole filling).
    eye_dome_group: wgpu::BindGroup,
    /// The resolved image (`width * height` RGBA8 words).
    image: wgpu::Buffer,
    /// Whether a frame was resolved into `image` since it was made.
    resolved: bool,
}

impl Target {
    fn new(
        ctx: &GpuContext,
        passes: &Passes,
        per_frame: &PerFrame,
        width: u32,
        height: u32,
    ) -> Result<Target, GpuError> {
        let pixels = width as u64 * height as u64;
        let key_bytes = pixels * if matches!(passes.draw, DrawPasses::U64(_)) { 8 } else { 4 };
        if key_bytes > ctx.max_binding() || pixels == 0 {
            return Err(GpuError::TooLarge {
                what: "the framebuffer",
                needed: key_bytes,
                limit: ctx.max_binding(),
            });
        }
        let copy = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        let frame = entry(binding::FRAME, per_frame.frame_uniforms.as_entire_binding());
        let counters = entry(binding::COUNTERS, per_frame.counters.as_entire_binding());
        let (keys, draw_groups) = match &passes.draw {
            DrawPasses::U64(draw) => {
                let keys = storage(ctx, "keys", key_bytes, copy);
                let g = draw.bind_group(
                    ctx,
                    0,
                    &[
                        frame,
                        entry(binding::KEYS, keys.as_entire_binding()),
                        counters,
                        entry(binding::KEY_WORDS, keys.as_entire_binding()),
                    ],
                );
                (Keys::U64(keys), vec![g])
            }
            DrawPasses::TwoPass32([depth, index]) => {
                let depths = storage(ctx, "keys", key_bytes, copy);
                let indices = storage(ctx, "indices", pixels * 4, copy);
                let g0 = depth.bind_group(
                    ctx,
                    0,
                    &[frame.clone(), entry(binding::DEPTHS, depths.as_entire_binding())],
                );
                let g1 = index.bind_group(
                    ctx,
                    0,
                    &[
                        frame,
                        entry(binding::DEPTHS, depths.as_entire_binding()),
                        counters,
                        entry(binding::INDICES, indices.as_entire_binding()),
                    ],
                );
                (Keys::TwoPass32 { depths, indices }, vec![g0, g1])
            }
        };
        let clear_groups = keys
            .buffers()
            .into_iter()
            .map(|buf| {
                (
                    passes.clear.bind_group(
                        ctx,
                        0,
                        &[entry(binding::CLEAR_WORDS, buf.as_entire_binding())],
                    ),
                    (buf.size() / 4).div_ceil(256) as u32,
                )
            })
            .collect();
        let image = storage(ctx, "image", pixels * 4, wgpu::BufferUsages::COPY_SRC);
        let eye_dome_group = |depths: &wgpu::Buffer| {
            passes.eye_dome.bind_group(
                ctx,
                0,
                &[
                    entry(
                        binding::EYE_DOME_PARAMS,
                        per_frame.eye_dome_uniforms.as_entire_binding(),
                    ),
                    entry(binding::EYE_DOME_DEPTH_WORDS, depths.as_entire_binding()),
                    entry(binding::EYE_DOME_IMAGE, image.as_entire_binding()),
                ],
            )
        };
        let (index_words, depth_words, _, _) = keys.words();
        let filled = (pixels * 8 <= ctx.max_binding()).then(|| {
            let filled = storage(ctx, "filled keys", pixels * 8, wgpu::BufferUsages::COPY_SRC);
            let fill_group = passes.hole_fill.bind_group(
                ctx,
                0,
                &[
                    entry(binding::FILL_PARAMS, per_frame.fill_uniforms.as_entire_binding()),
                    entry(binding::FILL_INDEX_WORDS, index_words.as_entire_binding()),
                    entry(binding::FILL_DEPTH_WORDS, depth_words.as_entire_binding()),
                    entry(binding::FILL_FILLED, filled.as_entire_binding()),
                ],
            );
            let edl_group = eye_dome_group(&filled);
            (filled, fill_group, edl_group)
        });
        let eye_dome_group = eye_dome_group(depth_words);
        ctx.check()?;
        Ok(Target {
            width,
            height,
            keys,
            clear_groups,
            draw_groups,
            filled,
            eye_dome_group,
            image,
            resolved: false,
        })
    }
}

/// The GPU rasterizer: pipelines built once, per-frame buffers, and the framebuffer of one
/// viewport size.
pub struct GpuRasterizer {
    path: AtomicPath,
    passes: Passes,
    per_frame: PerFrame,
    target: Target,
    /// Bound as the colours of a resolve dispatch when the scene holds no chunk.
    no_colors: wgpu::Buffer,
    queries: Option<Timestamps>,
    tuning: DrawTuning,
}

/// Timestamp slots: clear begin/end, draw begin/end, hole fill, resolve and eye-dome lighting
/// begin/end, plan begin/end.
const QUERIES: u32 = 12;
/// The first slot of the resolve's passes (hole fill).
const RESOLVE_QUERIES: u32 = 4;
/// The plan pass's slots.
const PLAN_QUERIES: u32 = 10;

impl GpuRasterizer {
    /// A rasterizer for `width x height` pixels on the context's atomic path.
    pub fn new(ctx: &GpuContext, width: u32, height: u32) -> Result<GpuRasterizer, GpuError> {
        let path = ctx.atomic_path();
        let shared = SharedLayouts::new(ctx);
        let draw = match path {
            AtomicPath::U64 => DrawPasses::U64(PassPipeline::new(ctx, Pass::Draw64, &shared)),
            AtomicPath::TwoPass32 => DrawPasses::TwoPass32([
                PassPipeline::new(ctx, Pass::DrawDepth32, &shared),
                PassPipeline::new(ctx, Pass::DrawIndex32, &shared),
            ]),
        };
        let passes = Passes {
            clear: PassPipeline::new(ctx, Pass::Clear, &shared),
            plan: PassPipeline::new(ctx, Pass::Plan, &shared),
            draw,
            resolve: PassPipeline::new(ctx, Pass::Resolve, &shared),
            hole_fill: PassPipeline::new(ctx, Pass::HoleFill, &shared),
            eye_dome: PassPipeline::new(ctx, Pass::EyeDome, &shared),
            shared,
        };
        let copy = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        let per_frame = PerFrame {
            frame_uniforms: uniform::<FrameUniforms>(ctx, "frame uniforms"),
            counters: storage(ctx, "counters", 8, copy),
            // Grown by the first frame that draws anything.
            records: storage(ctx, "draw records", 0, wgpu::BufferUsages::COPY_DST),
            plan_uniforms: uniform::<PlanUniforms>(ctx, "plan uniforms"),
            plan_counters: storage(ctx, "plan counters", 4 * plan_counter::WORDS as u64, copy),
            resolve_uniforms: Vec::new(),
            fill_uniforms: uniform::<HoleFillUniforms>(ctx, "hole fill uniforms"),
            eye_dome_uniforms: uniform::<EyeDomeUniforms>(ctx, "eye-dome uniforms"),
        };
        let target = Target::new(ctx, &passes, &per_frame, width, height)?;
        let queries = ctx.has_timestamps().then(|| Timestamps::new(ctx, "pass times", QUERIES));
        let no_colors = storage(ctx, "no colours", 4, wgpu::BufferUsages::empty());
        ctx.check()?;
        Ok(GpuRasterizer {
            path,
            passes,
            per_frame,
            target,
            no_colors,
            queries,
            tuning: DrawTuning::default(),
        })
    }

    /// Rebuilds the 64-bit draw pipeline with `tuning` (measurements only: see [`DrawTuning`]).
    pub fn set_tuning(&mut self, ctx: &GpuContext, tuning: DrawTuning) -> Result<(), GpuError> {
        if (tuning.kernel, tuning.workgroup) != (self.tuning.kernel, self.tuning.workgroup) {
            let DrawPasses::U64(_) = self.passes.draw else {
                return Err(GpuError::Device(
                    "draw kernels and workgroup sizes apply to the 64-bit path only".into(),
                ));
            };
            if !(32..=1024).contains(&tuning.workgroup) || tuning.kernel > 4 {
                return Err(GpuError::Device(format!("draw tuning out of range: {tuning:?}")));
            }
            let constants = [("KERNEL", tuning.kernel as f64), ("WG", tuning.workgroup as f64)];
            self.passes.draw = DrawPasses::U64(PassPipeline::with_constants(
                ctx,
                Pass::Draw64,
                &self.passes.shared,
                &constants,
            ));
            self.target = Target::new(
                ctx,
                &self.passes,
                &self.per_frame,
                self.target.width,
                self.target.height,
            )?;
        }
        self.tuning = tuning;
        ctx.check()
    }

    /// The atomic path in use.
    pub fn atomic_path(&self) -> AtomicPath {
        self.path
    }

    /// The viewport size `(width, height)` in pixels.
    pub fn size(&self) -> (u32, u32) {
        (self.target.width, self.target.height)
    }

    /// Changes the viewport size: the framebuffer (and the resolved image) are made anew, the
    /// pipelines kept. A frame must be drawn before the next read.
    pub fn resize(&mut self, ctx: &GpuContext, width: u32, height: u32) -> Result<(), GpuError> {
        if (width, height) == self.size() {
            return Ok(());
        }
        self.target = Target::new(ctx, &self.passes, &self.per_frame, width, height)?;
        Ok(())
    }

    /// The resolved image of the last frame drawn with `resolve` (RGBA8 packed
    /// `r | g << 8 | b << 16 | a << 24`, row-major, `width * height` words; a storage buffer), for
    /// passes that use it on the GPU (the window's present pass).
    pub fn image_buffer(&self) -> Option<&wgpu::Buffer> {
        self.target.resolved.then_some(&self.target.image)
    }

    /// Draws the scene for `camera` into a cleared framebuffer; with `resolve` also resolves the
    /// image from the scene's colours as [`mortar_core::render::resolve::resolve`] does (hole
    /// filling, colours, eye-dome lighting, background). Waits for the GPU.
    pub fn draw(
        &mut self,
        ctx: &GpuContext,
        scene: &mut GpuScene,
        camera: &Camera,
        options: &RasterOptions,
        resolve: Option<&ResolveOptions>,
    ) -> Result<GpuFrame, GpuError> {
        self.draw_selected(ctx, scene, None, camera, options, resolve)
    }

    /// [`draw`](Self::draw) of only the scene's batches listed in `selected` (positions in
    /// [`GpuScene::batches`], any order, each at most once; `None`: every batch). The framebuffer
    /// holds the scene's point indices as usual, so the resolve needs no change: this is how a
    /// level-of-detail selection is drawn from a scene holding every node once.
    pub fn draw_selected(
        &mut self,
        ctx: &GpuContext,
        scene: &mut GpuScene,
        selected: Option<&[u32]>,
        camera: &Camera,
        options: &RasterOptions,
        resolve: Option<&ResolveOptions>,
    ) -> Result<GpuFrame, GpuError> {
        let start = Instant::now();
        let (width, height) = self.size();
        if camera.width != width || camera.height != height {
            return Err(RasterError::Viewport {
                fb_width: width,
                fb_height: height,
                width: camera.width,
                height: camera.height,
            }
            .into());
        }
        if let Some(r) = resolve {
            self.check_resolve(ctx, scene, r)?;
        }
        scene.flush(ctx)?;
        let record_size = std::mem::size_of::<DrawRecord>() as u64;
        let mut stats = RasterStats::default();
        // Every batch planned on the GPU (the plan pass writes the records) or, for a selection or
        // when asked, on the host with the same plan.
        let on_gpu = selected.is_none() && self.tuning.plan_on_gpu && !scene.batches.is_empty();
        let ranges: Vec<(usize, usize, usize)> = if on_gpu {
            Planner::new(camera, scene.grid(), options)?;
            let f = &mut self.per_frame;
            let needed = (scene.records_total as u64 * record_size).max(record_size);
            if f.records.size() < needed {
                let size = grown_size(ctx, f.records.size(), needed);
                f.records = storage(ctx, "draw records", size, wgpu::BufferUsages::COPY_DST);
            }
            let mut u = PlanUniforms::new(
                camera,
                scene.grid(),
                options,
                self.tuning.division.unwrap_or(ctx.division()),
            );
            u.batches = scene.batches.len() as u32;
            ctx.queue.write_buffer(&f.plan_uniforms, 0, bytemuck::bytes_of(&u));
            ctx.queue.write_buffer(&f.plan_counters, 0, &[0u8; 4 * plan_counter::WORDS]);
            stats.batches = scene.batches.len() as u64;
            scene
                .record_ranges
                .iter()
                .enumerate()
                .filter(|r| r.1 .1 > 0)
                .map(|(chunk, &(first, count))| (chunk, first as usize, count as usize))
                .collect()
        } else {
            self.plan_on_host(ctx, scene, selected, camera, options, &mut stats)?
        };
        let plan_seconds = start.elapsed().as_secs_f64();
        if let Some(r) = ranges.iter().find(|r| r.2 as u64 * record_size > ctx.max_binding()) {
            return Err(GpuError::TooLarge {
                what: "one chunk's draw records",
                needed: r.2 as u64 * record_size,
                limit: ctx.max_binding(),
            });
        }
        let f = &mut self.per_frame;
        ctx.queue.write_buffer(
            &f.frame_uniforms,
            0,
            bytemuck::bytes_of(&FrameUniforms::new(
                camera,
                self.tuning.division.unwrap_or(ctx.division()),
            )),
        );
        ctx.queue.write_buffer(&f.counters, 0, &[0u8; 8]);
        let f = &self.per_frame;
        let t = &self.target;
        let passes = &self.passes;
        let queries = self.queries.as_ref();

        let dev = &ctx.device;
        let mut enc =
            dev.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        if on_gpu {
            let Some(plan_batches) = &scene.plan_buffer else {
                return Err(GpuError::Device("the scene's plan batches were not written".into()));
            };
            let group = passes.plan.bind_group(
                ctx,
                0,
                &[
                    entry(binding::PLAN_PARAMS, f.plan_uniforms.as_entire_binding()),
                    entry(binding::PLAN_BATCHES, plan_batches.as_entire_binding()),
                    entry(binding::PLAN_RECORDS, f.records.as_entire_binding()),
                    entry(binding::PLAN_COUNTERS, f.plan_counters.as_entire_binding()),
                ],
            );
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("plan"),
                timestamp_writes: queries
                    .map(|q| q.writes(Some(PLAN_QUERIES), Some(PLAN_QUERIES + 1))),
            });
            pass.set_pipeline(passes.plan.pipeline());
            pass.set_bind_group(0, &group, &[]);
            let (x, y) = ctx.split_dispatch((scene.batches.len() as u32).div_ceil(256));
            pass.dispatch_workgroups(x, y, 1);
        }
        // Clear.
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("clear"),
                timestamp_writes: queries.map(|q| q.writes(Some(0), Some(1))),
            });
            pass.set_pipeline(passes.clear.pipeline());
            for (bg, n) in &t.clear_groups {
                let (x, y) = ctx.split_dispatch(*n);
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        // Draw: one pass per step (the 32-bit path's second step must see the first's depths),
        // every step with the same batches bind groups (one per chunk).
        let batches: Vec<(wgpu::BindGroup, u32)> = ranges
            .iter()
            .map(|&(chunk, first, count)| {
                let rec = wgpu::BufferBinding {
                    buffer: &f.records,
                    offset: first as u64 * record_size,
                    size: NonZeroU64::new(count as u64 * record_size),
                };
                (batches_group(ctx, &passes.shared, rec, &scene.chunks[chunk].words), count as u32)
            })
            .collect();
        let steps = passes.draw.steps();
        for (step, (pipe, group0)) in steps.iter().zip(&t.draw_groups).enumerate() {
            let ts = queries.map(|q| {
                q.writes((step == 0).then_some(2), (step + 1 == steps.len()).then_some(3))
            });
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(pipe.pass().file()),
                timestamp_writes: ts,
            });
            pass.set_pipeline(pipe.pipeline());
            pass.set_bind_group(0, group0, &[]);
            for (bg, n) in &batches {
                let (x, y) = ctx.split_dispatch(*n);
                pass.set_bind_group(1, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        if let Some(r) = resolve {
            self.encode_resolve(ctx, &mut enc, scene, r)?;
        }
        let counters_read = readback(ctx, &mut enc, &self.per_frame.counters, 8);
        let plan_read = on_gpu.then(|| {
            readback(ctx, &mut enc, &self.per_frame.plan_counters, 4 * plan_counter::WORDS as u64)
        });
        let times_read = self.queries.as_ref().map(|q| {
            enc.resolve_query_set(&q.set, 0..QUERIES, &q.buffer, 0);
            readback(ctx, &mut enc, &q.buffer, QUERIES as u64 * 8)
        });
        ctx.queue.submit([enc.finish()]);
        let counters = map_read(ctx, &counters_read)?;
        let c: &[u32] = bytemuck::cast_slice(&counters);
        stats.points_drawn = c[0] as u64 | (c[1] as u64) << 32;
        if let Some(buf) = plan_read {
            let pc: Vec<u32> = bytemuck::pod_collect_to_vec(&map_read(ctx, &buf)?);
            stats.batches_culled = pc[plan_counter::CULLED] as u64;
            stats.batches_drawn = pc[plan_counter::DRAWN] as u64;
            for w in 0..3 {
                stats.points_by_precision[w] = pc[plan_counter::POINTS_BY_WORDS + w] as u64;
            }
        }
        let timings = match times_read {
            Some(buf) => {
                let t: Vec<u64> = bytemuck::pod_collect_to_vec(&map_read(ctx, &buf)?);
                let period = ctx.queue.get_timestamp_period() as f64 * 1e-6;
                let ms = |a: usize| t[a + 1].saturating_sub(t[a]) as f64 * period;
                let post = resolve.map(|r| resolve_timings(&t, period, r));
                Some(GpuTimings {
                    clear_ms: ms(0),
                    draw_ms: ms(2),
                    resolve_ms: post.map(|p| p.1),
                    hole_fill_ms: post.and_then(|p| p.0),
                    eye_dome_ms: post.and_then(|p| p.2),
                    plan_ms: on_gpu.then(|| ms(PLAN_QUERIES as usize)),
                })
            }
            None => None,
        };
        ctx.check()?;
        Ok(GpuFrame { stats, timings, plan_seconds, frame_seconds: start.elapsed().as_secs_f64() })
    }

    /// Plans the batches (all, or those `selected`) on the host, writes their records per chunk
    /// (each chunk's records starting at a storage-offset boundary; padding records have no
    /// points) and returns the chunks' record ranges `(chunk, first record, count)`.
    fn plan_on_host(
        &mut self,
        ctx: &GpuContext,
        scene: &GpuScene,
        selected: Option<&[u32]>,
        camera: &Camera,
        options: &RasterOptions,
        stats: &mut RasterStats,
    ) -> Result<Vec<(usize, usize, usize)>, GpuError> {
        let planner = Planner::new(camera, scene.grid(), options)?;
        // The batches to draw, in scene order (so that each chunk's records are contiguous).
        let order: Vec<u32> = match selected {
            None => (0..scene.batches.len() as u32).collect(),
            Some(ids) => {
                let mut v = ids.to_vec();
                v.sort_unstable();
                v.dedup();
                if let Some(&bad) = v.iter().find(|&&i| i as usize >= scene.batches.len()) {
                    return Err(GpuError::Selection(format!(
                        "batch {bad} selected, but the scene holds {}",
                        scene.batches.len()
                    )));
                }
                v
            }
        };
        let plans: Vec<BatchPlan> = order
            .par_iter()
            .map(|&i| {
                let b = &scene.batches[i as usize];
                planner.plan(&b.grid, &b.bounds, b.count as usize)
            })
            .collect();
        stats.batches = plans.len() as u64;
        let align = ctx.limits().min_storage_buffer_offset_alignment.max(1) as usize;
        let mut records: Vec<DrawRecord> = Vec::new();
        let mut ranges: Vec<(usize, usize, usize)> = Vec::new();
        for (b, plan) in order.iter().map(|&i| &scene.batches[i as usize]).zip(&plans) {
            match plan {
                BatchPlan::Empty => {}
                BatchPlan::Culled => stats.batches_culled += 1,
                BatchPlan::Draw { precision, projection } => {
                    stats.batches_drawn += 1;
                    stats.points_by_precision[precision.words() - 1] += b.count as u64;
                    match ranges.last_mut() {
                        Some(r) if r.0 == b.chunk as usize => r.2 += 1,
                        _ => {
                            while !(records.len() * std::mem::size_of::<DrawRecord>())
                                .is_multiple_of(align)
                            {
                                records.push(bytemuck::Zeroable::zeroed());
                            }
                            ranges.push((b.chunk as usize, records.len(), 1));
                        }
                    }
                    records.push(DrawRecord {
                        projection: *projection,
                        offset: b.offset,
                        count: b.count,
                        first_index: b.first_index,
                        _pad: 0,
                    });
                }
            }
        }
        if self.tuning.order != RecordOrder::Scene {
            for &(_, first, count) in &ranges {
                let part = records[first..first + count].to_vec();
                for (dst, src) in self.tuning.order.permutation(count).into_iter().enumerate() {
                    records[first + dst] = part[src];
                }
            }
        }
        let record_size = std::mem::size_of::<DrawRecord>() as u64;
        let f = &mut self.per_frame;
        let needed = (records.len() as u64 * record_size).max(record_size);
        if f.records.size() < needed {
            let size = grown_size(ctx, f.records.size(), needed);
            f.records = storage(ctx, "draw records", size, wgpu::BufferUsages::COPY_DST);
        }
        if !records.is_empty() {
            ctx.queue.write_buffer(&f.records, 0, bytemuck::cast_slice(&records));
        }
        Ok(ranges)
    }

    /// Resolves the framebuffer as it is (the last frame drawn) again, with `options` and the
    /// scene's colours as they are now: for callers that choose colours after seeing the keys
    /// (`mortar render` colours scalar modes by the visible points' percentiles), then
    /// [`GpuScene::set_colors`]. Waits for the GPU; returns the passes' times (hole fill,
    /// resolve, eye-dome lighting) where the device has timestamps.
    pub fn resolve(
        &mut self,
        ctx: &GpuContext,
        scene: &mut GpuScene,
        options: &ResolveOptions,
    ) -> Result<Option<GpuTimings>, GpuError> {
        self.check_resolve(ctx, scene, options)?;
        scene.flush(ctx)?;
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("resolve") });
        self.encode_resolve(ctx, &mut enc, scene, options)?;
        let times_read = self.queries.as_ref().map(|q| {
            enc.resolve_query_set(&q.set, 0..QUERIES, &q.buffer, 0);
            readback(ctx, &mut enc, &q.buffer, QUERIES as u64 * 8)
        });
        ctx.queue.submit([enc.finish()]);
        let timings = match times_read {
            Some(buf) => {
                let t: Vec<u64> = bytemuck::pod_collect_to_vec(&map_read(ctx, &buf)?);
                let period = ctx.queue.get_timestamp_period() as f64 * 1e-6;
                let (hole_fill_ms, resolve_ms, eye_dome_ms) = resolve_timings(&t, period, options);
                Some(GpuTimings {
                    clear_ms: 0.0,
                    draw_ms: 0.0,
                    resolve_ms: Some(resolve_ms),
                    hole_fill_ms,
                    eye_dome_ms,
                    plan_ms: None,
                })
            }
            None => {
                ctx.wait()?;
                None
            }
        };
        ctx.check()?;
        Ok(timings)
    }

    /// Whether `scene` and this rasterizer can resolve with `options`.
    fn check_resolve(
        &self,
        ctx: &GpuContext,
        scene: &GpuScene,
        options: &ResolveOptions,
    ) -> Result<(), GpuError> {
        if !scene.has_colors() {
            return Err(GpuError::Colors("resolve asked for but the scene has no colours".into()));
        }
        if options.hole_fill.is_some() && self.target.filled.is_none() {
            let needed = self.target.width as u64 * self.target.height as u64 * 8;
            return Err(GpuError::TooLarge {
                what: "the hole-filled keys",
                needed,
                limit: ctx.max_binding(),
            });
        }
        Ok(())
    }

    /// Records the resolve's passes into `enc`: hole filling (the framebuffer into the filled
    /// keys), one colour dispatch per chunk from the filled keys or the framebuffer, eye-dome
    /// lighting of the image from the same keys' depths.
    fn encode_resolve(
        &mut self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        scene: &GpuScene,
        options: &ResolveOptions,
    ) -> Result<(), GpuError> {
        let (width, height) = self.size();
        let pixels = width as u64 * height as u64;
        let t = &mut self.target;
        let passes = &self.passes;
        let queries = self.queries.as_ref();
        let f = &mut self.per_frame;
        let (split_x, split_y) = ctx.split_dispatch(pixels.div_ceil(256) as u32);
        let (index_words, depth_words, stride, depth_offset) = t.keys.words();
        // Where the colours and the eye-dome depths are read from.
        let (index_buf, depth_buf, stride, depth_offset, eye_dome_group) =
            match (&options.hole_fill, &t.filled) {
                (Some(fill), Some((filled, fill_group, edl_group))) => {
                    let u = HoleFillUniforms::new(fill, width, height, stride, depth_offset);
                    ctx.queue.write_buffer(&f.fill_uniforms, 0, bytemuck::bytes_of(&u));
                    let slots = (Some(RESOLVE_QUERIES), Some(RESOLVE_QUERIES + 1));
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("hole fill"),
                        timestamp_writes: queries.map(|q| q.writes(slots.0, slots.1)),
                    });
                    pass.set_pipeline(passes.hole_fill.pipeline());
                    pass.set_bind_group(0, fill_group, &[]);
                    pass.dispatch_workgroups(split_x, split_y, 1);
                    (filled, filled, 2, 1, edl_group)
                }
                (Some(_), None) => {
                    return Err(GpuError::TooLarge {
                        what: "the hole-filled keys",
                        needed: pixels * 8,
                        limit: ctx.max_binding(),
                    })
                }
                (None, _) => (index_words, depth_words, stride, depth_offset, &t.eye_dome_group),
            };
        // Colours: one dispatch per chunk.
        while f.resolve_uniforms.len() < scene.chunks.len().max(1) {
            f.resolve_uniforms.push(uniform::<ResolveUniforms>(ctx, "resolve uniforms"));
        }
        let chunk_list: Vec<(u32, u32, Option<&wgpu::Buffer>)> = if scene.chunks.is_empty() {
            vec![(0, 0, Some(&self.no_colors))]
        } else {
            scene.chunks.iter().map(|c| (c.first_index, c.len, c.colors.as_ref())).collect()
        };
        let mut groups = Vec::with_capacity(chunk_list.len());
        for (i, (first_index, count, colors)) in chunk_list.into_iter().enumerate() {
            // Checked by check_resolve: a scene with colours has them in every chunk.
            let Some(colors) = colors else {
                return Err(GpuError::Colors("a chunk of the scene has no colours".into()));
            };
            let u = ResolveUniforms {
                width,
                height,
                key_stride: stride,
                depth_offset,
                first_index,
                count,
                background: options.background,
                write_background: (i == 0) as u32,
            };
            ctx.queue.write_buffer(&f.resolve_uniforms[i], 0, bytemuck::bytes_of(&u));
            groups.push(passes.resolve.bind_group(
                ctx,
                0,
                &[
                    entry(binding::RESOLVE_PARAMS, f.resolve_uniforms[i].as_entire_binding()),
                    entry(binding::RESOLVE_INDEX_WORDS, index_buf.as_entire_binding()),
                    entry(binding::RESOLVE_DEPTH_WORDS, depth_buf.as_entire_binding()),
                    entry(binding::RESOLVE_COLORS, colors.as_entire_binding()),
                    entry(binding::RESOLVE_IMAGE, t.image.as_entire_binding()),
                ],
            ));
        }
        {
            let slots = (Some(RESOLVE_QUERIES + 2), Some(RESOLVE_QUERIES + 3));
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("resolve"),
                timestamp_writes: queries.map(|q| q.writes(slots.0, slots.1)),
            });
            pass.set_pipeline(passes.resolve.pipeline());
            for bg in &groups {
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(split_x, split_y, 1);
            }
        }
        if let Some(edl) = &options.eye_dome {
            let u = EyeDomeUniforms::new(edl, width, height, stride, depth_offset);
            ctx.queue.write_buffer(&f.eye_dome_uniforms, 0, bytemuck::bytes_of(&u));
            let slots = (Some(RESOLVE_QUERIES + 4), Some(RESOLVE_QUERIES + 5));
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("eye-dome lighting"),
                timestamp_writes: queries.map(|q| q.writes(slots.0, slots.1)),
            });
            pass.set_pipeline(passes.eye_dome.pipeline());
            pass.set_bind_group(0, eye_dome_group, &[]);
            pass.dispatch_workgroups(split_x, split_y, 1);
        }
        t.resolved = true;
        Ok(())
    }

    /// The hole-filled keys of the last frame resolved with hole filling, as
    /// [`mortar_core::render::resolve::fill_holes`] returns them (what the resolve's colours and
    /// eye-dome lighting read).
    pub fn read_filled_keys(&self, ctx: &GpuContext) -> Result<Vec<u64>, GpuError> {
        let pixels = self.target.width as u64 * self.target.height as u64;
        let Some((filled, _, _)) = &self.target.filled else {
            return Err(GpuError::TooLarge {
                what: "the hole-filled keys",
                needed: pixels * 8,
                limit: ctx.max_binding(),
            });
        };
        let pixels = self.target.width as usize * self.target.height as usize;
        let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("read filled keys"),
        });
        let buf = readback(ctx, &mut enc, filled, filled.size());
        ctx.queue.submit([enc.finish()]);
        Ok(bytemuck::pod_collect_to_vec::<u8, u64>(&map_read(ctx, &buf)?)[..pixels].to_vec())
    }

    /// The framebuffer's keys as the CPU rasterizer writes them (`depth bits << 32 | index`,
    /// [`EMPTY_KEY`] for an empty pixel), row-major from the top-left pixel.
    pub fn read_keys(&self, ctx: &GpuContext) -> Result<Vec<u64>, GpuError> {
        let pixels = self.target.width as usize * self.target.height as usize;
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("read keys") });
        match &self.target.keys {
            Keys::U64(keys) => {
                let keys = readback(ctx, &mut enc, keys, keys.size());
                ctx.queue.submit([enc.finish()]);
                Ok(bytemuck::pod_collect_to_vec::<u8, u64>(&map_read(ctx, &keys)?)[..pixels]
                    .to_vec())
            }
            Keys::TwoPass32 { depths, indices } => {
                let d = readback(ctx, &mut enc, depths, depths.size());
                let i = readback(ctx, &mut enc, indices, indices.size());
                ctx.queue.submit([enc.finish()]);
                let d: Vec<u32> = bytemuck::pod_collect_to_vec(&map_read(ctx, &d)?);
                let i: Vec<u32> = bytemuck::pod_collect_to_vec(&map_read(ctx, &i)?);
                Ok((0..pixels)
                    .map(|p| {
                        if d[p] == u32::MAX {
                            EMPTY_KEY
                        } else {
                            (d[p] as u64) << 32 | i[p] as u64
                        }
                    })
                    .collect())
            }
        }
    }

    /// The resolved image (RGBA8 packed `r | g << 8 | b << 16 | a << 24`, row-major) of the last
    /// frame drawn with `resolve`.
    pub fn read_image(&self, ctx: &GpuContext) -> Result<Vec<u32>, GpuError> {
        let Some(image) = self.image_buffer() else {
            return Err(GpuError::Colors("no frame was resolved yet".into()));
        };
        read_image_buffer(ctx, image, self.target.width, self.target.height)
    }
}

/// The resolve's pass times `(hole fill, resolve, eye-dome lighting)` in milliseconds from the
/// timestamps `t` (ticks of `period` ms), the passes `options` did not run `None`.
fn resolve_timings(
    t: &[u64],
    period: f64,
    options: &ResolveOptions,
) -> (Option<f64>, f64, Option<f64>) {
    let ms = |a: u32| t[a as usize + 1].saturating_sub(t[a as usize]) as f64 * period;
    (
        options.hole_fill.map(|_| ms(RESOLVE_QUERIES)),
        ms(RESOLVE_QUERIES + 2),
        options.eye_dome.map(|_| ms(RESOLVE_QUERIES + 4)),
    )
}
