//! Voxel sampling state of inner nodes (paper 004 §3.3, §5.2; averaging from §8).
//!
//! A node's 128³ grid is sampled per octant (64³ cells each), so that its 8 children's tasks
//! sample it in parallel. Occupancy is sparse, not the paper's dense 256 KiB bit grid: per octant,
//! [`SparseBits`] keeps a 512-entry `u16` table of 8³-cell bricks (1 KiB, allocated with the
//! octant's first voxel) and 64-byte bit bricks for occupied bricks only. Surfaces touch few
//! bricks, so a typical node of ~16 k voxels needs ~25 KiB. The averaged mode needs the voxel of
//! a cell, not only its bit: [`SparseIndex`] has the same two levels with a `u32` accumulator index
//! per cell of an occupied brick (2 KiB per brick); Wand et al. use hash maps, but bricks keep
//! nearby points in one cache line or a few.

use super::chunks::Chunks;
use super::cube::Cube;
use super::types::{ColorMode, Point, Voxel, GRID_LOG2, VOXEL_CHUNK_MAX};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

/// Averaged voxels are published in fixed chunks of this many voxels: chunk `k` holds voxels
/// `k * AVERAGED_CHUNK ..`, and a chunk is rebuilt when a voxel in it changes colour.
pub const AVERAGED_CHUNK: usize = 1 << 12;

/// An averaged voxel stops accumulating after this many points (its sums are `u32`).
pub const MAX_AVERAGED_SAMPLES: u32 = 1 << 24;

/// The key `x | y << 7 | z << 14` of a cell.
#[cfg(test)]
#[inline]
pub(crate) fn cell_key(c: [u32; 3]) -> u32 {
    c[0] | c[1] << GRID_LOG2 | c[2] << (2 * GRID_LOG2)
}

/// Inverse of [`cell_key`].
#[cfg(test)]
#[inline]
pub(crate) fn key_coord(k: u32) -> [u8; 3] {
    [(k & 127) as u8, (k >> GRID_LOG2 & 127) as u8, (k >> (2 * GRID_LOG2) & 127) as u8]
}

/// The rounded mean `(sum + count / 2) / count` of each RGBA channel, packed as
/// `r | g << 8 | b << 16 | a << 24` (0 for `count == 0`).
pub fn mean_color(sum: [u32; 4], count: u32) -> u32 {
    if count == 0 {
        return 0;
    }
    let c = count as u64;
    (0..4).map(|i| (((sum[i] as u64 + c / 2) / c) as u32) << (8 * i)).fold(0, |a, b| a | b)
}

/// Sparse occupancy of one octant (64³ cells) of a node's grid: a table of its 8³ bricks plus
/// bit bricks for the occupied bricks only.
#[derive(Debug, Default)]
pub(crate) struct SparseBits {
    /// Brick index + 1 for each of the 8³ bricks (0: empty); empty until the first insert.
    table: Vec<u16>,
    /// 8³ bits per occupied brick.
    bricks: Vec<[u64; 8]>,
}

impl SparseBits {
    #[inline]
    fn brick_and_bit(c: [u32; 3]) -> (usize, u32) {
        let b = ((c[0] >> 3) & 7) | ((c[1] >> 3) & 7) << 3 | ((c[2] >> 3) & 7) << 6;
        let bit = (c[0] & 7) | (c[1] & 7) << 3 | (c[2] & 7) << 6;
        (b as usize, bit)
    }

    /// Sets the bit of cell `c` (each coordinate `< 128`; only its low 6 bits are used: the
    /// octant is implied); true if it was clear.
    #[inline]
    pub(crate) fn insert(&mut self, c: [u32; 3]) -> bool {
        if self.table.is_empty() {
            self.table = vec![0; 512];
        }
        let (b, bit) = Self::brick_and_bit(c);
        let mut t = self.table[b];
        if t == 0 {
            self.bricks.push([0; 8]);
            t = self.bricks.len() as u16; // at most 512 bricks
            self.table[b] = t;
        }
        let w = &mut self.bricks[t as usize - 1][(bit >> 6) as usize];
        let m = 1u64 << (bit & 63);
        let was_clear = *w & m == 0;
        *w |= m;
        was_clear
    }

