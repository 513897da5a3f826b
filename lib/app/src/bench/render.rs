//! `mortar-bench-render`: run time against image error of the CPU reference rasterizer (paper 003
//! §3.3, adaptive precision; §3.2, culling). For each view it draws the input with precision
//! adaptive, 10, 20 and 30 bits, each with culling on and off, and reports the median raster time
//! of several runs, the points drawn, and the error against the brute-force render (30 bits, no
//! culling) of the same view: pixels whose winning point differs, pixels whose colour differs,
//! coverage differences and PSNR. Writes a markdown table (stdout, and `--out DIR`) and a plot of
//! time against error per view (PNG, drawn here with a built-in bitmap font).

use crate::cli as common;
use crate::draw;
use crate::draw::ColorChoice;
use crate::render;
use crate::render::{CameraArgs, PrecisionArg, ViewArg};
use anyhow::{bail, Result};
use clap::Parser;
use mortar_core::grid::Grid;
use mortar_core::metrics::{median, psnr};
use mortar_core::quantize::Precision;
use mortar_core::render::framebuffer::{key_index, EMPTY_KEY};
use mortar_core::render::precision::{
    choose_precision, decode_error_px, quantization_box, sufficient_precision,
};
use mortar_core::render::resolve::{resolve, ResolveOptions};
use mortar_core::render::{
    precision_for_pixels, rasterize, BatchRef, Camera, Framebuffer, PrecisionMode, RasterOptions,
    RasterStats,
};
use mortar_io::batch_input;
use mortar_io::batchfile::BatchFile;
use rayon::prelude::*;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Parser)]
#[command(
    name = "mortar-bench-render",
    about = "Raster time against image error: precision adaptive/10/20/30, culling on/off"
)]
pub struct Args {
    /// A batch file, or LAS/LAZ (batched into a temporary batch file first).
    #[arg(required = true)]
    inputs: Vec<String>,
    /// Views to measure.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "iso,closeup,inside")]
    views: Vec<ViewArg>,
    /// Image width.
    #[arg(long, default_value_t = 1920)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 1080)]
    height: u32,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 50.0)]
    fov: f64,
    /// Timed runs per configuration (the median is reported), after one untimed warm-up run.
    #[arg(long, default_value_t = 5)]
    runs: usize,
    /// Colour mode for the colour error (see `mortar render --color`).
    #[arg(long, default_value = "auto")]
    color: String,
    /// Name of the dataset in the table and the file names (default: the input's file stem).
    #[arg(long)]
    label: Option<String>,
    /// Directory for `<label>.md`, `<label>-<view>.png` plots and, with --images, the renders.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Also write every configuration's image to --out.
    #[arg(long)]
    images: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Measure the adaptive rule against the plain 500 px rule (which `adaptive` was before the
    /// decode-error bound): configurations 30 bits (with and without culling), the 500 px rule and
    /// adaptive, plus a per-batch report of the N batches that lose most pixels under the 500 px
    /// rule (projected size, precision, error bound and measured error in pixels against the exact
    /// positions).
    #[arg(long, value_name = "N")]
    rule_report: Option<usize>,
    /// With --rule-report, also the 500 px rule raised to keep the decode error bound under each of
    /// these pixel budgets (emulated like the 500 px rule).
    #[arg(long, value_delimiter = ',')]
    budgets: Vec<f64>,
}

/// One configuration: a rasterizer option, or the 500 px rule alone (emulated with fixed
/// precisions per batch group, which draws the very keys the rule drew).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Config {
    Options(PrecisionArg, bool),
    /// The 500 px rule, then raised while the decode error bound reaches this many pixels
    /// (infinite: the 500 px rule alone).
    Budget(f64),
}

const RULE500: Config = Config::Budget(f64::INFINITY);

impl Config {
    fn name(self) -> String {
        match self {
            Config::Options(p, _) => p.name().to_string(),
            Config::Budget(b) if b.is_infinite() => "500px rule".to_string(),
            Config::Budget(b) => format!("error < {b} px"),
        }
    }
    fn cull(self) -> bool {
        match self {
            Config::Options(_, c) => c,
            Config::Budget(_) => true,
        }
    }
}

