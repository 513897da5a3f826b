//! `mortar render <las|laz> --progressive` end to end (issue 6, paper 000): the converged image is
//! the brute-force image, frame k of a preloaded run draws k budgets, earlier frames show fewer
//! pixels, loading while rendering converges to the same image, the adaptive budget, and bad
//! input (batch files, stores, budget 0, broken files) ends in a clear error with exit code 1.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::Output;

fn sample() -> PathBuf {
    root().join("data-samples/autzen_trim.laz")
}

/// Points of the sample.
const POINTS: u64 = 110_000;

/// The view of every image here: small, transparent background (alpha marks covered pixels),
/// full precision (the comparison with the batch rasterizer is then about rounding alone).
const VIEW: &[&str] =
    &["--width", "320", "--height", "240", "--precision", "30", "--background", "transparent"];

/// RGBA8 pixels of a PNG, packed `r | g << 8 | b << 16 | a << 24`.
fn pixels(p: &Path) -> Vec<u32> {
    let bytes = std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    let mut reader =
        png::Decoder::new(std::io::Cursor::new(bytes)).read_info().expect("PNG header");
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).expect("PNG data");
    assert_eq!((info.width, info.height, info.color_type), (320, 240, png::ColorType::Rgba));
    buf[..info.buffer_size()]
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

fn opaque(px: &[u32]) -> usize {
    px.iter().filter(|&&c| c >> 24 != 0).count()
}

fn render(input: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut c = mortar();
    c.arg("render").arg(input).arg("-o").arg(out).args(VIEW).args(extra);
    c.output().expect("spawn")
}

