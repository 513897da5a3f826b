//! `arrival.bin`: each leaf point's arrival rank (its place in the build's inputs, 0 for the
//! first record of the first input), so that the store's own points can stand for its inputs
//! (issue 29 item 4, `mortar build --append` without the original files; STORE_FORMAT.md,
//! "`arrival.bin`").
//!
//! The ranks are listed leaf by leaf, the leaves in Morton order of their cubes (depth first,
//! children by octant: the sorted engine's order of all records), each leaf's points in its
//! coded order: GPS time order where the payload is coded so (codec 2), else payload order. Scans
//! arrive in time order, so consecutive ranks then differ by little and the file is small (a
//! leaf's Morton order would interleave its flight lines). Written once, after the last commit
//! and before the build record says the build finished, by the sorted, GPU and partitioned
//! engines (the last streams them from `.partition/ranks.bin`; [`write_blocks`] codes a few
//! blocks at a time, so memory does not grow with the store), and by a distributed build's
//! merge (from the parts' own `arrival.bin`, each listing a job's leaves); a store without it
//! (the incremental engine, parts of an older mortar merged, or an older mortar) is extended
//! from its original inputs.
//!
//! The file also keeps the box the inputs' headers declared (on the store's grid, with the
//! build's margin of one unit; [`super::bounds`]), which places the root cube of a build of
//! them: `source.las` keeps no bounds.
//!
//! Since version 2 it also keeps the largest RGB component and intensity of the inputs, which
//! chose the payloads' colours (`mortar_core::color`): an append that keeps the store's nodes
//! must know that the new points do not change them.
//!
//! Layout (little endian): magic `MORTARRV`, `u32` version (2; 1 is read too), `u32` flags (bit
//! 0: a declared box follows; bit 1: the colour maxima follow), `u64` points, `u64` blocks, the
//! box (`i32` min x, y, z, then max; zero without one), in version 2 the largest RGB component
//! and intensity (`u16` each) and four zero bytes, then each block's stored length (`u64`),
//! then the blocks. A block holds up to
//! [`BLOCK`] ranks: the zig-zag of the wrapping differences of consecutive ranks (the first from
//! 0) as eight byte planes, in one zstd frame (level 1).

use crate::error::{Error, Result, StoreError};
use rayon::prelude::*;
use std::path::Path;

/// The file's name in a store directory.
pub const ARRIVAL_FILE: &str = "arrival.bin";
const MAGIC: [u8; 8] = *b"MORTARRV";
const VERSION: u32 = 2;
/// The header's bytes in version 2 (version 1: 56, without the colour maxima).
const HEADER: usize = 64;
const HEADER_V1: usize = 56;

/// The box the inputs' headers declared, on the store's grid (see the module docs).
pub type DeclaredBox = Option<([i32; 3], [i32; 3])>;

/// What `arrival.bin` holds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Arrival {
    /// Per leaf point (in the order the module docs give), its arrival rank.
    pub ranks: Vec<u64>,
    /// The box the inputs' headers declared.
    pub declared: DeclaredBox,
    /// The inputs' colour maxima (version 2 files).
    pub colors: Option<ColorMaxima>,
}

/// The largest RGB component and intensity of a build's inputs: what chose its colours
/// (`mortar_core::color`; `engine::color_of`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ColorMaxima {
    /// The largest RGB component (0 where the records have none).
    pub max_rgb: u16,
    /// The largest intensity.
    pub max_intensity: u16,
}
/// Ranks per block.
pub const BLOCK: usize = 1 << 20;

