//! The options of `mortar view` ([`Args`]) and of `mortar build --preview` ([`PreviewArgs`]), and
//! the checks of the window's.

use crate::cli as common;
use crate::draw::ColorChoice;
use crate::render::{AtomicsArg, CameraArgs, PrecisionArg};
use anyhow::{bail, Result};
use std::path::PathBuf;

/// Which rasterizer draws the window's frames.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ViewBackend {
    /// The GPU rasterizer on a hardware GPU that can present to the window, else the CPU one.
    Auto,
    /// The GPU rasterizer on any adapter that can present to the window, software ones included.
    Gpu,
    /// The CPU rasterizer; frames are uploaded to the window as pixels (no GPU needed).
    Cpu,
}

/// Arguments of `mortar view`.
#[derive(clap::Args)]
pub struct Args {
    /// A batch file, an octree store (every point, no LOD yet), or LAS/LAZ files, directories,
    /// glob patterns or - (batched on the fly into a temporary batch file, as `mortar batch`
    /// would).
    #[arg(required = true)]
    pub inputs: Vec<String>,
    #[command(flatten)]
    pub view: crate::render::ViewArgs,
    /// Rasterizer: auto (a hardware GPU if one can present to the window, else cpu), gpu (any
    /// adapter, software included) or cpu.
    #[arg(long, value_enum, default_value = "auto")]
    pub backend: ViewBackend,
    /// Write what the window shows after --frames frames to this PNG and exit.
    #[arg(long, value_name = "PNG")]
    pub screenshot: Option<PathBuf>,
    /// Frames to draw before the screenshot (each a full draw, resolve and present).
    #[arg(long, value_name = "N", requires = "screenshot", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    pub frames: u32,
    /// With --screenshot: print statistics (backend, adapter, frame times) as JSON on stdout.
    #[arg(long, requires = "screenshot")]
    pub json: bool,
    /// No status line in the window (the title still shows it).
    #[arg(long)]
    pub no_status: bool,
    #[command(flatten)]
    pub sort: common::SortArgs,
    #[command(flatten)]
    pub lod: crate::render::LodArgs,
    /// Raw LAS/LAZ: batch the points into a temporary batch file first and draw every point each
    /// frame, instead of the progressive renderer (paper 000) that shows them as they load.
    #[arg(long)]
    pub no_progressive: bool,
}

/// The preview options of `mortar build`.
#[derive(clap::Args, Clone, Debug)]
pub struct PreviewArgs {
    /// Show the store in a window while it is built (orbit/pan/zoom with the mouse, F fits, C
    /// cycles colours; the status line shows the build's progress). The store is committed at
    /// least every second for it; the build never waits for the window.
    #[arg(long)]
    pub preview: bool,
    /// The preview's rasterizer: auto, gpu or cpu (as `mortar view --backend`).
    #[arg(long, value_enum, default_value = "auto", requires = "preview")]
    pub preview_backend: ViewBackend,
    /// Preview window width and height in pixels.
    #[arg(long, value_name = "WxH", default_value = "1280x720", value_parser = parse_size_wxh, requires = "preview")]
    pub preview_size: (u32, u32),
    /// With --preview: once the build is done and its last commit shown, write what the window
    /// shows to this PNG and close the window (for tests and scripted runs).
    #[arg(long, value_name = "PNG", requires = "preview")]
    pub preview_screenshot: Option<PathBuf>,
    /// With --preview: draw the preview off screen, without a window, at most 60 frames per
    /// second from the fixed camera, and report the frames in --json (for benchmarks, and for
    /// servers with a GPU but no display).
    #[arg(long, requires = "preview", conflicts_with = "preview_screenshot")]
    pub preview_offscreen: bool,
    /// The preview's hole filling (as `mortar view --hole-fill [N]`).
    #[arg(long, value_name = "N", num_args = 0..=1, default_missing_value = "3", value_parser = clap::value_parser!(u32).range(1..=8), requires = "preview")]
    pub preview_hole_fill: Option<u32>,
    /// The preview's eye-dome lighting (as `mortar view --edl [STRENGTH]`).
    #[arg(long, value_name = "STRENGTH", num_args = 0..=1, default_missing_value = "1.0", requires = "preview")]
    pub preview_edl: Option<f32>,
}

pub(super) fn parse_size_wxh(s: &str) -> std::result::Result<(u32, u32), String> {
    let bad = || format!("'{s}' is not WIDTHxHEIGHT");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    Ok((w.trim().parse().map_err(|_| bad())?, h.trim().parse().map_err(|_| bad())?))
}

impl PreviewArgs {
    /// The window's options for a preview of `store` seen from `camera`.
    pub fn view_args(&self, store: &std::path::Path, camera: &CameraArgs) -> Args {
        Args {
            inputs: vec![store.display().to_string()],
            view: crate::render::ViewArgs {
                width: self.preview_size.0,
                height: self.preview_size.1,
                camera: camera.clone(),
                color: ColorChoice::Auto,
                range: None,
                precision: PrecisionArg::Adaptive,
                atomics: AtomicsArg::Auto,
                hole_fill: self.preview_hole_fill,
                edl: self.preview_edl,
                background: 0xff00_0000,
            },
            backend: self.preview_backend,
            screenshot: self.preview_screenshot.clone(),
            frames: 1,
            json: false,
            no_status: false,
            sort: common::SortArgs::default(),
            lod: crate::render::LodArgs::default(),
            no_progressive: false,
        }
    }
}

/// Checks the window options shared by `mortar view` and `mortar build --preview`.
pub(super) fn check_window(a: &Args) -> Result<()> {
    if a.view.width == 0 || a.view.height == 0 || a.view.width > 16384 || a.view.height > 16384 {
        bail!(
            "--width {} --height {}: each side must be 1 to 16384 pixels",
            a.view.width,
            a.view.height
        );
    }
    if !(a.view.camera.fov > 0.0 && a.view.camera.fov < 180.0) {
        bail!("--fov {}: must be between 0 and 180 degrees", a.view.camera.fov);
    }
    Ok(())
}
