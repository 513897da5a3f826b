//! `mortar view` in a real window (issue 6): under Xvfb the viewer opens its window, draws a few
//! frames with the GPU rasterizer (resolved on the GPU and put on the window's surface by the
//! present pass) and writes what the surface shows; the CPU fallback (frames uploaded to the
//! window as pixels) shows the same picture.
//!
//! Needs `Xvfb` (Debian package `xvfb`) and, for the GPU half, a Vulkan adapter (lavapipe in CI).
//! Without Xvfb the window tests skip with a printed reason, unless `MORTAR_REQUIRE_GPU` is set
//! (CI), where they fail instead.

mod common;

use common::*;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// Rows of the status line's bar at widths below 1600 px (8 px glyphs and 3 px padding).
const STATUS_ROWS: usize = 14;

fn sample() -> PathBuf {
    root().join("data-samples/autzen_trim.laz")
}

fn required() -> bool {
    std::env::var_os("MORTAR_REQUIRE_GPU").is_some()
}

fn find_in_path(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path).map(|d| d.join(name)).find(|p| p.is_file())
}

/// An Xvfb server on a display number it chose itself (`-displayfd`), stopped when dropped.
struct Xvfb {
    child: Child,
    display: String,
}

impl Xvfb {
    /// Starts Xvfb, or says why not: `Err` with a reason when it is not installed (a skip, or a
    /// failure under `MORTAR_REQUIRE_GPU`).
    fn start() -> Result<Xvfb, String> {
        let Some(bin) = find_in_path("Xvfb") else {
            return Err("no Xvfb in PATH (install the Debian package xvfb)".into());
        };
        let mut child = Command::new(bin)
            // `-noreset`: without it the server resets whenever its last client leaves, and a viewer
            // started during that reset is refused ("Failed to open connection to X server").
            .args([
                "-displayfd",
                "1",
                "-screen",
                "0",
                "1024x768x24",
                "-nolisten",
                "tcp",
                "-noreset",
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("cannot start Xvfb: {e}"))?;
        // Xvfb writes the display number it took once it accepts connections.
        let stdout = child.stdout.take().expect("piped");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut r = BufReader::new(stdout);
            let mut line = String::new();
            let _ = r.read_line(&mut line);
            let _ = tx.send(line);
            // Keep the pipe open (drained) while the server runs: a write to a closed pipe would
            // kill it with SIGPIPE in the middle of a test.
            let _ = std::io::copy(&mut r, &mut std::io::sink());
        });
        match rx.recv_timeout(Duration::from_secs(30)) {
            Ok(line) if line.trim().parse::<u32>().is_ok() => {
                Ok(Xvfb { child, display: format!(":{}", line.trim()) })
            }
            other => {
                let _ = child.kill();
                let _ = child.wait();
                panic!("Xvfb did not report a display: {other:?}");
            }
        }
    }
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Xvfb, or `None` after printing why the test skips (a panic under `MORTAR_REQUIRE_GPU`).
fn xvfb_or_skip() -> Option<Xvfb> {
    match Xvfb::start() {
        Ok(x) => Some(x),
        Err(why) if !required() => {
            eprintln!("SKIPPED: {why}");
            None
        }
        Err(why) => panic!("MORTAR_REQUIRE_GPU is set but the window test cannot run: {why}"),
    }
}

fn view(display: &str, args: &[&str]) -> std::process::Output {
    let mut c = mortar();
    c.arg("view").args(args).env("DISPLAY", display).env_remove("WAYLAND_DISPLAY");
    run_limited(c, Duration::from_secs(300))
}

/// An RGBA8 PNG as `(width, height, pixels)`.
fn read_png(p: &Path) -> (u32, u32, Vec<[u8; 4]>) {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size()];
    let info = r.next_frame(&mut buf).unwrap();
    assert_eq!((info.color_type, info.bit_depth), (png::ColorType::Rgba, png::BitDepth::Eight));
    let px = buf[..info.buffer_size()].chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect();
    (info.width, info.height, px)
}

/// Pixels below the status line whose colour is not the background (black).
fn drawn_below_status(w: u32, px: &[[u8; 4]]) -> usize {
    px[STATUS_ROWS * w as usize..].iter().filter(|p| p[..3] != [0, 0, 0]).count()
}

