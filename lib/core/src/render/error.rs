//! Why a rasterization was refused: the error of the CPU rasterizer and of the planning both
//! rasterizers share.

use super::camera::CameraError;

/// Why a rasterization was refused (before anything was drawn).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RasterError {
    /// The camera is not usable.
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// Framebuffer and camera viewport differ.
    #[error("framebuffer is {fb_width}x{fb_height} but the camera's viewport is {width}x{height}")]
    Viewport {
        /// Framebuffer width.
        fb_width: u32,
        /// Framebuffer height.
        fb_height: u32,
        /// Camera width.
        width: u32,
        /// Camera height.
        height: u32,
    },
    /// A batch's three word arrays have different lengths.
    #[error("batch {batch}: coarse, medium and fine words have different lengths {lengths:?}")]
    WordCounts {
        /// Position of the batch in the slice.
        batch: usize,
        /// The three lengths.
        lengths: [usize; 3],
    },
    /// A batch's point indices do not fit in 32 bits.
    #[error(
        "batch {batch}: points {first_index}.. ({count} points) exceed the 32-bit point index"
    )]
    IndexOverflow {
        /// Position of the batch in the slice.
        batch: usize,
        /// Its first index.
        first_index: u32,
        /// Its point count.
        count: usize,
    },
    /// A gathered batch has another number of point indices than points.
    #[error("gathered batch {batch}: {points} points but {indices} point indices")]
    IndexCount {
        /// Position of the batch in the slice.
        batch: usize,
        /// Its number of points (word count).
        points: usize,
        /// Its number of indices.
        indices: usize,
    },
}
