//! The GPU rasterizer against the CPU reference on the same scenes and views: identical keys
//! (winning point per pixel and its depth) on both atomic paths, with chunked buffers and split
//! dispatches, and the resolve passes (hole filling, colours, eye-dome lighting) against the CPU
//! resolve, byte for byte.
//!
//! Runs on any adapter, software ones included (lavapipe in CI). Skips with a printed reason only
//! where no adapter exists at all, unless `MORTAR_REQUIRE_GPU` is set (CI sets it).

use mortar_core::grid::Grid;
use mortar_core::quantize::Precision;
use mortar_core::render::framebuffer::{key_depth, key_index, EMPTY_KEY};
use mortar_core::render::resolve::{
    fill_holes, resolve_with_colors, EyeDome, HoleFill, ResolveOptions,
};
use mortar_core::render::testutil::Scene;
use mortar_core::render::{
    rasterize, Camera, Framebuffer, PrecisionMode, RasterOptions, RasterStats, ViewPreset,
};
use mortar_render::{
    AtomicPath, DrawTuning, GpuContext, GpuError, GpuRasterizer, GpuScene, RecordOrder,
    SceneOptions,
};

fn context(atomics: AtomicPath, max_dispatch: Option<u32>) -> Option<GpuContext> {
    mortar_render::testing::context_or_skip(atomics, max_dispatch)
}

fn cpu_keys(scene: &Scene, cam: &Camera, opts: &RasterOptions) -> (Vec<u64>, RasterStats) {
    let fb = Framebuffer::new(cam.width, cam.height);
    let stats = rasterize(&fb, &scene.refs(), &scene.grid, cam, opts).unwrap();
    (fb.into_keys(), stats)
}

fn upload(ctx: &GpuContext, scene: &Scene, chunk_points: Option<u32>) -> GpuScene {
    let mut g = GpuScene::new(
        ctx,
        scene.grid,
        scene.points.len() as u64,
        SceneOptions { chunk_points, colors: true },
    )
    .unwrap();
    for b in scene.refs() {
        let s = b.first_index as usize;
        g.push(ctx, &b, Some(&scene.colors[s..s + b.len()])).unwrap();
    }
    g
}

/// Pixels whose winner differs, split into exact depth ties (same depth, other index) and others.
fn compare(gpu: &[u64], cpu: &[u64]) -> (usize, usize) {
    let (mut ties, mut other) = (0, 0);
    for (g, c) in gpu.iter().zip(cpu) {
        if g == c {
            continue;
        }
        if *g != EMPTY_KEY
            && *c != EMPTY_KEY
            && key_depth(*g) == key_depth(*c)
            && key_index(*g) != key_index(*c)
        {
            ties += 1;
        } else {
            other += 1;
        }
    }
    (ties, other)
}

fn cameras(scene: &Scene) -> Vec<(String, Camera)> {
    let mut cams = vec![
        (
            "iso".to_string(),
            Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 640, 400).unwrap(),
        ),
        (
            "top ortho".to_string(),
            Camera::frame_orthographic(&scene.bounds, ViewPreset::Top, 500, 380).unwrap(),
        ),
        ("close-up".to_string(), Camera::close_up(&scene.bounds, 0.8, 640, 400).unwrap()),
        ("inside".to_string(), Camera::inside(&scene.bounds, 1.2, 640, 400).unwrap()),
    ];
    let c = scene.bounds.center();
    // Looking partly past the data: points on every side of the viewport, batches culled.
    cams.push((
        "past".to_string(),
        Camera {
            eye: [c[0] - 30.0, c[1], c[2] + 5.0],
            target: [c[0] + 10.0, c[1] + 25.0, c[2]],
            ..cams[0].1
        },
    ));
    cams
}

