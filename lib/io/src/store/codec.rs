//! Version 3 node payloads: the version 2 payload (`format.rs`, STORE_FORMAT.md) coded into
//! fewer bytes, and decoded back to exactly those bytes.
//!
//! A coded payload keeps the 64-byte [`NodeHeader`] as it is, with three of its padding words
//! set: `_pad[0]` the codec ([`RAW`] or [`ZSTD_COLUMNS`]), `_pad[1]` the bytes of the coded
//! body that follows the header, `_pad[2]` how colours are kept (below). The body is one zstd
//! frame (level [`LEVEL`]) of, in order:
//!
//! 1. positions: per axis, the point's offset from the frame's minimum as a `u32`, as the
//!    difference from the previous point's (wrapping, zig-zag: `(d << 1) ^ (d >> 31)`), split in
//!    four byte planes (all low bytes, then all second bytes, ...): points in Morton order are
//!    near their predecessor, so the high planes are mostly zero;
//! 2. colours, by `_pad[2]`'s low byte: [`COLOR_PLANES`] four byte planes of the RGBA8 words;
//!    [`COLOR_GREY`] one plane (grey: `g = b = r`, `a = 255`, as intensity colours are);
//!    [`COLOR_RGB8`] / [`COLOR_RGB16`] nothing: every colour is the record's RGB (at attribute
//!    offset `_pad[2] >> 8`) taken as 8-bit values or by their high bytes, as the build's colour
//!    rule makes them (`mortar_core::color`), so they are computed again from the records;
//! 3. attributes transposed: byte `j` of every point's attributes, for `j` in `0..attr_len`.
//!
//! [`ZSTD_GPS_ORDER`] codes the same columns with the points in acquisition order (a stable sort
//! by GPS time), where the records keep GPS time: consecutive pulses are near each other and their
//! times differ little, which zstd codes far better than Morton order's jumps (real scans 1.5x
//! smaller, BENCHMARKS.md "Store v3"). The body starts with the node cube's corner (3 `i64`) and
//! the GPS time's attribute offset (`u32`); then the positions (as above, in coded order), the
//! colours, GPS time as the wrapping differences of its order-preserving `u64` key (eight byte
//! planes) and the other attribute bytes as planes. Decoding puts the points back in the node's
//! order by a stable sort of their full-resolution Morton keys relative to the cube's corner,
//! which is the order every engine gives a node (Morton order of the root's grid, points at one
//! position by arrival); the encoder takes this codec only where that sort gives the payload's
//! order back exactly (not where points at one position arrived out of GPS time order, nor for
//! the incremental engine's leaves, which keep arrival order), so decoding stays exact.
//!
//! The coded words are not stored: a payload's words are `BatchGrid::encode` of its exact
//! positions, so they are computed again. A payload whose words are not that (none that mortar
//! writes) or that holds no point stays [`RAW`]: the version 2 bytes, padding words zero. So
//! [`decode`] of [`encode`] is the version 2 payload byte for byte, what the tests check.
//!
//! Decoding never allocates by what a header claims before the data is there: the frame is read
//! as a stream into a buffer that grows with what it yields, cut at the size the header implies.

use super::format::{payload_len, NodeEntry, NodeHeader, NODE_MAGIC};
use crate::error::PayloadError;
use mortar_core::octree::NodeKey;
use mortar_core::quantize::BatchGrid;
use std::io::Read;

/// The version 2 layout, as it is.
pub(crate) const RAW: u32 = 0;
/// Columns coded as the module docs say, in one zstd frame.
pub(crate) const ZSTD_COLUMNS: u32 = 1;
/// Columns coded in acquisition order (GPS time), the node's order recomputed on decoding
/// ([`Order`]).
pub(crate) const ZSTD_GPS_ORDER: u32 = 2;
/// Largest raw payload that is coded: larger ones (nodes beyond the depth limit, or inner nodes
/// of extreme density) stay raw, so every engine writes them in slices without holding them,
/// and every engine gives a node the same bytes whatever its memory budget. An engine codes
/// payloads up to this size in memory even under a budget whose encoding groups are smaller
/// (below `--memory` 256M): one such payload at a time, about 2.5 times this size.
pub(crate) const CODE_LIMIT: u64 = 16 << 20;
/// zstd's level: the fastest, measured against 3 in BENCHMARKS.md ("Store v3").
pub(crate) const LEVEL: i32 = 1;

/// Colours as four byte planes.
pub(crate) const COLOR_PLANES: u32 = 0;
/// Grey colours: one plane.
pub(crate) const COLOR_GREY: u32 = 1;
/// Colours are the records' 8-bit RGB values.
pub(crate) const COLOR_RGB8: u32 = 2;
/// Colours are the high bytes of the records' 16-bit RGB values.
pub(crate) const COLOR_RGB16: u32 = 3;

/// Attribute offsets of RGB in the LAS point formats that have it (2: 8; 3, 5: 16; 7, 8, 10:
/// 18), the candidates for [`COLOR_RGB8`] and [`COLOR_RGB16`].
const RGB_OFFSETS: [usize; 3] = [8, 16, 18];

fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
}

fn rgb_of(attrs: &[u8], off: usize, sixteen: bool) -> u32 {
    let c = |k: usize| {
        let v = u16::from_le_bytes([attrs[off + 2 * k], attrs[off + 2 * k + 1]]);
        (if sixteen { v >> 8 } else { v & 0xff }) as u32
    };
    c(0) | (c(1) << 8) | (c(2) << 16) | (255 << 24)
}

/// The points a payload is coded from: a version 2 payload's columns ([`Columns`]) or an
/// engine's records gathered into columns ([`Gathered`]), so that one coder serves both (and
/// the engines code without making the version 2 payload first).
trait Points<'a> {
    fn len(&self) -> usize;
    /// The exact position of point `i`.
    fn pos(&self, i: usize) -> [i32; 3];
    /// Its RGBA8 colour word.
    fn color(&self, i: usize) -> u32;
    /// Its attribute bytes (the record after X, Y, Z).
    fn attrs(&self, i: usize) -> &'a [u8];
}

/// The columns of a version 2 payload; positions are decoded from the words where they are
/// needed (no copy: a payload of CODE_LIMIT bytes is coded under tight budgets, two at a time).
struct Columns<'a> {
    grid: BatchGrid,
    w: [&'a [u8]; 3],
    colors: &'a [u8],
    attrs: &'a [u8],
    n: usize,
    al: usize,
}

impl Columns<'_> {
    fn words(&self, i: usize) -> [u32; 3] {
        [u32_at(self.w[0], i), u32_at(self.w[1], i), u32_at(self.w[2], i)]
    }
}

