//! The octree of paper 004 built in one pass over points in Morton order (the build engine of
//! `mortar build`; ARCHITECTURE.md, "The build engine").
//!
//! The incremental [`Builder`](super::Builder) and this function build the same tree, because
//! the tree is a function of the points and their arrival order alone:
//!
//! - a node is inner exactly when more than [`BuilderConfig::leaf_capacity`] points fall in its
//!   cube and it may split (at least 2^[`MIN_INNER_SIZE_LOG2`] units wide, above
//!   [`BuilderConfig::max_level`]); counts only grow, so the order in which points came does not
//!   matter, and a split creates all 8 children;
//! - a leaf holds every point of its cube;
//! - an inner node's voxel for a cell of its 128³ grid is the point that arrived first in that
//!   cell ([`ColorMode::FirstCome`]), i.e. the one with the smallest arrival number.
//!
//! With the points sorted by their Morton code relative to the root's corner (full resolution,
//! ties in any order), every node's cube and every grid cell is one contiguous range of the
//! sorted points. So the children of a node are found by binary search, and the voxels are
//! found bottom-up: a leaf scans its points once and gives its parent, per cell of the parent's
//! grid, the earliest point; an inner node's voxels are its children's candidates laid end to
//! end (in Morton order), and it reduces them by eight for its own parent. The work is the
//! number of points plus the number of voxels; sibling subtrees run in parallel (rayon).
//!
//! Only [`ColorMode::FirstCome`] is built here: averaged colours stop accumulating after the
//! first 2^24 points in arrival order, which would need those points in arrival order.
//!
//! This is also the unit of parallel work that the distributed build hands to separate jobs: a
//! subtree under a Morton prefix depends on the points in its cube alone.

use super::cube::{Cube, NodeKey};
use super::types::MAX_ROOT_SIZE_LOG2;
use super::types::{BuilderConfig, ColorMode, OctreeError, GRID_LOG2, MIN_INNER_SIZE_LOG2};
use rayon::prelude::*;
use std::ops::Range;

/// Subtrees with fewer points than this are built on the current thread.
const PAR_MIN: usize = 1 << 14;

/// One node of a [`SortedTree`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SortedNode {
    /// Where the node is.
    pub key: NodeKey,
    /// Its cube.
    pub cube: Cube,
    /// What it holds.
    pub content: SortedContent,
}

/// What a [`SortedNode`] holds, as indices into the sorted points.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SortedContent {
    /// A leaf: the points `range` of the sorted order (Morton order).
    Leaf(Range<usize>),
    /// An inner node: one point per occupied cell of its grid, the earliest to arrive, in the
    /// Morton order of the cells.
    Inner(Vec<u32>),
}

impl SortedNode {
    /// Whether the node is a leaf.
    pub fn is_leaf(&self) -> bool {
        matches!(self.content, SortedContent::Leaf(_))
    }

    /// Points (leaf) or voxels (inner node).
    pub fn count(&self) -> usize {
        match &self.content {
            SortedContent::Leaf(r) => r.len(),
            SortedContent::Inner(v) => v.len(),
        }
    }
}

/// An octree over sorted points: its nodes level by level (the root first), each level in the
/// Morton order of its nodes.
#[derive(Clone, Debug, Default)]
pub struct SortedTree {
    /// The nodes.
    pub nodes: Vec<SortedNode>,
}

impl SortedTree {
    /// Ranges of [`nodes`](Self::nodes) holding one level each, from the root down.
    pub fn levels(&self) -> Vec<Range<usize>> {
        let mut out: Vec<Range<usize>> = Vec::new();
        for (i, n) in self.nodes.iter().enumerate() {
            match out.last_mut() {
                Some(r) if self.nodes[r.start].key.level == n.key.level => r.end = i + 1,
                _ => out.push(i..i + 1),
            }
        }
        out
    }

    /// Points in the leaves.
    pub fn points(&self) -> u64 {
        self.nodes.iter().filter(|n| n.is_leaf()).map(|n| n.count() as u64).sum()
    }
}

/// What the function building a tree needs: the points' positions in Morton order and their
/// arrival numbers.
struct Ctx<'a, P, S> {
    pos: &'a P,
    arrival: &'a S,
    config: BuilderConfig,
}

