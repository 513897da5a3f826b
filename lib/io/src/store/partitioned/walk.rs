//! Pass 2 of the partitioned engine, the walk: the tree's top visited depth first from the root
//! (or from a distributed job's subtrees), each node a unit built at once, an inner node made
//! from its children's candidates, or a cell denser than a unit ([`dense`]); every finished
//! visit logged for `--resume`.

use super::checksum::{checksum, checksum_at, RankHash};
use super::log::{log_record, Logged, LOG};
use super::partition::cell_depth;
use super::ranks::RankLog;
use super::unit::{read_unit, unit_bytes_per_point};
use crate::dataset::Dataset;
use crate::error::{Error, Result};
use crate::store::arrival::{ColorMaxima, DeclaredBox};
use crate::store::codec::{CodedOrder, Order};
use crate::store::dense::{self, Level};
use crate::store::format::*;
use crate::store::options::{BuildOptions, BuildReport};
use crate::store::runs::{Cands, Run};
use crate::store::writer::*;
use mortar_core::color::ColorSource;
use mortar_core::layout::read_xyz;
use mortar_core::octree::{build_subtree, splits, Cube, NodeKey, SortedContent};
use rayon::prelude::*;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The depth-first walk over the tree's top (pass 2).
pub(super) struct Walk<'a, 'w> {
    pub(super) ds: &'a Dataset,
    pub(super) writer: &'w mut StoreWriter,
    pub(super) opts: &'a BuildOptions,
    pub(super) root: Cube,
    pub(super) unit_points: u64,
    pub(super) color: ColorSource,
    pub(super) rl: usize,
    /// (level, depth-first number, entry) of every node written.
    pub(super) entries: Vec<(u32, u64, NodeEntry)>,
    pub(super) seq: u64,
    pub(super) points: u64,
    pub(super) report: &'a mut BuildReport,
    /// Visits a stopped build finished, by key (`--resume`).
    pub(super) replay: std::collections::HashMap<(u32, [u32; 3]), Logged>,
    /// The log of finished visits.
    pub(super) log: std::fs::File,
    pub(super) log_path: PathBuf,
    /// [`checksum`] of each payload in `entries`.
    pub(super) hashes: Vec<u64>,
    /// Where finer partitions of dense cells go.
    pub(super) state: PathBuf,
    /// Provisional commits as visits finish ([`super::preview`]); none for a distributed job.
    pub(super) preview: Option<super::preview::Preview>,
    /// The integer bounds of every point (pass 1).
    pub(super) bounds: ([i32; 3], [i32; 3]),
    /// The leaves' arrival ranks as they are written (`None`: none kept).
    pub(super) ranks: Option<RankLog>,
}

impl Walk<'_, '_> {
    /// Builds the node `key` (cube `cube`, at `depth`, over the cells `cells` of `lv`) and
    /// everything under it; returns its candidates for its parent.
    pub(super) fn visit(
        &mut self,
        lv: &Level,
        key: NodeKey,
        cube: Cube,
        depth: u8,
        cells: std::ops::Range<usize>,
    ) -> Result<Cands> {
        crate::cleanup::check_interrupted()?;
        if let Some(l) = self.replay.remove(&(key.level as u32, key.index)) {
            self.seq = l.seq_after;
            return Ok(l.cands);
        }
        let count: u64 = lv.hist[cells.clone()].iter().sum();
        if depth == lv.depth || count <= self.unit_points {
            if count > self.unit_points {
                return self.dense(lv, key, cube, cells, count, None);
            }
            let before = self.entries.len();
            let points_before = self.points;
            let out = self.unit(lv, key, cube, cells, count)?;
            self.logged(key, before, self.points - points_before, &out)?;
            return Ok(out);
        }
        // More points than a unit, so more than a leaf, in a cube that may split: inner.
        let step = cells.len() / 8;
        self.inner(key, cube, |w, o| {
            w.visit(
                lv,
                key.child(o),
                cube.child(o),
                depth + 1,
                cells.start + o * step..cells.start + (o + 1) * step,
            )
        })
    }