impl<'a> Points<'a> for Columns<'a> {
    fn len(&self) -> usize {
        self.n
    }
    fn pos(&self, i: usize) -> [i32; 3] {
        self.grid.decode_exact(self.words(i))
    }
    fn color(&self, i: usize) -> u32 {
        u32_at(self.colors, i)
    }
    fn attrs(&self, i: usize) -> &'a [u8] {
        &self.attrs[i * self.al..(i + 1) * self.al]
    }
}

/// An engine's points copied into columns of their own ([`encode_payload`]).
struct Gathered {
    pos: Vec<[i32; 3]>,
    color: Vec<u32>,
    attrs: Vec<u8>,
    al: usize,
}

impl Gathered {
    fn of<'r>(
        n: usize,
        al: usize,
        pos: impl Fn(usize) -> [i32; 3],
        color: impl Fn(usize) -> u32,
        attrs: impl Fn(usize) -> &'r [u8],
    ) -> Gathered {
        let mut g = Gathered {
            pos: Vec::with_capacity(n),
            color: Vec::with_capacity(n),
            attrs: Vec::with_capacity(n * al),
            al,
        };
        for i in 0..n {
            g.pos.push(pos(i));
            g.color.push(color(i));
            g.attrs.extend_from_slice(&attrs(i)[..al]);
        }
        g
    }
}

impl<'a> Points<'a> for &'a Gathered {
    fn len(&self) -> usize {
        self.pos.len()
    }
    #[inline]
    fn pos(&self, i: usize) -> [i32; 3] {
        self.pos[i]
    }
    #[inline]
    fn color(&self, i: usize) -> u32 {
        self.color[i]
    }
    #[inline]
    fn attrs(&self, i: usize) -> &'a [u8] {
        &self.attrs[i * self.al..(i + 1) * self.al]
    }
}

/// How the colours of the points are kept (the `_pad[2]` word).
fn color_mode<'a>(src: &impl Points<'a>, al: usize) -> u32 {
    let n = src.len();
    for off in RGB_OFFSETS.into_iter().filter(|&o| o + 6 <= al) {
        // 8-bit values must fit a byte for the colour to be the value itself.
        for (mode, sixteen) in [(COLOR_RGB8, false), (COLOR_RGB16, true)] {
            let fits = (0..n).all(|i| {
                let a = src.attrs(i);
                (sixteen || (0..3).all(|k| a[off + 2 * k + 1] == 0))
                    && rgb_of(a, off, sixteen) == src.color(i)
            });
            if fits {
                return mode | (off as u32) << 8;
            }
        }
    }
    let grey = (0..n).all(|i| {
        let c = src.color(i);
        let r = c & 0xff;
        c == r | r << 8 | r << 16 | 255 << 24
    });
    if grey {
        COLOR_GREY
    } else {
        COLOR_PLANES
    }
}

thread_local! {
    static COMPRESSOR: std::cell::RefCell<Option<zstd::bulk::Compressor<'static>>> =
        const { std::cell::RefCell::new(None) };
}

fn zstd_compress(body: &[u8]) -> Option<Vec<u8>> {
    COMPRESSOR.with(|c| {
        let mut c = c.borrow_mut();
        if c.is_none() {
            *c = zstd::bulk::Compressor::new(LEVEL).ok();
        }
        c.as_mut()?.compress(body).ok()
    })
}

/// The version 3 payload of the version 2 payload `raw` (made by `encode_payload`): coded, or
/// `raw` itself where coding does not apply (see the module docs). With `order` (the node's cube
/// and where its records keep GPS time) the points are coded in GPS time order where the
/// node's own order can be recomputed from them ([`ZSTD_GPS_ORDER`]), else in their order.
pub(crate) fn encode(raw: Vec<u8>, order: Option<Order>) -> Vec<u8> {
    if raw.len() as u64 > CODE_LIMIT || raw.len() < 64 {
        return raw;
    }
    let h: NodeHeader = bytemuck::pod_read_unaligned(&raw[..64]);
    let (n, al) = (h.count as usize, h.attr_len as usize);
    if h.magic != NODE_MAGIC
        || n == 0
        || h._pad != [0; 3]
        || (raw.len() as u64) < payload_len(n as u64, al as u64)
        || h.bits[..3].iter().any(|&b| b > 30)
    {
        return raw;
    }
    let col = |k: usize| &raw[64 + 4 * n * k..64 + 4 * n * (k + 1)];
    let src = Columns {
        grid: BatchGrid { min: h.min, bits: [h.bits[0], h.bits[1], h.bits[2]] },
        w: [col(0), col(1), col(2)],
        colors: col(3),
        attrs: &raw[64 + 16 * n..64 + 16 * n + n * al],
        n,
        al,
    };
    // The words must be those of the exact positions, as every payload mortar writes has them.
    if (0..n).any(|i| src.grid.encode(src.pos(i)) != src.words(i)) {
        return raw;
    }
    coded(h, &src, order, raw.len()).map_or(raw, |(c, _)| c)
}

/// The coded payload of the points `src` under header `h`, or `None` where it would not be
/// smaller than the version 2 payload's `raw_len` bytes.
fn coded<'a>(
    h: NodeHeader,
    src: &impl Points<'a>,
    order: Option<Order>,
    raw_len: usize,
) -> Option<(Vec<u8>, Option<Vec<u32>>)> {
    let order = order.filter(|_| !morton_only());
    let (codec, mode, body, seq) = body_of(src, h.min, h.attr_len as usize, order)?;
    let z = zstd_compress(&body)?;
    let total = (64 + z.len()).next_multiple_of(8);
    if total >= raw_len || z.len() > u32::MAX as usize {
        return None;
    }
    let mut out = Vec::with_capacity(total);
    let h = NodeHeader { _pad: [codec, z.len() as u32, mode], ..h };
    out.extend_from_slice(bytemuck::bytes_of(&h));
    out.extend_from_slice(&z);
    out.resize(total, 0);
    Some((out, seq))
}

/// Encodes one node's payload (entry offset left 0) from its `count` points: `pos(i)`,
/// `color(i)` and `attrs(i)` (the record's bytes after X, Y, Z: `attr_len` of them). One pass
/// for the bounds, then the version 3 coding straight from the points (the bytes [`encode`]
/// gives for the version 2 payload
/// [`encode_raw_payload`](super::format::encode_raw_payload) makes, which is made only where the
/// payload stays raw).
#[allow(clippy::too_many_arguments)]
pub(crate) fn encode_payload<'r>(
    key: NodeKey,
    kind: u32,
    count: usize,
    attr_len: usize,
    pos: impl Fn(usize) -> [i32; 3],
    color: impl Fn(usize) -> u32,
    attrs: impl Fn(usize) -> &'r [u8],
    order: Option<Order>,
) -> std::result::Result<(NodeEntry, Vec<u8>), PayloadError> {
    encode_payload_ordered(key, kind, count, attr_len, pos, color, attrs, order)
        .map(|(e, b, _)| (e, b))
}

