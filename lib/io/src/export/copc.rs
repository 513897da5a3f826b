//! COPC 1.0 (<https://copc.io>): a LAZ 1.4 file of PDRF 6, 7 or 8 whose first VLR (at byte 375)
//! is the `copc` info record (the readers' cube, the root spacing, where the root hierarchy
//! page is, the GPS time range), with one variable-size LAZ chunk per node and the hierarchy
//! as an EVLR (`copc` 1000) of 32-byte entries in pages: the root page holds the nodes of the
//! first [`PAGE_LEVELS`] levels, and each node at a multiple of [`PAGE_LEVELS`] levels that has
//! nodes below gets its own page (its entry in the parent page has point count -1).
//!
//! The header's bounds are the octree's cube, not the points' box: copclib places a node of
//! level `l` at the header's minimum plus `index * span / 2^l`, `span` the header's largest
//! extent, while laspy, PDAL and copc.js use the info record's center and halfsize; with both
//! the same cube every reader finds each point inside its node (the points' own box is the
//! `position` range that `mortar info` prints).
//!
//! Layout: header, VLRs (`copc` info, `laszip encoded`, the dataset's VLRs: CRS, extra bytes
//! descriptions, ...), the offset of the chunk table, the chunks in the order of the nodes
//! (level by level), the chunk table, the hierarchy EVLR, the dataset's EVLRs. Written to a
//! temporary name and renamed.

