//! The GPU octree builder of paper 004 (SimLOD) for `mortar build --engine gpu` (issue 29): the
//! passes of `shaders/octree_*.wgsl` over points in arrival order, giving the
//! [`ArrivalTree`] that the CPU twin [`mortar_core::octree::arrival::build_arrival`] gives (same
//! nodes, same voxels; slots differ only in their order inside a leaf, which the store engine
//! sorts away). The store engine (`mortar_io::store`) holds it as a [`TreeBackend`].
//!
//! Steps (module docs of `arrival` for the why):
//!
//! 1. the points are uploaded in segments (one storage binding each; every upload and read-back
//!    in parts of at most [`TRANSFER_BYTES`], a submission each); each segment is a batch:
//!    `octree_insert` (mode 0) descends its points and counts them, then `octree_split` and
//!    `octree_insert` (mode 1, every point inserted so far whose leaf split) alternate until no
//!    leaf splits; the host reads 12 bytes of state per round. A node buffer that fills up is
//!    grown (copied) and the split pass run again;
//! 2. the host reads the nodes back, numbers the inner nodes' grids and the leaves' ranges
//!    (depth first) and writes them back;
//! 3. voxels, a group of grids at a time, on sparse grids (16³ bricks of 8³ cells, a brick
//!    allocated only where a point falls): `octree_mark_bricks` (every point marks its bricks),
//!    `octree_alloc_bricks` (each marked brick takes one from a counter; the host sizes the pool,
//!    and cuts a group whose bricks exceed it to what fits), `octree_voxels` (every point,
//!    atomicMax of its NOT-ed arrival per cell), `octree_count_cells` (occupied cells per brick), a prefix sum on
//!    the host, `octree_write_cells` (arrivals in Morton order of the cells: bricks in Morton
//!    order, cells in Morton order within each), read back;
//! 4. `octree_slots` gives every point its slot; the slots are read back. The store's engine
//!    skips this step ([`GpuTreeBuilder::build_tree_with`]): it puts the records in order
//!    itself and needs only the nodes and voxels.
//!
//! Before step 1, where the store's engine asks for the points' order
//! ([`GpuTreeBuilder::build_tree_ordered`], [`TreeBackend::build_ordered`]) and every segment
//! and the sort's buffers fit at once ([`GpuTreeBuilder::sorts_points`]), the segments are
//! uploaded, sorted by [`crate::radix`] and the order read back and handed over; the segments
//! stay for the passes, so the points cross to the GPU once.
//!
//! With a budget (`--gpu-memory`) segments of points beyond half of it are paged out (their
//! leaves read back) and in again as the passes need them; a paged-out segment is skipped by a
//! split round when none of its points' leaves split. For the voxel passes the points are then
//! put in leaf order (leaves depth first, each in arrival order, a counting sort on the host of
//! the leaves read back) and cut into new segments, each point's arrival number beside it (the
//! voxel pass's mode 2): grids are numbered depth first too, so a group of consecutive grids is
//! a few subtrees, whose points are a few consecutive segments, and a group walks only the
//! segments that touch it. (Walked in arrival order, a segment of a flight line touched nearly
//! every group.) With slots (not the store's engine) the segments keep arrival order and a
//! group skips those none of whose points' leaves lie under its grids.
//!
//! What is not done yet (issue 29): the preview does not draw from these buffers; the points are
//! sorted on the GPU only where they all fit it at once with the sort (else the host sorts them,
//! at the same time, on its cores).

use crate::buffers::{read_in_parts, upload_in_parts};
use crate::context::{GpuContext, GpuError};
use crate::radix::{self, GpuRadixSort};
use crate::shaders::{binding, Pass};
use mortar_core::octree::arrival::{
    check, check_nodes, leaf_bases, ArrivalNode, ArrivalTree, TreeBackend, NO_CHILD,
};
use mortar_core::octree::BuilderConfig;
use mortar_core::render::gpu::{OctreeNode, OctreeUniforms};
use rayon::prelude::*;
use std::time::Instant;
use wgpu::util::DeviceExt;

/// Bricks of one voxel grid (16³ bricks of 8³ cells: 128³ cells).
const BRICKS: u64 = 1 << 12;
/// Cells of one brick (`BRICK_CELLS` in the WGSL).
const BRICK_CELLS: u64 = 512;
/// Threads per workgroup of every octree pass.
const WORKGROUP: u32 = 256;
/// Most bytes one submission moves between host and GPU: a segment of a hundred million points
/// is 1.2 GB, whose upload in one copy held the GPU's transfers for 60-70 ms, and a window drawing
/// on the same GPU (`build --preview --engine gpu`, another device) waited for it to read its
/// frame back.
const TRANSFER_BYTES: u64 = 64 << 20;

/// The passes, compiled once.
pub struct GpuTreeBuilder {
    ctx: GpuContext,
    layout: wgpu::BindGroupLayout,
    pipelines: Vec<(Pass, wgpu::ComputePipeline)>,
    /// Points per segment (one binding and one batch); `None`: as many as a binding holds.
    segment_points: Option<usize>,
    /// Most bytes one submission uploads or reads back ([`TRANSFER_BYTES`]).
    transfer_bytes: u64,
    /// The node buffer's first capacity; `None`: from the points and the leaf capacity.
    first_nodes: Option<u32>,
    /// GPU memory the build may use (`--gpu-memory`; by default [`default_gpu_memory`] of what
    /// the adapter reports); `None` (an adapter that reports none): as much as it needs.
    budget: Option<u64>,
    /// Segments on the GPU at once; `None`: from the budget.
    resident: Option<usize>,
    /// The radix sort (`None` where the adapter's limits refuse it, or where turned off by
    /// [`with_sort`](GpuTreeBuilder::with_sort)).
    sort: Option<GpuRadixSort>,
}

