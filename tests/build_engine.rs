//! Issue 13: the sorted build engine builds the tree the incremental engine builds (same nodes,
//! same points in every leaf, same voxel points in every inner node) on every real file of
//! `../shared/data`, alone and merged; its stores are readable at every commit (the tree top
//! down, one level per commit) and hold each node once. The partitioned engine (inputs larger
//! than `--memory`) writes the sorted engine's store: the same entries and the same payload
//! bytes, node for node, on every real file and on merged tiles, with budgets that split the
//! input into many units.

mod common;

use common::*;
use mortar_io::store::{Store, LEAF};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Every node of a store: key -> (leaf, its records sorted), records rebuilt from the payload
/// (decoded position + the attribute bytes).
/// Node key -> (leaf, its records sorted).
type Nodes = BTreeMap<(u32, [u32; 3]), (bool, Vec<Vec<u8>>)>;

fn nodes_of(dir: &Path) -> (mortar_core::octree::Cube, Nodes) {
    let s = Store::open(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    let mut out = BTreeMap::new();
    for (i, e) in s.entries.iter().enumerate() {
        let d = s.node(i);
        let g = d.grid();
        let al = d.header.attr_len as usize;
        let mut recs: Vec<Vec<u8>> = (0..d.header.count as usize)
            .map(|k| {
                let p = g.decode_exact([d.words[0][k], d.words[1][k], d.words[2][k]]);
                let mut r: Vec<u8> = p.iter().flat_map(|v| v.to_le_bytes()).collect();
                r.extend_from_slice(&d.attributes[k * al..(k + 1) * al]);
                r
            })
            .collect();
        recs.sort();
        let old = out.insert((e.level, e.index), (e.kind == LEAF, recs));
        assert!(old.is_none(), "{}: node {:?} twice", dir.display(), (e.level, e.index));
    }
    (s.root_cube(), out)
}

fn build(
    inputs: &[PathBuf],
    out: &Path,
    engine: &str,
    extra: &[&str],
) -> Result<serde_json::Value, String> {
    let mut c = mortar();
    c.arg("build")
        .args(inputs)
        .arg("-o")
        .arg(out)
        .args(["--engine", engine, "--json", "--leaf-capacity", "3000", "--batch-points", "20000"])
        .args(extra);
    let o = c.output().unwrap();
    if o.status.success() {
        Ok(serde_json::from_slice(&o.stdout).unwrap())
    } else {
        Err(String::from_utf8_lossy(&o.stderr).to_string())
    }
}

/// Builds `inputs` with both engines and compares the stores; returns whether the trees were
/// compared node by node (false when the headers lie: the incremental engine grows its root
/// from the first batch's, the sorted engine starts from the points' box).
fn same_tree(inputs: &[PathBuf], tag: &str) -> bool {
    let dir = tempdir(tag);
    let (a, b) = (dir.join("sorted"), dir.join("incremental"));
    let ra = build(inputs, &a, "sorted", &[]);
    let rb = build(inputs, &b, "incremental", &[]);
    let name = inputs
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().to_string())
        .collect::<Vec<_>>()
        .join(" + ");
    match (&ra, &rb) {
        (Err(x), Err(y)) => {
            // Refused alike (same one-line error).
            // The message names the first node that failed, which depends on the order of work.
            let last = |e: &str, d: &Path| {
                let l = e.lines().last().unwrap_or("").replace(&d.display().to_string(), "STORE");
                l.split(' ')
                    .filter(|w| !(w.starts_with('r') && w[1..].chars().all(|c| c.is_ascii_digit())))
                    .collect::<Vec<_>>()
                    .join(" ")
            };
            assert_eq!(last(x, &a), last(y, &b), "{name}");
            let _ = std::fs::remove_dir_all(&dir);
            return true;
        }
        (Ok(_), Ok(_)) => {}
        _ => panic!("{name}: one engine failed: sorted {ra:?}, incremental {rb:?}"),
    }
    let (ja, jb) = (ra.unwrap(), rb.unwrap());
    assert_eq!(ja["engine"], "sorted");
    assert_eq!(jb["engine"], "incremental");
    assert_eq!(ja["points"], jb["points"], "{name}");
    let (root_a, na) = nodes_of(&a);
    let (root_b, nb) = nodes_of(&b);
    let compared = root_a == root_b;
    if compared {
        assert_eq!(na.len(), nb.len(), "{name}: node count");
        for (k, (leaf, recs)) in &na {
            let (leaf_b, recs_b) =
                nb.get(k).unwrap_or_else(|| panic!("{name}: node {k:?} only in the sorted store"));
            assert_eq!(leaf, leaf_b, "{name}: kind of {k:?}");
            assert!(
                recs == recs_b,
                "{name}: points of node {k:?} ({} vs {})",
                recs.len(),
                recs_b.len()
            );
        }
        // The sorted engine writes every node once.
        let s = Store::open(&a).unwrap();
        let live: u64 = s.entries.iter().map(|e| e.length).sum();
        assert_eq!(live, s.header.nodes_len, "{name}: nodes.bin holds only live payloads");
    }
    // Whatever the roots, the points are the same and sort alike.
    let (sa, sb) = (dir.join("a.las"), dir.join("b.las"));
    run_ok(mortar().arg("sort").arg(&a).arg("-o").arg(&sa));
    run_ok(mortar().arg("sort").arg(&b).arg("-o").arg(&sb));
    assert!(
        std::fs::read(&sa).unwrap() == std::fs::read(&sb).unwrap(),
        "{name}: sort of the two stores differs"
    );
    let _ = std::fs::remove_dir_all(&dir);
    compared
}

