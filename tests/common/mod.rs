//! Helpers for the end-to-end tests: run the built binaries, find the shared fixtures, read
//! LAS files with the las crate (an implementation independent of mortar's own reader).
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

pub fn mortar() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mortar"))
}

pub fn gen() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mortar-gen"))
}

pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `../shared/data` (or `$MORTAR_TEST_DATA`), if present.
pub fn shared_data() -> Option<PathBuf> {
    let p = std::env::var_os("MORTAR_TEST_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join("../shared/data"));
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("SKIP: no shared fixtures at {} (set MORTAR_TEST_DATA)", p.display());
        None
    }
}

/// The bad inputs listed in `../shared/data/README.md`, less the one that is valid: the README
/// lists `PDAL/test/data/apps/simple-laszip-compressor-version-1.2r0.laz` ("old LASzip layout
/// without chunk table"), a valid file of LASzip's pointwise compressor that PDAL and LAStools
/// read (`tests/old_laz.rs`).
pub const BAD_INPUTS: &[&str] = &[
    "LASzip/data/broken_coder.laz",
    "LASzip/data/broken_compressor.laz",
    "LASzip/data/broken_size.laz",
    "LASzip/data/broken_type.laz",
    "copc-validator/src/test/data/bad-ellipsoid.copc.laz",
    "PDAL/test/data/las/1.2-with-color-clipped.las",
    "PDAL/test/data/las/permutations/1.2-no-points.las",
    "PDAL/test/data/las/garbage_nVariableLength.las",
];

/// The file an independent reader reads in place of fixture `p`: laspy's lazrs (laz-rs 0.12)
/// panics on LAZ of LASzip's pointwise compressor ("Variable-size chunks, but no chunk table"),
/// so checks that read inputs with laspy read its uncompressed twin, which holds the same
/// points (`tests/old_laz.rs` checks that through mortar and the las crate).
pub fn laspy_twin(p: &Path) -> PathBuf {
    let s = p.to_string_lossy();
    match s.strip_suffix("PDAL/test/data/apps/simple-laszip-compressor-version-1.2r0.laz") {
        Some(dir) => PathBuf::from(format!("{dir}PDAL/test/data/apps/simple.las")),
        None => p.to_path_buf(),
    }
}

/// Every readable LAS/LAZ fixture (every 8th file of the 290-file EPT set).
pub fn readable_fixtures(data: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    walk(data, &mut out);
    out.sort();
    let mut ept = 0;
    out.retain(|p| {
        let rel = p.strip_prefix(data).unwrap().to_string_lossy().to_string();
        if BAD_INPUTS.contains(&rel.as_str()) {
            return false;
        }
        if rel.contains("PyForestScan/example_data/ept/ept-data/") {
            ept += 1;
            return ept % 8 == 1;
        }
        true
    });
    out
}

fn walk(d: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(d).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            walk(&p, out);
        } else if matches!(p.extension().and_then(|e| e.to_str()), Some("las" | "laz")) {
            out.push(p);
        }
    }
}

