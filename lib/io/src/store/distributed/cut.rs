//! The geometry of a plan's cut: the cube of a node of the tree's top, the partition cells
//! under it and the Morton code that orders the nodes of a level (the one-machine order).

use mortar_core::octree::{Cube, NodeKey};

/// The cube of `key` in `root`.
pub(super) fn cube_of(root: Cube, key: NodeKey) -> Cube {
    let size = 1i64 << (root.size_log2 - key.level);
    Cube {
        min: [0, 1, 2].map(|a| root.min[a] + key.index[a] as i64 * size),
        size_log2: root.size_log2 - key.level,
    }
}

/// The partition cells (at `depth`) under `key`.
pub(super) fn cells_of(key: NodeKey, depth: u8) -> std::ops::Range<usize> {
    let below = 3 * (depth - key.level) as u32;
    let start = (morton(key.index, key.level) as usize) << below;
    start..start + (1usize << below)
}

/// The Morton code of a node's index at `level` (x in the lowest bit of each triple: octant
/// order, so codes sort a level depth first).
pub(super) fn morton(index: [u32; 3], level: u8) -> u128 {
    let mut c = 0u128;
    for b in (0..level as u32).rev() {
        for a in 0..3 {
            c = c << 1 | ((index[2 - a] >> b) & 1) as u128;
        }
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_orders_a_level_depth_first() {
        // children of the root in octant order
        let kids: Vec<u128> = (0..8)
            .map(|o| {
                let k = NodeKey::ROOT.child(o);
                morton(k.index, 1)
            })
            .collect();
        assert_eq!(kids, (0..8).collect::<Vec<u128>>());
        // grandchildren: all of child 0 before any of child 1
        let k = NodeKey::ROOT.child(1).child(0);
        assert_eq!(morton(k.index, 2), 8);
        assert_eq!(cells_of(NodeKey::ROOT.child(3), 2), 24..32);
    }
}
