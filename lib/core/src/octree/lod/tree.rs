//! The tree a selection walks ([`LodTree`]): a node's cube, children, sample count and subtree
//! point count, whether the octree is a [`Snapshot`] in memory or a store on disk.

use crate::octree::cube::Cube;
use crate::octree::snapshot::Snapshot;
use crate::octree::types::NodeId;

/// A tree that [`select_nodes`] can walk: the octree of a [`Snapshot`] in memory, or of a store
/// on disk through a [`LodIndex`].
///
/// Nodes are numbered `0..node_count()` with the root at [`NodeId::ROOT`]; the children of an
/// inner node are 8 other nodes of the tree, one per octant (`x | y << 1 | z << 2`), each one
/// level deeper, so a walk from the root ends. [`LodIndex::new`] checks this for data read from
/// files; [`select_nodes`] may panic on an implementation that breaks it.
///
/// [`select_nodes`]: super::select_nodes
/// [`LodIndex`]: super::LodIndex
/// [`LodIndex::new`]: super::LodIndex::new
pub trait LodTree {
    /// Number of nodes (the root included).
    fn node_count(&self) -> usize;
    /// The node's cube in the integer grid.
    fn cube(&self, id: NodeId) -> Cube;
    /// Input points in the leaves below (or at) the node.
    fn subtree_points(&self, id: NodeId) -> u64;
    /// The 8 children by octant, `None` for a leaf.
    fn children(&self, id: NodeId) -> Option<[NodeId; 8]>;
    /// Samples the node holds: the points of a leaf, the voxels of an inner node.
    fn samples(&self, id: NodeId) -> u64;
    /// Whether the node is a leaf (holds points rather than voxels).
    fn is_leaf(&self, id: NodeId) -> bool {
        self.children(id).is_none()
    }
}

impl LodTree for Snapshot {
    fn node_count(&self) -> usize {
        Snapshot::node_count(self)
    }
    fn cube(&self, id: NodeId) -> Cube {
        self.node(id).cube()
    }
    fn subtree_points(&self, id: NodeId) -> u64 {
        self.node(id).subtree_points()
    }
    fn children(&self, id: NodeId) -> Option<[NodeId; 8]> {
        self.node(id).children()
    }
    fn samples(&self, id: NodeId) -> u64 {
        let n = self.node(id);
        n.point_count() + n.voxel_count()
    }
    fn is_leaf(&self, id: NodeId) -> bool {
        self.node(id).is_leaf()
    }
}
