//! The GPU radix sort of `mortar build --engine gpu` (issue 29; ARCHITECTURE.md, "Who orders the
//! records"): the points of a build, positions relative to the root's corner in arrival order,
//! put in the order of their full-resolution Morton code, ties in arrival order. That is the
//! order of the sorted engine's `sort_records` (Morton code on the bucket grid, ties by the bits
//! the grid's shift dropped, then arrival), so the host needs only to gather the records by it.
//! The CPU twin is [`mortar_core::octree::arrival::morton_order`].
//!
//! A stable least-significant-digit sort of 4-bit digits, `ceil(3 * size_log2 / 4)` passes, in
//! the portable form (WGSL promises neither subgroup operations nor progress between
//! workgroups): per pass a digit histogram per tile of 2048 elements (`sort_count`), an exclusive
//! scan of the histograms in digit-major order (`sort_reduce`, `sort_scan_sums`, `sort_scan`)
//! and a scatter that ranks each element within its tile (`sort_scatter`). Elements are 16 bytes
//! (the position and the arrival number) in two buffers that take turns: 32 bytes a point on the
//! GPU, and 4 more for the order read back (`shaders/sort_*.wgsl`).

use crate::buffers::{read_in_parts, upload_in_parts};
use crate::context::{GpuContext, GpuError};
use crate::shaders::{binding, Pass};
use mortar_core::render::gpu::SortUniforms;
use wgpu::util::DeviceExt;

/// Elements of one tile (`TILE` in `sort_common.wgsl`).
const TILE: u64 = 2048;
/// Histogram entries of one block of the scan (`BLOCK`).
const BLOCK: u64 = 2048;
/// Threads per workgroup.
const WORKGROUP: u32 = 256;
/// Workgroup memory the scatter pass uses (256 threads of 8 words).
const WORKGROUP_BYTES: u32 = 8 << 10;

/// GPU memory the sort takes per point: two buffers of elements (16 bytes each) and the order (4).
pub const BYTES_PER_POINT: u64 = 36;

/// The sort's passes, compiled once.
pub struct GpuRadixSort {
    layout: wgpu::BindGroupLayout,
    pipelines: Vec<(Pass, wgpu::ComputePipeline)>,
}

impl std::fmt::Debug for GpuRadixSort {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuRadixSort").finish()
    }
}

/// One segment of points on the GPU: its buffer (3 words a point), the arrival number of its
/// first point and its points.
pub struct SegmentRef<'a> {
    /// The points, 3 words each, relative to the root's corner.
    pub pos: &'a wgpu::Buffer,
    /// The arrival number of the first.
    pub base: u32,
    /// How many.
    pub count: u32,
}

/// Extra memory `n` points need besides [`BYTES_PER_POINT`]: the histograms and their sums.
pub fn fixed_bytes(n: u64) -> u64 {
    let entries = 16 * n.div_ceil(TILE);
    4 * (entries + entries.div_ceil(BLOCK)) + 4096
}

/// The most points one sort takes on `ctx`: the elements are one binding.
pub fn max_points(ctx: &GpuContext) -> u64 {
    (ctx.max_binding() / 16).min(u32::MAX as u64 - 1)
}

impl GpuRadixSort {
    /// Compiles the passes on `ctx`; refuses an adapter whose limits they exceed, naming them.
    pub fn new(ctx: &GpuContext) -> Result<GpuRadixSort, GpuError> {
        let l = ctx.limits();
        let storage = binding::SORT.len() as u32 - 1;
        if l.max_storage_buffers_per_shader_stage < storage
            || l.max_compute_invocations_per_workgroup < WORKGROUP
            || l.max_compute_workgroup_size_x < WORKGROUP
            || l.max_compute_workgroup_storage_size < WORKGROUP_BYTES
        {
            return Err(GpuError::Device(format!(
                "{}: the radix sort needs {storage} storage buffers per stage (it has {}), \
                 workgroups of {WORKGROUP} threads (it has {}) and {WORKGROUP_BYTES} bytes of \
                 workgroup memory (it has {})",
                ctx.adapter().name,
                l.max_storage_buffers_per_shader_stage,
                l.max_compute_invocations_per_workgroup.min(l.max_compute_workgroup_size_x),
                l.max_compute_workgroup_storage_size,
            )));
        }
        let (layout, pipelines) = crate::pipeline::one_group_pipelines(
            ctx,
            "radix sort",
            &binding::SORT,
            Pass::ALL.into_iter().filter(|p| p.sorts()),
        );
        Ok(GpuRadixSort { layout, pipelines })
    }

    fn pipeline(&self, pass: Pass) -> &wgpu::ComputePipeline {
        &self.pipelines.iter().find(|(p, _)| *p == pass).expect("compiled").1
    }

