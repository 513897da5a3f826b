//! `mortar export`: the octree handed to other tools, as COPC 1.0 ([`copc`]) or Potree 2.0
//! ([`potree`]). ARCHITECTURE.md, "Exports".
//!
//! Both formats want what a store does not hold: every point exactly once, the inner nodes
//! holding real points. So the export makes its own assignment from the tree of paper 004:
//!
//! - the inputs are read once and sorted in memory as the sorted build engine does
//!   ([`crate::store`]'s `engine`), and [`build_sorted`] makes the tree (first-come voxels);
//! - going down level by level, an inner node keeps those of its voxel points that no ancestor
//!   kept (a point that is a voxel of a node is a voxel of each ancestor up to where a cell
//!   of an ancestor's grid holds an earlier point), and a leaf keeps the points of its cube that
//!   no ancestor kept. Nodes left with no point and nothing below are dropped.
//!
//! Where nodes are, in the readers' arithmetic: COPC and Potree readers place a node of level
//! `l` at `min + i * 2 * halfsize / 2^l` in world coordinates (doubles). The octree is built on
//! the integer grid, and the cube handed to readers is that cube moved down by half a unit on
//! every axis: every node boundary then lies half a unit between two integer coordinates, so
//! each point is inside its node's box, by at least half a grid step, however the reader
//! rounds (a point on a boundary would fall to either side by one ulp; files written so fail
//! copclib's bounds check). A half-open integer cell `[a, b)` is exactly the box
//! `[a - 0.5, b - 0.5]` for integer points, so the tree is unchanged.
//!
//! Inputs whose axes have different scales (for example 0.01 m horizontally and 0.001 m
//! vertically) are built on a stretched grid: each axis multiplied by its scale over the
//! smallest one (an integer, checked), so that the cube is a cube in world units; records keep
//! their own coordinates.
//!
//! Not done yet: inputs larger than `--memory` (the partitioned engine of `mortar build` is the
//! way: its units are subtrees) and reusing the octree of an existing store (a store given as
//! input is read as points, and the tree is made again).

pub mod copc;
pub mod potree;

use crate::dataset::Dataset;
use crate::error::{Error, Result};
use crate::sort::{self, PieceStats};
use crate::store::engine::{self as eng, Sorted};
use mortar_core::layout::{base_len, merge_layouts, read_xyz, write_xyz, Conversion, RecordLayout};
use mortar_core::octree::{build_sorted, BuilderConfig, Cube, NodeKey, SortedContent};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// The output format.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExportFormat {
    /// One COPC 1.0 file (`.copc.laz`).
    Copc,
    /// A Potree 2.0 directory (`metadata.json`, `hierarchy.bin`, `octree.bin`).
    Potree,
}

/// The order of the points inside a node.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PointOrder {
    /// Morton order (leaves) and the Morton order of the voxel cells (inner nodes).
    Morton,
    /// By GPS time (ties in Morton order); Morton order where the records have no GPS time.
    GpsTime,
}

/// What an export is asked to do.
#[derive(Clone, Debug)]
pub struct ExportOptions {
    pub format: ExportFormat,
    /// Memory budget in bytes; the input must fit it (see the module docs).
    pub memory: u64,
    /// Most points per leaf and the deepest level (the tree of `mortar build`).
    pub config: BuilderConfig,
    pub order: PointOrder,
}

/// What an export did.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ExportReport {
    pub format: &'static str,
    pub output: String,
    pub points: u64,
    /// Nodes written (with points or with nodes below).
    pub nodes: u64,
    /// Deepest level.
    pub depth: u32,
    /// Point data record format written (COPC) or of the records the attributes come from.
    pub point_format: u8,
    /// Bytes of the output (all files).
    pub bytes: u64,
    pub seconds: f64,
    pub read_seconds: f64,
    pub sort_seconds: f64,
    pub tree_seconds: f64,
    pub write_seconds: f64,
    pub warnings: Vec<String>,
}