use super::nodes::{Frame, NodeWriter, OutNode};
use super::options::ExportReport;
use crate::cleanup::TempPath;
use crate::dataset::Dataset;
use crate::error::{Error, Result};
use crate::las::{self, HeaderOut, Vlr};
use crate::sort::PieceStats;
use laz::laszip::{ChunkTable, ChunkTableEntry};
use laz::record::{LayeredPointRecordCompressor, RecordCompressor};
#[cfg(test)]
use laz::LazItemRecordBuilder;
use laz::{LazItem, LazVlr, LazVlrBuilder};
use mortar_core::octree::NodeKey;
use rayon::prelude::*;
use std::collections::HashMap;
use std::fs::File;
use std::io::{BufWriter, Cursor, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// Levels per hierarchy page.
pub const PAGE_LEVELS: u8 = 4;
/// Bytes of a hierarchy entry.
const ENTRY: usize = 32;
/// Bytes of the info VLR's data.
const INFO_LEN: usize = 160;
/// Bytes of an EVLR header.
const EVLR_HEADER: u64 = 60;

fn vlr(user: &str, id: u16, desc: &str, data: Vec<u8>) -> Vlr {
    let mut user_id = [0u8; 16];
    user_id[..user.len()].copy_from_slice(user.as_bytes());
    let mut description = [0u8; 32];
    description[..desc.len()].copy_from_slice(desc.as_bytes());
    Vlr { reserved: 0, user_id, record_id: id, description, data }
}

/// The info VLR's data.
fn info_data(f: &Frame, root_hier_offset: u64, root_hier_size: u64, gps: (f64, f64)) -> Vec<u8> {
    let mut b = Vec::with_capacity(INFO_LEN);
    for a in 0..3 {
        b.extend_from_slice(&(f.cube_min[a] + f.halfsize).to_le_bytes());
    }
    b.extend_from_slice(&f.halfsize.to_le_bytes());
    b.extend_from_slice(&f.spacing().to_le_bytes());
    b.extend_from_slice(&root_hier_offset.to_le_bytes());
    b.extend_from_slice(&root_hier_size.to_le_bytes());
    b.extend_from_slice(&gps.0.to_le_bytes());
    b.extend_from_slice(&gps.1.to_le_bytes());
    b.resize(INFO_LEN, 0);
    b
}

/// One LAZ chunk (layered, LAZ 1.4 items) of `records`.
pub(crate) fn encode_chunk(items: &Vec<LazItem>, records: &[u8]) -> std::io::Result<Vec<u8>> {
    let mut c =
        LayeredPointRecordCompressor::new(Cursor::new(Vec::with_capacity(records.len() / 4)));
    c.set_fields_from(items).map_err(std::io::Error::other)?;
    c.compress_many(records)?;
    c.done()?;
    Ok(c.into_inner().into_inner())
}

/// [`encode_chunk`] of a node's `points` records (`rl` bytes each) given in slices of `slice`
/// points by `records(range)`, and the range of their GPS times (PDRF 6-8: at byte 22): the same
/// bytes, with one slice of records in memory at a time.
pub(crate) fn encode_chunk_slices(
    path: &Path,
    items: &Vec<LazItem>,
    rl: usize,
    points: usize,
    slice: usize,
    records: &dyn Fn(std::ops::Range<usize>) -> Vec<u8>,
) -> Result<(Vec<u8>, (f64, f64))> {
    let io = |e: std::io::Error| Error::io(path, e);
    let mut c = LayeredPointRecordCompressor::new(Cursor::new(Vec::new()));
    c.set_fields_from(items).map_err(|e| io(std::io::Error::other(e)))?;
    let mut t = (f64::INFINITY, f64::NEG_INFINITY);
    for s in (0..points).step_by(slice.max(1)) {
        crate::cleanup::check_interrupted()?;
        let recs = records(s..(s + slice.max(1)).min(points));
        c.compress_many(&recs).map_err(io)?;
        for r in recs.chunks_exact(rl) {
            let g = f64::from_le_bytes(r[22..30].try_into().expect("8 bytes"));
            t = (t.0.min(g), t.1.max(g));
        }
    }
    c.done().map_err(io)?;
    Ok((c.into_inner().into_inner(), t))
}

/// Where a node's chunk is.
#[derive(Clone, Copy, Debug, Default)]
struct Placed {
    offset: u64,
    bytes: u64,
    points: u64,
}

/// The hierarchy pages: `(page root, entries)` in file order, the root page first. A page holds
/// the entries of its root and of the nodes below it down to the next page level; a node at a
/// page level with nodes below has its own page.
fn pages(nodes: &[OutNode]) -> Vec<(NodeKey, Vec<usize>)> {
    let at: HashMap<NodeKey, usize> = nodes.iter().enumerate().map(|(i, n)| (n.key, i)).collect();
    let mut out: Vec<(NodeKey, Vec<usize>)> = Vec::new();
    let mut todo = vec![NodeKey::ROOT];
    while let Some(root) = todo.pop() {
        let mut entries = Vec::new();
        let mut stack = vec![root];
        while let Some(k) = stack.pop() {
            let i = at[&k];
            entries.push(i);
            let n = &nodes[i];
            let below_page = k != root && k.level % PAGE_LEVELS == 0;
            if below_page && n.children != 0 {
                // its own page; this entry is the pointer (entries list it once, as the pointer)
                todo.push(k);
                continue;
            }
            for o in (0..8).rev() {
                if n.children >> o & 1 == 1 {
                    stack.push(k.child(o));
                }
            }
        }
        out.push((root, entries));
    }
    out
}

/// The COPC file being written: nodes are appended as they come ([`NodeWriter`]), the
/// header, the chunk table and the hierarchy are written at the end.
pub(crate) struct CopcWriter<'a> {
    ds: &'a Dataset,
    frame: Frame,
    out: PathBuf,
    tmp: TempPath,
    w: BufWriter<File>,
    laz_vlr: LazVlr,
    items: Vec<LazItem>,
    header: las::Header,
    vlrs: Vec<Vlr>,
    header_len: u64,
    pos: u64,
    table: ChunkTable,
    placed: HashMap<NodeKey, Placed>,
    points: u64,
    gps: (f64, f64),
}

