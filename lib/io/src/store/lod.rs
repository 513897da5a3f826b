//! A store read for LOD rendering (paper 004 §6): the structure the view-dependent node
//! selection of [`mortar_core::octree::lod`] walks, and the selected nodes as the rasterizers'
//! batches, straight from the memory-mapped `nodes.bin` (paper 003 §3.5: "a node is a
//! variable-size batch"). What colours and draws them is mortar-app's (`draw::lod`).
//!
//! - [`StoreLod::new`] rebuilds the tree's structure from the hierarchy's keys
//!   ([`LodIndex`]: children found by key, subtree point counts summed from the leaves, every
//!   structural claim checked), so [`select_nodes`] walks a store exactly as it walks an in-memory
//!   [`Snapshot`](mortar_core::octree::Snapshot). No payload is read to select.
//! - [`StoreLod::batches`] turns the selected nodes into the rasterizer's [`BatchRef`]s without
//!   copying: a payload's coarse, medium and fine words are already the batch layout, and they
//!   are borrowed from the map (payloads start at multiples of 8 in a page-aligned map, so the
//!   `u32` arrays are aligned; [`Store::open`] checks the offsets). Point indices run consecutively
//!   over the selected nodes in selection order (ascending node id), as a batch file's do, so
//!   the GPU scene takes the batches as they come and one index names one sample of one node.
//! - A node's batch needs the world bounds of its samples. The payload records the frame's
//!   minimum (the samples' integer minimum) but not their maximum: it is taken from the coarse
//!   words on first use (exact for frames of up to 10 bits, otherwise at most `2^(bits - 10)`
//!   units above the true maximum: conservative, so culling stays correct) and cached.
//! - [`LodBatches`] gives a selected sample's stored colour, record attributes and exact
//!   position by its point index: what the colour rules of a renderer read.

use super::format::LEAF;
use super::reader::{NodeData, Store};
use crate::error::{Error, RenderError, Result, StoreError};
use mortar_core::grid::Grid;
use mortar_core::octree::{
    select_nodes, Cube, IndexEntry, LodIndex, LodOptions, LodSelection, LodTree, NodeId, NodeKey,
};
use mortar_core::render::{Aabb, BatchRef, Camera};
use rayon::prelude::*;
use std::path::Path;
use std::sync::OnceLock;

/// A store opened for LOD rendering: the store, its tree structure and the cached sample maxima.
pub struct StoreLod {
    store: Store,
    index: LodIndex,
    grid: Grid,
    /// Per node: the integer maximum of its samples (see the module docs), on first use.
    maxima: Vec<OnceLock<[i32; 3]>>,
}

impl std::fmt::Debug for StoreLod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StoreLod")
            .field("path", &self.store.path)
            .field("nodes", &self.store.entries.len())
            .finish()
    }
}

impl StoreLod {
    /// Opens the last commit of the store `dir` for LOD rendering.
    pub fn open(dir: &Path) -> Result<StoreLod> {
        StoreLod::new(Store::open(dir)?)
    }

    /// Rebuilds the tree of `store` from its hierarchy; an error naming the store where the
    /// entries do not form one octree.
    pub fn new(store: Store) -> Result<StoreLod> {
        let bad = |error: StoreError| Error::Store { path: store.path.clone(), error };
        let root_log2 = store.header.root_size_log2;
        let root = store.root_cube();
        if root_log2 > 32 {
            return Err(bad(StoreError::RootTooLarge { size_log2: root_log2 }));
        }
        // The cube must overlap the i32 grid of the points; a damaged corner overflowed the
        // cube arithmetic (fuzz regression root-min-overflow).
        let (lo, hi) = (i32::MIN as i64 - (1i64 << 32), i32::MAX as i64);
        if root.min.iter().any(|&m| !(lo..=hi).contains(&m)) {
            return Err(bad(StoreError::RootOutside { min: root.min }));
        }
        let mut entries = Vec::with_capacity(store.entries.len());
        for (i, e) in store.entries.iter().enumerate() {
            let level = u8::try_from(e.level)
                .map_err(|_| bad(StoreError::NodeLevel { node: i, level: e.level }))?;
            entries.push(IndexEntry {
                key: NodeKey { level, index: e.index },
                leaf: e.kind == LEAF,
                samples: e.count,
            });
        }
        let index = LodIndex::new_partial(root, &entries)
            .map_err(|error| bad(StoreError::Index { error }))?;
        let h = &store.meta.header;
        let grid = Grid { scale: h.scale, offset: h.offset };
        let maxima = (0..entries.len()).map(|_| OnceLock::new()).collect();
        Ok(StoreLod { store, index, grid, maxima })
    }

