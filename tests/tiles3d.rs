//! `mortar export --format 3dtiles` (issue 30 §3) checked by code that is not mortar's: every
//! tile through Khronos' glTF validator and every tileset through loaders.gl
//! (`tests/web/tiles_check.mjs`, Node), and the points placed on the globe against laspy and
//! pyproj (PROJ) (`tests/tiles3d_check.py`), on real files in several CRSs.

mod common;
use common::*;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Python with laspy, lazrs, pyproj and numpy; required with `MORTAR_REQUIRE_PYTHON=1`.
fn python() -> Option<PathBuf> {
    let py = laspy_python()?;
    let ok = Command::new(&py)
        .args(["-c", "import pyproj, numpy"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var("MORTAR_REQUIRE_PYTHON").as_deref() != Ok("1"),
            "MORTAR_REQUIRE_PYTHON=1 but {} cannot import pyproj and numpy",
            py.display()
        );
        eprintln!("SKIP: no pyproj/numpy");
        return None;
    }
    Some(py)
}

/// Whether Node and the npm glTF validator and loaders.gl are installed (tests/web); required
/// with `MORTAR_REQUIRE_WEB=1`.
fn node() -> bool {
    let w = root().join("tests/web/node_modules");
    let ok = w.join("gltf-validator").is_dir()
        && w.join("@loaders.gl/3d-tiles").is_dir()
        && Command::new("node").arg("--version").output().is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var("MORTAR_REQUIRE_WEB").as_deref() != Ok("1"),
            "MORTAR_REQUIRE_WEB=1 but tests/web is not installed (tests/web/install.sh)"
        );
        eprintln!("SKIP: tests/web not installed");
    }
    ok
}

fn export(input: &Path, out: &Path, extra: &[&str]) -> Output3 {
    let mut c = mortar();
    c.args(["export", s(input), "-o", s(out), "--format", "3dtiles", "--json", "--quiet"])
        .args(extra);
    let o = c.output().unwrap();
    Output3 {
        ok: o.status.success(),
        code: o.status.code(),
        json: serde_json::from_slice(&o.stdout).unwrap_or(Value::Null),
        stderr: String::from_utf8_lossy(&o.stderr).into_owned(),
    }
}

struct Output3 {
    ok: bool,
    code: Option<i32>,
    json: Value,
    stderr: String,
}

fn py_check(py: &Path, dir: &Path, input: &Path) -> Value {
    py_check_as(py, dir, input, None)
}

