//! The progressive renderer of paper 000 (Schütz et al., "Progressive Real-Time Rendering of One
//! Billion Points Without Hierarchical Acceleration Structures") on the GPU: the twin of
//! [`mortar_core::render::progressive::ProgressiveRenderer`], with the same keys frame by frame.
//!
//! - **The shuffled buffer** (§3.2-3.3): three 10-bit coordinate words per slot (coarse, medium,
//!   fine) in ONE quantization frame over the whole data set, as the CPU renderer holds them, plus
//!   (optionally) one RGBA8 colour per slot for the GPU resolve. It is split by slot range into
//!   chunks that fit the device's largest storage binding (at most
//!   [`MAX_CHUNK_POINTS`] slots, 1 GiB per word buffer: a billion
//!   points are four chunks on an H100). Every slot starts with the coarse word
//!   [`UNLOADED`](mortar_core::render::progressive::UNLOADED) (pass `progressive_unload.wgsl`), and Fill skips such slots, as the paper
//!   discards default-initialized vertices.
//! - **Insertion** ([`GpuProgressive::insert`], the Distribute step): the host encodes each
//!   point's words (and colour) and writes them in input order, in parallel, straight into wgpu's
//!   staging memory (`Queue::write_buffer_with`, no intermediate copy); the pass
//!   `progressive_scatter.wgsl` computes each point's slot with eq. 1-2 (the WGSL twin of core's
//!   [`Shuffle::target`], 64-bit square and remainder) and writes the record into its slot, one
//!   dispatch per chunk. 12 bytes per point uploaded (16 with colours). Uploads are not waited
//!   for until a GiB of them is in flight, and then only the oldest. The host still computes
//!   every slot once, for its bit per slot of what arrived (Fill's point count and the
//!   convergence test need it, as in the CPU renderer) and, on request, each point's payload by
//!   slot; it sets those bits after sorting the slots by region of the bit array
//!   (`SortedSlots`), which avoids a locked cache miss per point. Duplicates and recolouring
//!   are checked against the ranges of input indices that arrived (the shuffle is a bijection).
//! - **Per frame** (§3.4; [`GpuProgressive::frame`]): clear the 64-bit visibility buffer
//!   (`clear.wgsl`); **Reproject** (`progressive_reproject.wgsl`): draw the slots the last Prepare
//!   listed, reading their words from the shuffled buffer by slot; **Fill**
//!   (`progressive_fill.wgsl`): draw slots `[cursor, cursor + budget)`, wrapping around;
//!   **Prepare** (`progressive_prepare.wgsl`): append each pixel's winning slot to the visible
//!   list of its chunk with an atomic counter; then, with colours, **resolve** (the batch
//!   rasterizer's `hole_fill.wgsl`, `resolve.wgsl` one dispatch per chunk, `eye_dome.wgsl`, as
//!   [`ResolveOptions`] asks: the CPU resolve's bytes) into an RGBA8 image buffer that
//!   [`WindowSurface::present_image`](crate::present::WindowSurface::present_image) can show.
//!   The key is `depth_bits << 32 | slot`.
//! - **Exactness**: every slot shares one frame and one set of bounds, so core's
//!   [`Planner`] makes one plan (culling, precision, projection) for all of them, computed on the
//!   host in f64 exactly as the CPU renderer's `rasterize` calls make it; with the projection and
//!   decode of `common/decode.wgsl` the GPU keys are the CPU progressive renderer's keys, frame by
//!   frame for the same budgets (tested on lavapipe).
//! - **Adaptive fill budget** (§3.4.1): with [`FillBudget::Adaptive`] the frame is submitted in two
//!   parts: clear + Reproject + the probe Fill with timestamp queries; the host reads the
//!   timestamps back, feeds [`ProbeTimings`] (GPU times: probe pass, time since the clear began,
//!   the last frame's Prepare and resolve) to [`AdaptiveBudget::extra_points`], and submits the
//!   extra Fill, Prepare and resolve. Without TIMESTAMP_QUERY every pass is submitted on its own and
//!   timed with the host's clock ([`BudgetTiming`] says which). The paper computes the budget on the
//!   GPU and draws with an indirect call to avoid the round trip; here the host does it (one
//!   read-back per frame, which the statistics need anyway), and the `usable` share of the frame
//!   time covers the round trip.
//! - **Convergence** as in the CPU renderer: a bit per slot drawn since the view (camera and
//!   options) last changed; converged once every slot is loaded and drawn.
//! - **The frame grows** as the CPU renderer's ([`ProgressiveFrame`]): points inserted outside it
//!   grow it, and `progressive_reframe.wgsl` re-encodes every loaded slot in the new frame.
//! - **Depth ties** ([`GpuProgressive::depth_ties`], `progressive_ties.wgsl`): the pixels whose
//!   winner has a twin in depth, counted as the CPU's `count_depth_ties` counts them.
//!
//! GPU state, as in the batch rasterizer: the passes (pipelines with explicit bind-group layouts
//! from the tables of [`crate::shaders`]), the shuffled buffer and the per-frame buffers are made
//! with the renderer; the framebuffer, the visible lists and the bind groups that use them are
//! made by the first frame of a viewport size, the resolved image by the first frame of that size
//! drawn with `resolve`.
//!
//! Only the 64-bit atomic path is implemented: on a context whose
//! [`atomic_path`](GpuContext::atomic_path) is the 32-bit two-pass path,
//! [`GpuProgressive::new`] fails with [`ProgressiveGpuError::Needs64BitAtomics`] (the two-pass path
//! would need a second Reproject and Fill per frame; the CPU renderer serves such machines).
//! Deviations from the paper: no MSAA; 12 bytes of words per point (16 with colours) instead of
//! 16 bytes of floats and attributes; [`RasterStats`] counts one "batch" per dispatch.

use crate::buffers::{map_read, read_image_buffer, readback};
use crate::context::{AtomicPath, GpuContext, GpuError};
use crate::pipeline::{
    batches_group, entry, storage, uniform, PassPipeline, SharedLayouts, Timestamps,
};
use crate::scene::MAX_CHUNK_POINTS;
use crate::shaders::{binding, Pass};
use mortar_core::grid::Grid;
use mortar_core::quantize::BatchGrid;
use mortar_core::render::gpu::{
    DrawRecord, EyeDomeUniforms, FrameUniforms, HoleFillUniforms, ReframeUniforms, ResolveUniforms,
};
use mortar_core::render::progressive::{
    piece_box, AdaptiveBudget, FillBudget, FrameStats, ProbeTimings, ProgressiveError,
    ProgressiveFrame, Shuffle,
};
use mortar_core::render::resolve::ResolveOptions;
use mortar_core::render::{
    Aabb, BatchPlan, BatchProjection, Camera, Planner, RasterError, RasterOptions, RasterStats,
};
use rayon::prelude::*;
use std::num::NonZeroU64;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// The uniforms of the scatter and Prepare passes, defined with the other records the GPU reads
/// in [`mortar_core::render::gpu`] (re-exported here where they used to be).
pub use mortar_core::render::gpu::{PrepareUniforms, ScatterUniforms};

/// Slots (Fill) or list entries (Reproject) per thread of the draw passes; WGSL mirror
/// `SLOTS_PER_THREAD` in `shaders/progressive_types.wgsl`.
pub const SLOTS_PER_THREAD: u32 = 8;

/// Slots per workgroup of the draw passes (128 threads).
const SLOTS_PER_GROUP: u64 = 128 * SLOTS_PER_THREAD as u64;

/// Points per scatter upload.
const STAGING_POINTS: usize = 4 << 20;

/// Bytes of uploads the host may stage before it waits for the oldest to be done.
const MAX_IN_FLIGHT: u64 = 1 << 30;

