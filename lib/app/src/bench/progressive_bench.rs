//! `mortar-bench-progressive`: the GPU progressive renderer of paper 000
//! (`mortar_render::progressive`) on up to a few billion synthetic points.
//!
//! The points are generated in memory, in parallel, piece by piece (a hilly 4 km x 2.5 km terrain
//! on a 1 mm grid, uniform in x/y from a per-index hash, so any piece can be made on any thread
//! and 1e9 points take a few seconds on 16 cores), and inserted into the shuffled buffer as they
//! are made. Unless `--no-load-frames`, a frame is drawn after each piece, as the paper draws
//! while loading. Then, with the adaptive budget (`--target-ms`, default 16.6) or a fixed one,
//! frames of a still camera run until the image converged, and then frames of a moved camera (the
//! eye orbited by `--orbit-degrees` around the target, and moved closer) until it converged
//! again.
//!
//! Output: one JSON object per frame on stdout (phase, wall and GPU frame time, pass times, the
//! budget reached, points reprojected and visible), then a summary object (generation and insert
//! time, time to the first frame, frames and time to converge per phase, median frame times and
//! budgets); a short table on stderr.

use anyhow::{anyhow, bail, Result};
use clap::Parser;
use mortar_core::grid::Grid;
use mortar_core::metrics::median;
use mortar_core::render::progressive::{AdaptiveBudget, FillBudget};
use mortar_core::render::resolve::ResolveOptions;
use mortar_core::render::testutil::Rng;
use mortar_core::render::{Aabb, Camera, RasterOptions, ViewPreset};
use mortar_render::{
    GpuContext, GpuOptions, GpuProgressive, GpuProgressiveFrame, ProgressiveOptions,
};
use rayon::prelude::*;
use std::time::Instant;

#[derive(Parser)]
#[command(
    name = "mortar-bench-progressive",
    about = "GPU progressive renderer (paper 000): frames to convergence on synthetic points"
)]
pub struct Args {
    /// Points (e.g. 1e9; at most 4294967295).
    #[arg(long, default_value = "1e8")]
    points: f64,
    /// Points generated and inserted per piece.
    #[arg(long, default_value_t = 16_000_000)]
    piece: usize,
    /// Image width.
    #[arg(long, default_value_t = 1920)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 1080)]
    height: u32,
    /// Fill budget: `auto` (the adaptive budget of §3.4.1) or slots per frame.
    #[arg(long, default_value = "auto")]
    budget: String,
    /// Adaptive budget: the frame time to stay within, ms.
    #[arg(long, default_value_t = 16.6)]
    target_ms: f64,
    /// Adaptive budget: slots filled first to measure the rate.
    #[arg(long, default_value_t = 1_000_000)]
    probe: u64,
    /// Adaptive budget: share of the frame time planned for.
    #[arg(long, default_value_t = 0.9)]
    usable: f64,
    /// Frames at most per phase.
    #[arg(long, default_value_t = 2000)]
    max_frames: u64,
    /// Generate every point first and load from memory (the loading time then excludes
    /// generation).
    #[arg(long)]
    pregenerate: bool,
    /// Prepare each piece (checks, words, sorted slots) on another thread, a piece ahead, while
    /// the render thread uploads and draws.
    #[arg(long)]
    prepare_thread: bool,
    /// Do not draw a frame after each inserted piece.
    #[arg(long)]
    no_load_frames: bool,
    /// Do not resolve colours each frame (keys only).
    #[arg(long)]
    no_resolve: bool,
    /// Degrees the eye orbits around the target for the moved camera.
    #[arg(long, default_value_t = 20.0)]
    orbit_degrees: f64,
    /// Slots per chunk of the shuffled buffer (default: the device's largest binding, at most 2^28).
    #[arg(long)]
    chunk_slots: Option<u32>,
    /// Accept a software adapter (lavapipe).
    #[arg(long)]
    allow_software: bool,
    /// Seed of the generator.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

/// Terrain extent in metres.
const EXTENT: [f64; 2] = [4000.0, 2500.0];

/// The grid: 1 mm.
const GRID: Grid = Grid { scale: [0.001; 3], offset: [500_000.0, 5_400_000.0, 0.0] };

/// Height of the terrain at `(x, y)` metres.
fn height(x: f64, y: f64) -> f64 {
    60.0 + 25.0 * (x / 370.0).sin() * (y / 290.0).cos() + 4.0 * (x / 41.0 + y / 67.0).sin()
}

/// Points `first..first + xyz.len()` of the synthetic set, with colours.
fn generate(seed: u64, first: u64, xyz: &mut [[i32; 3]], colors: &mut [u32]) {
    xyz.par_chunks_mut(1 << 14).zip(colors.par_chunks_mut(1 << 14)).enumerate().for_each(
        |(k, (p, c))| {
            for (j, (p, c)) in p.iter_mut().zip(c.iter_mut()).enumerate() {
                let i = first + (k << 14) as u64 + j as u64;
                let mut rng = Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ i);
                let x = rng.unit() * EXTENT[0];
                let y = rng.unit() * EXTENT[1];
                let noise = rng.unit();
                let z = height(x, y) + 0.5 * noise;
                *p = [(x * 1000.0) as i32, (y * 1000.0) as i32, (z * 1000.0) as i32];
                let g =
                    (((z - 30.0) / 70.0).clamp(0.0, 1.0) * 200.0) as u32 + (noise * 55.0) as u32;
                *c = (g / 2) | (g << 8) | ((255 - g) << 16) | (255 << 24);
            }
        },
    );
}

