//! The export of inputs larger than `--memory`: the partitioned engine of `mortar build`
//! (`store/partitioned.rs`) with the export's writers as its sink.
//!
//! 1. Pass 1 of the partitioned engine: every piece read once, its records scattered by their
//!    cell at depth `D` of the root into run files in a temporary directory beside the output.
//! 2. The tree's top is walked depth first. A node whose points fit one unit's budget is a unit:
//!    its points are read back and sorted, [`build_subtree`] makes its subtree, and
//!    [`assign`](super::nodes::assign) gives each of its points to one node, starting with the unit's
//!    candidates marked as taken. That is exact: an inner node's voxels are its children's
//!    candidates end to end, so every candidate a unit hands up is a voxel of the node above
//!    it and is held there or higher, and no other point of the unit is held above it. The
//!    unit's nodes are written at once.
//! 3. A node above the units holds its voxels (its children's candidates) less those it hands
//!    its own parent; it is written when its children are done.
//!
//! The nodes and their points are those of the in-memory export (the tree is the sorted
//! engine's; `tests/export.rs` compares both node by node); the nodes come in another order in
//! the file. Axes with different scales are stretched as in memory: the run files hold the
//! stretched positions (base: the points' smallest position, so such inputs are read twice).
//! A partition cell denser than one unit's budget is partitioned again, or is a leaf written in
//! slices, as the build does (`store/dense.rs`).

use super::nodes::{assign, output_layout, stretch_factors, Frame, NodeWriter, OutNode, Stretch};
use super::options::{ExportOptions, ExportReport, PointOrder};
use super::writer::open_writer;
use crate::cleanup::TempPath;
use crate::dataset::Dataset;
use crate::error::{Error, Result};
use crate::store::dense::{self, Level};
use crate::store::partitioned::{cell_depth, partition_all, read_unit, unit_bytes_per_point};
use crate::store::runs::Cands;
use mortar_core::layout::{read_xyz, Conversion};
use mortar_core::octree::{build_subtree, splits, Cube, NodeKey};
use std::path::Path;
use std::time::Instant;

/// Exports `ds` through run files; returns the tree's shape.
pub(crate) fn export(
    ds: &Dataset,
    out: &Path,
    opts: &ExportOptions,
    report: &mut ExportReport,
) -> Result<Vec<OutNode>> {
    let t0 = Instant::now();
    let first = ds.inputs[0].path();
    let (layout, conv) = output_layout(&ds.layout)
        .map_err(|error| Error::Export { path: first.to_path_buf(), error })?;
    let m = stretch_factors(ds.grid.scale)
        .map_err(|error| Error::Export { path: first.to_path_buf(), error })?;
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let state = TempPath::dir_in(parent, "export-runs").map_err(|e| Error::io(parent, e))?;
    let mut header_warnings = Vec::new();
    let header = crate::store::header_bounds_of(ds, &mut header_warnings);
    let part =
        partition_all(ds, opts.memory, opts.config.max_level, m, header, state.path(), None)?;
    report.warnings.extend(header_warnings);
    report.warnings.extend(part.warnings.iter().cloned());
    report.read_seconds = t0.elapsed().as_secs_f64();
    if part.all.count == 0 {
        return Err(Error::NoPoints { path: first.to_path_buf(), action: "export" });
    }
    let rl = ds.layout.record_len;
    let unit_points = ((opts.memory / 2) / unit_bytes_per_point(rl as u64))
        .max(opts.config.leaf_capacity as u64 + 1);
    let stretch = Stretch { base: part.base, m };
    let frame = Frame::of(ds, layout, &stretch, part.root);
    report.point_format = frame.out.format;
    let out_rl = frame.out.record_len;
    let mut writer = open_writer(ds, frame, out, opts.format, &part.all, report)?;
    ds.progress.stage("building and writing", part.all.count, "points");
    let gps = match opts.order {
        PointOrder::GpsTime => ds.layout.attribute("gps_time").map(|a| a.offset),
        PointOrder::Morton => None,
    };
    let cells = part.hist.len();
    let lv = Level::new(part.runs, part.hist, cell_depth(part.root, opts.config.max_level));
    let mut w = Walk {
        ds,
        opts,
        root: part.root,
        unit_points,
        rl,
        out_rl,
        conv,
        stretch,
        gps,
        writer: &mut *writer,
        tree: Vec::new(),
        dir: state.path().to_path_buf(),
        report: &mut *report,
    };
    w.visit(&lv, NodeKey::ROOT, part.root, 0, 0..cells)?;
    let tree = std::mem::take(&mut w.tree);
    let tw = Instant::now();
    writer.finish(&tree, &part.all, report)?;
    report.write_seconds += tw.elapsed().as_secs_f64();
    drop(state);
    Ok(tree)
}