/// The order a payload's points are coded in where it is not the payload's own (codec 2).
pub(crate) type CodedOrder = Option<Vec<u32>>;

/// [`encode_payload`], and the coded order where it is not the payload's (codec 2): `seq[t]` is
/// the payload index of coded point `t`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn encode_payload_ordered<'r>(
    key: NodeKey,
    kind: u32,
    count: usize,
    attr_len: usize,
    pos: impl Fn(usize) -> [i32; 3],
    color: impl Fn(usize) -> u32,
    attrs: impl Fn(usize) -> &'r [u8],
    order: Option<Order>,
) -> std::result::Result<(NodeEntry, Vec<u8>, CodedOrder), PayloadError> {
    let raw_len = payload_len(count as u64, attr_len as u64);
    if count > 0 && raw_len <= CODE_LIMIT {
        // The points gathered once: the coder walks them several times (bounds, colour mode,
        // order check, columns), and an inner node's records are scattered over the whole
        // sorted input, so each walk through the closures paid the cache misses again.
        let src = Gathered::of(count, attr_len, &pos, &color, &attrs);
        let grid = super::format::payload_grid(key, count, |i| src.pos[i])?;
        let h = super::format::node_header(key, kind, count, &grid, attr_len);
        if let Some((c, seq)) = coded(h, &&src, order, raw_len as usize) {
            return Ok((super::format::node_entry(key, kind, count, c.len()), c, seq));
        }
    }
    let (entry, raw) =
        super::format::encode_raw_payload(key, kind, count, attr_len, pos, color, attrs)?;
    Ok((entry, raw, None))
}

/// The codec, the colour mode and the uncompressed body of the points `src` (records of `al`
/// attribute bytes; positions coded from the grid's minimum `min`), or `None` where none applies: [`ZSTD_GPS_ORDER`] where `order` applies and
/// the node's order can be recomputed from the coded sequence, else [`ZSTD_COLUMNS`].
fn body_of<'a>(
    src: &impl Points<'a>,
    min: [i32; 3],
    al: usize,
    order: Option<Order>,
) -> Option<(u32, u32, Vec<u8>, CodedOrder)> {
    let n = src.len();
    if n == 0 {
        return None;
    }
    let ordered = order.filter(|o| o.gps + 8 <= al && n >= 2).and_then(|o| {
        let gk: Vec<u64> = (0..n).map(|i| gps_key(&src.attrs(i)[o.gps..])).collect();
        // The node's order must be the stable sort of the coded sequence by the Morton key:
        // each point after its predecessor in Morton order, or at the same position and after
        // it in the time order (a stable sort by time keeps `i - 1` before `i` where its time
        // is not later). Checked before the sort, which a node that fails it does not need.
        let mut last = offset_in(src.pos(0), o.cube_min)?;
        for i in 1..n {
            let u = offset_in(src.pos(i), o.cube_min)?;
            let after = match morton_cmp(last, u) {
                std::cmp::Ordering::Less => true,
                std::cmp::Ordering::Equal => gk[i - 1] <= gk[i],
                std::cmp::Ordering::Greater => false,
            };
            if !after {
                return None;
            }
            last = u;
        }
        Some((o, time_order(&gk), gk))
    });
    let (codec, seq, gps) = match ordered {
        Some((o, seq, gk)) => (ZSTD_GPS_ORDER, seq, Some((o, gk))),
        None => (ZSTD_COLUMNS, (0..n as u32).collect(), None),
    };
    let mode = color_mode(src, al);
    let color_bytes = match mode & 0xff {
        COLOR_PLANES => 4 * n,
        COLOR_GREY => n,
        _ => 0,
    };
    let prefix = if gps.is_some() { ORDER_PREFIX } else { 0 };
    let mut body = vec![0u8; prefix + 12 * n + color_bytes + n * al];
    let (head, rest) = body.split_at_mut(prefix);
    let (pb, rest) = rest.split_at_mut(12 * n);
    let (cb, rest) = rest.split_at_mut(color_bytes);
    // GPS time's planes (ordered) first, then the other attribute bytes' planes.
    let (gb, ab) = rest.split_at_mut(if gps.is_some() { 8 * n } else { 0 });
    let g = gps.as_ref().map(|(o, _)| o.gps);
    if let Some((o, gk)) = &gps {
        for a in 0..3 {
            head[8 * a..8 * a + 8].copy_from_slice(&o.cube_min[a].to_le_bytes());
        }
        head[24..28].copy_from_slice(&(o.gps as u32).to_le_bytes());
        let mut prev = 0u64;
        for (t, &i) in seq.iter().enumerate() {
            let d = gk[i as usize].wrapping_sub(prev);
            prev = gk[i as usize];
            for b in 0..8 {
                gb[b * n + t] = (d >> (8 * b)) as u8;
            }
        }
    }
    // In blocks of points: each block's values made first, then written plane by plane, so
    // that every write is a run of contiguous bytes rather than one byte in each of 30-odd
    // planes per point.
    const BLOCK: usize = 64;
    // The kept bytes as runs of consecutive ones: (first plane, first byte, length).
    let mut runs: Vec<(usize, usize, usize)> = Vec::new();
    for (j, k) in kept_bytes(al, g).enumerate() {
        match runs.last_mut() {
            Some((_, k0, len)) if *k0 + *len == k => *len += 1,
            _ => runs.push((j, k, 1)),
        }
    }
    let mut prev = [0u32; 3];
    let mut z = [[0u32; BLOCK]; 3];
    let mut col = [0u32; BLOCK];
    let mut rec = vec![0u8; BLOCK * al];
    for (blk, ids) in seq.chunks(BLOCK).enumerate() {
        let (t0, m) = (blk * BLOCK, ids.len());
        for (o, &i) in ids.iter().enumerate() {
            let i = i as usize;
            let p = src.pos(i);
            for a in 0..3 {
                let u = (p[a] as i64 - min[a] as i64) as u32;
                let d = u.wrapping_sub(prev[a]) as i32;
                z[a][o] = ((d << 1) ^ (d >> 31)) as u32;
                prev[a] = u;
            }
            col[o] = src.color(i);
            rec[o * al..(o + 1) * al].copy_from_slice(&src.attrs(i)[..al]);
        }
        for a in 0..3 {
            for b in 0..4 {
                let dst = &mut pb[(4 * a + b) * n + t0..][..m];
                for (d, &v) in dst.iter_mut().zip(&z[a][..m]) {
                    *d = (v >> (8 * b)) as u8;
                }
            }
        }
        match mode & 0xff {
            COLOR_PLANES => {
                for b in 0..4 {
                    let dst = &mut cb[b * n + t0..][..m];
                    for (d, &c) in dst.iter_mut().zip(&col[..m]) {
                        *d = (c >> (8 * b)) as u8;
                    }
                }
            }
            COLOR_GREY => {
                for (d, &c) in cb[t0..t0 + m].iter_mut().zip(&col[..m]) {
                    *d = c as u8;
                }
            }
            _ => {}
        }
        for &(j, k, len) in &runs {
            planes_of(&rec[..m * al], al, k, len, &mut ab[j * n..], n, t0);
        }
    }
    Some((codec, mode, body, (codec == ZSTD_GPS_ORDER).then_some(seq)))
}

