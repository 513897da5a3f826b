//! Tests of the octree builder against its invariants and against a naive reference builder.

use super::voxels::cell_key;
use super::*;
use proptest::prelude::*;
use std::collections::{BTreeMap, HashMap, HashSet};

/// splitmix64: a small seeded generator for test data.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

fn point(pos: [i32; 3], color: u32, record: u64) -> Point {
    Point { pos, color, record }
}

/// `n` uniform points in `[origin, origin + extent)`.
fn random_points(n: usize, seed: u64, origin: [i32; 3], extent: u32) -> Vec<Point> {
    let mut r = Rng(seed);
    (0..n)
        .map(|i| {
            let pos = origin.map(|o| o + r.below(extent as u64) as i32);
            point(pos, r.next() as u32, i as u64)
        })
        .collect()
}

/// `n` points around a few centres, spread over a few units.
fn clustered_points(n: usize, seed: u64, extent: u32) -> Vec<Point> {
    let mut r = Rng(seed);
    let centres: Vec<[i32; 3]> =
        (0..5).map(|_| [0; 3].map(|_: i32| 200 + r.below(extent as u64 - 400) as i32)).collect();
    (0..n)
        .map(|i| {
            let c = centres[r.below(centres.len() as u64) as usize];
            let spread = [1, 8, 150][r.below(3) as usize];
            let pos = c.map(|v| v + r.below(2 * spread as u64) as i32 - spread);
            point(pos, r.next() as u32, i as u64)
        })
        .collect()
}

/// `n` points on 3 positions.
fn duplicate_points(n: usize, seed: u64) -> Vec<Point> {
    let mut r = Rng(seed);
    let spots = [[5, 5, 5], [1000, 7, 3], [1000, 7, 4]];
    (0..n).map(|i| point(spots[r.below(3) as usize], r.next() as u32, i as u64)).collect()
}

fn config(cap: u32, mode: ColorMode) -> BuilderConfig {
    BuilderConfig { leaf_capacity: cap, color_mode: mode, ..BuilderConfig::default() }
}

/// Builds from `points` cut into batches of `batch` points; returns the snapshot after each batch.
fn build(
    points: &[Point],
    root: Cube,
    cfg: BuilderConfig,
    batch: usize,
) -> (Builder, Vec<Snapshot>) {
    let mut b = Builder::new(root, cfg).unwrap();
    let mut snaps = Vec::new();
    for c in points.chunks(batch.max(1)) {
        b.add_batch(c).unwrap();
        snaps.push(b.snapshot());
    }
    (b, snaps)
}

/// A node with its payload flattened (chunking is not part of the result).
#[derive(Clone, Debug, PartialEq, Eq)]
struct Flat {
    leaf: bool,
    cube: Cube,
    points: Vec<Point>,
    voxels: Vec<Voxel>,
    subtree: u64,
}

fn flatten(s: &Snapshot) -> BTreeMap<NodeKey, Flat> {
    s.iter()
        .map(|(_, n)| {
            let f = Flat {
                leaf: n.is_leaf(),
                cube: n.cube(),
                points: n.points().map(|p| p.to_vec()).unwrap_or_default(),
                voxels: n.voxels().map(|v| v.to_vec()).unwrap_or_default(),
                subtree: n.subtree_points(),
            };
            (n.key(), f)
        })
        .collect()
}

/// `f` with each node's voxels sorted by cell: the voxel order within one update is by octant,
/// so it depends on where batches begin; the voxel set and colours do not.
fn canon(mut f: BTreeMap<NodeKey, Flat>) -> BTreeMap<NodeKey, Flat> {
    for n in f.values_mut() {
        n.voxels.sort_by_key(|v| (v.pos[2], v.pos[1], v.pos[0]));
    }
    f
}

/// The naive reference: the whole point sequence at once, top-down, in arrival order.
fn reference(points: &[Point], root: Cube, cfg: BuilderConfig) -> BTreeMap<NodeKey, Flat> {
    fn rec(
        key: NodeKey,
        cube: Cube,
        pts: Vec<Point>,
        cfg: &BuilderConfig,
        out: &mut BTreeMap<NodeKey, Flat>,
    ) {
        let splittable = cube.size_log2 >= MIN_INNER_SIZE_LOG2 && key.level < cfg.max_level;
        if pts.len() as u64 > cfg.leaf_capacity as u64 && splittable {
            let mut order: Vec<u32> = Vec::new();
            let mut first: HashMap<u32, Point> = HashMap::new();
            let mut sums: HashMap<u32, ([u32; 4], u32)> = HashMap::new();
            for p in &pts {
                let k = cell_key(cube.voxel_of(p.pos).map(|c| c as u32));
                if let std::collections::hash_map::Entry::Vacant(e) = first.entry(k) {
                    e.insert(*p);
                    order.push(k);
                }
                let e = sums.entry(k).or_insert(([0; 4], 0));
                for (s, c) in e.0.iter_mut().zip(p.color.to_le_bytes()) {
                    *s += c as u32;
                }
                e.1 += 1;
            }
            let voxels = order
                .iter()
                .map(|k| {
                    let color = match cfg.color_mode {
                        ColorMode::FirstCome => first[k].color,
                        ColorMode::Averaged => mean_color(sums[k].0, sums[k].1),
                    };
                    Voxel::of(&first[k], color)
                })
                .collect();
            let n = pts.len() as u64;
            let mut parts: [Vec<Point>; 8] = Default::default();
            for p in pts {
                parts[cube.octant_of(p.pos)].push(p);
            }
            for (o, part) in parts.into_iter().enumerate() {
                rec(key.child(o), cube.child(o), part, cfg, out);
            }
            out.insert(key, Flat { leaf: false, cube, points: vec![], voxels, subtree: n });
        } else {
            let n = pts.len() as u64;
            out.insert(key, Flat { leaf: true, cube, points: pts, voxels: vec![], subtree: n });
        }
    }
    let mut out = BTreeMap::new();
    rec(NodeKey::ROOT, root, points.to_vec(), &cfg, &mut out);
    canon(out)
}

