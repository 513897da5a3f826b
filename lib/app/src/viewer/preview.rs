//! `mortar build --preview`: the window (or, off screen, a fixed camera at most 60 frames per
//! second) on the store a build is growing, reading its commits while the build runs on
//! another thread; the build never waits for the window.

use super::args::*;
use super::build_state::*;
use super::content::*;
use super::window::*;
use crate::render::{build_camera, AtomicsArg};
use crate::viewer::store::StoreView;
use anyhow::{anyhow, Result};
use mortar_core::layout::RecordLayout;
use mortar_core::render::{Aabb, RasterOptions};
use mortar_io::store::{BuildProgress, BuildReport};
use mortar_render::{AtomicPath, GpuContext, GpuOptions, GpuRasterizer};
use std::sync::mpsc::TryRecvError;
use std::time::Instant;
use winit::event_loop::EventLoopProxy;

/// `mortar build --preview`: shows the store `dir` as `build` grows it. `build` runs on its own
/// thread and reports progress through the callback it is given, which never blocks (an
/// unbounded channel and a wake-up event): the builder never waits for the window. The window
/// reloads the store at each new commit and draws it with LOD, uploading only new nodes. If the
/// window is closed first, the build goes on without it and this waits for it; with
/// `--screenshot` the window closes itself once the last commit was shown. Returns the build's
/// report and the frames' statistics.
pub fn run_preview<F>(
    a: &Args,
    dir: &std::path::Path,
    bounds: Aabb,
    layout: &RecordLayout,
    build: F,
) -> Result<(BuildReport, serde_json::Value)>
where
    F: FnOnce(&mut dyn FnMut(&BuildProgress)) -> Result<BuildReport> + Send,
{
    check_window(a)?;
    let event_loop = event_loop()?;
    let proxy: EventLoopProxy<Wake> = event_loop.create_proxy();
    let mut view = StoreView::waiting(dir, bounds, layout, a.lod.options(true)?, a.view.range);
    view.show_mode(a.view.color)?;
    let label = dir.display().to_string();
    let (ptx, prx) = std::sync::mpsc::channel();
    let (rtx, rrx) = std::sync::mpsc::channel();
    std::thread::scope(|scope| {
        let wake = proxy.clone();
        scope.spawn(move || {
            let mut report = |p: &BuildProgress| {
                let _ = ptx.send(*p);
                let _ = wake.send_event(Wake::Progress);
            };
            let r = build(&mut report);
            drop(ptx);
            let ok = r.is_ok();
            let _ = rtx.send(r);
            let _ = proxy.send_event(Wake::Done(ok));
        });
        let frames = match show(a, event_loop, Box::new(view), label, Some(BuildState::new(prx))) {
            Ok(Shown { frames, build_done }) => {
                if !build_done {
                    eprintln!("mortar build: the preview was closed; the build goes on");
                }
                frames
            }
            Err(e) => {
                // The builder never waits for the window, so a failed window does not stop it.
                eprintln!("mortar build: preview: {e:#}; the build goes on without it");
                serde_json::Value::Null
            }
        };
        let result =
            rrx.recv().map_err(|_| anyhow!("the build's thread ended without a result"))?;
        result.map(|r| (r, frames))
    })
}

/// The frame period of the off-screen preview (60 frames per second).
pub(super) const OFFSCREEN_PERIOD_MS: f64 = 1000.0 / 60.0;

