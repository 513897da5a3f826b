//! A node's slots in the builder: where it is and what its children are ([`Shape`]), what it
//! holds ([`NodeData`]). The builder keeps one of each per node, indexed by node id.

use crate::octree::chunks::Chunks;
use crate::octree::cube::{Cube, NodeKey};
use crate::octree::types::Point;
use crate::octree::voxels::VoxelState;

/// `first_child` of a leaf. The root (id 0) is never a child, so 0 is free.
pub(super) const NO_CHILD: u32 = 0;

/// Where a node is and what its children are.
#[derive(Clone, Copy, Debug)]
pub(super) struct Shape {
    pub(super) key: NodeKey,
    pub(super) cube: Cube,
    pub(super) first_child: u32,
}

/// What a node holds.
#[derive(Default)]
pub(super) struct NodeData {
    /// A leaf's points.
    pub(super) points: Chunks<Point>,
    /// An inner node's voxels.
    pub(super) voxels: Option<Box<VoxelState>>,
    /// Leaves: points paged out to the caller ([`Builder::page_out`](super::Builder::page_out));
    /// they precede `points` in arrival order. Inner nodes: voxels whose records the caller saved
    /// at the last `page_out` ([`NodeView::saved_voxels`](crate::octree::NodeView::saved_voxels)).
    pub(super) paged: u64,
    /// Input points in the node's cube.
    pub(super) subtree: u64,
    /// Changed since the last publish.
    pub(super) changed: bool,
}