/// Codes `n` ranks (`rank(i)` for the leaves' point `i`) as one block each [`BLOCK`].
fn encode_block(ranks: impl Iterator<Item = u64>, len: usize) -> Vec<u8> {
    let mut planes = vec![0u8; 8 * len];
    let mut prev = 0u64;
    let mut zig = ranks.map(|r| {
        let d = r.wrapping_sub(prev) as i64;
        prev = r;
        ((d << 1) ^ (d >> 63)) as u64
    });
    // Eight ranks at a time, transposed in registers into eight bytes of each plane.
    for o in 0..len / 8 {
        let mut x = [0u64; 8];
        for x in &mut x {
            *x = zig.next().expect("len ranks");
        }
        super::codec::transpose8(&mut x);
        for (b, x) in x.iter().enumerate() {
            planes[b * len + 8 * o..][..8].copy_from_slice(&x.to_le_bytes());
        }
    }
    for (i, z) in (len / 8 * 8..len).zip(zig) {
        for (b, byte) in z.to_le_bytes().into_iter().enumerate() {
            planes[b * len + i] = byte;
        }
    }
    zstd::bulk::compress(&planes, 1).expect("zstd compresses into a growing buffer")
}

/// Writes `arrival.bin` into `dir` (a temporary name, then renamed): `n` ranks, `rank(i)` the
/// arrival rank of the leaves' point `i` (see the module docs), the inputs' declared box and
/// their colour maxima.
pub fn write(
    dir: &Path,
    n: usize,
    rank: impl Fn(usize) -> u64 + Sync,
    declared: DeclaredBox,
    colors: ColorMaxima,
) -> Result<()> {
    write_blocks(
        dir,
        n,
        |r, out| {
            out.extend(r.map(&rank));
            Ok(())
        },
        declared,
        colors,
        BLOCKS_AT_ONCE,
    )
}

/// Blocks [`write`] codes at once (in parallel) before it writes them.
pub const BLOCKS_AT_ONCE: usize = 32;

/// What coding one block holds in memory at its peak: its ranks, their planes and the code.
pub const BLOCK_BYTES: u64 = 3 * 8 * BLOCK as u64;

/// [`write`] with the ranks given a block at a time: `fill(range, out)` appends the ranks of
/// the leaves' points `range` to `out` (empty), in order. The blocks are coded `at_once` at a
/// time (in parallel; each holds up to [`BLOCK_BYTES`] while it is coded) and written as they
/// are coded, the header and the blocks' lengths last, so that memory does not grow with the
/// store.
pub fn write_blocks(
    dir: &Path,
    n: usize,
    fill: impl Fn(std::ops::Range<usize>, &mut Vec<u64>) -> Result<()> + Sync,
    declared: DeclaredBox,
    colors: ColorMaxima,
    at_once: usize,
) -> Result<()> {
    let at_once = at_once.max(1);
    use std::os::unix::fs::FileExt;
    let p = dir.join(ARRIVAL_FILE);
    let tmp = dir.join(format!("{ARRIVAL_FILE}.tmp"));
    let f = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    let nblocks = n.div_ceil(BLOCK);
    let mut lens = Vec::with_capacity(nblocks);
    let mut at = (HEADER + 8 * nblocks) as u64;
    for first in (0..nblocks).step_by(at_once) {
        let coded: Vec<Vec<u8>> = (first..(first + at_once).min(nblocks))
            .into_par_iter()
            .map(|b| {
                let s = b * BLOCK;
                let e = (s + BLOCK).min(n);
                let mut ranks = Vec::with_capacity(e - s);
                fill(s..e, &mut ranks)?;
                if ranks.len() != e - s {
                    return Err(Error::Internal {
                        path: p.clone(),
                        what: "a block of arrival ranks of another length than asked",
                    });
                }
                Ok(encode_block(ranks.into_iter(), e - s))
            })
            .collect::<Result<_>>()?;
        let bytes = coded.concat();
        f.write_all_at(&bytes, at).map_err(|e| Error::io(&tmp, e))?;
        at += bytes.len() as u64;
        lens.extend(coded.iter().map(|b| b.len() as u64));
    }
    let mut head = Vec::with_capacity(HEADER + 8 * nblocks);
    head.extend_from_slice(&MAGIC);
    head.extend_from_slice(&VERSION.to_le_bytes());
    head.extend_from_slice(&(declared.is_some() as u32 | 2).to_le_bytes());
    head.extend_from_slice(&(n as u64).to_le_bytes());
    head.extend_from_slice(&(nblocks as u64).to_le_bytes());
    let (lo, hi) = declared.unwrap_or_default();
    for v in lo.iter().chain(&hi) {
        head.extend_from_slice(&v.to_le_bytes());
    }
    head.extend_from_slice(&colors.max_rgb.to_le_bytes());
    head.extend_from_slice(&colors.max_intensity.to_le_bytes());
    head.extend_from_slice(&[0; 4]);
    for l in &lens {
        head.extend_from_slice(&l.to_le_bytes());
    }
    f.write_all_at(&head, 0).map_err(|e| Error::io(&tmp, e))?;
    drop(f);
    std::fs::rename(&tmp, &p).map_err(|e| Error::io(&p, e))
}