/// The smallest `--gpu-memory`: a quarter of it holds one full voxel grid (8 MiB of bricks).
pub const MIN_GPU_MEMORY: u64 = 32 << 20;

/// The GPU memory a build uses by default out of the `reported` device memory
/// ([`GpuContext::device_memory`]): three quarters, the rest left to the driver, a display and
/// other programs; at least [`MIN_GPU_MEMORY`].
pub fn default_gpu_memory(reported: u64) -> u64 {
    (reported / 4 * 3).max(MIN_GPU_MEMORY)
}

/// One segment of the points: its arrivals, and its buffers while it is on the GPU (the points,
/// and each point's leaf or slot), or its leaves on the host while it is paged out.
struct Segment<'p> {
    base: u32,
    /// The points in arrival order: the segment's own, or where `order` is given, all of them.
    pos: &'p [[u32; 3]],
    gpu: Option<(wgpu::Buffer, wgpu::Buffer)>,
    leaves: Option<Vec<u32>>,
    used: u64,
    /// For the voxel passes of a paged build, the segment's points in leaf order: entries
    /// `order` of the run's `perm` (arrival numbers, leaves depth first), whose positions are
    /// gathered from `pos` and whose arrival numbers go into the leaf buffer (mode 2).
    order: Option<std::ops::Range<usize>>,
}

impl Segment<'_> {
    fn len(&self) -> usize {
        self.order.as_ref().map_or(self.pos.len(), |r| r.len())
    }
}

impl std::fmt::Debug for GpuTreeBuilder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuTreeBuilder").field("adapter", self.ctx.adapter()).finish()
    }
}

/// The buffers of one build.
struct Run<'a, 'p> {
    b: &'a GpuTreeBuilder,
    nodes: wgpu::Buffer,
    node_capacity: u32,
    node_limit: u32,
    state: wgpu::Buffer,
    segments: Vec<Segment<'p>>,
    /// Segments on the GPU at most, and a clock for the least recently used.
    resident: usize,
    clock: u64,
    /// Bound where a pass needs no segment.
    dummy: (wgpu::Buffer, wgpu::Buffer),
    grids: wgpu::Buffer,
    blocks: wgpu::Buffer,
    out: wgpu::Buffer,
    config: BuilderConfig,
    /// Bytes uploaded and read back, and the seconds each took (transfers timed to their end).
    up: std::cell::Cell<(u64, f64)>,
    down: std::cell::Cell<(u64, f64)>,
    /// Arrival numbers in leaf order (leaves depth first, each in arrival order), for the
    /// segments that have an `order` (empty where none has).
    perm: Vec<u32>,
}

fn storage(ctx: &GpuContext, label: &str, size: u64) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: size.max(16).div_ceil(16) * 16,
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

impl GpuTreeBuilder {
    /// Compiles the passes on `ctx`; refuses an adapter whose limits the passes exceed, naming
    /// them.
    pub fn new(ctx: GpuContext) -> Result<GpuTreeBuilder, GpuError> {
        let l = ctx.limits();
        let storage = binding::OCTREE.len() as u32 - 1;
        if l.max_storage_buffers_per_shader_stage < storage
            || l.max_bindings_per_bind_group < binding::OCTREE.len() as u32
            || l.max_compute_invocations_per_workgroup < WORKGROUP
            || l.max_compute_workgroup_size_x < WORKGROUP
        {
            return Err(GpuError::Device(format!(
                "{}: the octree passes need {storage} storage buffers per stage (it has {}), {} \
                 bindings per group (it has {}) and workgroups of {WORKGROUP} threads (it has {})",
                ctx.adapter().name,
                l.max_storage_buffers_per_shader_stage,
                binding::OCTREE.len(),
                l.max_bindings_per_bind_group,
                l.max_compute_invocations_per_workgroup.min(l.max_compute_workgroup_size_x),
            )));
        }
        let (layout, pipelines) = crate::pipeline::one_group_pipelines(
            &ctx,
            "octree",
            &binding::OCTREE,
            Pass::ALL.into_iter().filter(|p| p.builds_octree()),
        );
        let budget = ctx.device_memory().map(default_gpu_memory);
        let sort = GpuRadixSort::new(&ctx).ok();
        Ok(GpuTreeBuilder {
            ctx,
            layout,
            pipelines,
            segment_points: None,
            transfer_bytes: TRANSFER_BYTES,
            first_nodes: None,
            budget,
            resident: None,
            sort,
        })
    }

    /// Segments (and batches) of at most `points` points: small values exercise the batch and
    /// segment paths in tests.
    pub fn with_segment_points(mut self, points: usize) -> GpuTreeBuilder {
        self.segment_points = Some(points.max(1));
        self
    }

    /// Uploads and read-backs in submissions of at most `bytes` bytes (a multiple of 4, at
    /// least 4; default [`TRANSFER_BYTES`]): small values exercise the cut in tests.
    pub fn with_transfer_bytes(mut self, bytes: u64) -> GpuTreeBuilder {
        self.transfer_bytes = (bytes / 4 * 4).max(4);
        self
    }

    /// A node buffer of `nodes` nodes at first (grown as it fills): small values exercise the
    /// growth in tests.
    pub fn with_first_nodes(mut self, nodes: u32) -> GpuTreeBuilder {
        self.first_nodes = Some(nodes.max(1));
        self
    }

    /// Keeps the build within `bytes` of GPU memory (at least [`MIN_GPU_MEMORY`]): an eighth
    /// for the node buffer, a sixteenth for a group's brick tables, a quarter for its bricks,
    /// half for segments of points;
    /// segments that do not fit are paged out (their leaves read back) and in again as passes
    /// need them.
    pub fn with_memory_budget(mut self, bytes: u64) -> Result<GpuTreeBuilder, GpuError> {
        if bytes < MIN_GPU_MEMORY {
            return Err(GpuError::Device(format!(
                "{bytes} bytes of GPU memory are below the {MIN_GPU_MEMORY} the octree passes \
                 need (a quarter of it for a full voxel grid of 8 MiB)"
            )));
        }
        self.budget = Some(bytes);
        Ok(self)
    }

