//! Potree 2.0 (the format of PotreeConverter 2 and the Potree viewer): a directory of
//!
//! - `metadata.json`: version "2.0", the point count, the octree's cube (`boundingBox`), the
//!   root spacing, the integer grid (`scale`, `offset`: the LAS ones, so positions are the
//!   records' own integers), the hierarchy's first chunk size, step and depth, the encoding
//!   (`DEFAULT`) and the attributes, each with its type, size and min/max;
//! - `octree.bin`: each node's points, one after the other, each point its attributes in the
//!   order of `metadata.json` (DEFAULT encoding);
//! - `hierarchy.bin`: 22-byte node records (type 0 inner, 1 leaf, 2 proxy; child mask with
//!   child `x << 2 | y << 1 | z`; point count; byte offset and size in `octree.bin`) in chunks:
//!   a chunk is a node and its subtree, breadth first, down to [`STEP`] levels below it, where
//!   nodes with children are proxies pointing at their own chunk (whose first record is that
//!   node again, with its data). The root's chunk comes first.
//!
//! The attributes are those of the LAS 1.4 record the points have (PDRF 6, 7 or 8; legacy
//! records converted as for COPC), every bit kept: position, intensity, return number, number
//! of returns, classification flags, scanner channel, scan direction flag, edge of flight line,
//! classification, user data, scan angle, point source id, gps-time, rgb, nir, and the extra
//! bytes as one `uint8` array. Written into a temporary directory and renamed.

use super::nodes::{Frame, NodeWriter, OutNode};
use super::options::ExportReport;
use crate::cleanup::TempPath;
use crate::dataset::Dataset;
use crate::error::{Error, Result};
use crate::sort::PieceStats;
use mortar_core::octree::NodeKey;
use rayon::prelude::*;
use serde_json::json;
use std::collections::HashMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Levels per hierarchy chunk (PotreeConverter's step).
pub const STEP: u8 = 4;
/// Bytes of a hierarchy record.
const RECORD: usize = 22;

/// How an attribute comes out of a LAS 1.4 record.
#[derive(Clone, Debug)]
struct Attr {
    name: &'static str,
    ty: &'static str,
    elem: usize,
    num: usize,
    /// Byte offset in the record.
    at: usize,
    /// For bit fields of one byte: (shift, mask).
    bits: Option<(u8, u8)>,
    /// Whether a 2-byte value is signed.
    signed: bool,
}

fn attributes(format: u8, record_len: usize) -> Vec<Attr> {
    let a = |name, ty: &'static str, elem, num, at| Attr {
        name,
        ty,
        elem,
        num,
        at,
        bits: None,
        signed: ty == "int16",
    };
    let b = |name, at, shift, mask| Attr {
        name,
        ty: "uint8",
        elem: 1,
        num: 1,
        at,
        bits: Some((shift, mask)),
        signed: false,
    };
    let mut v = vec![
        a("position", "int32", 4, 3, 0),
        a("intensity", "uint16", 2, 1, 12),
        b("return number", 14, 0, 0x0f),
        b("number of returns", 14, 4, 0x0f),
        b("classification flags", 15, 0, 0x0f),
        b("scanner channel", 15, 4, 0x03),
        b("scan direction flag", 15, 6, 0x01),
        b("edge of flight line", 15, 7, 0x01),
        a("classification", "uint8", 1, 1, 16),
        a("user data", "uint8", 1, 1, 17),
        a("scan angle", "int16", 2, 1, 18),
        a("point source id", "uint16", 2, 1, 20),
        a("gps-time", "double", 8, 1, 22),
    ];
    if matches!(format, 7 | 8) {
        v.push(a("rgb", "uint16", 2, 3, 30));
    }
    if format == 8 {
        v.push(a("nir", "uint16", 2, 1, 36));
    }
    let base = mortar_core::layout::base_len(format).unwrap_or(record_len);
    if record_len > base {
        v.push(a("extra bytes", "uint8", 1, record_len - base, base));
    }
    v
}

