//! GPU buffer helpers every renderer of this crate uses: growing a buffer, copying one back to
//! the host and reading it (the rasterizer, the scene, the progressive renderer, the window).

use crate::context::{GpuContext, GpuError};
use rayon::prelude::*;
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

/// Bytes each thread copies at a time between host memory and a mapped buffer (a multiple of
/// wgpu's map alignment, 8).
const PAR_COPY: usize = 1 << 20;

/// A buffer of `usage` (plus `COPY_DST`) holding `bytes` (a multiple of 4), uploaded in parts of
/// at most `part` bytes (a multiple of 4), a submission each: a mapped staging buffer per part,
/// filled by all threads. One large copy held the GPU's transfers long enough to delay another
/// device's frames, and one thread's copy was the upload's pace (issue 29, BENCHMARKS.md).
pub(crate) fn upload_in_parts(
    ctx: &GpuContext,
    label: &str,
    usage: wgpu::BufferUsages,
    bytes: &[u8],
    part: u64,
) -> Result<wgpu::Buffer, GpuError> {
    let buf = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: (bytes.len() as u64).max(4),
        usage: usage | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    for (k, src) in bytes.chunks(part as usize).enumerate() {
        let staging = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("upload"),
            size: src.len() as u64,
            usage: wgpu::BufferUsages::MAP_WRITE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: true,
        });
        let piece = PAR_COPY.min(src.len());
        let mut views: Vec<(wgpu::BufferViewMut, &[u8])> = src
            .chunks(piece)
            .enumerate()
            .map(|(i, s)| {
                let at = (i * piece) as u64;
                staging.get_mapped_range_mut(at..at + s.len() as u64).map(|v| (v, s))
            })
            .collect::<Result<_, _>>()
            .map_err(|e| GpuError::Device(format!("cannot upload: {e}")))?;
        views.par_iter_mut().for_each(|(v, s)| v.copy_from_slice(s));
        drop(views);
        staging.unmap();
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(&staging, 0, &buf, k as u64 * part, src.len() as u64);
        ctx.queue.submit([enc.finish()]);
    }
    Ok(buf)
}

/// Reads `dst.len()` bytes (a multiple of 4) of `src` from `offset` into `dst`, through one mapped
/// buffer of at most `part` bytes, a part per submission, each copied out by all threads (see
/// [`upload_in_parts`]).
pub(crate) fn read_in_parts(
    ctx: &GpuContext,
    src: &wgpu::Buffer,
    offset: u64,
    dst: &mut [u8],
    part: u64,
) -> Result<(), GpuError> {
    if dst.is_empty() {
        return Ok(());
    }
    let part = (dst.len() as u64).min(part);
    let rb = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("read in parts"),
        size: part,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    for (k, d) in dst.chunks_mut(part as usize).enumerate() {
        let n = d.len();
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(src, offset + k as u64 * part, &rb, 0, n as u64);
        ctx.queue.submit([enc.finish()]);
        map_read_with(ctx, &rb, |b| {
            d.par_chunks_mut(PAR_COPY)
                .zip(b[..n].par_chunks(PAR_COPY))
                .for_each(|(d, s)| d.copy_from_slice(s))
        })?;
    }
    Ok(())
}
