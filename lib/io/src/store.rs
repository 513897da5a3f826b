//! The octree LOD store (paper 004 on disk): `mortar build` writes it, `info`, `sort` and `batch`
//! read it. Layout in `lib/io/STORE_FORMAT.md`.
//!
//! A directory that can be read while it grows:
//!
//! - `source.las`: the LAS header, VLRs and EVLRs of the source (no points), written once, so the
//!   points go back to LAS with every field and record;
//! - `nodes.bin`: node payloads, append-only. A payload is a variable-size batch in the quantized
//!   layout of the batch file (paper 003 §3.5): coarse, medium and fine words relative to the
//!   node's integer bounds, RGBA8 colours, and for leaves the rest of every original record
//!   (all bytes after X, Y, Z), so leaves keep every attribute exactly. A node that changes is
//!   appended again; the hierarchy points at its newest version;
//! - `hierarchy.bin`: one entry per node (key, kind, count, payload offset and length) and the
//!   length of `nodes.bin` it covers, replaced atomically at each commit (payloads written and
//!   synced first, then a new hierarchy written, synced and renamed over the old one). A reader
//!   that opens the directory at any moment sees the last commit; a crash or Ctrl-C leaves it.
//!
//! Memory: the input is read piece by piece, never whole. After each commit the builder pages
//! out the points of every leaf (they are in `nodes.bin` now) and the records of the points added
//! since the last commit are dropped; a leaf that must split later gets its points back from its
//! last payload. So what is held is the inner nodes' voxels, the hierarchy and the points of one
//! commit interval: a commit is also made when those exceed a third of `--memory`.
//!
//! Not done yet: old versions of changed nodes stay in `nodes.bin` (no compaction): a leaf that
//! receives points in many commit intervals is rewritten whole each time, so `nodes.bin` grows
//! with input order as much as with input size (measured in BENCHMARKS.md).

use crate::cleanup::TempPath;
use crate::dataset::{Dataset, RecordSource, SourceMeta};
use crate::error::{Error, Result};
use crate::las::{self, Header, HeaderOut, Vlr};
use crate::source::{LasInput, Piece};
use memmap2::Mmap;
use mortar_core::color::{ColorSource, RgbDepth};
use mortar_core::layout::RecordLayout;
use mortar_core::octree::{Builder, BuilderConfig, Cube, NodeId, NodeView, OctreeError, Payload, Point, Snapshot};
use mortar_core::quantize::BatchGrid;
use rayon::prelude::*;
use std::borrow::Cow;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The source's LAS header, VLRs and EVLRs (no points).
pub const SOURCE_FILE: &str = "source.las";
/// Node payloads, append-only.
pub const NODES_FILE: &str = "nodes.bin";
/// The committed hierarchy.
pub const HIERARCHY_FILE: &str = "hierarchy.bin";

const NODE_MAGIC: [u8; 8] = *b"MORTNODE";
const HIERARCHY_MAGIC: [u8; 8] = *b"MORTHIER";
/// Version 2: inner nodes' voxels are real source points with their records (version 1 stored
/// cell centres and colours only).
const VERSION: u32 = 2;

/// Node kinds.
pub const LEAF: u32 = 0;
/// An inner node (voxels).
pub const INNER: u32 = 1;

/// The header of one node payload in `nodes.bin` (64 bytes, little-endian).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct NodeHeader {
    /// `MORTNODE`.
    pub magic: [u8; 8],
    /// Octree level (0: root).
    pub level: u32,
    /// [`LEAF`] or [`INNER`].
    pub kind: u32,
    /// Position of the node's cube among the cubes of its level.
    pub index: [u32; 3],
    /// Points (leaf) or voxels (inner node).
    pub count: u32,
    /// Integer minimum of the quantization frame.
    pub min: [i32; 3],
    /// Bits per axis of the quantization frame (three used).
    pub bits: [u8; 4],
    /// Bytes of attributes per point after the colours (record length - 12 for leaves, 0 for
    /// inner nodes).
    pub attr_len: u32,
    /// Zero.
    pub _pad: [u32; 3],
}

const _: () = assert!(std::mem::size_of::<NodeHeader>() == 64);

/// The header of `hierarchy.bin` (80 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct HierarchyHeader {
    /// `MORTHIER`.
    pub magic: [u8; 8],
    /// Format version (1).
    pub version: u32,
    /// Bytes per [`NodeEntry`] (48).
    pub entry_size: u32,
    /// Commit number, from 1.
    pub commit: u64,
    /// Number of node entries that follow.
    pub node_count: u64,
    /// Bytes of `nodes.bin` this commit covers.
    pub nodes_len: u64,
    /// Points in the leaves.
    pub points: u64,
    /// The root cube's integer minimum.
    pub root_min: [i64; 3],
    /// log2 of the root cube's edge.
    pub root_size_log2: u32,
    /// Leaf capacity the builder used.
    pub leaf_capacity: u32,
    /// Smallest integer coordinate of the points (LAS grid).
    pub min: [i32; 3],
    /// Largest integer coordinate of the points.
    pub max: [i32; 3],
}

const _: () = assert!(std::mem::size_of::<HierarchyHeader>() == 104);

/// Bytes of the hierarchy header.
const HIERARCHY_HEADER: usize = std::mem::size_of::<HierarchyHeader>();

/// One node of the hierarchy (48 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct NodeEntry {
    /// Octree level.
    pub level: u32,
    /// [`LEAF`] or [`INNER`].
    pub kind: u32,
    /// Cube index at its level.
    pub index: [u32; 3],
    /// Zero.
    pub _pad: u32,
    /// Points or voxels.
    pub count: u64,
    /// Offset of the payload ([`NodeHeader`] first) in `nodes.bin`.
    pub offset: u64,
    /// Bytes of the payload.
    pub length: u64,
}

const _: () = assert!(std::mem::size_of::<NodeEntry>() == 48);

