//! The GPU progressive renderer (paper 000) against the CPU one and the brute-force rasterizer:
//! with a still camera and a fixed budget the GPU keys, visible slots and frame statistics equal
//! the CPU progressive renderer's frame by frame (several chunks, split dispatches) and, after
//! `ceil(points / budget)` frames, the brute-force `rasterize` of all points; points inserted
//! between frames show up and converge; a moved camera (of another size) reprojects and
//! converges again; the GPU resolve equals the CPU resolve; the adaptive budget runs and says how
//! it was timed; a 32-bit context and bad input are errors, not panics.
//!
//! Runs on any adapter with 64-bit atomics, software ones included (lavapipe in CI). Skips with a
//! printed reason only where no such adapter exists, unless `MORTAR_REQUIRE_GPU` is set (CI).

use mortar_core::grid::Grid;
use mortar_core::render::framebuffer::EMPTY_KEY;
use mortar_core::render::progressive::{
    AdaptiveBudget, FillBudget, FrameStats, ProgressiveError, ProgressiveRenderer,
};
use mortar_core::render::resolve::{resolve_with_colors, ResolveOptions};
use mortar_core::render::testutil::{Rng, Scene};
use mortar_core::render::{rasterize, Aabb, Camera, Framebuffer, RasterOptions, ViewPreset};
use mortar_render::{
    AtomicPath, BudgetTiming, GpuContext, GpuError, GpuProgressive, ProgressiveGpuError,
    ProgressiveOptions,
};

/// A resolve onto `background` without post-processing.
fn bg(background: u32) -> ResolveOptions {
    ResolveOptions { background, ..Default::default() }
}

fn context(max_dispatch: Option<u32>) -> Option<GpuContext> {
    mortar_render::testing::context_or_skip(AtomicPath::U64, max_dispatch)
}