fn check_scene(
    name: &str,
    scene: &Scene,
    path: AtomicPath,
    chunk_points: Option<u32>,
    max_dispatch: Option<u32>,
) {
    let Some(ctx) = context(path, max_dispatch) else { return };
    assert_eq!(ctx.atomic_path(), path);
    let mut gs = upload(&ctx, scene, chunk_points);
    if let Some(cp) = chunk_points {
        assert!(
            gs.chunk_count() as u64 >= scene.points.len() as u64 / cp as u64,
            "{name}: {} chunks",
            gs.chunk_count()
        );
    }
    let mut total_ties = 0;
    for (cam_name, cam) in cameras(scene) {
        let mut gr = GpuRasterizer::new(&ctx, cam.width, cam.height).unwrap();
        for mode in [
            PrecisionMode::Adaptive,
            PrecisionMode::Fixed(Precision::Bits30),
            PrecisionMode::Fixed(Precision::Bits10),
        ] {
            for cull in [true, false] {
                let opts = RasterOptions { precision: mode, cull };
                let (want, want_stats) = cpu_keys(scene, &cam, &opts);
                let frame = gr.draw(&ctx, &mut gs, &cam, &opts, None).unwrap();
                let got = gr.read_keys(&ctx).unwrap();
                let (ties, other) = compare(&got, &want);
                let covered = want.iter().filter(|&&k| k != EMPTY_KEY).count();
                assert_eq!(other, 0, "{name} {path:?} {cam_name} {mode:?} cull={cull}: {other} of {covered} pixels differ beyond exact depth ties");
                total_ties += ties;
                assert_eq!(
                    frame.stats, want_stats,
                    "{name} {path:?} {cam_name} {mode:?} cull={cull}: statistics"
                );
                assert!(covered > 1000, "{name} {cam_name}: only {covered} pixels covered");
            }
        }
    }
    eprintln!("{name} {path:?}: exact depth ties that differ: {total_ties}");
    // The measurement variants of the draw pass and the host plan leave the same keys and
    // statistics (kernel 3 draws nothing by design).
    let (cam_name, cam) = cameras(scene).swap_remove(4);
    let mut gr = GpuRasterizer::new(&ctx, cam.width, cam.height).unwrap();
    let opts = RasterOptions::default();
    let (want, want_stats) = cpu_keys(scene, &cam, &opts);
    let kernels: &[u32] = if path == AtomicPath::U64 { &[0, 1, 2, 4] } else { &[0] };
    for &kernel in kernels {
        for plan_on_gpu in [true, false] {
            let tuning = DrawTuning {
                kernel,
                workgroup: if kernel == 4 { 64 } else { 128 },
                order: RecordOrder::Strided(5),
                plan_on_gpu,
                division: None,
            };
            gr.set_tuning(&ctx, tuning).unwrap();
            let frame = gr.draw(&ctx, &mut gs, &cam, &opts, None).unwrap();
            let got = gr.read_keys(&ctx).unwrap();
            assert_eq!(compare(&got, &want).1, 0, "{name} {path:?} {cam_name} {tuning:?}");
            assert_eq!(
                frame.stats, want_stats,
                "{name} {path:?} {cam_name} {tuning:?}: statistics"
            );
            assert_eq!(
                frame.timings.map(|t| t.plan_ms.is_some()),
                ctx.has_timestamps().then_some(plan_on_gpu)
            );
        }
    }
    assert!(want_stats.batches_culled > 0, "{name}: the 'past' view culls nothing");
}

fn utm_terrain(n: usize) -> Scene {
    Scene::terrain(n, 7, Grid { scale: [0.001; 3], offset: [500_000.0, 5_400_000.0, 0.0] })
}

#[test]
fn u64_path_matches_cpu_on_utm_terrain() {
    check_scene("UTM", &utm_terrain(300_000), AtomicPath::U64, None, None);
}

#[test]
fn two_pass_32_bit_path_matches_cpu_on_utm_terrain() {
    check_scene("UTM", &utm_terrain(300_000), AtomicPath::TwoPass32, None, None);
}

#[test]
fn both_paths_match_cpu_on_ecef_with_chunks_and_split_dispatches() {
    // ECEF-sized coordinates at 0.1 mm, several chunks of points and dispatches split at 7
    // workgroups per dimension.
    let scene = Scene::terrain(
        200_000,
        3,
        Grid { scale: [0.0001; 3], offset: [6_400_000.0, 6_400_000.0, 6_400_000.0] },
    );
    for path in [AtomicPath::U64, AtomicPath::TwoPass32] {
        check_scene("ECEF chunked", &scene, path, Some(50_000), Some(7));
    }
}

