//! What a GPU progressive renderer draws into, per viewport size ([`Target`]: the framebuffer,
//! the visible lists and the bind groups that use them) and per resolved size ([`Resolved`]: the
//! image, the hole-filled keys and the bind groups of the resolve).

use super::device::{round_up, GpuState};
use crate::context::{GpuContext, GpuError};
use crate::pipeline::{entry, storage};
use crate::shaders::binding;

/// The framebuffer of one viewport size, the visible lists, and the bind groups that use them,
/// made together by the first frame of that size ([`Target::ensure`]).
pub(super) struct Target {
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) keys: wgpu::Buffer,
    /// The visible lists, one region of `list_stride` entries per chunk (carried over, grown if
    /// needed, when the size changes: the next Reproject draws them in the new view).
    pub(super) lists: wgpu::Buffer,
    pub(super) list_stride: u32,
    pub(super) clear_group: wgpu::BindGroup,
    /// Group 0 of Fill (frame uniforms, keys, counters).
    pub(super) fill_group: wgpu::BindGroup,
    pub(super) prepare_group: wgpu::BindGroup,
}

/// The resolved image of a [`Target`], the hole-filled keys, and the bind groups of the resolve
/// (one per chunk, from the framebuffer or from the filled keys), hole filling and eye-dome
/// lighting, made by the first frame of that target drawn with `resolve`.
pub(super) struct Resolved {
    pub(super) image: wgpu::Buffer,
    /// The colour dispatches reading the framebuffer, and reading the filled keys.
    pub(super) groups: Vec<wgpu::BindGroup>,
    pub(super) groups_filled: Vec<wgpu::BindGroup>,
    /// Hole filling: the framebuffer into the filled keys (two words per pixel: index, depth,
    /// the 64-bit keys' layout).
    pub(super) fill_group: wgpu::BindGroup,
    /// Eye-dome lighting from the framebuffer's depths, and from the filled keys' depths.
    pub(super) eye_dome_group: wgpu::BindGroup,
    pub(super) eye_dome_group_filled: wgpu::BindGroup,
}

impl Target {
    /// The target of the next frame: `slot`'s if it has `width x height` pixels, else a new one
    /// (the last Prepare's visible lists carried over; the old resolved image dropped). On an
    /// error `slot` and `resolved` are left as they were.
    pub(super) fn ensure<'a>(
        slot: &'a mut Option<Target>,
        resolved: &mut Option<Resolved>,
        ctx: &GpuContext,
        gpu: &GpuState,
        list_counts: &[u32],
        width: u32,
        height: u32,
    ) -> Result<&'a Target, GpuError> {
        let t = match slot.take() {
            Some(t) if (t.width, t.height) == (width, height) => t,
            old => match Target::new(ctx, gpu, old.as_ref(), list_counts, width, height) {
                Ok(t) => {
                    *resolved = None;
                    t
                }
                Err(e) => {
                    *slot = old;
                    return Err(e);
                }
            },
        };
        Ok(slot.insert(t))
    }

    /// The framebuffer for `width x height`, the visible lists (`old`'s if they are large
    /// enough, else grown with `old`'s entries copied) and the bind groups of clear, Fill and
    /// Prepare.
    pub(super) fn new(
        ctx: &GpuContext,
        gpu: &GpuState,
        old: Option<&Target>,
        list_counts: &[u32],
        width: u32,
        height: u32,
    ) -> Result<Target, GpuError> {
        let pixels = width as u64 * height as u64;
        if pixels == 0 || pixels * 8 > ctx.max_binding() {
            return Err(GpuError::TooLarge {
                what: "the framebuffer",
                needed: pixels * 8,
                limit: ctx.max_binding(),
            });
        }
        let copy = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        let align = ctx.limits().min_storage_buffer_offset_alignment.max(4) as u64;
        let stride = round_up(pixels, align / 4);
        let (lists, list_stride) = match old {
            Some(o) if o.list_stride as u64 >= stride => (o.lists.clone(), o.list_stride),
            _ => {
                let size = gpu.chunks.len().max(1) as u64 * stride * 4;
                if size > ctx.max_binding() || stride > u32::MAX as u64 {
                    return Err(GpuError::TooLarge {
                        what: "the visible lists",
                        needed: size,
                        limit: ctx.max_binding(),
                    });
                }
                let lists = storage(ctx, "visible lists", size, copy);
                // The last Prepare's lists move along: the next Reproject draws them in the new
                // view.
                if let Some(o) = old {
                    let mut enc =
                        ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                            label: Some("grow visible lists"),
                        });
                    for (c, &count) in list_counts.iter().enumerate() {
                        if count > 0 {
                            enc.copy_buffer_to_buffer(
                                &o.lists,
                                c as u64 * o.list_stride as u64 * 4,
                                &lists,
                                c as u64 * stride * 4,
                                count as u64 * 4,
                            );
                        }
                    }
                    ctx.queue.submit([enc.finish()]);
                }
                (lists, stride as u32)
            }
        };
        let keys = storage(ctx, "progressive keys", pixels * 8, copy);
        let (passes, f) = (&gpu.passes, &gpu.per_frame);
        let clear_group = passes.clear.bind_group(
            ctx,
            0,
            &[entry(binding::CLEAR_WORDS, keys.as_entire_binding())],
        );
        let fill_group = passes.fill.bind_group(
            ctx,
            0,
            &[
                entry(binding::FRAME, f.frame_uniforms.as_entire_binding()),
                entry(binding::KEYS, keys.as_entire_binding()),
                entry(binding::COUNTERS, f.counters.as_entire_binding()),
            ],
        );
        let prepare_group = passes.prepare.bind_group(
            ctx,
            0,
            &[
                entry(binding::PREPARE_PARAMS, f.prepare_uniforms.as_entire_binding()),
                entry(binding::PREPARE_KEY_WORDS, keys.as_entire_binding()),
                entry(binding::PREPARE_LIST_COUNTS, f.list_counts.as_entire_binding()),
                entry(binding::PREPARE_LISTS, lists.as_entire_binding()),
            ],
        );
        ctx.check()?;
        Ok(Target {
            width,
            height,
            keys,
            lists,
            list_stride,
            clear_group,
            fill_group,
            prepare_group,
        })
    }
}