impl<'a> CopcWriter<'a> {
    /// Opens the temporary file and reserves the header; CRS notes go to `warnings`.
    pub(crate) fn create(
        ds: &'a Dataset,
        frame: Frame,
        out: &Path,
        warnings: &mut Vec<String>,
    ) -> Result<CopcWriter<'a>> {
        let rl = frame.out.record_len;
        let extra = (rl - mortar_core::layout::base_len(frame.out.format).unwrap_or(rl)) as u16;
        let laz_vlr: LazVlr = LazVlrBuilder::default()
            .with_point_format(frame.out.format, extra)
            .map_err(|error| Error::LazFormat { format: frame.out.format, error })?
            .with_variable_chunk_size()
            .build();
        let items = laz_vlr.items().clone();
        let mut laz_data = Vec::new();
        laz_vlr.write_to(&mut laz_data).map_err(|error| Error::LazSetup { error })?;
        // The CRS: WKT is what COPC readers want; GeoTIFF keys alone get the WKT of their EPSG code.
        let crs = crate::crs::CrsRecords::of(&ds.vlrs, &ds.evlrs);
        let mut wkt_vlr = None;
        if !crs.is_empty() && !crs.has_wkt() {
            let info = crs.describe();
            match info.epsg.and_then(|c| u16::try_from(c).ok()).and_then(crs_definitions::from_code) {
                Some(def) => {
                    let mut data = def.wkt.as_bytes().to_vec();
                    data.push(0);
                    wkt_vlr = Some(vlr("LASF_Projection", 2112, "OGC WKT (from the GeoTIFF keys)", data));
                    if info.vertical_epsg.is_some() {
                        warnings.push(format!(
                            "the CRS is GeoTIFF keys ({}); the WKT written for COPC readers is that of EPSG:{} alone (the vertical code is in the keys only)",
                            info.summary(),
                            def.code
                        ));
                    }
                }
                None => warnings.push(format!(
                    "the CRS is GeoTIFF keys only ({}) and mortar knows no WKT for it; COPC readers look for WKT (VLR LASF_Projection 2112), so most will show no CRS: give --assign-crs a LAS file with WKT",
                    info.summary()
                )),
            }
        }
        let mut header = ds.template.clone();
        header.version = (1, 4);
        header.extra_header.clear();
        header.global_encoding &= !0x6; // no waveform data
                                        // LAS 1.4 asks point formats 6-10 to set the WKT bit, and copclib refuses files without it.
        header.global_encoding |= 0x10;
        let mut vlrs = vec![
            vlr("copc", 1, "copc info", info_data(&frame, 0, 0, (0.0, 0.0))),
            vlr("laszip encoded", 22204, "mortar (laz-rs)", laz_data),
        ];
        vlrs.extend(ds.vlrs.iter().cloned());
        vlrs.extend(wkt_vlr);
        let tmp = TempPath::beside(out);
        let path = tmp.path().to_path_buf();
        let f = File::create(&path).map_err(|e| Error::io(&path, e))?;
        let mut me = CopcWriter {
            ds,
            frame,
            out: out.to_path_buf(),
            tmp,
            w: BufWriter::with_capacity(1 << 20, f),
            laz_vlr,
            items,
            header,
            vlrs,
            header_len: 0,
            pos: 0,
            table: ChunkTable::default(),
            placed: HashMap::new(),
            points: 0,
            gps: (f64::INFINITY, f64::NEG_INFINITY),
        };
        let hb = me.head(&[0; 15], 0, 0)?;
        debug_assert_eq!(&hb[377..381], b"copc");
        me.header_len = hb.len() as u64;
        me.w.write_all(&hb).map_err(|e| Error::io(&path, e))?;
        // The offset of the chunk table, known at the end.
        me.w.write_all(&0i64.to_le_bytes()).map_err(|e| Error::io(&path, e))?;
        me.pos = me.header_len + 8;
        Ok(me)
    }

    fn head(&self, by_return: &[u64; 15], evlr_start: u64, evlr_count: u32) -> Result<Vec<u8>> {
        let f = &self.frame;
        let g = &self.ds.grid;
        las::write_header(&HeaderOut {
            template: &self.header,
            point_format: f.out.format,
            compressed: true,
            record_len: f.out.record_len as u16,
            point_count: self.points,
            points_by_return: *by_return,
            scale: g.scale,
            offset: g.offset,
            // The octree's cube, not the points' box: copclib places nodes from the header's
            // minimum and its largest extent (module docs).
            min: f.cube_min,
            max: f.cube_min.map(|m| m + 2.0 * f.halfsize),
            vlrs: &self.vlrs,
            evlr_start,
            evlr_count,
        })
        .map_err(|error| Error::Las { path: self.out.clone(), error })
    }
}