#[test]
fn resolve_matches_cpu_resolve() {
    let scene = utm_terrain(120_000);
    for path in [AtomicPath::U64, AtomicPath::TwoPass32] {
        let Some(ctx) = context(path, None) else { continue };
        let mut gs = upload(&ctx, &scene, Some(30_000));
        let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 400, 300).unwrap();
        let mut gr = GpuRasterizer::new(&ctx, cam.width, cam.height).unwrap();
        let background = 0xff20_1008;
        gr.draw(
            &ctx,
            &mut gs,
            &cam,
            &RasterOptions::default(),
            Some(&ResolveOptions { background, ..Default::default() }),
        )
        .unwrap();
        let keys = gr.read_keys(&ctx).unwrap();
        let image = gr.read_image(&ctx).unwrap();
        let want = resolve_with_colors(
            &keys,
            cam.width,
            cam.height,
            &scene.colors,
            &ResolveOptions { background, ..Default::default() },
        );
        assert_eq!(image, want, "{path:?}");
        assert!(image.iter().filter(|&&c| c != background).count() > 10_000);
    }
}

/// The resolve options the post-processing tests run: hole filling with several
/// `min_neighbors`, eye-dome lighting at several strengths and radii, and both together.
fn post_options(background: u32) -> Vec<ResolveOptions> {
    let fill = |n| Some(HoleFill { min_neighbors: n });
    let edl = |strength, radius| Some(EyeDome { strength, radius });
    let o = |hole_fill, eye_dome| ResolveOptions { background, hole_fill, eye_dome };
    vec![
        o(fill(1), None),
        o(fill(3), None),
        o(fill(6), None),
        o(None, edl(1.0, 1.4)),
        o(None, edl(2.5, 3.0)),
        o(fill(3), edl(1.0, 1.4)),
        o(fill(2), edl(0.4, 2.2)),
    ]
}

#[test]
fn hole_filling_and_eye_dome_lighting_match_cpu_resolve() {
    // Sparse enough (about a point per pixel from above) that filling has holes to close, with
    // depth steps for the eye-dome lighting. Compared with the CPU resolve of the GPU's own keys:
    // the passes must agree with mortar_core byte for byte, whatever the draw left.
    let scene = utm_terrain(250_000);
    let background = 0xff40_2010;
    let mut shaded_total = 0;
    let mut filled_total = 0;
    for path in [AtomicPath::U64, AtomicPath::TwoPass32] {
        let Some(ctx) = context(path, None) else { continue };
        let mut gs = upload(&ctx, &scene, Some(60_000));
        let cams = [
            (
                "top ortho",
                Camera::frame_orthographic(&scene.bounds, ViewPreset::Top, 640, 480).unwrap(),
            ),
            (
                "iso",
                Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 600, 400).unwrap(),
            ),
            ("close-up", Camera::close_up(&scene.bounds, 0.8, 500, 350).unwrap()),
        ];
        for (cam_name, cam) in cams {
            let mut gr = GpuRasterizer::new(&ctx, cam.width, cam.height).unwrap();
            let plain = ResolveOptions { background, ..Default::default() };
            gr.draw(&ctx, &mut gs, &cam, &RasterOptions::default(), Some(&plain)).unwrap();
            let keys = gr.read_keys(&ctx).unwrap();
            let plain_image = gr.read_image(&ctx).unwrap();
            let holes = keys.iter().filter(|&&k| k == EMPTY_KEY).count();
            assert!(
                holes > 1000 && keys.len() - holes > 10_000,
                "{path:?} {cam_name}: {holes} of {} pixels empty",
                keys.len()
            );
            for (n, opts) in post_options(background).into_iter().enumerate() {
                let what = format!("{path:?} {cam_name} {opts:?}");
                // Every other case through a fresh draw, the rest through resolve() on the
                // framebuffer as it is.
                let frame = if n % 2 == 0 {
                    gr.draw(&ctx, &mut gs, &cam, &RasterOptions::default(), Some(&opts)).unwrap();
                    assert_eq!(
                        gr.read_keys(&ctx).unwrap(),
                        keys,
                        "{what}: the draw is deterministic"
                    );
                    None
                } else {
                    gr.resolve(&ctx, &mut gs, &opts).unwrap()
                };
                if let Some(t) = frame {
                    assert_eq!(t.hole_fill_ms.is_some(), opts.hole_fill.is_some(), "{what}");
                    assert_eq!(t.eye_dome_ms.is_some(), opts.eye_dome.is_some(), "{what}");
                }
                if let Some(fill) = &opts.hole_fill {
                    let want = fill_holes(&keys, cam.width, cam.height, fill);
                    let got = gr.read_filled_keys(&ctx).unwrap();
                    let differ = got.iter().zip(&want).filter(|(g, w)| g != w).count();
                    assert_eq!(differ, 0, "{what}: {differ} filled keys differ from fill_holes");
                    filled_total += want.iter().zip(&keys).filter(|(f, k)| f != k).count();
                }
                let want = resolve_with_colors(&keys, cam.width, cam.height, &scene.colors, &opts);
                let got = gr.read_image(&ctx).unwrap();
                let differ = got.iter().zip(&want).filter(|(g, w)| g != w).count();
                assert_eq!(differ, 0, "{what}: {differ} pixels differ from the CPU resolve");
                if opts.eye_dome.is_some() {
                    shaded_total += got.iter().zip(&plain_image).filter(|(g, p)| g != p).count();
                }
            }
        }
    }
    eprintln!(
        "pixels filled: {filled_total}, pixels the eye-dome lighting changed: {shaded_total}"
    );
    assert!(
        filled_total > 10_000 && shaded_total > 10_000,
        "the scenes do not exercise the passes: {filled_total} filled, {shaded_total} shaded"
    );
}

