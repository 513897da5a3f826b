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
//!   options) last changed; converged once every slot is loaded and drawn. The shuffle, the
//!   frame, the points loaded, Fill's cursor, the view and these bits are one
//!   [`ProgressiveState`] that both renderers hold and drive alike.
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
//! [`atomic_path`](crate::context::GpuContext::atomic_path) is the 32-bit two-pass path,
//! [`GpuProgressive::new`] fails with [`ProgressiveGpuError::Needs64BitAtomics`] (the two-pass path
//! would need a second Reproject and Fill per frame; the CPU renderer serves such machines).
//! Deviations from the paper: no MSAA; 12 bytes of words per point (16 with colours) instead of
//! 16 bytes of floats and attributes; [`RasterStats`] counts one "batch" per dispatch.
//!
//! The files, one concept each: `gpu` (the renderer, [`GpuProgressive`]), `device` (the GPU
//! state that lives as long as it), `target` (the framebuffer, visible lists and resolved image of
//! a viewport size), `encode` (recording the passes of a frame), `upload` (staging and scattering
//! records), `insert` (insert preparation: [`InsertPreparer`], [`PreparedInsert`], the sorted
//! slots), `slots` (the host's bookkeeping of the slots), `options` ([`ProgressiveOptions`]),
//! `frame` (what a frame reports: [`GpuProgressiveFrame`], [`BudgetTiming`],
//! [`ProgressiveGpuTimings`]) and `error` ([`ProgressiveGpuError`]).
//!
//! [`MAX_CHUNK_POINTS`]: crate::scene::MAX_CHUNK_POINTS
//! [`Shuffle::target`]: mortar_core::render::progressive::Shuffle::target
//! [`ResolveOptions`]: mortar_core::render::resolve::ResolveOptions
//! [`Planner`]: mortar_core::render::Planner
//! [`FillBudget::Adaptive`]: mortar_core::render::progressive::FillBudget::Adaptive
//! [`ProbeTimings`]: mortar_core::render::progressive::ProbeTimings
//! [`AdaptiveBudget::extra_points`]: mortar_core::render::progressive::AdaptiveBudget::extra_points
//! [`ProgressiveFrame`]: mortar_core::render::progressive::ProgressiveFrame
//! [`ProgressiveState`]: mortar_core::render::progressive::ProgressiveState
//! [`RasterStats`]: mortar_core::render::RasterStats

mod device;
mod encode;
mod error;
mod frame;
mod gpu;
mod insert;
mod options;
mod slots;
mod target;
mod upload;

pub use encode::SLOTS_PER_THREAD;
pub use error::ProgressiveGpuError;
pub use frame::{BudgetTiming, GpuProgressiveFrame, ProgressiveGpuTimings};
pub use gpu::GpuProgressive;
pub use insert::{InsertPreparer, PreparedInsert};
pub use options::ProgressiveOptions;

/// The uniforms of the scatter and Prepare passes, defined with the other records the GPU reads
/// in [`mortar_core::render::gpu`] (re-exported here where they used to be).
pub use mortar_core::render::gpu::{PrepareUniforms, ScatterUniforms};
