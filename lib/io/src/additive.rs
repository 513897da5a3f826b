//! Trees whose nodes add points to their parent's (COPC, EPT; 3D Tiles' `refine: ADD`), walked
//! by the store's node selection ([`select_nodes`]).
//!
//! Every point of such a tree is in exactly one node, so a coarse view draws the nodes near the
//! root and a finer one adds deeper nodes. The store's nodes instead replace their parent (voxels
//! stand for the points below). Both are selected by one rule: the selection's nodes are those a
//! store would draw; an additive view reads them *and every node the selection refined* (their
//! ancestors, and refined nodes whose children all fell out of view), whose points are not in
//! the children. (The point budget counts the selected nodes' points, not their ancestors'.)
//!
//! The tree's cube (a centre and a half-size in world units) is not a power of two in any
//! file's integer grid, so the selection walks it in a grid of its own ([`AdditiveTree::grid`]):
//! the root is the integer cube `[0, 2^ROOT_LOG2)` whose world box is exactly the tree's cube,
//! and node `(d, x, y, z)` is the integer cube at `(x, y, z) << (ROOT_LOG2 - d)` (exact: culling
//! and projected sizes are those of the node's box). Missing octants of a node that has children
//! are empty leaves of the index ([`LodIndex`] wants all 8).

use mortar_core::grid::Grid;
use mortar_core::octree::{
    select_nodes, Cube, IndexEntry, LodIndex, LodOptions, LodSelection, LodTree, NodeId, NodeKey,
};
use mortar_core::render::{Aabb, Camera, CameraError};
use std::collections::{HashMap, HashSet};

/// `log2` of the root cube's edge in the selection's grid (see the module docs).
pub const ROOT_LOG2: u8 = 32;

/// Deepest level accepted.
pub const MAX_LEVEL: u8 = 32;

/// An additive tree ready for node selection: the [`LodIndex`] of its nodes and which of the
/// caller's nodes each index node is.
#[derive(Clone, Debug)]
pub struct AdditiveTree {
    index: LodIndex,
    /// Per index node, the caller's node (a position in the list given to [`Self::new`]),
    /// `None` for nodes without points (an empty root, the empty octants).
    node_of: Vec<Option<usize>>,
    grid: Grid,
    center: [f64; 3],
    halfsize: f64,
}

impl AdditiveTree {
    /// The tree of the cube of half-size `halfsize` around `center` whose nodes with points are
    /// `nodes` (key, points; keys unique and checked by [`node_key`]). An error says why the
    /// nodes are not one tree.
    pub fn new(
        center: [f64; 3],
        halfsize: f64,
        nodes: &[(NodeKey, u64)],
    ) -> Result<AdditiveTree, String> {
        if nodes.iter().any(|(k, _)| k.level > MAX_LEVEL) {
            return Err(format!("a node deeper than level {MAX_LEVEL}"));
        }
        let by_key: HashMap<NodeKey, usize> =
            nodes.iter().enumerate().map(|(i, (k, _))| (*k, i)).collect();
        // Every node with points, its ancestors (a hierarchy may leave out a node without
        // points between a node and its children) and the octants beside them.
        let mut keys: HashSet<NodeKey> = HashSet::new();
        keys.insert(NodeKey::ROOT);
        for (k, _) in nodes {
            let mut k = *k;
            while k.level > 0 && keys.insert(k) {
                k = parent_key(k);
            }
        }
        let inner: HashSet<NodeKey> =
            keys.iter().filter(|k| k.level > 0).map(|&k| parent_key(k)).collect();
        for p in &inner {
            for o in 0..8 {
                keys.insert(p.child(o));
            }
        }
        // The root first, then by level and cell (deterministic ids).
        let mut order: Vec<NodeKey> = keys.into_iter().collect();
        order.sort_unstable_by_key(|k| (k.level, k.index[2], k.index[1], k.index[0]));
        let entries: Vec<IndexEntry> = order
            .iter()
            .map(|k| IndexEntry {
                key: *k,
                leaf: !inner.contains(k),
                samples: by_key.get(k).map_or(0, |&i| nodes[i].1),
            })
            .collect();
        let root = Cube::new([0; 3], ROOT_LOG2);
        let index = LodIndex::new(root, &entries).map_err(|e| e.to_string())?;
        let node_of = order.iter().map(|k| by_key.get(k).copied()).collect();
        let unit = 2.0 * halfsize / (1u64 << ROOT_LOG2) as f64;
        let grid = Grid { scale: [unit; 3], offset: [0, 1, 2].map(|a| center[a] - halfsize) };
        Ok(AdditiveTree { index, node_of, grid, center, halfsize })
    }

    /// The tree's structure (what [`select_nodes`] walks).
    pub fn index(&self) -> &LodIndex {
        &self.index
    }

    /// The selection's grid: the root cube `[0, 2^ROOT_LOG2)` is the tree's cube.
    pub fn grid(&self) -> Grid {
        self.grid
    }

    /// The tree's cube as a world box.
    pub fn cube_bounds(&self) -> Aabb {
        let h = self.halfsize;
        Aabb { min: self.center.map(|c| c - h), max: self.center.map(|c| c + h) }
    }

    /// The nodes to read for `camera`: the store's selection ([`select_nodes`]) and every node it
    /// refined (each ancestor of a selected node, and refined nodes whose children are all out
    /// of view), as ascending positions in the list given to [`Self::new`];
    /// with the selection itself.
    pub fn select(
        &self,
        camera: &Camera,
        options: &LodOptions,
    ) -> Result<(Vec<usize>, LodSelection), CameraError> {
        let sel = select_nodes(&self.index, &self.grid, camera, options)?;
        // The nodes the selection found visible: those it selected and those it refined (the
        // ancestors of the selected ones, and refined nodes all of whose children turned out
        // culled or empty: their own points are still in view). A walk from the root that
        // stops at selected, culled and empty nodes visits exactly those.
        let selected: HashSet<NodeId> = sel.nodes.iter().copied().collect();
        let culled: HashSet<NodeId> = sel.culled.iter().copied().collect();
        let mut take = vec![false; self.node_of.len()];
        let mut stack = vec![NodeId::ROOT];
        while let Some(n) = stack.pop() {
            if culled.contains(&n) || self.index.subtree_points(n) == 0 {
                continue;
            }
            take[n.index()] = true;
            if selected.contains(&n) {
                continue;
            }
            if let Some(children) = self.index.children(n) {
                stack.extend(children);
            }
        }
        let mut nodes: Vec<usize> =
            take.iter().zip(&self.node_of).filter(|(t, _)| **t).filter_map(|(_, n)| *n).collect();
        nodes.sort_unstable();
        Ok((nodes, sel))
    }
}

/// A recorded key as a [`NodeKey`], checked (level `0..=MAX_LEVEL`, cells inside the level).
pub fn node_key(raw: [i32; 4]) -> std::result::Result<NodeKey, String> {
    let [d, x, y, z] = raw;
    if !(0..=MAX_LEVEL as i32).contains(&d) {
        return Err(format!("has level {d} (0 to {MAX_LEVEL} accepted)"));
    }
    let cells = 1i64 << d;
    if [x, y, z].iter().any(|&v| v < 0 || v as i64 >= cells) {
        return Err(format!("lies outside the {cells} cells of its level"));
    }
    Ok(NodeKey { level: d as u8, index: [x as u32, y as u32, z as u32] })
}

/// The key one level up.
fn parent_key(k: NodeKey) -> NodeKey {
    NodeKey { level: k.level - 1, index: k.index.map(|v| v >> 1) }
}