/// Runs a command with a time limit; kills it and panics when it runs over. Its output is read
/// while it runs (a child writing more than a pipe holds would otherwise wait forever).
pub fn run_limited(mut c: Command, limit: Duration) -> Output {
    use std::io::Read;
    c.stdout(Stdio::piped()).stderr(Stdio::piped());
    let mut child = c.spawn().expect("spawn");
    let drain = |r: Option<Box<dyn Read + Send>>| {
        std::thread::spawn(move || {
            let mut v = Vec::new();
            if let Some(mut r) = r {
                let _ = r.read_to_end(&mut v);
            }
            v
        })
    };
    let out = drain(child.stdout.take().map(|r| Box::new(r) as Box<dyn Read + Send>));
    let err = drain(child.stderr.take().map(|r| Box::new(r) as Box<dyn Read + Send>));
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            let (stdout, stderr) = (out.join().unwrap(), err.join().unwrap());
            return Output { status, stdout, stderr };
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            panic!("command ran past {limit:?}: {c:?}");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

pub fn run_ok(c: &mut Command) -> Output {
    let o = c.output().expect("spawn");
    assert!(o.status.success(), "{c:?} failed: {}", String::from_utf8_lossy(&o.stderr));
    o
}

/// Raw point records and header of a LAS/LAZ file, read by the las crate.
pub fn las_records(p: &Path) -> Result<(Vec<u8>, usize, las::Header), String> {
    let mut r = las::Reader::from_path(p).map_err(|e| e.to_string())?;
    let header = r.header().clone();
    let pd = r.read_all().map_err(|e| e.to_string())?;
    Ok((pd.raw_bytes().to_vec(), pd.record_len(), header))
}

/// The records as a sorted list (a multiset).
pub fn multiset(bytes: &[u8], rl: usize) -> Vec<&[u8]> {
    let mut v: Vec<&[u8]> = bytes.chunks_exact(rl).collect();
    v.sort_unstable();
    v
}

pub fn tempdir(tag: &str) -> PathBuf {
    static N: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let d = std::env::temp_dir().join(format!("mortar-test-{tag}-{}-{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Files left in a directory.
pub fn entries(d: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(d)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// The Python with laspy and lazrs (`$MORTAR_PYTHON`, else `python3`); `None` (after a SKIP line)
/// when there is none, unless `MORTAR_REQUIRE_PYTHON=1`, which makes that a failure.
pub fn laspy_python() -> Option<PathBuf> {
    let py = std::env::var_os("MORTAR_PYTHON").map(PathBuf::from).unwrap_or_else(|| {
        let venv = root().join(".ci-venv/bin/python");
        if venv.exists() {
            venv
        } else {
            PathBuf::from("python3")
        }
    });
    let ok = std::process::Command::new(&py)
        .args(["-c", "import laspy, lazrs"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if ok {
        return Some(py);
    }
    if std::env::var("MORTAR_REQUIRE_PYTHON").as_deref() == Ok("1") {
        panic!("MORTAR_REQUIRE_PYTHON=1 but {} cannot import laspy and lazrs", py.display());
    }
    eprintln!("SKIP: no Python with laspy and lazrs (set MORTAR_PYTHON)");
    None
}

/// `las` (LAS 1.2, as `mortar sort` writes the sample) with its points twice, the second time
/// 10 km east (10^6 grid units of 1 cm), written to `out` with a true header.
pub fn twice_apart(las: &Path, out: &Path) -> PathBuf {
    let b = std::fs::read(las).unwrap();
    let u32_at = |at: usize| u32::from_le_bytes(b[at..at + 4].try_into().unwrap());
    let (start, rl, n) =
        (u32_at(96) as usize, u16::from_le_bytes([b[105], b[106]]) as usize, u32_at(107));
    let mut h = b[..start].to_vec();
    h[107..111].copy_from_slice(&(2 * n).to_le_bytes());
    for k in 0..5 {
        let at = 111 + 4 * k;
        h[at..at + 4].copy_from_slice(&(2 * u32_at(at)).to_le_bytes());
    }
    let scale_x = f64::from_le_bytes(b[131..139].try_into().unwrap());
    let max_x = f64::from_le_bytes(b[179..187].try_into().unwrap());
    h[179..187].copy_from_slice(&(max_x + 1e6 * scale_x).to_le_bytes());
    let records = &b[start..start + n as usize * rl];
    let mut moved = records.to_vec();
    for r in moved.chunks_exact_mut(rl) {
        let x = i32::from_le_bytes(r[..4].try_into().unwrap()) + 1_000_000;
        r[..4].copy_from_slice(&x.to_le_bytes());
    }
    std::fs::write(out, [&h[..], records, &moved].concat()).unwrap();
    out.to_path_buf()
}

/// The box of the points of the first piece of `las` (world coordinates), as the framing rule
/// reads it.
pub fn first_piece_box(las: &Path) -> ([f64; 3], [f64; 3]) {
    let ds = mortar_io::inputs::open(&[las.to_path_buf()]).unwrap();
    let first = mortar_io::framing::first_points(&ds).unwrap();
    let b = mortar_core::render::framing::IntBox::of(&first).unwrap().world(&ds.grid);
    (b.min, b.max)
}

/// Generated inputs whose partition cells are denser than a unit under 1 MiB (units of about
/// 4,500 points; leaves of 3,000): points at one position (alone: the root is one leaf; and
/// merged into a scan: a chain of inner nodes down to a leaf beyond the size limit), a cube of
/// 30 units (many positions in leaves too narrow to split, sorted in parts) alone and merged
/// into a scan on the same grid.
pub fn dense_sets(dir: &Path) -> Vec<Vec<PathBuf>> {
    let g = |name: &str, args: &[&str]| {
        let p = dir.join(name);
        run_ok(gen().args(args).arg("-o").arg(&p));
        p
    };
    let coincident = g("coincident.las", &["--points", "60000", "--shape", "coincident"]);
    let scan = g("scan.las", &["--points", "40000", "--seed", "3"]);
    let cube = g(
        "cube30.las",
        &["--points", "80000", "--shape", "cube", "--scale", "1", "--extent", "30"],
    );
    let scan1 = g("scan1.las", &["--points", "40000", "--seed", "4", "--scale", "1"]);
    let dups = g(
        "dups.las",
        &["--points", "80000", "--shape", "duplicates", "--scale", "1", "--extent", "200"],
    );
    vec![
        vec![coincident.clone()],
        vec![scan, coincident],
        vec![cube.clone()],
        vec![scan1, cube],
        vec![dups],
    ]
}

/// The four bcts tiles of lasR (real airborne LAZ, 2.83 M points together) that exist.
pub fn bcts_tiles(data: &Path) -> Vec<PathBuf> {
    (1..=4)
        .map(|i| data.join(format!("lasR/inst/extdata/bcts/bcts_{i}.laz")))
        .filter(|p| p.exists())
        .collect()
}

/// The first `n` files (by name) of PyForestScan's EPT tile (290 small real LAZ files).
pub fn ept_tiles(data: &Path, n: usize) -> Vec<PathBuf> {
    let dir = data.join("PyForestScan/example_data/ept/ept-data");
    let mut ept: Vec<PathBuf> =
        std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    ept.sort();
    ept.truncate(n);
    ept
}

/// The options the library-level store tests build the sample with: leaves of 2,000 points,
/// first-come voxels, batches of 10,000 points, a commit after every batch or level, 1 GiB of
/// memory, with `engine`.
pub fn small_build_options(engine: mortar_io::store::Engine) -> mortar_io::store::BuildOptions {
    use mortar_core::octree::{BuilderConfig, ColorMode};
    mortar_io::store::BuildOptions {
        config: BuilderConfig {
            leaf_capacity: 2000,
            color_mode: ColorMode::FirstCome,
            ..BuilderConfig::default()
        },
        batch_points: 10_000,
        first_commit_after: None,
        commit_every: 0.0,
        memory: 1 << 30,
        engine,
        resume: false,
        tree: None,
    }
}
