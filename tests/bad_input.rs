//! Bad input: every file listed as bad in `../shared/data/README.md`, and hostile files made
//! here, end in exit code 1 with one line naming the file and the problem: no panic, no hang, no
//! output left behind.

mod common;
use common::*;
use std::path::Path;
use std::time::Duration;

fn expect_clean_failure(args: &[&str], file: &Path, out_dir: &Path) {
    let mut c = mortar();
    c.args(args);
    let o = run_limited(c, Duration::from_secs(30));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{args:?} should fail with 1, stderr: {err}");
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    let lines: Vec<&str> = err.lines().collect();
    assert_eq!(lines.len(), 1, "{args:?} should print one line, got: {err}");
    let name = file.file_name().unwrap().to_string_lossy();
    assert!(lines[0].contains(&*name), "{args:?}: the error should name the file: {err}");
    assert!(o.stdout.is_empty() || args[0] == "info", "no data on stdout");
    assert!(entries(out_dir).is_empty(), "{args:?} left files behind: {:?}", entries(out_dir));
}

fn check_all_commands(f: &Path) {
    let dir = tempdir("bad");
    let fs = f.to_str().unwrap();
    let mbat = dir.join("out.mbat");
    let las = dir.join("out.las");
    let laz = dir.join("out.laz");
    expect_clean_failure(&["info", fs], f, &dir);
    expect_clean_failure(&["info", "--stats", "--json", fs], f, &dir);
    expect_clean_failure(&["sort", fs, "-o", las.to_str().unwrap()], f, &dir);
    expect_clean_failure(&["sort", fs, "-o", laz.to_str().unwrap()], f, &dir);
    expect_clean_failure(&["batch", fs, "-o", mbat.to_str().unwrap()], f, &dir);
    let png = dir.join("out.png");
    expect_clean_failure(
        &["render", fs, "-o", png.to_str().unwrap(), "--tmp-dir", dir.to_str().unwrap()],
        f,
        &dir,
    );
    expect_clean_failure(
        &[
            "batch",
            fs,
            "-o",
            mbat.to_str().unwrap(),
            "--memory",
            "64K",
            "--tmp-dir",
            dir.to_str().unwrap(),
        ],
        f,
        &dir,
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

macro_rules! bad_fixture {
    ($name:ident, $path:expr) => {
        #[test]
        fn $name() {
            let Some(data) = shared_data() else { return };
            check_all_commands(&data.join($path));
        }
    };
}

bad_fixture!(broken_coder, "LASzip/data/broken_coder.laz");
bad_fixture!(broken_compressor, "LASzip/data/broken_compressor.laz");
bad_fixture!(broken_size, "LASzip/data/broken_size.laz");
bad_fixture!(broken_type, "LASzip/data/broken_type.laz");
bad_fixture!(invalid_header_strings, "copc-validator/src/test/data/bad-ellipsoid.copc.laz");
bad_fixture!(header_count_larger_than_file, "PDAL/test/data/las/1.2-with-color-clipped.las");
bad_fixture!(header_count_no_points, "PDAL/test/data/las/permutations/1.2-no-points.las");
bad_fixture!(garbage_vlr_count, "PDAL/test/data/las/garbage_nVariableLength.las");

#[test]
fn the_bad_list_is_complete() {
    let Some(data) = shared_data() else { return };
    let readme = std::fs::read_to_string(data.join("README.md")).unwrap();
    let bad = readme.split("**Bad input").nth(1).unwrap().split("**Benchmark").next().unwrap();
    for f in BAD_INPUTS {
        let name = Path::new(f).file_name().unwrap().to_string_lossy().to_string();
        let stem = name.split('_').next().unwrap().to_string();
        assert!(bad.contains(&name) || bad.contains(&stem), "{f} is not in the README's bad list");
    }
}

/// Hostile files derived from a good one.
fn hostile(tag: &str, patch: impl Fn(&mut Vec<u8>)) -> std::path::PathBuf {
    let good = std::fs::read(root().join("data-samples/autzen_trim.laz")).unwrap();
    let mut b = good;
    patch(&mut b);
    let dir = tempdir(&format!("hostile-{tag}"));
    let p = dir.join(format!("{tag}.laz"));
    std::fs::write(&p, b).unwrap();
    p
}

#[test]
fn hostile_headers() {
    type Damage = Box<dyn Fn(&mut Vec<u8>)>;
    let cases: Vec<(&str, Damage)> = vec![
        ("not-las", Box::new(|b: &mut Vec<u8>| b[0] = b'X')),
        ("truncated-header", Box::new(|b: &mut Vec<u8>| b.truncate(100))),
        (
            "huge-count",
            Box::new(|b: &mut Vec<u8>| b[107..111].copy_from_slice(&u32::MAX.to_le_bytes())),
        ),
        ("bad-format", Box::new(|b: &mut Vec<u8>| b[104] = 0x80 | 42)),
        (
            "zero-scale",
            Box::new(|b: &mut Vec<u8>| b[131..139].copy_from_slice(&0f64.to_le_bytes())),
        ),
        (
            "truncated-points",
            Box::new(|b: &mut Vec<u8>| {
                let n = b.len() / 2;
                b.truncate(n)
            }),
        ),
        (
            "chunk-table-garbage",
            Box::new(|b: &mut Vec<u8>| {
                let n = b.len();
                b[n - 8..].copy_from_slice(&[0xff; 8]);
                let o = u32::from_le_bytes(b[96..100].try_into().unwrap()) as usize;
                b[o..o + 8].copy_from_slice(&[0xff; 8]);
            }),
        ),
        (
            "corrupt-chunk",
            Box::new(|b: &mut Vec<u8>| {
                let o = u32::from_le_bytes(b[96..100].try_into().unwrap()) as usize;
                for x in &mut b[o + 100..o + 5000] {
                    *x ^= 0x5a;
                }
            }),
        ),
    ];
    for (tag, patch) in cases {
        let p = hostile(tag, patch);
        let dir = p.parent().unwrap().to_path_buf();
        let out = dir.join("out");
        std::fs::create_dir_all(&out).unwrap();
        let mbat = out.join("o.mbat");
        let mut c = mortar();
        c.args(["batch", p.to_str().unwrap(), "-o", mbat.to_str().unwrap()]);
        let o = run_limited(c, Duration::from_secs(30));
        let err = String::from_utf8_lossy(&o.stderr);
        // A corrupt chunk may still decode to (wrong) points: LAZ has no checksum. Then it must
        // succeed cleanly; otherwise fail cleanly.
        if tag == "corrupt-chunk" && o.status.success() {
            continue;
        }
        assert_eq!(o.status.code(), Some(1), "{tag}: {err}");
        assert!(!err.contains("panicked"), "{tag}: {err}");
        assert_eq!(err.lines().count(), 1, "{tag}: {err}");
        assert!(err.contains(&format!("{tag}.laz")), "{tag}: {err}");
        assert!(entries(&out).is_empty(), "{tag}: left {:?}", entries(&out));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

#[test]
fn missing_input_and_bad_arguments() {
    let dir = tempdir("args");
    let o = mortar()
        .args(["batch", "/nonexistent/x.laz", "-o"])
        .arg(dir.join("o.mbat"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("/nonexistent/x.laz"));
    let o = mortar()
        .args(["batch", "data-samples/autzen_trim.laz", "--attributes", "nope", "-o"])
        .arg(dir.join("o.mbat"))
        .current_dir(root())
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("nope"));
    assert!(entries(&dir).is_empty());
    std::fs::remove_dir_all(&dir).unwrap();
}
