//! LAS/LAZ sources: inputs named as files, directories, globs or `-` (stdin), opened as memory
//! maps and read in pieces that can be decoded in parallel.
//!
//! A LAS file is read in place: a piece is a borrowed slice of the memory map, no copy. A LAZ file
//! is read chunk by chunk (LASzip compresses independent chunks, usually 50,000 points), each
//! chunk decoded on its own thread by laz-rs. Nothing is allocated from a header's claims before
//! it has been checked against the bytes that exist.
//!
//! The LASzip VLR's compressor says how the point data is laid out, and it is read first:
//! - compressor 2 (pointwise chunked) and 3 (layered chunked, LAS 1.4): chunks, found through the
//!   chunk table whose offset the first 8 bytes of the point data hold;
//! - compressor 1 (pointwise, LASzip 1.x and early LAStools): one arithmetic stream from the first
//!   byte of the point data, no chunk table and no offset. It is read as one chunk.
//!
//! A chunk of more than [`piece_points`] points (a pointwise file, a writer that put millions
//! of points in one chunk) is not decoded whole: it is cut into pieces of that many points, read
//! by decoders that go through the chunk in order and are kept between pieces ([`Streams`]), so
//! the memory a piece needs is bounded whatever the chunk's size. The same holds for fixed-size
//! chunks without a chunk table, decoded as one stream.

use crate::error::{Error, LazError, Result};
use crate::las::{self, LasMeta};
use memmap2::Mmap;
use mortar_core::layout::RecordLayout;
use std::borrow::Cow;
use std::collections::HashMap;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// Most points per piece of a LAS file.
pub const LAS_PIECE_POINTS: u64 = 1 << 20;
/// Most points per piece of a LAZ chunk larger than that (and of a LAZ stream without a chunk
/// table): what bounds the memory one piece needs. Real chunks hold 50,000 points.
pub const LAZ_PIECE_POINTS: u64 = 1 << 20;
/// Most bytes of records per piece: wide records (extra bytes) make pieces of fewer points, so
/// that a piece stays a small part of a memory budget (`--memory`).
pub const PIECE_BYTES: u64 = 36 << 20;

/// Points per piece for records of `record_len` bytes: [`LAS_PIECE_POINTS`] (1 Mi), fewer where
/// that would be more than [`PIECE_BYTES`] (records over 36 bytes).
pub fn piece_points(record_len: usize) -> u64 {
    (PIECE_BYTES / record_len.max(1) as u64).clamp(4096, LAS_PIECE_POINTS)
}

/// Most decoders part-way through a chunk that a file keeps for its next pieces.
const MAX_IDLE_STREAMS: usize = 64;

/// Most points a LAZ chunk may claim per compressed byte: what bounds the buffer a chunk
/// decodes into (100 points per byte is a compression ratio over 3,000:1 for 34-byte records;
/// real scans compress 5-15:1).
pub const MAX_LAZ_POINTS_PER_BYTE: u64 = 100;

/// The bytes of an input: a memory map, or a buffer (stdin).
pub enum Bytes {
    Map(Mmap),
    Owned(Vec<u8>),
}

impl std::ops::Deref for Bytes {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        match self {
            Bytes::Map(m) => m,
            Bytes::Owned(v) => v,
        }
    }
}

/// Reads a whole file (or stdin for `-`) as bytes.
pub fn open_bytes(path: &Path) -> Result<Bytes> {
    if path == Path::new("-") {
        let mut v = Vec::new();
        std::io::stdin().lock().read_to_end(&mut v).map_err(|e| Error::io("<stdin>", e))?;
        return Ok(Bytes::Owned(v));
    }
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = f.metadata().map_err(|e| Error::io(path, e))?.len();
    if len == 0 {
        return Ok(Bytes::Owned(Vec::new()));
    }
    // SAFETY: the map is read-only; a file truncated by another process while mortar reads it
    // is outside what mortar can guard against (as with every mmap-based reader).
    let m = unsafe { Mmap::map(&f) }.map_err(|e| Error::io(path, e))?;
    Ok(Bytes::Map(m))
}

/// One LAZ chunk: where its bytes are and how many points it holds.
#[derive(Clone, Debug)]
struct LazChunk {
    offset: usize,
    len: usize,
    points: u64,
}

enum Kind {
    Las {
        start: usize,
    },
    /// LAZ in chunks (a pointwise file is one chunk: its whole point data).
    Laz {
        vlr: laz::LazVlr,
        chunks: Vec<LazChunk>,
    },
    /// LAZ with fixed-size chunks but no chunk table: one stream over `start..end`, decoded in
    /// order (laz-rs finds the chunk boundaries from the chunk size).
    LazSequential {
        vlr: laz::LazVlr,
        start: usize,
        end: usize,
    },
}

