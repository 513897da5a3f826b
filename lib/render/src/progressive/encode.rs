//! Recording a frame's passes of the GPU progressive renderer into a command encoder: the draw
//! passes (Reproject and Fill, with their records and bind groups), the clear, Prepare and the
//! resolve.

use super::device::{Dispatch, GpuState};
use super::target::{Resolved, Target};
use crate::context::GpuContext;
use crate::pipeline::{batches_group, entry};
use crate::shaders::binding;
use mortar_core::render::gpu::{
    DrawRecord, EyeDomeUniforms, HoleFillUniforms, PrepareUniforms, ResolveUniforms,
};
use mortar_core::render::resolve::ResolveOptions;
use std::num::NonZeroU64;

/// Slots (Fill) or list entries (Reproject) per thread of the draw passes; WGSL mirror
/// `SLOTS_PER_THREAD` in `shaders/progressive_types.wgsl`.
pub const SLOTS_PER_THREAD: u32 = 8;

/// Slots per workgroup of the draw passes (128 threads).
const SLOTS_PER_GROUP: u64 = 128 * SLOTS_PER_THREAD as u64;

impl GpuState {
    /// Writes `dispatches` as records from slot `first_record` and returns their bind groups
    /// (group 1, and for Reproject group 0 with the chunk's list) with workgroup counts.
    pub(super) fn draw_groups(
        &self,
        ctx: &GpuContext,
        t: &Target,
        dispatches: &[Dispatch],
        first_record: usize,
        reproject: bool,
    ) -> Vec<(Option<wgpu::BindGroup>, wgpu::BindGroup, u32)> {
        let f = &self.per_frame;
        let record_size = std::mem::size_of::<DrawRecord>() as u64;
        dispatches
            .iter()
            .enumerate()
            .map(|(k, d)| {
                let offset = (first_record + k) as u64 * f.record_stride;
                ctx.queue.write_buffer(&f.records, offset, bytemuck::bytes_of(&d.record));
                let record = wgpu::BufferBinding {
                    buffer: &f.records,
                    offset,
                    size: NonZeroU64::new(record_size),
                };
                let g1 =
                    batches_group(ctx, &self.passes.shared, record, &self.chunks[d.chunk].words);
                let g0 = reproject.then(|| {
                    let list = wgpu::BufferBinding {
                        buffer: &t.lists,
                        offset: d.chunk as u64 * t.list_stride as u64 * 4,
                        size: NonZeroU64::new(d.record.count as u64 * 4),
                    };
                    self.passes.reproject.bind_group(
                        ctx,
                        0,
                        &[
                            entry(binding::FRAME, f.frame_uniforms.as_entire_binding()),
                            entry(binding::KEYS, t.keys.as_entire_binding()),
                            entry(binding::COUNTERS, f.counters.as_entire_binding()),
                            entry(binding::VISIBLE, wgpu::BindingResource::Buffer(list)),
                        ],
                    )
                });
                (g0, g1, (d.record.count as u64).div_ceil(SLOTS_PER_GROUP) as u32)
            })
            .collect()
    }

