//! Immutable views of a growing octree for renderers and store writers (paper 004 §4, §6: the
//! renderer draws the current state of the octree while updates go on).
//!
//! A [`Snapshot`] is a shared array of [`NodeView`]s, each holding `Arc`-shared payload chunks;
//! taking one costs one `Arc` clone, and it stays valid and unchanged however far the builder
//! goes on. See the module docs of [`crate::octree`] for what is monotone between snapshots.

use super::chunks::Chunks;
use super::cube::{Cube, NodeKey};
use super::types::{BuilderConfig, NodeId, Point, Voxel};
use std::sync::Arc;

/// What a node holds.
#[derive(Clone, Debug)]
pub enum Payload {
    /// A leaf's original points, in arrival order.
    Points(Chunks<Point>),
    /// An inner node's voxels, in the order their cells were first hit.
    Voxels(Chunks<Voxel>),
}

/// One node as published by the builder.
#[derive(Clone, Debug)]
pub struct NodeView {
    key: NodeKey,
    cube: Cube,
    first_child: Option<NodeId>,
    payload: Payload,
    subtree_points: u64,
    revision: u64,
    /// Leaves: points paged out; inner nodes: voxels saved ([`saved_voxels`](Self::saved_voxels)).
    paged_points: u64,
}

impl NodeView {
    pub(crate) fn new(
        key: NodeKey,
        cube: Cube,
        first_child: Option<NodeId>,
        payload: Payload,
        subtree_points: u64,
        revision: u64,
        paged_points: u64,
    ) -> NodeView {
        NodeView { key, cube, first_child, payload, subtree_points, revision, paged_points }
    }

    /// The node's key (level and cell index).
    pub fn key(&self) -> NodeKey {
        self.key
    }

    /// The node's cube in the integer grid.
    pub fn cube(&self) -> Cube {
        self.cube
    }

    /// Depth below the root.
    pub fn level(&self) -> u8 {
        self.key.level
    }

    /// Whether the node is a leaf (holds points).
    pub fn is_leaf(&self) -> bool {
        self.first_child.is_none()
    }

    /// The 8 children, indexed by octant; `None` for a leaf.
    pub fn children(&self) -> Option<[NodeId; 8]> {
        self.first_child.map(|f| std::array::from_fn(|o| NodeId(f.0 + o as u32)))
    }

    /// The child of octant `octant` (`x | y << 1 | z << 2`); `None` for a leaf.
    pub fn child(&self, octant: usize) -> Option<NodeId> {
        assert!(octant < 8, "octant {octant} out of range");
        self.first_child.map(|f| NodeId(f.0 + octant as u32))
    }

    /// The payload.
    pub fn payload(&self) -> &Payload {
        &self.payload
    }

    /// A leaf's points, `None` for an inner node.
    pub fn points(&self) -> Option<&Chunks<Point>> {
        match &self.payload {
            Payload::Points(p) => Some(p),
            Payload::Voxels(_) => None,
        }
    }

    /// An inner node's voxels, `None` for a leaf.
    pub fn voxels(&self) -> Option<&Chunks<Voxel>> {
        match &self.payload {
            Payload::Voxels(v) => Some(v),
            Payload::Points(_) => None,
        }
    }

    /// Points of the leaf held in memory, in [`points`](Self::points) (0 for an inner node).
    /// Without paging (see [`Builder::page_out`](super::Builder::page_out)) these are all its
    /// points.
    pub fn point_count(&self) -> u64 {
        self.points().map_or(0, Chunks::len)
    }

    /// Points of the leaf that the builder paged out to its caller (not in
    /// [`points`](Self::points); they come before the resident ones in arrival order). 0 unless
    /// [`Builder::page_out`](super::Builder::page_out) was used, and 0 for an inner node.
    pub fn paged_points(&self) -> u64 {
        if self.is_leaf() {
            self.paged_points
        } else {
            0
        }
    }

    /// All points of the leaf: resident plus paged out.
    pub fn total_points(&self) -> u64 {
        self.point_count() + self.paged_points()
    }

    /// The first voxels of an inner node whose records the caller saved before the last
    /// [`Builder::page_out`](super::Builder::page_out): their [`Voxel::record`]s are no longer
    /// the caller's to look up (a store has them in the node's last payload); the voxels after
    /// them carry records of the current commit interval. 0 for a leaf, and without paging.
    pub fn saved_voxels(&self) -> u64 {
        if self.is_leaf() {
            0
        } else {
            self.paged_points
        }
    }

