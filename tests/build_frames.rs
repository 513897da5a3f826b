//! `mortar build --frames DIR --every S` (issue 6 item 2): headless frames of the growing store
//! and a contact sheet.

mod common;

use common::*;
use std::path::Path;

/// (width, height, RGBA pixels) of a PNG.
fn read_png(p: &Path) -> (u32, u32, Vec<[u8; 4]>) {
    let mut dec = png::Decoder::new(std::io::Cursor::new(
        std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display())),
    ));
    dec.set_transformations(png::Transformations::EXPAND);
    let mut r = dec.read_info().expect("PNG header");
    let mut buf = vec![0; r.output_buffer_size()];
    let info = r.next_frame(&mut buf).expect("PNG data");
    assert_eq!(info.color_type, png::ColorType::Rgba);
    let px = buf[..info.buffer_size()].chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect();
    (info.width, info.height, px)
}

/// Pixels that are not the black background.
fn drawn(px: &[[u8; 4]]) -> usize {
    px.iter().filter(|p| p[0] | p[1] | p[2] != 0).count()
}

#[test]
fn frames_show_the_store_growing_and_end_in_a_contact_sheet() {
    let dir = tempdir("frames");
    let frames = dir.join("frames");
    let store = dir.join("s");
    let o = run_ok(
        mortar()
            .arg("build")
            .arg(root().join("data-samples/autzen_trim.laz"))
            .arg("-o")
            .arg(&store)
            .args(["--engine", "incremental", "--batch-points", "10000", "--frames"])
            .arg(&frames)
            .args([
                "--every",
                "0",
                "--frame-width",
                "320",
                "--frame-height",
                "200",
                "--view",
                "top",
                "--json",
            ]),
    );
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let f = &j["frames"];
    let n = f["count"].as_u64().unwrap() as usize;
    // --every 0 commits after every update: 11 updates of 10,000 points.
    assert!(n >= 10, "{f}");
    let list = f["frames"].as_array().unwrap();
    let points: Vec<u64> = list.iter().map(|x| x["points"].as_u64().unwrap()).collect();
    assert!(points.windows(2).all(|w| w[0] < w[1]), "each frame shows a later commit: {points:?}");
    assert_eq!(*points.last().unwrap(), 110_000);
    // With a fixed camera the drawn area grows with the store, and the last frame equals
    // `mortar render store/` with the same camera and LOD threshold.
    let mut counts = Vec::new();
    for k in 1..=n {
        let (w, h, px) = read_png(&frames.join(format!("frame-{k:04}.png")));
        assert_eq!((w, h), (320, 200));
        counts.push(drawn(&px));
    }
    assert!(counts[0] > 0 && counts[n - 1] > 3 * counts[0], "{counts:?}");
    let last = dir.join("last.png");
    run_ok(
        mortar()
            .arg("render")
            .arg(&store)
            .args(["--width", "320", "--height", "200", "--view", "top", "-o"])
            .arg(&last),
    );
    assert!(
        read_png(&last).2 == read_png(&frames.join(format!("frame-{n:04}.png"))).2,
        "the last frame is the render of the finished store"
    );
    // The contact sheet holds every frame scaled into a grid.
    let (sw, sh, sheet) = read_png(&frames.join("contact-sheet.png"));
    let cols = (n as f64).sqrt().ceil() as u32;
    let rows = (n as u32).div_ceil(cols);
    assert_eq!((sw, sh), (cols * 324 + 4, rows * 204 + 4));
    assert!(drawn(&sheet) > counts[n - 1], "the sheet shows the frames");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_frame_options_are_clear_errors() {
    let dir = tempdir("frames-bad");
    let o = mortar()
        .arg("build")
        .arg(root().join("data-samples/autzen_trim.laz"))
        .arg("-o")
        .arg(dir.join("s"))
        .arg("--frames")
        .arg(dir.join("f"))
        .args(["--frame-width", "0"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--frame-width"));
    assert!(!dir.join("s").exists());
    // --every without --frames is refused by the argument parser.
    let o = mortar()
        .arg("build")
        .arg(root().join("data-samples/autzen_trim.laz"))
        .arg("-o")
        .arg(dir.join("s"))
        .args(["--every", "1"])
        .output()
        .unwrap();
    assert_ne!(o.status.code(), Some(0));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn frames_on_the_gpu_equal_the_cpu_frames_and_the_offscreen_preview_reports_its_frames() {
    if mortar_render::testing::context_or_skip(mortar_render::AtomicPath::TwoPass32, None).is_none()
    {
        return;
    }
    let dir = tempdir("frames-gpu");
    let input = root().join("data-samples/autzen_trim.laz");
    let mut outs = Vec::new();
    for backend in ["cpu", "gpu"] {
        let frames = dir.join(format!("frames-{backend}"));
        let store = dir.join(format!("s-{backend}"));
        let o = run_ok(
            mortar()
                .arg("build")
                .arg(&input)
                .arg("-o")
                .arg(&store)
                .args(["--engine", "incremental", "--batch-points", "20000", "--frames"])
                .arg(&frames)
                .args([
                    "--every",
                    "0",
                    "--frame-width",
                    "240",
                    "--frame-height",
                    "160",
                    "--frame-backend",
                    backend,
                    "--json",
                ]),
        );
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        outs.push((frames, j["frames"]["count"].as_u64().unwrap()));
    }
    assert_eq!(outs[0].1, outs[1].1);
    assert!(outs[0].1 >= 5);
    for k in 1..=outs[0].1 {
        let name = format!("frame-{k:04}.png");
        let (a, b) = (read_png(&outs[0].0.join(&name)), read_png(&outs[1].0.join(&name)));
        assert!(a == b, "{name}: the GPU frame differs from the CPU frame");
    }

    // The preview off screen (no display needed): frames while the store grows, on the GPU.
    let store = dir.join("s-preview");
    let o = run_ok(mortar().arg("build").arg(&input).arg("-o").arg(&store).args([
        "--batch-points",
        "5000",
        "--commit-every",
        "0",
        "--preview",
        "--preview-offscreen",
        "--preview-backend",
        "gpu",
        "--preview-size",
        "320x240",
        "--json",
    ]));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["points"], 110_000);
    let p = &j["preview"];
    assert_eq!(p["renderer"]["backend"], "gpu", "{p}");
    let frames = p["frames"].as_array().unwrap();
    assert_eq!(p["frame_count"].as_u64().unwrap() as usize, frames.len());
    let last = frames.last().unwrap();
    assert!(last["points_drawn"].as_u64().unwrap() > 0, "{last}");
    assert_eq!(last["commit"], j["commits"], "the last preview frame shows the last commit");
    let uploaded: u64 = frames.iter().map(|f| f["nodes_uploaded"].as_u64().unwrap()).sum();
    assert!(uploaded > 0);

    // Paced uploads (one node a frame): a new commit stays behind the one shown until all its
    // selected nodes are on the GPU, then shows whole; the last frame is the whole last commit,
    // as drawn when every node is uploaded in one frame.
    let paced = dir.join("s-paced");
    let o = run_ok(
        mortar()
            .arg("build")
            .arg(&input)
            .arg("-o")
            .arg(&paced)
            .args(["--batch-points", "5000", "--commit-every", "0", "--preview"])
            .args(["--preview-offscreen", "--preview-backend", "gpu", "--preview-size"])
            .args(["320x240", "--json"])
            .env("MORTAR_UPLOAD_BUDGET_MS", "0"),
    );
    let q: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let qf = q["preview"]["frames"].as_array().unwrap();
    assert!(qf.iter().all(|f| f["nodes_uploaded"].as_u64().unwrap() <= 1), "one node a frame");
    let ql = qf.last().unwrap();
    assert_eq!(ql["commit"], q["commits"], "the last paced frame shows the last commit");
    assert!(ql["nodes_drawn"].as_u64().unwrap() > 1, "{ql}");
    assert_eq!(ql["nodes_drawn"], last["nodes_drawn"], "the last paced frame is whole");
    assert_eq!(ql["points_drawn"], last["points_drawn"], "the last paced frame is whole");
    // Frames went on while the nodes arrived one by one.
    assert!(qf.len() as u64 >= ql["nodes_drawn"].as_u64().unwrap(), "{} frames", qf.len());
}