fn shoot(
    display: &str,
    dir: &Path,
    name: &str,
    extra: &[&str],
) -> (serde_json::Value, (u32, u32, Vec<[u8; 4]>)) {
    let png = dir.join(name);
    let input = sample();
    let mut args = vec![
        input.to_str().unwrap(),
        "--no-progressive",
        "--width",
        "320",
        "--height",
        "240",
        "--screenshot",
        png.to_str().unwrap(),
        "--frames",
        "3",
        "--json",
    ];
    args.extend_from_slice(extra);
    let o = view(display, &args);
    assert!(o.status.success(), "mortar view {args:?}: {}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&o.stdout)));
    assert_eq!(j["frames"].as_array().map(Vec::len), Some(3), "{j}");
    assert_eq!(j["points"], 110_000);
    (j, read_png(&png))
}

#[test]
fn view_draws_the_sample_in_a_window_on_the_gpu_and_the_cpu() {
    let Some(x) = xvfb_or_skip() else { return };
    let dir = tempdir("window");
    // The CPU fallback needs no GPU: softbuffer puts its frames on the X window.
    let (cj, (w, h, cpu)) = shoot(&x.display, &dir, "cpu.png", &["--backend", "cpu"]);
    assert_eq!((w, h), (320, 240));
    assert_eq!(cj["renderer"]["backend"], "cpu");
    let drawn = drawn_below_status(w, &cpu);
    // The iso view of the 110,000 point sample covers about 14 % of a 320x240 window.
    assert!(drawn > 5_000 && drawn < 30_000, "{drawn} pixels drawn by the CPU");
    // The status line: a dark bar with white text over the top-left corner.
    let white =
        cpu[..STATUS_ROWS * w as usize].iter().filter(|p| **p == [255, 255, 255, 255]).count();
    assert!(white > 100, "{white} white pixels in the status line");

    if mortar_render::testing::context_or_skip(mortar_render::AtomicPath::TwoPass32, None).is_none()
    {
        return;
    }
    let (gj, (gw, gh, gpu)) = shoot(&x.display, &dir, "gpu.png", &["--backend", "gpu"]);
    assert_eq!((gw, gh), (320, 240));
    let r = &gj["renderer"];
    assert_eq!(r["backend"], "gpu", "{gj}");
    assert!(r["read_back"] == "surface texture" || r["read_back"] == "resolved image", "{gj}");
    eprintln!(
        "gpu: {} on {}, surface {}, read back from the {}",
        r["atomics"], r["adapter"], r["surface_format"], r["read_back"]
    );
    let drawn_gpu = drawn_below_status(gw, &gpu);
    assert!(drawn_gpu > 5_000 && drawn_gpu < 30_000, "{drawn_gpu} pixels drawn by the GPU");
    // Same view, same colours: the GPU's keys equal the CPU's (tests/gpu.rs), so the pictures
    // agree below the status line (whose frame times differ).
    let start = STATUS_ROWS * w as usize;
    let differ = cpu[start..].iter().zip(&gpu[start..]).filter(|(a, b)| a != b).count();
    assert_eq!(differ, 0, "{differ} pixels differ between the CPU and the GPU window");

    // Another colour mode and the 32-bit path, through the same present pass.
    let (_, (_, _, elev)) = shoot(
        &x.display,
        &dir,
        "elevation.png",
        &["--backend", "gpu", "--atomics", "32", "--color", "elevation", "--no-status"],
    );
    let drawn_elev = elev.iter().filter(|p| p[..3] != [0, 0, 0]).count();
    assert!(drawn_elev > 5_000, "{drawn_elev} pixels drawn in elevation colours");
    let recoloured = elev[start..]
        .iter()
        .zip(&gpu[start..])
        .filter(|(a, b)| a[..3] != [0, 0, 0] && a != b)
        .count();
    assert!(
        recoloured > drawn_elev / 2,
        "elevation colours look like RGB: {recoloured} of {drawn_elev} differ"
    );

    // Hole filling and eye-dome lighting: passes on the GPU, the CPU resolve on the CPU, the
    // same window either way; and not the plain picture.
    let post = ["--hole-fill", "2", "--edl", "2"];
    let (_, (_, _, cpu_post)) =
        shoot(&x.display, &dir, "cpu-post.png", &[&post[..], &["--backend", "cpu"]].concat());
    for atomics in ["64", "32"] {
        if atomics == "64"
            && mortar_render::testing::context_or_skip(mortar_render::AtomicPath::U64, None)
                .is_none()
        {
            continue;
        }
        let name = format!("gpu-post-{atomics}.png");
        let (_, (_, _, gpu_post)) = shoot(
            &x.display,
            &dir,
            &name,
            &[&post[..], &["--backend", "gpu", "--atomics", atomics]].concat(),
        );
        let differ =
            cpu_post[start..].iter().zip(&gpu_post[start..]).filter(|(a, b)| a != b).count();
        assert_eq!(differ, 0, "--atomics {atomics}: {differ} pixels differ between the CPU and the GPU window with hole filling and EDL");
    }
    let changed = cpu_post[start..].iter().zip(&cpu[start..]).filter(|(a, b)| a != b).count();
    assert!(changed > 1000, "hole filling and EDL changed only {changed} pixels");
}

#[test]
fn view_fails_clearly_on_bad_input_under_a_display() {
    let Some(x) = xvfb_or_skip() else { return };
    let dir = tempdir("window-bad");
    let missing = dir.join("missing.mbat");
    let o = view(
        &x.display,
        &[missing.to_str().unwrap(), "--screenshot", dir.join("x.png").to_str().unwrap()],
    );
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("missing.mbat"), "{err}");
    let bad = dir.join("bad.laz");
    std::fs::write(&bad, b"LASF not really").unwrap();
    let o = view(
        &x.display,
        &[bad.to_str().unwrap(), "--screenshot", dir.join("y.png").to_str().unwrap()],
    );
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("bad.laz") && !err.contains("panicked"), "{err}");
    assert!(!dir.join("y.png").exists() && !dir.join("x.png").exists());
}

