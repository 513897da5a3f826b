//! What one frame of a progressive renderer did ([`FrameStats`]), the same record for the CPU
//! renderer and its GPU twin.

use crate::render::raster::RasterStats;

/// What one frame did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameStats {
    /// Frame number, from 1.
    pub frame: u64,
    /// Points loaded when the frame was drawn.
    pub loaded: u64,
    /// Points drawn by Reproject (those visible at the end of the previous frame).
    pub reprojected: u64,
    /// Slots of the shuffled buffer swept by Fill (the budget spent; unloaded slots included).
    pub filled: u64,
    /// Of those, slots holding a point (the points Fill drew).
    pub fill_points: u64,
    /// With the adaptive budget: slots of the first, fixed step (included in `filled`).
    pub probe: u64,
    /// Points visible at the end of the frame (the next frame's Reproject buffer).
    pub visible: u64,
    /// What the rasterizer did, both passes together.
    pub raster: RasterStats,
    /// Time of the Reproject pass (framebuffer clear included), ms.
    pub reproject_ms: f64,
    /// Time of the Fill pass, ms.
    pub fill_ms: f64,
    /// Time of the Prepare pass, ms.
    pub prepare_ms: f64,
    /// Time of the whole frame, ms.
    pub total_ms: f64,
    /// Whether the image is final: every point loaded and drawn since the view last changed, so
    /// the keys equal the brute-force render of all points.
    pub converged: bool,
}
