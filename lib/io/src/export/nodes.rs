//! What both export paths and both formats share: the frame the readers see, the writer's
//! interface ([`NodeWriter`]), the stretched grid, the output records and layout, the assignment
//! of points to nodes (inner nodes keep the voxel points no ancestor kept, leaves the rest) and
//! the writing of nodes in groups under the memory budget.

use super::options::{ExportOptions, ExportReport, PointOrder};
use crate::dataset::Dataset;
use crate::error::{Error, ExportError, Result};
use crate::sort::PieceStats;
use crate::store::engine::{self as eng, Sorted};
use mortar_core::layout::{base_len, merge_layouts, read_xyz, write_xyz, Conversion, RecordLayout};
use mortar_core::octree::{build_sorted, Cube, NodeKey, SortedContent, SortedNode};
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// What a writer knows before the first node: the records it writes and the readers' cube.
#[derive(Clone, Debug)]
pub(crate) struct Frame {
    pub out: RecordLayout,
    /// The readers' cube in world coordinates: its smallest corner and half its edge.
    pub cube_min: [f64; 3],
    pub halfsize: f64,
}

impl Frame {
    /// Spacing of the root's points: its edge over the 128 cells of its grid.
    pub(crate) fn spacing(&self) -> f64 {
        2.0 * self.halfsize / mortar_core::octree::GRID_SIZE as f64
    }

    /// The frame of the tree over `root` (on the grid of `stretch`) for the records `out`.
    pub(crate) fn of(ds: &Dataset, out: RecordLayout, stretch: &Stretch, root: Cube) -> Frame {
        let smin = ds.grid.scale.iter().cloned().fold(f64::INFINITY, f64::min);
        let origin =
            [0, 1, 2].map(|a| ds.grid.offset[a] + ds.grid.scale[a] * stretch.base[a] as f64);
        let cube_min = [0, 1, 2].map(|a| origin[a] + smin * (root.min[a] as f64 - 0.5));
        Frame { out, cube_min, halfsize: smin * root.size() as f64 / 2.0 }
    }
}

/// The output being written, node by node.
pub(crate) trait NodeWriter {
    /// Encodes `nodes` (each its key and its output records, in order; none empty) in
    /// parallel and appends them in order.
    fn write_nodes(&mut self, nodes: Vec<(NodeKey, Vec<u8>)>) -> Result<()>;
    /// Appends one node of `points` points (not none) whose output records come in slices,
    /// `records(range)` giving those of the points `range`: a node larger than a group (points
    /// at one position, beyond the depth limit) is encoded without all its records in memory.
    /// The bytes written are those [`write_nodes`](Self::write_nodes) writes for the node.
    fn write_node_slices(
        &mut self,
        key: NodeKey,
        points: usize,
        slice: usize,
        records: &(dyn Fn(std::ops::Range<usize>) -> Vec<u8> + Sync),
    ) -> Result<()>;
    /// Writes the hierarchy of `tree` (every node that holds points or has such nodes below,
    /// with its children mask; its points are not looked at) and the metadata, and moves the
    /// output into place; sets `report.points` and `report.bytes`.
    fn finish(
        self: Box<Self>,
        tree: &[OutNode],
        stats: &PieceStats,
        report: &mut ExportReport,
    ) -> Result<()>;
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

impl OutNode {
    /// The node without its points (what the hierarchy needs).
    pub(crate) fn shape(&self) -> OutNode {
        OutNode { key: self.key, points: Vec::new(), children: self.children }
    }
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
    pub frame: Frame,
    /// The points' statistics (integer bounds on the dataset's grid, returns).
    pub stats: PieceStats,
}

impl Prepared {
    /// The output records of the points `range` of a node, in its order.
    pub(crate) fn node_records(&self, n: &OutNode, range: std::ops::Range<usize>) -> Vec<u8> {
        let pts = &n.points[range];
        output_records(
            pts.iter().map(|&i| self.sorted.record(i as usize)),
            pts.len(),
            self.sorted.rl,
            self.out.record_len,
            &self.conv,
            &self.stretch,
        )
    }
}

/// The output records of the input records `src` (`n` of them, `rl` bytes each): converted
/// to the output's format, positions back on the dataset's grid.
pub(crate) fn output_records<'r>(
    src: impl Iterator<Item = &'r [u8]>,
    n: usize,
    rl: usize,
    out_rl: usize,
    conv: &Option<Conversion>,
    stretch: &Stretch,
) -> Vec<u8> {
    let mut b = vec![0u8; n * out_rl];
    for (d, s) in b.chunks_exact_mut(out_rl).zip(src) {
        match conv {
            Some(c) => c.apply(s, rl, d),
            None => d.copy_from_slice(s),
        }
        if !stretch.is_identity() {
            write_xyz(d, stretch.inverse(read_xyz(s)));
        }
    }
    b
}

