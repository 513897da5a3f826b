//! Drawing the octree: node payloads as quantized batches (paper 003 §3.5, "a node is a
//! variable-size batch") and the view-dependent LOD node selection of paper 004 §6.
//!
//! # Node batches
//!
//! [`node_batch`] turns one node of a [`Snapshot`] into the batch layout that the rasterizer
//! ([`crate::render::rasterize`]) draws, so one renderer draws batch files and octrees alike:
//!
//! - a leaf's points keep their exact integer coordinates: the batch's frame
//!   ([`BatchGrid`]) is the tight integer bounds of the points, so [`BatchGrid::decode_exact`] of
//!   the words gives every point back bit for bit (paper 003 §3.3 in mortar's integer-grid form);
//! - an inner node's voxels are real source points (the first point that claimed each cell,
//!   [`Voxel`](super::Voxel)), drawn at their exact integer coordinates in the same way.
//!
//! The batch's samples are in the node's payload order (points in arrival order, voxels in the
//! order their cells were first hit), so index `i` of the batch is element `i` of
//! [`NodeView::points`] or [`NodeView::voxels`]: a resolve pass finds the record of a leaf point
//! or of a voxel's point through [`Point::record`](super::Point::record) /
//! [`Voxel::record`](super::Voxel::record).
//!
//! **Wide nodes.** A batch stores at most 30 bits per axis ([`MAX_BITS`]). A node whose samples
//! span `2^30` grid units or more on an axis is refused with [`NodeBatchError::TooWide`], never
//! stored lossily. This needs data wider than `2^30` units (1,074 km at millimetre scale) and
//! then concerns only the nodes above level `size_log2 - 30` of the root, at most the top two
//! levels; such nodes are normally drawn only from far away. Splitting them into several batches
//! (as [`crate::batching`] does for batch files) is not done here: see "Not done" below.
//!
//! # Node selection (paper 004 §6)
//!
//! [`select_nodes`] walks the tree from the root and picks the nodes to draw for one view:
//!
//! - nodes whose (conservatively expanded) cube lies outside the view frustum are skipped with
//!   their subtrees (when [`LodOptions::cull`] is set), and so are empty nodes;
//! - a visible inner node is replaced by its visible, non-empty children (the parent is then not
//!   drawn) when its projected size on screen, [`Camera::projected_size`] of its cube's world
//!   bounds, exceeds [`LodOptions::threshold_px`]: 128 px by default, because an inner node has
//!   128³ voxels and so its voxels stay about a pixel wide ("we need to draw their half-sized
//!   children if they grow larger than 128 pixels");
//! - a leaf, a node at most `threshold_px` wide, or a node whose refinement would overflow the
//!   point budget is drawn.
//!
//! With a [`LodOptions::point_budget`] (counting points and voxels alike, as the paper's "voxels &
//! points rendered"), candidates are refined largest projected size first (a priority queue), so
//! the budget goes to what is largest on screen; the first refinement that would exceed the
//! budget ends the walk (as Potree's point budget does), so no node is refined while a larger one
//! stays coarse. Every remaining candidate is then drawn as it is, so the selection still covers
//! all visible data, only coarser. The root is drawn whatever its size: a budget smaller than
//! the root's own voxels is exceeded (with the root alone) rather than leaving the screen empty.
//!
//! Culling matches the rasterizer's ([`crate::render::Planner`]): the frustum is widened by
//! [`CULL_MARGIN_PX`] on each side, and the cube by `size / 1024 + 1` grid units per axis (more
//! than twice the largest decode error of any batch inside the cube, at 10-bit precision) plus
//! a relative depth slack, so that no point or voxel of a culled node can be drawn.
//!
//! The walk needs only a node's cube, children, sample count and subtree point count: the
//! [`LodTree`] trait. [`Snapshot`] implements it, and so does [`LodIndex`], the structure of a
//! tree rebuilt (and checked) from its nodes' keys, which is how a store on disk is selected from
//! (`mortar_io::store::StoreLod`) without loading its payloads.
//!
//! Differences from the paper: the paper picks nodes on the GPU by the parent's size only, with
//! no budget; mortar selects on the host in f64 (as it plans batches, see
//! [`crate::render::Planner`]) and adds the budget of performance-sensitive viewers (§7.3: "would
//! limit the number of points/voxels of the same structure to a point budget").
//!
//! # Not done
//!
//! - Nodes wider than `2^30` grid units are refused by [`node_batch`] rather than split.
//! - Voxels are drawn as pixel-sized points like the paper's splats; growing their size to the
//!   cell's projected size (to fill holes in coarse selections) is left to the renderer.

use super::cube::{Cube, NodeKey};
use super::snapshot::{NodeView, Payload, Snapshot};
use super::types::NodeId;
use super::types::MAX_ROOT_SIZE_LOG2;
use crate::grid::Grid;
use crate::quantize::{bits_for_extent, BatchGrid, MAX_BITS};
use crate::render::frustum::{Containment, Frustum};
use crate::render::math::Aabb;
use crate::render::plan::CULL_MARGIN_PX;
use crate::render::raster::BatchRef;
use crate::render::{Camera, CameraError};
use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// Default [`LodOptions::threshold_px`]: the edge of an inner node's voxel grid (paper 004 §6).
pub const DEFAULT_THRESHOLD_PX: f64 = 128.0;