/// Writes `ds` to `out` as `opts.format` says; `out` appears whole or not at all.
pub fn export(ds: &Dataset, out: &Path, opts: &ExportOptions) -> Result<ExportReport> {
    let t0 = Instant::now();
    let mut report = ExportReport { output: out.display().to_string(), ..ExportReport::default() };
    let prep = prepare(ds, opts, &mut report)?;
    let tw = Instant::now();
    match opts.format {
        ExportFormat::Copc => {
            report.format = "copc";
            copc::write(ds, &prep, out, &mut report)?
        }
        ExportFormat::Potree => {
            report.format = "potree";
            potree::write(ds, &prep, out, &mut report)?
        }
    }
    report.write_seconds = tw.elapsed().as_secs_f64();
    report.points = prep.nodes.iter().map(|n| n.points.len() as u64).sum();
    report.nodes = prep.nodes.len() as u64;
    report.depth = prep.nodes.iter().map(|n| n.key.level as u32).max().unwrap_or(0);
    report.point_format = prep.out.format;
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(report)
}

/// Integer coordinates on the grid the tree is built on: `t = (p - base) * m` per axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Stretch {
    pub base: [i64; 3],
    pub m: [i64; 3],
}

impl Stretch {
    pub(crate) fn is_identity(&self) -> bool {
        self.m == [1; 3] && self.base == [0; 3]
    }
    #[inline]
    fn apply(&self, p: [i32; 3]) -> [i32; 3] {
        [0, 1, 2].map(|a| ((p[a] as i64 - self.base[a]) * self.m[a]) as i32)
    }
    #[inline]
    pub(crate) fn inverse(&self, t: [i32; 3]) -> [i32; 3] {
        [0, 1, 2].map(|a| (t[a] as i64 / self.m[a] + self.base[a]) as i32)
    }
}

/// One node of the output: its key, and its points as indices into the sorted records.
#[derive(Clone, Debug)]
pub(crate) struct OutNode {
    pub key: NodeKey,
    pub points: Vec<u32>,
    /// Children that are written, as a mask of octants `x | y << 1 | z << 2`.
    pub children: u8,
}

/// Everything the writers need.
pub(crate) struct Prepared {
    pub sorted: Sorted,
    pub stretch: Stretch,
    /// From the dataset's records to the output's (COPC wants PDRF 6, 7 or 8).
    pub conv: Option<Conversion>,
    pub out: RecordLayout,
    /// The nodes written, level by level from the root, each level in Morton order.
    pub nodes: Vec<OutNode>,
    /// The readers' cube in world coordinates: its smallest corner and half its edge.
    pub cube_min: [f64; 3],
    pub halfsize: f64,
    /// The points' statistics (integer bounds on the dataset's grid, returns).
    pub stats: PieceStats,
    /// Smallest and largest GPS time, where the records have one.
    pub gps: Option<(f64, f64)>,
}

impl Prepared {
    /// The output record of sorted point `i`, into `dst` (`out.record_len` bytes).
    #[inline]
    pub(crate) fn record_into(&self, i: usize, dst: &mut [u8]) {
        let src = self.sorted.record(i);
        match &self.conv {
            Some(c) => c.apply(src, self.sorted.rl, dst),
            None => dst.copy_from_slice(src),
        }
        if !self.stretch.is_identity() {
            write_xyz(dst, self.stretch.inverse(read_xyz(src)));
        }
    }

    /// The output records of a node, in its order.
    pub(crate) fn node_records(&self, n: &OutNode) -> Vec<u8> {
        let rl = self.out.record_len;
        let mut b = vec![0u8; n.points.len() * rl];
        for (d, &i) in b.chunks_exact_mut(rl).zip(&n.points) {
            self.record_into(i as usize, d);
        }
        b
    }

    /// Spacing of the root's points: its edge over the 128 cells of its grid.
    pub(crate) fn spacing(&self) -> f64 {
        2.0 * self.halfsize / mortar_core::octree::GRID_SIZE as f64
    }
}

