//! LOD rendering of an octree store (issue 5, item 4): `mortar render store/` selects nodes for
//! the view (paper 004 §6) and draws them from the store's payloads. With `--lod-threshold 0` it
//! draws what the full-detail render of the same points draws (the temporary batch file path,
//! `--no-lod`); coarser thresholds and point budgets draw fewer samples; the GPU rasterizer
//! leaves the CPU's keys; damaged hierarchies are clear errors.

mod common;

use common::*;
use mortar_core::octree::{LodOptions, LodTree, NodeId};
use mortar_core::quantize::Precision;
use mortar_core::render::framebuffer::{key_depth, key_index, EMPTY_KEY};
use mortar_core::render::{
    rasterize, BatchRef, Camera, Framebuffer, PrecisionMode, RasterOptions, ViewPreset,
};
use mortar_io::batch_input::{self, RenderSource};
use mortar_io::store::{LodBatches, StoreLod};
use mortar_render::{AtomicPath, GpuContext, GpuRasterizer, GpuScene, SceneOptions};
use std::path::{Path, PathBuf};

fn sample() -> PathBuf {
    root().join("data-samples/autzen_trim.laz")
}

/// A store of the sample (a deep tree: leaves of at most 2,000 points) and a batch file of the
/// store's points.
struct Fixture {
    dir: PathBuf,
    store: PathBuf,
    mbat: PathBuf,
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn fixture(tag: &str) -> Fixture {
    let dir = tempdir(tag);
    let store = dir.join("store");
    run_ok(
        mortar().arg("build").arg(sample()).arg("-o").arg(&store).args(["--leaf-capacity", "2000"]),
    );
    let mbat = dir.join("all.mbat");
    run_ok(mortar().arg("batch").arg(&store).arg("-o").arg(&mbat));
    Fixture { dir, store, mbat }
}

/// Framed views in perspective and orthographic, a close-up and a view from inside (which culls).
fn cameras(lod: &StoreLod, w: u32, h: u32) -> Vec<(String, Camera)> {
    let b = lod.bounds();
    let fov = 50f64.to_radians();
    let mut v = Vec::new();
    for p in ViewPreset::ALL {
        v.push((format!("{p:?}"), Camera::frame_perspective(&b, p, fov, w, h).unwrap()));
        v.push((format!("{p:?} ortho"), Camera::frame_orthographic(&b, p, w, h).unwrap()));
    }
    v.push(("close-up".into(), Camera::close_up(&b, fov, w, h).unwrap()));
    v.push(("inside".into(), Camera::inside(&b, fov, w, h).unwrap()));
    v
}

fn keys(refs: &[BatchRef<'_>], lod: &StoreLod, cam: &Camera, opts: &RasterOptions) -> Vec<u64> {
    let fb = Framebuffer::new(cam.width, cam.height);
    rasterize(&fb, refs, &lod.grid(), cam, opts).unwrap();
    fb.into_keys()
}

/// Node and sample of each pixel's winner.
fn winners(k: &[u64], b: &LodBatches<'_>) -> Vec<Option<(NodeId, usize, u32)>> {
    k.iter()
        .map(|&k| {
            (k != EMPTY_KEY).then(|| {
                let (bi, i) = b.locate(key_index(k)).expect("index in range");
                (b.nodes[bi], i, key_depth(k).to_bits())
            })
        })
        .collect()
}

/// Decoded integer position of a batch file's point `index`.
fn file_position(refs: &[BatchRef<'_>], index: u32) -> [i32; 3] {
    let b = refs.partition_point(|r| r.first_index <= index) - 1;
    let r = &refs[b];
    let i = (index - r.first_index) as usize;
    r.grid.decode_exact([r.words[0][i], r.words[1][i], r.words[2][i]])
}

#[test]
fn lod_threshold_zero_is_the_full_detail_render() {
    let f = fixture("lod-full");
    let lod = StoreLod::open(&f.store).unwrap();
    let src = RenderSource::open_batch_file(&f.mbat).unwrap();
    let views = batch_input::load_words(&src.file).unwrap();
    let file_refs = batch_input::batch_refs(&src.file, &views).unwrap();
    let leaves: Vec<NodeId> = (0..lod.node_count() as u32)
        .map(NodeId)
        .filter(|&id| lod.is_leaf(id) && lod.samples(id) > 0)
        .collect();
    assert!(leaves.len() > 50, "{} leaves", leaves.len());
    let all = lod.batches(&leaves).unwrap();
    assert_eq!(all.samples, 110_000);
    let (mut covered, mut differ, mut culled) = (0usize, 0usize, 0u64);
    for (name, cam) in cameras(&lod, 400, 250) {
        let sel = lod
            .select(&cam, &LodOptions { threshold_px: 0.0, point_budget: None, cull: true })
            .unwrap();
        assert_eq!(sel.stats.voxels, 0, "{name}");
        assert!(sel.nodes.iter().all(|&id| lod.is_leaf(id)), "{name}");
        culled += sel.stats.culled;
        let batches = lod.batches(&sel.nodes).unwrap();
        for precision in [PrecisionMode::Adaptive, PrecisionMode::Fixed(Precision::Bits30)] {
            let opts = RasterOptions { precision, cull: true };
            let got = keys(&batches.refs, &lod, &cam, &opts);
            // Every leaf drawn without selection or culling: the very same winners (node, sample
            // and depth; the indices differ because culled leaves take no numbers).
            let want = keys(&all.refs, &lod, &cam, &RasterOptions { cull: false, ..opts });
            let c = got.iter().filter(|&&k| k != EMPTY_KEY).count();
            assert!(c > 1_000, "{name}: {c} pixels");
            assert!(
                winners(&got, &batches) == winners(&want, &all),
                "{name} {precision:?}: winners differ from drawing every leaf"
            );
            if precision != PrecisionMode::Fixed(Precision::Bits30) {
                continue;
            }
            // The brute-force render of the batch file: the same pixels covered, and in each the
            // same depth up to f32 rounding (other batches have other frames, so the f32
            // projection may round a depth to the neighbouring value). The winning point itself
            // differs only where several points share the nearest depth (common in the top view:
            // ground points of one height): ties go to the smaller index, and the batch file
            // numbers points in Morton order, the LOD render in leaf order.
            let brute = keys(&file_refs, &lod, &cam, &RasterOptions { precision, cull: false });
            // (A point right at a pixel edge could move across it; none does here, a few would be
            // tolerated.)
            let (mut d, mut moved) = (0, 0);
            for (&a, &b) in got.iter().zip(&brute) {
                if (a == EMPTY_KEY) != (b == EMPTY_KEY) {
                    moved += 1;
                    continue;
                }
                if a == EMPTY_KEY
                    || batches.position(key_index(a))
                        == Some(file_position(&file_refs, key_index(b)))
                {
                    continue;
                }
                d += 1;
                let (x, y) = (key_depth(a) as f64, key_depth(b) as f64);
                moved += ((x - y).abs() > 2.5e-7 * y.abs()) as usize;
            }
            assert!(moved * 1000 <= c, "{name}: {moved} of {c} pixels differ in coverage or depth from the brute-force render");
            covered += c;
            differ += d;
        }
    }
    assert!(culled > 0, "some view culls nodes");
    // Ties aside, the same points win: most pixels agree on the point.
    assert!(
        differ * 10 <= covered,
        "{differ} of {covered} pixels have another winner than the brute-force render"
    );
    eprintln!("threshold 0 against brute force: {differ} of {covered} covered pixels won by another point at the same depth");
}

#[test]
fn node_batches_are_the_payloads_with_bounds_that_hold_their_samples() {
    let f = fixture("lod-bounds");
    let lod = StoreLod::open(&f.store).unwrap();
    let ids: Vec<NodeId> = (0..lod.node_count() as u32).map(NodeId).collect();
    let b = lod.batches(&ids).unwrap();
    let g = lod.grid();
    let mut wide = 0;
    let mut next = 0u32;
    for (k, r) in b.refs.iter().enumerate() {
        let d = lod.node(ids[k]);
        // In place: the very words and colours of the mapped payload, numbered consecutively.
        assert_eq!(r.first_index, next);
        assert!(std::ptr::eq(r.words[0], d.words[0]) && std::ptr::eq(b.colors[k], d.colors));
        assert_eq!(r.len() as u64, lod.samples(ids[k]));
        next += r.len() as u32;
        if r.is_empty() {
            continue;
        }
        let mut hi = [i32::MIN; 3];
        for i in 0..r.len() {
            let p = r.grid.decode_exact([r.words[0][i], r.words[1][i], r.words[2][i]]);
            for a in 0..3 {
                hi[a] = hi[a].max(p[a]);
                assert!(
                    r.bounds_min[a] <= g.world(a, p[a] as i64)
                        && g.world(a, p[a] as i64) <= r.bounds_max[a],
                    "node {k}: sample outside its bounds"
                );
            }
            assert_eq!(b.position(r.first_index + i as u32), Some(p));
        }
        // The bound is the true maximum, or above it by less than a coarse step.
        for (a, &max) in hi.iter().enumerate() {
            let bound = g.to_int(a, r.bounds_max[a]);
            let step = 1i64 << (r.grid.bits[a] as i64 - 10).max(0);
            assert!(
                bound >= max as i64 && bound < max as i64 + step,
                "node {k} axis {a}: bound {bound}, max {max}"
            );
            wide += (bound > max as i64) as usize;
        }
    }
    assert_eq!(next as u64, b.samples);
    assert_eq!(b.locate(next), None);
    eprintln!("{wide} node axes bounded above their maximum");
}

fn render_json(input: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let o = run_ok(
        mortar()
            .arg("render")
            .arg(input)
            .arg("-o")
            .arg(out)
            .args(["--width", "320", "--height", "200", "--json"])
            .args(extra),
    );
    serde_json::from_slice(&o.stdout).expect("JSON")
}

/// RGBA pixels of a PNG.
fn pixels(p: &Path) -> Vec<u32> {
    let mut dec = png::Decoder::new(std::io::Cursor::new(std::fs::read(p).unwrap()));
    dec.set_transformations(png::Transformations::EXPAND);
    let mut reader = dec.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgba);
    buf[..info.buffer_size()]
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

#[test]
fn render_cli_draws_a_store_with_lod() {
    let f = fixture("lod-cli");
    let out = f.dir.join("x.png");
    for view in ["iso", "side", "closeup"] {
        // Full detail through LOD against the brute-force path (--no-lod) with the same colours.
        let full = f.dir.join(format!("full-{view}.png"));
        let j = render_json(
            &f.store,
            &full,
            &[
                "--view",
                view,
                "--no-lod",
                "--color",
                "stored",
                "--precision",
                "30",
                "--backend",
                "cpu",
            ],
        );
        assert!(j.get("lod").is_none(), "{j}");
        let lod0 = f.dir.join(format!("lod0-{view}.png"));
        let j0 = render_json(
            &f.store,
            &lod0,
            &["--view", view, "--lod-threshold", "0", "--precision", "30", "--backend", "cpu"],
        );
        assert_eq!(j0["color"], "stored");
        assert_eq!(j0["lod"]["voxels"], 0, "{j0}");
        assert_eq!(j0["points"], 110_000);
        assert_eq!(j0["lod"]["samples"], j0["lod"]["points"]);
        let (a, b) = (pixels(&full), pixels(&lod0));
        let covered = b.iter().filter(|&&p| p != pixels_bg()).count();
        let differ = a.iter().zip(&b).filter(|(x, y)| x != y).count();
        // Only pixels where points tie in depth may take another colour (see
        // lod_threshold_zero_is_the_full_detail_render); few in these views.
        assert!(
            covered > 3_000 && differ * 100 <= covered,
            "{view}: {differ} of {covered} pixels differ from --no-lod"
        );
        if view == "iso" {
            // In a framed view nothing is culled: every point is drawn.
            assert_eq!(j0["lod"]["points"], 110_000);
            assert_eq!(j0["points_projected"], 110_000);
        }

        // Coarser thresholds draw fewer samples in framed views (in a close-up, a coarse node
        // may hold more voxels than the visible part of its culled children holds points); a
        // huge threshold draws the root's voxels alone.
        let mut last = u64::MAX;
        for t in ["0", "16", "64", "128", "512", "1e12"] {
            let j = render_json(
                &f.store,
                &out,
                &["--view", view, "--lod-threshold", t, "--backend", "cpu"],
            );
            let l = &j["lod"];
            let s = l["samples"].as_u64().unwrap();
            assert!(
                s <= last || view == "closeup",
                "{view} threshold {t}: {s} samples after {last}"
            );
            assert_eq!(s, l["points"].as_u64().unwrap() + l["voxels"].as_u64().unwrap());
            assert!(j["points_projected"].as_u64().unwrap() <= s);
            assert!(j["pixels_covered"].as_u64().unwrap() > 500, "{view} {t}: {j}");
            assert!(
                l["selection_seconds"].as_f64().is_some()
                    && l["nodes_selected"].as_u64().unwrap() >= 1
            );
            if t == "1e12" {
                assert_eq!(l["nodes_selected"], 1);
                assert_eq!(l["points"], 0);
            }
            if t == "128" && view == "iso" {
                assert!(s < 110_000 && l["voxels"].as_u64().unwrap() > 0, "{l}");
            }
            last = s;
        }
    }
    // The default threshold is 128 px.
    let j = render_json(&f.store, &out, &["--backend", "cpu"]);
    assert_eq!(j["lod"]["threshold_px"], 128.0);
}

/// Background of the default render: opaque black.
fn pixels_bg() -> u32 {
    0xff00_0000
}

#[test]
fn point_budget_is_respected() {
    let f = fixture("lod-budget");
    let out = f.dir.join("x.png");
    let unlimited = render_json(&f.store, &out, &["--lod-threshold", "0", "--backend", "cpu"]);
    let all = unlimited["lod"]["samples"].as_u64().unwrap();
    assert_eq!(unlimited["lod"]["budget_reached"], false);
    let root = render_json(&f.store, &out, &["--lod-threshold", "1e12", "--backend", "cpu"])["lod"]
        ["samples"]
        .as_u64()
        .unwrap();
    let mut last = 0;
    let mut bound = 0;
    for budget in [1, root, 20_000, 40_000, 60_000, 90_000, all, 1 << 40] {
        let b = budget.to_string();
        let j = render_json(
            &f.store,
            &out,
            &["--lod-threshold", "0", "--point-budget", &b, "--backend", "cpu"],
        );
        let l = &j["lod"];
        let s = l["samples"].as_u64().unwrap();
        assert!(s <= budget || l["nodes_selected"] == 1, "budget {budget}: {s} samples");
        assert!(s >= last, "budget {budget}: {s} samples, fewer than a smaller budget's {last}");
        assert_eq!(l["budget_reached"], budget < all, "budget {budget}: {l}");
        assert_eq!(l["point_budget"], budget);
        assert_eq!(
            j["points_projected"].as_u64().unwrap(),
            s,
            "a framed view draws every selected sample"
        );
        bound += (budget < all && s > 0) as usize;
        last = s;
    }
    assert_eq!(last, all);
    assert!(bound >= 5);
}

fn gpu_context(path: AtomicPath) -> Option<GpuContext> {
    mortar_render::testing::context_or_skip(path, None)
}

#[test]
fn gpu_keys_equal_cpu_keys_for_lod_renders() {
    let contexts: Vec<GpuContext> =
        [AtomicPath::U64, AtomicPath::TwoPass32].into_iter().filter_map(gpu_context).collect();
    if contexts.is_empty() {
        return;
    }
    let f = fixture("lod-gpu");
    let lod = StoreLod::open(&f.store).unwrap();
    let mut ties = 0;
    let mut compared = 0;
    for ctx in &contexts {
        let mut raster = GpuRasterizer::new(ctx, 400, 250).unwrap();
        for (name, cam) in cameras(&lod, 400, 250).into_iter().step_by(3) {
            for (threshold_px, point_budget) in [(0.0, None), (128.0, None), (16.0, Some(30_000))] {
                let sel = lod
                    .select(&cam, &LodOptions { threshold_px, point_budget, cull: true })
                    .unwrap();
                let batches = lod.batches(&sel.nodes).unwrap();
                let mut scene = GpuScene::new(
                    ctx,
                    lod.grid(),
                    batches.samples,
                    SceneOptions { chunk_points: Some(40_000), colors: false },
                )
                .unwrap();
                for b in &batches.refs {
                    scene.push(ctx, b, None).unwrap();
                }
                for precision in [PrecisionMode::Adaptive, PrecisionMode::Fixed(Precision::Bits10)]
                {
                    let opts = RasterOptions { precision, cull: true };
                    let fb = Framebuffer::new(cam.width, cam.height);
                    let cpu_stats =
                        rasterize(&fb, &batches.refs, &lod.grid(), &cam, &opts).unwrap();
                    let cpu = fb.into_keys();
                    let frame = raster.draw(ctx, &mut scene, &cam, &opts, None).unwrap();
                    let gpu = raster.read_keys(ctx).unwrap();
                    assert_eq!(frame.stats, cpu_stats, "{name} {threshold_px}");
                    let mut other = 0;
                    for (g, c) in gpu.iter().zip(&cpu) {
                        if g != c {
                            if *g != EMPTY_KEY && *c != EMPTY_KEY && key_depth(*g) == key_depth(*c)
                            {
                                ties += 1;
                            } else {
                                other += 1;
                            }
                        }
                    }
                    let covered = cpu.iter().filter(|&&k| k != EMPTY_KEY).count();
                    assert!(covered > 500, "{name}: {covered} pixels");
                    assert_eq!(other, 0, "{name} threshold {threshold_px} {precision:?} {:?}: {other} of {covered} pixels differ", ctx.atomic_path());
                    compared += 1;
                }
            }
        }
    }
    assert!(compared >= 12);
    eprintln!("LOD renders: GPU keys equal the CPU's except {ties} exact depth ties");
    // The command line: the same PNG from both backends.
    let args: &[&[&str]] = &[
        &[],
        &["--color", "elevation", "--edl", "--hole-fill", "--view", "top", "--ortho"],
        &["--point-budget", "20000", "--view", "closeup"],
    ];
    for (i, extra) in args.iter().enumerate() {
        let cpu_png = f.dir.join(format!("cpu{i}.png"));
        let gpu_png = f.dir.join(format!("gpu{i}.png"));
        let c = render_json(&f.store, &cpu_png, &[*extra, &["--backend", "cpu"]].concat());
        let g = render_json(&f.store, &gpu_png, &[*extra, &["--backend", "gpu"]].concat());
        assert_eq!(g["backend"], "gpu");
        for k in ["points_drawn", "points_projected", "pixels_covered", "lod"] {
            if k == "lod" {
                assert_eq!(g[k]["samples"], c[k]["samples"], "{extra:?}");
            } else {
                assert_eq!(g[k], c[k], "{extra:?}: {k}");
            }
        }
        assert!(
            std::fs::read(&gpu_png).unwrap() == std::fs::read(&cpu_png).unwrap(),
            "{extra:?}: PNGs differ"
        );
    }
}

#[test]
fn colour_modes_and_bad_stores_are_clear_errors() {
    let f = fixture("lod-errors");
    let out = f.dir.join("x.png");
    let fail = |input: &Path, extra: &[&str]| -> String {
        let o = mortar()
            .arg("render")
            .arg(input)
            .arg("-o")
            .arg(&out)
            .args(["--width", "64", "--height", "48", "--backend", "cpu"])
            .args(extra)
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(1), "{extra:?}: {}", String::from_utf8_lossy(&o.stderr));
        assert!(!out.exists());
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let store = f.store.to_str().unwrap();
    // Attribute colour modes work under LOD (voxels are real points with their records; see
    // tests/store_colors.rs), and through --no-lod.
    for mode in ["classification", "intensity", "gps-time", "return-number"] {
        let j = render_json(&f.store, &out, &["--color", mode, "--backend", "cpu"]);
        assert_eq!(j["color"], mode, "{j}");
        std::fs::remove_file(&out).unwrap();
    }
    run_ok(mortar().arg("render").arg(&f.store).arg("-o").arg(&out).args([
        "--width",
        "64",
        "--height",
        "48",
        "--backend",
        "cpu",
        "--no-lod",
        "--color",
        "classification",
    ]));
    std::fs::remove_file(&out).unwrap();
    // Elevation is computed from the positions.
    let j = render_json(&f.store, &out, &["--color", "elevation", "--backend", "cpu"]);
    assert_eq!(j["color"], "elevation");
    let r = j["color_range"].as_array().unwrap();
    assert!(r[0].as_f64().unwrap() < r[1].as_f64().unwrap());
    std::fs::remove_file(&out).unwrap();
    // LOD options are for stores only, and checked.
    let e = fail(&f.mbat, &["--lod-threshold", "10"]);
    assert!(e.contains("--lod-threshold") && e.contains("store"), "{e}");
    let e = fail(&f.store, &["--lod-threshold", "-1"]);
    assert!(e.contains("--lod-threshold"), "{e}");
    let e = fail(&f.store, &["--lod-threshold", "NaN"]);
    assert!(e.contains("--lod-threshold"), "{e}");
    // A hierarchy whose keys do not form a tree (two nodes with one key; every length still
    // right, so only the LOD index notices): an error naming the store, not a panic.
    let hp = f.store.join("hierarchy.bin");
    let h = std::fs::read(&hp).unwrap();
    let mut bad = h.clone();
    let entry = |i: usize| 104 + 48 * i;
    // Entries 1 and 2 are two children of the root: give the second the first's index.
    let first = bad[entry(1) + 8..entry(1) + 20].to_vec();
    bad[entry(2) + 8..entry(2) + 20].copy_from_slice(&first);
    std::fs::write(&hp, &bad).unwrap();
    let e = fail(&f.store, &[]);
    assert!(e.contains(store) && e.contains("same key") && e.lines().count() == 1, "{e}");
    std::fs::write(&hp, &h).unwrap();
    // An empty damaged case: a truncated hierarchy.
    std::fs::write(&hp, &h[..h.len() - 5]).unwrap();
    let e = fail(&f.store, &[]);
    assert!(e.contains(store), "{e}");
    std::fs::write(&hp, &h).unwrap();
    run_ok(mortar().arg("render").arg(&f.store).arg("-o").arg(&out).args([
        "--width",
        "64",
        "--height",
        "48",
        "--backend",
        "cpu",
    ]));
}