    /// Voxels stored in the node (0 for a leaf).
    pub fn voxel_count(&self) -> u64 {
        self.voxels().map_or(0, Chunks::len)
    }

    /// Input points inside the node's cube (in the leaves below it).
    pub fn subtree_points(&self) -> u64 {
        self.subtree_points
    }

    /// The builder revision (number of changes: batches added and root growths) at which this
    /// view was last changed.
    pub fn revision(&self) -> u64 {
        self.revision
    }
}

/// An immutable view of the whole tree at one revision.
#[derive(Clone)]
pub struct Snapshot {
    pub(crate) root: Cube,
    pub(crate) config: BuilderConfig,
    pub(crate) revision: u64,
    pub(crate) input_points: u64,
    pub(crate) nodes: Arc<[Arc<NodeView>]>,
}

impl std::fmt::Debug for Snapshot {
    /// A summary, not the nodes.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Snapshot")
            .field("root", &self.root)
            .field("revision", &self.revision)
            .field("input_points", &self.input_points)
            .field("nodes", &self.nodes.len())
            .finish()
    }
}

impl Snapshot {
    /// The root cube.
    pub fn root_cube(&self) -> Cube {
        self.root
    }

    /// The builder's settings.
    pub fn config(&self) -> BuilderConfig {
        self.config
    }

    /// Number of non-empty batches added before this snapshot.
    pub fn revision(&self) -> u64 {
        self.revision
    }

    /// Number of input points added before this snapshot (all of them are in leaves).
    pub fn input_points(&self) -> u64 {
        self.input_points
    }

    /// Number of nodes (at least 1, the root).
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// All nodes, indexed by [`NodeId::index`]; the root first, a split's 8 children consecutive.
    pub fn nodes(&self) -> &[Arc<NodeView>] {
        &self.nodes
    }

    /// The node `id`. Panics if `id` is not a node of this snapshot.
    pub fn node(&self, id: NodeId) -> &NodeView {
        &self.nodes[id.index()]
    }

    /// The node `id`, or `None` if this snapshot does not have it (yet).
    pub fn get(&self, id: NodeId) -> Option<&NodeView> {
        self.nodes.get(id.index()).map(|n| &**n)
    }

    /// The nodes with their ids.
    pub fn iter(&self) -> impl Iterator<Item = (NodeId, &NodeView)> + '_ {
        self.nodes.iter().enumerate().map(|(i, n)| (NodeId(i as u32), &**n))
    }

    /// The leaves with their ids.
    pub fn leaves(&self) -> impl Iterator<Item = (NodeId, &NodeView)> + '_ {
        self.iter().filter(|(_, n)| n.is_leaf())
    }

    /// Nodes changed after revision `revision` (new, split, or with new points or voxels): what a
    /// store writer that committed `revision` must write again.
    pub fn changed_since(&self, revision: u64) -> impl Iterator<Item = (NodeId, &NodeView)> + '_ {
        self.iter().filter(move |(_, n)| n.revision > revision)
    }

    /// The leaf whose cube holds `pos`, `None` outside the root cube.
    pub fn leaf_at(&self, pos: [i32; 3]) -> Option<NodeId> {
        if !self.root.contains(pos) {
            return None;
        }
        let mut id = NodeId::ROOT;
        loop {
            let n = self.node(id);
            match n.first_child {
                None => return Some(id),
                Some(f) => id = NodeId(f.0 + n.cube.octant_of(pos) as u32),
            }
        }
    }

    /// Points held in memory in all leaves (equals [`input_points`](Self::input_points) unless
    /// the builder paged points out).
    pub fn point_count(&self) -> u64 {
        self.nodes.iter().map(|n| n.point_count()).sum()
    }

    /// Points in all leaves, paged out or not (always [`input_points`](Self::input_points)).
    pub fn total_points(&self) -> u64 {
        self.nodes.iter().map(|n| n.total_points()).sum()
    }

    /// Voxels in all inner nodes.
    pub fn voxel_count(&self) -> u64 {
        self.nodes.iter().map(|n| n.voxel_count()).sum()
    }
}
