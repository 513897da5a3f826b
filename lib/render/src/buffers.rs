//! GPU buffer helpers every renderer of this crate uses: growing a buffer, copying one back to
//! the host and reading it (the rasterizer, the scene, the progressive renderer, the window).

use crate::context::{GpuContext, GpuError};
use std::sync::mpsc;

/// The size of a buffer grown from `old` bytes to hold at least `needed`: half as large again,
/// within the device's largest buffer, and a multiple of 256 bytes (a storage binding of the
/// whole buffer must be a multiple of 4; growing by half again and again would soon make it odd).
pub(crate) fn grown_size(ctx: &GpuContext, old: u64, needed: u64) -> u64 {
    let size = needed.max(old + old / 2).min(ctx.limits().max_buffer_size.max(needed));
    size.div_ceil(256) * 256
}

/// The first `width * height` RGBA8 pixels of an image buffer (a resolve pass's output).
pub(crate) fn read_image_buffer(
    ctx: &GpuContext,
    image: &wgpu::Buffer,
    width: u32,
    height: u32,
) -> Result<Vec<u32>, GpuError> {
    let mut enc = ctx
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("read image") });
    let buf = readback(ctx, &mut enc, image, image.size());
    ctx.queue.submit([enc.finish()]);
    let bytes = map_read(ctx, &buf)?;
    Ok(bytemuck::pod_collect_to_vec::<u8, u32>(&bytes)[..width as usize * height as usize].to_vec())
}

/// A mappable copy of `size` bytes of `src`, recorded in `enc`.
pub(crate) fn readback(
    ctx: &GpuContext,
    enc: &mut wgpu::CommandEncoder,
    src: &wgpu::Buffer,
    size: u64,
) -> wgpu::Buffer {
    let dst = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    enc.copy_buffer_to_buffer(src, 0, &dst, 0, size);
    dst
}

/// Maps a readback buffer (after its copy was submitted) and returns its bytes.
pub(crate) fn map_read(ctx: &GpuContext, buf: &wgpu::Buffer) -> Result<Vec<u8>, GpuError> {
    map_read_with(ctx, buf, |b| b.to_vec())
}

/// Maps a readback buffer (after its copy was submitted) and hands its bytes to `f` in place
/// (no copy of the whole buffer first).
pub(crate) fn map_read_with<R>(
    ctx: &GpuContext,
    buf: &wgpu::Buffer,
    f: impl FnOnce(&[u8]) -> R,
) -> Result<R, GpuError> {
    let (tx, rx) = mpsc::channel();
    buf.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    ctx.wait()?;
    match rx.recv() {
        Ok(Ok(())) => {}
        Ok(Err(e)) => return Err(GpuError::Device(format!("cannot read back: {e}"))),
        Err(_) => return Err(GpuError::Device("read back never completed".into())),
    }
    let out = {
        let view = buf
            .get_mapped_range(..)
            .map_err(|e| GpuError::Device(format!("cannot read back: {e}")))?;
        f(&view)
    };
    buf.unmap();
    Ok(out)
}