fn int_bounds(points: &[[i32; 3]]) -> ([i32; 3], [i32; 3]) {
    let mut lo = [i32::MAX; 3];
    let mut hi = [i32::MIN; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (lo, hi)
}

fn terrain(n: usize, seed: u64) -> Scene {
    Scene::terrain(n, seed, Grid { scale: [0.001; 3], offset: [500_000.0, 5_400_000.0, 0.0] })
}

/// A GPU and a CPU renderer over the scene's frame (nothing inserted).
fn pair(
    ctx: &GpuContext,
    scene: &Scene,
    chunk_slots: Option<u32>,
) -> (GpuProgressive, ProgressiveRenderer) {
    let (lo, hi) = int_bounds(&scene.points);
    let n = scene.points.len() as u64;
    let gpu = GpuProgressive::new(
        ctx,
        scene.grid,
        lo,
        hi,
        n,
        ProgressiveOptions { chunk_slots, colors: true, payloads: true, host_clock: false },
    )
    .unwrap();
    let cpu = ProgressiveRenderer::new(scene.grid, lo, hi, n).unwrap();
    (gpu, cpu)
}

/// Inserts points `s..e` into both renderers (payload = input index, colour = the scene's).
fn insert(
    ctx: &GpuContext,
    gpu: &mut GpuProgressive,
    cpu: &mut ProgressiveRenderer,
    scene: &Scene,
    s: usize,
    e: usize,
) {
    let payload: Vec<u64> = (s as u64..e as u64).collect();
    gpu.insert(ctx, s as u64, &scene.points[s..e], Some(&scene.colors[s..e]), Some(&payload))
        .unwrap();
    cpu.insert(s as u64, &scene.points[s..e], &payload).unwrap();
}

/// The statistics both renderers must agree on (times and rasterizer batch counts apart).
fn comparable(s: &FrameStats) -> (u64, u64, u64, u64, u64, u64, u64, bool, u64, [u64; 3]) {
    (
        s.frame,
        s.loaded,
        s.reprojected,
        s.filled,
        s.fill_points,
        s.probe,
        s.visible,
        s.converged,
        s.raster.points_drawn,
        s.raster.points_by_precision,
    )
}

/// One frame on both; asserts equal keys, visible slots and statistics.
fn frame_both(
    ctx: &GpuContext,
    gpu: &mut GpuProgressive,
    cpu: &mut ProgressiveRenderer,
    cam: &Camera,
    budget: u64,
    what: &str,
) -> FrameStats {
    let opts = RasterOptions::default();
    let g = gpu.frame(ctx, cam, &opts, &FillBudget::Fixed(budget), Some(&bg(0xff00_0000))).unwrap();
    let c = cpu.frame(cam, &opts, &FillBudget::Fixed(budget)).unwrap();
    assert_eq!(comparable(&g.stats), comparable(&c), "{what}: frame statistics");
    assert_eq!(gpu.read_keys(ctx).unwrap(), cpu.keys(), "{what}: keys of frame {}", c.frame);
    assert_eq!(
        gpu.read_visible(ctx).unwrap(),
        cpu.visible(),
        "{what}: visible slots of frame {}",
        c.frame
    );
    assert_eq!(
        g.timing,
        if ctx.has_timestamps() { BudgetTiming::GpuTimestamps } else { BudgetTiming::HostClock }
    );
    g.stats
}

fn brute_force(cpu: &ProgressiveRenderer, cam: &Camera) -> Vec<u64> {
    let fb = Framebuffer::new(cam.width, cam.height);
    rasterize(
        &fb,
        &cpu.all_points().expect("all loaded"),
        cpu.grid(),
        cam,
        &RasterOptions::default(),
    )
    .unwrap();
    fb.into_keys()
}

fn covered(keys: &[u64]) -> usize {
    keys.iter().filter(|&&k| k != EMPTY_KEY).count()
}

/// Colours by slot: the scene's colour of the point each slot holds.
fn slot_colors(gpu: &GpuProgressive, scene: &Scene) -> Vec<u32> {
    let mut c = vec![0; scene.points.len()];
    for i in 0..scene.points.len() as u32 {
        c[gpu.shuffle().target(i) as usize] = scene.colors[i as usize];
    }
    c
}

#[test]
fn still_camera_fixed_budget_equals_cpu_frame_by_frame_and_brute_force() {
    // Four chunks (30,000 slots each) and dispatches split at 5 workgroups per dimension.
    let Some(ctx) = context(Some(5)) else { return };
    let scene = terrain(110_000, 5);
    let (mut gpu, mut cpu) = pair(&ctx, &scene, Some(30_000));
    assert_eq!(gpu.chunk_count(), 4);
    insert(&ctx, &mut gpu, &mut cpu, &scene, 0, scene.points.len());
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 320, 240).unwrap();
    let budget = 25_000;
    let frames = 110_000u64.div_ceil(budget);
    let mut last = FrameStats::default();
    for k in 1..=frames {
        last = frame_both(&ctx, &mut gpu, &mut cpu, &cam, budget, "still");
        assert_eq!(last.converged, k == frames, "frame {k}");
    }
    assert!(gpu.converged());
    let keys = gpu.read_keys(&ctx).unwrap();
    assert_eq!(keys, brute_force(&cpu, &cam), "converged keys against the brute-force render");
    assert!(covered(&keys) > 10_000, "{} pixels", covered(&keys));
    assert_eq!(last.visible as usize, covered(&keys));
    // The GPU resolve colours each pixel with its slot's colour.
    let want = resolve_with_colors(
        &keys,
        cam.width,
        cam.height,
        &slot_colors(&gpu, &scene),
        &ResolveOptions { background: 0xff00_0000, ..Default::default() },
    );
    assert_eq!(gpu.read_image(&ctx).unwrap(), want);
    assert_eq!(gpu.size(), (320, 240));
    assert!(gpu.image_buffer().is_some());
    // Payloads travel with their point.
    for slot in gpu.read_visible(&ctx).unwrap().into_iter().take(2000) {
        assert_eq!(gpu.payload(slot), cpu.payload(slot));
    }
    // Still converged, and the same, one frame later (Reproject keeps it).
    let st = frame_both(&ctx, &mut gpu, &mut cpu, &cam, budget, "still, after");
    assert!(st.converged && st.reprojected == st.visible);
}