/// Relative depth slack of node culling, in units of (distance to the cube + its diagonal); the
/// same as the rasterizer's per-batch culling.
const CULL_DEPTH_MARGIN: f64 = 1e-5;

/// One node's payload in the quantized batch layout (paper 003 §3.3, §3.5), ready for
/// [`crate::render::rasterize`] through [`NodeBatch::batch_ref`].
#[derive(Clone, Debug, PartialEq)]
pub struct NodeBatch {
    /// The quantization frame: the tight integer bounds of the samples (points or voxel centres).
    pub grid: BatchGrid,
    /// Smallest world coordinate of the samples (on each axis; ordered for negative scales).
    pub bounds_min: [f64; 3],
    /// Largest world coordinate of the samples.
    pub bounds_max: [f64; 3],
    /// Coarse, medium and fine words ([`BatchGrid::encode`]), one per sample each.
    pub words: [Vec<u32>; 3],
    /// RGBA8 colour per sample, `r | g << 8 | b << 16 | a << 24`.
    pub colors: Vec<u32>,
}

impl NodeBatch {
    /// Number of samples (points or voxels).
    pub fn len(&self) -> usize {
        self.words[0].len()
    }

    /// Whether the batch has no samples.
    pub fn is_empty(&self) -> bool {
        self.words[0].is_empty()
    }

    /// The batch as the rasterizer takes it, its samples numbered from `first_index` in the
    /// framebuffer's 32-bit point index.
    pub fn batch_ref(&self, first_index: u32) -> BatchRef<'_> {
        BatchRef {
            grid: self.grid,
            bounds_min: self.bounds_min,
            bounds_max: self.bounds_max,
            words: [&self.words[0], &self.words[1], &self.words[2]],
            first_index,
        }
    }

    /// The world bounds as a box.
    pub fn bounds(&self) -> Aabb {
        Aabb::new(self.bounds_min, self.bounds_max)
    }
}

/// Why a node cannot become one batch.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NodeBatchError {
    /// The samples span more than a batch's 30 bits on an axis.
    #[error(
        "octree node {} spans {extent} grid units on axis {axis}; a batch holds at most 2^30 - 1 (30 bits), so the node cannot be drawn as one batch",
        .key.name()
    )]
    TooWide {
        /// The node.
        key: NodeKey,
        /// The axis, `x`, `y` or `z`.
        axis: char,
        /// Extent `max - min` of the samples on that axis, in grid units.
        extent: u64,
    },
}

/// Grows `(lo, hi)` by the integer position `p`.
#[inline]
fn grow(lo: &mut [i32; 3], hi: &mut [i32; 3], p: [i32; 3]) {
    for a in 0..3 {
        lo[a] = lo[a].min(p[a]);
        hi[a] = hi[a].max(p[a]);
    }
}

/// The node's payload as a quantized batch on the world grid `grid`: leaf points and the points
/// that inner-node voxels stand for, exactly. Fails for a node whose samples
/// span `2^30` grid units or more on an axis.
pub fn node_batch(node: &NodeView, grid: &Grid) -> Result<NodeBatch, NodeBatchError> {
    let cube = node.cube();
    let mut lo = [i32::MAX; 3];
    let mut hi = [i32::MIN; 3];
    let len = match node.payload() {
        Payload::Points(p) => {
            for pt in p.iter() {
                grow(&mut lo, &mut hi, pt.pos);
            }
            p.len() as usize
        }
        Payload::Voxels(v) => {
            for vx in v.iter() {
                grow(&mut lo, &mut hi, vx.pos);
            }
            v.len() as usize
        }
    };
    if len == 0 {
        // An empty batch: a zero-bit frame at the cube's corner (the rasterizer skips it).
        let min = cube.min.map(|m| m.clamp(i32::MIN as i64, i32::MAX as i64) as i32);
        lo = min;
        hi = min;
    }
    let mut bits = [0u8; 3];
    for a in 0..3 {
        let extent = (hi[a] as i64 - lo[a] as i64) as u64;
        let b = bits_for_extent(extent);
        if b > MAX_BITS {
            return Err(NodeBatchError::TooWide {
                key: node.key(),
                axis: ['x', 'y', 'z'][a],
                extent,
            });
        }
        bits[a] = b as u8;
    }
    let frame = BatchGrid { min: lo, bits };
    let mut words = [Vec::with_capacity(len), Vec::with_capacity(len), Vec::with_capacity(len)];
    let mut colors = Vec::with_capacity(len);
    let mut push = |p: [i32; 3], color: u32| {
        let w = frame.encode(p);
        for i in 0..3 {
            words[i].push(w[i]);
        }
        colors.push(color);
    };
    match node.payload() {
        Payload::Points(p) => {
            for c in p.chunks() {
                for pt in c.iter() {
                    push(pt.pos, pt.color);
                }
            }
        }
        Payload::Voxels(v) => {
            for c in v.chunks() {
                for vx in c.iter() {
                    push(vx.pos, vx.color);
                }
            }
        }
    }
    let mut bounds_min = [0.0; 3];
    let mut bounds_max = [0.0; 3];
    for a in 0..3 {
        let (x, y) = (grid.world(a, lo[a] as i64), grid.world(a, hi[a] as i64));
        bounds_min[a] = x.min(y);
        bounds_max[a] = x.max(y);
    }
    Ok(NodeBatch { grid: frame, bounds_min, bounds_max, words, colors })
}

