//! `mortar-bench-gpu`: frame times of the GPU rasterizer (and of the CPU one, for the same table)
//! on a batch file tiled to billions of points.
//!
//! The input's batches are repeated as tiles side by side on a square grid of tiles (each copy's
//! integer coordinates shifted by whole tile extents plus a 5 % gap; the point words are the same),
//! until each requested size is reached. The scene grows as it goes: tiles are streamed to the GPU
//! batch by batch and each size is measured once its points are in. Per size and variant it draws
//! `--frames` frames of a framed view and reports the median GPU pass times (timestamp queries),
//! the median wall time of a whole frame (host planning and upload of the draw records included)
//! and points per second. One JSON object per line on stdout, a table on stderr.

use anyhow::{anyhow, bail, Context, Result};
use clap::Parser;
use mortar_core::batch::SECTION_COLOR;
use mortar_core::metrics::median;
use mortar_core::quantize::Precision;
use mortar_core::render::framebuffer::{key_depth, EMPTY_KEY};
use mortar_core::render::{
    rasterize, Aabb, BatchRef, Camera, Framebuffer, PrecisionMode, RasterOptions, ViewPreset,
};
use mortar_io::batchfile::BatchFile;
use mortar_render::{
    AtomicPath, DrawTuning, GpuContext, GpuOptions, GpuRasterizer, GpuScene, RecordOrder,
    SceneOptions,
};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Parser)]
#[command(
    name = "mortar-bench-gpu",
    about = "GPU (and CPU) rasterizer frame times on a batch file tiled to billions of points"
)]
pub struct Args {
    /// A batch file (uncompressed or zstd) of a real scan.
    input: PathBuf,
    /// Scene sizes in millions of points, ascending.
    #[arg(long, value_delimiter = ',', default_value = "500,1000,2000,3000")]
    millions: Vec<f64>,
    /// Frames per measurement (the median is reported).
    #[arg(long, default_value_t = 20)]
    frames: usize,
    /// Image width.
    #[arg(long, default_value_t = 1920)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 1080)]
    height: u32,
    /// gpu or cpu.
    #[arg(long, default_value = "gpu")]
    backend: String,
    /// GPU atomics: 64 or 32 (default: 64 where available).
    #[arg(long)]
    atomics: Option<u32>,
    /// Accept a software adapter (lavapipe).
    #[arg(long)]
    allow_software: bool,
    /// Variants: adaptive (precision by size, culling: the default renderer), brute (30 bits, no
    /// culling), ten (10 bits, no culling).
    #[arg(long, value_delimiter = ',', default_value = "adaptive,brute")]
    variants: Vec<String>,
    /// View: iso or top (framing the tiles), or closeup (near the ground in the middle: most
    /// batches culled).
    #[arg(long, default_value = "iso")]
    view: String,
    /// Draw-pass kernels to measure (`DrawTuning::kernel`: 0 the renderer, 1 plain-load early
    /// test, 2 no early test, 3 no framebuffer access, 4 prefetch of four points).
    #[arg(long, value_delimiter = ',', default_value = "0")]
    kernels: Vec<u32>,
    /// Threads per workgroup of the draw pass.
    #[arg(long, value_delimiter = ',', default_value = "128")]
    workgroups: Vec<u32>,
    /// Orders of the draw records: scene, or strided:S.
    #[arg(long, value_delimiter = ',', default_value = "scene")]
    orders: Vec<String>,
    /// Divisions of the draw and plan passes: refined (exact; the default on hardware) or plain
    /// (WGSL's `/`; measures what exactness costs).
    #[arg(long, value_delimiter = ',', default_value = "default")]
    divisions: Vec<String>,
    /// Where the batches are planned: gpu (the plan pass, the default), host, or both in turn.
    #[arg(long, value_delimiter = ',', default_value = "gpu")]
    plans: Vec<String>,
    /// Rounds over all configurations per size (interleaved, so that clock changes show as
    /// differences between rounds rather than between configurations).
    #[arg(long, default_value_t = 1)]
    rounds: usize,
    /// Milliseconds of back-to-back frames drawn before each size's first measurement (GPU clocks
    /// up).
    #[arg(long, default_value_t = 0)]
    warmup_ms: u64,
    /// Milliseconds of back-to-back frames of each configuration before it is measured.
    #[arg(long, default_value_t = 0)]
    config_warmup_ms: u64,
    /// After each GPU measurement, draw the same frame with the CPU rasterizer and count the
    /// pixels whose key differs (exact depth ties apart).
    #[arg(long)]
    compare_cpu: bool,
}