    /// Builds the inner node `key` (cube `cube`) whose children `kid(o)` builds; returns its
    /// candidates for its parent.
    fn inner(
        &mut self,
        key: NodeKey,
        cube: Cube,
        mut kid: impl FnMut(&mut Self, usize) -> Result<Cands>,
    ) -> Result<Cands> {
        let seq = self.seq;
        self.seq += 1;
        let mut voxels = Cands::default();
        for o in 0..8 {
            let c = kid(self, o)?;
            voxels.append(c);
        }
        let rl = self.rl;
        let color = &self.color;
        let (e, b) = crate::store::codec::encode_payload(
            key,
            INNER,
            voxels.pos.len(),
            rl - 12,
            |i| voxels.pos[i],
            |i| color.rgba(&voxels.records[i * rl..(i + 1) * rl]),
            |i| &voxels.records[i * rl + 12..(i + 1) * rl],
            Order::of(self.root, key, &self.ds.layout),
        )
        .map_err(|error| Error::Payload { path: self.writer.dir.clone(), error })?;
        let before = self.entries.len();
        self.put(seq, e, &b)?;
        let out = voxels.pick(&voxels.for_parent(key, cube), rl);
        if key.level > 0 {
            self.logged(key, before, 0, &out)?;
        }
        Ok(out)
    }

    /// Builds the node `key` over the `count` points of `cells` of `lv`, more than a unit holds
    /// (bounds `known` where known): see [`dense`].
    fn dense(
        &mut self,
        lv: &Level,
        key: NodeKey,
        cube: Cube,
        cells: std::ops::Range<usize>,
        count: u64,
        known: Option<dense::Bounds>,
    ) -> Result<Cands> {
        let rl = self.rl;
        let block = dense::block_points(self.opts.memory, rl);
        let b = match known {
            Some(b) => b,
            None => lv.bounds(&cells, rl, block)?,
        };
        if splits(count, key, cube, &self.opts.config) {
            if let Some(o) = dense::one_octant(cube, b) {
                let c0 = cells.start;
                return self.inner(key, cube, |w, k| {
                    if k == o {
                        w.dense(lv, key.child(o), cube.child(o), cells.clone(), count, Some(b))
                    } else {
                        w.visit(lv, key.child(k), cube.child(k), key.level + 1, c0..c0)
                    }
                });
            }
            let d = dense::tree_split_depth(key, cube, self.opts.config.max_level);
            let sub = dense::split(&lv.runs, cells, rl, cube, key.level, d, block, &self.state)?;
            self.report.dense_cells += 1;
            let n = sub.hist.len();
            return self.visit(&sub, key, cube, key.level, 0..n);
        }
        // A leaf larger than a unit.
        let before = self.entries.len();
        let leaf = dense::big_leaf(
            lv,
            cells,
            count,
            key,
            cube,
            b,
            rl,
            self.unit_points,
            block,
            &self.state,
        )?;
        self.report.large_leaves += 1;
        let seq = self.seq;
        self.seq += 1;
        let tw = Instant::now();
        let attr_len = rl - 12;
        if payload_len(count, attr_len as u64) <= crate::store::codec::CODE_LIMIT {
            // Small enough to be coded, as the sorted engine codes it: in memory.
            let (recs, mut arr) = leaf.read(0..count, self.ranks.is_some())?;
            let rec = |i: usize| &recs[i * rl..(i + 1) * rl];
            let (e, b, coded) = crate::store::codec::encode_payload_ordered(
                key,
                LEAF,
                count as usize,
                attr_len,
                |i| read_xyz(rec(i)),
                |i| self.color.rgba(rec(i)),
                |i| &rec(i)[12..],
                Order::of(self.root, key, &self.ds.layout),
            )
            .map_err(|error| Error::Payload { path: self.writer.dir.clone(), error })?;
            drop(recs);
            if let Some(rk) = self.ranks.as_mut() {
                if let Some(o) = coded {
                    arr = o.iter().map(|&i| arr[i as usize]).collect();
                }
                rk.push(&mut arr)?;
            }
            self.put(seq, e, &b)?;
            self.points += count;
            self.ds.progress.add(count);
            self.report.write_seconds += tw.elapsed().as_secs_f64();
            let out = leaf.cands;
            self.logged(key, before, count, &out)?;
            return Ok(out);
        }
        let off = self.writer.reserve(&[payload_len(count, attr_len as u64)])[0];
        let slice = (self.writer.group_bytes / (16 + attr_len as u64)).max(1) as usize;
        let (w, color) = (&*self.writer, &self.color);
        let r = write_payload_blocks(
            key,
            LEAF,
            count as usize,
            attr_len,
            leaf.bounds,
            slice,
            |r| leaf.read(r.start as u64..r.end as u64, false).map(|x| x.0),
            |rec| color.rgba(rec),
            |at, bytes| w.write_at(off + at, bytes),
        )?;
        let mut e = r.map_err(|error| Error::Payload { path: w.dir.clone(), error })?;
        e.offset = off;
        let h = checksum_at(w, off, e.length)?;
        // Raw: its points in the leaf's order, read again for their ranks a slice at a time.
        if let Some(rk) = self.ranks.as_mut() {
            let mut at = 0;
            while at < count {
                let end = (at + slice as u64).min(count);
                rk.push(&mut leaf.read(at..end, true)?.1)?;
                at = end;
            }
        }
        self.entries.push((e.level, seq, e));
        self.hashes.push(h);
        self.points += count;
        self.ds.progress.add(count);
        self.report.write_seconds += tw.elapsed().as_secs_f64();
        let out = leaf.cands;
        self.logged(key, before, count, &out)?;
        Ok(out)
    }