/// Builds the octree over `root` of `n` points sorted by their Morton code relative to
/// `root.min` at full resolution: `pos(i)` is the position of sorted point `i` and `arrival(i)`
/// its arrival number (unique; smaller arrived earlier). Every point must lie in `root`.
pub fn build_sorted<P, S>(
    root: Cube,
    n: usize,
    pos: &P,
    arrival: &S,
    config: BuilderConfig,
) -> Result<SortedTree, OctreeError>
where
    P: Fn(usize) -> [i32; 3] + Sync,
    S: Fn(usize) -> u64 + Sync,
{
    if config.leaf_capacity == 0 {
        return Err(OctreeError::ZeroCapacity);
    }
    if root.size_log2 > MAX_ROOT_SIZE_LOG2 {
        return Err(OctreeError::RootTooLarge { size_log2: root.size_log2 });
    }
    let mut nodes = build_subtree(NodeKey::ROOT, root, n, pos, arrival, config)?.nodes;
    // Depth-first order within a level is the Morton order of the level's nodes.
    nodes.sort_by_key(|n| n.key.level);
    Ok(SortedTree { nodes })
}

/// A subtree built on its own: the unit of work of the partitioned build (larger than memory)
/// and of the distributed one. Joined by [`earliest_in_parent_cells`] and [`splits`] into the
/// tree [`build_sorted`] makes over all the points.
#[derive(Clone, Debug, Default)]
pub struct Subtree {
    /// Its nodes (the subtree's root first), depth first, children in octant order; indices
    /// are into the subtree's own sorted points.
    pub nodes: Vec<SortedNode>,
    /// For each occupied cell of the parent's grid inside the subtree's cube, the earliest point,
    /// in Morton order: what the subtree gives its parent's voxels (empty for the tree's root).
    pub candidates: Vec<u32>,
}

/// Builds the subtree of node `key` (cube `cube`, the cube of `key` in the tree's root) over
/// the `n` points of that cube, sorted as [`build_sorted`] wants them (Morton order relative to
/// the tree's root, full resolution): exactly the nodes `build_sorted` makes under `key` over
/// all the points, since a subtree depends on the points in its cube alone.
pub fn build_subtree<P, S>(
    key: NodeKey,
    cube: Cube,
    n: usize,
    pos: &P,
    arrival: &S,
    config: BuilderConfig,
) -> Result<Subtree, OctreeError>
where
    P: Fn(usize) -> [i32; 3] + Sync,
    S: Fn(usize) -> u64 + Sync,
{
    if config.leaf_capacity == 0 {
        return Err(OctreeError::ZeroCapacity);
    }
    if config.color_mode != ColorMode::FirstCome {
        return Err(OctreeError::Unsupported(
            "the sorted build makes first-come voxels only".into(),
        ));
    }
    if n > u32::MAX as usize {
        return Err(OctreeError::BatchTooLarge { points: n, spilled: 0 });
    }
    if let Some(index) = (0..n).into_par_iter().position_any(|i| !cube.contains(pos(i))) {
        return Err(OctreeError::PointOutsideRoot {
            index,
            pos: pos(index),
            min: cube.min,
            size: cube.size(),
        });
    }
    let ctx = Ctx { pos, arrival, config };
    let mut nodes = Vec::new();
    let candidates = subtree(&ctx, key, cube, 0..n, &mut nodes);
    Ok(Subtree { nodes, candidates })
}

/// Whether a node at `key` (cube `cube`) holding `count` points is an inner node: more points
/// than the leaf capacity, and it may split.
pub fn splits(count: u64, key: NodeKey, cube: Cube, config: &BuilderConfig) -> bool {
    count > config.leaf_capacity as u64
        && cube.size_log2 >= MIN_INNER_SIZE_LOG2
        && key.level < config.max_level
}

