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
//! - an inner node's voxels become points at their cell centres, in integer grid units:
//!   `cube.min + coord * cell + cell / 2` with `cell = 2^voxel_size_log2`, i.e.
//!   `cube.min + (coord + 0.5) * cell` rounded down (for a cell one unit wide, its only
//!   coordinate). Where a cell reaches past `i32::MAX` (the root cube is a power of two from the
//!   data's minimum and may overhang the `i32` range) the centre is clamped to `i32::MAX`, which is
//!   still inside the cell because an occupied cell holds a point, and points are `i32`.
//!
//! The batch's samples are in the node's payload order (points in arrival order, voxels in the
//! order their cells were first hit), so index `i` of the batch is element `i` of
//! [`NodeView::points`] or [`NodeView::voxels`]: a resolve pass finds a leaf point's record
//! through [`Point::record`](super::Point::record).
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
use super::{NodeId, GRID_LOG2};
use crate::grid::Grid;
use crate::quantize::{bits_for_extent, BatchGrid, MAX_BITS};
use crate::render::frustum::{Containment, Frustum};
use crate::render::math::Aabb;
use crate::render::raster::{BatchRef, CULL_MARGIN_PX};
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

/// The integer position a voxel is drawn at: the centre of its cell rounded down (see the module
/// docs), clamped into `i32`.
#[inline]
fn voxel_position(cube: &Cube, voxel_log2: u32, coord: [u8; 3]) -> [i32; 3] {
    let half = (1i64 << voxel_log2) >> 1;
    [0, 1, 2].map(|a| (cube.min[a] + ((coord[a] as i64) << voxel_log2) + half).clamp(i32::MIN as i64, i32::MAX as i64) as i32)
}

/// `log2` of the voxel edge of an inner node's cube (0 for a cube narrower than the grid, which
/// the builder never makes an inner node).
#[inline]
fn voxel_log2(cube: &Cube) -> u32 {
    cube.size_log2.saturating_sub(GRID_LOG2) as u32
}

/// Grows `(lo, hi)` by the integer position `p`.
#[inline]
fn grow(lo: &mut [i32; 3], hi: &mut [i32; 3], p: [i32; 3]) {
    for a in 0..3 {
        lo[a] = lo[a].min(p[a]);
        hi[a] = hi[a].max(p[a]);
    }
}