/// Choices of [`select_nodes`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LodOptions {
    /// A visible inner node is replaced by its children when its projected size (pixels, the
    /// larger side of its cube's screen rectangle) exceeds this; default
    /// [`DEFAULT_THRESHOLD_PX`]. 0 refines every visible inner node (all visible leaves are
    /// drawn); infinity (or NaN) never refines (the root alone is drawn).
    pub threshold_px: f64,
    /// Most samples (points plus voxels) to select, or `None` for no limit. Refinement stops at
    /// the first node whose refinement would exceed it; the root is selected even when it alone
    /// exceeds it.
    pub point_budget: Option<u64>,
    /// Whether nodes outside the view frustum are skipped.
    pub cull: bool,
}

impl Default for LodOptions {
    fn default() -> Self {
        LodOptions { threshold_px: DEFAULT_THRESHOLD_PX, point_budget: None, cull: true }
    }
}

/// What a [`select_nodes`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct LodStats {
    /// Nodes tested (frustum and projected size), the root included.
    pub visited: u64,
    /// Of those, nodes outside the frustum (skipped with their subtrees).
    pub culled: u64,
    /// Of those, nodes without any point in their cube (skipped).
    pub empty: u64,
    /// Inner nodes replaced by their children.
    pub refined: u64,
    /// Nodes selected.
    pub selected: u64,
    /// Points in the selected leaves.
    pub points: u64,
    /// Voxels in the selected inner nodes.
    pub voxels: u64,
    /// Whether the point budget stopped the refinement.
    pub budget_reached: bool,
}

impl LodStats {
    /// Samples selected: points plus voxels (what the point budget counts).
    pub fn samples(&self) -> u64 {
        self.points + self.voxels
    }
}

/// The nodes to draw for one view.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LodSelection {
    /// The selected nodes, by ascending id. No two of them are nested, and every non-empty leaf
    /// that is not below a culled node is, or lies below, exactly one of them.
    pub nodes: Vec<NodeId>,
    /// The nodes culled by the frustum test, by ascending id (their subtrees were not visited).
    pub culled: Vec<NodeId>,
    /// Counts.
    pub stats: LodStats,
}

/// A tree that [`select_nodes`] can walk: the octree of a [`Snapshot`] in memory, or of a store
/// on disk through a [`LodIndex`].
///
/// Nodes are numbered `0..node_count()` with the root at [`NodeId::ROOT`]; the children of an
/// inner node are 8 other nodes of the tree, one per octant (`x | y << 1 | z << 2`), each one
/// level deeper, so a walk from the root ends. [`LodIndex::new`] checks this for data read from
/// files; [`select_nodes`] may panic on an implementation that breaks it.
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

/// The outcome of testing one node.
enum Visit {
    Empty,
    Culled,
    /// Visible, with its projected size in pixels.
    Visible(f64),
}

/// The view-dependent parts of a selection.
struct View<'a> {
    grid: &'a Grid,
    camera: &'a Camera,
    frustum: Option<Frustum>,
}

impl View<'_> {
    fn visit<T: LodTree + ?Sized>(&self, tree: &T, id: NodeId) -> Visit {
        if tree.subtree_points(id) == 0 {
            return Visit::Empty;
        }
        let cube = tree.cube(id);
        let bounds = cube.world_bounds(self.grid);
        if let Some(frustum) = &self.frustum {
            // Decoded samples stay within size / 2^11 grid units of the cube (see the module
            // docs); f32 depth may be off by a tiny fraction of the distance.
            let units = (cube.size() >> 10) as f64 + 1.0;
            let d = bounds
                .center()
                .iter()
                .zip(&self.camera.eye)
                .map(|(c, e)| (c - e) * (c - e))
                .sum::<f64>()
                .sqrt();
            let slack = CULL_DEPTH_MARGIN * (d + bounds.diagonal());
            let margin = [0, 1, 2].map(|a| units * self.grid.scale[a].abs() + slack);
            if frustum.test_aabb(&bounds.expanded(margin)) == Containment::Outside {
                return Visit::Culled;
            }
        }
        Visit::Visible(self.camera.projected_size(&bounds))
    }
}

/// An inner node waiting to be refined, ordered by projected size (then by smaller id first).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Candidate {
    size: f64,
    id: NodeId,
}

impl Eq for Candidate {}

impl Ord for Candidate {
    fn cmp(&self, other: &Self) -> Ordering {
        self.size.total_cmp(&other.size).then_with(|| other.id.cmp(&self.id))
    }
}

