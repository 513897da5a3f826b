//! Writing a store: payloads appended to `nodes.bin`, then an atomic hierarchy commit.

use crate::cleanup::TempPath;
use crate::dataset::SourceMeta;
use crate::error::{Error, Result, StoreError};
use crate::las::{self, HeaderOut};
use mortar_core::octree::{Cube, NodeView, Payload, Point, Snapshot};
use rayon::prelude::*;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use super::format::*;

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
    pub(crate) dir: PathBuf,
    pub(crate) nodes: File,
    /// `nodes.bin` opened for reading old payloads back.
    pub(crate) reader: File,
    pub(crate) nodes_len: u64,
    pub(crate) entries: Vec<Option<NodeEntry>>,
    pub(crate) commit: u64,
    pub(crate) last_revision: Option<u64>,
    pub(crate) record_len: usize,
    /// The records' layout.
    pub(crate) layout: mortar_core::layout::RecordLayout,
    /// Registered for removal until the first commit.
    pub(crate) guard: Option<TempPath>,
    /// Payload bytes encoded at once ([`group_bytes`] of the build's budget).
    pub(crate) group_bytes: u64,
    /// Bytes covered of segments 1.. (files linked in whole by a merge, or written by a
    /// compaction; the engines append to segment 0 alone).
    pub(crate) segments: Vec<u64>,
}

