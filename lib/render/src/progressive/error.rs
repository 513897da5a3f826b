//! Why the GPU progressive renderer refused something or failed ([`ProgressiveGpuError`]).

use crate::context::GpuError;
use mortar_core::render::progressive::ProgressiveError;
use mortar_core::render::RasterError;

/// Why the GPU progressive renderer refused something or failed.
#[derive(Debug, thiserror::Error)]
pub enum ProgressiveGpuError {
    /// The context runs the 32-bit two-pass path.
    #[error("{adapter}: the GPU progressive renderer needs 64-bit atomics (SHADER_INT64 + SHADER_INT64_ATOMIC_MIN_MAX) and this context uses the 32-bit two-pass path; use the CPU progressive renderer")]
    Needs64BitAtomics {
        /// The adapter's name.
        adapter: String,
    },
    /// Bad points, frame or view (the CPU renderer's errors; nothing was changed).
    #[error(transparent)]
    Progressive(#[from] ProgressiveError),
    /// The device failed or something does not fit it.
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

impl From<RasterError> for ProgressiveGpuError {
    fn from(e: RasterError) -> Self {
        ProgressiveGpuError::Progressive(ProgressiveError::Raster(e))
    }
}