/// A large insert prepared on another thread (slots sorted for the host's bits, computed again
/// by the scatter pass across four chunks) then a small one at the end: the frame equals the CPU
/// renderer's.
#[test]
fn a_large_insert_across_chunks_equals_cpu() {
    let Some(ctx) = context(None) else { return };
    let scene = terrain(400_000, 21);
    let (mut gpu, mut cpu) = pair(&ctx, &scene, Some(100_000));
    assert_eq!(gpu.chunk_count(), 4);
    // The first 300,000 prepared on another thread (as a loader would), then inserted.
    let preparer = gpu.preparer();
    let payload: Vec<u64> = (0..300_000).collect();
    let prepared = std::thread::scope(|s| {
        s.spawn(|| {
            preparer.prepare(
                0,
                &scene.points[..300_000],
                Some(&scene.colors[..300_000]),
                Some(&payload),
            )
        })
        .join()
        .unwrap()
    })
    .unwrap();
    assert_eq!((prepared.first(), prepared.len()), (0, 300_000));
    // Points prepared for another renderer are refused.
    let (other, _) = pair(&ctx, &terrain(1000, 2), None);
    let foreign = other
        .preparer()
        .prepare(0, &terrain(1000, 2).points, Some(&terrain(1000, 2).colors), Some(&vec![0; 1000]))
        .unwrap();
    assert!(gpu.insert_prepared(&ctx, foreign).is_err());
    assert_eq!(gpu.loaded(), 0);
    gpu.insert_prepared(&ctx, prepared).unwrap();
    cpu.insert(0, &scene.points[..300_000], &payload).unwrap();
    assert!(matches!(
        gpu.insert(
            &ctx,
            299_999,
            &scene.points[299_999..300_001],
            Some(&scene.colors[299_999..300_001]),
            Some(&[0, 0])
        ),
        Err(ProgressiveGpuError::Progressive(ProgressiveError::Duplicate(299_999)))
    ));
    insert(&ctx, &mut gpu, &mut cpu, &scene, 300_000, 400_000);
    assert_eq!(gpu.loaded(), 400_000);
    assert!((0..400_000).all(|s| gpu.is_loaded(s)));
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 320, 240).unwrap();
    let st = frame_both(&ctx, &mut gpu, &mut cpu, &cam, 400_000, "large insert");
    assert!(st.converged && st.fill_points == 400_000);
    assert_eq!(gpu.read_keys(&ctx).unwrap(), brute_force(&cpu, &cam));
    for slot in gpu.read_visible(&ctx).unwrap().into_iter().take(5000) {
        assert_eq!(gpu.payload(slot), cpu.payload(slot));
    }
}

#[test]
fn points_inserted_between_frames_show_up_and_converge() {
    let Some(ctx) = context(None) else { return };
    let scene = terrain(90_000, 13);
    let (mut gpu, mut cpu) = pair(&ctx, &scene, Some(40_000));
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 300, 200).unwrap();
    let pieces: Vec<(usize, usize)> = (0..scene.points.len())
        .step_by(7_000)
        .map(|s| (s, (s + 7_000).min(scene.points.len())))
        .collect();
    let mut order: Vec<usize> = (0..pieces.len()).collect();
    let mut rng = Rng(3);
    for i in (1..order.len()).rev() {
        order.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
    }
    let mut shown = 0;
    for (k, &p) in order.iter().enumerate() {
        let (s, e) = pieces[p];
        insert(&ctx, &mut gpu, &mut cpu, &scene, s, e);
        let st = frame_both(&ctx, &mut gpu, &mut cpu, &cam, 11_000, "loading");
        let all = gpu.loaded() == scene.points.len() as u64;
        assert!(
            st.fill_points < st.filled || all,
            "frame {}: slots of points not yet loaded are skipped",
            k + 1
        );
        assert!(!st.converged);
        assert!(st.visible >= shown, "what arrived stays visible");
        shown = st.visible;
        assert!(gpu.read_visible(&ctx).unwrap().iter().all(|&slot| gpu.is_loaded(slot)));
    }
    assert_eq!(gpu.loaded(), scene.points.len() as u64);
    let mut extra = 0;
    while !frame_both(&ctx, &mut gpu, &mut cpu, &cam, 11_000, "loaded").converged {
        extra += 1;
        assert!(extra <= 10, "no convergence 10 frames after loading ended");
    }
    assert_eq!(gpu.read_keys(&ctx).unwrap(), brute_force(&cpu, &cam));
}

