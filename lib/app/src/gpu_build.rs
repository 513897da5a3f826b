//! `mortar build --engine gpu`: the GPU octree builder (`mortar_render::octree`) handed to the
//! store's GPU engine (`mortar_io::store`, which knows no GPU).

use anyhow::anyhow;
use mortar_core::octree::arrival::TreeBackend;
use mortar_render::octree::GpuTreeBuilder;
use mortar_render::{GpuContext, GpuOptions};
use std::sync::Arc;

/// Whether the GPU sorts the points (`MORTAR_GPU_SORT=1`; ARCHITECTURE.md, "Who orders the
/// records"): off by default, since on the H100 it made no difference to the build (3.89 s against
/// 3.87 s at 100 M points, the write bounding both; BENCHMARKS.md, "The GPU sorts") and on
/// lavapipe it is slower than the host's sort; the tests turn it on to run it on lavapipe, the
/// benchmarks to compare the two in one binary.
fn gpu_sort() -> bool {
    std::env::var("MORTAR_GPU_SORT").is_ok_and(|v| v == "1")
}

/// The best adapter's octree builder, within `gpu_memory` bytes of GPU memory when given
/// (`--gpu-memory`; segments of points beyond it are paged). Asked for by name (`--engine gpu`),
/// so a software adapter (lavapipe) is accepted where no GPU exists; no adapter at all is an
/// error naming the reason.
pub fn tree_backend(gpu_memory: Option<u64>) -> anyhow::Result<Arc<dyn TreeBackend>> {
    let ctx = GpuContext::new(&GpuOptions { allow_software: true, ..Default::default() })
        .map_err(|e| anyhow!("--engine gpu: {e}"))?;
    let mut b =
        GpuTreeBuilder::new(ctx).map_err(|e| anyhow!("--engine gpu: {e}"))?.with_sort(gpu_sort());
    if let Some(bytes) = gpu_memory {
        b = b.with_memory_budget(bytes).map_err(|e| anyhow!("--gpu-memory: {e}"))?;
    }
    Ok(Arc::new(b))
}
