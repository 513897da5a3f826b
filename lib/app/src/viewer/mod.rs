//! `mortar view`: a window on one of three kinds of content ([`Content`]): a batch file (every
//! point; other non-LAS inputs are batched on the fly as `mortar render` does), an octree store
//! ([`store::StoreView`]: LOD selection per frame, nodes uploaded on first selection) or raw
//! LAS/LAZ ([`progressive_view::ProgressiveView`]: the progressive renderer of paper 000, the window
//! open at once and points appearing as they are decoded); and the window of `mortar build
//! --preview`, which reads the growing store's commits. Each frame is drawn by the GPU
//! rasterizer (paper 003 §3.2-3.3: clear, draw, resolve in compute shaders) and put on the
//! window's surface by one render pass, without the image leaving the GPU; where no hardware GPU
//! can present to the window (or with `--backend cpu`) the CPU reference rasterizer draws and
//! the image is uploaded to the window as a plain pixel buffer (softbuffer).
//!
//! Frames are drawn on input (orbit, pan, zoom, keys, resizes) and when the content changes
//! (points decoded, a new commit of the previewed store). `--screenshot out.png --frames N`
//! draws N frames in the real window, writes what the last one put on the surface and exits
//! (tests run it under Xvfb).

pub mod args;
mod build_state;
pub mod content;
mod lod_source_view;
mod node_loader;
mod overlay;
mod preview;
pub mod progressive_view;
pub mod store;
mod window;

pub use args::{Args, PreviewArgs, ViewBackend};
pub use content::{group_digits, BatchContent, Content, GpuDrawn};
pub use preview::{run_preview, run_preview_offscreen};
pub use window::Wake;

use crate::draw;
use crate::viewer::lod_source_view::LodSourceView;
use crate::viewer::progressive_view::ProgressiveView;
use crate::viewer::store::StoreView;
use anyhow::{bail, Result};
use args::check_window;
use mortar_io::batch_input;
use mortar_io::inputs::InputKind;
use mortar_io::lod_source::{is_lod_source_path, LodSource};
use std::path::PathBuf;
use window::{event_loop, show};

/// Opens the input and the window, then runs the event loop until the window is closed (or the
/// screenshot is written).
pub fn run(a: Args) -> Result<()> {
    check_window(&a)?;
    // The display first: no point in batching a large LAZ file for a window that cannot open.
    let event_loop = event_loop()?;
    let store = match &a.inputs[..] {
        [one] if !a.lod.no_lod && InputKind::of(std::path::Path::new(one)) == InputKind::Store => {
            Some(PathBuf::from(one))
        }
        _ => None,
    };
    let lod_source = match &a.inputs[..] {
        [one] if !a.lod.no_lod && is_lod_source_path(std::path::Path::new(one)) => {
            let (src, warning) = LodSource::open(std::path::Path::new(one))?;
            if let Some(w) = warning {
                crate::cli::warn(&w);
            }
            src
        }
        _ => None,
    };
    if store.is_none()
        && lod_source.is_none()
        && (a.lod.lod_threshold.is_some() || a.lod.point_budget.is_some())
    {
        bail!("--lod-threshold and --point-budget apply to a single octree store (made by mortar build), COPC file or EPT directory, not to {}", a.inputs.join(" "));
    }
    if let Some(src) = lod_source {
        let open = a.sort.crs.options();
        let bounds = src.bounds(&open)?;
        let label = src.path().display().to_string();
        let view = LodSourceView::new(
            src,
            open,
            bounds,
            a.lod.options(true)?,
            a.view.color,
            a.view.range,
        )?;
        return show(&a, event_loop, Box::new(view), label, None).map(drop);
    }
    if let Some(dir) = store {
        let mut view = StoreView::open(&dir, a.lod.options(true)?, a.view.range)?;
        view.show_mode(a.view.color)?;
        let label = dir.display().to_string();
        return show(&a, event_loop, Box::new(view), label, None).map(drop);
    }
    if !a.no_progressive {
        let paths = mortar_io::inputs::expand(&a.inputs)?;
        let raw = !paths.is_empty() && paths.iter().all(|p| InputKind::of(p) == InputKind::Las);
        if raw {
            let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
            let view = ProgressiveView::open(&paths, a.view.color, a.view.range, threads)?;
            let label = paths.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" ");
            return show(&a, event_loop, Box::new(view), label, None).map(drop);
        }
    }
    let (source, bounds) = crate::render::open_source(&a.inputs, &a.sort, None)?;
    let file = &source.file;
    let own = |e| source.own_error(e);
    let label = source.name.display().to_string();
    if file.header.point_count == 0 {
        bail!("{label}: no points to draw");
    }
    draw::batch::check_color(file, a.view.color.resolved(file)).map_err(own)?;
    let views = batch_input::load_words(file).map_err(own)?;
    let refs = batch_input::batch_refs(file, &views).map_err(own)?;
    let content = BatchContent::new(label.clone(), file, &refs, bounds, a.view.color, a.view.range)
        .map_err(own)?;
    show(&a, event_loop, Box::new(content), label, None).map(drop)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn digits_are_grouped() {
        assert_eq!(group_digits(0), "0");
        assert_eq!(group_digits(999), "999");
        assert_eq!(group_digits(1000), "1,000");
        assert_eq!(group_digits(110_000), "110,000");
        assert_eq!(group_digits(1_234_567), "1,234,567");
    }
}
