//! What one frame of the GPU progressive renderer reports ([`GpuProgressiveFrame`]): the CPU
//! renderer's statistics, how the pass times were measured ([`BudgetTiming`]) and the GPU pass
//! times from timestamp queries ([`ProgressiveGpuTimings`]).

use mortar_core::render::progressive::FrameStats;

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