/// Whether the store `dir` has an arrival file.
pub fn exists(dir: &Path) -> bool {
    dir.join(ARRIVAL_FILE).is_file()
}

/// The ranks of the store `dir`'s `points` leaf points (see the module docs), checked: the
/// file's count must be `points` and the ranks a permutation of `0..points`. `None` where the
/// store has no arrival file. Holds every rank (8 bytes a point); [`RankFile`] reads them a
/// block at a time.
pub fn read(dir: &Path, points: u64) -> Result<Option<Arrival>> {
    let Some(f) = RankFile::open(dir, points)? else { return Ok(None) };
    let mut ranks = vec![0u64; f.n];
    ranks.par_chunks_mut(BLOCK).enumerate().try_for_each(|(b, out)| f.decode_into(b, out))?;
    let seen = RankCheck::new(&f);
    ranks.par_chunks(BLOCK).try_for_each(|r| seen.mark(r, &f))?;
    seen.finish(&f)?;
    Ok(Some(Arrival { ranks, declared: f.declared, colors: f.colors }))
}

/// An arrival file whose header and block table were read and checked, its ranks decoded a
/// block at a time as they are asked for: what reading ranks costs in memory is a few blocks
/// (and a bit a point to check them), not 8 bytes a point.
#[derive(Debug)]
pub struct RankFile {
    path: std::path::PathBuf,
    file: std::fs::File,
    /// Ranks listed.
    n: usize,
    /// Each block's bytes in the file.
    spans: Vec<std::ops::Range<u64>>,
    /// The box the inputs' headers declared.
    pub declared: DeclaredBox,
    /// The inputs' colour maxima (version 2 files).
    pub colors: Option<ColorMaxima>,
}

/// The block a [`RankFile`] decoded last: its index and ranks (a reader's cursor).
pub type BlockCache = Option<(usize, Vec<u64>)>;

