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
//!
//! # Files
//!
//! - `batch`: a node's payload as a quantized batch ([`node_batch`], [`NodeBatch`]).
//! - `tree`: the tree a selection walks ([`LodTree`]), implemented by [`Snapshot`].
//! - `index`: the structure of a tree rebuilt and checked from its nodes' keys ([`LodIndex`]).
//! - `select`: the node selection for one view ([`select_nodes`], [`LodOptions`]).
//!
//! [`Snapshot`]: super::Snapshot
//! [`NodeView::points`]: super::NodeView::points
//! [`NodeView::voxels`]: super::NodeView::voxels
//! [`BatchGrid`]: crate::quantize::BatchGrid
//! [`BatchGrid::decode_exact`]: crate::quantize::BatchGrid::decode_exact
//! [`MAX_BITS`]: crate::quantize::MAX_BITS
//! [`Camera::projected_size`]: crate::render::Camera::projected_size
//! [`CULL_MARGIN_PX`]: crate::render::plan::CULL_MARGIN_PX

mod batch;
mod index;
mod select;
#[cfg(test)]
mod testutil;
mod tree;

pub use batch::{node_batch, NodeBatch, NodeBatchError};
pub use index::{IndexEntry, LodIndex, LodIndexError};
pub use select::{select_nodes, LodOptions, LodSelection, LodStats, DEFAULT_THRESHOLD_PX};
pub use tree::LodTree;
