//! `mortar render store/`: LOD rendering of an octree store (paper 004 §6). The nodes to draw are
//! selected for the view from the store's hierarchy (culled by the frustum, refined while wider
//! than `--lod-threshold` pixels on screen, within `--point-budget`), then drawn straight from the
//! memory-mapped payloads by the CPU or the GPU rasterizer and resolved on the host with the
//! stored colours (or elevation), hole filling and eye-dome lighting. `--no-lod` draws every
//! point through a temporary batch file instead (the path of LAS/LAZ inputs; every colour mode).

use super::args::Args;
use super::output::{build_camera, encode_png, write_atomic};
use crate::draw;
use crate::draw::lod::LodColor;
use crate::draw::{RenderSettings, Rendered};
use anyhow::{anyhow, bail, Result};
use mortar_core::octree::{LodOptions, LodSelection};
use mortar_core::render::Camera;
use mortar_io::inputs::InputKind;
use mortar_io::store::{LodBatches, StoreLod};
use mortar_render::{GpuContext, GpuError};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The store to draw with LOD: the input when it is a single store directory and `--no-lod` is
/// not given. LOD options given for any other input are an error.
pub fn store_input(a: &Args) -> Result<Option<PathBuf>> {
    let store = match &a.inputs[..] {
        [one] if InputKind::of(Path::new(one)) == InputKind::Store => Some(PathBuf::from(one)),
        _ => None,
    };
    if store.is_none()
        && !super::copc::is_lod_source_input(a)
        && (a.lod.lod_threshold.is_some() || a.lod.point_budget.is_some() || a.lod.no_lod)
    {
        bail!("--lod-threshold, --point-budget and --no-lod apply to a single octree store (made by mortar build), COPC file or EPT directory, not to {}", a.inputs.join(" "));
    }
    Ok(if a.lod.no_lod { None } else { store })
}

/// Draws the view of the store `dir` with LOD, writes the PNG and (with `--json`) the statistics.
pub fn run(a: &Args, dir: &Path) -> Result<()> {
    let start = Instant::now();
    let lod = StoreLod::open(dir)?;
    let open_seconds = start.elapsed().as_secs_f64();
    let label = dir.display().to_string();
    if lod.drawable() == 0 {
        bail!("{label}: no points to draw");
    }
    let color = LodColor::of(lod.store(), a.view.color)?;
    let options = a.lod.options(!a.no_cull)?;
    let camera = build_camera(&a.view.camera, &lod.bounds(), a.view.width, a.view.height)
        .map_err(|e| anyhow!("{label}: {e:#}"))?;
    let t = Instant::now();
    let selection = lod.select(&camera, &options)?;
    let selection_seconds = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let batches = lod.batches(&selection.nodes)?;
    let prepare_seconds = t.elapsed().as_secs_f64();
    let settings = super::output::render_settings(a);
    let gpu = super::output::gpu_context(a)?;
    let (r, gpu_json) = match &gpu {
        None => (draw::lod::render(&lod, &batches, &camera, &settings)?, serde_json::Value::Null),
        Some(ctx) => {
            let (r, j) = render_gpu(ctx, &lod, &batches, &camera, &settings)
                .map_err(|e| anyhow!("{label}: GPU: {e}"))?;
            (r?, j)
        }
    };
    let t = Instant::now();
    let png = encode_png(r.width, r.height, &r.rgba)?;
    write_atomic(&a.output, &png)?;
    let png_seconds = t.elapsed().as_secs_f64();
    if a.json {
        let mut j = super::output::rendered_json(
            a,
            &label,
            &r,
            &gpu_json,
            color.name(),
            &camera,
            lod.point_count(),
            png_seconds,
        );
        j["lod"] = lod_json(&selection, &options, selection_seconds, prepare_seconds);
        j["open_seconds"] = serde_json::json!(open_seconds);
        super::output::print_json(a, &j)?;
    }
    Ok(())
}

/// The selection's statistics as JSON.
pub fn lod_json(
    sel: &LodSelection,
    options: &LodOptions,
    selection_seconds: f64,
    prepare_seconds: f64,
) -> serde_json::Value {
    let s = &sel.stats;
    serde_json::json!({
        "threshold_px": options.threshold_px,
        "point_budget": options.point_budget,
        "nodes_selected": s.selected,
        "points": s.points,
        "voxels": s.voxels,
        "samples": s.samples(),
        "budget_reached": s.budget_reached,
        "nodes_visited": s.visited,
        "nodes_culled": s.culled,
        "nodes_empty": s.empty,
        "nodes_refined": s.refined,
        "selection_seconds": selection_seconds,
        "prepare_seconds": prepare_seconds,
    })
}

/// Draws the selected nodes with the GPU rasterizer ([`draw_keys_gpu`](super::draw_keys_gpu),
/// in index order, so the framebuffer's index is the batches' sample index) and resolves the keys
/// on the host as the CPU path does. The outer error is the GPU's, the inner one the store's.
pub(crate) fn render_gpu(
    ctx: &GpuContext,
    lod: &StoreLod,
    batches: &LodBatches<'_>,
    camera: &Camera,
    settings: &RenderSettings,
) -> std::result::Result<(mortar_io::Result<Rendered>, serde_json::Value), GpuError> {
    let (keys, frame, j) = super::output::draw_keys_gpu(
        ctx,
        lod.grid(),
        batches.samples,
        &batches.refs,
        camera,
        &settings.raster,
    )?;
    Ok((
        draw::lod::resolve_keys(
            lod,
            batches,
            keys,
            frame.stats,
            frame.frame_seconds,
            camera,
            settings,
        ),
        j,
    ))
}
