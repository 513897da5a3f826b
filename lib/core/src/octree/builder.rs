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

use super::chunks::Chunks;
use super::cube::{Cube, NodeKey};
use super::snapshot::{NodeView, Payload, Snapshot};
use super::types::MAX_ROOT_SIZE_LOG2;
use super::types::{
    BuilderConfig, NodeId, OctreeError, Point, Voxel, GRID_LOG2, MIN_INNER_SIZE_LOG2,
    POINT_CHUNK_MAX,
};
use super::voxels::{Sample, Sampler, VoxelState};
use bytemuck::Zeroable;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The page-in callback of [`Builder::add_batch_paged`]: the paged-out points of a leaf.
pub type PageIn<'a> = dyn Fn(NodeId) -> Result<Vec<Point>, String> + Sync + 'a;

/// `first_child` of a leaf. The root (id 0) is never a child, so 0 is free.
const NO_CHILD: u32 = 0;
/// Points per parallel work item when counting.
const COUNT_CHUNK: usize = 1 << 14;
/// Sub-trees with fewer points than this are sampled on the current thread.
const PAR_MIN: usize = 1 << 12;
/// Fewest points per part of the parallel scatter in `insert_points`.
const SCATTER_MIN: usize = 1 << 15;

/// Where a node is and what its children are.
#[derive(Clone, Copy, Debug)]
struct Shape {
    key: NodeKey,
    cube: Cube,
    first_child: u32,
}

/// What a node holds.
#[derive(Default)]
struct NodeData {
    /// A leaf's points.
    points: Chunks<Point>,
    /// An inner node's voxels.
    voxels: Option<Box<VoxelState>>,
    /// Leaves: points paged out to the caller ([`Builder::page_out`]); they precede `points`
    /// in arrival order. Inner nodes: voxels whose records the caller saved at the last
    /// `page_out` ([`NodeView::saved_voxels`]).
    paged: u64,
    /// Input points in the node's cube.
    subtree: u64,
    /// Changed since the last publish.
    changed: bool,
}

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

/// The result of `expand`: the leaf of every point of the update and the spilled points.
struct Expansion {
    /// Final leaf of each batch point.
    batch_leaf: Vec<u32>,
    /// Points moved out of split leaves, in the order those leaves stored them.
    spill: Vec<Point>,
    /// Final leaf of each spilled point.
    spill_leaf: Vec<u32>,
    /// Level of the leaf each spilled point came from.
    spill_origin: Vec<u8>,
    /// New points per node in this update (0 for inner nodes).
    new_count: Vec<u64>,
    splits: usize,
    iterations: u32,
}

/// Adds `n` to `counts[leaf - base]` per run of equal leaves.
struct RunCounter<'a> {
    counts: &'a [AtomicU64],
    base: u32,
    leaf: u32,
    n: u64,
}

impl<'a> RunCounter<'a> {
    fn new(counts: &'a [AtomicU64], base: u32) -> Self {
        RunCounter { counts, base, leaf: 0, n: 0 }
    }

    #[inline]
    fn add(&mut self, leaf: u32) {
        if leaf == self.leaf {
            self.n += 1;
        } else {
            self.flush();
            self.leaf = leaf;
            self.n = 1;
        }
    }

    fn flush(&mut self) {
        if self.n > 0 {
            self.counts[(self.leaf - self.base) as usize].fetch_add(self.n, Ordering::Relaxed);
            self.n = 0;
        }
    }
}