/// Why the GPU progressive renderer refused something or failed.
#[derive(Debug, thiserror::Error)]
pub enum ProgressiveGpuError {
    /// The context runs the 32-bit two-pass path.
    #[error("{adapter}: the GPU progressive renderer needs 64-bit atomics (SHADER_INT64 + SHADER_INT64_ATOMIC_MIN_MAX) and this context uses the 32-bit two-pass path; use the CPU progressive renderer")]
    Needs64BitAtomics {
        /// The adapter's name.
        adapter: String,
    },
    /// Bad points, frame or view (the CPU renderer's errors; nothing was changed).
    #[error(transparent)]
    Progressive(#[from] ProgressiveError),
    /// The device failed or something does not fit it.
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

impl From<RasterError> for ProgressiveGpuError {
    fn from(e: RasterError) -> Self {
        ProgressiveGpuError::Progressive(ProgressiveError::Raster(e))
    }
}

/// Choices of a [`GpuProgressive`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct ProgressiveOptions {
    /// Slots per chunk (`None`: as many as the device's largest binding holds, at most
    /// [`MAX_CHUNK_POINTS`]). Small values exercise the chunking
    /// in tests.
    pub chunk_slots: Option<u32>,
    /// Whether points come with RGBA8 colours (for the GPU resolve and [`GpuProgressive::image_buffer`]).
    pub colors: bool,
    /// Whether points come with a 64-bit payload kept on the host by slot
    /// ([`GpuProgressive::payload`], as the CPU renderer keeps it), for colour rules resolved on
    /// the host.
    pub payloads: bool,
    /// Time the passes with the host's clock ([`BudgetTiming::HostClock`]) even where the device
    /// has timestamps (what a device without them does; tests use it).
    pub host_clock: bool,
}

/// How the adaptive budget's timings were measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BudgetTiming {
    /// GPU timestamp queries (TIMESTAMP_QUERY).
    GpuTimestamps,
    /// The host's clock around passes submitted one at a time (no timestamps on this device).
    HostClock,
}

impl BudgetTiming {
    /// A short name: "gpu-timestamps" or "host-clock".
    pub fn name(self) -> &'static str {
        match self {
            BudgetTiming::GpuTimestamps => "gpu-timestamps",
            BudgetTiming::HostClock => "host-clock",
        }
    }
}

/// GPU pass times of one frame from timestamp queries, ms.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ProgressiveGpuTimings {
    /// Clear and Reproject.
    pub reproject_ms: f64,
    /// The first Fill step (the probe with the adaptive budget, all of Fill with a fixed one).
    pub probe_ms: f64,
    /// The second Fill step (adaptive budget; 0 otherwise).
    pub extra_fill_ms: f64,
    /// Prepare.
    pub prepare_ms: f64,
    /// Resolve, when run.
    pub resolve_ms: Option<f64>,
    /// From the start of the clear to the end of the last pass (gaps between submissions
    /// included).
    pub frame_ms: f64,
}

/// What one frame did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GpuProgressiveFrame {
    /// The statistics of the CPU renderer's frames (pass times from timestamps where the device
    /// has them, else from the host's clock; `total_ms` is the host's wall time of the frame).
    pub stats: FrameStats,
    /// How the pass times (and the adaptive budget's timings) were measured.
    pub timing: BudgetTiming,
    /// GPU pass times, where the device has timestamps.
    pub gpu: Option<ProgressiveGpuTimings>,
}

/// One chunk of the shuffled buffer: slots `[first, first + len)`.
struct SlotChunk {
    words: [wgpu::Buffer; 3],
    colors: Option<wgpu::Buffer>,
    first: u32,
    len: u32,
}

/// The pipelines and layouts of the renderer: built once with it.
struct Passes {
    shared: SharedLayouts,
    clear: PassPipeline,
    unload: PassPipeline,
    scatter: PassPipeline,
    reproject: PassPipeline,
    fill: PassPipeline,
    prepare: PassPipeline,
    resolve: PassPipeline,
    reframe: PassPipeline,
    hole_fill: PassPipeline,
    eye_dome: PassPipeline,
    ties: PassPipeline,
}

/// What the renderer writes anew every frame: the camera's uniforms, the drawn-point counter,
/// the draw records, Prepare's constants and list counts, the resolve dispatches' uniforms. The
/// buffers live as long as the renderer.
struct PerFrame {
    frame_uniforms: wgpu::Buffer,
    counters: wgpu::Buffer,
    /// Draw records, one per `record_stride` bytes (a storage-offset boundary).
    records: wgpu::Buffer,
    record_stride: u64,
    prepare_uniforms: wgpu::Buffer,
    /// Entries of each chunk's visible list, as Prepare counted them.
    list_counts: wgpu::Buffer,
    /// One per chunk (at least one), with colours only.
    resolve_uniforms: Vec<wgpu::Buffer>,
    /// `HoleFillUniforms` and `EyeDomeUniforms` of the resolve.
    fill_uniforms: wgpu::Buffer,
    eye_dome_uniforms: wgpu::Buffer,
}

/// The framebuffer of one viewport size, the visible lists, and the bind groups that use them,
/// made together by the first frame of that size ([`Target::ensure`]).
struct Target {
    width: u32,
    height: u32,
    keys: wgpu::Buffer,
    /// The visible lists, one region of `list_stride` entries per chunk (carried over, grown if
    /// needed, when the size changes: the next Reproject draws them in the new view).
    lists: wgpu::Buffer,
    list_stride: u32,
    clear_group: wgpu::BindGroup,
    /// Group 0 of Fill (frame uniforms, keys, counters).
    fill_group: wgpu::BindGroup,
    prepare_group: wgpu::BindGroup,
}

/// The resolved image of a [`Target`], the hole-filled keys, and the bind groups of the resolve
/// (one per chunk, from the framebuffer or from the filled keys), hole filling and eye-dome
/// lighting, made by the first frame of that target drawn with `resolve`.
struct Resolved {
    image: wgpu::Buffer,
    /// The colour dispatches reading the framebuffer, and reading the filled keys.
    groups: Vec<wgpu::BindGroup>,
    groups_filled: Vec<wgpu::BindGroup>,
    /// Hole filling: the framebuffer into the filled keys (two words per pixel: index, depth,
    /// the 64-bit keys' layout).
    fill_group: wgpu::BindGroup,
    /// Eye-dome lighting from the framebuffer's depths, and from the filled keys' depths.
    eye_dome_group: wgpu::BindGroup,
    eye_dome_group_filled: wgpu::BindGroup,
}

/// The host's bookkeeping of the slots, as the CPU renderer keeps it.
struct SlotBook {
    /// A bit per slot: its point arrived.
    loaded_bits: Vec<AtomicU64>,
    loaded: u64,
    /// The input indices that arrived, as ranges (duplicates and recolouring are checked here).
    arrived: Ranges,
    /// A bit per slot: drawn since the view last changed, and how many.
    done: Vec<u64>,
    done_count: u64,
    /// The next slot Fill draws.
    cursor: u64,
}

/// The GPU state that lives as long as the renderer: the shuffled buffer, the passes, the
/// per-frame buffers and the constant uniforms.
struct GpuState {
    chunks: Vec<SlotChunk>,
    passes: Passes,
    per_frame: PerFrame,
    /// One [`ScatterUniforms`] per chunk, `scatter_uniform_stride` bytes apart (rewritten by
    /// every upload; queue writes are ordered with the submissions that read them).
    scatter_uniforms: wgpu::Buffer,
    scatter_uniform_stride: u64,
    /// A 4-byte buffer bound where a pass needs a buffer that is not there (no colours).
    dummy: wgpu::Buffer,
    queries: Option<Timestamps>,
}

/// One draw dispatch: a record and the chunk it reads.
#[derive(Clone, Copy)]
struct Dispatch {
    chunk: usize,
    record: DrawRecord,
}

/// Timestamp slots: clear begin, Reproject end, probe Fill begin/end, extra Fill begin/end,
/// Prepare begin/end, resolve begin/end.
const QUERIES: u32 = 10;

