//! Paper 000's promise, checked on real scans: the converged progressive image (CPU and GPU) is
//! the brute-force image of the same points, pixel for pixel, exact depth ties aside.
//!
//! The brute force is `mortar render`'s own path: the file Morton-sorted into a temporary batch
//! file (10,240 points per batch, each in its own quantization frame) and drawn by the batch
//! rasterizer at 30 bits. The progressive renderers hold every point in one frame over the
//! headers' box and number points by shuffled slot. For every pixel the keys are compared:
//! coverage and depth must be equal; where the winning points differ, their depths are equal
//! (a tie that the smaller index decides, and the two renderers number points differently): those
//! pixels are counted and reported, nothing else may differ.

mod common;

use common::*;
use mortar_app::draw::raw::{load_pieces, LoadedPiece, Payload};
use mortar_core::quantize::Precision;
use mortar_core::render::framebuffer::{key_depth, key_index};
use mortar_core::render::framing::{IntBox, ViewBox};
use mortar_core::render::progressive::ProgressiveFrame;
use mortar_core::render::progressive::{FillBudget, ProgressiveRenderer};
use mortar_core::render::{
    rasterize, Camera, Framebuffer, PrecisionMode, RasterOptions, ViewPreset, EMPTY_KEY,
};
use mortar_io::batch_input::{self, RenderSource};
use mortar_io::batchfile::AttributeSelection;
use mortar_io::dataset::Dataset;
use mortar_io::sort::SortOptions;
use mortar_render::{AtomicPath, GpuProgressive, ProgressiveOptions};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Mutex;

/// A raw file read the way the progressive renderers read it.
struct Raw {
    ds: Dataset,
    /// The progressive renderers' first frame: around the box the framing rule frames.
    frame: ProgressiveFrame,
    /// What framed views frame (the one framing rule).
    bounds: mortar_core::render::Aabb,
    points: u64,
    pieces: Vec<LoadedPiece>,
}

fn read(path: &Path) -> Raw {
    let ds = mortar_io::inputs::open(&[path.to_path_buf()])
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let view = mortar_io::framing::view_box(&ds).unwrap();
    let pieces = Mutex::new(Vec::new());
    load_pieces(&ds, Payload::Intensity, 2, &AtomicBool::new(false), |p| {
        pieces.lock().unwrap().push(p.unwrap());
        true
    })
    .unwrap();
    let mut pieces = pieces.into_inner().unwrap();
    pieces.sort_by_key(|p| p.first);
    let all = pieces.iter().filter_map(|p| IntBox::of(&p.xyz)).reduce(IntBox::union).unwrap();
    let start = match view {
        ViewBox::Header(h) => h,
        ViewBox::Points => all,
    };
    let frame = ProgressiveFrame::around(ds.grid, start).unwrap();
    let bounds = view.bounds(&ds.grid, || all);
    let points = pieces.iter().map(|p| p.xyz.len() as u64).sum();
    Raw { ds, frame, bounds, points, pieces }
}

/// Every pixel's key and, for covered pixels, the integer position of the winning point.
struct Image {
    keys: Vec<u64>,
    positions: Vec<Option<[i32; 3]>>,
}

const FULL: RasterOptions =
    RasterOptions { precision: PrecisionMode::Fixed(Precision::Bits30), cull: true };

/// The brute force of `mortar render`: a temporary batch file, drawn at 30 bits.
fn brute_force(raw: &Raw, cam: &Camera, tmp: &Path) -> Image {
    let opts = SortOptions::with_memory(1 << 30, tmp.to_path_buf());
    let source =
        RenderSource::batch_dataset(&raw.ds, &opts, &AttributeSelection::Only(vec![])).unwrap();
    let file = &source.file;
    let views = batch_input::load_words(file).unwrap();
    let refs = batch_input::batch_refs(file, &views).unwrap();
    let fb = Framebuffer::new(cam.width, cam.height);
    rasterize(&fb, &refs, &file.grid(), cam, &FULL).unwrap();
    let keys = fb.into_keys();
    let mut by_index = vec![[0i32; 3]; file.header.point_count as usize];
    for b in &refs {
        for k in 0..b.len() {
            by_index[b.first_index as usize + k] =
                b.grid.decode_exact([b.words[0][k], b.words[1][k], b.words[2][k]]);
        }
    }
    let positions =
        keys.iter().map(|&k| (k != EMPTY_KEY).then(|| by_index[key_index(k) as usize])).collect();
    Image { keys, positions }
}