/// The depth-first walk over the tree's top.
struct Walk<'a, 'w> {
    ds: &'a Dataset,
    opts: &'a ExportOptions,
    root: Cube,
    unit_points: u64,
    rl: usize,
    out_rl: usize,
    conv: Option<Conversion>,
    stretch: Stretch,
    /// Offset of the GPS time in the input records, when nodes are ordered by it.
    gps: Option<usize>,
    writer: &'w mut dyn NodeWriter,
    /// Every node written or with written nodes below.
    tree: Vec<OutNode>,
    dir: std::path::PathBuf,
    report: &'w mut ExportReport,
}

impl Walk<'_, '_> {
    /// Exports node `key` (cube `cube`, at `depth`, over the cells `cells` of `lv`) and
    /// everything under it; returns its candidates for its parent and whether it is kept.
    fn visit(
        &mut self,
        lv: &Level,
        key: NodeKey,
        cube: Cube,
        depth: u8,
        cells: std::ops::Range<usize>,
    ) -> Result<(Cands, bool)> {
        crate::cleanup::check_interrupted()?;
        let count: u64 = lv.hist[cells.clone()].iter().sum();
        if count == 0 {
            return Ok((Cands::default(), false));
        }
        if depth == lv.depth || count <= self.unit_points {
            if count > self.unit_points {
                return self.dense(lv, key, cube, cells, count, None);
            }
            return self.unit(lv, key, cube, cells, count);
        }
        // More points than a unit, so more than a leaf, in a cube that may split: inner.
        let step = cells.len() / 8;
        self.inner(key, cube, |w, o| {
            w.visit(
                lv,
                key.child(o),
                cube.child(o),
                depth + 1,
                cells.start + o * step..cells.start + (o + 1) * step,
            )
        })
    }

    /// Exports the inner node `key` (cube `cube`) whose children `kid(o)` exports.
    fn inner(
        &mut self,
        key: NodeKey,
        cube: Cube,
        mut kid: impl FnMut(&mut Self, usize) -> Result<(Cands, bool)>,
    ) -> Result<(Cands, bool)> {
        let mut voxels = Cands::default();
        let mut children = 0u8;
        for o in 0..8 {
            let (c, kept) = kid(self, o)?;
            if kept {
                children |= 1 << o;
            }
            voxels.append(c);
        }
        let rl = self.rl;
        let n = voxels.pos.len();
        let up = voxels.for_parent(key, cube);
        let mut above = vec![false; n];
        for &i in &up {
            above[i] = true;
        }
        let mut own: Vec<usize> = (0..n).filter(|&i| !above[i]).collect();
        if let Some(o) = self.gps {
            let t = |i: usize| {
                f64::from_le_bytes(
                    voxels.records[i * rl + o..i * rl + o + 8].try_into().expect("8 bytes"),
                )
            };
            own.sort_by(|a, b| t(*a).total_cmp(&t(*b)));
        }
        if !own.is_empty() {
            let recs = super::nodes::output_records(
                own.iter().map(|&i| &voxels.records[i * rl..(i + 1) * rl]),
                own.len(),
                rl,
                self.out_rl,
                &self.conv,
                &self.stretch,
            );
            let tw = Instant::now();
            self.writer.write_nodes(vec![(key, recs)])?;
            self.report.write_seconds += tw.elapsed().as_secs_f64();
        }
        let kept = !own.is_empty() || children != 0;
        if kept {
            self.tree.push(OutNode { key, points: Vec::new(), children });
        }
        Ok((voxels.pick(&up, rl), kept))
    }

