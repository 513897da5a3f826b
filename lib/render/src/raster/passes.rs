//! What the rasterizer builds once: the pipelines of its passes ([`Passes`], with the draw
//! pipelines of the atomic path, [`DrawPasses`]) and the buffers every frame writes anew
//! ([`PerFrame`]).

use crate::pipeline::{PassPipeline, SharedLayouts};

/// The draw pipelines of the context's atomic path.
pub(super) enum DrawPasses {
    /// `draw.wgsl`.
    U64(PassPipeline),
    /// `draw_depth.wgsl`, then `draw_index.wgsl`.
    TwoPass32([PassPipeline; 2]),
}

impl DrawPasses {
    /// The draw steps in order (one compute pass each).
    pub(super) fn steps(&self) -> &[PassPipeline] {
        match self {
            DrawPasses::U64(draw) => std::slice::from_ref(draw),
            DrawPasses::TwoPass32(steps) => steps,
        }
    }
}

/// The pipelines and layouts of the rasterizer: built once, whatever the viewport and the frame.
pub(super) struct Passes {
    pub(super) shared: SharedLayouts,
    pub(super) clear: PassPipeline,
    pub(super) plan: PassPipeline,
    pub(super) draw: DrawPasses,
    pub(super) resolve: PassPipeline,
    pub(super) hole_fill: PassPipeline,
    pub(super) eye_dome: PassPipeline,
}

/// What the rasterizer writes anew every frame: the camera's uniforms, the drawn-point counter,
/// the draw records and the uniforms of the resolve's passes. The buffers live as long as the
/// rasterizer; the records grow when a frame needs more.
pub(super) struct PerFrame {
    pub(super) frame_uniforms: wgpu::Buffer,
    pub(super) counters: wgpu::Buffer,
    pub(super) records: wgpu::Buffer,
    /// The plan pass's constants and counters.
    pub(super) plan_uniforms: wgpu::Buffer,
    pub(super) plan_counters: wgpu::Buffer,
    /// One per chunk of the last resolved scene (grown, never shrunk).
    pub(super) resolve_uniforms: Vec<wgpu::Buffer>,
    /// `HoleFillUniforms`.
    pub(super) fill_uniforms: wgpu::Buffer,
    /// `EyeDomeUniforms`.
    pub(super) eye_dome_uniforms: wgpu::Buffer,
}