#[test]
fn bad_calls_are_errors_not_panics() {
    let Some(ctx) = context(AtomicPath::TwoPass32, None) else { return };
    let scene = utm_terrain(30_000);
    let refs = scene.refs();
    let mut gs = GpuScene::new(&ctx, scene.grid, 30_000, SceneOptions::default()).unwrap();
    // Out of order.
    assert!(matches!(gs.push(&ctx, &refs[1], None), Err(GpuError::FirstIndex { expected: 0, .. })));
    // Colours where the scene has none.
    assert!(matches!(
        gs.push(&ctx, &refs[0], Some(&scene.colors[..refs[0].len()])),
        Err(GpuError::Colors(_))
    ));
    gs.push(&ctx, &refs[0], None).unwrap();
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Top, 0.8, 64, 48).unwrap();
    let mut gr = GpuRasterizer::new(&ctx, 64, 48).unwrap();
    // Resolve without colours, and a camera of another size.
    assert!(matches!(
        gr.draw(&ctx, &mut gs, &cam, &RasterOptions::default(), Some(&ResolveOptions::default())),
        Err(GpuError::Colors(_))
    ));
    assert!(matches!(
        gr.resolve(&ctx, &mut gs, &ResolveOptions::default()),
        Err(GpuError::Colors(_))
    ));
    let other = Camera { width: 65, ..cam };
    assert!(matches!(
        gr.draw(&ctx, &mut gs, &other, &RasterOptions::default(), None),
        Err(GpuError::Raster(_))
    ));
    // A framebuffer beyond the device's largest binding.
    assert!(
        matches!(GpuRasterizer::new(&ctx, 1 << 15, 1 << 15), Err(GpuError::TooLarge { .. }))
            || ctx.max_binding() >= 1u64 << 32
    );
    // An empty scene draws nothing.
    let mut empty = GpuScene::new(&ctx, scene.grid, 0, SceneOptions::default()).unwrap();
    let f = gr.draw(&ctx, &mut empty, &cam, &RasterOptions::default(), None).unwrap();
    assert_eq!(f.stats.points_drawn, 0);
    assert!(gr.read_keys(&ctx).unwrap().iter().all(|&k| k == EMPTY_KEY));
}