impl RankFile {
    /// Opens the arrival file of the store `dir` whose leaves hold `points` points (the count
    /// and the block table checked against them and the file's length; the ranks are checked
    /// by [`check`](Self::check)). `None` where the store has none.
    pub fn open(dir: &Path, points: u64) -> Result<Option<RankFile>> {
        use std::os::unix::fs::FileExt;
        let p = dir.join(ARRIVAL_FILE);
        let file = match std::fs::File::open(&p) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Error::io(&p, e)),
        };
        let bad =
            |why: String| Error::Store { path: p.clone(), error: StoreError::Arrival { why } };
        let file_len = file.metadata().map_err(|e| Error::io(&p, e))?.len();
        let mut head = vec![0u8; HEADER.min(file_len as usize)];
        file.read_exact_at(&mut head, 0).map_err(|e| Error::io(&p, e))?;
        if head.len() < HEADER_V1 || head[..8] != MAGIC {
            return Err(bad("not an arrival file (no MORTARRV header)".into()));
        }
        let u32_at = |at: usize| u32::from_le_bytes(head[at..at + 4].try_into().expect("4 bytes"));
        let u64_at = |at: usize| u64::from_le_bytes(head[at..at + 8].try_into().expect("8 bytes"));
        let version = u32_at(8);
        let header = match version {
            1 => HEADER_V1,
            VERSION if head.len() >= HEADER => HEADER,
            VERSION => return Err(bad("truncated (its header)".into())),
            _ => return Err(bad(format!("arrival file version {version} is not supported"))),
        };
        let flags = u32_at(12);
        let known = if version == 1 { 1 } else { 3 };
        if flags & !known != 0 {
            return Err(bad(format!("unknown flags {flags:#x}")));
        }
        let i32_at = |k: usize| u32_at(32 + 4 * k) as i32;
        let declared = (flags & 1 != 0).then(|| ([0, 1, 2].map(i32_at), [3, 4, 5].map(i32_at)));
        let u16_at = |at: usize| u16::from_le_bytes([head[at], head[at + 1]]);
        let colors = (flags & 2 != 0)
            .then(|| ColorMaxima { max_rgb: u16_at(56), max_intensity: u16_at(58) });
        let (n, nblocks) = (u64_at(16), u64_at(24));
        if n != points {
            return Err(bad(format!("holds {n} ranks, the store's leaves hold {points} points")));
        }
        // Both checked against the store's points (counted from its leaves), so sizes below
        // are bounded by what the store holds, not by this file's header.
        if nblocks != points.div_ceil(BLOCK as u64) {
            return Err(bad(format!("declares {nblocks} blocks for {points} ranks")));
        }
        let nb = nblocks as usize;
        let table_end = (header + 8 * nb) as u64;
        if file_len < table_end {
            return Err(bad("truncated (its block table)".into()));
        }
        let mut table = vec![0u8; 8 * nb];
        file.read_exact_at(&mut table, header as u64).map_err(|e| Error::io(&p, e))?;
        let mut spans = Vec::with_capacity(nb);
        let mut at = table_end;
        for (b, len) in table.chunks_exact(8).enumerate() {
            let len = u64::from_le_bytes(len.try_into().expect("8 bytes"));
            let Some(end) = at.checked_add(len).filter(|&e| e <= file_len) else {
                return Err(bad(format!("truncated (block {b})")));
            };
            spans.push(at..end);
            at = end;
        }
        if at != file_len {
            return Err(bad(format!("{} bytes after its last block", file_len - at)));
        }
        Ok(Some(RankFile { path: p, file, n: points as usize, spans, declared, colors }))
    }

    fn bad(&self, why: String) -> Error {
        Error::Store { path: self.path.clone(), error: StoreError::Arrival { why } }
    }

    /// The ranks listed.
    pub fn len(&self) -> usize {
        self.n
    }

    /// Whether it lists none.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Decodes block `b` into `out` (its ranks: [`BLOCK`], or fewer for the last block).
    fn decode_into(&self, b: usize, out: &mut [u64]) -> Result<()> {
        use std::os::unix::fs::FileExt;
        let span = &self.spans[b];
        let mut coded = vec![0u8; (span.end - span.start) as usize];
        self.file.read_exact_at(&mut coded, span.start).map_err(|e| Error::io(&self.path, e))?;
        let len = out.len();
        let planes = zstd::bulk::decompress(&coded, 8 * len)
            .map_err(|e| self.bad(format!("block {b}: {e}")))?;
        if planes.len() != 8 * len {
            return Err(self.bad(format!(
                "block {b} holds {} bytes, not {}",
                planes.len(),
                8 * len
            )));
        }
        let mut prev = 0u64;
        let mut add = |z: u64, r: &mut u64| {
            let d = ((z >> 1) as i64) ^ -((z & 1) as i64);
            prev = prev.wrapping_add(d as u64);
            *r = prev;
        };
        // Eight ranks at a time: eight bytes of each plane, transposed in registers.
        let len8 = len / 8 * 8;
        for (o, r8) in out[..len8].chunks_exact_mut(8).enumerate() {
            let mut x = [0u64; 8];
            for (k, x) in x.iter_mut().enumerate() {
                let at = k * len + 8 * o;
                *x = u64::from_le_bytes(planes[at..at + 8].try_into().expect("8 bytes"));
            }
            super::codec::transpose8(&mut x);
            for (x, r) in x.into_iter().zip(r8) {
                add(x, r);
            }
        }
        for (i, r) in out.iter_mut().enumerate().skip(len8) {
            let z = (0..8).fold(0u64, |z, k| z | (planes[k * len + i] as u64) << (8 * k));
            add(z, r);
        }
        Ok(())
    }

    /// The ranks of block `b`.
    fn block(&self, b: usize) -> Result<Vec<u64>> {
        let mut out = vec![0u64; (self.n - b * BLOCK).min(BLOCK)];
        self.decode_into(b, &mut out)?;
        Ok(out)
    }

    /// Appends the ranks of the listing's places `r` to `out`, decoding the blocks they lie in;
    /// `cache` keeps the last block decoded, so that reading a block's ranges in order decodes
    /// it once.
    pub fn copy(
        &self,
        r: std::ops::Range<usize>,
        cache: &mut BlockCache,
        out: &mut Vec<u64>,
    ) -> Result<()> {
        for (b, within) in self.pieces(r)? {
            if cache.as_ref().is_none_or(|(k, _)| *k != b) {
                *cache = Some((b, self.block(b)?));
            }
            let (_, ranks) = cache.as_ref().expect("just decoded");
            out.extend_from_slice(&ranks[within]);
        }
        Ok(())
    }

    /// The listing's places `r` as pieces of blocks: each block and the places within it; an
    /// error where `r` passes the listing's end.
    fn pieces(
        &self,
        r: std::ops::Range<usize>,
    ) -> Result<impl Iterator<Item = (usize, std::ops::Range<usize>)>> {
        if r.end > self.n {
            return Err(Error::Internal {
                path: self.path.clone(),
                what: "arrival ranks asked for beyond the listing",
            });
        }
        let blocks = if r.is_empty() { 0..0 } else { r.start / BLOCK..(r.end - 1) / BLOCK + 1 };
        Ok(blocks.map(move |b| {
            let s = r.start.max(b * BLOCK) - b * BLOCK;
            let e = r.end.min((b + 1) * BLOCK) - b * BLOCK;
            (b, s..e)
        }))
    }

    /// Checks that the ranks are a permutation of `0..len` (none at or above it, none twice),
    /// decoding `at_once` blocks at a time (in parallel): a bit a rank besides them.
    pub fn check(&self, at_once: usize) -> Result<()> {
        let at_once = at_once.max(1);
        let seen = RankCheck::new(self);
        let blocks: Vec<usize> = (0..self.spans.len()).collect();
        for group in blocks.chunks(at_once) {
            group.par_iter().try_for_each(|&b| seen.mark(&self.block(b)?, self))?;
        }
        seen.finish(self)
    }
}

