//! The GPU engine of `mortar build --engine gpu` (issue 29; ARCHITECTURE.md, "The GPU engine"):
//! the octree made by SimLOD's passes on the GPU (a [`TreeBackend`] the caller hands in
//! [`BuildOptions::tree`]: `mortar_render::octree` in the command line), then the store written
//! exactly as the sorted engine writes it, so that both engines give the same bytes.
//!
//! 1. every piece is read as the sorted engine reads it ([`super::engine::read_input`]), the same
//!    root chosen;
//! 2. the positions relative to the root's corner, in arrival order (12 bytes a point), go to the
//!    backend, which gives the nodes and each inner node's voxels (the earliest point of each
//!    cell) without the per-point slots;
//! 3. the records are put in the sorted engine's order (Morton order, ties by the bits a shifted
//!    code drops, then arrival; leaves depth first are in that order, so the records are then
//!    the leaves' ranges one after the other):
//!    - where the backend holds the points and its sort's buffers at once
//!      ([`TreeBackend::sorts`]), the GPU sorts them first (`mortar_render::radix`) and hands
//!      the order over ([`TreeBackend::build_ordered`]); the host checks it
//!      ([`mortar_core::octree::arrival::check_order`]) and gathers the records by it while the
//!      GPU builds the tree;
//!    - else the host sorts them with the sorted engine's sort ([`super::engine::sort_records`]),
//!      at the same time as the GPU builds on a discrete GPU, after it where the adapter runs on
//!      the host's cores (lavapipe);
//!
//!    the tree becomes the sorted engine's tree ([`ArrivalTree::into_sorted`]) once its leaves
//!    are checked against the order (counts adding up, every point in its leaf's cube: a GPU
//!    that got the tree wrong is refused);
//! 4. the nodes are encoded and committed level by level ([`super::engine::write_tree`]).
//!
//! The input must fit `--memory` as for the sorted engine (refused otherwise, naming the need);
//! on the GPU, `--gpu-memory` bounds what the builder holds (`mortar_render::octree`).
//! Whether the backend sorts is its own choice: the command line's GPU builder sorts only where
//! `MORTAR_GPU_SORT=1` (`mortar_app::gpu_build`; off by default: a draw on the H100, slower on
//! lavapipe; the tests turn it on to run it on lavapipe, the benchmarks to compare).
//!
//! History: until 2026-12-06 the GPU gave each point its slot and the host placed the records
//! and sorted within each leaf, after the GPU; then the host sorted the whole input with the
//! sorted engine's sort while the GPU built (BENCHMARKS.md, "The GPU engine sorts while the GPU
//! builds": 1.10x at 20 M points, a draw at 100 M and 1 B, the sort slowed by the transfers
//! beside it being the longer); then the GPU's radix sort (BENCHMARKS.md, "The GPU sorts").
//!
//! Not done yet (issue 29): the preview draws the store's commits rather than the GPU's buffers;
//! the payloads are coded on the CPU.

use super::engine::{
    bucket_shift, color_of, grid_of, histogram, piece_starts, read_input, sort_records,
    write_arrival, write_tree, Input, Sorted,
};
use super::options::{BuildOptions, BuildProgress, BuildReport, BuiltBy};
use super::writer::*;
use crate::dataset::Dataset;
use crate::error::{Error, Result};
use mortar_core::layout::read_xyz;
use mortar_core::octree::arrival::{check_nodes, ArrivalTree, NO_CHILD};
use mortar_core::octree::{Cube, OctreeError, SortedContent, SortedTree};
use mortar_core::par::SendPtr;
use rayon::prelude::*;
use std::time::Instant;

/// Bytes per point the GPU engine holds besides the records, as the OS counts it, on a software
/// adapter (lavapipe), where the tree is built first and the records sorted after it: the
/// positions handed to the GPU (12), wgpu's staging copy of them, the GPU's own buffers in host
/// memory (12 + 16), then the sort's arrival numbers (8) and per-bucket work, and the inverse (4),
/// with room to spare. Measured under lavapipe (BENCHMARKS.md, "memory"): points at one position
/// peaked at 175 MB (0.5 M), 734 MB (4 M) and 1,289 MB (8 M points of 34 bytes) when the GPU
/// also gave slots: 139 bytes a point besides [`FIXED`]; 559 MB at 4 M since it does not.
const PER_POINT_SHARED: u64 = 72;

