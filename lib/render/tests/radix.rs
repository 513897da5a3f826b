//! The GPU radix sort (issue 29) against its CPU twin, `mortar_core::octree::arrival::
//! morton_order`: the same order of the points, ties (points at one position, points that
//! differ only in bits below a digit) in arrival order. Runs on any adapter, lavapipe in CI.

use mortar_core::octree::arrival::{check_order, morton_order};
use mortar_core::octree::BuilderConfig;
use mortar_render::context::AtomicPath;
use mortar_render::octree::GpuTreeBuilder;
use mortar_render::radix::GpuRadixSort;
use mortar_render::testing::context_or_skip;

fn rng(seed: &mut u64) -> u32 {
    *seed ^= *seed << 13;
    *seed ^= *seed >> 7;
    *seed ^= *seed << 17;
    (*seed >> 16) as u32
}

/// Points below `2^size_log2`: random, clustered (many in few cells) and repeated positions.
fn points(n: usize, size_log2: u8, seed: &mut u64) -> Vec<[u32; 3]> {
    let mask = |v: u32| if size_log2 >= 32 { v } else { v & ((1u32 << size_log2) - 1) };
    let mut v = Vec::with_capacity(n);
    for i in 0..n {
        let p = match i % 4 {
            0 | 1 => [rng(seed), rng(seed), rng(seed)].map(|x| mask(x ^ (x << 16))),
            // a few clusters of 8 units
            2 => [0, 1, 2].map(|a| mask((rng(seed) % 8) + (a as u32) * 1000)),
            // repeats of earlier points
            _ => v[rng(seed) as usize % v.len().max(1)],
        };
        v.push(p);
    }
    v
}

#[test]
fn the_gpu_sorts_as_the_cpu_twin() {
    let Some(ctx) = context_or_skip(AtomicPath::TwoPass32, Some(7)) else { return };
    let sort = GpuRadixSort::new(&ctx).unwrap();
    let mut seed = 0x9e3779b97f4a7c15u64;
    // (points, root size log2, points per segment): empty, one, less than a tile, tiles and a
    // part, several segments, a root of 32 bits (24 passes, 96-bit keys) and of 1 bit.
    let cases: [(usize, u8, usize); 8] = [
        (0, 10, 100),
        (1, 10, 100),
        (777, 12, 1000),
        (5_000, 20, 5_000),
        (20_011, 24, 3_000),
        (9_000, 32, 4_096),
        (3_000, 1, 1_000),
        (70_000, 17, 70_000),
    ];
    for (n, size_log2, seg) in cases {
        let pos = points(n, size_log2, &mut seed);
        let gpu = sort.sort(&ctx, &pos, size_log2, seg).unwrap();
        let cpu = morton_order(&pos);
        assert_eq!(gpu, cpu, "{n} points, root 2^{size_log2}, segments of {seg}");
        check_order(&pos, &gpu).unwrap();
    }
}

#[test]
fn an_order_out_of_order_is_refused() {
    let mut seed = 7u64;
    let pos = points(1_000, 16, &mut seed);
    let good = morton_order(&pos);
    check_order(&pos, &good).unwrap();
    let mut swapped = good.clone();
    swapped.swap(10, 11);
    assert!(check_order(&pos, &swapped).is_err());
    let mut repeated = good.clone();
    repeated[5] = repeated[4];
    assert!(check_order(&pos, &repeated).is_err());
    let mut outside = good.clone();
    outside[0] = 1_000;
    assert!(check_order(&pos, &outside).is_err());
    assert!(check_order(&pos, &good[1..]).is_err());
    // Points at one position: only arrival order is right.
    let same = vec![[5u32, 5, 5]; 10];
    check_order(&same, &(0..10).collect::<Vec<_>>()).unwrap();
    assert!(check_order(&same, &(0..10).rev().collect::<Vec<_>>()).is_err());
}

#[test]
fn the_builder_hands_over_the_order_before_the_tree() {
    let Some(ctx) = context_or_skip(AtomicPath::TwoPass32, Some(7)) else { return };
    let gpu = GpuTreeBuilder::new(ctx).unwrap().with_segment_points(3_000);
    let mut seed = 11u64;
    let pos = points(10_000, 18, &mut seed);
    let config = BuilderConfig { leaf_capacity: 200, ..BuilderConfig::default() };
    assert!(gpu.sorts_points(pos.len()));
    let got = std::cell::RefCell::new(None);
    let tree = gpu
        .build_tree_ordered(18, &pos, &config, false, Some(&|v| *got.borrow_mut() = Some(v)))
        .unwrap();
    assert_eq!(got.into_inner().unwrap(), morton_order(&pos));
    let plain = gpu.build_tree_with(18, &pos, &config, false).unwrap();
    let root = mortar_core::octree::Cube::new([0; 3], 18);
    assert_eq!(
        tree.into_sorted(root, |a| a).unwrap().nodes,
        plain.into_sorted(root, |a| a).unwrap().nodes
    );
    // Under a budget that pages segments the builder does not sort (the engine sorts on the
    // host then).
    let Some(ctx2) = context_or_skip(AtomicPath::TwoPass32, Some(7)) else { return };
    let paged =
        GpuTreeBuilder::new(ctx2).unwrap().with_segment_points(3_000).with_resident_segments(2);
    assert!(!paged.sorts_points(pos.len()));
}