/// A [`RankFile`]'s blocks decoded once for readers on several threads that read ranges in
/// about the listing's order (the blocks of one listing coded from another's, in parallel):
/// each block is decoded by the first reader that needs it and kept for the others, at most
/// `keep` blocks at a time (the lowest dropped first).
pub struct SharedBlocks<'a> {
    f: &'a RankFile,
    keep: usize,
    #[allow(clippy::type_complexity)]
    blocks: std::sync::Mutex<
        std::collections::BTreeMap<usize, std::sync::Arc<std::sync::OnceLock<Option<Vec<u64>>>>>,
    >,
}

impl<'a> SharedBlocks<'a> {
    /// Blocks of `f`, `keep` of them kept at a time.
    pub fn new(f: &'a RankFile, keep: usize) -> SharedBlocks<'a> {
        SharedBlocks { f, keep: keep.max(2), blocks: Default::default() }
    }

    /// Drops every block kept (a reader that holds one keeps it until it is done; a later
    /// reader decodes it again).
    pub fn forget(&self) {
        self.blocks.lock().expect("not poisoned").clear();
    }

    /// Appends the ranks of the listing's places `r` to `out` ([`RankFile::copy`]).
    pub fn copy(&self, r: std::ops::Range<usize>, out: &mut Vec<u64>) -> Result<()> {
        let f = self.f;
        for (b, within) in f.pieces(r)? {
            let cell = {
                let mut m = self.blocks.lock().expect("not poisoned");
                let cell = m.entry(b).or_default().clone();
                while m.len() > self.keep {
                    let lowest = *m.keys().next().expect("not empty");
                    if lowest == b {
                        break;
                    }
                    m.remove(&lowest);
                }
                cell
            };
            // A block that does not decode is decoded again for its error (the same one).
            let Some(ranks) = cell.get_or_init(|| f.block(b).ok()) else {
                return Err(f.block(b).err().unwrap_or_else(|| f.bad(format!("block {b}"))));
            };
            out.extend_from_slice(&ranks[within]);
        }
        Ok(())
    }
}

/// The check that ranks are a permutation of `0..n`, as they are read (in any order, from any
/// thread): a bit a rank. [`mark`](Self::mark) and [`finish`](Self::finish) check a
/// [`RankFile`]'s ranks; [`mark_ranks`](Self::mark_ranks) and [`missing`](Self::missing) any.
pub struct RankCheck {
    n: u64,
    bits: Vec<std::sync::atomic::AtomicU64>,
    marked: std::sync::atomic::AtomicU64,
}

/// Why ranks are not a permutation of `0..n`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RankFault {
    /// A rank at or above `n`.
    Beyond(u64),
    /// A rank given twice.
    Twice(u64),
}