/// The same on a discrete GPU, whose buffers are not the process's memory, and where the sort
/// runs while the GPU builds, so the positions (12) are held with the sort's arrival numbers (8),
/// its per-bucket work and the inverse (4): measured on the H100 (BENCHMARKS.md, "The GPU engine
/// sorts while the GPU builds"), 100 M points of 34 bytes from a mapped LAS file peaked at
/// 10.05 GB, 32.5 bytes a point besides the mapped input and the sorted records (26 at 1 B
/// points); 40 leaves room.
const PER_POINT_DISCRETE: u64 = 40;

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
    let mut report = BuildReport { engine: BuiltBy::Gpu, ..BuildReport::default() };
    let Input { slabs, hist, all, root, promised, bounds } =
        read_input(ds, header, &mut report, t0)?;
    let records: Vec<&[u8]> = slabs.iter().map(|(r, _)| &**r).collect();
    let starts = piece_starts(&records, rl);
    let n = starts[records.len()];
    if n >= u32::MAX as usize {
        return Err(Error::TooManyPoints { what: "build --engine gpu" });
    }
    let g = grid_of(root);
    let shift = bucket_shift(root);
    // 2. the positions for the GPU, in arrival order.
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
    // 3. the tree on the GPU and the records sorted by the sorted engine's sort: at the same
    // time on a discrete GPU (the host's cores are free while it builds), one after the other
    // where the GPU's work runs on the same cores and its buffers are this process's memory.
    let tree_on_gpu = |pos: &[[u32; 3]]| {
        let tt = Instant::now();
        let tree = backend.build_without_slots(root.size_log2, pos, &opts.config);
        (tree, tt.elapsed().as_secs_f64())
    };
    let sort = || {
        let ts = Instant::now();
        // The headers' box was not the points': the counts again, on the root's grid.
        let fresh: Vec<Vec<u32>>;
        let hist = if root != promised {
            fresh = records.par_iter().map(|s| histogram(s, rl, &g, shift)).collect();
            &fresh
        } else {
            &hist
        };
        let sorted = sort_records(&records, hist, rl, &g, shift, &ds.progress, |p, i| {
            (p as u64) << 32 | i as u64
        });
        (sorted, ts.elapsed().as_secs_f64())
    };
    let gpu_failed =
        |m: String| Error::Octree { error: OctreeError::Unsupported(format!("GPU: {m}")) };
    // The tree, the sorted records and, where the GPU sorted, the inverse of its order.
    let (tree, tree_seconds, sorted, sort_seconds, inv) = if backend.sorts(n) {
        // 3'. the order from the GPU's sort, the records gathered by it while the GPU builds
        // the tree.
        ds.progress.stage("sorting and indexing on the GPU", all.count, "points");
        let (tx, rx) = std::sync::mpsc::channel::<Vec<u32>>();
        let held = &pos;
        let ((tree, tree_seconds), gathered) = beside_gpu(
            move || {
                let give = |v: Vec<u32>| {
                    let _ = tx.send(v);
                };
                let tt = Instant::now();
                let tree = backend.build_ordered(root.size_log2, held, &opts.config, &give);
                (tree, tt.elapsed().as_secs_f64())
            },
            // The order comes before the GPU builds the tree; none if it failed first.
            || {
                rx.recv().ok().map(|order| {
                    let ts = Instant::now();
                    let g = gather(&records, &starts, rl, root, order, &ds.progress);
                    (g, ts.elapsed().as_secs_f64())
                })
            },
        );
        drop(pos);
        let tree = tree.map_err(gpu_failed)?;
        let Some((gathered, sort_seconds)) = gathered else {
            return Err(gpu_failed("the backend gave no order".into()));
        };
        let (sorted, inv) = gathered?;
        (tree, tree_seconds, sorted, sort_seconds, Some(inv))
    } else {
        // 3. the host's sort (the GPU cannot hold the points and the sort's buffers at once).
        let ((tree, tree_seconds), (sorted, sort_seconds)) =
            if backend.holds_buffers_in_host_memory() {
                ds.progress.stage("indexing on the GPU", 0, "");
                let t = tree_on_gpu(&pos);
                drop(pos);
                crate::cleanup::check_interrupted()?;
                ds.progress.stage("sorting", 2 * all.count, "points");
                (t, sort())
            } else {
                ds.progress.stage("sorting, indexing on the GPU", 2 * all.count, "points");
                let t = beside_gpu(|| tree_on_gpu(&pos), sort);
                drop(pos);
                t
            };
        (tree.map_err(gpu_failed)?, tree_seconds, sorted, sort_seconds, None)
    };
    drop(records);
    drop(slabs);
    report.gpu = Some(backend.name());
    report.gpu_steps = tree.phases.clone();
    report.tree_seconds = tree_seconds;
    report.sort_seconds = sort_seconds;
    crate::cleanup::trace("tree on the GPU and records ordered", t0);
    crate::cleanup::check_interrupted()?;
    // 4. the GPU's tree over the sorted records: its voxels' arrival numbers to sorted indices,
    // its leaves checked against the order.
    let ts = Instant::now();
    let inv = inv.unwrap_or_else(|| {
        let mut inv = crate::sort::zeroed_huge::<u32>(n);
        let ip = SendPtr(inv.as_mut_ptr());
        sorted.arrival.par_iter().enumerate().for_each(|(i, &a)| {
            let ip = &ip;
            // The sort's arrival numbers (piece << 32 | index) are a permutation of the
            // pieces' records; the GPU numbers them 0..n in the same order.
            let at = starts[(a >> 32) as usize] + (a & 0xffff_ffff) as usize;
            // SAFETY: each `at` is below n and written once.
            unsafe { ip.write(at, i as u32) };
        });
        inv
    });
    let stree = leaves_checked(tree, root, &sorted, &inv)?;
    drop(inv);
    report.sort_seconds += ts.elapsed().as_secs_f64();
    report.batch_seconds.push(report.tree_seconds);
    crate::cleanup::trace("leaves checked", t0);
    let color = color_of(ds, &all);
    ds.progress.stage("writing", stree.nodes.len() as u64, "nodes");
    let mut sorted = sorted;
    let mut arrival = std::mem::take(&mut sorted.arrival);
    write_tree(
        writer,
        &stree,
        root,
        opts,
        &sorted,
        &mut arrival,
        &color,
        bounds,
        &mut report,
        progress,
        &ds.progress,
        ds.declared_points(),
        t0,
    )?;
    write_arrival(writer, &arrival, &starts, header, &all)?;
    crate::cleanup::trace("arrival ranks written", t0);
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(report)
}

