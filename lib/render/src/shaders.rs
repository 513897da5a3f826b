//! The WGSL passes of the GPU rasterizer and of the GPU progressive renderer, assembled from
//! `shaders/` exactly as the pipelines and the validation test use them: WGSL has no `#include`,
//! so each pass is the shared files of `shaders/common/` (and, for the progressive passes,
//! `shaders/progressive_types.wgsl`) followed by the pass's own file.

/// The shared types and the split-dispatch helper (every pass).
const TYPES: &str = include_str!("../../../shaders/common/types.wgsl");
/// The one position decode and projection (draw passes).
const DECODE: &str = include_str!("../../../shaders/common/decode.wgsl");
/// The batch bindings and the per-point load-decode-project step (draw passes).
const BATCHES: &str = include_str!("../../../shaders/common/batches.wgsl");
/// The drawn-point counter (draw passes that count).
const COUNTERS: &str = include_str!("../../../shaders/common/counters.wgsl");
/// The progressive renderer's constants and uniform structs (its passes, after `TYPES`).
const PROGRESSIVE: &str = include_str!("../../../shaders/progressive_types.wgsl");

/// The window's present pass (`shaders/present.wgsl`: a vertex and a fragment entry point, no
/// shared files), used by [`crate::present::WindowSurface`].
pub const PRESENT: &str = include_str!("../../../shaders/present.wgsl");

/// A compute pass of the rasterizer; one WGSL file each.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Pass {
    /// Sets framebuffer words to all ones (`shaders/clear.wgsl`).
    Clear,
    /// Draws batches with 64-bit `atomicMin` on depth|index keys (`shaders/draw.wgsl`).
    Draw64,
    /// 32-bit path, step 1: `atomicMin` of the depth (`shaders/draw_depth.wgsl`).
    DrawDepth32,
    /// 32-bit path, step 2: `atomicMin` of the index among the nearest (`shaders/draw_index.wgsl`).
    DrawIndex32,
    /// Point index to colour (`shaders/resolve.wgsl`).
    Resolve,
    /// Progressive renderer: marks a chunk's slots unloaded (`shaders/progressive_unload.wgsl`).
    ProgressiveUnload,
    /// Progressive renderer: staged points into their shuffled slots
    /// (`shaders/progressive_scatter.wgsl`).
    ProgressiveScatter,
    /// Progressive renderer: draws the last frame's visible slots
    /// (`shaders/progressive_reproject.wgsl`).
    ProgressiveReproject,
    /// Progressive renderer: draws a run of slots, skipping unloaded ones
    /// (`shaders/progressive_fill.wgsl`).
    ProgressiveFill,
    /// Progressive renderer: the visible slots into the next Reproject lists
    /// (`shaders/progressive_prepare.wgsl`).
    ProgressivePrepare,
}

impl Pass {
    /// Every pass.
    pub const ALL: [Pass; 10] = [
        Pass::Clear,
        Pass::Draw64,
        Pass::DrawDepth32,
        Pass::DrawIndex32,
        Pass::Resolve,
        Pass::ProgressiveUnload,
        Pass::ProgressiveScatter,
        Pass::ProgressiveReproject,
        Pass::ProgressiveFill,
        Pass::ProgressivePrepare,
    ];

    /// The pass's file under `shaders/`.
    pub fn file(self) -> &'static str {
        match self {
            Pass::Clear => "clear.wgsl",
            Pass::Draw64 => "draw.wgsl",
            Pass::DrawDepth32 => "draw_depth.wgsl",
            Pass::DrawIndex32 => "draw_index.wgsl",
            Pass::Resolve => "resolve.wgsl",
            Pass::ProgressiveUnload => "progressive_unload.wgsl",
            Pass::ProgressiveScatter => "progressive_scatter.wgsl",
            Pass::ProgressiveReproject => "progressive_reproject.wgsl",
            Pass::ProgressiveFill => "progressive_fill.wgsl",
            Pass::ProgressivePrepare => "progressive_prepare.wgsl",
        }
    }

    fn own_source(self) -> &'static str {
        match self {
            Pass::Clear => include_str!("../../../shaders/clear.wgsl"),
            Pass::Draw64 => include_str!("../../../shaders/draw.wgsl"),
            Pass::DrawDepth32 => include_str!("../../../shaders/draw_depth.wgsl"),
            Pass::DrawIndex32 => include_str!("../../../shaders/draw_index.wgsl"),
            Pass::Resolve => include_str!("../../../shaders/resolve.wgsl"),
            Pass::ProgressiveUnload => include_str!("../../../shaders/progressive_unload.wgsl"),
            Pass::ProgressiveScatter => include_str!("../../../shaders/progressive_scatter.wgsl"),
            Pass::ProgressiveReproject => include_str!("../../../shaders/progressive_reproject.wgsl"),
            Pass::ProgressiveFill => include_str!("../../../shaders/progressive_fill.wgsl"),
            Pass::ProgressivePrepare => include_str!("../../../shaders/progressive_prepare.wgsl"),
        }
    }

    /// Whether the pass uses 64-bit integers and atomics (SHADER_INT64 +
    /// SHADER_INT64_ATOMIC_MIN_MAX).
    pub fn needs_int64(self) -> bool {
        matches!(self, Pass::Draw64 | Pass::ProgressiveReproject | Pass::ProgressiveFill)
    }

    /// The complete WGSL module of the pass, as the pipeline compiles it.
    pub fn source(self) -> String {
        let mut parts = vec![TYPES];
        match self {
            Pass::Clear | Pass::Resolve => {}
            Pass::Draw64 | Pass::DrawIndex32 => parts.extend([DECODE, BATCHES, COUNTERS]),
            Pass::DrawDepth32 => parts.extend([DECODE, BATCHES]),
            Pass::ProgressiveUnload | Pass::ProgressiveScatter | Pass::ProgressivePrepare => parts.push(PROGRESSIVE),
            Pass::ProgressiveReproject | Pass::ProgressiveFill => parts.extend([PROGRESSIVE, DECODE, BATCHES, COUNTERS]),
        }
        parts.push(self.own_source());
        parts.join("\n")
    }
}