fn order(name: &str) -> Result<RecordOrder> {
    if name == "scene" {
        return Ok(RecordOrder::Scene);
    }
    match name.strip_prefix("strided:").and_then(|s| s.parse().ok()) {
        Some(s) => Ok(RecordOrder::Strided(s)),
        None => bail!("unknown order {name} (scene, strided:S)"),
    }
}

fn options(variant: &str) -> Result<RasterOptions> {
    Ok(match variant {
        "adaptive" => RasterOptions::default(),
        "brute" => {
            RasterOptions { precision: PrecisionMode::Fixed(Precision::Bits30), cull: false }
        }
        "ten" => RasterOptions { precision: PrecisionMode::Fixed(Precision::Bits10), cull: false },
        v => bail!("unknown variant {v} (adaptive, brute, ten)"),
    })
}

/// Runs the benchmark the arguments describe.
pub fn run(a: Args) -> Result<()> {
    let file = BatchFile::open(&a.input).with_context(|| format!("{}", a.input.display()))?;
    let sections = [0, 1, 2, SECTION_COLOR];
    let views = (0..file.batch_count())
        .map(|i| file.batch_sections(i, &sections))
        .collect::<mortar_io::Result<Vec<_>>>()?;
    let grid = file.grid();
    let src_points = file.header.point_count;
    if src_points == 0 {
        bail!("{}: no points", a.input.display());
    }
    // Tile extent in integer units (+5 %), from the batches' integer bounds.
    let mut lo = [i64::MAX; 3];
    let mut hi = [i64::MIN; 3];
    for v in &views {
        let g = v.entry.grid();
        for ax in 0..3 {
            lo[ax] = lo[ax].min(g.min[ax] as i64);
            hi[ax] = hi[ax].max(g.min[ax] as i64 + (1i64 << g.bits[ax]) - 1);
        }
    }
    let step = [0, 1].map(|ax| ((hi[ax] - lo[ax] + 1) as f64 * 1.05).ceil() as i64);
    let max_points = (a.millions.iter().cloned().fold(0.0, f64::max) * 1e6) as u64;
    if max_points >= 1u64 << 32 {
        bail!("at most 4294 million points (32-bit point indices)");
    }
    let tiles_total = max_points.div_ceil(src_points);
    let cols = (tiles_total as f64).sqrt().ceil() as i64;
    for ax in 0..2 {
        if lo[ax] + step[ax] * cols > i32::MAX as i64 || lo[ax] < i32::MIN as i64 {
            bail!("{} tiles per row do not fit the 32-bit integer grid", cols);
        }
    }
    eprintln!(
        "{}: {} points in {} batches; tiles of {}x{} units, {} columns",
        a.input.display(),
        src_points,
        views.len(),
        step[0],
        step[1],
        cols
    );

    let gpu = a.backend == "gpu";
    let ctx = if gpu {
        let atomics = match a.atomics {
            None => None,
            Some(64) => Some(AtomicPath::U64),
            Some(32) => Some(AtomicPath::TwoPass32),
            Some(n) => bail!("--atomics {n}: 64 or 32"),
        };
        Some(
            GpuContext::new(&GpuOptions {
                atomics,
                allow_software: a.allow_software,
                ..Default::default()
            })
            .map_err(|e| anyhow!("{e}"))?,
        )
    } else {
        None
    };
    if let Some(c) = &ctx {
        let ad = c.adapter();
        eprintln!(
            "adapter: {} ({}, {}), driver {}, atomics {}, timestamps {}",
            ad.name,
            ad.backend,
            ad.device_type,
            ad.driver,
            c.atomic_path().name(),
            c.has_timestamps()
        );
    }
    let mut scene = match &ctx {
        Some(c) => Some(
            GpuScene::new(c, grid, max_points, SceneOptions { chunk_points: None, colors: true })
                .map_err(|e| anyhow!("{e}"))?,
        ),
        None => None,
    };
    let mut raster = match &ctx {
        Some(c) => Some(GpuRasterizer::new(c, a.width, a.height).map_err(|e| anyhow!("{e}"))?),
        None => None,
    };
    let mut cpu_refs: Vec<BatchRef<'_>> = Vec::new();
    let mut points = 0u64;
    let mut bounds = Aabb::EMPTY;
    let mut tile = 0i64;
    let mut upload_seconds = 0.0;
    for &m in &a.millions {
        let target = (m * 1e6) as u64;
        let t = Instant::now();
        'fill: while points < target {
            let off = [(tile % cols) * step[0], (tile / cols) * step[1]];
            for v in &views {
                if points >= target {
                    break 'fill;
                }
                let e = v.entry;
                let mut g = e.grid();
                g.min[0] += off[0] as i32;
                g.min[1] += off[1] as i32;
                let shift = |ax: usize, w: f64| w + off[ax] as f64 * grid.scale[ax];
                let bmin = [
                    shift(0, e.world_min[0].min(e.world_max[0])),
                    shift(1, e.world_min[1].min(e.world_max[1])),
                    e.world_min[2].min(e.world_max[2]),
                ];
                let bmax = [
                    shift(0, e.world_min[0].max(e.world_max[0])),
                    shift(1, e.world_min[1].max(e.world_max[1])),
                    e.world_min[2].max(e.world_max[2]),
                ];
                let b = BatchRef {
                    grid: g,
                    bounds_min: bmin,
                    bounds_max: bmax,
                    words: [v.words(0), v.words(1), v.words(2)],
                    first_index: points as u32,
                };
                bounds.grow(bmin);
                bounds.grow(bmax);
                points += b.len() as u64;
                if let (Some(c), Some(s)) = (&ctx, &mut scene) {
                    s.push(c, &b, Some(v.colors())).map_err(|e| anyhow!("{e}"))?;
                }
                cpu_refs.push(b);
            }
            tile += 1;
        }
        if let (Some(c), Some(s)) = (&ctx, &mut scene) {
            s.flush(c).map_err(|e| anyhow!("{e}"))?;
            c.wait().map_err(|e| anyhow!("{e}"))?;
        }
        upload_seconds += t.elapsed().as_secs_f64();
        let cam = match a.view.as_str() {
            // Close to the ground in the middle of the tiles: most batches culled.
            "closeup" => Camera::close_up(&bounds, 50f64.to_radians(), a.width, a.height),
            "top" => Camera::frame_perspective(
                &bounds,
                ViewPreset::Top,
                50f64.to_radians(),
                a.width,
                a.height,
            ),
            _ => Camera::frame_perspective(
                &bounds,
                ViewPreset::Iso,
                50f64.to_radians(),
                a.width,
                a.height,
            ),
        }
        .map_err(|e| anyhow!("{e}"))?;
        if let (Some(c), Some(s), Some(r), true) = (&ctx, &mut scene, &mut raster, a.warmup_ms > 0)
        {
            let t = Instant::now();
            while t.elapsed().as_millis() < a.warmup_ms as u128 {
                r.draw(
                    c,
                    s,
                    &cam,
                    &RasterOptions::default(),
                    Some(&mortar_core::render::resolve::ResolveOptions::default()),
                )
                .map_err(|e| anyhow!("{e}"))?;
            }
        }
        let mut configs = Vec::new();
        for round in 0..a.rounds.max(1) {
            for variant in &a.variants {
                for &kernel in &a.kernels {
                    for &workgroup in &a.workgroups {
                        for o in &a.orders {
                            for p in &a.plans {
                                let plan_on_gpu = match p.as_str() {
                                    "gpu" => true,
                                    "host" => false,
                                    p => bail!("--plans {p}: gpu or host"),
                                };
                                for d in &a.divisions {
                                    let division = match d.as_str() {
                                        "default" => None,
                                        "refined" => {
                                            Some(mortar_core::render::gpu::DIVISION_REFINED)
                                        }
                                        "plain" => Some(mortar_core::render::gpu::DIVISION_PLAIN),
                                        d => bail!("--divisions {d}: default, refined or plain"),
                                    };
                                    configs.push((
                                        round,
                                        variant.clone(),
                                        DrawTuning {
                                            kernel,
                                            workgroup,
                                            order: order(o)?,
                                            plan_on_gpu,
                                            division,
                                        },
                                        o.clone(),
                                    ));
                                }
                            }
                        }
                    }
                }
            }
        }
        for (round, variant, tuning, order_name) in &configs {
            let variant = variant.as_str();
            if let (Some(c), Some(r)) = (&ctx, &mut raster) {
                r.set_tuning(c, *tuning).map_err(|e| anyhow!("{e}"))?;
            }
            let opts = options(variant)?;
            // Each configuration drawn back to back for a while first, so that the GPU's clocks
            // are up whatever ran before (METHOD.md: warm up; the first run did not).
            if let (Some(c), Some(s), Some(r), true) =
                (&ctx, &mut scene, &mut raster, a.config_warmup_ms > 0)
            {
                let t = Instant::now();
                while t.elapsed().as_millis() < a.config_warmup_ms as u128 {
                    r.draw(
                        c,
                        s,
                        &cam,
                        &opts,
                        Some(&mortar_core::render::resolve::ResolveOptions::default()),
                    )
                    .map_err(|e| anyhow!("{e}"))?;
                }
            }
            let (mut draw, mut clear, mut resolve, mut wall, mut plan) =
                (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
            let mut gpu_plan = Vec::new();
            let mut stats = Default::default();
            for _ in 0..a.frames + 1 {
                let t = Instant::now();
                match (&ctx, &mut scene, &mut raster) {
                    (Some(c), Some(s), Some(r)) => {
                        let f = r
                            .draw(
                                c,
                                s,
                                &cam,
                                &opts,
                                Some(&mortar_core::render::resolve::ResolveOptions::default()),
                            )
                            .map_err(|e| anyhow!("{e}"))?;
                        stats = f.stats;
                        if let Some(tm) = f.timings {
                            draw.push(tm.draw_ms);
                            clear.push(tm.clear_ms);
                            resolve.push(tm.resolve_ms.unwrap_or(0.0));
                            gpu_plan.push(tm.plan_ms.unwrap_or(0.0));
                        }
                        plan.push(f.plan_seconds * 1e3);
                    }
                    _ => {
                        let fb = Framebuffer::new(a.width, a.height);
                        stats = rasterize(&fb, &cpu_refs, &grid, &cam, &opts)?;
                        draw.push(t.elapsed().as_secs_f64() * 1e3);
                    }
                }
                wall.push(t.elapsed().as_secs_f64() * 1e3);
            }
            // The first frame warms caches and pipelines: left out.
            for v in [&mut draw, &mut clear, &mut resolve, &mut wall, &mut plan, &mut gpu_plan] {
                if !v.is_empty() {
                    v.remove(0);
                }
            }
            let mut compare = serde_json::Value::Null;
            if let (true, Some(c), Some(r), Some(sc)) =
                (a.compare_cpu && tuning.kernel != 3, &ctx, &mut raster, &mut scene)
            {
                r.draw(c, sc, &cam, &opts, None).map_err(|e| anyhow!("{e}"))?;
                let f = r.read_keys(c).map_err(|e| anyhow!("{e}"))?;
                let fb = Framebuffer::new(a.width, a.height);
                rasterize(&fb, &cpu_refs, &grid, &cam, &opts)?;
                let cpu = fb.into_keys();
                let (mut ties, mut other, mut covered) = (0u64, 0u64, 0u64);
                for (g, k) in f.iter().zip(&cpu) {
                    covered += (*k != EMPTY_KEY) as u64;
                    if g != k {
                        if *g != EMPTY_KEY && *k != EMPTY_KEY && key_depth(*g) == key_depth(*k) {
                            ties += 1;
                        } else {
                            other += 1;
                        }
                    }
                }
                compare =
                    serde_json::json!({ "covered": covered, "depth_ties": ties, "other": other });
                eprintln!("  GPU vs CPU keys: {other} of {covered} covered pixels differ, {ties} exact depth ties");
            }
            let draw_ms = median(&draw);
            let gpu_ms = draw_ms + median(&clear) + median(&resolve) + median(&gpu_plan);
            let j = serde_json::json!({
                "backend": a.backend,
                "atomics": ctx.as_ref().map(|c| c.atomic_path().name()),
                "adapter": ctx.as_ref().map(|c| c.adapter().name.clone()),
                "driver": ctx.as_ref().map(|c| c.adapter().driver.clone()),
                "threads": rayon::current_num_threads(),
                "variant": variant,
                "kernel": tuning.kernel,
                "workgroup": tuning.workgroup,
                "order": order_name,
                "round": round,
                "unix_ms": std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_millis() as u64).unwrap_or(0),
                "draw_ms_min": draw.iter().cloned().fold(f64::INFINITY, f64::min),
                "draw_ms_max": draw.iter().cloned().fold(0.0, f64::max),
                "view": a.view,
                "points": points,
                "tiles": tile,
                "width": a.width,
                "height": a.height,
                "frames": a.frames,
                "draw_ms": draw_ms,
                "clear_ms": median(&clear),
                "resolve_ms": median(&resolve),
                "gpu_frame_ms": if gpu { Some(gpu_ms) } else { None },
                "wall_frame_ms": median(&wall),
                "plan_ms": median(&plan),
                "plan_on_gpu": tuning.plan_on_gpu,
                "division": tuning.division,
                "gpu_plan_ms": median(&gpu_plan),
                "gpoints_per_s": points as f64 / (draw_ms * 1e-3) / 1e9,
                "points_drawn": stats.points_drawn,
                "batches_culled": stats.batches_culled,
                "points_by_precision": stats.points_by_precision,
                "upload_seconds_total": upload_seconds,
                "gpu_bytes": scene.as_ref().map(|s| s.gpu_bytes()),
                "cpu_compare": compare,
            });
            println!("{j}");
            eprintln!(
                "{:>6} M points  {:<8} k{} wg{} {:<11} {} r{}  draw {:8.3} ms ({:6.1} G points/s)  gpu frame {:8.3} ms  wall {:8.3} ms  host plan {:6.2} ms  gpu plan {:6.3} ms",
                points / 1_000_000,
                variant,
                tuning.kernel,
                tuning.workgroup,
                order_name,
                match (tuning.plan_on_gpu, tuning.division) {
                    (true, Some(0)) => "gpu-plan/plain-div",
                    (false, Some(0)) => "host-plan/plain-div",
                    (true, _) => "gpu-plan",
                    (false, _) => "host-plan",
                },
                round,
                draw_ms,
                points as f64 / (draw_ms * 1e-3) / 1e9,
                if gpu { gpu_ms } else { f64::NAN },
                j["wall_frame_ms"].as_f64().unwrap_or(f64::NAN),
                j["plan_ms"].as_f64().unwrap_or(f64::NAN),
                median(&gpu_plan)
            );
        }
    }
    Ok(())
}
