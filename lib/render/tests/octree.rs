//! The GPU octree builder (issue 29) against its CPU twin, `mortar_core::octree::arrival`: the
//! same nodes, the same voxels, and every point in a slot of its leaf's range (the order inside
//! a leaf is left to the atomics). Runs on any adapter, lavapipe in CI.

use mortar_core::octree::arrival::{build_arrival, leaf_bases, ArrivalTree, NO_CHILD};
use mortar_core::octree::{BuilderConfig, Cube, SortedContent, SortedNode};
use mortar_render::context::AtomicPath;
use mortar_render::octree::GpuTreeBuilder;
use mortar_render::testing::context_or_skip;

fn rng(seed: &mut u64) -> u32 {
    *seed ^= *seed << 13;
    *seed ^= *seed >> 7;
    *seed ^= *seed << 17;
    (*seed >> 16) as u32
}

/// Per point, the depth-first number of its leaf (from the range its slot is in).
fn leaves_of(t: &ArrivalTree) -> Vec<u32> {
    let bases = leaf_bases(&t.nodes);
    let mut starts: Vec<u32> = t
        .nodes
        .iter()
        .enumerate()
        .filter(|(_, n)| n.first_child == NO_CHILD && n.count > 0)
        .map(|(i, _)| bases[i])
        .collect();
    starts.sort_unstable();
    let mut seen = vec![false; t.slot.len()];
    t.slot
        .iter()
        .map(|&s| {
            assert!(!seen[s as usize], "slot {s} given twice");
            seen[s as usize] = true;
            (starts.partition_point(|&b| b <= s) - 1) as u32
        })
        .collect()
}

/// The same tree: the same nodes by key, leaves with the same counts, the same voxels, every
/// point in the same leaf. (Node ids follow the order of the GPU's atomics.)
fn same(gpu: &ArrivalTree, cpu: &ArrivalTree, what: &str) {
    assert_eq!(leaves_of(gpu), leaves_of(cpu), "{what}: leaves of the points");
    let root = Cube::new([0; 3], 32);
    let (g, c) = (gpu.clone().into_sorted(root, |a| a), cpu.clone().into_sorted(root, |a| a));
    assert_eq!(g.unwrap().nodes, c.unwrap().nodes, "{what}: nodes");
}

/// The same nodes (keys, leaf ranges, voxels), the first difference named without printing
/// the trees.
fn same_nodes(g: &[SortedNode], c: &[SortedNode], what: &str) {
    assert_eq!(g.len(), c.len(), "{what}: nodes");
    if let Some(i) = (0..g.len()).find(|&i| g[i] != c[i]) {
        let (a, b) = (&g[i], &c[i]);
        let diff = match (&a.content, &b.content) {
            (SortedContent::Inner(x), SortedContent::Inner(y)) => {
                let k = (0..x.len().min(y.len())).find(|&k| x[k] != y[k]);
                format!("voxels {} / {}, first difference at {k:?}", x.len(), y.len())
            }
            _ => "contents differ".to_string(),
        };
        panic!("{what}: node {i} ({:?}) differs: {diff}", a.key);
    }
}

#[test]
fn the_gpu_builds_the_cpu_twins_tree() {
    let Some(ctx) = context_or_skip(AtomicPath::TwoPass32, Some(7)) else { return };
    // Small segments: several batches, reassignments across segments, split dispatches.
    let gpu = GpuTreeBuilder::new(ctx).unwrap().with_segment_points(2_000);
    let mut seed = 0x2545f4914f6cdd1du64;
    let cases: [(usize, u8, u32, u32); 6] = [
        (0, 10, 5, 10),
        (1, 10, 5, 10),
        (9_000, 18, 50, 18),
        (20_000, 12, 30, 5),
        (6_000, 24, 100, 24),
        (5_000, 32, 64, 32),
    ];
    for (n, size_log2, cap, spread) in cases {
        let pos: Vec<[u32; 3]> = (0..n)
            .map(|_| {
                [0; 3].map(|_| {
                    let v = rng(&mut seed) as u64 % (1u64 << spread);
                    (v << (size_log2 as u32 - spread)) as u32
                })
            })
            .collect();
        let config = BuilderConfig { leaf_capacity: cap, ..BuilderConfig::default() };
        let cpu = build_arrival(size_log2, &pos, &config).unwrap();
        let g = gpu.build_tree(size_log2, &pos, &config).unwrap();
        same(&g, &cpu, &format!("{n} points in 2^{size_log2}, capacity {cap}"));
    }
}

