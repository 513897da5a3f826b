//! Reading a store's last commit.

use crate::dataset::RecordSource;
use crate::error::{Error, Result, StoreError};
use crate::las::{self, Header, Vlr};
use crate::source::{LasInput, Piece};
use memmap2::Mmap;
use mortar_core::layout::RecordLayout;
use mortar_core::octree::Cube;
use mortar_core::quantize::BatchGrid;
use std::borrow::Cow;
use std::fs::File;
use std::path::{Path, PathBuf};

use super::codec;
use super::format::*;
use crate::error::PayloadError;

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
    /// Bytes of each payload segment this commit covers (segment 0, `nodes.bin`, first).
    pub covered: Vec<u64>,
    /// Each segment's map (`None` where it covers nothing).
    nodes: Vec<Option<Mmap>>,
    leaves: Vec<usize>,
    /// Coded payloads decoded on first use by [`node`](Store::node) (raw ones are read in the
    /// map). Kept while the store is open: a view holds what it has drawn (not bounded yet).
    decoded: Vec<std::sync::OnceLock<Vec<u64>>>,
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
        BatchGrid {
            min: self.header.min,
            bits: [self.header.bits[0], self.header.bits[1], self.header.bits[2]],
        }
    }
}

impl Store {
    /// Opens the last commit of the store `dir`, checking every length against the bytes that
    /// exist. A segment that a compaction removed between reading the hierarchy and opening
    /// the segment is found by reading the new hierarchy (a few tries).
    pub fn open(dir: &Path) -> Result<Store> {
        let mut tries = 0;
        loop {
            match Store::open_once(dir) {
                Err(Error::Io { path, source })
                    if tries < 3
                        && source.kind() == std::io::ErrorKind::NotFound
                        && path
                            .file_name()
                            .is_some_and(|n| n.to_string_lossy().starts_with("nodes-")) =>
                {
                    tries += 1;
                }
                r => return r,
            }
        }
    }

