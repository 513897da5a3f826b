//! A tree of the sorted build extended by points that arrive after all of its own (`mortar build
//! --append` keeping the nodes the new points do not reach; ARCHITECTURE.md, "`--append`").
//!
//! The tree [`build_sorted`](super::build_sorted) makes is a function of the points and their
//! arrival order, and every new point arrives after every old one. With the root unchanged:
//!
//! - a node whose cube no new point falls in keeps its subtree as it was, node for node (a
//!   subtree depends on the points in its cube alone);
//! - an old inner node stays inner (counts only grow); its voxel for a cell its old voxels
//!   occupy stays that voxel (an old point arrived first), and a cell no old voxel occupies gets
//!   the earliest new point in it, if any;
//! - an old leaf (empty ones included) holds its old points and the new ones in its cube, in
//!   Morton order, old before new at one position; where they are more than the leaf capacity
//!   and it may split, its subtree is built from them ([`build_subtree`]) with the old points'
//!   arrival ranks, which the store keeps for its leaves only (an inner node's voxels need none:
//!   they win their cells against any new point).
//!
//! So the patched tree is the tree of all the points, and only the nodes on the new points' paths
//! are coded again. Growing the root changes every node's grid and is not done here: the caller
//! builds everything again then.

use super::cube::{Cube, NodeKey};
use super::sorted::{build_subtree, splits, SortedContent};
use super::types::{BuilderConfig, OctreeError, GRID_LOG2};
use crate::morton::encode96;
use rayon::prelude::*;
use std::collections::HashMap;
use std::ops::Range;

/// A node of the tree being extended, as its store lists it (the sorted build's order: level by
/// level, Morton order within a level).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OldNode {
    /// Where it is.
    pub key: NodeKey,
    /// Whether it is a leaf.
    pub leaf: bool,
}

/// What an old node held, as [`patch_tree`] asks for it: its points (leaf) or voxels (inner
/// node) in their stored order, and for a leaf each point's arrival rank (below every new
/// point's); empty for an inner node.
#[derive(Clone, Debug, Default)]
pub struct OldContent {
    /// Positions, in the node's order.
    pub pos: Vec<[i32; 3]>,
    /// Arrival ranks of a leaf's points, in the same order.
    pub arrival: Vec<u64>,
}

/// A point of a patched node: the `i`th point or voxel of the old node it came from, or new
/// point `j` (its index in the sorted new points).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Item {
    /// Of the old node's content.
    Old(u32),
    /// Of the new points.
    New(u32),
}

/// What a node of the patched tree holds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PatchedContent {
    /// The old node of this id, unchanged.
    Kept(usize),
    /// A leaf: its points in Morton order; [`Item::Old`] indexes the content of old node `old`.
    Leaf {
        /// The old node whose points it holds (none where the old tree had no node there).
        old: Option<usize>,
        /// Its points.
        items: Vec<Item>,
    },
    /// An inner node: one point per occupied cell of its grid, in the cells' Morton order;
    /// [`Item::Old`] indexes the content of old node `old` (its voxels where that was an inner
    /// node, its points where it was a leaf that split).
    Inner {
        /// The old node the old items are of.
        old: Option<usize>,
        /// Its voxels.
        items: Vec<Item>,
    },
}

/// A node of the patched tree.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PatchedNode {
    /// Where it is.
    pub key: NodeKey,
    /// Its cube.
    pub cube: Cube,
    /// What it holds.
    pub content: PatchedContent,
}

/// The full-resolution Morton code of `p` relative to `root`'s corner (which must hold it):
/// the order of the sorted build's points.
#[inline]
pub fn code_in(root: Cube, p: [i32; 3]) -> u128 {
    encode96([0, 1, 2].map(|a| (p[a] as i64 - root.min[a]) as u32))
}

