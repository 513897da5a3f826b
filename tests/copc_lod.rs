//! Issue 30 §1: COPC files as LOD sources. `mortar render` reads the hierarchy, selects nodes
//! with the store's rule and decodes only their chunks; at threshold 0 the picture is the flat
//! read's (`--no-lod`), a closeup decodes a small share of the file, `info` shows the levels,
//! and a damaged hierarchy is said and the file read flat.

mod common;
use common::*;
use std::path::{Path, PathBuf};

/// The COPC files of the shared data (third-party writers: PDAL/untwine, laspy's test data,
/// Potree's sample, lasR, silvimetric, copc-validator's valid ones).
fn copc_files(data: &Path) -> Vec<PathBuf> {
    [
        "PDAL/test/data/copc/lone-star.copc.laz",
        "PDAL/test/data/copc/1.2-with-color.copc.laz",
        "PDAL/test/data/tindex/autzen_clip_native.copc.laz",
        "PDAL/test/data/tindex/autzen_clip_4326.copc.laz",
        "potree/pointclouds/lion_takanawa.copc.laz",
        "las-rs/tests/data/autzen.copc.laz",
        "laspy/tests/data/simple_with_page.copc.laz",
        "lasR/inst/extdata/example.copc.laz",
        "silvimetric/tests/data/test_data_2.copc.laz",
        "copc-validator/src/test/data/ellipsoid.copc.laz",
    ]
    .iter()
    .map(|f| data.join(f))
    .filter(|p| p.exists())
    .collect()
}

fn read_png(p: &Path) -> Vec<[u8; 4]> {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size()];
    let info = r.next_frame(&mut buf).unwrap();
    buf[..info.buffer_size()].chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect()
}

fn render_json(args: &[&str]) -> serde_json::Value {
    let o = run_ok(mortar().arg("render").args(args).arg("--json"));
    serde_json::from_slice(&o.stdout).unwrap()
}

fn header_points(f: &Path) -> u64 {
    let o = run_ok(mortar().arg("info").arg(f).arg("--json"));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    j[0]["point_count"].as_u64().unwrap()
}

