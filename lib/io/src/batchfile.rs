//! The batch file (paper 003 §3.1-3.3): Morton-ordered points in batches of 10,240, coordinates
//! quantized to 30 bits per batch and split into coarse/medium/fine 10-bit words, each section a
//! separate array so a renderer reads only what it needs. The byte layout is in
//! `lib/io/BATCH_FORMAT.md`; the structs read in place are in [`mortar_core::batch`].
//!
//! [`BatchSink`] writes one from the Morton sort; [`BatchFile`] opens one as a read-only memory
//! map with zero-copy access to any batch's arrays (uncompressed files), and is itself a
//! [`RecordSource`] so a batch file converts back to LAS bit for bit.

use crate::cleanup::TempPath;
use crate::dataset::{RecordSource, SourceMeta};
use crate::error::{BatchError, Error, Result};
use crate::las::{self, Header, HeaderOut, Vlr};
use crate::sort::{Key, OrderedSink, Summary};
use crate::source::{open_bytes, Bytes, Piece};
use mortar_core::batch::*;
use mortar_core::batching::{plan_batches, PlannedBatch};
use mortar_core::color::{ColorSource, RgbDepth};
use mortar_core::grid::Grid;
use mortar_core::layout::{read_xyz, write_xyz, Attribute, RecordLayout};
use mortar_core::morton::MortonGrid;
use mortar_core::BATCH_SIZE;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// Section compression.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Compression {
    None,
    Zstd,
}

/// A byte range in the file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Range {
    pub offset: u64,
    pub len: u64,
}

/// How the render colour was derived.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ColorMeta {
    /// `rgb` or `intensity`.
    pub source: String,
    /// For rgb: 8 or 16 (how the 16-bit fields were read).
    pub rgb_bits: Option<u8>,
    pub max_intensity: u16,
}

/// The JSON metadata of a batch file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Meta {
    pub generator: String,
    pub batch_size: usize,
    pub compression: Compression,
    pub point_format: u8,
    pub record_len: usize,
    pub scale: [f64; 3],
    pub offset: [f64; 3],
    /// Integer bounds of all points (inclusive).
    pub int_min: [i32; 3],
    pub int_max: [i32; 3],
    pub world_min: [f64; 3],
    pub world_max: [f64; 3],
    pub morton_origin: [i64; 3],
    pub morton_shift: u32,
    pub points_by_return: [u64; 15],
    pub color: ColorMeta,
    /// Kept attributes, in section order from section 4.
    pub attributes: Vec<AttributeMeta>,
    /// Attributes of the source format not kept (zero when converted back to LAS).
    pub dropped: Vec<String>,
    /// The source's LAS header and VLRs (parseable as a LAS header) and its EVLRs.
    pub las_header: Range,
    pub evlrs: Range,
}

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct AttributeMeta {
    pub name: String,
    pub offset: usize,
    pub width: usize,
}

/// What to keep besides coordinates and colour.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum AttributeSelection {
    All,
    Only(Vec<String>),
}

pub use crate::error::UnknownAttribute;

impl AttributeSelection {
    /// Parses `all`, `none` or a comma-separated list of names.
    pub fn parse(s: &str) -> AttributeSelection {
        match s {
            "all" => AttributeSelection::All,
            "none" | "" => AttributeSelection::Only(Vec::new()),
            _ => AttributeSelection::Only(s.split(',').map(|n| n.trim().to_string()).collect()),
        }
    }

    /// The attributes of `layout` this selection keeps; an error names an unknown attribute.
    pub fn resolve(
        &self,
        layout: &RecordLayout,
    ) -> std::result::Result<Vec<Attribute>, UnknownAttribute> {
        match self {
            AttributeSelection::All => Ok(layout.attributes.clone()),
            AttributeSelection::Only(names) => {
                let mut out = Vec::new();
                for n in names {
                    match layout.attribute(n) {
                        Some(a) => out.push(a.clone()),
                        None => {
                            let have = layout.attributes.iter().map(|a| a.name.clone()).collect();
                            return Err(UnknownAttribute {
                                format: layout.format,
                                name: n.clone(),
                                have,
                            });
                        }
                    }
                }
                out.sort_by_key(|a| a.offset);
                out.dedup();
                Ok(out)
            }
        }
    }
}

/// Writes a batch file from Morton-ordered records.
pub struct BatchSink {
    target: PathBuf,
    tmp: TempPath,
    t: SourceMeta,
    attributes: Vec<Attribute>,
    compression: Compression,
    out: Option<File>,
    pos: u64,
    carry: Vec<u8>,
    entries: Vec<BatchEntry>,
    sections: Vec<SectionEntry>,
    meta: Option<Meta>,
    color: Option<ColorSource>,
    /// Batches placed in the file but not yet written (written while the next ones are built).
    pending: Vec<(u64, Vec<Vec<u8>>)>,
    written: u64,
}

struct BuiltBatch {
    entry: BatchEntry,
    sections: Vec<Vec<u8>>,
}

impl BatchSink {
    pub fn new(
        target: &Path,
        t: SourceMeta,
        attributes: Vec<Attribute>,
        compression: Compression,
    ) -> BatchSink {
        BatchSink {
            target: target.to_path_buf(),
            tmp: TempPath::beside(target),
            t,
            attributes,
            compression,
            out: None,
            pos: 0,
            carry: Vec::new(),
            entries: Vec::new(),
            sections: Vec::new(),
            meta: None,
            color: None,
            pending: Vec::new(),
            written: 0,
        }
    }

    fn section_count(&self) -> usize {
        FIRST_ATTRIBUTE_SECTION + self.attributes.len()
    }

    fn put(&mut self, bytes: &[u8]) -> Result<Range> {
        let p = self.tmp.path().to_path_buf();
        let w = self.out.as_ref().expect("begun");
        let offset = self.pos.next_multiple_of(SECTION_ALIGN);
        w.write_all_at(bytes, offset).map_err(|e| Error::io(&p, e))?;
        self.pos = offset + bytes.len() as u64;
        Ok(Range { offset, len: bytes.len() as u64 })
    }

