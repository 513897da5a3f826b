//! Octree cubes in the LAS integer grid and node keys (paper 004 §3.1).

use super::types::{GRID_LOG2, GRID_SIZE};
use crate::grid::Grid;
use crate::render::math::Aabb;

/// An axis-aligned cube of the integer grid: the integer coordinates `min[a] <= p[a] < min[a] +
/// 2^size_log2`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Cube {
    /// Smallest integer coordinate on each axis.
    pub min: [i64; 3],
    /// `log2` of the edge length in grid units.
    pub size_log2: u8,
}

impl Cube {
    /// The cube at `min` with edge `2^size_log2`.
    pub fn new(min: [i64; 3], size_log2: u8) -> Cube {
        Cube { min, size_log2 }
    }

    /// The smallest power-of-two cube at `min` that holds every integer coordinate of the
    /// inclusive bounds `[min, max]` (a dataset's bounds). Empty bounds (`max < min`) give a cube
    /// of one grid unit.
    pub fn covering(min: [i32; 3], max: [i32; 3]) -> Cube {
        let extent =
            (0..3).map(|a| (max[a] as i64 - min[a] as i64).max(0) as u64).max().unwrap_or(0);
        let size_log2 = (64 - extent.leading_zeros()) as u8;
        Cube { min: min.map(|v| v as i64), size_log2 }
    }

    /// Edge length in grid units.
    #[inline]
    pub fn size(&self) -> u64 {
        1u64 << self.size_log2
    }

    /// The first integer coordinate past the cube on each axis (exclusive maximum).
    pub fn end(&self) -> [i64; 3] {
        self.min.map(|m| m + self.size() as i64)
    }

    /// Whether the integer coordinate `p` lies in the cube.
    #[inline]
    pub fn contains(&self, p: [i32; 3]) -> bool {
        self.contains_i64(p.map(|v| v as i64))
    }

    /// [`contains`](Self::contains) for a coordinate given as `i64`.
    #[inline]
    pub fn contains_i64(&self, p: [i64; 3]) -> bool {
        (0..3).all(|a| (p[a].wrapping_sub(self.min[a]) as u64) < self.size())
    }

    /// Offset of `p` from `min` (which must be inside the cube).
    #[inline]
    pub(crate) fn offset(&self, p: [i32; 3]) -> [u32; 3] {
        [
            (p[0] as i64 - self.min[0]) as u32,
            (p[1] as i64 - self.min[1]) as u32,
            (p[2] as i64 - self.min[2]) as u32,
        ]
    }

    /// The octant `x | y << 1 | z << 2` of `p` (inside the cube; the cube at least 2 units wide).
    #[inline]
    pub fn octant_of(&self, p: [i32; 3]) -> usize {
        debug_assert!(self.size_log2 >= 1);
        let o = self.offset(p);
        let s = self.size_log2 as u32 - 1;
        ((o[0] >> s) & 1 | ((o[1] >> s) & 1) << 1 | ((o[2] >> s) & 1) << 2) as usize
    }

    /// The child cube of octant `octant` (`0..8`).
    pub fn child(&self, octant: usize) -> Cube {
        debug_assert!(self.size_log2 >= 1 && octant < 8);
        let half = (self.size() / 2) as i64;
        let mut min = self.min;
        for (a, m) in min.iter_mut().enumerate() {
            if octant >> a & 1 == 1 {
                *m += half;
            }
        }
        Cube { min, size_log2: self.size_log2 - 1 }
    }

    /// `log2` of a voxel's edge in grid units when this cube is an inner node, or `None` when the
    /// cube is narrower than the 128³ grid.
    #[inline]
    pub fn voxel_size_log2(&self) -> Option<u8> {
        self.size_log2.checked_sub(GRID_LOG2)
    }

    /// The 128³-grid cell of `p` (inside the cube; the cube at least 128 units wide).
    #[inline]
    pub fn voxel_of(&self, p: [i32; 3]) -> [u8; 3] {
        let s = (self.size_log2 - GRID_LOG2) as u32;
        self.offset(p).map(|o| (o >> s) as u8)
    }

    /// Smallest integer coordinate of the voxel cell `coord` (the cube at least 128 units wide);
    /// the cell is `2^voxel_size_log2` units wide.
    pub fn voxel_min(&self, coord: [u8; 3]) -> [i64; 3] {
        let s = (self.size_log2 - GRID_LOG2) as u32;
        debug_assert!(coord.iter().all(|&c| (c as u32) < GRID_SIZE));
        [0, 1, 2].map(|a| self.min[a] + ((coord[a] as i64) << s))
    }

    /// The world-space box of the cube on the LAS grid `grid`: from the world position of `min`
    /// to that of `min + size` on each axis (ordered, so negative scales work too).
    pub fn world_bounds(&self, grid: &Grid) -> Aabb {
        let mut min = [0.0; 3];
        let mut max = [0.0; 3];
        for a in 0..3 {
            let lo = grid.world(a, self.min[a]);
            let hi = grid.world(a, self.min[a] + self.size() as i64);
            min[a] = lo.min(hi);
            max[a] = lo.max(hi);
        }
        Aabb::new(min, max)
    }
}

/// A node's place in the tree: its level (root 0) and its cell index at that level, so that its
/// cube is `root.min + index * (root.size >> level)` with edge `root.size >> level`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct NodeKey {
    /// Depth below the root.
    pub level: u8,
    /// Cell index at `level` on each axis, in `0..2^level`.
    pub index: [u32; 3],
}

impl NodeKey {
    /// The root's key.
    pub const ROOT: NodeKey = NodeKey { level: 0, index: [0; 3] };

