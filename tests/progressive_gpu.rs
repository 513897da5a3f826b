//! `mortar render <las|laz> --progressive ... --backend gpu` end to end (paper 000 on the GPU):
//! the converged PNG equals the CPU backend's in several colour modes and views; with `--preload`
//! and a fixed budget every frame's statistics equal the CPU's and so does an unfinished image;
//! the adaptive budget reports GPU-timestamp timings where the device has them; `--atomics 32`
//! is a clear error (the GPU progressive renderer needs 64-bit atomics), with no PNG.
//!
//! Runs on any adapter with 64-bit atomics, software ones included (lavapipe in CI). Skips with a
//! printed reason only where there is none, unless `MORTAR_REQUIRE_GPU` is set (CI sets it).

mod common;

use common::*;
use mortar_render::AtomicPath;
use std::path::{Path, PathBuf};

fn sample() -> PathBuf {
    root().join("data-samples/autzen_trim.laz")
}

/// Whether a 64-bit GPU context exists (else the test returns after a printed reason).
fn have_gpu() -> bool {
    mortar_render::testing::context_or_skip(AtomicPath::U64, None).is_some()
}

const VIEW: &[&str] = &["--width", "320", "--height", "240"];

/// Renders with `backend` and returns the JSON.
fn render(out: &Path, backend: &str, extra: &[&str]) -> serde_json::Value {
    let o = mortar()
        .arg("render")
        .arg(sample())
        .arg("-o")
        .arg(out)
        .args(VIEW)
        .args(extra)
        .args(["--backend", backend, "--json"])
        .output()
        .expect("spawn");
    assert!(
        o.status.success(),
        "render {extra:?} --backend {backend} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).expect("JSON on stdout")
}

fn same_png(a: &Path, b: &Path) -> bool {
    std::fs::read(a).unwrap() == std::fs::read(b).unwrap()
}

#[test]
fn converged_gpu_png_equals_the_cpu_png() {
    if !have_gpu() {
        return;
    }
    let dir = tempdir("progressive-gpu-png");
    let cases: &[&[&str]] = &[
        &[],
        &["--budget", "20000"],
        &["--budget", "auto", "--probe", "5000"],
        &["--view", "top", "--ortho", "--color", "classification", "--budget", "50000"],
        &["--color", "elevation", "--edl", "--hole-fill", "--precision", "30"],
        &[
            "--view",
            "closeup",
            "--color",
            "intensity",
            "--background",
            "#203040",
            "--budget",
            "33333",
        ],
    ];
    for (i, extra) in cases.iter().enumerate() {
        let args = [&["--progressive", "converge"][..], extra].concat();
        let cpu_png = dir.join(format!("cpu{i}.png"));
        let gpu_png = dir.join(format!("gpu{i}.png"));
        let cpu = render(&cpu_png, "cpu", &args);
        let gpu = render(&gpu_png, "gpu", &args);
        assert_eq!((cpu["backend"].as_str(), gpu["backend"].as_str()), (Some("cpu"), Some("gpu")));
        assert!(cpu["gpu"].is_null());
        assert!(gpu["gpu"]["adapter"].as_str().is_some_and(|s| !s.is_empty()));
        assert_eq!(gpu["gpu"]["atomics"], "64");
        assert_eq!(
            (cpu["converged"].as_bool(), gpu["converged"].as_bool()),
            (Some(true), Some(true)),
            "case {extra:?}"
        );
        for k in ["points", "pixels_covered", "color", "color_range", "shuffle"] {
            assert_eq!(gpu[k], cpu[k], "case {extra:?}: {k}");
        }
        assert!(
            same_png(&cpu_png, &gpu_png),
            "case {extra:?}: the GPU's converged PNG differs from the CPU's"
        );
    }
}

#[test]
fn preloaded_frames_equal_the_cpu_frames() {
    if !have_gpu() {
        return;
    }
    let dir = tempdir("progressive-gpu-frames");
    // 110,000 points in budgets of 30,000: converged at frame 4; frame 2 is unfinished.
    for (frames, converged) in [("2", false), ("5", true)] {
        let args = ["--progressive", frames, "--preload", "--budget", "30000"];
        let cpu_png = dir.join(format!("cpu{frames}.png"));
        let gpu_png = dir.join(format!("gpu{frames}.png"));
        let cpu = render(&cpu_png, "cpu", &args);
        let gpu = render(&gpu_png, "gpu", &args);
        assert_eq!(gpu["converged"].as_bool(), Some(converged));
        let (cf, gf) = (cpu["frames"].as_array().unwrap(), gpu["frames"].as_array().unwrap());
        assert_eq!(cf.len(), gf.len());
        for (c, g) in cf.iter().zip(gf) {
            for k in [
                "frame",
                "loaded",
                "reprojected",
                "filled",
                "fill_points",
                "visible",
                "points_drawn",
                "converged",
            ] {
                assert_eq!(g[k], c[k], "--progressive {frames}, frame {}: {k}", c["frame"]);
            }
            assert!(c["gpu_frame_ms"].is_null());
            assert_eq!(g["gpu_frame_ms"].is_f64(), gpu["gpu"]["timestamps"] == true);
        }
        assert_eq!(gpu["convergence_frame"], cpu["convergence_frame"]);
        assert!(same_png(&cpu_png, &gpu_png), "--progressive {frames}: PNGs differ");
    }
}

#[test]
fn adaptive_budget_reports_how_it_was_timed() {
    if !have_gpu() {
        return;
    }
    let ctx = mortar_render::testing::context_or_skip(AtomicPath::U64, None).expect("checked");
    let dir = tempdir("progressive-gpu-auto");
    let j = render(
        &dir.join("a.png"),
        "gpu",
        &[
            "--progressive",
            "4",
            "--preload",
            "--budget",
            "auto",
            "--probe",
            "10000",
            "--target-ms",
            "60000",
        ],
    );
    let timing = if ctx.has_timestamps() { "gpu-timestamps" } else { "host-clock" };
    assert_eq!(j["gpu"]["timing"], timing);
    assert_eq!(j["gpu"]["timestamps"], ctx.has_timestamps());
    assert!(j["budget"]["auto"].is_object());
    let frames = j["frames"].as_array().unwrap();
    assert!(frames.iter().all(|f| f["probe"] == 10_000 && f["filled"].as_u64().unwrap() >= 10_000));
    // A minute of frame time is plenty for the whole sample after the probe, even when the
    // probe was timed on a loaded two-core machine under a software GPU (a one-second target
    // filled 93,514 of 110,000 points on CI).
    assert_eq!(frames[0]["filled"], 110_000);
    assert_eq!(j["convergence_frame"], 1);
}

#[test]
fn the_32_bit_path_is_refused_with_a_clear_message() {
    if mortar_render::testing::context_or_skip(AtomicPath::TwoPass32, None).is_none() {
        return;
    }
    let dir = tempdir("progressive-gpu-32");
    let out = dir.join("x.png");
    let o = mortar()
        .arg("render")
        .arg(sample())
        .arg("-o")
        .arg(&out)
        .args(["--progressive", "converge", "--backend", "gpu", "--atomics", "32"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("needs 64-bit atomics") && err.contains("--backend gpu"), "{err}");
    assert!(!out.exists());
}
