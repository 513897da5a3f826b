//! Batch quantization (paper 003 §3.3): coordinates become 30-bit fixed-point numbers relative to
//! the batch's bounding box, split into a coarse, a medium and a fine 10-bit word per axis, each
//! word-triple packed into a `u32` as `x | y << 10 | z << 20`.
//!
//! mortar quantizes on the source's integer grid, so the round trip is exact: on each axis a batch
//! stores the smallest integer coordinate `min` and the number of bits `bits` (0-30) that its extent
//! `max - min` needs. A point's offset `q = X - min` (< 2^bits) is placed in the top bits of the
//! 30-bit number, `q30 = q << (30 - bits)`. The coarse word is therefore always the position at
//! 1/1024 of the batch extent, as in the paper, and `X = min + (q30 >> (30 - bits))` gives the
//! integer back bit for bit. Batches whose extent needs more than 30 bits are split by
//! [`crate::batching`], never stored lossily.
//!
//! Rendering decodes `q30` from 1, 2 or 3 words ([`Precision`]); missing low bits are replaced by
//! the middle of the cell, so the error of a decode is at most [`BatchGrid::error_bound`].

/// Largest number of bits per axis a batch may use.
pub const MAX_BITS: u32 = 30;

/// How many of the three words a decode reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Precision {
    /// Coarse word only: 10 bits per axis.
    Bits10 = 1,
    /// Coarse and medium words: 20 bits per axis.
    Bits20 = 2,
    /// All three words: 30 bits per axis, exact.
    Bits30 = 3,
}

impl Precision {
    pub fn bits(self) -> u32 {
        self as u32 * 10
    }
    pub fn words(self) -> usize {
        self as usize
    }
}

/// The quantization frame of one batch, per axis, in the source's integer grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BatchGrid {
    /// Smallest integer coordinate of the batch.
    pub min: [i32; 3],
    /// Bits the extent needs, 0..=30.
    pub bits: [u8; 3],
}

/// Bits needed to store offsets `0..=extent`.
#[inline]
pub fn bits_for_extent(extent: u64) -> u32 {
    64 - extent.leading_zeros()
}

impl BatchGrid {
    /// The frame of integer bounds `[min, max]`; `None` if an axis needs more than 30 bits.
    pub fn for_bounds(min: [i32; 3], max: [i32; 3]) -> Option<BatchGrid> {
        let mut bits = [0u8; 3];
        for a in 0..3 {
            let extent = (max[a] as i64 - min[a] as i64).max(0) as u64;
            let b = bits_for_extent(extent);
            if b > MAX_BITS {
                return None;
            }
            bits[a] = b as u8;
        }
        Some(BatchGrid { min, bits })
    }

    /// The 30-bit quantized coordinate of integer coordinate `p` (which must lie in the frame).
    #[inline]
    pub fn q30(&self, p: [i32; 3]) -> [u32; 3] {
        let mut q = [0u32; 3];
        for a in 0..3 {
            let d = (p[a] as i64 - self.min[a] as i64) as u32;
            q[a] = if self.bits[a] == 0 { 0 } else { d << (MAX_BITS - self.bits[a] as u32) };
        }
        q
    }

    /// The three packed words (coarse, medium, fine) of integer coordinate `p`.
    #[inline]
    pub fn encode(&self, p: [i32; 3]) -> [u32; 3] {
        split_words(self.q30(p))
    }

    /// The exact integer coordinate from all three words.
    #[inline]
    pub fn decode_exact(&self, words: [u32; 3]) -> [i32; 3] {
        let q = join_words(words, Precision::Bits30);
        let mut p = [0i32; 3];
        for a in 0..3 {
            let off = if self.bits[a] == 0 { 0 } else { q[a] >> (MAX_BITS - self.bits[a] as u32) };
            p[a] = (self.min[a] as i64 + off as i64) as i32;
        }
        p
    }

    /// The position in integer-grid units relative to `min`, from the first `precision.words()`
    /// words (words not loaded may hold anything). Where the batch needs more bits than were loaded,
    /// the unknown low bits are replaced by the middle of their range.
    #[inline]
    pub fn decode_relative(&self, words: [u32; 3], precision: Precision) -> [f64; 3] {
        let q = join_words(words, precision);
        let mut r = [0f64; 3];
        for a in 0..3 {
            let bits = self.bits[a] as u32;
            if bits == 0 {
                continue;
            }
            let known = q[a] >> (MAX_BITS - bits);
            let missing = bits.saturating_sub(precision.bits());
            r[a] = known as f64 + ((1u64 << missing) - 1) as f64 * 0.5;
        }
        r
    }

    /// Largest error of [`decode_relative`](Self::decode_relative) on each axis, in integer-grid
    /// units: `(2^m - 1) / 2` where `m = bits - precision_bits` low bits are unknown; 0 when the
    /// loaded words hold every bit the batch uses.
    pub fn error_bound(&self, precision: Precision) -> [f64; 3] {
        let mut e = [0f64; 3];
        for a in 0..3 {
            let missing = (self.bits[a] as u32).saturating_sub(precision.bits());
            e[a] = ((1u64 << missing) - 1) as f64 * 0.5;
        }
        e
    }
}