    /// The store.
    pub fn store(&self) -> &Store {
        &self.store
    }

    /// The store's directory.
    pub fn path(&self) -> &Path {
        &self.store.path
    }

    /// The tree's structure.
    pub fn index(&self) -> &LodIndex {
        &self.index
    }

    /// The world grid of the store's integer coordinates.
    pub fn grid(&self) -> Grid {
        self.grid
    }

    /// Points in the leaves.
    pub fn point_count(&self) -> u64 {
        self.store.header.points
    }

    /// Points a view can draw: those of the leaves, and the voxels of the frontier of a commit
    /// whose deeper levels are not written yet.
    pub fn drawable(&self) -> u64 {
        self.index.point_count()
    }

    /// World bounds of every point (empty bounds at the origin for a store without points).
    pub fn bounds(&self) -> Aabb {
        let h = &self.store.header;
        // A commit of a build under way may hold inner levels only: their bounds are set.
        let set = (0..3).all(|a| h.min[a] <= h.max[a]);
        let (lo, hi) = if (h.points == 0 && self.index.point_count() == 0) || !set {
            ([0; 3], [0; 3])
        } else {
            (h.min, h.max)
        };
        world_box(&self.grid, lo, hi)
    }

    /// The nodes to draw for `camera` ([`select_nodes`] on the store's tree).
    pub fn select(&self, camera: &Camera, options: &LodOptions) -> Result<LodSelection> {
        select_nodes(self, &self.grid, camera, options).map_err(|error| Error::Render {
            path: self.store.path.clone(),
            error: RenderError::Camera { error },
        })
    }

    /// The payload of node `id`.
    pub fn node(&self, id: NodeId) -> NodeData<'_> {
        self.store.node(id.index())
    }

    /// The integer maximum of node `id`'s samples (see the module docs), computed on first use.
    fn sample_max(&self, id: NodeId) -> [i32; 3] {
        *self.maxima[id.index()].get_or_init(|| {
            let d = self.node(id);
            let g = d.grid();
            let mut top = [0u32; 3];
            for &w in d.words[0] {
                for (a, t) in top.iter_mut().enumerate() {
                    *t = (*t).max(w >> (10 * a) & 0x3ff);
                }
            }
            [0, 1, 2].map(|a| {
                let bits = g.bits[a] as u32;
                let span = (1u64 << bits) - 1;
                // The largest q30 with this coarse field, back in grid units.
                let q30 = ((top[a] as u64 + 1) << 20) - 1;
                let units = (q30 >> (30 - bits)).min(span);
                (g.min[a] as i64 + units as i64).min(i32::MAX as i64) as i32
            })
        })
    }

    /// The batches of `nodes` (a selection's nodes, in the order given), numbered consecutively
    /// from 0. Fails where they hold more than 2^32 samples (point indices are 32-bit).
    pub fn batches(&self, nodes: &[NodeId]) -> Result<LodBatches<'_>> {
        if let Some(&id) = nodes.iter().find(|id| id.index() >= self.store.entries.len()) {
            return Err(Error::Store {
                path: self.store.path.clone(),
                error: StoreError::NoSuchNode { node: id.0 },
            });
        }
        let samples: u64 = nodes.iter().map(|&id| self.store.entries[id.index()].count).sum();
        if samples > 1u64 << 32 {
            return Err(Error::Render {
                path: self.store.path.clone(),
                error: RenderError::TooManySamples { samples },
            });
        }
        // Coded payloads are decoded here, in parallel, and a damaged one is an error.
        nodes.par_iter().try_for_each(|&id| self.store.try_node(id.index()).map(|_| ()))?;
        nodes.par_iter().for_each(|&id| {
            self.sample_max(id);
        });
        let mut refs = Vec::with_capacity(nodes.len());
        let mut colors = Vec::with_capacity(nodes.len());
        let mut attributes = Vec::with_capacity(nodes.len());
        let mut first = Vec::with_capacity(nodes.len());
        let mut next = 0u64;
        for &id in nodes {
            let d = self.node(id);
            refs.push(self.node_batch(id, next as u32));
            colors.push(d.colors);
            attributes.push(d.attributes);
            first.push(next as u32);
            next += d.header.count as u64;
        }
        let attr_len = self.store.layout.record_len - 12;
        // The samples the batches hold: a payload that did not decode reads as a node without
        // points (`Store::node`), fewer than its entry declares.
        let samples = next;
        Ok(LodBatches { refs, colors, attributes, attr_len, first, nodes: nodes.to_vec(), samples })
    }

    /// Node `id` as one batch whose samples are numbered from `first_index` (the node must be in
    /// the store: ids from [`select`](Self::select) or below [`LodTree::node_count`]).
    pub fn node_batch(&self, id: NodeId, first_index: u32) -> BatchRef<'_> {
        let d = self.node(id);
        let g = d.grid();
        let b = world_box(&self.grid, g.min, self.sample_max(id));
        BatchRef { grid: g, bounds_min: b.min, bounds_max: b.max, words: d.words, first_index }
    }

    /// Where node `id`'s payload lies (segment, byte offset, length) and the key it has there.
    /// Segments only grow and a payload is never rewritten in place, so across commits of one
    /// store an equal place means the same node contents: what a viewer of a growing store keys
    /// its uploads by. (The key and length are part of it because a segment number can come back
    /// after its file was removed: a partitioned build's provisional segment, then a compaction's.)
    pub fn payload_place(&self, id: NodeId) -> PayloadPlace {
        let e = &self.store.entries[id.index()];
        (e.segment, e.offset, e.length, e.level, e.index)
    }
}

