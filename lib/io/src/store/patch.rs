//! `mortar build --append STORE MORE` in place of a whole build: the store's nodes that no new
//! point reaches are kept, payload bytes and all, and only the nodes on the new points' paths
//! are coded again (`mortar_core::octree::patch`). The result is the store a build of all the
//! inputs gives, node for node and byte for byte in every payload, `arrival.bin`, `source.las`
//! and `build.json`; its payloads lie in other places (ARCHITECTURE.md, "`--append`").
//!
//! How: the new store is made in the working directory `STORE.append` as the whole-build append
//! makes it, and exchanged with the store the same way ([`super::append::replace_store`]). The
//! store's payload files are hard-linked into it as segments `1..` (copied where the file system
//! cannot link), its new and changed payloads go to `nodes.bin` (segment 0), and the hierarchy
//! lists every node in the sorted engine's order. Nothing of the store is written: until the
//! exchange it is the old store, whole. `mortar build --compact` later drops the superseded
//! payloads from the linked segments.
//!
//! When: the store keeps its arrival ranks and colour maxima (`arrival.bin` of version 2, from
//! the sorted, partitioned or GPU engine), its colours are first-come, and the new points change neither the
//! merged grid nor the record layout, nor the root cube, nor the colour scale (the largest RGB
//! component or intensity where they choose the colours). Otherwise [`append_in_place`] says
//! why, and the caller builds everything again as before.
//!
//! Memory: a bit a point of the store to check its ranks (read a few blocks at a time, not
//! held: [`arrival::RankFile`]), the new records with their sort keys (48 bytes a point besides
//! the record), and the records and ranks of the nodes the new points reach, at once; where
//! that passes `--memory`, the whole build is taken (which has its own rules).

use super::append::{grid_moved, AppendPlan, StoreInArrivalOrder};
use super::arrival::{self, ColorMaxima};
use super::bounds::{bounds_warning, header_bounds};
use super::codec;
use super::engine::color_source;
use super::format::*;
use super::options::{BuildReport, BuiltBy};
use super::reader::{node_data, Store};
use super::record::BuildRecord;
use super::writer::StoreWriter;
use crate::dataset::{Dataset, OpenOptions, RecordSource};
use crate::error::{Error, Result, StoreError};
use crate::sort::PieceStats;
use mortar_core::morton::encode96;
use mortar_core::octree::patch::{code_in, patch_tree, Item, OldContent, OldNode, PatchedContent};
use mortar_core::octree::{ColorMode, Cube, NodeKey};
use rayon::prelude::*;
use std::collections::HashMap;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// What [`append_in_place`] did.
#[derive(Debug)]
pub enum InPlace {
    /// The store was extended into the plan's working directory (not yet exchanged).
    Done(Box<BuildReport>),
    /// It cannot be, for this reason: build everything again.
    Rebuild(String),
}

