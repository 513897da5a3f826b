//! Why a progressive renderer refused something ([`ProgressiveError`]; nothing was changed): the
//! errors of the CPU renderer, which its GPU twin reports too.

use crate::render::error::RasterError;

/// Why the progressive renderer refused something (nothing was changed).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProgressiveError {
    /// More points than 32-bit indices can address.
    #[error("{0} points: the progressive renderer holds at most {max} points (32-bit indices)", max = u32::MAX)]
    TooManyPoints(u64),
    /// The frame's bounds are empty or need more than 30 bits on an axis.
    #[error("bounds {min:?}..{max:?} on the integer grid are empty or span more than 2^30 steps on an axis")]
    Frame {
        /// Smallest integer coordinate.
        min: [i32; 3],
        /// Largest integer coordinate.
        max: [i32; 3],
    },
    /// A point lies outside the frame given to
    /// [`ProgressiveRenderer::new`](super::ProgressiveRenderer::new).
    #[error("point {index} at {point:?} lies outside the bounds {min:?}..{max:?} (integer grid) the renderer was made for")]
    OutsideFrame {
        /// The point's input index.
        index: u64,
        /// Its integer coordinates.
        point: [i32; 3],
        /// Smallest integer coordinate of the frame.
        min: [i32; 3],
        /// Largest integer coordinate of the frame.
        max: [i32; 3],
    },
    /// Indices past the capacity.
    #[error("points {first}..{end} do not fit in a renderer of {capacity} points")]
    IndexRange {
        /// First index inserted.
        first: u64,
        /// One past the last.
        end: u64,
        /// The capacity.
        capacity: u64,
    },
    /// A point was inserted twice.
    #[error("point {0} was inserted twice")]
    Duplicate(u64),
    /// A payload was replaced for a point not inserted yet.
    #[error("point {0} has no payload to replace: it was not inserted")]
    NotLoaded(u64),
    /// Coordinates and payloads of different lengths.
    #[error("{points} points but {payloads} payloads")]
    PayloadCount {
        /// Number of points.
        points: usize,
        /// Number of payloads.
        payloads: usize,
    },
    /// The rasterizer refused the view.
    #[error(transparent)]
    Raster(#[from] RasterError),
}
