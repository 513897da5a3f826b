//! The GPU engine of `mortar build --engine gpu` (issue 29; ARCHITECTURE.md, "The GPU engine"):
//! the octree made by SimLOD's passes on the GPU (a [`TreeBackend`] the caller hands in
//! [`BuildOptions::tree`]: `mortar_render::octree` in the command line), then the store written
//! exactly as the sorted engine writes it, so that both engines give the same bytes.
//!
//! 1. every piece is read as the sorted engine reads it ([`super::engine::read_input`]), the same
//!    root chosen;
//! 2. the positions relative to the root's corner, in arrival order (12 bytes a point), go to the
//!    backend, which gives the nodes, each inner node's voxels (the earliest point of each cell)
//!    and each point's slot in its leaf's range (leaves depth first);
//! 3. the records are scattered to their slots and each leaf's range sorted in Morton order
//!    (ties as the sorted engine breaks them: the bits a shifted code drops, then arrival): the
//!    records are then in the sorted engine's order, and the tree is its tree
//!    ([`ArrivalTree::into_sorted`]);
//! 4. the nodes are encoded and committed level by level ([`super::engine::write_tree`]).
//!
//! The input must fit `--memory` as for the sorted engine (refused otherwise, naming the need);
//! on the GPU, `--gpu-memory` bounds what the builder holds (`mortar_render::octree`).
//!
//! Not done yet (issue 29): the preview draws the store's commits rather than the GPU's buffers,
//! and the host still places the records and sorts within leaves.

use super::engine::{code_of, color_of, grid_of, read_input, write_tree, Input, Sorted};
use super::options::{BuildOptions, BuildProgress, BuildReport, BuiltBy};
use super::writer::*;
use crate::dataset::Dataset;
use crate::error::{Error, Result};
use mortar_core::layout::read_xyz;
use mortar_core::octree::arrival::{leaf_bases, ArrivalTree, NO_CHILD};
use mortar_core::octree::OctreeError;
use mortar_core::par::SendPtr;
use rayon::prelude::*;
use std::time::Instant;

/// Bytes per point the GPU engine holds besides the records, as the OS counts it, on a software
/// adapter (lavapipe): the positions handed to the GPU (12), wgpu's staging copy of them, the
/// GPU's own buffers in host memory (12 + 16), the slots read back (4 + 4 while copied), then
/// arrival (8), slot (4) and its inverse (4), with room to spare. Measured under lavapipe
/// (BENCHMARKS.md, "memory"): points at one position peaked at 175 MB (0.5 M), 734 MB (4 M)
/// and 1,289 MB (8 M points of 34 bytes): 139 bytes a point besides [`FIXED`].
const PER_POINT_SHARED: u64 = 72;

/// The same on a discrete GPU, whose buffers are not the process's memory: measured on the H100
/// (BENCHMARKS.md, "1 B points"), 100 M points of 34 bytes from a mapped LAS file peaked at
/// 8.75 GB, 19.5 bytes a point besides the mapped input and the sorted records; 32 leaves room.
const PER_POINT_DISCRETE: u64 = 32;

/// Bytes the GPU engine holds whatever the input: the process, the GPU driver and its shader
/// compiler (a software adapter compiles with LLVM in the process): 175 MB measured at 0.5 M
/// points.
const FIXED: u64 = 192 << 20;

