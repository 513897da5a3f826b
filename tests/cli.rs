//! End-to-end behaviour of the `mortar` commands: inputs (files, directories, globs, stdin),
//! merging grids, pipes, the external sort, attribute selection, georeferenced coordinates.

mod common;
use common::*;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Stdio;

fn sample() -> PathBuf {
    root().join("data-samples/autzen_trim.laz")
}

fn sort_to(inputs: &[&Path], out: &Path, extra: &[&str]) -> std::process::Output {
    let mut c = mortar();
    c.arg("sort").args(inputs).arg("-o").arg(out).args(extra);
    run_ok(&mut c)
}

#[test]
fn external_sort_equals_in_memory_and_cleans_up() {
    let dir = tempdir("ext");
    let tmp = dir.join("tmp");
    std::fs::create_dir_all(&tmp).unwrap();
    let a = dir.join("a.mbat");
    let b = dir.join("b.mbat");
    run_ok(mortar().args(["batch"]).arg(sample()).arg("-o").arg(&a));
    let o = run_ok(
        mortar()
            .args(["batch", "--json", "--memory", "1M", "--tmp-dir"])
            .arg(&tmp)
            .arg(sample())
            .arg("-o")
            .arg(&b),
    );
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["external_sort"], true);
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    assert!(entries(&tmp).is_empty(), "temporary files left: {:?}", entries(&tmp));
    // LAS output through the external sort too
    let s1 = dir.join("s1.las");
    let s2 = dir.join("s2.las");
    sort_to(&[&sample()], &s1, &[]);
    sort_to(&[&sample()], &s2, &["--memory", "500K", "--tmp-dir", tmp.to_str().unwrap()]);
    assert_eq!(std::fs::read(&s1).unwrap(), std::fs::read(&s2).unwrap());
    assert!(entries(&tmp).is_empty());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn stdin_stdout_directories_and_globs() {
    let dir = tempdir("io");
    let s = dir.join("s.las");
    sort_to(&[&sample()], &s, &[]);
    let expected = std::fs::read(&s).unwrap();
    // stdin -> stdout
    let mut child = mortar()
        .args(["sort", "-", "-o", "-"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let data = std::fs::read(sample()).unwrap();
    let mut stdin = child.stdin.take().unwrap();
    let writer = std::thread::spawn(move || stdin.write_all(&data));
    let out = child.wait_with_output().unwrap();
    writer.join().unwrap().unwrap();
    assert!(out.status.success());
    assert_eq!(out.stdout, expected);
    // a directory and a glob
    let tiles = dir.join("tiles");
    std::fs::create_dir_all(&tiles).unwrap();
    std::fs::copy(sample(), tiles.join("a.laz")).unwrap();
    let d = dir.join("d.las");
    sort_to(&[&tiles], &d, &[]);
    assert_eq!(std::fs::read(&d).unwrap(), expected);
    let g = dir.join("g.las");
    let pattern = format!("{}/*.laz", tiles.display());
    run_ok(mortar().args(["sort", &pattern, "-o"]).arg(&g));
    assert_eq!(std::fs::read(&g).unwrap(), expected);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn closed_pipe_exits_zero() {
    let mut child = mortar()
        .args(["sort"])
        .arg(sample())
        .args(["-o", "-"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut so = child.stdout.take().unwrap();
    let mut buf = [0u8; 100];
    std::io::Read::read_exact(&mut so, &mut buf).unwrap();
    assert_eq!(&buf[..4], b"LASF");
    drop(so);
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(0), "stderr: {}", String::from_utf8_lossy(&out.stderr));
}

/// Writes a copy of a LAS file with coordinates on a grid 10x finer and a shifted offset.
fn regrid(src: &Path, dst: &Path) {
    let mut b = std::fs::read(src).unwrap();
    let rl = u16::from_le_bytes([b[105], b[106]]) as usize;
    let start = u32::from_le_bytes(b[96..100].try_into().unwrap()) as usize;
    let n = u32::from_le_bytes(b[107..111].try_into().unwrap()) as usize;
    let f64_at = |b: &[u8], o: usize| f64::from_le_bytes(b[o..o + 8].try_into().unwrap());
    for a in 0..3 {
        let scale = f64_at(&b, 131 + 8 * a);
        let offset = f64_at(&b, 155 + 8 * a);
        b[131 + 8 * a..139 + 8 * a].copy_from_slice(&(scale / 10.0).to_le_bytes());
        // new offset = old offset + 7 old steps: X' = 10 X - 70
        b[155 + 8 * a..163 + 8 * a].copy_from_slice(&(offset + 7.0 * scale).to_le_bytes());
        for i in 0..n {
            let o = start + i * rl + 4 * a;
            let v = i32::from_le_bytes(b[o..o + 4].try_into().unwrap());
            b[o..o + 4].copy_from_slice(&(v * 10 - 70).to_le_bytes());
        }
    }
    std::fs::write(dst, b).unwrap();
}

fn world_points(p: &Path) -> Vec<[i64; 3]> {
    // world coordinates in micrometres, exact for these grids
    let mut r = las::Reader::from_path(p).unwrap();
    let pd = r.read_all().unwrap();
    let mut v: Vec<[i64; 3]> = pd
        .x()
        .zip(pd.y())
        .zip(pd.z())
        .map(|((x, y), z)| [x, y, z].map(|c| (c * 1e6).round() as i64))
        .collect();
    v.sort();
    v
}

#[test]
fn inputs_on_different_grids_merge_exactly() {
    let Some(data) = shared_data() else { return };
    let dir = tempdir("grid");
    let a = data.join("PDAL/test/data/las/autzen_trim.las");
    let b = dir.join("fine.las");
    regrid(&a, &b);
    let out = dir.join("merged.las");
    let o = sort_to(&[&a, &b], &out, &[]);
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("merged exactly"),
        "a message says the grids were merged"
    );
    let mut expect = world_points(&a);
    expect.extend(world_points(&b));
    expect.sort();
    assert_eq!(world_points(&out), expect);
    // point formats 3 and 1 merge into 3 (RGB of the format-1 points is zero)
    let other = data.join("laz-rs/tests/data/point-time.las");
    let merged = dir.join("formats.las");
    let o = sort_to(&[&a, &other], &merged, &[]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("merged into point format 3"));
    let (m, rl, h) = las_records(&merged).unwrap();
    assert_eq!(h.point_format().to_u8().unwrap(), 3);
    let (p1, rl1, _) = las_records(&other).unwrap();
    assert_eq!(m.len() / rl, 110_000 + p1.len() / rl1);
    let zero_rgb = m.chunks_exact(rl).filter(|r| r[28..34] == [0; 6]).count();
    assert!(zero_rgb >= p1.len() / rl1);
    // legacy and LAS 1.4 formats merge now (tests/real_scans.rs); test1_4.las has a scale that
    // autzen's is no multiple of: a clear error before any work
    let o = mortar()
        .args(["sort"])
        .arg(&a)
        .arg(data.join("PDAL/test/data/las/test1_4.las"))
        .arg("-o")
        .arg(dir.join("x.las"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("cannot be merged exactly"));
    assert!(!dir.join("x.las").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn split_tiles_merge_into_the_whole() {
    let Some(data) = shared_data() else { return };
    let dir = tempdir("tiles");
    let whole = dir.join("whole.las");
    let parts = dir.join("parts.las");
    sort_to(&[&data.join("PDAL/test/data/ept/source/lone-star.laz")], &whole, &[]);
    sort_to(&[&data.join("PDAL/test/data/ept/source/lone-star-split")], &parts, &[]);
    assert_eq!(world_points(&whole), world_points(&parts));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn attribute_selection_drops_only_what_was_asked() {
    let dir = tempdir("attrs");
    let m = dir.join("a.mbat");
    run_ok(
        mortar()
            .args(["batch", "--attributes", "intensity,classification"])
            .arg(sample())
            .arg("-o")
            .arg(&m),
    );
    let o = run_ok(mortar().args(["info", "--json"]).arg(&m));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let kept: Vec<String> =
        serde_json::from_value(j[0]["batch"]["kept_attributes"].clone()).unwrap();
    assert_eq!(kept, ["intensity", "classification"]);
    let back = dir.join("back.las");
    let full = dir.join("full.las");
    let o = run_ok(mortar().args(["sort"]).arg(&m).arg("-o").arg(&back));
    let _ = o;
    sort_to(&[&sample()], &full, &[]);
    let (a, rl, _) = las_records(&back).unwrap();
    let (b, _, _) = las_records(&full).unwrap();
    for (ra, rb) in a.chunks_exact(rl).zip(b.chunks_exact(rl)) {
        assert_eq!(ra[..14], rb[..14], "xyz and intensity kept");
        assert_eq!(ra[15], rb[15], "classification kept");
        assert_eq!(&ra[20..], &[0u8; 14][..], "gps time and rgb dropped");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn georeferenced_extremes_round_trip_exactly() {
    let dir = tempdir("geo");
    // ECEF-scale coordinates with scale 0.0001, and geographic degrees with scale 1e-7
    for (tag, origin, scale, extent) in [
        ("ecef", "6400000,0,6000000", "0.0001", "150"),
        ("degrees", "-123.1,44.05,0", "0.0000001", "0.01"),
    ] {
        let las = dir.join(format!("{tag}.las"));
        run_ok(
            gen()
                .args([
                    "--points",
                    "200000",
                    &format!("--origin={origin}"),
                    "--scale",
                    scale,
                    "--extent",
                    extent,
                    "-o",
                ])
                .arg(&las),
        );
        let s = dir.join(format!("{tag}-s.las"));
        let m = dir.join(format!("{tag}.mbat"));
        let back = dir.join(format!("{tag}-back.las"));
        sort_to(&[&las], &s, &[]);
        run_ok(mortar().arg("batch").arg(&las).arg("-o").arg(&m));
        sort_to(&[&m], &back, &[]);
        assert_eq!(std::fs::read(&s).unwrap(), std::fs::read(&back).unwrap(), "{tag}");
        let (a, rl, _) = las_records(&las).unwrap();
        let (b, _, _) = las_records(&s).unwrap();
        assert_eq!(multiset(&a, rl), multiset(&b, rl), "{tag}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn wrong_header_bounds_give_a_warning_and_computed_values() {
    let dir = tempdir("bounds");
    let src = dir.join("src.las");
    sort_to(&[&sample()], &src, &[]);
    let mut b = std::fs::read(&src).unwrap();
    let max_x = f64::from_le_bytes(b[179..187].try_into().unwrap());
    b[179..187].copy_from_slice(&(max_x + 1000.0).to_le_bytes());
    let bad = dir.join("bad.las");
    std::fs::write(&bad, &b).unwrap();
    let o = run_ok(mortar().args(["info", "--stats"]).arg(&bad));
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("header bounds on x"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let out = dir.join("out.las");
    sort_to(&[&bad], &out, &[]);
    let o = std::fs::read(&out).unwrap();
    assert_eq!(
        f64::from_le_bytes(o[179..187].try_into().unwrap()),
        max_x,
        "the output header has the real bounds"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn info_json_is_stable() {
    let o = run_ok(mortar().args(["info", "--json", "--stats"]).arg(sample()));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let f = &j[0];
    for key in [
        "path",
        "kind",
        "version",
        "point_format",
        "record_length",
        "point_count",
        "points_by_return",
        "scale",
        "offset",
        "header_bounds",
        "crs",
        "attributes",
        "extra_bytes",
        "vlrs",
        "evlrs",
        "stats",
        "warnings",
    ] {
        assert!(f.get(key).is_some(), "missing {key}");
    }
    assert_eq!(f["kind"], "laz");
    assert_eq!(f["point_count"], 110000);
    assert_eq!(f["stats"]["point_count"], 110000);
    assert_eq!(f["crs"]["kind"], "wkt+geotiff");
}

#[test]
fn ctrl_c_removes_temporary_files_and_partial_output() {
    let dir = tempdir("sigint");
    let las = dir.join("big.las");
    run_ok(gen().args(["--points", "3000000", "-o"]).arg(&las));
    let tmp = dir.join("tmp");
    std::fs::create_dir_all(&tmp).unwrap();
    let out_dir = dir.join("out");
    std::fs::create_dir_all(&out_dir).unwrap();
    let child = mortar()
        .args(["batch", "--memory", "4M", "--tmp-dir"])
        .arg(&tmp)
        .arg(&las)
        .arg("-o")
        .arg(out_dir.join("o.mbat"))
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // wait until the external sort has written temporary files, then interrupt
    let start = std::time::Instant::now();
    while entries(&tmp).is_empty() && start.elapsed() < std::time::Duration::from_secs(20) {
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    assert!(!entries(&tmp).is_empty(), "the external sort should have started");
    std::process::Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(130), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    assert!(entries(&tmp).is_empty(), "temporary files left: {:?}", entries(&tmp));
    assert!(entries(&out_dir).is_empty(), "partial output left: {:?}", entries(&out_dir));
    std::fs::remove_dir_all(&dir).unwrap();
}
