//! The framebuffer of one viewport size ([`Keys`] on the context's atomic path) and the bind
//! groups that use it, made together ([`Target`]).

use super::passes::{DrawPasses, Passes, PerFrame};
use crate::context::{GpuContext, GpuError};
use crate::pipeline::{entry, storage};
use crate::shaders::binding;

/// The framebuffer of the atomic path.
pub(super) enum Keys {
    /// 64-bit depth|index keys (`width * height * 8` bytes).
    U64(wgpu::Buffer),
    /// The 32-bit path's depths and point indices (`width * height * 4` bytes each).
    TwoPass32 { depths: wgpu::Buffer, indices: wgpu::Buffer },
}

impl Keys {
    /// Every buffer of the framebuffer (what the clear pass clears).
    fn buffers(&self) -> Vec<&wgpu::Buffer> {
        match self {
            Keys::U64(keys) => vec![keys],
            Keys::TwoPass32 { depths, indices } => vec![depths, indices],
        }
    }

    /// The framebuffer read as 32-bit words: the buffers holding the indices and the depth bits,
    /// the words per pixel and the depth word's offset (the uniforms' `key_stride`,
    /// `depth_offset`).
    pub(super) fn words(&self) -> (&wgpu::Buffer, &wgpu::Buffer, u32, u32) {
        match self {
            Keys::U64(keys) => (keys, keys, 2, 1),
            Keys::TwoPass32 { depths, indices } => (indices, depths, 1, 0),
        }
    }
}

/// The framebuffer of one viewport size and the bind groups that use it, made together
/// ([`GpuRasterizer::new`], [`GpuRasterizer::resize`]).
///
/// [`GpuRasterizer::new`]: super::GpuRasterizer::new
/// [`GpuRasterizer::resize`]: super::GpuRasterizer::resize
pub(super) struct Target {
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) keys: Keys,
    /// The clear pass's bind group per framebuffer buffer, with its workgroup count.
    pub(super) clear_groups: Vec<(wgpu::BindGroup, u32)>,
    /// Group 0 of each draw step (frame uniforms, framebuffer, counters).
    pub(super) draw_groups: Vec<wgpu::BindGroup>,
    /// The hole-filled keys (two words per pixel, index then depth: a 64-bit key's
    /// little-endian words, on both atomic paths) with the hole-fill pass's bind group (the
    /// framebuffer in, these out) and the eye-dome pass's over them; `None` where
    /// `width * height * 8` bytes exceed the device's largest binding (32-bit path only).
    pub(super) filled: Option<(wgpu::Buffer, wgpu::BindGroup, wgpu::BindGroup)>,
    /// The eye-dome pass's bind group over the framebuffer (no hole filling).
    pub(super) eye_dome_group: wgpu::BindGroup,
    /// The resolved image (`width * height` RGBA8 words).
    pub(super) image: wgpu::Buffer,
    /// Whether a frame was resolved into `image` since it was made.
    pub(super) resolved: bool,
}

impl Target {
    pub(super) fn new(
        ctx: &GpuContext,
        passes: &Passes,
        per_frame: &PerFrame,
        width: u32,
        height: u32,
    ) -> Result<Target, GpuError> {
        let pixels = width as u64 * height as u64;
        let key_bytes = pixels * if matches!(passes.draw, DrawPasses::U64(_)) { 8 } else { 4 };
        if key_bytes > ctx.max_binding() || pixels == 0 {
            return Err(GpuError::TooLarge {
                what: "the framebuffer",
                needed: key_bytes,
                limit: ctx.max_binding(),
            });
        }
        let copy = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        let frame = entry(binding::FRAME, per_frame.frame_uniforms.as_entire_binding());
        let counters = entry(binding::COUNTERS, per_frame.counters.as_entire_binding());
        let (keys, draw_groups) = match &passes.draw {
            DrawPasses::U64(draw) => {
                let keys = storage(ctx, "keys", key_bytes, copy);
                let g = draw.bind_group(
                    ctx,
                    0,
                    &[
                        frame,
                        entry(binding::KEYS, keys.as_entire_binding()),
                        counters,
                        entry(binding::KEY_WORDS, keys.as_entire_binding()),
                    ],
                );
                (Keys::U64(keys), vec![g])
            }
            DrawPasses::TwoPass32([depth, index]) => {
                let depths = storage(ctx, "keys", key_bytes, copy);
                let indices = storage(ctx, "indices", pixels * 4, copy);
                let g0 = depth.bind_group(
                    ctx,
                    0,
                    &[frame.clone(), entry(binding::DEPTHS, depths.as_entire_binding())],
                );
                let g1 = index.bind_group(
                    ctx,
                    0,
                    &[
                        frame,
                        entry(binding::DEPTHS, depths.as_entire_binding()),
                        counters,
                        entry(binding::INDICES, indices.as_entire_binding()),
                    ],
                );
                (Keys::TwoPass32 { depths, indices }, vec![g0, g1])
            }
        };
        let clear_groups = keys
            .buffers()
            .into_iter()
            .map(|buf| {
                (
                    passes.clear.bind_group(
                        ctx,
                        0,
                        &[entry(binding::CLEAR_WORDS, buf.as_entire_binding())],
                    ),
                    (buf.size() / 4).div_ceil(256) as u32,
                )
            })
            .collect();
        let image = storage(ctx, "image", pixels * 4, wgpu::BufferUsages::COPY_SRC);
        let eye_dome_group = |depths: &wgpu::Buffer| {
            passes.eye_dome.bind_group(
                ctx,
                0,
                &[
                    entry(
                        binding::EYE_DOME_PARAMS,
                        per_frame.eye_dome_uniforms.as_entire_binding(),
                    ),
                    entry(binding::EYE_DOME_DEPTH_WORDS, depths.as_entire_binding()),
                    entry(binding::EYE_DOME_IMAGE, image.as_entire_binding()),
                ],
            )
        };
        let (index_words, depth_words, _, _) = keys.words();
        let filled = (pixels * 8 <= ctx.max_binding()).then(|| {
            let filled = storage(ctx, "filled keys", pixels * 8, wgpu::BufferUsages::COPY_SRC);
            let fill_group = passes.hole_fill.bind_group(
                ctx,
                0,
                &[
                    entry(binding::FILL_PARAMS, per_frame.fill_uniforms.as_entire_binding()),
                    entry(binding::FILL_INDEX_WORDS, index_words.as_entire_binding()),
                    entry(binding::FILL_DEPTH_WORDS, depth_words.as_entire_binding()),
                    entry(binding::FILL_FILLED, filled.as_entire_binding()),
                ],
            );
            let edl_group = eye_dome_group(&filled);
            (filled, fill_group, edl_group)
        });
        let eye_dome_group = eye_dome_group(depth_words);
        ctx.check()?;
        Ok(Target {
            width,
            height,
            keys,
            clear_groups,
            draw_groups,
            filled,
            eye_dome_group,
            image,
            resolved: false,
        })
    }
}
