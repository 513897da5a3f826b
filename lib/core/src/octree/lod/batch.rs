//! A node's payload as one quantized batch for the rasterizer ([`node_batch`], [`NodeBatch`];
//! paper 003 §3.5, "a node is a variable-size batch"): see "Node batches" in the
//! [`lod`](super) docs.

use crate::grid::Grid;
use crate::octree::cube::NodeKey;
use crate::octree::snapshot::{NodeView, Payload};
use crate::quantize::{bits_for_extent, BatchGrid, MAX_BITS};
use crate::render::math::Aabb;
use crate::render::raster::BatchRef;

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

/// Grows `(lo, hi)` by the integer position `p`.
#[inline]
fn grow(lo: &mut [i32; 3], hi: &mut [i32; 3], p: [i32; 3]) {
    for a in 0..3 {
        lo[a] = lo[a].min(p[a]);
        hi[a] = hi[a].max(p[a]);
    }
}

/// The node's payload as a quantized batch on the world grid `grid`: leaf points and the points
/// that inner-node voxels stand for, exactly. Fails for a node whose samples
/// span `2^30` grid units or more on an axis.
pub fn node_batch(node: &NodeView, grid: &Grid) -> Result<NodeBatch, NodeBatchError> {
    let cube = node.cube();
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
                grow(&mut lo, &mut hi, vx.pos);
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
            return Err(NodeBatchError::TooWide {
                key: node.key(),
                axis: ['x', 'y', 'z'][a],
                extent,
            });
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
                    push(vx.pos, vx.color);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::cube::Cube;
    use crate::octree::lod::testutil::{reference_batch, terrain_tree, GRID};
    use crate::octree::types::NodeId;
    use crate::octree::{Builder, BuilderConfig, Point};
    use crate::render::testutil::Rng;

    #[test]
    fn leaf_batches_are_exact_and_voxels_sit_in_their_cells() {
        let (_, snap) = terrain_tree(60_000, 1_500);
        assert!(snap.nodes().iter().any(|n| !n.is_leaf()) && snap.leaves().count() > 8);
        for (id, n) in snap.iter() {
            let b = node_batch(n, &GRID).unwrap();
            assert_eq!(b.len() as u64, n.point_count() + n.voxel_count(), "{id:?}");
            assert_eq!(b.colors.len(), b.len());
            assert!(b.grid.bits.iter().all(|&x| x as u32 <= MAX_BITS));
            let r = b.batch_ref(1234);
            assert_eq!((r.first_index, r.len(), r.grid), (1234, b.len(), b.grid));
            assert_eq!(r.bounds(), b.bounds());
            let decoded: Vec<[i32; 3]> = (0..b.len())
                .map(|i| b.grid.decode_exact([b.words[0][i], b.words[1][i], b.words[2][i]]))
                .collect();
            let bounds = b.bounds();
            for p in &decoded {
                let w = [0, 1, 2].map(|a| GRID.world(a, p[a] as i64));
                assert!(
                    (0..3).all(|a| bounds.min[a] <= w[a] && w[a] <= bounds.max[a]),
                    "{id:?} {p:?}"
                );
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
                    for ((v, p), c) in vx.iter().zip(&decoded).zip(&b.colors) {
                        assert!(cube.contains(*p), "{id:?} {p:?}");
                        assert_eq!(v.pos, *p, "{id:?}: the representative point, exactly");
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
        b.add_batch(&[
            Point { pos: [0, 0, 0], ..Point::default() },
            Point { pos: [i32::MAX, 3, 0], ..Point::default() },
        ])
        .unwrap();
        let snap = b.snapshot();
        let err = node_batch(snap.node(NodeId::ROOT), &GRID).unwrap_err();
        assert_eq!(
            err,
            NodeBatchError::TooWide { key: NodeKey::ROOT, axis: 'x', extent: i32::MAX as u64 }
        );
        assert!(err.to_string().contains("node r "), "{err}");

        // A tree over the whole i32 range: only nodes wider than 2^30 units can fail.
        let mut rng = Rng(9);
        let pts: Vec<Point> = (0..4_000)
            .map(|i| Point { pos: [0; 3].map(|_: i32| rng.next_u64() as i32), color: 0, record: i })
            .collect();
        let mut b = Builder::for_bounds(
            [i32::MIN; 3],
            [i32::MAX; 3],
            BuilderConfig { leaf_capacity: 200, ..BuilderConfig::default() },
        )
        .unwrap();
        b.add_batch(&pts).unwrap();
        let snap = b.snapshot();
        assert_eq!(snap.root_cube().size_log2, 32);
        assert!(matches!(
            node_batch(snap.node(NodeId::ROOT), &GRID),
            Err(NodeBatchError::TooWide { .. })
        ));
        for (id, n) in snap.iter().filter(|(_, n)| n.cube().size_log2 <= 30) {
            node_batch(n, &GRID).unwrap_or_else(|e| panic!("{id:?}: {e}"));
        }

        // A root cube overhanging i32::MAX: voxels are real points inside their cells.
        let lo = i32::MAX - 1000;
        let mut pts: Vec<Point> = (0..600)
            .map(|i| Point { pos: [lo + (i * 7919) % 1001; 3], color: i as u32, record: i as u64 })
            .collect();
        pts.push(Point { pos: [lo; 3], color: 1, record: 600 });
        pts.push(Point { pos: [i32::MAX; 3], color: 2, record: 601 });
        let mut b = Builder::for_bounds(
            [lo; 3],
            [i32::MAX; 3],
            BuilderConfig { leaf_capacity: 50, ..BuilderConfig::default() },
        )
        .unwrap();
        b.add_batch(&pts).unwrap();
        let snap = b.snapshot();
        let root = snap.node(NodeId::ROOT);
        assert!(root.cube().end()[0] > i32::MAX as i64 && !root.is_leaf());
        let nb = node_batch(root, &GRID).unwrap();
        let mut top = 0;
        for (v, i) in root.voxels().unwrap().iter().zip(0..) {
            let p = nb.grid.decode_exact([nb.words[0][i], nb.words[1][i], nb.words[2][i]]);
            assert_eq!(p, v.pos);
            assert!(
                pts.iter().any(|q| q.pos == p && q.record == v.record),
                "a voxel is a source point"
            );
            top += (p == [i32::MAX; 3]) as usize;
        }
        assert_eq!(top, 1);
    }
}