fn splittable(cube: Cube, level: u8, cfg: &BuilderConfig) -> bool {
    cube.size_log2 >= MIN_INNER_SIZE_LOG2 && level < cfg.max_level
}

/// The structural invariants of a snapshot that holds exactly `input`.
fn check_invariants(s: &Snapshot, input: &[Point]) {
    let cfg = s.config();
    let root = s.root_cube();
    assert_eq!(s.input_points(), input.len() as u64);
    assert_eq!(s.point_count(), input.len() as u64);

    // Every input point is in exactly one leaf: the multisets are equal.
    let mut stored: Vec<Point> =
        s.leaves().flat_map(|(_, n)| n.points().unwrap().iter().copied()).collect();
    let mut want = input.to_vec();
    let by = |p: &Point| (p.record, p.pos, p.color);
    stored.sort_by_key(by);
    want.sort_by_key(by);
    assert_eq!(stored, want, "leaves do not hold the input exactly once");

    // Cells every inner node must have a voxel for, and points per cube.
    let mut cells: Vec<HashSet<[u8; 3]>> = vec![HashSet::new(); s.node_count()];
    let mut inside = vec![0u64; s.node_count()];
    for p in input {
        let mut id = NodeId::ROOT;
        loop {
            let n = s.node(id);
            inside[id.index()] += 1;
            match n.children() {
                None => break,
                Some(ch) => {
                    cells[id.index()].insert(n.cube().voxel_of(p.pos));
                    id = ch[n.cube().octant_of(p.pos)];
                }
            }
        }
    }

    for (id, n) in s.iter() {
        assert_eq!(n.cube(), n.key().cube_in(root), "{}", n.key().name());
        assert_eq!(n.subtree_points(), inside[id.index()], "subtree of {}", n.key().name());
        match n.children() {
            None => {
                assert!(n.voxels().is_none());
                let pts = n.points().unwrap();
                assert!(
                    pts.len() <= cfg.leaf_capacity as u64 || !splittable(n.cube(), n.level(), &cfg),
                    "leaf {} holds {} points",
                    n.key().name(),
                    pts.len()
                );
                for p in pts.iter() {
                    assert!(
                        n.cube().contains(p.pos),
                        "point {:?} outside leaf {}",
                        p.pos,
                        n.key().name()
                    );
                    assert_eq!(s.leaf_at(p.pos), Some(id));
                }
                assert!(pts.chunks().iter().all(|c| !c.is_empty() && c.len() <= POINT_CHUNK_MAX));
            }
            Some(ch) => {
                assert!(n.points().is_none());
                assert!(n.cube().size_log2 >= MIN_INNER_SIZE_LOG2);
                for (o, c) in ch.iter().enumerate() {
                    let c = s.node(*c);
                    assert_eq!(c.key(), n.key().child(o));
                    assert_eq!(c.cube(), n.cube().child(o));
                }
                let vox = n.voxels().unwrap();
                assert!(vox.len() <= (GRID_SIZE as u64).pow(3));
                let mut seen = HashSet::new();
                for v in vox.iter() {
                    assert!(
                        n.cube().contains(v.pos),
                        "voxel {:?} outside {}",
                        v.pos,
                        n.key().name()
                    );
                    let cell = n.cube().voxel_of(v.pos);
                    assert!(cell.iter().all(|&c| (c as u32) < GRID_SIZE));
                    assert!(seen.insert(cell), "voxel {:?} twice in {}", cell, n.key().name());
                }
                assert_eq!(
                    seen,
                    cells[id.index()],
                    "voxels of {} are not the cells of its points",
                    n.key().name()
                );
            }
        }
    }
}