#[test]
fn view_without_a_display_is_a_clear_error() {
    let mut c = mortar();
    c.arg("view").arg(sample()).env_remove("DISPLAY").env_remove("WAYLAND_DISPLAY");
    let o = run_limited(c, Duration::from_secs(60));
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("cannot open a window") && !err.contains("panicked"), "{err}");
}

/// Builds the sample into a store `dir/name`.
fn build_store(dir: &Path, name: &str) -> PathBuf {
    let store = dir.join(name);
    run_ok(mortar().arg("build").arg(sample()).arg("-o").arg(&store));
    store
}

/// Pixels differing below the status line.
fn differ_below_status(w: u32, a: &[[u8; 4]], b: &[[u8; 4]]) -> usize {
    let start = STATUS_ROWS * w as usize;
    a[start..].iter().zip(&b[start..]).filter(|(x, y)| x != y).count()
}

#[test]
fn view_draws_a_store_with_lod_on_the_cpu_and_the_gpu() {
    let Some(x) = xvfb_or_skip() else { return };
    let dir = tempdir("window-store");
    let store = build_store(&dir, "store");
    let shot = |name: &str, extra: &[&str]| {
        let png = dir.join(name);
        let mut args = vec![
            store.to_str().unwrap(),
            "--width",
            "320",
            "--height",
            "240",
            "--screenshot",
            png.to_str().unwrap(),
            "--frames",
            "2",
            "--json",
        ];
        args.extend_from_slice(extra);
        let o = view(&x.display, &args);
        assert!(o.status.success(), "mortar view {args:?}: {}", String::from_utf8_lossy(&o.stderr));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(j["points"], 110_000, "{j}");
        (j, read_png(&png))
    };
    let (cj, (w, h, cpu)) = shot("cpu.png", &["--backend", "cpu"]);
    assert_eq!((w, h), (320, 240));
    assert_eq!(cj["color"], "auto");
    let drawn = drawn_below_status(w, &cpu);
    assert!(drawn > 5_000 && drawn < 30_000, "{drawn} pixels drawn by the CPU");
    // A coarse LOD threshold draws fewer samples than full detail.
    let (full, _) = shot("full.png", &["--backend", "cpu", "--lod-threshold", "0"]);
    let (coarse, _) = shot("coarse.png", &["--backend", "cpu", "--lod-threshold", "2000"]);
    let samples = |j: &serde_json::Value| j["frames"][1]["points_drawn"].as_u64().unwrap();
    assert!(
        samples(&coarse) < samples(&full),
        "coarse {} vs full {}",
        samples(&coarse),
        samples(&full)
    );
    // Attribute colours work under LOD: every sample is a real point with its record.
    let (kj, (_, _, cclass)) =
        shot("cpu-class.png", &["--backend", "cpu", "--color", "classification", "--no-status"]);
    assert_eq!(kj["color"], "classification");
    // A mode the format lacks is refused, naming the store.
    let o = view(
        &x.display,
        &[
            store.to_str().unwrap(),
            "--color",
            "no-such-mode",
            "--screenshot",
            dir.join("no.png").to_str().unwrap(),
        ],
    );
    assert_ne!(o.status.code(), Some(0));

    if mortar_render::testing::context_or_skip(mortar_render::AtomicPath::TwoPass32, None).is_none()
    {
        return;
    }
    // The GPU uploads the selected nodes and draws them from one scene: the same picture.
    let (gj, (_, _, gpu)) = shot("gpu.png", &["--backend", "gpu"]);
    assert_eq!(gj["renderer"]["backend"], "gpu", "{gj}");
    assert_eq!(differ_below_status(w, &cpu, &gpu), 0, "CPU and GPU store views differ");
    let (_, (_, _, ce)) =
        shot("cpu-elev.png", &["--backend", "cpu", "--color", "elevation", "--no-status"]);
    let (_, (_, _, ge)) =
        shot("gpu-elev.png", &["--backend", "gpu", "--color", "elevation", "--no-status"]);
    assert_eq!(differ_below_status(w, &ce, &ge), 0, "CPU and GPU elevation store views differ");
    assert!(
        differ_below_status(w, &ce, &cpu) > drawn / 2,
        "elevation looks like the stored colours"
    );
    let (_, (_, _, gclass)) =
        shot("gpu-class.png", &["--backend", "gpu", "--color", "classification", "--no-status"]);
    assert_eq!(
        differ_below_status(w, &cclass, &gclass),
        0,
        "CPU and GPU classification store views differ"
    );
    for mode in ["intensity", "gps-time", "return-number"] {
        let (_, (_, _, c)) =
            shot(&format!("cpu-{mode}.png"), &["--backend", "cpu", "--color", mode, "--no-status"]);
        let (_, (_, _, g)) =
            shot(&format!("gpu-{mode}.png"), &["--backend", "gpu", "--color", mode, "--no-status"]);
        assert_eq!(differ_below_status(w, &c, &g), 0, "CPU and GPU {mode} store views differ");
    }
}

