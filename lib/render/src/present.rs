//! Presenting the rasterizer's resolved image in a window (`mortar view`): the surface's
//! configuration (format, size, usages) and one render pass (`shaders/present.wgsl`) that copies
//! the resolve pass's RGBA8 image, with a status-line overlay, into the surface texture. The image
//! never leaves the GPU; only the overlay (a few KiB) is uploaded per frame.
//!
//! This module knows no window library: the caller creates the surface with
//! [`GpuContext::for_window`] from any window that has raw window and display handles.

use crate::buffers::map_read;
use crate::context::{GpuContext, GpuError};
use crate::pipeline::{bind_group_layout, entry};
use crate::raster::GpuRasterizer;
use crate::shaders::{binding, PRESENT_BINDINGS};

/// The present pass's uniforms, defined with the other records the GPU reads in
/// [`mortar_core::render::gpu`] (re-exported here where they used to be).
pub use mortar_core::render::gpu::PresentUniforms;

/// An RGBA8 image drawn over the top-left corner (alpha is coverage), e.g. a status line.
#[derive(Clone, Copy, Debug)]
pub struct Overlay<'a> {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height` words, packed `r | g << 8 | b << 16 | a << 24`, row-major.
    pub rgba: &'a [u32],
}

/// What [`WindowSurface::present`] did.
#[derive(Debug)]
pub enum Presented {
    /// The frame is on the surface; with `read_back`, the pixels drawn into the surface texture
    /// (RGBA8 packed, row-major).
    Shown(Option<Vec<u32>>),
    /// No surface texture this time (the window is hidden, or the surface was reconfigured):
    /// draw again later.
    Skipped(&'static str),
}

/// Where a screenshot comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReadBack {
    /// The surface texture itself, copied after the present pass drew into it.
    SurfaceTexture,
    /// The surface format or usages do not allow copying: the resolved image with the overlay
    /// blended on the host.
    ResolvedImage,
}

/// A configured window surface and the present pass drawing into it.
pub struct WindowSurface {
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    pipeline: wgpu::RenderPipeline,
    /// The layout of the pass's one bind group ([`PRESENT_BINDINGS`]).
    layout: wgpu::BindGroupLayout,
    uniforms: wgpu::Buffer,
    overlay: wgpu::Buffer,
    srgb: bool,
    /// Byte order of the surface format when it can be copied: `Some(true)` for BGRA.
    readable_bgra: Option<bool>,
}

impl std::fmt::Debug for WindowSurface {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WindowSurface")
            .field("format", &self.config.format)
            .field("size", &(self.config.width, self.config.height))
            .finish()
    }
}

/// The surface formats the present pass prefers: 8-bit unorm first (the image's bytes go through
/// unchanged), then sRGB (decoded in the shader, encoded again by the hardware).
const PREFERRED: [wgpu::TextureFormat; 4] = [
    wgpu::TextureFormat::Bgra8Unorm,
    wgpu::TextureFormat::Rgba8Unorm,
    wgpu::TextureFormat::Bgra8UnormSrgb,
    wgpu::TextureFormat::Rgba8UnormSrgb,
];