    /// Without the GPU's radix sort where `on` is false ([`sorts_points`](Self::sorts_points)
    /// then says no, and the store's engine sorts on the host).
    pub fn with_sort(mut self, on: bool) -> GpuTreeBuilder {
        if !on {
            self.sort = None;
        }
        self
    }

    /// At most `segments` segments on the GPU at once (at least 1): small values exercise the
    /// paging in tests.
    pub fn with_resident_segments(mut self, segments: usize) -> GpuTreeBuilder {
        self.resident = Some(segments.max(1));
        self
    }

    /// A storage buffer (also copied from and to) holding `bytes`, uploaded in parts of at
    /// most `transfer_bytes`.
    fn upload(&self, label: &str, bytes: &[u8]) -> Result<wgpu::Buffer, GpuError> {
        let usage = wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST;
        upload_in_parts(&self.ctx, label, usage, bytes, self.transfer_bytes)
    }

    /// The GPU memory the build keeps within: `--gpu-memory`, else [`default_gpu_memory`] of
    /// the adapter's; `None` where the adapter reports no memory size (then unbounded).
    pub fn memory_budget(&self) -> Option<u64> {
        self.budget
    }

    /// The device.
    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    /// Points per segment and segments on the GPU at once: half the budget for
    /// segments (16 bytes a point: the point and its leaf), at least two of them resident.
    fn plan(&self) -> (usize, usize) {
        let budget = self.budget.unwrap_or(u64::MAX);
        let seg = self
            .segment_points
            .unwrap_or(usize::MAX)
            .min((self.ctx.max_binding() / 12) as usize)
            .min((budget / 2 / 2 / 16).min(usize::MAX as u64) as usize)
            .max(1);
        let resident = self
            .resident
            .unwrap_or_else(|| (budget / 2 / (16 * seg as u64)).min(usize::MAX as u64) as usize)
            .max(1);
        (seg, resident)
    }

    /// Whether the build of `n` points can sort them on the GPU
    /// ([`TreeBackend::build_ordered`]): every segment resident at once, and the sort's buffers
    /// ([`radix::BYTES_PER_POINT`] a point, one binding of elements) within the half of the
    /// budget the segments leave, less the node buffer's eighth.
    pub fn sorts_points(&self, n: usize) -> bool {
        let (seg, resident) = self.plan();
        let budget = self.budget.unwrap_or(u64::MAX);
        self.sort.is_some()
            && n > 0
            && n.div_ceil(seg) <= resident
            && (n as u64) <= radix::max_points(&self.ctx)
            && (n as u64)
                .saturating_mul(radix::BYTES_PER_POINT)
                .saturating_add(radix::fixed_bytes(n as u64))
                <= budget / 8 * 3
    }

    fn pipeline(&self, pass: Pass) -> &wgpu::ComputePipeline {
        &self.pipelines.iter().find(|(p, _)| *p == pass).expect("compiled").1
    }

    /// Builds the tree (see [`TreeBackend::build`]), with the seconds of each step.
    pub fn build_tree(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &BuilderConfig,
    ) -> Result<ArrivalTree, GpuError> {
        self.build_tree_with(size_log2, pos, config, true)
    }

    /// [`build_tree`](Self::build_tree); without the slot pass and its read-back where `slots`
    /// is false (`slot` then empty).
    pub fn build_tree_with(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &BuilderConfig,
        slots: bool,
    ) -> Result<ArrivalTree, GpuError> {
        self.build_tree_ordered(size_log2, pos, config, slots, None)
    }