    /// Whether cell `c` is set.
    #[cfg(test)]
    pub(crate) fn contains(&self, c: [u32; 3]) -> bool {
        if self.table.is_empty() {
            return false;
        }
        let (b, bit) = Self::brick_and_bit(c);
        let t = self.table[b];
        t != 0 && self.bricks[t as usize - 1][(bit >> 6) as usize] >> (bit & 63) & 1 == 1
    }

    /// Heap bytes in use.
    pub(crate) fn heap_bytes(&self) -> usize {
        self.table.capacity() * 2 + self.bricks.capacity() * 64
    }
}

/// Sparse map from the cells of one octant (64³) to voxel indices: like [`SparseBits`], a
/// table of 8³-cell bricks, with a `u32` (index + 1, 0 for empty) per cell of occupied bricks
/// (2 KiB per brick). Lookups stay within a brick for nearby points, unlike a hash map.
#[derive(Debug, Default)]
pub(crate) struct SparseIndex {
    table: Vec<u16>,
    bricks: Vec<[u32; 512]>,
}

impl SparseIndex {
    /// The value of cell `c`, inserting `value` (less than `u32::MAX`) if absent; true when it
    /// was inserted.
    #[inline]
    pub(crate) fn get_or_insert(&mut self, c: [u32; 3], value: u32) -> (u32, bool) {
        if self.table.is_empty() {
            self.table = vec![0; 512];
        }
        let (b, cell) = SparseBits::brick_and_bit(c);
        let mut t = self.table[b];
        if t == 0 {
            self.bricks.push([0; 512]);
            t = self.bricks.len() as u16; // at most 512 bricks
            self.table[b] = t;
        }
        let slot = &mut self.bricks[t as usize - 1][cell as usize];
        if *slot == 0 {
            *slot = value + 1;
            (value, true)
        } else {
            (*slot - 1, false)
        }
    }

    /// Heap bytes in use.
    pub(crate) fn heap_bytes(&self) -> usize {
        self.table.capacity() * 2 + self.bricks.capacity() * 2048
    }
}

/// Marks one point's cell in a node's grid.
pub(crate) trait Sample {
    /// Samples a point of colour `color` in cell `cell` (each coordinate `< 128`); `seq` is the
    /// point's place in the update's sequence, by which [`VoxelState::publish`] finds the point
    /// that a new voxel stands for.
    fn sample(&mut self, cell: [u32; 3], color: u32, seq: u32);
}

/// A voxel created in the current update, before its point is looked up.
#[derive(Clone, Copy, Debug, Default)]
struct Pending {
    seq: u32,
    color: u32,
}

/// First-come sampling of one octant: occupancy bits and the voxels created in the current
/// update (the paper's backlog).
#[derive(Debug, Default)]
pub(crate) struct FirstCome {
    occupied: SparseBits,
    backlog: Vec<Pending>,
}

impl Sample for FirstCome {
    #[inline]
    fn sample(&mut self, cell: [u32; 3], color: u32, seq: u32) {
        if self.occupied.insert(cell) {
            self.backlog.push(Pending { seq, color });
        }
    }
}

/// No voxel of the node's list yet.
const UNPUBLISHED: u32 = u32::MAX;

/// Running sums of one averaged voxel.
#[derive(Clone, Copy, Debug)]
struct Accum {
    count: u32,
    sum: [u32; 4],
    /// Index in the node's voxel list, [`UNPUBLISHED`] until published.
    global: u32,
    /// The representative (the cell's first point); until published, `record` holds its
    /// `seq` in the update.
    first: Point,
}

impl Accum {
    #[inline]
    fn voxel(&self) -> Voxel {
        Voxel::of(&self.first, mean_color(self.sum, self.count))
    }
}