/// Bytes `k..k + len` of the `m` records of `al` bytes in `rec` written as planes: byte `k + c`
/// of record `o` to `dst[c * n + t0 + o]`. Eight records by eight bytes at a time, transposed
/// in registers (three rounds of block swaps on eight 64-bit rows), so that a block costs 16
/// loads and stores rather than 128; the rest byte by byte.
fn planes_of(rec: &[u8], al: usize, k: usize, len: usize, dst: &mut [u8], n: usize, t0: usize) {
    let m = rec.len() / al;
    let (m8, len8) = (m / 8 * 8, len / 8 * 8);
    for c0 in (0..len8).step_by(8) {
        for o in (0..m8).step_by(8) {
            let mut x = [0u64; 8];
            for (r, x) in x.iter_mut().enumerate() {
                let at = (o + r) * al + k + c0;
                *x = u64::from_le_bytes(rec[at..at + 8].try_into().expect("8 bytes"));
            }
            transpose8(&mut x);
            for (c, x) in x.iter().enumerate() {
                let at = (c0 + c) * n + t0 + o;
                dst[at..at + 8].copy_from_slice(&x.to_le_bytes());
            }
        }
        for c in c0..c0 + 8 {
            for o in m8..m {
                dst[c * n + t0 + o] = rec[o * al + k + c];
            }
        }
    }
    for c in len8..len {
        let d = &mut dst[c * n + t0..][..m];
        for (o, d) in d.iter_mut().enumerate() {
            *d = rec[o * al + k + c];
        }
    }
}

/// Transposes the 8x8 byte matrix whose row `r` is `x[r]` (byte `c` of a row: column `c`).
#[inline]
pub(crate) fn transpose8(x: &mut [u64; 8]) {
    for (half, mask) in
        [(4, 0x0000_0000_ffff_ffffu64), (2, 0x0000_ffff_0000_ffff), (1, 0x00ff_00ff_00ff_00ff)]
    {
        let shift = 8 * half as u32;
        for r in (0..8).filter(|r| r & half == 0) {
            let t = ((x[r] >> shift) ^ x[r + half]) & mask;
            x[r] ^= t << shift;
            x[r + half] ^= t;
        }
    }
}

/// The attribute bytes coded as planes of their own: all `al`, less GPS time's 8 at `g`.
fn kept_bytes(al: usize, g: Option<usize>) -> impl Iterator<Item = usize> {
    (0..al).filter(move |&k| g.is_none_or(|g| k < g || k >= g + 8))
}

/// The points' order by GPS time key `gk`, ties in their order.
///
/// A least-significant-digit radix sort (stable, so ties keep their order; it replaced a
/// comparison sort that was 15 % of a build's time, 2-core VM, `perf`, 10 M points) of one
/// 64-bit word per point: the key less the keys' minimum above the point's place. Where the
/// key's range and the places do not fit one word together (leaves span 41-48 bits of the key
/// in the bcts tiles, 49-56 in mortar-gen's scans), the range's lowest bits are dropped from
/// the word, and the runs of points whose kept bits tie (times within a few microseconds:
/// returns of one pulse, whose times are equal) are then put in the order of their whole keys.
/// One pass per byte of the kept bits that is not the same in every word (11-bit digits
/// measured no faster). Few points take the comparison sort.
fn time_order(gk: &[u64]) -> Vec<u32> {
    let n = gk.len();
    if n < 256 {
        // (key, place) pairs are unique: an unstable sort gives the stable order.
        let mut seq: Vec<u32> = (0..n as u32).collect();
        seq.sort_unstable_by_key(|&i| (gk[i as usize], i));
        return seq;
    }
    let lo = gk.iter().copied().min().unwrap_or(0);
    let hi = gk.iter().copied().max().unwrap_or(0);
    let place_bits = 32 - (n as u32 - 1).leading_zeros();
    let range_bits = 64 - (hi - lo).leading_zeros();
    let drop = (range_bits + place_bits).saturating_sub(64);
    let digits = (range_bits - drop).div_ceil(8) as usize;
    let w =
        gk.iter().enumerate().map(|(i, &k)| ((k - lo) >> drop) << place_bits | i as u64).collect();
    let shift = place_bits as usize;
    let mask = (1u64 << place_bits) - 1;
    let mut w = radix_sort(w, digits, |&x, d| ((x >> (shift + 8 * d)) & 0xff) as usize);
    if drop > 0 {
        // Runs of equal kept bits: by whole key, then place (unique pairs: an unstable sort
        // gives the stable order; runs are short, and a long one, as a hostile file's times
        // can make, costs n log n).
        let mut s = 0;
        while s < n {
            let top = w[s] >> place_bits;
            let mut e = s + 1;
            while e < n && w[e] >> place_bits == top {
                e += 1;
            }
            if e - s > 1 {
                w[s..e].sort_unstable_by_key(|&x| (gk[(x & mask) as usize], x & mask));
            }
            s = e;
        }
    }
    w.iter().map(|&x| (x & mask) as u32).collect()
}

/// Stable least-significant-digit radix sort of `items` on `digits` byte digits,
/// `digit(item, d)` being digit `d` (0 the lowest); a digit that all items share costs no pass.
fn radix_sort<T: Copy + Default>(
    mut items: Vec<T>,
    digits: usize,
    digit: impl Fn(&T, usize) -> usize,
) -> Vec<T> {
    let n = items.len();
    let mut counts = vec![[0u32; 256]; digits];
    for x in &items {
        for (d, c) in counts.iter_mut().enumerate() {
            c[digit(x, d)] += 1;
        }
    }
    let mut other = vec![T::default(); n];
    for (d, c) in counts.iter().enumerate() {
        if c.iter().any(|&k| k as usize == n) {
            continue;
        }
        let mut at = [0usize; 256];
        let mut sum = 0usize;
        for (a, &k) in at.iter_mut().zip(c.iter()) {
            *a = sum;
            sum += k as usize;
        }
        for x in &items {
            let b = digit(x, d);
            other[at[b]] = *x;
            at[b] += 1;
        }
        std::mem::swap(&mut items, &mut other);
    }
    items
}