    /// Exports node `key` over the `count` points of `cells` of `lv`, more than a unit holds
    /// (bounds `known` where known), as the build does (`store/dense.rs`).
    fn dense(
        &mut self,
        lv: &Level,
        key: NodeKey,
        cube: Cube,
        cells: std::ops::Range<usize>,
        count: u64,
        known: Option<dense::Bounds>,
    ) -> Result<(Cands, bool)> {
        let rl = self.rl;
        let block = dense::block_points(self.opts.memory, rl);
        let b = match known {
            Some(b) => b,
            None => lv.bounds(&cells, rl, block)?,
        };
        if splits(count, key, cube, &self.opts.config) {
            if let Some(o) = dense::one_octant(cube, b) {
                let c0 = cells.start;
                return self.inner(key, cube, |w, k| {
                    if k == o {
                        w.dense(lv, key.child(o), cube.child(o), cells.clone(), count, Some(b))
                    } else {
                        w.visit(lv, key.child(k), cube.child(k), key.level + 1, c0..c0)
                    }
                });
            }
            let d = dense::tree_split_depth(key, cube, self.opts.config.max_level);
            let dir = self.dir.clone();
            let sub = dense::split(&lv.runs, cells, rl, cube, key.level, d, block, &dir)?;
            self.report.dense_cells += 1;
            let n = sub.hist.len();
            return self.visit(&sub, key, cube, key.level, 0..n);
        }
        // A leaf larger than a unit: its points less the candidates it hands up, in slices.
        let ts = Instant::now();
        let leaf = dense::big_leaf(
            lv,
            cells,
            count,
            key,
            cube,
            b,
            rl,
            self.unit_points,
            block,
            &self.dir,
        )?;
        self.report.large_leaves += 1;
        self.report.sort_seconds += ts.elapsed().as_secs_f64();
        let kept = count - leaf.cand_index.len() as u64;
        if kept > 0 {
            let tw = Instant::now();
            let (conv, stretch, out_rl) = (&self.conv, &self.stretch, self.out_rl);
            let slice = (super::nodes::group_bytes(self.opts.memory) / out_rl.max(1) as u64).max(1)
                as usize;
            let failed: std::sync::Mutex<Option<Error>> = std::sync::Mutex::new(None);
            // By GPS time: parts sorted and merged as the writer reads them (in order).
            let timed = match self.gps {
                Some(o) => Some(std::sync::Mutex::new(leaf.time_order(
                    kept,
                    o,
                    self.unit_points,
                    block,
                    &self.dir,
                )?)),
                None => None,
            };
            let records = |r: std::ops::Range<usize>| -> Vec<u8> {
                let recs = match &timed {
                    Some(t) => t.lock().unwrap_or_else(|p| p.into_inner()).next(r.len()),
                    None => leaf.read_kept(r.start as u64..r.end as u64),
                };
                match recs {
                    Ok(recs) => super::nodes::output_records(
                        recs.chunks_exact(rl),
                        r.len(),
                        rl,
                        out_rl,
                        conv,
                        stretch,
                    ),
                    Err(e) => {
                        failed.lock().unwrap_or_else(|p| p.into_inner()).get_or_insert(e);
                        vec![0u8; r.len() * out_rl]
                    }
                }
            };
            self.writer.write_node_slices(key, kept as usize, slice, &records)?;
            if let Some(e) = failed.into_inner().unwrap_or_else(|p| p.into_inner()) {
                return Err(e);
            }
            self.report.write_seconds += tw.elapsed().as_secs_f64();
            self.tree.push(OutNode { key, points: Vec::new(), children: 0 });
        }
        Ok((leaf.cands, kept > 0))
    }

    /// Reads a unit's points back, builds, assigns and writes its subtree.
    fn unit(
        &mut self,
        lv: &Level,
        key: NodeKey,
        cube: Cube,
        cells: std::ops::Range<usize>,
        count: u64,
    ) -> Result<(Cands, bool)> {
        let rl = self.rl;
        let n = count as usize;
        let ts = Instant::now();
        let sorted = read_unit(&lv.runs, self.root, key, cells, count, rl, &self.dir)?;
        self.report.sort_seconds += ts.elapsed().as_secs_f64();
        let tt = Instant::now();
        let pos = |i: usize| read_xyz(sorted.record(i));
        let arr = |i: usize| sorted.arrival[i];
        let sub = build_subtree(key, cube, n, &pos, &arr, self.opts.config)
            .map_err(|error| Error::Octree { error })?;
        let mut nodes = sub.nodes;
        // Level by level, depth-first (= Morton) order in a level, as `assign` wants.
        nodes.sort_by_key(|x| x.key.level);
        let assigned =
            assign(&nodes, n, &sorted, &self.ds.layout, self.opts.order, &sub.candidates);
        drop(nodes);
        self.report.tree_seconds += tt.elapsed().as_secs_f64();
        let tw = Instant::now();
        let (conv, stretch, out_rl) = (&self.conv, &self.stretch, self.out_rl);
        let records = |x: &OutNode, r: std::ops::Range<usize>| {
            let pts = &x.points[r];
            super::nodes::output_records(
                pts.iter().map(|&i| sorted.record(i as usize)),
                pts.len(),
                rl,
                out_rl,
                conv,
                stretch,
            )
        };
        super::nodes::write_grouped(
            &mut *self.writer,
            &assigned,
            self.out_rl,
            super::nodes::group_bytes(self.opts.memory),
            &records,
        )?;
        self.report.write_seconds += tw.elapsed().as_secs_f64();
        let kept = assigned.iter().any(|x| x.key == key);
        self.tree.extend(assigned.iter().map(OutNode::shape));
        let mut out = Cands::default();
        for &i in &sub.candidates {
            let r = sorted.record(i as usize);
            out.push(read_xyz(r), sorted.arrival[i as usize], r);
        }
        Ok((out, kept))
    }
}