    /// Logs a finished visit (its entries from `before` on). Not synced: see the module docs.
    fn logged(&mut self, key: NodeKey, before: usize, points: u64, out: &Cands) -> Result<()> {
        let ranks_hash =
            self.ranks.as_mut().map_or(RankHash::default().finish(), |r| r.take_hash());
        let rec = log_record(
            key,
            self.seq,
            points,
            ranks_hash,
            self.writer.nodes_len,
            &self.entries[before..],
            &self.hashes[before..],
            out,
            self.rl,
        );
        self.log.write_all(&rec).map_err(|e| Error::io(&self.log_path, e))?;
        if let Some(pv) = self.preview.as_mut().filter(|p| p.due()) {
            let done: Vec<NodeEntry> = self.entries.iter().map(|&(_, _, e)| e).collect();
            pv.commit(self.writer, self.root, &done, self.points, Some(self.bounds))?;
        }
        Ok(())
    }

    /// Writes one payload at the end of `nodes.bin` and keeps its entry.
    fn put(&mut self, seq: u64, mut e: NodeEntry, bytes: &[u8]) -> Result<()> {
        let off = self.writer.reserve(&[bytes.len() as u64])[0];
        self.writer.write_at(off, bytes)?;
        e.offset = off;
        self.entries.push((e.level, seq, e));
        self.hashes.push(checksum(bytes));
        Ok(())
    }