#[test]
fn a_moved_camera_reprojects_and_converges_again() {
    let Some(ctx) = context(None) else { return };
    let scene = terrain(100_000, 17);
    let (mut gpu, mut cpu) = pair(&ctx, &scene, Some(64_000));
    insert(&ctx, &mut gpu, &mut cpu, &scene, 0, scene.points.len());
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 320, 240).unwrap();
    for _ in 0..4 {
        frame_both(&ctx, &mut gpu, &mut cpu, &cam, 25_000, "before the move");
    }
    assert!(gpu.converged());
    // Closer and of another size: the old view's visible points are drawn first, then the fill
    // completes the image; after ceil(points / budget) frames it is final again.
    // (More pixels than before: the visible lists grow and keep their entries.)
    let moved = Camera::close_up(&scene.bounds, 0.8, 400, 260).unwrap();
    let st = frame_both(&ctx, &mut gpu, &mut cpu, &moved, 25_000, "moved");
    assert!(st.reprojected > 10_000 && !st.converged, "{st:?}");
    let mut frames = 1;
    while !frame_both(&ctx, &mut gpu, &mut cpu, &moved, 25_000, "moved").converged {
        frames += 1;
        assert!(frames < 10);
    }
    assert_eq!(frames + 1, 4, "ceil(100000 / 25000) frames after the move");
    assert_eq!(gpu.read_keys(&ctx).unwrap(), brute_force(&cpu, &moved));
    // And back: a camera looking away from the data culls everything and draws nothing.
    let c = scene.bounds.center();
    let away = Camera {
        eye: [c[0], c[1], c[2] + 1000.0],
        target: [c[0], c[1], c[2] + 2000.0],
        up: [0.0, 1.0, 0.0],
        ..moved
    };
    let st = frame_both(&ctx, &mut gpu, &mut cpu, &away, 25_000, "looking away");
    assert_eq!((st.visible, st.raster.points_drawn), (0, 0));
}

#[test]
fn adaptive_budget_runs_and_says_how_it_was_timed() {
    let Some(ctx) = context(None) else { return };
    let scene = terrain(80_000, 23);
    for host_clock in [false, true] {
        adaptive_budget_with(&ctx, &scene, host_clock);
    }
}