    fn build(&self, records: &[u8], b: &PlannedBatch) -> Result<BuiltBatch> {
        let rl = self.t.layout.record_len;
        let n = b.range.len();
        let recs = &records[b.range.start * rl..b.range.end * rl];
        let grid = b.grid;
        let cs = self.color.expect("begun");
        let mut sections: Vec<Vec<u8>> = vec![vec![0u8; n * 4]; FIRST_ATTRIBUTE_SECTION];
        {
            let [c, m, f, col] = &mut sections[..4] else { unreachable!() };
            for (k, r) in recs.chunks_exact(rl).enumerate() {
                let w = grid.encode(read_xyz(r));
                c[4 * k..4 * k + 4].copy_from_slice(&w[0].to_le_bytes());
                m[4 * k..4 * k + 4].copy_from_slice(&w[1].to_le_bytes());
                f[4 * k..4 * k + 4].copy_from_slice(&w[2].to_le_bytes());
                col[4 * k..4 * k + 4].copy_from_slice(&cs.rgba(r).to_le_bytes());
            }
        }
        for a in &self.attributes {
            let mut col = Vec::with_capacity(n * a.width);
            mortar_core::layout::copy_column(recs, rl, a.offset, a.width, &mut col);
            sections.push(col);
        }
        if self.compression == Compression::Zstd {
            for s in sections.iter_mut() {
                *s = zstd::bulk::compress(s, 3).map_err(|error| Error::Compress { error })?;
            }
        }
        let g = &self.t.grid;
        let world = |a: usize, v: i32| g.offset[a] + g.scale[a] * v as f64;
        let entry = BatchEntry {
            count: n as u32,
            flags: 0,
            bits: [grid.bits[0], grid.bits[1], grid.bits[2], 0],
            min: grid.min,
            max: b.max,
            _pad: 0,
            first_point: 0,
            world_min: [world(0, grid.min[0]), world(1, grid.min[1]), world(2, grid.min[2])],
            world_max: [world(0, b.max[0]), world(1, b.max[1]), world(2, b.max[2])],
        };
        Ok(BuiltBatch { entry, sections })
    }

    /// Quantizes one window of at most 10,240 consecutive records (split if oversized).
    fn build_window(&self, recs: &[u8]) -> Result<Vec<BuiltBatch>> {
        let xyz: Vec<[i32; 3]> =
            recs.chunks_exact(self.t.layout.record_len).map(read_xyz).collect();
        let mut plan = Vec::new();
        plan_batches(&xyz, BATCH_SIZE, 0, &mut plan);
        plan.iter().map(|b| self.build(recs, b)).collect()
    }

    /// Builds the batches of `windows` windows in parallel, `window(i)` giving the records of
    /// window `i`, while the batches of the previous call are written (pipelined).
    fn build_and_write<'a, F>(&mut self, windows: usize, window: F) -> Result<()>
    where
        F: Fn(usize) -> Cow<'a, [u8]> + Sync,
    {
        let pending = std::mem::take(&mut self.pending);
        let this = &*self;
        let (written, built) = rayon::join(
            || this.write_placed(&pending),
            || -> Result<Vec<Vec<BuiltBatch>>> {
                (0..windows).into_par_iter().map(|w| this.build_window(&window(w))).collect()
            },
        );
        written?;
        let built = built?;
        for mut b in built.into_iter().flatten() {
            let base = self.pos.next_multiple_of(SECTION_ALIGN);
            let mut at = base;
            for s in &b.sections {
                self.sections.push(SectionEntry { offset: at, stored_len: s.len() as u64 });
                at = (at + s.len() as u64).next_multiple_of(SECTION_ALIGN);
            }
            self.pos = at;
            b.entry.first_point = self.written;
            self.written += b.entry.count as u64;
            self.entries.push(b.entry);
            self.pending.push((base, b.sections));
        }
        Ok(())
    }

    fn write_placed(&self, placed: &[(u64, Vec<Vec<u8>>)]) -> Result<()> {
        let f = self.out.as_ref().expect("begun");
        let p = self.tmp.path();
        for (base, sections) in placed {
            let mut at = *base;
            for s in sections {
                f.write_all_at(s, at).map_err(|e| Error::io(p, e))?;
                at = (at + s.len() as u64).next_multiple_of(SECTION_ALIGN);
            }
        }
        Ok(())
    }

    /// Builds and writes the batches of contiguous `records`; a trailing partial batch stays in
    /// the carry unless `last`.
    fn flush_records(&mut self, records: &[u8], last: bool) -> Result<()> {
        let rl = self.t.layout.record_len;
        let n = records.len() / rl;
        let full = if last { n } else { n / BATCH_SIZE * BATCH_SIZE };
        let windows = full.div_ceil(BATCH_SIZE);
        self.build_and_write(windows, |w| {
            Cow::Borrowed(&records[w * BATCH_SIZE * rl..((w + 1) * BATCH_SIZE).min(full) * rl])
        })?;
        self.carry = records[full * rl..].to_vec();
        Ok(())
    }

    /// Writes the tail, the metadata and the tables, then renames the file into place.
    pub fn finish(mut self) -> Result<u64> {
        let carry = std::mem::take(&mut self.carry);
        self.flush_records(&carry, true)?;
        let pending = std::mem::take(&mut self.pending);
        self.write_placed(&pending)?;
        let meta = self
            .meta
            .clone()
            .ok_or(Error::SinkOrder { what: "batch sink finished before it began" })?;
        let json = serde_json::to_vec_pretty(&meta).map_err(|error| Error::Json { error })?;
        let meta_r = self.put(&json)?;
        let entries = std::mem::take(&mut self.entries);
        let sections = std::mem::take(&mut self.sections);
        let table = self.put(bytemuck::cast_slice(&entries))?;
        self.put(bytemuck::cast_slice(&sections))?;
        let header = FileHeader {
            magic: MAGIC,
            version: VERSION,
            flags: if self.compression == Compression::Zstd { FLAG_ZSTD } else { 0 },
            point_count: self.written,
            batch_count: entries.len() as u64,
            section_count: self.section_count() as u32,
            _pad: 0,
            meta_offset: meta_r.offset,
            meta_len: meta_r.len,
            table_offset: table.offset,
        };
        let p = self.tmp.path().to_path_buf();
        let f = self.out.take().expect("begun");
        f.write_all_at(bytemuck::bytes_of(&header), 0).map_err(|e| Error::io(&p, e))?;
        f.set_len(self.pos).map_err(|e| Error::io(&p, e))?;
        drop(f);
        let written = self.written;
        let BatchSink { tmp, target, .. } = self;
        tmp.persist(&target).map_err(|e| Error::io(&target, e))?;
        Ok(written)
    }
}