/// Where the points of a LAZ piece are.
#[derive(Clone, Copy, Debug)]
struct PieceAt {
    /// The chunk (0 for a [`Kind::LazSequential`] stream).
    chunk: usize,
    /// Points of the chunk before the piece's first.
    skip: u64,
    /// The piece is the whole chunk (decoded on its own, no stream kept).
    whole: bool,
}

/// A decoder part-way through a chunk (or a sequential stream): the next point it gives is
/// point `next` of chunk `chunk`.
struct Cursor {
    chunk: usize,
    next: u64,
    dec: laz::LasZipDecompressor<'static, Chain>,
}

/// Decoders kept between the pieces of large chunks: a piece takes the one furthest along
/// that is not past its first point (or starts a new one), and gives it back after. Pieces
/// read in order (one thread, or the threads of a parallel pass taking pieces in turn) thus
/// decode every point once.
#[derive(Default)]
struct Streams {
    idle: Mutex<Vec<Cursor>>,
}

impl Streams {
    fn take(&self, chunk: usize, skip: u64) -> Option<Cursor> {
        let mut idle = self.idle.lock().unwrap_or_else(|e| e.into_inner());
        let best = idle
            .iter()
            .enumerate()
            .filter(|(_, c)| c.chunk == chunk && c.next <= skip)
            .max_by_key(|(_, c)| c.next)
            .map(|(i, _)| i)?;
        Some(idle.swap_remove(best))
    }

    fn put(&self, c: Cursor) {
        let mut idle = self.idle.lock().unwrap_or_else(|e| e.into_inner());
        if idle.len() >= MAX_IDLE_STREAMS {
            idle.remove(0);
        }
        idle.push(c);
    }

    fn clear(&self) {
        self.idle.lock().unwrap_or_else(|e| e.into_inner()).clear();
    }
}

/// The bytes a stream decoder reads: `head`, then `body` of the file's bytes, then `tail` (a
/// chunk of a chunked file is given the offset and chunk table laz-rs's stream decoder looks
/// for; borrowed from the file's map, no copy).
struct Chain {
    head: Vec<u8>,
    bytes: Arc<Bytes>,
    body: std::ops::Range<usize>,
    tail: Vec<u8>,
    pos: u64,
}

impl Chain {
    fn len(&self) -> u64 {
        (self.head.len() + self.body.len() + self.tail.len()) as u64
    }
}

impl Read for Chain {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let (h, b) = (self.head.len() as u64, self.body.len() as u64);
        let p = self.pos;
        let src: &[u8] = if p < h {
            &self.head[p as usize..]
        } else if p < h + b {
            &self.bytes[self.body.start + (p - h) as usize..self.body.end]
        } else if p < self.len() {
            &self.tail[(p - h - b) as usize..]
        } else {
            &[]
        };
        let n = src.len().min(buf.len());
        buf[..n].copy_from_slice(&src[..n]);
        self.pos += n as u64;
        Ok(n)
    }
}

impl Seek for Chain {
    fn seek(&mut self, to: SeekFrom) -> std::io::Result<u64> {
        let p = match to {
            SeekFrom::Start(o) => Some(o),
            SeekFrom::End(d) => self.len().checked_add_signed(d),
            SeekFrom::Current(d) => self.pos.checked_add_signed(d),
        };
        let p = p.ok_or_else(|| {
            std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "seek before the start of the LAZ data",
            )
        })?;
        self.pos = p;
        Ok(p)
    }
}

/// A range of points of one input that is read as a unit.
#[derive(Clone, Copy, Debug)]
pub struct Piece {
    pub index: usize,
    pub first_point: u64,
    pub points: u64,
}

/// An opened LAS/LAZ input.
pub struct LasInput {
    pub path: PathBuf,
    bytes: Arc<Bytes>,
    pub meta: LasMeta,
    pub layout: RecordLayout,
    pub point_count: u64,
    kind: Kind,
    pieces: Vec<Piece>,
    /// Where each LAZ piece is (empty for LAS).
    at: Vec<PieceAt>,
    /// Decoders part-way through large chunks.
    streams: Streams,
    /// The fields to decode ([`decode_only`](Self::decode_only)); `None`: all of them.
    skip: Option<Skip>,
}