/// The tree over `root` that the sorted build makes of the old tree's points followed by the
/// new points `new_pos` (sorted by [`code_in`], ties by arrival; `new_arrival` their arrival
/// numbers, each above every old rank): its nodes level by level, each level in Morton order,
/// as [`build_sorted`](super::build_sorted) orders them. `old` is the old tree over the same
/// root in that order (its root first); `load(id)` gives an old node's content, asked only for
/// nodes a new point reaches (in parallel).
pub fn patch_tree<L, E>(
    root: Cube,
    old: &[OldNode],
    new_pos: &[[i32; 3]],
    new_arrival: &[u64],
    load: &L,
    config: BuilderConfig,
) -> Result<Vec<PatchedNode>, E>
where
    L: Fn(usize) -> Result<OldContent, E> + Sync,
    E: From<OctreeError> + Send,
{
    if config.leaf_capacity == 0 {
        return Err(OctreeError::ZeroCapacity.into());
    }
    if old.first().map(|n| n.key) != Some(NodeKey::ROOT) {
        return Err(OctreeError::Unsupported("the tree to extend has no root".into()).into());
    }
    if let Some(index) = new_pos.iter().position(|&p| !root.contains(p)) {
        return Err(OctreeError::PointOutsideRoot {
            index,
            pos: new_pos[index],
            min: root.min,
            size: root.size(),
        }
        .into());
    }
    let codes: Vec<u128> = new_pos.par_iter().map(|&p| code_in(root, p)).collect();
    if codes.windows(2).zip(new_arrival.windows(2)).any(|(c, a)| (c[0], a[0]) > (c[1], a[1])) {
        return Err(
            OctreeError::Unsupported("the new points are not in Morton order".into()).into()
        );
    }
    let ids: HashMap<NodeKey, usize> = old.iter().enumerate().map(|(i, n)| (n.key, i)).collect();
    let ctx = Ctx { root, old, ids, pos: new_pos, arrival: new_arrival, codes, load, config };
    let mut nodes = ctx.walk(NodeKey::ROOT, root, Some(0), 0..new_pos.len())?;
    // Depth first within a level is the Morton order of the level's nodes.
    nodes.sort_by_key(|n| n.key.level);
    Ok(nodes)
}

struct Ctx<'a, L> {
    root: Cube,
    old: &'a [OldNode],
    ids: HashMap<NodeKey, usize>,
    pos: &'a [[i32; 3]],
    arrival: &'a [u64],
    codes: Vec<u128>,
    load: &'a L,
    config: BuilderConfig,
}