fn payload_len(count: u64, attr_len: u64) -> u64 {
    let raw = 64 + count * (16 + attr_len);
    raw.next_multiple_of(8)
}

/// The XYZ of a record (i32 at bytes 0, 4, 8).
fn read_xyz(r: &[u8]) -> [i32; 3] {
    [0, 4, 8].map(|o| i32::from_le_bytes([r[o], r[o + 1], r[o + 2], r[o + 3]]))
}

/// What a commit wrote.
#[derive(Clone, Copy, Debug, Default)]
pub struct CommitStats {
    /// Nodes (re)written.
    pub nodes_written: u64,
    /// Bytes appended to `nodes.bin`.
    pub bytes: u64,
}

/// Writes a store: payloads of changed nodes, then an atomic hierarchy commit.
pub struct StoreWriter {
    dir: PathBuf,
    nodes: File,
    /// `nodes.bin` opened for reading old payloads back.
    reader: File,
    nodes_len: u64,
    entries: Vec<Option<NodeEntry>>,
    commit: u64,
    last_revision: Option<u64>,
    record_len: usize,
    /// Registered for removal until the first commit.
    guard: Option<TempPath>,
}

impl StoreWriter {
    /// Creates the store directory `dir` (which must not exist, or be empty) with the source's
    /// metadata.
    pub fn create(dir: &Path, meta: &SourceMeta) -> Result<StoreWriter> {
        if dir.exists() {
            let empty = dir.is_dir() && std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?.next().is_none();
            if !empty {
                return Err(Error::input(dir, "exists and is not an empty directory; give a new directory for the store"));
            }
        } else {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        }
        let guard = TempPath::adopt(dir.to_path_buf());
        // source.las: header, VLRs, EVLRs, no points.
        let g = &meta.grid;
        let h = HeaderOut {
            template: &meta.header,
            point_format: meta.layout.format,
            compressed: false,
            record_len: meta.layout.record_len as u16,
            point_count: 0,
            points_by_return: [0; 15],
            scale: g.scale,
            offset: g.offset,
            min: [0.0; 3],
            max: [0.0; 3],
            vlrs: &meta.vlrs,
            evlr_start: 0,
            evlr_count: 0,
        };
        let mut bytes = las::write_header(&h).map_err(|e| Error::input(dir, e))?;
        if !meta.evlrs.is_empty() {
            let start = bytes.len() as u64;
            let h = HeaderOut { evlr_start: start, evlr_count: meta.evlrs.len() as u32, ..h };
            bytes = las::write_header(&h).map_err(|e| Error::input(dir, e))?;
            bytes.extend_from_slice(&las::write_evlrs(&meta.evlrs));
        }
        let src = dir.join(SOURCE_FILE);
        std::fs::write(&src, &bytes).map_err(|e| Error::io(&src, e))?;
        let np = dir.join(NODES_FILE);
        let nodes = File::create(&np).map_err(|e| Error::io(&np, e))?;
        let reader = File::open(&np).map_err(|e| Error::io(&np, e))?;
        Ok(StoreWriter {
            dir: dir.to_path_buf(),
            nodes,
            reader,
            nodes_len: 0,
            entries: Vec::new(),
            commit: 0,
            last_revision: None,
            record_len: meta.layout.record_len,
            guard: Some(guard),
        })
    }

