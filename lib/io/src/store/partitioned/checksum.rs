//! The partitioned engine's checksums: of the run files, the tables and every payload written,
//! so that `--resume` takes only what reached the disk as it was written.

use crate::error::{Error, Result};
use crate::store::format::NODES_FILE;
use crate::store::writer::StoreWriter;
use rayon::prelude::*;

/// [`checksum`] of the `len` bytes of `nodes.bin` at `off` (a payload written in slices), read
/// back a block at a time.
pub(super) fn checksum_at(w: &StoreWriter, off: u64, len: u64) -> Result<u64> {
    use std::os::unix::fs::FileExt;
    let path = w.dir.join(NODES_FILE);
    let read = |at: u64, n: usize| -> Result<Vec<u8>> {
        let mut b = vec![0u8; n];
        w.reader.read_exact_at(&mut b, off + at).map_err(|e| Error::io(&path, e))?;
        Ok(b)
    };
    if len <= 1 << 20 {
        return Ok(checksum(&read(0, len as usize)?));
    }
    let parts: Vec<u64> = (0..len.div_ceil(1 << 20))
        .into_par_iter()
        .map(|k| Ok(checksum_block(&read(k << 20, ((len - (k << 20)).min(1 << 20)) as usize)?)))
        .collect::<Result<_>>()?;
    Ok(checksum_block(bytemuck::cast_slice(&parts)))
}

fn checksum_block(b: &[u8]) -> u64 {
    let mut h = 0x243f_6a88_85a3_08d3u64 ^ b.len() as u64;
    let mut words = b.chunks_exact(8);
    for w in &mut words {
        h = (h ^ u64::from_le_bytes(w.try_into().expect("8 bytes")))
            .wrapping_mul(0x9e37_79b9_7f4a_7c15)
            .rotate_left(29);
    }
    for &x in words.remainder() {
        h = (h ^ x as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15).rotate_left(29);
    }
    h
}

/// A fast 64-bit checksum (8 bytes per step), in parallel over 1 MiB blocks for large inputs.
pub(super) fn checksum(b: &[u8]) -> u64 {
    if b.len() <= 1 << 20 {
        return checksum_block(b);
    }
    let parts: Vec<u64> = b.par_chunks(1 << 20).map(checksum_block).collect();
    checksum_block(bytemuck::cast_slice(&parts))
}

/// A running hash of a visit's leaf ranks (the log keeps it, so that `--resume` takes only
/// ranks that reached the disk as they were written): the visit's rank `i` goes into lane
/// `i % 4`, so that the multiplications of consecutive ranks do not wait on one another, and
/// the hash is the same however the ranks are handed to [`add`](Self::add).
#[derive(Clone, Copy)]
pub(super) struct RankHash {
    lanes: [u64; 4],
    n: u64,
}

impl Default for RankHash {
    fn default() -> Self {
        let s = 0x1319_8a2e_0370_7344u64;
        RankHash { lanes: [s, s ^ 1, s ^ 2, s ^ 3], n: 0 }
    }
}

impl RankHash {
    #[inline]
    fn mix(h: u64, r: u64) -> u64 {
        (h ^ r).wrapping_mul(0x9e37_79b9_7f4a_7c15).rotate_left(29)
    }

    /// Adds the visit's next ranks.
    pub(super) fn add(&mut self, ranks: &[u64]) {
        let lead = ((4 - self.n % 4) % 4).min(ranks.len() as u64) as usize;
        for &r in &ranks[..lead] {
            let l = (self.n % 4) as usize;
            self.lanes[l] = Self::mix(self.lanes[l], r);
            self.n += 1;
        }
        let mut q = self.lanes;
        let mut groups = ranks[lead..].chunks_exact(4);
        for g in &mut groups {
            for l in 0..4 {
                q[l] = Self::mix(q[l], g[l]);
            }
        }
        self.lanes = q;
        self.n += (ranks.len() - lead - groups.remainder().len()) as u64;
        for &r in groups.remainder() {
            let l = (self.n % 4) as usize;
            self.lanes[l] = Self::mix(self.lanes[l], r);
            self.n += 1;
        }
    }

    /// The hash of the ranks added.
    pub(super) fn finish(&self) -> u64 {
        self.lanes.iter().fold(self.n, |h, &l| Self::mix(h, l))
    }
}

#[cfg(test)]
mod tests {
    use super::RankHash;

    #[test]
    fn a_rank_hash_is_the_same_however_the_ranks_come() {
        let ranks: Vec<u64> = (0..1003u64).map(|i| i.wrapping_mul(0x9e37_79b9) % 5000).collect();
        let mut whole = RankHash::default();
        whole.add(&ranks);
        for cuts in [vec![1, 2, 3, 500], vec![4, 8, 999], vec![0, 0, 7, 1002], vec![333, 334]] {
            let mut h = RankHash::default();
            let mut at = 0;
            for c in cuts.into_iter().chain([ranks.len()]) {
                h.add(&ranks[at..c]);
                at = c;
            }
            assert_eq!(h.finish(), whole.finish());
        }
        // Another rank, one rank fewer, two swapped: another hash.
        let mut other = ranks.clone();
        other[500] ^= 1;
        let mut fewer = RankHash::default();
        fewer.add(&ranks[..1002]);
        other.swap(10, 11);
        let mut h = RankHash::default();
        h.add(&other);
        assert_ne!(h.finish(), whole.finish());
        assert_ne!(fewer.finish(), whole.finish());
        let mut swapped = ranks.clone();
        swapped.swap(10, 14);
        let mut h = RankHash::default();
        h.add(&swapped);
        assert_ne!(h.finish(), whole.finish());
    }
}
