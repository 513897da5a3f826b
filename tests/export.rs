//! `mortar export`: COPC 1.0 and Potree 2.0 outputs checked by readers that are not mortar's:
//! laspy's CopcReader, copclib and copc.js for COPC; a walk of the Potree files written from the
//! format description, and the potree-core loader in headless Chromium, for Potree
//! (`tests/export_check.py`, `tests/web/`). Every real file of ../shared/data, alone, and
//! merged sets.

mod common;
use common::*;
use std::path::{Path, PathBuf};
use std::process::Command;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Python with laspy and lazrs ([`laspy_python`]); with `MORTAR_REQUIRE_COPCLIB=1` it must
/// import copclib too.
fn python() -> Option<PathBuf> {
    let py = laspy_python()?;
    if std::env::var("MORTAR_REQUIRE_COPCLIB").as_deref() == Ok("1") {
        let c = Command::new(&py).args(["-c", "import copclib"]).output().unwrap();
        assert!(c.status.success(), "MORTAR_REQUIRE_COPCLIB=1 but copclib does not import");
    }
    Some(py)
}

/// Whether the web checks can run (node, tests/web installed, chromium); with
/// `MORTAR_REQUIRE_WEB=1` a missing piece fails the test.
fn web() -> bool {
    let w = root().join("tests/web");
    let ok = w.join("node_modules/copc").is_dir()
        && w.join("node_modules/potree-core").is_dir()
        && Command::new("node").arg("--version").output().is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var("MORTAR_REQUIRE_WEB").as_deref() != Ok("1"),
            "MORTAR_REQUIRE_WEB=1 but tests/web is not installed (tests/web/install.sh)"
        );
        eprintln!("SKIP: tests/web not installed (tests/web/install.sh)");
    }
    ok
}

fn export(inputs: &[&Path], out: &Path, extra: &[&str]) {
    let mut c = mortar();
    c.arg("export");
    for i in inputs {
        c.arg(i);
    }
    c.args(["-o", s(out), "--quiet"]).args(extra);
    run_ok(&mut c);
}

/// Runs the Python checks of `jobs`; panics with every failed job.
fn check(py: &Path, dir: &Path, jobs: &[serde_json::Value]) -> Vec<serde_json::Value> {
    let m = dir.join("manifest.json");
    std::fs::write(&m, serde_json::to_vec(jobs).unwrap()).unwrap();
    let o = Command::new(py).arg(root().join("tests/export_check.py")).arg(&m).output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    let results: Vec<serde_json::Value> =
        text.lines().filter_map(|l| serde_json::from_str(l).ok()).collect();
    let bad: Vec<&serde_json::Value> = results.iter().filter(|r| r["ok"] != true).collect();
    assert!(
        bad.is_empty() && results.len() == jobs.len(),
        "failed checks: {bad:#?}\nstderr: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    results
}

fn copc_js_try(file: &Path) -> Result<serde_json::Value, serde_json::Value> {
    let o = Command::new("node")
        .arg(root().join("tests/web/copc_check.mjs"))
        .arg(file)
        .output()
        .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&o.stdout)
        .unwrap_or_else(|_| panic!("copc.js: {}", String::from_utf8_lossy(&o.stderr)));
    if o.status.success() && v["ok"] == true {
        Ok(v)
    } else {
        Err(v)
    }
}

fn copc_js(file: &Path) -> serde_json::Value {
    copc_js_try(file).unwrap_or_else(|v| panic!("copc.js on {}: {v}", file.display()))
}

/// copc.js 0.0.8 cannot parse an extra bytes description whose no-data value is u64::MAX (it
/// converts the bigint to a number): a limit of that reader, on files whose descriptions mortar
/// copies as they are.
fn copc_js_limit(v: &serde_json::Value) -> bool {
    v["problems"].to_string().contains("extra-bytes.js")
}

fn samples() -> Vec<PathBuf> {
    vec![
        root().join("data-samples/autzen_trim.laz"),
        root().join("data-samples/point-time-color.laz"),
    ]
}