/// What a layered LAZ decoder leaves out, and the bytes that then read as zero.
#[derive(Clone, Debug)]
struct Skip {
    selection: laz::DecompressionSelection,
    /// Byte ranges (offset, width) of skipped attributes in a record.
    zero: Vec<(usize, usize)>,
    /// The byte of classification flags, scan direction and edge of flight line, when those are
    /// skipped (its scanner channel bits are always decoded, with the returns).
    flags_byte: Option<usize>,
}

impl Skip {
    /// The decoder's selection for the kept `attributes` of `layout` (point formats 6 to 10:
    /// the layered ones; `None` for the others, whose decoders cannot skip).
    fn of(layout: &RecordLayout, attributes: &[&str]) -> Option<Skip> {
        use laz::DecompressionSelection as D;
        if layout.format < 6 {
            return None;
        }
        let mut bits = D::Z;
        let mut zero = Vec::new();
        let mut flags_byte = None;
        for a in &layout.attributes {
            let bit = match a.name.as_str() {
                "intensity" => D::INTENSITY,
                "flags" => D::FLAGS,
                "classification" => D::CLASSIFICATION,
                "user_data" => D::USER_DATA,
                "scan_angle" => D::SCAN_ANGLE,
                "point_source_id" => D::POINT_SOURCE_ID,
                "gps_time" => D::GPS_TIME,
                "rgb" => D::RGB,
                "nir" => D::NIR,
                "wave_packet" => D::WAVEPACKET,
                "extra_bytes" => D::ALL_EXTRA_BYTES,
                _ => return None,
            };
            if attributes.contains(&a.name.as_str()) {
                bits |= bit;
            } else if a.name == "flags" {
                // byte 0: returns (always decoded); byte 1: flags and the scanner channel
                flags_byte = Some(a.offset + 1);
            } else {
                zero.push((a.offset, a.width));
            }
        }
        Some(Skip { selection: D(bits), zero, flags_byte })
    }

    /// Clears what the decoder skipped (it leaves the chunk's first values there).
    fn clear(&self, records: &mut [u8], record_len: usize) {
        if self.zero.is_empty() && self.flags_byte.is_none() {
            return;
        }
        for r in records.chunks_exact_mut(record_len) {
            for &(o, w) in &self.zero {
                r[o..o + w].fill(0);
            }
            if let Some(b) = self.flags_byte {
                r[b] &= 0b0011_0000;
            }
        }
    }
}

impl std::fmt::Debug for LasInput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LasInput")
            .field("path", &self.path)
            .field("points", &self.point_count)
            .finish()
    }
}

impl LasInput {
    /// Opens and checks a LAS/LAZ file (or stdin for `-`).
    pub fn open(path: &Path) -> Result<LasInput> {
        let bytes = open_bytes(path)?;
        Self::from_bytes(path.to_path_buf(), bytes)
    }

