//! Issue 29 item 4: `mortar build --append STORE MORE...` gives the store a build of the
//! store's inputs followed by MORE gives, byte for byte (hierarchy, payloads, source header,
//! build record), with every engine, across a grown root and chained appends; it is atomic (the
//! old store stays whole until the swap, nothing is left beside it) and a stopped append resumes.
//! Refusals name the store and the reason, exit 1 and leave the store as it was. A store that
//! keeps its points' arrival ranks (`arrival.bin`: the sorted, partitioned and GPU engines) is extended from
//! its own points, without its original inputs, to the same bytes, on real files of every kind.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

const FILES: [&str; 4] = ["nodes.bin", "hierarchy.bin", "source.las", "build.json"];

fn build(inputs: &[PathBuf], out: &Path, extra: &[&str]) {
    run_ok(mortar().arg("build").args(inputs).arg("-o").arg(out).arg("-q").args(extra));
}

fn append(store: &Path, more: &[PathBuf], extra: &[&str]) -> Command {
    let mut c = mortar();
    c.arg("build").arg("--append").arg(store).args(more).arg("-q").args(extra);
    c
}

/// The two stores are the same: every file byte for byte (the arrival ranks too, where either
/// has them), or, where one was extended in place (its old payload files linked in as segments
/// `nodes-<s>.bin`), the same source header, build record and ranks byte for byte and the same
/// tree ([`same_tree`]).
fn same_store(a: &Path, b: &Path, what: &str) {
    let arrival = [ARRIVAL];
    if a.join(ARRIVAL).exists() || b.join(ARRIVAL).exists() {
        same_files(a, b, &arrival, what);
    }
    if in_place(a) || in_place(b) {
        same_files(a, b, &["source.las", "build.json"], what);
        same_tree(a, b, what);
    } else {
        same_files(a, b, &FILES, what);
    }
}

/// Whether the store holds a payload segment besides `nodes.bin` (an append kept its nodes).
fn in_place(store: &Path) -> bool {
    store.join("nodes-1.bin").exists()
}

/// The two stores hold the same tree: the hierarchy's header but for its commit count and
/// payload lengths, and every node's entry in order (but for where its payload lies) and
/// payload bytes.
fn same_tree(a: &Path, b: &Path, what: &str) {
    use mortar_io::store::Store;
    let (x, y) = (Store::open(a).unwrap(), Store::open(b).unwrap());
    let head = |s: &Store| {
        let h = &s.header;
        (h.points, h.root_min, h.root_size_log2, h.leaf_capacity, h.min, h.max, h.node_count)
    };
    assert_eq!(head(&x), head(&y), "{what}: hierarchy headers differ");
    for (i, (e, f)) in x.entries.iter().zip(&y.entries).enumerate() {
        let key = |e: &mortar_io::store::NodeEntry| (e.level, e.kind, e.index, e.count, e.length);
        assert_eq!(key(e), key(f), "{what}: node {i}");
        assert!(x.node_bytes(i) == y.node_bytes(i), "{what}: node {i}'s payload differs");
    }
}

const ARRIVAL: &str = "arrival.bin";

fn same_files(a: &Path, b: &Path, files: &[&str], what: &str) {
    for f in files {
        let (x, y) = (std::fs::read(a.join(f)), std::fs::read(b.join(f)));
        let (x, y) = (x.unwrap_or_default(), y.unwrap_or_default());
        assert!(x == y, "{what}: {f} differs ({} and {} bytes)", x.len(), y.len());
    }
}

/// Nothing is left beside the store.
fn nothing_beside(store: &Path) {
    for suffix in [".append", ".append-old"] {
        let mut p = store.as_os_str().to_owned();
        p.push(suffix);
        assert!(!PathBuf::from(p).exists(), "{} left {suffix}", store.display());
    }
}

fn root_size(store: &Path) -> u8 {
    mortar_io::store::Store::open(store).unwrap().root_cube().size_log2
}

