//! `mortar-bench-lod`: time against image error of LOD rendering of an octree store (paper 004
//! §6) with the CPU rasterizer. For each view and LOD threshold it selects the nodes, draws them
//! (adaptive precision, culling) and reports the median selection, preparation and raster times
//! of several runs, the samples drawn, and the error against the full-detail render of the same
//! view (threshold 0: every visible leaf): pixels whose colour differs, coverage change and PSNR
//! of the stored colours. Writes a markdown table to stdout (and `--out DIR`), with `--images`
//! every render too.

use crate::draw;
use crate::draw::{ColorChoice, RenderSettings};
use anyhow::{bail, Context, Result};
use clap::Parser;
use mortar_core::metrics::{median, psnr};
use mortar_core::octree::{LodOptions, NodeId};
use mortar_core::render::framebuffer::{key_index, EMPTY_KEY};
use mortar_core::render::{
    rasterize, Camera, Framebuffer, PrecisionMode, RasterOptions, RasterStats, ViewPreset,
};
use mortar_io::batch_input::{self, RenderSource};
use mortar_io::store::StoreLod;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Parser)]
#[command(
    name = "mortar-bench-lod",
    about = "LOD rendering of a store: selection and raster time against image error, per threshold"
)]
pub struct Args {
    /// An octree store (made by `mortar build`).
    store: PathBuf,
    /// Views: iso, top, front, side, closeup, inside.
    #[arg(long, value_delimiter = ',', default_value = "iso,closeup,inside")]
    views: Vec<String>,
    /// LOD thresholds in pixels (0: full detail).
    #[arg(long, value_delimiter = ',', default_value = "0,32,64,128,256,512")]
    thresholds: Vec<f64>,
    /// Also draw this batch file of the same points (`mortar batch store/ -o FILE`) in every view,
    /// interleaved with the LOD renders: the brute-force render without a store.
    #[arg(long)]
    batch_file: Option<PathBuf>,
    /// Point budget for every threshold (none by default).
    #[arg(long)]
    point_budget: Option<u64>,
    /// Image width.
    #[arg(long, default_value_t = 1920)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 1080)]
    height: u32,
    /// Timed runs per configuration (the median is reported), after one untimed warm-up run.
    #[arg(long, default_value_t = 5)]
    runs: usize,
    /// Name of the dataset in the table (default: the store's directory name).
    #[arg(long)]
    label: Option<String>,
    /// Directory for `<label>-lod.md` and, with --images, the renders.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Also write every render to --out.
    #[arg(long)]
    images: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
}

fn camera(view: &str, lod: &StoreLod, w: u32, h: u32) -> Result<Camera> {
    let b = lod.bounds();
    let fov = 50f64.to_radians();
    let preset = |p| Camera::frame_perspective(&b, p, fov, w, h);
    Ok(match view {
        "iso" => preset(ViewPreset::Iso)?,
        "top" => preset(ViewPreset::Top)?,
        "front" => preset(ViewPreset::Front)?,
        "side" => preset(ViewPreset::Side)?,
        "closeup" => Camera::close_up(&b, fov, w, h)?,
        "inside" => Camera::inside(&b, fov, w, h)?,
        v => bail!("--views: '{v}' is not a view (iso, top, front, side, closeup, inside)"),
    })
}

/// One measured configuration.
struct Row {
    threshold: f64,
    nodes: u64,
    points: u64,
    voxels: u64,
    budget_reached: bool,
    select: Vec<f64>,
    prepare: Vec<f64>,
    raster: Vec<f64>,
    stats: RasterStats,
    keys: Vec<u64>,
    rgba: Vec<u32>,
}

