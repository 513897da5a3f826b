//! mortar-render: the wgpu compute rasterizer (paper 003), the GPU twin of mortar-core's CPU
//! reference rasterizer.
//!
//! - [`context`]: headless device setup with the adapter's real limits, 64-bit atomics
//!   (SHADER_INT64 + SHADER_INT64_ATOMIC_MIN_MAX) and timestamps where present, and the choice of
//!   the 64-bit or the 32-bit two-pass atomic path at run time.
//! - [`scene`]: point batches streamed into chunked storage buffers sized to the device.
//! - [`raster`]: per frame, the shared [`mortar_core::render::Planner`] decides culling, precision
//!   and projection per batch; the GPU clears, draws (one workgroup of 128 threads per batch,
//!   dispatches split past 65,535 workgroups) and resolves.
//! - [`progressive`]: the progressive renderer of paper 000 (shuffled buffer, Reproject, Fill,
//!   Prepare, adaptive fill budget from GPU timestamps), the twin of mortar-core's CPU one.
//! - [`shaders`]: the WGSL modules of `shaders/`, assembled from `shaders/common/` and one file
//!   per pass, and the binding table of every pass (tested against the WGSL).
//! - `pipeline` (private): what the renderers build once: each pass's pipeline with explicit
//!   bind-group layouts made from its binding table.
//!
//! The `#[repr(C)]` records the passes read are defined once, in [`mortar_core::render::gpu`].
//!
//! - [`present`]: the window's surface (`mortar view`): the resolved image drawn into the surface
//!   texture by one render pass, without leaving the GPU. The surface comes from
//!   [`GpuContext::for_window`]; this crate knows no window library.
//!
//! This crate opens no files: callers hand it in-memory batches ([`mortar_core::render::BatchRef`]).

#![deny(unsafe_op_in_unsafe_fn)]

mod buffers;
pub mod context;
pub mod octree;
mod pipeline;
pub mod present;
pub mod progressive;
pub mod radix;
pub mod raster;
pub mod scene;
pub mod shaders;
#[doc(hidden)]
pub mod testing;

/// The wgpu this crate is built on (its surface type is part of [`GpuContext::for_window`]).
pub use wgpu;

pub use context::{AdapterSummary, AtomicPath, GpuContext, GpuError, GpuOptions};
pub use present::{Overlay, Presented, ReadBack, WindowSurface};
pub use progressive::{
    BudgetTiming, GpuProgressive, GpuProgressiveFrame, InsertPreparer, PreparedInsert,
    ProgressiveGpuError, ProgressiveGpuTimings, ProgressiveOptions,
};
pub use raster::{DrawTuning, GpuFrame, GpuRasterizer, GpuTimings, RecordOrder};
pub use scene::{GpuBatch, GpuScene, SceneOptions};