/// The leaf below node `n` whose cube holds `p`.
#[inline]
fn descend(shapes: &[Shape], mut n: u32, p: [i32; 3]) -> u32 {
    loop {
        let s = &shapes[n as usize];
        if s.first_child == NO_CHILD {
            return n;
        }
        n = s.first_child + s.cube.octant_of(p) as u32;
    }
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

    /// Grows the root until it holds every point of `batch` ("Growing the root" in the module
    /// docs); returns the number of growths. Fails before changing anything if the root would
    /// exceed [`MAX_ROOT_SIZE_LOG2`], or if the saved voxel records of an inner root cannot be
    /// paged in.
    fn grow(&mut self, batch: &[Point], page_in: &PageIn<'_>) -> Result<u32, OctreeError> {
        let root = self.root;
        if batch.par_iter().all(|p| root.contains(p.pos)) {
            return Ok(0);
        }
        let (lo, hi) = batch
            .par_iter()
            .fold(
                || ([i64::MAX; 3], [i64::MIN; 3]),
                |(mut lo, mut hi), p| {
                    for a in 0..3 {
                        lo[a] = lo[a].min(p.pos[a] as i64);
                        hi[a] = hi[a].max(p.pos[a] as i64);
                    }
                    (lo, hi)
                },
            )
            .reduce(
                || ([i64::MAX; 3], [i64::MIN; 3]),
                |a, b| {
                    (
                        std::array::from_fn(|i| a.0[i].min(b.0[i])),
                        std::array::from_fn(|i| a.1[i].max(b.1[i])),
                    )
                },
            );
        // The cubes the root will pass through, checked before anything changes.
        let mut steps = Vec::new();
        let mut cube = root;
        while !(cube.contains_i64(lo) && cube.contains_i64(hi)) {
            if cube.size_log2 >= MAX_ROOT_SIZE_LOG2 {
                let index = batch.iter().position(|p| !cube.contains(p.pos)).unwrap_or(0);
                return Err(OctreeError::PointOutsideRoot {
                    index,
                    pos: batch[index].pos,
                    min: cube.min,
                    size: cube.size(),
                });
            }
            // The old root is the upper half on axes where points lie below it.
            let octant: usize = (0..3).map(|a| usize::from(lo[a] < cube.min[a]) << a).sum();
            let size = cube.size() as i64;
            let min =
                std::array::from_fn(|a| cube.min[a] - if octant >> a & 1 == 1 { size } else { 0 });
            cube = Cube { min, size_log2: cube.size_log2 + 1 };
            steps.push((cube, octant));
        }
        // An inner root's saved voxels get records of this interval back (their copies sample
        // the new root, and the moved old root is written again).
        let mut resolved: Option<Vec<Point>> = None;
        if self.shapes[0].first_child != NO_CHILD && self.data[0].paged > 0 {
            let pts = page_in(NodeId(0)).map_err(OctreeError::PageIn)?;
            if pts.len() as u64 != self.data[0].paged {
                return Err(OctreeError::PageIn(format!(
                    "root: {} voxels paged in, {} saved",
                    pts.len(),
                    self.data[0].paged
                )));
            }
            resolved = Some(pts);
        }
        if let Some(pts) = resolved {
            let v = self.data[0].voxels.as_mut().expect("an inner root has voxels");
            v.set_records(&pts);
            self.data[0].paged = 0;
        }
        self.revision += 1;
        let mode = self.config.color_mode;
        for &(cube, octant) in &steps {
            if self.shapes[0].first_child == NO_CHILD {
                // A leaf root only gets a larger cube; its points stay.
                self.shapes[0].cube = cube;
                self.data[0].changed = true;
                self.root = cube;
                continue;
            }
            let first =
                u32::try_from(self.shapes.len()).expect("an octree has fewer than 2^32 nodes");
            // Every key moves one level down, below the new root's octant.
            for sh in self.shapes.iter_mut().skip(1) {
                let l = sh.key.level as u32;
                sh.key = NodeKey {
                    level: sh.key.level + 1,
                    index: std::array::from_fn(|a| {
                        sh.key.index[a] + ((((octant >> a) & 1) as u32) << l)
                    }),
                };
            }
            // The new root samples its grid from the old root's voxels, in their order.
            let old = self.data[0].voxels.as_ref().expect("an inner root has voxels");
            let reps: Vec<Voxel> = old.chunks.to_vec();
            let mut state = VoxelState::new(mode);
            state.seed(&cube, &reps);
            let subtree = self.data[0].subtree;
            for o in 0..8 {
                let key = NodeKey::ROOT.child(o);
                self.shapes.push(Shape { key, cube: cube.child(o), first_child: NO_CHILD });
                self.data.push(NodeData { changed: true, ..NodeData::default() });
            }
            let moved = first as usize + octant;
            let old_root = self.shapes[0];
            self.shapes[moved] = Shape {
                key: NodeKey::ROOT.child(octant),
                cube: old_root.cube,
                first_child: old_root.first_child,
            };
            self.data.swap(0, moved);
            self.data[moved].changed = true;
            self.shapes[0] = Shape { key: NodeKey::ROOT, cube, first_child: first };
            self.data[0] = NodeData {
                voxels: Some(Box::new(state)),
                subtree,
                changed: true,
                ..NodeData::default()
            };
            self.root = cube;
        }
        // Every view again: keys changed; unchanged nodes keep their revision.
        let old_views = std::mem::take(&mut self.views);
        let rev = self.revision;
        self.views = self
            .shapes
            .iter()
            .zip(&self.data)
            .enumerate()
            .map(|(i, (shape, d))| {
                let payload = match &d.voxels {
                    Some(v) => Payload::Voxels(v.chunks.clone()),
                    None => Payload::Points(d.points.clone()),
                };
                let revision =
                    if d.changed { rev } else { old_views.get(i).map_or(rev, |v| v.revision()) };
                let first_child =
                    (shape.first_child != NO_CHILD).then_some(NodeId(shape.first_child));
                Arc::new(NodeView::new(
                    shape.key,
                    shape.cube,
                    first_child,
                    payload,
                    d.subtree,
                    revision,
                    d.paged,
                ))
            })
            .collect();
        for d in &mut self.data {
            d.changed = false;
        }
        self.published = self.views.iter().cloned().collect();
        Ok(steps.len() as u32)
    }

    /// Whether a leaf may become an inner node (see "Depth bound" in the module docs).
    fn splittable(&self, s: &Shape) -> bool {
        s.cube.size_log2 >= MIN_INNER_SIZE_LOG2 && s.key.level < self.config.max_level
    }

    /// §5.1: counting and splitting until no leaf splits. Fails, before changing anything, if the
    /// update would not fit 32-bit ids.
    fn expand(&mut self, batch: &[Point], page_in: &PageIn<'_>) -> Result<Expansion, OctreeError> {
        let cap = self.config.leaf_capacity as u64;

        // First counting pass: every batch point descends from the root.
        let n0 = self.shapes.len();
        let mut batch_leaf = vec![0u32; batch.len()];
        let counts: Vec<AtomicU64> = (0..n0).map(|_| AtomicU64::new(0)).collect();
        {
            let shapes = &self.shapes;
            batch_leaf.par_chunks_mut(COUNT_CHUNK).zip(batch.par_chunks(COUNT_CHUNK)).for_each(
                |(leaves, pts)| {
                    let mut run = RunCounter::new(&counts, 0);
                    for (l, p) in leaves.iter_mut().zip(pts) {
                        *l = descend(shapes, 0, p.pos);
                        run.add(*l);
                    }
                    run.flush();
                },
            );
        }
        let mut new_count: Vec<u64> = counts.into_iter().map(AtomicU64::into_inner).collect();

        // Only leaves that existed before this update store points, and they receive all their
        // counts in the first pass: the spill is known now, before anything changes.
        let mut to_split = Vec::new();
        let mut spilled = 0u64;
        for (i, &n) in new_count.iter().enumerate() {
            if n == 0 {
                continue;
            }
            let stored = self.data[i].points.len() + self.data[i].paged;
            if stored + n > cap && self.splittable(&self.shapes[i]) {
                to_split.push(i as u32);
                spilled += stored;
            }
        }
        if batch.len() as u64 + spilled > u32::MAX as u64 {
            return Err(OctreeError::BatchTooLarge { points: batch.len(), spilled });
        }
        // Leaves that split need their paged-out points back first.
        let paged: Vec<u32> =
            to_split.iter().copied().filter(|&l| self.data[l as usize].paged > 0).collect();
        if !paged.is_empty() {
            let loaded: Vec<Vec<Point>> = paged
                .par_iter()
                .map(|&l| {
                    let pts = page_in(NodeId(l)).map_err(OctreeError::PageIn)?;
                    let want = self.data[l as usize].paged;
                    if pts.len() as u64 != want {
                        return Err(OctreeError::PageIn(format!(
                            "leaf {l}: {} points paged in, {want} paged out",
                            pts.len()
                        )));
                    }
                    Ok(pts)
                })
                .collect::<Result<_, _>>()?;
            for (&l, pts) in paged.iter().zip(loaded) {
                let d = &mut self.data[l as usize];
                let mut all = Chunks::default();
                all.append(&pts, POINT_CHUNK_MAX);
                for c in d.points.chunks() {
                    all.append(c, POINT_CHUNK_MAX);
                }
                d.points = all;
                d.paged = 0;
            }
        }

        let mut spill = Vec::with_capacity(spilled as usize);
        let mut spill_leaf = Vec::with_capacity(spilled as usize);
        let mut spill_origin = Vec::with_capacity(spilled as usize);
        let mut splits = 0;
        let mut iterations = 1;
        while !to_split.is_empty() {
            // Splitting.
            let first_new = self.shapes.len();
            for &leaf in &to_split {
                self.split(leaf, &mut spill, &mut spill_leaf, &mut spill_origin);
                new_count[leaf as usize] = 0;
            }
            splits += to_split.len();
            let mut split_now = vec![false; first_new];
            for &leaf in &to_split {
                split_now[leaf as usize] = true;
            }

            // Counting: points of split leaves (batch and spill) move one level down into the
            // new children, which count them.
            let total = self.shapes.len();
            let counts: Vec<AtomicU64> = (first_new..total).map(|_| AtomicU64::new(0)).collect();
            let shapes = &self.shapes;
            let step = |leaves: &mut [u32], pts: &[Point]| {
                let mut run = RunCounter::new(&counts, first_new as u32);
                for (l, p) in leaves.iter_mut().zip(pts) {
                    if split_now[*l as usize] {
                        let s = &shapes[*l as usize];
                        *l = s.first_child + s.cube.octant_of(p.pos) as u32;
                        run.add(*l);
                    }
                }
                run.flush();
            };
            batch_leaf
                .par_chunks_mut(COUNT_CHUNK)
                .zip(batch.par_chunks(COUNT_CHUNK))
                .for_each(|(l, p)| step(l, p));
            spill_leaf
                .par_chunks_mut(COUNT_CHUNK)
                .zip(spill.par_chunks(COUNT_CHUNK))
                .for_each(|(l, p)| step(l, p));
            new_count.extend(counts.into_iter().map(AtomicU64::into_inner));
            iterations += 1;

            to_split = (first_new..total)
                .filter(|&i| new_count[i] > cap && self.splittable(&self.shapes[i]))
                .map(|i| i as u32)
                .collect();
        }
        Ok(Expansion { batch_leaf, spill, spill_leaf, spill_origin, new_count, splits, iterations })
    }

    /// Turns leaf `leaf` into an inner node with 8 empty leaf children; its points go to the
    /// spill list.
    fn split(
        &mut self,
        leaf: u32,
        spill: &mut Vec<Point>,
        spill_leaf: &mut Vec<u32>,
        spill_origin: &mut Vec<u8>,
    ) {
        let s = self.shapes[leaf as usize];
        let first = u32::try_from(self.shapes.len()).expect("an octree has fewer than 2^32 nodes");
        for o in 0..8 {
            self.shapes.push(Shape {
                key: s.key.child(o),
                cube: s.cube.child(o),
                first_child: NO_CHILD,
            });
            self.data.push(NodeData { changed: true, ..NodeData::default() });
        }
        self.shapes[leaf as usize].first_child = first;
        let mode = self.config.color_mode;
        let d = &mut self.data[leaf as usize];
        for chunk in std::mem::take(&mut d.points).chunks() {
            spill.extend_from_slice(chunk);
        }
        spill_leaf.resize(spill.len(), leaf);
        spill_origin.resize(spill.len(), s.key.level);
        d.voxels = Some(Box::new(VoxelState::new(mode)));
        d.changed = true;
    }

    /// §5.2: every point of the update samples the inner nodes on its path (spilled points from
    /// the node that spilled them down).
    fn sample_voxels(&mut self, exp: &Expansion, batch: &[Point]) {
        let root = self.shapes[0];
        if root.first_child == NO_CHILD {
            return;
        }
        // Records: spilled points first (they arrived earlier), then the batch in input order;
        // `seq` is the place in that sequence.
        let rec = |p: &Point, tag: u32, seq: usize| Rec {
            off: root.cube.offset(p.pos),
            color: p.color,
            tag,
            seq: seq as u32,
        };
        let total = exp.spill.len() + batch.len();
        let ns = exp.spill.len();
        self.work.clear();
        self.work.par_extend(
            exp.spill
                .par_iter()
                .zip(exp.spill_origin.par_iter())
                .enumerate()
                .map(|(i, (p, &o))| rec(p, o as u32 + 1, i))
                .chain(batch.par_iter().enumerate().map(|(i, p)| rec(p, 0, ns + i))),
        );
        self.scratch.clear();
        self.scratch.resize(total, Rec::default());
        let s = root.cube.size_log2 as u32 - 1;
        let counts = self
            .work
            .par_chunks(COUNT_CHUNK)
            .map(|chunk| {
                let mut c = [0usize; 8];
                for r in chunk {
                    c[((r.off[0] >> s) & 1
                        | ((r.off[1] >> s) & 1) << 1
                        | ((r.off[2] >> s) & 1) << 2) as usize] += 1;
                }
                c
            })
            .reduce(|| [0; 8], |a, b| std::array::from_fn(|o| a[o] + b[o]));
        let ctx = SampleCtx { shapes: &self.shapes, data: &self.data, root: root.cube };
        sample_subtree(&ctx, 0, &mut self.work, &mut self.scratch, counts);
    }

    /// §5.3-5.4: scatters the points of the update (spilled first, then the batch, each in
    /// order) straight into one new chunk per leaf and appends the chunks to their leaves.
    ///
    /// The sequence is cut into parts; each part counts its points per leaf and then writes into
    /// its own sub-slice of every leaf's chunk, so parts scatter in parallel and the order within
    /// a leaf is the sequence order.
    fn insert_points(&mut self, exp: &Expansion, batch: &[Point]) {
        debug_assert_eq!(exp.new_count.len(), self.shapes.len());
        let total = exp.spill.len() + batch.len();
        let leaves: Vec<u32> =
            (0..exp.new_count.len() as u32).filter(|&i| exp.new_count[i as usize] > 0).collect();
        let mut compact = vec![u32::MAX; exp.new_count.len()];
        for (k, &l) in leaves.iter().enumerate() {
            compact[l as usize] = k as u32;
        }
        let parts = (rayon::current_num_threads() * 4).min(total / SCATTER_MIN).max(1);
        let bounds: Vec<usize> = (0..=parts).map(|p| p * total / parts).collect();
        let seq = |a: usize, b: usize| {
            let s = exp.spill.len();
            let spill =
                exp.spill[a.min(s)..b.min(s)].iter().zip(&exp.spill_leaf[a.min(s)..b.min(s)]);
            let batch = batch[a.max(s) - s..b.max(s) - s]
                .iter()
                .zip(&exp.batch_leaf[a.max(s) - s..b.max(s) - s]);
            spill.chain(batch).map(|(p, &l)| (p, compact[l as usize] as usize))
        };

        // Points per part and leaf.
        let counts: Vec<Vec<u32>> = (0..parts)
            .into_par_iter()
            .map(|p| {
                let mut c = vec![0u32; leaves.len()];
                for (_, k) in seq(bounds[p], bounds[p + 1]) {
                    c[k] += 1;
                }
                c
            })
            .collect();

        // One new chunk per leaf, cut into one piece per part.
        let mut fresh: Vec<Arc<[Point]>> = leaves
            .par_iter()
            .map(|&l| {
                std::iter::repeat_n(Point::zeroed(), exp.new_count[l as usize] as usize).collect()
            })
            .collect();
        let mut pieces: Vec<Vec<&mut [Point]>> =
            (0..parts).map(|_| Vec::with_capacity(leaves.len())).collect();
        for (k, chunk) in fresh.iter_mut().enumerate() {
            let mut rest = Arc::get_mut(chunk).expect("a new chunk is not shared yet");
            for (p, piece) in pieces.iter_mut().enumerate() {
                let (a, r) = std::mem::take(&mut rest).split_at_mut(counts[p][k] as usize);
                piece.push(a);
                rest = r;
            }
            debug_assert!(rest.is_empty());
        }
        pieces.into_par_iter().enumerate().for_each(|(p, mut dst)| {
            let mut cursor = vec![0u32; dst.len()];
            for (pt, k) in seq(bounds[p], bounds[p + 1]) {
                dst[k][cursor[k] as usize] = *pt;
                cursor[k] += 1;
            }
        });

        // Append in parallel.
        let mut by_node: Vec<Option<Arc<[Point]>>> = vec![None; self.data.len()];
        for (&l, chunk) in leaves.iter().zip(fresh) {
            by_node[l as usize] = Some(chunk);
        }
        self.data.par_iter_mut().zip(by_node).for_each(|(d, chunk)| {
            if let Some(chunk) = chunk {
                debug_assert!(d.voxels.is_none(), "points go to leaves only");
                d.subtree += chunk.len() as u64;
                d.points.append_chunk(chunk, POINT_CHUNK_MAX);
                d.changed = true;
            }
        });
    }

    /// §5.4: appends each inner node's new voxels (the backlog) to its chunks; in averaged mode
    /// also rebuilds the chunks whose colours changed. Returns the number of new voxels.
    fn insert_voxels(&mut self, exp: &Expansion, batch: &[Point]) -> u64 {
        let ns = exp.spill.len();
        let point = |seq: u32| -> Point {
            let i = seq as usize;
            if i < ns {
                exp.spill[i]
            } else {
                batch[i - ns]
            }
        };
        self.data
            .par_iter_mut()
            .map(|d| match &mut d.voxels {
                Some(v) => {
                    let (new, sampled, through) = v.publish(&point);
                    d.subtree += through;
                    d.changed |= sampled > 0;
                    new
                }
                None => 0,
            })
            .sum()
    }

    /// Pages out the points of every leaf: the builder drops them (keeping their count), so a
    /// caller that has written them elsewhere (a store) bounds the builder's memory. Snapshots
    /// taken afterwards show those leaves with [`NodeView::paged_points`] instead of the points,
    /// with their revision unchanged (the change was saved, not made). Snapshots taken before
    /// keep their points. Returns the number of points dropped.
    ///
    /// Later updates append to such leaves as usual; a leaf that must split gets its paged-out
    /// points back from the `page_in` of [`add_batch_paged`](Self::add_batch_paged) first.
    pub fn page_out(&mut self) -> u64 {
        let mut dropped = 0;
        let mut republish = false;
        for (i, (shape, d)) in self.shapes.iter().zip(self.data.iter_mut()).enumerate() {
            if let Some(v) = &d.voxels {
                // The caller saved these voxels' records with the node.
                if v.chunks.len() != d.paged {
                    d.paged = v.chunks.len();
                    let old = &self.views[i];
                    let first_child =
                        (shape.first_child != NO_CHILD).then_some(NodeId(shape.first_child));
                    self.views[i] = Arc::new(NodeView::new(
                        shape.key,
                        shape.cube,
                        first_child,
                        Payload::Voxels(v.chunks.clone()),
                        d.subtree,
                        old.revision(),
                        d.paged,
                    ));
                    republish = true;
                }
                continue;
            }
            if d.points.is_empty() {
                continue;
            }
            debug_assert!(!d.changed, "page_out runs between updates, after publish");
            dropped += d.points.len();
            d.paged += d.points.len();
            d.points = Chunks::default();
            let old = &self.views[i];
            let first_child = (shape.first_child != NO_CHILD).then_some(NodeId(shape.first_child));
            self.views[i] = Arc::new(NodeView::new(
                shape.key,
                shape.cube,
                first_child,
                Payload::Points(Chunks::default()),
                d.subtree,
                old.revision(),
                d.paged,
            ));
        }
        if dropped > 0 || republish {
            self.published = self.views.iter().cloned().collect();
        }
        dropped
    }

    /// Points held in memory by the leaves (not paged out).
    pub fn resident_points(&self) -> u64 {
        self.data.iter().map(|d| d.points.len()).sum()
    }

    /// Rebuilds the views of changed nodes and the shared node array that snapshots clone.
    fn publish(&mut self) {
        let old = self.views.len();
        for (i, (shape, d)) in self.shapes.iter().zip(self.data.iter_mut()).enumerate() {
            if !(d.changed || i >= old) {
                continue;
            }
            let payload = match &d.voxels {
                Some(v) => Payload::Voxels(v.chunks.clone()),
                None => Payload::Points(d.points.clone()),
            };
            let first_child = (shape.first_child != NO_CHILD).then_some(NodeId(shape.first_child));
            let view = Arc::new(NodeView::new(
                shape.key,
                shape.cube,
                first_child,
                payload,
                d.subtree,
                self.revision,
                d.paged,
            ));
            if i < old {
                self.views[i] = view;
            } else {
                self.views.push(view);
            }
            d.changed = false;
        }
        self.published = self.views.iter().cloned().collect();
    }
}

