//! The octree of paper 004 as an unordered builder makes it (the GPU engine of `mortar build`,
//! issue 29; ARCHITECTURE.md, "The GPU engine"): points in arrival order go in, and out come the
//! nodes, the leaf slot of every point and the voxels of every inner node, with no sort.
//!
//! The algorithm is SimLOD's (paper 004 §5) with its races made deterministic:
//!
//! 1. *expand*: every point descends from the root to its leaf, which counts it; a leaf whose
//!    count exceeds the capacity (and that may split: [`super::splits`]) gets 8 children
//!    (consecutive ids), and its points descend again from it; repeated until no leaf splits;
//! 2. *voxels*: every point visits the inner nodes on its path and offers itself to its cell of
//!    their 128³ grid; the earliest arrival wins the cell (an atomic minimum of the arrival number
//!    on the GPU), which is the point the incremental and the sorted engines pick;
//! 3. *slots*: leaves are numbered depth first (octant order), each gets the range of the
//!    Morton-ordered points its cube holds, and each point a slot in its leaf's range (on the GPU
//!    in the order the atomics happen to run: the order inside a leaf is the caller's sort).
//!
//! [`ArrivalTree::into_sorted`] turns the result into the [`SortedTree`] that
//! [`build_sorted`](super::build_sorted) makes over the same points once the caller has put the
//! points of each leaf in Morton order: the same nodes, leaves and voxels. [`build_arrival`] is
//! the CPU twin of the GPU passes (`mortar_render::octree`), the reference they are tested
//! against; a [`TreeBackend`] is what the store's GPU engine calls (no files, no GPU here).

use super::cube::{Cube, NodeKey};
use super::sorted::{splits, SortedContent, SortedNode, SortedTree};
use super::types::{BuilderConfig, ColorMode, OctreeError, GRID_LOG2, MAX_ROOT_SIZE_LOG2};

/// No child: the node is a leaf (`first_child` of [`ArrivalNode`]; the root is never a child).
pub const NO_CHILD: u32 = 0;

/// One node of an [`ArrivalTree`] by id (the root is id 0; the children of an inner node are the
/// 8 consecutive ids from `first_child`, in octant order; ids are given in the order splits
/// happen, which on the GPU is the order of its atomics: compare trees by
/// [`ArrivalTree::into_sorted`], not by ids).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct ArrivalNode {
    /// A leaf's points (an inner node's count is what it held when it split: it depends on the
    /// batches and means nothing).
    pub count: u32,
    /// The id of its first child, or [`NO_CHILD`] for a leaf.
    pub first_child: u32,
}

/// The octree over points in arrival order (see the module docs).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ArrivalTree {
    /// The nodes by id.
    pub nodes: Vec<ArrivalNode>,
    /// Per point, in arrival order: its place in the leaf-grouped order (leaves depth first,
    /// each leaf's points in a range of its own; the order inside a range is unspecified).
    pub slot: Vec<u32>,
    /// Per node id: for an inner node, the arrival numbers of its voxels (the earliest point of
    /// each occupied cell of its 128³ grid) in the Morton order of the cells; empty for a leaf.
    pub voxels: Vec<Vec<u32>>,
    /// What the builder measured: (step, seconds), for reports.
    pub phases: Vec<(String, f64)>,
}

/// What builds an [`ArrivalTree`]: the GPU passes of `mortar_render::octree`, or
/// [`CpuArrival`]. The store's GPU engine holds one and calls it once per build.
pub trait TreeBackend: Send + Sync + std::fmt::Debug {
    /// A short description for reports (the adapter's name).
    fn name(&self) -> String;

    /// Whether the backend's buffers live in the process's own memory (a software adapter such
    /// as lavapipe, or this CPU twin), so that a memory budget must count them; a discrete GPU's
    /// do not. The default says yes (the safe answer).
    fn holds_buffers_in_host_memory(&self) -> bool {
        true
    }

    /// Builds the tree over a root cube `2^size_log2` units wide of the points `pos` (arrival
    /// order; coordinates relative to the root's corner, each below `2^size_log2`).
    fn build(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &BuilderConfig,
    ) -> Result<ArrivalTree, String>;