    fn open_once(dir: &Path) -> Result<Store> {
        let bad = |error: StoreError| Error::Store { path: dir.to_path_buf(), error };
        let src = LasInput::open(&dir.join(SOURCE_FILE))?;
        let hp = dir.join(HIERARCHY_FILE);
        let hb = std::fs::read(&hp).map_err(|e| Error::io(&hp, e))?;
        if hb.len() < HIERARCHY_HEADER {
            return Err(bad(StoreError::HierarchyTruncated));
        }
        let header: HierarchyHeader = bytemuck::pod_read_unaligned(&hb[..HIERARCHY_HEADER]);
        if header.magic != HIERARCHY_MAGIC {
            return Err(bad(StoreError::NotHierarchy));
        }
        if !(OLDEST_READ..=VERSION).contains(&header.version) || header.entry_size != 48 {
            return Err(bad(StoreError::Version {
                version: header.version,
                entry_size: header.entry_size,
            }));
        }
        let avail = (hb.len() - HIERARCHY_HEADER) as u64 / 48;
        let end = (header.node_count as usize)
            .checked_mul(48)
            .and_then(|b| b.checked_add(HIERARCHY_HEADER))
            .filter(|&e| e <= hb.len())
            .ok_or_else(|| {
                bad(StoreError::NodeCount { declared: header.node_count, held: avail })
            })?;
        let entries: Vec<NodeEntry> = bytemuck::pod_collect_to_vec(&hb[HIERARCHY_HEADER..end]);
        let Some(more) = parse_segments(&hb[end..]) else {
            // Extra bytes that are no table: a hierarchy of another entry count, or damaged.
            if !(hb.len() - HIERARCHY_HEADER).is_multiple_of(48) || avail != header.node_count {
                return Err(bad(StoreError::NodeCount {
                    declared: header.node_count,
                    held: avail,
                }));
            }
            return Err(bad(StoreError::SegmentTable));
        };
        let mut covered = vec![header.nodes_len];
        covered.extend(more);
        let mut nodes = Vec::with_capacity(covered.len());
        for (s, &c) in covered.iter().enumerate() {
            let name = segment_file(s as u32);
            let np = dir.join(&name);
            if c == 0 && !np.exists() {
                nodes.push(None);
                continue;
            }
            let f = File::open(&np).map_err(|e| Error::io(&np, e))?;
            let file_len = f.metadata().map_err(|e| Error::io(&np, e))?.len();
            if c > file_len {
                return Err(bad(StoreError::NodesShort { file: name, held: file_len, covered: c }));
            }
            // SAFETY: segment 0 is only appended to while it is mapped (by a builder) and the
            // others never change once linked in; the part read (up to the covered length)
            // never changes after its commit.
            nodes.push(if c == 0 {
                None
            } else {
                Some(unsafe { Mmap::map(&f) }.map_err(|e| Error::io(&np, e))?)
            });
        }
        let layout = src.layout.clone();
        let attr_len = layout.record_len as u64 - 12;
        let mut leaves = Vec::new();
        let mut points = 0u64;
        for (i, e) in entries.iter().enumerate() {
            let al = attr_len;
            let damaged = || {
                bad(StoreError::EntryDamaged {
                    node: i,
                    kind: e.kind,
                    count: e.count,
                    length: e.length,
                    offset: e.offset,
                })
            };
            let seg = covered.get(e.segment as usize).copied().unwrap_or(0);
            if e.kind > INNER
                || e.offset % 8 != 0
                || e.count > u32::MAX as u64
                || e.length < 64
                || e.offset.checked_add(e.length).is_none_or(|end| end > seg)
            {
                return Err(damaged());
            }
            let nb = &nodes[e.segment as usize].as_ref().expect("covered bytes are mapped")
                [e.offset as usize..(e.offset + e.length) as usize];
            let h: NodeHeader = bytemuck::pod_read_unaligned(&nb[..64]);
            if h.magic != NODE_MAGIC
                || h.count as u64 != e.count
                || h.kind != e.kind
                || h.attr_len as u64 != al
                || h.bits[..3].iter().any(|&b| b > 30)
                || (header.version < VERSION && codec::codec_of(&h) != codec::RAW)
            {
                return Err(bad(StoreError::PayloadMismatch { node: i }));
            }
            if codec::stored_len(&h) != Some(e.length) {
                return Err(damaged());
            }
            if e.kind == LEAF {
                leaves.push(i);
                points += e.count;
            }
        }
        if points != header.points {
            return Err(bad(StoreError::LeafPoints { leaves: points, declared: header.points }));
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
        let decoded = (0..entries.len()).map(|_| std::sync::OnceLock::new()).collect();
        Ok(Store {
            path: dir.to_path_buf(),
            meta,
            layout,
            header,
            entries,
            covered,
            nodes,
            leaves,
            decoded,
        })
    }

    /// Every leaf record in arrival order (the order of the build's inputs), from the store's
    /// `arrival.bin` ([`super::arrival`]); `None` where it has none. The records are those
    /// `mortar sort store/` gives (exact positions, every attribute byte), each put at its rank:
    /// the leaves in Morton order of their cubes, each leaf's points in its coded order, are
    /// the order the file lists ranks in. Holds all records in memory.
    /// With them, the box the inputs' headers declared.
    pub fn records_in_arrival_order(
        &self,
    ) -> Result<Option<(Vec<u8>, super::arrival::DeclaredBox)>> {
        let Some(super::arrival::Arrival { ranks, declared, .. }) =
            super::arrival::read(&self.path, self.header.points)?
        else {
            return Ok(None);
        };
        let bad = |why: String| Error::Store {
            path: self.path.join(super::arrival::ARRIVAL_FILE),
            error: StoreError::Arrival { why },
        };
        let (leaves, starts): (Vec<usize>, Vec<usize>) =
            self.leaf_rank_starts().map_err(bad)?.into_iter().unzip();
        let rl = self.layout.record_len;
        let mut out = crate::sort::zeroed_huge::<u8>(ranks.len() * rl);
        let op = mortar_core::par::SendPtr(out.as_mut_ptr());
        use rayon::prelude::*;
        leaves.par_iter().zip(starts).try_for_each(|(&l, s)| {
            let op = &op;
            let (raw, seq) =
                codec::decode_ordered(self.node_bytes(l)).map_err(|e| self.damaged(l, e))?;
            let d = node_data(&raw);
            let g = d.grid();
            let al = d.header.attr_len as usize;
            for i in 0..d.header.count as usize {
                // The ranks are listed in the leaf's coded order.
                let c = seq.as_ref().map_or(i, |q| q[i] as usize);
                let to = ranks[s + c] as usize * rl;
                // SAFETY: the ranks are a permutation of 0..points (checked on reading), so
                // each record's slot is written once, within `out`.
                let slot = unsafe { std::slice::from_raw_parts_mut(op.0.add(to), 12 + al) };
                d.record_into(&g, i, slot);
            }
            Ok::<(), Error>(())
        })?;
        Ok(Some((out, declared)))
    }

    /// The leaves in the order `arrival.bin` lists their ranks (Morton order of their cubes'
    /// corners), each with where its ranks begin there; or why the tree cannot be listed.
    pub(crate) fn leaf_rank_starts(&self) -> std::result::Result<Vec<(usize, usize)>, String> {
        let log2 = self.header.root_size_log2;
        if log2 > 32 {
            return Err(format!("a root cube of 2^{log2} units is not supported"));
        }
        // Each leaf's corner, as an offset from the root's (below 2^32 on every axis).
        let mut leaves: Vec<(usize, [u32; 3])> = Vec::with_capacity(self.leaves.len());
        for &l in &self.leaves {
            let e = &self.entries[l];
            let Some(shift) = log2.checked_sub(e.level) else {
                return Err(format!(
                    "leaf {l} lies deeper (level {}) than its root's units",
                    e.level
                ));
            };
            leaves.push((l, e.index.map(|i| ((i as u64) << shift) as u32)));
        }
        leaves.sort_unstable_by(|a, b| codec::morton_cmp(a.1, b.1));
        let mut at = 0usize;
        Ok(leaves
            .into_iter()
            .map(|(l, _)| {
                let s = at;
                at += self.entries[l].count as usize;
                (l, s)
            })
            .collect())
    }

    /// Indices of the leaf entries.
    pub fn leaves(&self) -> &[usize] {
        &self.leaves
    }

    /// The root cube.
    pub fn root_cube(&self) -> Cube {
        Cube { min: self.header.root_min, size_log2: self.header.root_size_log2 as u8 }
    }

    /// The bytes of node entry `i`'s payload as stored (its header first; coded or raw).
    pub fn node_bytes(&self, i: usize) -> &[u8] {
        let e = &self.entries[i];
        &self.nodes[e.segment as usize].as_ref().expect("checked at open")
            [e.offset as usize..(e.offset + e.length) as usize]
    }

    /// The version 2 bytes of node entry `i`'s payload, decoded where it is coded (not kept).
    pub(crate) fn raw_node(&self, i: usize) -> Result<codec::Decoded<'_>> {
        codec::decode(self.node_bytes(i)).map_err(|error| self.damaged(i, error))
    }