/// `gpu` and `host` at the same time: `gpu` (the GPU's side) on a thread of its own, its parallel
/// copies in a small pool of their own (in the global pool they would queue behind the host's
/// tasks; with as many threads as the host's, both slowed down, the host's work being the
/// longer), `host` on this thread. A panic on the GPU's side is resumed here.
fn beside_gpu<A: Send, B>(gpu: impl FnOnce() -> A + Send, host: impl FnOnce() -> B) -> (A, B) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads((rayon::current_num_threads() / 4).max(1))
        .thread_name(|i| format!("mortar-gpu-{i}"))
        .build()
        .ok();
    std::thread::scope(|scope| {
        let side = scope.spawn(move || match &pool {
            Some(p) => p.install(gpu),
            None => gpu(),
        });
        let b = host();
        (side.join().unwrap_or_else(|e| std::panic::resume_unwind(e)), b)
    })
}

/// The records of the pieces `slabs` (piece `k`'s first point is number `starts[k]`) in the
/// backend's `order` (arrival numbers in Morton order), with the arrival numbers the sorted
/// engine gives (`piece << 32 | index`) and the inverse (per arrival number, its place). The
/// order is checked first to name points, then, on the gathered records (in sequence, where
/// the positions are in cache), to be the sorted engine's: each (Morton code of the position
/// relative to `root`'s corner, arrival) above the one before, which also makes the entries
/// distinct, so a permutation. A backend that got it wrong is refused.
fn gather(
    slabs: &[&[u8]],
    starts: &[usize],
    rl: usize,
    root: Cube,
    order: Vec<u32>,
    prog: &crate::progress::Progress,
) -> Result<(Sorted, Vec<u32>)> {
    let n = *starts.last().unwrap_or(&0);
    let broken = |m: String| Error::Octree {
        error: OctreeError::Unsupported(format!("GPU: the order is broken: {m}")),
    };
    if order.len() != n {
        return Err(broken(format!("{} entries for {n} points", order.len())));
    }
    if let Some(&a) = order.par_iter().find_any(|&&a| a as usize >= n) {
        return Err(broken(format!("entry {a} names no point of {n}")));
    }
    let mut records = crate::sort::zeroed_huge::<u8>(n * rl);
    let mut arrival = crate::sort::zeroed_huge::<u64>(n);
    const CHUNK: usize = 1 << 14;
    records
        .par_chunks_mut(CHUNK * rl)
        .zip(arrival.par_chunks_mut(CHUNK))
        .zip(order.par_chunks(CHUNK))
        .for_each(|((recs, arr), ord)| {
            for (k, &a) in ord.iter().enumerate() {
                let a = a as usize;
                let piece = starts.partition_point(|&s| s <= a) - 1;
                let idx = a - starts[piece];
                recs[k * rl..(k + 1) * rl].copy_from_slice(&slabs[piece][idx * rl..(idx + 1) * rl]);
                arr[k] = (piece as u64) << 32 | idx as u64;
            }
            prog.add(ord.len() as u64);
        });
    let key = |i: usize| {
        let q = read_xyz(&records[i * rl..]);
        let rel = [0, 1, 2].map(|a| (q[a] as i64 - root.min[a]) as u32);
        (mortar_core::morton::encode96(rel), arrival[i])
    };
    let bad = (0..n.div_ceil(CHUNK)).into_par_iter().find_map_any(|c| {
        let (a, b) = (c * CHUNK, ((c + 1) * CHUNK).min(n));
        let mut last = if a > 0 { Some(key(a - 1)) } else { None };
        for i in a..b {
            let k = key(i);
            if last.is_some_and(|l| l >= k) {
                return Some(i);
            }
            last = Some(k);
        }
        None
    });
    if let Some(i) = bad {
        return Err(broken(format!("entries {} and {i} are out of order", i - 1)));
    }
    let mut inv = crate::sort::zeroed_huge::<u32>(n);
    let ip = SendPtr(inv.as_mut_ptr());
    order.par_chunks(CHUNK).enumerate().for_each(|(c, ord)| {
        let ip = &ip;
        for (k, &a) in ord.iter().enumerate() {
            // SAFETY: the order is a permutation of 0..n (checked above): each `a` once.
            unsafe { ip.write(a as usize, (c * CHUNK + k) as u32) };
        }
    });
    Ok((Sorted { records, arrival, rl }, inv))
}