impl WindowSurface {
    /// Configures `surface` (from [`GpuContext::for_window`] with the same context) for
    /// `width x height` pixels and builds the present pass.
    pub fn new(
        ctx: &GpuContext,
        surface: wgpu::Surface<'static>,
        width: u32,
        height: u32,
    ) -> Result<WindowSurface, GpuError> {
        let caps = surface.get_capabilities(ctx.wgpu_adapter());
        let Some(&format) =
            PREFERRED.iter().find(|f| caps.formats.contains(f)).or(caps.formats.first())
        else {
            return Err(GpuError::Surface(format!(
                "{} offers no format for this window",
                ctx.adapter().name
            )));
        };
        if ctx.limits().max_storage_buffers_per_shader_stage < 2 {
            return Err(GpuError::Surface(format!(
                "{} cannot read storage buffers in a fragment shader",
                ctx.adapter().name
            )));
        }
        let copyable = caps.usages.contains(wgpu::TextureUsages::COPY_SRC);
        let readable_bgra = match format {
            wgpu::TextureFormat::Bgra8Unorm | wgpu::TextureFormat::Bgra8UnormSrgb if copyable => {
                Some(true)
            }
            wgpu::TextureFormat::Rgba8Unorm | wgpu::TextureFormat::Rgba8UnormSrgb if copyable => {
                Some(false)
            }
            _ => None,
        };
        let alpha_mode = if caps.alpha_modes.contains(&wgpu::CompositeAlphaMode::Opaque) {
            wgpu::CompositeAlphaMode::Opaque
        } else {
            caps.alpha_modes.first().copied().unwrap_or(wgpu::CompositeAlphaMode::Auto)
        };
        let config = wgpu::SurfaceConfiguration {
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                | if readable_bgra.is_some() {
                    wgpu::TextureUsages::COPY_SRC
                } else {
                    wgpu::TextureUsages::empty()
                },
            format,
            color_space: wgpu::SurfaceColorSpace::Auto,
            width: width.max(1),
            height: height.max(1),
            desired_maximum_frame_latency: 2,
            present_mode: wgpu::PresentMode::AutoVsync,
            alpha_mode,
            view_formats: vec![],
        };
        surface.configure(&ctx.device, &config);
        let module = ctx.device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("present.wgsl"),
            source: wgpu::ShaderSource::Wgsl(crate::shaders::PRESENT.into()),
        });
        let layout =
            bind_group_layout(ctx, "present", PRESENT_BINDINGS, 0, wgpu::ShaderStages::FRAGMENT);
        let pipeline_layout = ctx.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("present"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = ctx.device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("present"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs_main"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: wgpu::PrimitiveState::default(),
            depth_stencil: None,
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fs_main"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let uniforms = crate::pipeline::uniform::<PresentUniforms>(ctx, "present uniforms");
        let overlay = overlay_buffer(ctx, 4);
        ctx.check()?;
        Ok(WindowSurface {
            surface,
            config,
            pipeline,
            layout,
            uniforms,
            overlay,
            srgb: format.is_srgb(),
            readable_bgra,
        })
    }

    /// The surface's size in pixels.
    pub fn size(&self) -> (u32, u32) {
        (self.config.width, self.config.height)
    }

    /// The surface's texture format.
    pub fn format(&self) -> wgpu::TextureFormat {
        self.config.format
    }

    /// Where [`present`](Self::present) reads screenshots from.
    pub fn read_back(&self) -> ReadBack {
        if self.readable_bgra.is_some() {
            ReadBack::SurfaceTexture
        } else {
            ReadBack::ResolvedImage
        }
    }

    /// Reconfigures the surface for a new window size (sizes of 0 are raised to 1).
    pub fn resize(&mut self, ctx: &GpuContext, width: u32, height: u32) -> Result<(), GpuError> {
        let (width, height) = (width.max(1), height.max(1));
        if (width, height) != self.size() {
            self.config.width = width;
            self.config.height = height;
            self.surface.configure(&ctx.device, &self.config);
        }
        ctx.check()
    }

    /// Draws the last image `raster` resolved (its size must be the surface's) and `overlay` into
    /// the next surface texture and presents it. With `read_back`, also returns the pixels drawn
    /// (see [`read_back`](Self::read_back) for where they come from).
    pub fn present(
        &mut self,
        ctx: &GpuContext,
        raster: &GpuRasterizer,
        overlay: Option<Overlay<'_>>,
        read_back: bool,
    ) -> Result<Presented, GpuError> {
        let Some(image) = raster.image_buffer() else {
            return Err(GpuError::Surface(
                "no resolved image to present (draw with a background colour first)".into(),
            ));
        };
        self.present_image(ctx, image, raster.size(), overlay, read_back)
    }

    /// Draws `image` (a storage buffer of `size` row-major RGBA8 pixels from the top-left, as the
    /// resolve pass writes them; `size` must be the surface's) and `overlay` into the next
    /// surface texture and presents it. [`present`](Self::present) for any renderer that resolves
    /// its own image (the progressive renderer does).
    pub fn present_image(
        &mut self,
        ctx: &GpuContext,
        image: &wgpu::Buffer,
        size: (u32, u32),
        overlay: Option<Overlay<'_>>,
        read_back: bool,
    ) -> Result<Presented, GpuError> {
        let (width, height) = self.size();
        if size != (width, height) || image.size() < width as u64 * height as u64 * 4 {
            return Err(GpuError::Surface(format!(
                "image of {size:?} pixels for a surface of {width}x{height}"
            )));
        }
        let overlay = overlay.filter(|o| {
            o.width > 0 && o.height > 0 && o.rgba.len() == o.width as usize * o.height as usize
        });
        let (ow, oh) = overlay.map_or((0, 0), |o| (o.width, o.height));
        if let Some(o) = overlay {
            let bytes = o.rgba.len() as u64 * 4;
            if self.overlay.size() < bytes {
                self.overlay = overlay_buffer(ctx, bytes);
            }
            ctx.queue.write_buffer(&self.overlay, 0, bytemuck::cast_slice(o.rgba));
        }
        let u = PresentUniforms {
            width,
            height,
            overlay_width: ow,
            overlay_height: oh,
            srgb_target: self.srgb as u32,
            _pad0: 0,
            _pad1: 0,
            _pad2: 0,
        };
        ctx.queue.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&u));

        let texture = match self.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t)
            | wgpu::CurrentSurfaceTexture::Suboptimal(t) => t,
            wgpu::CurrentSurfaceTexture::Timeout => {
                return Ok(Presented::Skipped("the surface timed out"))
            }
            wgpu::CurrentSurfaceTexture::Occluded => {
                return Ok(Presented::Skipped("the window is hidden"))
            }
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                self.surface.configure(&ctx.device, &self.config);
                return Ok(Presented::Skipped("the surface was reconfigured"));
            }
            wgpu::CurrentSurfaceTexture::Validation => {
                ctx.check()?;
                return Err(GpuError::Surface("cannot get the next surface texture".into()));
            }
        };
        let view = texture.texture.create_view(&wgpu::TextureViewDescriptor::default());
        // Per frame: the image and the overlay buffer may change between frames.
        let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("present"),
            layout: &self.layout,
            entries: &[
                entry(binding::PRESENT_PARAMS, self.uniforms.as_entire_binding()),
                entry(binding::PRESENT_IMAGE, image.as_entire_binding()),
                entry(binding::PRESENT_OVERLAY, self.overlay.as_entire_binding()),
            ],
        });
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("present") });
        {
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("present"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &group, &[]);
            pass.draw(0..3, 0..1);
        }
        let row_bytes = (width * 4).next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT);
        let copy = match (read_back, self.readable_bgra) {
            (true, Some(_)) => {
                let buf = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("surface read-back"),
                    size: row_bytes as u64 * height as u64,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                enc.copy_texture_to_buffer(
                    texture.texture.as_image_copy(),
                    wgpu::TexelCopyBufferInfo {
                        buffer: &buf,
                        layout: wgpu::TexelCopyBufferLayout {
                            offset: 0,
                            bytes_per_row: Some(row_bytes),
                            rows_per_image: Some(height),
                        },
                    },
                    wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
                );
                Some(buf)
            }
            _ => None,
        };
        ctx.queue.submit([enc.finish()]);
        ctx.queue.present(texture);
        ctx.check()?;
        if !read_back {
            return Ok(Presented::Shown(None));
        }
        let pixels = match (copy, self.readable_bgra) {
            (Some(buf), Some(bgra)) => {
                let bytes = map_read(ctx, &buf)?;
                let mut out = Vec::with_capacity(width as usize * height as usize);
                for row in bytes.chunks_exact(row_bytes as usize) {
                    for p in row[..width as usize * 4].chunks_exact(4) {
                        let (r, b) = if bgra { (p[2], p[0]) } else { (p[0], p[2]) };
                        out.push(u32::from_le_bytes([r, p[1], b, 255]));
                    }
                }
                out
            }
            _ => {
                let mut img = crate::buffers::read_image_buffer(ctx, image, width, height)?;
                if let Some(o) = overlay {
                    blend_overlay(&mut img, width, &o);
                }
                img.iter_mut().for_each(|c| *c |= 0xff00_0000);
                img
            }
        };
        Ok(Presented::Shown(Some(pixels)))
    }
}

