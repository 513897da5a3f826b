//! The structure of an octree rebuilt from its nodes' keys ([`LodIndex`] from [`IndexEntry`]s,
//! e.g. a store's hierarchy), every structural claim checked ([`LodIndexError`]): how a tree that
//! is not in memory is selected from.

use super::tree::LodTree;
use crate::octree::cube::{Cube, NodeKey};
use crate::octree::types::NodeId;
use crate::octree::types::MAX_ROOT_SIZE_LOG2;

/// One node as a [`LodIndex`] is built from it: what a store's hierarchy records.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct IndexEntry {
    /// The node's key.
    pub key: NodeKey,
    /// Whether it is a leaf.
    pub leaf: bool,
    /// Points of a leaf, voxels of an inner node.
    pub samples: u64,
}

/// Why a list of nodes is not an octree.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LodIndexError {
    /// No node at all.
    #[error("the octree has no nodes")]
    Empty,
    /// The first node is not the root.
    #[error("node 0 is {} (level {}), not the root", .key.name(), .key.level)]
    FirstNotRoot {
        /// The first node's key.
        key: NodeKey,
    },
    /// A root wider than the integer grid needs.
    #[error("the root cube is 2^{size_log2} grid units wide; at most 2^{MAX_ROOT_SIZE_LOG2} is supported")]
    RootTooLarge {
        /// Its `size_log2`.
        size_log2: u8,
    },
    /// A key outside the root cube's levels or cells.
    #[error("node {node} has level {level} and index {index:?}, outside a root cube of 2^{root_log2} units")]
    BadKey {
        /// Position of the node in the list.
        node: usize,
        /// Its level.
        level: u8,
        /// Its index.
        index: [u32; 3],
        /// `size_log2` of the root cube.
        root_log2: u8,
    },
    /// Two nodes with one key.
    #[error("nodes {first} and {second} have the same key {}", .key.name())]
    Duplicate {
        /// The first.
        first: usize,
        /// The second.
        second: usize,
        /// Their key.
        key: NodeKey,
    },
    /// An inner node without one of its 8 children.
    #[error("inner node {node} ({}) has no child in octant {octant}", .key.name())]
    MissingChild {
        /// Position of the node in the list.
        node: usize,
        /// Its key.
        key: NodeKey,
        /// The missing octant.
        octant: usize,
    },
    /// A node that no walk from the root reaches (its parent is missing or a leaf).
    #[error("node {node} ({}) is not below the root: its parent is missing or a leaf", .key.name())]
    Orphan {
        /// Position of the node in the list.
        node: usize,
        /// Its key.
        key: NodeKey,
    },
    /// More nodes than 32-bit ids.
    #[error("{nodes} nodes: at most 2^32 - 1 are supported")]
    TooManyNodes {
        /// Number of nodes.
        nodes: usize,
    },
}

/// Children of one inner node, or none.
const NO_CHILDREN: u32 = u32::MAX;

/// One node of a [`LodIndex`].
#[derive(Clone, Copy, Debug)]
struct IndexNode {
    cube: Cube,
    samples: u64,
    subtree: u64,
    /// Index into `LodIndex::children`, or [`NO_CHILDREN`] for a leaf.
    children: u32,
}

/// The structure of an octree rebuilt from its nodes' keys ([`IndexEntry`], e.g. the entries of
/// a store's hierarchy): children found by key, subtree point counts summed bottom-up, every
/// structural claim checked. A [`LodTree`] for [`select_nodes`], so a tree that is not in memory
/// as a [`Snapshot`] is selected from with the same code.
///
/// [`select_nodes`]: super::select_nodes
/// [`Snapshot`]: crate::octree::Snapshot
#[derive(Clone, Debug)]
pub struct LodIndex {
    root: Cube,
    nodes: Vec<IndexNode>,
    children: Vec<[NodeId; 8]>,
}