/// The progressive renderer of paper 000 on the GPU (see the module documentation).
pub struct GpuProgressive {
    frame: ProgressiveFrame,
    /// Times the frame grew.
    grown: u32,
    shuffle: Shuffle,
    options: ProgressiveOptions,
    chunk_slots: u32,
    slots: SlotBook,
    payload: Option<Vec<AtomicU64>>,
    frames: u64,
    view: Option<(Camera, RasterOptions)>,
    gpu: GpuState,
    /// `None` until the first frame gives the viewport size.
    target: Option<Target>,
    /// `None` until a frame of the current target is drawn with `resolve`.
    resolved: Option<Resolved>,
    /// Entries of each chunk's list after the last Prepare.
    list_counts: Vec<u32>,
    /// Scatter records, grown by the first insert that needs more.
    staging: wgpu::Buffer,
    /// Time of the last frame's Prepare and resolve, ms (the adaptive budget's `after_fill_ms`).
    last_after_fill_ms: f64,
    /// Uploads submitted and maybe not done yet (submission, bytes), oldest first, and their
    /// bytes: wgpu holds a staging copy of each until the GPU has done it.
    in_flight: std::collections::VecDeque<(wgpu::SubmissionIndex, u64)>,
    /// Record buffers of prepared inserts, handed back for the next ones.
    record_pool: RecordPool,
    in_flight_bytes: u64,
}