impl StoreWriter {
    /// Creates the store directory `dir` (which must not exist, or be empty) with the source's
    /// metadata.
    pub fn create(dir: &Path, meta: &SourceMeta) -> Result<StoreWriter> {
        if dir.exists() {
            let empty = dir.is_dir()
                && std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?.next().is_none();
            if !empty {
                return Err(Error::Store { path: dir.to_path_buf(), error: StoreError::NotEmpty });
            }
        } else {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        }
        let guard = TempPath::adopt(dir.to_path_buf());
        let bytes = source_bytes(dir, meta)?;
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
            layout: meta.layout.clone(),
            guard: Some(guard),
            group_bytes: COMMIT_GROUP_BYTES,
            segments: Vec::new(),
        })
    }

    /// Reopens the store `dir` that a build left (killed, or out of disk) to continue it: the
    /// last commit's nodes are kept, anything appended after it is cut off. `None` when there is
    /// nothing to continue from (no commit yet: the caller starts over). Fails when the store was
    /// made from another source (its `source.las` differs from what `meta` gives).
    pub fn reopen(dir: &Path, meta: &SourceMeta) -> Result<Option<(StoreWriter, HierarchyHeader)>> {
        let src = dir.join(SOURCE_FILE);
        let hp = dir.join(HIERARCHY_FILE);
        if !hp.is_file() {
            return Ok(None);
        }
        let want = source_bytes(dir, meta)?;
        let have = std::fs::read(&src).map_err(|e| Error::io(&src, e))?;
        if have != want {
            return Err(Error::Store { path: dir.to_path_buf(), error: StoreError::OtherInputs });
        }
        let store = super::reader::Store::open(dir)?;
        let np = dir.join(NODES_FILE);
        let nodes =
            std::fs::OpenOptions::new().write(true).open(&np).map_err(|e| Error::io(&np, e))?;
        nodes.set_len(store.header.nodes_len).map_err(|e| Error::io(&np, e))?;
        let reader = File::open(&np).map_err(|e| Error::io(&np, e))?;
        let _ = std::fs::remove_file(dir.join(format!("{HIERARCHY_FILE}.tmp")));
        let w = StoreWriter {
            dir: dir.to_path_buf(),
            nodes,
            reader,
            nodes_len: store.header.nodes_len,
            entries: store.entries.iter().copied().map(Some).collect(),
            commit: store.header.commit,
            last_revision: None,
            record_len: meta.layout.record_len,
            layout: meta.layout.clone(),
            guard: None,
            group_bytes: COMMIT_GROUP_BYTES,
            segments: store.covered[1..].to_vec(),
        };
        Ok(Some((w, store.header)))
    }

    /// Reopens the store `dir` that a partitioned build left before its one commit (killed, or
    /// power loss), to continue it from its `.partition` state: `None` when it has a commit or
    /// no `nodes.bin`. Fails when the store was made from another source.
    pub fn reopen_uncommitted(dir: &Path, meta: &SourceMeta) -> Result<Option<StoreWriter>> {
        let src = dir.join(SOURCE_FILE);
        let np = dir.join(NODES_FILE);
        if dir.join(HIERARCHY_FILE).exists() || !np.is_file() || !src.is_file() {
            return Ok(None);
        }
        let want = source_bytes(dir, meta)?;
        let have = std::fs::read(&src).map_err(|e| Error::io(&src, e))?;
        if have != want {
            return Err(Error::Store { path: dir.to_path_buf(), error: StoreError::OtherInputs });
        }
        let nodes =
            std::fs::OpenOptions::new().write(true).open(&np).map_err(|e| Error::io(&np, e))?;
        let nodes_len = nodes.metadata().map_err(|e| Error::io(&np, e))?.len();
        let reader = File::open(&np).map_err(|e| Error::io(&np, e))?;
        Ok(Some(StoreWriter {
            dir: dir.to_path_buf(),
            nodes,
            reader,
            nodes_len,
            entries: Vec::new(),
            commit: 0,
            last_revision: None,
            record_len: meta.layout.record_len,
            layout: meta.layout.clone(),
            guard: None,
            group_bytes: COMMIT_GROUP_BYTES,
            segments: Vec::new(),
        }))
    }

    /// Cuts `nodes.bin` to `len` bytes (what a resumed build keeps of it).
    pub(crate) fn cut_nodes(&mut self, len: u64) -> Result<()> {
        use std::io::Seek;
        let np = self.dir.join(NODES_FILE);
        self.nodes.set_len(len).map_err(|e| Error::io(&np, e))?;
        self.nodes.seek(std::io::SeekFrom::Start(len)).map_err(|e| Error::io(&np, e))?;
        self.nodes_len = len;
        Ok(())
    }

    /// The entries committed or set so far, in id order.
    pub fn entries(&self) -> impl Iterator<Item = &NodeEntry> {
        self.entries.iter().flatten()
    }

    /// Commits: appends the payloads of the nodes changed since the last commit, syncs them, then
    /// replaces the hierarchy atomically. `record(h)` returns the full record of the point whose
    /// [`Point::record`] is `h`. A changed leaf with paged-out points ([`NodeView::paged_points`])
    /// is written whole: its last payload is read back and the new points appended. Payloads are
    /// encoded in parallel in groups of at most `group_bytes`, so a commit needs little
    /// memory beyond the nodes themselves. `bounds` are the integer bounds of the points so far.
    pub fn commit<'r>(
        &mut self,
        snap: &Snapshot,
        bounds: ([i32; 3], [i32; 3]),
        record: &(dyn Fn(u64) -> &'r [u8] + Sync),
    ) -> Result<CommitStats> {
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
            while end < changed.len() && (end == start || bytes < self.group_bytes) {
                let n = changed[end].1;
                bytes += payload_len(n.total_points() + n.voxel_count(), attr_len);
                end += 1;
            }
            self.write_group(&changed[start..end], record, &mut stats)?;
            start = end;
        }
        // Keys move when the root grows (a new root above the old one): the entries of nodes not
        // written again take their current keys (the payload keeps the key it was written with).
        for (id, n) in snap.iter() {
            if let Some(Some(e)) = self.entries.get_mut(id.index()) {
                let k = n.key();
                e.level = k.level as u32;
                e.index = k.index;
            }
        }
        self.write_hierarchy(
            snap.root_cube(),
            snap.total_points(),
            snap.config().leaf_capacity,
            bounds,
        )?;
        self.last_revision = Some(snap.revision());
        Ok(stats)
    }

    /// Makes what was appended since the last commit the store's new state: syncs `nodes.bin`,
    /// then writes the hierarchy of every node appended so far (entries in id order) to a
    /// temporary file, syncs it and renames it over `hierarchy.bin`.
    pub fn write_hierarchy(
        &mut self,
        root: Cube,
        points: u64,
        leaf_capacity: u32,
        bounds: ([i32; 3], [i32; 3]),
    ) -> Result<()> {
        let np = self.dir.join(NODES_FILE);
        self.nodes.sync_data().map_err(|e| Error::io(&np, e))?;
        self.commit += 1;
        let entries: Vec<NodeEntry> = self.entries.iter().flatten().copied().collect();
        let header = HierarchyHeader {
            magic: HIERARCHY_MAGIC,
            version: VERSION,
            entry_size: std::mem::size_of::<NodeEntry>() as u32,
            commit: self.commit,
            node_count: entries.len() as u64,
            nodes_len: self.nodes_len,
            points,
            root_min: root.min,
            root_size_log2: root.size_log2 as u32,
            leaf_capacity,
            min: bounds.0,
            max: bounds.1,
        };
        let mut bytes = bytemuck::bytes_of(&header).to_vec();
        bytes.extend_from_slice(bytemuck::cast_slice(&entries));
        let mut covered = vec![self.nodes_len];
        covered.extend_from_slice(&self.segments);
        bytes.extend_from_slice(&segments_bytes(&covered));
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
        // From the first commit on, the directory is a readable store: Ctrl-C leaves it.
        if let Some(g) = self.guard.take() {
            g.keep();
        }
        Ok(())
    }

    /// Commits made.
    pub fn commits(&self) -> u64 {
        self.commit
    }

    /// Encodes `nodes` in parallel and appends them in order.
    fn write_group<'r>(
        &mut self,
        nodes: &[(usize, &NodeView)],
        record: &(dyn Fn(u64) -> &'r [u8] + Sync),
        stats: &mut CommitStats,
    ) -> Result<()> {
        let record_len = self.record_len;
        let this = &*self;
        let payloads: Vec<(usize, NodeEntry, Vec<u8>)> = nodes
            .par_iter()
            .map(|&(id, n)| {
                let kept = n.paged_points() + n.saved_voxels();
                let old = if kept > 0 { Some(this.read_payload(id, Some(kept))?) } else { None };
                encode_node(n, old.as_deref(), record_len, record)
                    .map(|(e, b)| (id, e, b))
                    .map_err(|error| Error::Payload { path: this.dir.clone(), error })
            })
            .collect::<Result<_>>()?;
        self.append(payloads, stats)
    }

    /// Appends encoded payloads to `nodes.bin` in order; `id` is the node's place among the
    /// hierarchy's entries (the root 0). Not visible to readers before the next commit.
    pub fn append(
        &mut self,
        payloads: Vec<(usize, NodeEntry, Vec<u8>)>,
        stats: &mut CommitStats,
    ) -> Result<()> {
        let np = self.dir.join(NODES_FILE);
        let start = self.nodes_len;
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
        drop(w);
        self.start_writeback(start, self.nodes_len - start);
        Ok(())
    }

    /// Reserves room for payloads of `lens` bytes at the end of `nodes.bin`: their offsets, in
    /// order. Fill them with [`write_at`](Self::write_at) (from any thread) and record them with
    /// [`set_entry`](Self::set_entry) before the next commit.
    pub fn reserve(&mut self, lens: &[u64]) -> Vec<u64> {
        let mut out = Vec::with_capacity(lens.len());
        for &l in lens {
            out.push(self.nodes_len);
            self.nodes_len += l;
        }
        out
    }

    /// Writes `bytes` at `offset` of `nodes.bin` (a place [`reserve`](Self::reserve) gave).
    pub fn write_at(&self, offset: u64, bytes: &[u8]) -> Result<()> {
        use std::os::unix::fs::FileExt;
        self.nodes
            .write_all_at(bytes, offset)
            .map_err(|e| Error::io(self.dir.join(NODES_FILE), e))?;
        self.start_writeback(offset, bytes.len() as u64);
        Ok(())
    }

    /// Starts writing `len` bytes of `nodes.bin` from `offset` to the disk without waiting
    /// (Linux `sync_file_range(SYNC_FILE_RANGE_WRITE)`), so the disk works while the build
    /// encodes the next payloads and the commit's `fdatasync` finds little left to write. It
    /// promises nothing: durability is the commit's `fdatasync`, as before. Errors are ignored
    /// (the call is advice; the `fdatasync` reports what failed).
    fn start_writeback(&self, offset: u64, len: u64) {
        // Pieces under 1 MiB wait for the commit (or for the next large write).
        if len < 1 << 20 {
            return;
        }
        use std::os::fd::AsRawFd;
        // SAFETY: sync_file_range reads no memory of ours; the descriptor is open for the
        // writer's lifetime.
        unsafe {
            libc::sync_file_range(
                self.nodes.as_raw_fd(),
                offset as libc::off64_t,
                len as libc::off64_t,
                libc::SYNC_FILE_RANGE_WRITE,
            );
        }
    }

    /// Records node `id`'s payload for the next commit.
    pub fn set_entry(&mut self, id: usize, entry: NodeEntry) {
        if self.entries.len() <= id {
            self.entries.resize(id + 1, None);
        }
        self.entries[id] = Some(entry);
    }

    /// The last written payload of node `id`, which must hold `count` points or voxels.
    pub(crate) fn read_payload(&self, id: usize, count: Option<u64>) -> Result<Vec<u8>> {
        use std::os::unix::fs::FileExt;
        let np = self.dir.join(NODES_FILE);
        let e = self.entries.get(id).copied().flatten().ok_or_else(|| Error::Store {
            path: np.clone(),
            error: StoreError::NoPayload { node: id },
        })?;
        if count.is_some_and(|c| c != e.count) {
            return Err(Error::Store {
                path: np,
                error: StoreError::PayloadCount { node: id, held: e.count, saved: count },
            });
        }
        let mut buf = vec![0u8; e.length as usize];
        self.reader.read_exact_at(&mut buf, e.offset).map_err(|err| Error::io(&np, err))?;
        Ok(buf)
    }

    /// The paged-out points of leaf `id` (`count` of them, if given), read back from its last
    /// payload for a split, or the saved voxels of inner node `id` (for a root that grows): their
    /// full records are appended to `records` and each point's [`Point::record`] is
    /// `PAGED | index` of its record there.
    pub fn page_in(
        &self,
        id: usize,
        count: Option<u64>,
        records: &std::sync::Mutex<Vec<u8>>,
    ) -> Result<Vec<Point>> {
        let buf = self.read_payload(id, count)?;
        let bad = |m: PayloadError| Error::Payload {
            path: self.dir.join(NODES_FILE),
            error: m.in_node(id),
        };
        let raw = super::codec::decode(&buf).map_err(bad)?;
        let leaf = DecodedLeaf::parse(&raw).map_err(bad)?;
        let rl = self.record_len;
        let mut recs = vec![0u8; leaf.count * rl];
        for (i, r) in recs.chunks_exact_mut(rl).enumerate() {
            let p = leaf.position(i);
            for a in 0..3 {
                r[4 * a..4 * a + 4].copy_from_slice(&p[a].to_le_bytes());
            }
            r[12..].copy_from_slice(leaf.attributes(i));
        }
        let mut all = records.lock().map_err(|_| Error::ThreadPanicked { thread: "a page-in" })?;
        let base = (all.len() / rl) as u64;
        all.extend_from_slice(&recs);
        drop(all);
        Ok((0..leaf.count)
            .map(|i| Point {
                pos: leaf.position(i),
                color: leaf.color(i),
                record: PAGED | (base + i as u64),
            })
            .collect())
    }
}