impl LodIndex {
    /// The tree of root cube `root` whose nodes are `entries`, the root first; node `i` of the
    /// index is `entries[i]`. Fails unless the entries form one octree: unique keys inside the
    /// root cube, every inner node with its 8 children, every node below the root.
    pub fn new(root: Cube, entries: &[IndexEntry]) -> Result<LodIndex, LodIndexError> {
        Self::build(root, entries, false)
    }

    /// [`new`](Self::new) for a tree whose build is under way: an inner node none of whose
    /// children is there yet is a frontier, drawn like a leaf (its voxels); an inner node with
    /// some children but not all is still an error. The build engine commits the tree top down,
    /// one level after another (ARCHITECTURE.md, "The build engine").
    pub fn new_partial(root: Cube, entries: &[IndexEntry]) -> Result<LodIndex, LodIndexError> {
        Self::build(root, entries, true)
    }

    fn build(
        root: Cube,
        entries: &[IndexEntry],
        frontier: bool,
    ) -> Result<LodIndex, LodIndexError> {
        use std::collections::HashMap;
        if root.size_log2 > MAX_ROOT_SIZE_LOG2 {
            return Err(LodIndexError::RootTooLarge { size_log2: root.size_log2 });
        }
        let Some(first) = entries.first() else { return Err(LodIndexError::Empty) };
        if first.key != NodeKey::ROOT {
            return Err(LodIndexError::FirstNotRoot { key: first.key });
        }
        if entries.len() >= u32::MAX as usize {
            return Err(LodIndexError::TooManyNodes { nodes: entries.len() });
        }
        let mut by_key: HashMap<NodeKey, u32> = HashMap::with_capacity(entries.len());
        for (i, e) in entries.iter().enumerate() {
            let k = e.key;
            if k.level > root.size_log2 || k.index.iter().any(|&v| (v as u64) >> k.level != 0) {
                return Err(LodIndexError::BadKey {
                    node: i,
                    level: k.level,
                    index: k.index,
                    root_log2: root.size_log2,
                });
            }
            if let Some(&j) = by_key.get(&k) {
                return Err(LodIndexError::Duplicate { first: j as usize, second: i, key: k });
            }
            by_key.insert(k, i as u32);
        }
        let mut nodes: Vec<IndexNode> = entries
            .iter()
            .map(|e| IndexNode {
                cube: e.key.cube_in(root),
                samples: e.samples,
                subtree: 0,
                children: NO_CHILDREN,
            })
            .collect();
        let mut children = Vec::new();
        let mut reached = vec![false; entries.len()];
        reached[0] = true;
        for (i, e) in entries.iter().enumerate() {
            if e.leaf {
                continue;
            }
            let mut kids = [NodeId::ROOT; 8];
            let child_at = |o: usize| {
                (e.key.level < root.size_log2).then(|| by_key.get(&e.key.child(o))).flatten()
            };
            if frontier && (0..8).all(|o| child_at(o).is_none()) {
                continue;
            }
            for (o, kid) in kids.iter_mut().enumerate() {
                // A child key exists only below level 255 and inside the root (checked above for
                // the children themselves).
                let found =
                    (e.key.level < root.size_log2).then(|| by_key.get(&e.key.child(o))).flatten();
                let Some(&c) = found else {
                    return Err(LodIndexError::MissingChild { node: i, key: e.key, octant: o });
                };
                *kid = NodeId(c);
                reached[c as usize] = true;
            }
            nodes[i].children = children.len() as u32;
            children.push(kids);
        }
        if let Some(i) = reached.iter().position(|r| !r) {
            return Err(LodIndexError::Orphan { node: i, key: entries[i].key });
        }
        // Subtree points bottom-up: children are one level deeper than their parent.
        let mut order: Vec<u32> = (0..entries.len() as u32).collect();
        order.sort_unstable_by_key(|&i| std::cmp::Reverse(entries[i as usize].key.level));
        for &i in &order {
            let n = nodes[i as usize];
            nodes[i as usize].subtree = if n.children == NO_CHILDREN {
                n.samples
            } else {
                children[n.children as usize]
                    .iter()
                    .map(|c| nodes[c.index()].subtree)
                    .fold(0u64, u64::saturating_add)
            };
        }
        Ok(LodIndex { root, nodes, children })
    }