    pub(crate) fn damaged(&self, i: usize, error: PayloadError) -> Error {
        let file = segment_file(self.entries[i].segment);
        Error::Payload { path: self.path.join(file), error: error.in_node(i) }
    }

    /// The payload of node entry `i`: in the map where it is raw, else decoded once and kept
    /// while the store is open. An error names the store's `nodes.bin` where the payload does
    /// not decode.
    pub fn try_node(&self, i: usize) -> Result<NodeData<'_>> {
        let b: &[u8] =
            match codec::codec_of(&bytemuck::pod_read_unaligned(&self.node_bytes(i)[..64])) {
                codec::RAW => self.node_bytes(i),
                _ => {
                    let w = match self.decoded[i].get() {
                        Some(w) => w,
                        None => {
                            let w = self.raw_node(i)?.into_words();
                            self.decoded[i].get_or_init(|| w)
                        }
                    };
                    bytemuck::cast_slice(w)
                }
            };
        Ok(node_data(b))
    }

    /// [`try_node`](Self::try_node) for callers that cannot fail: a payload that does not decode
    /// reads as a node without points (the error is printed once per node).
    pub fn node(&self, i: usize) -> NodeData<'_> {
        match self.try_node(i) {
            Ok(d) => d,
            Err(e) => {
                let w = self.decoded[i].get_or_init(|| {
                    eprintln!("warning: {e}");
                    let h: NodeHeader = bytemuck::pod_read_unaligned(&self.node_bytes(i)[..64]);
                    let empty = NodeHeader { count: 0, _pad: [0; 3], ..h };
                    let mut w = vec![0u64; 8];
                    bytemuck::cast_slice_mut::<u64, u8>(&mut w)
                        .copy_from_slice(bytemuck::bytes_of(&empty));
                    w
                });
                node_data(bytemuck::cast_slice(w))
            }
        }
    }
}