/// The record layout COPC holds for `layout` (PDRF 6, 7 or 8 with the same extra bytes) and
/// the conversion into it, or why there is none.
pub(crate) fn output_layout(
    layout: &RecordLayout,
) -> std::result::Result<(RecordLayout, Option<Conversion>), ExportError> {
    match layout.format {
        6..=8 => Ok((layout.clone(), None)),
        4 | 5 | 9 | 10 => Err(ExportError::Waveforms {
            format: layout.format,
            instead: if layout.format == 10 {
                8
            } else if layout.format == 5 {
                7
            } else {
                6
            },
        }),
        f => {
            let extra = layout.record_len - base_len(f).unwrap_or(layout.record_len);
            let six =
                RecordLayout::new(6, 30 + extra).map_err(|error| ExportError::Layout { error })?;
            let (target, convs) = merge_layouts(&[layout.clone(), six])
                .map_err(|problem| ExportError::Convert { problem })?;
            Ok((target, convs.into_iter().next().flatten()))
        }
    }
}

/// The per-axis factors that make the grid's cells cubes in world units, or why there are none.
pub(crate) fn stretch_factors(scale: [f64; 3]) -> std::result::Result<[i64; 3], ExportError> {
    if !scale.iter().all(|s| s.is_finite() && *s > 0.0) {
        return Err(ExportError::ScalesNotPositive { scale });
    }
    let smin = scale.iter().cloned().fold(f64::INFINITY, f64::min);
    let mut m = [1i64; 3];
    for a in 0..3 {
        let r = scale[a] / smin;
        let k = r.round();
        if (r - k).abs() > 1e-6 * k || k > (1u64 << 20) as f64 {
            return Err(ExportError::ScalesNotMultiples { scale });
        }
        m[a] = k as i64;
    }
    Ok(m)
}

