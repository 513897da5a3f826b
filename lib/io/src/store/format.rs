//! The store's binary layout (STORE_FORMAT.md): file names, headers, entries, payloads.

use mortar_core::octree::NodeKey;
use mortar_core::quantize::BatchGrid;

/// The source's LAS header, VLRs and EVLRs (no points).
pub const SOURCE_FILE: &str = "source.las";
/// Node payloads, append-only.
pub const NODES_FILE: &str = "nodes.bin";
/// The committed hierarchy.
pub const HIERARCHY_FILE: &str = "hierarchy.bin";

/// The file of payload segment `s`: `nodes.bin` for 0 (where builds append), `nodes-<s>.bin`
/// for the others (a merged part's payloads, or a compacted segment).
pub fn segment_file(s: u32) -> String {
    if s == 0 {
        NODES_FILE.to_string()
    } else {
        format!("nodes-{s}.bin")
    }
}

/// Magic of the segment table that follows the entries in `hierarchy.bin` when some entry's
/// payload lies in a segment other than 0.
pub(crate) const SEGMENTS_MAGIC: [u8; 8] = *b"MORTSEGS";

/// The segment table of a hierarchy: the bytes each segment's file holds for this commit,
/// segment 0 (`nodes.bin`) first. Segment 0's is the header's `nodes_len`; a table follows the
/// entries only when there is more than one segment: `MORTSEGS`, the count of segments after
/// segment 0 (u64), then their covered lengths (u64 each; 0 for a number not in use).
pub(crate) fn segments_bytes(covered: &[u64]) -> Vec<u8> {
    if covered.len() <= 1 {
        return Vec::new();
    }
    let mut b = SEGMENTS_MAGIC.to_vec();
    b.extend_from_slice(&(covered.len() as u64 - 1).to_le_bytes());
    for c in &covered[1..] {
        b.extend_from_slice(&c.to_le_bytes());
    }
    b
}

/// The covered lengths of segments 1.. from the bytes after the entries (empty: none), or
/// `None` where they are no segment table.
pub(crate) fn parse_segments(b: &[u8]) -> Option<Vec<u64>> {
    if b.is_empty() {
        return Some(Vec::new());
    }
    if b.len() < 16 || b[..8] != SEGMENTS_MAGIC {
        return None;
    }
    let n = u64::from_le_bytes(b[8..16].try_into().ok()?);
    // Sized by the bytes that are there, never by the count alone.
    if n == 0 || (b.len() - 16) as u64 != n.checked_mul(8)? {
        return None;
    }
    Some(b[16..].chunks_exact(8).map(|c| u64::from_le_bytes(c.try_into().expect("8"))).collect())
}

pub(crate) const NODE_MAGIC: [u8; 8] = *b"MORTNODE";
pub(crate) const HIERARCHY_MAGIC: [u8; 8] = *b"MORTHIER";
/// Version 3: payloads coded (`codec.rs`). Version 2: inner nodes' voxels are real source points
/// with their records (version 1 stored cell centres and colours only). A version 3 store may hold
/// raw (version 2) payloads: a version 2 store resumed or merged by this version is one.
pub(crate) const VERSION: u32 = 3;
/// The oldest version read: version 2 payloads are version 3's raw ones.
pub(crate) const OLDEST_READ: u32 = 2;

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
    /// Version 3 coding (`codec.rs`): codec, bytes of the coded body, colour mode; zero in raw
    /// (version 2) payloads.
    pub _pad: [u32; 3],
}

const _: () = assert!(std::mem::size_of::<NodeHeader>() == 64);

/// The header of `hierarchy.bin` (104 bytes).
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
pub(crate) const HIERARCHY_HEADER: usize = std::mem::size_of::<HierarchyHeader>();

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
    /// The payload file ([`segment_file`]): 0 is `nodes.bin`, where builds append; a merge
    /// links each part's `nodes.bin` in as a segment of its own.
    pub segment: u32,
    /// Points or voxels.
    pub count: u64,
    /// Offset of the payload ([`NodeHeader`] first) in its segment.
    pub offset: u64,
    /// Bytes of the payload.
    pub length: u64,
}