#[test]
fn adapter_is_reported() {
    let Some(ctx) = context(AtomicPath::TwoPass32, None) else { return };
    let a = ctx.adapter();
    eprintln!(
        "adapter: {} ({}, {}, driver {}), timestamps: {}, largest binding: {} MiB",
        a.name,
        a.backend,
        a.device_type,
        a.driver,
        ctx.has_timestamps(),
        ctx.max_binding() >> 20
    );
    assert!(!a.name.is_empty());
    assert!(ctx.max_binding() >= 128 << 20);
}

#[test]
fn a_scene_drawn_while_it_grows_matches_cpu_after_every_batch() {
    // Draw after every batch pushed, planned on the GPU and on the host in turn: the records and
    // plan buffers grow many times (their whole-buffer bindings must stay 4-byte multiples; a
    // buffer grown by half again and again once became odd-sized on the H200).
    let scene = utm_terrain(200_000);
    let Some(ctx) = context(AtomicPath::U64, None) else { return };
    let mut gs = GpuScene::new(
        &ctx,
        scene.grid,
        1000,
        SceneOptions { chunk_points: Some(25_000), colors: false },
    )
    .unwrap();
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 160, 100).unwrap();
    let mut gr = GpuRasterizer::new(&ctx, cam.width, cam.height).unwrap();
    let refs = scene.refs();
    for (i, b) in refs.iter().enumerate() {
        gs.push(&ctx, b, None).unwrap();
        let plan_on_gpu = i % 3 != 1;
        gr.set_tuning(&ctx, DrawTuning { plan_on_gpu, ..Default::default() }).unwrap();
        let frame = gr.draw(&ctx, &mut gs, &cam, &RasterOptions::default(), None).unwrap();
        let fb = Framebuffer::new(cam.width, cam.height);
        let want_stats =
            rasterize(&fb, &refs[..=i], &scene.grid, &cam, &RasterOptions::default()).unwrap();
        assert_eq!(
            compare(&gr.read_keys(&ctx).unwrap(), &fb.into_keys()).1,
            0,
            "after batch {i}, plan on GPU: {plan_on_gpu}"
        );
        assert_eq!(frame.stats, want_stats, "after batch {i}");
    }
    assert!(gs.chunk_count() > 4);
}

#[test]
fn a_host_planned_frame_does_not_wait_for_a_busy_rayon_pool() {
    // `mortar build --preview`: the build keeps every thread of rayon's pool busy; a frame of a
    // few hundred batches planned on the host must not queue behind the build's jobs (frames of
    // 20-100 ms on the 16-core device when it did).
    let scene = utm_terrain(100_000);
    let Some(ctx) = context(AtomicPath::U64, None) else { return };
    let mut first = upload(&ctx, &scene, None);
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 160, 100).unwrap();
    let mut gr = GpuRasterizer::new(&ctx, cam.width, cam.height).unwrap();
    gr.set_tuning(&ctx, DrawTuning { plan_on_gpu: false, ..Default::default() }).unwrap();
    let want = gr.draw(&ctx, &mut first, &cam, &RasterOptions::default(), None).unwrap().stats;
    let mut gs = upload(&ctx, &scene, None);
    let n = rayon::current_num_threads();
    let started = std::sync::Arc::new(std::sync::Barrier::new(n + 1));
    let release = std::sync::Arc::new(std::sync::Barrier::new(n + 1));
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::scope(|s| {
        let (b, r) = (started.clone(), release.clone());
        s.spawn(move || {
            rayon::broadcast(|_| {
                b.wait();
                r.wait();
            })
        });
        started.wait();
        let (ctx, gs, gr, cam) = (&ctx, &mut gs, &mut gr, &cam);
        s.spawn(move || {
            let _ =
                tx.send(gr.draw(ctx, gs, cam, &RasterOptions::default(), None).map(|f| f.stats));
        });
        let got = rx.recv_timeout(std::time::Duration::from_secs(60));
        release.wait();
        let got = got.expect("the frame waited for rayon's busy threads");
        assert_eq!(got.unwrap(), want);
    });
}