/// Reads, sorts and builds the tree, and assigns every point to one node.
pub(crate) fn prepare(
    ds: &Dataset,
    opts: &ExportOptions,
    report: &mut ExportReport,
) -> Result<Prepared> {
    let t0 = Instant::now();
    let rl = ds.layout.record_len;
    let (out, conv) = output_layout(&ds.layout)
        .map_err(|error| Error::Export { path: ds.inputs[0].path().to_path_buf(), error })?;
    let m = stretch_factors(ds.grid.scale)
        .map_err(|error| Error::Export { path: ds.inputs[0].path().to_path_buf(), error })?;
    let total = ds.declared_points();
    ds.progress.stage("reading", total, "points");
    let mut header_warnings = Vec::new();
    let header = crate::store::header_bounds_of(ds, &mut header_warnings);
    let promised =
        header.map(|(l, h)| Cube::covering(l, h)).unwrap_or(Cube { min: [0; 3], size_log2: 32 });
    let (slabs, mut hist) = eng::read_pieces(ds, promised)?;
    let mut all = PieceStats::default();
    for (_, st) in &slabs {
        all.merge(st);
    }
    if all.count == 0 {
        return Err(Error::NoPoints { path: ds.inputs[0].path().to_path_buf(), action: "export" });
    }
    report.read_seconds = t0.elapsed().as_secs_f64();
    let (lo, hi) = (all.min, all.max);
    let stretch = if m == [1; 3] {
        Stretch { base: [0; 3], m }
    } else {
        Stretch { base: lo.map(|v| v as i64), m }
    };
    // The stretched copy (rare: axes with different scales).
    let stretched: Vec<Vec<u8>> = if stretch.is_identity() {
        Vec::new()
    } else {
        for a in 0..3 {
            if (hi[a] as i64 - lo[a] as i64) * m[a] >= i32::MAX as i64 {
                return Err(Error::ScalesDiffer {
                    path: ds.inputs[0].path().to_path_buf(),
                    scale: ds.grid.scale,
                    axis: a,
                });
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
    let records: Vec<&[u8]> = if stretch.is_identity() {
        slabs.iter().map(|(r, _)| &**r).collect()
    } else {
        stretched.iter().map(|v| &v[..]).collect()
    };
    let (tlo, thi) = if stretch.is_identity() {
        (lo, hi)
    } else {
        ([0; 3], [0, 1, 2].map(|a| ((hi[a] as i64 - lo[a] as i64) * m[a]) as i32))
    };
    let root = match header {
        Some((l, h)) if stretch.is_identity() && (0..3).all(|a| l[a] <= lo[a] && hi[a] <= h[a]) => {
            Cube::covering(l, h)
        }
        _ => Cube::covering(tlo, thi),
    };
    let g = eng::grid_of(root);
    let shift = eng::bucket_shift(root);
    if root != promised || !stretch.is_identity() {
        hist = records.par_iter().map(|s| eng::histogram(s, rl, &g, shift)).collect();
    }
    let ts = Instant::now();
    ds.progress.stage("sorting", 2 * all.count, "points");
    let sorted = eng::sort_records(&records, &hist, rl, &g, shift, &ds.progress, |p, i| {
        (p as u64) << 32 | i as u64
    });
    drop(records);
    drop(stretched);
    drop(slabs);
    report.sort_seconds = ts.elapsed().as_secs_f64();
    crate::cleanup::check_interrupted()?;
    let tt = Instant::now();
    ds.progress.stage("indexing", 0, "");
    let n = sorted.arrival.len();
    let pos = |i: usize| read_xyz(sorted.record(i));
    let arrival = |i: usize| sorted.arrival[i];
    let tree = build_sorted(root, n, &pos, &arrival, opts.config)
        .map_err(|error| Error::Octree { error })?;
    let nodes = assign(&tree.nodes, n, &sorted, &ds.layout, opts.order, &[]);
    report.tree_seconds = tt.elapsed().as_secs_f64();
    report.warnings.extend(header_warnings);
    let frame = Frame::of(ds, out, &stretch, root);
    Ok(Prepared { sorted, stretch, conv, out: frame.out.clone(), nodes, frame, stats: all })
}

/// Every point to one node (module docs), empty subtrees dropped, children masks set. `tree`
/// is a tree or a subtree, its nodes level by level (Morton order in a level); `taken` are the
/// points that the nodes above a subtree hold (its candidates).
pub(crate) fn assign(
    tree: &[SortedNode],
    n: usize,
    sorted: &Sorted,
    layout: &RecordLayout,
    order: PointOrder,
    taken_above: &[u32],
) -> Vec<OutNode> {
    let taken: Vec<AtomicU64> = (0..n.div_ceil(64)).map(|_| AtomicU64::new(0)).collect();
    for &i in taken_above {
        taken[i as usize / 64].fetch_or(1u64 << (i % 64), Ordering::Relaxed);
    }
    let gps = layout.attribute("gps_time").map(|a| a.offset);
    let mut nodes: Vec<OutNode> = Vec::with_capacity(tree.len());
    let mut levels: Vec<std::ops::Range<usize>> = Vec::new();
    for (i, nd) in tree.iter().enumerate() {
        match levels.last_mut() {
            Some(r) if tree[r.start].key.level == nd.key.level => r.end = i + 1,
            _ => levels.push(i..i + 1),
        }
    }
    for level in levels {
        let mut here: Vec<OutNode> = tree[level]
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
                    SortedContent::Leaf(r) => r
                        .clone()
                        .filter(|&i| {
                            taken[i / 64].load(Ordering::Relaxed) & (1u64 << (i % 64)) == 0
                        })
                        .map(|i| i as u32)
                        .collect(),
                };
                if let (PointOrder::GpsTime, Some(o)) = (order, gps) {
                    let t = |i: u32| {
                        f64::from_le_bytes(sorted.record(i as usize)[o..o + 8].try_into().unwrap())
                    };
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
            if let Some(&pi) = nodes[i].key.parent().and_then(|p| at.get(&p)) {
                keep[pi] = true;
                nodes[pi].children |= 1 << nodes[i].key.octant();
            }
        }
    }
    nodes.into_iter().zip(keep).filter(|(_, k)| *k).map(|(n, _)| n).collect()
}

/// Groups of consecutive nodes of about `bytes` output bytes each (at least one node), so that
/// the writers encode a group in parallel and hold one group at a time.
pub(crate) fn groups(
    nodes: &[OutNode],
    record_len: usize,
    bytes: u64,
) -> Vec<std::ops::Range<usize>> {
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

/// Writes the nodes `nodes` in groups of about `bytes` of output records: the nodes of a group
/// converted (`records(node, range)`: the output records of the node's points `range`) and
/// encoded in parallel, a node larger than a group alone and in slices, so the records held
/// at once stay within about `bytes` whatever the density.
pub(crate) fn write_grouped(
    w: &mut dyn NodeWriter,
    nodes: &[OutNode],
    record_len: usize,
    bytes: u64,
    records: &(dyn Fn(&OutNode, std::ops::Range<usize>) -> Vec<u8> + Sync),
) -> Result<()> {
    let slice = (bytes / record_len.max(1) as u64).max(1) as usize;
    for grp in groups(nodes, record_len, bytes) {
        let big = grp.len() == 1 && nodes[grp.start].points.len() > slice;
        if big {
            let n = &nodes[grp.start];
            w.write_node_slices(n.key, n.points.len(), slice, &|r| records(n, r))?;
        } else {
            let batch: Vec<(NodeKey, Vec<u8>)> = nodes[grp]
                .par_iter()
                .filter(|n| !n.points.is_empty())
                .map(|n| (n.key, records(n, 0..n.points.len())))
                .collect();
            w.write_nodes(batch)?;
        }
    }
    Ok(())
}

/// Bytes of output records encoded per group.
pub(crate) const GROUP_BYTES: u64 = 64 << 20;

/// Memory the in-memory export needs for `ds` under the budget `memory` (resident pages): what
/// the sorted build engine holds (the records as read and sorted, 16 bytes per point), each
/// point's place in its node (4 bytes and a bit), and two groups of output records.
pub(crate) fn in_memory_need(ds: &Dataset, memory: u64) -> u64 {
    eng::held_in_memory(ds, 16 + 5).saturating_add(2 * group_bytes(memory))
}

/// The output records converted and encoded at once under the budget `memory`: a sixteenth of
/// it, between 4 MiB and [`GROUP_BYTES`] (node order and output bytes do not depend on it).
pub(crate) fn group_bytes(memory: u64) -> u64 {
    (memory / 16).clamp(4 << 20, GROUP_BYTES)
}

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
