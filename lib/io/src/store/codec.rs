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

/// How the colours of `n` points are kept (the `_pad[2]` word).
fn color_mode(colors: &[u8], attrs: &[u8], n: usize, al: usize) -> u32 {
    for off in RGB_OFFSETS.into_iter().filter(|&o| o + 6 <= al) {
        // 8-bit values must fit a byte for the colour to be the value itself.
        for (mode, sixteen) in [(COLOR_RGB8, false), (COLOR_RGB16, true)] {
            let fits = (0..n).all(|i| {
                let a = &attrs[i * al..(i + 1) * al];
                (sixteen || (0..3).all(|k| a[off + 2 * k + 1] == 0))
                    && rgb_of(a, off, sixteen) == u32_at(colors, i)
            });
            if fits {
                return mode | (off as u32) << 8;
            }
        }
    }
    let grey = (0..n).all(|i| {
        let c = u32_at(colors, i);
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
/// `raw` itself where coding does not apply (see the module docs).
pub(crate) fn encode(raw: Vec<u8>) -> Vec<u8> {
    if raw.len() as u64 > CODE_LIMIT {
        return raw;
    }
    let Some((h, body)) = body_of(&raw) else { return raw };
    let Some(z) = zstd_compress(&body) else { return raw };
    let total = (64 + z.len()).next_multiple_of(8);
    if total >= raw.len() || z.len() > u32::MAX as usize {
        return raw;
    }
    let mut out = Vec::with_capacity(total);
    let h = NodeHeader { _pad: [ZSTD_COLUMNS, z.len() as u32, h._pad[2]], ..h };
    out.extend_from_slice(bytemuck::bytes_of(&h));
    out.extend_from_slice(&z);
    out.resize(total, 0);
    out
}

/// Encodes one node's payload (entry offset left 0) from its `count` points: `pos(i)`,
/// `color(i)` and `attrs(i)` (the record's bytes after X, Y, Z: `attr_len` of them). One pass
/// for the bounds, one that writes every column in place, then the version 3 coding
/// ([`encode`]); [`encode_raw_payload`](super::format::encode_raw_payload) stops before it.
#[allow(clippy::too_many_arguments)]
pub(crate) fn encode_payload<'r>(
    key: NodeKey,
    kind: u32,
    count: usize,
    attr_len: usize,
    pos: impl Fn(usize) -> [i32; 3],
    color: impl Fn(usize) -> u32,
    attrs: impl Fn(usize) -> &'r [u8],
) -> std::result::Result<(NodeEntry, Vec<u8>), PayloadError> {
    let (entry, raw) =
        super::format::encode_raw_payload(key, kind, count, attr_len, pos, color, attrs)?;
    let coded = encode(raw);
    Ok((NodeEntry { length: coded.len() as u64, ..entry }, coded))
}

/// The header (colour mode set) and uncompressed body of `raw`, or `None` where it stays raw.
fn body_of(raw: &[u8]) -> Option<(NodeHeader, Vec<u8>)> {
    if raw.len() < 64 {
        return None;
    }
    let h: NodeHeader = bytemuck::pod_read_unaligned(&raw[..64]);
    let (n, al) = (h.count as usize, h.attr_len as usize);
    if h.magic != NODE_MAGIC
        || n == 0
        || h._pad != [0; 3]
        || (raw.len() as u64) < payload_len(n as u64, al as u64)
        || h.bits[..3].iter().any(|&b| b > 30)
    {
        return None;
    }
    let grid = BatchGrid { min: h.min, bits: [h.bits[0], h.bits[1], h.bits[2]] };
    let col = |k: usize| &raw[64 + 4 * n * k..64 + 4 * n * (k + 1)];
    let (w, colors) = ([col(0), col(1), col(2)], col(3));
    let attrs = &raw[64 + 16 * n..64 + 16 * n + n * al];
    let mode = color_mode(colors, attrs, n, al);
    let color_bytes = match mode & 0xff {
        COLOR_PLANES => 4 * n,
        COLOR_GREY => n,
        _ => 0,
    };
    let mut body = vec![0u8; 12 * n + color_bytes + n * al];
    let (pos, rest) = body.split_at_mut(12 * n);
    let (cb, ab) = rest.split_at_mut(color_bytes);
    let mut prev = [0u32; 3];
    for i in 0..n {
        let words = [u32_at(w[0], i), u32_at(w[1], i), u32_at(w[2], i)];
        let p = grid.decode_exact(words);
        if grid.encode(p) != words {
            return None;
        }
        for a in 0..3 {
            let u = (p[a] as i64 - grid.min[a] as i64) as u32;
            let d = u.wrapping_sub(prev[a]) as i32;
            let z = ((d << 1) ^ (d >> 31)) as u32;
            prev[a] = u;
            for b in 0..4 {
                pos[(4 * a + b) * n + i] = (z >> (8 * b)) as u8;
            }
        }
    }
    match mode & 0xff {
        COLOR_PLANES => {
            for i in 0..n {
                for b in 0..4 {
                    cb[b * n + i] = colors[4 * i + b];
                }
            }
        }
        COLOR_GREY => {
            for i in 0..n {
                cb[i] = colors[4 * i];
            }
        }
        _ => {}
    }
    for i in 0..n {
        for j in 0..al {
            ab[j * n + i] = attrs[i * al + j];
        }
    }
    Some((NodeHeader { _pad: [0, 0, mode], ..h }, body))
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
        ZSTD_COLUMNS => Some((64 + h._pad[1] as u64).next_multiple_of(8)),
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
    if b.len() < 64 {
        return Err(PayloadError::Short);
    }
    let h: NodeHeader = bytemuck::pod_read_unaligned(&b[..64]);
    match codec_of(&h) {
        RAW => return Ok(Decoded::Borrowed(b)),
        ZSTD_COLUMNS => {}
        _ => return Err(PayloadError::Damaged),
    }
    let (n, al) = (h.count as usize, h.attr_len as usize);
    let z = h._pad[1] as usize;
    if h.magic != NODE_MAGIC || b.len() < 64 + z || h.bits[..3].iter().any(|&x| x > 30) {
        return Err(PayloadError::Damaged);
    }
    let mode = h._pad[2];
    let color_bytes = match mode & 0xff {
        COLOR_PLANES => 4 * n,
        COLOR_GREY => n,
        COLOR_RGB8 | COLOR_RGB16 if (mode >> 8) as usize + 6 <= al => 0,
        _ => return Err(PayloadError::Damaged),
    };
    let want = 12 * n as u64 + color_bytes as u64 + (n * al) as u64;
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
    let grid = BatchGrid { min: h.min, bits: [h.bits[0], h.bits[1], h.bits[2]] };
    let mut store = vec![0u64; payload_len(n as u64, al as u64) as usize / 8];
    let raw: &mut [u8] = bytemuck::cast_slice_mut(&mut store);
    raw[..64].copy_from_slice(bytemuck::bytes_of(&NodeHeader { _pad: [0; 3], ..h }));
    let (pos, rest) = body.split_at(12 * n);
    let (cb, ab) = rest.split_at(color_bytes);
    let (head, out_attrs) = raw[64..].split_at_mut(16 * n);
    let out_attrs = &mut out_attrs[..n * al];
    for j in 0..al {
        for i in 0..n {
            out_attrs[i * al + j] = ab[j * n + i];
        }
    }
    let (words, out_colors) = head.split_at_mut(12 * n);
    let mut prev = [0u32; 3];
    for i in 0..n {
        let mut p = [0i32; 3];
        for a in 0..3 {
            let z = (0..4).fold(0u32, |z, k| z | (pos[(4 * a + k) * n + i] as u32) << (8 * k));
            let d = ((z >> 1) as i32) ^ -((z & 1) as i32);
            let u = prev[a].wrapping_add(d as u32);
            prev[a] = u;
            let span = if grid.bits[a] == 0 { 0 } else { (1u64 << grid.bits[a]) - 1 };
            if u as u64 > span {
                return Err(PayloadError::Damaged);
            }
            p[a] = (grid.min[a] as i64 + u as i64) as i32;
        }
        let w = grid.encode(p);
        for (k, wk) in w.iter().enumerate() {
            words[4 * (k * n + i)..4 * (k * n + i) + 4].copy_from_slice(&wk.to_le_bytes());
        }
        let c = match mode & 0xff {
            COLOR_PLANES => u32::from_le_bytes([cb[i], cb[n + i], cb[2 * n + i], cb[3 * n + i]]),
            COLOR_GREY => {
                let r = cb[i] as u32;
                r | r << 8 | r << 16 | 255 << 24
            }
            m => rgb_of(&out_attrs[i * al..(i + 1) * al], (mode >> 8) as usize, m == COLOR_RGB16),
        };
        out_colors[4 * i..4 * i + 4].copy_from_slice(&c.to_le_bytes());
    }
    Ok(Decoded::Owned(store))
}

#[cfg(test)]
mod tests {
    use super::*;
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
                let coded = encode(raw.clone());
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
        let coded = encode(raw.clone());
        let h: NodeHeader = bytemuck::pod_read_unaligned(&coded[..64]);
        assert_eq!(h._pad[2], COLOR_RGB8 | 16 << 8);
        assert!(*decode(&coded).unwrap() == *raw);
    }

    /// Empty nodes stay raw; damaged coded payloads are errors, never panics.
    #[test]
    fn empty_stays_raw_and_damage_is_an_error() {
        let raw = payload(0, 7, |_, _| 0);
        assert!(encode(raw.clone()) == raw);
        let coded = encode(payload(500, 7, |i, _| i as u32));
        for cut in [63, 64, 70, coded.len() - 9] {
            assert!(decode(&coded[..cut]).is_err(), "cut at {cut}");
        }
        for at in (64..coded.len()).step_by(7) {
            let mut bad = coded.clone();
            bad[at] ^= 0x5a;
            let _ = decode(&bad);
        }
        let mut big = coded.clone();
        big[28..32].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode(&big).is_err());
    }
}