/// Two generated scans, the second beside the first (so that the root grows).
fn scans(dir: &Path, points: u64) -> (PathBuf, PathBuf) {
    let a = dir.join("a.las");
    run_ok(gen().args(["--points", &points.to_string(), "--seed", "3", "-o"]).arg(&a));
    (a, scan_at(dir, "b.laz", points / 2, 4, "501000,5000500,0"))
}

fn scan_at(dir: &Path, name: &str, points: u64, seed: u64, origin: &str) -> PathBuf {
    let p = dir.join(name);
    run_ok(
        gen()
            .args(["--points", &points.to_string(), "--seed", &seed.to_string()])
            .args(["--origin", origin, "--extent", "300", "-o"])
            .arg(&p),
    );
    p
}

#[test]
fn an_append_is_the_build_of_all_inputs_for_every_engine() {
    let dir = tempdir("append-engines");
    let (a, b) = scans(&dir, 300_000);
    // A third scan, below the first two (the root grows downwards too).
    let sample = scan_at(&dir, "c.las", 100_000, 5, "499700,4999800,-50");
    for (engine, extra) in [
        ("auto", vec![]),
        ("sorted", vec!["--leaf-capacity", "3000"]),
        ("partitioned", vec!["--memory", "256M"]),
        ("incremental", vec!["--averaged-colors", "--leaf-capacity", "5000"]),
        ("gpu", vec![]),
    ] {
        let e = ["--engine", engine];
        let whole = dir.join(format!("whole-{engine}"));
        let o = mortar()
            .arg("build")
            .args([&a, &b])
            .arg("-o")
            .arg(&whole)
            .arg("-q")
            .args(e)
            .args(&extra)
            .output()
            .unwrap();
        if !o.status.success() && String::from_utf8_lossy(&o.stderr).contains("no GPU adapter") {
            assert!(std::env::var_os("MORTAR_REQUIRE_GPU").is_none(), "no adapter");
            eprintln!("SKIP gpu: no adapter");
            continue;
        }
        assert!(o.status.success(), "{engine}: {}", String::from_utf8_lossy(&o.stderr));
        let store = dir.join(format!("store-{engine}"));
        build(std::slice::from_ref(&a), &store, &[e.as_slice(), &extra].concat());
        let before = root_size(&store);
        // The store's settings are kept: no flag but the engine is given again.
        // Named with a trailing slash, as users type directories.
        let slash = PathBuf::from(format!("{}/", store.display()));
        run_ok(&mut append(&slash, std::slice::from_ref(&b), &e));
        same_store(&store, &whole, engine);
        assert!(root_size(&store) > before, "{engine}: the root grew for the second scan");
        nothing_beside(&store);
        // A third input, appended to the appended store.
        let third = dir.join(format!("third-{engine}"));
        build(&[a.clone(), b.clone(), sample.clone()], &third, &[e.as_slice(), &extra].concat());
        run_ok(&mut append(&store, std::slice::from_ref(&sample), &e));
        same_store(&store, &third, &format!("{engine}, chained"));
        nothing_beside(&store);
    }
}

#[test]
fn appended_real_tiles_equal_the_merged_build() {
    let Some(data) = shared_data() else { return };
    let tiles = bcts_tiles(&data);
    assert_eq!(tiles.len(), 4);
    let dir = tempdir("append-bcts");
    let whole = dir.join("whole");
    build(&tiles, &whole, &["--leaf-capacity", "2000"]);
    let store = dir.join("s");
    build(&tiles[..1], &store, &["--leaf-capacity", "2000"]);
    // From inside the store's directory, as `.`.
    let mut c = mortar();
    c.current_dir(&store).args(["build", "--append", ".", "-q"]).arg(&tiles[1]);
    run_ok(&mut c);
    run_ok(&mut append(&store, &tiles[2..], &["--engine", "sorted"]));
    same_store(&store, &whole, "bcts 1, then 2, then 3 and 4");
    // And the store reads back as the merged tiles: every record once.
    let o = run_ok(mortar().arg("info").arg(&store).arg("--json"));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let declared: u64 = tiles.iter().map(|t| las_records(t).unwrap().2.number_of_points()).sum();
    assert_eq!(j[0]["point_count"].as_u64(), Some(declared));
}