/// Averaged sampling of one octant: cell → accumulator map, the sums, and which published
/// chunks of the node went stale.
#[derive(Debug, Default)]
pub(crate) struct Averaged {
    index: SparseIndex,
    acc: Vec<Accum>,
    /// First accumulator without a place in the node's voxel list.
    fresh: usize,
    /// One bit per [`AVERAGED_CHUNK`] chunk of the node's voxel list that changed.
    dirty: Vec<u64>,
}

fn mark(dirty: &mut Vec<u64>, voxel: usize) {
    let k = voxel / AVERAGED_CHUNK;
    if k / 64 >= dirty.len() {
        dirty.resize(k / 64 + 1, 0);
    }
    dirty[k / 64] |= 1 << (k % 64);
}

impl Sample for Averaged {
    #[inline]
    fn sample(&mut self, cell: [u32; 3], color: u32, seq: u32) {
        let (i, inserted) = self.index.get_or_insert(cell, self.acc.len() as u32);
        let ch = color.to_le_bytes().map(|c| c as u32);
        if inserted {
            let first = Point { pos: [0; 3], color, record: seq as u64 };
            self.acc.push(Accum { count: 1, sum: ch, global: UNPUBLISHED, first });
            return;
        }
        let a = &mut self.acc[i as usize];
        if a.count >= MAX_AVERAGED_SAMPLES {
            return;
        }
        a.count += 1;
        for (s, c) in a.sum.iter_mut().zip(ch) {
            *s += c;
        }
        if a.global != UNPUBLISHED {
            let g = a.global as usize;
            mark(&mut self.dirty, g);
        }
    }
}

/// The sampler of one octant, by colour mode.
#[derive(Debug)]
pub(crate) enum Sampler {
    FirstCome(FirstCome),
    Averaged(Averaged),
}

/// The sampling state of one octant of an inner node's grid: one task samples it at a time.
#[derive(Debug)]
pub(crate) struct Octant {
    pub(crate) sampler: Sampler,
    /// Points sampled since the last publish.
    pub(crate) sampled: u64,
    /// Of those, points new in the node's cube (not spilled by the node itself).
    pub(crate) through: u64,
}

/// Bits of the accumulator index in an entry of [`VoxelState::order`].
const LOCAL_BITS: u32 = 18;

/// An inner node's voxels: the published payload and the per-octant sampling state behind it.
///
/// The grid is sampled per octant (the cell's upper bit on each axis is the child octant), so the
/// 8 child tasks of a node sample it in parallel, each in arrival order. New voxels are published
/// octant by octant: within one update, a node's new voxels are ordered by octant, then arrival.
#[derive(Debug)]
pub(crate) struct VoxelState {
    /// Voxels as published to snapshots.
    pub(crate) chunks: Chunks<Voxel>,
    octants: [Mutex<Octant>; 8],
    /// Averaged mode: voxel index → `octant << 18 | accumulator index`.
    order: Vec<u32>,
    /// Averaged mode: stale chunks of `chunks`.
    dirty: Vec<u64>,
}

impl VoxelState {
    pub(crate) fn new(mode: ColorMode) -> VoxelState {
        let octants = std::array::from_fn(|_| {
            let sampler = match mode {
                ColorMode::FirstCome => Sampler::FirstCome(FirstCome::default()),
                ColorMode::Averaged => Sampler::Averaged(Averaged::default()),
            };
            Mutex::new(Octant { sampler, sampled: 0, through: 0 })
        });
        VoxelState { chunks: Chunks::default(), octants, order: Vec::new(), dirty: Vec::new() }
    }