fn round_up(v: u64, to: u64) -> u64 {
    v.div_ceil(to) * to
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

    /// A renderer for `capacity` points in `frame` (e.g. [`ProgressiveFrame::around`] the
    /// headers' box), as [`ProgressiveRenderer::with_frame`](mortar_core::render::progressive::ProgressiveRenderer::with_frame).
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
        let len = u32::try_from(capacity).map_err(|_| ProgressiveError::TooManyPoints(capacity))?;
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
        let words64 = n.div_ceil(64);
        let r = GpuProgressive {
            frame,
            grown: 0,
            shuffle: Shuffle::new(len),
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
            slots: SlotBook {
                loaded_bits: (0..words64).map(|_| AtomicU64::new(0)).collect(),
                loaded: 0,
                arrived: Ranges::default(),
                done: vec![0; words64],
                done_count: 0,
                cursor: 0,
            },
            payload: options.payloads.then(|| (0..n).map(|_| AtomicU64::new(0)).collect()),
            frames: 0,
            view: None,
            target: None,
            resolved: None,
            staging: storage(ctx, "scatter staging", 0, wgpu::BufferUsages::COPY_DST),
            last_after_fill_ms: 0.0,
            in_flight: Default::default(),
            record_pool: Default::default(),
            in_flight_bytes: 0,
        };
        ctx.wait()?;
        Ok(r)
    }
    /// Number of points the renderer holds once everything arrived.
    pub fn capacity(&self) -> u64 {
        self.shuffle.len() as u64
    }

    /// Points inserted so far.
    pub fn loaded(&self) -> u64 {
        self.slots.loaded
    }

    /// The shuffle placing input index `i` at slot `shuffle().target(i)`.
    pub fn shuffle(&self) -> &Shuffle {
        &self.shuffle
    }

    /// The quantization frame of the words.
    pub fn quantization(&self) -> &BatchGrid {
        &self.frame.quant
    }

    /// The frame: quantization, bounds, and the box of the points expected and arrived.
    pub fn frame_state(&self) -> &ProgressiveFrame {
        &self.frame
    }

    /// World bounds of the frame.
    pub fn bounds(&self) -> &Aabb {
        &self.frame.bounds
    }

    /// How often the frame grew to hold points outside it.
    pub fn growths(&self) -> u32 {
        self.grown
    }

    /// Frames drawn so far.
    pub fn frames(&self) -> u64 {
        self.frames
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
        self.slots
            .loaded_bits
            .get(slot as usize / 64)
            .is_some_and(|w| w.load(Ordering::Relaxed) >> (slot % 64) & 1 == 1)
    }

    /// The payload of the point in slot `slot`, if loaded and the renderer keeps payloads.
    pub fn payload(&self, slot: u32) -> Option<u64> {
        let p = self.payload.as_ref()?;
        self.is_loaded(slot).then(|| p[slot as usize].load(Ordering::Relaxed))
    }

    /// Whether the last frame's image is final (see [`FrameStats::converged`]).
    pub fn converged(&self) -> bool {
        self.slots.converged(self.capacity())
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
        if let Some(b) = piece_box(xyz) {
            if let Some(grown) = self.frame.grown(b)? {
                self.reframe(ctx, grown)?;
            }
            self.frame.data = self.frame.data.union(b);
        }
        let prep = self.preparer();
        // The words encoded straight into the staging memory, then the slots for the bits
        // (the GPU copies and scatters the last uploads meanwhile).
        let frame = self.frame.quant;
        let stride = 3 + colors.is_some() as usize;
        let mut s = 0;
        while s < n {
            let e = (s + STAGING_POINTS).min(n);
            self.upload(ctx, first + s as u64, e - s, stride, false, |k, m, out| {
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
            })?;
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
        slots.apply(&mut self.slots.loaded_bits);
        if let (Some(store), Some(values)) = (&self.payload, payload) {
            let shuffle = self.shuffle;
            values.par_iter().enumerate().with_min_len(4096).for_each(|(k, &v)| {
                store[shuffle.target((first + k as u64) as u32) as usize]
                    .store(v, Ordering::Relaxed)
            });
        }
        self.slots.loaded += n as u64;
        self.slots.arrived.insert(first, first + n as u64);
    }

    /// What [`InsertPreparer::prepare`] needs of this renderer (a few numbers, `Send`).
    pub fn preparer(&self) -> InsertPreparer {
        InsertPreparer {
            frame: self.frame.quant,
            frame_max: self.frame.max,
            shuffle: self.shuffle,
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
            self.upload(ctx, first + s as u64, e - s, stride, false, |k, m, out| {
                out.copy_from_slice(bytemuck::cast_slice(&records[k * stride..(k + m) * stride]))
            })?;
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
        let end = first.saturating_add(n as u64);
        if end > self.capacity() {
            return Err(
                ProgressiveError::IndexRange { first, end, capacity: self.capacity() }.into()
            );
        }
        if let Some(k) = self.slots.arrived.first_missing(first, end) {
            return Err(ProgressiveError::NotLoaded(k).into());
        }
        let mut s = 0;
        while s < n {
            let e = (s + STAGING_POINTS).min(n);
            let part = &colors[s..e];
            self.upload(ctx, first + s as u64, e - s, 1, true, |k, m, out| {
                out.copy_from_slice(bytemuck::cast_slice(&part[k..k + m]))
            })?;
            s = e;
        }
        Ok(())
    }

    /// Uploads `count` records of `stride` words for input points `first..`, written in parallel
    /// straight into wgpu's staging memory (`fill(k, m, out)` writes records `k..k + m` into
    /// `out`), and dispatches the scatter pass over them once per chunk; `colors_only`: one colour
    /// per record, only the colours are written.
    fn upload(
        &mut self,
        ctx: &GpuContext,
        first: u64,
        count: usize,
        stride: usize,
        colors_only: bool,
        fill: impl Fn(usize, usize, &mut wgpu::WriteOnly<[u8]>) + Sync,
    ) -> Result<(), GpuError> {
        let bytes = (count * stride * 4) as u64;
        if self.staging.size() < bytes {
            let size = (STAGING_POINTS as u64 * 16).max(bytes);
            if size > ctx.limits().max_buffer_size {
                return Err(GpuError::TooLarge {
                    what: "the scatter staging buffer",
                    needed: size,
                    limit: ctx.limits().max_buffer_size,
                });
            }
            self.staging = storage(ctx, "scatter staging", size, wgpu::BufferUsages::COPY_DST);
        }
        let Some(size) = NonZeroU64::new(bytes) else { return Ok(()) };
        {
            let mut view =
                ctx.queue.write_buffer_with(&self.staging, 0, size).ok_or_else(|| {
                    GpuError::Device(format!(
                        "no staging memory for {bytes} bytes of scatter records"
                    ))
                })?;
            // Pieces of 16 Ki records, written by as many threads.
            const PIECE: usize = 1 << 14;
            let mut rest = view.slice(..);
            let mut pieces: Vec<(usize, usize, SendWrite)> =
                Vec::with_capacity(count.div_ceil(PIECE));
            for k in (0..count).step_by(PIECE) {
                let m = (count - k).min(PIECE);
                let (head, tail) = rest.split_at(m * stride * 4);
                pieces.push((k, m, SendWrite(head)));
                rest = tail;
            }
            pieces
                .into_par_iter()
                .for_each(|(k, m, mut out): (usize, usize, SendWrite)| fill(k, m, &mut out.0));
        }
        // One dispatch per chunk, each with its uniforms at its own aligned offset.
        let ustride = self.gpu.scatter_uniform_stride;
        let prime = self.shuffle.prime().unwrap_or(0);
        for (c, chunk) in self.gpu.chunks.iter().enumerate() {
            let u = ScatterUniforms {
                colors: (stride == 4) as u32,
                colors_only: colors_only as u32,
                prime,
                first: first as u32,
                chunk_first: chunk.first,
                chunk_len: chunk.len,
                count: count as u32,
                _pad: 0,
            };
            ctx.queue.write_buffer(
                &self.gpu.scatter_uniforms,
                c as u64 * ustride,
                bytemuck::bytes_of(&u),
            );
        }
        let usize_ = NonZeroU64::new(std::mem::size_of::<ScatterUniforms>() as u64);
        let groups: Vec<wgpu::BindGroup> = self
            .gpu
            .chunks
            .iter()
            .enumerate()
            .map(|(c, chunk)| {
                self.gpu.passes.scatter.bind_group(
                    ctx,
                    0,
                    &[
                        entry(
                            binding::SCATTER_PARAMS,
                            wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                buffer: &self.gpu.scatter_uniforms,
                                offset: c as u64 * ustride,
                                size: usize_,
                            }),
                        ),
                        entry(
                            binding::SCATTER_STAGED,
                            wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                buffer: &self.staging,
                                offset: 0,
                                size: Some(size),
                            }),
                        ),
                        entry(binding::SCATTER_COARSE, chunk.words[0].as_entire_binding()),
                        entry(binding::SCATTER_MEDIUM, chunk.words[1].as_entire_binding()),
                        entry(binding::SCATTER_FINE, chunk.words[2].as_entire_binding()),
                        entry(
                            binding::SCATTER_COLORS,
                            chunk.colors.as_ref().unwrap_or(&self.gpu.dummy).as_entire_binding(),
                        ),
                    ],
                )
            })
            .collect();
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("scatter") });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("scatter"),
                timestamp_writes: None,
            });
            pass.set_pipeline(self.gpu.passes.scatter.pipeline());
            let (x, y) = ctx.split_dispatch((count as u32).div_ceil(256));
            for bg in &groups {
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        let index = ctx.queue.submit([enc.finish()]);
        // wgpu keeps a staging copy of every upload until the GPU has done it: past
        // MAX_IN_FLIGHT bytes, wait for the oldest uploads only, so that the GPU copies and
        // scatters while the host stages the next ones (waiting for all of them every GiB cost a
        // billion-point load a third of its time).
        self.in_flight.push_back((index, bytes));
        self.in_flight_bytes += bytes;
        while self.in_flight_bytes > MAX_IN_FLIGHT {
            let Some((index, b)) = self.in_flight.pop_front() else { break };
            ctx.device
                .poll(wgpu::PollType::Wait { submission_index: Some(index), timeout: None })
                .map_err(|e| GpuError::Device(e.to_string()))?;
            self.in_flight_bytes -= b;
        }
        ctx.check()
    }

    /// Re-encodes every loaded slot in the frame `to` (the reframe pass, one dispatch per chunk,
    /// after the uploads in flight) and starts convergence over, as the CPU renderer does.
    fn reframe(&mut self, ctx: &GpuContext, to: ProgressiveFrame) -> Result<(), GpuError> {
        let from = self.frame.quant;
        let buffers: Vec<(wgpu::Buffer, wgpu::BindGroup, u32)> = self
            .gpu
            .chunks
            .iter()
            .map(|c| {
                let u = uniform::<ReframeUniforms>(ctx, "reframe uniforms");
                ctx.queue.write_buffer(
                    &u,
                    0,
                    bytemuck::bytes_of(&ReframeUniforms::new(&from, &to.quant, c.len)),
                );
                let g = self.gpu.passes.reframe.bind_group(
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
            pass.set_pipeline(self.gpu.passes.reframe.pipeline());
            for (_, g, n) in &buffers {
                let (x, y) = ctx.split_dispatch(*n);
                pass.set_bind_group(0, g, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        ctx.queue.submit([enc.finish()]);
        ctx.check()?;
        self.frame = to;
        self.view = None;
        self.grown += 1;
        Ok(())
    }

    fn read_queries(ctx: &GpuContext, buf: &wgpu::Buffer) -> Result<Vec<f64>, GpuError> {
        let t = map_read(ctx, buf)?;
        let period = ctx.queue.get_timestamp_period() as f64 * 1e-6;
        let raw: Vec<u64> = bytemuck::pod_collect_to_vec(&t);
        Ok(raw.iter().map(|&v| v.wrapping_sub(raw[0]) as f64 * period).collect())
    }

    /// Draws one frame for `camera`: clear, Reproject, Fill with `budget`, Prepare and, with
    /// `resolve` (background, hole filling, eye-dome lighting; the renderer must have colours),
    /// the resolve into [`image_buffer`](Self::image_buffer): the passes of the batch rasterizer
    /// (`hole_fill.wgsl`, `resolve.wgsl`, `eye_dome.wgsl`), the CPU resolve's bytes. Waits for the GPU. A change of camera or options
    /// keeps the visible lists (that is what they are for) but starts convergence over.
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
        let planner = Planner::new(camera, &self.frame.grid, options)?;
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
        if self.view != Some((*camera, *options)) {
            self.view = Some((*camera, *options));
            self.slots.done.par_iter_mut().with_min_len(1 << 14).for_each(|w| *w = 0);
            self.slots.done_count = 0;
        }
        self.frames += 1;
        let mut st =
            FrameStats { frame: self.frames, loaded: self.slots.loaded, ..FrameStats::default() };
        // One plan for every slot: one frame, one set of bounds.
        let plan = planner.plan(&self.frame.quant, &self.frame.bounds, n as usize);
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
        let (first, adaptive): (u64, Option<AdaptiveBudget>) = match budget {
            FillBudget::Fixed(b) => (*b, None),
            FillBudget::Adaptive(a) => (a.probe_points.min(n), Some(*a)),
        };
        let (runs, points) = self.slots.sweep(first, &gpu.chunks, self.chunk_slots, n);
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
                        after_fill_ms: self.last_after_fill_ms,
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
                        after_fill_ms: self.last_after_fill_ms,
                    }
                }
            };
            let more = a.extra_points(&timings).min(n - st.filled);
            let (runs, points) = self.slots.sweep(more, &gpu.chunks, self.chunk_slots, n);
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
                self.last_after_fill_ms = g.prepare_ms + g.resolve_ms.unwrap_or(0.0);
            }
            None => {
                st.reproject_ms = host_times[0];
                st.fill_ms = host_times[1];
                st.prepare_ms = host_times[2];
                self.last_after_fill_ms = host_times[2] + host_times[3];
            }
        }
        st.raster = raster;
        st.total_ms = host_ms(start);
        st.converged = self.slots.converged(n);
        ctx.check()?;
        Ok(GpuProgressiveFrame { stats: st, timing: gpu.timing(), gpu: gpu_times })
    }

    /// The pixels of the last frame in which another point has exactly the winner's depth (the
    /// ties pass over every slot, with the last frame's camera and options; the twin of the CPU
    /// renderer's
    /// [`depth_ties`](mortar_core::render::progressive::ProgressiveRenderer::depth_ties)).
    /// `None` until every point arrived and a frame was drawn.
    pub fn depth_ties(&mut self, ctx: &GpuContext) -> Result<Option<u64>, ProgressiveGpuError> {
        let (Some((camera, options)), Some(t)) = (self.view, &self.target) else { return Ok(None) };
        if self.slots.loaded != self.capacity() {
            return Ok(None);
        }
        let planner = Planner::new(&camera, &self.frame.grid, &options)?;
        let BatchPlan::Draw { projection, .. } =
            planner.plan(&self.frame.quant, &self.frame.bounds, self.capacity() as usize)
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

/// What [`GpuProgressive::preparer`] hands out: the numbers [`prepare`](Self::prepare) needs
/// and the renderer's pool of record buffers.
#[derive(Clone, Debug)]
pub struct InsertPreparer {
    frame: BatchGrid,
    frame_max: [i32; 3],
    shuffle: Shuffle,
    options: ProgressiveOptions,
    bit_words: usize,
    pool: RecordPool,
}

/// Record buffers handed back by [`GpuProgressive::insert_prepared`] for reuse.
type RecordPool = std::sync::Arc<std::sync::Mutex<Vec<Vec<u32>>>>;

/// The scatter records of `xyz` (and `colors`) into `out`: per point its coarse, medium and fine
/// words and, with colours, the colour (3 or 4 words).
fn encode_records(frame: &BatchGrid, xyz: &[[i32; 3]], colors: Option<&[u32]>, out: &mut [u32]) {
    let stride = 3 + colors.is_some() as usize;
    for (k, r) in out.chunks_exact_mut(stride).enumerate() {
        r[..3].copy_from_slice(&frame.encode(xyz[k]));
        if let Some(c) = colors {
            r[3] = c[k];
        }
    }
}

thread_local! {
    /// Each thread's buffer for records encoded before they are copied into staging memory.
    static ENCODED: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Points ready for [`GpuProgressive::insert_prepared`]: their words (and colours) staged in
/// input order and their slots sorted by region of the host's bit array.
pub struct PreparedInsert {
    /// The renderer it was prepared for: capacity, colours, payloads, frame.
    of: (u32, bool, bool, [i32; 3], [i32; 3]),
    first: u64,
    n: usize,
    stride: usize,
    records: Vec<u32>,
    slots: SortedSlots,
    payload: Option<Vec<u64>>,
}

impl PreparedInsert {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.n
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Input index of the first point.
    pub fn first(&self) -> u64 {
        self.first
    }
}

impl InsertPreparer {
    /// The checks of an insert that need no state: colours and payloads as the renderer was
    /// made, the index range, every point inside the frame.
    fn check(
        &self,
        first: u64,
        xyz: &[[i32; 3]],
        colors: Option<&[u32]>,
        payload: Option<&[u64]>,
        in_frame: bool,
    ) -> Result<(), ProgressiveGpuError> {
        let n = xyz.len();
        match (self.options.colors, colors) {
            (true, Some(c)) if c.len() == n => {}
            (true, Some(c)) => {
                return Err(GpuError::Colors(format!("{} colours for {n} points", c.len())).into())
            }
            (true, None) => {
                return Err(GpuError::Colors(
                    "the renderer has colours but points came without".into(),
                )
                .into())
            }
            (false, Some(_)) => {
                return Err(GpuError::Colors("the renderer was made without colours".into()).into())
            }
            (false, None) => {}
        }
        match (self.options.payloads, payload) {
            (true, Some(p)) if p.len() != n => {
                return Err(ProgressiveError::PayloadCount { points: n, payloads: p.len() }.into())
            }
            (true, None) => {
                return Err(ProgressiveError::PayloadCount { points: n, payloads: 0 }.into())
            }
            (false, Some(p)) => {
                return Err(ProgressiveError::PayloadCount { points: n, payloads: p.len() }.into())
            }
            _ => {}
        }
        let capacity = self.shuffle.len() as u64;
        let end = first.saturating_add(n as u64);
        if end > capacity {
            return Err(ProgressiveError::IndexRange { first, end, capacity }.into());
        }
        let (min, max) = (self.frame.min, self.frame_max);
        if !in_frame {
            return Ok(());
        }
        if let Some(k) =
            xyz.par_iter().position_first(|p| (0..3).any(|a| p[a] < min[a] || p[a] > max[a]))
        {
            return Err(ProgressiveError::OutsideFrame {
                index: first + k as u64,
                point: xyz[k],
                min,
                max,
            }
            .into());
        }
        Ok(())
    }

    /// The costly, stateless half of [`GpuProgressive::insert`], which may run on any thread
    /// while frames are drawn: checks the points (colours and payloads as the renderer was made,
    /// index range, inside the frame), encodes their words, computes and sorts their slots.
    /// Duplicates are checked by [`GpuProgressive::insert_prepared`].
    pub fn prepare(
        &self,
        first: u64,
        xyz: &[[i32; 3]],
        colors: Option<&[u32]>,
        payload: Option<&[u64]>,
    ) -> Result<PreparedInsert, ProgressiveGpuError> {
        self.check(first, xyz, colors, payload, true)?;
        let n = xyz.len();
        let (min, max) = (self.frame.min, self.frame_max);
        let stride = 3 + colors.is_some() as usize;
        // A buffer handed back by an earlier insert if there is one (its pages are mapped).
        let mut records = self.pool.lock().ok().and_then(|mut p| p.pop()).unwrap_or_default();
        records.resize(n * stride, 0);
        let frame = self.frame;
        const PIECE: usize = 1 << 14;
        records.par_chunks_mut(PIECE * stride).enumerate().for_each(|(j, out)| {
            let (a, b) = (j * PIECE, (j * PIECE + PIECE).min(n));
            encode_records(&frame, &xyz[a..b], colors.map(|c| &c[a..b]), out);
        });
        let shuffle = self.shuffle;
        Ok(PreparedInsert {
            of: (self.shuffle.len(), self.options.colors, self.options.payloads, min, max),
            first,
            n,
            stride,
            records,
            slots: SortedSlots::new(self.bit_words, first as u32, n, |i| shuffle.target(i)),
            payload: payload.map(<[u64]>::to_vec),
        })
    }
}

/// The slots `target(first + k)`, `k < n`, sorted by region of a bit array of `words` words, per
/// task (a counting sort), ready to set their bits. The slots are random: one atomic OR per slot
/// costs a locked cache miss each (55 M points/s on two cores); setting each region's bits from
/// one thread, which owns its words and keeps them in cache, is about twice as fast with the
/// sort included, and the sort can run on another thread than the one that owns the bits.
struct SortedSlots {
    /// Regions of 2^shift slots (whole words: shift >= 6), at most about 4096 of them.
    shift: u32,
    /// Per task: its slots by region, and where each region starts.
    tasks: Vec<(Vec<u32>, Vec<u32>)>,
}

impl SortedSlots {
    fn new(words: usize, first: u32, n: usize, target: impl Fn(u32) -> u32 + Sync) -> SortedSlots {
        const TASK: usize = 1 << 16;
        let slots = words as u64 * 64;
        let shift = (64 - slots.saturating_sub(1).leading_zeros()).saturating_sub(12).max(14);
        let regions = (slots >> shift) as usize + 1;
        let tasks = (0..n)
            .step_by(TASK)
            .collect::<Vec<_>>()
            .into_par_iter()
            .map(|s| {
                let m = (n - s).min(TASK);
                let targets: Vec<u32> = (0..m).map(|k| target(first + (s + k) as u32)).collect();
                let mut starts = vec![0u32; regions + 1];
                for &t in &targets {
                    starts[(t >> shift) as usize + 1] += 1;
                }
                for r in 0..regions {
                    starts[r + 1] += starts[r];
                }
                let mut next = starts.clone();
                let mut out = vec![0u32; m];
                for &t in &targets {
                    let r = (t >> shift) as usize;
                    out[next[r] as usize] = t;
                    next[r] += 1;
                }
                (out, starts)
            })
            .collect();
        SortedSlots { shift, tasks }
    }

    /// Sets the slots' bits in `bits` (the array of `words` words they were sorted for).
    fn apply(&self, bits: &mut [AtomicU64]) {
        if self.tasks.is_empty() {
            return;
        }
        let words = 1usize << (self.shift - 6);
        bits.par_chunks_mut(words).enumerate().for_each(|(r, region)| {
            let base = r * words;
            for (out, starts) in &self.tasks {
                for &t in &out[starts[r] as usize..starts[r + 1] as usize] {
                    *region[t as usize / 64 - base].get_mut() |= 1 << (t % 64);
                }
            }
        });
    }
}

/// A piece of a staging view handed to one thread.
struct SendWrite<'a>(wgpu::WriteOnly<'a, [u8]>);

// SAFETY: a `WriteOnly<[u8]>` is an exclusive, write-only view of bytes, like `&mut [u8]`, which
// is `Send`; wgpu implements `Send` for `WriteOnly<T>` only for sized `T: Send` (its impl lacks
// `?Sized`), not for a slice. The pieces are disjoint (`split_at`).
unsafe impl Send for SendWrite<'_> {}

/// A set of `u64` indices kept as disjoint, non-adjacent ranges `[start, end)`.
#[derive(Default)]
struct Ranges(std::collections::BTreeMap<u64, u64>);

impl Ranges {
    /// The smallest index of `[s, e)` in the set.
    fn first_in(&self, s: u64, e: u64) -> Option<u64> {
        if let Some((_, &end)) = self.0.range(..=s).next_back() {
            if end > s && s < e {
                return Some(s);
            }
        }
        self.0.range(s..e).next().map(|(&start, _)| start)
    }

    /// The smallest index of `[s, e)` not in the set.
    fn first_missing(&self, s: u64, e: u64) -> Option<u64> {
        if s >= e {
            return None;
        }
        match self.0.range(..=s).next_back() {
            Some((_, &end)) if end > s => (end < e).then_some(end),
            _ => Some(s),
        }
    }

    /// Adds `[s, e)` (disjoint from the set), merging with the ranges it touches.
    fn insert(&mut self, mut s: u64, mut e: u64) {
        if s >= e {
            return;
        }
        if let Some((&start, &end)) = self.0.range(..=s).next_back() {
            if end == s {
                self.0.remove(&start);
                s = start;
            }
        }
        if let Some(end) = self.0.remove(&e) {
            e = end;
        }
        self.0.insert(s, e);
    }
}

impl SlotBook {
    /// The runs of Fill for `count` slots from the cursor (wrapping around), split at chunk
    /// boundaries, as `(chunk, offset in chunk, slots)`; advances the cursor and marks the loaded
    /// slots drawn. Returns the runs and the points (loaded slots) among them.
    fn sweep(
        &mut self,
        count: u64,
        chunks: &[SlotChunk],
        chunk_slots: u32,
        capacity: u64,
    ) -> (Vec<(usize, u32, u32)>, u64) {
        let n = capacity;
        let mut left = count.min(n);
        let mut runs = Vec::new();
        let mut points = 0;
        while left > 0 {
            let s = self.cursor;
            let c = (s / chunk_slots as u64) as usize;
            let chunk = &chunks[c];
            let chunk_end = chunk.first as u64 + chunk.len as u64;
            let e = (s + left).min(chunk_end);
            runs.push((c, (s - chunk.first as u64) as u32, (e - s) as u32));
            points += self.mark(s as usize, e as usize, capacity);
            left -= e - s;
            self.cursor = if e == n { 0 } else { e };
        }
        (runs, points)
    }

    /// Marks the loaded slots of `[s, e)` drawn since the view changed; returns how many there are.
    fn mark(&mut self, s: usize, e: usize, capacity: u64) -> u64 {
        let all = self.loaded == capacity;
        let (ws, we) = (s / 64, e.div_ceil(64));
        let bits = &self.loaded_bits[ws..we];
        let (points, new): (u64, u64) = self.done[ws..we]
            .par_iter_mut()
            .zip(bits)
            .enumerate()
            .with_min_len(1024)
            .map(|(k, (d, l))| {
                let w = ws + k;
                let lo = s.max(w * 64) - w * 64;
                let hi = e.min(w * 64 + 64) - w * 64;
                let range = if hi - lo == 64 { u64::MAX } else { ((1u64 << (hi - lo)) - 1) << lo };
                let mask = if all { range } else { range & l.load(Ordering::Relaxed) };
                let new = (mask & !*d).count_ones() as u64;
                *d |= mask;
                (mask.count_ones() as u64, new)
            })
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        self.done_count += new;
        points
    }

    /// Whether every slot is loaded and drawn since the view last changed.
    fn converged(&self, capacity: u64) -> bool {
        self.loaded == capacity && self.done_count == capacity
    }
}

impl Target {
    /// The target of the next frame: `slot`'s if it has `width x height` pixels, else a new one
    /// (the last Prepare's visible lists carried over; the old resolved image dropped). On an
    /// error `slot` and `resolved` are left as they were.
    fn ensure<'a>(
        slot: &'a mut Option<Target>,
        resolved: &mut Option<Resolved>,
        ctx: &GpuContext,
        gpu: &GpuState,
        list_counts: &[u32],
        width: u32,
        height: u32,
    ) -> Result<&'a Target, GpuError> {
        let t = match slot.take() {
            Some(t) if (t.width, t.height) == (width, height) => t,
            old => match Target::new(ctx, gpu, old.as_ref(), list_counts, width, height) {
                Ok(t) => {
                    *resolved = None;
                    t
                }
                Err(e) => {
                    *slot = old;
                    return Err(e);
                }
            },
        };
        Ok(slot.insert(t))
    }

    /// The framebuffer for `width x height`, the visible lists (`old`'s if they are large
    /// enough, else grown with `old`'s entries copied) and the bind groups of clear, Fill and
    /// Prepare.
    fn new(
        ctx: &GpuContext,
        gpu: &GpuState,
        old: Option<&Target>,
        list_counts: &[u32],
        width: u32,
        height: u32,
    ) -> Result<Target, GpuError> {
        let pixels = width as u64 * height as u64;
        if pixels == 0 || pixels * 8 > ctx.max_binding() {
            return Err(GpuError::TooLarge {
                what: "the framebuffer",
                needed: pixels * 8,
                limit: ctx.max_binding(),
            });
        }
        let copy = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        let align = ctx.limits().min_storage_buffer_offset_alignment.max(4) as u64;
        let stride = round_up(pixels, align / 4);
        let (lists, list_stride) = match old {
            Some(o) if o.list_stride as u64 >= stride => (o.lists.clone(), o.list_stride),
            _ => {
                let size = gpu.chunks.len().max(1) as u64 * stride * 4;
                if size > ctx.max_binding() || stride > u32::MAX as u64 {
                    return Err(GpuError::TooLarge {
                        what: "the visible lists",
                        needed: size,
                        limit: ctx.max_binding(),
                    });
                }
                let lists = storage(ctx, "visible lists", size, copy);
                // The last Prepare's lists move along: the next Reproject draws them in the new view.
                if let Some(o) = old {
                    let mut enc =
                        ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                            label: Some("grow visible lists"),
                        });
                    for (c, &count) in list_counts.iter().enumerate() {
                        if count > 0 {
                            enc.copy_buffer_to_buffer(
                                &o.lists,
                                c as u64 * o.list_stride as u64 * 4,
                                &lists,
                                c as u64 * stride * 4,
                                count as u64 * 4,
                            );
                        }
                    }
                    ctx.queue.submit([enc.finish()]);
                }
                (lists, stride as u32)
            }
        };
        let keys = storage(ctx, "progressive keys", pixels * 8, copy);
        let (passes, f) = (&gpu.passes, &gpu.per_frame);
        let clear_group = passes.clear.bind_group(
            ctx,
            0,
            &[entry(binding::CLEAR_WORDS, keys.as_entire_binding())],
        );
        let fill_group = passes.fill.bind_group(
            ctx,
            0,
            &[
                entry(binding::FRAME, f.frame_uniforms.as_entire_binding()),
                entry(binding::KEYS, keys.as_entire_binding()),
                entry(binding::COUNTERS, f.counters.as_entire_binding()),
            ],
        );
        let prepare_group = passes.prepare.bind_group(
            ctx,
            0,
            &[
                entry(binding::PREPARE_PARAMS, f.prepare_uniforms.as_entire_binding()),
                entry(binding::PREPARE_KEY_WORDS, keys.as_entire_binding()),
                entry(binding::PREPARE_LIST_COUNTS, f.list_counts.as_entire_binding()),
                entry(binding::PREPARE_LISTS, lists.as_entire_binding()),
            ],
        );
        ctx.check()?;
        Ok(Target {
            width,
            height,
            keys,
            lists,
            list_stride,
            clear_group,
            fill_group,
            prepare_group,
        })
    }
}