    pub fn from_bytes(path: PathBuf, bytes: Bytes) -> Result<LasInput> {
        let err = |error: LazError| Error::Laz { path: path.clone(), error };
        let mut meta =
            las::parse(&bytes).map_err(|error| Error::Las { path: path.clone(), error })?;
        let h = &meta.header;
        let layout = RecordLayout::new(h.point_format, h.record_len as usize)
            .map_err(|error| Error::Layout { path: path.clone(), error })?;
        let start = h.offset_to_point_data as usize;
        let laszip = meta.vlrs.iter().find(|v| v.is_laszip());
        let kind;
        let mut pieces = Vec::new();
        let mut at = Vec::new();
        let point_count = h.point_count;
        if h.compressed || laszip.is_some() {
            let Some(lv) = laszip else {
                return Err(err(LazError::NoLaszipVlr));
            };
            let vlr = laz::LazVlr::from_buffer(&lv.data)
                .map_err(|error| err(LazError::BadVlr { error }))?;
            // Summed here in u64: laz sums the item sizes in u16 (an overflow panic in debug
            // builds, a wrapped size in release; fuzz regression laz-item-sizes-overflow).
            let items_size: u64 = vlr.items().iter().map(|i| u64::from(i.size())).sum();
            if items_size != h.record_len as u64 {
                return Err(err(LazError::ItemSizes { items_size, record_len: h.record_len }));
            }
            // Reject unknown items up front (decoding them would fail or panic mid-way).
            if let Err(e) = check_laz_items(&vlr) {
                return Err(err(e));
            }
            let data_end =
                if h.evlr_start > 0 && h.evlr_count > 0 && (h.evlr_start as usize) >= start {
                    (h.evlr_start as usize).min(bytes.len())
                } else {
                    bytes.len()
                };
            let plausible = |points: u64| -> std::result::Result<(), LazError> {
                let room = data_end.saturating_sub(start);
                if points > (room as u64).saturating_mul(MAX_LAZ_POINTS_PER_BYTE) {
                    return Err(LazError::Implausible { points, bytes: room });
                }
                Ok(())
            };
            // The compressor first: a pointwise file has no chunk table and no offset to one,
            // and its first 8 bytes are compressed points.
            let compressor = lv.data.get(..2).map_or(0, |b| u16::from_le_bytes([b[0], b[1]]));
            if compressor == POINTWISE {
                if point_count > 0 && data_end <= start {
                    return Err(err(LazError::NoPointData));
                }
                plausible(point_count).map_err(err)?;
                let chunks = if point_count > 0 {
                    vec![LazChunk { offset: start, len: data_end - start, points: point_count }]
                } else {
                    Vec::new()
                };
                kind = Kind::Laz { vlr, chunks };
            } else {
                match read_chunk_table(&bytes, start, data_end, &vlr, point_count) {
                    Ok(Some(chunks)) => kind = Kind::Laz { vlr, chunks },
                    Ok(None) => {
                        if vlr.uses_variable_size_chunks() {
                            return Err(err(LazError::NoChunkTable));
                        }
                        plausible(point_count).map_err(err)?;
                        kind = Kind::LazSequential { vlr, start, end: data_end };
                    }
                    Err(e) => return Err(err(e)),
                }
            }
            let pointwise = compressor == POINTWISE;
            let per_piece = piece_points(h.record_len as usize);
            let mut first = 0;
            let mut add = |chunk: usize, skip: u64, points: u64, whole: bool| {
                pieces.push(Piece { index: pieces.len(), first_point: first, points });
                at.push(PieceAt { chunk, skip, whole });
                first += points;
            };
            match &kind {
                Kind::Laz { chunks, .. } => {
                    for (i, c) in chunks.iter().enumerate() {
                        // a pointwise stream is read as a stream, which reports where it ends
                        if c.points <= per_piece && !pointwise {
                            add(i, 0, c.points, true);
                        } else {
                            for skip in (0..c.points).step_by(per_piece as usize) {
                                add(i, skip, per_piece.min(c.points - skip), false);
                            }
                        }
                    }
                }
                _ => {
                    for skip in (0..point_count).step_by(per_piece as usize) {
                        add(0, skip, per_piece.min(point_count - skip), false);
                    }
                }
            }
            meta.vlrs.retain(|v| !v.is_laszip());
        } else {
            let rl = h.record_len as u64;
            let mut end = bytes.len() as u64;
            if h.evlr_start > 0 && h.evlr_count > 0 && h.evlr_start >= start as u64 {
                end = end.min(h.evlr_start);
            }
            if h.waveform_start > start as u64 && (h.global_encoding & 0x2) != 0 {
                end = end.min(h.waveform_start);
            }
            let available = (end - start as u64) / rl;
            if available > point_count && (h.evlr_count == 0 || h.evlr_start == 0) {
                meta.warnings.push(format!(
                    "the file holds {available} points of data but the header says {point_count}; reading {point_count}"
                ));
            }
            if point_count > available {
                return Err(Error::Truncated {
                    path: path.clone(),
                    declared: point_count,
                    available,
                    bytes: end - start as u64,
                    record_len: rl,
                });
            }
            let mut first = 0;
            let mut i = 0;
            while first < point_count {
                let n = piece_points(rl as usize).min(point_count - first);
                pieces.push(Piece { index: i, first_point: first, points: n });
                first += n;
                i += 1;
            }
            kind = Kind::Las { start };
        }
        Ok(LasInput {
            path,
            bytes: Arc::new(bytes),
            meta,
            layout,
            point_count,
            kind,
            pieces,
            at,
            streams: Streams::default(),
            skip: None,
        })
    }

    /// Decodes only the named attributes (positions always) from now on: a LAS 1.4 layered
    /// LAZ file (point formats 6 to 10) skips the other layers, whose bytes then read as zero.
    /// Other files decode everything as before.
    pub fn decode_only(&mut self, attributes: &[&str]) {
        self.skip = match self.kind {
            Kind::Las { .. } => None,
            _ => Skip::of(&self.layout, attributes),
        };
        // kept decoders decode the old selection
        self.streams.clear();
    }

    /// The whole file's bytes (the COPC hierarchy is read from them).
    pub fn file_bytes(&self) -> &[u8] {
        &self.bytes
    }

