//! The GPU state that lives as long as a GPU progressive renderer ([`GpuState`]): the shuffled
//! buffer in chunks of slots ([`SlotChunk`]), the passes ([`Passes`]), the buffers written anew
//! every frame ([`PerFrame`]), the scatter uniforms and the timestamp queries; and the draw
//! dispatches of Fill runs ([`Dispatch`]).

use super::frame::BudgetTiming;
use crate::buffers::readback;
use crate::context::GpuContext;
use crate::pipeline::{PassPipeline, SharedLayouts, Timestamps};
use mortar_core::render::gpu::DrawRecord;
use mortar_core::render::BatchProjection;

/// One chunk of the shuffled buffer: slots `[first, first + len)`.
pub(super) struct SlotChunk {
    pub(super) words: [wgpu::Buffer; 3],
    pub(super) colors: Option<wgpu::Buffer>,
    pub(super) first: u32,
    pub(super) len: u32,
}

/// The pipelines and layouts of the renderer: built once with it.
pub(super) struct Passes {
    pub(super) shared: SharedLayouts,
    pub(super) clear: PassPipeline,
    pub(super) unload: PassPipeline,
    pub(super) scatter: PassPipeline,
    pub(super) reproject: PassPipeline,
    pub(super) fill: PassPipeline,
    pub(super) prepare: PassPipeline,
    pub(super) resolve: PassPipeline,
    pub(super) reframe: PassPipeline,
    pub(super) hole_fill: PassPipeline,
    pub(super) eye_dome: PassPipeline,
    pub(super) ties: PassPipeline,
}

/// What the renderer writes anew every frame: the camera's uniforms, the drawn-point counter,
/// the draw records, Prepare's constants and list counts, the resolve dispatches' uniforms. The
/// buffers live as long as the renderer.
pub(super) struct PerFrame {
    pub(super) frame_uniforms: wgpu::Buffer,
    pub(super) counters: wgpu::Buffer,
    /// Draw records, one per `record_stride` bytes (a storage-offset boundary).
    pub(super) records: wgpu::Buffer,
    pub(super) record_stride: u64,
    pub(super) prepare_uniforms: wgpu::Buffer,
    /// Entries of each chunk's visible list, as Prepare counted them.
    pub(super) list_counts: wgpu::Buffer,
    /// One per chunk (at least one), with colours only.
    pub(super) resolve_uniforms: Vec<wgpu::Buffer>,
    /// `HoleFillUniforms` and `EyeDomeUniforms` of the resolve.
    pub(super) fill_uniforms: wgpu::Buffer,
    pub(super) eye_dome_uniforms: wgpu::Buffer,
}

/// The GPU state that lives as long as the renderer: the shuffled buffer, the passes, the
/// per-frame buffers and the constant uniforms.
pub(super) struct GpuState {
    pub(super) chunks: Vec<SlotChunk>,
    pub(super) passes: Passes,
    pub(super) per_frame: PerFrame,
    /// One [`ScatterUniforms`](mortar_core::render::gpu::ScatterUniforms) per chunk,
    /// `scatter_uniform_stride` bytes apart (rewritten by every upload; queue writes are ordered
    /// with the submissions that read them).
    pub(super) scatter_uniforms: wgpu::Buffer,
    pub(super) scatter_uniform_stride: u64,
    /// A 4-byte buffer bound where a pass needs a buffer that is not there (no colours).
    pub(super) dummy: wgpu::Buffer,
    pub(super) queries: Option<Timestamps>,
}

/// One draw dispatch: a record and the chunk it reads.
#[derive(Clone, Copy)]
pub(super) struct Dispatch {
    pub(super) chunk: usize,
    pub(super) record: DrawRecord,
}

/// Timestamp slots: clear begin, Reproject end, probe Fill begin/end, extra Fill begin/end,
/// Prepare begin/end, resolve begin/end.
pub(super) const QUERIES: u32 = 10;

pub(super) fn round_up(v: u64, to: u64) -> u64 {
    v.div_ceil(to) * to
}

impl GpuState {
    pub(super) fn timestamps(
        &self,
        begin: Option<u32>,
        end: Option<u32>,
    ) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        if begin.is_none() && end.is_none() {
            return None;
        }
        self.queries.as_ref().map(|q| q.writes(begin, end))
    }

    /// How the adaptive budget's timings are measured.
    pub(super) fn timing(&self) -> BudgetTiming {
        if self.queries.is_some() {
            BudgetTiming::GpuTimestamps
        } else {
            BudgetTiming::HostClock
        }
    }

    /// The draw dispatches of Fill runs.
    pub(super) fn fill_dispatches(
        &self,
        runs: &[(usize, u32, u32)],
        projection: &BatchProjection,
    ) -> Vec<Dispatch> {
        runs.iter()
            .map(|&(c, offset, count)| Dispatch {
                chunk: c,
                record: DrawRecord {
                    projection: *projection,
                    offset,
                    count,
                    first_index: self.chunks[c].first + offset,
                    _pad: 0,
                },
            })
            .collect()
    }

    /// Reads `count` timestamps from slot 0 (resolved into the query buffer by `enc`).
    pub(super) fn resolve_queries(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        count: u32,
    ) -> Option<wgpu::Buffer> {
        self.queries.as_ref().map(|q| {
            enc.resolve_query_set(&q.set, 0..count, &q.buffer, 0);
            readback(ctx, enc, &q.buffer, count as u64 * 8)
        })
    }
}