    /// [`build_tree_with`](Self::build_tree_with); where `order` is given, the points are first
    /// sorted on the GPU (the segments once uploaded stay for the tree's passes) and their order
    /// handed to it before the tree is built (fails where [`sorts_points`](Self::sorts_points)
    /// says no).
    pub fn build_tree_ordered(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &BuilderConfig,
        slots: bool,
        order: Option<&dyn Fn(Vec<u32>)>,
    ) -> Result<ArrivalTree, GpuError> {
        check(size_log2, pos.len(), config).map_err(|e| GpuError::Device(e.to_string()))?;
        let outside = |p: &[u32; 3]| p.iter().any(|&v| (v as u64) >> size_log2 != 0);
        if let Some(i) = pos.par_iter().position_any(outside) {
            return Err(GpuError::Device(format!(
                "point {i} at {:?} lies outside the root cube of 2^{size_log2} units",
                pos[i]
            )));
        }
        if pos.is_empty() {
            if let Some(give) = order {
                give(Vec::new());
            }
            return Ok(ArrivalTree {
                nodes: vec![ArrivalNode::default()],
                slot: Vec::new(),
                voxels: vec![Vec::new()],
                phases: Vec::new(),
            });
        }
        let ctx = &self.ctx;
        let max_binding = ctx.max_binding();
        let budget = self.budget.unwrap_or(u64::MAX);
        if order.is_some() && !self.sorts_points(pos.len()) {
            return Err(GpuError::Device(format!(
                "{} points do not fit the GPU's sort within its budget",
                pos.len()
            )));
        }
        let (seg, resident) = self.plan();
        let mut phases = Vec::new();
        let t = Instant::now();
        let segments: Vec<Segment<'_>> = pos
            .chunks(seg)
            .enumerate()
            .map(|(k, c)| Segment {
                base: (k * seg) as u32,
                pos: c,
                gpu: None,
                leaves: None,
                used: 0,
                order: None,
            })
            .collect();
        // Room for the nodes of a tree with leaves about half full, grown when it fills, within
        // a binding and an eighth of the budget.
        let node_limit = (max_binding / 32).min(budget / 8 / 32).min(u32::MAX as u64) as u32;
        let node_capacity = (1 + 8 * (2 * pos.len() / config.leaf_capacity as usize + 64))
            .min(node_limit as usize) as u32;
        let node_capacity = self.first_nodes.unwrap_or(node_capacity).min(node_limit);
        let mut run = Run {
            b: self,
            nodes: storage(ctx, "octree nodes", 32 * node_capacity as u64),
            node_capacity,
            node_limit,
            state: storage(ctx, "octree state", 16),
            segments,
            resident,
            clock: 0,
            dummy: (storage(ctx, "octree no points", 16), storage(ctx, "octree no leaves", 16)),
            grids: storage(ctx, "octree grids", 16),
            blocks: storage(ctx, "octree blocks", 16),
            out: storage(ctx, "octree cells", 16),
            config: *config,
            up: Default::default(),
            down: Default::default(),
            perm: Vec::new(),
        };
        let root = OctreeNode { size_level: size_log2 as u32, ..OctreeNode::default() };
        ctx.queue.write_buffer(&run.nodes, 0, bytemuck::bytes_of(&root));
        ctx.queue.write_buffer(&run.state, 0, bytemuck::cast_slice(&[1u32, 0, 0, 0]));
        ctx.wait()?;
        phases.push(("setup".to_string(), t.elapsed().as_secs_f64()));
        // 0. the order, where asked for: every segment uploaded (they stay for the passes
        // below), sorted, the order read back and handed over.
        if let (Some(give), Some(sorter)) = (order, &self.sort) {
            let t = Instant::now();
            for s in 0..run.segments.len() {
                run.page_in(s)?;
            }
            let tu = Instant::now();
            let refs: Vec<radix::SegmentRef<'_>> = run
                .segments
                .iter()
                .map(|sg| radix::SegmentRef {
                    pos: &sg.gpu.as_ref().expect("resident").0,
                    base: sg.base,
                    count: sg.len() as u32,
                })
                .collect();
            let v = sorter.sort_segments(ctx, &refs, size_log2, self.transfer_bytes)?;
            let (b, secs) = run.down.get();
            run.down.set((b + 4 * v.len() as u64, secs));
            phases.push(("sort".to_string(), tu.elapsed().as_secs_f64()));
            give(v);
            phases.push(("upload and sort".to_string(), t.elapsed().as_secs_f64()));
        }
        // 1. expand, a segment (batch) at a time.
        let t = Instant::now();
        let mut rounds = 0u32;
        for s in 0..run.segments.len() {
            run.dispatch(Pass::OctreeInsert, Some(s), 0)?;
            loop {
                rounds += 1;
                let before = run.read_state()?[0];
                run.dispatch_nodes(before)?;
                let st = run.read_state()?;
                if st[2] != 0 {
                    run.grow_nodes(before, st[1])?;
                    continue;
                }
                if st[1] == 0 {
                    break;
                }
                ctx.queue.write_buffer(&run.state, 4, bytemuck::cast_slice(&[0u32]));
                // Segments paged out whose points lie in no leaf that split stay out: their
                // leaves on the host say so (the children made this round are ids `before..`).
                let split = if (0..=s).any(|r| run.segments[r].gpu.is_none()) {
                    let raw: Vec<OctreeNode> = run.read(&run.nodes, 32 * before as u64)?;
                    Some(raw.iter().map(|n| n.child >= before).collect::<Vec<bool>>())
                } else {
                    None
                };
                for r in 0..=s {
                    if let (Some(split), Some(leaves)) = (&split, &run.segments[r].leaves) {
                        let hit = |&l: &u32| split.get(l as usize).copied().unwrap_or(true);
                        if !leaves.par_iter().any(hit) {
                            continue;
                        }
                    }
                    run.dispatch(Pass::OctreeInsert, Some(r), 1)?;
                }
            }
        }
        let count = run.read_state()?[0] as usize;
        phases.push(("expand".to_string(), t.elapsed().as_secs_f64()));
        // 2. the nodes back; grids of inner nodes and ranges of leaves.
        let t = Instant::now();
        let mut raw: Vec<OctreeNode> = run.read(&run.nodes, 32 * count as u64)?;
        let nodes: Vec<ArrivalNode> =
            raw.iter().map(|n| ArrivalNode { count: n.count, first_child: n.child }).collect();
        check_nodes(&nodes).map_err(|e| GpuError::Device(e.to_string()))?;
        let bases = leaf_bases(&nodes);
        // Grids numbered depth first, so that a group of consecutive grids is a few subtrees
        // (what a segment of nearby points touches, see below; numbering the top levels first
        // made more walks: 45 against 35 for 5 M points within 64 MiB).
        let mut inner = Vec::new();
        let mut parent = vec![u32::MAX; nodes.len()];
        let mut stack = vec![0usize];
        while let Some(i) = stack.pop() {
            let n = &mut raw[i];
            if n.child != NO_CHILD {
                n.grid = inner.len() as u32;
                inner.push(i);
                for o in (0..8).rev() {
                    parent[(n.child + o) as usize] = i as u32;
                    stack.push((n.child + o) as usize);
                }
            } else {
                n.cursor = bases[i];
            }
        }
        ctx.queue.write_buffer(&run.nodes, 0, bytemuck::cast_slice(&raw));
        // With segments paged, the voxel passes walk the points in leaf order (leaves depth
        // first, as the grids are numbered): a group of consecutive grids is then touched by a
        // few consecutive segments, where segments in arrival order (a flight line crosses the
        // whole scene) each touched nearly every group, so that every group walked every point
        // again (1 B points within 1.6 GB: 1,007 walks, BENCHMARKS.md). The first-come voxels do
        // not depend on the order points are walked in (an atomic minimum of their arrival).
        // The slot pass needs the segments in arrival order: with slots, each segment keeps its
        // order and walks the groups that its points' leaves lie under.
        let paged = run.segments.len() > run.resident;
        let mut grid_span: Vec<(u64, u64)> = Vec::new();
        let seg_grids: Option<Vec<Vec<u32>>> = if paged && !slots {
            let leaves: Vec<Vec<u32>> = (0..run.segments.len())
                .map(|k| match run.segments[k].leaves.take() {
                    Some(v) if run.segments[k].gpu.is_none() => Ok(v),
                    _ => run.read_leaves(k),
                })
                .collect::<Result<_, GpuError>>()?;
            let seg_bases: Vec<u32> = run.segments.iter().map(|s| s.base).collect();
            run.perm = leaf_order(&nodes, &bases, &leaves, &seg_bases)?;
            drop(leaves);
            // Each grid's points: a range of the leaf order.
            grid_span = vec![(0, 0); inner.len()];
            for (i, s) in subtree_spans(&nodes, &bases).into_iter().enumerate() {
                if raw[i].child != NO_CHILD {
                    grid_span[raw[i].grid as usize] = s;
                }
            }
            let n = pos.len();
            run.segments = (0..n.div_ceil(seg))
                .map(|k| Segment {
                    base: 0,
                    pos,
                    gpu: None,
                    leaves: None,
                    used: 0,
                    order: Some(k * seg..((k + 1) * seg).min(n)),
                })
                .collect();
            None
        } else if paged {
            let mut all = Vec::with_capacity(run.segments.len());
            for k in 0..run.segments.len() {
                let leaves = run.read_leaves(k)?;
                let mut seen = vec![false; nodes.len()];
                for &l in &leaves {
                    let mut a = parent.get(l as usize).copied().unwrap_or(u32::MAX);
                    while a != u32::MAX && !seen[a as usize] {
                        seen[a as usize] = true;
                        a = parent[a as usize];
                    }
                }
                let mut g: Vec<u32> =
                    (0..nodes.len()).filter(|&i| seen[i]).map(|i| raw[i].grid).collect();
                g.sort_unstable();
                all.push(g);
            }
            Some(all)
        } else {
            None
        };
        let segments_in_order: Vec<Option<std::ops::Range<usize>>> =
            run.segments.iter().map(|s| s.order.clone()).collect();
        let touches = |k: usize, first: u32, g: u32| match &segments_in_order[k] {
            // In leaf order: a grid's points are a range of it.
            Some(r) => grid_span[first as usize..(first + g) as usize]
                .iter()
                .any(|&(a, b)| a < r.end as u64 && (r.start as u64) < b),
            None => seg_grids.as_ref().is_none_or(|v| {
                let i = v[k].partition_point(|&x| x < first);
                i < v[k].len() && v[k][i] < first + g
            }),
        };
        phases.push(("number".to_string(), t.elapsed().as_secs_f64()));
        // 3. voxels, a group of grids at a time: their brick tables within a sixteenth of the
        // budget (and a binding), their bricks within a quarter.
        let t = Instant::now();
        let mut voxels = vec![Vec::new(); nodes.len()];
        let table_limit = max_binding.min(budget / 16);
        let pool_limit = max_binding.min(budget / 4);
        let per_group = ((table_limit / (8 * BRICKS)) as usize).clamp(1, 1 << 19);
        // Groups in order; a group whose bricks overflow the pool is cut to the share that its
        // count says fits, and the next group sized from the last one's bricks per grid (each
        // try walks the group's segments once).
        let mut first = 0usize;
        let mut size = per_group;
        // Segment walks of the voxel passes (a paged-out segment is paged in for each).
        let mut walks = 0u32;
        // A voxel pass over the segments that touch the grids `first..first + g`.
        let walk = |run: &mut Run, pass: Pass, first: u32, g: u64| -> Result<u32, GpuError> {
            let mut walked = 0;
            for s in 0..run.segments.len() {
                if touches(s, first, g as u32) {
                    walked += 1;
                    let n = run.segments[s].len() as u32;
                    run.dispatch_grids(pass, Some(s), n, first, g)?;
                }
            }
            Ok(walked)
        };
        while first < inner.len() {
            let g = size.min(inner.len() - first).max(1);
            let group = &inner[first..first + g];
            let e = BRICKS * g as u64;
            if run.blocks.size() < 8 * e {
                run.blocks = storage(ctx, "octree bricks", 8 * e);
            }
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            enc.clear_buffer(&run.blocks, 0, Some(8 * e));
            ctx.queue.submit([enc.finish()]);
            ctx.queue.write_buffer(&run.state, 12, bytemuck::cast_slice(&[0u32]));
            let (first32, g64) = (first as u32, g as u64);
            walks += walk(&mut run, Pass::OctreeMarkBricks, first32, g64)?;
            run.dispatch_grids(Pass::OctreeAllocBricks, None, e as u32, first32, g64)?;
            let bricks = run.read_state()?[3] as u64;
            let used = bricks * 4 * BRICK_CELLS;
            // The grids this pool holds at the bricks per grid just counted, with a tenth spare.
            let fitting = |g: usize| ((g as u64 * pool_limit / used.max(1)) * 9 / 10) as usize;
            if used > pool_limit {
                if g == 1 {
                    return Err(GpuError::TooLarge {
                        what: "the voxel bricks of one node (a quarter of --gpu-memory)",
                        needed: used,
                        limit: pool_limit,
                    });
                }
                size = fitting(g).clamp(1, g - 1);
                continue;
            }
            size = fitting(g).clamp(1, per_group);
            first += g;
            if run.grids.size() < 4 * BRICK_CELLS * bricks {
                run.grids = storage(ctx, "octree bricks", 4 * BRICK_CELLS * bricks);
            }
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            enc.clear_buffer(&run.grids, 0, Some(4 * BRICK_CELLS * bricks));
            ctx.queue.submit([enc.finish()]);
            walks += walk(&mut run, Pass::OctreeVoxels, first32, g64)?;
            run.dispatch_grids(Pass::OctreeCountCells, None, e as u32, first32, g64)?;
            let counts: Vec<u32> = run.read_at(&run.blocks, 4 * e, 4 * e)?;
            let mut offsets = Vec::with_capacity(counts.len());
            let mut total = 0u64;
            for c in &counts {
                offsets.push(total as u32);
                total += *c as u64;
            }
            if total == 0 {
                continue;
            }
            if run.out.size() < 4 * total {
                run.out = storage(ctx, "octree cells", 4 * total);
            }
            ctx.queue.write_buffer(&run.blocks, 4 * e, bytemuck::cast_slice(&offsets));
            run.dispatch_grids(Pass::OctreeWriteCells, None, e as u32, first32, g64)?;
            let cells: Vec<u32> = run.read(&run.out, 4 * total)?;
            let per_grid = BRICKS as usize;
            for (k, &n) in group.iter().enumerate() {
                let a = offsets[k * per_grid] as usize;
                let b = offsets.get((k + 1) * per_grid).map_or(total as usize, |&o| o as usize);
                voxels[n] = cells[a..b].to_vec();
            }
        }
        phases.push(("voxels".to_string(), t.elapsed().as_secs_f64()));
        // 4. slots (where asked for).
        let t = Instant::now();
        let mut slot = Vec::new();
        for s in (0..run.segments.len()).filter(|_| slots) {
            run.dispatch(Pass::OctreeSlots, Some(s), 0)?;
            let v = run.take_leaves(s)?;
            if slot.is_empty() {
                slot = v;
            } else {
                slot.extend_from_slice(&v);
            }
        }
        phases.push(("slots".to_string(), t.elapsed().as_secs_f64()));
        phases.push(("rounds".to_string(), rounds as f64));
        phases.push(("voxel walks".to_string(), walks as f64));
        // Transfers, timed inside the steps above: bytes and seconds each way.
        let (ub, us) = run.up.get();
        let (db, ds) = run.down.get();
        phases.push(("upload bytes".to_string(), ub as f64));
        phases.push(("upload seconds".to_string(), us));
        phases.push(("read-back bytes".to_string(), db as f64));
        phases.push(("read-back seconds".to_string(), ds));
        Ok(ArrivalTree { nodes, slot, voxels, phases })
    }
}

