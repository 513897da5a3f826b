//! Issue 12, "real scans as users have them": mixed point formats merged onto one LAS 1.4 format
//! (checked point by point with the las crate), CRS refusal and `--assign-crs`, COPC and other
//! offset-dependent records dropped (the output read in full by laspy, an independent reader),
//! `mortar info` on truncated files, lying counts and coordinates on the file's own grid.
//! Fixtures are built here with the las crate; the shared real files are used where present.

mod common;
use common::*;
use las::{Builder, Point, Transform, Vector, Vlr};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn projection_vlr(record_id: u16, data: Vec<u8>) -> Vlr {
    Vlr { user_id: "LASF_Projection".into(), record_id, description: "crs".into(), data }
}

/// A GeoTIFF key directory naming a projected EPSG code.
fn geotiff(code: u16) -> Vlr {
    let words: [u16; 12] = [1, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, code];
    projection_vlr(34735, words.iter().flat_map(|w| w.to_le_bytes()).collect())
}

fn wkt_vlr(name: &str, code: u32) -> Vlr {
    let w = format!(
        r#"PROJCS["{name}",GEOGCS["WGS 84",AUTHORITY["EPSG","4326"]],AUTHORITY["EPSG","{code}"]]"#
    );
    let mut data = w.into_bytes();
    data.push(0);
    projection_vlr(2112, data)
}

struct Fixture {
    version: (u8, u8),
    format: u8,
    vlrs: Vec<Vlr>,
    evlrs: Vec<Vlr>,
    /// x of the first point (files do not overlap, so (x, y, z) names a point).
    x0: f64,
    n: usize,
    seed: u64,
    laz: bool,
}

impl Fixture {
    fn new(version: (u8, u8), format: u8, x0: f64) -> Fixture {
        Fixture {
            version,
            format,
            vlrs: Vec::new(),
            evlrs: Vec::new(),
            x0,
            n: 300,
            seed: format as u64 + 1,
            laz: false,
        }
    }
}

/// Writes a fixture with the las crate: every field set to varied values the format can hold.
fn write_fixture(path: &Path, f: &Fixture) {
    let mut b = Builder::from(f.version);
    let mut fmt = las::point::Format::new(f.format).unwrap();
    fmt.is_compressed = f.laz;
    b.point_format = fmt;
    b.transforms = Vector {
        x: Transform { scale: 0.01, offset: 0.0 },
        y: Transform { scale: 0.01, offset: 0.0 },
        z: Transform { scale: 0.01, offset: 0.0 },
    };
    b.vlrs = f.vlrs.clone();
    b.evlrs = f.evlrs.clone();
    b.has_wkt_crs = f
        .vlrs
        .iter()
        .chain(&f.evlrs)
        .any(|v| v.user_id == "LASF_Projection" && v.record_id == 2112);
    let header = b.into_header().unwrap();
    let mut w = las::Writer::from_path(path, header).unwrap();
    let mut s = f.seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    let mut next = |m: u64| {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s % m
    };
    let extended = f.format >= 6;
    for i in 0..f.n {
        // the las crate allows 5 returns and no class 12 (overlap) in legacy files
        let nret = 1 + next(if extended { 15 } else { 5 }) as u8;
        let class = next(if extended { 64 } else { 32 }) as u8;
        let class = if class == 12 { 13 } else { class };
        let p = Point {
            x: f.x0 + i as f64 * 0.37,
            y: 5000.0 + next(100_000) as f64 * 0.01,
            z: 100.0 + next(5000) as f64 * 0.01,
            intensity: next(65536) as u16,
            return_number: 1 + next(nret as u64) as u8,
            number_of_returns: nret,
            scan_direction: if next(2) == 0 {
                las::point::ScanDirection::LeftToRight
            } else {
                las::point::ScanDirection::RightToLeft
            },
            is_edge_of_flight_line: next(2) == 0,
            classification: las::point::Classification::new(class).unwrap(),
            is_synthetic: next(2) == 0,
            is_key_point: next(2) == 0,
            is_withheld: next(2) == 0,
            is_overlap: extended && next(2) == 0,
            scanner_channel: if extended { next(4) as u8 } else { 0 },
            scan_angle: if extended {
                (next(30001) as i32 - 15000) as f32 * 0.006
            } else {
                (next(181) as i32 - 90) as f32
            },
            user_data: next(256) as u8,
            point_source_id: next(65536) as u16,
            gps_time: fmt.has_gps_time.then(|| 1.0e8 + next(1 << 30) as f64 * 1e-3),
            color: fmt.has_color.then(|| {
                las::Color::new(next(65536) as u16, next(65536) as u16, next(65536) as u16)
            }),
            nir: fmt.has_nir.then(|| next(65536) as u16),
            waveform: fmt.has_waveform.then(las::raw::point::Waveform::default),
            ..Default::default()
        };
        w.write_point(p).unwrap();
    }
    w.close().unwrap();
}

