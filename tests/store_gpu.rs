//! Issue 29: `mortar build --engine gpu` (SimLOD's passes on the GPU, `mortar_render::octree`)
//! writes the store `--engine sorted` writes, byte for byte: the same hierarchy, the same
//! payloads, the same source header. On every real file, on merged tiles and on hostile density
//! (points at one position, duplicates, cells denser than the grid). Runs on lavapipe in CI
//! (`MORTAR_REQUIRE_GPU`); skips with a printed reason where no adapter exists at all.

mod common;

use common::*;
use std::path::{Path, PathBuf};

/// Whether a GPU engine build failed only because there is no adapter (a skip outside CI).
fn no_adapter(stderr: &str) -> bool {
    stderr.contains("no GPU adapter") && std::env::var_os("MORTAR_REQUIRE_GPU").is_none()
}

/// Builds `inputs` into `out` with `engine`: the JSON report, or the error output.
fn build(
    inputs: &[PathBuf],
    out: &Path,
    engine: &str,
    extra: &[&str],
) -> Result<serde_json::Value, String> {
    build_sorting(inputs, out, engine, extra, false)
}

/// [`build`], with the GPU's radix sort on any adapter where `gpu_sort` (lavapipe keeps the
/// host's sort by default: it is faster there).
fn build_sorting(
    inputs: &[PathBuf],
    out: &Path,
    engine: &str,
    extra: &[&str],
    gpu_sort: bool,
) -> Result<serde_json::Value, String> {
    let o = mortar()
        .env("MORTAR_GPU_SORT", if gpu_sort { "1" } else { "" })
        .arg("build")
        .args(inputs)
        .arg("-o")
        .arg(out)
        .args(["--engine", engine, "--json", "--quiet"])
        .args(extra)
        .output()
        .unwrap();
    if o.status.success() {
        Ok(serde_json::from_slice(&o.stdout).unwrap())
    } else {
        assert_eq!(o.status.code(), Some(1), "{}", String::from_utf8_lossy(&o.stderr));
        assert!(!out.exists(), "a failed build left {}", out.display());
        Err(String::from_utf8_lossy(&o.stderr).to_string())
    }
}

/// The store's files but build.json (which names the engine).
fn store_files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().unwrap() != "build.json")
        .map(|p| (p.file_name().unwrap().to_string_lossy().to_string(), std::fs::read(&p).unwrap()))
        .collect();
    v.sort();
    v
}

/// Builds `inputs` with both engines; `Some(true)` when both built the same store, `Some(false)`
/// when both refused the input, `None` when there is no GPU adapter (skip).
fn same_store(inputs: &[PathBuf], extra: &[&str], tag: &str) -> Option<bool> {
    same_store_sorting(inputs, extra, tag, false)
}

/// [`same_store`], the GPU engine sorting on the GPU (any adapter) where `gpu_sort`.
fn same_store_sorting(
    inputs: &[PathBuf],
    extra: &[&str],
    tag: &str,
    gpu_sort: bool,
) -> Option<bool> {
    let dir = tempdir(tag);
    let (a, b) = (dir.join("sorted"), dir.join("gpu"));
    let name = inputs
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().to_string())
        .collect::<Vec<_>>()
        .join(" + ");
    let ra = build(inputs, &a, "sorted", extra);
    let rb = build_sorting(inputs, &b, "gpu", extra, gpu_sort);
    let out = match (&ra, &rb) {
        (_, Err(e)) if no_adapter(e) => {
            eprintln!("SKIPPED: {e}");
            None
        }
        (Err(_), Err(_)) => Some(false),
        (Ok(ja), Ok(jb)) => {
            assert_eq!(jb["engine"], "gpu", "{jb}");
            assert_eq!(ja["points"], jb["points"], "{name}");
            let (fa, fb) = (store_files(&a), store_files(&b));
            assert_eq!(
                fa.iter().map(|f| &f.0).collect::<Vec<_>>(),
                fb.iter().map(|f| &f.0).collect::<Vec<_>>(),
                "{name}: files"
            );
            for (x, y) in fa.iter().zip(&fb) {
                assert!(
                    x.1 == y.1,
                    "{name}: {} differs between the sorted and the GPU engine",
                    x.0
                );
            }
            Some(true)
        }
        _ => panic!("{name}: one engine failed: sorted {ra:?}, gpu {rb:?}"),
    };
    let _ = std::fs::remove_dir_all(&dir);
    out
}