    /// Which of the chunk table's chunks are those at the file offsets of `chunks` (offset,
    /// point count); the offset and the reason where one is not in the table or holds another
    /// number of points.
    pub fn find_chunks(
        &self,
        chunks: &[(u64, u64)],
    ) -> std::result::Result<Vec<bool>, (u64, String)> {
        let Kind::Laz { chunks: table, .. } = &self.kind else {
            return Err((0, "the file has no chunk table".into()));
        };
        let at: HashMap<u64, usize> =
            table.iter().enumerate().map(|(i, c)| (c.offset as u64, i)).collect();
        let mut keep = vec![false; table.len()];
        for &(offset, points) in chunks {
            let Some(&i) = at.get(&offset) else {
                return Err((
                    offset,
                    format!("names a chunk at byte {offset} that the chunk table does not list"),
                ));
            };
            if table[i].points != points {
                return Err((
                    offset,
                    format!("says {points} points but the chunk table says {}", table[i].points),
                ));
            }
            keep[i] = true;
        }
        Ok(keep)
    }

    /// Keeps only the chunks at the file offsets of `chunks` (see [`find_chunks`]), in their
    /// file order: reading the input then decodes those alone (a COPC file's selected nodes).
    /// On an error the input is unchanged.
    ///
    /// [`find_chunks`]: Self::find_chunks
    pub fn keep_chunks(&mut self, chunks: &[(u64, u64)]) -> std::result::Result<(), (u64, String)> {
        let keep = self.find_chunks(chunks)?;
        let (mut pieces, mut places) = (Vec::new(), Vec::new());
        let mut first = 0;
        for (p, a) in self.pieces.iter().zip(&self.at) {
            if keep[a.chunk] {
                pieces.push(Piece { index: pieces.len(), first_point: first, points: p.points });
                places.push(*a);
                first += p.points;
            }
        }
        self.pieces = pieces;
        self.at = places;
        self.point_count = first;
        self.streams.clear();
        Ok(())
    }

    pub fn is_laz(&self) -> bool {
        !matches!(self.kind, Kind::Las { .. })
    }

    pub fn pieces(&self) -> &[Piece] {
        &self.pieces
    }

    /// Maps every page of the point data now, in one system call instead of a page fault per
    /// 4 KiB later (for the in-memory sort, which reads all of it; Linux 5.14+, else a no-op).
    pub fn prefetch(&self) {
        if let (Kind::Las { .. }, Bytes::Map(m)) = (&self.kind, &*self.bytes) {
            const MADV_POPULATE_READ: libc::c_int = 22;
            // SAFETY: advice on a mapping this input owns; it changes no contents.
            unsafe { libc::madvise(m.as_ptr() as *mut libc::c_void, m.len(), MADV_POPULATE_READ) };
        }
    }

    /// Drops the pages of a LAS piece from this process's mapping (they stay in the page cache),
    /// so that a pass over a file larger than the memory budget keeps a bounded resident size.
    pub fn release_piece(&self, piece: &Piece) {
        if let (Kind::Las { start }, Bytes::Map(m)) = (&self.kind, &*self.bytes) {
            let rl = self.layout.record_len;
            let s = start + piece.first_point as usize * rl;
            let page = 4096;
            let a = s.div_ceil(page) * page;
            let e = (s + piece.points as usize * rl) / page * page;
            if e > a {
                // SAFETY: the map is private and read-only, nothing holds references into this
                // range after the piece was processed; DONTNEED only drops the pages from the map.
                let _ = unsafe {
                    m.unchecked_advise_range(memmap2::UncheckedAdvice::DontNeed, a, e - a)
                };
            }
        }
    }