    /// Commits: appends the payloads of the nodes changed since the last commit, syncs them, then
    /// replaces the hierarchy atomically. `record(h)` returns the full record of the point whose
    /// [`Point::record`] is `h`. A changed leaf with paged-out points ([`NodeView::paged_points`])
    /// is written whole: its last payload is read back and the new points appended. Payloads are
    /// encoded in parallel in groups of at most [`COMMIT_GROUP_BYTES`], so a commit needs little
    /// memory beyond the nodes themselves. `bounds` are the integer bounds of the points so far.
    pub fn commit<'r>(&mut self, snap: &Snapshot, bounds: ([i32; 3], [i32; 3]), record: &(dyn Fn(u64) -> &'r [u8] + Sync)) -> Result<CommitStats> {
        let changed: Vec<(usize, &NodeView)> = match self.last_revision {
            None => snap.iter().map(|(id, n)| (id.index(), n)).collect(),
            Some(rev) => snap.changed_since(rev).map(|(id, n)| (id.index(), n)).collect(),
        };
        let attr_len = self.record_len as u64 - 12;
        let mut stats = CommitStats::default();
        let mut start = 0;
        while start < changed.len() {
            let mut end = start;
            let mut bytes = 0u64;
            while end < changed.len() && (end == start || bytes < COMMIT_GROUP_BYTES) {
                let n = changed[end].1;
                bytes += payload_len(n.total_points() + n.voxel_count(), attr_len);
                end += 1;
            }
            self.write_group(&changed[start..end], record, &mut stats)?;
            start = end;
        }
        let np = self.dir.join(NODES_FILE);
        self.nodes.sync_data().map_err(|e| Error::io(&np, e))?;
        self.commit += 1;
        // Keys move when the root grows (a new root above the old one): the entries of nodes not
        // written again take their current keys (the payload keeps the key it was written with).
        for (id, n) in snap.iter() {
            if let Some(Some(e)) = self.entries.get_mut(id.index()) {
                let k = n.key();
                e.level = k.level as u32;
                e.index = k.index;
            }
        }
        let root = snap.root_cube();
        let entries: Vec<NodeEntry> = self.entries.iter().flatten().copied().collect();
        let header = HierarchyHeader {
            magic: HIERARCHY_MAGIC,
            version: VERSION,
            entry_size: std::mem::size_of::<NodeEntry>() as u32,
            commit: self.commit,
            node_count: entries.len() as u64,
            nodes_len: self.nodes_len,
            points: snap.total_points(),
            root_min: root.min,
            root_size_log2: root.size_log2 as u32,
            leaf_capacity: snap.config().leaf_capacity,
            min: bounds.0,
            max: bounds.1,
        };
        let mut bytes = bytemuck::bytes_of(&header).to_vec();
        bytes.extend_from_slice(bytemuck::cast_slice(&entries));
        let hp = self.dir.join(HIERARCHY_FILE);
        let tmp = self.dir.join(format!("{HIERARCHY_FILE}.tmp"));
        {
            let mut f = File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
            f.write_all(&bytes).map_err(|e| Error::io(&tmp, e))?;
            f.sync_all().map_err(|e| Error::io(&tmp, e))?;
        }
        std::fs::rename(&tmp, &hp).map_err(|e| Error::io(&hp, e))?;
        if let Ok(d) = File::open(&self.dir) {
            let _ = d.sync_all();
        }
        self.last_revision = Some(snap.revision());
        // From the first commit on, the directory is a readable store: Ctrl-C leaves it.
        if let Some(g) = self.guard.take() {
            g.keep();
        }
        Ok(stats)
    }

    /// Commits made.
    pub fn commits(&self) -> u64 {
        self.commit
    }

    /// Encodes `nodes` in parallel and appends them in order.
    fn write_group<'r>(&mut self, nodes: &[(usize, &NodeView)], record: &(dyn Fn(u64) -> &'r [u8] + Sync), stats: &mut CommitStats) -> Result<()> {
        let record_len = self.record_len;
        let this = &*self;
        let payloads: Vec<(usize, NodeEntry, Vec<u8>)> = nodes
            .par_iter()
            .map(|&(id, n)| {
                let kept = n.paged_points() + n.saved_voxels();
                let old = if kept > 0 { Some(this.read_payload(id, Some(kept))?) } else { None };
                encode_node(n, old.as_deref(), record_len, record).map(|(e, b)| (id, e, b)).map_err(|m| Error::input(&this.dir, m))
            })
            .collect::<Result<_>>()?;
        let np = self.dir.join(NODES_FILE);
        let mut w = std::io::BufWriter::with_capacity(8 << 20, &self.nodes);
        for (id, mut entry, bytes) in payloads {
            entry.offset = self.nodes_len;
            w.write_all(&bytes).map_err(|e| Error::io(&np, e))?;
            self.nodes_len += bytes.len() as u64;
            stats.bytes += bytes.len() as u64;
            stats.nodes_written += 1;
            if self.entries.len() <= id {
                self.entries.resize(id + 1, None);
            }
            self.entries[id] = Some(entry);
        }
        w.flush().map_err(|e| Error::io(&np, e))?;
        Ok(())
    }

    /// The last written payload of node `id`, which must hold `count` points or voxels.
    fn read_payload(&self, id: usize, count: Option<u64>) -> Result<Vec<u8>> {
        use std::os::unix::fs::FileExt;
        let np = self.dir.join(NODES_FILE);
        let e = self.entries.get(id).copied().flatten().ok_or_else(|| Error::input(&np, format!("node {id} has saved points but no payload")))?;
        if count.is_some_and(|c| c != e.count) {
            return Err(Error::input(&np, format!("node {id}: the last payload holds {} points, {count:?} were saved", e.count)));
        }
        let mut buf = vec![0u8; e.length as usize];
        self.reader.read_exact_at(&mut buf, e.offset).map_err(|err| Error::io(&np, err))?;
        Ok(buf)
    }

    /// The paged-out points of leaf `id` (`count` of them, if given), read back from its last
    /// payload for a split, or the saved voxels of inner node `id` (for a root that grows): their
    /// full records are appended to `records` and each point's [`Point::record`] is
    /// `PAGED | index` of its record there.
    pub fn page_in(&self, id: usize, count: Option<u64>, records: &std::sync::Mutex<Vec<u8>>) -> Result<Vec<Point>> {
        let buf = self.read_payload(id, count)?;
        let leaf = DecodedLeaf::parse(&buf).map_err(|m| Error::input(self.dir.join(NODES_FILE), format!("node {id}: {m}")))?;
        let rl = self.record_len;
        let mut recs = vec![0u8; leaf.count * rl];
        for (i, r) in recs.chunks_exact_mut(rl).enumerate() {
            let p = leaf.position(i);
            for a in 0..3 {
                r[4 * a..4 * a + 4].copy_from_slice(&p[a].to_le_bytes());
            }
            r[12..].copy_from_slice(leaf.attributes(i));
        }
        let mut all = records.lock().map_err(|_| Error::Usage("a page-in thread panicked".into()))?;
        let base = (all.len() / rl) as u64;
        all.extend_from_slice(&recs);
        drop(all);
        Ok((0..leaf.count).map(|i| Point { pos: leaf.position(i), color: leaf.color(i), record: PAGED | (base + i as u64) }).collect())
    }
}

/// Tag of [`Point::record`] for points paged back in: the rest is an index into the paged-in
/// records (see [`StoreWriter::page_in`]); without it, an index into the records read this
/// commit interval.
pub const PAGED: u64 = 1 << 63;

/// Most bytes of payloads one commit encodes at once.
pub const COMMIT_GROUP_BYTES: u64 = 128 << 20;

/// A node payload read back from `nodes.bin` (leaf points or an inner node's voxel points).
struct DecodedLeaf<'a> {
    count: usize,
    grid: BatchGrid,
    words: [&'a [u8]; 3],
    colors: &'a [u8],
    attributes: &'a [u8],
    attr_len: usize,
}