impl<L, E> Ctx<'_, L>
where
    L: Fn(usize) -> Result<OldContent, E> + Sync,
    E: From<OctreeError> + Send,
{
    /// The patched subtree of `key` (old node `id`, if any) with the new points `r`, depth
    /// first.
    fn walk(
        &self,
        key: NodeKey,
        cube: Cube,
        id: Option<usize>,
        r: Range<usize>,
    ) -> Result<Vec<PatchedNode>, E> {
        match id {
            Some(id) if r.is_empty() => {
                let mut out = Vec::new();
                self.kept(id, cube, &mut out);
                Ok(out)
            }
            None if r.is_empty() => Ok(Vec::new()),
            Some(id) if !self.old[id].leaf => self.inner(key, cube, id, r),
            _ => self.leaf(key, cube, id, r),
        }
    }

    /// Old node `id` and its subtree, kept, depth first.
    fn kept(&self, id: usize, cube: Cube, out: &mut Vec<PatchedNode>) {
        let n = self.old[id];
        out.push(PatchedNode { key: n.key, cube, content: PatchedContent::Kept(id) });
        if !n.leaf {
            for o in 0..8 {
                if let Some(&c) = self.ids.get(&n.key.child(o)) {
                    self.kept(c, cube.child(o), out);
                }
            }
        }
    }

    /// An old inner node reached by the new points `r`: its old voxels and the earliest new
    /// point of each cell they leave empty; then its children.
    fn inner(
        &self,
        key: NodeKey,
        cube: Cube,
        id: usize,
        r: Range<usize>,
    ) -> Result<Vec<PatchedNode>, E> {
        let content = (self.load)(id)?;
        let old_codes: Vec<u128> = content.pos.iter().map(|&p| code_in(self.root, p)).collect();
        if content.pos.iter().any(|&p| !cube.contains(p))
            || old_codes.windows(2).any(|c| c[0] > c[1])
        {
            return Err(OctreeError::Unsupported(format!(
                "the voxels of node {id} do not lie in its cube in Morton order"
            ))
            .into());
        }
        // A cell of the node's grid is a run of codes sharing the bits above 3 * cell_log2.
        let cell_log2 = (cube.size_log2 - GRID_LOG2) as u32;
        let cell = |code: u128| code >> (3 * cell_log2);
        let mut items = Vec::with_capacity(content.pos.len());
        let (mut a, mut b) = (0usize, r.start);
        while a < old_codes.len() || b < r.end {
            let next_old = old_codes.get(a).copied();
            let next_new = (b < r.end).then(|| self.codes[b]);
            let c = match (next_old, next_new) {
                (Some(o), Some(n)) => cell(o.min(n)),
                (Some(o), None) => cell(o),
                (None, Some(n)) => cell(n),
                (None, None) => unreachable!("the loop's condition"),
            };
            let mut pick: Option<Item> = None;
            while a < old_codes.len() && cell(old_codes[a]) == c {
                pick = pick.or(Some(Item::Old(a as u32)));
                a += 1;
            }
            let mut earliest: Option<(u64, u32)> = None;
            while b < r.end && cell(self.codes[b]) == c {
                if earliest.is_none_or(|(t, _)| self.arrival[b] < t) {
                    earliest = Some((self.arrival[b], b as u32));
                }
                b += 1;
            }
            items.push(pick.unwrap_or_else(|| Item::New(earliest.expect("a point in the cell").1)));
        }
        drop(content);
        let node =
            PatchedNode { key, cube, content: PatchedContent::Inner { old: Some(id), items } };
        // The children's ranges: octants ascend in Morton order.
        let shift = 3 * (cube.size_log2 as u32 - 1);
        let octant = |i: usize| ((self.codes[i] >> shift) & 7) as usize;
        let mut bounds = [r.start; 9];
        for o in 0..8 {
            let from = bounds[o];
            bounds[o + 1] = from + (from..r.end).take_while(|&i| octant(i) <= o).count();
        }
        let children: Vec<Vec<PatchedNode>> = (0..8)
            .into_par_iter()
            .map(|o| {
                let k = key.child(o);
                self.walk(k, cube.child(o), self.ids.get(&k).copied(), bounds[o]..bounds[o + 1])
            })
            .collect::<Result<_, E>>()?;
        let mut out = vec![node];
        for c in children {
            out.extend(c);
        }
        Ok(out)
    }

    /// An old leaf (or a place the old tree has no node) reached by the new points `r`: its old
    /// points and the new ones, a leaf or, past the capacity, the subtree the sorted build makes
    /// of them.
    fn leaf(
        &self,
        key: NodeKey,
        cube: Cube,
        id: Option<usize>,
        r: Range<usize>,
    ) -> Result<Vec<PatchedNode>, E> {
        let content = match id {
            Some(id) => (self.load)(id)?,
            None => OldContent::default(),
        };
        let n_old = content.pos.len();
        let first_new = r.clone().map(|b| self.arrival[b]).min().unwrap_or(u64::MAX);
        if content.arrival.len() != n_old
            || content.pos.iter().any(|&p| !cube.contains(p))
            || content.arrival.iter().any(|&t| t >= first_new)
        {
            return Err(OctreeError::Unsupported(format!(
                "the points of node {} do not lie in its cube, or arrived after the new ones",
                id.map_or(-1, |i| i as i64)
            ))
            .into());
        }
        // Old and new merged by (code, arrival): at one position the old point first.
        let old_codes: Vec<u128> = content.pos.iter().map(|&p| code_in(self.root, p)).collect();
        let mut merged: Vec<(Item, [i32; 3], u64)> = Vec::with_capacity(n_old + r.len());
        let (mut a, mut b) = (0usize, r.start);
        while a < n_old || b < r.end {
            let take_old = b >= r.end
                || (a < n_old
                    && (old_codes[a], content.arrival[a]) <= (self.codes[b], self.arrival[b]));
            if take_old {
                merged.push((Item::Old(a as u32), content.pos[a], content.arrival[a]));
                a += 1;
            } else {
                merged.push((Item::New(b as u32), self.pos[b], self.arrival[b]));
                b += 1;
            }
        }
        drop(content);
        if !splits(merged.len() as u64, key, cube, &self.config) {
            let items = merged.iter().map(|m| m.0).collect();
            return Ok(vec![PatchedNode {
                key,
                cube,
                content: PatchedContent::Leaf { old: id, items },
            }]);
        }
        let sub = build_subtree(
            key,
            cube,
            merged.len(),
            &|i| merged[i].1,
            &|i| merged[i].2,
            self.config,
        )?;
        Ok(sub
            .nodes
            .into_iter()
            .map(|n| {
                let content = match n.content {
                    SortedContent::Leaf(range) => PatchedContent::Leaf {
                        old: id,
                        items: merged[range].iter().map(|m| m.0).collect(),
                    },
                    SortedContent::Inner(v) => PatchedContent::Inner {
                        old: id,
                        items: v.iter().map(|&i| merged[i as usize].0).collect(),
                    },
                };
                PatchedNode { key: n.key, cube: n.cube, content }
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::super::{build_sorted, SortedTree};
    use super::*;

    /// Points in clusters (dense spots that split, sparse ones that do not), some coincident.
    fn points(n: usize, seed: u64, spread: i32) -> Vec<[i32; 3]> {
        let mut s = seed;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        (0..n)
            .map(|i| {
                let c = (next() % 5) as i32;
                let base = [c * 3000, (c % 3) * 2000, c * 100];
                if i % 17 == 0 {
                    return base;
                }
                [0, 1, 2].map(|a| base[a] + (next() % spread as u64) as i32)
            })
            .collect()
    }

    /// The tree's nodes with each point named by its arrival number.
    fn named(tree: &SortedTree, arrival: &[u64]) -> Vec<(NodeKey, bool, Vec<u64>)> {
        tree.nodes
            .iter()
            .map(|n| match &n.content {
                SortedContent::Leaf(r) => (n.key, true, arrival[r.clone()].to_vec()),
                SortedContent::Inner(v) => {
                    (n.key, false, v.iter().map(|&i| arrival[i as usize]).collect())
                }
            })
            .collect()
    }

    /// Points sorted as the sorted build wants them, with their arrival numbers.
    fn sorted(root: Cube, pts: &[[i32; 3]], first: u64) -> (Vec<[i32; 3]>, Vec<u64>) {
        let mut idx: Vec<usize> = (0..pts.len()).collect();
        idx.sort_by_key(|&i| (code_in(root, pts[i]), i));
        (idx.iter().map(|&i| pts[i]).collect(), idx.iter().map(|&i| first + i as u64).collect())
    }

    #[test]
    fn a_patched_tree_is_the_tree_of_all_points() {
        let root = Cube::new([0; 3], 15);
        for (cap, n_old, n_new, spread) in
            [(50, 3000, 400, 900), (200, 5000, 5000, 3000), (20, 1000, 3, 30), (1000, 500, 300, 64)]
        {
            let config = BuilderConfig { leaf_capacity: cap, ..BuilderConfig::default() };
            let all = points(n_old + n_new, cap as u64 + 7, spread);
            let (op, oa) = sorted(root, &all[..n_old], 0);
            let old = build_sorted(root, op.len(), &|i| op[i], &|i| oa[i], config).unwrap();
            let (np, na) = sorted(root, &all[n_old..], n_old as u64);
            let (ap, aa) = sorted(root, &all, 0);
            let want = build_sorted(root, ap.len(), &|i| ap[i], &|i| aa[i], config).unwrap();
            let old_nodes: Vec<OldNode> =
                old.nodes.iter().map(|n| OldNode { key: n.key, leaf: n.is_leaf() }).collect();
            let loads = std::sync::atomic::AtomicUsize::new(0);
            let load = |id: usize| -> Result<OldContent, OctreeError> {
                loads.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                Ok(match &old.nodes[id].content {
                    SortedContent::Leaf(r) => {
                        OldContent { pos: op[r.clone()].to_vec(), arrival: oa[r.clone()].to_vec() }
                    }
                    SortedContent::Inner(v) => OldContent {
                        pos: v.iter().map(|&i| op[i as usize]).collect(),
                        arrival: Vec::new(),
                    },
                })
            };
            let patched = patch_tree(root, &old_nodes, &np, &na, &load, config).unwrap();
            let old_named = named(&old, &oa);
            let got: Vec<(NodeKey, bool, Vec<u64>)> = patched
                .iter()
                .map(|n| {
                    let of = |old: Option<usize>, items: &[Item]| -> Vec<u64> {
                        items
                            .iter()
                            .map(|it| match *it {
                                Item::New(j) => na[j as usize],
                                Item::Old(i) => old_named[old.unwrap()].2[i as usize],
                            })
                            .collect()
                    };
                    match &n.content {
                        PatchedContent::Kept(id) => old_named[*id].clone(),
                        PatchedContent::Leaf { old, items } => (n.key, true, of(*old, items)),
                        PatchedContent::Inner { old, items } => (n.key, false, of(*old, items)),
                    }
                })
                .collect();
            let want = named(&want, &aa);
            assert_eq!(got.len(), want.len(), "capacity {cap}: node count");
            for (g, w) in got.iter().zip(&want) {
                assert_eq!(g, w, "capacity {cap}");
            }
            let kept = patched.iter().filter(|n| matches!(n.content, PatchedContent::Kept(_)));
            let loaded = loads.load(std::sync::atomic::Ordering::Relaxed);
            assert!(loaded <= old.nodes.len(), "capacity {cap}");
            if n_new < 10 {
                assert!(kept.count() > 0 && loaded < old.nodes.len() / 2, "capacity {cap}");
            }
        }
    }
}