/// The value of element `e` of `attr` in `rec`, for the min/max.
#[inline]
fn value(attr: &Attr, rec: &[u8], e: usize) -> f64 {
    let o = attr.at + e * attr.elem;
    if let Some((s, m)) = attr.bits {
        return ((rec[o] >> s) & m) as f64;
    }
    match (attr.elem, attr.signed) {
        (4, _) => i32::from_le_bytes(rec[o..o + 4].try_into().unwrap()) as f64,
        (2, false) => u16::from_le_bytes([rec[o], rec[o + 1]]) as f64,
        (2, true) => i16::from_le_bytes([rec[o], rec[o + 1]]) as f64,
        (8, _) => f64::from_le_bytes(rec[o..o + 8].try_into().unwrap()),
        _ => rec[o] as f64,
    }
}

/// Potree's child index of our octant (`x | y << 1 | z << 2`): `x << 2 | y << 1 | z`.
fn potree_child(octant: usize) -> usize {
    ((octant & 1) << 2) | (octant & 2) | ((octant >> 2) & 1)
}

/// Our octant of Potree's child index.
fn our_octant(child: usize) -> usize {
    potree_child(child) // the map swaps bits 0 and 2: it is its own inverse
}

/// The hierarchy chunks: `(chunk root, nodes breadth first)`, the root's chunk first.
fn chunks(nodes: &[OutNode]) -> Vec<(NodeKey, Vec<usize>)> {
    let at: HashMap<NodeKey, usize> = nodes.iter().enumerate().map(|(i, n)| (n.key, i)).collect();
    let mut out = Vec::new();
    let mut todo = std::collections::VecDeque::from([NodeKey::ROOT]);
    while let Some(root) = todo.pop_front() {
        let mut list = Vec::new();
        let mut queue = std::collections::VecDeque::from([root]);
        while let Some(k) = queue.pop_front() {
            let i = at[&k];
            list.push(i);
            let n = &nodes[i];
            if k != root && k.level - root.level == STEP && n.children != 0 {
                todo.push_back(k);
                continue;
            }
            for c in 0..8 {
                let o = our_octant(c);
                if n.children >> o & 1 == 1 {
                    queue.push_back(k.child(o));
                }
            }
        }
        out.push((root, list));
    }
    out
}

/// The Potree directory being written: `octree.bin` grows as nodes come ([`NodeWriter`]);
/// `hierarchy.bin` and `metadata.json` are written at the end.
pub(crate) struct PotreeWriter<'a> {
    ds: &'a Dataset,
    frame: Frame,
    out: PathBuf,
    tmp: TempPath,
    octree_path: PathBuf,
    w: BufWriter<File>,
    attrs: Vec<Attr>,
    nvals: usize,
    lo: Vec<f64>,
    hi: Vec<f64>,
    placed: HashMap<NodeKey, (u64, u64, u32)>,
    pos: u64,
    points: u64,
}

/// The DEFAULT encoding of output records `recs` (`rl` bytes each): the attributes of each
/// point in turn, and each value's range.
fn encode_records(
    attrs: &[Attr],
    nvals: usize,
    recs: &[u8],
    rl: usize,
) -> (Vec<u8>, Vec<f64>, Vec<f64>) {
    let bpp: usize = attrs.iter().map(|a| a.elem * a.num).sum();
    let mut b = Vec::with_capacity(recs.len() / rl * bpp);
    let mut l = vec![f64::INFINITY; nvals];
    let mut h = vec![f64::NEG_INFINITY; nvals];
    for r in recs.chunks_exact(rl) {
        let mut v = 0;
        for a in attrs {
            match a.bits {
                Some((s, m)) => b.push((r[a.at] >> s) & m),
                None => b.extend_from_slice(&r[a.at..a.at + a.elem * a.num]),
            }
            for e in 0..a.num {
                let x = value(a, r, e);
                l[v] = l[v].min(x);
                h[v] = h[v].max(x);
                v += 1;
            }
        }
    }
    (b, l, h)
}

