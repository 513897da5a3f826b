//! Headless live preview of `mortar build` (issue 6 item 2): `--frames DIR --every SECONDS`
//! writes PNG frames of the growing store, as committed, from a fixed camera (the `render`
//! camera options) or a scripted one (`--orbit`: degrees of turn about the vertical axis per
//! frame), and at the end `contact-sheet.png`, the frames in one grid.
//!
//! A frame is drawn from the last commit on disk (the store is readable while it grows) with the
//! LOD selection of paper 004 §6 and the CPU rasterizer, on the build's thread: the build waits
//! while a frame is drawn (measured: `frame_seconds` in `--json`). Every frame uses one camera
//! framing the bounds the headers declare, so frames of one build line up.

use crate::draw;
use crate::draw::RenderSettings;
use crate::render::{build_camera, encode_png, write_atomic, CameraArgs};
use anyhow::{bail, Context, Result};
use mortar_core::octree::LodOptions;
use mortar_core::render::{Aabb, Camera};
use mortar_io::dataset::Dataset;
use mortar_io::store::StoreLod;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The frame options of `mortar build`.
#[derive(clap::Args, Clone, Debug)]
pub struct FramesArgs {
    /// Write PNG frames of the growing store into this directory (created if missing; frames
    /// are `frame-0001.png`, ...) and `contact-sheet.png` at the end.
    #[arg(long)]
    pub frames: Option<PathBuf>,
    /// Seconds between frames (the store is then committed at least this often).
    #[arg(long, default_value_t = 2.0, requires = "frames")]
    pub every: f64,
    /// Frame width in pixels.
    #[arg(long, default_value_t = 640, requires = "frames")]
    pub frame_width: u32,
    /// Frame height in pixels.
    #[arg(long, default_value_t = 360, requires = "frames")]
    pub frame_height: u32,
    /// Scripted camera: degrees to turn about the vertical axis through the target per frame.
    #[arg(long, default_value_t = 0.0, requires = "frames", allow_hyphen_values = true)]
    pub orbit: f64,
    /// LOD threshold of the frames in pixels (paper 004 §6; 0 draws every leaf).
    #[arg(long, default_value_t = mortar_core::octree::DEFAULT_THRESHOLD_PX, requires = "frames")]
    pub frame_lod_threshold: f64,
    /// Rasterizer of the frames: cpu (the default), gpu (any adapter, a CPU Vulkan included) or
    /// auto (a hardware GPU if there is one, else cpu). The images are the same.
    #[arg(long, value_enum, default_value = "cpu", requires = "frames")]
    pub frame_backend: crate::render::Backend,
    #[command(flatten)]
    pub camera: CameraArgs,
}

/// One written frame.
#[derive(Clone, Debug)]
pub struct FrameInfo {
    pub file: PathBuf,
    /// Seconds since the build started.
    pub at_seconds: f64,
    /// Store commit drawn.
    pub commit: u64,
    /// Points in that commit.
    pub points: u64,
    /// Samples (points + voxels) drawn.
    pub samples: u64,
    /// Seconds to open, select, draw and write the frame.
    pub frame_seconds: f64,
}

/// Writes the frames of one build.
pub struct FrameRecorder {
    dir: PathBuf,
    store: PathBuf,
    every: f64,
    orbit: f64,
    lod: LodOptions,
    camera: Camera,
    start: Instant,
    last: Option<Instant>,
    last_commit: u64,
    /// The GPU drawing the frames (`None`: the CPU rasterizer).
    gpu: Option<mortar_render::GpuContext>,
    pub frames: Vec<FrameInfo>,
    thumbs: Vec<(u32, u32, Vec<u32>)>,
}

/// World bounds of the points as the headers declare them.
pub fn header_bounds(ds: &Dataset) -> Aabb {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for s in ds.inputs.iter().filter(|s| s.point_count() > 0) {
        let h = s.header();
        for a in 0..3 {
            lo[a] = lo[a].min(h.min[a]);
            hi[a] = hi[a].max(h.max[a]);
        }
    }
    if lo.iter().zip(&hi).any(|(l, h)| !(l.is_finite() && h.is_finite() && l <= h)) {
        (lo, hi) = ([0.0; 3], [1.0; 3]);
    }
    Aabb::new(lo, hi)
}

