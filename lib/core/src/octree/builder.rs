//! The incremental update of paper 004 §5: `expand` (§5.1), `sample_voxels` (§5.2) and
//! `insert_points` (§5.3-5.4), then publishing the changed nodes for snapshots.
//!
//! Parallelism (rayon): counting descends the points in parallel chunks (counts are added per run
//! of equal leaves, so Morton-ordered input hardly contends). Sampling partitions the points
//! top-down, stably, by octant; the task of child octant `o` samples octant `o` of its parent's
//! grid (cells of different octants never meet) in arrival order and then goes on into the child,
//! so no grid is sampled by two threads and even the root's grid is sampled by 8 tasks. Points are
//! scattered straight into each leaf's new chunk and the leaves append their chunks in parallel.
//! Nothing depends on the thread count.
//!
//! One concept per file; this one holds the [`Builder`] type, its statistics and the update
//! that runs the phases in order ([`Builder::add_batch_paged`]). The children:
//!
//! - `node`: a node's slots in the builder: where it is and what its children are (`Shape`),
//!   what it holds (`NodeData`).
//! - `grow`: growing the root above the old one for points outside it.
//! - `expand`: counting and splitting (§5.1), with the leaves' paged-out points asked back.
//! - `sample`: voxel sampling (§5.2): the update's points as records, handed to the partition.
//! - `partition`: the sampling recursion: records partitioned top-down by octant, each octant
//!   of a grid sampled by the task of its child.
//! - `insert`: appending points to leaves (§5.3-5.4) and new voxels to inner nodes (§5.4).
//! - `publish`: what snapshots see: the changed nodes' views after an update, and the leaves'
//!   points paged out between updates.

mod expand;
mod grow;
mod insert;
mod node;
mod partition;
mod publish;
mod sample;

use super::cube::{Cube, NodeKey};
use super::snapshot::{NodeView, Snapshot};
use super::types::MAX_ROOT_SIZE_LOG2;
use super::types::{BuilderConfig, NodeId, OctreeError, Point};
use node::{NodeData, Shape, NO_CHILD};
use partition::Rec;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The page-in callback of [`Builder::add_batch_paged`]: the paged-out points of a leaf.
pub type PageIn<'a> = dyn Fn(NodeId) -> Result<Vec<Point>, String> + Sync + 'a;

/// Wall time of each phase of one [`Builder::add_batch`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PhaseTimes {
    /// Growing the root for points outside it.
    pub grow: Duration,
    /// Counting and splitting (§5.1).
    pub expand: Duration,
    /// Voxel sampling (§5.2).
    pub sample_voxels: Duration,
    /// Appending points to leaves (§5.3-5.4).
    pub insert_points: Duration,
    /// Appending new voxels to inner nodes (§5.4).
    pub insert_voxels: Duration,
    /// Publishing changed nodes for snapshots.
    pub publish: Duration,
}

/// What one [`Builder::add_batch`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BatchStats {
    /// Times the root grew (a new root above the old one) for points outside it.
    pub growths: u32,
    /// Points in the batch.
    pub points: usize,
    /// Stored points moved out of split leaves and inserted again.
    pub spilled: usize,
    /// Leaves split into 8 children.
    pub splits: usize,
    /// Counting passes of the expansion (1 when nothing split).
    pub expand_iterations: u32,
    /// Voxels created in inner nodes.
    pub new_voxels: u64,
    /// Nodes in the tree afterwards.
    pub nodes: usize,
    /// Time per phase.
    pub times: PhaseTimes,
}

/// Builds the octree of paper 004 batch by batch; see the [module docs](crate::octree).
pub struct Builder {
    config: BuilderConfig,
    root: Cube,
    shapes: Vec<Shape>,
    data: Vec<NodeData>,
    views: Vec<Arc<NodeView>>,
    published: Arc<[Arc<NodeView>]>,
    revision: u64,
    input_points: u64,
    /// Reused buffers of the sampling partition.
    work: Vec<Rec>,
    scratch: Vec<Rec>,
}

impl std::fmt::Debug for Builder {
    /// A summary, not the payloads.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Builder")
            .field("root", &self.root)
            .field("config", &self.config)
            .field("nodes", &self.shapes.len())
            .field("revision", &self.revision)
            .field("input_points", &self.input_points)
            .finish()
    }
}