    /// [`build`](Self::build) without the slots (`slot` left empty), for a caller that puts
    /// the points in order itself (the store's GPU engine sorts them on the host while the
    /// tree is built); a backend may then skip the slot pass. The default builds them and
    /// drops them.
    fn build_without_slots(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &BuilderConfig,
    ) -> Result<ArrivalTree, String> {
        let mut tree = self.build(size_log2, pos, config)?;
        tree.slot = Vec::new();
        Ok(tree)
    }

    /// Whether [`build_ordered`](Self::build_ordered) puts `n` points in order on the backend
    /// itself (a GPU that holds them and the sort's buffers at once); the default says no.
    fn sorts(&self, _n: usize) -> bool {
        false
    }

    /// [`build_without_slots`](Self::build_without_slots), handing `order` the points' order
    /// ([`morton_order`]'s) as soon as it is known, before the tree is done: the caller
    /// gathers its records while the backend goes on. The default sorts on the CPU first.
    fn build_ordered(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &BuilderConfig,
        order: &dyn Fn(Vec<u32>),
    ) -> Result<ArrivalTree, String> {
        order(morton_order(pos));
        self.build_without_slots(size_log2, pos, config)
    }
}

/// The points `pos` (arrival order) in the order of their full-resolution Morton code
/// ([`crate::morton::encode96`]), ties by arrival: `order[i]` is the arrival number of the
/// `i`-th. The order of the sorted engine's sort, and the CPU twin of the GPU's radix sort
/// (`mortar_render::radix`).
pub fn morton_order(pos: &[[u32; 3]]) -> Vec<u32> {
    use rayon::prelude::*;
    let mut keys: Vec<(u128, u32)> =
        pos.par_iter().enumerate().map(|(i, &p)| (crate::morton::encode96(p), i as u32)).collect();
    keys.par_sort_unstable();
    keys.into_iter().map(|(_, i)| i).collect()
}

/// Checks that `order` is [`morton_order`] of `pos`: as many entries as points, each a point,
/// and each (Morton code, arrival) above the one before, which also makes the entries
/// distinct (a point's code is its own): what a backend's order must be before it is used.
pub fn check_order(pos: &[[u32; 3]], order: &[u32]) -> Result<(), String> {
    use rayon::prelude::*;
    let n = pos.len();
    if order.len() != n {
        return Err(format!("{} entries for {n} points", order.len()));
    }
    if let Some(&a) = order.par_iter().find_any(|&&a| a as usize >= n) {
        return Err(format!("entry {a} names no point of {n}"));
    }
    let key = |a: u32| (crate::morton::encode96(pos[a as usize]), a);
    match order.par_windows(2).position_any(|w| key(w[0]) >= key(w[1])) {
        Some(i) => Err(format!("entries {i} and {} are out of order", i + 1)),
        None => Ok(()),
    }
}

/// The CPU twin of the GPU passes ([`build_arrival`]) as a [`TreeBackend`] (tests, and the
/// reference the GPU is compared with).
#[derive(Clone, Copy, Debug, Default)]
pub struct CpuArrival;

impl TreeBackend for CpuArrival {
    fn name(&self) -> String {
        "cpu".into()
    }

    fn build(
        &self,
        size_log2: u8,
        pos: &[[u32; 3]],
        config: &BuilderConfig,
    ) -> Result<ArrivalTree, String> {
        build_arrival(size_log2, pos, config).map_err(|e| e.to_string())
    }
}

/// The Morton index of cell `c` (7 bits per axis) of a node's grid: `x | y << 1 | z << 2` per
/// bit, as `shaders/octree_common.wgsl` computes it.
#[inline]
pub fn cell_morton(c: [u32; 3]) -> u32 {
    crate::morton::encode(c[0], c[1], c[2]) as u32
}

/// The cell of relative position `p` in the grid of a node with corner `min` and size
/// `2^size_log2` (at least `2^GRID_LOG2`).
#[inline]
pub fn cell_of(p: [u32; 3], min: [u32; 3], size_log2: u8) -> [u32; 3] {
    let s = (size_log2 - GRID_LOG2) as u32;
    [0, 1, 2].map(|a| (p[a] - min[a]) >> s)
}

/// A node's cube while building: corner (relative to the root's), size, level.
#[derive(Clone, Copy)]
struct Place {
    min: [u32; 3],
    size_log2: u8,
    level: u8,
}