/// Builds the store in `writer` from `ds` with the GPU engine; `header` is the headers' box
/// (see [`super::build`]).
pub(crate) fn build_into(
    ds: &Dataset,
    writer: &mut StoreWriter,
    opts: &BuildOptions,
    progress: &mut dyn FnMut(&BuildProgress),
    header: Option<([i32; 3], [i32; 3])>,
    t0: Instant,
) -> Result<BuildReport> {
    let Some(backend) = opts.tree.as_ref() else {
        return Err(Error::Octree {
            error: OctreeError::Unsupported("the GPU engine was given no GPU".into()),
        });
    };
    // The records as read and as placed, and per point what the build holds at its peak (see
    // PER_POINT_SHARED).
    let per_point =
        if backend.holds_buffers_in_host_memory() { PER_POINT_SHARED } else { PER_POINT_DISCRETE };
    let needed = super::engine::held_in_memory(ds, per_point)
        .saturating_add(2 * group_bytes(opts.memory))
        .saturating_add(FIXED);
    if needed > opts.memory {
        return Err(Error::OverBudget { what: "the GPU engine", needed, budget: opts.memory });
    }
    let rl = ds.layout.record_len;
    let total = ds.declared_points();
    let mut report = BuildReport { engine: BuiltBy::Gpu, ..BuildReport::default() };
    let Input { slabs, all, root, bounds, .. } = read_input(ds, header, &mut report, t0)?;
    let records: Vec<&[u8]> = slabs.iter().map(|(r, _)| &**r).collect();
    let mut starts = vec![0usize; records.len() + 1];
    for (k, r) in records.iter().enumerate() {
        starts[k + 1] = starts[k] + r.len() / rl;
    }
    let n = starts[records.len()];
    if n >= u32::MAX as usize {
        return Err(Error::TooManyPoints { what: "build --engine gpu" });
    }
    // 2. the tree on the GPU.
    let tt = Instant::now();
    ds.progress.stage("indexing on the GPU", 0, "");
    let mut pos = crate::sort::zeroed_huge::<[u32; 3]>(n);
    {
        let pp = SendPtr(pos.as_mut_ptr());
        records.par_iter().enumerate().for_each(|(k, slab)| {
            let pp = &pp;
            for (i, r) in slab.chunks_exact(rl).enumerate() {
                let q = read_xyz(r);
                let rel = [0, 1, 2].map(|a| (q[a] as i64 - root.min[a]) as u32);
                // SAFETY: the pieces' ranges starts[k].. are disjoint and within n.
                unsafe { pp.write(starts[k] + i, rel) };
            }
        });
    }
    let tree = backend
        .build(root.size_log2, &pos, &opts.config)
        .map_err(|m| Error::Octree { error: OctreeError::Unsupported(format!("GPU: {m}")) })?;
    drop(pos);
    report.gpu = Some(backend.name());
    report.gpu_steps = tree.phases.clone();
    report.tree_seconds = tt.elapsed().as_secs_f64();
    crate::cleanup::trace("tree on the GPU", t0);
    crate::cleanup::check_interrupted()?;
    // 3. the records in the sorted engine's order.
    let ts = Instant::now();
    ds.progress.stage("sorting", all.count, "points");
    let sorted = order_records(&records, &starts, rl, &tree, root)?;
    drop(records);
    drop(slabs);
    let mut inv = crate::sort::zeroed_huge::<u32>(n);
    {
        let ip = SendPtr(inv.as_mut_ptr());
        sorted.arrival.par_iter().enumerate().for_each(|(i, &a)| {
            let ip = &ip;
            // SAFETY: arrivals are a permutation of 0..n (the slots were checked).
            unsafe { ip.write(a as usize, i as u32) };
        });
    }
    let stree = tree
        .into_sorted(root, |a| inv.get(a as usize).copied().unwrap_or(u32::MAX))
        .map_err(|error| Error::Octree { error })?;
    drop(inv);
    if stree.nodes.iter().any(|nd| match &nd.content {
        mortar_core::octree::SortedContent::Inner(v) => v.iter().any(|&i| i as usize >= n),
        mortar_core::octree::SortedContent::Leaf(r) => r.end > n,
    }) {
        return Err(Error::Octree {
            error: OctreeError::Unsupported("GPU: a voxel or leaf out of range".into()),
        });
    }
    report.sort_seconds = ts.elapsed().as_secs_f64();
    report.batch_seconds.push(report.tree_seconds);
    crate::cleanup::trace("records ordered", t0);
    let color = color_of(ds, &all);
    ds.progress.stage("writing", stree.nodes.len() as u64, "nodes");
    write_tree(
        writer,
        &stree,
        root,
        opts,
        &sorted,
        &color,
        bounds,
        &mut report,
        progress,
        &ds.progress,
        total,
        t0,
    )?;
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(report)
}