    /// The sampling state of octant `o`.
    pub(crate) fn octant(&self, o: usize) -> MutexGuard<'_, Octant> {
        self.octants[o].lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Moves what was sampled since the last call into the published chunks (§5.4, voxels from
    /// the backlog into their node); `point(seq)` is the point of the update's sequence that a
    /// new voxel stands for. Returns the number of new voxels, and the points sampled and new in
    /// the cube since the last call.
    pub(crate) fn publish(&mut self, point: &(dyn Fn(u32) -> Point + Sync)) -> (u64, u64, u64) {
        let before = self.chunks.len();
        let mut octs =
            self.octants.each_mut().map(|m| m.get_mut().unwrap_or_else(PoisonError::into_inner));
        let sampled = octs.iter().map(|o| o.sampled).sum();
        let through = octs.iter().map(|o| o.through).sum();
        for o in octs.iter_mut() {
            o.sampled = 0;
            o.through = 0;
        }
        if sampled == 0 {
            return (0, 0, 0);
        }
        let mut new_firstcome: Vec<Voxel> = Vec::new();
        for (o, oct) in octs.iter_mut().enumerate() {
            match &mut oct.sampler {
                Sampler::FirstCome(s) => {
                    new_firstcome
                        .extend(s.backlog.iter().map(|v| Voxel::of(&point(v.seq), v.color)));
                    s.backlog = Vec::new();
                }
                Sampler::Averaged(s) => {
                    for (w, bits) in s.dirty.iter_mut().enumerate() {
                        if *bits != 0 {
                            if w >= self.dirty.len() {
                                self.dirty.resize(w + 1, 0);
                            }
                            self.dirty[w] |= std::mem::take(bits);
                        }
                    }
                    for (l, a) in s.acc.iter_mut().enumerate().skip(s.fresh) {
                        let p = point(a.first.record as u32);
                        a.first = Point { pos: p.pos, color: a.first.color, record: p.record };
                        a.global = self.order.len() as u32;
                        mark(&mut self.dirty, self.order.len());
                        self.order.push((o as u32) << LOCAL_BITS | l as u32);
                    }
                    s.fresh = s.acc.len();
                }
            }
        }
        if !new_firstcome.is_empty() {
            self.chunks.append(&new_firstcome, VOXEL_CHUNK_MAX);
        }
        if !self.dirty.is_empty() {
            let accs: [&[Accum]; 8] = std::array::from_fn(|o| match &octs[o].sampler {
                Sampler::Averaged(s) => &s.acc[..],
                Sampler::FirstCome(_) => &[][..],
            });
            for w in 0..self.dirty.len() {
                let mut bits = std::mem::take(&mut self.dirty[w]);
                while bits != 0 {
                    let k = w * 64 + bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    let start = k * AVERAGED_CHUNK;
                    let end = (start + AVERAGED_CHUNK).min(self.order.len());
                    let chunk: Arc<[Voxel]> = self.order[start..end]
                        .iter()
                        .map(|&e| {
                            accs[(e >> LOCAL_BITS) as usize][(e & ((1 << LOCAL_BITS) - 1)) as usize]
                                .voxel()
                        })
                        .collect();
                    self.chunks.put_chunk(k, chunk);
                }
            }
        }
        (self.chunks.len() - before, sampled, through)
    }

    /// Samples the grid of `cube` (a new root) from `reps`, the voxels of the old root, in
    /// their order, and publishes the result: each new voxel is the first of `reps` in its cell
    /// (in averaged mode with the mean of their colours, each counted once: the old root's sums
    /// are not kept, so a coarse voxel averages the finer voxels, not their points).
    pub(crate) fn seed(&mut self, cube: &Cube, reps: &[Voxel]) {
        let shift = (cube.size_log2 - GRID_LOG2) as u32;
        for (i, v) in reps.iter().enumerate() {
            let off = cube.offset(v.pos);
            let cell = off.map(|o| o >> shift);
            let o = (cell[0] >> 6 | (cell[1] >> 6) << 1 | (cell[2] >> 6) << 2) as usize;
            let oct = self.octants[o].get_mut().unwrap_or_else(PoisonError::into_inner);
            match &mut oct.sampler {
                Sampler::FirstCome(s) => s.sample(cell, v.color, i as u32),
                Sampler::Averaged(s) => s.sample(cell, v.color, i as u32),
            }
            oct.sampled += 1;
        }
        self.publish(&|i| reps[i as usize].point());
    }

    /// Replaces the records of the first `points.len()` voxels (saved ones paged back in,
    /// in voxel order) with those of `points`.
    pub(crate) fn set_records(&mut self, points: &[Point]) {
        // Chunk by chunk, so the chunking (fixed in averaged mode) stays.
        let mut at = 0usize;
        for k in 0..self.chunks.chunks().len() {
            let old = &self.chunks.chunks()[k];
            if at >= points.len() {
                break;
            }
            let chunk: Arc<[Voxel]> = old
                .iter()
                .enumerate()
                .map(|(i, v)| Voxel {
                    record: points.get(at + i).map_or(v.record, |p| p.record),
                    ..*v
                })
                .collect();
            at += chunk.len();
            self.chunks.put_chunk(k, chunk);
        }
        for o in self.octants.iter_mut() {
            if let Sampler::Averaged(s) =
                &mut o.get_mut().unwrap_or_else(PoisonError::into_inner).sampler
            {
                for a in &mut s.acc {
                    if a.global != UNPUBLISHED && (a.global as usize) < points.len() {
                        a.first.record = points[a.global as usize].record;
                    }
                }
            }
        }
    }

    /// Heap bytes of the sampling state (not of the published chunks).
    pub(crate) fn sampler_bytes(&self) -> usize {
        let octs: usize = (0..8)
            .map(|o| match &self.octant(o).sampler {
                Sampler::FirstCome(s) => {
                    s.occupied.heap_bytes() + s.backlog.capacity() * std::mem::size_of::<Pending>()
                }
                Sampler::Averaged(s) => {
                    s.index.heap_bytes()
                        + s.acc.capacity() * std::mem::size_of::<Accum>()
                        + s.dirty.capacity() * 8
                }
            })
            .sum();
        octs + self.order.capacity() * 4 + self.dirty.capacity() * 8
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::{HashMap, HashSet};

    #[test]
    fn mean_rounds_half_up() {
        assert_eq!(mean_color([255, 0, 0, 255], 1), 0xff00_00ff);
        assert_eq!(mean_color([255, 1, 0, 510], 2), 0xff00_0180);
        assert_eq!(mean_color([10, 11, 0, 0], 3), 0x0000_0403);
        assert_eq!(mean_color([1, 1, 1, 1], 0), 0);
        let big = MAX_AVERAGED_SAMPLES;
        assert_eq!(mean_color([255 * big; 4], big), u32::MAX);
    }

    #[test]
    fn keys_round_trip() {
        for c in [[0, 0, 0], [127, 0, 5], [1, 127, 127], [127, 127, 127]] {
            assert_eq!(key_coord(cell_key(c)), c.map(|v| v as u8));
        }
    }

    #[test]
    fn full_octant_fits_sparse_bits() {
        let mut s = SparseBits::default();
        let mut n = 0;
        for z in 64..128 {
            for y in 0..64 {
                for x in 64..128 {
                    n += s.insert([x, y, z]) as u32;
                }
            }
        }
        assert_eq!(n, 64 * 64 * 64);
        assert!(!s.insert([127, 0, 64]));
        assert_eq!(s.bricks.len(), 512);
        assert_eq!(s.heap_bytes(), 1024 + 512 * 64);
    }

    /// Samples one point as the sampling pass does; its `seq` is its cell's key, and [`at`]
    /// gives it back as the point at that cell (a node of 128 units at the origin).
    fn sample_at(v: &VoxelState, cell: [u32; 3], color: u32) {
        let mut o = v.octant((cell[0] >> 6 | (cell[1] >> 6) << 1 | (cell[2] >> 6) << 2) as usize);
        match &mut o.sampler {
            Sampler::FirstCome(s) => s.sample(cell, color, cell_key(cell)),
            Sampler::Averaged(s) => s.sample(cell, color, cell_key(cell)),
        }
        o.sampled += 1;
        o.through += 1;
    }

    fn at(seq: u32) -> Point {
        Point { pos: key_coord(seq).map(|c| c as i32), color: 0, record: seq as u64 }
    }

    fn cell(v: &Voxel) -> [u8; 3] {
        v.pos.map(|c| c as u8)
    }

    #[test]
    fn first_come_publishes_by_octant_then_arrival() {
        let mut v = VoxelState::new(ColorMode::FirstCome);
        sample_at(&v, [100, 0, 0], 1);
        sample_at(&v, [1, 0, 0], 2);
        sample_at(&v, [100, 0, 0], 3);
        sample_at(&v, [0, 0, 0], 4);
        assert_eq!(v.publish(&at), (3, 4, 4));
        let got: Vec<([u8; 3], u32)> = v.chunks.iter().map(|x| (cell(x), x.color)).collect();
        assert_eq!(got, vec![([1, 0, 0], 2), ([0, 0, 0], 4), ([100, 0, 0], 1)]);
        assert_eq!(v.publish(&at), (0, 0, 0));
    }

    #[test]
    fn averaged_chunks_rebuild_when_colours_change() {
        let mut v = VoxelState::new(ColorMode::Averaged);
        // AVERAGED_CHUNK + 10 distinct cells, spread over two octants
        let cells: Vec<[u32; 3]> =
            (0..AVERAGED_CHUNK as u32 + 10).map(|i| [i & 127, i >> 7 & 127, i >> 14]).collect();
        for &c in &cells {
            sample_at(&v, c, 0xff00_0000);
        }
        assert_eq!(v.publish(&at).0, cells.len() as u64);
        assert_eq!(v.chunks.chunks().len(), 2);
        let first = v.chunks.chunks()[0].clone();
        let second = v.chunks.chunks()[1].clone();
        let last = *second.last().unwrap();
        let c = cell(&last).map(|c| c as u32);
        sample_at(&v, c, 0xff00_00ff);
        assert_eq!(v.publish(&at).0, 0);
        // only the second chunk was rebuilt
        assert!(Arc::ptr_eq(&first, &v.chunks.chunks()[0]));
        assert!(!Arc::ptr_eq(&second, &v.chunks.chunks()[1]));
        assert_eq!(v.chunks.chunks()[1].last().unwrap().color, 0xff00_0080);
        assert_eq!(second.last().unwrap().color, 0xff00_0000);
        assert_eq!(v.chunks.len(), cells.len() as u64);
        // every cell once
        let set: HashSet<[u8; 3]> = v.chunks.iter().map(cell).collect();
        assert_eq!(set.len(), cells.len());
        // a new voxel in a new chunk
        sample_at(&v, [127, 127, 127], 0xff00_0000);
        assert_eq!(v.publish(&at).0, 1);
        assert!(Arc::ptr_eq(&first, &v.chunks.chunks()[0]));
    }

    proptest! {
        #![proptest_config(ProptestConfig { failure_persistence: None, ..ProptestConfig::default() })]

        #[test]
        fn sparse_bits_is_a_set(cells in prop::collection::vec(prop::array::uniform3(0u32..64), 0..400)) {
            let mut s = SparseBits::default();
            let mut h = HashSet::new();
            for &c in &cells {
                prop_assert_eq!(s.insert(c), h.insert(c));
            }
            for &c in &cells {
                prop_assert!(s.contains(c));
            }
            prop_assert!(!s.contains([63, 63, 63]) || h.contains(&[63, 63, 63]));
        }

        #[test]
        fn sparse_index_is_a_map(cells in prop::collection::vec(prop::array::uniform3(0u32..64), 0..2000)) {
            let mut m = SparseIndex::default();
            let mut h = HashMap::new();
            for (i, &c) in cells.iter().enumerate() {
                let next = h.len() as u32;
                let got = m.get_or_insert(c, next);
                let want = match h.get(&c) {
                    Some(&v) => (v, false),
                    None => { h.insert(c, next); (next, true) }
                };
                prop_assert_eq!(got, want, "at {}", i);
            }
        }
    }
}