impl OrderedSink for BatchSink {
    fn begin(&mut self, s: &Summary) -> Result<()> {
        let p = self.tmp.path().to_path_buf();
        let f = File::create(&p).map_err(|e| Error::io(&p, e))?;
        self.out = Some(f);
        self.put(&[0u8; std::mem::size_of::<FileHeader>()])?;
        let g = self.t.grid;
        let world = |a: usize, v: i32| g.offset[a] + g.scale[a] * v as f64;
        let world_min = [world(0, s.min[0]), world(1, s.min[1]), world(2, s.min[2])];
        let world_max = [world(0, s.max[0]), world(1, s.max[1]), world(2, s.max[2])];
        let hb = las::write_header(&HeaderOut {
            template: &self.t.header,
            point_format: self.t.layout.format,
            compressed: false,
            record_len: self.t.layout.record_len as u16,
            point_count: s.count,
            points_by_return: s.points_by_return,
            scale: g.scale,
            offset: g.offset,
            min: world_min,
            max: world_max,
            vlrs: &self.t.vlrs,
            evlr_start: 0,
            evlr_count: 0,
        })
        .map_err(|error| Error::Las { path: self.target.clone(), error })?;
        let las_header = self.put(&hb)?;
        let evlrs = self.put(&las::write_evlrs(&self.t.evlrs))?;
        let color = match self.t.layout.attribute("rgb") {
            Some(a) if s.max_rgb > 0 => {
                ColorSource::Rgb { offset: a.offset, depth: RgbDepth::detect(s.max_rgb) }
            }
            _ => ColorSource::Intensity { max_intensity: s.max_intensity },
        };
        self.color = Some(color);
        let color_meta = match color {
            ColorSource::Rgb { depth, .. } => ColorMeta {
                source: "rgb".into(),
                rgb_bits: Some(if depth == RgbDepth::Eight { 8 } else { 16 }),
                max_intensity: s.max_intensity,
            },
            ColorSource::Intensity { max_intensity } => {
                ColorMeta { source: "intensity".into(), rgb_bits: None, max_intensity }
            }
        };
        self.meta = Some(Meta {
            generator: format!("mortar {}", env!("CARGO_PKG_VERSION")),
            batch_size: BATCH_SIZE,
            compression: self.compression,
            point_format: self.t.layout.format,
            record_len: self.t.layout.record_len,
            scale: g.scale,
            offset: g.offset,
            int_min: s.min,
            int_max: s.max,
            world_min,
            world_max,
            morton_origin: s.morton.origin,
            morton_shift: s.morton.shift,
            points_by_return: s.points_by_return,
            color: color_meta,
            attributes: self
                .attributes
                .iter()
                .map(|a| AttributeMeta { name: a.name.clone(), offset: a.offset, width: a.width })
                .collect(),
            dropped: self
                .t
                .layout
                .attributes
                .iter()
                .filter(|a| !self.attributes.contains(a))
                .map(|a| a.name.clone())
                .collect(),
            las_header,
            evlrs,
        });
        Ok(())
    }

    fn prefers_keyed(&self) -> bool {
        true
    }

    fn write_keyed(&mut self, slabs: &[&[u8]], keys: &[Key], rl: usize) -> Result<()> {
        if !self.carry.is_empty() {
            return self.write(&crate::sort::gather(slabs, keys, rl));
        }
        let full = keys.len() / BATCH_SIZE * BATCH_SIZE;
        self.build_and_write(full / BATCH_SIZE, |w| {
            Cow::Owned(crate::sort::gather(slabs, &keys[w * BATCH_SIZE..(w + 1) * BATCH_SIZE], rl))
        })?;
        self.carry = crate::sort::gather(slabs, &keys[full..], rl);
        Ok(())
    }

    fn write(&mut self, records: &[u8]) -> Result<()> {
        if self.carry.is_empty() {
            self.flush_records(records, false)
        } else {
            let mut joined = std::mem::take(&mut self.carry);
            joined.extend_from_slice(records);
            self.flush_records(&joined, false)
        }
    }
}

/// One batch's arrays, borrowed from the map (uncompressed files) or decompressed.
pub struct BatchView<'a> {
    pub entry: &'a BatchEntry,
    sections: Vec<SectionData<'a>>,
}

/// One section's bytes: borrowed from the map, or decompressed into a `u32`-aligned buffer.
enum SectionData<'a> {
    Borrowed(&'a [u8]),
    Owned(Vec<u32>, usize),
}

impl SectionData<'_> {
    fn bytes(&self) -> &[u8] {
        match self {
            SectionData::Borrowed(b) => b,
            SectionData::Owned(v, len) => &bytemuck::cast_slice(v)[..*len],
        }
    }
}

impl<'a> BatchView<'a> {
    /// Coordinate words: 0 coarse, 1 medium, 2 fine.
    pub fn words(&self, level: usize) -> &[u32] {
        bytemuck::cast_slice(self.sections[SECTION_COARSE + level].bytes())
    }
    /// Render colours, RGBA8 packed as `r | g << 8 | b << 16 | a << 24`.
    pub fn colors(&self) -> &[u32] {
        bytemuck::cast_slice(self.sections[SECTION_COLOR].bytes())
    }
    /// Raw bytes of kept attribute `i` (`width` bytes per point).
    pub fn attribute(&self, i: usize) -> &[u8] {
        self.sections[FIRST_ATTRIBUTE_SECTION + i].bytes()
    }
    pub fn len(&self) -> usize {
        self.entry.count as usize
    }
    pub fn is_empty(&self) -> bool {
        self.entry.count == 0
    }
}

/// An opened batch file.
pub struct BatchFile {
    pub path: PathBuf,
    bytes: Bytes,
    pub header: FileHeader,
    pub meta: Meta,
    pub las: las::LasMeta,
    pub layout: RecordLayout,
    table_offset: usize,
}