/// The columns of the version 2 payload `b` (8-aligned: in the map, or decoded into words).
impl NodeData<'_> {
    /// The whole record of leaf point `i` (exact position, then every attribute byte) written
    /// into `out` (`12 + attr_len` bytes); `g` is [`NodeData::grid`].
    pub(crate) fn record_into(&self, g: &BatchGrid, i: usize, out: &mut [u8]) {
        let al = self.header.attr_len as usize;
        let p = g.decode_exact([self.words[0][i], self.words[1][i], self.words[2][i]]);
        for a in 0..3 {
            out[4 * a..4 * a + 4].copy_from_slice(&p[a].to_le_bytes());
        }
        out[12..12 + al].copy_from_slice(&self.attributes[i * al..(i + 1) * al]);
    }
}

pub(crate) fn node_data(b: &[u8]) -> NodeData<'_> {
    let header: NodeHeader = bytemuck::pod_read_unaligned(&b[..64]);
    let n = header.count as usize;
    let words_at =
        |k: usize| -> &[u32] { bytemuck::cast_slice(&b[64 + 4 * n * k..64 + 4 * n * (k + 1)]) };
    let attributes = &b[64 + 16 * n..64 + 16 * n + n * header.attr_len as usize];
    NodeData {
        header,
        words: [words_at(0), words_at(1), words_at(2)],
        colors: words_at(3),
        attributes,
    }
}

/// Leaves per piece when a store is read as records (about 1 M points with full leaves).
pub(crate) const LEAVES_PER_PIECE: usize = 20;

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
        let leaves = self
            .leaves
            .get(start..(start + LEAVES_PER_PIECE).min(self.leaves.len()))
            .unwrap_or(&[]);
        let mut out = Vec::with_capacity(piece.points as usize * rl);
        for &l in leaves {
            let raw = self.raw_node(l)?;
            let d = node_data(&raw);
            let g = d.grid();
            let al = d.header.attr_len as usize;
            for i in 0..d.header.count as usize {
                let at = out.len();
                out.resize(at + 12 + al, 0);
                d.record_into(&g, i, &mut out[at..]);
            }
        }
        if out.len() != piece.points as usize * rl {
            return Err(Error::Store {
                path: self.path.clone(),
                error: StoreError::PieceCount { piece: piece.index },
            });
        }
        Ok(Cow::Owned(out))
    }
    fn is_compressed(&self) -> bool {
        false
    }
}
