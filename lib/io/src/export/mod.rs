//! `mortar export`: the octree handed to other tools, as COPC 1.0 ([`copc`]), Potree 2.0
//! ([`potree`]) or 3D Tiles 1.1 ([`tiles3d`]). ARCHITECTURE.md, "Exports".
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
//! Inputs larger than `--memory` go through the partitioned engine of `mortar build`
//! ([`stream`]): the records are scattered once into run files by cell, and each unit (a
//! subtree that fits the budget) is read back, built, assigned and written on its own. The
//! nodes are the same and hold the same points as in memory; only their order in the file
//! differs. Not done: reusing the octree of an existing store (a store given as input is read
//! as points, and the tree is made again: its inner nodes hold copies, not the points).
//!
//! Both paths hand the nodes to a [`NodeWriter`](nodes::NodeWriter) ([`copc::CopcWriter`],
//! [`potree::PotreeWriter`]): nodes are encoded in parallel and appended as they come, and the
//! hierarchy is written at the end from the tree's shape.

pub mod copc;
mod glb;
mod nodes;
mod options;
pub mod potree;
mod stream;
pub mod tiles3d;
mod writer;

pub use options::{ExportFormat, ExportOptions, ExportReport, PointOrder};

use crate::dataset::Dataset;
use crate::error::Result;
use nodes::{group_bytes, in_memory_need, prepare, write_grouped, OutNode};
use std::path::Path;
use std::time::Instant;
use writer::open_writer;

/// Writes `ds` to `out` as `opts.format` says; `out` appears whole or not at all.
pub fn export(ds: &Dataset, out: &Path, opts: &ExportOptions) -> Result<ExportReport> {
    let t0 = Instant::now();
    let mut report = ExportReport { output: out.display().to_string(), ..ExportReport::default() };
    report.format = match opts.format {
        ExportFormat::Copc => "copc",
        ExportFormat::Potree => "potree",
        ExportFormat::Tiles3d => "3dtiles",
    };
    let tree = if in_memory_need(ds, opts.memory) <= opts.memory
        && ds.declared_points() < u32::MAX as u64
    {
        report.engine = "memory";
        in_memory(ds, out, opts, &mut report)?
    } else {
        report.engine = "partitioned";
        stream::export(ds, out, opts, &mut report)?
    };
    report.nodes = tree.len() as u64;
    report.depth = tree.iter().map(|n| n.key.level as u32).max().unwrap_or(0);
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(report)
}

/// The in-memory export: every point read, sorted and assigned, then the nodes written level
/// by level. Returns the tree's shape.
fn in_memory(
    ds: &Dataset,
    out: &Path,
    opts: &ExportOptions,
    report: &mut ExportReport,
) -> Result<Vec<OutNode>> {
    let prep = prepare(ds, opts, report)?;
    let tw = Instant::now();
    let mut w = open_writer(ds, prep.frame.clone(), out, opts.format, &prep.stats, report)?;
    let points: u64 = prep.nodes.iter().map(|n| n.points.len() as u64).sum();
    ds.progress.stage("writing", points, "points");
    write_grouped(
        &mut *w,
        &prep.nodes,
        prep.frame.out.record_len,
        group_bytes(opts.memory),
        &|n, r| prep.node_records(n, r),
    )?;
    let shape: Vec<OutNode> = prep.nodes.iter().map(OutNode::shape).collect();
    w.finish(&shape, &prep.stats, report)?;
    report.write_seconds = tw.elapsed().as_secs_f64();
    report.point_format = prep.frame.out.format;
    Ok(shape)
}