/// The adaptive budget's checks, timed by GPU timestamps where the device has them (or with
/// `host_clock` by the host's clock, the fallback for devices without).
fn adaptive_budget_with(ctx: &GpuContext, scene: &Scene, host_clock: bool) {
    let (lo, hi) = int_bounds(&scene.points);
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 200, 150).unwrap();
    let make = || {
        let mut g = GpuProgressive::new(
            ctx,
            scene.grid,
            lo,
            hi,
            80_000,
            ProgressiveOptions {
                chunk_slots: Some(50_000),
                colors: true,
                payloads: false,
                host_clock,
            },
        )
        .unwrap();
        g.insert(ctx, 0, &scene.points, Some(&scene.colors), None).unwrap();
        g
    };
    let want = {
        let mut c = ProgressiveRenderer::new(scene.grid, lo, hi, 80_000).unwrap();
        c.insert(0, &scene.points, &vec![0; 80_000]).unwrap();
        brute_force(&c, &cam)
    };
    let timing = if ctx.has_timestamps() && !host_clock {
        BudgetTiming::GpuTimestamps
    } else {
        BudgetTiming::HostClock
    };
    assert_eq!(make().timing(), timing);
    // No time at all: only the probe is filled, so it converges after ceil(n / probe) frames.
    let mut g = make();
    let none =
        FillBudget::Adaptive(AdaptiveBudget { target_ms: 0.0, probe_points: 30_000, usable: 0.9 });
    let st: Vec<_> = (0..3)
        .map(|_| g.frame(ctx, &cam, &RasterOptions::default(), &none, None).unwrap())
        .collect();
    for f in &st {
        assert_eq!((f.stats.probe, f.stats.filled), (30_000, 30_000));
        assert_eq!(f.timing, timing);
        assert_eq!(f.gpu.is_some(), timing == BudgetTiming::GpuTimestamps);
        assert!(f.stats.fill_ms > 0.0 && f.stats.total_ms > 0.0, "{:?}", f.stats);
    }
    assert!(!st[1].stats.converged && st[2].stats.converged);
    assert_eq!(g.read_keys(ctx).unwrap(), want);
    // A generous target: the probe, then the rest of the buffer in the same frame.
    let mut g = make();
    let lots =
        FillBudget::Adaptive(AdaptiveBudget { target_ms: 1e6, probe_points: 1_000, usable: 0.9 });
    let f = g.frame(ctx, &cam, &RasterOptions::default(), &lots, Some(&bg(0))).unwrap();
    assert_eq!((f.stats.probe, f.stats.filled, f.stats.fill_points), (1_000, 80_000, 80_000));
    assert!(f.stats.converged);
    assert_eq!(g.read_keys(ctx).unwrap(), want);
    if let Some(t) = f.gpu {
        eprintln!("GPU timings of a whole-buffer frame: {t:?}");
        assert!(t.probe_ms >= 0.0 && t.extra_fill_ms > 0.0 && t.resolve_ms.is_some());
        assert!(
            t.frame_ms >= t.reproject_ms + t.probe_ms + t.extra_fill_ms + t.prepare_ms - 1e-6,
            "{t:?}"
        );
    }
    // A realistic target: the frames stay about within it and the image converges.
    let mut g = make();
    let target =
        FillBudget::Adaptive(AdaptiveBudget { target_ms: 50.0, probe_points: 5_000, usable: 0.9 });
    let mut frames = 0;
    while !g.frame(ctx, &cam, &RasterOptions::default(), &target, None).unwrap().stats.converged {
        frames += 1;
        assert!(frames < 200, "no convergence in 200 frames");
    }
    assert_eq!(g.read_keys(ctx).unwrap(), want);
}

#[test]
fn a_32_bit_context_is_refused() {
    let Some(ctx) = mortar_render::testing::context_or_skip(AtomicPath::TwoPass32, None) else {
        return;
    };
    let grid = Grid { scale: [0.01; 3], offset: [0.0; 3] };
    let e = GpuProgressive::new(&ctx, grid, [0; 3], [100; 3], 10, ProgressiveOptions::default())
        .err()
        .expect("refused");
    assert!(matches!(e, ProgressiveGpuError::Needs64BitAtomics { .. }));
    assert!(e.to_string().contains("needs 64-bit atomics"), "{e}");
}