impl Place {
    fn octant(&self, p: [u32; 3]) -> u32 {
        let b = self.size_log2 as u32 - 1;
        (0..3).map(|a| (((p[a] - self.min[a]) >> b) & 1) << a).sum()
    }

    fn child(&self, o: u32) -> Place {
        let h = 1u32 << (self.size_log2 - 1);
        Place {
            min: [0, 1, 2].map(|a| self.min[a] + if o >> a & 1 == 1 { h } else { 0 }),
            size_log2: self.size_log2 - 1,
            level: self.level + 1,
        }
    }

    fn cube(&self) -> Cube {
        Cube::new(self.min.map(|v| v as i64), self.size_log2)
    }
}

/// Builds the [`ArrivalTree`] of `pos` (see [`TreeBackend::build`]) on the CPU, in the GPU
/// passes' steps: expand by counting and splitting until no leaf splits, the earliest arrival per
/// cell of every inner node, slots in arrival order within each leaf.
pub fn build_arrival(
    size_log2: u8,
    pos: &[[u32; 3]],
    config: &BuilderConfig,
) -> Result<ArrivalTree, OctreeError> {
    check(size_log2, pos.len(), config)?;
    if let Some(index) = pos.iter().position(|p| p.iter().any(|&v| (v as u64) >> size_log2 != 0)) {
        let p = pos[index];
        return Err(OctreeError::PointOutsideRoot {
            index,
            pos: p.map(|v| v as i32),
            min: [0; 3],
            size: 1u64 << size_log2,
        });
    }
    let mut places = vec![Place { min: [0; 3], size_log2, level: 0 }];
    let mut nodes = vec![ArrivalNode::default()];
    let descend = |nodes: &[ArrivalNode], places: &[Place], mut n: usize, p: [u32; 3]| {
        while nodes[n].first_child != NO_CHILD {
            n = (nodes[n].first_child + places[n].octant(p)) as usize;
        }
        n
    };
    // expand: all points as one batch (the GPU engine's batches give the same tree).
    let mut leaf: Vec<u32> = vec![0; pos.len()];
    for (i, &p) in pos.iter().enumerate() {
        let n = descend(&nodes, &places, 0, p);
        leaf[i] = n as u32;
        nodes[n].count += 1;
    }
    loop {
        let mut split = false;
        for n in 0..nodes.len() {
            let pl = places[n];
            let key = NodeKey { level: pl.level, index: [0; 3] };
            if nodes[n].first_child == NO_CHILD
                && splits(nodes[n].count as u64, key, pl.cube(), config)
            {
                nodes[n].first_child = nodes.len() as u32;
                for o in 0..8 {
                    nodes.push(ArrivalNode::default());
                    places.push(pl.child(o));
                }
                split = true;
            }
        }
        if !split {
            break;
        }
        for (i, &p) in pos.iter().enumerate() {
            let l = leaf[i] as usize;
            if nodes[l].first_child != NO_CHILD {
                let n = descend(&nodes, &places, l, p);
                leaf[i] = n as u32;
                nodes[n].count += 1;
            }
        }
    }
    // voxels: (node, cell, arrival), the earliest per (node, cell).
    let mut offers: Vec<(u32, u32, u32)> = Vec::new();
    for (i, &p) in pos.iter().enumerate() {
        let mut n = 0usize;
        while nodes[n].first_child != NO_CHILD {
            let pl = places[n];
            offers.push((n as u32, cell_morton(cell_of(p, pl.min, pl.size_log2)), i as u32));
            n = (nodes[n].first_child + pl.octant(p)) as usize;
        }
    }
    offers.sort_unstable();
    offers.dedup_by_key(|o| (o.0, o.1));
    let mut voxels = vec![Vec::new(); nodes.len()];
    for (n, _, a) in offers {
        voxels[n as usize].push(a);
    }
    // slots: leaves depth first, points in arrival order within a leaf.
    let mut cursor = leaf_bases(&nodes);
    let slot = leaf
        .iter()
        .map(|&l| {
            let s = cursor[l as usize];
            cursor[l as usize] += 1;
            s
        })
        .collect();
    Ok(ArrivalTree { nodes, slot, voxels, phases: Vec::new() })
}