impl RankCheck {
    /// The check of `f`'s ranks, none read yet.
    pub fn new(f: &RankFile) -> RankCheck {
        RankCheck::of_len(f.n as u64)
    }

    /// The check of a permutation of `0..n`, no rank read yet.
    pub fn of_len(n: u64) -> RankCheck {
        RankCheck {
            n,
            bits: (0..n.div_ceil(64)).map(|_| Default::default()).collect(),
            marked: Default::default(),
        }
    }

    /// Marks `ranks` read: an error where one is not below `f`'s count or was read before.
    pub fn mark(&self, ranks: &[u64], f: &RankFile) -> Result<()> {
        self.mark_ranks(ranks).map_err(|e| match e {
            RankFault::Beyond(r) => {
                f.bad(format!("rank {r} is not below the store's {} points", self.n))
            }
            RankFault::Twice(r) => f.bad(format!("rank {r} is given twice")),
        })
    }

    /// Marks `ranks` read: the first that is not below `n` or was read before.
    pub fn mark_ranks(&self, ranks: &[u64]) -> std::result::Result<(), RankFault> {
        use std::sync::atomic::Ordering::Relaxed;
        // Consecutive ranks mostly share a word (scans arrive in time order): their bits are
        // gathered and set with one atomic operation a word.
        let (mut word, mut mask) = (u64::MAX, 0u64);
        let flush = |word: u64, mask: u64| -> std::result::Result<(), RankFault> {
            if mask != 0 {
                let had = self.bits[word as usize].fetch_or(mask, Relaxed) & mask;
                if had != 0 {
                    return Err(RankFault::Twice(64 * word + had.trailing_zeros() as u64));
                }
            }
            Ok(())
        };
        for &r in ranks {
            if r >= self.n {
                return Err(RankFault::Beyond(r));
            }
            if r / 64 != word {
                flush(word, mask)?;
                (word, mask) = (r / 64, 0);
            }
            let bit = 1u64 << (r % 64);
            if mask & bit != 0 {
                return Err(RankFault::Twice(r));
            }
            mask |= bit;
        }
        flush(word, mask)?;
        self.marked.fetch_add(ranks.len() as u64, Relaxed);
        Ok(())
    }

    /// How many of the `n` ranks were not marked (once all places were read, a permutation has
    /// none missing).
    pub fn missing(&self) -> u64 {
        self.n - self.marked.load(std::sync::atomic::Ordering::Relaxed).min(self.n)
    }