/// The record layout COPC holds for `layout` (PDRF 6, 7 or 8 with the same extra bytes) and
/// the conversion into it, or why there is none.
pub(crate) fn output_layout(layout: &RecordLayout) -> std::result::Result<(RecordLayout, Option<Conversion>), String> {
    match layout.format {
        6..=8 => Ok((layout.clone(), None)),
        4 | 5 | 9 | 10 => Err(format!(
            "point format {} carries waveforms; COPC holds point formats 6, 7 and 8 only (give the points without waveforms, e.g. `pdal translate` to format {})",
            layout.format,
            if layout.format == 10 { 8 } else if layout.format == 5 { 7 } else { 6 }
        )),
        f => {
            let extra = layout.record_len - base_len(f).unwrap_or(layout.record_len);
            let six = RecordLayout::new(6, 30 + extra).map_err(|e| e.to_string())?;
            let (target, convs) = merge_layouts(&[layout.clone(), six])?;
            Ok((target, convs.into_iter().next().flatten()))
        }
    }
}

/// The per-axis factors that make the grid's cells cubes in world units, or why there are none.
fn stretch_factors(scale: [f64; 3]) -> std::result::Result<[i64; 3], String> {
    if !scale.iter().all(|s| s.is_finite() && *s > 0.0) {
        return Err(format!("the scales {scale:?} are not all positive; the export needs positive scales (a reader's octree grows with the world coordinates)"));
    }
    let smin = scale.iter().cloned().fold(f64::INFINITY, f64::min);
    let mut m = [1i64; 3];
    for a in 0..3 {
        let r = scale[a] / smin;
        let k = r.round();
        if (r - k).abs() > 1e-6 * k || k > (1u64 << 20) as f64 {
            return Err(format!(
                "the scales {scale:?} are not whole multiples of one another, so no octree cube has whole cells on every axis (re-scale the input, e.g. with `las2las -rescale`)"
            ));
        }
        m[a] = k as i64;
    }
    Ok(m)
}