/// The codec of a stored payload's header.
pub(crate) fn codec_of(h: &NodeHeader) -> u32 {
    h._pad[0]
}

/// Bytes a stored payload with header `h` must have: the version 2 length for [`RAW`], the
/// header and the coded body padded to 8 for [`ZSTD_COLUMNS`]; `None` for an unknown codec.
pub(crate) fn stored_len(h: &NodeHeader) -> Option<u64> {
    match codec_of(h) {
        RAW => Some(payload_len(h.count as u64, h.attr_len as u64)),
        ZSTD_COLUMNS | ZSTD_GPS_ORDER => Some((64 + h._pad[1] as u64).next_multiple_of(8)),
        _ => None,
    }
}

/// A version 2 payload: borrowed from the stored bytes, or decoded into words (so its `u32`
/// columns are aligned, as they are in a store's map).
#[derive(Debug)]
pub(crate) enum Decoded<'a> {
    /// A [`RAW`] payload as stored.
    Borrowed(&'a [u8]),
    /// A decoded payload (its length a multiple of 8, as every payload's).
    Owned(Vec<u64>),
}

impl std::ops::Deref for Decoded<'_> {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        match self {
            Decoded::Borrowed(b) => b,
            Decoded::Owned(w) => bytemuck::cast_slice(w),
        }
    }
}

impl Decoded<'_> {
    /// The decoded bytes, owned.
    pub(crate) fn into_words(self) -> Vec<u64> {
        match self {
            Decoded::Borrowed(b) => {
                let mut w = vec![0u64; b.len().div_ceil(8)];
                bytemuck::cast_slice_mut::<u64, u8>(&mut w)[..b.len()].copy_from_slice(b);
                w
            }
            Decoded::Owned(w) => w,
        }
    }
}

/// The version 2 payload of the stored payload `b` (borrowed where it is [`RAW`]).
pub(crate) fn decode(b: &[u8]) -> Result<Decoded<'_>, PayloadError> {
    decode_ordered(b).map(|(d, _)| d)
}

/// [`decode`], and the coded order where it is not the payload's (codec 2): `seq[i]` is the
/// coded place of payload point `i`.
pub(crate) fn decode_ordered(b: &[u8]) -> Result<(Decoded<'_>, Option<Vec<u32>>), PayloadError> {
    if b.len() < 64 {
        return Err(PayloadError::Short);
    }
    let h: NodeHeader = bytemuck::pod_read_unaligned(&b[..64]);
    let ordered = match codec_of(&h) {
        RAW => return Ok((Decoded::Borrowed(b), None)),
        ZSTD_COLUMNS => false,
        ZSTD_GPS_ORDER => true,
        _ => return Err(PayloadError::Damaged),
    };
    let (n, al) = (h.count as usize, h.attr_len as usize);
    let z = h._pad[1] as usize;
    if h.magic != NODE_MAGIC
        || b.len() < 64 + z
        || h.bits[..3].iter().any(|&x| x > 30)
        || (ordered && al < 8)
    {
        return Err(PayloadError::Damaged);
    }
    let mode = h._pad[2];
    let color_bytes = match mode & 0xff {
        COLOR_PLANES => 4 * n,
        COLOR_GREY => n,
        COLOR_RGB8 | COLOR_RGB16 if (mode >> 8) as usize + 6 <= al => 0,
        _ => return Err(PayloadError::Damaged),
    };
    let prefix = if ordered { ORDER_PREFIX } else { 0 };
    let want = (prefix + 12 * n + color_bytes) as u64 + n as u64 * al as u64;
    let mut body = Vec::new();
    zstd::stream::read::Decoder::with_buffer(&b[64..64 + z])
        .map_err(|_| PayloadError::Damaged)?
        .take(want + 1)
        .read_to_end(&mut body)
        .map_err(|_| PayloadError::Damaged)?;
    if body.len() as u64 != want {
        return Err(PayloadError::Damaged);
    }
    // The body is there: the raw payload is about its size.
    let (head, rest) = body.split_at(prefix);
    let (pb, rest) = rest.split_at(12 * n);
    let (cb, rest) = rest.split_at(color_bytes);
    let order = if ordered {
        let cube_min: [i64; 3] =
            [0, 1, 2].map(|a| i64::from_le_bytes(head[8 * a..8 * a + 8].try_into().expect("8")));
        let g = u32::from_le_bytes(head[24..28].try_into().expect("4")) as usize;
        if g + 8 > al {
            return Err(PayloadError::Damaged);
        }
        Some(Order { cube_min, gps: g })
    } else {
        None
    };
    let (gb, ab) = rest.split_at(if ordered { 8 * n } else { 0 });
    let grid = BatchGrid { min: h.min, bits: [h.bits[0], h.bits[1], h.bits[2]] };
    // The points in coded order.
    let mut pos = Vec::with_capacity(n);
    let mut prev = [0u32; 3];
    for t in 0..n {
        let mut p = [0i32; 3];
        for a in 0..3 {
            let z = (0..4).fold(0u32, |z, k| z | (pb[(4 * a + k) * n + t] as u32) << (8 * k));
            let d = ((z >> 1) as i32) ^ -((z & 1) as i32);
            let u = prev[a].wrapping_add(d as u32);
            prev[a] = u;
            let span = if grid.bits[a] == 0 { 0 } else { (1u64 << grid.bits[a]) - 1 };
            if u as u64 > span {
                return Err(PayloadError::Damaged);
            }
            p[a] = (grid.min[a] as i64 + u as i64) as i32;
        }
        pos.push(p);
    }
    // The node's order: coded order, or the stable sort of the Morton keys from the cube's
    // corner (the key above the coded place: unique, so an unstable sort is the stable one).
    let seq: Vec<u32> = match &order {
        None => (0..n as u32).collect(),
        Some(o) => {
            let mut keys = Vec::with_capacity(n);
            for (t, p) in pos.iter().enumerate() {
                let m = morton96(offset_in(*p, o.cube_min).ok_or(PayloadError::Damaged)?);
                keys.push(m << 32 | t as u128);
            }
            keys.sort_unstable();
            keys.iter().map(|&k| k as u32).collect()
        }
    };
    let mut store = vec![0u64; payload_len(n as u64, al as u64) as usize / 8];
    let raw: &mut [u8] = bytemuck::cast_slice_mut(&mut store);
    raw[..64].copy_from_slice(bytemuck::bytes_of(&NodeHeader { _pad: [0; 3], ..h }));
    let (out_head, out_attrs) = raw[64..].split_at_mut(16 * n);
    let out_attrs = &mut out_attrs[..n * al];
    let (words, out_colors) = out_head.split_at_mut(12 * n);
    // Attributes plane by plane (each plane read at the permuted places: it is in cache); GPS
    // time from its key differences.
    if let Some(o) = &order {
        let mut key = 0u64;
        let mut gps = Vec::with_capacity(n);
        for t in 0..n {
            key = key.wrapping_add((0..8).fold(0u64, |d, k| d | (gb[k * n + t] as u64) << (8 * k)));
            gps.push(gps_of_key(key));
        }
        for (i, &t) in seq.iter().enumerate() {
            let at = i * al + o.gps;
            out_attrs[at..at + 8].copy_from_slice(&gps[t as usize].to_le_bytes());
        }
    }
    let g = order.map(|o| o.gps);
    for (j, k) in kept_bytes(al, g).enumerate() {
        let plane = &ab[j * n..(j + 1) * n];
        for (i, &t) in seq.iter().enumerate() {
            out_attrs[i * al + k] = plane[t as usize];
        }
    }
    for (i, &t) in seq.iter().enumerate() {
        let t = t as usize;
        let w = grid.encode(pos[t]);
        for (k, wk) in w.iter().enumerate() {
            words[4 * (k * n + i)..4 * (k * n + i) + 4].copy_from_slice(&wk.to_le_bytes());
        }
        let c = match mode & 0xff {
            COLOR_PLANES => u32::from_le_bytes([cb[t], cb[n + t], cb[2 * n + t], cb[3 * n + t]]),
            COLOR_GREY => {
                let r = cb[t] as u32;
                r | r << 8 | r << 16 | 255 << 24
            }
            m => rgb_of(&out_attrs[i * al..(i + 1) * al], (mode >> 8) as usize, m == COLOR_RGB16),
        };
        out_colors[4 * i..4 * i + 4].copy_from_slice(&c.to_le_bytes());
    }
    Ok((Decoded::Owned(store), order.map(|_| seq)))
}