impl std::fmt::Debug for BatchFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BatchFile")
            .field("path", &self.path)
            .field("batches", &self.header.batch_count)
            .finish()
    }
}

/// Whether the bytes start like a batch file.
pub fn is_batch_file(path: &Path) -> bool {
    let mut m = [0u8; 8];
    File::open(path).and_then(|mut f| std::io::Read::read_exact(&mut f, &mut m)).is_ok()
        && m == MAGIC
}

impl BatchFile {
    pub fn open(path: &Path) -> Result<BatchFile> {
        Self::from_bytes(path, open_bytes(path)?)
    }

    /// Opens a batch file held in `bytes` (`path` names it in messages); every length is
    /// checked against the bytes that exist. The fuzz targets' entry point.
    pub fn from_bytes(path: &Path, bytes: Bytes) -> Result<BatchFile> {
        let err = |error: BatchError| Error::Batch { path: path.to_path_buf(), error };
        let hs = std::mem::size_of::<FileHeader>();
        if bytes.len() < hs || bytes[..8] != MAGIC {
            return Err(err(BatchError::NotBatchFile));
        }
        let header: FileHeader = bytemuck::pod_read_unaligned(&bytes[..hs]);
        if header.version != VERSION {
            return Err(err(BatchError::Version { found: header.version, supported: VERSION }));
        }
        let len = bytes.len() as u64;
        let in_file = |o: u64, l: u64| o.checked_add(l).is_some_and(|e| e <= len);
        if !in_file(header.meta_offset, header.meta_len) {
            return Err(err(BatchError::MetaOutside));
        }
        let meta: Meta = serde_json::from_slice(
            &bytes[header.meta_offset as usize..(header.meta_offset + header.meta_len) as usize],
        )
        .map_err(|error| err(BatchError::BadMeta { error }))?;
        let sc = header.section_count as u64;
        if sc != (FIRST_ATTRIBUTE_SECTION + meta.attributes.len()) as u64 {
            return Err(err(BatchError::SectionCount));
        }
        let table_len = header.batch_count.checked_mul(96).and_then(|a| {
            header
                .batch_count
                .checked_mul(sc)
                .and_then(|b| b.checked_mul(16))
                .and_then(|b| a.checked_add(b))
        });
        match table_len {
            Some(tl)
                if in_file(header.table_offset, tl) && header.table_offset.is_multiple_of(8) => {}
            _ => return Err(err(BatchError::TableOutside)),
        }
        if !in_file(meta.las_header.offset, meta.las_header.len)
            || !in_file(meta.evlrs.offset, meta.evlrs.len)
        {
            return Err(err(BatchError::LasHeaderOutside));
        }
        let hb = &bytes[meta.las_header.offset as usize
            ..(meta.las_header.offset + meta.las_header.len) as usize];
        let mut lasmeta =
            las::parse(hb).map_err(|error| err(BatchError::BadLasHeader { error }))?;
        let eb = &bytes[meta.evlrs.offset as usize..(meta.evlrs.offset + meta.evlrs.len) as usize];
        lasmeta.evlrs = parse_evlr_blob(eb).map_err(|error| err(BatchError::BadEvlrs { error }))?;
        let layout = RecordLayout::new(meta.point_format, meta.record_len)
            .map_err(|error| err(BatchError::Layout { error }))?;
        // Records are rebuilt from the attribute columns: each must lie inside a record (fuzz
        // regression attribute-outside-record), and records are LAS records (at most 65,535 bytes).
        if meta.record_len > u16::MAX as usize {
            return Err(err(BatchError::RecordTooLong { record_len: meta.record_len }));
        }
        if let Some(a) = meta.attributes.iter().find(|a| {
            a.offset.checked_add(a.width).is_none_or(|e| e > meta.record_len) || a.offset < 12
        }) {
            return Err(err(BatchError::AttributeOutside {
                name: a.name.clone(),
                offset: a.offset,
                width: a.width,
                record_len: meta.record_len,
            }));
        }
        let f = BatchFile {
            path: path.to_path_buf(),
            bytes,
            header,
            meta,
            las: lasmeta,
            layout,
            table_offset: header.table_offset as usize,
        };
        f.check_table().map_err(err)?;
        Ok(f)
    }

    /// All batch entries (zero-copy).
    pub fn entries(&self) -> &[BatchEntry] {
        let n = self.header.batch_count as usize;
        bytemuck::cast_slice(&self.bytes[self.table_offset..self.table_offset + n * 96])
    }

    fn section_entries(&self) -> &[SectionEntry] {
        let n = self.header.batch_count as usize;
        let s = self.table_offset + n * 96;
        bytemuck::cast_slice(&self.bytes[s..s + n * self.header.section_count as usize * 16])
    }

    fn widths(&self) -> Vec<usize> {
        let mut w = vec![4, 4, 4, 4];
        w.extend(self.meta.attributes.iter().map(|a| a.width));
        w
    }

    fn check_table(&self) -> std::result::Result<(), BatchError> {
        let sc = self.header.section_count as usize;
        let widths = self.widths();
        let mut total = 0u64;
        for (i, e) in self.entries().iter().enumerate() {
            if e.count as usize > (1 << 24) || e.bits.iter().take(3).any(|&b| b > 30) {
                return Err(BatchError::BadEntry { batch: i });
            }
            if e.first_point != total {
                return Err(BatchError::BatchStart {
                    batch: i,
                    first: e.first_point,
                    preceding: total,
                });
            }
            total += e.count as u64;
            for (s, se) in self.section_entries()[i * sc..(i + 1) * sc].iter().enumerate() {
                if se
                    .offset
                    .checked_add(se.stored_len)
                    .is_none_or(|end| end > self.bytes.len() as u64)
                {
                    return Err(BatchError::SectionOutside { batch: i, section: s });
                }
                let raw = e.count as u64 * widths[s] as u64;
                if self.meta.compression == Compression::None
                    && (se.stored_len != raw || se.offset % 4 != 0)
                {
                    return Err(BatchError::SectionLen {
                        batch: i,
                        section: s,
                        len: se.stored_len,
                        expected: raw,
                    });
                }
            }
        }
        if total != self.header.point_count {
            return Err(BatchError::PointCount { total, declared: self.header.point_count });
        }
        Ok(())
    }