impl Resolved {
    /// `slot`'s image and bind groups, made for `t` if there are none.
    fn ensure<'a>(
        slot: &'a mut Option<Resolved>,
        ctx: &GpuContext,
        gpu: &GpuState,
        t: &Target,
    ) -> Result<&'a Resolved, GpuError> {
        let r = match slot.take() {
            Some(r) => r,
            None => Resolved::new(ctx, gpu, t)?,
        };
        Ok(slot.insert(r))
    }

    /// The image of `t`, the filled keys, one resolve bind group per chunk for each source of
    /// keys (the dummy colours when there is no chunk), and the hole-fill and eye-dome groups.
    fn new(ctx: &GpuContext, gpu: &GpuState, t: &Target) -> Result<Resolved, GpuError> {
        let pixels = t.width as u64 * t.height as u64;
        let image = storage(ctx, "progressive image", pixels * 4, wgpu::BufferUsages::COPY_SRC);
        let filled =
            storage(ctx, "progressive filled keys", pixels * 8, wgpu::BufferUsages::COPY_SRC);
        let colors: Vec<&wgpu::Buffer> = if gpu.chunks.is_empty() {
            vec![&gpu.dummy]
        } else {
            // A renderer with colours (checked by `frame`) has them in every chunk.
            gpu.chunks
                .iter()
                .map(|c| {
                    c.colors.as_ref().ok_or_else(|| {
                        GpuError::Colors("resolve asked for but the renderer has no colours".into())
                    })
                })
                .collect::<Result<_, _>>()?
        };
        let f = &gpu.per_frame;
        // The 64-bit keys read as words: index at 2p, depth bits at 2p + 1; the filled keys alike.
        let groups_of = |keys: &wgpu::Buffer| -> Vec<wgpu::BindGroup> {
            colors
                .iter()
                .zip(&f.resolve_uniforms)
                .map(|(colors, u)| {
                    gpu.passes.resolve.bind_group(
                        ctx,
                        0,
                        &[
                            entry(binding::RESOLVE_PARAMS, u.as_entire_binding()),
                            entry(binding::RESOLVE_INDEX_WORDS, keys.as_entire_binding()),
                            entry(binding::RESOLVE_DEPTH_WORDS, keys.as_entire_binding()),
                            entry(binding::RESOLVE_COLORS, colors.as_entire_binding()),
                            entry(binding::RESOLVE_IMAGE, image.as_entire_binding()),
                        ],
                    )
                })
                .collect()
        };
        let eye_dome_of = |keys: &wgpu::Buffer| {
            gpu.passes.eye_dome.bind_group(
                ctx,
                0,
                &[
                    entry(binding::EYE_DOME_PARAMS, f.eye_dome_uniforms.as_entire_binding()),
                    entry(binding::EYE_DOME_DEPTH_WORDS, keys.as_entire_binding()),
                    entry(binding::EYE_DOME_IMAGE, image.as_entire_binding()),
                ],
            )
        };
        let fill_group = gpu.passes.hole_fill.bind_group(
            ctx,
            0,
            &[
                entry(binding::FILL_PARAMS, f.fill_uniforms.as_entire_binding()),
                entry(binding::FILL_INDEX_WORDS, t.keys.as_entire_binding()),
                entry(binding::FILL_DEPTH_WORDS, t.keys.as_entire_binding()),
                entry(binding::FILL_FILLED, filled.as_entire_binding()),
            ],
        );
        let r = Resolved {
            groups: groups_of(&t.keys),
            groups_filled: groups_of(&filled),
            fill_group,
            eye_dome_group: eye_dome_of(&t.keys),
            eye_dome_group_filled: eye_dome_of(&filled),
            image,
        };
        ctx.check()?;
        Ok(r)
    }
}