impl FrameRecorder {
    /// A recorder for the build of `ds` into `store`, or `None` without `--frames`.
    pub fn new(a: &FramesArgs, ds: &Dataset, store: &Path) -> Result<Option<FrameRecorder>> {
        let Some(dir) = &a.frames else { return Ok(None) };
        if !(a.every >= 0.0 && a.every.is_finite()) {
            bail!("--every {}: must be a number of seconds, 0 or more", a.every);
        }
        if a.frame_width == 0
            || a.frame_height == 0
            || a.frame_width > 8192
            || a.frame_height > 8192
        {
            bail!(
                "--frame-width/--frame-height {}x{}: must be 1 to 8192 pixels",
                a.frame_width,
                a.frame_height
            );
        }
        if !(a.frame_lod_threshold >= 0.0) || !a.orbit.is_finite() {
            bail!("--frame-lod-threshold must be 0 or more and --orbit a number of degrees");
        }
        std::fs::create_dir_all(dir)
            .with_context(|| format!("{}: cannot create the frames directory", dir.display()))?;
        let camera = build_camera(&a.camera, &header_bounds(ds), a.frame_width, a.frame_height)?;
        let gpu = match a.frame_backend {
            crate::render::Backend::Cpu => None,
            crate::render::Backend::Gpu => Some(
                mortar_render::GpuContext::new(&mortar_render::GpuOptions {
                    allow_software: true,
                    ..Default::default()
                })
                .map_err(|e| anyhow::anyhow!("--frame-backend gpu: {e}"))?,
            ),
            crate::render::Backend::Auto => {
                mortar_render::GpuContext::new(&mortar_render::GpuOptions::default()).ok()
            }
        };
        Ok(Some(FrameRecorder {
            dir: dir.clone(),
            store: store.to_path_buf(),
            every: a.every,
            orbit: a.orbit,
            lod: LodOptions { threshold_px: a.frame_lod_threshold, ..LodOptions::default() },
            camera,
            start: Instant::now(),
            last: None,
            last_commit: 0,
            gpu,
            frames: Vec::new(),
            thumbs: Vec::new(),
        }))
    }

    /// Seconds the store must be committed within for the frames.
    pub fn every(&self) -> f64 {
        self.every
    }

    /// The camera of frame `k`: the base camera turned `k * orbit` degrees about the vertical
    /// axis through its target.
    fn camera(&self, k: usize) -> Result<Camera> {
        let c = &self.camera;
        if self.orbit == 0.0 {
            return Ok(*c);
        }
        let t = (k as f64 * self.orbit).to_radians();
        let (s, co) = t.sin_cos();
        let d = [c.eye[0] - c.target[0], c.eye[1] - c.target[1]];
        let eye =
            [c.target[0] + co * d[0] - s * d[1], c.target[1] + s * d[0] + co * d[1], c.eye[2]];
        // The distance to the target and so the clip planes stay the same.
        Ok(Camera { eye, ..*c })
    }

    /// After a commit (`commits` so far): draws a frame if the store has a new commit and
    /// `--every` seconds have passed since the last frame (always with `force`, for the last).
    pub fn on_commit(&mut self, commits: u64, force: bool) -> Result<()> {
        if commits == 0 || commits == self.last_commit {
            return Ok(());
        }
        if !force && self.last.is_some_and(|t| t.elapsed().as_secs_f64() < self.every) {
            return Ok(());
        }
        let t0 = Instant::now();
        let lod = StoreLod::open(&self.store)?;
        let camera = self.camera(self.frames.len())?;
        let sel = lod.select(&camera, &self.lod)?;
        let batches = lod.batches(&sel.nodes)?;
        let settings = RenderSettings::default();
        let img = match &self.gpu {
            Some(ctx) => {
                crate::render::lod::render_gpu(ctx, &lod, &batches, &camera, &settings)
                    .map_err(|e| anyhow::anyhow!("{}: GPU: {e}", self.store.display()))?
                    .0?
            }
            None => draw::lod::render(&lod, &batches, &camera, &settings)?,
        };
        let file = self.dir.join(format!("frame-{:04}.png", self.frames.len() + 1));
        write_atomic(&file, &encode_png(img.width, img.height, &img.rgba)?)?;
        // Only the thumbnail stays in memory (a long build's frames would not fit in --memory).
        self.thumbs.push(thumbnail(img.width, img.height, &img.rgba));
        self.frames.push(FrameInfo {
            file,
            at_seconds: self.start.elapsed().as_secs_f64(),
            commit: lod.store().header.commit,
            points: lod.point_count(),
            samples: sel.stats.samples(),
            frame_seconds: t0.elapsed().as_secs_f64(),
        });
        self.last = Some(Instant::now());
        self.last_commit = commits;
        Ok(())
    }