/// What coding in acquisition order needs to know of a node: its cube's corner (so that its
/// points' order is recomputed as the Morton order of their offsets from it) and the attribute
/// offset of the records' GPS time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Order {
    pub cube_min: [i64; 3],
    pub gps: usize,
}

impl Order {
    /// The order of node `key` of the tree over `root` for records of `layout`; `None` where
    /// the records keep no GPS time.
    pub(crate) fn of(
        root: mortar_core::octree::Cube,
        key: NodeKey,
        layout: &mortar_core::layout::RecordLayout,
    ) -> Option<Order> {
        let g = layout.attribute("gps_time")?;
        (g.offset >= 12).then(|| Order { cube_min: key.cube_in(root).min, gps: g.offset - 12 })
    }
}

/// Whether `MORTAR_STORE_CODEC=1` asks for payloads coded in their own order only (codec 1): the
/// benchmarks' and tests' way to compare the two codings of one store.
fn morton_only() -> bool {
    static ONLY: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ONLY.get_or_init(|| std::env::var("MORTAR_STORE_CODEC").is_ok_and(|v| v == "1"))
}

/// Bytes of the ordered body's prefix: the cube's corner and the GPS offset.
const ORDER_PREFIX: usize = 28;

// The full-resolution Morton key of an offset from a cube's corner: the order the engines give
// a node's points (ties, points at one position, by arrival).
use mortar_core::morton::encode96 as morton96;

/// GPS time's f64 bits as a key that orders as the times do.
fn gps_key(b: &[u8]) -> u64 {
    let v = u64::from_le_bytes(b[..8].try_into().expect("8 bytes"));
    if v >> 63 == 1 {
        !v
    } else {
        v | 1 << 63
    }
}

fn gps_of_key(k: u64) -> u64 {
    if k >> 63 == 1 {
        k & !(1 << 63)
    } else {
        !k
    }
}

/// How `a` and `b` compare in the full-resolution Morton order ([`morton96`]: x on bit 0, y on
/// bit 1, z on bit 2 of each triple), without making the keys: the axis whose coordinates differ
/// in the highest bit decides, z before y before x where that bit is the same.
#[inline]
pub(crate) fn morton_cmp(a: [u32; 3], b: [u32; 3]) -> std::cmp::Ordering {
    let mut axis = 0;
    let mut top = a[0] ^ b[0];
    for k in 1..3 {
        let d = a[k] ^ b[k];
        // `d`'s highest bit is at least `top`'s: the later axis is the more significant.
        if d.leading_zeros() <= top.leading_zeros() && d != 0 {
            axis = k;
            top = d;
        }
    }
    a[axis].cmp(&b[axis])
}