/// Segment, offset, length, level and index of a node's payload ([`StoreLod::payload_place`]).
pub type PayloadPlace = (u32, u64, u64, u32, [u32; 3]);

/// World box of the integer bounds `lo..=hi` on `grid` (ordered for negative scales).
fn world_box(grid: &Grid, lo: [i32; 3], hi: [i32; 3]) -> Aabb {
    let mut min = [0.0; 3];
    let mut max = [0.0; 3];
    for a in 0..3 {
        let (x, y) = (grid.world(a, lo[a] as i64), grid.world(a, hi[a] as i64));
        min[a] = x.min(y);
        max[a] = x.max(y);
    }
    Aabb::new(min, max)
}

impl LodTree for StoreLod {
    fn node_count(&self) -> usize {
        self.index.node_count()
    }
    fn cube(&self, id: NodeId) -> Cube {
        self.index.cube(id)
    }
    fn subtree_points(&self, id: NodeId) -> u64 {
        self.index.subtree_points(id)
    }
    fn children(&self, id: NodeId) -> Option<[NodeId; 8]> {
        self.index.children(id)
    }
    fn samples(&self, id: NodeId) -> u64 {
        self.index.samples(id)
    }
    fn is_leaf(&self, id: NodeId) -> bool {
        self.index.is_leaf(id)
    }
}

/// Selected nodes as the rasterizers take them, borrowed from the store's map.
#[derive(Clone, Debug)]
pub struct LodBatches<'a> {
    /// One batch per node, `first_index` consecutive from 0.
    pub refs: Vec<BatchRef<'a>>,
    /// The nodes' RGBA8 colours, one per sample.
    pub colors: Vec<&'a [u32]>,
    /// The nodes' record attributes (every byte of a record after X, Y, Z), one per sample.
    pub attributes: Vec<&'a [u8]>,
    /// Bytes of attributes per sample.
    pub attr_len: usize,
    /// The nodes, in batch order.
    pub nodes: Vec<NodeId>,
    /// Samples in all (points and voxels).
    pub samples: u64,
    first: Vec<u32>,
}

impl LodBatches<'_> {
    /// The batch (position in [`refs`](Self::refs)) and sample in it of point index `index`.
    #[inline]
    pub fn locate(&self, index: u32) -> Option<(usize, usize)> {
        if index as u64 >= self.samples {
            return None;
        }
        let b = self.first.partition_point(|&f| f <= index) - 1;
        Some((b, (index - self.first[b]) as usize))
    }

    /// The stored colour of point index `index`.
    #[inline]
    pub fn color(&self, index: u32) -> Option<u32> {
        self.locate(index).map(|(b, i)| self.colors[b][i])
    }

    /// The record attributes (after X, Y, Z) of point index `index`.
    #[inline]
    pub fn attributes(&self, index: u32) -> Option<&[u8]> {
        self.locate(index)
            .map(|(b, i)| &self.attributes[b][i * self.attr_len..(i + 1) * self.attr_len])
    }

    /// The exact integer position of point index `index` (a leaf point's or a voxel's point's
    /// own coordinates).
    pub fn position(&self, index: u32) -> Option<[i32; 3]> {
        self.locate(index).map(|(b, i)| {
            let r = &self.refs[b];
            r.grid.decode_exact([r.words[0][i], r.words[1][i], r.words[2][i]])
        })
    }
}
