//! `mortar build --engine gpu`: the GPU octree builder (`mortar_render::octree`) handed to the
//! store's GPU engine (`mortar_io::store`, which knows no GPU).

use anyhow::anyhow;
use mortar_core::octree::arrival::TreeBackend;
use mortar_render::octree::GpuTreeBuilder;
use mortar_render::{GpuContext, GpuOptions};
use std::sync::Arc;

/// The best adapter's octree builder. Asked for by name (`--engine gpu`), so a software adapter
/// (lavapipe) is accepted where no GPU exists; no adapter at all is an error naming the reason.
pub fn tree_backend() -> anyhow::Result<Arc<dyn TreeBackend>> {
    let ctx = GpuContext::new(&GpuOptions { allow_software: true, ..Default::default() })
        .map_err(|e| anyhow!("--engine gpu: {e}"))?;
    let b = GpuTreeBuilder::new(ctx).map_err(|e| anyhow!("--engine gpu: {e}"))?;
    Ok(Arc::new(b))
}
