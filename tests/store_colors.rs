//! Issue 12, items 3 and 4: every sample of a store is a real source point with its record, so
//! LOD renders colour by any attribute at draw time, with the ranges raw renders use: an
//! intensity-only scan with outliers looks like its raw render (not almost black), all-zero
//! intensity renders the grey raw renders give, and at threshold 0 every colour mode equals the
//! brute-force render of the same points, on the CPU and the GPU.

mod common;

use common::*;
use std::path::{Path, PathBuf};

fn sample() -> PathBuf {
    root().join("data-samples/autzen_trim.laz")
}

/// A LAS 1.2 file of point format 1 (intensity, no RGB) with `n` points on a wavy surface:
/// intensities `intensity(i)`.
fn intensity_cloud(path: &Path, n: usize, intensity: impl Fn(usize) -> u16) {
    let mut b = las::Builder::from((1, 2));
    b.point_format = las::point::Format::new(1).unwrap();
    b.transforms = las::Vector {
        x: las::Transform { scale: 0.01, offset: 500_000.0 },
        y: las::Transform { scale: 0.01, offset: 4_000_000.0 },
        z: las::Transform { scale: 0.01, offset: 0.0 },
    };
    let header = b.into_header().unwrap();
    let mut w = las::Writer::from_path(path, header).unwrap();
    let side = (n as f64).sqrt().ceil() as usize;
    for i in 0..n {
        let (u, v) = ((i % side) as f64, (i / side) as f64);
        let p = las::Point {
            x: 500_000.0 + u * 0.25,
            y: 4_000_000.0 + v * 0.25,
            z: 100.0 + 3.0 * (u / 40.0).sin() * (v / 55.0).cos(),
            intensity: intensity(i),
            classification: las::point::Classification::new([2u8, 5, 6][i % 3]).unwrap(),
            return_number: 1 + (i % 3) as u8,
            number_of_returns: 3,
            gps_time: Some(1000.0 + i as f64 * 0.001),
            ..Default::default()
        };
        w.write_point(p).unwrap();
    }
    w.close().unwrap();
}

fn pixels(p: &Path) -> Vec<[u8; 4]> {
    let decoder = png::Decoder::new(std::fs::File::open(p).unwrap());
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf[..info.buffer_size()].chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect()
}

/// Mean grey of the covered pixels (background: opaque black, never a point's colour here).
fn mean_brightness(px: &[[u8; 4]]) -> (f64, usize) {
    let covered: Vec<&[u8; 4]> = px.iter().filter(|p| **p != [0, 0, 0, 255]).collect();
    let sum: f64 = covered.iter().map(|p| (p[0] as f64 + p[1] as f64 + p[2] as f64) / 3.0).sum();
    (sum / covered.len().max(1) as f64, covered.len())
}

fn render(input: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let o = run_ok(
        mortar()
            .arg("render")
            .arg(input)
            .arg("-o")
            .arg(out)
            .args(["--width", "320", "--height", "240", "--json"])
            .args(extra),
    );
    serde_json::from_slice(&o.stdout).unwrap()
}