impl Resolved {
    /// `slot`'s image and bind groups, made for `t` if there are none.
    pub(super) fn ensure<'a>(
        slot: &'a mut Option<Resolved>,
        ctx: &GpuContext,
        gpu: &GpuState,
        t: &Target,
    ) -> Result<&'a Resolved, GpuError> {
        let r = match slot.take() {
            Some(r) => r,
            None => Resolved::new(ctx, gpu, t)?,
        };
        Ok(slot.insert(r))
    }

    /// The image of `t`, the filled keys, one resolve bind group per chunk for each source of
    /// keys (the dummy colours when there is no chunk), and the hole-fill and eye-dome groups.
    pub(super) fn new(ctx: &GpuContext, gpu: &GpuState, t: &Target) -> Result<Resolved, GpuError> {
        let pixels = t.width as u64 * t.height as u64;
        let image = storage(ctx, "progressive image", pixels * 4, wgpu::BufferUsages::COPY_SRC);
        let filled =
            storage(ctx, "progressive filled keys", pixels * 8, wgpu::BufferUsages::COPY_SRC);
        let colors: Vec<&wgpu::Buffer> = if gpu.chunks.is_empty() {
            vec![&gpu.dummy]
        } else {
            // A renderer with colours (checked by `frame`) has them in every chunk.
            gpu.chunks
                .iter()
                .map(|c| {
                    c.colors.as_ref().ok_or_else(|| {
                        GpuError::Colors("resolve asked for but the renderer has no colours".into())
                    })
                })
                .collect::<Result<_, _>>()?
        };
        let f = &gpu.per_frame;
        // The 64-bit keys read as words: index at 2p, depth bits at 2p + 1; the filled keys alike.
        let groups_of = |keys: &wgpu::Buffer| -> Vec<wgpu::BindGroup> {
            colors
                .iter()
                .zip(&f.resolve_uniforms)
                .map(|(colors, u)| {
                    gpu.passes.resolve.bind_group(
                        ctx,
                        0,
                        &[
                            entry(binding::RESOLVE_PARAMS, u.as_entire_binding()),
                            entry(binding::RESOLVE_INDEX_WORDS, keys.as_entire_binding()),
                            entry(binding::RESOLVE_DEPTH_WORDS, keys.as_entire_binding()),
                            entry(binding::RESOLVE_COLORS, colors.as_entire_binding()),
                            entry(binding::RESOLVE_IMAGE, image.as_entire_binding()),
                        ],
                    )
                })
                .collect()
        };
        let eye_dome_of = |keys: &wgpu::Buffer| {
            gpu.passes.eye_dome.bind_group(
                ctx,
                0,
                &[
                    entry(binding::EYE_DOME_PARAMS, f.eye_dome_uniforms.as_entire_binding()),
                    entry(binding::EYE_DOME_DEPTH_WORDS, keys.as_entire_binding()),
                    entry(binding::EYE_DOME_IMAGE, image.as_entire_binding()),
                ],
            )
        };
        let fill_group = gpu.passes.hole_fill.bind_group(
            ctx,
            0,
            &[
                entry(binding::FILL_PARAMS, f.fill_uniforms.as_entire_binding()),
                entry(binding::FILL_INDEX_WORDS, t.keys.as_entire_binding()),
                entry(binding::FILL_DEPTH_WORDS, t.keys.as_entire_binding()),
                entry(binding::FILL_FILLED, filled.as_entire_binding()),
            ],
        );
        let r = Resolved {
            groups: groups_of(&t.keys),
            groups_filled: groups_of(&filled),
            fill_group,
            eye_dome_group: eye_dome_of(&t.keys),
            eye_dome_group_filled: eye_dome_of(&filled),
            image,
        };
        ctx.check()?;
        Ok(r)
    }
}