    pub fn batch_count(&self) -> usize {
        self.header.batch_count as usize
    }

    /// The arrays of batch `i`; sections listed in `which` (others left empty). Uncompressed
    /// files are borrowed from the map without copying.
    pub fn batch_sections(&self, i: usize, which: &[usize]) -> Result<BatchView<'_>> {
        let e = &self.entries()[i];
        let sc = self.header.section_count as usize;
        let widths = self.widths();
        let ses = &self.section_entries()[i * sc..(i + 1) * sc];
        let mut sections = Vec::with_capacity(sc);
        for (s, se) in ses.iter().enumerate() {
            if !which.contains(&s) {
                sections.push(SectionData::Owned(Vec::new(), 0));
                continue;
            }
            let stored = &self.bytes[se.offset as usize..(se.offset + se.stored_len) as usize];
            let raw = e.count as usize * widths[s];
            match self.meta.compression {
                Compression::None => sections.push(SectionData::Borrowed(stored)),
                Compression::Zstd => {
                    let mut v = vec![0u32; raw.div_ceil(4)];
                    let n = zstd::bulk::Decompressor::new()
                        .and_then(|mut d| {
                            d.decompress_to_buffer(
                                stored,
                                &mut bytemuck::cast_slice_mut::<u32, u8>(&mut v)[..raw],
                            )
                        })
                        .map_err(|error| Error::Batch {
                            path: self.path.clone(),
                            error: BatchError::SectionCorrupt { batch: i, section: s, error },
                        })?;
                    if n != raw {
                        return Err(Error::Batch {
                            path: self.path.clone(),
                            error: BatchError::SectionSize {
                                batch: i,
                                section: s,
                                len: n,
                                expected: raw,
                            },
                        });
                    }
                    sections.push(SectionData::Owned(v, raw));
                }
            }
        }
        Ok(BatchView { entry: e, sections })
    }

    /// Every array of batch `i`.
    pub fn batch(&self, i: usize) -> Result<BatchView<'_>> {
        let all: Vec<usize> = (0..self.header.section_count as usize).collect();
        self.batch_sections(i, &all)
    }

    pub fn grid(&self) -> Grid {
        Grid { scale: self.meta.scale, offset: self.meta.offset }
    }

    /// The whole file as bytes (the memory map), e.g. to check that views point into it.
    pub fn bytes(&self) -> &[u8] {
        &self.bytes
    }

    pub fn morton(&self) -> MortonGrid {
        MortonGrid { origin: self.meta.morton_origin, shift: self.meta.morton_shift }
    }

    /// Rebuilds LAS records of batches `range` (dropped attributes are zero).
    pub fn records(&self, range: std::ops::Range<usize>) -> Result<Vec<u8>> {
        let rl = self.layout.record_len;
        let n: usize = self.entries()[range.clone()].iter().map(|e| e.count as usize).sum();
        let mut out = vec![0u8; n * rl];
        let mut at = 0;
        for i in range {
            let b = self.batch(i)?;
            let g = b.entry.grid();
            let (c, m, f) = (b.words(0), b.words(1), b.words(2));
            for k in 0..b.len() {
                let rec = &mut out[(at + k) * rl..(at + k + 1) * rl];
                write_xyz(rec, g.decode_exact([c[k], m[k], f[k]]));
            }
            for (ai, a) in self.meta.attributes.iter().enumerate() {
                let col = b.attribute(ai);
                for k in 0..b.len() {
                    out[(at + k) * rl + a.offset..(at + k) * rl + a.offset + a.width]
                        .copy_from_slice(&col[k * a.width..(k + 1) * a.width]);
                }
            }
            at += b.len();
        }
        Ok(out)
    }
}

fn parse_evlr_blob(b: &[u8]) -> std::result::Result<Vec<Vlr>, las::LasError> {
    let mut out = Vec::new();
    let mut p = 0usize;
    while p < b.len() {
        let (v, next) = las::parse_evlr(b, p)?;
        out.push(v);
        p = next;
    }
    Ok(out)
}

/// Batches per piece when a batch file is read back as records.
const BATCHES_PER_PIECE: usize = 64;