fn points_of(p: &Path) -> (las::Header, Vec<Point>) {
    let mut r = las::Reader::from_path(p).unwrap();
    let h = r.header().clone();
    let pts = r.read_all().unwrap().points().collect::<Result<Vec<_>, _>>().unwrap();
    (h, pts)
}

fn key(p: &Point) -> (i64, i64, i64) {
    ((p.x * 100.0).round() as i64, (p.y * 100.0).round() as i64, (p.z * 100.0).round() as i64)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn stderr_of(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// LAS 1.4 scan angle units for a legacy rank, computed here independently of mortar.
fn expected_scan_angle(rank: f32) -> i16 {
    (rank as f64 / 0.006).round() as i16
}

/// Checks that `out` holds exactly the points of `inputs` converted onto a LAS 1.4 format.
fn check_converted(out: &Path, inputs: &[&Path], format: u8) {
    let (h, got) = points_of(out);
    assert_eq!(h.version(), las::Version::new(1, 4), "a converted output is LAS 1.4");
    assert_eq!(h.point_format().to_u8().unwrap(), format);
    let mut by_key: HashMap<(i64, i64, i64), Point> =
        got.into_iter().map(|p| (key(&p), p)).collect();
    let mut total = 0;
    for i in inputs {
        let (ih, pts) = points_of(i);
        let legacy = !ih.point_format().is_extended;
        for p in pts {
            total += 1;
            let o = by_key.remove(&key(&p)).unwrap_or_else(|| {
                panic!("{}: point {:?} missing from the output", i.display(), key(&p))
            });
            let ctx = format!("{} point {:?}", i.display(), key(&p));
            assert_eq!(o.intensity, p.intensity, "{ctx}");
            assert_eq!(o.return_number, p.return_number, "{ctx}");
            assert_eq!(o.number_of_returns, p.number_of_returns, "{ctx}");
            assert_eq!(o.scan_direction, p.scan_direction, "{ctx}");
            assert_eq!(o.is_edge_of_flight_line, p.is_edge_of_flight_line, "{ctx}");
            assert_eq!(u8::from(o.classification), u8::from(p.classification), "{ctx}");
            assert_eq!(
                (o.is_synthetic, o.is_key_point, o.is_withheld),
                (p.is_synthetic, p.is_key_point, p.is_withheld),
                "{ctx}"
            );
            assert_eq!(o.user_data, p.user_data, "{ctx}");
            assert_eq!(o.point_source_id, p.point_source_id, "{ctx}");
            if legacy {
                assert!(!o.is_overlap, "{ctx}");
                assert_eq!(o.scanner_channel, 0, "{ctx}");
                let units = (o.scan_angle as f64 / 0.006).round() as i16;
                assert_eq!(units, expected_scan_angle(p.scan_angle), "{ctx}: scan angle");
                assert_eq!(
                    o.scan_angle.round(),
                    p.scan_angle,
                    "{ctx}: the rank comes back by rounding"
                );
            } else {
                assert_eq!(o.is_overlap, p.is_overlap, "{ctx}");
                assert_eq!(o.scanner_channel, p.scanner_channel, "{ctx}");
                assert_eq!(o.scan_angle, p.scan_angle, "{ctx}");
            }
            assert_eq!(
                o.gps_time,
                Some(p.gps_time.unwrap_or(0.0)),
                "{ctx}: gps time (0 where absent)"
            );
            let zero = las::Color::new(0, 0, 0);
            if h.point_format().has_color {
                assert_eq!(o.color, Some(p.color.unwrap_or(zero)), "{ctx}: rgb (0 where absent)");
            }
            if h.point_format().has_nir {
                assert_eq!(o.nir, Some(p.nir.unwrap_or(0)), "{ctx}: nir");
            }
        }
    }
    assert!(by_key.is_empty(), "{} points in the output come from no input", by_key.len());
    assert_eq!(h.number_of_points(), total);
}

#[test]
fn mixed_formats_merge_onto_one_las14_format_point_by_point() {
    let d = tempdir("mixed");
    let crs = || vec![geotiff(32610)];
    let mut inputs = Vec::new();
    for (i, (version, format)) in
        [((1, 2), 0u8), ((1, 2), 1), ((1, 3), 2), ((1, 2), 3), ((1, 4), 6), ((1, 4), 7)]
            .into_iter()
            .enumerate()
    {
        let p = d.join(format!("f{format}.las"));
        let mut f = Fixture::new(version, format, 1000.0 * (i + 1) as f64);
        f.vlrs = crs();
        write_fixture(&p, &f);
        inputs.push(p);
    }
    let all: Vec<&str> = inputs.iter().map(|p| s(p)).collect();
    for (names, format) in [
        (vec![0usize, 4], 6u8),
        (vec![1, 4], 6),
        (vec![0, 1, 2, 3, 4, 5], 7),
        (vec![3, 5], 7),
        (vec![2, 4], 7),
    ] {
        let ins: Vec<&str> = names.iter().map(|&i| all[i]).collect();
        let paths: Vec<&Path> = names.iter().map(|&i| inputs[i].as_path()).collect();
        for ext in ["las", "laz"] {
            let out = d.join(format!("out-{format}-{}.{ext}", names.len()));
            let o = run_ok(mortar().arg("sort").args(&ins).args(["-o", s(&out)]));
            assert!(
                stderr_of(&o).contains(&format!("merged into point format {format}")),
                "{}",
                stderr_of(&o)
            );
            check_converted(&out, &paths, format);
        }
    }
    // every command sees the one layout: batch -> sort gives the bytes of the direct sort
    let direct = d.join("direct.las");
    run_ok(mortar().arg("sort").args(&all).args(["-o", s(&direct)]));
    let mbat = d.join("all.mbat");
    run_ok(mortar().arg("batch").args(&all).args(["-o", s(&mbat)]));
    let back = d.join("back.las");
    run_ok(mortar().args(["sort", s(&mbat), "-o", s(&back)]));
    assert_eq!(std::fs::read(&direct).unwrap(), std::fs::read(&back).unwrap());
    let store = d.join("store");
    run_ok(mortar().arg("build").args(&all).args(["-o", s(&store)]));
    let from_store = d.join("from-store.las");
    run_ok(mortar().args(["sort", s(&store), "-o", s(&from_store)]));
    check_converted(&from_store, &inputs.iter().map(|p| p.as_path()).collect::<Vec<_>>(), 7);
    let j = info_json(&mbat);
    assert_eq!(j["point_format"], 7);
    assert_eq!(j["version"], "1.4");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn waveform_formats_are_not_merged_with_others() {
    let d = tempdir("wave");
    let a = d.join("a.las");
    let b = d.join("b.las");
    write_fixture(&a, &Fixture::new((1, 2), 1, 1000.0));
    write_fixture(&b, &Fixture::new((1, 4), 9, 3000.0));
    let out = d.join("out.las");
    let o = mortar().args(["sort", s(&a), s(&b), "-o", s(&out)]).output().unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr_of(&o).contains("waveform"), "{}", stderr_of(&o));
    assert!(!out.exists());
    std::fs::remove_dir_all(&d).unwrap();
}

fn info_json(p: &Path) -> serde_json::Value {
    let o = run_ok(mortar().args(["info", "--json", s(p)]));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    v[0].clone()
}

fn crs_fixtures(d: &Path) -> (PathBuf, PathBuf, PathBuf, PathBuf) {
    let a = d.join("utm10.las");
    let b = d.join("utm11.las");
    let none = d.join("nocrs.las");
    let wkt = d.join("wkt.las");
    let mut f = Fixture::new((1, 2), 1, 1000.0);
    f.vlrs = vec![geotiff(32610)];
    write_fixture(&a, &f);
    let mut f = Fixture::new((1, 2), 1, 3000.0);
    f.vlrs = vec![geotiff(32611)];
    write_fixture(&b, &f);
    write_fixture(&none, &Fixture::new((1, 2), 1, 5000.0));
    let mut f = Fixture::new((1, 4), 6, 7000.0);
    f.vlrs = vec![wkt_vlr("WGS 84 / UTM zone 12N", 32612)];
    write_fixture(&wkt, &f);
    (a, b, none, wkt)
}

#[test]
fn inputs_whose_crss_disagree_are_refused_naming_both() {
    let d = tempdir("crs-refuse");
    let (a, b, _, _) = crs_fixtures(&d);
    let out_dir = d.join("out");
    std::fs::create_dir_all(&out_dir).unwrap();
    let out = out_dir.join("out.las");
    let mbat = out_dir.join("out.mbat");
    let store = out_dir.join("store");
    let png = out_dir.join("out.png");
    for args in [
        vec!["sort", s(&a), s(&b), "-o", s(&out)],
        vec!["batch", s(&a), s(&b), "-o", s(&mbat)],
        vec!["build", s(&a), s(&b), "-o", s(&store)],
        vec!["render", s(&a), s(&b), "-o", s(&png), "--backend", "cpu"],
    ] {
        let o = mortar().args(&args).output().unwrap();
        let err = stderr_of(&o);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {err}");
        let lines: Vec<&str> = err.lines().collect();
        assert_eq!(lines.len(), 1, "{args:?}: one line: {err}");
        for want in [
            "utm10.las",
            "utm11.las",
            "WGS 84 / UTM zone 10N (EPSG:32610, geotiff)",
            "WGS 84 / UTM zone 11N (EPSG:32611, geotiff)",
            "--assign-crs",
        ] {
            assert!(lines[0].contains(want), "{args:?}: '{want}' missing from: {err}");
        }
        assert!(entries(&out_dir).is_empty(), "{args:?} left {:?}", entries(&out_dir));
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn inputs_without_a_crs_take_the_one_crs_with_a_warning() {
    let d = tempdir("crs-one");
    let (a, _, none, _) = crs_fixtures(&d);
    let out = d.join("out.las");
    let o = run_ok(mortar().args(["sort", s(&none), s(&a), "-o", s(&out)]));
    let err = stderr_of(&o);
    assert!(err.contains("nocrs.las has no CRS") && err.contains("EPSG:32610"), "{err}");
    let (h, _) = points_of(&out);
    let crs: Vec<&Vlr> = h.vlrs().iter().filter(|v| v.user_id == "LASF_Projection").collect();
    assert_eq!(crs.len(), 1);
    assert_eq!(crs[0].data, geotiff(32610).data);
    assert_eq!(info_json(&out)["crs"]["epsg"], 32610);
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn assign_crs_from_a_file_or_an_epsg_code() {
    let d = tempdir("crs-assign");
    let (a, b, _, wkt) = crs_fixtures(&d);
    // FILE: the file's CRS records byte for byte, WKT bit set
    let out = d.join("file.las");
    run_ok(mortar().args(["sort", s(&a), s(&b), "-o", s(&out), "--assign-crs", s(&wkt)]));
    let (h, pts) = points_of(&out);
    assert_eq!(pts.len(), 600);
    let crs: Vec<&Vlr> = h.all_vlrs().filter(|v| v.user_id == "LASF_Projection").collect();
    assert_eq!(crs.len(), 1, "the inputs' GeoTIFF keys are replaced");
    assert_eq!(crs[0].data, wkt_vlr("WGS 84 / UTM zone 12N", 32612).data);
    let j = info_json(&out);
    assert_eq!(j["crs"]["epsg"], 32612);
    assert_eq!(j["crs"]["kind"], "wkt");
    // EPSG: GeoTIFF keys, with a vertical code
    let out = d.join("epsg.las");
    run_ok(mortar().args(["sort", s(&a), s(&b), "-o", s(&out), "--assign-crs", "EPSG:26910+5703"]));
    let j = info_json(&out);
    assert_eq!(j["crs"]["kind"], "geotiff");
    assert_eq!(j["crs"]["epsg"], 26910);
    assert_eq!(j["crs"]["vertical_epsg"], 5703);
    assert_eq!(j["crs"]["name"], "NAD83 / UTM zone 10N");
    assert!(j["crs"]["problems"].as_array().unwrap().is_empty());
    let (h, _) = points_of(&out);
    assert!(!h.has_wkt_crs());
    // geographic codes get GeographicTypeGeoKey
    let out = d.join("geo.las");
    run_ok(mortar().args(["sort", s(&a), "-o", s(&out), "--assign-crs", "epsg:4326"]));
    let keys = info_json(&out)["crs"]["geokeys"].clone();
    assert!(
        keys.as_array()
            .unwrap()
            .iter()
            .any(|k| k["name"] == "GeographicTypeGeoKey" && k["value"] == "4326"),
        "{keys}"
    );
    // batch files and stores carry it too
    let mbat = d.join("o.mbat");
    run_ok(mortar().args(["batch", s(&a), s(&b), "-o", s(&mbat), "--assign-crs", "EPSG:32633"]));
    assert_eq!(info_json(&mbat)["crs"]["epsg"], 32633);
    let store = d.join("store");
    run_ok(mortar().args(["build", s(&a), s(&b), "-o", s(&store), "--assign-crs", s(&wkt)]));
    assert_eq!(info_json(&store)["crs"]["epsg"], 32612);
    // bad values: one line naming the problem, nothing written
    let bad_out = d.join("bad.las");
    let missing = d.join("missing.las");
    for (v, want) in
        [(s(&missing), "missing.las"), (s(&a.with_file_name("nocrs.las")), "no CRS records")]
    {
        let o =
            mortar().args(["sort", s(&a), "-o", s(&bad_out), "--assign-crs", v]).output().unwrap();
        assert_eq!(o.status.code(), Some(1), "{}", stderr_of(&o));
        assert!(
            stderr_of(&o).contains(want) && stderr_of(&o).lines().count() == 1,
            "{}",
            stderr_of(&o)
        );
        assert!(!bad_out.exists());
    }
    let o = mortar()
        .args(["sort", s(&a), "-o", s(&bad_out), "--assign-crs", "EPSG:4978"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr_of(&o).contains("geocentric"), "{}", stderr_of(&o));
    let o = mortar()
        .args(["sort", s(&a), "-o", s(&bad_out), "--assign-crs", "EPSG:x"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(!bad_out.exists());
    std::fs::remove_dir_all(&d).unwrap();
}

/// What laspy reads of a file: point count, (E)VLR ids, and the sorted X/Y/Z integers' digest.
fn laspy_read(py: &Path, f: &Path) -> serde_json::Value {
    let script = r#"
import sys, json, hashlib, laspy, numpy as np
with laspy.open(sys.argv[1]) as r:
    las = r.read()
xyz = np.stack([las.X, las.Y, las.Z], axis=1).astype('<i4')
xyz = xyz[np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))]
print(json.dumps({
    "points": int(len(las.points)),
    "header_points": int(las.header.point_count),
    "vlrs": [[v.user_id, v.record_id] for v in las.vlrs],
    "evlrs": [[v.user_id, v.record_id] for v in (las.evlrs or [])],
    "xyz": hashlib.sha256(xyz.tobytes()).hexdigest(),
}))
"#;
    let o = Command::new(py).arg("-c").arg(script).arg(f).output().unwrap();
    assert!(o.status.success(), "laspy could not read {}: {}", f.display(), stderr_of(&o));
    serde_json::from_slice(&o.stdout).unwrap()
}

fn has_copc(j: &serde_json::Value) -> bool {
    j["vlrs"]
        .as_array()
        .unwrap()
        .iter()
        .chain(j["evlrs"].as_array().unwrap())
        .any(|v| v[0] == "copc" || (v[0] == "LAStools" && v[1] == 30))
}

#[test]
fn sorted_copc_has_no_copc_records_and_laspy_reads_it_in_full() {
    let Some(py) = laspy_python() else { return };
    let d = tempdir("copc");
    let src = d.join("fake.copc.laz");
    let mut f = Fixture::new((1, 4), 6, 1000.0);
    f.n = 5000;
    f.laz = true;
    f.vlrs = vec![
        Vlr {
            user_id: "copc".into(),
            record_id: 1,
            description: "copc info".into(),
            data: vec![7; 160],
        },
        wkt_vlr("WGS 84 / UTM zone 10N", 32610),
        Vlr {
            user_id: "LAStools".into(),
            record_id: 10,
            description: "tile without buffer".into(),
            data: vec![3; 28],
        },
    ];
    f.evlrs = vec![
        Vlr {
            user_id: "copc".into(),
            record_id: 1000,
            description: "EPT hierarchy".into(),
            data: vec![9; 32],
        },
        Vlr {
            user_id: "LAStools".into(),
            record_id: 30,
            description: "LAX spatial indexing (LASindex)".into(),
            data: vec![1; 64],
        },
    ];
    write_fixture(&src, &f);
    let input = laspy_read(&py, &src);
    assert!(has_copc(&input));
    for ext in ["las", "laz"] {
        let out = d.join(format!("sorted.{ext}"));
        let o = run_ok(mortar().args(["sort", s(&src), "-o", s(&out)]));
        let err = stderr_of(&o);
        let notes: Vec<&str> = err.lines().filter(|l| l.contains("dropped")).collect();
        assert_eq!(notes.len(), 1, "one line about the dropped records: {err}");
        for want in ["copc 1 (COPC info)", "copc 1000 (COPC hierarchy)", "LAStools 30"] {
            assert!(notes[0].contains(want), "'{want}' missing: {err}");
        }
        let got = laspy_read(&py, &out);
        assert!(!has_copc(&got), "{got}");
        assert_eq!(got["points"], 5000);
        assert_eq!(got["header_points"], 5000);
        assert_eq!(got["xyz"], input["xyz"], "the same points");
        assert!(
            got["vlrs"].as_array().unwrap().iter().any(|v| v[0] == "LASF_Projection"),
            "the CRS stays"
        );
        assert!(
            got["vlrs"].as_array().unwrap().iter().any(|v| v[0] == "LAStools" && v[1] == 10),
            "the tiling VLR stays"
        );
    }
    let mbat = d.join("o.mbat");
    run_ok(mortar().args(["batch", s(&src), "-o", s(&mbat)]));
    let store = d.join("store");
    run_ok(mortar().args(["build", s(&src), "-o", s(&store)]));
    for p in [&mbat, &store] {
        let j = info_json(p);
        let ids: Vec<String> = j["vlrs"]
            .as_array()
            .unwrap()
            .iter()
            .chain(j["evlrs"].as_array().unwrap())
            .map(|v| v["user_id"].as_str().unwrap().to_string())
            .collect();
        assert!(!ids.iter().any(|i| i == "copc"), "{}: {ids:?}", p.display());
        assert_eq!(
            ids.iter().filter(|i| *i == "LAStools").count(),
            1,
            "{}: only the tiling record: {ids:?}",
            p.display()
        );
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn real_copc_files_sort_into_files_laspy_reads_in_full() {
    let Some(data) = shared_data() else { return };
    let Some(py) = laspy_python() else { return };
    let d = tempdir("copc-real");
    for rel in [
        "PDAL/test/data/copc/1.2-with-color.copc.laz",
        "laspy/tests/data/simple_with_page.copc.laz",
        "las-rs/tests/data/autzen.copc.laz",
    ] {
        let src = data.join(rel);
        if !src.exists() {
            continue;
        }
        let input = laspy_read(&py, &src);
        let out = d.join("sorted.laz");
        let o = run_ok(mortar().args(["sort", s(&src), "-o", s(&out)]));
        assert!(stderr_of(&o).contains("copc 1 (COPC info)"), "{rel}: {}", stderr_of(&o));
        let got = laspy_read(&py, &out);
        assert!(!has_copc(&got), "{rel}: {got}");
        assert_eq!(got["points"], input["points"], "{rel}");
        assert_eq!(got["xyz"], input["xyz"], "{rel}");
    }
    std::fs::remove_dir_all(&d).unwrap();
}

fn patch(p: &Path, at: usize, bytes: &[u8]) {
    let mut b = std::fs::read(p).unwrap();
    b[at..at + bytes.len()].copy_from_slice(bytes);
    std::fs::write(p, b).unwrap();
}

#[test]
fn info_prints_coordinates_on_the_files_grid() {
    let d = tempdir("grid");
    let p = d.join("a.las");
    write_fixture(&p, &Fixture::new((1, 2), 1, 848935.2));
    // header max x / min x as a careless writer leaves them
    patch(&p, 187, &848935.2000000001f64.to_le_bytes());
    patch(&p, 179, &849045.8300000001f64.to_le_bytes());
    let o = run_ok(mortar().args(["info", s(&p)]));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("x [848935.20, 849045.83]"), "{text}");
    assert!(!text.contains("0000001"), "{text}");
    let j = info_json(&p);
    assert_eq!(j["header_bounds"]["min"][0].to_string(), "848935.2");
    assert_eq!(j["header_bounds"]["max"][0].to_string(), "849045.83");
    let o = run_ok(mortar().args(["info", "--stats", "--json", s(&p)]));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v[0]["stats"]["bounds"]["min"][0].to_string(), "848935.2");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn info_on_truncated_files_and_lying_counts() {
    let d = tempdir("trunc");
    for ext in ["las", "laz"] {
        let p = d.join(format!("whole.{ext}"));
        let mut f = Fixture::new((1, 2), 3, 1000.0);
        f.n = 60_000;
        f.laz = ext == "laz";
        write_fixture(&p, &f);
        let bytes = std::fs::read(&p).unwrap();
        let cut = d.join(format!("cut.{ext}"));
        std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
        for stats in [false, true] {
            let mut c = mortar();
            c.arg("info");
            if stats {
                c.arg("--stats");
            }
            let o = c.arg(s(&cut)).output().unwrap();
            let err = stderr_of(&o);
            assert_eq!(o.status.code(), Some(1), "{ext} stats={stats}: {err}");
            assert!(
                err.contains("cut.") && err.contains("truncated") && err.lines().count() == 1,
                "{ext} stats={stats}: {err}"
            );
        }
    }
    // a header that claims fewer points than the file holds: a warning, exit 0
    let p = d.join("fewer.las");
    write_fixture(&p, &Fixture::new((1, 2), 1, 1000.0));
    patch(&p, 107, &200u32.to_le_bytes());
    let o = run_ok(mortar().args(["info", s(&p)]));
    assert!(
        stderr_of(&o).contains("holds 300 points of data but the header says 200"),
        "{}",
        stderr_of(&o)
    );
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn sort_warns_when_the_headers_points_by_return_lie() {
    let d = tempdir("byret");
    let p = d.join("a.las");
    write_fixture(&p, &Fixture::new((1, 2), 1, 1000.0));
    let out = d.join("o.las");
    let o = run_ok(mortar().args(["sort", s(&p), "-o", s(&out)]));
    assert!(!stderr_of(&o).contains("by return"), "{}", stderr_of(&o));
    let (h, _) = points_of(&out);
    let truth: Vec<u64> = (1..=5).map(|r| h.number_of_points_by_return(r).unwrap_or(0)).collect();
    patch(&p, 111, &(truth[0] as u32 + 5).to_le_bytes());
    let o = run_ok(mortar().args(["sort", s(&p), "-o", s(&out)]));
    let err = stderr_of(&o);
    assert!(
        err.contains("points by return") && err.contains(&format!("{}", truth[0] + 5)),
        "{err}"
    );
    let mbat = d.join("o.mbat");
    let o = run_ok(mortar().args(["batch", s(&p), "-o", s(&mbat)]));
    assert!(stderr_of(&o).contains("points by return"), "{}", stderr_of(&o));
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn real_mixed_formats_and_crss_merge() {
    let Some(data) = shared_data() else { return };
    let d = tempdir("real-mixed");
    let a = data.join("PDAL/test/data/autzen/autzen-point-format-3.las");
    let b = data.join("PDAL/test/data/autzen/autzen-bmx-2010.las");
    if !a.exists() || !b.exists() {
        return;
    }
    let out = d.join("o.las");
    let o = mortar().args(["sort", s(&a), s(&b), "-o", s(&out)]).output().unwrap();
    if o.status.success() {
        check_converted(&out, &[&a, &b], 7);
    } else {
        // the two tiles name their CRS differently: refused, or merged when the user says so
        let err = stderr_of(&o);
        assert!(
            err.contains("autzen-point-format-3.las") && err.contains("autzen-bmx-2010.las"),
            "{err}"
        );
        run_ok(mortar().args(["sort", s(&a), s(&b), "-o", s(&out), "--assign-crs", s(&b)]));
        check_converted(&out, &[&a, &b], 7);
    }
    std::fs::remove_dir_all(&d).unwrap();
}