    /// Writes `contact-sheet.png`: the frames in a grid of about 4:3 cells, each scaled down to
    /// at most 480 pixels wide (box filter), in order, on a dark background. Returns its path.
    pub fn finish(&mut self) -> Result<PathBuf> {
        let n = self.thumbs.len();
        let path = self.dir.join("contact-sheet.png");
        if n == 0 {
            bail!("{}: no frame was drawn", self.dir.display());
        }
        let (tw, th) = (self.thumbs[0].0, self.thumbs[0].1);
        let cols = (n as f64).sqrt().ceil() as u32;
        let rows = (n as u32).div_ceil(cols);
        let gap = 4;
        let (sw, sh) = (cols * (tw + gap) + gap, rows * (th + gap) + gap);
        let mut sheet = vec![0xff20_2020u32; (sw * sh) as usize];
        for (k, (_, _, thumb)) in self.thumbs.iter().enumerate() {
            let (cx, cy) =
                ((k as u32 % cols) * (tw + gap) + gap, (k as u32 / cols) * (th + gap) + gap);
            for y in 0..th {
                let row = (y * tw) as usize;
                let at = ((cy + y) * sw + cx) as usize;
                sheet[at..at + tw as usize].copy_from_slice(&thumb[row..row + tw as usize]);
            }
        }
        write_atomic(&path, &encode_png(sw, sh, &sheet)?)?;
        self.thumbs.clear();
        Ok(path)
    }
}

/// A frame scaled down to at most 480 pixels wide by an integer factor (box filter, rounded).
fn thumbnail(w: u32, h: u32, rgba: &[u32]) -> (u32, u32, Vec<u32>) {
    let f = w.div_ceil(480).max(1);
    let (tw, th) = (w / f, h / f);
    let mut out = Vec::with_capacity((tw * th) as usize);
    for y in 0..th {
        for x in 0..tw {
            let mut acc = [0u32; 4];
            for dy in 0..f {
                for dx in 0..f {
                    let c = rgba[((y * f + dy) * w + x * f + dx) as usize];
                    for (i, v) in acc.iter_mut().enumerate() {
                        *v += (c >> (8 * i)) & 0xff;
                    }
                }
            }
            let m = f * f;
            out.push((0..4).fold(0u32, |p, i| p | ((acc[i] + m / 2) / m) << (8 * i)));
        }
    }
    (tw, th, out)
}

/// The `frames` object of `mortar build --json`.
pub fn frames_json(r: &FrameRecorder, sheet: &Path) -> serde_json::Value {
    let secs: Vec<f64> = r.frames.iter().map(|f| f.frame_seconds).collect();
    serde_json::json!({
        "dir": r.dir,
        "count": r.frames.len(),
        "contact_sheet": sheet,
        "frame_seconds_total": secs.iter().sum::<f64>(),
        "frame_seconds_max": secs.iter().cloned().fold(0.0, f64::max),
        "frames": r.frames.iter().map(|f| serde_json::json!({
            "file": f.file,
            "at_seconds": f.at_seconds,
            "commit": f.commit,
            "points": f.points,
            "samples": f.samples,
            "frame_seconds": f.frame_seconds,
        })).collect::<Vec<_>>(),
    })
}
