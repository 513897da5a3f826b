//! The progressive renderer of paper 000 on the GPU ([`GpuProgressive`]): made with its shuffled
//! buffer and passes, it inserts points (the Distribute step), draws frames (clear, Reproject,
//! Fill, Prepare and the resolve, with the adaptive budget's two submissions), re-encodes the
//! buffer when the frame grows, counts depth ties and reads back keys, images and visible slots.
//! See the documentation of [`progressive`](super).

use super::device::{round_up, Dispatch, GpuState, Passes, PerFrame, SlotChunk, QUERIES};
use super::error::ProgressiveGpuError;
use super::frame::{BudgetTiming, GpuProgressiveFrame, ProgressiveGpuTimings};
use super::insert::{
    encode_records, InsertPreparer, PreparedInsert, RecordPool, SortedSlots, ENCODED,
};
use super::options::ProgressiveOptions;
use super::slots::SlotBook;
use super::target::{Resolved, Target};
use super::upload::{Uploads, STAGING_POINTS};
use crate::buffers::{map_read, read_image_buffer, readback};
use crate::context::{AtomicPath, GpuContext, GpuError};
use crate::pipeline::{entry, storage, uniform, PassPipeline, SharedLayouts, Timestamps};
use crate::scene::MAX_CHUNK_POINTS;
use crate::shaders::{binding, Pass};
use mortar_core::grid::Grid;
use mortar_core::quantize::BatchGrid;
use mortar_core::render::gpu::{
    DrawRecord, EyeDomeUniforms, FrameUniforms, HoleFillUniforms, PrepareUniforms, ReframeUniforms,
    ResolveUniforms, ScatterUniforms,
};
use mortar_core::render::progressive::{
    FillBudget, ProbeTimings, ProgressiveError, ProgressiveFrame, ProgressiveState, Shuffle,
};
use mortar_core::render::resolve::ResolveOptions;
use mortar_core::render::{
    Aabb, BatchPlan, Camera, Planner, RasterError, RasterOptions, RasterStats,
};
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// The progressive renderer of paper 000 on the GPU (see the documentation of
/// [`progressive`](super)).
pub struct GpuProgressive {
    /// The shuffle, the frame, the points loaded, Fill's cursor, the view and the slots drawn
    /// since it changed: the state the CPU renderer shares.
    state: ProgressiveState,
    options: ProgressiveOptions,
    chunk_slots: u32,
    slots: SlotBook,
    payload: Option<Vec<AtomicU64>>,
    gpu: GpuState,
    /// `None` until the first frame gives the viewport size.
    target: Option<Target>,
    /// `None` until a frame of the current target is drawn with `resolve`.
    resolved: Option<Resolved>,
    /// Entries of each chunk's list after the last Prepare.
    list_counts: Vec<u32>,
    /// The staging memory of the uploads and those in flight.
    uploads: Uploads,
    /// Record buffers of prepared inserts, handed back for the next ones.
    record_pool: RecordPool,
}

impl GpuProgressive {
    /// A renderer for `capacity` points whose integer coordinates (on `grid`) lie in `[min, max]`
    /// (the quantization frame and the planner's bounds, as
    /// [`ProgressiveRenderer::new`](mortar_core::render::progressive::ProgressiveRenderer::new)
    /// takes them; points outside grow it). Allocates the whole shuffled buffer on the GPU and
    /// marks every slot unloaded.
    pub fn new(
        ctx: &GpuContext,
        grid: Grid,
        min: [i32; 3],
        max: [i32; 3],
        capacity: u64,
        options: ProgressiveOptions,
    ) -> Result<GpuProgressive, ProgressiveGpuError> {
        GpuProgressive::with_frame(ctx, ProgressiveFrame::exact(grid, min, max)?, capacity, options)
    }