    /// The root cube.
    pub fn root_cube(&self) -> Cube {
        self.root
    }

    /// Points in all leaves.
    pub fn point_count(&self) -> u64 {
        self.nodes[0].subtree
    }
}

impl LodTree for LodIndex {
    fn node_count(&self) -> usize {
        self.nodes.len()
    }
    fn cube(&self, id: NodeId) -> Cube {
        self.nodes[id.index()].cube
    }
    fn subtree_points(&self, id: NodeId) -> u64 {
        self.nodes[id.index()].subtree
    }
    fn children(&self, id: NodeId) -> Option<[NodeId; 8]> {
        let c = self.nodes[id.index()].children;
        (c != NO_CHILDREN).then(|| self.children[c as usize])
    }
    fn samples(&self, id: NodeId) -> u64 {
        self.nodes[id.index()].samples
    }
    fn is_leaf(&self, id: NodeId) -> bool {
        self.nodes[id.index()].children == NO_CHILDREN
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::lod::select::{select_nodes, LodOptions};
    use crate::octree::lod::testutil::{all_cameras, terrain_tree, GRID};
    use crate::octree::snapshot::Snapshot;
    use crate::render::testutil::Rng;

    /// The entries a store's hierarchy records for `snap`'s nodes, in id order.
    fn entries_of(snap: &Snapshot) -> Vec<IndexEntry> {
        snap.iter()
            .map(|(_, n)| IndexEntry {
                key: n.key(),
                leaf: n.is_leaf(),
                samples: n.point_count() + n.voxel_count(),
            })
            .collect()
    }

    #[test]
    fn lod_index_rebuilt_from_keys_selects_like_the_snapshot() {
        let (scene, snap) = terrain_tree(150_000, 3_000);
        let entries = entries_of(&snap);
        assert!(entries.len() > 100, "{} nodes", entries.len());
        // Shuffled (the root stays first): children are found by key, not by consecutive ids.
        let mut perm: Vec<usize> = (1..entries.len()).collect();
        let mut rng = Rng(77);
        for i in (1..perm.len()).rev() {
            let j = (rng.next_u64() % (i as u64 + 1)) as usize;
            perm.swap(i, j);
        }
        perm.insert(0, 0);
        let shuffled: Vec<IndexEntry> = perm.iter().map(|&i| entries[i]).collect();
        let root = snap.root_cube();
        let index = LodIndex::new(root, &entries).unwrap();
        let mixed = LodIndex::new(root, &shuffled).unwrap();
        assert_eq!(index.point_count(), snap.point_count());
        assert_eq!(mixed.point_count(), snap.point_count());
        assert_eq!(LodTree::node_count(&index), snap.node_count());
        for (id, n) in snap.iter() {
            assert_eq!(LodTree::cube(&index, id), n.cube());
            assert_eq!(LodTree::children(&index, id), n.children());
            assert_eq!(LodTree::subtree_points(&index, id), n.subtree_points(), "{id:?}");
            assert_eq!(LodTree::samples(&index, id), n.point_count() + n.voxel_count());
            assert_eq!(LodTree::is_leaf(&index, id), n.is_leaf());
        }
        let mut compared = 0;
        for cam in all_cameras(&scene) {
            for threshold_px in [0.0, 32.0, 128.0, 512.0] {
                for point_budget in [None, Some(40_000)] {
                    let opts = LodOptions { threshold_px, point_budget, cull: true };
                    let want = select_nodes(&snap, &GRID, &cam, &opts).unwrap();
                    assert_eq!(select_nodes(&index, &GRID, &cam, &opts).unwrap(), want);
                    // Through the shuffled index: the same nodes, renumbered.
                    let got = select_nodes(&mixed, &GRID, &cam, &opts).unwrap();
                    let mut back: Vec<NodeId> =
                        got.nodes.iter().map(|id| NodeId(perm[id.index()] as u32)).collect();
                    back.sort_unstable();
                    assert_eq!(back, want.nodes);
                    assert_eq!(got.stats, want.stats);
                    compared += !want.nodes.is_empty() as usize;
                }
            }
        }
        assert!(compared > 50, "{compared} non-empty selections compared");
    }

    #[test]
    fn lod_index_rejects_malformed_trees() {
        let (_, snap) = terrain_tree(20_000, 1_000);
        let root = snap.root_cube();
        let entries = entries_of(&snap);
        assert!(LodIndex::new(root, &entries).is_ok());
        assert_eq!(LodIndex::new(root, &[]).unwrap_err(), LodIndexError::Empty);
        let big = Cube { size_log2: 33, ..root };
        assert!(matches!(
            LodIndex::new(big, &entries),
            Err(LodIndexError::RootTooLarge { size_log2: 33 })
        ));
        // The root not first.
        let mut e = entries.clone();
        e.swap(0, 1);
        assert!(matches!(LodIndex::new(root, &e), Err(LodIndexError::FirstNotRoot { .. })));
        // A key outside the root's cells, and one below the deepest level.
        let mut e = entries.clone();
        e[1].key.index[0] = 2;
        assert!(matches!(LodIndex::new(root, &e), Err(LodIndexError::BadKey { node: 1, .. })));
        let mut e = entries.clone();
        e[1].key.level = root.size_log2 + 1;
        assert!(matches!(LodIndex::new(root, &e), Err(LodIndexError::BadKey { node: 1, .. })));
        // Two nodes with one key.
        let mut e = entries.clone();
        e[2].key = e[1].key;
        assert!(matches!(
            LodIndex::new(root, &e),
            Err(LodIndexError::Duplicate { first: 1, second: 2, .. })
        ));
        // An inner node without a child.
        let inner = entries.iter().rposition(|x| !x.leaf).unwrap();
        let child = snap.node(NodeId(inner as u32)).child(5).unwrap();
        let mut e = entries.clone();
        e.remove(child.index());
        let err = LodIndex::new(root, &e).unwrap_err();
        assert!(matches!(err, LodIndexError::MissingChild { octant: 5, .. }), "{err}");
        assert!(err.to_string().contains("octant 5"), "{err}");
        // An inner node recorded as a leaf: its children hang below nothing.
        let mut e = entries.clone();
        e[inner].leaf = true;
        assert!(matches!(LodIndex::new(root, &e), Err(LodIndexError::Orphan { .. })));
        // An inner node at the deepest level has no room for children.
        let tiny = Cube { size_log2: 0, ..root };
        let e = [IndexEntry { key: NodeKey::ROOT, leaf: false, samples: 1 }];
        assert!(matches!(
            LodIndex::new(tiny, &e),
            Err(LodIndexError::MissingChild { node: 0, octant: 0, .. })
        ));
        // While a build is under way, an inner node without any child is a frontier; one with
        // some children is still damaged.
        let p = LodIndex::new_partial(tiny, &e).unwrap();
        assert_eq!(p.point_count(), 1);
        let mut e = entries.clone();
        e.remove(child.index());
        assert!(matches!(
            LodIndex::new_partial(root, &e),
            Err(LodIndexError::MissingChild { octant: 5, .. })
        ));
        let top: Vec<IndexEntry> = entries.iter().filter(|x| x.key.level == 0).copied().collect();
        assert_eq!(LodIndex::new_partial(root, &top).unwrap().point_count(), top[0].samples);
    }
}