    /// The order of `pos` (positions below `2^size_log2` on every axis, in arrival order):
    /// uploaded, sorted, read back (tests and benchmarks; the builder sorts the segments it
    /// already holds, [`sort_segments`](Self::sort_segments)).
    pub fn sort(
        &self,
        ctx: &GpuContext,
        pos: &[[u32; 3]],
        size_log2: u8,
        segment_points: usize,
    ) -> Result<Vec<u32>, GpuError> {
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        let mut bufs = Vec::new();
        for c in pos.chunks(segment_points.max(1)) {
            bufs.push(upload_in_parts(
                ctx,
                "sort points",
                usage,
                bytemuck::cast_slice(c),
                64 << 20,
            )?);
        }
        let segs: Vec<SegmentRef<'_>> = bufs
            .iter()
            .zip(pos.chunks(segment_points.max(1)))
            .enumerate()
            .map(|(k, (b, c))| SegmentRef {
                pos: b,
                base: (k * segment_points.max(1)) as u32,
                count: c.len() as u32,
            })
            .collect();
        self.sort_segments(ctx, &segs, size_log2, 64 << 20)
    }

    /// The order of the points of `segments` (together the points `0..n` in arrival order,
    /// positions below `2^size_log2`): `order[i]` is the arrival number of the `i`-th point in
    /// Morton order. Read back in parts of at most `transfer_bytes`.
    pub fn sort_segments(
        &self,
        ctx: &GpuContext,
        segments: &[SegmentRef<'_>],
        size_log2: u8,
        transfer_bytes: u64,
    ) -> Result<Vec<u32>, GpuError> {
        let n: u64 = segments.iter().map(|s| s.count as u64).sum();
        if n == 0 {
            return Ok(Vec::new());
        }
        if n > max_points(ctx) {
            return Err(GpuError::TooLarge {
                what: "the radix sort's elements (one binding of 16 bytes a point)",
                needed: 16 * n,
                limit: ctx.max_binding(),
            });
        }
        let tiles = n.div_ceil(TILE);
        let entries = 16 * tiles;
        let blocks = entries.div_ceil(BLOCK);
        let buf = |label: &str, size: u64| {
            ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: size.max(16).div_ceil(16) * 16,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        };
        let mut a = buf("sort elements", 16 * n);
        let mut b = buf("sort elements", 16 * n);
        let hist = buf("sort histogram", 4 * entries);
        let sums = buf("sort sums", 4 * blocks);
        let dummy = buf("sort nothing", 16);
        let dummy2 = buf("sort nothing", 16);
        let base = SortUniforms {
            count: n as u32,
            tiles: tiles as u32,
            blocks: blocks as u32,
            entries: entries as u32,
            ..SortUniforms::default()
        };
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        let run = |enc: &mut wgpu::CommandEncoder,
                   pass: Pass,
                   mut u: SortUniforms,
                   groups: u64,
                   bufs: [&wgpu::Buffer; 4]| {
            let (gx, gy) = ctx.split_dispatch(groups as u32);
            u.groups_x = gx;
            let ub = ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("sort uniforms"),
                contents: bytemuck::bytes_of(&u),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            use crate::pipeline::entry;
            let bg = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(pass.file()),
                layout: &self.layout,
                entries: &[
                    entry(binding::SORT_PARAMS, ub.as_entire_binding()),
                    entry(binding::SORT_SRC, bufs[0].as_entire_binding()),
                    entry(binding::SORT_DST, bufs[1].as_entire_binding()),
                    entry(binding::SORT_HIST, hist.as_entire_binding()),
                    entry(binding::SORT_SUMS, sums.as_entire_binding()),
                    entry(binding::SORT_POS, bufs[2].as_entire_binding()),
                    entry(binding::SORT_ORDER, bufs[3].as_entire_binding()),
                ],
            });
            let mut cp = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(pass.file()),
                timestamp_writes: None,
            });
            cp.set_pipeline(self.pipeline(pass));
            cp.set_bind_group(0, &bg, &[]);
            cp.dispatch_workgroups(gx, gy, 1);
        };
        for s in segments.iter().filter(|s| s.count > 0) {
            let u = SortUniforms { count: s.count, base: s.base, ..base };
            let groups = (s.count as u64).div_ceil(WORKGROUP as u64);
            run(&mut enc, Pass::SortInit, u, groups, [&dummy, &a, s.pos, &dummy2]);
        }
        let passes = (3 * size_log2 as u32).div_ceil(4);
        for p in 0..passes {
            let u = SortUniforms { bit: 4 * p, ..base };
            run(&mut enc, Pass::SortCount, u, tiles, [&a, &b, &dummy, &dummy2]);
            run(&mut enc, Pass::SortReduce, u, blocks, [&a, &b, &dummy, &dummy2]);
            run(&mut enc, Pass::SortScanSums, u, 1, [&a, &b, &dummy, &dummy2]);
            run(&mut enc, Pass::SortScan, u, blocks, [&a, &b, &dummy, &dummy2]);
            run(&mut enc, Pass::SortScatter, u, tiles, [&a, &b, &dummy, &dummy2]);
            std::mem::swap(&mut a, &mut b);
        }
        // The order into the buffer that held the last pass's input (free now).
        let order = b;
        run(
            &mut enc,
            Pass::SortExtract,
            base,
            n.div_ceil(WORKGROUP as u64),
            [&a, &dummy, &dummy2, &order],
        );
        ctx.queue.submit([enc.finish()]);
        ctx.wait()?;
        drop(a);
        let mut out = vec![0u32; n as usize];
        read_in_parts(ctx, &order, 0, bytemuck::cast_slice_mut(&mut out), transfer_bytes)?;
        Ok(out)
    }
}
