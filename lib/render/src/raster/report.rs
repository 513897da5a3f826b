//! What a frame reports: its statistics and host times ([`GpuFrame`]), the GPU time of each pass
//! ([`GpuTimings`]), and the timestamp slots those times are read from.

use mortar_core::render::resolve::ResolveOptions;
use mortar_core::render::RasterStats;

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

/// Timestamp slots: clear begin/end, draw begin/end, hole fill, resolve and eye-dome lighting
/// begin/end, plan begin/end.
pub(super) const QUERIES: u32 = 12;

/// The first slot of the resolve's passes (hole fill).
pub(super) const RESOLVE_QUERIES: u32 = 4;

/// The plan pass's slots.
pub(super) const PLAN_QUERIES: u32 = 10;

/// The resolve's pass times `(hole fill, resolve, eye-dome lighting)` in milliseconds from the
/// timestamps `t` (ticks of `period` ms), the passes `options` did not run `None`.
pub(super) fn resolve_timings(
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
