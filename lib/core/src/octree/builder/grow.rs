//! Growing the root (not in the paper, whose root is fixed): while a point of the batch lies
//! outside the root cube, a new root of twice the size goes above the old one ("Growing the
//! root" in the [octree docs](crate::octree)).

use super::node::{NodeData, Shape, NO_CHILD};
use super::{Builder, PageIn};
use crate::octree::cube::{Cube, NodeKey};
use crate::octree::snapshot::{NodeView, Payload};
use crate::octree::types::{NodeId, OctreeError, Point, Voxel, MAX_ROOT_SIZE_LOG2};
use crate::octree::voxels::VoxelState;
use rayon::prelude::*;
use std::sync::Arc;

impl Builder {
    /// Grows the root until it holds every point of `batch` ("Growing the root" in the module
    /// docs); returns the number of growths. Fails before changing anything if the root would
    /// exceed [`MAX_ROOT_SIZE_LOG2`], or if the saved voxel records of an inner root cannot be
    /// paged in.
    pub(super) fn grow(
        &mut self,
        batch: &[Point],
        page_in: &PageIn<'_>,
    ) -> Result<u32, OctreeError> {
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
}