/// The GPU's tree over the records of `sorted` (the sorted engine's order): its voxels' arrival
/// numbers (`0..n` in the pieces' order) made sorted indices by `inv`, and its leaves checked to
/// be runs of that order: their counts add up to the points, and the first and last point of a
/// leaf's range lie in the leaf's cube (leaves depth first are in Morton order, as the records
/// are), every voxel in its node's. Fails on a tree the GPU got wrong rather than writing it.
fn leaves_checked(
    tree: ArrivalTree,
    root: Cube,
    sorted: &Sorted,
    inv: &[u32],
) -> Result<SortedTree> {
    let n = inv.len();
    let broken = |what: String| Error::Octree {
        error: OctreeError::Unsupported(format!("GPU: the tree is broken: {what}")),
    };
    if tree.nodes.is_empty() || tree.voxels.len() != tree.nodes.len() {
        return Err(broken("no root, or voxels for other nodes".into()));
    }
    check_nodes(&tree.nodes).map_err(|error| Error::Octree { error })?;
    let mut held = 0u64;
    let mut stack = vec![0usize];
    while let Some(i) = stack.pop() {
        let nd = tree.nodes[i];
        if nd.first_child == NO_CHILD {
            held += nd.count as u64;
        } else {
            stack.extend(nd.first_child as usize..nd.first_child as usize + 8);
        }
    }
    if held != n as u64 {
        return Err(broken(format!("its leaves hold {held} points, the input {n}")));
    }
    if tree.voxels.par_iter().any(|v| v.iter().any(|&a| a as usize >= n)) {
        return Err(broken("a voxel names no point".into()));
    }
    let stree =
        tree.into_sorted(root, |a| inv[a as usize]).map_err(|error| Error::Octree { error })?;
    let outside = stree.nodes.par_iter().find_any(|nd| match &nd.content {
        // A cube is an interval of the Morton order the records are sorted in: its first and
        // last point inside means every point between is.
        SortedContent::Leaf(r) => {
            !r.is_empty()
                && [r.start, r.end - 1]
                    .iter()
                    .any(|&i| !nd.cube.contains(read_xyz(sorted.record(i))))
        }
        SortedContent::Inner(v) => {
            v.iter().any(|&i| !nd.cube.contains(read_xyz(sorted.record(i as usize))))
        }
    });
    if let Some(nd) = outside {
        return Err(broken(format!("node {:?} holds points outside its cube", nd.key)));
    }
    Ok(stree)
}