impl PartialOrd for Candidate {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// Selects the nodes of `tree` (a [`Snapshot`], a [`LodIndex`] of a store, any [`LodTree`]) to
/// draw for `camera` (paper 004 §6; see the module docs): from the root down, culling nodes
/// outside the frustum, replacing inner nodes larger than `options.threshold_px` on screen by
/// their children, largest first, within the point budget. `grid` is the world grid of the
/// tree's integer coordinates. Fails only for an unusable camera.
pub fn select_nodes<T: LodTree + ?Sized>(
    tree: &T,
    grid: &Grid,
    camera: &Camera,
    options: &LodOptions,
) -> Result<LodSelection, CameraError> {
    camera.validate()?;
    let view =
        View { grid, camera, frustum: options.cull.then(|| Frustum::new(camera, CULL_MARGIN_PX)) };
    let refinable = |id: NodeId, size: f64| !tree.is_leaf(id) && size > options.threshold_px;
    let mut sel = LodSelection::default();
    let mut drawn = vec![false; tree.node_count()];
    let mut heap = BinaryHeap::new();
    let mut total = 0u64;

    sel.stats.visited = 1;
    match view.visit(tree, NodeId::ROOT) {
        Visit::Empty => sel.stats.empty = 1,
        Visit::Culled => {
            sel.stats.culled = 1;
            sel.culled.push(NodeId::ROOT);
        }
        Visit::Visible(size) => {
            drawn[0] = true;
            total = tree.samples(NodeId::ROOT);
            if refinable(NodeId::ROOT, size) {
                heap.push(Candidate { size, id: NodeId::ROOT });
            }
        }
    }

    while let Some(Candidate { id, .. }) = heap.pop() {
        let Some(children) = tree.children(id) else { continue };
        let mut kids = [(NodeId::ROOT, 0.0); 8];
        let mut n_kids = 0;
        let mut culled = [NodeId::ROOT; 8];
        let mut n_culled = 0;
        let mut n_empty = 0;
        let mut cost = 0u64;
        for c in children {
            match view.visit(tree, c) {
                Visit::Empty => n_empty += 1,
                Visit::Culled => {
                    culled[n_culled] = c;
                    n_culled += 1;
                }
                Visit::Visible(size) => {
                    kids[n_kids] = (c, size);
                    n_kids += 1;
                    cost = cost.saturating_add(tree.samples(c));
                }
            }
        }
        let after = (total - tree.samples(id)).saturating_add(cost);
        if options.point_budget.is_some_and(|b| after > b) {
            sel.stats.budget_reached = true;
            break;
        }
        total = after;
        drawn[id.index()] = false;
        sel.stats.refined += 1;
        sel.stats.visited += 8;
        sel.stats.empty += n_empty;
        sel.stats.culled += n_culled as u64;
        sel.culled.extend_from_slice(&culled[..n_culled]);
        for &(c, size) in &kids[..n_kids] {
            drawn[c.index()] = true;
            if refinable(c, size) {
                heap.push(Candidate { size, id: c });
            }
        }
    }

    sel.nodes =
        drawn.iter().enumerate().filter(|(_, d)| **d).map(|(i, _)| NodeId(i as u32)).collect();
    sel.culled.sort_unstable();
    for &id in &sel.nodes {
        let s = tree.samples(id);
        if tree.is_leaf(id) {
            sel.stats.points += s;
        } else {
            sel.stats.voxels += s;
        }
    }
    sel.stats.selected = sel.nodes.len() as u64;
    debug_assert_eq!(sel.stats.samples(), total);
    Ok(sel)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::batching::int_bounds;
    use crate::octree::{Builder, BuilderConfig, Point};
    use crate::quantize::Precision;
    use crate::render::framebuffer::key_index;
    use crate::render::testutil::{Rng, Scene};
    use crate::render::{
        rasterize, Framebuffer, PrecisionMode, RasterOptions, ViewPreset, EMPTY_KEY,
    };
    use std::collections::HashSet;

    /// A georeferenced millimetre grid (UTM-like offsets).
    const GRID: Grid = Grid { scale: [0.001; 3], offset: [500_000.0, 5_400_000.0, 0.0] };

    /// [`Scene::terrain`] built into an octree in a shuffled arrival order, in several batches;
    /// `Point::record` is the point's index in the scene (its global index there).
    fn terrain_tree(n: usize, cap: u32) -> (Scene, Snapshot) {
        let scene = Scene::terrain(n, 11, GRID);
        let mut pts: Vec<Point> = scene
            .points
            .iter()
            .zip(&scene.colors)
            .enumerate()
            .map(|(i, (p, c))| Point { pos: *p, color: *c, record: i as u64 })
            .collect();
        let mut rng = Rng(5);
        for i in (1..pts.len()).rev() {
            let j = (rng.next_u64() % (i as u64 + 1)) as usize;
            pts.swap(i, j);
        }
        let (min, max) = int_bounds(&scene.points);
        let mut b = Builder::for_bounds(
            min,
            max,
            BuilderConfig { leaf_capacity: cap, ..BuilderConfig::default() },
        )
        .unwrap();
        for c in pts.chunks(37_000) {
            b.add_batch(c).unwrap();
        }
        (scene, b.snapshot())
    }

    fn small(c: Camera) -> Camera {
        Camera { width: 640, height: 360, ..c }
    }

    /// Every preset framed, in perspective and orthographic.
    fn framed(scene: &Scene) -> Vec<Camera> {
        let mut cams = Vec::new();
        for preset in ViewPreset::ALL {
            cams.push(Camera::frame_perspective(&scene.bounds, preset, 0.8, 640, 360).unwrap());
            cams.push(Camera::frame_orthographic(&scene.bounds, preset, 640, 360).unwrap());
        }
        cams
    }

    /// Framed views and views in which much of the tree is outside the frustum.
    fn all_cameras(scene: &Scene) -> Vec<Camera> {
        let mut cams = framed(scene);
        cams.extend(scene.cameras().into_iter().skip(8).map(small));
        cams.push(Camera::close_up(&scene.bounds, 0.8, 640, 360).unwrap());
        cams.push(Camera::inside(&scene.bounds, 1.2, 640, 360).unwrap());
        cams
    }

    fn parents(snap: &Snapshot) -> Vec<Option<NodeId>> {
        let mut p = vec![None; snap.node_count()];
        for (id, n) in snap.iter() {
            for c in n.children().into_iter().flatten() {
                p[c.index()] = Some(id);
            }
        }
        p
    }

    /// `id` and its ancestors up to the root.
    fn lineage(parents: &[Option<NodeId>], id: NodeId) -> Vec<NodeId> {
        let mut v = vec![id];
        while let Some(p) = parents[v.last().unwrap().index()] {
            v.push(p);
        }
        v
    }

    /// Whether the f64 reference projection puts `p` in the viewport and depth range.
    fn visible(cam: &Camera, p: [i32; 3]) -> bool {
        let w = [0, 1, 2].map(|a| GRID.world(a, p[a] as i64));
        cam.project(w).is_some_and(|q| {
            q.x >= 0.0 && q.x < cam.width as f64 && q.y >= 0.0 && q.y < cam.height as f64
        })
    }

    /// The leaves below (or at) `id`.
    fn leaves_below(snap: &Snapshot, id: NodeId, out: &mut Vec<NodeId>) {
        match snap.node(id).children() {
            None => out.push(id),
            Some(cs) => cs.iter().for_each(|&c| leaves_below(snap, c, out)),
        }
    }

    /// A leaf's batch built independently of [`node_batch`]: the frame of
    /// [`BatchGrid::for_bounds`] over the points, world bounds of its corners.
    fn reference_batch(points: &[Point]) -> NodeBatch {
        let pos: Vec<[i32; 3]> = points.iter().map(|p| p.pos).collect();
        let (min, max) = int_bounds(&pos);
        let frame = BatchGrid::for_bounds(min, max).unwrap();
        let mut words = [Vec::new(), Vec::new(), Vec::new()];
        for p in &pos {
            let w = frame.encode(*p);
            (0..3).for_each(|i| words[i].push(w[i]));
        }
        let world = |v: [i32; 3]| [0, 1, 2].map(|a| GRID.world(a, v[a] as i64));
        NodeBatch {
            grid: frame,
            bounds_min: world(min),
            bounds_max: world(max),
            words,
            colors: points.iter().map(|p| p.color).collect(),
        }
    }

    fn render(cam: &Camera, refs: &[BatchRef<'_>], cull: bool) -> Vec<u64> {
        render_with(cam, refs, &RasterOptions { cull, ..RasterOptions::default() })
    }

    fn render_with(cam: &Camera, refs: &[BatchRef<'_>], options: &RasterOptions) -> Vec<u64> {
        let fb = Framebuffer::new(cam.width, cam.height);
        rasterize(&fb, refs, &GRID, cam, options).unwrap();
        fb.into_keys()
    }

    #[test]
    fn leaf_batches_are_exact_and_voxels_sit_in_their_cells() {
        let (_, snap) = terrain_tree(60_000, 1_500);
        assert!(snap.nodes().iter().any(|n| !n.is_leaf()) && snap.leaves().count() > 8);
        for (id, n) in snap.iter() {
            let b = node_batch(n, &GRID).unwrap();
            assert_eq!(b.len() as u64, n.point_count() + n.voxel_count(), "{id:?}");
            assert_eq!(b.colors.len(), b.len());
            assert!(b.grid.bits.iter().all(|&x| x as u32 <= MAX_BITS));
            let r = b.batch_ref(1234);
            assert_eq!((r.first_index, r.len(), r.grid), (1234, b.len(), b.grid));
            assert_eq!(r.bounds(), b.bounds());
            let decoded: Vec<[i32; 3]> = (0..b.len())
                .map(|i| b.grid.decode_exact([b.words[0][i], b.words[1][i], b.words[2][i]]))
                .collect();
            let bounds = b.bounds();
            for p in &decoded {
                let w = [0, 1, 2].map(|a| GRID.world(a, p[a] as i64));
                assert!(
                    (0..3).all(|a| bounds.min[a] <= w[a] && w[a] <= bounds.max[a]),
                    "{id:?} {p:?}"
                );
            }
            match n.payload() {
                Payload::Points(pts) => {
                    for ((pt, p), c) in pts.iter().zip(&decoded).zip(&b.colors) {
                        assert_eq!(pt.pos, *p, "{id:?}");
                        assert_eq!(pt.color, *c);
                    }
                    if !pts.is_empty() {
                        // The same batch as an independent encoding of the points.
                        assert_eq!(b, reference_batch(&pts.to_vec()), "{id:?}");
                    }
                }
                Payload::Voxels(vx) => {
                    let cube = n.cube();
                    for ((v, p), c) in vx.iter().zip(&decoded).zip(&b.colors) {
                        assert!(cube.contains(*p), "{id:?} {p:?}");
                        assert_eq!(v.pos, *p, "{id:?}: the representative point, exactly");
                        assert_eq!(v.color, *c);
                    }
                }
            }
        }
    }

    #[test]
    fn wide_nodes_are_refused_and_edge_cells_clamped() {
        // A single leaf spanning 2^31 - 1 units.
        let mut b = Builder::new(Cube::new([0; 3], 31), BuilderConfig::default()).unwrap();
        b.add_batch(&[
            Point { pos: [0, 0, 0], ..Point::default() },
            Point { pos: [i32::MAX, 3, 0], ..Point::default() },
        ])
        .unwrap();
        let snap = b.snapshot();
        let err = node_batch(snap.node(NodeId::ROOT), &GRID).unwrap_err();
        assert_eq!(
            err,
            NodeBatchError::TooWide { key: NodeKey::ROOT, axis: 'x', extent: i32::MAX as u64 }
        );
        assert!(err.to_string().contains("node r "), "{err}");

        // A tree over the whole i32 range: only nodes wider than 2^30 units can fail.
        let mut rng = Rng(9);
        let pts: Vec<Point> = (0..4_000)
            .map(|i| Point { pos: [0; 3].map(|_: i32| rng.next_u64() as i32), color: 0, record: i })
            .collect();
        let mut b = Builder::for_bounds(
            [i32::MIN; 3],
            [i32::MAX; 3],
            BuilderConfig { leaf_capacity: 200, ..BuilderConfig::default() },
        )
        .unwrap();
        b.add_batch(&pts).unwrap();
        let snap = b.snapshot();
        assert_eq!(snap.root_cube().size_log2, 32);
        assert!(matches!(
            node_batch(snap.node(NodeId::ROOT), &GRID),
            Err(NodeBatchError::TooWide { .. })
        ));
        for (id, n) in snap.iter().filter(|(_, n)| n.cube().size_log2 <= 30) {
            node_batch(n, &GRID).unwrap_or_else(|e| panic!("{id:?}: {e}"));
        }

        // A root cube overhanging i32::MAX: voxels are real points inside their cells.
        let lo = i32::MAX - 1000;
        let mut pts: Vec<Point> = (0..600)
            .map(|i| Point { pos: [lo + (i * 7919) % 1001; 3], color: i as u32, record: i as u64 })
            .collect();
        pts.push(Point { pos: [lo; 3], color: 1, record: 600 });
        pts.push(Point { pos: [i32::MAX; 3], color: 2, record: 601 });
        let mut b = Builder::for_bounds(
            [lo; 3],
            [i32::MAX; 3],
            BuilderConfig { leaf_capacity: 50, ..BuilderConfig::default() },
        )
        .unwrap();
        b.add_batch(&pts).unwrap();
        let snap = b.snapshot();
        let root = snap.node(NodeId::ROOT);
        assert!(root.cube().end()[0] > i32::MAX as i64 && !root.is_leaf());
        let nb = node_batch(root, &GRID).unwrap();
        let mut top = 0;
        for (v, i) in root.voxels().unwrap().iter().zip(0..) {
            let p = nb.grid.decode_exact([nb.words[0][i], nb.words[1][i], nb.words[2][i]]);
            assert_eq!(p, v.pos);
            assert!(
                pts.iter().any(|q| q.pos == p && q.record == v.record),
                "a voxel is a source point"
            );
            top += (p == [i32::MAX; 3]) as usize;
        }
        assert_eq!(top, 1);
    }

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

    #[test]
    fn threshold_zero_selects_the_visible_leaves_and_draws_every_point() {
        let (scene, snap) = terrain_tree(150_000, 3_000);
        let parents = parents(&snap);
        let leaves: Vec<NodeId> =
            snap.leaves().filter(|(_, n)| n.point_count() > 0).map(|(id, _)| id).collect();
        // One global numbering of all leaf points, by leaf id: the same for both renders.
        let mut first = vec![0u32; snap.node_count()];
        let mut records = Vec::new();
        let mut all = Vec::new();
        for &id in &leaves {
            first[id.index()] = records.len() as u32;
            let pts = snap.node(id).points().unwrap().to_vec();
            records.extend(pts.iter().map(|p| p.record));
            all.push(reference_batch(&pts));
        }
        let all_refs: Vec<BatchRef<'_>> =
            leaves.iter().zip(&all).map(|(id, b)| b.batch_ref(first[id.index()])).collect();
        let scene_refs = scene.refs();
        let opts = LodOptions { threshold_px: 0.0, point_budget: None, cull: true };

        // Without culling: every non-empty leaf.
        let sel =
            select_nodes(&snap, &GRID, &framed(&scene)[0], &LodOptions { cull: false, ..opts })
                .unwrap();
        assert_eq!(sel.nodes, leaves);
        assert_eq!(sel.stats.points, snap.point_count());

        let mut culling_seen = false;
        for (ci, cam) in all_cameras(&scene).iter().enumerate() {
            let sel = select_nodes(&snap, &GRID, cam, &opts).unwrap();
            let chosen: HashSet<NodeId> = sel.nodes.iter().copied().collect();
            // Exactly the non-empty leaves not below a culled node.
            let culled: HashSet<NodeId> = sel.culled.iter().copied().collect();
            let want: Vec<NodeId> = leaves
                .iter()
                .copied()
                .filter(|&l| !lineage(&parents, l).iter().any(|a| culled.contains(a)))
                .collect();
            assert_eq!(sel.nodes, want, "camera {ci}");
            culling_seen |= !culled.is_empty();
            assert_eq!(sel.stats.voxels, 0);
            assert_eq!(sel.stats.selected, sel.nodes.len() as u64);
            assert_eq!(sel.stats.culled, sel.culled.len() as u64);
            // Every leaf with a visible point is selected.
            for &l in &leaves {
                if snap.node(l).points().unwrap().iter().any(|p| visible(cam, p.pos)) {
                    assert!(chosen.contains(&l), "camera {ci}: visible leaf {l:?} not selected");
                }
            }

            // The selected leaves, drawn through node_batch and culled, give the very keys of all
            // leaves drawn without culling.
            let batches: Vec<NodeBatch> =
                sel.nodes.iter().map(|&id| node_batch(snap.node(id), &GRID).unwrap()).collect();
            let refs: Vec<BatchRef<'_>> = sel
                .nodes
                .iter()
                .zip(&batches)
                .map(|(id, b)| b.batch_ref(first[id.index()]))
                .collect();
            let got = render(cam, &refs, true);
            let want_keys = render(cam, &all_refs, false);
            let covered = want_keys.iter().filter(|&&k| k != EMPTY_KEY).count();
            assert!(covered > 1_000, "camera {ci}: {covered} pixels");
            assert_eq!(got, want_keys, "camera {ci}: keys differ");

            // Against the original points in Morton batches (other frames, so f32 rounding may
            // move a point across a pixel edge): the same winning record almost everywhere.
            let exact =
                RasterOptions { precision: PrecisionMode::Fixed(Precision::Bits30), cull: false };
            let got = render_with(cam, &refs, &exact);
            let orig = render_with(cam, &scene_refs, &exact);
            let differ = got
                .iter()
                .zip(&orig)
                .filter(|(&a, &b)| match (a == EMPTY_KEY, b == EMPTY_KEY) {
                    (true, true) => false,
                    (false, false) => records[key_index(a) as usize] != key_index(b) as u64,
                    _ => true,
                })
                .count();
            assert!(
                differ * 100 <= covered,
                "camera {ci}: {differ} of {covered} pixels differ from the original points"
            );
        }
        assert!(culling_seen, "some camera culls nodes");
    }

    #[test]
    fn larger_thresholds_select_fewer_samples() {
        let (scene, snap) = terrain_tree(150_000, 3_000);
        let thresholds = [0.0, 4.0, 16.0, 64.0, 128.0, 256.0, 600.0, 2_000.0, 1e9, f64::INFINITY];
        let mut coarse = 0;
        for (ci, cam) in framed(&scene).iter().enumerate() {
            for cull in [true, false] {
                let mut last = u64::MAX;
                for &t in &thresholds {
                    let sel = select_nodes(
                        &snap,
                        &GRID,
                        cam,
                        &LodOptions { threshold_px: t, point_budget: None, cull },
                    )
                    .unwrap();
                    assert!(sel.stats.samples() <= last, "camera {ci} cull {cull} threshold {t}");
                    last = sel.stats.samples();
                    if t >= 1e9 {
                        assert_eq!(sel.nodes, vec![NodeId::ROOT], "camera {ci}");
                        assert_eq!(sel.stats.voxels, snap.node(NodeId::ROOT).voxel_count());
                    }
                }
            }
            // The default threshold refines something, and in most framed views stops above the leaves.
            let sel = select_nodes(&snap, &GRID, cam, &LodOptions::default()).unwrap();
            assert!(sel.stats.refined > 0, "camera {ci}: {:?}", sel.stats);
            coarse += (sel.stats.samples() < snap.point_count()) as usize;
        }
        assert!(coarse >= 4, "{coarse} framed views stop above the leaves");
        // A camera looking away from the data sees nothing.
        let c = scene.bounds.center();
        let away = Camera {
            eye: [c[0], c[1] - 400.0, c[2]],
            target: [c[0], c[1] - 401.0, c[2]],
            ..small(scene.cameras()[8])
        };
        let sel = select_nodes(&snap, &GRID, &away, &LodOptions::default()).unwrap();
        assert!(sel.nodes.is_empty() && sel.culled == vec![NodeId::ROOT], "{sel:?}");
        // An unusable camera is an error, not a panic.
        let bad = Camera { target: c, eye: c, ..away };
        assert!(select_nodes(&snap, &GRID, &bad, &LodOptions::default()).is_err());
    }

    #[test]
    fn budget_is_respected_and_the_view_stays_covered() {
        let (scene, snap) = terrain_tree(150_000, 3_000);
        let parents = parents(&snap);
        let leaves: Vec<NodeId> =
            snap.leaves().filter(|(_, n)| n.point_count() > 0).map(|(id, _)| id).collect();
        let root_voxels = snap.node(NodeId::ROOT).voxel_count();
        let budgets = [
            Some(0),
            Some(root_voxels),
            Some(20_000),
            Some(50_000),
            Some(90_000),
            Some(u64::MAX),
            None,
        ];
        let nframed = framed(&scene).len();
        let mut limited = 0;
        for (ci, cam) in all_cameras(&scene).iter().enumerate() {
            // Which leaves have a visible point.
            let seen: Vec<NodeId> = leaves
                .iter()
                .copied()
                .filter(|&l| snap.node(l).points().unwrap().iter().any(|p| visible(cam, p.pos)))
                .collect();
            for threshold_px in [0.0, 32.0, 128.0] {
                let mut last = 0;
                for budget in budgets {
                    let opts = LodOptions { threshold_px, point_budget: budget, cull: true };
                    let sel = select_nodes(&snap, &GRID, cam, &opts).unwrap();
                    let s = sel.stats.samples();
                    if let Some(b) = budget {
                        assert!(
                            s <= b || sel.nodes == [NodeId::ROOT],
                            "camera {ci}: {s} samples over budget {b}"
                        );
                    }
                    limited += sel.stats.budget_reached as usize;
                    let chosen: HashSet<NodeId> = sel.nodes.iter().copied().collect();
                    // No two selected nodes are nested.
                    for &id in &sel.nodes {
                        assert!(
                            lineage(&parents, id)[1..].iter().all(|a| !chosen.contains(a)),
                            "camera {ci}: {id:?} nested"
                        );
                    }
                    // Every visible leaf is covered exactly once.
                    for &l in &seen {
                        let n = lineage(&parents, l).iter().filter(|a| chosen.contains(a)).count();
                        assert_eq!(
                            n, 1,
                            "camera {ci} budget {budget:?}: leaf {l:?} covered {n} times"
                        );
                    }
                    // In framed views no non-empty node is culled, so refining never lowers the
                    // count: a larger budget selects at least as much.
                    if ci < nframed {
                        assert!(s >= last, "camera {ci}: budget {budget:?} selects {s} < {last}");
                        last = s;
                    }
                    if budget.is_none() {
                        let unlimited = select_nodes(
                            &snap,
                            &GRID,
                            cam,
                            &LodOptions { point_budget: Some(u64::MAX), ..opts },
                        )
                        .unwrap();
                        assert_eq!(unlimited, sel);
                        assert!(!sel.stats.budget_reached);
                    }
                }
            }
        }
        assert!(limited > 10, "budgets bind in {limited} selections");
        // A budget below the root's voxels still shows the root.
        let sel = select_nodes(
            &snap,
            &GRID,
            &framed(&scene)[0],
            &LodOptions { point_budget: Some(1), ..LodOptions::default() },
        )
        .unwrap();
        assert_eq!(sel.nodes, vec![NodeId::ROOT]);
        assert!(sel.stats.budget_reached);
    }

    #[test]
    fn budget_refines_the_largest_nodes_first() {
        let (scene, snap) = terrain_tree(150_000, 3_000);
        let parents = parents(&snap);
        let mut checked = 0;
        for cam in all_cameras(&scene) {
            let size = |id: NodeId| cam.projected_size(&snap.node(id).cube().world_bounds(&GRID));
            for threshold_px in [16.0, 128.0] {
                let opts = LodOptions { threshold_px, ..LodOptions::default() };
                let full = select_nodes(&snap, &GRID, &cam, &opts).unwrap();
                for k in 1..10 {
                    let budget = full.stats.samples() * k / 10;
                    let sel = select_nodes(
                        &snap,
                        &GRID,
                        &cam,
                        &LodOptions { point_budget: Some(budget), ..opts },
                    )
                    .unwrap();
                    assert!(sel.stats.budget_reached, "{budget}: {:?}", sel.stats);
                    if sel.stats.refined == 0 {
                        continue;
                    }
                    checked += 1;
                    // Every inner node left coarse above the threshold is no larger on screen than
                    // every node that was refined (the parents of selected nodes).
                    let refined_min = sel
                        .nodes
                        .iter()
                        .filter_map(|&id| parents[id.index()])
                        .map(size)
                        .fold(f64::INFINITY, f64::min);
                    for &id in &sel.nodes {
                        if !snap.node(id).is_leaf() && size(id) > threshold_px {
                            assert!(
                                size(id) <= refined_min,
                                "{id:?}: {} px left coarse, a {refined_min} px node refined",
                                size(id)
                            );
                        }
                    }
                }
            }
        }
        assert!(checked >= 10, "{checked} budgets refined something");
    }

    #[test]
    fn culled_nodes_are_outside() {
        let (scene, snap) = terrain_tree(150_000, 3_000);
        let mut culled_total = 0;
        for (ci, cam) in all_cameras(&scene).iter().enumerate() {
            for threshold_px in [0.0, 128.0] {
                let sel = select_nodes(
                    &snap,
                    &GRID,
                    cam,
                    &LodOptions { threshold_px, ..LodOptions::default() },
                )
                .unwrap();
                culled_total += sel.culled.len();
                let mut batches = Vec::new();
                for &id in &sel.culled {
                    // No point below a culled node is visible...
                    let mut below = Vec::new();
                    leaves_below(&snap, id, &mut below);
                    for l in below {
                        for p in snap.node(l).points().unwrap().iter() {
                            assert!(
                                !visible(cam, p.pos),
                                "camera {ci}: visible point {p:?} below culled {id:?}"
                            );
                        }
                    }
                    // ...and the rasterizer, not culling, draws nothing of its batch.
                    batches.push(node_batch(snap.node(id), &GRID).unwrap());
                }
                let refs: Vec<BatchRef<'_>> = batches.iter().map(|b| b.batch_ref(0)).collect();
                let fb = Framebuffer::new(cam.width, cam.height);
                let stats = rasterize(
                    &fb,
                    &refs,
                    &GRID,
                    cam,
                    &RasterOptions { cull: false, ..RasterOptions::default() },
                )
                .unwrap();
                assert_eq!(
                    stats.points_drawn, 0,
                    "camera {ci}: culled nodes draw {} points",
                    stats.points_drawn
                );
            }
        }
        assert!(culled_total > 20, "{culled_total} nodes culled");
    }
}