/// Of `items` (in Morton order, all in `cube`), the earliest to arrive in each cell of the
/// parent's grid (cells `2^(cube.size_log2 - 6)` wide), in order: what a node whose children's
/// candidates (or whose points) are `items` gives its own parent.
pub fn earliest_in_parent_cells<T: Copy>(
    cube: Cube,
    items: impl IntoIterator<Item = T>,
    pos: impl Fn(T) -> [i32; 3],
    arrival: impl Fn(T) -> u64,
) -> Vec<T> {
    let cell_log2 = cube.size_log2 - (GRID_LOG2 - 1);
    let min = cube.min;
    let cell = |p: [i32; 3]| [0, 1, 2].map(|a| ((p[a] as i64 - min[a]) as u64) >> cell_log2);
    let mut out = Vec::new();
    let mut current: Option<([u64; 3], T, u64)> = None;
    for i in items {
        let c = cell(pos(i));
        let t = arrival(i);
        match &mut current {
            Some((cc, best, bt)) if *cc == c => {
                if t < *bt {
                    *best = i;
                    *bt = t;
                }
            }
            _ => {
                if let Some((_, b, _)) = current {
                    out.push(b);
                }
                current = Some((c, i, t));
            }
        }
    }
    if let Some((_, b, _)) = current {
        out.push(b);
    }
    out
}

/// Builds the subtree of node `key` (cube `cube`) over the sorted points `range`, appending its
/// nodes to `out` depth first; returns, for each occupied cell of the parent's grid inside this
/// cube (cells `2^(cube.size_log2 - 6)` wide), the earliest point, in Morton order. Nothing for
/// the root.
fn subtree<P: Fn(usize) -> [i32; 3] + Sync, S: Fn(usize) -> u64 + Sync>(
    ctx: &Ctx<'_, P, S>,
    key: NodeKey,
    cube: Cube,
    range: Range<usize>,
    out: &mut Vec<SortedNode>,
) -> Vec<u32> {
    if !splits(range.len() as u64, key, cube, &ctx.config) {
        let candidates = if key.level == 0 {
            Vec::new()
        } else {
            earliest_per_cell(ctx, cube, range.clone().map(|i| i as u32))
        };
        out.push(SortedNode { key, cube, content: SortedContent::Leaf(range) });
        return candidates;
    }
    // Children: the octant is monotone over the node's points in Morton order.
    let mut bounds = [range.start; 9];
    bounds[8] = range.end;
    for o in 1..8 {
        // The first point of octant o or above (binary search).
        let (mut a, mut b) = (bounds[o - 1], range.end);
        while a < b {
            let m = a + (b - a) / 2;
            if cube.octant_of((ctx.pos)(m)) < o {
                a = m + 1;
            } else {
                b = m;
            }
        }
        bounds[o] = a;
    }
    let child = |o: usize, out: &mut Vec<SortedNode>| {
        subtree(ctx, key.child(o), cube.child(o), bounds[o]..bounds[o + 1], out)
    };
    let mut kids: Vec<(Vec<SortedNode>, Vec<u32>)> = if range.len() >= PAR_MIN {
        (0..8)
            .into_par_iter()
            .map(|o| {
                let mut v = Vec::new();
                let c = child(o, &mut v);
                (v, c)
            })
            .collect()
    } else {
        (0..8)
            .map(|o| {
                let mut v = Vec::new();
                let c = child(o, &mut v);
                (v, c)
            })
            .collect()
    };
    let voxels: Vec<u32> = kids.iter_mut().flat_map(|(_, c)| std::mem::take(c)).collect();
    let candidates = if key.level == 0 {
        Vec::new()
    } else {
        earliest_per_cell(ctx, cube, voxels.iter().copied())
    };
    out.push(SortedNode { key, cube, content: SortedContent::Inner(voxels) });
    for (v, _) in kids {
        out.extend(v);
    }
    candidates
}

/// [`earliest_in_parent_cells`] over sorted point indices.
fn earliest_per_cell<P: Fn(usize) -> [i32; 3] + Sync, S: Fn(usize) -> u64 + Sync>(
    ctx: &Ctx<'_, P, S>,
    cube: Cube,
    items: impl Iterator<Item = u32>,
) -> Vec<u32> {
    earliest_in_parent_cells(cube, items, |i| (ctx.pos)(i as usize), |i| (ctx.arrival)(i as usize))
}