#[test]
fn copc_lod_at_threshold_zero_draws_what_the_flat_read_draws() {
    let Some(data) = shared_data() else { return };
    let dir = tempdir("copc-lod");
    // Also mortar's own export of the sample (several levels).
    let own = dir.join("sample.copc.laz");
    run_ok(
        mortar()
            .arg("export")
            .arg(root().join("data-samples/autzen_trim.laz"))
            .args(["--format", "copc", "--leaf-capacity", "5000", "-q", "-o"])
            .arg(&own),
    );
    let mut files = copc_files(&data);
    assert!(files.len() >= 8, "COPC fixtures missing: {files:?}");
    files.push(own);
    for f in &files {
        let name = f.file_name().unwrap().to_string_lossy().to_string();
        for color in ["auto", "elevation", "intensity"] {
            let lod = dir.join(format!("{name}-{color}-lod.png"));
            let flat = dir.join(format!("{name}-{color}-flat.png"));
            let fs = f.to_str().unwrap();
            let base = ["--width", "320", "--height", "240", "--color", color, "--backend", "cpu"];
            let j = render_json(
                &[&[fs, "-o", lod.to_str().unwrap(), "--lod-threshold", "0"][..], &base[..]]
                    .concat(),
            );
            let c = &j["lod_source"];
            assert!(c.is_object(), "{name}: not read as COPC: {j}");
            // Framed on the whole file, every node is in view: all are read.
            assert_eq!(c["nodes_read"], c["nodes"], "{name}: {c}");
            assert_eq!(c["points_read"].as_u64(), Some(header_points(f)), "{name}: {c}");
            let jf = render_json(
                &[&[fs, "-o", flat.to_str().unwrap(), "--no-lod"][..], &base[..]].concat(),
            );
            assert!(jf["lod_source"].is_null(), "{name}: --no-lod reads flat");
            assert_eq!(
                std::fs::read(&lod).unwrap(),
                std::fs::read(&flat).unwrap(),
                "{name} ({color}): the LOD picture at threshold 0 differs from the flat read's"
            );
        }
        // The default threshold reads no more than every node.
        let j = render_json(&[
            f.to_str().unwrap(),
            "-o",
            dir.join("d.png").to_str().unwrap(),
            "--width",
            "320",
            "--height",
            "240",
        ]);
        assert!(j["lod_source"]["nodes_read"].as_u64() <= j["lod_source"]["nodes"].as_u64());
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_closeup_of_a_copc_file_decodes_a_small_share_and_draws_what_the_flat_read_draws() {
    let dir = tempdir("copc-closeup");
    let las = dir.join("g.las");
    run_ok(gen().args(["--points", "1000000", "--seed", "3", "-o"]).arg(&las));
    let copc = dir.join("g.copc.laz");
    run_ok(
        mortar()
            .arg("export")
            .arg(&las)
            .args(["--format", "copc", "--leaf-capacity", "20000", "-q", "-o"])
            .arg(&copc),
    );
    let view = ["--target", "500100,5000100,0", "--eye", "500100,5000040,60"];
    let size = ["--width", "320", "--height", "240", "--backend", "cpu"];
    let cs = copc.to_str().unwrap();
    let (a, b, c) = (dir.join("a.png"), dir.join("b.png"), dir.join("c.png"));
    let j = render_json(&[&[cs, "-o", a.to_str().unwrap()][..], &view[..], &size[..]].concat());
    let k = &j["lod_source"];
    let share = k["bytes_read"].as_f64().unwrap() / k["bytes"].as_f64().unwrap();
    assert!(share < 0.2, "a closeup read {:.1} % of the file: {k}", share * 100.0);
    assert!(k["nodes_read"].as_u64().unwrap() * 4 < k["nodes"].as_u64().unwrap(), "{k}");
    assert!(j["points_drawn"].as_u64().unwrap() > 0, "{j}");
    // Threshold 0 with culling: only the nodes in view, and the same picture as every point.
    let j = render_json(
        &[&[cs, "-o", b.to_str().unwrap(), "--lod-threshold", "0"][..], &view[..], &size[..]]
            .concat(),
    );
    assert!(j["lod_source"]["nodes_read"].as_u64() < j["lod_source"]["nodes"].as_u64(), "{j}");
    render_json(&[&[cs, "-o", c.to_str().unwrap(), "--no-lod"][..], &view[..], &size[..]].concat());
    assert_eq!(
        std::fs::read(&b).unwrap(),
        std::fs::read(&c).unwrap(),
        "the culled closeup at threshold 0 differs from the flat read's"
    );
    // A point budget reads less still.
    let j = render_json(
        &[&[cs, "-o", b.to_str().unwrap(), "--point-budget", "1000"][..], &size[..]].concat(),
    );
    assert_eq!(j["lod_source"]["nodes_read"], 1, "the root alone: {j}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn info_shows_the_copc_levels_and_a_damaged_hierarchy_is_read_flat() {
    let Some(data) = shared_data() else { return };
    for f in copc_files(&data) {
        let o = run_ok(mortar().arg("info").arg(&f).arg("--json"));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let c = &j[0]["hierarchy"];
        assert!(c["error"].is_null(), "{}: {c}", f.display());
        let levels = c["levels"].as_array().unwrap();
        let sum: u64 = levels.iter().map(|l| l["points"].as_u64().unwrap()).sum();
        assert_eq!(sum, j[0]["point_count"].as_u64().unwrap(), "{}", f.display());
        assert_eq!(levels[0]["nodes"], 1, "{}: one root", f.display());
        let text = run_ok(mortar().arg("info").arg(&f));
        assert!(String::from_utf8_lossy(&text.stdout).contains("level 0"));
    }
    // Not COPC: no copc object.
    let o =
        run_ok(mortar().arg("info").arg(root().join("data-samples/autzen_trim.laz")).arg("--json"));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(j[0].get("hierarchy").is_none());

    // Damage: a node's chunk where the chunk table has none; the root page's offset past the end; a page size not in whole entries; a loop
    // (the root page listing itself as a child page). Each is said, and the file drawn flat.
    let dir = tempdir("copc-damaged");
    let src = data.join("laspy/tests/data/simple_with_page.copc.laz");
    let bytes = std::fs::read(&src).unwrap();
    let info_at = 375 + 54; // the info VLR's data: the first VLR after the 375-byte header
    let root_off = u64::from_le_bytes(bytes[info_at + 40..info_at + 48].try_into().unwrap());
    let root_size = u64::from_le_bytes(bytes[info_at + 48..info_at + 56].try_into().unwrap());
    let mut past = bytes.clone();
    past[info_at + 40..info_at + 48].copy_from_slice(&(bytes.len() as u64 + 100).to_le_bytes());
    let mut ragged = bytes.clone();
    ragged[info_at + 48..info_at + 56].copy_from_slice(&(root_size - 5).to_le_bytes());
    let mut looped = bytes.clone();
    // The root page's last entry made a child page pointing at the root page.
    let last = (root_off + root_size) as usize - 32;
    looped[last + 16..last + 24].copy_from_slice(&root_off.to_le_bytes());
    looped[last + 24..last + 28].copy_from_slice(&(root_size as i32).to_le_bytes());
    looped[last + 28..last + 32].copy_from_slice(&(-1i32).to_le_bytes());
    // The first entry's chunk one byte off: the hierarchy and the chunk table disagree.
    let mut moved = bytes.clone();
    let first = root_off as usize;
    let at = u64::from_le_bytes(moved[first + 16..first + 24].try_into().unwrap());
    moved[first + 16..first + 24].copy_from_slice(&(at + 1).to_le_bytes());
    for (name, b, why) in [
        ("moved", moved, "chunk table does not list"),
        ("past", past, "outside the file"),
        ("ragged", ragged, "whole number"),
        ("looped", looped, "twice"),
    ] {
        let f = dir.join(format!("{name}.copc.laz"));
        std::fs::write(&f, b).unwrap();
        let png = dir.join(format!("{name}.png"));
        let o = run_ok(mortar().arg("render").arg(&f).arg("-o").arg(&png).args([
            "--width",
            "160",
            "--height",
            "120",
            "--backend",
            "cpu",
            "--json",
        ]));
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("reading it as a flat LAZ file") && err.contains(why),
            "{name}: {err}"
        );
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert!(j["lod_source"].is_null(), "{name}");
        assert_eq!(j["points"].as_u64(), Some(1065), "{name}: every point drawn flat: {j}");
        let o = run_ok(mortar().arg("info").arg(&f).arg("--json"));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert!(j[0]["hierarchy"]["error"].as_str().unwrap().contains(why), "{name}: {j}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_ept_directory_is_a_lod_source_whose_closeups_read_a_small_share() {
    let Some(data) = shared_data() else { return };
    let ept = data.join("PyForestScan/example_data/ept");
    let dir = tempdir("ept-lod");
    let es = ept.to_str().unwrap();
    let png = |n: &str| dir.join(n).to_str().unwrap().to_string();
    // A closeup from above the data: the default threshold reads a small share; threshold 0
    // (culled) draws what threshold 0 without culling (every node read, the same camera) draws:
    // the same points, and the same picture but where points tie in depth (the subset's points
    // are numbered otherwise than the whole's, and ties go to the lower number).
    let view = [
        "--target",
        "202150,2184150,1300",
        "--eye",
        "202150,2183950,1700",
        "--fov",
        "15",
        "--width",
        "320",
        "--height",
        "240",
        "--backend",
        "cpu",
        "--color",
        "intensity",
        "--range",
        "2687,11305",
        "--precision",
        "30",
    ];
    let j = render_json(&[&[es, "-o", &png("a.png")][..], &view[..]].concat());
    let c = &j["lod_source"];
    assert_eq!(c["format"], "ept", "{j}");
    let share = c["bytes_read"].as_f64().unwrap() / c["bytes"].as_f64().unwrap();
    assert!(share < 0.1, "the closeup read {:.1} % of the bytes: {c}", share * 100.0);
    let j0 =
        render_json(&[&[es, "-o", &png("b.png"), "--lod-threshold", "0"][..], &view[..]].concat());
    let all = render_json(
        &[&[es, "-o", &png("c.png"), "--lod-threshold", "0", "--no-cull"][..], &view[..]].concat(),
    );
    assert_eq!(all["lod_source"]["nodes_read"], all["lod_source"]["nodes"], "{all}");
    assert_eq!(all["lod_source"]["points_read"].as_u64(), Some(14_142_410));
    assert!(
        j0["lod_source"]["nodes_read"].as_u64().unwrap() * 5
            < all["lod_source"]["nodes_read"].as_u64().unwrap()
    );
    assert_eq!(j0["points_drawn"], all["points_drawn"], "culling dropped points in view");
    let (a, b) = (read_png(&dir.join("b.png")), read_png(&dir.join("c.png")));
    let differ = a.iter().zip(&b).filter(|(x, y)| x != y).count() as u64;
    let ties = all["depth_ties"].as_u64().unwrap();
    eprintln!("{differ} pixels differ, {ties} depth ties");
    assert!(differ <= ties, "{differ} pixels differ, more than the {ties} depth ties");
    // ept.json named directly is the same source; --no-lod reads every LAZ file flat.
    let j = render_json(&[
        ept.join("ept.json").to_str().unwrap(),
        "-o",
        &png("e.png"),
        "--width",
        "64",
        "--height",
        "48",
        "--point-budget",
        "50000",
    ]);
    assert_eq!(j["lod_source"]["nodes_read"], 1, "the root alone within 50,000 points: {j}");
    // info: one input, the hierarchy's levels summing to ept.json's points.
    let o = run_ok(mortar().arg("info").arg(&ept).arg("--json"));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j.as_array().unwrap().len(), 1);
    assert_eq!(
        (j[0]["kind"].as_str(), j[0]["point_count"].as_u64()),
        (Some("ept"), Some(14_142_410))
    );
    let h = &j[0]["hierarchy"];
    assert_eq!((h["format"].as_str(), h["nodes"].as_u64()), (Some("ept"), Some(290)), "{h}");
    let sum: u64 =
        h["levels"].as_array().unwrap().iter().map(|l| l["points"].as_u64().unwrap()).sum();
    assert_eq!(sum, 14_142_410);
    // A node whose file is missing: exit 1 naming the node, no picture.
    let holed = dir.join("holed-ept");
    for sub in ["ept-hierarchy", "ept-data"] {
        std::fs::create_dir_all(holed.join(sub)).unwrap();
        for e in std::fs::read_dir(ept.join(sub)).unwrap() {
            let e = e.unwrap();
            if e.file_name() != "1-0-0-1.laz" {
                std::fs::copy(e.path(), holed.join(sub).join(e.file_name())).unwrap();
            }
        }
    }
    std::fs::copy(ept.join("ept.json"), holed.join("ept.json")).unwrap();
    let o = mortar()
        .arg("render")
        .arg(&holed)
        .args(["-o", &png("g.png"), "--width", "200", "--height", "100", "--lod-threshold", "0"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("node 1-0-0-1") && err.contains("no file"), "{err}");
    assert!(!dir.join("g.png").exists());
    // A damaged ept.json is said, and the directory read flat.
    let bad = dir.join("bad-ept");
    std::fs::create_dir_all(&bad).unwrap();
    let raw = std::fs::read_to_string(ept.join("ept.json")).unwrap();
    std::fs::write(bad.join("ept.json"), raw.replace("\"laszip\"", "\"zstandard\"")).unwrap();
    std::fs::copy(ept.join("ept-data/0-0-0-0.laz"), bad.join("0-0-0-0.laz")).unwrap();
    let o = run_ok(mortar().arg("render").arg(&bad).args(["-o", &png("f.png"), "--json"]));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("zstandard") && err.contains("flat"), "{err}");
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(j["lod_source"].is_null());
    let o = run_ok(mortar().arg("info").arg(&bad).arg("--json"));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j[0]["kind"], "laz", "the damaged directory's files described one by one");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn laspy_counts_the_same_points_per_copc_level_as_info() {
    // An independent reader of the hierarchy: laspy's CopcReader queries each level.
    let Some(data) = shared_data() else { return };
    let Some(py) = laspy_python() else { return };
    let files = copc_files(&data);
    let script = r#"
import json, sys, laspy
out = {}
for p in sys.argv[1:]:
    with laspy.CopcReader.open(p) as r:
        counts, lvl = [], 0
        while True:
            n = len(r.query(level=lvl))
            if n == 0 and lvl > 0 and sum(counts) >= r.header.point_count:
                break
            counts.append(n)
            lvl += 1
            if lvl > 32:
                break
        out[p] = counts
print(json.dumps(out))
"#;
    let o = std::process::Command::new(py).arg("-c").arg(script).args(&files).output().unwrap();
    assert!(o.status.success(), "laspy: {}", String::from_utf8_lossy(&o.stderr));
    let theirs: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    for f in &files {
        let o = run_ok(mortar().arg("info").arg(f).arg("--json"));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let ours: Vec<u64> = j[0]["hierarchy"]["levels"]
            .as_array()
            .unwrap()
            .iter()
            .map(|l| l["points"].as_u64().unwrap())
            .collect();
        let t: Vec<u64> = theirs[f.to_str().unwrap()]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap())
            .collect();
        assert_eq!(ours, t, "{}: points per level, mortar against laspy", f.display());
    }
}
