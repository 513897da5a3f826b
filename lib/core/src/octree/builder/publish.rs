//! What snapshots see: the views of the changed nodes, rebuilt after an update (`publish`), and
//! the leaves' points paged out between updates ([`Builder::page_out`]).

use super::node::NO_CHILD;
use super::Builder;
use crate::octree::chunks::Chunks;
use crate::octree::snapshot::{NodeView, Payload};
use crate::octree::types::NodeId;
use std::sync::Arc;

impl Builder {
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
    pub(super) fn publish(&mut self) {
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