#[test]
fn bad_input_is_refused_without_changes() {
    let Some(ctx) = context(None) else { return };
    let grid = Grid { scale: [0.01; 3], offset: [0.0; 3] };
    let opts =
        ProgressiveOptions { chunk_slots: None, colors: true, payloads: false, host_clock: false };
    let progressive = |r: Result<_, ProgressiveGpuError>| match r {
        Err(ProgressiveGpuError::Progressive(e)) => e,
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("accepted"),
    };
    assert!(matches!(
        progressive(GpuProgressive::new(&ctx, grid, [0; 3], [10; 3], 1 << 32, opts).map(|_| ())),
        ProgressiveError::TooManyPoints(_)
    ));
    assert!(matches!(
        progressive(GpuProgressive::new(&ctx, grid, [0; 3], [-1, 5, 5], 10, opts).map(|_| ())),
        ProgressiveError::Frame { .. }
    ));
    let mut r = GpuProgressive::new(&ctx, grid, [0; 3], [100; 3], 10, opts).unwrap();
    let p = [[1, 2, 3], [4, 5, 6]];
    let red = [0xff00_00ffu32; 2];
    assert!(matches!(
        progressive(r.insert(&ctx, 9, &p, Some(&red), None)),
        ProgressiveError::IndexRange { .. }
    ));
    // Points outside the frame grow it (`a_frame_that_grows_...`), except past 30 bits; a
    // prepared insert, encoded off the renderer's thread, must lie in the frame it was prepared for.
    assert!(matches!(
        progressive(r.insert(&ctx, 0, &[[1, 2, 3], [4, 1 << 30, 6]], Some(&red), None)),
        ProgressiveError::Frame { .. }
    ));
    assert!(matches!(
        progressive(
            r.preparer().prepare(0, &[[1, 2, 3], [4, 101, 6]], Some(&red), None).map(|_| ())
        ),
        ProgressiveError::OutsideFrame { index: 1, .. }
    ));
    assert_eq!(r.growths(), 0);
    assert!(matches!(
        progressive(r.insert(&ctx, 0, &p, Some(&red), Some(&[1, 2]))),
        ProgressiveError::PayloadCount { .. }
    ));
    assert!(matches!(
        r.insert(&ctx, 0, &p, None, None),
        Err(ProgressiveGpuError::Gpu(GpuError::Colors(_)))
    ));
    assert!(matches!(
        r.insert(&ctx, 0, &p, Some(&red[..1]), None),
        Err(ProgressiveGpuError::Gpu(GpuError::Colors(_)))
    ));
    assert_eq!(r.loaded(), 0);
    r.insert(&ctx, 3, &p, Some(&red), None).unwrap();
    assert!(matches!(
        progressive(r.insert(&ctx, 4, &p, Some(&red), None)),
        ProgressiveError::Duplicate(4)
    ));
    assert_eq!(r.loaded(), 2);
    assert!(r.is_loaded(r.shuffle().target(3)) && !r.is_loaded(r.shuffle().target(0)));
    // An unusable camera, a framebuffer past the device's binding, a resolve without colours.
    let cam = Camera::frame_orthographic(&Aabb::new([0.0; 3], [1.0; 3]), ViewPreset::Top, 16, 16)
        .unwrap();
    let bad = Camera { far: cam.near, ..cam };
    assert!(matches!(
        progressive(
            r.frame(&ctx, &bad, &RasterOptions::default(), &FillBudget::Fixed(4), None).map(|_| ())
        ),
        ProgressiveError::Raster(_)
    ));
    let huge = Camera { width: 16384, height: 16384, ..cam };
    assert!(
        matches!(
            r.frame(&ctx, &huge, &RasterOptions::default(), &FillBudget::Fixed(4), None),
            Err(ProgressiveGpuError::Gpu(GpuError::TooLarge { .. }))
        ) || ctx.max_binding() >= 16384 * 16384 * 8
    );
    let mut plain =
        GpuProgressive::new(&ctx, grid, [0; 3], [100; 3], 10, ProgressiveOptions::default())
            .unwrap();
    assert!(matches!(
        plain.frame(&ctx, &cam, &RasterOptions::default(), &FillBudget::Fixed(4), Some(&bg(0))),
        Err(ProgressiveGpuError::Gpu(GpuError::Colors(_)))
    ));
    assert!(plain.read_image(&ctx).is_err());
    // An empty renderer draws empty frames and is converged.
    let mut e = GpuProgressive::new(&ctx, grid, [0; 3], [0; 3], 0, opts).unwrap();
    let f = e
        .frame(
            &ctx,
            &cam,
            &RasterOptions::default(),
            &FillBudget::Fixed(100),
            Some(&bg(0xff11_2233)),
        )
        .unwrap();
    assert!(f.stats.converged && f.stats.visible == 0);
    assert!(e.read_keys(&ctx).unwrap().iter().all(|&k| k == EMPTY_KEY));
    assert!(e.read_image(&ctx).unwrap().iter().all(|&c| c == 0xff11_2233));
}