/// Runs the benchmark the arguments describe.
pub fn run(a: Args) -> Result<()> {
    if let Some(t) = a.threads {
        rayon::ThreadPoolBuilder::new().num_threads(t.max(1)).build_global()?;
    }
    if a.thresholds.iter().any(|t| t.is_nan() || *t < 0.0) {
        bail!("--thresholds: every threshold must be 0 or more pixels");
    }
    let t = Instant::now();
    let lod = StoreLod::open(&a.store)?;
    let open_ms = t.elapsed().as_secs_f64() * 1e3;
    if lod.point_count() == 0 {
        bail!("{}: no points to draw", a.store.display());
    }
    let label = a.label.clone().unwrap_or_else(|| {
        a.store
            .file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "store".into())
    });
    let leaves = lod.store().leaves().len();
    // Every node's bounds once (what the first render of each node pays).
    let all: Vec<NodeId> = (0..lod.store().entries.len() as u32).map(NodeId).collect();
    let t = Instant::now();
    lod.batches(&all)?;
    let scan_ms = t.elapsed().as_secs_f64() * 1e3;
    let settings = RenderSettings::default();
    let source = match &a.batch_file {
        Some(p) => Some(RenderSource::open_batch_file(p)?),
        None => None,
    };
    let words = match &source {
        Some(s) => batch_input::load_words(&s.file)?,
        None => Vec::new(),
    };
    let file_refs = match &source {
        Some(s) => batch_input::batch_refs(&s.file, &words)?,
        None => Vec::new(),
    };
    if let Some(s) = &source {
        if s.file.header.point_count != lod.point_count() {
            bail!(
                "--batch-file {}: {} points, the store has {}",
                s.name.display(),
                s.file.header.point_count,
                lod.point_count()
            );
        }
    }
    let mut md = String::new();
    writeln!(
        md,
        "### {label}: {} points, {} nodes ({leaves} leaves), {}x{}, {} threads, median of {} runs\n\nStore opened (hierarchy read, tree checked) in {open_ms:.1} ms; the first use of every node's payload (a scan of its coarse words for its bounds, cached) took {scan_ms:.1} ms for all nodes.\n",
        lod.point_count(),
        lod.store().entries.len(),
        a.width,
        a.height,
        rayon::current_num_threads(),
        a.runs,
    )?;
    writeln!(md, "Every render uses adaptive precision and culling. Error is against the full-detail render of the same view (threshold 0: every visible leaf); `colour %` counts pixels whose colour differs, `coverage Δ %` the net change of covered pixels, both as a share of the pixels covered at threshold 0. `select` is the node selection, `prepare` making the selected nodes' batches (borrowed from the map), `raster` the CPU rasterizer; `speed-up` is threshold 0's select + prepare + raster time over this row's. The `batch file` row (with --batch-file) draws a batch file of the same points without a store (the brute-force render; `points` are those of the batches not culled), and its `colour %` counts pixels won by another point (compared by position, since a batch file and a store may map intensity to grey over different ranges): points that tie in depth, and points that adaptive precision rounds differently in the two (other batches, other quantization frames).\n")?;
    writeln!(md, "| view | threshold px | budget | nodes | points + voxels drawn | samples vs full | select ms | prepare ms | raster ms (min-max) | speed-up | colour % | coverage Δ % | PSNR dB |")?;
    writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|---|---|")?;
    for view in &a.views {
        let cam = camera(view, &lod, a.width, a.height)?;
        // The reference (threshold 0, no budget) first, then every threshold, then the batch
        // file (a NaN threshold).
        let mut configs = vec![(0.0, None)];
        configs.extend(
            a.thresholds.iter().map(|&t| (t, a.point_budget)).filter(|&c| c != (0.0, None)),
        );
        if source.is_some() {
            configs.push((f64::NAN, None));
        }
        let opts = RasterOptions { precision: PrecisionMode::Adaptive, cull: true };
        let mut rows: Vec<Row> = Vec::new();
        for &(threshold, point_budget) in &configs {
            if let (true, Some(src)) = (threshold.is_nan(), &source) {
                let fb = Framebuffer::new(cam.width, cam.height);
                let stats = rasterize(&fb, &file_refs, &src.file.grid(), &cam, &opts)?;
                let r = draw::batch::resolve_keys(
                    &src.file,
                    fb.into_keys(),
                    stats,
                    0.0,
                    &cam,
                    &RenderSettings { color: ColorChoice::Stored, ..settings },
                )?;
                rows.push(Row {
                    threshold,
                    nodes: 0,
                    points: stats.points_projected(),
                    voxels: 0,
                    budget_reached: false,
                    select: vec![0.0],
                    prepare: vec![0.0],
                    raster: Vec::with_capacity(a.runs),
                    stats,
                    keys: r.keys,
                    rgba: r.rgba,
                });
                continue;
            }
            let options = LodOptions { threshold_px: threshold, point_budget, cull: true };
            let sel = lod.select(&cam, &options)?;
            let batches = lod.batches(&sel.nodes)?;
            let fb = Framebuffer::new(cam.width, cam.height);
            let stats = rasterize(&fb, &batches.refs, &lod.grid(), &cam, &opts)?;
            let keys = fb.into_keys();
            let r = draw::lod::resolve_keys(&lod, &batches, keys, stats, 0.0, &cam, &settings)?;
            rows.push(Row {
                threshold,
                nodes: sel.stats.selected,
                points: sel.stats.points,
                voxels: sel.stats.voxels,
                budget_reached: sel.stats.budget_reached,
                select: Vec::with_capacity(a.runs),
                prepare: Vec::with_capacity(a.runs),
                raster: Vec::with_capacity(a.runs),
                stats,
                keys: r.keys,
                rgba: r.rgba,
            });
        }
        // Timed rounds, interleaved over the configurations (load from other processes on a
        // shared machine spreads over all of them alike).
        let mut fb = Framebuffer::new(cam.width, cam.height);
        for _ in 0..a.runs.max(1) {
            for (row, &(threshold, point_budget)) in rows.iter_mut().zip(&configs) {
                if let (true, Some(src)) = (threshold.is_nan(), &source) {
                    fb.clear();
                    let t = Instant::now();
                    let stats = rasterize(&fb, &file_refs, &src.file.grid(), &cam, &opts)?;
                    row.raster.push(t.elapsed().as_secs_f64());
                    if stats != row.stats {
                        bail!("{view}: the batch file drew differently in two runs");
                    }
                    continue;
                }
                let options = LodOptions { threshold_px: threshold, point_budget, cull: true };
                let t = Instant::now();
                let sel = lod.select(&cam, &options)?;
                row.select.push(t.elapsed().as_secs_f64());
                let t = Instant::now();
                let batches = lod.batches(&sel.nodes)?;
                row.prepare.push(t.elapsed().as_secs_f64());
                fb.clear();
                let t = Instant::now();
                let stats = rasterize(&fb, &batches.refs, &lod.grid(), &cam, &opts)?;
                row.raster.push(t.elapsed().as_secs_f64());
                if stats != row.stats {
                    bail!("{view}: threshold {threshold} drew differently in two runs");
                }
            }
        }
        let reference = &rows[0];
        let covered = reference.keys.iter().filter(|&&k| k != EMPTY_KEY).count() as u64;
        let full_samples = reference.points + reference.voxels;
        let total = |r: &Row| median(&r.select) + median(&r.prepare) + median(&r.raster);
        let full_time = total(reference);
        let reference_batches = lod.batches(
            &lod.select(&cam, &LodOptions { threshold_px: 0.0, point_budget: None, cull: true })?
                .nodes,
        )?;
        for (k, r) in rows.iter().enumerate() {
            let colour = if r.threshold.is_nan() {
                // Pixels won by another point (positions compared; the colours of a batch file
                // and a store may come from different intensity ranges).
                let position = |index: u32| {
                    let b = file_refs.partition_point(|f| f.first_index <= index) - 1;
                    let f = &file_refs[b];
                    let i = (index - f.first_index) as usize;
                    f.grid.decode_exact([f.words[0][i], f.words[1][i], f.words[2][i]])
                };
                r.keys
                    .iter()
                    .zip(&reference.keys)
                    .filter(|(&x, &y)| match (x == EMPTY_KEY, y == EMPTY_KEY) {
                        (true, true) => false,
                        (false, false) => {
                            Some(position(key_index(x))) != reference_batches.position(key_index(y))
                        }
                        _ => true,
                    })
                    .count() as u64
            } else {
                r.rgba.iter().zip(&reference.rgba).filter(|(x, y)| x != y).count() as u64
            };
            let mine = r.keys.iter().filter(|&&k| k != EMPTY_KEY).count() as u64;
            let pct = |v: f64| 100.0 * v / covered.max(1) as f64;
            let (min, max) = (
                r.raster.iter().copied().fold(f64::INFINITY, f64::min),
                r.raster.iter().copied().fold(0.0, f64::max),
            );
            let p = if r.threshold.is_nan() { f64::NAN } else { psnr(&r.rgba, &reference.rgba) };
            let samples = r.points + r.voxels;
            let name = if k == 0 {
                "0 (reference)".to_string()
            } else if r.threshold.is_nan() {
                "batch file".to_string()
            } else {
                format!("{}", r.threshold)
            };
            let budget = match configs[k].1 {
                Some(b) => format!("{b}{}", if r.budget_reached { " (reached)" } else { "" }),
                None => "-".into(),
            };
            writeln!(
                md,
                "| {view} | {name} | {budget} | {} | {} + {} | {:.3} | {:.2} | {:.2} | {:.1} ({:.1}-{:.1}) | {:.2}x | {:.3} | {:+.3} | {} |",
                if r.threshold.is_nan() { format!("{} batches", r.stats.batches) } else { r.nodes.to_string() },
                r.points,
                r.voxels,
                samples as f64 / full_samples.max(1) as f64,
                median(&r.select) * 1e3,
                median(&r.prepare) * 1e3,
                median(&r.raster) * 1e3,
                min * 1e3,
                max * 1e3,
                full_time / total(r),
                pct(colour as f64),
                pct(mine as f64 - covered as f64),
                if p.is_nan() {
                    "-".into()
                } else if p.is_finite() {
                    format!("{p:.1}")
                } else {
                    "inf".into()
                },
            )?;
            if a.images {
                if let Some(dir) = &a.out {
                    std::fs::create_dir_all(dir).with_context(|| dir.display().to_string())?;
                    let tag = if k == 0 {
                        "ref".to_string()
                    } else if r.threshold.is_nan() {
                        "batch-file".to_string()
                    } else {
                        format!("{}", r.threshold)
                    };
                    write_png(
                        &dir.join(format!("{label}-{view}-{tag}.png")),
                        a.width,
                        a.height,
                        &r.rgba,
                    )?;
                }
            }
        }
    }
    print!("{md}");
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).with_context(|| dir.display().to_string())?;
        std::fs::write(dir.join(format!("{label}-lod.md")), md.as_bytes())
            .with_context(|| dir.display().to_string())?;
    }
    Ok(())
}

/// Writes an RGBA8 image (packed `r | g << 8 | b << 16 | a << 24`) as PNG.
fn write_png(path: &std::path::Path, width: u32, height: u32, rgba: &[u32]) -> Result<()> {
    let f = std::fs::File::create(path).with_context(|| path.display().to_string())?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(f), width, height);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header()?;
    let bytes: Vec<u8> = rgba.iter().flat_map(|c| c.to_le_bytes()).collect();
    w.write_image_data(&bytes)?;
    w.finish()?;
    Ok(())
}