#[test]
fn uploads_and_read_backs_cut_into_small_parts_give_the_same_tree() {
    let Some(ctx) = context_or_skip(AtomicPath::TwoPass32, None) else { return };
    // Transfers of 4,092 bytes (341 points, the last part short), two segments paged out and in
    // again (their leaves uploaded and read back in parts too), against the twin.
    let gpu = GpuTreeBuilder::new(ctx)
        .unwrap()
        .with_transfer_bytes(4_094)
        .with_segment_points(7_000)
        .with_resident_segments(1);
    let mut seed = 0x9e3779b97f4a7c15u64;
    let pos: Vec<[u32; 3]> =
        (0..20_000).map(|_| [0; 3].map(|_| rng(&mut seed) % (1 << 20))).collect();
    let config = BuilderConfig { leaf_capacity: 40, ..BuilderConfig::default() };
    let cpu = build_arrival(20, &pos, &config).unwrap();
    let g = gpu.build_tree(20, &pos, &config).unwrap();
    same(&g, &cpu, "transfers in parts");
    // The transfers are counted: every point's position at least once, and the leaves of the
    // segments paged back in.
    let step = |name: &str| g.phases.iter().find(|(n, _)| n == name).map(|p| p.1);
    let up = step("upload bytes").expect("upload bytes reported");
    assert!(up >= 12.0 * 20_000.0 + 4.0 * 7_000.0, "{up} bytes uploaded");
    assert!(step("upload seconds").is_some_and(|s| s > 0.0));
}

#[test]
fn coincident_points_depth_limits_and_a_growing_node_buffer() {
    let Some(ctx) = context_or_skip(AtomicPath::TwoPass32, None) else { return };
    // A node buffer of 20 nodes at first: grown many times, in the middle of split passes.
    let gpu = GpuTreeBuilder::new(ctx).unwrap().with_segment_points(3_000).with_first_nodes(20);
    // All at one position, plus a spread: leaves beyond the depth limit keep their points.
    let mut pos = vec![[1000u32, 77, 5]; 7_000];
    pos.extend((0..5_000u32).map(|i| [i * 7919 % 65536, i * 104_729 % 65536, i * 13 % 65536]));
    for config in [
        BuilderConfig { leaf_capacity: 20, ..BuilderConfig::default() },
        BuilderConfig { leaf_capacity: 3, max_level: 3, ..BuilderConfig::default() },
        BuilderConfig { leaf_capacity: 1, ..BuilderConfig::default() },
    ] {
        let cpu = build_arrival(16, &pos, &config).unwrap();
        let g = gpu.build_tree(16, &pos, &config).unwrap();
        same(&g, &cpu, &format!("{config:?}"));
    }
    assert!(gpu.build_tree(4, &[[16, 0, 0]], &BuilderConfig::default()).is_err());
}

#[test]
fn paged_segments_give_the_same_tree() {
    // Issue 29 item 2: segments paged out (their leaves read back) and in again as the passes
    // need them, with one or two segments on the GPU at a time.
    let Some(ctx) = context_or_skip(AtomicPath::TwoPass32, None) else { return };
    let mut seed = 0x853c49e6748fea9bu64;
    let pos: Vec<[u32; 3]> =
        (0..15_000).map(|_| [0; 3].map(|_| rng(&mut seed) % (1 << 20))).collect();
    let config = BuilderConfig { leaf_capacity: 40, ..BuilderConfig::default() };
    let cpu = build_arrival(20, &pos, &config).unwrap();
    let gpu = GpuTreeBuilder::new(ctx).unwrap().with_segment_points(1_000);
    assert!(gpu.with_memory_budget(1 << 20).is_err(), "a budget below the minimum is refused");
    let ctx = context_or_skip(AtomicPath::TwoPass32, None).unwrap();
    let mut gpu = GpuTreeBuilder::new(ctx)
        .unwrap()
        .with_segment_points(1_000)
        .with_memory_budget(mortar_render::octree::MIN_GPU_MEMORY)
        .unwrap();
    let walks = |t: &ArrivalTree| {
        t.phases.iter().find(|(k, _)| k == "voxel walks").map(|(_, v)| *v as u32).unwrap()
    };
    let root = Cube::new([0; 3], 32);
    let cpu_nodes = cpu.clone().into_sorted(root, |a| a).unwrap().nodes;
    for resident in [1, 2] {
        gpu = gpu.with_resident_segments(resident);
        let g = gpu.build_tree(20, &pos, &config).unwrap();
        same(&g, &cpu, &format!("{resident} segments on the GPU"));
        // Without slots (the store's engine) the voxel passes walk the points in leaf order,
        // their arrival numbers beside them: the same nodes and voxels, in fewer walks.
        let h = gpu.build_tree_with(20, &pos, &config, false).unwrap();
        let what = format!("{resident} segments on the GPU, in leaf order");
        same_nodes(&h.clone().into_sorted(root, |a| a).unwrap().nodes, &cpu_nodes, &what);
        assert!(walks(&h) < walks(&g), "{what}: {} walks against {}", walks(&h), walks(&g));
    }
}