#[test]
fn recolor_streams_new_colours_in_and_keeps_the_positions() {
    // Three chunks; the new colours arrive in two pieces, in input order, as a loader delivers them.
    let Some(ctx) = context(None) else { return };
    let scene = terrain(60_000, 21);
    let (mut gpu, mut cpu) = pair(&ctx, &scene, Some(25_000));
    insert(&ctx, &mut gpu, &mut cpu, &scene, 0, scene.points.len());
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 200, 150).unwrap();
    frame_both(&ctx, &mut gpu, &mut cpu, &cam, 60_000, "before");
    let keys = gpu.read_keys(&ctx).unwrap();
    let opts = ResolveOptions { background: 0xff00_0000, ..Default::default() };
    let new_colors: Vec<u32> = scene.colors.iter().map(|c| !c | 0xff00_0000).collect();
    // First half: pixels of the first half's points take their new colour, the others keep theirs.
    gpu.recolor(&ctx, 0, &new_colors[..30_000]).unwrap();
    frame_both(&ctx, &mut gpu, &mut cpu, &cam, 60_000, "half");
    assert_eq!(gpu.read_keys(&ctx).unwrap(), keys, "recolouring moved points");
    let mut by_slot = slot_colors(&gpu, &scene);
    for i in 0..30_000u32 {
        by_slot[gpu.shuffle().target(i) as usize] = new_colors[i as usize];
    }
    assert_eq!(
        gpu.read_image(&ctx).unwrap(),
        resolve_with_colors(&keys, cam.width, cam.height, &by_slot, &opts)
    );
    gpu.recolor(&ctx, 30_000, &new_colors[30_000..]).unwrap();
    frame_both(&ctx, &mut gpu, &mut cpu, &cam, 60_000, "all");
    for i in 30_000..60_000u32 {
        by_slot[gpu.shuffle().target(i) as usize] = new_colors[i as usize];
    }
    assert_eq!(
        gpu.read_image(&ctx).unwrap(),
        resolve_with_colors(&keys, cam.width, cam.height, &by_slot, &opts)
    );
    // Points not inserted and ranges past the end are refused.
    let (mut fresh, _) = pair(&ctx, &scene, None);
    assert!(fresh.recolor(&ctx, 0, &new_colors[..10]).is_err());
    assert!(gpu.recolor(&ctx, 59_990, &new_colors[..20]).is_err());
}

#[test]
fn a_frame_that_grows_for_points_outside_it_equals_cpu_frame_by_frame() {
    // Framed for a tenth of the scene (a header that lies); pieces arrive between frames, most of
    // them outside: both renderers grow their frame alike (the GPU re-encodes its slots with the
    // reframe pass, three chunks), and keys, visible slots and statistics stay equal; converged,
    // the keys are the brute force of all points.
    let Some(ctx) = context(None) else { return };
    let scene = terrain(90_000, 31);
    let (lo, hi) = int_bounds(&scene.points);
    let small = mortar_core::render::framing::IntBox {
        min: lo,
        max: [0, 1, 2].map(|a| lo[a] + (hi[a] - lo[a]) / 10),
    };
    let frame =
        mortar_core::render::progressive::ProgressiveFrame::around(scene.grid, small).unwrap();
    let n = scene.points.len() as u64;
    let mut gpu = GpuProgressive::with_frame(
        &ctx,
        frame,
        n,
        ProgressiveOptions {
            chunk_slots: Some(32_768),
            colors: true,
            payloads: true,
            host_clock: false,
        },
    )
    .unwrap();
    let mut cpu = ProgressiveRenderer::with_frame(frame, n).unwrap();
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 256, 192).unwrap();
    for s in (0..scene.points.len()).step_by(15_000) {
        insert(&ctx, &mut gpu, &mut cpu, &scene, s, (s + 15_000).min(scene.points.len()));
        assert_eq!(gpu.frame_state(), cpu.frame_state());
        frame_both(&ctx, &mut gpu, &mut cpu, &cam, 20_000, "growing");
    }
    assert!(gpu.growths() >= 1 && gpu.growths() == cpu.growths(), "{} growths", gpu.growths());
    while !frame_both(&ctx, &mut gpu, &mut cpu, &cam, 20_000, "grown").converged {}
    assert_eq!(gpu.read_keys(&ctx).unwrap(), brute_force(&cpu, &cam));
    assert_eq!(gpu.depth_ties(&ctx).unwrap(), cpu.depth_ties().unwrap());
}