/// Converged keys of the CPU progressive renderer, and its count of tied pixels.
fn progressive_cpu(raw: &Raw, cam: &Camera) -> (Image, u64, u32) {
    let mut r = ProgressiveRenderer::with_frame(raw.frame, raw.points).unwrap();
    for p in &raw.pieces {
        r.insert(p.first, &p.xyz, &p.payload).unwrap();
    }
    let budget = FillBudget::Fixed(raw.points.div_ceil(3));
    while !r.frame(cam, &FULL, &budget).unwrap().converged {}
    let keys = r.keys();
    let positions =
        keys.iter().map(|&k| (k != EMPTY_KEY).then(|| r.position(key_index(k)).unwrap())).collect();
    (Image { keys, positions }, r.depth_ties().unwrap().unwrap(), r.growths())
}

/// Converged keys of the GPU progressive renderer and its count of tied pixels (`None` without a
/// 64-bit GPU).
fn progressive_gpu(raw: &Raw, cam: &Camera) -> Option<(Vec<u64>, u64)> {
    let ctx = mortar_render::testing::context_or_skip(AtomicPath::U64, None)?;
    let mut r =
        GpuProgressive::with_frame(&ctx, raw.frame, raw.points, ProgressiveOptions::default())
            .unwrap();
    for p in &raw.pieces {
        r.insert(&ctx, p.first, &p.xyz, None, None).unwrap();
    }
    let budget = FillBudget::Fixed(raw.points.div_ceil(3));
    while !r.frame(&ctx, cam, &FULL, &budget, None).unwrap().stats.converged {}
    Some((r.read_keys(&ctx).unwrap(), r.depth_ties(&ctx).unwrap().unwrap()))
}

/// How two images of the same points differ.
#[derive(Debug, Default, Clone, Copy, PartialEq)]
struct Comparison {
    covered: usize,
    /// Pixels covered in one image only, or with another depth.
    moved: usize,
    /// Pixels with the same depth but another point: exact depth ties.
    ties: usize,
    /// Pixels showing another point (or covered in one image only), for whatever reason.
    other_point: usize,
}

fn compare(a: &Image, b: &Image) -> Comparison {
    let mut c = Comparison::default();
    for p in 0..a.keys.len() {
        let (ka, kb) = (a.keys[p], b.keys[p]);
        if ka != EMPTY_KEY {
            c.covered += 1;
        }
        if a.positions[p] != b.positions[p] {
            c.other_point += 1;
        }
        if (ka == EMPTY_KEY) != (kb == EMPTY_KEY)
            || (ka != EMPTY_KEY && key_depth(ka) != key_depth(kb))
        {
            c.moved += 1;
        } else if a.positions[p] != b.positions[p] {
            c.ties += 1;
        }
    }
    c
}

/// The views compared: framed overviews (perspective and orthographic) and a close-up.
fn cameras(raw: &Raw, w: u32, h: u32) -> Vec<(&'static str, Camera)> {
    let b = raw.bounds;
    let fov = 50f64.to_radians();
    vec![
        ("iso", Camera::frame_perspective(&b, ViewPreset::Iso, fov, w, h).unwrap()),
        ("top-ortho", Camera::frame_orthographic(&b, ViewPreset::Top, w, h).unwrap()),
        ("closeup", Camera::close_up(&b, fov, w, h).unwrap()),
    ]
}

/// The real scans: the shipped sample and files of `../shared/data` (one of them, the lion, has a
/// header whose z minimum is 1 cm above its lowest points).
fn scans() -> Vec<PathBuf> {
    let mut v = vec![root().join("data-samples/autzen_trim.laz")];
    if let Some(d) = shared_data() {
        for f in [
            "lidR/inst/extdata/Megaplot.laz",
            "laserchicken/testdata/AHN3.laz",
            "potree/pointclouds/lion_takanawa.copc.laz",
            "PDAL/test/data/ept/source/lone-star.laz",
        ] {
            v.push(d.join(f));
        }
    }
    v
}