/// The points' arrival numbers in leaf order: the leaves depth first (`bases`, from
/// [`leaf_bases`]), each leaf's points in arrival order; `leaves[k]` gives the leaf of each
/// point of segment `k`, whose first point is number `seg_bases[k]`. A counting sort in a few
/// parallel parts (consecutive segments each, so that its counters stay one per node and part,
/// whatever the number of segments). A leaf that is not a leaf of `nodes`, or more points in
/// one than it counts, is an error of the device.
fn leaf_order(
    nodes: &[ArrivalNode],
    bases: &[u32],
    leaves: &[Vec<u32>],
    seg_bases: &[u32],
) -> Result<Vec<u32>, GpuError> {
    let n: usize = leaves.iter().map(|l| l.len()).sum();
    let is_leaf = |l: u32| nodes.get(l as usize).is_some_and(|x| x.first_child == NO_CHILD);
    if let Some(&l) = leaves.par_iter().flatten().find_any(|&&l| !is_leaf(l)) {
        return Err(GpuError::Device(format!("a point's leaf {l} is not a leaf of the tree")));
    }
    let per = leaves.len().div_ceil(rayon::current_num_threads().max(1)).max(1);
    let parts: Vec<(&[Vec<u32>], &[u32])> = leaves.chunks(per).zip(seg_bases.chunks(per)).collect();
    // Per part, its points per node; then, in place, where they begin in the leaf order.
    let mut at: Vec<Vec<u32>> = parts
        .par_iter()
        .map(|(segs, _)| {
            let mut c = vec![0u32; nodes.len()];
            for &l in segs.iter().flatten() {
                c[l as usize] += 1;
            }
            c
        })
        .collect();
    let mut next: Vec<u64> = bases.iter().map(|&b| b as u64).collect();
    for c in at.iter_mut() {
        for (x, nx) in c.iter_mut().zip(next.iter_mut()) {
            let k = *x as u64;
            *x = *nx as u32;
            *nx += k;
        }
    }
    for (i, nd) in nodes.iter().enumerate() {
        if nd.first_child == NO_CHILD && next[i] != bases[i] as u64 + nd.count as u64 {
            return Err(GpuError::Device(format!(
                "leaf {i} holds {} points where it counts {}",
                next[i] - bases[i] as u64,
                nd.count
            )));
        }
    }
    drop(next);
    let mut perm = vec![0u32; n];
    let pp = mortar_core::par::SendPtr(perm.as_mut_ptr());
    parts.par_iter().zip(at).for_each(|(&(segs, sb), mut at)| {
        let pp = &pp;
        for (ls, &base) in segs.iter().zip(sb) {
            for (i, &l) in ls.iter().enumerate() {
                let slot = &mut at[l as usize];
                // SAFETY: the leaves' ranges (`bases`, their counts checked above) are disjoint
                // and within n, and each part writes its own share of each.
                unsafe { pp.write(*slot as usize, base + i as u32) };
                *slot += 1;
            }
        }
    });
    Ok(perm)
}