impl Builder {
    /// An empty octree over `root` (which must hold every point that will be added).
    pub fn new(root: Cube, config: BuilderConfig) -> Result<Builder, OctreeError> {
        if config.leaf_capacity == 0 {
            return Err(OctreeError::ZeroCapacity);
        }
        if root.size_log2 > MAX_ROOT_SIZE_LOG2 {
            return Err(OctreeError::RootTooLarge { size_log2: root.size_log2 });
        }
        let mut b = Builder {
            config,
            root,
            shapes: vec![Shape { key: NodeKey::ROOT, cube: root, first_child: NO_CHILD }],
            data: vec![NodeData { changed: true, ..NodeData::default() }],
            views: Vec::new(),
            published: Arc::from(Vec::new()),
            revision: 0,
            input_points: 0,
            work: Vec::new(),
            scratch: Vec::new(),
        };
        b.publish();
        Ok(b)
    }

    /// An empty octree over the smallest cube that covers the inclusive integer bounds
    /// `[min, max]` of a dataset ([`Cube::covering`]).
    pub fn for_bounds(
        min: [i32; 3],
        max: [i32; 3],
        config: BuilderConfig,
    ) -> Result<Builder, OctreeError> {
        Builder::new(Cube::covering(min, max), config)
    }

    /// The root cube.
    pub fn root(&self) -> Cube {
        self.root
    }

    /// The settings.
    pub fn config(&self) -> BuilderConfig {
        self.config
    }

    /// Number of non-empty batches added.
    pub fn revision(&self) -> u64 {
        self.revision
    }

    /// Number of points added.
    pub fn input_points(&self) -> u64 {
        self.input_points
    }

    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.shapes.len()
    }

    /// Heap bytes of the voxel sampling state of all inner nodes (occupancy, and in averaged mode
    /// the maps and sums); payloads not included.
    pub fn sampling_bytes(&self) -> usize {
        self.data.iter().map(|d| d.voxels.as_ref().map_or(0, |v| v.sampler_bytes())).sum()
    }

    /// The current tree, in O(1). It shares payload chunks with the builder and never changes.
    pub fn snapshot(&self) -> Snapshot {
        Snapshot {
            root: self.root,
            config: self.config,
            revision: self.revision,
            input_points: self.input_points,
            nodes: self.published.clone(),
        }
    }

    /// Adds a batch of points (paper 004 §5): `expand`, `sample_voxels`, `insert_points`, then
    /// publishes the changed nodes. Every point must lie in the root cube; on an error nothing
    /// changes.
    pub fn add_batch(&mut self, points: &[Point]) -> Result<BatchStats, OctreeError> {
        self.add_batch_paged(points, &|id| {
            Err(format!("leaf {} has paged-out points but no pager was given", id.0))
        })
    }

    /// [`add_batch`](Self::add_batch) for a builder whose leaves may hold points paged out with
    /// [`page_out`](Self::page_out): before a leaf with paged-out points splits, `page_in(id)`
    /// must return exactly those points, in their order (called in parallel, before anything
    /// changes; an error is returned as [`OctreeError::PageIn`] and leaves the tree as it was).
    pub fn add_batch_paged(
        &mut self,
        points: &[Point],
        page_in: &PageIn<'_>,
    ) -> Result<BatchStats, OctreeError> {
        if points.is_empty() {
            return Ok(BatchStats { nodes: self.shapes.len(), ..BatchStats::default() });
        }
        let mut times = PhaseTimes::default();

        let t = Instant::now();
        let growths = self.grow(points, page_in)?;
        times.grow = t.elapsed();

        let t = Instant::now();
        let exp = self.expand(points, page_in)?;
        times.expand = t.elapsed();
        self.revision += 1;

        let t = Instant::now();
        self.sample_voxels(&exp, points);
        times.sample_voxels = t.elapsed();

        let t = Instant::now();
        self.insert_points(&exp, points);
        times.insert_points = t.elapsed();

        let t = Instant::now();
        let new_voxels = self.insert_voxels(&exp, points);
        times.insert_voxels = t.elapsed();

        let t = Instant::now();
        self.publish();
        times.publish = t.elapsed();

        self.input_points += points.len() as u64;
        Ok(BatchStats {
            growths,
            points: points.len(),
            spilled: exp.spill.len(),
            splits: exp.splits,
            expand_iterations: exp.iterations,
            new_voxels,
            nodes: self.shapes.len(),
            times,
        })
    }
}