/// Tag of [`Point::record`] for points paged back in: the rest is an index into the paged-in
/// records (see [`StoreWriter::page_in`]); without it, an index into the records read this
/// commit interval.
pub const PAGED: u64 = 1 << 63;

/// Most bytes of payloads one commit encodes at once.
pub const COMMIT_GROUP_BYTES: u64 = 128 << 20;

/// The payload bytes encoded at once under the memory budget `memory`: a sixteenth of it,
/// between 4 MiB and [`COMMIT_GROUP_BYTES`] (the groups change no output byte: payloads are
/// placed in the same order whatever their grouping).
pub fn group_bytes(memory: u64) -> u64 {
    (memory / 16).clamp(4 << 20, COMMIT_GROUP_BYTES)
}

/// attributes are taken from it; positions and colours from the voxels in memory).
/// Encodes one node's payload (entry offset left 0). `old` is the node's last payload when it is
/// a leaf with paged-out points (those come first) or an inner node with saved voxels (their
pub(crate) fn encode_node<'r>(
    n: &NodeView,
    old: Option<&[u8]>,
    record_len: usize,
    record: &(dyn Fn(u64) -> &'r [u8] + Sync),
) -> std::result::Result<(NodeEntry, Vec<u8>), PayloadError> {
    let key = n.key();
    let attr_len = record_len - 12;
    let old = old.map(super::codec::decode).transpose().map_err(|m| m.in_node(key.name()))?;
    let old =
        old.as_deref().map(DecodedLeaf::parse).transpose().map_err(|m| m.in_node(key.name()))?;
    let kept = if n.is_leaf() { n.paged_points() } else { n.saved_voxels() };
    if old.as_ref().is_some_and(|o| o.attr_len != attr_len || o.count as u64 != kept) {
        return Err(PayloadError::Stale { node: key.name() });
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
    if attrs.len() != count * attr_len {
        return Err(PayloadError::AttributeBytes { node: key.name(), bytes: attrs.len(), count });
    }
    crate::store::codec::encode_payload(
        key,
        kind,
        count,
        attr_len,
        |i| positions[i],
        |i| colors[i],
        |i| &attrs[i * attr_len..(i + 1) * attr_len],
        // The incremental engine's leaves are in arrival order: coded as they are.
        None,
    )
}

/// The bytes of `source.las`: the source's LAS header, VLRs and EVLRs, no points.
pub(crate) fn source_bytes(dir: &Path, meta: &SourceMeta) -> Result<Vec<u8>> {
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
    let mut bytes =
        las::write_header(&h).map_err(|error| Error::Las { path: dir.to_path_buf(), error })?;
    if !meta.evlrs.is_empty() {
        let start = bytes.len() as u64;
        let h = HeaderOut { evlr_start: start, evlr_count: meta.evlrs.len() as u32, ..h };
        bytes =
            las::write_header(&h).map_err(|error| Error::Las { path: dir.to_path_buf(), error })?;
        bytes.extend_from_slice(&las::write_evlrs(&meta.evlrs));
    }
    Ok(bytes)
}