/// `path` copied to `dir` with its header's x maximum 10 % short of the points and its z maximum
/// 3 m below them (a header that lies, as older files' often do; `mortar info --stats` warns).
fn lying_copy(path: &Path, dir: &Path) -> PathBuf {
    let mut bytes = std::fs::read(path).unwrap();
    let f = |b: &[u8], at: usize| f64::from_le_bytes(b[at..at + 8].try_into().unwrap());
    let (max_x, min_x, max_z) = (f(&bytes, 179), f(&bytes, 187), f(&bytes, 211));
    bytes[179..187].copy_from_slice(&(max_x - 0.1 * (max_x - min_x)).to_le_bytes());
    bytes[211..219].copy_from_slice(&(max_z - 3.0).to_le_bytes());
    let out = dir.join(format!("lying-{}", path.file_name().unwrap().to_str().unwrap()));
    std::fs::write(&out, bytes).unwrap();
    out
}

/// `path` (LAZ) copied to `dir` with its header's box shrunk to `lo..hi`.
fn with_header_box(path: &Path, dir: &Path, name: &str, lo: [f64; 3], hi: [f64; 3]) -> PathBuf {
    let mut bytes = std::fs::read(path).unwrap();
    for a in 0..3 {
        bytes[187 + 16 * a..195 + 16 * a].copy_from_slice(&lo[a].to_le_bytes());
        bytes[179 + 16 * a..187 + 16 * a].copy_from_slice(&hi[a].to_le_bytes());
    }
    let out = dir.join(name);
    std::fs::write(&out, bytes).unwrap();
    out
}

#[test]
fn converged_progressive_equals_the_brute_force_up_to_counted_ties() {
    let tmp = tempdir("progressive-exact");
    let mut files: Vec<(PathBuf, &str)> = scans().into_iter().map(|p| (p, "as is")).collect();
    let sample = files[0].0.clone();
    files.push((lying_copy(&sample, &tmp), "lying"));
    // Half the points 10 km from the header's box (the first LAZ chunk's): the frame grows.
    let las = tmp.join("x.las");
    run_ok(mortar().arg("sort").arg(&sample).arg("-o").arg(&las));
    let far = tmp.join("far.laz");
    run_ok(mortar().arg("sort").arg(twice_apart(&las, &tmp.join("twice.las"))).arg("-o").arg(&far));
    let (lo, hi) = first_piece_box(&far);
    files.push((with_header_box(&far, &tmp, "grows.laz", lo, hi), "grows"));
    // A header a metre wide, away from the points: the points' box is framed.
    let (lo, _) = first_piece_box(&sample);
    let off = [lo[0] - 5000.0, lo[1], lo[2]];
    files.push((
        with_header_box(
            &sample,
            &tmp,
            "nowhere.laz",
            off,
            [off[0] + 1.0, off[1] + 1.0, off[2] + 1.0],
        ),
        "points",
    ));
    let (mut pixels, mut tied, mut counted) = (0, 0, 0);
    for (path, what) in files {
        let raw = read(&path);
        for (name, cam) in cameras(&raw, 480, 360) {
            let want = brute_force(&raw, &cam, &tmp);
            let (got, ties, growths) = progressive_cpu(&raw, &cam);
            let c = compare(&got, &want);
            eprintln!("{} ({what}) {name}: {} covered pixels, {} differ, all exact depth ties; {ties} tied pixels counted", path.display(), c.covered, c.ties);
            assert!(c.covered > 2_000, "{} {name}: {c:?}", path.display());
            assert_eq!(
                c.moved,
                0,
                "{} {name}: pixels differ beyond exact depth ties: {c:?}",
                path.display()
            );
            assert_eq!(c.other_point, c.ties);
            assert!(
                c.ties as u64 <= ties,
                "{} {name}: {} ties seen, {ties} counted",
                path.display(),
                c.ties
            );
            assert_eq!(
                growths >= 1,
                what == "grows",
                "{} {name}: {growths} growths",
                path.display()
            );
            // The GPU twin leaves the CPU renderer's keys and counts the same ties.
            if let Some((keys, gpu_ties)) = progressive_gpu(&raw, &cam) {
                assert!(
                    keys == got.keys,
                    "{} {name}: GPU keys differ from the CPU's in {} pixels",
                    path.display(),
                    keys.iter().zip(&got.keys).filter(|(a, b)| a != b).count()
                );
                assert_eq!(gpu_ties, ties, "{} {name}", path.display());
            }
            pixels += c.covered;
            tied += c.ties;
            counted += ties;
        }
    }
    eprintln!("{tied} pixels differ, all of them exact depth ties ({counted} tied pixels counted), in {pixels} covered pixels");
}
