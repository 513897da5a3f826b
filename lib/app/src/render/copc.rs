//! `mortar render file.copc.laz`: a COPC file drawn as a LOD source (issue 30 §1). The hierarchy
//! is read, the nodes for the view are chosen by the store's rule (`--lod-threshold`,
//! `--point-budget`; see `mortar_io::copc`), and only their LAZ chunks are decoded (only the
//! layers the colour mode needs), then drawn as any LAS/LAZ input is (a temporary batch file),
//! so every colour mode and both rasterizers work. `--no-lod` reads the file flat (every chunk).
//! A hierarchy that cannot be used is said in a warning and the file is read flat.

use super::args::Args;
use super::output::build_camera;
use crate::cli as common;
use anyhow::{anyhow, bail, Result};
use mortar_core::render::framing::ViewBox;
use mortar_core::render::Aabb;
use mortar_io::batch_input::RenderSource;
use mortar_io::batchfile::AttributeSelection;
use mortar_io::copc::CopcFile;
use std::path::Path;
use std::time::Instant;

/// A COPC file's selected nodes, batched for drawing.
pub struct CopcSource {
    /// The nodes' points as a temporary batch file.
    pub source: RenderSource,
    /// The box the view frames (the whole file's, by the framing rule of every renderer).
    pub bounds: Aabb,
    /// What was read (`copc` in `--json`).
    pub json: serde_json::Value,
}

/// Whether `inputs` is one COPC file drawn with LOD (a cheap look at its VLRs).
pub fn is_copc_input(a: &Args) -> bool {
    matches!(&a.inputs[..], [one] if mortar_io::copc::is_copc_path(Path::new(one)))
}

/// The COPC input of `a` with the nodes its view needs, or `None` when the input is not a single
/// COPC file, `--no-lod` asks for the flat read, or the hierarchy cannot be used (warned).
pub fn open(a: &Args) -> Result<Option<CopcSource>> {
    let [one] = &a.inputs[..] else { return Ok(None) };
    if a.lod.no_lod || !is_copc_input(a) {
        return Ok(None);
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
    let json = serde_json::json!({
        "nodes": h.nodes.len(),
        "nodes_read": nodes.len(),
        "points": h.points(),
        "points_read": points_read,
        "hierarchy_pages": h.pages,
        "bytes": file.file_len(),
        "bytes_read": file.index_bytes() + chunk_bytes,
        "selected": selection.stats.selected,
        "culled": selection.stats.culled,
        "refined": selection.stats.refined,
        "budget_reached": selection.stats.budget_reached,
    });
    let keep = a.view.color.attributes(file.layout());
    let ds = file.nodes(&nodes, &crs, &keep)?;
    common::print_warnings(&ds.warnings);
    let attributes = AttributeSelection::Only(keep.iter().map(|n| n.to_string()).collect());
    let source = RenderSource::batch_dataset(&ds, &a.sort.options(), &attributes)?;
    let mut json = json;
    json["seconds"] = serde_json::json!(t.elapsed().as_secs_f64());
    Ok(Some(CopcSource { source, bounds, json }))
}