/// What every builder of an [`ArrivalTree`] checks first.
pub fn check(size_log2: u8, points: usize, config: &BuilderConfig) -> Result<(), OctreeError> {
    if config.leaf_capacity == 0 {
        return Err(OctreeError::ZeroCapacity);
    }
    if config.color_mode != ColorMode::FirstCome {
        return Err(OctreeError::Unsupported("the GPU engine makes first-come voxels only".into()));
    }
    if size_log2 > MAX_ROOT_SIZE_LOG2 {
        return Err(OctreeError::RootTooLarge { size_log2 });
    }
    // Arrival numbers and slots are u32, and u32::MAX marks an empty cell on the GPU.
    if points >= u32::MAX as usize {
        return Err(OctreeError::BatchTooLarge { points, spilled: 0 });
    }
    Ok(())
}

/// Fails unless `nodes` is a tree: children after their parent and in range, each node the child
/// of one parent at most (what came back from a GPU is checked before it is walked).
pub fn check_nodes(nodes: &[ArrivalNode]) -> Result<(), OctreeError> {
    let mut parent = vec![false; nodes.len()];
    for (n, node) in nodes.iter().enumerate() {
        let c = node.first_child as usize;
        if c == NO_CHILD as usize {
            continue;
        }
        if c <= n || c + 8 > nodes.len() || parent[c..c + 8].iter().any(|&p| p) {
            return Err(OctreeError::Unsupported(format!(
                "the GPU's tree is broken: node {n} has children at {c} of {}",
                nodes.len()
            )));
        }
        parent[c..c + 8].fill(true);
    }
    Ok(())
}

/// Per node id: where its leaf's range starts in the leaf-grouped order (leaves depth first,
/// octant order), for leaves; 0 for inner nodes. `nodes` must be a tree (children after their
/// parent, in range; [`ArrivalTree::into_sorted`] checks it).
pub fn leaf_bases(nodes: &[ArrivalNode]) -> Vec<u32> {
    let mut base = vec![0u32; nodes.len()];
    let mut next = 0u32;
    let mut stack = vec![0usize];
    while let Some(n) = stack.pop() {
        let c = nodes[n].first_child;
        if c == NO_CHILD {
            base[n] = next;
            next += nodes[n].count;
        } else {
            stack.extend((0..8).rev().map(|o| (c + o) as usize));
        }
    }
    base
}

