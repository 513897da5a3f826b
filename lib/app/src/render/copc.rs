//! `mortar render file.copc.laz` and `mortar render ept-dir/`: a COPC file or an EPT directory
//! drawn as a LOD source (issue 30 §1). The hierarchy is read, the nodes for the view are chosen
//! by the store's rule (`--lod-threshold`, `--point-budget`; see `mortar_io::additive`), and only
//! their LAZ chunks (COPC) or files (EPT) are decoded (only the layers the colour mode needs),
//! then drawn as any LAS/LAZ input is (a temporary batch file), so every colour mode and both
//! rasterizers work. `--no-lod` reads the input flat (every chunk, every file). A hierarchy that
//! cannot be used is said in a warning and the input is read flat.
//!
//! Framing: a COPC view frames what a flat read frames (the header's box, checked against the
//! root chunk); an EPT view frames `boundsConforming` of `ept.json` (the points' box; the flat
//! read frames the union of the node files' headers, which may differ by rounding), else its
//! cube.

use super::args::Args;
use super::output::build_camera;
use crate::cli as common;
use anyhow::{anyhow, bail, Result};
use mortar_core::render::Aabb;
use mortar_io::batch_input::RenderSource;
use mortar_io::batchfile::AttributeSelection;
use mortar_io::lod_source::{is_lod_source_path, LodSource};
use std::path::Path;
use std::time::Instant;

/// A COPC file's or an EPT directory's selected nodes, batched for drawing.
pub struct LodSourceInput {
    /// The nodes' points as a temporary batch file.
    pub source: RenderSource,
    /// The box the view frames (the whole file's, by the framing rule of every renderer).
    pub bounds: Aabb,
    /// What was read (`copc` in `--json`).
    pub json: serde_json::Value,
}

/// What a LOD source's view read against the whole: (read, total) of nodes, points and bytes.
struct Read {
    format: &'static str,
    nodes: (usize, usize),
    points: (u64, u64),
    /// Read, and the whole (unknown for an EPT directory over HTTP).
    bytes: (u64, Option<u64>),
    pages: u64,
}

impl Read {
    /// `lod_source` of `render --json`.
    fn json(&self, selection: &mortar_core::octree::LodSelection) -> serde_json::Value {
        serde_json::json!({
            "format": self.format,
            "nodes_read": self.nodes.0,
            "nodes": self.nodes.1,
            "points_read": self.points.0,
            "points": self.points.1,
            "bytes_read": self.bytes.0,
            "bytes": self.bytes.1,
            "hierarchy_pages": self.pages,
            "selected": selection.stats.selected,
            "culled": selection.stats.culled,
            "refined": selection.stats.refined,
            "budget_reached": selection.stats.budget_reached,
        })
    }
}

/// Whether `inputs` is one COPC file (a cheap look at its VLRs) or one EPT directory.
pub fn is_lod_source_input(a: &Args) -> bool {
    matches!(&a.inputs[..], [one] if is_lod_source_path(Path::new(one)))
}

/// The COPC or EPT input of `a` with the nodes its view needs, or `None` when the input is not
/// a single COPC file or EPT directory, `--no-lod` asks for the flat read, or the hierarchy
/// cannot be used (warned).
pub fn open(a: &Args) -> Result<Option<LodSourceInput>> {
    let [one] = &a.inputs[..] else { return Ok(None) };
    if a.lod.no_lod || !is_lod_source_input(a) {
        return Ok(None);
    }
    let t = Instant::now();
    let (src, warning) = LodSource::open(Path::new(one))?;
    if let Some(w) = warning {
        common::warn(&w);
    }
    let Some(src) = src else { return Ok(None) };
    let label = src.path().display().to_string();
    let crs = a.sort.crs.options();
    let bounds = src.bounds(&crs)?;
    let camera = build_camera(&a.view.camera, &bounds, a.view.width, a.view.height)
        .map_err(|e| anyhow!("{label}: {e:#}"))?;
    let options = a.lod.options(!a.no_cull)?;
    let (nodes, selection) = src.select(&camera, &options).map_err(|e| anyhow!("{label}: {e}"))?;
    if nodes.is_empty() {
        bail!("{label}: no node of the {} hierarchy is in view", src.format().to_uppercase());
    }
    // The layout names the attributes the colour mode needs.
    let keep = a.view.color.attributes(&src.layout()?);
    let ds = src.dataset(&nodes, &crs, &keep)?;
    common::print_warnings(&ds.warnings);
    let attributes = AttributeSelection::Only(keep.iter().map(|n| n.to_string()).collect());
    let source = RenderSource::batch_dataset(&ds, &a.sort.options(), &attributes)?;
    // What was read (after the dataset: over HTTP, node sizes are known once fetched).
    let points_read: u64 = nodes.iter().map(|&i| src.node_points(i)).sum();
    let mut json = Read {
        format: src.format(),
        nodes: (nodes.len(), src.node_count()),
        points: (points_read, src.points()),
        bytes: (src.index_bytes() + src.node_bytes(&nodes), src.total_bytes()),
        pages: src.pages(),
    }
    .json(&selection);
    json["seconds"] = serde_json::json!(t.elapsed().as_secs_f64());
    json["bytes_fetched"] = serde_json::json!(src.bytes_fetched());
    Ok(Some(LodSourceInput { source, bounds, json }))
}