/// Blends `overlay` over the top-left corner of `image` (`width` pixels per row) on the host, as
/// the present pass does (alpha is coverage; the result is opaque).
pub fn blend_overlay(image: &mut [u32], width: u32, overlay: &Overlay<'_>) {
    let height = image.len() / width.max(1) as usize;
    for y in 0..(overlay.height as usize).min(height) {
        for x in 0..(overlay.width.min(width)) as usize {
            let o = overlay.rgba[y * overlay.width as usize + x].to_le_bytes();
            let px = &mut image[y * width as usize + x];
            let c = px.to_le_bytes();
            let a = o[3] as u32;
            let mix = |i: usize| ((c[i] as u32 * (255 - a) + o[i] as u32 * a + 127) / 255) as u8;
            *px = u32::from_le_bytes([mix(0), mix(1), mix(2), 255]);
        }
    }
}

fn overlay_buffer(ctx: &GpuContext, bytes: u64) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("overlay"),
        size: bytes.max(4).next_multiple_of(4),
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overlay_blends_over_the_corner_only() {
        let mut img = vec![0x0000_00ffu32; 4 * 3]; // opaque-less red, 4x3
        let o = [0xff00_ff00u32, 0x8000_0000, 0x0000_0000]; // green, half black, nothing; 3x1
        blend_overlay(&mut img, 4, &Overlay { width: 3, height: 1, rgba: &o });
        assert_eq!(img[0], 0xff00_ff00);
        assert_eq!(img[1], 0xff00_007f);
        assert_eq!(img[2], 0xff00_00ff);
        assert_eq!(img[3], 0x0000_00ff, "outside the overlay: untouched");
        assert_eq!(img[4], 0x0000_00ff);
    }
}