    /// A renderer for `capacity` points in `frame` (e.g. [`ProgressiveFrame::around`] the headers'
    /// box), as
    /// [`ProgressiveRenderer::with_frame`](mortar_core::render::progressive::ProgressiveRenderer::with_frame).
    pub fn with_frame(
        ctx: &GpuContext,
        frame: ProgressiveFrame,
        capacity: u64,
        options: ProgressiveOptions,
    ) -> Result<GpuProgressive, ProgressiveGpuError> {
        if ctx.atomic_path() != AtomicPath::U64 {
            return Err(ProgressiveGpuError::Needs64BitAtomics {
                adapter: ctx.adapter().name.clone(),
            });
        }
        let state = ProgressiveState::new(frame, capacity)?;
        let len = state.shuffle().len();
        let by_device =
            ((ctx.max_binding() / 4).min(MAX_CHUNK_POINTS as u64) as u32 & !255).max(256);
        let chunk_slots = options.chunk_slots.unwrap_or(by_device).clamp(1, by_device);
        let shared = SharedLayouts::new(ctx);
        let passes = Passes {
            clear: PassPipeline::new(ctx, Pass::Clear, &shared),
            unload: PassPipeline::new(ctx, Pass::ProgressiveUnload, &shared),
            scatter: PassPipeline::new(ctx, Pass::ProgressiveScatter, &shared),
            reproject: PassPipeline::new(ctx, Pass::ProgressiveReproject, &shared),
            fill: PassPipeline::new(ctx, Pass::ProgressiveFill, &shared),
            prepare: PassPipeline::new(ctx, Pass::ProgressivePrepare, &shared),
            resolve: PassPipeline::new(ctx, Pass::Resolve, &shared),
            reframe: PassPipeline::new(ctx, Pass::ProgressiveReframe, &shared),
            hole_fill: PassPipeline::new(ctx, Pass::HoleFill, &shared),
            eye_dome: PassPipeline::new(ctx, Pass::EyeDome, &shared),
            ties: PassPipeline::new(ctx, Pass::ProgressiveTies, &shared),
            shared,
        };
        let dev = &ctx.device;
        let mut chunks = Vec::new();
        let mut first = 0u64;
        while first < len as u64 {
            let n = (len as u64 - first).min(chunk_slots as u64) as u32;
            let make =
                |label: &str| storage(ctx, label, n as u64 * 4, wgpu::BufferUsages::COPY_DST);
            let words = [
                make("shuffled coarse words"),
                make("shuffled medium words"),
                make("shuffled fine words"),
            ];
            let colors = options.colors.then(|| make("shuffled colours"));
            chunks.push(SlotChunk { words, colors, first: first as u32, len: n });
            first += n as u64;
        }
        ctx.check()?;
        // Every slot unloaded.
        let mut enc =
            dev.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("unload") });
        {
            let groups: Vec<(wgpu::BindGroup, u32)> = chunks
                .iter()
                .map(|c| {
                    (
                        passes.unload.bind_group(
                            ctx,
                            0,
                            &[entry(binding::UNLOAD_COARSE, c.words[0].as_entire_binding())],
                        ),
                        c.len.div_ceil(256),
                    )
                })
                .collect();
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("unload"),
                timestamp_writes: None,
            });
            pass.set_pipeline(passes.unload.pipeline());
            for (bg, n) in &groups {
                let (x, y) = ctx.split_dispatch(*n);
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        ctx.queue.submit([enc.finish()]);
        let copy = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        let scatter_uniform_stride = round_up(
            std::mem::size_of::<ScatterUniforms>() as u64,
            ctx.limits().min_uniform_buffer_offset_alignment.max(4) as u64,
        );
        let scatter_uniforms = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("scatter uniforms"),
            size: scatter_uniform_stride * chunks.len().max(1) as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let align = ctx.limits().min_storage_buffer_offset_alignment.max(4) as u64;
        let record_size = std::mem::size_of::<DrawRecord>() as u64;
        let record_stride = round_up(record_size, align);
        // Reproject: one record per chunk; each Fill step: at most one per chunk plus one for the
        // run that wraps around inside a chunk.
        let max_records = 3 * chunks.len().max(1) as u64 + 2;
        let per_frame = PerFrame {
            frame_uniforms: uniform::<FrameUniforms>(ctx, "frame uniforms"),
            counters: storage(ctx, "progressive counters", 8, copy),
            records: storage(
                ctx,
                "progressive draw records",
                max_records * record_stride,
                wgpu::BufferUsages::COPY_DST,
            ),
            record_stride,
            prepare_uniforms: uniform::<PrepareUniforms>(ctx, "prepare uniforms"),
            list_counts: storage(ctx, "visible list counts", chunks.len().max(1) as u64 * 4, copy),
            resolve_uniforms: if options.colors {
                (0..chunks.len().max(1))
                    .map(|_| uniform::<ResolveUniforms>(ctx, "resolve uniforms"))
                    .collect()
            } else {
                Vec::new()
            },
            fill_uniforms: uniform::<HoleFillUniforms>(ctx, "hole fill uniforms"),
            eye_dome_uniforms: uniform::<EyeDomeUniforms>(ctx, "eye-dome uniforms"),
        };
        let queries = (ctx.has_timestamps() && !options.host_clock)
            .then(|| Timestamps::new(ctx, "progressive pass times", QUERIES));
        let n = len as usize;
        let r = GpuProgressive {
            state,
            options,
            chunk_slots,
            list_counts: vec![0; chunks.len()],
            gpu: GpuState {
                chunks,
                passes,
                per_frame,
                scatter_uniforms,
                scatter_uniform_stride,
                dummy: storage(ctx, "unused", 4, wgpu::BufferUsages::empty()),
                queries,
            },
            slots: SlotBook::new(n),
            payload: options.payloads.then(|| (0..n).map(|_| AtomicU64::new(0)).collect()),
            target: None,
            resolved: None,
            uploads: Uploads::new(ctx),
            record_pool: Default::default(),
        };
        ctx.wait()?;
        Ok(r)
    }

    /// The state the renderer shares with the CPU renderer: shuffle, frame, points loaded,
    /// Fill's cursor, view, slots drawn since it changed.
    pub fn state(&self) -> &ProgressiveState {
        &self.state
    }

    /// Number of points the renderer holds once everything arrived.
    pub fn capacity(&self) -> u64 {
        self.state.capacity()
    }

    /// Points inserted so far.
    pub fn loaded(&self) -> u64 {
        self.state.loaded()
    }

    /// The shuffle placing input index `i` at slot `shuffle().target(i)`.
    pub fn shuffle(&self) -> &Shuffle {
        self.state.shuffle()
    }

    /// The quantization frame of the words.
    pub fn quantization(&self) -> &BatchGrid {
        &self.state.frame().quant
    }

    /// The frame: quantization, bounds, and the box of the points expected and arrived.
    pub fn frame_state(&self) -> &ProgressiveFrame {
        self.state.frame()
    }

    /// World bounds of the frame.
    pub fn bounds(&self) -> &Aabb {
        &self.state.frame().bounds
    }

    /// How often the frame grew to hold points outside it.
    pub fn growths(&self) -> u32 {
        self.state.growths()
    }

    /// Frames drawn so far.
    pub fn frames(&self) -> u64 {
        self.state.frames()
    }

    /// Chunks of the shuffled buffer.
    pub fn chunk_count(&self) -> usize {
        self.gpu.chunks.len()
    }

    /// Slots per full chunk.
    pub fn chunk_slots(&self) -> u32 {
        self.chunk_slots
    }

    /// Bytes of GPU memory of the shuffled buffer.
    pub fn gpu_bytes(&self) -> u64 {
        self.gpu.chunks.iter().map(|c| c.len as u64 * 4 * (3 + c.colors.is_some() as u64)).sum()
    }

    /// How the adaptive budget's timings are measured on this device.
    pub fn timing(&self) -> BudgetTiming {
        self.gpu.timing()
    }

    /// Whether slot `slot` holds a point.
    pub fn is_loaded(&self, slot: u32) -> bool {
        self.slots.is_loaded(slot)
    }

    /// The payload of the point in slot `slot`, if loaded and the renderer keeps payloads.
    pub fn payload(&self, slot: u32) -> Option<u64> {
        let p = self.payload.as_ref()?;
        self.is_loaded(slot).then(|| p[slot as usize].load(Ordering::Relaxed))
    }

    /// Whether the last frame's image is final (see
    /// [`FrameStats::converged`](mortar_core::render::progressive::FrameStats::converged)).
    pub fn converged(&self) -> bool {
        self.state.converged()
    }

    /// The payloads of every point inserted so far, in slot order (empty when the renderer keeps
    /// no payloads), as the CPU renderer's
    /// [`loaded_payloads`](mortar_core::render::progressive::ProgressiveRenderer::loaded_payloads).
    pub fn loaded_payloads(&self) -> Vec<u64> {
        let Some(p) = &self.payload else { return Vec::new() };
        p.par_iter()
            .enumerate()
            .filter(|(s, _)| self.is_loaded(*s as u32))
            .map(|(_, v)| v.load(Ordering::Relaxed))
            .collect()
    }

    /// The viewport size `(width, height)` of the last frame (`(0, 0)` before the first).
    pub fn size(&self) -> (u32, u32) {
        self.target.as_ref().map_or((0, 0), |t| (t.width, t.height))
    }

    /// The resolved image of the last frame drawn with `resolve` (RGBA8 packed
    /// `r | g << 8 | b << 16 | a << 24`, row-major, `width * height` words; a storage buffer), for
    /// [`WindowSurface::present_image`](crate::present::WindowSurface::present_image).
    pub fn image_buffer(&self) -> Option<&wgpu::Buffer> {
        self.resolved.as_ref().map(|r| &r.image)
    }

    /// Inserts points `first..first + xyz.len()` of the input (integer coordinates on the grid)
    /// at their shuffled slots, with one RGBA8 colour each when the renderer has colours and one
    /// payload each when it keeps payloads. Checks everything before changing anything (the CPU
    /// renderer's errors). The points are on the GPU when this returns (submitted).
    /// The same as [`preparer`](Self::preparer)`().prepare(..)` then
    /// [`insert_prepared`](Self::insert_prepared), in one pass (the words are encoded straight
    /// into staging memory); the two halves let a caller do the costly one on another thread
    /// while frames are drawn.
    pub fn insert(
        &mut self,
        ctx: &GpuContext,
        first: u64,
        xyz: &[[i32; 3]],
        colors: Option<&[u32]>,
        payload: Option<&[u64]>,
    ) -> Result<(), ProgressiveGpuError> {
        self.preparer().check(first, xyz, colors, payload, false)?;
        let n = xyz.len();
        if let Some(k) = self.slots.arrived.first_in(first, first + n as u64) {
            return Err(ProgressiveError::Duplicate(k).into());
        }
        // Points outside the frame grow it: the slots held are re-encoded on the GPU first.
        let gpu = &self.gpu;
        self.state.grow_for(xyz, |from, to| {
            Self::reframe(ctx, gpu, &from.quant, to).map_err(ProgressiveGpuError::from)
        })?;
        let prep = self.preparer();
        // The words encoded straight into the staging memory, then the slots for the bits
        // (the GPU copies and scatters the last uploads meanwhile).
        let frame = self.state.frame().quant;
        let stride = 3 + colors.is_some() as usize;
        let mut s = 0;
        while s < n {
            let e = (s + STAGING_POINTS).min(n);
            self.uploads.upload(
                ctx,
                &self.gpu,
                self.state.shuffle().prime().unwrap_or(0),
                first + s as u64,
                e - s,
                stride,
                false,
                |k, m, out| {
                    ENCODED.with_borrow_mut(|buf| {
                        buf.resize(m * stride, 0);
                        encode_records(
                            &frame,
                            &xyz[s + k..s + k + m],
                            colors.map(|c| &c[s + k..s + k + m]),
                            buf,
                        );
                        out.copy_from_slice(bytemuck::cast_slice(buf));
                    })
                },
            )?;
            s = e;
        }
        let slots = SortedSlots::new(prep.bit_words, first as u32, n, |i| prep.shuffle.target(i));
        self.finish_insert(first, n, &slots, payload);
        Ok(())
    }

    /// The host's bookkeeping of an insert whose points are on their way: the loaded bits, the
    /// payloads, the ranges that arrived.
    fn finish_insert(
        &mut self,
        first: u64,
        n: usize,
        slots: &SortedSlots,
        payload: Option<&[u64]>,
    ) {
        if let (Some(store), Some(values)) = (&self.payload, payload) {
            let shuffle = *self.state.shuffle();
            values.par_iter().enumerate().with_min_len(4096).for_each(|(k, &v)| {
                store[shuffle.target((first + k as u64) as u32) as usize]
                    .store(v, Ordering::Relaxed)
            });
        }
        self.slots.arrive(first, n, slots);
        self.state.add_loaded(n);
    }

    /// What [`InsertPreparer::prepare`] needs of this renderer (a few numbers, `Send`).
    pub fn preparer(&self) -> InsertPreparer {
        let frame = self.state.frame();
        InsertPreparer {
            frame: frame.quant,
            frame_max: frame.max,
            shuffle: *self.state.shuffle(),
            options: self.options,
            bit_words: self.slots.loaded_bits.len(),
            pool: self.record_pool.clone(),
        }
    }

    /// Inserts points prepared by [`InsertPreparer::prepare`] (from this renderer's
    /// [`preparer`](Self::preparer)): refuses points that arrived already (nothing changed), then
    /// uploads the staged words, which the scatter pass puts into their slots (computed on the
    /// GPU), and sets the host's bit per slot from the prepared, sorted slots. The host's share
    /// here is a parallel copy into wgpu's staging memory and the bits (about a third of
    /// [`insert`](Self::insert)'s time on 16 cores).
    pub fn insert_prepared(
        &mut self,
        ctx: &GpuContext,
        p: PreparedInsert,
    ) -> Result<(), ProgressiveGpuError> {
        let mine = self.preparer();
        if p.of
            != (
                mine.shuffle.len(),
                mine.options.colors,
                mine.options.payloads,
                mine.frame.min,
                mine.frame_max,
            )
        {
            return Err(GpuError::Colors("points prepared for another renderer (capacity, colours, payloads or frame differ)".into()).into());
        }
        let (first, n) = (p.first, p.n);
        let end = first + n as u64;
        // The shuffle is a bijection: a slot is taken exactly when its input index arrived.
        if let Some(k) = self.slots.arrived.first_in(first, end) {
            return Err(ProgressiveError::Duplicate(k).into());
        }
        if n == 0 {
            return Ok(());
        }
        // The GPU first: the staged words, scattered by the pass; the GPU copies and scatters
        // the last uploads while the host sets the bits.
        let stride = p.stride;
        let mut s = 0;
        while s < n {
            let e = (s + STAGING_POINTS).min(n);
            let records = &p.records[s * stride..e * stride];
            self.uploads.upload(
                ctx,
                &self.gpu,
                self.state.shuffle().prime().unwrap_or(0),
                first + s as u64,
                e - s,
                stride,
                false,
                |k, m, out| {
                    out.copy_from_slice(bytemuck::cast_slice(
                        &records[k * stride..(k + m) * stride],
                    ))
                },
            )?;
            s = e;
        }
        self.finish_insert(first, n, &p.slots, p.payload.as_deref());
        // The records' memory goes back to the preparers (no page faults for the next piece).
        if let Ok(mut pool) = self.record_pool.lock() {
            if pool.len() < 4 {
                pool.push(p.records);
            }
        }
        Ok(())
    }

    /// Replaces the colours of points `first..first + colors.len()` of the input (already
    /// inserted), leaving their positions alone: a colour-mode switch streamed in piece by piece
    /// (§3.5) while frames go on. The points not replaced yet keep their colour. Checks everything
    /// before changing anything.
    pub fn recolor(
        &mut self,
        ctx: &GpuContext,
        first: u64,
        colors: &[u32],
    ) -> Result<(), ProgressiveGpuError> {
        if !self.options.colors {
            return Err(GpuError::Colors("the renderer was made without colours".into()).into());
        }
        let n = colors.len();
        let end = self.state.check_range(first, n)?;
        if let Some(k) = self.slots.arrived.first_missing(first, end) {
            return Err(ProgressiveError::NotLoaded(k).into());
        }
        let mut s = 0;
        while s < n {
            let e = (s + STAGING_POINTS).min(n);
            let part = &colors[s..e];
            self.uploads.upload(
                ctx,
                &self.gpu,
                self.state.shuffle().prime().unwrap_or(0),
                first + s as u64,
                e - s,
                1,
                true,
                |k, m, out| out.copy_from_slice(bytemuck::cast_slice(&part[k..k + m])),
            )?;
            s = e;
        }
        Ok(())
    }

    /// Re-encodes every loaded slot of `gpu`'s chunks from the frame `from` in the frame `to`
    /// (the reframe pass, one dispatch per chunk, after the uploads in flight), as the CPU
    /// renderer does when its frame grows (the state then starts convergence over).
    fn reframe(
        ctx: &GpuContext,
        gpu: &GpuState,
        from: &BatchGrid,
        to: &ProgressiveFrame,
    ) -> Result<(), GpuError> {
        let buffers: Vec<(wgpu::Buffer, wgpu::BindGroup, u32)> = gpu
            .chunks
            .iter()
            .map(|c| {
                let u = uniform::<ReframeUniforms>(ctx, "reframe uniforms");
                ctx.queue.write_buffer(
                    &u,
                    0,
                    bytemuck::bytes_of(&ReframeUniforms::new(from, &to.quant, c.len)),
                );
                let g = gpu.passes.reframe.bind_group(
                    ctx,
                    0,
                    &[
                        entry(binding::REFRAME_PARAMS, u.as_entire_binding()),
                        entry(binding::REFRAME_COARSE, c.words[0].as_entire_binding()),
                        entry(binding::REFRAME_MEDIUM, c.words[1].as_entire_binding()),
                        entry(binding::REFRAME_FINE, c.words[2].as_entire_binding()),
                    ],
                );
                (u, g, c.len.div_ceil(256))
            })
            .collect();
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("reframe") });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("reframe"),
                timestamp_writes: None,
            });
            pass.set_pipeline(gpu.passes.reframe.pipeline());
            for (_, g, n) in &buffers {
                let (x, y) = ctx.split_dispatch(*n);
                pass.set_bind_group(0, g, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        ctx.queue.submit([enc.finish()]);
        ctx.check()
    }

    fn read_queries(ctx: &GpuContext, buf: &wgpu::Buffer) -> Result<Vec<f64>, GpuError> {
        let t = map_read(ctx, buf)?;
        let period = ctx.queue.get_timestamp_period() as f64 * 1e-6;
        let raw: Vec<u64> = bytemuck::pod_collect_to_vec(&t);
        Ok(raw.iter().map(|&v| v.wrapping_sub(raw[0]) as f64 * period).collect())
    }

    /// Draws one frame for `camera`: clear, Reproject, Fill with `budget`, Prepare and, with
    /// `resolve` (background, hole filling, eye-dome lighting; the renderer must have colours), the
    /// resolve into [`image_buffer`](Self::image_buffer): the passes of the batch rasterizer
    /// (`hole_fill.wgsl`, `resolve.wgsl`, `eye_dome.wgsl`), the CPU resolve's bytes. Waits for the
    /// GPU. A change of camera or options keeps the visible lists (that is what they are for) but
    /// starts convergence over.
    pub fn frame(
        &mut self,
        ctx: &GpuContext,
        camera: &Camera,
        options: &RasterOptions,
        budget: &FillBudget,
        resolve: Option<&ResolveOptions>,
    ) -> Result<GpuProgressiveFrame, ProgressiveGpuError> {
        let start = Instant::now();
        camera.validate().map_err(RasterError::from)?;
        if resolve.is_some() && !self.options.colors {
            return Err(GpuError::Colors(
                "resolve asked for but the renderer has no colours".into(),
            )
            .into());
        }
        let planner = Planner::new(camera, &self.state.frame().grid, options)?;
        let n = self.capacity();
        let gpu = &self.gpu;
        let t = Target::ensure(
            &mut self.target,
            &mut self.resolved,
            ctx,
            gpu,
            &self.list_counts,
            camera.width,
            camera.height,
        )?;
        let resolving = match resolve {
            Some(post) => Some((post, Resolved::ensure(&mut self.resolved, ctx, gpu, t)?)),
            None => None,
        };
        let mut st = self.state.begin_frame(camera, options);
        // One plan for every slot: one frame, one set of bounds.
        let plan = planner.plan(&self.state.frame().quant, &self.state.frame().bounds, n as usize);
        let projection = match plan {
            BatchPlan::Draw { precision, projection } => Some((precision, projection)),
            _ => None,
        };
        let mut raster = RasterStats::default();
        let count_batches = |raster: &mut RasterStats, dispatches: usize, points: u64| {
            raster.batches += dispatches as u64;
            match &projection {
                Some((precision, _)) => {
                    raster.batches_drawn += dispatches as u64;
                    raster.points_by_precision[precision.words() - 1] += points;
                }
                None if plan == BatchPlan::Culled => raster.batches_culled += dispatches as u64,
                None => {}
            }
        };
        ctx.queue.write_buffer(
            &gpu.per_frame.frame_uniforms,
            0,
            bytemuck::bytes_of(&FrameUniforms::new(camera, ctx.division())),
        );
        ctx.queue.write_buffer(&gpu.per_frame.counters, 0, &[0u8; 8]);

        // Reproject: each chunk's list of the last Prepare.
        let reproject: Vec<Dispatch> = match &projection {
            Some((_, p)) => self
                .list_counts
                .iter()
                .enumerate()
                .filter(|(_, &count)| count > 0)
                .map(|(c, &count)| Dispatch {
                    chunk: c,
                    record: DrawRecord {
                        projection: *p,
                        offset: 0,
                        count,
                        first_index: gpu.chunks[c].first,
                        _pad: 0,
                    },
                })
                .collect(),
            None => Vec::new(),
        };
        st.reprojected = self.list_counts.iter().map(|&c| c as u64).sum();
        count_batches(
            &mut raster,
            self.list_counts.iter().filter(|&&c| c > 0).count(),
            st.reprojected,
        );

        // Fill, first step: the fixed budget or the probe.
        let (first, adaptive) = self.state.first_fill(budget);
        let (runs, points) = self.slots.sweep(&mut self.state, first, self.chunk_slots);
        st.filled = first.min(n);
        st.fill_points = points;
        count_batches(&mut raster, runs.len(), points);
        let probe: Vec<Dispatch> =
            projection.as_ref().map(|(_, p)| gpu.fill_dispatches(&runs, p)).unwrap_or_default();
        let timed = gpu.queries.is_some();
        let host_ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;

        let dev = &ctx.device;
        let mut enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("progressive frame"),
        });
        gpu.encode_clear(ctx, &mut enc, t, (Some(0), None));
        gpu.encode_draw(ctx, &mut enc, t, "reproject", &reproject, 0, true, (None, Some(1)));
        let mut host_times = [0.0f64; 4]; // reproject, fill, prepare, resolve (host clock)
        if !timed {
            let t = Instant::now();
            ctx.queue.submit([enc.finish()]);
            ctx.wait()?;
            host_times[0] = host_ms(t);
            enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("progressive frame"),
            });
        }
        let t_fill = Instant::now();
        gpu.encode_draw(
            ctx,
            &mut enc,
            t,
            "fill",
            &probe,
            reproject.len(),
            false,
            (Some(2), Some(3)),
        );
        let mut extra_dispatches = Vec::new();
        if let Some(a) = adaptive {
            st.probe = st.filled;
            // Read the probe's timings back, then plan the rest of the fill.
            let timings = match gpu.resolve_queries(ctx, &mut enc, 4) {
                Some(q) => {
                    ctx.queue.submit([enc.finish()]);
                    let t = Self::read_queries(ctx, &q)?;
                    enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("progressive frame"),
                    });
                    ProbeTimings {
                        probe_points: st.probe,
                        probe_ms: t[3] - t[2],
                        elapsed_ms: t[3],
                        after_fill_ms: self.state.after_fill_ms(),
                    }
                }
                None => {
                    ctx.queue.submit([enc.finish()]);
                    ctx.wait()?;
                    enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("progressive frame"),
                    });
                    ProbeTimings {
                        probe_points: st.probe,
                        probe_ms: host_ms(t_fill),
                        elapsed_ms: host_ms(start),
                        after_fill_ms: self.state.after_fill_ms(),
                    }
                }
            };
            let more = a.extra_points(&timings).min(n - st.filled);
            let (runs, points) = self.slots.sweep(&mut self.state, more, self.chunk_slots);
            st.filled += more;
            st.fill_points += points;
            count_batches(&mut raster, runs.len(), points);
            if let Some((_, p)) = &projection {
                extra_dispatches = gpu.fill_dispatches(&runs, p);
            }
        }
        // The second Fill step (empty without the adaptive budget, timed all the same).
        gpu.encode_draw(
            ctx,
            &mut enc,
            t,
            "fill more",
            &extra_dispatches,
            reproject.len() + probe.len(),
            false,
            (Some(4), Some(5)),
        );
        if !timed {
            ctx.queue.submit([enc.finish()]);
            ctx.wait()?;
            host_times[1] = host_ms(t_fill);
            enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("progressive frame"),
            });
        }
        let t_prepare = Instant::now();
        gpu.encode_prepare(ctx, &mut enc, t, self.chunk_slots, (Some(6), Some(7)));
        if !timed {
            ctx.queue.submit([enc.finish()]);
            ctx.wait()?;
            host_times[2] = host_ms(t_prepare);
            enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("progressive frame"),
            });
        }
        let t_resolve = Instant::now();
        if let Some((post, r)) = resolving {
            gpu.encode_resolve(ctx, &mut enc, t, r, post, (Some(8), Some(9)));
        }
        let stamps = if resolve.is_some() { 10 } else { 8 };
        let queries = gpu.resolve_queries(ctx, &mut enc, stamps);
        let counters_read = readback(ctx, &mut enc, &gpu.per_frame.counters, 8);
        let counts_read =
            readback(ctx, &mut enc, &gpu.per_frame.list_counts, gpu.per_frame.list_counts.size());
        ctx.queue.submit([enc.finish()]);
        let c: Vec<u32> = bytemuck::pod_collect_to_vec(&map_read(ctx, &counters_read)?);
        raster.points_drawn = c[0] as u64 | (c[1] as u64) << 32;
        let counts: Vec<u32> = bytemuck::pod_collect_to_vec(&map_read(ctx, &counts_read)?);
        self.list_counts.copy_from_slice(&counts[..gpu.chunks.len()]);
        st.visible = self.list_counts.iter().map(|&c| c as u64).sum();
        host_times[3] = host_ms(t_resolve);
        let gpu_times = match queries {
            Some(q) => {
                let t = Self::read_queries(ctx, &q)?;
                let resolve_ms = resolve.map(|_| t[9] - t[8]);
                Some(ProgressiveGpuTimings {
                    reproject_ms: t[1],
                    probe_ms: t[3] - t[2],
                    extra_fill_ms: t[5] - t[4],
                    prepare_ms: t[7] - t[6],
                    resolve_ms,
                    frame_ms: t[stamps as usize - 1],
                })
            }
            None => None,
        };
        match &gpu_times {
            Some(g) => {
                st.reproject_ms = g.reproject_ms;
                st.fill_ms = g.probe_ms + g.extra_fill_ms;
                st.prepare_ms = g.prepare_ms;
                self.state.set_after_fill_ms(g.prepare_ms + g.resolve_ms.unwrap_or(0.0));
            }
            None => {
                st.reproject_ms = host_times[0];
                st.fill_ms = host_times[1];
                st.prepare_ms = host_times[2];
                self.state.set_after_fill_ms(host_times[2] + host_times[3]);
            }
        }
        st.raster = raster;
        st.total_ms = host_ms(start);
        st.converged = self.state.converged();
        ctx.check()?;
        Ok(GpuProgressiveFrame { stats: st, timing: gpu.timing(), gpu: gpu_times })
    }

    /// The pixels of the last frame in which another point has exactly the winner's depth (the
    /// ties pass over every slot, with the last frame's camera and options; the twin of the CPU
    /// renderer's
    /// [`depth_ties`](mortar_core::render::progressive::ProgressiveRenderer::depth_ties)).
    /// `None` until every point arrived and a frame was drawn.
    pub fn depth_ties(&mut self, ctx: &GpuContext) -> Result<Option<u64>, ProgressiveGpuError> {
        let (Some((camera, options)), Some(t)) = (self.state.view(), &self.target) else {
            return Ok(None);
        };
        if !self.state.all_loaded() {
            return Ok(None);
        }
        let frame = self.state.frame();
        let planner = Planner::new(&camera, &frame.grid, &options)?;
        let BatchPlan::Draw { projection, .. } =
            planner.plan(&frame.quant, &frame.bounds, self.capacity() as usize)
        else {
            return Ok(Some(0));
        };
        let gpu = &self.gpu;
        let pixels = t.width as u64 * t.height as u64;
        let flags = storage(
            ctx,
            "tie flags",
            pixels * 4,
            wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
        );
        // The frame uniforms are still the last frame's (its camera).
        let g0 = gpu.passes.ties.bind_group(
            ctx,
            0,
            &[
                entry(binding::FRAME, gpu.per_frame.frame_uniforms.as_entire_binding()),
                entry(binding::TIES_KEY_WORDS, t.keys.as_entire_binding()),
                entry(binding::TIES_FLAGS, flags.as_entire_binding()),
            ],
        );
        let runs: Vec<(usize, u32, u32)> =
            gpu.chunks.iter().enumerate().map(|(c, ch)| (c, 0, ch.len)).collect();
        let groups = gpu.draw_groups(ctx, t, &gpu.fill_dispatches(&runs, &projection), 0, false);
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("ties") });
        enc.clear_buffer(&flags, 0, None);
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("ties"),
                timestamp_writes: None,
            });
            pass.set_pipeline(gpu.passes.ties.pipeline());
            for (_, g1, n) in &groups {
                if *n == 0 {
                    continue;
                }
                pass.set_bind_group(0, &g0, &[]);
                pass.set_bind_group(1, g1, &[]);
                let (x, y) = ctx.split_dispatch(*n);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        let read = readback(ctx, &mut enc, &flags, flags.size());
        ctx.queue.submit([enc.finish()]);
        let marks: Vec<u32> = bytemuck::pod_collect_to_vec(&map_read(ctx, &read)?);
        ctx.check()?;
        Ok(Some(marks.iter().filter(|&&m| m != 0).count() as u64))
    }

    /// The visibility buffer of the last frame (row-major depth|index keys; indices are slots, as
    /// in the CPU renderer), empty before the first frame.
    pub fn read_keys(&self, ctx: &GpuContext) -> Result<Vec<u64>, GpuError> {
        let Some(t) = &self.target else { return Ok(Vec::new()) };
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("read keys") });
        let buf = readback(ctx, &mut enc, &t.keys, t.keys.size());
        ctx.queue.submit([enc.finish()]);
        let bytes = map_read(ctx, &buf)?;
        Ok(bytemuck::pod_collect_to_vec::<u8, u64>(&bytes)[..t.width as usize * t.height as usize]
            .to_vec())
    }

    /// The resolved image of the last frame drawn with `resolve` (RGBA8 packed, row-major).
    pub fn read_image(&self, ctx: &GpuContext) -> Result<Vec<u32>, GpuError> {
        match (&self.target, &self.resolved) {
            (Some(t), Some(r)) => read_image_buffer(ctx, &r.image, t.width, t.height),
            _ => Err(GpuError::Colors("no frame was resolved yet".into())),
        }
    }

    /// The slots of the points visible at the end of the last frame (the next Reproject's input),
    /// in increasing order.
    pub fn read_visible(&self, ctx: &GpuContext) -> Result<Vec<u32>, GpuError> {
        let Some(t) = &self.target else { return Ok(Vec::new()) };
        let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("read visible"),
        });
        let buf = readback(ctx, &mut enc, &t.lists, t.lists.size());
        ctx.queue.submit([enc.finish()]);
        let all: Vec<u32> = bytemuck::pod_collect_to_vec(&map_read(ctx, &buf)?);
        let mut out = Vec::with_capacity(self.list_counts.iter().map(|&c| c as usize).sum());
        for (c, &count) in self.list_counts.iter().enumerate() {
            let s = c * t.list_stride as usize;
            out.extend_from_slice(&all[s..s + count as usize]);
        }
        out.par_sort_unstable();
        Ok(out)
    }
}