impl ArrivalTree {
    /// The [`SortedTree`] over `root` that [`build_sorted`](super::build_sorted) makes, given
    /// that the points were put in their slots and each leaf's range sorted in Morton order:
    /// `sorted_index(a)` is where the point of arrival number `a` ended. Fails on a tree whose
    /// structure is not an octree of this root (a GPU that returned garbage).
    pub fn into_sorted(
        self,
        root: Cube,
        sorted_index: impl Fn(u32) -> u32,
    ) -> Result<SortedTree, OctreeError> {
        let bad =
            |what: &str| OctreeError::Unsupported(format!("the GPU's tree is broken: {what}"));
        check_nodes(&self.nodes)?;
        if self.voxels.len() != self.nodes.len() {
            return Err(bad("voxels for a different number of nodes"));
        }
        let bases = leaf_bases(&self.nodes);
        let mut voxels = self.voxels;
        let mut out = Vec::with_capacity(self.nodes.len());
        let mut stack = vec![(0usize, NodeKey::ROOT, root)];
        while let Some((n, key, cube)) = stack.pop() {
            let node = self.nodes[n];
            if node.first_child == NO_CHILD {
                let s = bases[n] as usize;
                out.push(SortedNode {
                    key,
                    cube,
                    content: SortedContent::Leaf(s..s + node.count as usize),
                });
            } else {
                let c = node.first_child as usize;
                let v = std::mem::take(&mut voxels[n]);
                out.push(SortedNode {
                    key,
                    cube,
                    content: SortedContent::Inner(v.into_iter().map(&sorted_index).collect()),
                });
                for o in (0..8).rev() {
                    stack.push((c + o, key.child(o), cube.child(o)));
                }
            }
        }
        out.sort_by_key(|n| n.key.level);
        Ok(SortedTree { nodes: out })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::build_sorted;

    fn rng(seed: &mut u64) -> u32 {
        *seed ^= *seed << 13;
        *seed ^= *seed >> 7;
        *seed ^= *seed << 17;
        (*seed >> 16) as u32
    }

    /// The points sorted as the store's engines sort them (Morton code, then arrival), and the
    /// tree `into_sorted` makes from `build_arrival`, against `build_sorted`'s.
    fn same_as_sorted(size_log2: u8, pos: &[[u32; 3]], config: BuilderConfig) {
        let tree = build_arrival(size_log2, pos, &config).unwrap();
        // Put the points in their slots, then sort each leaf's range in Morton order.
        let mut at = vec![u32::MAX; pos.len()];
        for (a, &s) in tree.slot.iter().enumerate() {
            assert_eq!(at[s as usize], u32::MAX, "slot {s} given twice");
            at[s as usize] = a as u32;
        }
        let code = |a: u32| {
            let p = pos[a as usize];
            (crate::morton::encode(p[0], p[1], p[2]), a)
        };
        let bases = leaf_bases(&tree.nodes);
        for (n, node) in tree.nodes.iter().enumerate() {
            if node.first_child == NO_CHILD {
                let r = bases[n] as usize..(bases[n] + node.count) as usize;
                at[r].sort_by_key(|&a| code(a));
            }
        }
        let mut inv = vec![0u32; pos.len()];
        for (i, &a) in at.iter().enumerate() {
            inv[a as usize] = i as u32;
        }
        let root = Cube::new([0; 3], size_log2);
        let got = tree.into_sorted(root, |a| inv[a as usize]).unwrap();
        let p = |i: usize| pos[at[i] as usize].map(|v| v as i32);
        let want = build_sorted(root, pos.len(), &p, &|i| at[i] as u64, config).unwrap();
        // The sorted order is the global Morton order.
        assert!(at.windows(2).all(|w| code(w[0]) < code(w[1])));
        assert_eq!(got.nodes, want.nodes);
    }

    #[test]
    fn the_unordered_tree_is_the_sorted_tree() {
        let mut seed = 0x9e3779b97f4a7c15u64;
        for (n, size_log2, cap, spread) in [
            (0, 10, 5, 10),
            (1, 10, 5, 10),
            (3000, 16, 40, 16),
            (5000, 12, 7, 6),
            (4000, 20, 30, 9),
        ] {
            let pos: Vec<[u32; 3]> = (0..n)
                .map(|_| {
                    [0; 3].map(|_| (rng(&mut seed) % (1u32 << spread)) << (size_log2 - spread))
                })
                .collect();
            let config = BuilderConfig { leaf_capacity: cap, ..BuilderConfig::default() };
            same_as_sorted(size_log2, &pos, config);
        }
    }

    #[test]
    fn coincident_points_and_depth_limits() {
        // All points at one position: leaves beyond the depth limit keep them all.
        let pos = vec![[77u32, 5, 900]; 500];
        same_as_sorted(12, &pos, BuilderConfig { leaf_capacity: 10, ..BuilderConfig::default() });
        let config = BuilderConfig { leaf_capacity: 3, max_level: 2, ..BuilderConfig::default() };
        let pos: Vec<[u32; 3]> = (0..300u32).map(|i| [i * 13 % 4096, i * 7 % 4096, i]).collect();
        same_as_sorted(12, &pos, config);
    }

    #[test]
    fn points_outside_the_root_and_averaged_colours_are_refused() {
        let c = BuilderConfig::default();
        assert!(matches!(
            build_arrival(4, &[[16, 0, 0]], &c),
            Err(OctreeError::PointOutsideRoot { index: 0, .. })
        ));
        let avg = BuilderConfig { color_mode: ColorMode::Averaged, ..c };
        assert!(build_arrival(4, &[[1, 0, 0]], &avg).is_err());
        let zero = BuilderConfig { leaf_capacity: 0, ..c };
        assert!(matches!(build_arrival(4, &[], &zero), Err(OctreeError::ZeroCapacity)));
    }

    #[test]
    fn a_broken_tree_is_refused() {
        let t = ArrivalTree {
            nodes: vec![ArrivalNode { count: 1, first_child: 5 }],
            slot: vec![0],
            voxels: vec![vec![]],
            phases: Vec::new(),
        };
        assert!(t.into_sorted(Cube::new([0; 3], 8), |a| a).is_err());
    }
}