/// `mortar build --preview --preview-offscreen`: the preview's frames drawn without a window,
/// paced to 60 per second, by the same store view as the window (GPU or CPU), from the fixed
/// camera of the options. Returns the build's report and the frames' statistics.
pub fn run_preview_offscreen<F>(
    a: &Args,
    dir: &std::path::Path,
    bounds: Aabb,
    layout: &RecordLayout,
    build: F,
) -> Result<(BuildReport, serde_json::Value)>
where
    F: FnOnce(&mut dyn FnMut(&BuildProgress)) -> Result<BuildReport> + Send,
{
    check_window(a)?;
    let mut view = StoreView::waiting(dir, bounds, layout, a.lod.options(true)?, a.view.range);
    view.show_mode(a.view.color)?;
    let camera = build_camera(&a.view.camera, &bounds, a.view.width, a.view.height)?;
    let options = RasterOptions { precision: a.view.precision.mode(), cull: true };
    let atomics = match a.view.atomics {
        AtomicsArg::Auto => None,
        AtomicsArg::U64 => Some(AtomicPath::U64),
        AtomicsArg::U32 => Some(AtomicPath::TwoPass32),
    };
    let ctx = match a.backend {
        ViewBackend::Cpu => None,
        ViewBackend::Gpu => Some(
            GpuContext::new(&GpuOptions { atomics, allow_software: true, ..Default::default() })
                .map_err(|e| anyhow!("--preview-backend gpu: {e}"))?,
        ),
        ViewBackend::Auto => {
            GpuContext::new(&GpuOptions { atomics, allow_software: false, ..Default::default() })
                .ok()
        }
    };
    let mut raster = match &ctx {
        Some(ctx) => {
            view.use_gpu(ctx)?;
            Some(GpuRasterizer::new(ctx, a.view.width, a.view.height)?)
        }
        None => None,
    };
    let (ptx, prx) = std::sync::mpsc::channel();
    let (rtx, rrx) = std::sync::mpsc::channel();
    let start = Instant::now();
    let (frames, result) = std::thread::scope(|scope| -> Result<_> {
        scope.spawn(move || {
            let r = build(&mut |p: &BuildProgress| {
                let _ = ptx.send(*p);
            });
            drop(ptx);
            let _ = rtx.send(r);
        });
        let mut state = BuildState::new(prx);
        let mut frames = Vec::new();
        let mut result = None;
        let mut reloaded_last = false;
        let mut next = Instant::now();
        loop {
            let t = Instant::now();
            match if result.is_some() { Err(TryRecvError::Empty) } else { rrx.try_recv() } {
                // A failed build leaves no store to draw: its error is the command's.
                Ok(r) if r.is_err() => return Ok((frames, r)),
                Ok(r) => result = Some(r),
                Err(TryRecvError::Empty) => {}
                Err(TryRecvError::Disconnected) => {
                    return Err(anyhow!("the build's thread ended without a result"))
                }
            }
            let committed = state.poll();
            let last = result.is_some();
            if committed || (last && !reloaded_last) {
                view.reload()?;
                reloaded_last = last;
            }
            let (drawn, gpu_ms) = match (&ctx, &mut raster) {
                (Some(ctx), Some(raster)) => {
                    let f =
                        view.draw_gpu(ctx, raster, &camera, &options, &a.view.resolve_options())?;
                    (f.points_drawn, f.draw_ms.map(|d| d + f.resolve_ms.unwrap_or(0.0)))
                }
                _ => view
                    .draw_cpu(&camera, &options, &a.view.resolve_options())
                    .map(|(_, n)| (n, None))?,
            };
            let frame_ms = t.elapsed().as_secs_f64() * 1e3;
            frames.push(serde_json::json!({
                "at_seconds": start.elapsed().as_secs_f64(),
                "frame_ms": frame_ms,
                "gpu_ms": gpu_ms,
                "points_drawn": drawn,
                "nodes_drawn": view.selected.nodes,
                "nodes_uploaded": view.selected.uploaded_nodes,
                "commit": view.commit(),
            }));
            // After the build, frames go on until the last commit is shown whole.
            if last && !view.busy() {
                break;
            }
            // Frames start on a 60 Hz clock (as a display's vertical sync): a frame that ran
            // late starts the next one at once and the clock restarts from there.
            next += std::time::Duration::from_secs_f64(OFFSCREEN_PERIOD_MS * 1e-3);
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            } else {
                next = now;
            }
        }
        Ok((frames, result.expect("the loop ends once the build's result arrived")))
    })?;
    let report = result?;
    let ms: Vec<f64> = frames.iter().filter_map(|f| f["frame_ms"].as_f64()).collect();
    let pick = |q: f64| mortar_core::metrics::percentile(&ms, q);
    let seconds = report.seconds.max(1e-9);
    let during =
        frames.iter().filter(|f| f["at_seconds"].as_f64().is_some_and(|t| t <= seconds)).count();
    let j = serde_json::json!({
        "offscreen": true,
        "renderer": match &ctx { Some(c) => serde_json::json!({ "backend": "gpu", "adapter": c.adapter().name }), None => serde_json::json!({ "backend": "cpu" }) },
        "width": a.view.width,
        "height": a.view.height,
        "frame_count": frames.len(),
        "frames_per_second_during_build": during as f64 / seconds,
        "frame_ms_median": pick(0.5),
        "frame_ms_p95": pick(0.95),
        "frames_over_period": ms.iter().filter(|&&m| m > OFFSCREEN_PERIOD_MS).count(),
        "frame_ms_max": pick(1.0),
        "frames": frames,
    });
    Ok((report, j))
}