impl RecordSource for BatchFile {
    fn path(&self) -> &Path {
        &self.path
    }
    fn header(&self) -> &Header {
        &self.las.header
    }
    fn vlrs(&self) -> &[Vlr] {
        &self.las.vlrs
    }
    fn evlrs(&self) -> &[Vlr] {
        &self.las.evlrs
    }
    fn layout(&self) -> &RecordLayout {
        &self.layout
    }
    fn point_count(&self) -> u64 {
        self.header.point_count
    }
    fn pieces(&self) -> Vec<Piece> {
        let e = self.entries();
        (0..e.len())
            .step_by(BATCHES_PER_PIECE)
            .enumerate()
            .map(|(i, s)| {
                let end = (s + BATCHES_PER_PIECE).min(e.len());
                Piece {
                    index: i,
                    first_point: e[s].first_point,
                    points: e[s..end].iter().map(|x| x.count as u64).sum(),
                }
            })
            .collect()
    }
    fn read_piece(&self, piece: &Piece) -> Result<Cow<'_, [u8]>> {
        let s = piece.index * BATCHES_PER_PIECE;
        let end = (s + BATCHES_PER_PIECE).min(self.batch_count());
        Ok(Cow::Owned(self.records(s..end)?))
    }
    fn is_compressed(&self) -> bool {
        self.meta.compression != Compression::None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{self, SynthOptions};

    /// Points of the test files: one full batch and a partial one.
    const N: usize = BATCH_SIZE + 1_500;

    /// A fresh directory under the system's temporary directory.
    fn scratch(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("mortar-batchfile-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn vlr(record_id: u16, data: &[u8]) -> Vlr {
        let mut user_id = [0u8; 16];
        user_id[..6].copy_from_slice(b"mortar");
        Vlr { reserved: 0, user_id, record_id, description: [7; 32], data: data.to_vec() }
    }

    /// What a test file was written from: the source and its records in Morton order.
    struct Written {
        path: PathBuf,
        t: SourceMeta,
        records: Vec<u8>,
        summary: Summary,
    }

    /// Writes `N` synthetic points (point format 3) as a batch file keeping `keep`.
    fn write(dir: &Path, compression: Compression, keep: &AttributeSelection) -> Written {
        let o =
            SynthOptions { points: N as u64, seed: 3, extent: 200.0, ..SynthOptions::default() };
        let layout = o.layout();
        let header = synth::header(&o);
        let grid = Grid { scale: header.scale, offset: header.offset };
        let t = SourceMeta {
            header,
            vlrs: vec![vlr(1, b"a vlr")],
            evlrs: vec![vlr(2, b"an evlr"), vlr(3, &[])],
            layout,
            grid,
        };
        let (records, stats) = synth::records(&o, 0, N as u64);
        let summary = stats.summary();
        // Morton order, as the sort hands them over.
        let rl = t.layout.record_len;
        let mut order: Vec<usize> = (0..N).collect();
        let code = |i: usize| {
            let p = read_xyz(&records[i * rl..]);
            summary.morton.code(p.map(|v| v as i64))
        };
        order.sort_by_key(|&i| (code(i), i));
        let records: Vec<u8> =
            order.iter().flat_map(|&i| records[i * rl..(i + 1) * rl].to_vec()).collect();
        let path = dir.join(format!("{compression:?}.mbat"));
        let attrs = keep.resolve(&t.layout).unwrap();
        let mut sink = BatchSink::new(&path, t.clone(), attrs, compression);
        sink.begin(&summary).unwrap();
        // In two writes that do not end on a batch: the carry joins them.
        let cut = 3_000 * rl;
        sink.write(&records[..cut]).unwrap();
        sink.write(&records[cut..]).unwrap();
        assert_eq!(sink.finish().unwrap(), N as u64);
        Written { path, t, records, summary }
    }

    /// The error `BatchFile::from_bytes` gives for `bytes`.
    fn refusal(bytes: Vec<u8>) -> BatchError {
        let path = Path::new("damaged.mbat");
        match BatchFile::from_bytes(path, Bytes::Owned(bytes)) {
            Err(Error::Batch { path: p, error }) => {
                assert_eq!(p, path);
                error
            }
            Err(e) => panic!("another error: {e}"),
            Ok(_) => panic!("a damaged file was opened"),
        }
    }

    fn header_of(b: &[u8]) -> FileHeader {
        bytemuck::pod_read_unaligned(&b[..std::mem::size_of::<FileHeader>()])
    }

    /// `b` with its header changed by `f`.
    fn with_header(b: &[u8], f: impl Fn(&mut FileHeader)) -> Vec<u8> {
        let mut h = header_of(b);
        f(&mut h);
        let mut out = b.to_vec();
        out[..std::mem::size_of::<FileHeader>()].copy_from_slice(bytemuck::bytes_of(&h));
        out
    }

    /// `b` with batch entry `i` changed by `f`.
    fn with_entry(b: &[u8], i: usize, f: impl Fn(&mut BatchEntry)) -> Vec<u8> {
        let at = header_of(b).table_offset as usize + 96 * i;
        let mut e: BatchEntry = bytemuck::pod_read_unaligned(&b[at..at + 96]);
        f(&mut e);
        let mut out = b.to_vec();
        out[at..at + 96].copy_from_slice(bytemuck::bytes_of(&e));
        out
    }

    /// `b` with the section entry of batch `i`, section `s` changed by `f`.
    fn with_section(b: &[u8], i: usize, s: usize, f: impl Fn(&mut SectionEntry)) -> Vec<u8> {
        let h = header_of(b);
        let sc = h.section_count as usize;
        let at = (h.table_offset + 96 * h.batch_count) as usize + 16 * (i * sc + s);
        let mut e: SectionEntry = bytemuck::pod_read_unaligned(&b[at..at + 16]);
        f(&mut e);
        let mut out = b.to_vec();
        out[at..at + 16].copy_from_slice(bytemuck::bytes_of(&e));
        out
    }

    /// `b` with its metadata changed by `f` (the new JSON appended, the header pointed at it).
    fn with_meta(b: &[u8], f: impl Fn(&mut Meta)) -> Vec<u8> {
        let h = header_of(b);
        let mut m: Meta = serde_json::from_slice(
            &b[h.meta_offset as usize..(h.meta_offset + h.meta_len) as usize],
        )
        .unwrap();
        f(&mut m);
        let json = serde_json::to_vec(&m).unwrap();
        let mut out = b.to_vec();
        let at = out.len() as u64;
        out.extend_from_slice(&json);
        with_header(&out, |h| (h.meta_offset, h.meta_len) = (at, json.len() as u64))
    }

    #[test]
    fn a_batch_file_is_read_back_as_written() {
        let dir = scratch("roundtrip");
        let keep = AttributeSelection::parse("gps_time,intensity,classification");
        for compression in [Compression::None, Compression::Zstd] {
            let w = write(&dir, compression, &keep);
            let rl = w.t.layout.record_len;
            let f = BatchFile::open(&w.path).unwrap();
            // The header.
            assert_eq!((f.header.magic, f.header.version), (MAGIC, VERSION));
            let zstd = compression == Compression::Zstd;
            assert_eq!(f.header.flags, if zstd { FLAG_ZSTD } else { 0 });
            assert_eq!(f.header.point_count, N as u64);
            assert_eq!(f.batch_count(), 2);
            assert_eq!(f.header.section_count as usize, FIRST_ATTRIBUTE_SECTION + 3);
            assert_eq!(f.header.table_offset % 8, 0);
            assert_eq!(f.is_compressed(), zstd);
            // The metadata: kept attributes in record order, the others dropped.
            let m = &f.meta;
            assert_eq!((m.batch_size, m.compression), (BATCH_SIZE, compression));
            assert_eq!((m.point_format, m.record_len), (3, 34));
            assert_eq!((m.scale, m.offset), (w.t.grid.scale, w.t.grid.offset));
            assert_eq!((m.int_min, m.int_max), (w.summary.min, w.summary.max));
            assert_eq!(
                (m.morton_origin, m.morton_shift),
                (w.summary.morton.origin, w.summary.morton.shift)
            );
            assert_eq!(m.points_by_return, w.summary.points_by_return);
            assert!(m.generator.starts_with("mortar "));
            // Synthetic colours are 16-bit.
            assert_eq!(
                m.color,
                ColorMeta {
                    source: "rgb".into(),
                    rgb_bits: Some(16),
                    max_intensity: w.summary.max_intensity
                }
            );
            let kept: Vec<(&str, usize, usize)> =
                m.attributes.iter().map(|a| (a.name.as_str(), a.offset, a.width)).collect();
            assert_eq!(
                kept,
                [("intensity", 12, 2), ("classification", 15, 1), ("gps_time", 20, 8)]
            );
            assert_eq!(m.dropped, ["flags", "scan_angle", "user_data", "point_source_id", "rgb"]);
            // The LAS front matter, whole.
            assert_eq!(f.las.header.point_count, N as u64);
            assert_eq!(f.las.header.point_format, 3);
            assert_eq!(f.las.vlrs, w.t.vlrs);
            assert_eq!(f.las.evlrs, w.t.evlrs);
            assert_eq!(f.layout, w.t.layout);
            // Batches: consecutive, a full one then the rest.
            let e = f.entries();
            assert_eq!((e[0].count, e[0].first_point), (BATCH_SIZE as u32, 0));
            assert_eq!(
                (e[1].count, e[1].first_point),
                ((N - BATCH_SIZE) as u32, BATCH_SIZE as u64)
            );
            // Every word, colour and attribute as the records say.
            let color = ColorSource::Rgb { offset: 28, depth: RgbDepth::Sixteen };
            let mut at = 0;
            for i in 0..f.batch_count() {
                let b = f.batch(i).unwrap();
                let g = b.entry.grid();
                assert_eq!(b.len(), b.entry.count as usize);
                for k in 0..b.len() {
                    let r = &w.records[(at + k) * rl..(at + k + 1) * rl];
                    let p = g.decode_exact([b.words(0)[k], b.words(1)[k], b.words(2)[k]]);
                    assert_eq!(p, read_xyz(r), "batch {i} point {k}");
                    assert!((0..3).all(|a| b.entry.min[a] <= p[a] && p[a] <= b.entry.max[a]));
                    assert_eq!(b.colors()[k], color.rgba(r));
                    assert_eq!(&b.attribute(0)[2 * k..2 * k + 2], &r[12..14]);
                    assert_eq!(b.attribute(1)[k], r[15]);
                    assert_eq!(&b.attribute(2)[8 * k..8 * k + 8], &r[20..28]);
                }
                // Only the sections asked for.
                let v = f.batch_sections(i, &[SECTION_FINE]).unwrap();
                assert_eq!(v.words(2), b.words(2));
                assert!(v.words(0).is_empty() && v.colors().is_empty());
                at += b.len();
            }
            assert_eq!(at, N);
            // Records rebuilt: positions and kept attributes as written, dropped ones zero.
            let back = f.records(0..f.batch_count()).unwrap();
            assert_eq!(back.len(), N * rl);
            let mut expect = vec![0u8; N * rl];
            for (o, r) in expect.chunks_exact_mut(rl).zip(w.records.chunks_exact(rl)) {
                for (a, n) in [(0, 12), (12, 2), (15, 1), (20, 8)] {
                    o[a..a + n].copy_from_slice(&r[a..a + n]);
                }
            }
            assert!(back == expect, "records rebuilt from {compression:?}");
            // As a record source: its pieces cover every point, in order.
            let pieces = f.pieces();
            assert_eq!(pieces.len(), 1);
            assert_eq!((pieces[0].first_point, pieces[0].points), (0, N as u64));
            assert!(f.read_piece(&pieces[0]).unwrap()[..] == back[..]);
            assert!(is_batch_file(&w.path));
        }
        std::fs::write(dir.join("short"), &MAGIC[..7]).unwrap();
        assert!(!is_batch_file(&dir.join("short")));
        assert!(!is_batch_file(&dir.join("missing")));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn attribute_selections_parse_and_resolve_in_record_order() {
        assert_eq!(AttributeSelection::parse("all"), AttributeSelection::All);
        assert_eq!(AttributeSelection::parse("none"), AttributeSelection::Only(Vec::new()));
        assert_eq!(AttributeSelection::parse(""), AttributeSelection::Only(Vec::new()));
        let sel = AttributeSelection::parse("rgb, intensity,rgb");
        assert_eq!(
            sel,
            AttributeSelection::Only(vec!["rgb".into(), "intensity".into(), "rgb".into()])
        );
        let layout = RecordLayout::new(3, 34).unwrap();
        let names = |s: &AttributeSelection| -> Vec<String> {
            s.resolve(&layout).unwrap().into_iter().map(|a| a.name).collect()
        };
        // Sorted by offset, each once.
        assert_eq!(names(&sel), ["intensity", "rgb"]);
        assert_eq!(names(&AttributeSelection::All).len(), layout.attributes.len());
        assert!(names(&AttributeSelection::parse("none")).is_empty());
        let e = AttributeSelection::parse("intensity,colour").resolve(&layout).unwrap_err();
        assert_eq!((e.format, e.name.as_str()), (3, "colour"));
        assert!(e.have.iter().any(|n| n == "rgb") && e.have.len() == layout.attributes.len());
    }

    #[test]
    fn damaged_files_are_refused_with_the_reason_and_no_panic() {
        let dir = scratch("damaged");
        let w = write(&dir, Compression::None, &AttributeSelection::All);
        let good = std::fs::read(&w.path).unwrap();
        assert!(BatchFile::from_bytes(&w.path, Bytes::Owned(good.clone())).is_ok());
        let h = header_of(&good);
        let sc = h.section_count as usize;
        assert_eq!(sc, FIRST_ATTRIBUTE_SECTION + 8);
        // Not a batch file: empty, shorter than a header, another magic.
        assert!(matches!(refusal(Vec::new()), BatchError::NotBatchFile));
        assert!(matches!(refusal(good[..40].to_vec()), BatchError::NotBatchFile));
        let mut b = good.clone();
        b[0] = b'L';
        assert!(matches!(refusal(b), BatchError::NotBatchFile));
        assert!(matches!(
            refusal(with_header(&good, |h| h.version = 2)),
            BatchError::Version { found: 2, supported: VERSION }
        ));
        // Truncated: the metadata (written after the sections) is gone.
        assert!(matches!(refusal(good[..good.len() / 2].to_vec()), BatchError::MetaOutside));
        // Offsets and lengths that lie, also past u64.
        assert!(matches!(
            refusal(with_header(&good, |h| h.meta_len = u64::MAX)),
            BatchError::MetaOutside
        ));
        assert!(matches!(
            refusal(with_header(&good, |h| h.meta_offset = good.len() as u64)),
            BatchError::MetaOutside
        ));
        assert!(matches!(
            refusal(with_header(&good, |h| h.meta_offset += 1)),
            BatchError::BadMeta { .. }
        ));
        assert!(matches!(
            refusal(with_header(&good, |h| h.section_count += 1)),
            BatchError::SectionCount
        ));
        // Batch counts whose table would not fit (no allocation of that size is tried).
        for n in [h.batch_count + 1, 1 << 40, u64::MAX / 96 + 1, u64::MAX] {
            assert!(
                matches!(
                    refusal(with_header(&good, |h| h.batch_count = n)),
                    BatchError::TableOutside
                ),
                "batch count {n}"
            );
        }
        assert!(matches!(
            refusal(with_header(&good, |h| h.table_offset += 4)),
            BatchError::TableOutside
        ));
        assert!(matches!(
            refusal(with_header(&good, |h| h.point_count += 1)),
            BatchError::PointCount { total, declared }
                if total == N as u64 && declared == N as u64 + 1
        ));
        // Batch and section entries that lie.
        assert!(matches!(
            refusal(with_entry(&good, 0, |e| e.bits[1] = 31)),
            BatchError::BadEntry { batch: 0 }
        ));
        assert!(matches!(
            refusal(with_entry(&good, 1, |e| e.count = 1 << 25)),
            BatchError::BadEntry { batch: 1 }
        ));
        assert!(matches!(
            refusal(with_entry(&good, 1, |e| e.first_point += 1)),
            BatchError::BatchStart { batch: 1, first, preceding }
                if first == BATCH_SIZE as u64 + 1 && preceding == BATCH_SIZE as u64
        ));
        assert!(matches!(
            refusal(with_section(&good, 1, 2, |s| s.offset = u64::MAX - 2)),
            BatchError::SectionOutside { batch: 1, section: 2 }
        ));
        assert!(matches!(
            refusal(with_section(&good, 0, 5, |s| s.offset = good.len() as u64 - 1)),
            BatchError::SectionOutside { batch: 0, section: 5 }
        ));
        assert!(matches!(
            refusal(with_section(&good, 0, SECTION_COLOR, |s| s.stored_len -= 4)),
            BatchError::SectionLen { batch: 0, section: SECTION_COLOR, len, expected }
                if expected == 4 * BATCH_SIZE as u64 && len == expected - 4
        ));
        assert!(matches!(
            refusal(with_section(&good, 0, 0, |s| s.offset += 2)),
            BatchError::SectionLen { batch: 0, section: 0, .. }
        ));
        // Metadata that lies about the records (a new one appended, the header pointed at it).
        assert!(BatchFile::from_bytes(&w.path, Bytes::Owned(with_meta(&good, |_| {}))).is_ok());
        let meta = |f: fn(&mut Meta)| refusal(with_meta(&good, f));
        assert!(matches!(
            meta(|m| {
                m.attributes.pop();
            }),
            BatchError::SectionCount
        ));
        assert!(matches!(
            meta(|m| m.attributes[0].offset = 4),
            BatchError::AttributeOutside { offset: 4, width: 2, record_len: 34, .. }
        ));
        assert!(matches!(
            meta(|m| m.attributes[7].offset = 30),
            BatchError::AttributeOutside { ref name, offset: 30, width: 6, record_len: 34 }
                if name == "rgb"
        ));
        assert!(matches!(
            meta(|m| m.attributes[7].width = usize::MAX),
            BatchError::AttributeOutside { .. }
        ));
        assert!(matches!(
            meta(|m| m.record_len = 70_000),
            BatchError::RecordTooLong { record_len: 70_000 }
        ));
        assert!(matches!(meta(|m| m.record_len = 20), BatchError::Layout { .. }));
        assert!(matches!(meta(|m| m.point_format = 42), BatchError::Layout { .. }));
        assert!(matches!(meta(|m| m.las_header.len = u64::MAX), BatchError::LasHeaderOutside));
        assert!(matches!(meta(|m| m.evlrs.offset = 1 << 50), BatchError::LasHeaderOutside));
        assert!(matches!(meta(|m| m.las_header.offset += 1), BatchError::BadLasHeader { .. }));
        assert!(matches!(meta(|m| m.evlrs.len -= 1), BatchError::BadEvlrs { .. }));
        // Sections said to be compressed that are not: opened, refused when read.
        let b = with_meta(&good, |m| m.compression = Compression::Zstd);
        let f = BatchFile::from_bytes(&w.path, Bytes::Owned(b)).unwrap();
        assert!(matches!(
            f.batch(0),
            Err(Error::Batch {
                error: BatchError::SectionCorrupt { batch: 0, section: 0, .. },
                ..
            })
        ));
        // A compressed section that holds another section's bytes: refused by its size.
        let z = write(&dir, Compression::Zstd, &AttributeSelection::All);
        let zb = std::fs::read(&z.path).unwrap();
        let f = BatchFile::from_bytes(&z.path, Bytes::Owned(zb.clone())).unwrap();
        assert!(f.batch(1).is_ok());
        // Section 6 is the classification: one byte a point, where the words have four.
        let zh = header_of(&zb);
        let at =
            (zh.table_offset + 96 * zh.batch_count) as usize + 16 * (zh.section_count as usize + 6);
        let class: SectionEntry = bytemuck::pod_read_unaligned(&zb[at..at + 16]);
        let swapped = with_section(&zb, 1, SECTION_MEDIUM, |s| *s = class);
        let f = BatchFile::from_bytes(&z.path, Bytes::Owned(swapped)).unwrap();
        let n = N - BATCH_SIZE;
        assert!(matches!(
            f.batch(1),
            Err(Error::Batch {
                error: BatchError::SectionSize { batch: 1, section: SECTION_MEDIUM, len, expected },
                ..
            }) if len == n && expected == 4 * n
        ));
        assert!(f.batch_sections(1, &[SECTION_COARSE]).is_ok(), "other sections still read");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
