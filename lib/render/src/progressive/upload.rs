//! The uploads of the GPU progressive renderer ([`Uploads`]): scatter records written in parallel
//! straight into wgpu's staging memory, the scatter pass dispatched over them once per chunk, and
//! at most [`MAX_IN_FLIGHT`] bytes of them staged before the host waits for the oldest.

use super::device::GpuState;
use crate::context::{GpuContext, GpuError};
use crate::pipeline::{entry, storage};
use crate::shaders::binding;
use mortar_core::render::gpu::ScatterUniforms;
use rayon::prelude::*;
use std::num::NonZeroU64;

/// Points per scatter upload.
pub(super) const STAGING_POINTS: usize = 4 << 20;

/// Bytes of uploads the host may stage before it waits for the oldest to be done.
const MAX_IN_FLIGHT: u64 = 1 << 30;

/// A piece of a staging view handed to one thread.
struct SendWrite<'a>(wgpu::WriteOnly<'a, [u8]>);

// SAFETY: a `WriteOnly<[u8]>` is an exclusive, write-only view of bytes, like `&mut [u8]`, which
// is `Send`; wgpu implements `Send` for `WriteOnly<T>` only for sized `T: Send` (its impl lacks
// `?Sized`), not for a slice. The pieces are disjoint (`split_at`).
unsafe impl Send for SendWrite<'_> {}

/// The staging buffer of the scatter records and the uploads that may still be in flight.
pub(super) struct Uploads {
    /// Scatter records, grown by the first insert that needs more.
    staging: wgpu::Buffer,
    /// Uploads submitted and maybe not done yet (submission, bytes), oldest first, and their
    /// bytes: wgpu holds a staging copy of each until the GPU has done it.
    in_flight: std::collections::VecDeque<(wgpu::SubmissionIndex, u64)>,
    in_flight_bytes: u64,
}

impl Uploads {
    /// No staging memory yet, nothing in flight.
    pub(super) fn new(ctx: &GpuContext) -> Uploads {
        Uploads {
            staging: storage(ctx, "scatter staging", 0, wgpu::BufferUsages::COPY_DST),
            in_flight: Default::default(),
            in_flight_bytes: 0,
        }
    }

    /// Uploads `count` records of `stride` words for input points `first..`, written in parallel
    /// straight into wgpu's staging memory (`fill(k, m, out)` writes records `k..k + m` into
    /// `out`), and dispatches the scatter pass over them once per chunk; `colors_only`: one colour
    /// per record, only the colours are written; `gpu`'s chunks receive them, `prime` is the
    /// shuffle's (0 for none).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn upload(
        &mut self,
        ctx: &GpuContext,
        gpu: &GpuState,
        prime: u32,
        first: u64,
        count: usize,
        stride: usize,
        colors_only: bool,
        fill: impl Fn(usize, usize, &mut wgpu::WriteOnly<[u8]>) + Sync,
    ) -> Result<(), GpuError> {
        let bytes = (count * stride * 4) as u64;
        if self.staging.size() < bytes {
            let size = (STAGING_POINTS as u64 * 16).max(bytes);
            if size > ctx.limits().max_buffer_size {
                return Err(GpuError::TooLarge {
                    what: "the scatter staging buffer",
                    needed: size,
                    limit: ctx.limits().max_buffer_size,
                });
            }
            self.staging = storage(ctx, "scatter staging", size, wgpu::BufferUsages::COPY_DST);
        }
        let Some(size) = NonZeroU64::new(bytes) else { return Ok(()) };
        {
            let mut view =
                ctx.queue.write_buffer_with(&self.staging, 0, size).ok_or_else(|| {
                    GpuError::Device(format!(
                        "no staging memory for {bytes} bytes of scatter records"
                    ))
                })?;
            // Pieces of 16 Ki records, written by as many threads.
            const PIECE: usize = 1 << 14;
            let mut rest = view.slice(..);
            let mut pieces: Vec<(usize, usize, SendWrite)> =
                Vec::with_capacity(count.div_ceil(PIECE));
            for k in (0..count).step_by(PIECE) {
                let m = (count - k).min(PIECE);
                let (head, tail) = rest.split_at(m * stride * 4);
                pieces.push((k, m, SendWrite(head)));
                rest = tail;
            }
            pieces
                .into_par_iter()
                .for_each(|(k, m, mut out): (usize, usize, SendWrite)| fill(k, m, &mut out.0));
        }
        // One dispatch per chunk, each with its uniforms at its own aligned offset.
        let ustride = gpu.scatter_uniform_stride;
        for (c, chunk) in gpu.chunks.iter().enumerate() {
            let u = ScatterUniforms {
                colors: (stride == 4) as u32,
                colors_only: colors_only as u32,
                prime,
                first: first as u32,
                chunk_first: chunk.first,
                chunk_len: chunk.len,
                count: count as u32,
                _pad: 0,
            };
            ctx.queue.write_buffer(
                &gpu.scatter_uniforms,
                c as u64 * ustride,
                bytemuck::bytes_of(&u),
            );
        }
        let usize_ = NonZeroU64::new(std::mem::size_of::<ScatterUniforms>() as u64);
        let groups: Vec<wgpu::BindGroup> = gpu
            .chunks
            .iter()
            .enumerate()
            .map(|(c, chunk)| {
                gpu.passes.scatter.bind_group(
                    ctx,
                    0,
                    &[
                        entry(
                            binding::SCATTER_PARAMS,
                            wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                buffer: &gpu.scatter_uniforms,
                                offset: c as u64 * ustride,
                                size: usize_,
                            }),
                        ),
                        entry(
                            binding::SCATTER_STAGED,
                            wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                buffer: &self.staging,
                                offset: 0,
                                size: Some(size),
                            }),
                        ),
                        entry(binding::SCATTER_COARSE, chunk.words[0].as_entire_binding()),
                        entry(binding::SCATTER_MEDIUM, chunk.words[1].as_entire_binding()),
                        entry(binding::SCATTER_FINE, chunk.words[2].as_entire_binding()),
                        entry(
                            binding::SCATTER_COLORS,
                            chunk.colors.as_ref().unwrap_or(&gpu.dummy).as_entire_binding(),
                        ),
                    ],
                )
            })
            .collect();
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("scatter") });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("scatter"),
                timestamp_writes: None,
            });
            pass.set_pipeline(gpu.passes.scatter.pipeline());
            let (x, y) = ctx.split_dispatch((count as u32).div_ceil(256));
            for bg in &groups {
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        let index = ctx.queue.submit([enc.finish()]);
        // wgpu keeps a staging copy of every upload until the GPU has done it: past
        // MAX_IN_FLIGHT bytes, wait for the oldest uploads only, so that the GPU copies and
        // scatters while the host stages the next ones (waiting for all of them every GiB cost a
        // billion-point load a third of its time).
        self.in_flight.push_back((index, bytes));
        self.in_flight_bytes += bytes;
        while self.in_flight_bytes > MAX_IN_FLIGHT {
            let Some((index, b)) = self.in_flight.pop_front() else { break };
            ctx.device
                .poll(wgpu::PollType::Wait { submission_index: Some(index), timeout: None })
                .map_err(|e| GpuError::Device(e.to_string()))?;
            self.in_flight_bytes -= b;
        }
        ctx.check()
    }
}