/// Splits 30-bit numbers into the coarse, medium and fine packed words.
#[inline]
pub fn split_words(q: [u32; 3]) -> [u32; 3] {
    let word = |shift: u32| -> u32 {
        ((q[0] >> shift) & 0x3ff)
            | (((q[1] >> shift) & 0x3ff) << 10)
            | (((q[2] >> shift) & 0x3ff) << 20)
    };
    [word(20), word(10), word(0)]
}

/// Joins the first `precision.words()` packed words back into 30-bit numbers (missing bits 0).
#[inline]
pub fn join_words(words: [u32; 3], precision: Precision) -> [u32; 3] {
    let mut q = [0u32; 3];
    for (i, &w) in words.iter().enumerate().take(precision.words()) {
        let shift = 20 - 10 * i as u32;
        for (a, qa) in q.iter_mut().enumerate() {
            *qa |= ((w >> (10 * a)) & 0x3ff) << shift;
        }
    }
    q
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn grid_and_point() -> impl Strategy<Value = (BatchGrid, [i32; 3])> {
        (prop::array::uniform3(any::<i32>()), prop::array::uniform3(0u32..=30)).prop_flat_map(
            |(min, bits)| {
                let mut lo = [0i32; 3];
                let mut bits8 = [0u8; 3];
                for a in 0..3 {
                    // keep min + 2^bits - 1 inside i32
                    let span = (1i64 << bits[a]) - 1;
                    lo[a] = (min[a] as i64).min(i32::MAX as i64 - span) as i32;
                    bits8[a] = bits[a] as u8;
                }
                let g = BatchGrid { min: lo, bits: bits8 };
                let pts = (0..3)
                    .map(|a| {
                        let span = (1i64 << bits[a]) - 1;
                        (lo[a] as i64..=lo[a] as i64 + span).prop_map(|v| v as i32)
                    })
                    .collect::<Vec<_>>();
                (Just(g), pts).prop_map(|(g, p)| (g, [p[0], p[1], p[2]]))
            },
        )
    }

    proptest! {
        #[test]
        fn exact_roundtrip((g, p) in grid_and_point()) {
            prop_assert_eq!(g.decode_exact(g.encode(p)), p);
        }

        #[test]
        fn error_within_bound((g, p) in grid_and_point()) {
            let words = g.encode(p);
            for prec in [Precision::Bits10, Precision::Bits20, Precision::Bits30] {
                let mut w = words;
                for x in w.iter_mut().skip(prec.words()) { *x = 0; }
                let r = g.decode_relative(w, prec);
                let bound = g.error_bound(prec);
                for a in 0..3 {
                    let truth = p[a] as i64 - g.min[a] as i64;
                    let err = (r[a] - truth as f64).abs();
                    prop_assert!(err <= bound[a] + 1e-9, "axis {} prec {:?} err {} bound {} bits {}", a, prec, err, bound[a], g.bits[a]);
                }
            }
        }
    }

    #[test]
    fn zero_extent_axes_and_single_points() {
        let g = BatchGrid::for_bounds([5, -7, i32::MAX], [5, -7, i32::MAX]).unwrap();
        assert_eq!(g.bits, [0, 0, 0]);
        let w = g.encode([5, -7, i32::MAX]);
        assert_eq!(w, [0, 0, 0]);
        assert_eq!(g.decode_exact(w), [5, -7, i32::MAX]);
        assert_eq!(g.error_bound(Precision::Bits10), [0.0; 3]);
    }

    #[test]
    fn extent_limits() {
        assert!(BatchGrid::for_bounds([0; 3], [(1 << 30) - 1; 3]).is_some());
        assert!(BatchGrid::for_bounds([0; 3], [1 << 30, 0, 0]).is_none());
        assert!(BatchGrid::for_bounds([i32::MIN; 3], [i32::MAX; 3]).is_none());
        let g = BatchGrid::for_bounds([i32::MIN, 0, 0], [i32::MIN + 1000, 0, 0]).unwrap();
        assert_eq!(g.decode_exact(g.encode([i32::MIN + 999, 0, 0])), [i32::MIN + 999, 0, 0]);
    }

    #[test]
    fn coarse_word_is_top_ten_bits() {
        // A batch of extent 1023 units needs 10 bits, so the coarse word alone is exact.
        let g = BatchGrid::for_bounds([100, 100, 100], [1123, 1123, 1123]).unwrap();
        assert_eq!(g.bits, [10, 10, 10]);
        let w = g.encode([1123, 100, 600]);
        assert_eq!(w[0], 1023 | (500 << 20));
        assert_eq!(w[1], 0);
        assert_eq!(w[2], 0);
        assert_eq!(g.error_bound(Precision::Bits10), [0.0; 3]);
    }
}