#[test]
fn refused_appends_leave_the_store_as_it_was() {
    let dir = tempdir("append-refused");
    let (a, b) = scans(&dir, 50_000);
    let store = dir.join("s");
    build(std::slice::from_ref(&a), &store, &[]);
    let snapshot: Vec<Vec<u8>> =
        FILES.iter().map(|f| std::fs::read(store.join(f)).unwrap()).collect();
    let unchanged = |what: &str| {
        for (f, want) in FILES.iter().zip(&snapshot) {
            assert!(&std::fs::read(store.join(f)).unwrap() == want, "{what}: {f} changed");
        }
        nothing_beside(&store);
    };
    let refused = |c: &mut Command, says: &str| {
        let o = c.output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr).to_string();
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert!(err.contains(says), "{err} should say {says}");
        err
    };
    // Other settings than the store's.
    refused(
        &mut append(&store, std::slice::from_ref(&b), &["--leaf-capacity", "77"]),
        "leaf capacity",
    );
    unchanged("other leaf capacity");
    // Not a store.
    refused(&mut append(&dir.join("nothing"), std::slice::from_ref(&b), &[]), "not a mortar store");
    // A bad new input: named, and the store stays.
    let bad = dir.join("bad.las");
    std::fs::write(&bad, b"LASF but not really").unwrap();
    refused(&mut append(&store, &[bad], &[]), "bad.las");
    unchanged("bad input");
    // A store without arrival ranks (an older mortar's, or another engine's) is built again
    // from its inputs, which must be there, unchanged.
    std::fs::remove_file(store.join(ARRIVAL)).unwrap();
    // The store's input changed since the build.
    let f = std::fs::OpenOptions::new().append(true).open(&a).unwrap();
    f.set_modified(std::time::SystemTime::now() + Duration::from_secs(5)).unwrap();
    drop(f);
    let err = refused(&mut append(&store, std::slice::from_ref(&b), &[]), "changed since");
    assert!(err.contains("a.las"), "{err}");
    unchanged("changed input");
    // Gone.
    std::fs::rename(&a, dir.join("moved.las")).unwrap();
    refused(&mut append(&store, std::slice::from_ref(&b), &[]), "cannot be read");
    unchanged("missing input");
}

#[test]
fn a_stopped_append_resumes_into_the_same_store() {
    let dir = tempdir("append-resume");
    let (a, b) = scans(&dir, 2_000_000);
    let whole = dir.join("whole");
    build(&[a.clone(), b.clone()], &whole, &[]);
    let store = dir.join("s");
    build(std::slice::from_ref(&a), &store, &[]);
    let work = dir.join("s.append");
    let inputs = |s: &Path| -> usize {
        mortar_io::store::BuildRecord::read(s).unwrap().unwrap().inputs.len()
    };
    // Stop appends at growing moments until one is stopped after it began its store.
    let mut stopped = false;
    for ms in [200u64, 400, 700, 1000, 1500, 2500] {
        let mut c = append(&store, std::slice::from_ref(&b), &["--commit-every", "0.05"]);
        let mut child = c.spawn().unwrap();
        std::thread::sleep(Duration::from_millis(ms));
        let _ = child.kill();
        if child.wait().unwrap().success() || inputs(&store) == 2 {
            // Finished, or stopped between the swap and the removal of the old store.
            let _ = std::fs::remove_dir_all(&work);
            break;
        }
        // The store itself is untouched while the append is stopped.
        assert_eq!(mortar_io::store::Store::open(&store).unwrap().header.points, 2_000_000);
        if work.join("hierarchy.bin").exists() {
            stopped = true;
            // Without --resume the stopped append is named, not overwritten.
            let o = append(&store, std::slice::from_ref(&b), &[]).output().unwrap();
            let err = String::from_utf8_lossy(&o.stderr);
            assert_eq!(o.status.code(), Some(1), "{err}");
            assert!(err.contains("--resume") && err.contains("s.append"), "{err}");
            run_ok(&mut append(&store, std::slice::from_ref(&b), &["--resume"]));
            break;
        }
        let _ = std::fs::remove_dir_all(&work);
    }
    if !stopped {
        eprintln!("no kill landed while the append was writing (the machine was fast)");
    }
    if inputs(&store) == 1 {
        run_ok(&mut append(&store, std::slice::from_ref(&b), &[]));
    }
    same_store(&store, &whole, "resumed append");
    nothing_beside(&store);
}