const _: () = assert!(std::mem::size_of::<NodeEntry>() == 48);

pub(crate) fn payload_len(count: u64, attr_len: u64) -> u64 {
    let raw = 64 + count * (16 + attr_len);
    raw.next_multiple_of(8)
}

/// The XYZ of a record (i32 at bytes 0, 4, 8).
pub(crate) fn read_xyz(r: &[u8]) -> [i32; 3] {
    [0, 4, 8].map(|o| i32::from_le_bytes([r[o], r[o + 1], r[o + 2], r[o + 3]]))
}

/// A node payload read back from `nodes.bin` (leaf points or an inner node's voxel points).
pub(crate) struct DecodedLeaf<'a> {
    pub(crate) count: usize,
    pub(crate) grid: BatchGrid,
    pub(crate) words: [&'a [u8]; 3],
    pub(crate) colors: &'a [u8],
    pub(crate) attributes: &'a [u8],
    pub(crate) attr_len: usize,
}

pub use crate::error::PayloadError;

impl PayloadError {
    /// `self` as an error of node `node`.
    pub(crate) fn in_node(self, node: impl ToString) -> PayloadError {
        PayloadError::InNode { node: node.to_string(), error: Box::new(self) }
    }
}

impl<'a> DecodedLeaf<'a> {
    pub(crate) fn parse(b: &'a [u8]) -> std::result::Result<DecodedLeaf<'a>, PayloadError> {
        if b.len() < 64 {
            return Err(PayloadError::Short);
        }
        let h: NodeHeader = bytemuck::pod_read_unaligned(&b[..64]);
        let (n, al) = (h.count as usize, h.attr_len as usize);
        if h.magic != NODE_MAGIC
            || h.kind > INNER
            || h._pad[0] != 0
            || (b.len() as u64) < payload_len(n as u64, al as u64)
            || h.bits[..3].iter().any(|&x| x > 30)
        {
            return Err(PayloadError::Damaged);
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

    pub(crate) fn u32_at(b: &[u8], i: usize) -> u32 {
        u32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
    }

    pub(crate) fn position(&self, i: usize) -> [i32; 3] {
        self.grid.decode_exact([0, 1, 2].map(|k| Self::u32_at(self.words[k], i)))
    }

    pub(crate) fn color(&self, i: usize) -> u32 {
        Self::u32_at(self.colors, i)
    }

    pub(crate) fn attributes(&self, i: usize) -> &'a [u8] {
        &self.attributes[i * self.attr_len..(i + 1) * self.attr_len]
    }
}

/// Encodes one node's raw (version 2) payload (entry offset left 0) from its `count` points:
/// `pos(i)`, `color(i)` and `attrs(i)` (the record's bytes after X, Y, Z: `attr_len` of them).
/// One pass for the bounds, one that writes every column in place. `codec::encode_payload`
/// codes it (what the engines write).
#[allow(clippy::too_many_arguments)]
pub(crate) fn encode_raw_payload<'r>(
    key: NodeKey,
    kind: u32,
    count: usize,
    attr_len: usize,
    pos: impl Fn(usize) -> [i32; 3],
    color: impl Fn(usize) -> u32,
    attrs: impl Fn(usize) -> &'r [u8],
) -> std::result::Result<(NodeEntry, Vec<u8>), PayloadError> {
    let grid = payload_grid(key, count, &pos)?;
    let len = payload_len(count as u64, attr_len as u64) as usize;
    let mut out = vec![0u8; len];
    let header = node_header(key, kind, count, &grid, attr_len);
    out[..64].copy_from_slice(bytemuck::bytes_of(&header));
    let (head, rest) = out[64..].split_at_mut(16 * count);
    let (w0, r) = head.split_at_mut(4 * count);
    let (w1, r) = r.split_at_mut(4 * count);
    let (w2, cols) = r.split_at_mut(4 * count);
    for i in 0..count {
        let w = grid.encode(pos(i));
        w0[4 * i..4 * i + 4].copy_from_slice(&w[0].to_le_bytes());
        w1[4 * i..4 * i + 4].copy_from_slice(&w[1].to_le_bytes());
        w2[4 * i..4 * i + 4].copy_from_slice(&w[2].to_le_bytes());
        cols[4 * i..4 * i + 4].copy_from_slice(&color(i).to_le_bytes());
        let a = attrs(i);
        debug_assert_eq!(a.len(), attr_len);
        rest[i * attr_len..(i + 1) * attr_len].copy_from_slice(a);
    }
    Ok((node_entry(key, kind, count, len), out))
}

/// The entry of a payload of `length` bytes for node `key` (segment and offset left 0: the
/// writer places it).
pub(crate) fn node_entry(key: NodeKey, kind: u32, count: usize, length: usize) -> NodeEntry {
    NodeEntry {
        level: key.level as u32,
        kind,
        index: key.index,
        segment: 0,
        count: count as u64,
        offset: 0,
        length: length as u64,
    }
}

/// The grid of a payload of `count` points `pos(i)`: the smallest that holds their bounds (one
/// pass over them). Errors where the node holds more points than a payload counts or its points
/// span more than 30 bits.
pub(crate) fn payload_grid(
    key: NodeKey,
    count: usize,
    pos: impl Fn(usize) -> [i32; 3],
) -> std::result::Result<BatchGrid, PayloadError> {
    if count > u32::MAX as usize {
        return Err(PayloadError::TooManyPoints { node: key.name(), count });
    }
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    for i in 0..count {
        let p = pos(i);
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    if count == 0 {
        (lo, hi) = ([0; 3], [0; 3]);
    }
    BatchGrid::for_bounds(lo, hi).ok_or_else(|| PayloadError::TooWide { node: key.name() })
}

/// The 64-byte header of a payload.
pub(crate) fn node_header(
    key: NodeKey,
    kind: u32,
    count: usize,
    grid: &BatchGrid,
    attr_len: usize,
) -> NodeHeader {
    NodeHeader {
        magic: NODE_MAGIC,
        level: key.level as u32,
        kind,
        index: key.index,
        count: count as u32,
        min: grid.min,
        bits: [grid.bits[0], grid.bits[1], grid.bits[2], 0],
        attr_len: attr_len as u32,
        _pad: [0; 3],
    }
}

/// `codec::encode_payload` for a node too large to hold encoded in memory (points at one position,
/// beyond the depth limit): the same bytes, written by `write(offset in the payload, bytes)`
/// column by column in slices of `slice` points, each slice encoded in parallel. Returns the
/// entry (its `offset` left 0).
#[allow(clippy::too_many_arguments)]
pub(crate) fn write_payload_sliced<'r, E>(
    key: NodeKey,
    kind: u32,
    count: usize,
    attr_len: usize,
    slice: usize,
    pos: impl Fn(usize) -> [i32; 3] + Sync,
    color: impl Fn(usize) -> u32 + Sync,
    attrs: impl Fn(usize) -> &'r [u8] + Sync,
    mut write: impl FnMut(u64, &[u8]) -> std::result::Result<(), E>,
) -> std::result::Result<std::result::Result<NodeEntry, PayloadError>, E> {
    use rayon::prelude::*;
    if count > u32::MAX as usize {
        return Ok(Err(PayloadError::TooManyPoints { node: key.name(), count }));
    }
    let (lo, hi) = (0..count)
        .into_par_iter()
        .fold(
            || ([i32::MAX; 3], [i32::MIN; 3]),
            |(mut lo, mut hi), i| {
                let p = pos(i);
                for a in 0..3 {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
                (lo, hi)
            },
        )
        .reduce(
            || ([i32::MAX; 3], [i32::MIN; 3]),
            |a, b| ([0, 1, 2].map(|k| a.0[k].min(b.0[k])), [0, 1, 2].map(|k| a.1[k].max(b.1[k]))),
        );
    let (lo, hi) = if count == 0 { ([0; 3], [0; 3]) } else { (lo, hi) };
    let Some(grid) = BatchGrid::for_bounds(lo, hi) else {
        return Ok(Err(PayloadError::TooWide { node: key.name() }));
    };
    let len = payload_len(count as u64, attr_len as u64);
    let header = node_header(key, kind, count, &grid, attr_len);
    write(0, bytemuck::bytes_of(&header))?;
    let n = count as u64;
    let slice = slice.max(1);
    for s in (0..count).step_by(slice) {
        let e = (s + slice).min(count);
        write_slice(
            &grid,
            n,
            s,
            e - s,
            attr_len,
            |k| pos(s + k),
            |k| color(s + k),
            |k| attrs(s + k),
            &mut write,
        )?;
    }
    let end = 64 + n * (16 + attr_len as u64);
    if len > end {
        write(end, &vec![0u8; (len - end) as usize])?;
    }
    Ok(Ok(NodeEntry {
        level: key.level as u32,
        kind,
        index: key.index,
        segment: 0,
        count: n,
        offset: 0,
        length: len,
    }))
}

/// Writes the columns of the points `s..s + m` of a payload of `n` points on `grid` (`pos`,
/// `color` and `attrs` of the slice's point `k`).
#[allow(clippy::too_many_arguments)]
fn write_slice<'r, E>(
    grid: &BatchGrid,
    n: u64,
    s: usize,
    m: usize,
    attr_len: usize,
    pos: impl Fn(usize) -> [i32; 3] + Sync,
    color: impl Fn(usize) -> u32 + Sync,
    attrs: impl Fn(usize) -> &'r [u8] + Sync,
    write: &mut impl FnMut(u64, &[u8]) -> std::result::Result<(), E>,
) -> std::result::Result<(), E> {
    use rayon::prelude::*;
    let mut cols = vec![0u8; 16 * m];
    let mut at = vec![0u8; attr_len * m];
    cols.par_chunks_mut(4).zip(0..4 * m).for_each(|(c, j)| {
        let (col, k) = (j / m, j % m);
        let v = if col < 3 { grid.encode(pos(k))[col] } else { color(k) };
        c.copy_from_slice(&v.to_le_bytes());
    });
    if attr_len > 0 {
        at.par_chunks_mut(attr_len).enumerate().for_each(|(k, a)| a.copy_from_slice(attrs(k)));
    }
    for col in 0..4u64 {
        let c = col as usize;
        write(64 + col * 4 * n + 4 * s as u64, &cols[4 * m * c..4 * m * (c + 1)])?;
    }
    write(64 + 16 * n + (s * attr_len) as u64, &at)
}

/// The payload `codec::encode_payload` makes of a node of `count` points inside `bounds` (their
/// smallest and largest position) whose records (`12 + attr_len` bytes: position, then the
/// attributes) `records(range)` reads, `slice` points at a time, in order: a leaf larger than
/// memory (`dense.rs`). `color` gives a record's packed colour.
#[allow(clippy::too_many_arguments)]
pub(crate) fn write_payload_blocks<E>(
    key: NodeKey,
    kind: u32,
    count: usize,
    attr_len: usize,
    bounds: ([i32; 3], [i32; 3]),
    slice: usize,
    mut records: impl FnMut(std::ops::Range<usize>) -> std::result::Result<Vec<u8>, E>,
    color: impl Fn(&[u8]) -> u32 + Sync,
    mut write: impl FnMut(u64, &[u8]) -> std::result::Result<(), E>,
) -> std::result::Result<std::result::Result<NodeEntry, PayloadError>, E> {
    if count > u32::MAX as usize {
        return Ok(Err(PayloadError::TooManyPoints { node: key.name(), count }));
    }
    let (lo, hi) = if count == 0 { ([0; 3], [0; 3]) } else { bounds };
    let Some(grid) = BatchGrid::for_bounds(lo, hi) else {
        return Ok(Err(PayloadError::TooWide { node: key.name() }));
    };
    let len = payload_len(count as u64, attr_len as u64);
    let header = node_header(key, kind, count, &grid, attr_len);
    write(0, bytemuck::bytes_of(&header))?;
    let n = count as u64;
    let rl = 12 + attr_len;
    let slice = slice.max(1);
    for s in (0..count).step_by(slice) {
        let e = (s + slice).min(count);
        let recs = records(s..e)?;
        let rec = |k: usize| &recs[k * rl..(k + 1) * rl];
        write_slice(
            &grid,
            n,
            s,
            e - s,
            attr_len,
            |k| mortar_core::layout::read_xyz(rec(k)),
            |k| color(rec(k)),
            |k| &rec(k)[12..],
            &mut write,
        )?;
    }
    let end = 64 + n * (16 + attr_len as u64);
    if len > end {
        write(end, &vec![0u8; (len - end) as usize])?;
    }
    Ok(Ok(NodeEntry {
        level: key.level as u32,
        kind,
        index: key.index,
        segment: 0,
        count: n,
        offset: 0,
        length: len,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A payload written in slices is the payload encoded whole, byte for byte, whatever the
    /// slice (one point, a few, more than the node).
    #[test]
    fn sliced_payload_equals_whole_payload() {
        let attr_len = 7;
        let n = 1000;
        let pos = |i: usize| {
            [(i as i32 * 37) % 1001 - 500, (i as i32 * 11) % 97, 123_456 + (i as i32 % 5)]
        };
        let color = |i: usize| 0x0102_0304u32.wrapping_mul(i as u32 + 1);
        let attrs: Vec<u8> = (0..n * attr_len).map(|b| (b * 31 % 251) as u8).collect();
        let attr = |i: usize| &attrs[i * attr_len..(i + 1) * attr_len];
        let key = NodeKey { level: 3, index: [1, 2, 3] };
        let (want_entry, want) =
            encode_raw_payload(key, LEAF, n, attr_len, pos, color, attr).unwrap();
        for slice in [1, 3, 64, 999, 1000, 5000] {
            let mut got = vec![0xAAu8; want.len()];
            let entry = write_payload_sliced::<()>(
                key,
                LEAF,
                n,
                attr_len,
                slice,
                pos,
                color,
                attr,
                |at, b| {
                    got[at as usize..at as usize + b.len()].copy_from_slice(b);
                    Ok(())
                },
            )
            .unwrap()
            .unwrap();
            assert!(got == want, "slice {slice}: the bytes differ");
            assert_eq!(
                (entry.count, entry.length, entry.kind),
                (want_entry.count, want_entry.length, want_entry.kind)
            );
        }
    }
}

#[cfg(test)]
mod segment_tests {
    use super::*;

    #[test]
    fn a_segment_table_reads_back_and_damaged_ones_are_refused() {
        assert!(segments_bytes(&[5]).is_empty(), "one segment: no table");
        assert_eq!(parse_segments(&[]), Some(vec![]));
        let b = segments_bytes(&[8, 0, 64]);
        assert_eq!(b.len(), 16 + 16);
        assert_eq!(parse_segments(&b), Some(vec![0, 64]));
        // Short, another magic, a count that lies, a count of zero: no table.
        assert_eq!(parse_segments(&b[..b.len() - 1]), None);
        let mut m = b.clone();
        m[0] = b'X';
        assert_eq!(parse_segments(&m), None);
        let mut c = b.clone();
        c[8..16].copy_from_slice(&u64::MAX.to_le_bytes());
        assert_eq!(parse_segments(&c), None);
        let mut z = b[..16].to_vec();
        z[8..16].copy_from_slice(&0u64.to_le_bytes());
        assert_eq!(parse_segments(&z), None);
        assert_eq!(segment_file(0), NODES_FILE);
        assert_eq!(segment_file(12), "nodes-12.bin");
    }
}