    /// Records one draw pass (Reproject or Fill) of `dispatches` into `enc`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn encode_draw(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        t: &Target,
        label: &str,
        dispatches: &[Dispatch],
        first_record: usize,
        reproject: bool,
        ts: (Option<u32>, Option<u32>),
    ) {
        let pipe = if reproject { &self.passes.reproject } else { &self.passes.fill };
        let groups = self.draw_groups(ctx, t, dispatches, first_record, reproject);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: self.timestamps(ts.0, ts.1),
        });
        pass.set_pipeline(pipe.pipeline());
        for (g0, g1, n) in &groups {
            if *n == 0 {
                continue;
            }
            // Reproject binds its chunk's list in group 0; Fill the target's one group 0.
            let g0 = match g0 {
                Some(g) => g,
                None => &t.fill_group,
            };
            pass.set_bind_group(0, g0, &[]);
            pass.set_bind_group(1, g1, &[]);
            let (x, y) = ctx.split_dispatch(*n);
            pass.dispatch_workgroups(x, y, 1);
        }
    }

    /// Records the clear of the framebuffer.
    pub(super) fn encode_clear(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        t: &Target,
        ts: (Option<u32>, Option<u32>),
    ) {
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("clear"),
            timestamp_writes: self.timestamps(ts.0, ts.1),
        });
        pass.set_pipeline(self.passes.clear.pipeline());
        pass.set_bind_group(0, &t.clear_group, &[]);
        let (x, y) = ctx.split_dispatch((t.keys.size() / 4).div_ceil(256) as u32);
        pass.dispatch_workgroups(x, y, 1);
    }

    /// Records Prepare (the list counts zeroed first).
    pub(super) fn encode_prepare(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        t: &Target,
        chunk_slots: u32,
        ts: (Option<u32>, Option<u32>),
    ) {
        let pixels = t.width * t.height;
        let u = PrepareUniforms {
            pixels,
            chunk_slots,
            list_stride: t.list_stride,
            chunks: self.chunks.len() as u32,
        };
        ctx.queue.write_buffer(&self.per_frame.prepare_uniforms, 0, bytemuck::bytes_of(&u));
        enc.clear_buffer(&self.per_frame.list_counts, 0, None);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("prepare"),
            timestamp_writes: self.timestamps(ts.0, ts.1),
        });
        pass.set_pipeline(self.passes.prepare.pipeline());
        pass.set_bind_group(0, &t.prepare_group, &[]);
        let (x, y) = ctx.split_dispatch(pixels.div_ceil(256));
        pass.dispatch_workgroups(x, y, 1);
    }

    /// Records the resolve into `r`'s image: hole filling (the framebuffer into the filled keys),
    /// the colours (one dispatch per chunk, from the filled keys or the framebuffer) and eye-dome
    /// lighting of the image from the same keys' depths, as the batch rasterizer resolves; the
    /// timestamps `ts` around all of them.
    pub(super) fn encode_resolve(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        t: &Target,
        r: &Resolved,
        post: &ResolveOptions,
        ts: (Option<u32>, Option<u32>),
    ) {
        let (x, y) = ctx.split_dispatch((t.width as u64 * t.height as u64).div_ceil(256) as u32);
        // Both key buffers hold two words per pixel: the index, then the depth bits.
        let (stride, depth_offset) = (2, 1);
        let last_is_resolve = post.eye_dome.is_none();
        if let Some(fill) = &post.hole_fill {
            let u = HoleFillUniforms::new(fill, t.width, t.height, stride, depth_offset);
            ctx.queue.write_buffer(&self.per_frame.fill_uniforms, 0, bytemuck::bytes_of(&u));
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("hole fill"),
                timestamp_writes: self.timestamps(ts.0, None),
            });
            pass.set_pipeline(self.passes.hole_fill.pipeline());
            pass.set_bind_group(0, &r.fill_group, &[]);
            pass.dispatch_workgroups(x, y, 1);
        }
        for (i, u) in self.per_frame.resolve_uniforms.iter().enumerate().take(r.groups.len()) {
            let (first_index, count) = self.chunks.get(i).map_or((0, 0), |c| (c.first, c.len));
            let u_val = ResolveUniforms {
                width: t.width,
                height: t.height,
                key_stride: stride,
                depth_offset,
                first_index,
                count,
                background: post.background,
                write_background: (i == 0) as u32,
            };
            ctx.queue.write_buffer(u, 0, bytemuck::bytes_of(&u_val));
        }
        {
            let begin = if post.hole_fill.is_some() { None } else { ts.0 };
            let end = if last_is_resolve { ts.1 } else { None };
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("resolve"),
                timestamp_writes: self.timestamps(begin, end),
            });
            pass.set_pipeline(self.passes.resolve.pipeline());
            let groups = if post.hole_fill.is_some() { &r.groups_filled } else { &r.groups };
            for bg in groups {
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        if let Some(edl) = &post.eye_dome {
            let u = EyeDomeUniforms::new(edl, t.width, t.height, stride, depth_offset);
            ctx.queue.write_buffer(&self.per_frame.eye_dome_uniforms, 0, bytemuck::bytes_of(&u));
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("eye-dome lighting"),
                timestamp_writes: self.timestamps(None, ts.1),
            });
            pass.set_pipeline(self.passes.eye_dome.pipeline());
            pass.set_bind_group(
                0,
                if post.hole_fill.is_some() { &r.eye_dome_group_filled } else { &r.eye_dome_group },
                &[],
            );
            pass.dispatch_workgroups(x, y, 1);
        }
    }
}