    /// Reads the points of `cells` back, sorts them and builds their subtree.
    fn unit(
        &mut self,
        lv: &Level,
        key: NodeKey,
        cube: Cube,
        cells: std::ops::Range<usize>,
        count: u64,
    ) -> Result<Cands> {
        let rl = self.rl;
        let n = count as usize;
        let ts = Instant::now();
        let mut sorted = read_unit(&lv.runs, self.root, key, cells, count, rl, &self.writer.dir)?;
        self.ds.progress.add(count);
        self.report.sort_seconds += ts.elapsed().as_secs_f64();
        let tt = Instant::now();
        let pos = |i: usize| read_xyz(sorted.record(i));
        let arr = |i: usize| sorted.arrival[i];
        let sub = build_subtree(key, cube, n, &pos, &arr, self.opts.config)
            .map_err(|error| Error::Octree { error })?;
        self.report.tree_seconds += tt.elapsed().as_secs_f64();
        let tw = Instant::now();
        let base = self.seq;
        self.seq += sub.nodes.len() as u64;
        let attr_len = rl - 12;
        let dir = self.writer.dir.clone();
        let color = &self.color;
        let root = self.root;
        // The coded order of each leaf coded in another order than its records' (codec 2).
        let mut orders: Vec<(usize, Vec<u32>)> = Vec::new();
        let mut start = 0;
        while start < sub.nodes.len() {
            let mut end = start;
            let mut bytes = 0u64;
            while end < sub.nodes.len() && (end == start || bytes < self.writer.group_bytes) {
                bytes += payload_len(sub.nodes[end].count() as u64, attr_len as u64);
                end += 1;
            }
            // Coded lengths are known once encoded: encode (in parallel), place, then write
            // (nodes too large to encode in memory are written raw, in slices, in place).
            let group = self.writer.group_bytes.max(crate::store::codec::CODE_LIMIT);
            let big = |i: usize| payload_len(sub.nodes[i].count() as u64, attr_len as u64) > group;
            let coded: Vec<Option<(NodeEntry, Vec<u8>, CodedOrder)>> = (start..end)
                .into_par_iter()
                .map(|i| {
                    if big(i) {
                        return Ok(None);
                    }
                    let nd = &sub.nodes[i];
                    let (kind, idx): (u32, Box<dyn Fn(usize) -> usize + Sync>) = match &nd.content {
                        SortedContent::Leaf(r) => {
                            let s = r.start;
                            (LEAF, Box::new(move |i| s + i))
                        }
                        SortedContent::Inner(v) => (INNER, Box::new(move |i| v[i] as usize)),
                    };
                    crate::store::codec::encode_payload_ordered(
                        nd.key,
                        kind,
                        nd.count(),
                        attr_len,
                        |i| read_xyz(sorted.record(idx(i))),
                        |i| color.rgba(sorted.record(idx(i))),
                        |i| &sorted.record(idx(i))[12..],
                        Order::of(root, nd.key, &self.ds.layout),
                    )
                    .map(|(e, b, o)| Some((e, b, if kind == LEAF { o } else { None })))
                    .map_err(|error| Error::Payload { path: dir.clone(), error })
                })
                .collect::<Result<_>>()?;
            let lens: Vec<u64> = (start..end)
                .zip(&coded)
                .map(|(i, c)| match c {
                    Some((_, b, _)) => b.len() as u64,
                    None => payload_len(sub.nodes[i].count() as u64, attr_len as u64),
                })
                .collect();
            let offsets = self.writer.reserve(&lens);
            let w = &*self.writer;
            let coded: Vec<Option<(NodeEntry, Vec<u8>)>> = (start..end)
                .zip(coded)
                .map(|(i, c)| {
                    c.map(|(e, b, o)| {
                        if let (Some(o), SortedContent::Leaf(r)) = (o, &sub.nodes[i].content) {
                            orders.push((r.start, o));
                        }
                        (e, b)
                    })
                })
                .collect();
            let done: Vec<(NodeEntry, u64)> = (start..end)
                .into_par_iter()
                .zip(coded.into_par_iter())
                .zip(offsets.into_par_iter())
                .map(|((i, c), off)| match c {
                    None => {
                        let mut e = crate::store::engine::write_sliced(
                            w,
                            off,
                            &sub.nodes[i],
                            attr_len,
                            &sorted,
                            color,
                        )?;
                        e.offset = off;
                        Ok((e, checksum_at(w, off, e.length)?))
                    }
                    Some((mut e, b)) => {
                        w.write_at(off, &b)?;
                        e.offset = off;
                        Ok((e, checksum(&b)))
                    }
                })
                .collect::<Result<_>>()?;
            for (i, (e, h)) in (start..end).zip(done) {
                self.entries.push((e.level, base + i as u64, e));
                self.hashes.push(h);
            }
            start = end;
        }
        self.points +=
            sub.nodes.iter().filter(|x| x.is_leaf()).map(|x| x.count() as u64).sum::<u64>();
        self.report.write_seconds += tw.elapsed().as_secs_f64();
        let mut out = Cands::default();
        for &i in &sub.candidates {
            let r = sorted.record(i as usize);
            out.push(read_xyz(r), sorted.arrival[i as usize], r);
        }
        if let Some(rk) = self.ranks.as_mut() {
            // The leaves' arrival numbers in their coded order, the leaves in Morton order.
            let mut leaves: Vec<std::ops::Range<usize>> = sub
                .nodes
                .iter()
                .filter_map(|x| match &x.content {
                    SortedContent::Leaf(r) => Some(r.clone()),
                    SortedContent::Inner(_) => None,
                })
                .collect();
            leaves.sort_by_key(|r| r.start);
            orders.sort_by_key(|o| o.0);
            let mut rest: &mut [u64] = &mut sorted.arrival;
            let mut done = 0;
            let mut runs: Vec<(&mut [u64], Vec<u32>)> = Vec::with_capacity(orders.len());
            for (at, o) in orders {
                let len = o.len();
                let (_, tail) = std::mem::take(&mut rest).split_at_mut(at - done);
                let (run, tail) = tail.split_at_mut(len);
                runs.push((run, o));
                rest = tail;
                done = at + len;
            }
            runs.into_par_iter().for_each(|(run, o)| {
                let tmp: Vec<u64> = o.iter().map(|&i| run[i as usize]).collect();
                run.copy_from_slice(&tmp);
            });
            for r in leaves {
                rk.push(&mut sorted.arrival[r])?;
            }
        }
        Ok(out)
    }
}