    /// Decodes one piece into `out` (exactly `piece.points` records).
    pub fn read_piece_into(&self, piece: &Piece, out: &mut [u8]) -> Result<()> {
        let rl = self.layout.record_len;
        if out.len() != piece.points as usize * rl {
            return Err(Error::Internal {
                path: self.path.clone(),
                what: "piece buffer of the wrong size",
            });
        }
        let laz_err = |error: LazError| Error::Laz { path: self.path.clone(), error };
        let at = match (&self.kind, self.at.get(piece.index)) {
            (Kind::Las { .. }, _) => {
                out.copy_from_slice(&self.read_piece(piece)?);
                return Ok(());
            }
            (_, Some(at)) => *at,
            (_, None) => {
                return Err(Error::Internal {
                    path: self.path.clone(),
                    what: "a piece of another file",
                })
            }
        };
        let selection =
            self.skip.as_ref().map_or(laz::DecompressionSelection::all(), |s| s.selection);
        match &self.kind {
            Kind::Laz { vlr, chunks } if at.whole => {
                let c = &chunks[at.chunk];
                let entry = laz::laszip::ChunkTableEntry {
                    point_count: c.points,
                    byte_count: c.len as u64,
                };
                let src = &self.bytes[c.offset..c.offset + c.len];
                if c.points > 0 {
                    check_layer_sizes(vlr, src, at.chunk).map_err(laz_err)?;
                }
                let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    laz::par_decompress_selective(
                        src,
                        out,
                        vlr,
                        std::slice::from_ref(&entry),
                        selection,
                    )
                }));
                match r {
                    Ok(Ok(())) => {}
                    Ok(Err(error)) => {
                        return Err(laz_err(LazError::ChunkCorrupt { chunk: at.chunk, error }))
                    }
                    Err(_) => return Err(laz_err(LazError::ChunkGaveUp { chunk: at.chunk })),
                }
            }
            _ => self.read_stream(at, out, selection).map_err(laz_err)?,
        }
        if let Some(s) = &self.skip {
            s.clear(out, rl);
        }
        Ok(())
    }

    /// Decodes a piece of a large chunk or of a sequential stream with a kept decoder.
    fn read_stream(
        &self,
        at: PieceAt,
        out: &mut [u8],
        selection: laz::DecompressionSelection,
    ) -> std::result::Result<(), LazError> {
        let rl = self.layout.record_len;
        let mut cur = match self.streams.take(at.chunk, at.skip) {
            Some(c) => c,
            None => self.new_cursor(at.chunk, selection)?,
        };
        let points = (out.len() / rl) as u64;
        let mut done = 0u64;
        let r =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| -> std::io::Result<()> {
                let mut scratch = Vec::new();
                while cur.next < at.skip {
                    let n = (at.skip - cur.next).min(65_536) as usize;
                    scratch.resize(n * rl, 0);
                    cur.dec.decompress_many(&mut scratch)?;
                    cur.next += n as u64;
                }
                for part in out.chunks_mut(65_536 * rl) {
                    cur.dec.decompress_many(part)?;
                    done += (part.len() / rl) as u64;
                }
                Ok(())
            }));
        let chunk = at.chunk;
        let sequential = matches!(self.kind, Kind::LazSequential { .. });
        match r {
            Ok(Ok(())) => {
                cur.next = at.skip + points;
                self.streams.put(cur);
                Ok(())
            }
            Ok(Err(error)) if error.kind() == std::io::ErrorKind::UnexpectedEof => {
                Err(LazError::EndsEarly {
                    got: (cur.next.min(at.skip) + done) as usize,
                    expected: self.chunk_points(chunk),
                })
            }
            Ok(Err(error)) if sequential => Err(LazError::DataCorrupt { error }),
            Ok(Err(error)) => {
                Err(LazError::ChunkCorrupt { chunk, error: laz::LasZipError::IoError(error) })
            }
            Err(_) if sequential => Err(LazError::DataGaveUp),
            Err(_) => Err(LazError::ChunkGaveUp { chunk }),
        }
    }

    /// Points of chunk `chunk` (of the whole stream for a sequential file).
    fn chunk_points(&self, chunk: usize) -> u64 {
        match &self.kind {
            Kind::Laz { chunks, .. } => chunks.get(chunk).map_or(0, |c| c.points),
            _ => self.point_count,
        }
    }

    /// A decoder at the first point of `chunk` (of the stream, for a sequential file).
    fn new_cursor(
        &self,
        chunk: usize,
        selection: laz::DecompressionSelection,
    ) -> std::result::Result<Cursor, LazError> {
        let (source, vlr) = match &self.kind {
            Kind::LazSequential { vlr, start, end } => {
                check_sequential_table(&self.bytes[*start..*end])?;
                (
                    Chain {
                        head: Vec::new(),
                        bytes: self.bytes.clone(),
                        body: *start..*end,
                        tail: Vec::new(),
                        pos: 0,
                    },
                    vlr.clone(),
                )
            }
            Kind::Laz { vlr, chunks } => {
                let c = &chunks[chunk];
                check_layer_sizes(vlr, &self.bytes[c.offset..c.offset + c.len], chunk)?;
                // The chunk as a file of one variable-size chunk: the offset of its table, its
                // bytes, a table of one entry (laz-rs's stream decoder needs the table to know
                // the chunk's points; a pointwise stream is such a chunk).
                let one =
                    laz::LazVlrBuilder::new(vlr.items().clone()).with_variable_chunk_size().build();
                let mut table = laz::laszip::ChunkTable::with_capacity(1);
                table.push(laz::laszip::ChunkTableEntry {
                    point_count: c.points,
                    byte_count: c.len as u64,
                });
                let mut tail = Vec::new();
                table.write_to(&mut tail, &one).map_err(|error| LazError::ChunkCorrupt {
                    chunk,
                    error: laz::LasZipError::IoError(error),
                })?;
                let head = (8 + c.len as i64).to_le_bytes().to_vec();
                (
                    Chain {
                        head,
                        bytes: self.bytes.clone(),
                        body: c.offset..c.offset + c.len,
                        tail,
                        pos: 0,
                    },
                    one,
                )
            }
            Kind::Las { .. } => unreachable!("LAS pieces are read in place"),
        };
        let sequential = matches!(self.kind, Kind::LazSequential { .. });
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            laz::LasZipDecompressor::selective(source, vlr, selection)
        }));
        match r {
            Ok(Ok(dec)) => Ok(Cursor { chunk, next: 0, dec }),
            Ok(Err(laz::LasZipError::IoError(error))) if sequential => {
                Err(LazError::DataCorrupt { error })
            }
            Ok(Err(error)) => Err(LazError::ChunkCorrupt { chunk, error }),
            Err(_) if sequential => Err(LazError::DataGaveUp),
            Err(_) => Err(LazError::ChunkGaveUp { chunk }),
        }
    }

    /// The raw records of one piece: borrowed from the map for LAS, decoded for LAZ.
    pub fn read_piece(&self, piece: &Piece) -> Result<Cow<'_, [u8]>> {
        let rl = self.layout.record_len;
        match &self.kind {
            Kind::Las { start } => {
                let s = start + piece.first_point as usize * rl;
                Ok(Cow::Borrowed(&self.bytes[s..s + piece.points as usize * rl]))
            }
            _ => {
                let mut out = vec![0u8; piece.points as usize * rl];
                self.read_piece_into(piece, &mut out)?;
                Ok(Cow::Owned(out))
            }
        }
    }
}

