//! 3-D Morton (z-order) codes, 21 bits per axis, over the integer coordinate grid of the merged
//! inputs (paper 003 §3.1: Morton order gives batches the locality that culling and quantization
//! need).
//!
//! The grid is the LAS integer grid (`X = round((x - offset) / scale)`), so codes never depend on
//! floating point. [`MortonGrid`] maps integer coordinates to the 21-bit cells of a code: it
//! subtracts the grid origin (the minimum of the data) and shifts right by the smallest amount that
//! makes the largest extent fit into 21 bits. Coordinates outside the grid's box are clamped, so
//! every point gets a code and the order stays total and deterministic.

/// Bits per axis in a Morton code.
pub const BITS_PER_AXIS: u32 = 21;
const AXIS_MAX: u64 = (1 << BITS_PER_AXIS) - 1;

/// Spreads the low 21 bits of `v` so that bit i lands on bit 3i.
#[inline]
pub fn spread3(v: u64) -> u64 {
    let mut x = v & AXIS_MAX;
    x = (x | (x << 32)) & 0x001f_0000_0000_ffff;
    x = (x | (x << 16)) & 0x001f_0000_ff00_00ff;
    x = (x | (x << 8)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x << 4)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x << 2)) & 0x1249_2492_4924_9249;
    x
}

/// Inverse of [`spread3`].
#[inline]
pub fn compact3(v: u64) -> u64 {
    let mut x = v & 0x1249_2492_4924_9249;
    x = (x | (x >> 2)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x >> 4)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x >> 8)) & 0x001f_0000_ff00_00ff;
    x = (x | (x >> 16)) & 0x001f_0000_0000_ffff;
    x = (x | (x >> 32)) & AXIS_MAX;
    x
}

/// Interleaves three 21-bit cell coordinates: x on bit 0, y on bit 1, z on bit 2.
#[inline]
pub fn encode(x: u32, y: u32, z: u32) -> u64 {
    spread3(x as u64) | (spread3(y as u64) << 1) | (spread3(z as u64) << 2)
}

/// The full-resolution Morton code of three 32-bit coordinates (96 bits: x on bit 0, y on bit 1,
/// z on bit 2 of each triple): the order the store's engines give points (an offset from a
/// cube's corner), whose low 63 bits are [`encode`] of the coordinates' low 21 bits.
#[inline]
pub fn encode96(u: [u32; 3]) -> u128 {
    let hi = encode(u[0] >> 21, u[1] >> 21, u[2] >> 21) as u128;
    let lo = encode(u[0] & 0x1f_ffff, u[1] & 0x1f_ffff, u[2] & 0x1f_ffff);
    hi << 63 | lo as u128
}

/// Splits a code back into its three cell coordinates.
#[inline]
pub fn decode(code: u64) -> [u32; 3] {
    [compact3(code) as u32, compact3(code >> 1) as u32, compact3(code >> 2) as u32]
}

/// The mapping from integer grid coordinates to Morton cells.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MortonGrid {
    /// Integer coordinate of cell 0 on each axis (the data's minimum).
    pub origin: [i64; 3],
    /// Right shift applied to `coordinate - origin` (the same on every axis, so cells are cubes).
    pub shift: u32,
}

impl MortonGrid {
    /// The grid for data whose integer coordinates lie in `[min, max]` (inclusive).
    pub fn for_bounds(min: [i64; 3], max: [i64; 3]) -> MortonGrid {
        let extent = (0..3).map(|a| (max[a] - min[a]).max(0) as u64).max().unwrap_or(0);
        let bits = 64 - extent.leading_zeros();
        let shift = bits.saturating_sub(BITS_PER_AXIS);
        MortonGrid { origin: min, shift }
    }

    /// The Morton code of an integer coordinate.
    #[inline]
    pub fn code(&self, p: [i64; 3]) -> u64 {
        let cell = |a: usize| -> u32 {
            let d = p[a] - self.origin[a];
            if d <= 0 {
                0
            } else {
                ((d as u64) >> self.shift).min(AXIS_MAX) as u32
            }
        };
        encode(cell(0), cell(1), cell(2))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn small_codes() {
        assert_eq!(encode(0, 0, 0), 0);
        assert_eq!(encode(1, 0, 0), 1);
        assert_eq!(encode(0, 1, 0), 2);
        assert_eq!(encode(0, 0, 1), 4);
        assert_eq!(encode(1, 1, 1), 7);
        assert_eq!(encode(2, 0, 0), 8);
        assert_eq!(encode(AXIS_MAX as u32, AXIS_MAX as u32, AXIS_MAX as u32), (1u64 << 63) - 1);
    }

    #[test]
    fn grid_shift_fits_extent() {
        let g = MortonGrid::for_bounds([0, 0, 0], [(1 << 21) - 1, 5, 5]);
        assert_eq!(g.shift, 0);
        let g = MortonGrid::for_bounds([0, 0, 0], [1 << 21, 5, 5]);
        assert_eq!(g.shift, 1);
        let g = MortonGrid::for_bounds([i32::MIN as i64; 3], [i32::MAX as i64; 3]);
        assert_eq!(g.shift, 11);
        assert_eq!(g.code([i32::MAX as i64; 3]), (1u64 << 63) - 1);
        // clamped outside the box
        assert_eq!(g.code([i64::MIN / 2; 3]), 0);
    }

    proptest! {
        #[test]
        fn roundtrip(x in 0u32..(1 << 21), y in 0u32..(1 << 21), z in 0u32..(1 << 21)) {
            prop_assert_eq!(decode(encode(x, y, z)), [x, y, z]);
        }

        #[test]
        fn monotone_per_axis(x in 0u32..((1 << 21) - 1), y in 0u32..(1 << 21), z in 0u32..(1 << 21)) {
            prop_assert!(encode(x + 1, y, z) > encode(x, y, z));
            prop_assert!(encode(y, x + 1, z) > encode(y, x, z));
            prop_assert!(encode(y, z, x + 1) > encode(y, z, x));
        }
    }
}