#[test]
fn intensity_only_stores_look_like_their_raw_render() {
    let dir = tempdir("store-intensity");
    // Median intensity ~45, one point in 500 at 62,000 (the outliers that darkened the baked
    // colours), and a file of all-zero intensity.
    type Intensity = Box<dyn Fn(usize) -> u16>;
    let cases: [(&str, Intensity); 2] = [
        (
            "outliers.las",
            Box::new(|i| if i % 500 == 7 { 62_000 } else { 30 + ((i * 7919) % 31) as u16 }),
        ),
        ("zero.las", Box::new(|_| 0)),
    ];
    for (name, f) in cases {
        let las = dir.join(name);
        intensity_cloud(&las, 60_000, f);
        let store = dir.join(format!("{name}.store"));
        run_ok(
            mortar().arg("build").arg(&las).arg("-o").arg(&store).args(["--leaf-capacity", "3000"]),
        );
        let raw_png = dir.join("raw.png");
        let raw = render(&las, &raw_png, &["--backend", "cpu"]);
        for threshold in ["0", "128", "100000"] {
            let store_png = dir.join("store.png");
            let st =
                render(&store, &store_png, &["--backend", "cpu", "--lod-threshold", threshold]);
            assert_eq!(st["color"], "intensity", "{name}: {st}");
            let (a, na) = mean_brightness(&pixels(&raw_png));
            let (b, nb) = mean_brightness(&pixels(&store_png));
            assert!(na > 1000 && nb > 200, "{name} {threshold}: {na} / {nb} pixels covered");
            // Within a few percent of the raw render's mean brightness (of the grey range).
            assert!(
                (a - b).abs() <= 0.04 * 255.0,
                "{name} threshold {threshold}: raw mean {a:.1}, store mean {b:.1} ({raw} / {st})"
            );
            if name == "zero.las" {
                assert_eq!(st["color_range"], raw["color_range"], "{name}");
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// At threshold 0 the LOD render draws every leaf point, so in every colour mode it equals the
/// brute-force render (`--no-lod`) of the same points but where points tie in depth; coarser
/// thresholds draw voxels, which are real points, in every mode; the GPU gives the CPU's PNG.
#[test]
fn every_colour_mode_works_under_lod() {
    let dir = tempdir("store-modes");
    let store = dir.join("store");
    run_ok(
        mortar().arg("build").arg(sample()).arg("-o").arg(&store).args(["--leaf-capacity", "2000"]),
    );
    let gpu = mortar_render::testing::context_or_skip(mortar_render::AtomicPath::TwoPass32, None)
        .is_some();
    for mode in
        ["auto", "rgb", "intensity", "classification", "return-number", "gps-time", "elevation"]
    {
        let full = dir.join("full.png");
        let lod0 = dir.join("lod0.png");
        render(
            &store,
            &full,
            &["--no-lod", "--color", mode, "--precision", "30", "--backend", "cpu"],
        );
        let b = render(
            &store,
            &lod0,
            &["--lod-threshold", "0", "--color", mode, "--precision", "30", "--backend", "cpu"],
        );
        assert_eq!(b["lod"]["voxels"], 0, "{b}");
        if mode != "auto" && mode != "rgb" {
            assert_eq!(b["color"], mode, "{b}");
        }
        let (pa, pb) = (pixels(&full), pixels(&lod0));
        let covered = pb.iter().filter(|p| **p != [0, 0, 0, 255]).count();
        let differ = pa.iter().zip(&pb).filter(|(x, y)| x != y).count();
        assert!(
            covered > 3_000 && differ * 100 <= covered,
            "{mode}: {differ} of {covered} pixels differ from --no-lod"
        );
        // A coarse threshold draws voxels, coloured from their records.
        let coarse = dir.join("coarse.png");
        let c = render(
            &store,
            &coarse,
            &["--lod-threshold", "256", "--color", mode, "--backend", "cpu"],
        );
        assert!(c["lod"]["voxels"].as_u64().unwrap() > 0, "{c}");
        let (m, n) = mean_brightness(&pixels(&coarse));
        assert!(n > 1000 && m > 10.0, "{mode}: coarse render mean {m:.1} over {n} pixels");
        if gpu {
            let g = dir.join("gpu.png");
            render(&store, &g, &["--lod-threshold", "256", "--color", mode, "--backend", "gpu"]);
            assert!(
                std::fs::read(&g).unwrap() == std::fs::read(&coarse).unwrap(),
                "{mode}: GPU and CPU LOD PNGs differ"
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A store of an intensity-only file refuses `--color rgb`, naming the store.
#[test]
fn modes_a_store_lacks_are_refused() {
    let dir = tempdir("store-lacks");
    let las = dir.join("i.las");
    intensity_cloud(&las, 5_000, |i| i as u16);
    let store = dir.join("s");
    run_ok(mortar().arg("build").arg(&las).arg("-o").arg(&store));
    let out = dir.join("x.png");
    let o = mortar()
        .arg("render")
        .arg(&store)
        .arg("-o")
        .arg(&out)
        .args(["--color", "rgb"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains(store.to_str().unwrap()) && e.contains("rgb") && e.lines().count() == 1,
        "{e}"
    );
    assert!(!out.exists());
    let _ = std::fs::remove_dir_all(&dir);
}