/// `b` is a later snapshot of the same builder as `a` (see "what is monotone").
fn check_monotone(a: &Snapshot, b: &Snapshot) {
    assert!(b.node_count() >= a.node_count());
    assert!(b.revision() >= a.revision());
    assert!(b.input_points() >= a.input_points());
    let first_come = a.config().color_mode == ColorMode::FirstCome;
    for (id, na) in a.iter() {
        let nb = b.node(id);
        assert_eq!(na.key(), nb.key());
        assert_eq!(na.cube(), nb.cube());
        assert!(nb.subtree_points() >= na.subtree_points());
        match (na.is_leaf(), nb.is_leaf()) {
            (true, true) => {
                let pa = na.points().unwrap().to_vec();
                let pb = nb.points().unwrap().to_vec();
                assert_eq!(&pb[..pa.len()], &pa[..], "leaf {} lost points", na.key().name());
            }
            (true, false) => {
                // all its points are in leaves below it
                for p in na.points().unwrap().iter() {
                    let leaf = b.node(b.leaf_at(p.pos).unwrap());
                    assert!(leaf.key().level > na.key().level);
                    assert!(
                        leaf.points().unwrap().iter().any(|q| q == p),
                        "split leaf {} lost {:?}",
                        na.key().name(),
                        p
                    );
                }
            }
            (false, true) => panic!("inner node {} became a leaf", na.key().name()),
            (false, false) => {
                let va = na.voxels().unwrap().to_vec();
                let vb = nb.voxels().unwrap().to_vec();
                assert!(vb.len() >= va.len());
                if first_come {
                    assert_eq!(&vb[..va.len()], &va[..], "voxels of {} changed", na.key().name());
                } else {
                    for (x, y) in va.iter().zip(&vb) {
                        assert_eq!(
                            (x.pos, x.record),
                            (y.pos, y.record),
                            "voxel points of {} changed",
                            na.key().name()
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn every_point_in_exactly_one_leaf() {
    let root = Cube::new([0; 3], 16);
    let sets: Vec<(&str, Vec<Point>)> = vec![
        ("random", random_points(20_000, 1, [0; 3], 1 << 16)),
        ("clustered", clustered_points(20_000, 2, 1 << 16)),
        ("duplicates", duplicate_points(5_000, 3)),
        ("small extent", random_points(20_000, 4, [100; 3], 300)),
    ];
    for cap in [1, 16, 1000, 50_000] {
        for (name, pts) in &sets {
            for batch in [pts.len(), 3_000, 777] {
                for mode in [ColorMode::FirstCome, ColorMode::Averaged] {
                    let (_, snaps) = build(pts, root, config(cap, mode), batch);
                    let s = snaps.last().unwrap();
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                        check_invariants(s, pts)
                    }))
                    .unwrap_or_else(|_| {
                        panic!("{name}, capacity {cap}, batches of {batch}, {mode:?}")
                    });
                }
            }
        }
    }
}

#[test]
fn matches_reference_on_fixed_cases() {
    let root = Cube::new([-1000, -1000, -1000], 12);
    let mut pts = random_points(3000, 7, [-1000; 3], 4096);
    pts.extend(
        duplicate_points(500, 8).into_iter().map(|p| Point { record: p.record + 3000, ..p }),
    );
    pts.extend(clustered_points(2000, 9, 4096).into_iter().map(|p| Point {
        pos: p.pos.map(|v| v - 1000),
        record: p.record + 3500,
        ..p
    }));
    for cap in [1, 16, 100] {
        for mode in [ColorMode::FirstCome, ColorMode::Averaged] {
            let cfg = config(cap, mode);
            let want = reference(&pts, root, cfg);
            for batch in [pts.len(), 1000, 333, 10] {
                let (_, snaps) = build(&pts, root, cfg, batch);
                assert!(
                    canon(flatten(snaps.last().unwrap())) == want,
                    "capacity {cap}, {mode:?}, batches of {batch}"
                );
            }
        }
    }
}

#[test]
fn snapshots_are_monotone() {
    let root = Cube::new([0; 3], 16);
    let mut pts = clustered_points(30_000, 11, 1 << 16);
    pts.extend(
        random_points(10_000, 12, [0; 3], 1 << 16)
            .into_iter()
            .map(|p| Point { record: p.record + 30_000, ..p }),
    );
    for mode in [ColorMode::FirstCome, ColorMode::Averaged] {
        let mut b = Builder::new(root, config(200, mode)).unwrap();
        let empty = b.snapshot();
        assert_eq!(empty.node_count(), 1);
        assert!(empty.node(NodeId::ROOT).is_leaf());
        let mut snaps = vec![empty];
        let mut flats = vec![flatten(&snaps[0])];
        let mut added = 0;
        for c in pts.chunks(4_000) {
            b.add_batch(c).unwrap();
            added += c.len();
            let s = b.snapshot();
            check_invariants(&s, &pts[..added]);
            check_monotone(snaps.last().unwrap(), &s);
            flats.push(flatten(&s));
            snaps.push(s);
        }
        check_monotone(&snaps[1], snaps.last().unwrap());
        // earlier snapshots never change
        for (s, f) in snaps.iter().zip(&flats) {
            assert!(flatten(s) == *f);
        }
        // snapshots of an unchanged builder share everything
        let again = b.snapshot();
        assert!(std::sync::Arc::ptr_eq(&again.nodes, &snaps.last().unwrap().nodes));
    }
}

#[test]
fn first_come_and_averaged_colours_by_hand() {
    // 256 units: voxels of 2 units in the root; capacity 2, so 3 points split the root.
    let root = Cube::new([0; 3], 8);
    let red = 0xff00_00ff;
    let green = 0xff00_ff00;
    let blue = 0xffff_0000;
    let pts = [
        point([0, 0, 0], red, 0),
        point([1, 1, 1], green, 1),
        point([200, 0, 0], blue, 2),
        point([1, 0, 1], blue, 3),
    ];

    let mut b = Builder::new(root, config(2, ColorMode::FirstCome)).unwrap();
    b.add_batch(&pts).unwrap();
    let s = b.snapshot();
    let r = s.node(NodeId::ROOT);
    assert!(!r.is_leaf());
    assert_eq!(
        r.voxels().unwrap().to_vec(),
        vec![Voxel::of(&pts[0], red), Voxel::of(&pts[2], blue)]
    );
    // child 0 (128 units, 1-unit voxels) holds 3 points: it splits too
    let c0 = s.node(r.child(0).unwrap());
    assert_eq!(
        c0.voxels().unwrap().to_vec(),
        vec![Voxel::of(&pts[0], red), Voxel::of(&pts[1], green), Voxel::of(&pts[3], blue)]
    );
    // its children are 64 wide: leaves, whatever they hold
    assert_eq!(s.node(c0.child(0).unwrap()).point_count(), 3);
    assert_eq!(s.node(r.child(1).unwrap()).point_count(), 1);

    let mut b = Builder::new(root, config(2, ColorMode::Averaged)).unwrap();
    b.add_batch(&pts).unwrap();
    let s = b.snapshot();
    let r = s.node(NodeId::ROOT);
    // (255 + 0 + 0) / 3 = 85, (0 + 255 + 0) / 3 = 85, (0 + 0 + 255) / 3 = 85, alpha 255
    assert_eq!(
        r.voxels().unwrap().to_vec(),
        vec![Voxel::of(&pts[0], 0xff55_5555), Voxel::of(&pts[2], blue)]
    );
}

#[test]
fn spilled_points_keep_first_come_and_are_averaged_once() {
    let root = Cube::new([0; 3], 8);
    let a = point([0, 0, 0], 0xff00_0010, 0);
    let b = point([1, 1, 1], 0xff00_0020, 1);
    let c = point([1, 0, 0], 0xff00_0090, 2);
    for mode in [ColorMode::FirstCome, ColorMode::Averaged] {
        let mut bld = Builder::new(root, config(2, mode)).unwrap();
        let st = bld.add_batch(&[a, b]).unwrap();
        assert_eq!((st.splits, st.spilled), (0, 0));
        assert!(bld.snapshot().node(NodeId::ROOT).is_leaf());
        let st = bld.add_batch(&[c]).unwrap();
        assert_eq!(st.spilled, 2);
        assert!(st.splits >= 1);
        let s = bld.snapshot();
        let v = s.node(NodeId::ROOT).voxels().unwrap().to_vec();
        let want = match mode {
            ColorMode::FirstCome => 0xff00_0010,
            ColorMode::Averaged => 0xff00_0040, // (0x10 + 0x20 + 0x90) / 3
        };
        assert_eq!(v, vec![Voxel::of(&a, want)]);
        check_invariants(&s, &[a, b, c]);
        // the leaf keeps arrival order: spilled points first
        let leaf = s.node(s.leaf_at([0, 0, 0]).unwrap());
        assert_eq!(leaf.points().unwrap().to_vec(), vec![a, b, c]);
    }
}

#[test]
fn thread_count_does_not_change_the_tree() {
    let root = Cube::new([0; 3], 20);
    let mut pts = random_points(150_000, 21, [0; 3], 1 << 20);
    pts.extend(
        clustered_points(150_000, 22, 1 << 20)
            .into_iter()
            .map(|p| Point { record: p.record + 150_000, ..p }),
    );
    for mode in [ColorMode::FirstCome, ColorMode::Averaged] {
        let cfg = config(2_000, mode);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let (_, snaps) = build(&pts, root, cfg, 70_000);
                let s = snaps.last().unwrap().clone();
                let chunking: Vec<Vec<usize>> = s
                    .iter()
                    .map(|(_, n)| match n.payload() {
                        Payload::Points(p) => p.chunks().iter().map(|c| c.len()).collect(),
                        Payload::Voxels(v) => v.chunks().iter().map(|c| c.len()).collect(),
                    })
                    .collect();
                (flatten(&s), chunking, s.node_count())
            })
        };
        let one = run(1);
        let four = run(4);
        assert!(one == four, "{mode:?}: 1 and 4 threads differ");
        assert!(one.2 > 100);
    }
}

#[test]
fn batching_does_not_change_the_tree() {
    let root = Cube::new([0; 3], 18);
    let pts = clustered_points(60_000, 31, 1 << 18);
    for mode in [ColorMode::FirstCome, ColorMode::Averaged] {
        let cfg = config(500, mode);
        let want = canon(flatten(build(&pts, root, cfg, pts.len()).1.last().unwrap()));
        for batch in [1_000, 7_777, 30_000] {
            let got = canon(flatten(build(&pts, root, cfg, batch).1.last().unwrap()));
            assert!(got == want, "{mode:?}, batches of {batch}");
        }
    }
}

/// Paging leaves out after every batch and back in on splits gives the tree of an in-core
/// build: the pager keeps each leaf's points as a caller would on disk.
#[test]
fn paging_out_and_in_does_not_change_the_tree() {
    let root = Cube::new([0; 3], 18);
    let pts = clustered_points(60_000, 41, 1 << 18);
    for mode in [ColorMode::FirstCome, ColorMode::Averaged] {
        let cfg = config(500, mode);
        let want = canon(flatten(build(&pts, root, cfg, 7_777).1.last().unwrap()));
        let mut b = Builder::new(root, cfg).unwrap();
        // What the "store" holds: every leaf's full point sequence as of its last page-out.
        let mut saved: HashMap<u32, Vec<Point>> = HashMap::new();
        let mut paged_in = 0usize;
        for c in pts.chunks(7_777) {
            let calls = std::sync::atomic::AtomicUsize::new(0);
            let page_in = |id: NodeId| -> Result<Vec<Point>, String> {
                calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                saved.get(&id.0).cloned().ok_or_else(|| format!("nothing saved for {}", id.0))
            };
            b.add_batch_paged(c, &page_in).unwrap();
            paged_in += calls.into_inner();
            // Save the changed leaves whole (paged part + resident part), then page out.
            let snap = b.snapshot();
            for (id, n) in snap.leaves() {
                let mut all = if n.paged_points() > 0 { saved[&id.0].clone() } else { Vec::new() };
                assert_eq!(all.len() as u64, n.paged_points());
                all.extend(n.points().unwrap().iter().copied());
                saved.insert(id.0, all);
            }
            let resident = b.resident_points();
            assert_eq!(b.page_out(), resident);
            assert_eq!(b.resident_points(), 0);
            let after = b.snapshot();
            assert_eq!(after.point_count(), 0);
            assert_eq!(after.total_points(), b.input_points());
            assert_eq!(
                after.changed_since(snap.revision()).count(),
                0,
                "paging out is not a change"
            );
            // The snapshot taken before paging out keeps its points.
            assert_eq!(snap.point_count(), resident);
            assert_eq!(snap.total_points(), b.input_points());
        }
        assert!(paged_in > 0, "some paged-out leaf split");
        // Rebuild the flat view with the saved points.
        let snap = b.snapshot();
        let mut got = flatten(&snap);
        for (id, n) in snap.leaves() {
            got.get_mut(&n.key()).unwrap().points = saved.get(&id.0).cloned().unwrap_or_default();
        }
        assert!(canon(got) == want, "{mode:?}");
    }
}

#[test]
fn a_failing_page_in_leaves_the_builder_unchanged() {
    let root = Cube::new([0; 3], 18);
    let pts = random_points(3_000, 5, [0; 3], 1 << 18);
    let mut b = Builder::new(root, config(1_000, ColorMode::FirstCome)).unwrap();
    b.add_batch(&pts[..900]).unwrap();
    b.page_out();
    let before = flatten(&b.snapshot());
    let err = b.add_batch_paged(&pts[900..], &|_| Err("disk gone".into())).unwrap_err();
    assert_eq!(err, OctreeError::PageIn("disk gone".into()));
    assert!(flatten(&b.snapshot()) == before);
    let err = b.add_batch_paged(&pts[900..], &|_| Ok(vec![])).unwrap_err();
    assert!(matches!(err, OctreeError::PageIn(_)), "{err}");
    // Plain add_batch refuses to split a paged-out leaf.
    assert!(matches!(b.add_batch(&pts[900..]), Err(OctreeError::PageIn(_))));
    assert_eq!(b.input_points(), 900);
}

#[test]
fn duplicates_stop_at_the_size_limit() {
    let root = Cube::new([0; 3], 20);
    let pts: Vec<Point> = (0..10_000).map(|i| point([777, 12345, 99], i as u32, i)).collect();
    let (b, snaps) = build(&pts, root, config(16, ColorMode::FirstCome), 2_500);
    let s = snaps.last().unwrap();
    let leaf = s.node(s.leaf_at([777, 12345, 99]).unwrap());
    assert_eq!(leaf.point_count(), 10_000);
    assert_eq!(leaf.cube().size_log2, MIN_INNER_SIZE_LOG2 - 1);
    assert_eq!(leaf.level(), 20 - 6);
    // one split per level: 8 children each
    assert_eq!(b.node_count(), 1 + 8 * 14);
    check_invariants(s, &pts);
    // every inner node has exactly one voxel
    assert!(s.iter().filter(|(_, n)| !n.is_leaf()).all(|(_, n)| n.voxel_count() == 1));
}

#[test]
fn max_level_is_respected() {
    let root = Cube::new([0; 3], 20);
    let pts = random_points(20_000, 41, [0; 3], 1 << 20);
    let cfg = BuilderConfig { leaf_capacity: 10, max_level: 2, ..BuilderConfig::default() };
    let (b, snaps) = build(&pts, root, cfg, 5_000);
    assert_eq!(b.node_count(), 1 + 8 + 64);
    assert!(snaps.last().unwrap().iter().all(|(_, n)| n.level() <= 2));
    check_invariants(snaps.last().unwrap(), &pts);
    assert_eq!(reference(&pts, root, cfg), canon(flatten(snaps.last().unwrap())));
}

#[test]
fn a_full_voxel_grid() {
    // a 128-unit root with every cell occupied (plus duplicates): exactly 128³ voxels
    let root = Cube::new([0; 3], 7);
    let mut pts = Vec::with_capacity(1 << 21);
    for z in 0..128 {
        for y in 0..128 {
            for x in 0..128 {
                pts.push(point([x, y, z], (x ^ y ^ z) as u32, pts.len() as u64));
            }
        }
    }
    pts.extend(
        random_points(10_000, 51, [0; 3], 128)
            .into_iter()
            .map(|p| Point { record: p.record + (1 << 21), ..p }),
    );
    let mut b = Builder::new(root, config(1, ColorMode::FirstCome)).unwrap();
    for c in pts.chunks(1 << 20) {
        b.add_batch(c).unwrap();
    }
    let s = b.snapshot();
    let r = s.node(NodeId::ROOT);
    assert_eq!(r.voxel_count(), 128 * 128 * 128);
    assert_eq!(s.node_count(), 9);
    assert_eq!(s.point_count(), pts.len() as u64);
    // first come: the grid points came first, so each voxel has its grid point's colour
    assert!(r.voxels().unwrap().iter().all(|v| v.color == (v.pos[0] ^ v.pos[1] ^ v.pos[2]) as u32));
    // per octant: 512 bricks of 64 bytes plus a 1 KiB table
    assert_eq!(b.sampling_bytes(), 8 * (512 * 64 + 1024));
}

#[test]
fn occupancy_is_compact() {
    // a plane of points: an inner node holds far less than a dense 256 KiB grid
    let root = Cube::new([0; 3], 16);
    let mut r = Rng(61);
    let pts: Vec<Point> = (0..200_000)
        .map(|i| point([r.below(1 << 16) as i32, r.below(1 << 16) as i32, 1000], 0, i))
        .collect();
    let (b, snaps) = build(&pts, root, config(5_000, ColorMode::FirstCome), 100_000);
    let inner = snaps.last().unwrap().iter().filter(|(_, n)| !n.is_leaf()).count();
    assert!(inner >= 5);
    assert!(
        b.sampling_bytes() < inner * 40 * 1024,
        "{} bytes for {inner} inner nodes",
        b.sampling_bytes()
    );
}

#[test]
fn changed_since_names_the_touched_nodes() {
    let root = Cube::new([0; 3], 16);
    let pts = random_points(5_000, 71, [0; 3], 1 << 16);
    let mut b = Builder::new(root, config(100, ColorMode::FirstCome)).unwrap();
    b.add_batch(&pts).unwrap();
    let s1 = b.snapshot();
    assert_eq!(s1.changed_since(0).count(), s1.node_count());
    // one more point in a corner: only the nodes on its path change
    let p = point([3, 3, 3], 0, 9_999);
    b.add_batch(&[p]).unwrap();
    let s2 = b.snapshot();
    let changed: Vec<NodeKey> = s2.changed_since(s1.revision()).map(|(_, n)| n.key()).collect();
    let leaf = s2.node(s2.leaf_at(p.pos).unwrap()).key();
    assert!(changed.contains(&leaf));
    for (id, n) in s2.changed_since(s1.revision()) {
        // on the point's path, or new (children of a split on the path)
        let on_path = n.cube().contains(p.pos);
        let new_sibling = id.index() >= s1.node_count()
            && s2.node(s2.leaf_at(p.pos).unwrap()).key().parent() == n.key().parent();
        assert!(on_path || new_sibling, "{} changed", n.key().name());
    }
    // an unchanged node is the same allocation in both snapshots
    let (id, _) = s1.iter().find(|(_, n)| n.key().level == 1 && n.key().octant() == 7).unwrap();
    assert!(std::sync::Arc::ptr_eq(&s1.nodes()[id.index()], &s2.nodes()[id.index()]));
}

#[test]
fn errors_leave_the_builder_unchanged() {
    assert_eq!(
        Builder::new(Cube::new([0; 3], 4), config(0, ColorMode::FirstCome)).unwrap_err(),
        OctreeError::ZeroCapacity
    );
    assert_eq!(
        Builder::new(Cube::new([0; 3], 33), BuilderConfig::default()).unwrap_err(),
        OctreeError::RootTooLarge { size_log2: 33 }
    );
    let b = Builder::for_bounds([0; 3], [100, 50, 10], config(4, ColorMode::FirstCome)).unwrap();
    assert_eq!(b.root(), Cube::new([0; 3], 7));
    // A root of 2^31 units from -5 grows once, downwards for i32::MIN; then the 2^32 cube ends
    // before i32::MAX, and the root cannot grow further.
    let mut b = Builder::new(Cube::new([-5; 3], 31), config(4, ColorMode::FirstCome)).unwrap();
    b.add_batch(&random_points(100, 81, [0; 3], 100)).unwrap();
    let before = flatten(&b.snapshot());
    let bad =
        [point([1, 1, 1], 0, 0), point([i32::MIN, 0, 0], 0, 1), point([i32::MAX, 0, 0], 0, 2)];
    let err = b.add_batch(&bad).unwrap_err();
    assert_eq!(
        err,
        OctreeError::PointOutsideRoot {
            index: 2,
            pos: [i32::MAX, 0, 0],
            min: [-5 - (1 << 31), -5, -5],
            size: 1 << 32
        }
    );
    assert!(err.to_string().contains("outside the octree's root cube"));
    assert!(flatten(&b.snapshot()) == before);
    assert_eq!(b.revision(), 1);
    assert_eq!(b.input_points(), 100);
    // empty batches change nothing
    assert_eq!(b.add_batch(&[]).unwrap().points, 0);
    assert_eq!(b.revision(), 1);
    // Debug output summarizes
    assert!(format!("{b:?} {:?}", b.snapshot()).len() < 400);
    assert!(format!("{:?}", b.snapshot().node(NodeId::ROOT)).len() < 400);
}

#[test]
fn the_whole_i32_range() {
    let pts = vec![
        point([i32::MIN; 3], 1, 0),
        point([i32::MAX; 3], 2, 1),
        point([0, 0, 0], 3, 2),
        point([i32::MIN, i32::MAX, 0], 4, 3),
        point([-1, -1, -1], 5, 4),
    ];
    let root = Cube::covering([i32::MIN; 3], [i32::MAX; 3]);
    for mode in [ColorMode::FirstCome, ColorMode::Averaged] {
        let cfg = config(1, mode);
        let (_, snaps) = build(&pts, root, cfg, 2);
        check_invariants(snaps.last().unwrap(), &pts);
        assert_eq!(canon(flatten(snaps.last().unwrap())), reference(&pts, root, cfg));
    }
}

#[test]
fn snapshots_cross_threads() {
    fn assert_send_sync<T: Send + Sync>() {}
    assert_send_sync::<Snapshot>();
    assert_send_sync::<Builder>();
    let root = Cube::new([0; 3], 16);
    let pts = random_points(10_000, 91, [0; 3], 1 << 16);
    let mut b = Builder::new(root, config(500, ColorMode::FirstCome)).unwrap();
    b.add_batch(&pts[..5_000]).unwrap();
    let s = b.snapshot();
    let reader = std::thread::spawn(move || s.point_count());
    b.add_batch(&pts[5_000..]).unwrap();
    assert_eq!(reader.join().unwrap(), 5_000);
    assert_eq!(b.snapshot().point_count(), 10_000);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    /// A root far too small for the points grows (a new root above the old one, as often as
    /// needed, in any direction): the leaves, their points in arrival order, the subtree counts
    /// and the occupied voxel cells are those of a tree built over the grown root from the
    /// start; only the representatives of the grown roots' cells may be other points of the
    /// same cells.
    #[test]
    fn a_growing_root_matches_the_reference(
        raw in prop::collection::vec((prop::array::uniform3(0u32..4096), any::<u32>()), 1..500),
        start in prop::array::uniform3(0u32..4096),
        cap in 1u32..30,
        cuts in prop::collection::vec(1usize..150, 1..5),
        averaged in any::<bool>(),
        paged in any::<bool>(),
    ) {
        let pts: Vec<Point> = raw.iter().enumerate().map(|(i, (p, c))| point(p.map(|v| v as i32 - 2000), *c, i as u64)).collect();
        let mode = if averaged { ColorMode::Averaged } else { ColorMode::FirstCome };
        let cfg = config(cap, mode);
        let s0 = start.map(|v| v as i32 - 2000);
        let mut b = Builder::for_bounds(s0, s0, cfg).unwrap();
        // Paged: every leaf and voxel record saved after each batch, as a store does.
        let saved = std::sync::Mutex::new(std::collections::HashMap::<u32, Vec<Point>>::new());
        let mut at = 0;
        let mut grew = 0;
        for k in 0.. {
            if at >= pts.len() { break; }
            let end = (at + cuts[k % cuts.len()]).min(pts.len());
            let page_in = |id: NodeId| -> Result<Vec<Point>, String> { saved.lock().unwrap().get(&id.0).cloned().ok_or_else(|| format!("nothing saved for {}", id.0)) };
            grew += b.add_batch_paged(&pts[at..end], &page_in).unwrap().growths;
            if paged {
                // Save what a store would, then page out: a leaf's points (those saved before
                // and the resident ones), an inner node's voxels.
                let snap = b.snapshot();
                let mut sv = saved.lock().unwrap();
                for (id, n) in snap.iter() {
                    let mut all: Vec<Point> = Vec::new();
                    match n.voxels() {
                        Some(v) => all.extend(v.iter().map(|v| v.point())),
                        None => {
                            if n.paged_points() > 0 {
                                all.extend_from_slice(&sv[&id.0][..n.paged_points() as usize]);
                            }
                            all.extend(n.points().unwrap().iter().copied());
                        }
                    }
                    sv.insert(id.0, all);
                }
                drop(sv);
                b.page_out();
            }
            at = end;
        }
        let root = b.root();
        prop_assert!(pts.iter().all(|p| root.contains(p.pos)));
        if pts.iter().any(|p| p.pos != s0) { prop_assert!(grew > 0); }
        if !paged {
            check_invariants(&b.snapshot(), &pts);
        }
        let want = reference(&pts, root, cfg);
        let got = canon(flatten(&b.snapshot()));
        prop_assert_eq!(got.keys().collect::<Vec<_>>(), want.keys().collect::<Vec<_>>());
        for (k, w) in &want {
            let g = &got[k];
            prop_assert_eq!(g.leaf, w.leaf);
            prop_assert_eq!(g.cube, w.cube);
            prop_assert_eq!(g.subtree, w.subtree, "subtree of {}", k.name());
            if !paged {
                prop_assert_eq!(&g.points, &w.points, "points of {}", k.name());
            }
            let cells = |v: &[Voxel]| v.iter().map(|x| w.cube.voxel_of(x.pos)).collect::<HashSet<_>>();
            prop_assert_eq!(cells(&g.voxels), cells(&w.voxels), "voxel cells of {}", k.name());
            // Every representative is a source point of its cell.
            for v in &g.voxels {
                prop_assert!(pts.iter().any(|p| p.pos == v.pos && p.record == v.record));
            }
        }
    }

    #[test]
    fn matches_reference(
        raw in prop::collection::vec((prop::array::uniform3(0u32..4096), any::<u32>()), 0..600),
        extent_log2 in 0u8..12,
        cap in 1u32..40,
        cuts in prop::collection::vec(1usize..200, 1..6),
        averaged in any::<bool>(),
    ) {
        let extent = 1u32 << extent_log2;
        let pts: Vec<Point> = raw.iter().enumerate()
            .map(|(i, (p, c))| point(p.map(|v| (v % extent) as i32 - 50), *c, i as u64))
            .collect();
        let root = Cube::new([-50; 3], 12);
        let mode = if averaged { ColorMode::Averaged } else { ColorMode::FirstCome };
        let cfg = config(cap, mode);
        let mut b = Builder::new(root, cfg).unwrap();
        let mut start = 0;
        let mut prev = b.snapshot();
        for k in 0.. {
            if start >= pts.len() { break; }
            let end = (start + cuts[k % cuts.len()]).min(pts.len());
            b.add_batch(&pts[start..end]).unwrap();
            let s = b.snapshot();
            check_monotone(&prev, &s);
            prev = s;
            start = end;
        }
        let s = b.snapshot();
        check_invariants(&s, &pts);
        prop_assert!(canon(flatten(&s)) == reference(&pts, root, cfg));
    }
}

/// Time of `add_batch` for batches of 1 M points (run with `--ignored --nocapture`): uniform
/// random points in a cube (the worst case: every grid fills up) and random points on a terrain
/// surface, in random order.
#[test]
#[ignore]
fn time_one_million_random_points() {
    let root = Cube::new([0; 3], 24);
    let n = 1 << 20;
    let terrain = |seed: u64| -> Vec<Point> {
        let mut r = Rng(seed);
        (0..n)
            .map(|i| {
                let x = r.below(1 << 24) as f64;
                let y = r.below(1 << 24) as f64;
                let z = (1 << 22) as f64 * (1.5 + (x / 900_000.0).sin() * (y / 1_300_000.0).cos())
                    + r.below(64) as f64;
                point([x as i32, y as i32, z as i32], r.next() as u32, i as u64)
            })
            .collect()
    };
    for (name, cube) in [("cube", true), ("terrain", false)] {
        for mode in [ColorMode::FirstCome, ColorMode::Averaged] {
            let mut b =
                Builder::new(root, BuilderConfig { color_mode: mode, ..BuilderConfig::default() })
                    .unwrap();
            let mut sum = std::time::Duration::ZERO;
            for k in 0..4u64 {
                let pts = if cube {
                    random_points(n, 100 + k, [0; 3], 1 << 24)
                } else {
                    terrain(200 + k)
                };
                let pts: Vec<Point> = pts
                    .into_iter()
                    .map(|p| Point { record: p.record + k * n as u64, ..p })
                    .collect();
                let t = std::time::Instant::now();
                let st = b.add_batch(&pts).unwrap();
                let total = t.elapsed();
                sum += total;
                let snap = std::time::Instant::now();
                let s = b.snapshot();
                let snap = snap.elapsed();
                eprintln!(
                    "{name} {mode:?} batch {k}: {n} points in {total:.1?} ({:.1} M points/s; expand {:.1?} in {} passes, sample_voxels {:.1?}, insert_points {:.1?}, insert_voxels {:.1?}, publish {:.1?}); {} spilled, {} splits, {} new voxels, {} nodes; snapshot {snap:.1?}; threads {}",
                    n as f64 / total.as_secs_f64() / 1e6,
                    st.times.expand,
                    st.expand_iterations,
                    st.times.sample_voxels,
                    st.times.insert_points,
                    st.times.insert_voxels,
                    st.times.publish,
                    st.spilled,
                    st.splits,
                    st.new_voxels,
                    s.node_count(),
                    rayon::current_num_threads(),
                );
            }
            eprintln!(
                "{name} {mode:?}: 4 batches in {sum:.1?}, {:.1} M points/s; sampling state {} KiB",
                4.0 * n as f64 / sum.as_secs_f64() / 1e6,
                b.sampling_bytes() / 1024
            );
        }
    }
}

/// The points in full-resolution Morton order relative to `root.min` (ties by record).
fn morton_sorted(points: &[Point], root: Cube) -> Vec<Point> {
    let mut s = points.to_vec();
    // The octant of a cube is x | y << 1 | z << 2 of the offset's upper bit: z is the high bit.
    s.sort_by_key(|p| {
        let o = [0, 1, 2].map(|a| (p.pos[a] as i64 - root.min[a]) as u64);
        let mut c = 0u128;
        for bit in (0..33).rev() {
            c = c << 3
                | (((o[2] >> bit) & 1) << 2 | ((o[1] >> bit) & 1) << 1 | ((o[0] >> bit) & 1))
                    as u128;
        }
        (c, p.record)
    });
    s
}

/// The tree [`build_sorted`] makes, flattened like [`flatten`] (leaf points in record order, voxels canonical).
fn sorted_flat(points: &[Point], root: Cube, cfg: BuilderConfig) -> BTreeMap<NodeKey, Flat> {
    let s = morton_sorted(points, root);
    let pos: Vec<[i32; 3]> = s.iter().map(|p| p.pos).collect();
    let tree =
        build_sorted(root, pos.len(), &|i: usize| pos[i], &|i: usize| s[i].record, cfg).unwrap();
    // Levels in order, the root first.
    let levels: Vec<u8> = tree.nodes.iter().map(|n| n.key.level).collect();
    assert!(levels.windows(2).all(|w| w[0] <= w[1]));
    assert_eq!(tree.nodes[0].key, NodeKey::ROOT);
    let mut out = BTreeMap::new();
    let mut sub: HashMap<NodeKey, u64> = HashMap::new();
    for n in tree.nodes.iter().rev() {
        let f = match &n.content {
            SortedContent::Leaf(r) => {
                let mut points = s[r.clone()].to_vec();
                points.sort_by_key(|p| p.record);
                Flat {
                    leaf: true,
                    cube: n.cube,
                    subtree: points.len() as u64,
                    points,
                    voxels: vec![],
                }
            }
            SortedContent::Inner(v) => {
                // Voxels are in the Morton order of their cells.
                let cells: Vec<[u8; 3]> =
                    v.iter().map(|&i| n.cube.voxel_of(s[i as usize].pos)).collect();
                let mut uniq = cells.clone();
                uniq.dedup();
                assert_eq!(uniq.len(), cells.len(), "one voxel per cell in {}", n.key.name());
                let subtree = (0..8).map(|o| sub[&n.key.child(o)]).sum();
                Flat {
                    leaf: false,
                    cube: n.cube,
                    points: vec![],
                    voxels: v
                        .iter()
                        .map(|&i| Voxel::of(&s[i as usize], s[i as usize].color))
                        .collect(),
                    subtree,
                }
            }
        };
        sub.insert(n.key, f.subtree);
        out.insert(n.key, f);
    }
    let mut r = canon(out);
    for f in r.values_mut() {
        f.points.sort_by_key(|p| p.record);
    }
    r
}

fn reference_by_record(
    points: &[Point],
    root: Cube,
    cfg: BuilderConfig,
) -> BTreeMap<NodeKey, Flat> {
    let mut r = reference(points, root, cfg);
    for f in r.values_mut() {
        f.points.sort_by_key(|p| p.record);
    }
    r
}

#[test]
fn the_sorted_build_matches_the_reference() {
    let cfg = config(300, ColorMode::FirstCome);
    let root = Cube::new([0; 3], 16);
    for (name, pts) in [
        ("random", random_points(20_000, 3, [0; 3], 1 << 16)),
        ("clustered", clustered_points(20_000, 4, 1 << 16)),
        ("duplicates", duplicate_points(5_000, 5)),
        ("small", random_points(200, 6, [0; 3], 1 << 16)),
        ("empty", Vec::new()),
    ] {
        assert!(sorted_flat(&pts, root, cfg) == reference_by_record(&pts, root, cfg), "{name}");
    }
    // Against the incremental builder too, batched.
    let pts = clustered_points(30_000, 9, 1 << 16);
    let (b, _) = build(&pts, root, cfg, 7_000);
    let mut inc = canon(flatten(&b.snapshot()));
    for f in inc.values_mut() {
        f.points.sort_by_key(|p| p.record);
    }
    assert!(sorted_flat(&pts, root, cfg) == inc);
}

#[test]
fn the_sorted_build_refuses_what_it_cannot_build() {
    let root = Cube::new([0; 3], 10);
    let pos = [[5, 5, 5], [2000, 0, 0]];
    assert!(matches!(
        build_sorted(
            root,
            2,
            &|i: usize| pos[i],
            &|i: usize| i as u64,
            config(1, ColorMode::FirstCome)
        ),
        Err(OctreeError::PointOutsideRoot { index: 1, .. })
    ));
    assert!(matches!(
        build_sorted(
            root,
            1,
            &|i: usize| pos[i],
            &|i: usize| i as u64,
            config(1, ColorMode::Averaged)
        ),
        Err(OctreeError::Unsupported(_))
    ));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]
    #[test]
    fn the_sorted_build_matches_the_reference_everywhere(
        raw in prop::collection::vec((prop::array::uniform3(0u32..4096), any::<u32>()), 0..800),
        extent_log2 in 0u8..12,
        cap in 1u32..40,
        max_level in 1u8..8,
    ) {
        let extent = 1u32 << extent_log2;
        let pts: Vec<Point> = raw.iter().enumerate()
            .map(|(i, (p, c))| point(p.map(|v| (v % extent) as i32 - 50), *c, i as u64))
            .collect();
        let root = Cube::new([-50; 3], 12);
        let cfg = BuilderConfig { max_level, ..config(cap, ColorMode::FirstCome) };
        prop_assert!(sorted_flat(&pts, root, cfg) == reference_by_record(&pts, root, cfg));
    }
}
