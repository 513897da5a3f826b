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
use mortar_core::render::framing::ViewBox;
use mortar_core::render::Aabb;
use mortar_io::batch_input::RenderSource;
use mortar_io::batchfile::AttributeSelection;
use mortar_io::copc::CopcFile;
use mortar_io::ept::{ept_dir, EptSource};
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
    bytes: (u64, u64),
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
    matches!(&a.inputs[..], [one] if mortar_io::copc::is_copc_path(Path::new(one))
        || ept_dir(Path::new(one)).is_some())
}

/// The COPC input of `a` with the nodes its view needs, or `None` when the input is not a single
/// COPC file, `--no-lod` asks for the flat read, or the hierarchy cannot be used (warned).
pub fn open(a: &Args) -> Result<Option<LodSourceInput>> {
    let [one] = &a.inputs[..] else { return Ok(None) };
    if a.lod.no_lod || !is_lod_source_input(a) {
        return Ok(None);
    }
    if let Some(dir) = ept_dir(Path::new(one)) {
        return open_ept(a, &dir);
    }
    let t = Instant::now();
    let (file, warning) = CopcFile::open(Path::new(one))?;
    if let Some(w) = warning {
        common::warn(&w);
    }
    let Some(file) = file else { return Ok(None) };
    let label = one.clone();
    let crs = a.sort.crs.options();
    // The view frames what the whole file's renderers frame (the header's box, checked against
    // the first chunk: the root node).
    let whole = file.whole(&crs)?;
    let bounds = match mortar_io::framing::view_box(&whole)? {
        ViewBox::Header(h) => h.world(&whole.grid),
        ViewBox::Points => file.lod.cube_bounds(),
    };
    drop(whole);
    let camera = build_camera(&a.view.camera, &bounds, a.view.width, a.view.height)
        .map_err(|e| anyhow!("{label}: {e:#}"))?;
    let options = a.lod.options(!a.no_cull)?;
    let (nodes, selection) =
        file.lod.select(&camera, &options).map_err(|e| anyhow!("{label}: {e}"))?;
    let h = &file.lod.hierarchy;
    if nodes.is_empty() {
        bail!("{label}: no node of the COPC hierarchy is in view");
    }
    let read: Vec<_> = nodes.iter().map(|&i| h.nodes[i]).collect();
    let points_read: u64 = read.iter().map(|n| n.points).sum();
    let chunk_bytes: u64 = read.iter().map(|n| n.bytes).sum();
    let json = Read {
        format: "copc",
        nodes: (nodes.len(), h.nodes.len()),
        points: (points_read, h.points()),
        bytes: (file.index_bytes() + chunk_bytes, file.file_len()),
        pages: h.pages,
    }
    .json(&selection);
    let keep = a.view.color.attributes(file.layout());
    let ds = file.nodes(&nodes, &crs, &keep)?;
    common::print_warnings(&ds.warnings);
    let attributes = AttributeSelection::Only(keep.iter().map(|n| n.to_string()).collect());
    let source = RenderSource::batch_dataset(&ds, &a.sort.options(), &attributes)?;
    let mut json = json;
    json["seconds"] = serde_json::json!(t.elapsed().as_secs_f64());
    Ok(Some(LodSourceInput { source, bounds, json }))
}

/// [`open`] for an EPT directory.
fn open_ept(a: &Args, dir: &Path) -> Result<Option<LodSourceInput>> {
    let t = Instant::now();
    let label = dir.display().to_string();
    let ept = match EptSource::open(dir) {
        Ok(e) => e,
        Err(e) => {
            common::warn(&format!("{label}: EPT: {e}; reading its LAZ files flat"));
            return Ok(None);
        }
    };
    let bounds = ept.conforming.unwrap_or_else(|| ept.tree.cube_bounds());
    let camera = build_camera(&a.view.camera, &bounds, a.view.width, a.view.height)
        .map_err(|e| anyhow!("{label}: {e:#}"))?;
    let options = a.lod.options(!a.no_cull)?;
    let (nodes, selection) = ept.select(&camera, &options).map_err(|e| anyhow!("{label}: {e}"))?;
    if nodes.is_empty() {
        bail!("{label}: no node of the EPT hierarchy is in view");
    }
    let points_read: u64 = nodes.iter().map(|&i| ept.nodes[i].points).sum();
    // The first node's layout names the attributes the colour mode needs.
    let first = mortar_io::source::LasInput::open(&ept.node_path(nodes[0]))?;
    let keep = a.view.color.attributes(&first.layout);
    drop(first);
    let crs = a.sort.crs.options();
    let ds = ept.dataset(&nodes, &crs, &keep)?;
    common::print_warnings(&ds.warnings);
    let attributes = AttributeSelection::Only(keep.iter().map(|n| n.to_string()).collect());
    let source = RenderSource::batch_dataset(&ds, &a.sort.options(), &attributes)?;
    let mut json = Read {
        format: "ept",
        nodes: (nodes.len(), ept.nodes.len()),
        points: (points_read, ept.points),
        bytes: (ept.meta_bytes + ept.hierarchy_bytes + ept.node_bytes(&nodes), ept.total_bytes()),
        pages: ept.hierarchy_files,
    }
    .json(&selection);
    json["seconds"] = serde_json::json!(t.elapsed().as_secs_f64());
    Ok(Some(LodSourceInput { source, bounds, json }))
}