/// Per node, its points as a range of the leaf order ([`leaf_order`]): from the base of its
/// first leaf depth first to the end of its last.
fn subtree_spans(nodes: &[ArrivalNode], bases: &[u32]) -> Vec<(u64, u64)> {
    let mut span = vec![(0u64, 0u64); nodes.len()];
    // Depth first, then backwards: children before their parents.
    let mut order = Vec::with_capacity(nodes.len());
    let mut stack = vec![0usize];
    while let Some(i) = stack.pop() {
        order.push(i);
        let c = nodes[i].first_child;
        if c != NO_CHILD {
            stack.extend((0..8).rev().map(|o| (c + o) as usize));
        }
    }
    for &i in order.iter().rev() {
        let c = nodes[i].first_child;
        span[i] = if c == NO_CHILD {
            (bases[i] as u64, bases[i] as u64 + nodes[i].count as u64)
        } else {
            (span[c as usize].0, span[c as usize + 7].1)
        };
    }
    span
}

impl Run<'_, '_> {
    fn uniforms(&self, first: u32, count: u32, mode: u32, base: u32) -> OctreeUniforms {
        OctreeUniforms {
            first,
            count,
            capacity: self.config.leaf_capacity,
            max_level: self.config.max_level as u32,
            node_capacity: self.node_capacity,
            mode,
            base,
            ..OctreeUniforms::default()
        }
    }