/// One frame's JSON line.
fn frame_json(phase: &str, f: &GpuProgressiveFrame, at_s: f64) -> serde_json::Value {
    let s = &f.stats;
    serde_json::json!({
        "phase": phase,
        "frame": s.frame,
        "loaded": s.loaded,
        "wall_ms": s.total_ms,
        "gpu_ms": f.gpu.map(|g| g.frame_ms),
        "reproject_ms": s.reproject_ms,
        "probe_ms": f.gpu.map(|g| g.probe_ms),
        "fill_ms": s.fill_ms,
        "prepare_ms": s.prepare_ms,
        "resolve_ms": f.gpu.and_then(|g| g.resolve_ms),
        "budget": s.filled,
        "probe": s.probe,
        "fill_points": s.fill_points,
        "reprojected": s.reprojected,
        "visible": s.visible,
        "points_drawn": s.raster.points_drawn,
        "converged": s.converged,
        "at_s": at_s,
    })
}

/// What a phase of frames did.
struct Phase {
    frames: Vec<GpuProgressiveFrame>,
    /// End of the phase's first frame, seconds since the start.
    first_at_s: Option<f64>,
    converged_after: Option<(u64, f64)>,
}

impl Phase {
    fn json(&self, name: &str) -> serde_json::Value {
        let f = &self.frames;
        serde_json::json!({
            "phase": name,
            "frames": f.len(),
            "converged": self.converged_after.is_some(),
            "frames_to_converge": self.converged_after.map(|c| c.0),
            "seconds_to_converge": self.converged_after.map(|c| c.1),
            "wall_ms_median": median(&f.iter().map(|x| x.stats.total_ms).collect::<Vec<f64>>()),
            "wall_ms_max": f.iter().map(|x| x.stats.total_ms).fold(0.0, f64::max),
            "gpu_ms_median": median(&f.iter().filter_map(|x| x.gpu.map(|g| g.frame_ms)).collect::<Vec<f64>>()),
            "budget_median": median(&f.iter().map(|x| x.stats.filled as f64).collect::<Vec<f64>>()),
            "budget_max": f.iter().map(|x| x.stats.filled).max(),
            "reprojected_median": median(&f.iter().map(|x| x.stats.reprojected as f64).collect::<Vec<f64>>()),
            "fill_share_median": median(&f.iter().map(|x| x.stats.fill_ms / (x.stats.reproject_ms + x.stats.fill_ms + x.stats.prepare_ms).max(1e-9)).collect::<Vec<f64>>()),
        })
    }
}