impl<'a> PotreeWriter<'a> {
    /// Makes the temporary directory and opens `octree.bin` in it.
    pub(crate) fn create(ds: &'a Dataset, frame: Frame, out: &Path) -> Result<PotreeWriter<'a>> {
        let attrs = attributes(frame.out.format, frame.out.record_len);
        let nvals: usize = attrs.iter().map(|a| a.num).sum();
        let tmp = TempPath::beside(out);
        let dir = tmp.path().to_path_buf();
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let octree_path = dir.join("octree.bin");
        let w = BufWriter::with_capacity(
            1 << 20,
            File::create(&octree_path).map_err(|e| Error::io(&octree_path, e))?,
        );
        Ok(PotreeWriter {
            ds,
            frame,
            out: out.to_path_buf(),
            tmp,
            octree_path,
            w,
            attrs,
            nvals,
            lo: vec![f64::INFINITY; nvals],
            hi: vec![f64::NEG_INFINITY; nvals],
            placed: HashMap::new(),
            pos: 0,
            points: 0,
        })
    }
}

impl NodeWriter for PotreeWriter<'_> {
    fn write_nodes(&mut self, nodes: Vec<(NodeKey, Vec<u8>)>) -> Result<()> {
        crate::cleanup::check_interrupted()?;
        let rl = self.frame.out.record_len;
        let (attrs, nvals, progress) = (&self.attrs, self.nvals, &self.ds.progress);
        let enc: Vec<(Vec<u8>, Vec<f64>, Vec<f64>)> = nodes
            .par_iter()
            .map(|(_, recs)| {
                progress.add((recs.len() / rl) as u64);
                encode_records(attrs, nvals, recs, rl)
            })
            .collect();
        for ((key, recs), (b, l, h)) in nodes.iter().zip(enc) {
            self.w.write_all(&b).map_err(|e| Error::io(&self.octree_path, e))?;
            let n = (recs.len() / rl) as u32;
            self.placed.insert(*key, (self.pos, b.len() as u64, n));
            self.pos += b.len() as u64;
            self.points += n as u64;
            for v in 0..nvals {
                self.lo[v] = self.lo[v].min(l[v]);
                self.hi[v] = self.hi[v].max(h[v]);
            }
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
        let rl = self.frame.out.record_len;
        let at = self.pos;
        for s in (0..points).step_by(slice) {
            crate::cleanup::check_interrupted()?;
            let recs = records(s..(s + slice).min(points));
            let (b, l, h) = encode_records(&self.attrs, self.nvals, &recs, rl);
            self.w.write_all(&b).map_err(|e| Error::io(&self.octree_path, e))?;
            self.pos += b.len() as u64;
            for v in 0..self.nvals {
                self.lo[v] = self.lo[v].min(l[v]);
                self.hi[v] = self.hi[v].max(h[v]);
            }
            self.ds.progress.add((recs.len() / rl) as u64);
        }
        self.placed.insert(key, (at, self.pos - at, points as u32));
        self.points += points as u64;
        Ok(())
    }

    fn finish(
        self: Box<Self>,
        tree: &[OutNode],
        stats: &PieceStats,
        report: &mut ExportReport,
    ) -> Result<()> {
        let PotreeWriter {
            ds,
            frame,
            out,
            tmp,
            octree_path,
            w,
            attrs,
            lo,
            hi,
            placed,
            pos,
            points,
            ..
        } = *self;
        let dir = tmp.path().to_path_buf();
        let f = w.into_inner().map_err(|e| Error::io(&octree_path, e.into_error()))?;
        drop(f);
        // hierarchy.bin
        let chunks = chunks(tree);
        let mut chunk_at: HashMap<NodeKey, (u64, u64)> = HashMap::new();
        let mut at = 0u64;
        for (root, list) in &chunks {
            let size = (list.len() * RECORD) as u64;
            chunk_at.insert(*root, (at, size));
            at += size;
        }
        let mut hier = Vec::with_capacity(at as usize);
        for (root, list) in &chunks {
            for &i in list {
                let n = &tree[i];
                let mut mask = 0u8;
                for o in 0..8 {
                    if n.children >> o & 1 == 1 {
                        mask |= 1 << potree_child(o);
                    }
                }
                let (offset, size, count) = placed.get(&n.key).copied().unwrap_or_default();
                let (ty, offset, size) = match chunk_at.get(&n.key) {
                    Some(&(o, s)) if n.key != *root => (2u8, o, s),
                    _ => (if n.children == 0 { 1u8 } else { 0u8 }, offset, size),
                };
                hier.push(ty);
                hier.push(mask);
                hier.extend_from_slice(&count.to_le_bytes());
                hier.extend_from_slice(&offset.to_le_bytes());
                hier.extend_from_slice(&size.to_le_bytes());
            }
        }
        let hp = dir.join("hierarchy.bin");
        std::fs::write(&hp, &hier).map_err(|e| Error::io(&hp, e))?;
        // metadata.json
        let g = &ds.grid;
        let s = stats;
        let world = |a: usize, v: i32| g.offset[a] + g.scale[a] * v as f64;
        let mut v = 0;
        let attributes: Vec<serde_json::Value> = attrs
            .iter()
            .map(|a| {
                let (mn, mx): (Vec<f64>, Vec<f64>) = if a.name == "position" {
                    (
                        (0..3).map(|k| world(k, s.min[k])).collect(),
                        (0..3).map(|k| world(k, s.max[k])).collect(),
                    )
                } else {
                    (lo[v..v + a.num].to_vec(), hi[v..v + a.num].to_vec())
                };
                v += a.num;
                json!({
                    "name": a.name, "description": "", "size": a.elem * a.num, "numElements": a.num,
                    "elementSize": a.elem, "type": a.ty, "min": mn, "max": mx,
                    "scale": vec![1.0; a.num], "offset": vec![0.0; a.num],
                })
            })
            .collect();
        let cube_max: Vec<f64> = frame.cube_min.iter().map(|m| m + 2.0 * frame.halfsize).collect();
        let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let meta = json!({
            "version": "2.0",
            "name": name,
            "description": "written by mortar export",
            "points": points,
            "projection": "",
            "hierarchy": {"firstChunkSize": chunk_at[&NodeKey::ROOT].1, "stepSize": STEP, "depth": tree.iter().map(|n| n.key.level).max().unwrap_or(0)},
            "offset": g.offset,
            "scale": g.scale,
            "spacing": frame.spacing(),
            "boundingBox": {"min": frame.cube_min, "max": cube_max},
            "encoding": "DEFAULT",
            "attributes": attributes,
        });
        let mp = dir.join("metadata.json");
        let text = serde_json::to_vec_pretty(&meta)
            .map_err(|error| Error::JsonFile { path: mp.clone(), error })?;
        std::fs::write(&mp, text).map_err(|e| Error::io(&mp, e))?;
        report.points = points;
        report.bytes =
            pos + hier.len() as u64 + std::fs::metadata(&mp).map(|m| m.len()).unwrap_or(0);
        if out.is_dir() {
            // an empty directory given as the output (checked before the export began)
            std::fs::remove_dir(&out).map_err(|e| Error::io(&out, e))?;
        }
        tmp.persist(&out).map_err(|e| Error::io(&out, e))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn child_index_swaps_x_and_z() {
        assert_eq!(potree_child(0b001), 0b100, "x");
        assert_eq!(potree_child(0b010), 0b010, "y");
        assert_eq!(potree_child(0b100), 0b001, "z");
        for o in 0..8 {
            assert_eq!(our_octant(potree_child(o)), o);
        }
    }

    #[test]
    fn attributes_cover_the_record() {
        for (f, len) in [(6u8, 30usize), (7, 36), (8, 38), (7, 40)] {
            let a = attributes(f, len);
            let bytes: usize = a.iter().filter(|a| a.bits.is_none()).map(|a| a.elem * a.num).sum();
            // every byte but 14 and 15 (bit fields) copied once
            assert_eq!(bytes + 2, len, "format {f}");
        }
    }
}
