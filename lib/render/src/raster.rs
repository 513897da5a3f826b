//! The GPU rasterizer (paper 003 §3.2-3.3 in wgpu compute shaders): per frame the host plans every
//! batch with the same [`Planner`] as the CPU reference (culling, precision, projection), uploads
//! one [`DrawRecord`] per drawn batch, and the GPU runs the passes of `shaders/`: clear, draw
//! batches (one workgroup of 128 threads per batch; 64-bit `atomicMin` or the 32-bit two-pass
//! path) and, when asked, resolve: depth-aware hole filling into a second key buffer, point index
//! to colour, eye-dome lighting of the image, as [`mortar_core::render::resolve::resolve`] does
//! on the host and equal to it byte for byte, without reading the keys back. The keys it leaves
//! are those of [`mortar_core::render::rasterize`] for the same view (see `docs/render.md` for
//! where a GPU may round differently).
//!
//! The rasterizer's files, one concept each:
//!
//! - `passes`: what it builds once: the pipelines of its passes and the buffers every frame
//!   writes anew.
//! - `target`: the framebuffer of one viewport size and the bind groups that use it.
//! - `tuning`: the draw pass's variants for measurements ([`DrawTuning`], [`RecordOrder`]).
//! - `report`: what a frame reports ([`GpuFrame`], [`GpuTimings`]) and the timestamp slots its
//!   pass times are read from.
//! - `draw`: one frame: planning (on the GPU or the host), clear and draw.
//! - `resolve`: the resolve's passes: hole filling, colours, eye-dome lighting.
//! - `read`: reading the keys, the hole-filled keys and the image back to the host.
//!
//! [`Planner`]: mortar_core::render::Planner
//! [`DrawRecord`]: mortar_core::render::gpu::DrawRecord

mod draw;
mod passes;
mod read;
mod report;
mod resolve;
mod target;
mod tuning;

use crate::context::{AtomicPath, GpuContext, GpuError};
use crate::pipeline::{storage, uniform, PassPipeline, SharedLayouts, Timestamps};
use crate::shaders::Pass;
use mortar_core::render::gpu::{
    plan_counter, EyeDomeUniforms, FrameUniforms, HoleFillUniforms, PlanUniforms,
};
use passes::{DrawPasses, Passes, PerFrame};
use report::QUERIES;
use target::Target;

pub use report::{GpuFrame, GpuTimings};
pub use tuning::{DrawTuning, RecordOrder};

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
}