/// Reads, sorts and builds the tree, and assigns every point to one node.
pub(crate) fn prepare(ds: &Dataset, opts: &ExportOptions, report: &mut ExportReport) -> Result<Prepared> {
    let t0 = Instant::now();
    let rl = ds.layout.record_len;
    let (out, conv) = output_layout(&ds.layout).map_err(|e| Error::input(ds.inputs[0].path(), e))?;
    let m = stretch_factors(ds.grid.scale).map_err(|e| Error::input(ds.inputs[0].path(), e))?;
    let need = eng::in_memory_need(ds);
    if need > opts.memory {
        return Err(Error::Usage(format!(
            "the export holds the input in memory: {} points need about {} MiB, above --memory ({} MiB); give more memory (exports larger than memory are not done yet)",
            ds.declared_points(),
            need >> 20,
            opts.memory >> 20
        )));
    }
    if ds.declared_points() >= u32::MAX as u64 {
        return Err(Error::Usage("too many points for one in-memory export (at most 4,294,967,294)".into()));
    }
    let total = ds.declared_points();
    ds.progress.stage("reading", total, "points");
    let mut header_warnings = Vec::new();
    let header = crate::store::header_bounds_of(ds, &mut header_warnings);
    let promised = header.map(|(l, h)| Cube::covering(l, h)).unwrap_or(Cube { min: [0; 3], size_log2: 32 });
    let (slabs, mut hist) = eng::read_pieces(ds, promised)?;
    let mut all = PieceStats::default();
    for (_, st) in &slabs {
        all.merge(st);
    }
    if all.count == 0 {
        return Err(Error::input(ds.inputs[0].path(), "no points to export"));
    }
    report.read_seconds = t0.elapsed().as_secs_f64();
    let (lo, hi) = (all.min, all.max);
    let stretch = if m == [1; 3] { Stretch { base: [0; 3], m } } else { Stretch { base: lo.map(|v| v as i64), m } };
    // The stretched copy (rare: axes with different scales).
    let stretched: Vec<Vec<u8>> = if stretch.is_identity() {
        Vec::new()
    } else {
        for a in 0..3 {
            if (hi[a] as i64 - lo[a] as i64) * m[a] >= i32::MAX as i64 {
                return Err(Error::input(ds.inputs[0].path(), format!(
                    "its axes' scales {:?} differ, and its extent on axis {a} on the finest of them does not fit the octree's grid (2^31 units); re-scale it to one scale on all axes (e.g. `las2las -rescale`)",
                    ds.grid.scale
                )));
            }
        }
        slabs
            .par_iter()
            .map(|(s, _)| {
                let mut v = s.to_vec();
                for r in v.chunks_exact_mut(rl) {
                    let t = stretch.apply(read_xyz(r));
                    write_xyz(r, t);
                }
                v
            })
            .collect()
    };
    let records: Vec<&[u8]> = if stretch.is_identity() { slabs.iter().map(|(r, _)| &**r).collect() } else { stretched.iter().map(|v| &v[..]).collect() };
    let (tlo, thi) = if stretch.is_identity() { (lo, hi) } else { ([0; 3], [0, 1, 2].map(|a| ((hi[a] as i64 - lo[a] as i64) * m[a]) as i32)) };
    let root = match header {
        Some((l, h)) if stretch.is_identity() && (0..3).all(|a| l[a] <= lo[a] && hi[a] <= h[a]) => Cube::covering(l, h),
        _ => Cube::covering(tlo, thi),
    };
    let g = eng::grid_of(root);
    let shift = eng::bucket_shift(root);
    if root != promised || !stretch.is_identity() {
        hist = records.par_iter().map(|s| eng::histogram(s, rl, &g, shift)).collect();
    }
    let ts = Instant::now();
    ds.progress.stage("sorting", 2 * all.count, "points");
    let sorted = eng::sort_records(&records, &hist, rl, &g, shift, &ds.progress, |p, i| (p as u64) << 32 | i as u64);
    drop(records);
    drop(stretched);
    drop(slabs);
    report.sort_seconds = ts.elapsed().as_secs_f64();
    sort::check_interrupted()?;
    let tt = Instant::now();
    ds.progress.stage("indexing", 0, "");
    let n = sorted.arrival.len();
    let pos = |i: usize| read_xyz(sorted.record(i));
    let arrival = |i: usize| sorted.arrival[i];
    let tree = build_sorted(root, n, &pos, &arrival, opts.config).map_err(|e| Error::Usage(format!("octree: {e}")))?;
    let nodes = assign(&tree, n, &sorted, &ds.layout, opts.order);
    report.tree_seconds = tt.elapsed().as_secs_f64();
    // The readers' cube in world units.
    let smin = ds.grid.scale.iter().cloned().fold(f64::INFINITY, f64::min);
    let origin = [0, 1, 2].map(|a| ds.grid.offset[a] + ds.grid.scale[a] * stretch.base[a] as f64);
    let cube_min = [0, 1, 2].map(|a| origin[a] + smin * (root.min[a] as f64 - 0.5));
    let halfsize = smin * root.size() as f64 / 2.0;
    let gps = ds.layout.attribute("gps_time").map(|a| {
        let o = a.offset;
        (0..n)
            .into_par_iter()
            .map(|i| {
                let t = f64::from_le_bytes(sorted.record(i)[o..o + 8].try_into().unwrap());
                (t, t)
            })
            .reduce(|| (f64::INFINITY, f64::NEG_INFINITY), |a, b| (a.0.min(b.0), a.1.max(b.1)))
    });
    report.warnings.extend(header_warnings);
    Ok(Prepared { sorted, stretch, conv, out, nodes, cube_min, halfsize, stats: all, gps })
}