/// A point as the sampling partition moves it: offset from the root's minimum, colour, `tag`
/// (0 for a batch point, `level + 1` of the node that spilled it for a spilled point) and `seq`,
/// its place in the update's sequence (spill, then batch), by which a new voxel finds its point.
#[derive(Clone, Copy, Debug, Default)]
struct Rec {
    off: [u32; 3],
    color: u32,
    tag: u32,
    seq: u32,
}

/// Shared state of the sampling recursion.
struct SampleCtx<'a> {
    shapes: &'a [Shape],
    data: &'a [NodeData],
    root: Cube,
}

impl SampleCtx<'_> {
    /// Offset of node `s`'s minimum from the root's.
    #[inline]
    fn base(&self, s: &Shape) -> [u32; 3] {
        [0, 1, 2].map(|a| (s.cube.min[a] - self.root.min[a]) as u32)
    }
}

/// At inner node `node` with its points `recs` (in arrival order) and their octant counts:
/// partitions them stably by octant into `scratch`; then, one task per octant, samples that
/// octant of the node's grid and recurses into the child if it is inner (large octants in
/// parallel). `recs` becomes the children's scratch space.
fn sample_subtree(
    ctx: &SampleCtx<'_>,
    node: u32,
    recs: &mut [Rec],
    scratch: &mut [Rec],
    counts: [usize; 8],
) {
    let shape = &ctx.shapes[node as usize];
    debug_assert_ne!(shape.first_child, NO_CHILD);
    let base = ctx.base(shape);
    let s = shape.cube.size_log2 as u32 - 1;
    let mut pos = [0usize; 8];
    for o in 1..8 {
        pos[o] = pos[o - 1] + counts[o - 1];
    }
    for r in recs.iter() {
        let l = [0, 1, 2].map(|a| r.off[a].wrapping_sub(base[a]) >> s);
        let o = (l[0] | l[1] << 1 | l[2] << 2) as usize;
        scratch[pos[o]] = *r;
        pos[o] += 1;
    }
    let vox = ctx.data[node as usize].voxels.as_deref().expect("inner nodes have voxel state");

    rayon::scope(|sc| {
        let mut rest_in: &mut [Rec] = scratch;
        let mut rest_scratch: &mut [Rec] = recs;
        for (o, &n) in counts.iter().enumerate() {
            let (child_recs, r) = std::mem::take(&mut rest_in).split_at_mut(n);
            rest_in = r;
            let (child_scratch, r) = std::mem::take(&mut rest_scratch).split_at_mut(n);
            rest_scratch = r;
            if n == 0 {
                continue;
            }
            let mut work = move || {
                let mut child_counts = [0usize; 8];
                {
                    let mut oct = vox.octant(o);
                    let oct = &mut *oct;
                    let (sampled, through) = match &mut oct.sampler {
                        Sampler::FirstCome(s) => {
                            sample_recs(shape, base, child_recs, s, &mut child_counts)
                        }
                        Sampler::Averaged(s) => {
                            sample_recs(shape, base, child_recs, s, &mut child_counts)
                        }
                    };
                    oct.sampled += sampled;
                    oct.through += through;
                }
                let child = shape.first_child + o as u32;
                if ctx.shapes[child as usize].first_child != NO_CHILD {
                    sample_subtree(ctx, child, child_recs, child_scratch, child_counts);
                }
            };
            if n >= PAR_MIN {
                sc.spawn(move |_| {
                    let mut work = work;
                    work()
                });
            } else {
                work();
            }
        }
    });
}

