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

/// The seed of [`rank_hash`]: the hash of no ranks.
pub(super) const RANK_SEED: u64 = 0x1319_8a2e_0370_7344;

/// Folds `ranks` into the running hash `h` of a visit's leaf ranks (the log keeps it, so that
/// `--resume` takes only ranks that reached the disk as they were written).
pub(super) fn rank_hash(h: u64, ranks: &[u64]) -> u64 {
    ranks.iter().fold(h, |h, &r| (h ^ r).wrapping_mul(0x9e37_79b9_7f4a_7c15).rotate_left(29))
}