#[test]
fn samples_read_back_by_independent_readers() {
    let Some(py) = python() else { return };
    let d = tempdir("export-samples");
    let mut jobs = Vec::new();
    for (i, f) in samples().iter().enumerate() {
        // a small leaf capacity for several levels and hierarchy pages
        for cap in ["100000", "500"] {
            let c = d.join(format!("{i}-{cap}.copc.laz"));
            export(&[f], &c, &["--leaf-capacity", cap]);
            jobs.push(serde_json::json!({"kind": "copc", "out": c, "inputs": [f]}));
            let p = d.join(format!("{i}-{cap}-potree"));
            export(&[f], &p, &["--leaf-capacity", cap]);
            jobs.push(serde_json::json!({"kind": "potree", "out": p, "inputs": [f]}));
        }
    }
    // Morton order inside nodes (the default is GPS time): the same points
    let g = d.join("gps.copc.laz");
    export(&[&samples()[0]], &g, &["--order", "morton", "--leaf-capacity", "2000"]);
    jobs.push(serde_json::json!({"kind": "copc", "out": g, "inputs": [samples()[0]]}));
    // a store as input: read as points, the same points come out
    let st = d.join("store");
    run_ok(mortar().args(["build", s(&samples()[0]), "-o", s(&st), "--quiet"]));
    for (name, fmt) in [("st.copc.laz", "copc"), ("st-potree", "potree")] {
        export(&[&st], &d.join(name), &["--leaf-capacity", "3000"]);
        jobs.push(serde_json::json!({"kind": fmt, "out": d.join(name), "inputs": [samples()[0]]}));
    }
    let r = check(&py, &d, &jobs);
    assert!(
        r.iter().any(|r| r["depth"].as_u64().unwrap_or(0) >= 3),
        "a deep tree was checked: {r:?}"
    );
    // a check that can fail: the wrong input
    let m = d.join("wrong.json");
    std::fs::write(&m, serde_json::to_vec(&serde_json::json!([{"kind": "copc", "out": d.join("0-500.copc.laz"), "inputs": [samples()[1]]}])).unwrap()).unwrap();
    let o = Command::new(&py).arg(root().join("tests/export_check.py")).arg(&m).output().unwrap();
    assert!(!o.status.success(), "the check must fail on the wrong input");
    if web() {
        for j in &jobs {
            if j["kind"] == "copc" {
                copc_js(Path::new(j["out"].as_str().unwrap()));
            }
        }
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn every_real_file_alone_and_merged() {
    let Some(data) = shared_data() else { return };
    let Some(py) = python() else { return };
    let d = tempdir("export-real");
    let mut jobs = Vec::new();
    let mut refused = Vec::new();
    let files = readable_fixtures(&data);
    for (i, f) in files.iter().enumerate() {
        for (kind, name) in [("copc", format!("{i}.copc.laz")), ("potree", format!("{i}-potree"))] {
            let out = d.join(&name);
            let o = mortar()
                .args([
                    "export",
                    s(f),
                    "-o",
                    s(&out),
                    "--quiet",
                    "--leaf-capacity",
                    "2000",
                    "--format",
                    kind,
                ])
                .output()
                .unwrap();
            if o.status.success() {
                jobs.push(serde_json::json!({"kind": kind, "out": out, "inputs": [laspy_twin(f)]}));
            } else {
                let err = String::from_utf8_lossy(&o.stderr).to_string();
                assert_eq!(o.status.code(), Some(1), "{}: {err}", f.display());
                assert!(!err.contains("panicked"), "{}: {err}", f.display());
                assert!(!out.exists(), "{}: a refused export left {}", f.display(), out.display());
                refused.push((f.clone(), err));
            }
        }
    }
    // Refusals are the documented ones only: waveforms, scales that share no cube, files that
    // are not readable as points.
    for (f, e) in &refused {
        assert!(
            e.contains("waveform") || e.contains("scales") || e.contains("no points"),
            "{}: {e}",
            f.display()
        );
    }
    assert!(
        jobs.len() >= files.len(),
        "most real files export: {} jobs of {} files; refused {refused:?}",
        jobs.len(),
        files.len()
    );
    // merged: the bcts tiles, and 8 EPT tiles
    let bcts: Vec<PathBuf> =
        files.iter().filter(|f| f.to_string_lossy().contains("bcts_")).cloned().collect();
    let ept: Vec<PathBuf> = files
        .iter()
        .filter(|f| f.to_string_lossy().contains("ept-data/"))
        .take(8)
        .cloned()
        .collect();
    for (tag, set) in [("bcts", &bcts), ("ept", &ept)] {
        if set.len() < 2 {
            continue;
        }
        let refs: Vec<&Path> = set.iter().map(|p| p.as_path()).collect();
        let c = d.join(format!("{tag}.copc.laz"));
        export(&refs, &c, &["--leaf-capacity", "5000"]);
        jobs.push(serde_json::json!({"kind": "copc", "out": c, "inputs": set}));
        let p = d.join(format!("{tag}-potree"));
        export(&refs, &p, &["--leaf-capacity", "5000"]);
        jobs.push(serde_json::json!({"kind": "potree", "out": p, "inputs": set}));
    }
    check(&py, &d, &jobs);
    if web() {
        let (mut ok, mut limits) = (0, Vec::new());
        for j in jobs.iter().filter(|j| j["kind"] == "copc") {
            match copc_js_try(Path::new(j["out"].as_str().unwrap())) {
                Ok(_) => ok += 1,
                Err(v) if copc_js_limit(&v) => limits.push(j["inputs"].clone()),
                Err(v) => panic!("copc.js: {v}"),
            }
        }
        eprintln!(
            "copc.js read {ok} COPC files; {} hit its extra-bytes limit: {limits:?}",
            limits.len()
        );
        assert!(
            ok >= 9 * (ok + limits.len()) / 10,
            "copc.js read {ok}, {} hit its limit",
            limits.len()
        );
    }
    std::fs::remove_dir_all(&d).unwrap();
}

/// Exports `inputs` with `extra`; the JSON summary, or the error text of a refusal (exit 1).
fn export_json(inputs: &[&Path], out: &Path, extra: &[&str]) -> Result<serde_json::Value, String> {
    let mut c = mortar();
    c.arg("export");
    for i in inputs {
        c.arg(i);
    }
    let o = c.args(["-o", s(out), "--quiet", "--json"]).args(extra).output().unwrap();
    if o.status.success() {
        return Ok(serde_json::from_slice(&o.stdout).unwrap());
    }
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(!out.exists(), "a refused export left {}", out.display());
    Err(err)
}

/// Inputs larger than `--memory` go through run files, one subtree at a time: the same nodes
/// with the same records in the same order as the in-memory export, on the samples and on
/// every real file alone and merged, and no run file left behind.
#[test]
fn larger_than_memory_gives_the_same_export() {
    let Some(py) = python() else { return };
    let d = tempdir("export-stream");
    let mut sets: Vec<Vec<PathBuf>> = samples().into_iter().map(|p| vec![p]).collect();
    if let Some(data) = shared_data() {
        let files = readable_fixtures(&data);
        let bcts: Vec<PathBuf> =
            files.iter().filter(|f| f.to_string_lossy().contains("bcts_")).cloned().collect();
        sets.extend(files.into_iter().map(|f| vec![f]));
        sets.push(bcts);
    }
    let (mut jobs, mut streamed) = (Vec::new(), 0);
    for (i, set) in sets.iter().enumerate() {
        let refs: Vec<&Path> = set.iter().map(|p| p.as_path()).collect();
        for (kind, a, b) in [
            ("copc", format!("{i}-mem.copc.laz"), format!("{i}-part.copc.laz")),
            ("potree", format!("{i}-mem"), format!("{i}-part")),
        ] {
            let (a, b) = (d.join(a), d.join(b));
            let common = ["--format", kind, "--leaf-capacity", "2000"];
            if export_json(&refs, &a, &common).is_err() {
                continue; // refused in memory too: every_real_file_alone_and_merged checks why
            }
            // small enough for many units (and dense cells partitioned again in most files)
            let memory = if set.len() > 1 { "16M" } else { "4M" };
            match export_json(&refs, &b, &[&common[..], &["--memory", memory]].concat()) {
                Ok(j) => {
                    assert_eq!(j["engine"], "partitioned", "{set:?}");
                    streamed += 1;
                    jobs.push(serde_json::json!({"kind": "same", "format": kind, "a": a, "b": b}));
                    if i == 0 || set.len() > 1 {
                        jobs.push(serde_json::json!({"kind": kind, "out": b, "inputs": set}));
                    }
                }
                // No cell is too dense any more (`store/dense.rs`).
                Err(e) => panic!("{set:?} --memory {memory}: {e}"),
            }
        }
    }
    eprintln!("{streamed} exports through run files");
    check(&py, &d, &jobs);
    let left: Vec<_> = std::fs::read_dir(&d)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
    std::fs::remove_dir_all(&d).unwrap();
}

/// Partition cells denser than a unit (`tests/common::dense_sets`): the export through run files
/// under 1 MiB equals the one in memory node by node, read by laspy (and copclib), in both point
/// orders (by GPS time, the default: leaves larger than a unit are merge-sorted on disk).
#[test]
fn cells_denser_than_a_unit_give_the_same_export() {
    let Some(py) = python() else { return };
    let d = tempdir("export-dense");
    let mut jobs = Vec::new();
    for (i, set) in dense_sets(&d).iter().enumerate() {
        let refs: Vec<&Path> = set.iter().map(|p| p.as_path()).collect();
        for (kind, order, a, b) in [
            ("copc", "gps-time", format!("{i}-mem.copc.laz"), format!("{i}-part.copc.laz")),
            ("copc", "morton", format!("{i}-mem-m.copc.laz"), format!("{i}-part-m.copc.laz")),
            ("potree", "gps-time", format!("{i}-mem"), format!("{i}-part")),
        ] {
            let (a, b) = (d.join(a), d.join(b));
            let common = ["--format", kind, "--leaf-capacity", "3000", "--order", order];
            export_json(&refs, &a, &common).unwrap_or_else(|e| panic!("{set:?} in memory: {e}"));
            let j = export_json(&refs, &b, &[&common[..], &["--memory", "1M"]].concat())
                .unwrap_or_else(|e| panic!("{set:?} --memory 1M: {e}"));
            assert_eq!(j["engine"], "partitioned", "{set:?}");
            assert!(j["large_leaves"].as_u64().unwrap() >= 1, "{set:?}: {j}");
            jobs.push(serde_json::json!({"kind": "same", "format": kind, "a": a, "b": b}));
            jobs.push(serde_json::json!({"kind": kind, "out": b, "inputs": set}));
        }
    }
    check(&py, &d, &jobs);
    let left: Vec<_> = std::fs::read_dir(&d)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn sort_of_the_copc_gives_the_points_back() {
    let d = tempdir("export-sort");
    let mut files = samples();
    if let Some(data) = shared_data() {
        files.extend(
            readable_fixtures(&data)
                .into_iter()
                .filter(|f| f.to_string_lossy().contains("bcts_"))
                .take(2),
        );
    }
    for f in &files {
        let c = d.join("x.copc.laz");
        export(&[f], &c, &["--leaf-capacity", "1000"]);
        let a = d.join("a.las");
        let b = d.join("b.las");
        // COPC holds PDRF 6-8: the input sorted through the same conversion
        run_ok(mortar().args(["sort", s(&c), "-o", s(&a), "--quiet"]));
        run_ok(mortar().args(["sort", s(f), "-o", s(&b), "--quiet"]));
        let (ra, la, ha) = las_records(&a).unwrap();
        let (rb, lb, hb) = las_records(&b).unwrap();
        assert_eq!(ha.number_of_points(), hb.number_of_points(), "{}", f.display());
        if ha.point_format() == hb.point_format() {
            assert_eq!(multiset(&ra, la), multiset(&rb, lb), "{}", f.display());
        } else {
            // legacy input: positions, intensity and GPS time compared (every field: laspy's check)
            let gps_b = hb.point_format().has_gps_time.then_some(20);
            let key =
                |r: &[u8], g: Option<usize>| (r[..14].to_vec(), g.map(|g| r[g..g + 8].to_vec()));
            let mut ka: Vec<_> = ra.chunks_exact(la).map(|r| key(r, gps_b.map(|_| 22))).collect();
            let mut kb: Vec<_> = rb.chunks_exact(lb).map(|r| key(r, gps_b)).collect();
            ka.sort();
            kb.sort();
            assert_eq!(ka, kb, "{}", f.display());
        }
        for p in [&c, &a, &b] {
            std::fs::remove_file(p).unwrap();
        }
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn potree_in_a_real_browser() {
    if !web() {
        return;
    }
    let Some(py) = python() else { return };
    let d = tempdir("export-browser");
    let f = root().join("data-samples/autzen_trim.laz");
    let p = d.join("autzen-potree");
    export(&[&f], &p, &["--leaf-capacity", "5000"]);
    let report = d.join("report.json");
    let o = Command::new("bash")
        .arg(root().join("tests/web/potree_check.sh"))
        .arg(&p)
        .arg(&report)
        .arg(d.join("shot.png"))
        .output()
        .unwrap();
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap_or_default())
        .unwrap_or_else(|_| panic!("no report: {}", String::from_utf8_lossy(&o.stderr)));
    assert!(o.status.success() && r["loaded"] == true, "{r}");
    assert_eq!(r["points"], 110_000, "every point decoded by the loader: {r}");
    assert_eq!(r["points"], r["node_points_sum"], "{r}");
    assert!(r["nodes"].as_u64().unwrap() > 10, "several nodes: {r}");
    // the picture: pixels covered against a 1-pixel top view of the input made in Python
    let x = check(&py, &d, &[serde_json::json!({"kind": "raster", "inputs": [f]})]);
    let want = x[0]["covered_pixels"].as_f64().unwrap();
    let got = r["covered_pixels"].as_f64().unwrap();
    assert!(
        (got - want).abs() / want < 0.03,
        "covered pixels {got} in the browser, {want} expected"
    );
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn bad_input_and_interruptions_leave_nothing() {
    let d = tempdir("export-bad");
    // no such input
    let o = mortar()
        .args(["export", s(&d.join("missing.laz")), "-o", s(&d.join("x.copc.laz"))])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing.laz"));
    // a truncated LAZ: an error naming it, nothing left
    let src = std::fs::read(root().join("data-samples/autzen_trim.laz")).unwrap();
    let t = d.join("trunc.laz");
    std::fs::write(&t, &src[..src.len() * 2 / 3]).unwrap();
    for out in ["t.copc.laz", "t-potree"] {
        let o = mortar().args(["export", s(&t), "-o", s(&d.join(out))]).output().unwrap();
        assert_eq!(o.status.code(), Some(1), "{}", String::from_utf8_lossy(&o.stderr));
        assert!(
            String::from_utf8_lossy(&o.stderr).contains("trunc.laz"),
            "{}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
    assert_eq!(entries(&d), vec!["trunc.laz".to_string()]);
    // a Potree directory that is not empty is refused before any work
    let full = d.join("full");
    std::fs::create_dir(&full).unwrap();
    std::fs::write(full.join("keep.txt"), b"x").unwrap();
    let o = mortar()
        .args(["export", s(&samples()[0]), "-o", s(&full), "--format", "potree"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert_eq!(entries(&full), vec!["keep.txt".to_string()]);
    // a budget far below the densest cell of the partition (all points of one tile in one cell
    // of a root that a far tile makes 100 km wide): the cell is partitioned again, every point
    // is written, and nothing else is left
    let (near, far) = (d.join("near.las"), d.join("far.las"));
    run_ok(gen().args(["--points", "200000", "--extent", "1", "-o", s(&near)]));
    run_ok(gen().args([
        "--points",
        "10",
        "--extent",
        "1",
        "--origin",
        "600000,5000000,0",
        "-o",
        s(&far),
    ]));
    let m = d.join("m.copc.laz");
    let o = run_ok(mortar().args([
        "export",
        s(&near),
        s(&far),
        "-o",
        s(&m),
        "--memory",
        "1M",
        "--leaf-capacity",
        "1000",
        "--json",
    ]));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["points"], 200_010, "{j}");
    assert!(j["dense_cells"].as_u64().unwrap() >= 1, "{j}");
    let (recs, rl, _) = las_records(&m).unwrap();
    assert_eq!(recs.len() / rl, 200_010);
    std::fs::remove_file(&m).unwrap();
    std::fs::remove_file(&near).unwrap();
    std::fs::remove_file(&far).unwrap();
    // Ctrl-C in the middle: exit 130, nothing left
    let big = d.join("big.las");
    run_ok(gen().args(["--points", "4000000", "-o", s(&big)]));
    for (out, memory) in [("i.copc.laz", "2G"), ("i-potree", "2G"), ("j.copc.laz", "32M")] {
        let child = mortar()
            .args(["export", s(&big), "-o", s(&d.join(out)), "--threads", "1", "--memory", memory])
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        std::thread::sleep(std::time::Duration::from_millis(700));
        unsafe {
            libc::kill(child.id() as i32, libc::SIGINT);
        }
        let o = child.wait_with_output().unwrap();
        assert!(o.status.code() == Some(130) || o.status.success(), "{:?}", o.status);
        if o.status.code() == Some(130) {
            assert!(!d.join(out).exists());
        } else {
            std::fs::remove_dir_all(d.join(out))
                .or_else(|_| std::fs::remove_file(d.join(out)))
                .unwrap();
        }
    }
    assert_eq!(
        entries(&d),
        vec!["big.las".to_string(), "full".to_string(), "trunc.laz".to_string()]
    );
    std::fs::remove_dir_all(&d).unwrap();
}