impl GpuState {
    fn timestamps(
        &self,
        begin: Option<u32>,
        end: Option<u32>,
    ) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        if begin.is_none() && end.is_none() {
            return None;
        }
        self.queries.as_ref().map(|q| q.writes(begin, end))
    }

    /// How the adaptive budget's timings are measured.
    fn timing(&self) -> BudgetTiming {
        if self.queries.is_some() {
            BudgetTiming::GpuTimestamps
        } else {
            BudgetTiming::HostClock
        }
    }

    /// Writes `dispatches` as records from slot `first_record` and returns their bind groups
    /// (group 1, and for Reproject group 0 with the chunk's list) with workgroup counts.
    fn draw_groups(
        &self,
        ctx: &GpuContext,
        t: &Target,
        dispatches: &[Dispatch],
        first_record: usize,
        reproject: bool,
    ) -> Vec<(Option<wgpu::BindGroup>, wgpu::BindGroup, u32)> {
        let f = &self.per_frame;
        let record_size = std::mem::size_of::<DrawRecord>() as u64;
        dispatches
            .iter()
            .enumerate()
            .map(|(k, d)| {
                let offset = (first_record + k) as u64 * f.record_stride;
                ctx.queue.write_buffer(&f.records, offset, bytemuck::bytes_of(&d.record));
                let record = wgpu::BufferBinding {
                    buffer: &f.records,
                    offset,
                    size: NonZeroU64::new(record_size),
                };
                let g1 =
                    batches_group(ctx, &self.passes.shared, record, &self.chunks[d.chunk].words);
                let g0 = reproject.then(|| {
                    let list = wgpu::BufferBinding {
                        buffer: &t.lists,
                        offset: d.chunk as u64 * t.list_stride as u64 * 4,
                        size: NonZeroU64::new(d.record.count as u64 * 4),
                    };
                    self.passes.reproject.bind_group(
                        ctx,
                        0,
                        &[
                            entry(binding::FRAME, f.frame_uniforms.as_entire_binding()),
                            entry(binding::KEYS, t.keys.as_entire_binding()),
                            entry(binding::COUNTERS, f.counters.as_entire_binding()),
                            entry(binding::VISIBLE, wgpu::BindingResource::Buffer(list)),
                        ],
                    )
                });
                (g0, g1, (d.record.count as u64).div_ceil(SLOTS_PER_GROUP) as u32)
            })
            .collect()
    }

    /// Records one draw pass (Reproject or Fill) of `dispatches` into `enc`.
    #[allow(clippy::too_many_arguments)]
    fn encode_draw(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        t: &Target,
        label: &str,
        dispatches: &[Dispatch],
        first_record: usize,
        reproject: bool,
        ts: (Option<u32>, Option<u32>),
    ) {
        let pipe = if reproject { &self.passes.reproject } else { &self.passes.fill };
        let groups = self.draw_groups(ctx, t, dispatches, first_record, reproject);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: self.timestamps(ts.0, ts.1),
        });
        pass.set_pipeline(pipe.pipeline());
        for (g0, g1, n) in &groups {
            if *n == 0 {
                continue;
            }
            // Reproject binds its chunk's list in group 0; Fill the target's one group 0.
            let g0 = match g0 {
                Some(g) => g,
                None => &t.fill_group,
            };
            pass.set_bind_group(0, g0, &[]);
            pass.set_bind_group(1, g1, &[]);
            let (x, y) = ctx.split_dispatch(*n);
            pass.dispatch_workgroups(x, y, 1);
        }
    }

    /// Records the clear of the framebuffer.
    fn encode_clear(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        t: &Target,
        ts: (Option<u32>, Option<u32>),
    ) {
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("clear"),
            timestamp_writes: self.timestamps(ts.0, ts.1),
        });
        pass.set_pipeline(self.passes.clear.pipeline());
        pass.set_bind_group(0, &t.clear_group, &[]);
        let (x, y) = ctx.split_dispatch((t.keys.size() / 4).div_ceil(256) as u32);
        pass.dispatch_workgroups(x, y, 1);
    }

    /// Records Prepare (the list counts zeroed first).
    fn encode_prepare(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        t: &Target,
        chunk_slots: u32,
        ts: (Option<u32>, Option<u32>),
    ) {
        let pixels = t.width * t.height;
        let u = PrepareUniforms {
            pixels,
            chunk_slots,
            list_stride: t.list_stride,
            chunks: self.chunks.len() as u32,
        };
        ctx.queue.write_buffer(&self.per_frame.prepare_uniforms, 0, bytemuck::bytes_of(&u));
        enc.clear_buffer(&self.per_frame.list_counts, 0, None);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("prepare"),
            timestamp_writes: self.timestamps(ts.0, ts.1),
        });
        pass.set_pipeline(self.passes.prepare.pipeline());
        pass.set_bind_group(0, &t.prepare_group, &[]);
        let (x, y) = ctx.split_dispatch(pixels.div_ceil(256));
        pass.dispatch_workgroups(x, y, 1);
    }

    /// Records the resolve into `r`'s image: hole filling (the framebuffer into the filled keys),
    /// the colours (one dispatch per chunk, from the filled keys or the framebuffer) and eye-dome
    /// lighting of the image from the same keys' depths, as the batch rasterizer resolves; the
    /// timestamps `ts` around all of them.
    fn encode_resolve(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        t: &Target,
        r: &Resolved,
        post: &ResolveOptions,
        ts: (Option<u32>, Option<u32>),
    ) {
        let (x, y) = ctx.split_dispatch((t.width as u64 * t.height as u64).div_ceil(256) as u32);
        // Both key buffers hold two words per pixel: the index, then the depth bits.
        let (stride, depth_offset) = (2, 1);
        let last_is_resolve = post.eye_dome.is_none();
        if let Some(fill) = &post.hole_fill {
            let u = HoleFillUniforms::new(fill, t.width, t.height, stride, depth_offset);
            ctx.queue.write_buffer(&self.per_frame.fill_uniforms, 0, bytemuck::bytes_of(&u));
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("hole fill"),
                timestamp_writes: self.timestamps(ts.0, None),
            });
            pass.set_pipeline(self.passes.hole_fill.pipeline());
            pass.set_bind_group(0, &r.fill_group, &[]);
            pass.dispatch_workgroups(x, y, 1);
        }
        for (i, u) in self.per_frame.resolve_uniforms.iter().enumerate().take(r.groups.len()) {
            let (first_index, count) = self.chunks.get(i).map_or((0, 0), |c| (c.first, c.len));
            let u_val = ResolveUniforms {
                width: t.width,
                height: t.height,
                key_stride: stride,
                depth_offset,
                first_index,
                count,
                background: post.background,
                write_background: (i == 0) as u32,
            };
            ctx.queue.write_buffer(u, 0, bytemuck::bytes_of(&u_val));
        }
        {
            let begin = if post.hole_fill.is_some() { None } else { ts.0 };
            let end = if last_is_resolve { ts.1 } else { None };
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("resolve"),
                timestamp_writes: self.timestamps(begin, end),
            });
            pass.set_pipeline(self.passes.resolve.pipeline());
            let groups = if post.hole_fill.is_some() { &r.groups_filled } else { &r.groups };
            for bg in groups {
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        if let Some(edl) = &post.eye_dome {
            let u = EyeDomeUniforms::new(edl, t.width, t.height, stride, depth_offset);
            ctx.queue.write_buffer(&self.per_frame.eye_dome_uniforms, 0, bytemuck::bytes_of(&u));
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("eye-dome lighting"),
                timestamp_writes: self.timestamps(None, ts.1),
            });
            pass.set_pipeline(self.passes.eye_dome.pipeline());
            pass.set_bind_group(
                0,
                if post.hole_fill.is_some() { &r.eye_dome_group_filled } else { &r.eye_dome_group },
                &[],
            );
            pass.dispatch_workgroups(x, y, 1);
        }
    }

    /// The draw dispatches of Fill runs.
    fn fill_dispatches(
        &self,
        runs: &[(usize, u32, u32)],
        projection: &BatchProjection,
    ) -> Vec<Dispatch> {
        runs.iter()
            .map(|&(c, offset, count)| Dispatch {
                chunk: c,
                record: DrawRecord {
                    projection: *projection,
                    offset,
                    count,
                    first_index: self.chunks[c].first + offset,
                    _pad: 0,
                },
            })
            .collect()
    }

    /// Reads `count` timestamps from slot 0 (resolved into the query buffer by `enc`).
    fn resolve_queries(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        count: u32,
    ) -> Option<wgpu::Buffer> {
        self.queries.as_ref().map(|q| {
            enc.resolve_query_set(&q.set, 0..count, &q.buffer, 0);
            readback(ctx, enc, &q.buffer, count as u64 * 8)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bits sorted slots set equal one OR per slot, for one and many tasks and capacities
    /// that do and do not fill the last region.
    #[test]
    fn sorted_slots_set_the_same_bits_as_one_or_per_slot() {
        for (capacity, first, n) in [
            (3u32, 0u32, 0usize),
            (1000, 10, 900),
            (300_000, 0, 300_000),
            (1 << 20, 5, 600_000),
            ((1 << 22) + 77, 123_456, 2_000_000),
        ] {
            let shuffle = Shuffle::new(capacity);
            let words = (capacity as usize).div_ceil(64);
            let mut bits: Vec<AtomicU64> = (0..words).map(|_| AtomicU64::new(0)).collect();
            SortedSlots::new(words, first, n, |t| shuffle.target(t)).apply(&mut bits);
            let mut want = vec![0u64; words];
            for k in 0..n {
                let t = shuffle.target(first + k as u32);
                want[t as usize / 64] |= 1 << (t % 64);
            }
            let got: Vec<u64> = bits.iter().map(|w| w.load(Ordering::Relaxed)).collect();
            assert_eq!(got, want, "capacity {capacity}");
            assert_eq!(got.iter().map(|w| w.count_ones() as usize).sum::<usize>(), n);
        }
    }

    #[test]
    fn ranges_merge_and_answer_first_in_and_first_missing() {
        let mut r = Ranges::default();
        assert_eq!(r.first_in(0, 10), None);
        assert_eq!(r.first_missing(0, 10), Some(0));
        assert_eq!(r.first_missing(5, 5), None);
        r.insert(10, 20);
        r.insert(30, 40);
        assert_eq!(r.first_in(0, 10), None);
        assert_eq!(r.first_in(0, 11), Some(10));
        assert_eq!(r.first_in(15, 16), Some(15));
        assert_eq!(r.first_in(20, 30), None);
        assert_eq!(r.first_in(25, 100), Some(30));
        assert_eq!(r.first_missing(10, 20), None);
        assert_eq!(r.first_missing(12, 25), Some(20));
        assert_eq!(r.first_missing(9, 12), Some(9));
        r.insert(20, 30);
        assert_eq!(r.0.len(), 1, "touching ranges merge: {:?}", r.0);
        assert_eq!(r.first_missing(10, 40), None);
        assert_eq!(r.first_missing(10, 41), Some(40));
        r.insert(0, 10);
        r.insert(40, 41);
        assert_eq!(r.0.iter().map(|(&a, &b)| (a, b)).collect::<Vec<_>>(), vec![(0, 41)]);
    }
}