impl<'a> DecodedLeaf<'a> {
    fn parse(b: &'a [u8]) -> std::result::Result<DecodedLeaf<'a>, String> {
        if b.len() < 64 {
            return Err("payload shorter than its header".into());
        }
        let h: NodeHeader = bytemuck::pod_read_unaligned(&b[..64]);
        let (n, al) = (h.count as usize, h.attr_len as usize);
        if h.magic != NODE_MAGIC || h.kind > INNER || (b.len() as u64) < payload_len(n as u64, al as u64) || h.bits[..3].iter().any(|&x| x > 30) {
            return Err("damaged payload".into());
        }
        let w = |k: usize| &b[64 + 4 * n * k..64 + 4 * n * (k + 1)];
        Ok(DecodedLeaf {
            count: n,
            grid: BatchGrid { min: h.min, bits: [h.bits[0], h.bits[1], h.bits[2]] },
            words: [w(0), w(1), w(2)],
            colors: w(3),
            attributes: &b[64 + 16 * n..64 + 16 * n + n * al],
            attr_len: al,
        })
    }

    fn u32_at(b: &[u8], i: usize) -> u32 {
        u32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
    }

    fn position(&self, i: usize) -> [i32; 3] {
        self.grid.decode_exact([0, 1, 2].map(|k| Self::u32_at(self.words[k], i)))
    }

    fn color(&self, i: usize) -> u32 {
        Self::u32_at(self.colors, i)
    }

    fn attributes(&self, i: usize) -> &'a [u8] {
        &self.attributes[i * self.attr_len..(i + 1) * self.attr_len]
    }
}