/// The offset of `p` from `cube_min`, where it lies in a cube of mortar's (at most 2^32 wide).
fn offset_in(p: [i32; 3], cube_min: [i64; 3]) -> Option<[u32; 3]> {
    let mut u = [0u32; 3];
    for a in 0..3 {
        // A damaged payload's corner can be any i64: the difference may not exist.
        u[a] = u32::try_from((p[a] as i64).checked_sub(cube_min[a])?).ok()?;
    }
    Some(u)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Cut copies of `coded` are refused; copies with a byte flipped every `step` bytes decode
    /// or are refused, without a panic.
    pub(super) fn damaged_copies_refused(coded: &[u8], step: usize) {
        for cut in [63, 64, 70, coded.len() - 9] {
            assert!(decode(&coded[..cut]).is_err(), "cut at {cut}");
        }
        for at in (64..coded.len()).step_by(step) {
            let mut bad = coded.to_vec();
            bad[at] ^= 0x5a;
            let _ = decode(&bad);
        }
    }
    use crate::store::format::{encode_raw_payload, INNER, LEAF};
    use mortar_core::octree::NodeKey;

    fn payload(n: usize, al: usize, color: impl Fn(usize, &[u8]) -> u32) -> Vec<u8> {
        let pos = |i: usize| {
            [
                1_000_000 + (i as i32 * 37) % 1001,
                -5 + (i as i32 * 11) % 97,
                6_400_000 + (i as i32 % 5),
            ]
        };
        let attrs: Vec<u8> = (0..n * al).map(|b| (b * 31 % 251) as u8).collect();
        let attr = |i: usize| &attrs[i * al..(i + 1) * al];
        let key = NodeKey { level: 3, index: [1, 2, 3] };
        encode_raw_payload(key, LEAF, n, al, pos, |i| color(i, attr(i)), attr).unwrap().1
    }

    /// Every colour mode codes smaller than raw and decodes to the raw bytes.
    /// The radix order equals the comparison sort by (key, place) on keys with ties, spans of
    /// one to eight bytes, and digits that are constant (skipped passes).
    #[test]
    fn time_order_is_the_stable_sort_by_key() {
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        for case in 0..64 {
            let n = [0, 1, 2, 255, 256, 257, 4095, 5000][case % 8];
            let span_bits = 1 + (case * 7) % 64;
            let base = next();
            let gk: Vec<u64> = (0..n)
                .map(|_| {
                    let r = if span_bits == 64 { next() } else { next() & ((1 << span_bits) - 1) };
                    // Some keys repeated, some with a constant middle byte.
                    let r = if next() % 4 == 0 { r & !0xff00 } else { r };
                    base.wrapping_add(r) & if case % 5 == 0 { !0xffu64 } else { !0 }
                })
                .collect();
            let mut want: Vec<u32> = (0..n as u32).collect();
            want.sort_by_key(|&i| gk[i as usize]);
            assert_eq!(time_order(&gk), want, "case {case}");
        }
        // Keys over 63 bits in clusters that differ in their low 12 bits only (below the bits
        // a word keeps beside 13 place bits), repeated keys among them, one cluster holding
        // most points: the runs of equal kept bits are ordered by the whole keys.
        for n in [300, 5000] {
            let gk: Vec<u64> = (0..n)
                .map(|i| {
                    let cluster = if i % 3 == 0 { next() % 256 } else { 17 };
                    let low = if i % 5 == 0 { 7 } else { next() & 0xfff };
                    cluster << 55 | low
                })
                .collect();
            let mut want: Vec<u32> = (0..n as u32).collect();
            want.sort_by_key(|&i| gk[i as usize]);
            assert_eq!(time_order(&gk), want, "clusters of {n}");
        }
    }

    #[test]
    fn coded_payloads_decode_to_the_raw_bytes() {
        let al = 22;
        type Rule = Box<dyn Fn(usize, &[u8]) -> u32>;
        let cases: [(&str, u32, Rule); 4] = [
            ("planes", COLOR_PLANES, Box::new(|i, _| 0x0102_0304u32.wrapping_mul(i as u32 + 1))),
            ("grey", COLOR_GREY, Box::new(|i, _| ((i as u32 % 200) * 0x10101) | (255 << 24))),
            ("rgb16", COLOR_RGB16 | 16 << 8, Box::new(|_, a| rgb_of(a, 16, true))),
            ("rgb16 at 8", COLOR_RGB16 | 8 << 8, Box::new(|_, a| rgb_of(a, 8, true))),
        ];
        for (name, mode, color) in cases {
            for n in [1, 2, 1000] {
                let raw = payload(n, al, &color);
                let coded = encode(raw.clone(), None);
                let h: NodeHeader = bytemuck::pod_read_unaligned(&coded[..64]);
                assert!(*decode(&coded).unwrap() == *raw, "{name} {n}: the bytes differ");
                if n < 10 && codec_of(&h) == RAW {
                    // Too few points to gain from coding: kept raw.
                    assert!(coded == raw);
                    continue;
                }
                assert_eq!(codec_of(&h), ZSTD_COLUMNS, "{name} {n}");
                assert_eq!(h._pad[2], mode, "{name} {n}");
                assert_eq!(stored_len(&h), Some(coded.len() as u64));
                assert!(coded.len() < raw.len(), "{name} {n}: {} >= {}", coded.len(), raw.len());
                assert!(*decode(&coded).unwrap() == *raw, "{name} {n}: the bytes differ");
            }
        }
    }

    /// 8-bit RGB in 16-bit fields: the colour is the value itself.
    #[test]
    fn eight_bit_rgb_is_computed_again() {
        let al = 16 + 6;
        let mut attrs = vec![0u8; 300 * al];
        for (i, a) in attrs.chunks_exact_mut(al).enumerate() {
            for k in 0..3 {
                a[16 + 2 * k] = (i * (k + 3)) as u8;
            }
        }
        let at = |i: usize| &attrs[i * al..(i + 1) * al];
        let key = NodeKey { level: 0, index: [0; 3] };
        let raw = encode_raw_payload(
            key,
            INNER,
            300,
            al,
            |i| [i as i32; 3],
            |i| rgb_of(at(i), 16, false),
            at,
        )
        .unwrap()
        .1;
        let coded = encode(raw.clone(), None);
        let h: NodeHeader = bytemuck::pod_read_unaligned(&coded[..64]);
        assert_eq!(h._pad[2], COLOR_RGB8 | 16 << 8);
        assert!(*decode(&coded).unwrap() == *raw);
    }

    /// The Morton comparison without keys is the keys' comparison, on coordinates that share
    /// high bits and on equal ones.
    #[test]
    fn morton_cmp_is_the_keys_order() {
        let mut x = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        for t in 0..200_000 {
            let a = [next() as u32, next() as u32, next() as u32];
            // Mostly near `a`: a few low bits changed on some axes, or none.
            let mut b = a;
            for c in b.iter_mut() {
                match next() % 4 {
                    0 => *c ^= (next() as u32) >> (next() % 32),
                    1 => *c = next() as u32,
                    _ => {}
                }
            }
            if t % 7 == 0 {
                b = a;
            }
            assert_eq!(morton_cmp(a, b), morton96(a).cmp(&morton96(b)), "{a:?} {b:?}");
        }
    }

    /// The planes written eight by eight are the byte-by-byte planes, for every block size,
    /// run start and length.
    #[test]
    fn planes_are_the_transposed_bytes() {
        let al = 29;
        let rec: Vec<u8> = (0..64 * al).map(|b| (b * 131 % 253) as u8).collect();
        for m in [1, 7, 8, 9, 63, 64] {
            for (k, len) in [(0, 29), (3, 8), (5, 17), (20, 9), (0, 7)] {
                let (n, t0) = (200, 70);
                let mut dst = vec![0u8; len * n];
                planes_of(&rec[..m * al], al, k, len, &mut dst, n, t0);
                for c in 0..len {
                    for o in 0..m {
                        assert_eq!(dst[c * n + t0 + o], rec[o * al + k + c], "{m} {k} {len}");
                    }
                }
            }
        }
    }

    /// Empty nodes stay raw; damaged coded payloads are errors, never panics.
    #[test]
    fn empty_stays_raw_and_damage_is_an_error() {
        let raw = payload(0, 7, |_, _| 0);
        assert!(encode(raw.clone(), None) == raw);
        let coded = encode(payload(500, 7, |i, _| i as u32), None);
        damaged_copies_refused(&coded, 7);
        let mut big = coded.clone();
        big[28..32].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode(&big).is_err());
    }
}

#[cfg(test)]
mod order_tests {
    use super::*;
    use crate::store::format::{encode_raw_payload, LEAF};
    use mortar_core::octree::{Cube, NodeKey};

    /// Records of point format 1 after XYZ (8 bytes, then GPS time at 8): attribute length 16.
    const AL: usize = 16;
    const GPS: usize = 8;