/// [`py_check`] with the EPSG code pyproj is to take the input in (where laspy reads no CRS
/// from its records: user-defined GeoTIFF keys, a broken WKT).
fn py_check_as(py: &Path, dir: &Path, input: &Path, epsg: Option<u32>) -> Value {
    let mut c = Command::new(py);
    c.arg(root().join("tests/tiles3d_check.py")).arg(dir).arg(input);
    if let Some(e) = epsg {
        c.arg(e.to_string());
    }
    let o = c.output().unwrap();
    assert!(
        o.status.success(),
        "tiles3d_check.py {input:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).unwrap()
}

fn node_check(dir: &Path) -> Value {
    let o = run_limited(
        {
            let mut c = Command::new("node");
            c.arg(root().join("tests/web/tiles_check.mjs")).arg(dir);
            c
        },
        std::time::Duration::from_secs(300),
    );
    let v: Value = serde_json::from_slice(&o.stdout).unwrap_or_else(|_| {
        panic!("tiles_check.mjs {dir:?}: {}", String::from_utf8_lossy(&o.stderr))
    });
    assert!(o.status.success(), "tiles_check.mjs {dir:?}: {v}");
    v
}

/// Real files in several CRSs: WKT Lambert in feet, geographic degrees, Albers with a vertical
/// code, WKT 2 Lambert-93, UTM, a State Plane in feet; the shipped sample alone without
/// `../shared/data`.
///
/// With the EPSG code of the same CRS for pyproj where laspy reads none: user-defined GeoTIFF
/// keys (Autzen's Lambert with its false easting in metres, a user-defined UTM 22N) and a WKT
/// whose compound node closes early.
fn placed_files() -> Vec<(PathBuf, Option<u32>)> {
    let mut v = vec![(root().join("data-samples/autzen_trim.laz"), None)];
    if let Some(d) = shared_data() {
        for (f, epsg) in [
            ("PDAL/test/data/autzen/autzen-dd.las", None),
            ("lasR/inst/extdata/bcts/bcts_1.laz", None),
            ("laspy/tests/data/file_with_both_wkt_and_geotiff_vlrs.las", None),
            ("PDAL/test/data/laz/las_with_several_extra_byte_bloc.laz", None),
            ("PyForestScan/example_data/ept/ept-data/0-0-0-0.laz", None),
            ("PDAL/test/data/las/bad-geotiff-keys.las", None),
            ("PDAL/test/data/autzen/thin-1.las", Some(2994)),
            ("PDAL/test/data/las/interesting.las", Some(2994)),
            ("lasR/inst/extdata/extra_byte.las", Some(32622)),
            ("lasR/inst/extdata/las14_pdrf6.laz", Some(32610)),
        ] {
            v.push((d.join(f), epsg));
        }
    }
    v
}

fn assert_placed(j: &Value, report: &Value, input: &Path) {
    assert_eq!(j["points"], j["input_points"], "{input:?}: {j}");
    assert_eq!(j["attributes_equal"], true, "{input:?}: {j}");
    let bound = report["position_error_bound"].as_f64().unwrap();
    assert!(bound < 0.05, "{input:?}: error bound {bound} m");
    // order-free statistics of the points against PROJ's: within the storage's error
    assert!(j["centroid_m"].as_f64().unwrap() <= bound + 1e-3, "{input:?}: {j}");
    assert!(j["extremes_m"].as_f64().unwrap() <= bound + 1e-3, "{input:?}: {j}");
    // the root box's centre against the same box of PROJ's points
    assert!(j["root_centre_m"].as_f64().unwrap() < 1.0, "{input:?}: {j}");
}

#[test]
fn real_files_are_placed_on_the_globe_and_read_by_others() {
    let (py, node) = (python(), node());
    let d = tempdir("tiles3d-real");
    for (i, (f, epsg)) in placed_files().iter().enumerate() {
        let out = d.join(format!("t{i}"));
        let r = export(f, &out, &[]);
        assert!(r.ok, "{f:?}: {}", r.stderr);
        assert!(r.json["tiles_crs"].is_string(), "{f:?}: {}", r.json);
        let e = r.json["ecef_center"].as_array().unwrap();
        let radius = e.iter().map(|v| v.as_f64().unwrap().powi(2)).sum::<f64>().sqrt();
        assert!((6.3e6..6.4e6).contains(&radius), "{f:?}: ECEF centre {e:?}");
        if let Some(py) = &py {
            assert_placed(&py_check_as(py, &out, f, *epsg), &r.json, f);
        }
        if node {
            let n = node_check(&out);
            assert_eq!(n["points"], r.json["points"], "{f:?}: {n}");
            assert_eq!(n["validator_errors"], 0, "{f:?}: {n}");
            assert_eq!(n["validator_warnings"], 0, "{f:?}: {n}");
        }
    }
    std::fs::remove_dir_all(&d).ok();
}

/// Whether the CesiumJS check can run (chromium, npm cesium); required with
/// `MORTAR_REQUIRE_WEB=1`.
fn cesium() -> bool {
    let chromium = std::path::Path::new("/usr/lib/chromium/chromium").exists()
        || Command::new("sh")
            .args(["-c", "command -v chromium"])
            .output()
            .is_ok_and(|o| o.status.success());
    let ok = node()
        && chromium
        && root().join("tests/web/node_modules/cesium/Build/Cesium/Cesium.js").is_file();
    if !ok {
        assert!(
            std::env::var("MORTAR_REQUIRE_WEB").as_deref() != Ok("1"),
            "MORTAR_REQUIRE_WEB=1 but chromium or npm cesium is missing"
        );
        eprintln!("SKIP: no chromium or npm cesium");
    }
    ok
}

/// CesiumJS 1.145 in headless Chromium loads the tileset, draws a non-empty picture, and puts
/// its bounding sphere's centre within 1 m of the centre of the input's points placed by PROJ.
#[test]
fn cesium_draws_the_tileset_at_the_right_place() {
    if !cesium() {
        return;
    }
    let py = python();
    let d = tempdir("tiles3d-cesium");
    let mut files = vec![root().join("data-samples/autzen_trim.laz")];
    if let Some(data) = shared_data() {
        files.push(data.join("lasR/inst/extdata/bcts/bcts_1.laz"));
    }
    for (i, f) in files.iter().enumerate() {
        let out = d.join(format!("t{i}"));
        let r = export(f, &out, &[]);
        assert!(r.ok, "{f:?}: {}", r.stderr);
        let mut c = Command::new("node");
        c.arg("--no-deprecation").arg(root().join("tests/web/cesium_check.mjs")).arg(&out);
        let o = run_limited(c, std::time::Duration::from_secs(240));
        let v: Value = serde_json::from_slice(&o.stdout).unwrap_or_else(|_| {
            panic!("cesium_check.mjs {f:?}: {}", String::from_utf8_lossy(&o.stderr))
        });
        assert!(o.status.success() && v["loaded"] == true, "{f:?}: {v}");
        let covered = v["covered_pixels"].as_u64().unwrap();
        assert!(covered > 800 * 600 / 100, "{f:?}: {covered} pixels drawn");
        let loaded = v["points_loaded"].as_u64().unwrap();
        assert!(loaded > 0 && loaded <= r.json["points"].as_u64().unwrap(), "{f:?}: {v}");
        let centre: Vec<f64> = v["bounding_sphere_center"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let want: Vec<f64> = match &py {
            Some(py) => py_check(py, &out, f)["ref_centre_ecef"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect(),
            None => r.json["ecef_center"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect(),
        };
        let dist = (0..3).map(|a| (centre[a] - want[a]).powi(2)).sum::<f64>().sqrt();
        assert!(dist < 1.0, "{f:?}: CesiumJS's centre {centre:?} is {dist} m from {want:?}");
    }
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn deep_trees_are_split_into_external_tilesets_and_streamed_exports_agree() {
    let d = tempdir("tiles3d-deep");
    let f = root().join("data-samples/autzen_trim.laz");
    let (a, b) = (d.join("mem"), d.join("part"));
    let ra = export(&f, &a, &["--leaf-capacity", "100"]);
    assert!(ra.ok, "{}", ra.stderr);
    assert_eq!(ra.json["engine"], "memory");
    assert!(
        ra.json["depth"].as_u64().unwrap() > mortar_io::export::tiles3d::SPLIT as u64,
        "{}",
        ra.json
    );
    let externals = entries(&a.join("tiles")).iter().filter(|n| n.ends_with(".json")).count();
    assert!(externals > 0, "no external tileset");
    let rb = export(&f, &b, &["--leaf-capacity", "100", "--memory", "4M"]);
    assert!(rb.ok, "{}", rb.stderr);
    assert_eq!(rb.json["engine"], "partitioned");
    // The same tiles with the same bytes, and the same tilesets.
    assert_eq!(entries(&a.join("tiles")), entries(&b.join("tiles")));
    for n in entries(&a.join("tiles")) {
        assert!(
            std::fs::read(a.join("tiles").join(&n)).unwrap()
                == std::fs::read(b.join("tiles").join(&n)).unwrap(),
            "tile {n} differs between the in-memory and the partitioned export"
        );
    }
    assert_eq!(
        std::fs::read(a.join("tileset.json")).unwrap(),
        std::fs::read(b.join("tileset.json")).unwrap()
    );
    if let Some(py) = python() {
        assert_placed(&py_check(&py, &b, &f), &rb.json, &f);
    }
    if node() {
        let n = node_check(&b);
        assert_eq!(n["points"], 110_000, "{n}");
        assert!(n["tilesets"].as_u64().unwrap() > 1, "{n}");
        assert_eq!(n["validator_errors"], 0, "{n}");
    }
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn inputs_without_a_crs_are_written_in_a_local_frame_with_a_warning() {
    let Some(data) = shared_data() else { return };
    let d = tempdir("tiles3d-local");
    let f = data.join("laserchicken/testdata/AHN3.laz");
    let out = d.join("t");
    let r = export(&f, &out, &[]);
    assert!(r.ok, "{}", r.stderr);
    let w = r.json["warnings"].to_string();
    assert!(w.contains("no CRS") && w.contains("AHN3.laz"), "{w}");
    assert!(r.json["tiles_crs"].is_null() && r.json["ecef_center"].is_null(), "{}", r.json);
    if let Some(py) = python() {
        let j = py_check(&py, &out, &f);
        assert_eq!(j["local_frame"], true);
        assert_placed(&j, &r.json, &f);
    }
    // The same points given a CRS are placed on the globe (Amersfoort / RD New).
    let g = d.join("g");
    let r = export(&f, &g, &["--assign-crs", "EPSG:28992"]);
    assert!(r.ok, "{}", r.stderr);
    assert!(r.json["tiles_crs"].as_str().unwrap().contains("Amersfoort"), "{}", r.json);
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn crs_that_cannot_be_placed_is_refused_and_leaves_nothing() {
    let Some(data) = shared_data() else { return };
    let d = tempdir("tiles3d-bad");
    // lone-star's GeoTIFF keys say WGS 84 degrees; its coordinates are UTM metres.
    let f = data.join("PDAL/test/data/ept/source/lone-star.laz");
    let out = d.join("t");
    let r = export(&f, &out, &[]);
    assert!(!r.ok && r.code == Some(1), "{}", r.stderr);
    assert!(
        r.stderr.contains("lone-star.laz")
            && r.stderr.contains("WGS 84")
            && r.stderr.contains("--assign-crs"),
        "{}",
        r.stderr
    );
    assert!(!out.exists());
    assert_eq!(entries(&d), Vec::<String>::new(), "something was left beside the output");
    // Given the right CRS, it is placed.
    let r = export(&f, &out, &["--assign-crs", "EPSG:32612"]);
    assert!(r.ok, "{}", r.stderr);
    std::fs::remove_dir_all(&d).ok();
}