/// Encodes one node's payload (entry offset left 0). `old` is the node's last payload when it is
/// a leaf with paged-out points (those come first) or an inner node with saved voxels (their
/// attributes are taken from it; positions and colours from the voxels in memory).
fn encode_node<'r>(n: &NodeView, old: Option<&[u8]>, record_len: usize, record: &(dyn Fn(u64) -> &'r [u8] + Sync)) -> std::result::Result<(NodeEntry, Vec<u8>), String> {
    let key = n.key();
    let attr_len = record_len - 12;
    let old = old.map(DecodedLeaf::parse).transpose().map_err(|m| format!("node {}: {m}", key.name()))?;
    let kept = if n.is_leaf() { n.paged_points() } else { n.saved_voxels() };
    if old.as_ref().is_some_and(|o| o.attr_len != attr_len || o.count as u64 != kept) {
        return Err(format!("node {}: its last payload does not match the points saved", key.name()));
    }
    let k = old.as_ref().map_or(0, |o| o.count);
    let mut attrs: Vec<u8> = Vec::new();
    let (kind, positions, colors): (u32, Vec<[i32; 3]>, Vec<u32>) = match n.payload() {
        Payload::Points(p) => {
            let mut pos = Vec::with_capacity(k + p.len() as usize);
            let mut col = Vec::with_capacity(k + p.len() as usize);
            if let Some(o) = &old {
                pos.extend((0..k).map(|i| o.position(i)));
                col.extend((0..k).map(|i| o.color(i)));
                attrs.extend_from_slice(o.attributes);
            }
            pos.extend(p.iter().map(|q| q.pos));
            col.extend(p.iter().map(|q| q.color));
            for q in p.iter() {
                attrs.extend_from_slice(&record(q.record)[12..]);
            }
            (LEAF, pos, col)
        }
        Payload::Voxels(v) => {
            if let Some(o) = &old {
                attrs.extend_from_slice(o.attributes);
            }
            for x in v.iter().skip(k) {
                attrs.extend_from_slice(&record(x.record)[12..]);
            }
            (INNER, v.iter().map(|x| x.pos).collect(), v.iter().map(|x| x.color).collect())
        }
    };
    let count = positions.len();
    if count > u32::MAX as usize {
        return Err(format!("node {} holds {count} points, more than a payload can (2^32 - 1)", key.name()));
    }
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    for p in &positions {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    if count == 0 {
        (lo, hi) = ([0; 3], [0; 3]);
    }
    let grid = BatchGrid::for_bounds(lo, hi).ok_or_else(|| format!("node {} spans more than 2^30 grid units on an axis", key.name()))?;
    let len = payload_len(count as u64, attr_len as u64) as usize;
    let mut out = Vec::with_capacity(len);
    let header = NodeHeader {
        magic: NODE_MAGIC,
        level: key.level as u32,
        kind,
        index: key.index,
        count: count as u32,
        min: grid.min,
        bits: [grid.bits[0], grid.bits[1], grid.bits[2], 0],
        attr_len: attr_len as u32,
        _pad: [0; 3],
    };
    out.extend_from_slice(bytemuck::bytes_of(&header));
    let words: Vec<[u32; 3]> = positions.iter().map(|p| grid.encode(*p)).collect();
    drop(positions);
    for level in 0..3 {
        for w in &words {
            out.extend_from_slice(&w[level].to_le_bytes());
        }
    }
    for c in &colors {
        out.extend_from_slice(&c.to_le_bytes());
    }
    debug_assert_eq!(attrs.len(), count * attr_len);
    out.extend_from_slice(&attrs);
    out.resize(len, 0);
    let entry = NodeEntry { level: key.level as u32, kind, index: key.index, _pad: 0, count: count as u64, offset: 0, length: len as u64 };
    Ok((entry, out))
}

/// Choices of `mortar build`.
#[derive(Clone, Debug)]
pub struct BuildOptions {
    /// The builder's configuration (leaf capacity, colour mode).
    pub config: BuilderConfig,
    /// Points per `add_batch`.
    pub batch_points: usize,
    /// Seconds between commits (the last one is always made).
    pub commit_every: f64,
    /// Seconds after the start at which the first commit is made, when sooner than
    /// `commit_every` (a preview shows the store from its first commit on).
    pub first_commit_after: Option<f64>,
    /// Memory budget in bytes: a commit (after which the builder pages out every leaf's points)
    /// is also made when the points and records held since the last one exceed a third of it.
    pub memory: u64,
}

/// Progress of a build, reported after every batch.
#[derive(Clone, Copy, Debug, Default)]
pub struct BuildProgress {
    /// Points added so far.
    pub points: u64,
    /// Points in all (as the headers declare).
    pub total: u64,
    /// Nodes so far.
    pub nodes: usize,
    /// Commits so far.
    pub commits: u64,
}

/// What a build did.
#[derive(Clone, Debug, Default)]
pub struct BuildReport {
    /// Points in the store.
    pub points: u64,
    /// Nodes, leaves.
    pub nodes: u64,
    /// Leaves.
    pub leaves: u64,
    /// Voxels of the inner nodes.
    pub voxels: u64,
    /// Commits.
    pub commits: u64,
    /// Bytes of `nodes.bin`.
    pub nodes_bytes: u64,
    /// Seconds reading (decoding) the input.
    pub read_seconds: f64,
    /// Seconds in `add_batch`, per batch.
    pub batch_seconds: Vec<f64>,
    /// Seconds committing.
    pub commit_seconds: f64,
    /// Leaves paged back in for splits.
    pub paged_in_leaves: u64,
    /// Most bytes of points and records held between two commits.
    pub peak_interval_bytes: u64,
    /// Seconds in all.
    pub seconds: f64,
    /// Times the octree's root grew for points outside it.
    pub root_growths: u64,
    /// Problems that did not stop the build (headers that lie about the bounds).
    pub warnings: Vec<String>,
}

/// The integer bounds the inputs' headers declare (one unit of margin), on the merged grid, with
/// a warning for each input whose header bounds are not usable; `None` when no header is.
fn header_bounds(ds: &Dataset, warnings: &mut Vec<String>) -> Option<([i32; 3], [i32; 3])> {
    let (mut lo, mut hi) = ([i64::MAX; 3], [i64::MIN; 3]);
    for src in &ds.inputs {
        let h = src.header();
        if src.point_count() == 0 {
            continue;
        }
        if src.point_count() > 1 && (0..3).all(|a| h.min[a] == 0.0 && h.max[a] == 0.0) {
            warnings.push(format!("{}: the header's bounds are all zero (not set by the writer); the octree is placed from the points", src.path().display()));
            continue;
        }
        if let Some(a) = (0..3).find(|&a| !(h.min[a].is_finite() && h.max[a].is_finite()) || h.min[a] > h.max[a]) {
            warnings.push(format!(
                "{}: the header's bounds on axis {} are not usable ({} .. {}); the octree is placed from the points",
                src.path().display(),
                ['x', 'y', 'z'][a],
                h.min[a],
                h.max[a]
            ));
            continue;
        }
        for a in 0..3 {
            lo[a] = lo[a].min(ds.grid.to_int(a, h.min[a]).saturating_sub(1));
            hi[a] = hi[a].max(ds.grid.to_int(a, h.max[a]).saturating_add(1));
        }
    }
    if lo[0] > hi[0] {
        return None;
    }
    let c = |v: i64| v.clamp(i32::MIN as i64, i32::MAX as i64) as i32;
    Some((lo.map(c), hi.map(c)))
}

/// A warning when the points of `src` (`st`, on the merged grid) reach outside the bounds its
/// header declares, with both ranges in world coordinates on the file's grid.
fn bounds_warning(ds: &Dataset, src: &dyn RecordSource, st: &crate::sort::PieceStats) -> Option<String> {
    let h = src.header();
    if st.count == 0 || (0..3).any(|a| !(h.min[a].is_finite() && h.max[a].is_finite()) || h.min[a] > h.max[a]) {
        return None;
    }
    let g = &ds.grid;
    let outside = (0..3).any(|a| (st.min[a] as i64) < g.to_int(a, h.min[a]) - 1 || (st.max[a] as i64) > g.to_int(a, h.max[a]) + 1);
    if !outside {
        return None;
    }
    let digits = |a: usize| (-h.scale[a].log10()).ceil().clamp(0.0, 12.0) as usize;
    let range = |a: usize, lo: f64, hi: f64| format!("{} [{:.*}, {:.*}]", ['x', 'y', 'z'][a], digits(a), lo, digits(a), hi);
    let real: Vec<String> = (0..3).map(|a| range(a, g.world(a, st.min[a] as i64), g.world(a, st.max[a] as i64))).collect();
    let declared: Vec<String> = (0..3).map(|a| range(a, h.min[a], h.max[a])).collect();
    Some(format!(
        "{}: its points reach {}, outside the bounds its header declares ({}); the octree's root grew to hold them (`mortar sort` writes the file with true bounds)",
        src.path().display(),
        real.join(", "),
        declared.join(", ")
    ))
}

/// Builds the store `dir` from `ds`: reads the input piece by piece (pieces of a batch in
/// parallel) and adds the points to the octree in batches of about `batch_points` in input order,
/// committing every `commit_every` seconds, whenever the points held since the last commit exceed
/// a third of the memory budget, and at the end; after each commit the leaves' points are paged
/// out (see the module docs). The octree's root cube comes from the headers' bounds and the first
/// points; where points fall outside it (headers lie), the root grows (a new root above the old
/// one) and the report warns about each such file with its points' real range. On an error the
/// directory is removed; on Ctrl-C the last commit stays readable.
pub fn build(ds: &Dataset, dir: &Path, opts: &BuildOptions, progress: &mut dyn FnMut(&BuildProgress)) -> Result<BuildReport> {
    let t0 = Instant::now();
    let meta = ds.source_meta();
    let mut warnings = Vec::new();
    let bounds = header_bounds(ds, &mut warnings);
    let mut writer = StoreWriter::create(dir, &meta)?;
    let result = build_into(ds, &mut writer, opts, progress, bounds, t0).map(|mut r| {
        warnings.append(&mut r.warnings);
        r.warnings = warnings;
        r
    });
    match result {
        Ok(r) => Ok(r),
        Err(Error::Interrupted) => Err(Error::Interrupted),
        Err(e) => {
            // Not a store the user asked for: remove what was written (also after commits).
            let _ = std::fs::remove_dir_all(dir);
            Err(e)
        }
    }
}

fn build_into(ds: &Dataset, writer: &mut StoreWriter, opts: &BuildOptions, progress: &mut dyn FnMut(&BuildProgress), header: Option<([i32; 3], [i32; 3])>, t0: Instant) -> Result<BuildReport> {
    let rl = ds.layout.record_len;
    let pieces = ds.pieces();
    let total: u64 = pieces.iter().map(|p| p.piece.points).sum();
    let batch = opts.batch_points.max(1);
    // Bytes held per point between commits: its record, its Point in a leaf, the batch's work.
    let per_point = rl as u64 + 24 + 48;
    let interval_points = ((opts.memory / 3) / per_point).max(batch as u64);
    let mut report = BuildReport::default();
    // Made with the first points: its root covers the headers' bounds and those points.
    let mut builder: Option<Builder> = None;
    // The real bounds of each input's points, for the warnings about headers that lie.
    let mut real: Vec<crate::sort::PieceStats> = vec![crate::sort::PieceStats::default(); ds.inputs.len()];
    // Records of the points added since the last commit (index = Point::record) and of points
    // paged back in (PAGED | index).
    let mut records: Vec<u8> = Vec::with_capacity((interval_points.min(total) as usize + batch).saturating_mul(rl).min(1 << 30));
    let paged = std::sync::Mutex::new(Vec::<u8>::new());
    let mut color: Option<ColorSource> = None;
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    let mut last_commit = Instant::now();
    let mut points: Vec<Point> = Vec::new();
    let mut done = 0u64;
    let mut next = 0usize;
    while next < pieces.len() {
        crate::sort::check_interrupted()?;
        // The next pieces, up to about one batch of points.
        let first = next;
        let mut n = 0u64;
        while next < pieces.len() && (next == first || n + pieces[next].piece.points <= batch as u64) {
            n += pieces[next].piece.points;
            next += 1;
        }
        let tr = Instant::now();
        let base = records.len();
        let bytes = usize::try_from(n).ok().and_then(|n| n.checked_mul(rl)).ok_or_else(|| Error::Usage(format!("a piece of {n} points does not fit in memory")))?;
        records.resize(base + bytes, 0);
        {
            let mut slices = Vec::with_capacity(next - first);
            let mut rest = &mut records[base..];
            for p in &pieces[first..next] {
                let (head, tail) = rest.split_at_mut(p.piece.points as usize * rl);
                slices.push((p, head));
                rest = tail;
            }
            let stats: Vec<(usize, crate::sort::PieceStats)> = slices
                .into_par_iter()
                .map(|(p, out)| {
                    crate::sort::check_interrupted()?;
                    ds.read_piece_into(p, out)?;
                    // Read once: a mapped input's pages leave this process's memory.
                    ds.inputs[p.input].release_piece(&p.piece);
                    Ok((p.input, crate::sort::PieceStats::of(out, &ds.layout)))
                })
                .collect::<Result<_>>()?;
            for (i, st) in stats {
                real[i].merge(&st);
            }
        }
        let recs = &records[base..];
        let st = recs.par_chunks(rl * 65_536).map(|c| crate::sort::PieceStats::of(c, &ds.layout)).reduce(crate::sort::PieceStats::default, |mut a, b| {
            a.merge(&b);
            a
        });
        report.read_seconds += tr.elapsed().as_secs_f64();
        if builder.is_none() && st.count > 0 {
            // The headers' box when it holds the first points; otherwise the headers lie, and
            // the root starts from the first points alone (it grows for the rest).
            let (l, h) = match header {
                Some((l, h)) if (0..3).all(|a| l[a] <= st.min[a] && st.max[a] <= h[a]) => (l, h),
                _ => (st.min, st.max),
            };
            builder = Some(Builder::for_bounds(l, h, opts.config).map_err(|e| Error::Usage(format!("octree: {e}")))?);
        }
        let Some(builder) = builder.as_mut() else { continue };
        if st.count > 0 {
            for a in 0..3 {
                lo[a] = lo[a].min(st.min[a]);
                hi[a] = hi[a].max(st.max[a]);
            }
        }
        // The colour source is chosen once, from the first batch (as batch files choose it from
        // the whole input).
        let color = *color.get_or_insert_with(|| match ds.layout.attribute("rgb") {
            Some(a) if st.max_rgb > 0 => ColorSource::Rgb { offset: a.offset, depth: RgbDepth::detect(st.max_rgb) },
            _ => ColorSource::Intensity { max_intensity: st.max_intensity },
        });
        // Updates of about `batch` points each; a commit may come between two of them.
        let mut cursor = base;
        while cursor < records.len() {
            crate::sort::check_interrupted()?;
            let end = (cursor + batch * rl).min(records.len());
            let first_index = (cursor / rl) as u64;
            points.clear();
            points.par_extend(records[cursor..end].par_chunks_exact(rl).enumerate().map(|(i, r)| Point { pos: read_xyz(r), color: color.rgba(r), record: first_index + i as u64 }));
            let tb = Instant::now();
            let paged_in = std::sync::atomic::AtomicU64::new(0);
            {
                let w = &*writer;
                let page_in = |id: NodeId| -> std::result::Result<Vec<Point>, String> {
                    paged_in.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    w.page_in(id.index(), None, &paged).map_err(|e| e.to_string())
                };
                let st = builder.add_batch_paged(&points, &page_in).map_err(|e| match e {
                    OctreeError::PageIn(m) => Error::input(&w.dir, format!("reading a node back: {m}")),
                    e => Error::Usage(format!("octree: {e}")),
                })?;
                report.root_growths += st.growths as u64;
            }
            report.paged_in_leaves += paged_in.into_inner();
            report.batch_seconds.push(tb.elapsed().as_secs_f64());
            done += points.len() as u64;
            cursor = end;
            let held = records.len() as u64 + paged.lock().map_or(0, |p| p.len() as u64) + builder.resident_points() * 24;
            report.peak_interval_bytes = report.peak_interval_bytes.max(held);
            let since = last_commit.elapsed().as_secs_f64();
            let first_due = writer.commits() == 0 && opts.first_commit_after.is_some_and(|f| since >= f);
            let due = since >= opts.commit_every || first_due || builder.resident_points() >= interval_points;
            let last = next == pieces.len() && cursor == records.len();
            if due && !last {
                commit_and_page_out(writer, builder, (lo, hi), &mut records, cursor, &paged, rl, &mut report)?;
                cursor = 0;
                last_commit = Instant::now();
            }
            progress(&BuildProgress { points: done, total, nodes: builder.node_count(), commits: writer.commits() });
        }
    }
    if done == 0 {
        (lo, hi) = ([0; 3], [0; 3]);
    }
    let builder = match builder.as_mut() {
        Some(b) => b,
        None => builder.insert(Builder::for_bounds([0; 3], [0; 3], opts.config).map_err(|e| Error::Usage(format!("octree: {e}")))?),
    };
    let all = records.len();
    commit_and_page_out(writer, builder, (lo, hi), &mut records, all, &paged, rl, &mut report)?;
    // Headers that lie: the points' real range, per file.
    for (src, st) in ds.inputs.iter().zip(&real) {
        if let Some(w) = bounds_warning(ds, src.as_ref(), st) {
            report.warnings.push(w);
        }
    }
    let snap = builder.snapshot();
    report.points = snap.total_points();
    report.nodes = snap.node_count() as u64;
    report.leaves = snap.leaves().count() as u64;
    report.voxels = snap.voxel_count();
    report.commits = writer.commits();
    report.nodes_bytes = writer.nodes_len;
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(report)
}

/// Commits, then pages out every leaf's points and drops the records they needed: the first
/// `added` bytes of `records` (the rest, not added yet, moves to the front).
#[allow(clippy::too_many_arguments)]
fn commit_and_page_out(writer: &mut StoreWriter, builder: &mut Builder, bounds: ([i32; 3], [i32; 3]), records: &mut Vec<u8>, added: usize, paged: &std::sync::Mutex<Vec<u8>>, rl: usize, report: &mut BuildReport) -> Result<()> {
    let tc = Instant::now();
    {
        let paged = paged.lock().map_err(|_| Error::Usage("a page-in thread panicked".into()))?;
        let recs: &[u8] = records;
        let pg: &[u8] = &paged;
        let record = |h: u64| -> &[u8] {
            if h & PAGED != 0 {
                let i = (h & !PAGED) as usize;
                &pg[i * rl..(i + 1) * rl]
            } else {
                &recs[h as usize * rl..(h as usize + 1) * rl]
            }
        };
        writer.commit(&builder.snapshot(), bounds, &record)?;
    }
    builder.page_out();
    records.drain(..added);
    if let Ok(mut p) = paged.lock() {
        p.clear();
        p.shrink_to_fit();
    }
    report.commit_seconds += tc.elapsed().as_secs_f64();
    Ok(())
}

/// Whether `path` is a store directory.
pub fn is_store(path: &Path) -> bool {
    path.is_dir() && path.join(HIERARCHY_FILE).is_file() && path.join(SOURCE_FILE).is_file()
}

/// A store opened for reading (the last commit).
pub struct Store {
    /// The directory.
    pub path: PathBuf,
    /// The source's header (with the store's point count), VLRs and EVLRs.
    pub meta: las::LasMeta,
    /// The record layout.
    pub layout: RecordLayout,
    /// The hierarchy header.
    pub header: HierarchyHeader,
    /// Every node.
    pub entries: Vec<NodeEntry>,
    nodes: Option<Mmap>,
    leaves: Vec<usize>,
}

/// One node's payload, borrowed from the memory map.
#[derive(Clone, Copy, Debug)]
pub struct NodeData<'a> {
    /// The payload's header.
    pub header: NodeHeader,
    /// Coarse, medium, fine words.
    pub words: [&'a [u32]; 3],
    /// RGBA8 colours.
    pub colors: &'a [u32],
    /// `attr_len` bytes per point (leaves).
    pub attributes: &'a [u8],
}

impl NodeData<'_> {
    /// The quantization frame.
    pub fn grid(&self) -> BatchGrid {
        BatchGrid { min: self.header.min, bits: [self.header.bits[0], self.header.bits[1], self.header.bits[2]] }
    }
}