/// The node's payload as a quantized batch on the world grid `grid`: leaf points exactly,
/// inner-node voxels at their cell centres (see the module docs). Fails for a node whose samples
/// span `2^30` grid units or more on an axis.
pub fn node_batch(node: &NodeView, grid: &Grid) -> Result<NodeBatch, NodeBatchError> {
    let cube = node.cube();
    let vlog2 = voxel_log2(&cube);
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
                grow(&mut lo, &mut hi, voxel_position(&cube, vlog2, vx.coord));
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
            return Err(NodeBatchError::TooWide { key: node.key(), axis: ['x', 'y', 'z'][a], extent });
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
                    push(voxel_position(&cube, vlog2, vx.coord), vx.color);
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

/// Samples a node holds (points of a leaf, voxels of an inner node).
#[inline]
fn samples(node: &NodeView) -> u64 {
    node.point_count() + node.voxel_count()
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
    fn visit(&self, node: &NodeView) -> Visit {
        if node.subtree_points() == 0 {
            return Visit::Empty;
        }
        let cube = node.cube();
        let bounds = cube.world_bounds(self.grid);
        if let Some(frustum) = &self.frustum {
            // Decoded samples stay within size / 2^11 grid units of the cube (see the module
            // docs); f32 depth may be off by a tiny fraction of the distance.
            let units = (cube.size() >> 10) as f64 + 1.0;
            let d = bounds.center().iter().zip(&self.camera.eye).map(|(c, e)| (c - e) * (c - e)).sum::<f64>().sqrt();
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

/// Selects the nodes of `snapshot` to draw for `camera` (paper 004 §6; see the module docs):
/// from the root down, culling nodes outside the frustum, replacing inner nodes larger than
/// `options.threshold_px` on screen by their children, largest first, within the point budget.
/// `grid` is the world grid of the snapshot's integer coordinates. Fails only for an unusable
/// camera.
pub fn select_nodes(snapshot: &Snapshot, grid: &Grid, camera: &Camera, options: &LodOptions) -> Result<LodSelection, CameraError> {
    camera.validate()?;
    let view = View { grid, camera, frustum: options.cull.then(|| Frustum::new(camera, CULL_MARGIN_PX)) };
    let refinable = |node: &NodeView, size: f64| !node.is_leaf() && size > options.threshold_px;
    let mut sel = LodSelection::default();
    let mut drawn = vec![false; snapshot.node_count()];
    let mut heap = BinaryHeap::new();
    let mut total = 0u64;

    let root = snapshot.node(NodeId::ROOT);
    sel.stats.visited = 1;
    match view.visit(root) {
        Visit::Empty => sel.stats.empty = 1,
        Visit::Culled => {
            sel.stats.culled = 1;
            sel.culled.push(NodeId::ROOT);
        }
        Visit::Visible(size) => {
            drawn[0] = true;
            total = samples(root);
            if refinable(root, size) {
                heap.push(Candidate { size, id: NodeId::ROOT });
            }
        }
    }

    while let Some(Candidate { id, .. }) = heap.pop() {
        let node = snapshot.node(id);
        let children = node.children().expect("only inner nodes are refined");
        let mut kids = [(NodeId::ROOT, 0.0); 8];
        let mut n_kids = 0;
        let mut culled = [NodeId::ROOT; 8];
        let mut n_culled = 0;
        let mut n_empty = 0;
        let mut cost = 0u64;
        for c in children {
            match view.visit(snapshot.node(c)) {
                Visit::Empty => n_empty += 1,
                Visit::Culled => {
                    culled[n_culled] = c;
                    n_culled += 1;
                }
                Visit::Visible(size) => {
                    kids[n_kids] = (c, size);
                    n_kids += 1;
                    cost += samples(snapshot.node(c));
                }
            }
        }
        let after = total - samples(node) + cost;
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
            if refinable(snapshot.node(c), size) {
                heap.push(Candidate { size, id: c });
            }
        }
    }

    sel.nodes = drawn.iter().enumerate().filter(|(_, d)| **d).map(|(i, _)| NodeId(i as u32)).collect();
    sel.culled.sort_unstable();
    for &id in &sel.nodes {
        let n = snapshot.node(id);
        sel.stats.points += n.point_count();
        sel.stats.voxels += n.voxel_count();
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
    use crate::render::framebuffer::key_index;
    use crate::render::testutil::{Rng, Scene};
    use crate::quantize::Precision;
    use crate::render::{rasterize, Framebuffer, PrecisionMode, RasterOptions, ViewPreset, EMPTY_KEY};
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
        let mut b = Builder::for_bounds(min, max, BuilderConfig { leaf_capacity: cap, ..BuilderConfig::default() }).unwrap();
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
        cam.project(w).is_some_and(|q| q.x >= 0.0 && q.x < cam.width as f64 && q.y >= 0.0 && q.y < cam.height as f64)
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
            assert_eq!(b.len() as u64, samples(n), "{id:?}");
            assert_eq!(b.colors.len(), b.len());
            assert!(b.grid.bits.iter().all(|&x| x as u32 <= MAX_BITS));
            let r = b.batch_ref(1234);
            assert_eq!((r.first_index, r.len(), r.grid), (1234, b.len(), b.grid));
            assert_eq!(r.bounds(), b.bounds());
            let decoded: Vec<[i32; 3]> =
                (0..b.len()).map(|i| b.grid.decode_exact([b.words[0][i], b.words[1][i], b.words[2][i]])).collect();
            let bounds = b.bounds();
            for p in &decoded {
                let w = [0, 1, 2].map(|a| GRID.world(a, p[a] as i64));
                assert!((0..3).all(|a| bounds.min[a] <= w[a] && w[a] <= bounds.max[a]), "{id:?} {p:?}");
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
                    let cell = 1i64 << cube.voxel_size_log2().unwrap();
                    for ((v, p), c) in vx.iter().zip(&decoded).zip(&b.colors) {
                        assert!(cube.contains(*p), "{id:?} {p:?}");
                        let lo = cube.voxel_min(v.coord);
                        for a in 0..3 {
                            assert_eq!(p[a] as i64, lo[a] + cell / 2, "{id:?} the centre, rounded down");
                            assert!(lo[a] <= p[a] as i64 && (p[a] as i64) < lo[a] + cell);
                        }
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
        b.add_batch(&[Point { pos: [0, 0, 0], ..Point::default() }, Point { pos: [i32::MAX, 3, 0], ..Point::default() }])
            .unwrap();
        let snap = b.snapshot();
        let err = node_batch(snap.node(NodeId::ROOT), &GRID).unwrap_err();
        assert_eq!(err, NodeBatchError::TooWide { key: NodeKey::ROOT, axis: 'x', extent: i32::MAX as u64 });
        assert!(err.to_string().contains("node r "), "{err}");

        // A tree over the whole i32 range: only nodes wider than 2^30 units can fail.
        let mut rng = Rng(9);
        let pts: Vec<Point> = (0..4_000)
            .map(|i| Point { pos: [0; 3].map(|_: i32| rng.next_u64() as i32), color: 0, record: i })
            .collect();
        let mut b = Builder::for_bounds([i32::MIN; 3], [i32::MAX; 3], BuilderConfig { leaf_capacity: 200, ..BuilderConfig::default() })
            .unwrap();
        b.add_batch(&pts).unwrap();
        let snap = b.snapshot();
        assert_eq!(snap.root_cube().size_log2, 32);
        assert!(matches!(node_batch(snap.node(NodeId::ROOT), &GRID), Err(NodeBatchError::TooWide { .. })));
        for (id, n) in snap.iter().filter(|(_, n)| n.cube().size_log2 <= 30) {
            node_batch(n, &GRID).unwrap_or_else(|e| panic!("{id:?}: {e}"));
        }

        // A root cube overhanging i32::MAX: the top cell's centre is clamped, still in its cell.
        let lo = i32::MAX - 1000;
        let mut pts: Vec<Point> = (0..600).map(|i| Point { pos: [lo + (i * 7919) % 1001; 3], color: i as u32, record: i as u64 }).collect();
        pts.push(Point { pos: [lo; 3], color: 1, record: 600 });
        pts.push(Point { pos: [i32::MAX; 3], color: 2, record: 601 });
        let mut b = Builder::for_bounds([lo; 3], [i32::MAX; 3], BuilderConfig { leaf_capacity: 50, ..BuilderConfig::default() }).unwrap();
        b.add_batch(&pts).unwrap();
        let snap = b.snapshot();
        let root = snap.node(NodeId::ROOT);
        assert!(root.cube().end()[0] > i32::MAX as i64 && !root.is_leaf());
        let nb = node_batch(root, &GRID).unwrap();
        let mut clamped = 0;
        for (v, i) in root.voxels().unwrap().iter().zip(0..) {
            let p = nb.grid.decode_exact([nb.words[0][i], nb.words[1][i], nb.words[2][i]]);
            let cmin = root.cube().voxel_min(v.coord);
            let cell = 1i64 << root.cube().voxel_size_log2().unwrap();
            for a in 0..3 {
                assert!(cmin[a] <= p[a] as i64 && (p[a] as i64) < cmin[a] + cell);
            }
            clamped += (p == [i32::MAX; 3]) as usize;
        }
        assert_eq!(clamped, 1);
    }

    #[test]
    fn threshold_zero_selects_the_visible_leaves_and_draws_every_point() {
        let (scene, snap) = terrain_tree(150_000, 3_000);
        let parents = parents(&snap);
        let leaves: Vec<NodeId> = snap.leaves().filter(|(_, n)| n.point_count() > 0).map(|(id, _)| id).collect();
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
        let all_refs: Vec<BatchRef<'_>> = leaves.iter().zip(&all).map(|(id, b)| b.batch_ref(first[id.index()])).collect();
        let scene_refs = scene.refs();
        let opts = LodOptions { threshold_px: 0.0, point_budget: None, cull: true };

        // Without culling: every non-empty leaf.
        let sel = select_nodes(&snap, &GRID, &framed(&scene)[0], &LodOptions { cull: false, ..opts }).unwrap();
        assert_eq!(sel.nodes, leaves);
        assert_eq!(sel.stats.points, snap.point_count());

        let mut culling_seen = false;
        for (ci, cam) in all_cameras(&scene).iter().enumerate() {
            let sel = select_nodes(&snap, &GRID, cam, &opts).unwrap();
            let chosen: HashSet<NodeId> = sel.nodes.iter().copied().collect();
            // Exactly the non-empty leaves not below a culled node.
            let culled: HashSet<NodeId> = sel.culled.iter().copied().collect();
            let want: Vec<NodeId> =
                leaves.iter().copied().filter(|&l| !lineage(&parents, l).iter().any(|a| culled.contains(a))).collect();
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
            let batches: Vec<NodeBatch> = sel.nodes.iter().map(|&id| node_batch(snap.node(id), &GRID).unwrap()).collect();
            let refs: Vec<BatchRef<'_>> = sel.nodes.iter().zip(&batches).map(|(id, b)| b.batch_ref(first[id.index()])).collect();
            let got = render(cam, &refs, true);
            let want_keys = render(cam, &all_refs, false);
            let covered = want_keys.iter().filter(|&&k| k != EMPTY_KEY).count();
            assert!(covered > 1_000, "camera {ci}: {covered} pixels");
            assert_eq!(got, want_keys, "camera {ci}: keys differ");

            // Against the original points in Morton batches (other frames, so f32 rounding may
            // move a point across a pixel edge): the same winning record almost everywhere.
            let exact = RasterOptions { precision: PrecisionMode::Fixed(Precision::Bits30), cull: false };
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
            assert!(differ * 100 <= covered, "camera {ci}: {differ} of {covered} pixels differ from the original points");
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
                    let sel = select_nodes(&snap, &GRID, cam, &LodOptions { threshold_px: t, point_budget: None, cull }).unwrap();
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
        let away = Camera { eye: [c[0], c[1] - 400.0, c[2]], target: [c[0], c[1] - 401.0, c[2]], ..small(scene.cameras()[8]) };
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
        let leaves: Vec<NodeId> = snap.leaves().filter(|(_, n)| n.point_count() > 0).map(|(id, _)| id).collect();
        let root_voxels = snap.node(NodeId::ROOT).voxel_count();
        let budgets = [Some(0), Some(root_voxels), Some(20_000), Some(50_000), Some(90_000), Some(u64::MAX), None];
        let nframed = framed(&scene).len();
        let mut limited = 0;
        for (ci, cam) in all_cameras(&scene).iter().enumerate() {
            // Which leaves have a visible point.
            let seen: Vec<NodeId> =
                leaves.iter().copied().filter(|&l| snap.node(l).points().unwrap().iter().any(|p| visible(cam, p.pos))).collect();
            for threshold_px in [0.0, 32.0, 128.0] {
                let mut last = 0;
                for budget in budgets {
                    let opts = LodOptions { threshold_px, point_budget: budget, cull: true };
                    let sel = select_nodes(&snap, &GRID, cam, &opts).unwrap();
                    let s = sel.stats.samples();
                    if let Some(b) = budget {
                        assert!(s <= b || sel.nodes == [NodeId::ROOT], "camera {ci}: {s} samples over budget {b}");
                    }
                    limited += sel.stats.budget_reached as usize;
                    let chosen: HashSet<NodeId> = sel.nodes.iter().copied().collect();
                    // No two selected nodes are nested.
                    for &id in &sel.nodes {
                        assert!(lineage(&parents, id)[1..].iter().all(|a| !chosen.contains(a)), "camera {ci}: {id:?} nested");
                    }
                    // Every visible leaf is covered exactly once.
                    for &l in &seen {
                        let n = lineage(&parents, l).iter().filter(|a| chosen.contains(a)).count();
                        assert_eq!(n, 1, "camera {ci} budget {budget:?}: leaf {l:?} covered {n} times");
                    }
                    // In framed views no non-empty node is culled, so refining never lowers the
                    // count: a larger budget selects at least as much.
                    if ci < nframed {
                        assert!(s >= last, "camera {ci}: budget {budget:?} selects {s} < {last}");
                        last = s;
                    }
                    if budget.is_none() {
                        let unlimited = select_nodes(&snap, &GRID, cam, &LodOptions { point_budget: Some(u64::MAX), ..opts }).unwrap();
                        assert_eq!(unlimited, sel);
                        assert!(!sel.stats.budget_reached);
                    }
                }
            }
        }
        assert!(limited > 10, "budgets bind in {limited} selections");
        // A budget below the root's voxels still shows the root.
        let sel = select_nodes(&snap, &GRID, &framed(&scene)[0], &LodOptions { point_budget: Some(1), ..LodOptions::default() }).unwrap();
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
                    let sel = select_nodes(&snap, &GRID, &cam, &LodOptions { point_budget: Some(budget), ..opts }).unwrap();
                    assert!(sel.stats.budget_reached, "{budget}: {:?}", sel.stats);
                    if sel.stats.refined == 0 {
                        continue;
                    }
                    checked += 1;
                    // Every inner node left coarse above the threshold is no larger on screen than
                    // every node that was refined (the parents of selected nodes).
                    let refined_min =
                        sel.nodes.iter().filter_map(|&id| parents[id.index()]).map(size).fold(f64::INFINITY, f64::min);
                    for &id in &sel.nodes {
                        if !snap.node(id).is_leaf() && size(id) > threshold_px {
                            assert!(size(id) <= refined_min, "{id:?}: {} px left coarse, a {refined_min} px node refined", size(id));
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
                let sel = select_nodes(&snap, &GRID, cam, &LodOptions { threshold_px, ..LodOptions::default() }).unwrap();
                culled_total += sel.culled.len();
                let mut batches = Vec::new();
                for &id in &sel.culled {
                    // No point below a culled node is visible...
                    let mut below = Vec::new();
                    leaves_below(&snap, id, &mut below);
                    for l in below {
                        for p in snap.node(l).points().unwrap().iter() {
                            assert!(!visible(cam, p.pos), "camera {ci}: visible point {p:?} below culled {id:?}");
                        }
                    }
                    // ...and the rasterizer, not culling, draws nothing of its batch.
                    batches.push(node_batch(snap.node(id), &GRID).unwrap());
                }
                let refs: Vec<BatchRef<'_>> = batches.iter().map(|b| b.batch_ref(0)).collect();
                let fb = Framebuffer::new(cam.width, cam.height);
                let stats = rasterize(&fb, &refs, &GRID, cam, &RasterOptions { cull: false, ..RasterOptions::default() }).unwrap();
                assert_eq!(stats.points_drawn, 0, "camera {ci}: culled nodes draw {} points", stats.points_drawn);
            }
        }
        assert!(culled_total > 20, "{culled_total} nodes culled");
    }
}