/// The nodes a distributed job wrote: (level, depth-first number, entry) of each, the
/// candidates of each unit for its parent, and the points in the leaves.
pub(crate) type Units = (Vec<(u32, u64, NodeEntry)>, Vec<Cands>, u64);

/// Builds the subtrees `units` (key, cube, partition cells) from the runs into `writer`, each
/// as the partitioned engine builds a node and everything under it, with `color` for the
/// payloads. With `arrival` (a directory, the inputs' declared box and colour maxima), the
/// leaves' arrival ranks (among all of `ds`'s records) are written there as an `arrival.bin`
/// listing the units' leaves in the order of `units`, each unit's as the partitioned engine
/// lists them.
#[allow(clippy::too_many_arguments)]
pub(crate) fn build_units(
    ds: &Dataset,
    writer: &mut StoreWriter,
    config: mortar_core::octree::BuilderConfig,
    memory: u64,
    root: Cube,
    runs: &[Run],
    hist: &[u64],
    units: &[(NodeKey, Cube, std::ops::Range<usize>)],
    color: ColorSource,
    state: &Path,
    arrival: Option<(&Path, DeclaredBox, ColorMaxima)>,
) -> Result<Units> {
    let rl = ds.layout.record_len;
    let opts = BuildOptions {
        config,
        batch_points: 0,
        commit_every: f64::INFINITY,
        first_commit_after: None,
        memory,
        engine: crate::store::options::Engine::Partitioned,
        resume: false,
        tree: None,
    };
    let unit_points =
        ((memory / 2) / unit_bytes_per_point(rl as u64)).max(config.leaf_capacity as u64 + 1);
    let log_path = state.join(LOG);
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .map_err(|e| Error::io(&log_path, e))?;
    let mut report = BuildReport::default();
    let depth = cell_depth(root, config.max_level);
    let lv = Level::new(runs.to_vec(), hist.to_vec(), depth);
    let ranks = match arrival {
        Some(_) => Some(RankLog::open(state, ds.pieces().iter().map(|p| p.piece.points), 0)?),
        None => None,
    };
    let mut w = Walk {
        ds,
        writer,
        opts: &opts,
        root,
        unit_points,
        color,
        rl,
        entries: Vec::new(),
        hashes: Vec::new(),
        seq: 0,
        points: 0,
        report: &mut report,
        replay: Default::default(),
        log,
        log_path,
        state: state.to_path_buf(),
        preview: None,
        bounds: ([0; 3], [0; 3]),
        ranks,
    };
    let mut cands = Vec::with_capacity(units.len());
    for (key, cube, cells) in units {
        // An empty subtree too: it is an empty leaf where its parent is inner.
        cands.push(w.visit(&lv, *key, *cube, key.level, cells.clone())?);
    }
    let Walk { entries, points, ranks, .. } = w;
    if let (Some(rk), Some((dir, declared, colors))) = (ranks, arrival) {
        rk.write_arrival(dir, points, declared, colors, memory)?;
    }
    Ok((entries, cands, points))
}