/// The sampling loop of one octant of a node's grid; also counts the points per octant of the
/// child (the next bit of the cell). Returns how many points sampled the node and how many of
/// those are new in its cube (spilled points passing through the node that spilled them were
/// already counted there).
#[inline]
fn sample_recs<S: Sample>(
    shape: &Shape,
    base: [u32; 3],
    recs: &[Rec],
    s: &mut S,
    child_counts: &mut [usize; 8],
) -> (u64, u64) {
    let level = shape.key.level as u32;
    let shift = (shape.cube.size_log2 - GRID_LOG2) as u32;
    let mut sampled = 0u64;
    let mut through = 0u64;
    for r in recs {
        let cell = [
            r.off[0].wrapping_sub(base[0]) >> shift,
            r.off[1].wrapping_sub(base[1]) >> shift,
            r.off[2].wrapping_sub(base[2]) >> shift,
        ];
        // bit 5 of the cell is the point's octant in the child (meaningful when the child is
        // inner, i.e. at least 128 units wide)
        child_counts[((cell[0] >> 5) & 1 | ((cell[1] >> 5) & 1) << 1 | ((cell[2] >> 5) & 1) << 2)
            as usize] += 1;
        // batch points (tag 0) and points spilled at this level or above sample here
        if r.tag <= level + 1 {
            s.sample(cell, r.color, r.seq);
            sampled += 1;
            // new in this cube unless spilled by this very node
            through += u64::from(r.tag != level + 1);
        }
    }
    (sampled, through)
}