impl Store {
    /// Opens the last commit of the store `dir`, checking every length against the bytes that
    /// exist.
    pub fn open(dir: &Path) -> Result<Store> {
        let bad = |m: String| Error::input(dir, m);
        let src = LasInput::open(&dir.join(SOURCE_FILE))?;
        let hp = dir.join(HIERARCHY_FILE);
        let hb = std::fs::read(&hp).map_err(|e| Error::io(&hp, e))?;
        if hb.len() < HIERARCHY_HEADER {
            return Err(bad("hierarchy.bin is truncated".into()));
        }
        let header: HierarchyHeader = bytemuck::pod_read_unaligned(&hb[..HIERARCHY_HEADER]);
        if header.magic != HIERARCHY_MAGIC {
            return Err(bad("hierarchy.bin is not a mortar store hierarchy".into()));
        }
        if header.version != VERSION || header.entry_size != 48 {
            return Err(bad(format!("store version {} (entry size {}) is not supported", header.version, header.entry_size)));
        }
        let avail = (hb.len() - HIERARCHY_HEADER) as u64 / 48;
        if header.node_count != avail || (hb.len() - HIERARCHY_HEADER) % 48 != 0 {
            return Err(bad(format!("hierarchy.bin declares {} nodes but holds {avail}", header.node_count)));
        }
        let entries: Vec<NodeEntry> = bytemuck::pod_collect_to_vec(&hb[HIERARCHY_HEADER..]);
        let np = dir.join(NODES_FILE);
        let f = File::open(&np).map_err(|e| Error::io(&np, e))?;
        let file_len = f.metadata().map_err(|e| Error::io(&np, e))?.len();
        if header.nodes_len > file_len {
            return Err(bad(format!("nodes.bin holds {file_len} bytes, fewer than the {} the hierarchy covers", header.nodes_len)));
        }
        // SAFETY: the file is only appended to while it is mapped (by a builder); the part read
        // (up to nodes_len) never changes after its commit.
        let nodes = if file_len == 0 { None } else { Some(unsafe { Mmap::map(&f) }.map_err(|e| Error::io(&np, e))?) };
        let layout = src.layout.clone();
        let attr_len = layout.record_len as u64 - 12;
        let mut leaves = Vec::new();
        let mut points = 0u64;
        for (i, e) in entries.iter().enumerate() {
            let al = attr_len;
            if e.kind > INNER || e.offset % 8 != 0 || e.count > u32::MAX as u64 || e.length != payload_len(e.count, al) || e.offset.checked_add(e.length).is_none_or(|end| end > header.nodes_len) {
                return Err(bad(format!("node entry {i} is damaged (kind {}, {} points, {} bytes at {})", e.kind, e.count, e.length, e.offset)));
            }
            let nb = &nodes.as_ref().expect("non-empty")[e.offset as usize..(e.offset + e.length) as usize];
            let h: NodeHeader = bytemuck::pod_read_unaligned(&nb[..64]);
            if h.magic != NODE_MAGIC || h.count as u64 != e.count || h.kind != e.kind || h.attr_len as u64 != al || h.bits[..3].iter().any(|&b| b > 30) {
                return Err(bad(format!("node payload {i} does not match its hierarchy entry")));
            }
            if e.kind == LEAF {
                leaves.push(i);
                points += e.count;
            }
        }
        if points != header.points {
            return Err(bad(format!("the leaves hold {points} points, the hierarchy says {}", header.points)));
        }
        let mut meta = src.meta.clone();
        meta.header.point_count = points;
        if points > 0 {
            let h = &mut meta.header;
            for a in 0..3 {
                let w = |v: i32| h.offset[a] + h.scale[a] * v as f64;
                let (x, y) = (w(header.min[a]), w(header.max[a]));
                h.min[a] = x.min(y);
                h.max[a] = x.max(y);
            }
        }
        Ok(Store { path: dir.to_path_buf(), meta, layout, header, entries, nodes, leaves })
    }