    /// A leaf of `n` points in Morton order of their offsets from `cube`'s corner, GPS times by
    /// `gps(i)`; its raw payload.
    fn leaf(n: usize, cube: Cube, gps: impl Fn(usize) -> f64, dup: bool) -> Vec<u8> {
        let mut pts: Vec<[i32; 3]> = (0..n)
            .map(|i| {
                let i = if dup { i / 2 } else { i } as i64;
                [0, 1, 2].map(|a| (cube.min[a] + (i * (7 + 3 * a as i64) * 7919) % 4096) as i32)
            })
            .collect();
        pts.sort_by_key(|p| morton96(offset_in(*p, cube.min).unwrap()));
        let mut attrs = vec![0u8; n * AL];
        for (i, a) in attrs.chunks_exact_mut(AL).enumerate() {
            a[0] = (i % 251) as u8;
            a[1] = 7;
            a[GPS..GPS + 8].copy_from_slice(&gps(i).to_le_bytes());
        }
        let at = |i: usize| &attrs[i * AL..(i + 1) * AL];
        let key = NodeKey { level: 2, index: [1, 0, 3] };
        encode_raw_payload(key, LEAF, n, AL, |i| pts[i], |i| (i as u32) * 0x10101, at).unwrap().1
    }

    #[test]
    fn gps_ordered_payloads_decode_to_the_raw_bytes_and_unordered_ones_fall_back() {
        let cube = Cube { min: [1_000_000, -2_000, 6_400_000], size_log2: 12 };
        let order = Some(Order { cube_min: cube.min, gps: GPS });
        // GPS times that are no function of the order (negative ones too: adjusted GPS time).
        let shuffled = |i: usize| ((i * 7_654_321) % 10_007) as f64 * 0.25 - 1_000.0;
        for n in [2, 3, 1000, 4000] {
            let raw = leaf(n, cube, shuffled, false);
            let coded = encode(raw.clone(), order);
            let h: NodeHeader = bytemuck::pod_read_unaligned(&coded[..64]);
            assert!(*decode(&coded).unwrap() == *raw, "{n}: the bytes differ");
            if n >= 1000 {
                assert_eq!(codec_of(&h), ZSTD_GPS_ORDER, "{n}");
                assert_eq!(stored_len(&h), Some(coded.len() as u64));
            }
        }
        // Points at one position whose GPS times run against their order: that order cannot
        // be recomputed, so they are coded in it.
        let raw = leaf(1000, cube, |i| -(i as f64), true);
        let coded = encode(raw.clone(), order);
        let h: NodeHeader = bytemuck::pod_read_unaligned(&coded[..64]);
        assert_eq!(codec_of(&h), ZSTD_COLUMNS);
        assert!(*decode(&coded).unwrap() == *raw);
        // ... and with their times in their order, recomputed.
        let raw = leaf(1000, cube, |i| i as f64, true);
        let coded = encode(raw.clone(), order);
        let h: NodeHeader = bytemuck::pod_read_unaligned(&coded[..64]);
        assert_eq!(codec_of(&h), ZSTD_GPS_ORDER);
        assert!(*decode(&coded).unwrap() == *raw);
        // A cube that does not hold the points: no ordered coding.
        let far = Some(Order { cube_min: [0; 3], gps: GPS });
        let raw = leaf(1000, Cube { min: [0, 0, 0], size_log2: 12 }, shuffled, false);
        let _ = encode(raw.clone(), far);
        // Damage is an error, never a panic.
        let raw = leaf(1000, cube, shuffled, false);
        super::tests::damaged_copies_refused(&encode(raw, order), 5);
    }
}

/// The coder's speed and exactness on a real store: `MORTAR_CODEC_BENCH=STORE cargo test
/// --release -p mortar-io codec_bench -- --ignored --nocapture` decodes every payload of STORE
/// to its points, codes them again as the engines do ([`encode_payload`], one thread, 3 rounds)
/// and checks that every coded payload is the stored one byte for byte (the store written by
/// another build of mortar: a change of the coder that changes a byte fails here). It prints
/// the coder's points a second (BENCHMARKS.md "Store v3").
#[cfg(test)]
mod bench {
    use super::*;

    #[test]
    #[ignore = "needs a store named by MORTAR_CODEC_BENCH"]
    fn codec_bench() {
        let Ok(dir) = std::env::var("MORTAR_CODEC_BENCH") else { return };
        let store = crate::store::reader::Store::open(std::path::Path::new(&dir)).unwrap();
        struct Node {
            key: NodeKey,
            kind: u32,
            pos: Vec<[i32; 3]>,
            color: Vec<u32>,
            attrs: Vec<u8>,
            al: usize,
            stored: Vec<u8>,
        }
        let mut nodes = Vec::new();
        for (i, e) in store.entries.iter().enumerate() {
            let raw = store.raw_node(i).unwrap();
            let h: NodeHeader = bytemuck::pod_read_unaligned(&raw[..64]);
            let (n, al) = (h.count as usize, h.attr_len as usize);
            if n == 0 || raw.len() as u64 > CODE_LIMIT {
                continue;
            }
            let col = |k: usize| &raw[64 + 4 * n * k..64 + 4 * n * (k + 1)];
            let grid = BatchGrid { min: h.min, bits: [h.bits[0], h.bits[1], h.bits[2]] };
            let w = [col(0), col(1), col(2)];
            nodes.push(Node {
                key: NodeKey { level: e.level as u8, index: e.index },
                kind: e.kind,
                pos: (0..n)
                    .map(|i| grid.decode_exact([u32_at(w[0], i), u32_at(w[1], i), u32_at(w[2], i)]))
                    .collect(),
                color: (0..n).map(|i| u32_at(col(3), i)).collect(),
                attrs: raw[64 + 16 * n..64 + 16 * n + n * al].to_vec(),
                al,
                stored: store.node_bytes(i).to_vec(),
            });
        }
        let points: usize = nodes.iter().map(|n| n.pos.len()).sum();
        let mut best = f64::MAX;
        for _ in 0..3 {
            let t = std::time::Instant::now();
            for nd in &nodes {
                let order = Order::of(store.root_cube(), nd.key, &store.layout);
                let (_, c) = encode_payload(
                    nd.key,
                    nd.kind,
                    nd.pos.len(),
                    nd.al,
                    |i| nd.pos[i],
                    |i| nd.color[i],
                    |i| &nd.attrs[i * nd.al..(i + 1) * nd.al],
                    order,
                )
                .unwrap();
                assert!(c == nd.stored, "node {:?}: the coded bytes differ", nd.key);
            }
            best = best.min(t.elapsed().as_secs_f64());
        }
        println!(
            "codec_bench: {} nodes, {points} points, best of 3 {best:.3} s, {:.2} M points/s",
            nodes.len(),
            points as f64 / best / 1e6
        );
    }
}