/// Extends the store of `plan` by its new inputs into `plan.work`, keeping the nodes the new
/// points do not reach (see the module docs), or says why a whole build is needed. `memory` is
/// `--memory`.
pub fn append_in_place(plan: &AppendPlan, opts: &OpenOptions, memory: u64) -> Result<InPlace> {
    let t0 = Instant::now();
    let rebuild = |why: &str| Ok(InPlace::Rebuild(why.to_string()));
    if plan.config.color_mode != ColorMode::FirstCome {
        return rebuild("averaged colours change with every point");
    }
    let store = Store::open(&plan.store)?;
    let old_n = store.header.points;
    if old_n == 0 {
        return rebuild("the store holds no points");
    }
    let Some(record) = BuildRecord::read(&plan.store)? else {
        return rebuild("the store has no build record");
    };
    let rl = store.layout.record_len as u64;
    let mut warnings = Vec::new();
    let mut more: Vec<Box<dyn RecordSource>> = Vec::new();
    for p in crate::inputs::expand(&plan.more)? {
        let (src, mut w) = crate::inputs::open_source(&p)?;
        warnings.append(&mut w);
        more.push(src);
    }
    let new_declared: u64 = more.iter().map(|s| s.point_count()).sum();
    // The ranks' blocks coded at once, the store's blocks kept for them (`at_once + 2` of 8
    // MiB), and the check of the ranks (a bit a point); the new records, their places and sort
    // keys.
    let at_once = (memory / 16 / arrival::BLOCK_BYTES).clamp(1, arrival::BLOCKS_AT_ONCE as u64);
    let need = old_n / 8 + 2 * at_once * arrival::BLOCK_BYTES + new_declared * (rl + 48);
    if need > memory {
        return rebuild(&format!(
            "keeping the store's nodes needs about {} MiB here, over --memory ({} MiB)",
            need >> 20,
            memory >> 20
        ));
    }
    let Some(arr) = arrival::RankFile::open(&plan.store, old_n)? else {
        return rebuild("the store keeps no arrival ranks (arrival.bin)");
    };
    let Some(old_colors) = arr.colors else {
        return rebuild("its arrival.bin is of an older mortar (without the colour maxima)");
    };
    // The dataset of the whole build: the store standing for its inputs, then the new ones.
    let mut inputs: Vec<Box<dyn RecordSource>> =
        vec![Box::new(StoreInArrivalOrder::stand_in(&store, arr.declared, plan.recorded.clone()))];
    inputs.append(&mut more);
    let mut ds = Dataset::with_options(inputs, opts)?;
    if grid_moved(&ds) {
        return rebuild("the new inputs change the store's scale or offset");
    }
    if ds.layout != store.layout {
        return rebuild("the new inputs change the store's record layout");
    }
    warnings.append(&mut ds.warnings);
    let declared = header_bounds(&ds, &mut warnings);

    // The new records in arrival order, with their statistics.
    let tr = Instant::now();
    let pieces: Vec<_> = ds.pieces().into_iter().filter(|p| p.input > 0).collect();
    let slabs: Vec<(std::borrow::Cow<'_, [u8]>, PieceStats)> = pieces
        .par_iter()
        .map(|p| {
            crate::cleanup::check_interrupted()?;
            let slab = ds.read_piece(p)?;
            if slab.len() as u64 != p.piece.points * rl {
                return Err(Error::PieceCount {
                    path: ds.inputs[p.input].path().to_path_buf(),
                    piece: p.piece.index,
                });
            }
            let st = PieceStats::of_with(&slab, &ds.layout, |_, _| {});
            Ok((slab, st))
        })
        .collect::<Result<_>>()?;
    let mut all = PieceStats::default();
    let mut per_input = vec![PieceStats::default(); ds.inputs.len()];
    for (p, (_, st)) in pieces.iter().zip(&slabs) {
        all.merge(st);
        per_input[p.input].merge(st);
    }
    for (src, st) in ds.inputs.iter().zip(&per_input).skip(1) {
        if let Some(w) = bounds_warning(&ds, src.as_ref(), st) {
            warnings.push(w);
        }
    }
    let read_seconds = tr.elapsed().as_secs_f64();
    crate::cleanup::trace("append in place: new points read", t0);

    // The root the whole build would place, and its colours.
    let root = store.root_cube();
    let (mut lo, mut hi) = (store.header.min, store.header.max);
    for a in 0..3 {
        lo[a] = lo[a].min(all.min[a]);
        hi[a] = hi[a].max(all.max[a]);
    }
    let want_root = match declared {
        Some((l, h)) if (0..3).all(|a| l[a] <= lo[a] && hi[a] <= h[a]) => Cube::covering(l, h),
        _ => Cube::covering(lo, hi),
    };
    if want_root != root {
        return rebuild("the new points move the octree's root cube");
    }
    let colors = ColorMaxima {
        max_rgb: old_colors.max_rgb.max(all.max_rgb),
        max_intensity: old_colors.max_intensity.max(all.max_intensity),
    };
    let color = color_source(&ds.layout, colors.max_rgb, colors.max_intensity);
    if color != color_source(&ds.layout, old_colors.max_rgb, old_colors.max_intensity) {
        return rebuild("the new points change the colour scale (largest RGB or intensity)");
    }

    // The new points in Morton order, ties by arrival.
    let rl = rl as usize;
    let records: Vec<&[u8]> = slabs.iter().flat_map(|(s, _)| s.chunks_exact(rl)).collect();
    let n_new = records.len();
    let mut order: Vec<(u128, u32)> = records
        .par_iter()
        .enumerate()
        .map(|(i, r)| (code_in(root, read_xyz(r)), i as u32))
        .collect();
    order.par_sort_unstable();
    let new_rec = |j: u32| records[order[j as usize].1 as usize];
    let new_pos: Vec<[i32; 3]> = (0..n_new as u32).map(|j| read_xyz(new_rec(j))).collect();
    let new_arrival: Vec<u64> = order.iter().map(|&(_, i)| old_n + i as u64).collect();

    // What the nodes the new points reach hold, held while the tree is patched: each such
    // node's cube is a range of codes that holds a new point.
    let reached_ids: Vec<usize> = (0..store.entries.len())
        .into_par_iter()
        .filter(|&id| {
            let e = &store.entries[id];
            let key = NodeKey { level: e.level as u8, index: e.index };
            let c = key.cube_in(root);
            let first = encode96([0, 1, 2].map(|a| (c.min[a] - root.min[a]) as u32));
            let span = 1u128 << (3 * c.size_log2 as u32);
            let i = order.partition_point(|&(code, _)| code < first);
            i < order.len() && order[i].0 - first < span
        })
        .collect();
    let reached: u64 = reached_ids.iter().map(|&id| store.entries[id].count).sum();
    let need = need + reached * (rl as u64 + 64);
    if need > memory {
        return rebuild(&format!(
            "the nodes the new points reach hold {reached} points, and keeping the others needs \
             about {} MiB, over --memory ({} MiB)",
            need >> 20,
            memory >> 20
        ));
    }

    // The old tree, and its nodes' records as the new points reach them.
    let old: Vec<OldNode> = store
        .entries
        .iter()
        .map(|e| OldNode {
            key: NodeKey { level: e.level as u8, index: e.index },
            leaf: e.kind == LEAF,
        })
        .collect();
    let bad_arrival = |why: String| Error::Store {
        path: plan.store.join(arrival::ARRIVAL_FILE),
        error: StoreError::Arrival { why },
    };
    let starts: HashMap<usize, usize> =
        store.leaf_rank_starts().map_err(bad_arrival)?.into_iter().collect();
    // The ranks of the leaves the new points reach, kept (in the listing's order, each block
    // decoded once); the others are copied a block at a time into the new listing below. All
    // are checked as they are read (a permutation of the store's points) and the check is
    // finished once the new listing is written (an error then leaves the store as it was).
    let check = arrival::RankCheck::new(&arr);
    let mut reached_leaves: Vec<(usize, usize)> =
        reached_ids.iter().filter_map(|id| starts.get(id).map(|&s| (s, *id))).collect();
    reached_leaves.sort_unstable();
    let mut cache: arrival::BlockCache = None;
    let mut old_ranks: HashMap<usize, Vec<u64>> = HashMap::with_capacity(reached_leaves.len());
    for &(s, id) in &reached_leaves {
        let mut v = Vec::with_capacity(store.entries[id].count as usize);
        arr.copy(s..s + store.entries[id].count as usize, &mut cache, &mut v)?;
        check.mark(&v, &arr)?;
        old_ranks.insert(id, v);
    }
    drop(cache);
    crate::cleanup::trace("append in place: reached leaves' ranks read", t0);
    #[allow(clippy::type_complexity)]
    let loaded: Mutex<HashMap<usize, Arc<(Vec<u8>, Vec<u64>)>>> = Mutex::new(HashMap::new());
    let load = |id: usize| -> Result<OldContent> {
        let (raw, seq) =
            codec::decode_ordered(store.node_bytes(id)).map_err(|e| store.damaged(id, e))?;
        let d = node_data(&raw);
        let n = d.header.count as usize;
        if d.header.attr_len as usize != rl - 12 {
            return Err(store.damaged(id, PayloadError::RecordLength));
        }
        let g = d.grid();
        let mut recs = vec![0u8; n * rl];
        for (i, r) in recs.chunks_exact_mut(rl).enumerate() {
            d.record_into(&g, i, r);
        }
        let pos = recs.chunks_exact(rl).map(read_xyz).collect();
        let arrival = match old_ranks.get(&id) {
            Some(r) if r.len() == n => {
                (0..n).map(|i| r[seq.as_ref().map_or(i, |q| q[i] as usize)]).collect()
            }
            Some(r) => {
                return Err(bad_arrival(format!(
                    "leaf {id} holds {n} points, its entry {}",
                    r.len()
                )))
            }
            None if starts.contains_key(&id) => {
                return Err(bad_arrival(format!("no ranks kept for the reached leaf {id}")))
            }
            None => Vec::new(),
        };
        let out = OldContent { pos, arrival: arrival.clone() };
        loaded.lock().expect("not poisoned").insert(id, Arc::new((recs, arrival)));
        Ok(out)
    };
    let tt = Instant::now();
    let patched = patch_tree(root, &old, &new_pos, &new_arrival, &load, plan.config)?;
    let tree_seconds = tt.elapsed().as_secs_f64();
    crate::cleanup::trace("append in place: tree patched", t0);
    let loaded = loaded.into_inner().expect("not poisoned");

    // The new store: the old payload files linked in, the changed payloads coded.
    let tw = Instant::now();
    if plan.work.exists() {
        std::fs::remove_dir_all(&plan.work).map_err(|e| Error::io(&plan.work, e))?;
    }
    let mut writer = StoreWriter::create(&plan.work, &ds.source_meta())?;
    // Removed on an error (a stopped append's work is not worth resuming: it is done again).
    let unfinished = crate::cleanup::TempPath::adopt(plan.work.clone());
    let mut new_record = BuildRecord::of(&ds, &plan.config, &record.engine);
    new_record.write(&plan.work)?;
    for (s, _) in store.covered.iter().enumerate() {
        link_or_copy(
            &plan.store.join(segment_file(s as u32)),
            &plan.work.join(segment_file(s as u32 + 1)),
        )?;
    }
    writer.segments = store.covered.clone();
    writer.group_bytes = super::writer::group_bytes(memory);
    let attr_len = rl - 12;
    let empty = Arc::new((Vec::new(), Vec::new()));
    let mut listed: HashMap<usize, Vec<u64>> = HashMap::new();
    let mut kept = 0u64;
    let mut start = 0;
    while start < patched.len() {
        crate::cleanup::check_interrupted()?;
        let mut end = start;
        let mut bytes = 0u64;
        while end < patched.len() && (end == start || bytes < writer.group_bytes) {
            if let PatchedContent::Leaf { items, .. } | PatchedContent::Inner { items, .. } =
                &patched[end].content
            {
                bytes += payload_len(items.len() as u64, attr_len as u64);
            }
            end += 1;
        }
        #[allow(clippy::type_complexity)]
        let coded: Vec<Option<(NodeEntry, Vec<u8>, Option<Vec<u64>>)>> = patched[start..end]
            .par_iter()
            .map(|n| {
                let (kind, old, items) = match &n.content {
                    PatchedContent::Kept(_) => return Ok(None),
                    PatchedContent::Leaf { old, items } => (LEAF, old, items),
                    PatchedContent::Inner { old, items } => (INNER, old, items),
                };
                let (recs, old_ranks) = &**old.and_then(|o| loaded.get(&o)).unwrap_or(&empty);
                let rec = |i: usize| -> &[u8] {
                    match items[i] {
                        Item::Old(k) => &recs[k as usize * rl..(k as usize + 1) * rl],
                        Item::New(j) => new_rec(j),
                    }
                };
                let (e, b, seq) = codec::encode_payload_ordered(
                    n.key,
                    kind,
                    items.len(),
                    attr_len,
                    |i| read_xyz(rec(i)),
                    |i| color.rgba(rec(i)),
                    |i| &rec(i)[12..],
                    codec::Order::of(root, n.key, &ds.layout),
                )
                .map_err(|error| Error::Payload { path: plan.work.clone(), error })?;
                let ranks = (kind == LEAF).then(|| {
                    // Old points of a leaf are an old leaf's (an inner node's voxels are in no
                    // leaf of the patched tree's making: they are not points of a new leaf).
                    let rank = |i: usize| match items[i] {
                        Item::New(j) => new_arrival[j as usize],
                        Item::Old(k) => old_ranks[k as usize],
                    };
                    match &seq {
                        Some(s) => s.iter().map(|&t| rank(t as usize)).collect(),
                        None => (0..items.len()).map(rank).collect(),
                    }
                });
                Ok(Some((e, b, ranks)))
            })
            .collect::<Result<_>>()?;
        let mut payloads = Vec::new();
        for (id, c) in (start..end).zip(coded) {
            match (c, &patched[id].content) {
                (Some((e, b, ranks)), _) => {
                    if let Some(r) = ranks {
                        listed.insert(id, r);
                    }
                    payloads.push((id, e, b));
                }
                (None, PatchedContent::Kept(o)) => {
                    let e = store.entries[*o];
                    kept += 1;
                    writer.set_entry(id, NodeEntry { segment: e.segment + 1, ..e });
                }
                (None, _) => unreachable!("only kept nodes are not coded"),
            }
        }
        writer.append(payloads, &mut Default::default())?;
        start = end;
    }
    let total = old_n + n_new as u64;
    crate::cleanup::trace("append in place: payloads written", t0);
    writer.write_hierarchy(root, total, plan.config.leaf_capacity, (lo, hi))?;

    // The ranks, leaf by leaf in Morton order of their corners.
    let log2 = root.size_log2 as u32;
    let mut leaves: Vec<(usize, [u32; 3], u64)> = Vec::new();
    for (id, n) in patched.iter().enumerate() {
        let count = match &n.content {
            PatchedContent::Kept(o) if store.entries[*o].kind == LEAF => store.entries[*o].count,
            PatchedContent::Leaf { items, .. } => items.len() as u64,
            _ => continue,
        };
        let shift = log2 - n.key.level as u32;
        leaves.push((id, n.key.index.map(|i| ((i as u64) << shift) as u32), count));
    }
    leaves.sort_unstable_by(|a, b| codec::morton_cmp(a.1, b.1));
    // Runs of the listing: where each leaf's ranks begin, and whence (the store's listing, or
    // the coded leaf's), looked up by position as the file is coded block by block.
    enum Run<'a> {
        /// The store's listing from this place.
        Kept(usize),
        Coded(&'a [u64]),
    }
    let mut runs: Vec<(usize, Run)> = Vec::with_capacity(leaves.len());
    let mut ends: Vec<usize> = Vec::with_capacity(leaves.len());
    let mut at = 0usize;
    for &(id, _, count) in &leaves {
        let run = match &patched[id].content {
            PatchedContent::Kept(o) => Run::Kept(starts[o]),
            _ => Run::Coded(&listed[&id]),
        };
        runs.push((at, run));
        at += count as usize;
        ends.push(at);
    }
    if at as u64 != total {
        return Err(bad_arrival(format!(
            "the extended tree's leaves hold {at} points, not {total}"
        )));
    }
    // Kept leaves come in the store's listing's order: the blocks coded at once read a few
    // consecutive blocks of it, each decoded once.
    let shared = arrival::SharedBlocks::new(&arr, at_once as usize + 2);
    let fill = |r: std::ops::Range<usize>, out: &mut Vec<u64>| {
        let mut k = runs.partition_point(|run| run.0 <= r.start) - 1;
        let mut i = r.start;
        while i < r.end {
            let (start, run) = &runs[k];
            let take = ends[k].min(r.end) - i;
            match run {
                Run::Kept(from) => {
                    let s = from + (i - start);
                    let had = out.len();
                    shared.copy(s..s + take, out)?;
                    check.mark(&out[had..], &arr)?;
                }
                Run::Coded(ranks) => out.extend_from_slice(&ranks[i - start..i - start + take]),
            }
            i += take;
            k += 1;
        }
        Ok(())
    };
    arrival::write_blocks(&plan.work, at, fill, declared, colors, at_once as usize)?;
    check.finish(&arr)?;
    crate::cleanup::trace("append in place: ranks written", t0);
    new_record.complete = true;
    new_record.write(&plan.work)?;
    unfinished.keep();
    let write_seconds = tw.elapsed().as_secs_f64();

    let leaf_count = leaves.len() as u64;
    let voxels = patched
        .iter()
        .map(|n| match &n.content {
            PatchedContent::Inner { items, .. } => items.len() as u64,
            PatchedContent::Kept(o) if store.entries[*o].kind != LEAF => store.entries[*o].count,
            _ => 0,
        })
        .sum();
    Ok(InPlace::Done(Box::new(BuildReport {
        // The store's engine, as `build.json` keeps it (a build of all inputs by it would record
        // it; only the sorted, partitioned and GPU engines keep the ranks this needs).
        engine: [BuiltBy::Gpu, BuiltBy::Partitioned]
            .into_iter()
            .find(|e| record.engine == e.name())
            .unwrap_or(BuiltBy::Sorted),
        points: total,
        nodes: patched.len() as u64,
        leaves: leaf_count,
        voxels,
        commits: writer.commits(),
        nodes_bytes: writer.nodes_len,
        read_seconds,
        tree_seconds,
        write_seconds,
        seconds: t0.elapsed().as_secs_f64(),
        kept_nodes: kept,
        warnings,
        ..BuildReport::default()
    })))
}

/// Hard-links `from` to `to`, or copies it where the file system cannot link.
fn link_or_copy(from: &Path, to: &Path) -> Result<()> {
    if std::fs::hard_link(from, to).is_ok() {
        return Ok(());
    }
    std::fs::copy(from, to).map(|_| ()).map_err(|e| Error::io(to, e))
}