/// Every point to one node (module docs), empty subtrees dropped, children masks set.
fn assign(tree: &mortar_core::octree::SortedTree, n: usize, sorted: &Sorted, layout: &RecordLayout, order: PointOrder) -> Vec<OutNode> {
    let taken: Vec<AtomicU64> = (0..n.div_ceil(64)).map(|_| AtomicU64::new(0)).collect();
    let gps = layout.attribute("gps_time").map(|a| a.offset);
    let mut nodes: Vec<OutNode> = Vec::with_capacity(tree.nodes.len());
    for level in tree.levels() {
        let mut here: Vec<OutNode> = tree.nodes[level]
            .par_iter()
            .map(|node| {
                let mut points: Vec<u32> = match &node.content {
                    SortedContent::Inner(v) => v
                        .iter()
                        .copied()
                        .filter(|&i| {
                            let bit = 1u64 << (i % 64);
                            taken[i as usize / 64].fetch_or(bit, Ordering::Relaxed) & bit == 0
                        })
                        .collect(),
                    SortedContent::Leaf(r) => r.clone().filter(|&i| taken[i / 64].load(Ordering::Relaxed) & (1u64 << (i % 64)) == 0).map(|i| i as u32).collect(),
                };
                if let (PointOrder::GpsTime, Some(o)) = (order, gps) {
                    let t = |i: u32| f64::from_le_bytes(sorted.record(i as usize)[o..o + 8].try_into().unwrap());
                    points.sort_by(|a, b| t(*a).total_cmp(&t(*b)));
                }
                OutNode { key: node.key, points, children: 0 }
            })
            .collect();
        nodes.append(&mut here);
    }
    // Bottom-up: a node is kept when it has points or a kept child.
    let at: HashMap<NodeKey, usize> = nodes.iter().enumerate().map(|(i, n)| (n.key, i)).collect();
    let mut keep: Vec<bool> = nodes.iter().map(|n| !n.points.is_empty()).collect();
    for i in (0..nodes.len()).rev() {
        if keep[i] {
            if let Some(p) = nodes[i].key.parent() {
                let pi = at[&p];
                keep[pi] = true;
                nodes[pi].children |= 1 << nodes[i].key.octant();
            }
        }
    }
    nodes.into_iter().zip(keep).filter(|(_, k)| *k).map(|(n, _)| n).collect()
}

/// Groups of consecutive nodes of about `bytes` output bytes each (at least one node), so that
/// the writers encode a group in parallel and hold one group at a time.
pub(crate) fn groups(nodes: &[OutNode], record_len: usize, bytes: u64) -> Vec<std::ops::Range<usize>> {
    let mut out = Vec::new();
    let mut start = 0;
    while start < nodes.len() {
        let mut end = start;
        let mut b = 0u64;
        while end < nodes.len() && (end == start || b < bytes) {
            b += (nodes[end].points.len() * record_len) as u64;
            end += 1;
        }
        out.push(start..end);
        start = end;
    }
    out
}

/// Bytes of output records encoded per group.
pub(crate) const GROUP_BYTES: u64 = 64 << 20;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stretch_factors_of_common_scales() {
        assert_eq!(stretch_factors([0.01, 0.01, 0.01]), Ok([1, 1, 1]));
        assert_eq!(stretch_factors([0.01, 0.01, 0.001]), Ok([10, 10, 1]));
        assert_eq!(stretch_factors([1e-7, 1e-7, 0.01]), Ok([1, 1, 100_000]));
        assert!(stretch_factors([0.01, 0.01, 0.003]).is_err());
        assert!(stretch_factors([0.01, -0.01, 0.01]).is_err());
        let s = Stretch { base: [5, -3, 100], m: [10, 10, 1] };
        for p in [[5, -3, 100], [1000, 2000, -7], [i32::MAX / 20, 0, 0]] {
            assert_eq!(s.inverse(s.apply(p)), p);
        }
    }

    #[test]
    fn copc_layouts() {
        let (l, c) = output_layout(&RecordLayout::new(3, 34 + 2).unwrap()).unwrap();
        assert_eq!((l.format, l.record_len), (7, 36 + 2));
        assert!(c.unwrap().legacy_to_extended);
        let (l, c) = output_layout(&RecordLayout::new(0, 20).unwrap()).unwrap();
        assert_eq!((l.format, l.record_len), (6, 30));
        assert!(c.is_some());
        let (l, c) = output_layout(&RecordLayout::new(8, 38).unwrap()).unwrap();
        assert_eq!(l.format, 8);
        assert!(c.is_none());
        assert!(output_layout(&RecordLayout::new(9, 59).unwrap()).is_err());
        assert!(output_layout(&RecordLayout::new(4, 57).unwrap()).is_err());
    }
}