/// Appends from the store's own points: the originals removed, the same bytes as the build of
/// all inputs (generated scans with a grown root, chained; real files of every kind, paired);
/// a damaged arrival file or too little memory refused, the store unchanged.
#[test]
fn a_store_with_arrival_ranks_needs_no_original_inputs() {
    let dir = tempdir("append-own-points");
    let (a, b) = scans(&dir, 200_000);
    let c = scan_at(&dir, "c.las", 50_000, 5, "499700,4999800,-50");
    let whole = dir.join("whole");
    build(&[a.clone(), b.clone(), c.clone()], &whole, &[]);
    let whole_ab = dir.join("whole-ab");
    build(&[a.clone(), b.clone()], &whole_ab, &[]);
    let store = dir.join("s");
    build(std::slice::from_ref(&a), &store, &[]);
    assert!(store.join(ARRIVAL).exists(), "the sorted engine keeps arrival ranks");
    let o = run_ok(mortar().arg("info").arg(&store).arg("--json"));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let said = j[0]["store"]["arrival_bytes"].as_u64();
    assert_eq!(said, Some(std::fs::metadata(store.join(ARRIVAL)).unwrap().len()), "{j}");
    let kept = dir.join("a.kept");
    std::fs::rename(&a, &kept).unwrap();
    run_ok(&mut append(&store, std::slice::from_ref(&b), &[]));
    same_store(&store, &whole_ab, "a (gone), then b");
    nothing_beside(&store);
    // Damaged ranks: refused, named, the store unchanged.
    let ranks = std::fs::read(store.join(ARRIVAL)).unwrap();
    std::fs::write(store.join(ARRIVAL), &ranks[..ranks.len() / 2]).unwrap();
    let o = append(&store, std::slice::from_ref(&c), &[]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains(ARRIVAL) && err.contains("truncated"), "{err}");
    nothing_beside(&store);
    std::fs::write(store.join(ARRIVAL), &ranks).unwrap();
    same_store(&store, &whole_ab, "after a refused append");
    // Too little memory to hold the store's points, and the originals gone: refused.
    let o = append(&store, std::slice::from_ref(&c), &["--memory", "4M"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("--memory") && err.contains("a.las"), "{err}");
    same_store(&store, &whole_ab, "after a refusal for memory");
    // Chained.
    run_ok(&mut append(&store, std::slice::from_ref(&c), &[]));
    same_store(&store, &whole, "a (gone), then b, then c");
    std::fs::rename(&kept, &a).unwrap();

    // Real files, each with the next one of the fixtures (those a build can merge).
    let Some(data) = shared_data() else { return };
    let files: Vec<PathBuf> = readable_fixtures(&data)
        .into_iter()
        .filter(|p| std::fs::metadata(p).map(|m| m.len() < 3 << 20).unwrap_or(false))
        .collect();
    let (mut pairs, mut merged, mut regridded) = (0, 0, 0);
    for w in files.windows(2) {
        let (f, g) = (&w[0], &w[1]);
        let d = dir.join(format!("real-{pairs}"));
        pairs += 1;
        std::fs::create_dir_all(&d).unwrap();
        let ext = f.extension().unwrap().to_string_lossy().to_string();
        let x = d.join(format!("x.{ext}"));
        std::fs::copy(f, &x).unwrap();
        let s = d.join("s");
        if !mortar()
            .arg("build")
            .arg(&x)
            .arg("-o")
            .arg(&s)
            .arg("-q")
            .output()
            .unwrap()
            .status
            .success()
        {
            std::fs::remove_dir_all(&d).unwrap();
            continue;
        }
        let all = d.join("all");
        let o =
            mortar().arg("build").arg(&x).arg(g).arg("-o").arg(&all).arg("-q").output().unwrap();
        std::fs::remove_file(&x).unwrap();
        let app = append(&s, std::slice::from_ref(g), &[]).output().unwrap();
        let what = format!("{} then {}", f.display(), g.display());
        if !o.status.success() {
            // Inputs that cannot be merged (CRSs that disagree, say) cannot be appended either.
            assert_eq!(app.status.code(), Some(1), "{what}: appended, but not built together");
            std::fs::remove_dir_all(&d).unwrap();
            continue;
        }
        let err = String::from_utf8_lossy(&app.stderr);
        if err.contains("change the store's scale or offset") {
            // Refused, as documented: the originals are gone and the grid moved.
            assert_eq!(app.status.code(), Some(1), "{what}: {err}");
            regridded += 1;
            std::fs::remove_dir_all(&d).unwrap();
            continue;
        }
        assert!(app.status.success(), "{what}: {err}");
        same_store(&s, &all, &what);
        merged += 1;
        std::fs::remove_dir_all(&d).unwrap();
    }
    eprintln!(
        "{merged} of {pairs} pairs of real files appended from the store's own points, \
         {regridded} refused (the new file moves the grid)"
    );
    assert!(merged > 50, "only {merged} of {pairs} pairs merged");
}

/// A site of `points` points of `mortar-gen --seed seed` (`a.las`, 1 km square) and a day's
/// flight of 60 k points inside its root cube (`b.las`).
fn site_and_flight(dir: &Path, points: u64, seed: u64) -> (PathBuf, PathBuf) {
    let a = dir.join("a.las");
    run_ok(
        gen().args(["--points", &points.to_string(), "--seed", &seed.to_string(), "-o"]).arg(&a),
    );
    (a, scan_at(dir, "b.las", 60_000, 4, "500200,5000200,0"))
}

/// A store the partitioned engine built (its input larger than `--memory`) keeps its arrival
/// ranks as the sorted engine does, and is extended in place where keeping its nodes fits the
/// append's `--memory`: the store of the partitioned build of all inputs, with the same ranks;
/// under the budget it was built with, it is built again within it.
#[test]
fn a_store_larger_than_memory_is_extended_in_place() {
    let dir = tempdir("append-partitioned");
    let (a, b) = site_and_flight(&dir, 400_000, 9);
    let small = ["--memory", "16M", "--leaf-capacity", "3000"];
    let whole = dir.join("whole");
    build(&[a.clone(), b.clone()], &whole, &small);
    let sorted = dir.join("sorted");
    build(&[a.clone(), b.clone()], &sorted, &["--engine", "sorted", "--leaf-capacity", "3000"]);
    let engine = |s: &Path| {
        let r: serde_json::Value =
            serde_json::from_slice(&std::fs::read(s.join("build.json")).unwrap()).unwrap();
        r["engine"].as_str().unwrap().to_string()
    };
    assert_eq!(engine(&whole), "partitioned");
    same_files(&whole, &sorted, &[ARRIVAL], "the partitioned and sorted engines' ranks");
    let s = dir.join("s");
    build(std::slice::from_ref(&a), &s, &small);
    assert_eq!(engine(&s), "partitioned");
    assert!(s.join(ARRIVAL).exists(), "the partitioned engine keeps arrival ranks");
    let j = append_json(&s, std::slice::from_ref(&b), &["--memory", "256M"]);
    assert!(j["kept_nodes"].as_u64().unwrap() > 0 && in_place(&s), "nothing kept: {j}");
    assert_eq!(j["engine"], "partitioned", "the report names the store's engine: {j}");
    same_store(&s, &whole, "a partitioned store, then b in place");
    nothing_beside(&s);
    // Under the budget it was built with: built again, by the partitioned engine.
    let m = dir.join("m");
    build(std::slice::from_ref(&a), &m, &small);
    let j = append_json(&m, std::slice::from_ref(&b), &small[..2]);
    assert!(!in_place(&m) && j["engine"] == "partitioned", "{j}");
    same_store(&m, &whole, "a partitioned store, then b built again within 16M");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A store whose arrival ranks alone (8 bytes a point) pass the append's `--memory` is still
/// extended in place: its ranks are read a block at a time (and checked as they are), not held.
/// 8 M points are 64 MB of ranks; the flight reaches few of their leaves.
#[test]
fn a_store_whose_ranks_pass_memory_is_extended_in_place() {
    let dir = tempdir("append-ranks-stream");
    let a = dir.join("a.las");
    run_ok(gen().args(["--points", "8000000", "--seed", "11", "-o"]).arg(&a));
    let b = dir.join("b.las");
    run_ok(
        gen()
            .args(["--points", "20000", "--seed", "4", "--origin", "500400,5000400,0"])
            .args(["--extent", "30", "-o"])
            .arg(&b),
    );
    let whole = dir.join("whole");
    build(&[a.clone(), b.clone()], &whole, &[]);
    let s = dir.join("s");
    build(std::slice::from_ref(&a), &s, &[]);
    // A copy whose well-formed ranks name one point twice: refused once read, the file named,
    // the store as it was.
    let d = dir.join("d");
    std::fs::create_dir(&d).unwrap();
    for f in std::fs::read_dir(&s).unwrap() {
        let f = f.unwrap().path();
        std::fs::copy(&f, d.join(f.file_name().unwrap())).unwrap();
    }
    let arr = mortar_io::store::arrival::read(&d, 8_000_000).unwrap().unwrap();
    let mut ranks = arr.ranks;
    ranks[5_000_000] = ranks[17];
    let colors = arr.colors.unwrap();
    mortar_io::store::arrival::write(&d, ranks.len(), |i| ranks[i], arr.declared, colors).unwrap();
    let damaged = std::fs::read(d.join(ARRIVAL)).unwrap();
    let o = append(&d, std::slice::from_ref(&b), &["--memory", "64M"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains(ARRIVAL) && err.contains("twice"), "{err}");
    nothing_beside(&d);
    assert!(std::fs::read(d.join(ARRIVAL)).unwrap() == damaged && !in_place(&d));
    let j = append_json(&s, std::slice::from_ref(&b), &["--memory", "64M"]);
    assert!(j["kept_nodes"].as_u64().unwrap() > 0 && in_place(&s), "nothing kept: {j}");
    same_store(&s, &whole, "8 M points, then 20 k in place within 64M");
    nothing_beside(&s);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `mortar build --append STORE MORE --json`, which must succeed: its report.
fn append_json(store: &Path, more: &[PathBuf], extra: &[&str]) -> serde_json::Value {
    let o = run_ok(&mut append(store, more, &[extra, &["--json"]].concat()));
    serde_json::from_slice(&o.stdout).unwrap()
}

/// New points inside the root, with the colour scale unchanged: the store's nodes that no new
/// point reaches are kept (its old payload file linked in, only the reached nodes coded again),
/// and the store is the build of all inputs, node for node and payload byte for payload byte,
/// with the same ranks, source header and build record: across leaves that split, points that
/// coincide with old ones (a scan appended to itself), chained appends, a compaction, the GPU
/// engine's store, and `MORTAR_APPEND_REBUILD=1`'s whole build. Where the root moves, or
/// keeping the nodes would pass `--memory`, every node is built again, and the warning says why.
#[test]
fn an_append_inside_the_root_keeps_the_nodes_it_does_not_reach() {
    let dir = tempdir("append-in-place");
    let (a, b) = site_and_flight(&dir, 300_000, 3);
    for extra in [vec![], vec!["--leaf-capacity", "3000"]] {
        let what = format!("{extra:?}");
        let whole_ab = dir.join("whole-ab");
        let whole_aba = dir.join("whole-aba");
        let _ = std::fs::remove_dir_all(&whole_ab);
        let _ = std::fs::remove_dir_all(&whole_aba);
        build(&[a.clone(), b.clone()], &whole_ab, &extra);
        build(&[a.clone(), b.clone(), a.clone()], &whole_aba, &extra);
        let s = dir.join("s");
        let _ = std::fs::remove_dir_all(&s);
        build(std::slice::from_ref(&a), &s, &extra);
        let nodes = std::fs::read(s.join("nodes.bin")).unwrap();
        let j = append_json(&s, std::slice::from_ref(&b), &[]);
        let kept = j["kept_nodes"].as_u64().unwrap();
        assert!(kept > 0 && in_place(&s), "{what}: nothing kept: {j}");
        assert!(kept < j["nodes"].as_u64().unwrap(), "{what}: every node kept: {j}");
        // The old payloads are the first segment, as they were; the new file holds less.
        assert!(std::fs::read(s.join("nodes-1.bin")).unwrap() == nodes, "{what}");
        assert!(std::fs::metadata(s.join("nodes.bin")).unwrap().len() < nodes.len() as u64);
        same_store(&s, &whole_ab, &format!("{what}: a, then b in place"));
        nothing_beside(&s);
        // Every point again (each position then holds an old and a new point), chained.
        let j = append_json(&s, std::slice::from_ref(&a), &[]);
        assert!(j["kept_nodes"].as_u64().unwrap() > 0, "{what}: {j}");
        assert!(s.join("nodes-2.bin").exists(), "{what}: the second append links two segments");
        same_store(&s, &whole_aba, &format!("{what}: a, b, then a in place"));
        // Compacted: one segment of live payloads, the same tree.
        run_ok(mortar().arg("build").arg("--compact").arg(&s).arg("-q"));
        same_tree(&s, &whole_aba, &format!("{what}: compacted"));
        // The whole build on request: the same bytes as the build of all inputs.
        let r = dir.join("r");
        let _ = std::fs::remove_dir_all(&r);
        build(std::slice::from_ref(&a), &r, &extra);
        run_ok(append(&r, std::slice::from_ref(&b), &[]).env("MORTAR_APPEND_REBUILD", "1"));
        assert!(!in_place(&r), "{what}: MORTAR_APPEND_REBUILD=1 builds everything");
        same_store(&r, &whole_ab, &format!("{what}: a, then b built again"));
    }
    // The root moves: everything is built again, and said so.
    let s = dir.join("s");
    let far = scan_at(&dir, "far.las", 20_000, 6, "501000,5000500,0");
    let j = append_json(&s, std::slice::from_ref(&far), &[]);
    let said = j["warnings"].to_string();
    assert!(said.contains("every node is built again") && said.contains("root cube"), "{j}");
    assert!(!in_place(&s), "{j}");
    // Too little --memory to keep the nodes: everything is built again within it, and said so.
    let m = dir.join("m");
    build(std::slice::from_ref(&a), &m, &[]);
    let j = append_json(&m, std::slice::from_ref(&b), &["--memory", "3M"]);
    let said = j["warnings"].to_string();
    assert!(said.contains("every node is built again") && said.contains("--memory"), "{j}");
    assert!(!in_place(&m) && j["points"] == 360_000, "{j}");
    // The GPU engine's store is extended in place too, to the GPU engine's build of all inputs.
    let g = dir.join("g");
    let o =
        mortar().arg("build").arg(&a).arg("-o").arg(&g).args(["-q", "--engine", "gpu"]).output();
    let o = o.unwrap();
    if !o.status.success() && String::from_utf8_lossy(&o.stderr).contains("no GPU adapter") {
        assert!(std::env::var_os("MORTAR_REQUIRE_GPU").is_none(), "no adapter");
        eprintln!("SKIP gpu: no adapter");
        return;
    }
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let whole_g = dir.join("whole-g");
    build(&[a.clone(), b.clone()], &whole_g, &["--engine", "gpu"]);
    let j = append_json(&g, std::slice::from_ref(&b), &[]);
    assert!(j["kept_nodes"].as_u64().unwrap() > 0 && j["engine"] == "gpu", "{j}");
    same_store(&g, &whole_g, "the GPU engine's store, then b in place");
}

/// Real files of every kind (a fourth of the fixtures, LAS and LAZ, every point format and
/// version mortar reads): each appended to its own store in place equals the build of the file
/// twice (every point coincides with an old one), and the two halves of each (written by the
/// las crate, both declaring the file's box; the second half arriving after the first) appended
/// in place equal the build of both halves.
#[test]
fn real_files_appended_in_place_equal_the_merged_build() {
    let Some(data) = shared_data() else { return };
    let dir = tempdir("append-in-place-real");
    let files: Vec<PathBuf> = readable_fixtures(&data)
        .into_iter()
        .filter(|p| std::fs::metadata(p).map(|m| m.len() < 3 << 20).unwrap_or(false))
        .enumerate()
        .filter(|(i, _)| i % 4 == 0)
        .map(|(_, p)| p)
        .collect();
    let (mut twice, mut halved, mut tried) = (0, 0, 0);
    for f in &files {
        tried += 1;
        let s = dir.join("s");
        let w = dir.join("w");
        for d in [&s, &w] {
            let _ = std::fs::remove_dir_all(d);
        }
        let one = mortar().arg("build").arg(f).arg("-o").arg(&s).arg("-q").output().unwrap();
        if !one.status.success() {
            continue;
        }
        let points = mortar_io::store::Store::open(&s).unwrap().header.points;
        build(&[f.clone(), f.clone()], &w, &[]);
        let j = append_json(&s, std::slice::from_ref(f), &[]);
        let what = format!("{} twice", f.display());
        if points > 0 {
            assert!(in_place(&s) && j["kept_nodes"].as_u64().is_some(), "{what}: {j}");
            twice += 1;
        }
        same_store(&s, &w, &what);
        let Some((h1, h2)) = halves(f, &dir) else { continue };
        for d in [&s, &w] {
            let _ = std::fs::remove_dir_all(d);
        }
        build(&[h1.clone(), h2.clone()], &w, &[]);
        build(std::slice::from_ref(&h1), &s, &[]);
        let j = append_json(&s, std::slice::from_ref(&h2), &[]);
        same_store(&s, &w, &format!("{} in halves", f.display()));
        halved += usize::from(in_place(&s));
        if !in_place(&s) {
            eprintln!("{} in halves, built again: {}", f.display(), j["warnings"]);
        }
    }
    eprintln!("{twice} of {tried} real files appended to themselves in place, {halved} in halves");
    assert!(twice > 45 && halved > 25, "only {twice} and {halved} of {tried}");
}

/// The first and second halves of `f`'s points, written as LAS by the las crate with `f`'s
/// header (its bounds too); `None` where the las crate cannot read or write it, or it holds under 2 points.
fn halves(f: &Path, dir: &Path) -> Option<(PathBuf, PathBuf)> {
    let mut r = las::Reader::from_path(f).ok()?;
    let header = r.header().clone();
    let all = r.read_all().ok()?;
    let (n, rl) = (all.len(), all.record_len());
    if n < 2 {
        return None;
    }
    let (first, second) = all.raw_bytes().split_at(n / 2 * rl);
    let mut out = Vec::new();
    for (name, part) in [("h1.las", first), ("h2.las", second)] {
        let p = dir.join(name);
        let mut b = las::Builder::from(header.clone());
        b.point_format.is_compressed = false;
        // Uncompressed: without LASzip's record, which would say the points are compressed.
        b.vlrs.retain(|v| v.user_id != "laszip encoded");
        let h = b.into_header().ok()?;
        let pd =
            las::PointDataBuilder::new().for_header(&h).build_from_bytes(part.to_vec()).ok()?;
        let mut w = las::Writer::from_path(&p, h).ok()?;
        w.write_points(&pd).ok()?;
        w.close().ok()?;
        drop(w);
        // The whole file's bounds in both halves' headers, as tiles of one survey declare the
        // box they cover (the las crate writes its points' own).
        let b = header.bounds();
        let mut bytes = std::fs::read(&p).ok()?;
        let box_ = [b.max.x, b.min.x, b.max.y, b.min.y, b.max.z, b.min.z];
        for (k, v) in box_.iter().enumerate() {
            bytes[179 + 8 * k..187 + 8 * k].copy_from_slice(&v.to_le_bytes());
        }
        std::fs::write(&p, bytes).ok()?;
        out.push(p);
    }
    Some((out[0].clone(), out[1].clone()))
}
