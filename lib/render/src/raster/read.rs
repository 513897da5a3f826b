//! Reading the last frame back to the host: the framebuffer's keys as the CPU rasterizer writes
//! them, the hole-filled keys and the resolved image.

use super::target::Keys;
use super::GpuRasterizer;
use crate::buffers::{map_read, read_image_buffer, readback};
use crate::context::{GpuContext, GpuError};
use mortar_core::render::framebuffer::EMPTY_KEY;

impl GpuRasterizer {
    /// The hole-filled keys of the last frame resolved with hole filling, as
    /// [`mortar_core::render::resolve::fill_holes`] returns them (what the resolve's colours and
    /// eye-dome lighting read).
    pub fn read_filled_keys(&self, ctx: &GpuContext) -> Result<Vec<u64>, GpuError> {
        let pixels = self.target.width as u64 * self.target.height as u64;
        let Some((filled, _, _)) = &self.target.filled else {
            return Err(GpuError::TooLarge {
                what: "the hole-filled keys",
                needed: pixels * 8,
                limit: ctx.max_binding(),
            });
        };
        let pixels = self.target.width as usize * self.target.height as usize;
        let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("read filled keys"),
        });
        let buf = readback(ctx, &mut enc, filled, filled.size());
        ctx.queue.submit([enc.finish()]);
        Ok(bytemuck::pod_collect_to_vec::<u8, u64>(&map_read(ctx, &buf)?)[..pixels].to_vec())
    }

    /// The framebuffer's keys as the CPU rasterizer writes them (`depth bits << 32 | index`,
    /// [`EMPTY_KEY`] for an empty pixel), row-major from the top-left pixel.
    pub fn read_keys(&self, ctx: &GpuContext) -> Result<Vec<u64>, GpuError> {
        let pixels = self.target.width as usize * self.target.height as usize;
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("read keys") });
        match &self.target.keys {
            Keys::U64(keys) => {
                let keys = readback(ctx, &mut enc, keys, keys.size());
                ctx.queue.submit([enc.finish()]);
                Ok(bytemuck::pod_collect_to_vec::<u8, u64>(&map_read(ctx, &keys)?)[..pixels]
                    .to_vec())
            }
            Keys::TwoPass32 { depths, indices } => {
                let d = readback(ctx, &mut enc, depths, depths.size());
                let i = readback(ctx, &mut enc, indices, indices.size());
                ctx.queue.submit([enc.finish()]);
                let d: Vec<u32> = bytemuck::pod_collect_to_vec(&map_read(ctx, &d)?);
                let i: Vec<u32> = bytemuck::pod_collect_to_vec(&map_read(ctx, &i)?);
                Ok((0..pixels)
                    .map(|p| {
                        if d[p] == u32::MAX {
                            EMPTY_KEY
                        } else {
                            (d[p] as u64) << 32 | i[p] as u64
                        }
                    })
                    .collect())
            }
        }
    }

    /// The resolved image (RGBA8 packed `r | g << 8 | b << 16 | a << 24`, row-major) of the last
    /// frame drawn with `resolve`.
    pub fn read_image(&self, ctx: &GpuContext) -> Result<Vec<u32>, GpuError> {
        let Some(image) = self.image_buffer() else {
            return Err(GpuError::Colors("no frame was resolved yet".into()));
        };
        read_image_buffer(ctx, image, self.target.width, self.target.height)
    }
}
