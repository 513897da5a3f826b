//! `mortar render`: one view of a batch file (or of LAS/LAZ batched on the fly) drawn by the CPU
//! reference rasterizer or the wgpu compute rasterizer (paper 003 §3.2-3.4) to a PNG. Both leave
//! the same visibility buffer; the colours are chosen from the visible points alone. The CPU
//! path resolves on the host; the GPU path reads the keys back only to choose the colours, and
//! hole filling, colours and eye-dome lighting run on the GPU (the same image, byte for byte).

mod args;
pub mod copc;
pub mod lod;
mod output;
pub mod progressive_render;

pub use args::*;
pub use output::*;

use crate::draw;
use anyhow::{anyhow, bail, Result};
use mortar_io::batch_input;
use std::time::Instant;

/// Opens the input, draws the view, writes the PNG and (with `--json`) the statistics.
pub fn run(a: Args) -> Result<()> {
    if a.view.width == 0 || a.view.height == 0 || a.view.width > 16384 || a.view.height > 16384 {
        bail!(
            "--width {} --height {}: each side must be 1 to 16384 pixels",
            a.view.width,
            a.view.height
        );
    }
    // Checked again by build_camera; here so that a typo fails before LAS input is batched.
    if !(a.view.camera.fov > 0.0 && a.view.camera.fov < 180.0) {
        bail!("--fov {}: must be between 0 and 180 degrees", a.view.camera.fov);
    }
    if a.progressive.progressive.is_some() {
        return crate::render::progressive_render::run(&a);
    }
    if let Some(store) = crate::render::lod::store_input(&a)? {
        return crate::render::lod::run(&a, &store);
    }
    let start = Instant::now();
    let (source, bounds, copc_json) = match copc::open(&a)? {
        Some(c) => (c.source, c.bounds, c.json),
        None => {
            let (s, b) = open_source(&a.inputs, &a.sort, Some(a.view.color))?;
            (s, b, serde_json::Value::Null)
        }
    };
    let batch_seconds = start.elapsed().as_secs_f64();
    let file = &source.file;
    let own = |e| source.own_error(e);
    let label = source.name.display().to_string();
    if file.header.point_count == 0 {
        bail!("{label}: no points to draw");
    }
    draw::batch::check_color(file, a.view.color).map_err(own)?;
    let camera = build_camera(&a.view.camera, &bounds, a.view.width, a.view.height)
        .map_err(|e| anyhow!("{label}: {e:#}"))?;
    let views = batch_input::load_words(file).map_err(own)?;
    let refs = batch_input::batch_refs(file, &views).map_err(own)?;
    let settings = render_settings(&a);
    let gpu = gpu_context(&a)?;
    let (r, gpu_json) = match &gpu {
        None => (
            draw::batch::render(file, &refs, &camera, &settings).map_err(own)?,
            serde_json::Value::Null,
        ),
        Some(ctx) => {
            let (r, j) = render_gpu(ctx, file, &refs, &camera, &settings)
                .map_err(|e| anyhow!("{label}: GPU: {e}"))?;
            (r.map_err(own)?, j)
        }
    };
    let t = Instant::now();
    let png = encode_png(r.width, r.height, &r.rgba)?;
    write_atomic(&a.output, &png)?;
    let png_seconds = t.elapsed().as_secs_f64();
    if a.json {
        let projected = r.stats.points_projected() as f64;
        let mut j = rendered_json(
            &a,
            &label,
            &r,
            &gpu_json,
            a.view.color.resolved(file).name(),
            &camera,
            file.header.point_count,
            png_seconds,
        );
        // Pixels whose winner ties in depth with another point (where a renderer numbering the
        // points otherwise may show another of them): a second pass over the points on the CPU,
        // on the CPU backend only.
        j["depth_ties"] = serde_json::json!(match &gpu {
            None => Some(
                mortar_core::render::count_depth_ties(
                    &r.keys,
                    &refs,
                    &file.grid(),
                    &camera,
                    &settings.raster
                )
                .map_err(|e| anyhow!("{label}: {e}"))?
            ),
            Some(_) => None,
        });
        j["batch_seconds"] =
            serde_json::json!(if source.is_temporary() { Some(batch_seconds) } else { None });
        j["lod_source"] = copc_json;
        j["gpu_points_per_second"] = serde_json::json!(gpu_json
            .get("draw_ms")
            .and_then(|v| v.as_f64())
            .map(|ms| projected / (ms * 1e-3).max(1e-12)));
        print_json(&a, &j)?;
    }
    Ok(())
}