    /// Indices of the leaf entries.
    pub fn leaves(&self) -> &[usize] {
        &self.leaves
    }

    /// The root cube.
    pub fn root_cube(&self) -> Cube {
        Cube { min: self.header.root_min, size_log2: self.header.root_size_log2 as u8 }
    }

    /// The payload of node entry `i`.
    pub fn node(&self, i: usize) -> NodeData<'_> {
        let e = &self.entries[i];
        let b = &self.nodes.as_ref().expect("checked at open")[e.offset as usize..(e.offset + e.length) as usize];
        let header: NodeHeader = bytemuck::pod_read_unaligned(&b[..64]);
        let n = header.count as usize;
        // Offsets are multiples of 8 in a page-aligned map: the u32 arrays are aligned.
        let words_at = |k: usize| -> &[u32] { bytemuck::cast_slice(&b[64 + 4 * n * k..64 + 4 * n * (k + 1)]) };
        let attributes = &b[64 + 16 * n..64 + 16 * n + n * header.attr_len as usize];
        NodeData { header, words: [words_at(0), words_at(1), words_at(2)], colors: words_at(3), attributes }
    }
}

/// Leaves per piece when a store is read as records (about 1 M points with full leaves).
const LEAVES_PER_PIECE: usize = 20;

impl RecordSource for Store {
    fn path(&self) -> &Path {
        &self.path
    }
    fn header(&self) -> &Header {
        &self.meta.header
    }
    fn vlrs(&self) -> &[Vlr] {
        &self.meta.vlrs
    }
    fn evlrs(&self) -> &[Vlr] {
        &self.meta.evlrs
    }
    fn layout(&self) -> &RecordLayout {
        &self.layout
    }
    fn point_count(&self) -> u64 {
        self.header.points
    }
    fn pieces(&self) -> Vec<Piece> {
        let mut first = 0;
        self.leaves
            .chunks(LEAVES_PER_PIECE)
            .enumerate()
            .map(|(i, c)| {
                let points = c.iter().map(|&l| self.entries[l].count).sum();
                let p = Piece { index: i, first_point: first, points };
                first += points;
                p
            })
            .collect()
    }
    fn read_piece(&self, piece: &Piece) -> Result<Cow<'_, [u8]>> {
        let rl = self.layout.record_len;
        let start = piece.index * LEAVES_PER_PIECE;
        let leaves = self.leaves.get(start..(start + LEAVES_PER_PIECE).min(self.leaves.len())).unwrap_or(&[]);
        let mut out = Vec::with_capacity(piece.points as usize * rl);
        for &l in leaves {
            let d = self.node(l);
            let g = d.grid();
            let al = d.header.attr_len as usize;
            for i in 0..d.header.count as usize {
                let p = g.decode_exact([d.words[0][i], d.words[1][i], d.words[2][i]]);
                for v in p {
                    out.extend_from_slice(&v.to_le_bytes());
                }
                out.extend_from_slice(&d.attributes[i * al..(i + 1) * al]);
            }
        }
        if out.len() != piece.points as usize * rl {
            return Err(Error::input(&self.path, format!("piece {} holds another number of points than its leaves declare", piece.index)));
        }
        Ok(Cow::Owned(out))
    }
    fn is_compressed(&self) -> bool {
        false
    }
}