    /// Once every rank was read: an error where some were not (then some place was not read).
    pub fn finish(&self, f: &RankFile) -> Result<()> {
        if self.missing() != 0 {
            let m = self.n - self.missing();
            return Err(f.bad(format!("{m} of its {} ranks were read", f.n)));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmpdir(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("mortar-arrival-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn round_trip_and_checks() {
        let d = tmpdir("rt");
        // A permutation over more than one block: a scanline-like walk reversed in places.
        let n = BLOCK + 12_345;
        let perm: Vec<u64> = (0..n as u64)
            .map(|i| if (i / 1000) % 2 == 0 { i } else { (i / 1000) * 1000 + 999 - i % 1000 })
            .collect();
        let declared = Some(([-5, 0, 7], [9, i32::MAX, 8]));
        let colors = ColorMaxima { max_rgb: 255, max_intensity: 4000 };
        write(&d, n, |i| perm[i], declared, colors).unwrap();
        let got = read(&d, n as u64).unwrap().unwrap();
        assert_eq!(got, Arrival { ranks: perm.clone(), declared, colors: Some(colors) });
        // Read a block at a time: ranges across the blocks' border, in order and not, with
        // one cache, give the listing's ranks; the check passes; ranges beyond are refused.
        let f = RankFile::open(&d, n as u64).unwrap().unwrap();
        assert_eq!((f.len(), f.declared, f.colors), (n, declared, Some(colors)));
        f.check(1).unwrap();
        f.check(64).unwrap();
        let mut cache = None;
        for r in [0..10, BLOCK - 5..BLOCK + 7, 3..BLOCK + 12_345, 17..17, n - 1..n, 5..6] {
            let mut out = vec![42];
            f.copy(r.clone(), &mut cache, &mut out).unwrap();
            assert_eq!(out[1..], perm[r.clone()], "{r:?}");
            assert_eq!(out[0], 42);
        }
        assert!(f.copy(n - 1..n + 1, &mut cache, &mut Vec::new()).is_err());
        let shared = SharedBlocks::new(&f, 2);
        for r in [BLOCK - 5..BLOCK + 7, 3..BLOCK + 12_345, 0..1, n - 1..n] {
            let mut out = Vec::new();
            shared.copy(r.clone(), &mut out).unwrap();
            assert_eq!(out, perm[r.clone()], "{r:?}");
        }
        assert!(shared.copy(n - 1..n + 1, &mut Vec::new()).is_err());
        drop(f);
        // Version 1 (no colour maxima): the same file less bytes 56..64, version and flag 1.
        let p = d.join(ARRIVAL_FILE);
        let v2 = std::fs::read(&p).unwrap();
        let mut v1 = v2[..56].to_vec();
        v1[8..12].copy_from_slice(&1u32.to_le_bytes());
        v1[12..16].copy_from_slice(&1u32.to_le_bytes());
        v1.extend_from_slice(&v2[64..]);
        std::fs::write(&p, &v1).unwrap();
        let got = read(&d, n as u64).unwrap().unwrap();
        assert_eq!(got, Arrival { ranks: perm, declared, colors: None });
        std::fs::write(&p, &v2).unwrap();
        // Another count than the store's, a file cut short, a rank twice, a rank too large.
        assert!(read(&d, n as u64 - 1).is_err());
        let whole = std::fs::read(&p).unwrap();
        std::fs::write(&p, &whole[..whole.len() - 3]).unwrap();
        let e = read(&d, n as u64).unwrap_err().to_string();
        assert!(e.contains("arrival.bin") && e.contains("truncated"), "{e}");
        assert!(RankFile::open(&d, n as u64).unwrap_err().to_string().contains("truncated"));
        write(&d, 3, |i| [0, 2, 0][i], None, colors).unwrap();
        assert!(read(&d, 3).unwrap_err().to_string().contains("twice"));
        let f = RankFile::open(&d, 3).unwrap().unwrap();
        assert!(f.check(1).unwrap_err().to_string().contains("twice"));
        write(&d, 3, |i| [0, 1, 7][i], None, colors).unwrap();
        assert!(read(&d, 3).unwrap_err().to_string().contains("not below"));
        let f = RankFile::open(&d, 3).unwrap().unwrap();
        assert!(f.check(2).unwrap_err().to_string().contains("not below"));
        assert!(RankFile::open(&d, 4).is_err());
        std::fs::write(&p, b"MORTARRV").unwrap();
        assert!(read(&d, 3).is_err());
        std::fs::remove_file(&p).unwrap();
        assert!(read(&d, 3).unwrap().is_none());
        assert!(RankFile::open(&d, 3).unwrap().is_none());
        write(&d, 0, |_| 0, None, ColorMaxima::default()).unwrap();
        assert_eq!(
            read(&d, 0).unwrap().unwrap(),
            Arrival { ranks: Vec::new(), declared: None, colors: Some(ColorMaxima::default()) }
        );
        let _ = std::fs::remove_dir_all(&d);
    }
}
