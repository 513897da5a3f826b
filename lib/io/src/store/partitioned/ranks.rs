//! The partitioned engine's arrival ranks (`arrival.bin`, [`crate::store::arrival`]): each
//! finished visit appends its leaves' ranks, in the file's order (leaves depth first, each
//! leaf's points in its coded order), to `ranks.bin` in `.partition/` (8 bytes a point, native
//! order), and the end of the build codes them into `arrival.bin` a block at a time. The walk
//! visits the leaves in Morton order of their cubes, so the file is the sorted engine's.
//!
//! `--resume`: the log keeps the hash of each visit's ranks ([`super::checksum::RankHash`]);
//! a visit whose ranks did not reach the disk as written is redone, and the file is cut after
//! the ranks of the visits kept.

use super::checksum::RankHash;
use crate::error::{Error, Result};
use crate::store::arrival::{self, ColorMaxima, DeclaredBox};
use rayon::prelude::*;
use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// The ranks file's name in `.partition/`.
pub(super) const RANKS: &str = "ranks.bin";

/// The ranks file being written.
pub(super) struct RankLog {
    file: std::io::BufWriter<std::fs::File>,
    path: PathBuf,
    /// Where each piece of the dataset begins among all records (arrival number
    /// `piece << 32 | index` to rank).
    starts: Vec<u64>,
    /// The hash of the ranks appended since the last [`take_hash`](Self::take_hash).
    pending: RankHash,
    /// Ranks in the file.
    pub(super) len: u64,
}

impl RankLog {
    /// Opens the ranks file in `state`, keeping its first `keep` ranks (those of the visits a
    /// resumed build kept; 0 for a new one); `pieces` are the dataset's pieces' point counts.
    pub(super) fn open(state: &Path, pieces: impl Iterator<Item = u64>, keep: u64) -> Result<Self> {
        let path = state.join(RANKS);
        let file = std::fs::OpenOptions::new()
            .create(true)
            .read(true)
            .write(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        file.set_len(keep * 8).map_err(|e| Error::io(&path, e))?;
        let mut f = std::io::BufWriter::with_capacity(1 << 20, file);
        use std::io::Seek;
        f.seek(std::io::SeekFrom::End(0)).map_err(|e| Error::io(&path, e))?;
        let mut starts = vec![0u64];
        for n in pieces {
            starts.push(starts.last().expect("one start") + n);
        }
        Ok(RankLog { file: f, path, starts, pending: RankHash::default(), len: keep })
    }

    /// Appends the leaf points whose arrival numbers are `arrival` (in the file's order),
    /// turning them into ranks in place.
    pub(super) fn push(&mut self, arrival: &mut [u64]) -> Result<()> {
        let starts = &self.starts;
        arrival.par_chunks_mut(1 << 16).try_for_each(|c| {
            for a in c.iter_mut() {
                let start = starts.get((*a >> 32) as usize).ok_or_else(|| Error::Internal {
                    path: self.path.clone(),
                    what: "an arrival number names a piece the dataset does not have",
                })?;
                *a = start + (*a & 0xffff_ffff);
            }
            Ok::<(), Error>(())
        })?;
        self.pending.add(arrival);
        self.file.write_all(bytemuck::cast_slice(arrival)).map_err(|e| Error::io(&self.path, e))?;
        self.len += arrival.len() as u64;
        Ok(())
    }

    /// The hash of the ranks appended since the last call (what the log keeps of a visit).
    pub(super) fn take_hash(&mut self) -> u64 {
        std::mem::take(&mut self.pending).finish()
    }

    /// Codes the ranks into the store's `arrival.bin` in `dir` (the store's `points` leaf
    /// points; the inputs' declared box and colour maxima), as many blocks at once as
    /// `memory` holds.
    pub(super) fn write_arrival(
        mut self,
        dir: &Path,
        points: u64,
        declared: DeclaredBox,
        colors: ColorMaxima,
        memory: u64,
    ) -> Result<()> {
        self.file.flush().map_err(|e| Error::io(&self.path, e))?;
        if self.len != points {
            return Err(Error::Internal {
                path: self.path.clone(),
                what: "the ranks file holds another count than the store's leaves",
            });
        }
        let (file, path) = (self.file.get_ref(), &self.path);
        let fill = |r: std::ops::Range<usize>, out: &mut Vec<u64>| -> Result<()> {
            out.resize(r.len(), 0);
            file.read_exact_at(bytemuck::cast_slice_mut(out), r.start as u64 * 8)
                .map_err(|e| Error::io(path, e))
        };
        let at_once = (memory / arrival::BLOCK_BYTES).clamp(1, arrival::BLOCKS_AT_ONCE as u64);
        arrival::write_blocks(dir, points as usize, fill, declared, colors, at_once as usize)
    }
}

/// Whether the ranks of a logged visit (`count` of them from rank `from` on) in the ranks file
/// `file` hash to `hash`.
pub(super) fn ranks_ok(file: Option<&std::fs::File>, from: u64, count: u64, hash: u64) -> bool {
    let Some(f) = file else { return false };
    const STEP: u64 = 1 << 16;
    let mut h = RankHash::default();
    let mut buf = vec![0u64; STEP.min(count) as usize];
    let mut at = 0;
    while at < count {
        let m = STEP.min(count - at) as usize;
        if f.read_exact_at(bytemuck::cast_slice_mut(&mut buf[..m]), (from + at) * 8).is_err() {
            return false;
        }
        h.add(&buf[..m]);
        at += m as u64;
    }
    h.finish() == hash
}