#[test]
fn build_preview_shows_the_store_while_it_grows() {
    let Some(x) = xvfb_or_skip() else { return };
    let dir = tempdir("window-preview");
    // The preview below builds with the incremental engine (a commit per update), so the
    // reference does too: the same hierarchy bytes and the same baked colours.
    let reference = dir.join("reference");
    run_ok(
        mortar()
            .arg("build")
            .arg(sample())
            .arg("-o")
            .arg(&reference)
            .args(["--engine", "incremental"]),
    );
    let mut backends = vec!["cpu"];
    if mortar_render::testing::context_or_skip(mortar_render::AtomicPath::TwoPass32, None).is_some()
    {
        backends.push("gpu");
    }
    let view_png = dir.join("view.png");
    let o = view(
        &x.display,
        &[
            reference.to_str().unwrap(),
            "--width",
            "320",
            "--height",
            "240",
            "--backend",
            "cpu",
            "--no-status",
            "--screenshot",
            view_png.to_str().unwrap(),
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (_, _, expected) = read_png(&view_png);
    for backend in backends {
        let store = dir.join(format!("store-{backend}"));
        let png = dir.join(format!("preview-{backend}.png"));
        let mut c = mortar();
        c.arg("build").arg(sample()).arg("-o").arg(&store);
        c.args([
            "--preview",
            "--preview-backend",
            backend,
            "--preview-size",
            "320x240",
            "--preview-screenshot",
        ])
        .arg(&png);
        // A commit after every 5,000-point update: the window sees the store grow.
        c.args([
            "--engine",
            "incremental",
            "--commit-every",
            "0",
            "--batch-points",
            "5000",
            "--json",
        ]);
        c.env("DISPLAY", &x.display).env_remove("WAYLAND_DISPLAY");
        let o = run_limited(c, Duration::from_secs(300));
        assert!(
            o.status.success(),
            "build --preview {backend}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(j["points"], 110_000);
        assert!(j["commits"].as_u64().unwrap() >= 20, "{}", j["commits"]);
        let p = &j["preview"];
        assert_eq!(p["renderer"]["backend"], backend, "{p}");
        let frames = p["frames"].as_array().unwrap();
        // Frames were drawn while the store grew, not only at the end: at least one before the
        // last (how many depends on how the two threads are scheduled; on a loaded 2-core
        // machine a build of 22 commits has been seen with 2), and one of them partial (below).
        assert!(frames.len() >= 2, "{} preview frames", frames.len());
        let drawn: Vec<u64> = frames.iter().map(|f| f["points_drawn"].as_u64().unwrap()).collect();
        assert!(
            drawn.iter().any(|&d| d > 0 && d < *drawn.last().unwrap()),
            "no partial store was shown: {drawn:?}"
        );
        // The last frame shows the finished store as `mortar view` shows it.
        let (w, h, shown) = read_png(&png);
        assert_eq!((w, h), (320, 240));
        assert_eq!(
            differ_below_status(w, &shown, &expected),
            0,
            "{backend}: the preview's last frame is not the finished store"
        );
        // The store itself is the same as one built without a window.
        let a = std::fs::read(store.join("hierarchy.bin")).unwrap();
        let b = std::fs::read(reference.join("hierarchy.bin")).unwrap();
        assert_eq!(a.len(), b.len());
    }
}

#[test]
fn view_draws_raw_las_progressively_until_the_image_is_final() {
    let Some(x) = xvfb_or_skip() else { return };
    let dir = tempdir("window-progressive");
    let input = sample();
    let shot = |name: &str, extra: &[&str]| {
        let png = dir.join(name);
        let mut args = vec![
            input.to_str().unwrap(),
            "--width",
            "320",
            "--height",
            "240",
            "--no-status",
            "--screenshot",
            png.to_str().unwrap(),
            "--json",
        ];
        args.extend_from_slice(extra);
        let o = view(&x.display, &args);
        assert!(o.status.success(), "mortar view {args:?}: {}", String::from_utf8_lossy(&o.stderr));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        (j, read_png(&png))
    };
    // Progressive (the default for raw LAS/LAZ): the screenshot waits for the final image.
    let (pj, (w, h, progressive)) = shot("progressive.png", &["--backend", "cpu"]);
    assert_eq!((w, h), (320, 240));
    assert_eq!(pj["points"], 110_000);
    let frames = pj["frames"].as_array().unwrap();
    assert!(!frames.is_empty());
    // The final image is the headless progressive render's once converged (which
    // tests/progressive.rs checks against the brute-force render), pixel for pixel.
    let png = dir.join("render.png");
    run_ok(
        mortar()
            .arg("render")
            .arg(&input)
            .args(["--progressive", "converge", "--width", "320", "--height", "240", "-o"])
            .arg(&png),
    );
    let (_, _, rendered) = read_png(&png);
    let differ = progressive.iter().zip(&rendered).filter(|(a, b)| a != b).count();
    let drawn = rendered.iter().filter(|p| p[..3] != [0, 0, 0]).count();
    assert!(drawn > 5_000, "{drawn}");
    assert_eq!(differ, 0, "{differ} of {drawn} pixels differ between the window and mortar render --progressive converge");
    // The first frames show part of the points, the last all of them.
    let drawn: Vec<u64> = frames.iter().map(|f| f["points_drawn"].as_u64().unwrap()).collect();
    assert!(drawn.len() >= 2 && drawn[0] < *drawn.iter().max().unwrap(), "{drawn:?}");
    // The GPU progressive renderer (64-bit atomics) in the window: same keys, and for RGB the
    // same colours, so the same final picture.
    if mortar_render::testing::context_or_skip(mortar_render::AtomicPath::U64, None).is_some() {
        let (gj, (_, _, gpu)) = shot("progressive-gpu.png", &["--backend", "gpu"]);
        assert_eq!(gj["renderer"]["backend"], "gpu", "{gj}");
        let differ = gpu.iter().zip(&progressive).filter(|(a, b)| a != b).count();
        assert_eq!(
            differ, 0,
            "{differ} pixels differ between the GPU and the CPU progressive window"
        );
        // With 32-bit atomics the progressive view falls back to the CPU renderer.
        let (cj, _) = shot("progressive-32.png", &["--backend", "gpu", "--atomics", "32"]);
        assert_eq!(cj["renderer"]["backend"], "cpu", "{cj}");
    }
    // Another colour mode that needs another attribute: streamed in, then final again.
    let (cj, (_, _, class)) = shot("class.png", &["--backend", "cpu", "--color", "classification"]);
    assert_eq!(cj["color"], "classification");
    let recoloured = class.iter().zip(&progressive).filter(|(a, b)| a != b).count();
    assert!(recoloured > 1000, "{recoloured} pixels changed colour");
}

#[test]
fn a_failing_build_closes_its_preview_and_reports_the_error() {
    let Some(x) = xvfb_or_skip() else { return };
    let dir = tempdir("window-preview-bad");
    // A LAZ file whose second chunk is damaged: the build fails after it started (its first
    // batch, the first chunk, went in).
    let las = dir.join("bad.laz");
    let mut b = std::fs::read(sample()).unwrap();
    let at = b.len() * 6 / 10;
    for x in &mut b[at..at + 2000] {
        *x = x.wrapping_mul(7).wrapping_add(13);
    }
    std::fs::write(&las, &b).unwrap();
    for extra in [
        &["--preview-backend", "cpu"][..],
        &["--preview-backend", "cpu", "--preview-offscreen"][..],
    ] {
        let store = dir.join("s");
        let mut c = mortar();
        c.arg("build")
            .arg(&las)
            .arg("-o")
            .arg(&store)
            .args(["--batch-points", "50000"])
            .arg("--preview")
            .args(extra);
        c.env("DISPLAY", &x.display).env_remove("WAYLAND_DISPLAY");
        let o = run_limited(c, Duration::from_secs(120));
        assert_eq!(o.status.code(), Some(1), "{extra:?}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("bad.laz") && err.contains("corrupt") && !err.contains("panicked"),
            "{extra:?}: {err}"
        );
        assert!(!store.exists(), "no half-written store");
    }
}

#[test]
fn progressive_and_no_progressive_windows_show_the_same_picture() {
    // The one framing rule and the one colour-range rule: `mortar view` of raw LAS/LAZ draws the
    // same picture whether it draws progressively or batches the file first (CPU and GPU), with
    // hole filling and eye-dome lighting, intensity over the range of all points; only pixels
    // whose winner ties in depth with another point may show another one (the two renderers
    // number points otherwise), and hole filling may carry such a pixel into its neighbours.
    // At full precision: the batch rasterizer's adaptive 10-bit batches move points by up to a
    // quarter pixel.
    let Some(x) = xvfb_or_skip() else { return };
    let dir = tempdir("window-same");
    let input = sample();
    let common = [
        "--width",
        "320",
        "--height",
        "240",
        "--precision",
        "30",
        "--color",
        "intensity",
        "--hole-fill",
        "--edl",
    ];
    let shot = |name: &str, extra: &[&str]| {
        let png = dir.join(name);
        let mut args = vec![
            input.to_str().unwrap(),
            "--no-status",
            "--screenshot",
            png.to_str().unwrap(),
            "--frames",
            "2",
        ];
        args.extend_from_slice(&common);
        args.extend_from_slice(extra);
        let o = view(&x.display, &args);
        assert!(o.status.success(), "mortar view {args:?}: {}", String::from_utf8_lossy(&o.stderr));
        read_png(&png).2
    };
    let png = dir.join("render.png");
    let o = run_ok(
        mortar()
            .arg("render")
            .arg(&input)
            .args(["--progressive", "converge", "--json", "-o"])
            .arg(&png)
            .args(common),
    );
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let ties = j["depth_ties"].as_u64().unwrap() as usize;
    let progressive = shot("p-cpu.png", &["--backend", "cpu"]);
    let batched = shot("b-cpu.png", &["--backend", "cpu", "--no-progressive"]);
    let drawn = batched.iter().filter(|p| p[..3] != [0, 0, 0]).count();
    assert!(drawn > 5_000, "{drawn}");
    let differ = |a: &[[u8; 4]], b: &[[u8; 4]]| a.iter().zip(b).filter(|(p, q)| p != q).count();
    let d = differ(&progressive, &batched);
    eprintln!("{d} of {drawn} pixels differ, {ties} tied pixels");
    assert!(
        d <= 9 * ties,
        "{d} of {drawn} pixels differ between --progressive and --no-progressive ({ties} ties)"
    );
    if mortar_render::testing::context_or_skip(mortar_render::AtomicPath::U64, None).is_some() {
        let gpu_progressive = shot("p-gpu.png", &["--backend", "gpu"]);
        let gpu_batched = shot("b-gpu.png", &["--backend", "gpu", "--no-progressive"]);
        assert_eq!(differ(&gpu_progressive, &progressive), 0, "GPU and CPU progressive windows");
        assert_eq!(differ(&gpu_batched, &batched), 0, "GPU and CPU batch windows");
    }
}

#[test]
fn build_preview_runs_the_gpu_engine() {
    // Issue 29: the GPU engine under the preview: it commits level by level as the sorted engine
    // does, the window shows the growing store, and the store is the sorted engine's.
    let Some(x) = xvfb_or_skip() else { return };
    if mortar_render::testing::context_or_skip(mortar_render::AtomicPath::TwoPass32, None).is_none()
    {
        return;
    }
    let dir = tempdir("window-preview-gpu");
    let reference = dir.join("reference");
    run_ok(mortar().arg("build").arg(sample()).arg("-o").arg(&reference).args([
        "--engine",
        "sorted",
        "--leaf-capacity",
        "500",
    ]));
    let view_png = dir.join("view.png");
    let o = view(
        &x.display,
        &[
            reference.to_str().unwrap(),
            "--width",
            "320",
            "--height",
            "240",
            "--backend",
            "gpu",
            "--no-status",
            "--screenshot",
            view_png.to_str().unwrap(),
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (_, _, expected) = read_png(&view_png);
    let store = dir.join("store");
    let png = dir.join("preview.png");
    let mut c = mortar();
    c.arg("build").arg(sample()).arg("-o").arg(&store);
    c.args(["--preview", "--preview-backend", "gpu", "--preview-size", "320x240"]);
    c.arg("--preview-screenshot").arg(&png);
    c.args(["--engine", "gpu", "--leaf-capacity", "500", "--json"]);
    c.env("DISPLAY", &x.display).env_remove("WAYLAND_DISPLAY");
    let o = run_limited(c, Duration::from_secs(300));
    assert!(
        o.status.success(),
        "build --preview --engine gpu: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((j["engine"].as_str(), j["points"].as_u64()), (Some("gpu"), Some(110_000)), "{j}");
    // One commit per level.
    assert!(j["commits"].as_u64().unwrap() >= 3, "{}", j["commits"]);
    assert_eq!(j["preview"]["renderer"]["backend"], "gpu");
    assert!(!j["preview"]["frames"].as_array().unwrap().is_empty());
    let (w, _, shown) = read_png(&png);
    assert_eq!(differ_below_status(w, &shown, &expected), 0, "the last frame is not the store");
    for f in ["nodes.bin", "hierarchy.bin", "source.las"] {
        assert!(
            std::fs::read(store.join(f)).unwrap() == std::fs::read(reference.join(f)).unwrap(),
            "{f} differs from the sorted engine's"
        );
    }
}

/// Issue 30 §1: `mortar view` of a COPC file or an EPT directory selects nodes by the store's
/// rule and decodes only those: every node framed at threshold 0 (the picture `mortar render`
/// draws, but where points tie in depth), a small share for a closeup; the GPU draws what the
/// CPU draws.
#[test]
fn view_streams_copc_and_ept_nodes() {
    let Some(x) = xvfb_or_skip() else { return };
    let dir = tempdir("window-copc");
    let copc = dir.join("sample.copc.laz");
    run_ok(
        mortar()
            .arg("export")
            .arg(sample())
            .args(["--format", "copc", "--leaf-capacity", "5000", "-q", "-o"])
            .arg(&copc),
    );
    let gpu = mortar_render::testing::context_or_skip(mortar_render::AtomicPath::TwoPass32, None)
        .is_some();
    let mut inputs = vec![(copc.clone(), 110_000u64)];
    if let Some(data) = shared_data() {
        inputs.push((data.join("potree/pointclouds/lion_takanawa.copc.laz"), 341_989));
        inputs.push((data.join("PyForestScan/example_data/ept"), 14_142_410));
    }
    let differ = |a: &[[u8; 4]], b: &[[u8; 4]]| a.iter().zip(b).filter(|(p, q)| p != q).count();
    for (input, points) in &inputs {
        let name = input.file_name().unwrap().to_string_lossy().to_string();
        let s = input.to_str().unwrap();
        for color in ["classification", "auto"] {
            let common = [
                "--width",
                "320",
                "--height",
                "240",
                "--precision",
                "30",
                "--color",
                color,
                "--range",
                "0,255",
                "--lod-threshold",
                "0",
            ];
            let shot = |backend: &str| {
                let png = dir.join(format!("{name}-{color}-{backend}.png"));
                let mut args = vec![s, "--no-status", "--screenshot", png.to_str().unwrap()];
                args.extend_from_slice(&["--json", "--backend", backend]);
                args.extend_from_slice(&common);
                let o = view(&x.display, &args);
                assert!(
                    o.status.success(),
                    "view {args:?}: {}",
                    String::from_utf8_lossy(&o.stderr)
                );
                let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
                (j, read_png(&png).2)
            };
            let (j, cpu) = shot("cpu");
            let c = &j["lod_source"];
            assert_eq!(j["points"].as_u64(), Some(*points), "{name}: {j}");
            assert_eq!(c["nodes_read"], c["nodes"], "{name}: framed at threshold 0: {c}");
            assert_eq!(c["points_read"].as_u64(), Some(*points), "{name}: {c}");
            let png = dir.join(format!("{name}-{color}-render.png"));
            let o = run_ok(
                mortar()
                    .arg("render")
                    .arg(input)
                    .args(["--backend", "cpu", "--json", "-o"])
                    .arg(&png)
                    .args(common),
            );
            let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
            let ties = r["depth_ties"].as_u64().unwrap() as usize;
            let rendered = read_png(&png).2;
            let drawn = rendered.iter().filter(|p| p[..3] != [0, 0, 0]).count();
            let d = differ(&cpu, &rendered);
            eprintln!("{name} {color}: {d} of {drawn} pixels differ, {ties} depth ties");
            assert!(drawn > 2_000, "{name}: {drawn} pixels drawn");
            assert!(d <= ties, "{name} {color}: {d} pixels differ from render, {ties} ties");
            if gpu {
                let (gj, g) = shot("gpu");
                assert_eq!(gj["renderer"]["backend"], "gpu", "{gj}");
                // The GPU numbers points in upload order (coarse nodes first), the CPU in read
                // order: they differ at most where points tie in depth.
                let d = differ(&g, &cpu);
                assert!(d <= ties, "{name} {color}: the GPU and CPU views differ in {d} pixels");
            }
        }
    }
    // Closeups read a small share of the bytes, and draw what `mortar render` draws of the
    // same view (the same selection) but where points tie in depth.
    let mut closeups =
        vec![(copc.clone(), ["636300,849100,430", "636300,849000,500", "10"], 0.5, 100)];
    if let Some(data) = shared_data() {
        let ept = data.join("PyForestScan/example_data/ept");
        closeups.push((ept, ["202150,2184150,1300", "202150,2183950,1700", "15"], 0.1, 1_000));
    }
    // (input, camera, most bytes read, fewest pixels drawn: the sample is sparse)
    for (input, [target, eye, fov], most, fewest) in &closeups {
        let common = [
            "--width",
            "320",
            "--height",
            "240",
            "--target",
            target,
            "--eye",
            eye,
            "--fov",
            fov,
            "--precision",
            "30",
            "--color",
            "classification",
            "--backend",
            "cpu",
            "--json",
        ];
        let png = dir.join("closeup.png");
        let mut args = vec![input.to_str().unwrap(), "--no-status", "--screenshot"];
        args.push(png.to_str().unwrap());
        args.extend_from_slice(&common);
        let o = view(&x.display, &args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let c = &j["lod_source"];
        let share = c["bytes_read"].as_f64().unwrap() / c["bytes"].as_f64().unwrap();
        assert!(
            share < *most,
            "{input:?}: the closeup read {:.1} % of the bytes: {c}",
            share * 100.0
        );
        assert!(c["nodes_read"].as_u64().unwrap() * 4 < c["nodes"].as_u64().unwrap(), "{c}");
        let shown = read_png(&png).2;
        let rpng = dir.join("closeup-render.png");
        let o = run_ok(mortar().arg("render").arg(input).arg("-o").arg(&rpng).args(common));
        let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(r["lod_source"]["nodes_read"], c["nodes_read"], "{r}");
        let rendered = read_png(&rpng).2;
        let d = differ(&shown, &rendered);
        let ties = r["depth_ties"].as_u64().unwrap() as usize;
        let drawn = drawn_below_status(320, &rendered);
        assert!(drawn > *fewest, "{input:?}: the closeup drew {drawn} pixels");
        assert!(d <= ties, "{input:?}: the closeup differs from render in {d} pixels, {ties} ties");
    }
}