/// LASzip's compressor 1: one pointwise stream, no chunks.
const POINTWISE: u16 = 1;

fn check_laz_items(vlr: &laz::LazVlr) -> std::result::Result<(), LazError> {
    use laz::LazItemType as T;
    for item in vlr.items() {
        let ok = match item.item_type() {
            T::Point10 | T::GpsTime | T::RGB12 | T::Byte(_) => matches!(item.version(), 1 | 2),
            T::Point14 | T::RGB14 | T::RGBNIR14 | T::Byte14(_) => {
                item.version() == 3 || item.version() == 4
            }
            T::WavePacket13 => item.version() == 1,
            T::WavePacket14 => item.version() == 3 || item.version() == 4,
            #[allow(unreachable_patterns)]
            _ => false,
        };
        if !ok {
            return Err(LazError::UnsupportedItem {
                item: format!("{:?}", item.item_type()),
                version: item.version(),
            });
        }
    }
    Ok(())
}

/// Checks the layer sizes at the start of a layered (LAS 1.4, LASzip v3/v4) chunk against the
/// chunk's bytes: laz-rs allocates each layer's claimed size before reading it, so a damaged
/// size of up to 4 GiB per layer was a huge allocation (fuzz regression laz-layer-size). The
/// chunk starts with the first point raw, the point count (u32), then one u32 size per layer.
fn check_layer_sizes(
    vlr: &laz::LazVlr,
    chunk: &[u8],
    index: usize,
) -> std::result::Result<(), LazError> {
    use laz::LazItemType as T;
    let mut layers = 0usize;
    for item in vlr.items() {
        if !matches!(item.version(), 3 | 4) {
            continue;
        }
        layers += match item.item_type() {
            T::Point14 => 9,
            T::RGB14 | T::WavePacket14 => 1,
            T::RGBNIR14 => 2,
            T::Byte14(n) => n as usize,
            _ => 0,
        };
    }
    if layers == 0 {
        return Ok(());
    }
    let sizes_at = vlr.items_size() as usize + 4;
    let Some(sizes) = chunk.get(sizes_at..sizes_at + 4 * layers) else {
        return Ok(()); // too short: laz-rs reports the truncation itself
    };
    let total: u64 =
        sizes.chunks_exact(4).map(|b| u32::from_le_bytes(b.try_into().unwrap()) as u64).sum();
    let room = (chunk.len() - sizes_at - 4 * layers) as u64;
    if total > room {
        return Err(LazError::ChunkLayers { chunk: index, total, room });
    }
    Ok(())
}

