//! The node selection for one view (paper 004 §6): [`select_nodes`] walks a [`LodTree`] from the
//! root, culling, refining by projected size and within a point budget ([`LodOptions`]), and
//! returns the nodes to draw ([`LodSelection`], [`LodStats`]); see "Node selection" in the
//! [`lod`](super) docs.

use super::tree::LodTree;
use crate::grid::Grid;
use crate::octree::types::NodeId;
use crate::render::frustum::{Containment, Frustum};
use crate::render::plan::CULL_MARGIN_PX;
use crate::render::{Camera, CameraError};
use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// Default [`LodOptions::threshold_px`]: the edge of an inner node's voxel grid (paper 004 §6).
pub const DEFAULT_THRESHOLD_PX: f64 = 128.0;

/// Relative depth slack of node culling, in units of (distance to the cube + its diagonal); the
/// same as the rasterizer's per-batch culling.
const CULL_DEPTH_MARGIN: f64 = 1e-5;

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
///
/// [`Snapshot`]: crate::octree::Snapshot
/// [`LodIndex`]: super::LodIndex
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
    use crate::octree::lod::batch::{node_batch, NodeBatch};
    use crate::octree::lod::testutil::{
        all_cameras, framed, reference_batch, small, terrain_tree, GRID,
    };
    use crate::octree::snapshot::Snapshot;
    use crate::quantize::Precision;
    use crate::render::framebuffer::key_index;
    use crate::render::raster::BatchRef;
    use crate::render::{rasterize, Framebuffer, PrecisionMode, RasterOptions, EMPTY_KEY};
    use std::collections::HashSet;

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

    fn render(cam: &Camera, refs: &[BatchRef<'_>], cull: bool) -> Vec<u64> {
        render_with(cam, refs, &RasterOptions { cull, ..RasterOptions::default() })
    }

    fn render_with(cam: &Camera, refs: &[BatchRef<'_>], options: &RasterOptions) -> Vec<u64> {
        let fb = Framebuffer::new(cam.width, cam.height);
        rasterize(&fb, refs, &GRID, cam, options).unwrap();
        fb.into_keys()
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