#[allow(clippy::too_many_arguments)]
fn run_phase(
    ctx: &GpuContext,
    r: &mut GpuProgressive,
    name: &str,
    cam: &Camera,
    budget: &FillBudget,
    resolve: Option<&ResolveOptions>,
    max_frames: u64,
    start: Instant,
) -> Result<Phase> {
    let t = Instant::now();
    let mut frames = Vec::new();
    let mut converged_after = None;
    let mut first_at_s = None;
    while (frames.len() as u64) < max_frames {
        let f = r
            .frame(ctx, cam, &RasterOptions::default(), budget, resolve)
            .map_err(|e| anyhow!("{e}"))?;
        let at = start.elapsed().as_secs_f64();
        first_at_s.get_or_insert(at);
        println!("{}", frame_json(name, &f, at));
        frames.push(f);
        if f.stats.converged {
            converged_after = Some((frames.len() as u64, t.elapsed().as_secs_f64()));
            break;
        }
    }
    let p = Phase { frames, first_at_s, converged_after };
    let j = p.json(name);
    eprintln!(
        "{name:>6}: {} frames, converged {} after {:.3} s; wall {:.2} ms (median), GPU {:.2} ms, budget {:.2} M slots (median), Fill {:.0} % of the pass time",
        p.frames.len(),
        p.converged_after.is_some(),
        p.converged_after.map_or(f64::NAN, |c| c.1),
        j["wall_ms_median"].as_f64().unwrap_or(f64::NAN),
        j["gpu_ms_median"].as_f64().unwrap_or(f64::NAN),
        j["budget_median"].as_f64().unwrap_or(f64::NAN) / 1e6,
        j["fill_share_median"].as_f64().unwrap_or(f64::NAN) * 100.0
    );
    Ok(p)
}