/// The records of `slabs` (piece `k` holds arrivals `starts[k]..`) put in their slots, then each
/// leaf's range sorted as the sorted engine orders points: Morton code on the root's grid, then
/// the bits a shifted code drops, then arrival. Fails on slots that are not a permutation.
fn order_records(
    slabs: &[&[u8]],
    starts: &[usize],
    rl: usize,
    tree: &ArrivalTree,
    root: mortar_core::octree::Cube,
) -> Result<Sorted> {
    let n = starts[slabs.len()];
    let broken = |what: &str| Error::Octree {
        error: OctreeError::Unsupported(format!("GPU: the slots are not a permutation ({what})")),
    };
    if tree.slot.len() != n {
        return Err(broken("a slot per point"));
    }
    // A permutation of 0..n: all below n, and their sum and the sum of their squares those of
    // 0..n (a cheap check of what came back from the device; the scatter below writes in
    // bounds whatever they are).
    let (sum, sq) = tree
        .slot
        .par_iter()
        .map(|&s| (s as u128, (s as u128) * (s as u128)))
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    let m = n as u128;
    let want_sq = if n == 0 { 0 } else { (m - 1) * m * (2 * m - 1) / 6 };
    if tree.slot.par_iter().any(|&s| s as usize >= n)
        || sum != m * m.saturating_sub(1) / 2
        || sq != want_sq
    {
        return Err(broken("out of range or repeated"));
    }
    let mut records = crate::sort::zeroed_huge::<u8>(n * rl);
    let mut arrival = crate::sort::zeroed_huge::<u64>(n);
    {
        let rp = SendPtr(records.as_mut_ptr());
        let ap = SendPtr(arrival.as_mut_ptr());
        slabs.par_iter().enumerate().for_each(|(k, slab)| {
            let (rp, ap) = (&rp, &ap);
            for (i, r) in slab.chunks_exact(rl).enumerate() {
                let a = starts[k] + i;
                let s = tree.slot[a] as usize;
                // SAFETY: the slots are a permutation of 0..n (checked above).
                unsafe {
                    std::ptr::copy_nonoverlapping(r.as_ptr(), rp.0.add(s * rl), rl);
                    ap.write(s, a as u64);
                }
            }
        });
    }
    // Each leaf's range, sorted.
    let bases = leaf_bases(&tree.nodes);
    let mut ranges: Vec<(usize, usize)> = tree
        .nodes
        .iter()
        .enumerate()
        .filter(|(_, nd)| nd.first_child == NO_CHILD && nd.count > 1)
        .map(|(i, nd)| (bases[i] as usize, nd.count as usize))
        .collect();
    ranges.sort_unstable();
    let g = grid_of(root);
    let mask = (1i64 << g.shift) - 1;
    let mut parts: Vec<(&mut [u8], &mut [u64])> = Vec::with_capacity(ranges.len());
    {
        let (mut rr, mut ar): (&mut [u8], &mut [u64]) = (&mut records, &mut arrival);
        let mut at = 0usize;
        for &(s, c) in &ranges {
            if s < at || s + c > n {
                return Err(broken("leaf ranges overlap"));
            }
            let (_, r1) = std::mem::take(&mut rr).split_at_mut((s - at) * rl);
            let (x, r2) = r1.split_at_mut(c * rl);
            let (_, a1) = std::mem::take(&mut ar).split_at_mut(s - at);
            let (y, a2) = a1.split_at_mut(c);
            parts.push((x, y));
            rr = r2;
            ar = a2;
            at = s + c;
        }
    }
    parts.into_par_iter().for_each_init(
        || (Vec::<(u64, u64, u64, u32)>::new(), Vec::<u8>::new(), Vec::<u64>::new()),
        |(keys, tmp, tarr), (recs, arr)| {
            keys.clear();
            keys.extend(recs.chunks_exact(rl).zip(arr.iter()).enumerate().map(|(i, (r, &a))| {
                let residual = if g.shift > 0 {
                    let q = read_xyz(r);
                    let low = |x: usize| ((q[x] as i64 - g.origin[x]) & mask) as u32;
                    mortar_core::morton::encode(low(0), low(1), low(2))
                } else {
                    0
                };
                (code_of(r, &g), residual, a, i as u32)
            }));
            if keys.windows(2).all(|w| w[0] < w[1]) {
                return;
            }
            keys.sort_unstable();
            tmp.clear();
            tmp.extend_from_slice(recs);
            tarr.clear();
            tarr.extend_from_slice(arr);
            for (d, k) in keys.iter().enumerate() {
                let j = k.3 as usize;
                recs[d * rl..(d + 1) * rl].copy_from_slice(&tmp[j * rl..(j + 1) * rl]);
                arr[d] = tarr[j];
            }
        },
    );
    Ok(Sorted { records, arrival, rl })
}