#[test]
fn leaf_order_walks_follow_the_groups() {
    // Points along "flight lines" (each segment crosses the scene, as an airborne scan's
    // arrival order does) under the smallest budget: in leaf order the voxel groups walk a few
    // segments each, and the voxels stay the CPU twin's (first come by arrival, ties between
    // points at one position and between coincident lines included).
    let Some(ctx) = context_or_skip(AtomicPath::TwoPass32, None) else { return };
    let mut seed = 0x2545f4914f6cdd1du64;
    let mut pos: Vec<[u32; 3]> = Vec::new();
    for line in 0..40u32 {
        let y = (line % 20) * (1 << 15) + rng(&mut seed) % 1024;
        for k in 0..1_000u32 {
            pos.push([k * 1024 + rng(&mut seed) % 64, y, rng(&mut seed) % 4096]);
        }
    }
    let config = BuilderConfig { leaf_capacity: 60, ..BuilderConfig::default() };
    let cpu = build_arrival(20, &pos, &config).unwrap();
    let root = Cube::new([0; 3], 32);
    let gpu = GpuTreeBuilder::new(ctx)
        .unwrap()
        .with_segment_points(2_000)
        .with_memory_budget(mortar_render::octree::MIN_GPU_MEMORY)
        .unwrap()
        .with_resident_segments(2);
    let g = gpu.build_tree_with(20, &pos, &config, false).unwrap();
    // With slots the segments keep arrival order: each line crosses most groups.
    let a = gpu.build_tree(20, &pos, &config).unwrap();
    let walks = |t: &ArrivalTree| {
        t.phases.iter().find(|(k, _)| k == "voxel walks").map(|(_, v)| *v as u32).unwrap()
    };
    assert!(
        walks(&g) < walks(&a),
        "flight lines: {} walks in leaf order against {} in arrival order",
        walks(&g),
        walks(&a)
    );
    same(&a, &cpu, "flight lines in arrival order");
    same_nodes(
        &g.into_sorted(root, |a| a).unwrap().nodes,
        &cpu.into_sorted(root, |a| a).unwrap().nodes,
        "flight lines in leaf order",
    );
}

/// Without `--gpu-memory` the builder keeps within three quarters of the memory the adapter
/// reports (lavapipe reports a device-local heap of host memory; a GPU its own memory).
#[test]
fn the_default_budget_is_the_adapters_memory() {
    let Some(ctx) = context_or_skip(AtomicPath::TwoPass32, Some(7)) else { return };
    let reported = ctx.device_memory();
    let backend = ctx.adapter().backend.clone();
    let gpu = GpuTreeBuilder::new(ctx).unwrap();
    if backend.to_lowercase().contains("vulkan") {
        let m = reported.expect("a Vulkan adapter reports its heaps");
        assert!(m >= 64 << 20, "{m} bytes of device memory");
        assert_eq!(gpu.memory_budget(), Some(mortar_render::octree::default_gpu_memory(m)));
        assert!(mortar_core::octree::arrival::TreeBackend::name(&gpu).contains("within"));
    } else {
        assert_eq!(gpu.memory_budget(), reported.map(mortar_render::octree::default_gpu_memory));
    }
    // An explicit budget wins.
    let gpu = gpu.with_memory_budget(64 << 20).unwrap();
    assert_eq!(gpu.memory_budget(), Some(64 << 20));
}