/// Runs the benchmark the arguments describe.
pub fn run(a: Args) -> Result<()> {
    if !(a.points >= 1.0 && a.points < 4_294_967_296.0) {
        bail!("--points {}: 1 to 4294967295", a.points);
    }
    if a.piece == 0 {
        bail!("--piece 0: at least one point per piece");
    }
    let n = a.points as u64;
    let budget = match a.budget.as_str() {
        "auto" => FillBudget::Adaptive(AdaptiveBudget {
            target_ms: a.target_ms,
            probe_points: a.probe.max(1),
            usable: a.usable,
        }),
        b => match b.parse::<u64>() {
            Ok(v) if v > 0 => FillBudget::Fixed(v),
            _ => bail!("--budget '{b}': 'auto' or a positive number of slots"),
        },
    };
    let ctx =
        GpuContext::new(&GpuOptions { allow_software: a.allow_software, ..Default::default() })
            .map_err(|e| anyhow!("{e}"))?;
    let ad = ctx.adapter();
    eprintln!(
        "adapter: {} ({}, {}), driver {}, atomics {}, timestamps {}",
        ad.name,
        ad.backend,
        ad.device_type,
        ad.driver,
        ctx.atomic_path().name(),
        ctx.has_timestamps()
    );
    let max = [(EXTENT[0] * 1000.0) as i32, (EXTENT[1] * 1000.0) as i32, 120_000];
    let options = ProgressiveOptions {
        chunk_slots: a.chunk_slots,
        colors: !a.no_resolve,
        payloads: false,
        host_clock: false,
    };
    let start = Instant::now();
    let mut r =
        GpuProgressive::new(&ctx, GRID, [0, 0, 0], max, n, options).map_err(|e| anyhow!("{e}"))?;
    let alloc_seconds = start.elapsed().as_secs_f64();
    eprintln!(
        "{} points: {} chunks of {} slots, {:.2} GiB on the GPU, allocated in {:.2} s",
        n,
        r.chunk_count(),
        r.chunk_slots(),
        r.gpu_bytes() as f64 / (1u64 << 30) as f64,
        alloc_seconds
    );
    let bounds = {
        let w = |a: usize, v: i32| GRID.world(a, v as i64);
        Aabb::new([w(0, 0), w(1, 0), w(2, 20_000)], [w(0, max[0]), w(1, max[1]), w(2, 100_000)])
    };
    let cam =
        Camera::frame_perspective(&bounds, ViewPreset::Iso, 50f64.to_radians(), a.width, a.height)
            .map_err(|e| anyhow!("{e}"))?;
    let post = ResolveOptions { background: 0xff00_0000, ..Default::default() };
    let resolve = (!a.no_resolve).then_some(&post);

    // Generate and insert piece by piece, drawing a frame after each. With --pregenerate every
    // point is made first and loading runs from memory; with --prepare-thread the costly half
    // of each insert (checks, words, sorted slots) runs on another thread, a piece ahead, while
    // the render thread uploads and draws.
    let piece = a.piece.min(n as usize);
    let pieces: Vec<(u64, usize)> =
        (0..n).step_by(piece).map(|f| (f, (n - f).min(piece as u64) as usize)).collect();
    let t = Instant::now();
    let all = a.pregenerate.then(|| {
        let mut xyz = vec![[0i32; 3]; n as usize];
        let mut colors = vec![0u32; n as usize];
        generate(a.seed, 0, &mut xyz, &mut colors);
        (xyz, colors)
    });
    let pregenerate_s = t.elapsed().as_secs_f64();
    if a.pregenerate {
        eprintln!("generated {n} points in memory in {pregenerate_s:.2} s");
    }
    let preparer = r.preparer();
    let colored = !a.no_resolve;
    // Makes (or takes) piece `(f, m)` and prepares it; returns it and the seconds of each part.
    let make = |(f, m): (u64, usize)| -> Result<(mortar_render::PreparedInsert, f64, f64)> {
        let t = Instant::now();
        let own;
        let (xyz, colors): (&[[i32; 3]], &[u32]) = match &all {
            Some((x, c)) => (&x[f as usize..f as usize + m], &c[f as usize..f as usize + m]),
            None => {
                let mut x = vec![[0i32; 3]; m];
                let mut c = vec![0u32; m];
                generate(a.seed, f, &mut x, &mut c);
                own = (x, c);
                (&own.0, &own.1)
            }
        };
        let gen = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let p = preparer
            .prepare(f, xyz, colored.then_some(colors), None)
            .map_err(|e| anyhow!("{e}"))?;
        Ok((p, gen, t.elapsed().as_secs_f64()))
    };
    let (mut gen_s, mut prepare_s, mut insert_s) = (0.0, 0.0, 0.0);
    let mut insert_ms = Vec::new();
    let mut first_frame_s = None;
    let mut load_frames = Vec::new();
    let mut frame_ends = Vec::new();
    let load_start = Instant::now();
    let mut consume = |r: &mut GpuProgressive,
                       (p, g, pr): (mortar_render::PreparedInsert, f64, f64)|
     -> Result<()> {
        gen_s += g;
        prepare_s += pr;
        let done = p.first() + p.len() as u64;
        let t = Instant::now();
        r.insert_prepared(&ctx, p).map_err(|e| anyhow!("{e}"))?;
        insert_s += t.elapsed().as_secs_f64();
        insert_ms.push(t.elapsed().as_secs_f64() * 1e3);
        if !a.no_load_frames && done < n {
            let f = r
                .frame(&ctx, &cam, &RasterOptions::default(), &budget, resolve)
                .map_err(|e| anyhow!("{e}"))?;
            println!("{}", frame_json("load", &f, start.elapsed().as_secs_f64()));
            first_frame_s.get_or_insert(start.elapsed().as_secs_f64());
            frame_ends.push(load_start.elapsed().as_secs_f64());
            load_frames.push(f);
        }
        Ok(())
    };
    if a.prepare_thread {
        std::thread::scope(|sc| -> Result<()> {
            let (tx, rx) = std::sync::mpsc::sync_channel(1);
            let producer = sc.spawn(move || {
                for &pc in &pieces {
                    if tx.send(make(pc)).is_err() {
                        break;
                    }
                }
            });
            for got in rx {
                consume(&mut r, got?)?;
            }
            producer.join().map_err(|_| anyhow!("the preparing thread panicked"))
        })?;
    } else {
        for &pc in &pieces {
            consume(&mut r, make(pc)?)?;
        }
    }
    ctx.wait().map_err(|e| anyhow!("{e}"))?;
    let load_s = load_start.elapsed().as_secs_f64();
    let loaded_s = start.elapsed().as_secs_f64();
    let intervals: Vec<f64> = frame_ends.windows(2).map(|w| (w[1] - w[0]) * 1e3).collect();
    let bpp = if a.no_resolve { 12.0 } else { 16.0 };
    eprintln!(
        "loaded in {load_s:.2} s ({:.0} M points/s, {:.1} GB/s of records): generated {gen_s:.2} s, prepared {prepare_s:.2} s{}, inserted {insert_s:.2} s on the render thread (a piece {:.1} ms median); {} frames while loading, wall {:.2} ms median, {:.2} ms max, one every {:.2} ms (median)",
        n as f64 / load_s / 1e6,
        n as f64 * bpp / load_s / 1e9,
        if a.prepare_thread { " on another thread" } else { "" },
        median(&insert_ms),
        load_frames.len(),
        median(&load_frames.iter().map(|f| f.stats.total_ms).collect::<Vec<f64>>()),
        load_frames.iter().map(|f| f.stats.total_ms).fold(0.0, f64::max),
        median(&intervals)
    );

    let still = run_phase(&ctx, &mut r, "still", &cam, &budget, resolve, a.max_frames, start)?;
    let first_frame_s = first_frame_s.or(still.first_at_s);
    // The moved camera: the eye orbited around the target and 20 % closer.
    let (s, c) = a.orbit_degrees.to_radians().sin_cos();
    let d = [0, 1, 2].map(|k| cam.eye[k] - cam.target[k]);
    let moved = Camera {
        eye: [
            cam.target[0] + 0.8 * (c * d[0] - s * d[1]),
            cam.target[1] + 0.8 * (s * d[0] + c * d[1]),
            cam.target[2] + 0.8 * d[2],
        ],
        ..cam
    };
    let moved_phase =
        run_phase(&ctx, &mut r, "moved", &moved, &budget, resolve, a.max_frames, start)?;
    let summary = serde_json::json!({
        "summary": true,
        "adapter": ad.name,
        "driver": ad.driver,
        "timing": r.timing().name(),
        "points": n,
        "chunks": r.chunk_count(),
        "gpu_bytes": r.gpu_bytes(),
        "width": a.width,
        "height": a.height,
        "budget": a.budget,
        "target_ms": a.target_ms,
        "probe": a.probe,
        "usable": a.usable,
        "allocate_seconds": alloc_seconds,
        "pregenerate": a.pregenerate,
        "pregenerate_seconds": pregenerate_s,
        "prepare_thread": a.prepare_thread,
        "generate_seconds": gen_s,
        "prepare_seconds": prepare_s,
        "insert_seconds": insert_s,
        "load_seconds": load_s,
        "load_points_per_second": n as f64 / load_s,
        "load_frame_interval_ms_median": median(&intervals),
        "load_frame_interval_ms_max": intervals.iter().copied().fold(0.0, f64::max),
        "loaded_seconds": loaded_s,
        "first_frame_seconds": first_frame_s,
        "insert_bytes_per_point": bpp,
        "insert_piece_ms_median": median(&insert_ms),
        "insert_piece_ms_max": insert_ms.iter().copied().fold(0.0, f64::max),
        "load_frames": load_frames.len(),
        "load_frame_wall_ms_median": median(&load_frames.iter().map(|f| f.stats.total_ms).collect::<Vec<f64>>()),
        "load_frame_wall_ms_max": load_frames.iter().map(|f| f.stats.total_ms).fold(0.0, f64::max),
        "still": still.json("still"),
        "moved": moved_phase.json("moved"),
    });
    println!("{summary}");
    Ok(())
}