#[test]
fn both_engines_build_the_same_tree_on_every_real_file() {
    let Some(data) = shared_data() else { return };
    let files = readable_fixtures(&data);
    assert!(files.len() > 40, "{} fixtures", files.len());
    let mut compared = 0;
    for (i, f) in files.iter().enumerate() {
        if same_tree(std::slice::from_ref(f), &format!("engines-{i}")) {
            compared += 1;
        }
    }
    // Most files have honest headers.
    assert!(
        compared * 10 >= files.len() * 8,
        "{compared} of {} compared node by node",
        files.len()
    );
}

#[test]
fn both_engines_build_the_same_tree_on_merged_tiles() {
    let Some(data) = shared_data() else { return };
    let bcts = bcts_tiles(&data);
    assert!(bcts.len() >= 2);
    assert!(same_tree(&bcts, "engines-bcts"));
    let ept = ept_tiles(&data, 60);
    assert!(same_tree(&ept, "engines-ept"));
}

#[test]
fn a_sorted_build_is_readable_at_every_commit_coarse_first() {
    use mortar_io::store::{build, Engine};
    let dir = tempdir("sorted-commits");
    let store = dir.join("s");
    let ds = mortar_io::inputs::open(&[root().join("data-samples/autzen_trim.laz")]).unwrap();
    let opts = small_build_options(Engine::Sorted);
    let mut seen: Vec<(u64, u64, usize, u8)> = Vec::new();
    let mut check = |p: &mortar_io::store::BuildProgress| {
        let s = Store::open(&store).expect("a committed store opens");
        assert_eq!(s.header.commit, p.commits);
        let deepest = s.entries.iter().map(|e| e.level as u8).max().unwrap();
        let nodes = s.entries.len();
        // Drawable at every commit: the deepest level's inner nodes are a frontier.
        let lod = mortar_io::store::StoreLod::new(s).expect("every commit is a drawable tree");
        assert!(lod.index().point_count() > 0);
        seen.push((p.commits, p.points, nodes, deepest));
    };
    let r = build(&ds, &store, &opts, &mut check).unwrap();
    assert_eq!(r.engine, mortar_io::store::BuiltBy::Sorted);
    assert_eq!(r.points, 110_000);
    // One level per commit, from the root down; the points arrive with the levels of leaves.
    assert!(seen.len() >= 4, "{seen:?}");
    assert_eq!(seen[0].3, 0, "the first commit holds the root: {seen:?}");
    assert!(
        seen.windows(2).all(|w| w[1].3 == w[0].3 + 1 && w[1].2 > w[0].2 && w[1].1 >= w[0].1),
        "{seen:?}"
    );
    assert_eq!(seen.last().unwrap().1, 110_000);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Builds `inputs` with the sorted engine and with the partitioned one under `memory`, and
/// checks that the stores hold the same entries (all but the payloads' offsets) and the same
/// payload bytes in the same order; returns the partitioned build's JSON.
fn partitioned_equals_sorted(inputs: &[PathBuf], memory: &str, tag: &str) -> serde_json::Value {
    let dir = tempdir(tag);
    let (a, b) = (dir.join("sorted"), dir.join("partitioned"));
    let name = inputs
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().to_string())
        .collect::<Vec<_>>()
        .join(" + ");
    let ra = build(inputs, &a, "sorted", &[]);
    let rb = build(inputs, &b, "partitioned", &["--memory", memory]);
    let jb = match (&ra, &rb) {
        (Err(_), Err(_)) => {
            let _ = std::fs::remove_dir_all(&dir);
            return serde_json::Value::Null;
        }
        (Ok(_), Ok(j)) => j.clone(),
        _ => panic!("{name}: one engine failed: sorted {ra:?}, partitioned {rb:?}"),
    };
    let (sa, sb) = (Store::open(&a).unwrap(), Store::open(&b).unwrap());
    assert_eq!(sa.header.points, sb.header.points, "{name}");
    assert_eq!(sa.root_cube(), sb.root_cube(), "{name}: root");
    assert_eq!(sa.entries.len(), sb.entries.len(), "{name}: node count");
    if jb["engine"] == "partitioned" {
        for (i, (x, y)) in sa.entries.iter().zip(&sb.entries).enumerate() {
            assert_eq!(
                (x.level, x.kind, x.index, x.count, x.length),
                (y.level, y.kind, y.index, y.count, y.length),
                "{name}: entry {i}"
            );
            assert!(
                sa.node_bytes(i) == sb.node_bytes(i),
                "{name}: payload of node {i} ({:?})",
                (x.level, x.index)
            );
        }
        // The same arrival ranks (`arrival.bin`), byte for byte.
        let ranks = |d: &Path| std::fs::read(d.join("arrival.bin")).unwrap();
        assert!(ranks(&a) == ranks(&b), "{name}: arrival.bin");
        let live: u64 = sb.entries.iter().map(|e| e.length).sum();
        assert_eq!(live, sb.header.nodes_len, "{name}: nodes.bin holds only live payloads");
        // No run files are left in the store.
        let left: Vec<String> = std::fs::read_dir(&b)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
            .filter(|n| n.starts_with('.'))
            .collect();
        assert!(left.is_empty(), "{name}: left in the store: {left:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
    jb
}

#[test]
fn the_partitioned_engine_writes_the_sorted_engines_store_on_every_real_file() {
    let Some(data) = shared_data() else { return };
    let files = readable_fixtures(&data);
    let mut partitioned = 0;
    for (i, f) in files.iter().enumerate() {
        // 2 MiB: units of about 8,000 points, so the larger files split into many.
        let j = partitioned_equals_sorted(std::slice::from_ref(f), "2M", &format!("part-{i}"));
        if j["engine"] == "partitioned" {
            partitioned += 1;
        }
    }
    assert!(
        partitioned * 10 >= files.len() * 8,
        "{partitioned} of {} built by the partitioned engine",
        files.len()
    );
}

#[test]
fn the_partitioned_engine_writes_the_sorted_engines_store_on_merged_tiles() {
    let Some(data) = shared_data() else { return };
    let bcts = bcts_tiles(&data);
    for memory in ["16M", "64M"] {
        let j = partitioned_equals_sorted(&bcts, memory, &format!("part-bcts-{memory}"));
        assert_eq!(j["engine"], "partitioned", "{j}");
    }
    let ept = ept_tiles(&data, 60);
    let j = partitioned_equals_sorted(&ept, "16M", "part-ept");
    assert_eq!(j["engine"], "partitioned", "{j}");
}

#[test]
fn auto_takes_the_partitioned_engine_above_the_budget_even_for_dense_cells() {
    let dir = tempdir("part-auto");
    let input = dir.join("g.las");
    run_ok(gen().args(["--points", "400000", "--seed", "9", "-o"]).arg(&input));
    let j = partitioned_equals_sorted(std::slice::from_ref(&input), "16M", "part-auto-a");
    assert_eq!(j["engine"], "partitioned", "{j}");
    let s = dir.join("auto");
    let o = run_ok(
        mortar().arg("build").arg(&input).arg("-o").arg(&s).args(["--json", "--memory", "16M"]),
    );
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["engine"], "partitioned", "{j}");
    // A budget too small for one cell of the partition: the cells are partitioned again, and the
    // store is the sorted engine's all the same.
    let j = partitioned_equals_sorted(std::slice::from_ref(&input), "20K", "part-auto-dense");
    assert_eq!(j["engine"], "partitioned", "{j}");
    let s2 = dir.join("dense");
    let o = run_ok(mortar().arg("build").arg(&input).arg("-o").arg(&s2).args([
        "--json",
        "--memory",
        "20K",
        "--leaf-capacity",
        "100",
    ]));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["engine"], "partitioned", "{j}");
    assert!(j["dense_cells"].as_u64().unwrap() >= 1, "{j}");
    let (a, b) = (dir.join("a.las"), dir.join("b.las"));
    run_ok(mortar().arg("sort").arg(&s).arg("-o").arg(&a));
    run_ok(mortar().arg("sort").arg(&s2).arg("-o").arg(&b));
    assert!(std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn cells_denser_than_a_unit_give_the_sorted_engines_store() {
    let dir = tempdir("part-dense");
    for (i, set) in dense_sets(&dir).iter().enumerate() {
        let j = partitioned_equals_sorted(set, "1M", &format!("part-dense-{i}"));
        assert_eq!(j["engine"], "partitioned", "{set:?}: {j}");
        eprintln!(
            "{set:?}: {} cells partitioned again, {} leaves larger than a unit",
            j["dense_cells"], j["large_leaves"]
        );
        assert!(j["large_leaves"].as_u64().unwrap() >= 1, "{set:?}: {j}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