/// One measured configuration.
struct Row {
    config: Config,
    /// Median, min and max raster seconds.
    median: f64,
    min: f64,
    max: f64,
    stats: RasterStats,
    /// Pixels whose winning point differs from the reference (covered in either).
    winner_diff: u64,
    /// Pixels covered in exactly one of the two.
    coverage_diff: u64,
    /// Pixels whose colour differs.
    color_diff: u64,
    /// PSNR of the RGB image against the reference, dB (infinite when identical).
    psnr: f64,
    /// Pixels covered in the reference.
    covered: u64,
    /// Pixels covered in this render.
    covered_self: u64,
}

/// Per configuration: the keys of its last run, its stats and its raster times.
type Measured = Vec<(Vec<u64>, RasterStats, Vec<f64>)>;

/// The brute-force render: keys, image and the colour range it used.
type Reference = (Vec<u64>, Vec<u32>, Option<[f64; 2]>);

/// The batches of a view grouped by the precision the 500 px rule gives them, raised while the
/// decode error bound reaches `budget` pixels.
fn budget_groups<'a>(
    refs: &[BatchRef<'a>],
    grid: &Grid,
    cam: &Camera,
    budget: f64,
) -> [(Precision, Vec<BatchRef<'a>>); 3] {
    let mut g = [
        (Precision::Bits10, Vec::new()),
        (Precision::Bits20, Vec::new()),
        (Precision::Bits30, Vec::new()),
    ];
    for b in refs {
        let p = budget_precision(cam, grid, b, budget);
        g[p.words() - 1].1.push(*b);
    }
    g
}

/// The precision of the plain 500 px rule (the adaptive rule before the decode-error bound),
/// raised while the decode error bound reaches `budget` pixels.
fn budget_precision(cam: &Camera, grid: &Grid, b: &BatchRef<'_>, budget: f64) -> Precision {
    let enough = sufficient_precision(&b.grid);
    let mut p =
        precision_for_pixels(cam.projected_size(&quantization_box(grid, &b.grid))).min(enough);
    while budget.is_finite()
        && p < enough
        && decode_error_px(cam, grid, &b.grid, &b.bounds(), p) >= budget
    {
        p = if p == Precision::Bits10 { Precision::Bits20 } else { Precision::Bits30 };
    }
    p
}

/// Draws one configuration into `fb`.
fn draw(
    fb: &Framebuffer,
    refs: &[BatchRef<'_>],
    groups: Option<&[(Precision, Vec<BatchRef<'_>>); 3]>,
    grid: &Grid,
    cam: &Camera,
    cfg: Config,
) -> Result<RasterStats> {
    Ok(match (cfg, groups) {
        (Config::Options(p, cull), _) => {
            rasterize(fb, refs, grid, cam, &RasterOptions { precision: p.mode(), cull })?
        }
        (Config::Budget(_), None) => unreachable!("budget configurations come with their groups"),
        (Config::Budget(_), Some(groups)) => {
            let mut s = RasterStats::default();
            for (p, g) in groups {
                s = s.merge(rasterize(
                    fb,
                    g,
                    grid,
                    cam,
                    &RasterOptions { precision: PrecisionMode::Fixed(*p), cull: true },
                )?);
            }
            s
        }
    })
}

/// Draws every configuration once untimed, then `runs` rounds in which each configuration draws
/// once into its cleared framebuffer (interleaved, so that load from other processes on a shared
/// machine spreads over all configurations alike). Returns per configuration the keys of its last
/// run, its stats and its times.
fn measure(
    refs: &[BatchRef<'_>],
    file: &BatchFile,
    cam: &Camera,
    configs: &[Config],
    runs: usize,
) -> Result<Measured> {
    let grid = file.grid();
    let groups: Vec<_> = configs
        .iter()
        .map(|c| match c {
            Config::Budget(b) => Some(budget_groups(refs, &grid, cam, *b)),
            Config::Options(..) => None,
        })
        .collect();
    let mut fbs: Vec<Framebuffer> =
        configs.iter().map(|_| Framebuffer::new(cam.width, cam.height)).collect();
    let mut out: Vec<(RasterStats, Vec<f64>)> = Vec::with_capacity(configs.len());
    for ((fb, &cfg), g) in fbs.iter().zip(configs).zip(&groups) {
        out.push((draw(fb, refs, g.as_ref(), &grid, cam, cfg)?, Vec::with_capacity(runs)));
    }
    for _ in 0..runs.max(1) {
        for (((fb, &cfg), (stats, times)), g) in
            fbs.iter_mut().zip(configs).zip(out.iter_mut()).zip(&groups)
        {
            fb.clear();
            let t = Instant::now();
            *stats = draw(fb, refs, g.as_ref(), &grid, cam, cfg)?;
            times.push(t.elapsed().as_secs_f64());
        }
    }
    Ok(fbs
        .into_iter()
        .zip(out)
        .map(|(fb, (stats, times))| (fb.into_keys(), stats, times))
        .collect())
}

fn colorize(
    file: &BatchFile,
    keys: &[u64],
    cam: &Camera,
    color: ColorChoice,
    range: Option<[f64; 2]>,
) -> Result<(Vec<u32>, Option<[f64; 2]>)> {
    let colors = draw::batch::colors_for_keys(file, keys, color, range)?;
    let opts = ResolveOptions::default();
    let bg = opts.background;
    Ok((resolve(keys, cam.width, cam.height, |i| colors.get(i).unwrap_or(bg), &opts), colors.range))
}

/// Runs the benchmark the arguments describe.
pub fn run(a: Args) -> Result<()> {
    if let Some(t) = a.threads {
        rayon::ThreadPoolBuilder::new().num_threads(t.max(1)).build_global()?;
    }
    let Some(color) = ColorChoice::from_name(&a.color) else {
        bail!(
            "--color {}: not a colour mode (one of {})",
            a.color,
            ColorChoice::names().join(", ")
        );
    };
    let (source, bounds) = render::open_source(&a.inputs, &common::SortArgs::default(), None)?;
    let file = &source.file;
    if file.header.point_count == 0 {
        bail!("{}: no points to draw", a.inputs.join(" "));
    }
    draw::batch::check_color(file, color)?;
    let label = a.label.clone().unwrap_or_else(|| {
        PathBuf::from(&a.inputs[0])
            .file_stem()
            .map(|s| s.to_string_lossy().split('.').next().unwrap_or("input").to_string())
            .unwrap_or_else(|| "input".into())
    });
    let views = batch_input::load_words(file)?;
    let refs = batch_input::batch_refs(file, &views)?;
    let threads = rayon::current_num_threads();
    let mut md = String::new();
    writeln!(
        md,
        "### {label}: {} points, {} batches, {}x{}, {} threads, median of {} runs\n",
        file.header.point_count,
        file.batch_count(),
        a.width,
        a.height,
        threads,
        a.runs
    )?;
    writeln!(md, "Error is against the brute-force render (30 bits, no culling) of the same view; `winner` counts pixels whose nearest point is another point, `colour` pixels whose colour differs, `coverage` pixels empty in one image and not the other, all as a share of the pixels covered in the reference; `covered Δ` is the net change of covered pixels (negative: holes opened).\n")?;
    writeln!(md, "| view | precision | cull | raster ms (min-max) | M points/s | batches drawn/culled | points projected (10/20/30 bits) | points depth-tested | winner % | colour % | coverage % | covered Δ % | PSNR dB |")?;
    writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|---|---|")?;
    let mut summaries = Vec::new();
    for &view in &a.views {
        let cam_args = CameraArgs {
            view: Some(view),
            eye: None,
            target: None,
            up: [0.0, 0.0, 1.0],
            fov: a.fov,
            ortho: false,
        };
        let cam = render::build_camera(&cam_args, &bounds, a.width, a.height)?;
        let view_name = format!("{view:?}").to_lowercase();
        // The reference first: brute force, every batch, all words.
        let configs: Vec<Config> = if a.rule_report.is_some() {
            let mut c = vec![
                Config::Options(PrecisionArg::Bits30, false),
                Config::Options(PrecisionArg::Bits30, true),
                RULE500,
                Config::Options(PrecisionArg::Adaptive, true),
            ];
            c.extend(a.budgets.iter().map(|&b| Config::Budget(b)));
            c
        } else {
            [
                PrecisionArg::Bits30,
                PrecisionArg::Bits20,
                PrecisionArg::Bits10,
                PrecisionArg::Adaptive,
            ]
            .into_iter()
            .flat_map(|p| [Config::Options(p, false), Config::Options(p, true)])
            .collect()
        };
        let measured = measure(&refs, file, &cam, &configs, a.runs)?;
        let mut reference: Option<Reference> = None;
        let mut rows = Vec::new();
        let mut keys_of = Vec::new();
        for (config, (keys, stats, times)) in configs.iter().copied().zip(measured) {
            let (min, max) = (
                times.iter().copied().fold(f64::INFINITY, f64::min),
                times.iter().copied().fold(0.0, f64::max),
            );
            let med = median(&times);
            // Colour with the reference's range, so that only the points differ.
            let range = reference.as_ref().and_then(|r| r.2);
            let (rgba, used_range) = colorize(file, &keys, &cam, color, range)?;
            if reference.is_none() {
                reference = Some((keys.clone(), rgba.clone(), used_range));
            }
            let (rk, rc, _) = reference.as_ref().expect("set above");
            let mut row = Row {
                config,
                median: med,
                min,
                max,
                stats,
                winner_diff: 0,
                coverage_diff: 0,
                color_diff: 0,
                psnr: psnr(&rgba, rc),
                covered: rk.iter().filter(|&&k| k != EMPTY_KEY).count() as u64,
                covered_self: keys.iter().filter(|&&k| k != EMPTY_KEY).count() as u64,
            };
            for i in 0..keys.len() {
                let (k, r) = (keys[i], rk[i]);
                if (k == EMPTY_KEY) != (r == EMPTY_KEY) {
                    row.coverage_diff += 1;
                }
                if (k == EMPTY_KEY) != (r == EMPTY_KEY)
                    || (k != EMPTY_KEY && key_index(k) != key_index(r))
                {
                    row.winner_diff += 1;
                }
                if rgba[i] != rc[i] {
                    row.color_diff += 1;
                }
            }
            if a.images {
                if let Some(dir) = &a.out {
                    std::fs::create_dir_all(dir)?;
                    let name = format!(
                        "{label}-{view_name}-{}-{}.png",
                        config.name().replace(' ', "-"),
                        if config.cull() { "cull" } else { "nocull" }
                    );
                    render::write_atomic(
                        &dir.join(name),
                        &render::encode_png(a.width, a.height, &rgba)?,
                    )?;
                }
            }
            rows.push(row);
            keys_of.push(keys);
        }
        let pct = |v: u64, n: u64| 100.0 * v as f64 / n.max(1) as f64;
        for r in &rows {
            let s = &r.stats;
            writeln!(
                md,
                "| {view_name} | {} | {} | {:.1} ({:.1}-{:.1}) | {:.0} | {}/{} | {} ({}/{}/{}) | {} | {:.3} | {:.3} | {:.4} | {:+.4} | {} |",
                r.config.name(),
                if r.config.cull() { "on" } else { "off" },
                r.median * 1e3,
                r.min * 1e3,
                r.max * 1e3,
                s.points_projected() as f64 / r.median / 1e6,
                s.batches_drawn,
                s.batches_culled,
                s.points_projected(),
                s.points_by_precision[0],
                s.points_by_precision[1],
                s.points_by_precision[2],
                s.points_drawn,
                pct(r.winner_diff, r.covered),
                pct(r.color_diff, r.covered),
                pct(r.coverage_diff, r.covered),
                100.0 * (r.covered_self as f64 - r.covered as f64) / r.covered.max(1) as f64,
                if r.psnr.is_finite() { format!("{:.1}", r.psnr) } else { "inf".into() },
            )?;
        }
        let find = |c: Config| rows.iter().find(|r| r.config == c);
        let (ad, full, brute) = (
            find(Config::Options(PrecisionArg::Adaptive, true)).expect("always measured"),
            find(Config::Options(PrecisionArg::Bits30, true)).expect("always measured"),
            find(Config::Options(PrecisionArg::Bits30, false)).expect("always measured"),
        );
        summaries.push(format!(
            "- {view_name}: adaptive + culling {:.1} ms ({:.0} M points/s projected), 30-bit + culling {:.1} ms: adaptive is {:.2}x faster; brute force (30-bit, no culling) {:.1} ms: {:.2}x",
            ad.median * 1e3,
            ad.stats.points_projected() as f64 / ad.median / 1e6,
            full.median * 1e3,
            full.median / ad.median,
            brute.median * 1e3,
            brute.median / ad.median,
        ));
        if let (Some(n), Some(old)) = (a.rule_report, find(RULE500)) {
            summaries.push(format!(
                "- {view_name}: the 500 px rule alone {:.1} ms, PSNR {:.1} dB, colour {:.3} %; adaptive {:.1} ms, PSNR {:.1} dB, colour {:.3} %; 30-bit / 500 px rule {:.2}x, 30-bit / adaptive {:.2}x",
                old.median * 1e3,
                old.psnr,
                pct(old.color_diff, old.covered),
                ad.median * 1e3,
                ad.psnr,
                pct(ad.color_diff, ad.covered),
                full.median / old.median,
                full.median / ad.median,
            ));
            let at = |c: Config| configs.iter().position(|&x| x == c).expect("measured");
            let reference = &keys_of[at(Config::Options(PrecisionArg::Bits30, false))];
            let old_keys = &keys_of[at(RULE500)];
            let new_keys = &keys_of[at(Config::Options(PrecisionArg::Adaptive, true))];
            batch_report(
                &mut md,
                &view_name,
                n,
                &refs,
                &file.grid(),
                &cam,
                reference,
                old_keys,
                new_keys,
            )?;
        }
        if let Some(dir) = &a.out {
            std::fs::create_dir_all(dir)?;
            let title =
                format!("{label} {view_name} {}x{}: raster time vs error", a.width, a.height);
            let png = plot::time_vs_error(&title, &rows)?;
            render::write_atomic(&dir.join(format!("{label}-{view_name}.png")), &png)?;
        }
    }
    writeln!(md)?;
    for s in &summaries {
        writeln!(md, "{s}")?;
    }
    print!("{md}");
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir)?;
        render::write_atomic(&dir.join(format!("{label}.md")), md.as_bytes())?;
    }
    Ok(())
}

/// Per batch of a view: the precision of the 500 px rule and of the adaptive rule, the bound of
/// their decode error on screen and the error measured on the batch's points (f64 projections of
/// the decoded and the exact positions, points within 2 px of the viewport), and the pixels each
/// loses (reference pixels whose winner is one of the batch's points and that another point, or
/// nothing, wins in that render).
struct BatchLoss {
    batch: usize,
    points: usize,
    px: f64,
    depth_ratio: f64,
    old: (Precision, f64, f64, u64),
    new: (Precision, f64, f64, u64),
}

/// The largest distance (pixels) between the f64 projections of a batch's points decoded at
/// `precision` and exactly, over points within 2 px of the viewport.
fn measured_error_px(b: &BatchRef<'_>, grid: &Grid, cam: &Camera, precision: Precision) -> f64 {
    if precision == Precision::Bits30 {
        return 0.0;
    }
    let (w, h) = (cam.width as f64, cam.height as f64);
    let world = |rel: [f64; 3]| {
        [0, 1, 2].map(|a| grid.offset[a] + grid.scale[a] * (b.grid.min[a] as f64 + rel[a]))
    };
    let mut worst = 0f64;
    for i in 0..b.len() {
        let words = [b.words[0][i], b.words[1][i], b.words[2][i]];
        let (Some(d), Some(e)) = (
            cam.project(world(b.grid.decode_relative(words, precision))),
            cam.project(world(b.grid.decode_relative(words, Precision::Bits30))),
        ) else {
            continue;
        };
        let inside = |x: f64, y: f64| x >= -2.0 && x <= w + 2.0 && y >= -2.0 && y <= h + 2.0;
        if inside(d.x, d.y) || inside(e.x, e.y) {
            worst = worst.max(((d.x - e.x).powi(2) + (d.y - e.y).powi(2)).sqrt());
        }
    }
    worst
}

#[allow(clippy::too_many_arguments)]
fn batch_report(
    md: &mut String,
    view: &str,
    n: usize,
    refs: &[BatchRef<'_>],
    grid: &Grid,
    cam: &Camera,
    reference: &[u64],
    old_keys: &[u64],
    new_keys: &[u64],
) -> Result<()> {
    let starts: Vec<u32> = refs.iter().map(|b| b.first_index).collect();
    let batch_of = |index: u32| starts.partition_point(|&s| s <= index) - 1;
    let (mut lost_old, mut lost_new) = (vec![0u64; refs.len()], vec![0u64; refs.len()]);
    for i in 0..reference.len() {
        let r = reference[i];
        if r == EMPTY_KEY {
            continue;
        }
        let b = batch_of(key_index(r));
        let differs = |k: u64| k == EMPTY_KEY || key_index(k) != key_index(r);
        if differs(old_keys[i]) {
            lost_old[b] += 1;
        }
        if differs(new_keys[i]) {
            lost_new[b] += 1;
        }
    }
    let axes = cam.axes().expect("validated camera");
    let frustum = mortar_core::render::Frustum::new(cam, 1.0);
    let losses: Vec<BatchLoss> = refs
        .par_iter()
        .enumerate()
        .map(|(i, b)| {
            let bounds = b.bounds();
            let px = cam.projected_size(&quantization_box(grid, &b.grid));
            let depths = bounds
                .corners()
                .map(|c| (0..3).map(|a| axes.forward[a] * (c[a] - cam.eye[a])).sum::<f64>());
            let (zmin, zmax) = depths
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &z| (lo.min(z), hi.max(z)));
            let p_old = budget_precision(cam, grid, b, f64::INFINITY);
            let (p_new, _) = choose_precision(PrecisionMode::Adaptive, cam, grid, &b.grid, &bounds);
            let visible = lost_old[i] > 0
                || lost_new[i] > 0
                || frustum.test_aabb(&bounds) != mortar_core::render::Containment::Outside;
            let measure =
                |p: Precision| if visible { measured_error_px(b, grid, cam, p) } else { 0.0 };
            let m_old = measure(p_old);
            let m_new = if p_new == p_old { m_old } else { measure(p_new) };
            BatchLoss {
                batch: i,
                points: b.len(),
                px,
                depth_ratio: if zmin > 0.0 { zmax / zmin } else { f64::INFINITY },
                old: (
                    p_old,
                    decode_error_px(cam, grid, &b.grid, &bounds, p_old),
                    m_old,
                    lost_old[i],
                ),
                new: (
                    p_new,
                    decode_error_px(cam, grid, &b.grid, &bounds, p_new),
                    m_new,
                    lost_new[i],
                ),
            }
        })
        .collect();
    let count = |f: &dyn Fn(&BatchLoss) -> bool| losses.iter().filter(|l| f(l)).count();
    let by_precision = |sel: &dyn Fn(&BatchLoss) -> Precision| {
        [Precision::Bits10, Precision::Bits20, Precision::Bits30].map(|p| count(&|l| sel(l) == p))
    };
    let (bo, bn) = (by_precision(&|l| l.old.0), by_precision(&|l| l.new.0));
    let worst = |sel: &dyn Fn(&BatchLoss) -> f64| losses.iter().map(sel).fold(0f64, f64::max);
    let violations = count(&|l| l.old.2 > l.old.1 + 1e-9 || l.new.2 > l.new.1 + 1e-9);
    writeln!(md, "\n#### {view}: per batch, the 500 px rule against adaptive\n")?;
    writeln!(
        md,
        "Batches at 10/20/30 bits: 500 px rule {}/{}/{}, adaptive {}/{}/{}. Batches whose measured error is at least 1 px: {} / {}; at least 0.5 px: {} / {}. Largest measured error {:.3} / {:.3} px, largest bound {:.3} / {:.3} px; measured above bound: {violations}. Pixels lost (reference winner's batch): {} / {}.\n",
        bo[0], bo[1], bo[2], bn[0], bn[1], bn[2],
        count(&|l| l.old.2 >= 1.0), count(&|l| l.new.2 >= 1.0),
        count(&|l| l.old.2 >= 0.5), count(&|l| l.new.2 >= 0.5),
        worst(&|l| l.old.2), worst(&|l| l.new.2), worst(&|l| if l.old.0 == Precision::Bits30 { 0.0 } else { l.old.1 }), worst(&|l| if l.new.0 == Precision::Bits30 { 0.0 } else { l.new.1 }),
        lost_old.iter().sum::<u64>(), lost_new.iter().sum::<u64>(),
    )?;
    let mut top: Vec<&BatchLoss> = losses.iter().filter(|l| l.old.3 > 0).collect();
    top.sort_by_key(|l| std::cmp::Reverse(l.old.3));
    writeln!(md, "| batch | points | box px | depth far/near | 500 px rule: bits, bound px, measured px, pixels lost | adaptive: bits, bound px, measured px, pixels lost |")?;
    writeln!(md, "|---|---|---|---|---|---|")?;
    for l in top.iter().take(n) {
        writeln!(
            md,
            "| {} | {} | {:.0} | {:.2} | {}, {:.3}, {:.3}, {} | {}, {:.3}, {:.3}, {} |",
            l.batch,
            l.points,
            l.px,
            l.depth_ratio,
            l.old.0.bits(),
            l.old.1,
            l.old.2,
            l.old.3,
            l.new.0.bits(),
            l.new.1,
            l.new.2,
            l.new.3
        )?;
    }
    Ok(())
}

/// The plot: time on x, error on y, one marker per configuration, drawn on an RGBA canvas.
mod plot {
    use super::{Config, PrecisionArg, Row};
    use anyhow::Result;

    const W: i32 = 900;
    const H: i32 = 600;
    const LEFT: i32 = 90;
    const RIGHT: i32 = 230;
    const TOP: i32 = 50;
    const BOTTOM: i32 = 70;
    const WHITE: u32 = 0xffff_ffff;
    const BLACK: u32 = 0xff00_0000;
    const GREY: u32 = 0xffdd_dddd;

    /// 5x7 glyphs, one row per byte (bit 4 is the leftmost column). Lowercase prints as uppercase.
    fn glyph(c: char) -> [u8; 7] {
        match c.to_ascii_uppercase() {
            '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
            '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
            '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
            '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
            '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
            '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
            '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
            '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
            '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
            '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
            'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
            'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
            'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
            'D' => [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C],
            'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
            'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
            'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
            'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
            'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
            'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
            'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
            'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
            'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
            'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
            'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
            'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
            'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
            'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
            'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
            'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
            'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
            'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
            'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
            'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
            'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
            'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
            '.' => [0, 0, 0, 0, 0, 0x0C, 0x0C],
            ',' => [0, 0, 0, 0, 0x0C, 0x04, 0x08],
            '-' => [0, 0, 0, 0x1F, 0, 0, 0],
            '+' => [0, 0x04, 0x04, 0x1F, 0x04, 0x04, 0],
            '=' => [0, 0, 0x1F, 0, 0x1F, 0, 0],
            '%' => [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03],
            '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
            ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
            ':' => [0, 0x0C, 0x0C, 0, 0x0C, 0x0C, 0],
            '/' => [0, 0x01, 0x02, 0x04, 0x08, 0x10, 0],
            '_' => [0, 0, 0, 0, 0, 0, 0x1F],
            ' ' => [0; 7],
            _ => [0x1F, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1F],
        }
    }

    struct Canvas {
        px: Vec<u32>,
    }

    impl Canvas {
        fn set(&mut self, x: i32, y: i32, c: u32) {
            if (0..W).contains(&x) && (0..H).contains(&y) {
                self.px[(y * W + x) as usize] = c;
            }
        }

        fn line(&mut self, (mut x0, mut y0): (i32, i32), (x1, y1): (i32, i32), c: u32) {
            let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
            let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
            let mut err = dx + dy;
            loop {
                self.set(x0, y0, c);
                if x0 == x1 && y0 == y1 {
                    break;
                }
                let e2 = 2 * err;
                if e2 >= dy {
                    err += dy;
                    x0 += sx;
                }
                if e2 <= dx {
                    err += dx;
                    y0 += sy;
                }
            }
        }

        /// Text at scale `s` with its top-left corner at (x, y).
        fn text(&mut self, x: i32, y: i32, s: i32, t: &str, c: u32) {
            for (i, ch) in t.chars().enumerate() {
                let g = glyph(ch);
                for (row, bits) in g.iter().enumerate() {
                    for col in 0..5 {
                        if bits >> (4 - col) & 1 == 1 {
                            for u in 0..s {
                                for v in 0..s {
                                    self.set(
                                        x + (i as i32 * 6 + col) * s + u,
                                        y + row as i32 * s + v,
                                        c,
                                    );
                                }
                            }
                        }
                    }
                }
            }
        }

        fn text_width(t: &str, s: i32) -> i32 {
            t.chars().count() as i32 * 6 * s
        }

        /// A marker: filled disc (culling on) or hollow square (culling off).
        fn marker(&mut self, x: i32, y: i32, filled: bool, c: u32) {
            for u in -6..=6i32 {
                for v in -6..=6i32 {
                    let on = if filled {
                        u * u + v * v <= 30
                    } else {
                        (u.abs() == 6 || v.abs() == 6) || (u.abs() == 5 || v.abs() == 5)
                    };
                    if on {
                        self.set(x + u, y + v, c);
                    }
                }
            }
        }
    }

    fn color_of(p: PrecisionArg) -> u32 {
        let rgb = |r: u32, g: u32, b: u32| r | g << 8 | b << 16 | 0xff00_0000;
        match p {
            PrecisionArg::Adaptive => rgb(220, 30, 30),
            PrecisionArg::Bits10 => rgb(240, 150, 0),
            PrecisionArg::Bits20 => rgb(30, 90, 220),
            PrecisionArg::Bits30 => rgb(20, 150, 60),
        }
    }

    /// A "nice" tick step for a range of `span` with about `n` ticks.
    fn tick_step(span: f64, n: f64) -> f64 {
        let raw = (span / n).max(1e-12);
        let mag = 10f64.powf(raw.log10().floor());
        [1.0, 2.0, 2.5, 5.0, 10.0]
            .into_iter()
            .map(|m| m * mag)
            .find(|&s| s >= raw)
            .unwrap_or(10.0 * mag)
    }

    fn label(v: f64, step: f64) -> String {
        let decimals = if step >= 1.0 { 0 } else { (-step.log10()).ceil() as usize };
        format!("{v:.decimals$}")
    }

    /// The plot of `rows` as PNG bytes: x the median raster time in ms, y the share of pixels whose
    /// colour differs from the brute-force render, in %.
    pub fn time_vs_error(title: &str, rows: &[Row]) -> Result<Vec<u8>> {
        let mut c = Canvas { px: vec![WHITE; (W * H) as usize] };
        let err = |r: &Row| 100.0 * r.color_diff as f64 / r.covered.max(1) as f64;
        let x_max = rows.iter().map(|r| r.median * 1e3).fold(0.0, f64::max).max(1e-3) * 1.1;
        let y_max = rows.iter().map(err).fold(0.0, f64::max).max(0.01) * 1.15;
        let (x_step, y_step) = (tick_step(x_max, 6.0), tick_step(y_max, 5.0));
        let (x_max, y_max) = ((x_max / x_step).ceil() * x_step, (y_max / y_step).ceil() * y_step);
        let (x0, x1, y0, y1) = (LEFT, W - RIGHT, H - BOTTOM, TOP);
        let sx = |v: f64| x0 + ((v / x_max) * (x1 - x0) as f64).round() as i32;
        let sy = |v: f64| y0 - ((v / y_max) * (y0 - y1) as f64).round() as i32;
        // Grid and ticks.
        let mut v = 0.0;
        while v <= x_max + 1e-9 {
            let x = sx(v);
            c.line((x, y0), (x, y1), GREY);
            c.line((x, y0), (x, y0 + 5), BLACK);
            let t = label(v, x_step);
            c.text(x - Canvas::text_width(&t, 2) / 2, y0 + 10, 2, &t, BLACK);
            v += x_step;
        }
        let mut v = 0.0;
        while v <= y_max + 1e-9 {
            let y = sy(v);
            c.line((x0, y), (x1, y), GREY);
            c.line((x0 - 5, y), (x0, y), BLACK);
            let t = label(v, y_step);
            c.text(x0 - 10 - Canvas::text_width(&t, 2), y - 7, 2, &t, BLACK);
            v += y_step;
        }
        c.line((x0, y0), (x1, y0), BLACK);
        c.line((x0, y0), (x0, y1), BLACK);
        let xl = "raster time (ms, median)";
        c.text((x0 + x1) / 2 - Canvas::text_width(xl, 2) / 2, y0 + 36, 2, xl, BLACK);
        c.text(8, 26, 2, "pixels differing (%)", BLACK);
        c.text(LEFT, 8, 2, title, BLACK);
        for r in rows {
            let color = match r.config {
                Config::Options(p, _) => color_of(p),
                Config::Budget(_) => 0xff80_0080,
            };
            c.marker(sx(r.median * 1e3), sy(err(r)), r.config.cull(), color);
        }
        // Legend.
        let lx = W - RIGHT + 20;
        let mut ly = TOP + 10;
        for p in [
            PrecisionArg::Adaptive,
            PrecisionArg::Bits10,
            PrecisionArg::Bits20,
            PrecisionArg::Bits30,
        ] {
            c.marker(lx + 6, ly + 7, true, color_of(p));
            let name = if p == PrecisionArg::Adaptive {
                "adaptive".to_string()
            } else {
                format!("{} bits", p.name())
            };
            c.text(lx + 20, ly, 2, &name, BLACK);
            ly += 26;
        }
        ly += 10;
        c.marker(lx + 6, ly + 7, true, BLACK);
        c.text(lx + 20, ly, 2, "culling", BLACK);
        ly += 26;
        c.marker(lx + 6, ly + 7, false, BLACK);
        c.text(lx + 20, ly, 2, "no culling", BLACK);
        crate::render::encode_png(W as u32, H as u32, &c.px)
    }
}