    /// Runs `pass` over the points of segment `seg` (paged in first).
    fn dispatch(&mut self, pass: Pass, seg: Option<usize>, mode: u32) -> Result<(), GpuError> {
        let s = seg.expect("a segment");
        self.page_in(s)?;
        let sg = &self.segments[s];
        let u = self.uniforms(0, sg.len() as u32, mode, sg.base);
        self.submit(pass, seg, u)
    }

    /// The split pass over the first `count` nodes.
    fn dispatch_nodes(&mut self, count: u32) -> Result<(), GpuError> {
        let u = self.uniforms(0, count, 0, 0);
        self.submit(Pass::OctreeSplit, None, u)
    }

    /// Runs a voxel pass over `items` (the points of segment `seg`, paged in first, or blocks of
    /// cells) with the grids `first..first + count` bound.
    fn dispatch_grids(
        &mut self,
        pass: Pass,
        seg: Option<usize>,
        items: u32,
        first: u32,
        count: u64,
    ) -> Result<(), GpuError> {
        if let Some(s) = seg {
            self.page_in(s)?;
        }
        let base = seg.map_or(0, |s| self.segments[s].base);
        // Mode 2: the points' arrival numbers are in the leaf buffer (a segment in leaf order).
        let mode = match seg {
            Some(s) if self.segments[s].order.is_some() => 2,
            _ => 0,
        };
        let mut u = self.uniforms(0, items, mode, base);
        u.grid_first = first;
        u.grid_count = count as u32;
        self.submit(pass, seg, u)
    }

    /// Puts segment `s` on the GPU, paging out the least recently used ones beyond the limit.
    fn page_in(&mut self, s: usize) -> Result<(), GpuError> {
        self.clock += 1;
        self.segments[s].used = self.clock;
        if self.segments[s].gpu.is_some() {
            return Ok(());
        }
        while self.segments.iter().filter(|x| x.gpu.is_some()).count() >= self.resident {
            let lru = (0..self.segments.len())
                .filter(|&k| self.segments[k].gpu.is_some())
                .min_by_key(|&k| self.segments[k].used)
                .expect("a resident segment");
            // A segment in leaf order is made again from `perm` when it comes back.
            if self.segments[lru].order.is_none() {
                let leaves = self.read_leaves(lru)?;
                self.segments[lru].leaves = Some(leaves);
            }
            self.segments[lru].gpu = None;
        }
        let ctx = &self.b.ctx;
        // Timed alone, from an idle queue to the upload's end (the passes wait for it anyway).
        ctx.wait()?;
        let t = Instant::now();
        let sg = &mut self.segments[s];
        let mut bytes = 12 * sg.len() as u64;
        let (p, l) = if let Some(r) = &sg.order {
            // Gathered in leaf order, with their arrival numbers for the leaf buffer.
            let arrivals = &self.perm[r.clone()];
            let all = sg.pos;
            let gathered: Vec<[u32; 3]> = arrivals.par_iter().map(|&a| all[a as usize]).collect();
            bytes += 4 * arrivals.len() as u64;
            (
                self.b.upload("octree points", bytemuck::cast_slice(&gathered))?,
                self.b.upload("octree leaves", bytemuck::cast_slice(arrivals))?,
            )
        } else {
            let p = self.b.upload("octree points", bytemuck::cast_slice(sg.pos))?;
            let l = match sg.leaves.take() {
                Some(v) => {
                    bytes += 4 * v.len() as u64;
                    self.b.upload("octree leaves", bytemuck::cast_slice(&v))?
                }
                None => storage(ctx, "octree leaves", 4 * sg.pos.len() as u64),
            };
            (p, l)
        };
        sg.gpu = Some((p, l));
        ctx.wait()?;
        let (b, secs) = self.up.get();
        self.up.set((b + bytes, secs + t.elapsed().as_secs_f64()));
        Ok(())
    }

    /// The leaves (or slots) of segment `s`, read from the GPU where it is there.
    fn read_leaves(&self, s: usize) -> Result<Vec<u32>, GpuError> {
        let sg = &self.segments[s];
        match (&sg.gpu, &sg.leaves) {
            (Some((_, l)), _) => self.read(l, 4 * sg.len() as u64),
            (None, Some(v)) => Ok(v.clone()),
            (None, None) => Ok(vec![0; sg.len()]),
        }
    }

    /// The slots of segment `s` (after the slot pass), its buffers freed.
    fn take_leaves(&mut self, s: usize) -> Result<Vec<u32>, GpuError> {
        let v = self.read_leaves(s)?;
        self.segments[s].gpu = None;
        self.segments[s].leaves = None;
        Ok(v)
    }