#[test]
fn the_gpu_engine_writes_the_sorted_engines_store_on_the_sample_and_every_real_file() {
    let sample = root().join("data-samples/autzen_trim.laz");
    for (cap, gpu_sort) in [("50000", false), ("500", false), ("500", true)] {
        let one = std::slice::from_ref(&sample);
        let Some(same) = same_store_sorting(one, &["--leaf-capacity", cap], "gpu-sample", gpu_sort)
        else {
            return;
        };
        assert!(same);
    }
    let Some(data) = shared_data() else { return };
    let files = readable_fixtures(&data);
    assert!(files.len() > 40, "{} fixtures", files.len());
    let mut built = 0;
    for (i, f) in files.iter().enumerate() {
        // Small leaves: deep trees with many inner nodes even on small files; every third file
        // sorted by the GPU's radix sort.
        let cap = if i % 2 == 0 { "3000" } else { "200" };
        let (one, tag) = (std::slice::from_ref(f), format!("gpu-{i}"));
        if same_store_sorting(one, &["--leaf-capacity", cap], &tag, i % 3 == 0) == Some(true) {
            built += 1;
        }
    }
    assert!(built * 10 >= files.len() * 8, "{built} of {} built by both", files.len());
}

#[test]
fn the_gpu_engine_writes_the_sorted_engines_store_on_merged_tiles() {
    let Some(data) = shared_data() else { return };
    let bcts = bcts_tiles(&data);
    assert!(bcts.len() >= 2);
    if same_store(&bcts, &["--leaf-capacity", "2000"], "gpu-bcts").is_none() {
        return;
    }
    assert_eq!(
        same_store_sorting(&bcts, &["--leaf-capacity", "2000"], "gpu-bcts-s", true),
        Some(true)
    );
    // Within 32 MiB of GPU memory: segments of 524,288 points, two on the GPU at a time, the
    // others paged out and back; one voxel grid at a time.
    assert_eq!(
        same_store(&bcts, &["--leaf-capacity", "20000", "--gpu-memory", "32M"], "gpu-bcts-paged"),
        Some(true)
    );
    // Copies of one real tile, paged: every point has twins in other segments, so the first
    // come voxels of the leaf-order walk must be decided by arrival number alone.
    let autzen = data.join("PDAL/test/data/las/autzen_trim.las");
    if autzen.exists() {
        let copies = vec![autzen; 12];
        assert_eq!(
            same_store(&copies, &["--leaf-capacity", "200", "--gpu-memory", "32M"], "gpu-twins"),
            Some(true)
        );
    }
    let dir = tempdir("gpu-small-budget");
    let e = build(&bcts, &dir.join("s"), "gpu", &["--gpu-memory", "1M"]).unwrap_err();
    assert!(e.contains("--gpu-memory") && !e.contains("panicked"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
    let ept = ept_tiles(&data, 60);
    assert_eq!(same_store(&ept, &[], "gpu-ept"), Some(true));
}

#[test]
fn the_gpu_engine_writes_the_sorted_engines_store_on_hostile_density() {
    let dir = tempdir("gpu-dense");
    for (k, set) in dense_sets(&dir).iter().enumerate() {
        let tag = format!("gpu-dense-{k}");
        match same_store_sorting(set, &["--leaf-capacity", "3000"], &tag, k % 2 == 0) {
            None => return,
            Some(same) => assert!(same, "{set:?}"),
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_gpu_engine_refuses_averaged_colours_clearly() {
    let dir = tempdir("gpu-averaged");
    let sample = root().join("data-samples/autzen_trim.laz");
    let e = build(&[sample], &dir.join("s"), "gpu", &["--averaged-colors"]).unwrap_err();
    assert!(e.contains("first-come") && !e.contains("panicked"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_gpu_engine_keeps_the_memory_promise() {
    // `--memory` is a promise: an input whose records do not fit it is refused before anything
    // is read or written, with the need named (the GPU engine holds the input as the sorted
    // engine does).
    let dir = tempdir("gpu-memory-promise");
    let las = dir.join("g4.las");
    run_ok(gen().args(["--points", "4000000", "--seed", "5"]).arg("-o").arg(&las));
    let e = build(std::slice::from_ref(&las), &dir.join("s"), "gpu", &["--memory", "256M"])
        .unwrap_err();
    assert!(e.contains("--memory") && e.contains("GPU engine") && !e.contains("panicked"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A tree backend that builds with the CPU twin of the GPU passes, then spoils the tree as a
/// faulty GPU might; as a discrete GPU (the engine then sorts on the host while it builds) where
/// the flag says so, else as one whose buffers are host memory (one after the other); where the
/// third says so it sorts the points itself (the CPU twin of the GPU's sort), an order that the
/// "order-" faults spoil.
#[derive(Debug)]
struct Faulty(&'static str, bool, bool);

impl mortar_core::octree::arrival::TreeBackend for Faulty {
    fn name(&self) -> String {
        format!("cpu twin, {}", self.0)
    }

    fn holds_buffers_in_host_memory(&self) -> bool {
        !self.1
    }

    fn sorts(&self, _n: usize) -> bool {
        self.2
    }

    fn build_ordered(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &mortar_core::octree::BuilderConfig,
        order: &dyn Fn(Vec<u32>),
    ) -> Result<mortar_core::octree::arrival::ArrivalTree, String> {
        let mut o = mortar_core::octree::arrival::morton_order(pos);
        match self.0 {
            "order-swapped" => o.swap(100, 101),
            "order-short" => {
                o.pop();
            }
            "order-repeated" => o[7] = o[8],
            _ => {}
        }
        order(o);
        self.build_without_slots(size_log2, pos, config)
    }

    fn build(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &mortar_core::octree::BuilderConfig,
    ) -> Result<mortar_core::octree::arrival::ArrivalTree, String> {
        use mortar_core::octree::arrival::{CpuArrival, NO_CHILD};
        let mut t = CpuArrival.build(size_log2, pos, config)?;
        // The leaves depth first.
        let mut leaves = Vec::new();
        let mut stack = vec![0usize];
        while let Some(i) = stack.pop() {
            match t.nodes[i].first_child {
                NO_CHILD => leaves.push(i),
                c => stack.extend((0..8).rev().map(|o| c as usize + o)),
            }
        }
        match self.0 {
            "none" | "order-swapped" | "order-short" | "order-repeated" => {}
            // A point counted in the next leaf: the counts add up, the ranges are wrong.
            "moved" => {
                let k = (0..leaves.len() - 1).find(|&k| t.nodes[leaves[k]].count > 0).unwrap();
                t.nodes[leaves[k]].count -= 1;
                t.nodes[leaves[k + 1]].count += 1;
            }
            "extra" => t.nodes[leaves[0]].count += 1,
            "voxel" => t.voxels[0][0] = pos.len() as u32,
            // A leaf made the parent of the root's children.
            "shared" => t.nodes[leaves[0]].first_child = t.nodes[0].first_child,
            _ => unreachable!(),
        }
        Ok(t)
    }
}

#[test]
fn the_gpu_engine_writes_the_sorted_store_from_a_correct_tree_and_refuses_a_spoilt_one() {
    use mortar_io::store::{build, BuildOptions, Engine};
    // Needs no GPU: the engine's host side around a backend, the CPU twin of the passes.
    let dir = tempdir("gpu-faulty");
    let ds = mortar_io::inputs::open(&[root().join("data-samples/autzen_trim.laz")]).unwrap();
    let opts = |engine, tree: Option<Faulty>| BuildOptions {
        tree: tree.map(|t| std::sync::Arc::new(t) as _),
        ..small_build_options(engine)
    };
    let sorted = dir.join("sorted");
    build(&ds, &sorted, &opts(Engine::Sorted, None), &mut |_| {}).unwrap();
    for (discrete, sorts) in [(false, false), (true, false), (false, true), (true, true)] {
        let good = dir.join(format!("good-{discrete}-{sorts}"));
        let backend = Faulty("none", discrete, sorts);
        let r = build(&ds, &good, &opts(Engine::Gpu, Some(backend)), &mut |_| {}).unwrap();
        assert_eq!(r.engine, mortar_io::store::BuiltBy::Gpu);
        assert_eq!(store_files(&sorted), store_files(&good), "discrete {discrete}, sorts {sorts}");
    }
    let faults =
        ["moved", "extra", "voxel", "shared", "order-swapped", "order-short", "order-repeated"];
    for (k, fault) in faults.into_iter().enumerate() {
        let out = dir.join(fault);
        // The tree's faults with either sort, the order's with the backend's.
        let backend = Faulty(fault, k % 2 == 0, fault.starts_with("order") || k % 3 == 0);
        let e = build(&ds, &out, &opts(Engine::Gpu, Some(backend)), &mut |_| {})
            .expect_err(fault)
            .to_string();
        assert!(e.contains("GPU") && e.contains("broken"), "{fault}: {e}");
        assert!(!out.exists(), "{fault}: a refused build left {}", out.display());
    }
    let _ = std::fs::remove_dir_all(&dir);
}