/// Checks what laz's sequential decompressor reads as a chunk table in `data` (the point data
/// onwards, as its source sees it): it looks for one itself, at the offset in the first 8 bytes
/// or in the last 8, and allocates the chunk count it finds there before reading the entries. A
/// count the bytes after it cannot hold is refused (fuzz regression laz-sequential-table: 11 GB
/// asked for by a 2 KB file).
fn check_sequential_table(data: &[u8]) -> std::result::Result<(), LazError> {
    let at = |i: usize| data.get(i..i + 8).map(|x| i64::from_le_bytes(x.try_into().unwrap()));
    let Some(mut off) = at(0) else { return Ok(()) };
    if off <= 0 {
        match at(data.len().saturating_sub(8)) {
            Some(t) if t > 0 => off = t,
            _ => return Ok(()),
        }
    }
    let Some(head) = usize::try_from(off).ok().and_then(|o| data.get(o..o.checked_add(8)?)) else {
        return Ok(());
    };
    let count = u32::from_le_bytes(head[4..8].try_into().unwrap()) as u64;
    let room = (data.len() - off as usize - 8) as u64;
    if count > room.saturating_mul(8).min(1 << 26) {
        return Err(LazError::SequentialTable { chunks: count, bytes: room });
    }
    Ok(())
}

/// Reads and checks the LAZ chunk table; `Ok(None)` when the file has none.
fn read_chunk_table(
    b: &[u8],
    start: usize,
    data_end: usize,
    vlr: &laz::LazVlr,
    point_count: u64,
) -> std::result::Result<Option<Vec<LazChunk>>, LazError> {
    if data_end < start + 8 || data_end > b.len() {
        return if point_count == 0 { Ok(Some(Vec::new())) } else { Err(LazError::NoPointData) };
    }
    let mut table_at = i64::from_le_bytes(b[start..start + 8].try_into().unwrap());
    // The table follows the 8-byte offset itself: an offset inside those 8 bytes is no table
    // (fuzz regression laz-chunk-table-in-offset).
    let first = start as i64 + 8;
    if table_at < first || table_at as u64 + 8 > data_end as u64 {
        // writers that could not seek back put the offset in the last 8 bytes
        let tail = i64::from_le_bytes(b[data_end - 8..data_end].try_into().unwrap());
        if tail >= first && (tail as u64) + 8 <= data_end as u64 {
            table_at = tail;
        } else if table_at > start as i64 && table_at as u64 + 8 > b.len() as u64 && point_count > 0
        {
            return Err(LazError::TableTruncated {
                at: table_at,
                file_len: b.len(),
                points: point_count,
            });
        } else {
            return Ok(None);
        }
    }
    let table_at = table_at as usize;
    let n_chunks = u32::from_le_bytes(b[table_at + 4..table_at + 8].try_into().unwrap()) as u64;
    let data_bytes = (table_at - start - 8) as u64;
    if n_chunks > data_bytes.max(1) || n_chunks > (1 << 26) {
        return Err(LazError::TooManyChunks { chunks: n_chunks, bytes: data_bytes });
    }
    let variable = vlr.uses_variable_size_chunks();
    let mut cur = std::io::Cursor::new(&b[table_at..data_end]);
    let table = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        laz::laszip::ChunkTable::read(&mut cur, variable)
    }))
    .map_err(|_| LazError::BadTable { error: None })?
    .map_err(|e| LazError::BadTable { error: Some(e) })?;
    let mut chunks = Vec::with_capacity(n_chunks as usize);
    let mut offset = start as u64 + 8;
    let mut total = 0u64;
    let entries = table.as_ref();
    for (i, e) in entries.iter().enumerate() {
        let points = if variable {
            e.point_count
        } else if i + 1 == entries.len() {
            point_count.saturating_sub(total)
        } else {
            vlr.chunk_size() as u64
        };
        // The decoded chunk is allocated from this claim: bound it by the chunk's bytes (fuzz
        // regression laz-chunk-points).
        if points > e.byte_count.saturating_mul(MAX_LAZ_POINTS_PER_BYTE).max(1) {
            return Err(LazError::ChunkPoints { chunk: i, points, bytes: e.byte_count });
        }
        if offset.checked_add(e.byte_count).is_none_or(|end| end > table_at as u64) {
            return Err(LazError::ChunkPastTable { chunk: i });
        }
        chunks.push(LazChunk { offset: offset as usize, len: e.byte_count as usize, points });
        offset += e.byte_count;
        total += points;
    }
    if total != point_count {
        return Err(LazError::CountMismatch { declared: point_count, table: total });
    }
    Ok(Some(chunks))
}