fn render_json(input: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let o = render(input, out, &[extra, &["--json"]].concat());
    assert!(o.status.success(), "render {extra:?} failed: {}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).expect("JSON on stdout")
}

#[test]
fn converges_to_the_brute_force_image() {
    let dir = tempdir("progressive-converge");
    let final_png = dir.join("converged.png");
    let j = render_json(&sample(), &final_png, &["--progressive", "converge", "--budget", "20000"]);
    assert_eq!(j["renderer"], "progressive");
    assert_eq!(j["points"], POINTS);
    assert_eq!(j["loaded"], POINTS);
    assert_eq!(j["converged"], true);
    assert_eq!(j["budget"]["fixed"], 20000);
    assert_eq!(j["budget"]["frames_to_converge"], 6);
    assert!(j["convergence_frame"].as_u64().unwrap() >= 6, "{}", j["convergence_frame"]);
    assert!(j["convergence_seconds"].as_f64().unwrap() > 0.0);
    // The largest prime 3 mod 4 at most 110000 is 109987: 13 points stay in place.
    assert_eq!(j["shuffle"]["prime"], 109_987);
    assert_eq!(j["shuffle"]["unshuffled"], 13);
    let frames = j["frames"].as_array().unwrap();
    for w in frames.windows(2) {
        assert_eq!(w[1]["reprojected"], w[0]["visible"], "Reproject draws what Prepare collected");
        assert_eq!(w[1]["filled"], 20000);
    }
    let converged = pixels(&final_png);
    assert_eq!(opaque(&converged) as u64, j["pixels_covered"].as_u64().unwrap());
    assert!(opaque(&converged) > 8_000, "{}", opaque(&converged));

    // Preloaded, frame k draws budgets 1..k: ceil(110000 / 20000) = 6 frames converge, 5 do not.
    let six = dir.join("six.png");
    let j6 =
        render_json(&sample(), &six, &["--progressive", "6", "--preload", "--budget", "20000"]);
    assert_eq!((j6["frames_drawn"].as_u64(), j6["convergence_frame"].as_u64()), (Some(6), Some(6)));
    assert_eq!(
        std::fs::read(&six).unwrap(),
        std::fs::read(&final_png).unwrap(),
        "6 frames give the converged PNG"
    );
    let mut covered = Vec::new();
    for n in [1, 3, 5] {
        let png = dir.join(format!("frame{n}.png"));
        let jn = render_json(
            &sample(),
            &png,
            &["--progressive", &n.to_string(), "--preload", "--budget", "20000"],
        );
        assert_eq!(jn["converged"], false, "{n} frames");
        assert_eq!(jn["convergence_frame"], serde_json::Value::Null);
        let px = pixels(&png);
        // Still camera: a covered pixel stays covered (by the same or a nearer point).
        for (a, b) in px.iter().zip(&converged) {
            assert!(
                a >> 24 == 0 || b >> 24 != 0,
                "{n} frames: a pixel covered early is empty at the end"
            );
        }
        covered.push(opaque(&px));
    }
    covered.push(opaque(&converged));
    assert!(covered.windows(2).all(|w| w[0] < w[1]), "covered pixels per frame count: {covered:?}");
    // Frame 1 draws 18 % of the points, shuffled: already a good part of the image.
    assert!(covered[0] * 3 > covered[3], "{covered:?}");

    // One frame with a budget of every point: the brute-force render in the same frame.
    let all = dir.join("all.png");
    render_json(
        &sample(),
        &all,
        &["--progressive", "1", "--preload", "--budget", &POINTS.to_string()],
    );
    assert_eq!(std::fs::read(&all).unwrap(), std::fs::read(&final_png).unwrap());

    // The batch rasterizer (`mortar render` on a Morton-batched temporary file): other
    // quantization frames, but a point's key does not depend on them, so the same pixels are
    // covered and only ties of equal depth, which go to the smaller index in another numbering,
    // may show another point: at most the pixels both renders count as tied.
    let brute = dir.join("brute.png");
    let jb = render_json(&sample(), &brute, &["--backend", "cpu"]);
    let b = pixels(&brute);
    let coverage =
        b.iter().zip(&converged).filter(|(x, y)| (*x >> 24 == 0) != (*y >> 24 == 0)).count();
    let differ = b.iter().zip(&converged).filter(|(x, y)| x != y).count();
    let ties = j["depth_ties"].as_u64().unwrap() as usize;
    assert_eq!(coverage, 0, "coverage differs in {coverage} pixels");
    assert_eq!(jb["depth_ties"], j["depth_ties"], "both renders count the same ties");
    assert!(differ <= ties, "{differ} pixels differ from mortar render's, {ties} ties");
    assert!(ties * 100 < opaque(&b), "{ties} ties");
}

#[test]
fn loading_while_rendering_and_the_adaptive_budget_converge_alike() {
    let dir = tempdir("progressive-load");
    let reference = dir.join("ref.png");
    render_json(
        &sample(),
        &reference,
        &["--progressive", "1", "--preload", "--budget", &POINTS.to_string()],
    );
    // One loader thread, frames drawn while it decodes; small budget.
    let slow = dir.join("slow.png");
    let j = render_json(
        &sample(),
        &slow,
        &["--progressive", "converge", "--budget", "5000", "--load-threads", "1"],
    );
    assert_eq!(j["converged"], true);
    assert!(j["convergence_frame"].as_u64().unwrap() >= 22);
    let frames = j["frames"].as_array().unwrap();
    assert!(frames.iter().all(|f| f["fill_points"].as_u64() <= f["filled"].as_u64()));
    assert!(frames.windows(2).all(|w| w[0]["loaded"].as_u64() <= w[1]["loaded"].as_u64()));
    assert_eq!(std::fs::read(&slow).unwrap(), std::fs::read(&reference).unwrap());
    // The adaptive budget: a probe first, then what fits in the target frame time.
    let auto = dir.join("auto.png");
    let j = render_json(
        &sample(),
        &auto,
        &["--progressive", "converge", "--budget", "auto", "--target-ms", "5", "--probe", "2000"],
    );
    assert_eq!(j["budget"]["auto"]["target_ms"], 5.0);
    assert_eq!(j["budget"]["auto"]["probe"], 2000);
    let frames = j["frames"].as_array().unwrap();
    assert!(frames.iter().all(|f| f["probe"] == 2000 && f["filled"].as_u64().unwrap() >= 2000));
    assert_eq!(std::fs::read(&auto).unwrap(), std::fs::read(&reference).unwrap());
    // Paced like a 33 Hz display: frame k + 1 starts 30 ms after frame k.
    let paced = dir.join("paced.png");
    let j = render_json(
        &sample(),
        &paced,
        &["--progressive", "3", "--preload", "--budget", "20000", "--pace", "--target-ms", "30"],
    );
    assert_eq!(j["pace_ms"], 30.0);
    let at: Vec<f64> =
        j["frames"].as_array().unwrap().iter().map(|f| f["at_ms"].as_f64().unwrap()).collect();
    let first_ms = j["frames"][0]["frame_ms"].as_f64().unwrap();
    assert!(at[2] - at[0] >= 60.0 - first_ms - 1.0, "{at:?}");
    // A run cut short says so (without --json: a warning), and still writes its image.
    let short = dir.join("short.png");
    let o = render(&sample(), &short, &["--progressive", "1", "--preload", "--budget", "1000"]);
    assert!(o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("not final after 1 frames"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(opaque(&pixels(&short)) < opaque(&pixels(&reference)) / 10);
}

#[test]
fn colour_modes_match_the_batch_rasterizer() {
    let dir = tempdir("progressive-colours");
    for mode in ["classification", "return-number", "stored"] {
        let p = dir.join(format!("{mode}-p.png"));
        let b = dir.join(format!("{mode}-b.png"));
        let j = render_json(
            &sample(),
            &p,
            &["--progressive", "converge", "--budget", "50000", "--color", mode],
        );
        let ties = j["depth_ties"].as_u64().unwrap() as usize;
        let o = render(&sample(), &b, &["--backend", "cpu", "--color", mode]);
        assert!(o.status.success(), "{mode}: {}", String::from_utf8_lossy(&o.stderr));
        let (p, b) = (pixels(&p), pixels(&b));
        let differ = p.iter().zip(&b).filter(|(x, y)| x != y).count();
        // Only where the winner ties in depth.
        assert!(differ <= ties, "{mode}: {differ} pixels differ, {ties} ties");
    }
    // Elevation over a given range, with hole filling and eye-dome lighting on top.
    let (p, b) = (dir.join("el-p.png"), dir.join("el-b.png"));
    let extra = ["--color", "elevation", "--range", "400,480", "--hole-fill", "--edl"];
    let j = render_json(&sample(), &p, &[&["--progressive", "converge"][..], &extra].concat());
    let ties = j["depth_ties"].as_u64().unwrap() as usize;
    assert!(render(&sample(), &b, &[&["--backend", "cpu"][..], &extra].concat()).status.success());
    let (p, b) = (pixels(&p), pixels(&b));
    let differ = p.iter().zip(&b).filter(|(x, y)| x != y).count();
    // A tie pixel may also change the neighbours hole filling takes it into.
    assert!(differ <= 9 * ties, "elevation: {differ} pixels differ, {ties} ties");
    // Intensity over the range of all points (no --range): the same rule in both renderers.
    let (p, b) = (dir.join("i-p.png"), dir.join("i-b.png"));
    let j = render_json(
        &sample(),
        &p,
        &["--progressive", "converge", "--color", "intensity", "--view", "closeup"],
    );
    let jb = render_json(
        &sample(),
        &b,
        &["--backend", "cpu", "--color", "intensity", "--view", "closeup"],
    );
    assert_eq!(j["color_range"], jb["color_range"]);
    let differ = pixels(&p).iter().zip(&pixels(&b)).filter(|(x, y)| x != y).count();
    assert!(
        differ <= j["depth_ties"].as_u64().unwrap() as usize,
        "intensity: {differ} pixels differ"
    );
}

/// `mortar render input --progressive converge` and the brute-force render of `input`: the same
/// PNG but for counted depth ties, framed as `framing` says. Returns the progressive JSON.
fn same_as_brute_force(dir: &Path, input: &Path, framing: &str, points: u64) -> serde_json::Value {
    let (p, b) = (dir.join("same-p.png"), dir.join("same-b.png"));
    let j = render_json(input, &p, &["--progressive", "converge", "--budget", "40000"]);
    let jb = render_json(input, &b, &["--backend", "cpu"]);
    assert_eq!(
        (j["loaded"].as_u64(), j["converged"].as_bool()),
        (Some(points), Some(true)),
        "{}: {j}",
        input.display()
    );
    assert_eq!(j["framing"], framing, "{}", input.display());
    assert_eq!(j["camera"], jb["camera"], "{}: the same view", input.display());
    let (p, b) = (pixels(&p), pixels(&b));
    let differ = p.iter().zip(&b).filter(|(x, y)| x != y).count();
    let ties = j["depth_ties"].as_u64().unwrap() as usize;
    assert!(opaque(&b) > 5_000, "{}: {} pixels", input.display(), opaque(&b));
    assert!(differ <= ties, "{}: {differ} pixels differ, {ties} ties", input.display());
    j
}

/// A failing command: exit code 1, the expected words in its one-line message, no output file.
fn fails(input: &Path, out: &Path, extra: &[&str], words: &[&str]) {
    let o = render(input, out, extra);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{extra:?} should fail with 1: {err}");
    assert!(!err.contains("panicked"), "{err}");
    for w in words {
        assert!(err.contains(w), "{extra:?}: '{w}' not in: {err}");
    }
    assert!(!out.exists(), "{extra:?} wrote {}", out.display());
}

#[test]
fn bad_input_fails_clearly() {
    let dir = tempdir("progressive-bad");
    let out = dir.join("out.png");
    let s = sample();
    fails(
        &s,
        &out,
        &["--progressive", "3", "--budget", "0"],
        &["--budget 0", "at least one point"],
    );
    fails(&s, &out, &["--progressive", "0"], &["--progressive 0"]);
    fails(&s, &out, &["--progressive", "soon"], &["'soon'", "converge"]);
    fails(&s, &out, &["--progressive", "3", "--budget", "many"], &["--budget 'many'"]);
    fails(
        &s,
        &out,
        &["--progressive", "3", "--budget", "10", "--target-ms", "5"],
        &["--budget auto", "--pace"],
    );
    fails(
        &s,
        &out,
        &["--progressive", "3", "--budget", "auto", "--target-ms", "0"],
        &["--target-ms"],
    );
    fails(&s, &out, &["--progressive", "3", "--load-threads", "0"], &["--load-threads 0"]);
    // --budget alone is a usage error.
    assert!(!render(&s, &out, &["--budget", "10"]).status.success());
    // Batch files and stores are not raw LAS/LAZ.
    let mbat = dir.join("s.mbat");
    run_ok(mortar().arg("batch").arg(&s).arg("-o").arg(&mbat));
    fails(&mbat, &out, &["--progressive", "3"], &["s.mbat", "batch file", "without --progressive"]);
    let store = dir.join("store");
    run_ok(
        mortar()
            .arg("build")
            .arg(root().join("data-samples/point-time-color.laz"))
            .arg("-o")
            .arg(&store),
    );
    fails(
        &store,
        &out,
        &["--progressive", "3"],
        &["store", "octree store", "without --progressive"],
    );
    // Headers that lie: a z range 3 m short and an x range 10 % short are drawn in full (every
    // point loaded), framed by the header's box as the brute force frames it; the same image
    // but for ties.
    let las = dir.join("x.las");
    run_ok(mortar().arg("sort").arg(&s).arg("-o").arg(&las));
    let good = std::fs::read(&las).unwrap();
    let f = |b: &[u8], at: usize| f64::from_le_bytes(b[at..at + 8].try_into().unwrap());
    let mut bytes = good.clone();
    let (max_x, min_x, max_z) = (f(&good, 179), f(&good, 187), f(&good, 211));
    bytes[179..187].copy_from_slice(&(max_x - 0.1 * (max_x - min_x)).to_le_bytes());
    bytes[211..219].copy_from_slice(&(max_z - 3.0).to_le_bytes());
    let lying = dir.join("lying.las");
    std::fs::write(&lying, &bytes).unwrap();
    same_as_brute_force(&dir, &lying, "header", POINTS);
    // A header whose box is the first LAZ chunk's only, while half the points lie 10 km away
    // (the sample twice, the copy moved east, Morton-sorted into LAZ): the progressive
    // renderer's frame grows to hold them instead of refusing them, and the view stays the
    // header's, as the brute force's does.
    let far = dir.join("far.laz");
    run_ok(mortar().arg("sort").arg(twice_apart(&las, &dir.join("twice.las"))).arg("-o").arg(&far));
    let (lo, hi) = first_piece_box(&far);
    let mut bytes = std::fs::read(&far).unwrap();
    for a in 0..3 {
        bytes[187 + 16 * a..195 + 16 * a].copy_from_slice(&lo[a].to_le_bytes());
        bytes[179 + 16 * a..187 + 16 * a].copy_from_slice(&hi[a].to_le_bytes());
    }
    let short = dir.join("short.laz");
    std::fs::write(&short, &bytes).unwrap();
    let j = same_as_brute_force(&dir, &short, "header", 2 * POINTS);
    assert!(j["frame_growths"].as_u64().unwrap() >= 1, "{}", j["frame_growths"]);
    // A header that shrinks the box to a metre away from the first points frames nothing: the
    // points' own box is framed (every point read before the first frame), by both renderers.
    let mut bytes = good.clone();
    for (hi, lo) in [(179, 187), (195, 203), (211, 219)] {
        let v = f(&good, lo) + 1.0;
        bytes[hi..hi + 8].copy_from_slice(&v.to_le_bytes());
    }
    let bad = dir.join("xbad.las");
    std::fs::write(&bad, &bytes).unwrap();
    same_as_brute_force(&dir, &bad, "points", POINTS);
    // Broken files: the loader's error, never a panic or a hang.
    if let Some(data) = shared_data() {
        for bad in BAD_INPUTS {
            let mut c = mortar();
            c.arg("render").arg(data.join(bad)).arg("-o").arg(&out).args([
                "--progressive",
                "converge",
                "--budget",
                "1000",
            ]);
            let o = run_limited(c, std::time::Duration::from_secs(60));
            let err = String::from_utf8_lossy(&o.stderr);
            assert_eq!(o.status.code(), Some(1), "{bad}: {err}");
            assert!(
                !err.contains("panicked")
                    && err.contains(Path::new(bad).file_name().unwrap().to_str().unwrap()),
                "{bad}: {err}"
            );
            assert!(!out.exists(), "{bad}");
        }
    }
}