#[test]
fn the_ties_pass_counts_what_the_cpu_counts() {
    // Pixels whose winner has a twin in depth, in a perspective view and a top view (where the
    // depth is the height, 1 mm steps here, and many points of a pixel share it).
    let Some(ctx) = context(None) else { return };
    let scene = terrain(80_000, 12);
    let (mut gpu, mut cpu) = pair(&ctx, &scene, Some(32_768));
    assert_eq!(gpu.depth_ties(&ctx).unwrap(), None, "nothing drawn yet");
    insert(&ctx, &mut gpu, &mut cpu, &scene, 0, scene.points.len());
    for cam in [
        Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 320, 240).unwrap(),
        Camera::frame_orthographic(&scene.bounds, ViewPreset::Top, 320, 240).unwrap(),
    ] {
        while !frame_both(&ctx, &mut gpu, &mut cpu, &cam, 40_000, "ties").converged {}
        let ties = cpu.depth_ties().unwrap().unwrap();
        assert_eq!(gpu.depth_ties(&ctx).unwrap(), Some(ties));
        eprintln!("{ties} ties");
    }
    assert!(cpu.depth_ties().unwrap().unwrap() > 0, "the top view has ties");
}

#[test]
fn hole_filling_and_eye_dome_lighting_equal_the_cpu_resolve() {
    // The GPU renderer's resolve runs the batch rasterizer's hole-fill and eye-dome passes on its
    // own keys: its image equals the CPU resolve of the same keys, alone and together, with the
    // colours by slot (two chunks).
    use mortar_core::render::resolve::{EyeDome, HoleFill};
    let Some(ctx) = context(None) else { return };
    let scene = terrain(60_000, 8);
    let (mut gpu, mut cpu) = pair(&ctx, &scene, Some(32_768));
    insert(&ctx, &mut gpu, &mut cpu, &scene, 0, scene.points.len());
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 300, 200).unwrap();
    let colors = slot_colors(&gpu, &scene);
    let cases = [
        ResolveOptions {
            background: 0xff20_3040,
            hole_fill: Some(HoleFill { min_neighbors: 3 }),
            eye_dome: None,
        },
        ResolveOptions {
            background: 0xff00_0000,
            hole_fill: None,
            eye_dome: Some(EyeDome { strength: 1.5, ..EyeDome::default() }),
        },
        ResolveOptions {
            background: 0,
            hole_fill: Some(HoleFill { min_neighbors: 1 }),
            eye_dome: Some(EyeDome::default()),
        },
    ];
    for post in &cases {
        let f = gpu
            .frame(&ctx, &cam, &RasterOptions::default(), &FillBudget::Fixed(60_000), Some(post))
            .unwrap();
        assert!(f.stats.converged);
        let keys = gpu.read_keys(&ctx).unwrap();
        let want = resolve_with_colors(&keys, cam.width, cam.height, &colors, post);
        let got = gpu.read_image(&ctx).unwrap();
        let differ = got.iter().zip(&want).filter(|(a, b)| a != b).count();
        assert_eq!(differ, 0, "{post:?}: {differ} pixels differ from the CPU resolve");
        // Not a no-op: the post-processing changed the image.
        let plain =
            resolve_with_colors(&keys, cam.width, cam.height, &colors, &bg(post.background));
        assert!(plain.iter().zip(&want).filter(|(a, b)| a != b).count() > 100, "{post:?}");
    }
}
