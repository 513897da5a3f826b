//! Test fixtures of the LOD tests: an octree over a terrain scene, the cameras that look at it,
//! and a leaf's batch built independently of [`node_batch`](super::node_batch).

use super::batch::NodeBatch;
use crate::batching::int_bounds;
use crate::grid::Grid;
use crate::octree::snapshot::Snapshot;
use crate::octree::{Builder, BuilderConfig, Point};
use crate::quantize::BatchGrid;
use crate::render::testutil::{Rng, Scene};
use crate::render::{Camera, ViewPreset};

/// A georeferenced millimetre grid (UTM-like offsets).
pub(super) const GRID: Grid = Grid { scale: [0.001; 3], offset: [500_000.0, 5_400_000.0, 0.0] };

/// [`Scene::terrain`] built into an octree in a shuffled arrival order, in several batches;
/// `Point::record` is the point's index in the scene (its global index there).
pub(super) fn terrain_tree(n: usize, cap: u32) -> (Scene, Snapshot) {
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

pub(super) fn small(c: Camera) -> Camera {
    Camera { width: 640, height: 360, ..c }
}

/// Every preset framed, in perspective and orthographic.
pub(super) fn framed(scene: &Scene) -> Vec<Camera> {
    let mut cams = Vec::new();
    for preset in ViewPreset::ALL {
        cams.push(Camera::frame_perspective(&scene.bounds, preset, 0.8, 640, 360).unwrap());
        cams.push(Camera::frame_orthographic(&scene.bounds, preset, 640, 360).unwrap());
    }
    cams
}

/// Framed views and views in which much of the tree is outside the frustum.
pub(super) fn all_cameras(scene: &Scene) -> Vec<Camera> {
    let mut cams = framed(scene);
    cams.extend(scene.cameras().into_iter().skip(8).map(small));
    cams.push(Camera::close_up(&scene.bounds, 0.8, 640, 360).unwrap());
    cams.push(Camera::inside(&scene.bounds, 1.2, 640, 360).unwrap());
    cams
}

/// A leaf's batch built independently of [`node_batch`]: the frame of
/// [`BatchGrid::for_bounds`] over the points, world bounds of its corners.
pub(super) fn reference_batch(points: &[Point]) -> NodeBatch {
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