    fn submit(
        &self,
        pass: Pass,
        seg: Option<usize>,
        mut u: OctreeUniforms,
    ) -> Result<(), GpuError> {
        if u.count == 0 {
            return Ok(());
        }
        let ctx = &self.b.ctx;
        let (gx, gy) = ctx.split_dispatch(u.count.div_ceil(WORKGROUP));
        u.groups_x = gx;
        let ub = ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("octree uniforms"),
            contents: bytemuck::bytes_of(&u),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let (p, l) = match seg.and_then(|s| self.segments[s].gpu.as_ref()) {
            Some((p, l)) => (p, l),
            None => (&self.dummy.0, &self.dummy.1),
        };
        use crate::pipeline::entry;
        let bg = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(pass.file()),
            layout: &self.b.layout,
            entries: &[
                entry(binding::OCTREE_PARAMS, ub.as_entire_binding()),
                entry(binding::OCTREE_NODES, self.nodes.as_entire_binding()),
                entry(binding::OCTREE_STATE, self.state.as_entire_binding()),
                entry(binding::OCTREE_POS, p.as_entire_binding()),
                entry(binding::OCTREE_LEAF, l.as_entire_binding()),
                entry(binding::OCTREE_GRIDS, self.grids.as_entire_binding()),
                entry(binding::OCTREE_BLOCKS, self.blocks.as_entire_binding()),
                entry(binding::OCTREE_OUT, self.out.as_entire_binding()),
            ],
        });
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut cp = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(pass.file()),
                timestamp_writes: None,
            });
            cp.set_pipeline(self.b.pipeline(pass));
            cp.set_bind_group(0, &bg, &[]);
            cp.dispatch_workgroups(gx, gy, 1);
        }
        ctx.queue.submit([enc.finish()]);
        Ok(())
    }

    fn read<T: bytemuck::Pod>(&self, buf: &wgpu::Buffer, size: u64) -> Result<Vec<T>, GpuError> {
        self.read_at(buf, 0, size)
    }

    /// `size` bytes of `buf` from `offset` (a multiple of `T`'s size), through one mapped
    /// buffer of at most `transfer_bytes`, a part per submission: neither a copy that holds the
    /// GPU's transfers long nor a mapped buffer of the whole size (see [`TRANSFER_BYTES`]).
    fn read_at<T: bytemuck::Pod>(
        &self,
        buf: &wgpu::Buffer,
        offset: u64,
        size: u64,
    ) -> Result<Vec<T>, GpuError> {
        let t = std::mem::size_of::<T>() as u64;
        let mut out: Vec<T> = vec![bytemuck::Zeroable::zeroed(); (size / t) as usize];
        if out.is_empty() {
            return Ok(out);
        }
        let ctx = &self.b.ctx;
        // Reads of a few bytes (the state, every round) are waits for a pass, not transfers;
        // larger ones are timed alone, from an idle queue (the copy waits for the passes anyway).
        let timed = size >= 1 << 20;
        if timed {
            ctx.wait()?;
        }
        let t = Instant::now();
        read_in_parts(ctx, buf, offset, bytemuck::cast_slice_mut(&mut out), self.b.transfer_bytes)?;
        if timed {
            let (b, secs) = self.down.get();
            self.down.set((b + size, secs + t.elapsed().as_secs_f64()));
        }
        Ok(out)
    }

    fn read_state(&self) -> Result<[u32; 4], GpuError> {
        let v: Vec<u32> = self.read(&self.state, 16)?;
        Ok([v[0], v[1], v[2], v[3]])
    }

    /// The node buffer filled up during a split pass that began with `before` nodes: keeps the
    /// children given out in full, doubles the buffer and clears the overflow.
    fn grow_nodes(&mut self, before: u32, split: u32) -> Result<(), GpuError> {
        let ctx = &self.b.ctx;
        let valid = before + (self.node_capacity.saturating_sub(before)) / 8 * 8;
        let limit = self.node_limit;
        if self.node_capacity >= limit {
            return Err(GpuError::TooLarge {
                what: "the octree's nodes (a binding, or an eighth of --gpu-memory)",
                needed: 32 * (self.node_capacity as u64 + 8),
                limit: 32 * limit as u64,
            });
        }
        let cap = self.node_capacity.saturating_mul(2).min(limit);
        let bigger = storage(ctx, "octree nodes", 32 * cap as u64);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(&self.nodes, 0, &bigger, 0, 32 * valid as u64);
        ctx.queue.submit([enc.finish()]);
        ctx.queue.write_buffer(&self.state, 0, bytemuck::cast_slice(&[valid, split, 0, 0]));
        self.nodes = bigger;
        self.node_capacity = cap;
        ctx.wait()
    }
}

impl TreeBackend for GpuTreeBuilder {
    fn name(&self) -> String {
        let a = self.ctx.adapter();
        let within = match self.budget {
            Some(b) => format!(", within {:.1} GiB", b as f64 / (1u64 << 30) as f64),
            None => String::new(),
        };
        format!("{} ({}, {}{within})", a.name, a.backend, a.device_type)
    }

    fn holds_buffers_in_host_memory(&self) -> bool {
        // A software adapter's buffers are host memory of this process; an integrated GPU's
        // are host memory too, counted here to be safe.
        self.ctx.is_software() || self.ctx.adapter().device_type.contains("ntegrated")
    }

    fn build(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &BuilderConfig,
    ) -> Result<ArrivalTree, String> {
        self.build_tree(size_log2, pos, config).map_err(|e| e.to_string())
    }

    fn build_without_slots(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &BuilderConfig,
    ) -> Result<ArrivalTree, String> {
        self.build_tree_with(size_log2, pos, config, false).map_err(|e| e.to_string())
    }

    fn sorts(&self, n: usize) -> bool {
        self.sorts_points(n)
    }

    fn build_ordered(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &BuilderConfig,
        order: &dyn Fn(Vec<u32>),
    ) -> Result<ArrivalTree, String> {
        if !self.sorts_points(pos.len()) {
            order(mortar_core::octree::arrival::morton_order(pos));
            return self.build_without_slots(size_log2, pos, config);
        }
        self.build_tree_ordered(size_log2, pos, config, false, Some(order))
            .map_err(|e| e.to_string())
    }
}