    /// The key of child `octant` (`x | y << 1 | z << 2`).
    pub fn child(&self, octant: usize) -> NodeKey {
        debug_assert!(octant < 8);
        let index = [0, 1, 2].map(|a| self.index[a] << 1 | (octant as u32 >> a & 1));
        NodeKey { level: self.level + 1, index }
    }

    /// The parent's key, `None` for the root.
    pub fn parent(&self) -> Option<NodeKey> {
        (self.level > 0)
            .then(|| NodeKey { level: self.level - 1, index: self.index.map(|i| i >> 1) })
    }

    /// The octant of this node in its parent (0 for the root).
    pub fn octant(&self) -> usize {
        (0..3).map(|a| ((self.index[a] & 1) as usize) << a).sum()
    }

    /// The octants from the root down to this node (`level` of them).
    pub fn path(&self) -> impl Iterator<Item = u8> + '_ {
        (0..self.level).rev().map(move |shift| {
            // checked: a key read from a damaged store may claim 32+ levels (fuzz regression
            // key-name-deep-level)
            (0..3)
                .map(|a| ((self.index[a].checked_shr(shift as u32).unwrap_or(0) & 1) as u8) << a)
                .sum::<u8>()
        })
    }

    /// A printable name: `r` followed by the octant digits of [`path`](Self::path), e.g. `r07`.
    pub fn name(&self) -> String {
        let mut s = String::with_capacity(1 + self.level as usize);
        s.push('r');
        s.extend(self.path().map(|o| char::from(b'0' + o)));
        s
    }

    /// This node's cube in the tree of root cube `root`.
    pub fn cube_in(&self, root: Cube) -> Cube {
        let size_log2 = root.size_log2 - self.level;
        let min = [0, 1, 2].map(|a| root.min[a] + ((self.index[a] as i64) << size_log2));
        Cube { min, size_log2 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn covering_is_smallest_power_of_two() {
        assert_eq!(Cube::covering([0; 3], [0; 3]).size_log2, 0);
        assert_eq!(Cube::covering([0; 3], [1, 0, 0]).size_log2, 1);
        assert_eq!(Cube::covering([0; 3], [3, 0, 0]).size_log2, 2);
        assert_eq!(Cube::covering([0; 3], [0, 4, 0]).size_log2, 3);
        assert_eq!(Cube::covering([-5, 0, 0], [122, 0, 0]).size_log2, 7);
        assert_eq!(Cube::covering([-5, 0, 0], [123, 0, 0]).size_log2, 8);
        let full = Cube::covering([i32::MIN; 3], [i32::MAX; 3]);
        assert_eq!(full.size_log2, 32);
        assert!(full.contains([i32::MIN; 3]) && full.contains([i32::MAX; 3]));
        // empty bounds
        assert_eq!(Cube::covering([5; 3], [0; 3]).size_log2, 0);
    }

    #[test]
    fn contains_edges() {
        let c = Cube::new([-4, 0, 10], 3);
        assert!(c.contains([-4, 0, 10]));
        assert!(c.contains([3, 7, 17]));
        assert!(!c.contains([4, 0, 10]));
        assert!(!c.contains([-5, 0, 10]));
        assert!(!c.contains([0, 0, 18]));
        assert_eq!(c.end(), [4, 8, 18]);
    }

    #[test]
    fn key_names_and_paths() {
        let k = NodeKey::ROOT.child(0).child(7).child(2);
        assert_eq!(k.name(), "r072");
        assert_eq!(k.path().collect::<Vec<_>>(), vec![0, 7, 2]);
        assert_eq!(k.octant(), 2);
        assert_eq!(k.parent().unwrap().name(), "r07");
        assert_eq!(NodeKey::ROOT.name(), "r");
        assert_eq!(NodeKey::ROOT.parent(), None);
    }

    #[test]
    fn world_bounds_follow_grid() {
        let g = Grid { scale: [0.01, 0.01, -0.5], offset: [100.0, 0.0, 0.0] };
        let b = Cube::new([0, 100, 2], 2).world_bounds(&g);
        assert_eq!(b.min, [100.0, 1.0, -3.0]);
        assert_eq!(b.max, [100.04, 1.04, -1.0]);
    }

    proptest! {
        #![proptest_config(ProptestConfig { failure_persistence: None, ..ProptestConfig::default() })]

        #[test]
        fn child_cubes_partition_the_parent(
            min in prop::array::uniform3(-1000i64..1000),
            log2 in 2u8..12,
            p in prop::array::uniform3(0u32..4096),
        ) {
            let c = Cube::new(min, log2);
            let p = [0, 1, 2].map(|a| (min[a] + (p[a] as i64 % c.size() as i64)) as i32);
            prop_assert!(c.contains(p));
            let o = c.octant_of(p);
            prop_assert!(c.child(o).contains(p));
            for other in (0..8).filter(|&x| x != o) {
                prop_assert!(!c.child(other).contains(p));
            }
            // keys agree with cubes
            let key = NodeKey::ROOT.child(o);
            prop_assert_eq!(key.cube_in(c), c.child(o));
            prop_assert_eq!(key.child(3).cube_in(c), c.child(o).child(3));
            if log2 >= GRID_LOG2 {
                let v = c.voxel_of(p);
                let vmin = c.voxel_min(v);
                let vs = 1i64 << c.voxel_size_log2().unwrap();
                prop_assert!((0..3).all(|a| vmin[a] <= p[a] as i64 && (p[a] as i64) < vmin[a] + vs));
                // the cell's upper bit is the octant
                prop_assert_eq!((v[0] >> 6 | (v[1] >> 6) << 1 | (v[2] >> 6) << 2) as usize, o);
            }
        }
    }
}
