//! The incremental octree LOD builder of paper 004 (SimLOD, Schütz, Herzberger, Wimmer), on the CPU.
//!
//! # Structure (paper 004 §3.1, §3.3)
//!
//! An octree over a power-of-two root [`Cube`] in the LAS integer grid. Leaves hold the original
//! points ([`Point`]: integer coordinates, the caller's record index and an RGBA colour), at most
//! [`BuilderConfig::leaf_capacity`] of them (50,000 by default). Inner nodes hold voxels ([`Voxel`])
//! sampled on a 128³ grid inscribed in their cube: one voxel per occupied cell. Every input point
//! ends in exactly one leaf; inner nodes are a redundant level of detail. Children are the octants
//! of their parent, numbered `x | y << 1 | z << 2` from the upper bit of the offset in the parent
//! (the bit order of [`crate::morton`]); a split creates all 8 children at once, empty ones
//! included, and they get consecutive [`NodeId`]s.
//!
//! # One update (paper 004 §5, figure 6)
//!
//! [`Builder::add_batch`] inserts one batch (about 1 M points) in the paper's phases:
//!
//! 1. `expand` (§5.1): repeated *counting* (every point not yet in a final leaf descends to its
//!    leaf, which counts it) and *splitting* (a leaf whose stored plus counted points exceed the
//!    capacity becomes an inner node with 8 empty leaf children; the points it stored go to the
//!    spill list and are counted again like batch points); leaves that do not split are final for
//!    this update. It ends when no leaf splits. Spilled points descend from the node that spilled
//!    them rather than from the root (the result is the same, the walk shorter).
//! 0. `grow` (not in the paper, whose root is fixed): while a point of the batch lies outside
//!    the root cube, a new root of twice the size goes above the old one (see "Growing the
//!    root" below).
//! 2. `sample_voxels` (§5.2): every point walks down through the inner nodes on its path and, in
//!    each, marks its cell of the 128³ grid; a cell that was empty becomes a new voxel (the point
//!    itself: position, colour, record), kept in a per-node backlog. Spilled points sample only from the node that spilled them downward: the
//!    ancestors above saw them when they were first inserted.
//! 3. `insert_points` (§5.3-5.4): the paper's chunk allocation and insertion in one: each leaf
//!    that receives points gets one new chunk of exactly that size, the points (spilled first,
//!    then the batch, each in order) are scattered into those chunks, and the chunks are appended
//!    to the leaves' lists of `Arc`-shared chunks ([`Chunks`]), as the paper links chunks.
//! 4. `insert_voxels` (§5.4): each inner node appends its backlog of new voxels to its chunks.
//!
//! Then the changed nodes are published for [`Builder::snapshot`]. [`BatchStats`] reports what
//! each update did and how long each phase took.
//!
//! Where it differs from the GPU paper:
//!
//! - Occupancy is sparse, not a dense 256 KiB bit grid per inner node: per octant of the grid
//!   (64³ cells), a 512-entry table of 8³-cell bricks (1 KiB, allocated with the octant's first
//!   voxel) and 64 bytes of bits per occupied brick, in the spirit of the hash maps of Wand et al.
//!   that §3.1 mentions. A surface node of ~16 k voxels needs ~25 KiB; a full grid 264 KiB.
//! - Sampling is deterministic instead of racing on atomics: the points of the update are
//!   partitioned top-down, stably, by octant (as 24-byte records, so every level reads them
//!   sequentially), and octant `o` of a node's grid is sampled by the task of its child `o`, in
//!   arrival order. Cells of different octants never meet, so the 8 octants of every grid, the
//!   root's included, are sampled in parallel without locks contending.
//! - There is no chunk pool (§3.4): freed chunks are reference counted and may still be held by
//!   snapshots. Chunks are not of one fixed size: see [`Chunks`] for how appends stay few and
//!   large.
//!
//! # Colours
//!
//! [`ColorMode::FirstCome`] is the paper's choice: a voxel keeps the colour of the first point
//! that fell into its cell, in arrival order. [`ColorMode::Averaged`] is the colour filtering that
//! §8 names as future work: each voxel keeps a running sum and count and shows the rounded mean
//! `(sum + count / 2) / count` per RGBA channel (see [`mean_color`]). It costs a cell → voxel
//! index per octant (the same two-level bricks, 2 KiB per occupied brick), 28 bytes of sums per
//! voxel and 4 bytes of voxel order, and since colours change, a node's voxel chunks (fixed
//! chunks of [`AVERAGED_CHUNK`] voxels) are rebuilt whenever a batch changes a voxel in them. A
//! voxel stops accumulating after [`MAX_AVERAGED_SAMPLES`] points (its sums are u32): its colour
//! is then the mean of its first 2^24 points. Measured on a terrain surface: about 95 bytes of
//! sampling state per voxel, against under 2 bytes per voxel for first-come occupancy.
//!
//! # Depth bound
//!
//! A leaf splits only if its cube is at least 128 grid units wide ([`MIN_INNER_SIZE_LOG2`]: an
//! inner node's voxels are at least one grid unit) and its level is below
//! [`BuilderConfig::max_level`]. Other leaves keep every point they receive and may exceed the
//! capacity: many duplicate points, or points denser than the grid, end in a leaf 64 (or fewer)
//! grid units wide. The depth is therefore at most `root.size_log2 - 6 <= 26`, whatever the input.
//!
//! # Growing the root
//!
//! Headers lie, so the root cube given to [`Builder::new`] is a guess. When a batch has points
//! outside it, the root grows before `expand`: a new root cube of twice the size, with the old
//! root as its octant `o` (the upper half on the axes where points lie below the old root), as
//! often as needed up to [`MAX_ROOT_SIZE_LOG2`](types::MAX_ROOT_SIZE_LOG2). A leaf root only gets
//! the larger cube. An inner root moves to a new id (children are consecutive), every key moves
//! one level down (`level + 1`, `index + o << level`), the other 7 children are new empty
//! leaves, and the new root's grid is sampled from the old root's voxels in their order (real
//! points; in averaged mode each counts once). The saved voxel records of a paged builder are
//! asked back from the caller first (`page_in` of the root). The tree is then the one a builder
//! over the grown root would have built, but for which points represent the grown roots' cells.
//! A growth changes keys, so snapshots before and after it are not related by the monotonicity
//! below except through points and voxels (keys and ids of old nodes change).
//!
//! # Snapshots and what is monotone
//!
//! [`Builder::snapshot`] returns an immutable [`Snapshot`] in O(1) (one `Arc` clone); payloads are
//! shared, never copied. For two snapshots `a` taken before `b` of one builder:
//!
//! - `b` has at least the nodes of `a`; node `i` has the same key and cube in both.
//! - a leaf of `a` is either a leaf of `b` whose point sequence starts with its point sequence in
//!   `a`, or an inner node of `b` whose points are all in the leaves below it in `b`. So every
//!   point (record) visible in `a` is visible in `b`, and the point count never drops.
//! - an inner node of `a` is an inner node of `b`; its voxel sequence in `b` starts with the
//!   voxels (cells) of `a`, in the same order. With [`ColorMode::FirstCome`] those voxels keep
//!   their colours; with [`ColorMode::Averaged`] only their cells are kept, colours may change.
//! - `a` itself never changes.
//!
//! A node view also carries the revision (batch number) of its last change, so that a store
//! writer can write only [`Snapshot::changed_since`] its last commit.
//!
//! # Drawing (paper 004 §6)
//!
//! [`lod`] turns nodes into quantized batches for the rasterizer ([`node_batch`]) and picks the
//! nodes to draw for a view ([`select_nodes`]): culled by the frustum, refined while larger than
//! 128 px on screen, within an optional point budget.
//!
//! # Determinism
//!
//! The result depends only on the sequence of input points and where it is cut into batches,
//! never on the thread count. Nor does the batching change the tree, the points of each leaf (in
//! arrival order), the voxel cells of each node or any colour: a node is inner exactly when more
//! than `leaf_capacity` points fall into its cube (and it may split), leaves keep their points in
//! arrival order and every cell is sampled in arrival order. What batching does change is the
//! order of a node's voxels (within one update they are ordered by octant, then arrival) and the
//! chunking of payloads.
//!
//! # Costs
//!
//! Per update, besides the payloads: 4 bytes per batch point (its leaf) in `expand`, and two
//! buffers of 24 bytes per point (batch plus spill) for the sampling partition, kept by the
//! builder for the next update. Points in leaves cost 24 bytes each.
//!
//! # Limits (not done here)
//!
//! - In-core by default, as the paper: all points live in memory. A caller that saves the
//!   leaves' points elsewhere (the store writer) may [`Builder::page_out`] them between updates
//!   and give them back through [`Builder::add_batch_paged`] when a leaf splits; the monotonicity
//!   above then holds for total point counts ([`NodeView::total_points`]), and the points of a
//!   paged-out leaf are read from where the caller saved them. Inner nodes' voxels and sampling
//!   state always stay in memory.
//! - No time budget per update (§7.2): an update runs to completion.
//! - Ids inside one update are `u32`: a batch plus the points it spills must stay below 2^32
//!   ([`OctreeError::BatchTooLarge`]).

pub mod arrival;
mod builder;
mod chunks;
mod cube;
pub mod lod;
pub mod patch;
mod snapshot;
mod sorted;
mod types;
mod voxels;

#[cfg(test)]
mod tests;

pub use builder::{BatchStats, Builder, PageIn, PhaseTimes};
pub use chunks::Chunks;
pub use cube::{Cube, NodeKey};
pub use lod::{
    node_batch, select_nodes, IndexEntry, LodIndex, LodIndexError, LodOptions, LodSelection,
    LodStats, LodTree, NodeBatch, NodeBatchError, DEFAULT_THRESHOLD_PX,
};
pub use snapshot::{NodeView, Payload, Snapshot};
pub use sorted::{
    build_sorted, build_subtree, earliest_in_parent_cells, splits, SortedContent, SortedNode,
    SortedTree, Subtree,
};
pub use types::*;
pub use voxels::{mean_color, AVERAGED_CHUNK, MAX_AVERAGED_SAMPLES};
