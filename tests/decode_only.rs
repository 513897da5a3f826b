//! Layer skipping (issue 13): jobs that use only some attributes decode only those layers of LAS
//! 1.4 layered LAZ (point formats 6 to 10). Checked on every such real file of `../shared/data`:
//! the kept fields equal a full decode bit for bit, the skipped ones read as zero, and `batch`
//! and `render` give the bytes they give from the same points as plain LAS (never skipped).

mod common;
use common::*;
use mortar_io::source::LasInput;
use std::path::PathBuf;

/// The layered LAZ files among the readable fixtures.
fn layered_laz() -> Vec<(PathBuf, LasInput)> {
    let Some(data) = shared_data() else { return Vec::new() };
    readable_fixtures(&data)
        .into_iter()
        .filter(|p| p.extension().is_some_and(|e| e == "laz"))
        .filter_map(|p| LasInput::open(&p).ok().map(|i| (p, i)))
        .filter(|(_, i)| i.layout.format >= 6 && i.point_count > 0)
        .collect()
}

#[test]
fn kept_fields_equal_a_full_decode_and_skipped_ones_are_zero() {
    let files = layered_laz();
    if shared_data().is_none() {
        return;
    }
    assert!(files.len() >= 4, "expected several layered LAZ files, found {}", files.len());
    let keeps: &[&[&str]] = &[
        &[],
        &["rgb"],
        &["intensity", "gps_time"],
        &["classification", "flags", "extra_bytes"],
        &["nir", "scan_angle", "user_data", "point_source_id"],
    ];
    for (path, mut input) in files {
        let rl = input.layout.record_len;
        let full: Vec<Vec<u8>> = input
            .pieces()
            .to_vec()
            .iter()
            .map(|p| input.read_piece(p).unwrap().into_owned())
            .collect();
        for keep in keeps {
            input.decode_only(keep);
            for (p, want) in input.pieces().to_vec().iter().zip(&full) {
                let mut got = vec![0u8; want.len()];
                input.read_piece_into(p, &mut got).unwrap();
                let cow = input.read_piece(p).unwrap();
                assert_eq!(
                    &got[..],
                    &cow[..],
                    "{}: read_piece and read_piece_into disagree",
                    path.display()
                );
                for (g, w) in got.chunks_exact(rl).zip(want.chunks_exact(rl)) {
                    assert_eq!(
                        g[..12],
                        w[..12],
                        "{}: positions differ (keep {keep:?})",
                        path.display()
                    );
                    for a in &input.layout.attributes {
                        let (o, n) = (a.offset, a.width);
                        if keep.contains(&a.name.as_str()) {
                            assert_eq!(
                                g[o..o + n],
                                w[o..o + n],
                                "{}: kept {} differs",
                                path.display(),
                                a.name
                            );
                        } else if a.name == "flags" {
                            assert_eq!(g[o], w[o], "{}: the returns byte differs", path.display());
                            assert_eq!(
                                g[o + 1],
                                w[o + 1] & 0b0011_0000,
                                "{}: skipped flags (scanner channel kept)",
                                path.display()
                            );
                        } else {
                            assert!(
                                g[o..o + n].iter().all(|&b| b == 0),
                                "{}: skipped {} is not zero",
                                path.display(),
                                a.name
                            );
                        }
                    }
                }
            }
        }
    }
}

#[test]
fn batch_and_render_from_layered_laz_equal_those_from_las() {
    let files = layered_laz();
    if files.is_empty() {
        return;
    }
    let dir = tempdir("decode-only");
    let mut checked = 0;
    for (i, (path, _)) in files.iter().enumerate() {
        let las = dir.join(format!("{i}.las"));
        let out = mortar().args(["sort"]).arg(path).arg("-o").arg(&las).output().unwrap();
        if !out.status.success() {
            continue;
        }
        for attributes in ["none", "intensity", "gps_time,classification"] {
            let attributes = if attributes == "gps_time,classification"
                && !LasInput::open(path).unwrap().layout.has_gps_time()
            {
                "classification"
            } else {
                attributes
            };
            let (a, b) = (dir.join(format!("{i}-laz.mbat")), dir.join(format!("{i}-las.mbat")));
            run_ok(
                mortar()
                    .arg("batch")
                    .arg(path)
                    .arg("-o")
                    .arg(&a)
                    .args(["--attributes", attributes]),
            );
            run_ok(
                mortar()
                    .arg("batch")
                    .arg(&las)
                    .arg("-o")
                    .arg(&b)
                    .args(["--attributes", attributes]),
            );
            assert!(
                std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap(),
                "{} --attributes {attributes}: LAZ and LAS batch files differ",
                path.display()
            );
        }
        for color in ["auto", "intensity", "classification"] {
            let (a, b) = (dir.join(format!("{i}-laz.png")), dir.join(format!("{i}-las.png")));
            // A COPC file is drawn with LOD by default (issue 30); --no-lod reads every chunk,
            // as the LAS twin is read.
            let flat: &[&str] =
                if path.to_string_lossy().ends_with(".copc.laz") { &["--no-lod"] } else { &[] };
            run_ok(
                mortar()
                    .arg("render")
                    .arg(path)
                    .arg("-o")
                    .arg(&a)
                    .args(["--color", color, "--width", "96", "--height", "64"])
                    .args(flat),
            );
            run_ok(
                mortar()
                    .arg("render")
                    .arg(&las)
                    .arg("-o")
                    .arg(&b)
                    .args(["--color", color, "--width", "96", "--height", "64"]),
            );
            assert!(
                std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap(),
                "{} --color {color}: renders differ",
                path.display()
            );
        }
        checked += 1;
    }
    assert!(checked >= 3, "only {checked} layered LAZ files could be checked");
}