impl NodeWriter for CopcWriter<'_> {
    fn write_nodes(&mut self, nodes: Vec<(NodeKey, Vec<u8>)>) -> Result<()> {
        crate::cleanup::check_interrupted()?;
        let rl = self.frame.out.record_len;
        let path = self.tmp.path().to_path_buf();
        let items = &self.items;
        let progress = &self.ds.progress;
        let chunks: Vec<(Vec<u8>, (f64, f64))> = nodes
            .par_iter()
            .map(|(_, recs)| {
                let c = encode_chunk(items, recs).map_err(|e| Error::io(&path, e))?;
                // PDRF 6-8 keep the GPS time at byte 22.
                let t = recs
                    .chunks_exact(rl)
                    .map(|r| f64::from_le_bytes(r[22..30].try_into().expect("8 bytes")))
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |a, t| (a.0.min(t), a.1.max(t)));
                progress.add((recs.len() / rl) as u64);
                Ok((c, t))
            })
            .collect::<Result<_>>()?;
        for ((key, recs), (c, t)) in nodes.iter().zip(chunks) {
            let n = (recs.len() / rl) as u64;
            if n == 0 {
                continue;
            }
            self.w.write_all(&c).map_err(|e| Error::io(&path, e))?;
            self.placed.insert(*key, Placed { offset: self.pos, bytes: c.len() as u64, points: n });
            self.table.push(ChunkTableEntry { point_count: n, byte_count: c.len() as u64 });
            self.pos += c.len() as u64;
            self.points += n;
            self.gps = (self.gps.0.min(t.0), self.gps.1.max(t.1));
        }
        Ok(())
    }

    fn write_node_slices(
        &mut self,
        key: NodeKey,
        points: usize,
        slice: usize,
        records: &(dyn Fn(std::ops::Range<usize>) -> Vec<u8> + Sync),
    ) -> Result<()> {
        crate::cleanup::check_interrupted()?;
        let rl = self.frame.out.record_len;
        let path = self.tmp.path().to_path_buf();
        let io = |e: std::io::Error| Error::io(&path, e);
        let progress = &self.ds.progress;
        let (chunk, t) = encode_chunk_slices(&path, &self.items, rl, points, slice, &|r| {
            let recs = records(r);
            progress.add((recs.len() / rl) as u64);
            recs
        })?;
        self.w.write_all(&chunk).map_err(io)?;
        let n = points as u64;
        self.placed.insert(key, Placed { offset: self.pos, bytes: chunk.len() as u64, points: n });
        self.table.push(ChunkTableEntry { point_count: n, byte_count: chunk.len() as u64 });
        self.pos += chunk.len() as u64;
        self.points += n;
        self.gps = (self.gps.0.min(t.0), self.gps.1.max(t.1));
        Ok(())
    }

    fn finish(
        mut self: Box<Self>,
        tree: &[OutNode],
        stats: &PieceStats,
        report: &mut ExportReport,
    ) -> Result<()> {
        let path = self.tmp.path().to_path_buf();
        let io = |e| Error::io(&path, e);
        let table_offset = self.pos;
        let mut tb = Vec::new();
        self.table.write_to(&mut tb, &self.laz_vlr).map_err(io)?;
        self.w.write_all(&tb).map_err(io)?;
        self.pos += tb.len() as u64;
        // The hierarchy EVLR: pages laid out in order, each page's offset known before any is written.
        let evlr_start = self.pos;
        let pages = pages(tree);
        let data_start = evlr_start + EVLR_HEADER;
        let mut page_at: HashMap<NodeKey, (u64, u64)> = HashMap::new();
        let mut at = data_start;
        for (root, entries) in &pages {
            let size = (entries.len() * ENTRY) as u64;
            page_at.insert(*root, (at, size));
            at += size;
        }
        let mut hier = Vec::with_capacity((at - data_start) as usize);
        for (root, entries) in &pages {
            for &i in entries {
                let k = tree[i].key;
                for v in [k.level as i32, k.index[0] as i32, k.index[1] as i32, k.index[2] as i32] {
                    hier.extend_from_slice(&v.to_le_bytes());
                }
                let (offset, bytes, count) = match page_at.get(&k) {
                    Some(&(o, sz)) if k != *root => (o, sz, -1i32),
                    _ => {
                        let p = self.placed.get(&k).copied().unwrap_or_default();
                        (p.offset, p.bytes, p.points as i32)
                    }
                };
                hier.extend_from_slice(&offset.to_le_bytes());
                hier.extend_from_slice(&(bytes as i32).to_le_bytes());
                hier.extend_from_slice(&count.to_le_bytes());
            }
        }
        let mut evlrs = vec![vlr("copc", 1000, "EPT hierarchy", hier)];
        evlrs.extend(self.ds.evlrs.iter().cloned());
        self.w.write_all(&las::write_evlrs(&evlrs)).map_err(io)?;
        // The header again, now that the hierarchy and the EVLRs are placed.
        let (root_at, root_size) = page_at[&NodeKey::ROOT];
        let gps = if self.points == 0 { (0.0, 0.0) } else { self.gps };
        self.vlrs[0].data = info_data(&self.frame, root_at, root_size, gps);
        let hb2 = self.head(&stats.by_return, evlr_start, evlrs.len() as u32)?;
        debug_assert_eq!(hb2.len() as u64, self.header_len);
        self.w.seek(SeekFrom::Start(0)).map_err(io)?;
        self.w.write_all(&hb2).map_err(io)?;
        self.w.write_all(&(table_offset as i64).to_le_bytes()).map_err(io)?;
        let CopcWriter { w, tmp, out, .. } = *self;
        let f = w.into_inner().map_err(|e| Error::io(&path, e.into_error()))?;
        report.points = self.points;
        report.bytes = f.metadata().map_err(io)?.len();
        drop(f);
        tmp.persist(&out).map_err(|e| Error::io(&out, e))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A chunk compressed slice by slice is the chunk compressed whole (PDRF 7, real-looking
    /// records), whatever the slice.
    #[test]
    fn chunk_in_slices_equals_whole_chunk() {
        let rl = 36;
        let items = LazItemRecordBuilder::default_for_point_format_id(7, 0).unwrap();
        let n = 3000;
        let mut recs = vec![0u8; n * rl];
        for (i, r) in recs.chunks_exact_mut(rl).enumerate() {
            r[0..4].copy_from_slice(&(i as i32 * 7).to_le_bytes());
            r[4..8].copy_from_slice(&(i as i32 % 91).to_le_bytes());
            r[8..12].copy_from_slice(&(1000 - i as i32 % 13).to_le_bytes());
            r[12] = (i % 200) as u8;
            r[14] = 0x11;
            r[22..30].copy_from_slice(&(i as f64 * 0.5).to_le_bytes());
            r[30] = (i % 256) as u8;
        }
        let whole = encode_chunk(&items, &recs).unwrap();
        for slice in [1, 7, 1000, 3000, 10_000] {
            let (got, t) = encode_chunk_slices(Path::new("t"), &items, rl, n, slice, &|r| {
                recs[r.start * rl..r.end * rl].to_vec()
            })
            .unwrap();
            assert!(got == whole, "slice {slice}");
            assert_eq!(t, (0.0, (n - 1) as f64 * 0.5));
        }
    }

    fn node(level: u8, index: [u32; 3], children: u8) -> OutNode {
        OutNode { key: NodeKey { level, index }, points: vec![0], children }
    }

    #[test]
    fn pages_split_every_page_levels() {
        // a chain root -> ... -> level 9, octant 0 each time
        let nodes: Vec<OutNode> =
            (0..10u8).map(|l| node(l, [0; 3], if l < 9 { 1 } else { 0 })).collect();
        let p = pages(&nodes);
        assert_eq!(p.len(), 3, "{p:?}");
        assert_eq!(p[0].0, NodeKey::ROOT);
        assert_eq!(p[0].1, vec![0, 1, 2, 3, 4], "levels 0-3 and the pointer to level 4");
        let rest: Vec<_> = p[1..].iter().map(|(k, e)| (k.level, e.clone())).collect();
        assert!(rest.contains(&(4, vec![4, 5, 6, 7, 8])));
        assert!(rest.contains(&(8, vec![8, 9])));
    }
}
