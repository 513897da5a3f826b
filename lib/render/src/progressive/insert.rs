//! Insert preparation of the GPU progressive renderer: the costly, stateless half of an insert
//! ([`InsertPreparer::prepare`]: checks, the scatter records encoded, the slots sorted) that may
//! run on another thread, its result ([`PreparedInsert`]), and the slots sorted by region of the
//! host's bit array ([`SortedSlots`]).

use super::error::ProgressiveGpuError;
use super::options::ProgressiveOptions;
use crate::context::GpuError;
use mortar_core::quantize::BatchGrid;
use mortar_core::render::progressive::{ProgressiveError, Shuffle};
use rayon::prelude::*;
use std::sync::atomic::AtomicU64;

/// What [`GpuProgressive::preparer`](super::GpuProgressive::preparer) hands out: the numbers
/// [`prepare`](Self::prepare) needs and the renderer's pool of record buffers.
#[derive(Clone, Debug)]
pub struct InsertPreparer {
    pub(super) frame: BatchGrid,
    pub(super) frame_max: [i32; 3],
    pub(super) shuffle: Shuffle,
    pub(super) options: ProgressiveOptions,
    pub(super) bit_words: usize,
    pub(super) pool: RecordPool,
}

/// Record buffers handed back by
/// [`GpuProgressive::insert_prepared`](super::GpuProgressive::insert_prepared) for reuse.
pub(super) type RecordPool = std::sync::Arc<std::sync::Mutex<Vec<Vec<u32>>>>;

/// The scatter records of `xyz` (and `colors`) into `out`: per point its coarse, medium and fine
/// words and, with colours, the colour (3 or 4 words).
pub(super) fn encode_records(
    frame: &BatchGrid,
    xyz: &[[i32; 3]],
    colors: Option<&[u32]>,
    out: &mut [u32],
) {
    let stride = 3 + colors.is_some() as usize;
    for (k, r) in out.chunks_exact_mut(stride).enumerate() {
        r[..3].copy_from_slice(&frame.encode(xyz[k]));
        if let Some(c) = colors {
            r[3] = c[k];
        }
    }
}

thread_local! {
    /// Each thread's buffer for records encoded before they are copied into staging memory.
    pub(super) static ENCODED: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Points ready for [`GpuProgressive::insert_prepared`](super::GpuProgressive::insert_prepared):
/// their words (and colours) staged in input order and their slots sorted by region of the host's
/// bit array.
pub struct PreparedInsert {
    /// The renderer it was prepared for: capacity, colours, payloads, frame.
    pub(super) of: (u32, bool, bool, [i32; 3], [i32; 3]),
    pub(super) first: u64,
    pub(super) n: usize,
    pub(super) stride: usize,
    pub(super) records: Vec<u32>,
    pub(super) slots: SortedSlots,
    pub(super) payload: Option<Vec<u64>>,
}

impl PreparedInsert {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.n
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Input index of the first point.
    pub fn first(&self) -> u64 {
        self.first
    }
}

impl InsertPreparer {
    /// The checks of an insert that need no state: colours and payloads as the renderer was
    /// made, the index range, every point inside the frame.
    pub(super) fn check(
        &self,
        first: u64,
        xyz: &[[i32; 3]],
        colors: Option<&[u32]>,
        payload: Option<&[u64]>,
        in_frame: bool,
    ) -> Result<(), ProgressiveGpuError> {
        let n = xyz.len();
        match (self.options.colors, colors) {
            (true, Some(c)) if c.len() == n => {}
            (true, Some(c)) => {
                return Err(GpuError::Colors(format!("{} colours for {n} points", c.len())).into())
            }
            (true, None) => {
                return Err(GpuError::Colors(
                    "the renderer has colours but points came without".into(),
                )
                .into())
            }
            (false, Some(_)) => {
                return Err(GpuError::Colors("the renderer was made without colours".into()).into())
            }
            (false, None) => {}
        }
        match (self.options.payloads, payload) {
            (true, Some(p)) if p.len() != n => {
                return Err(ProgressiveError::PayloadCount { points: n, payloads: p.len() }.into())
            }
            (true, None) => {
                return Err(ProgressiveError::PayloadCount { points: n, payloads: 0 }.into())
            }
            (false, Some(p)) => {
                return Err(ProgressiveError::PayloadCount { points: n, payloads: p.len() }.into())
            }
            _ => {}
        }
        let capacity = self.shuffle.len() as u64;
        let end = first.saturating_add(n as u64);
        if end > capacity {
            return Err(ProgressiveError::IndexRange { first, end, capacity }.into());
        }
        let (min, max) = (self.frame.min, self.frame_max);
        if !in_frame {
            return Ok(());
        }
        if let Some(k) =
            xyz.par_iter().position_first(|p| (0..3).any(|a| p[a] < min[a] || p[a] > max[a]))
        {
            return Err(ProgressiveError::OutsideFrame {
                index: first + k as u64,
                point: xyz[k],
                min,
                max,
            }
            .into());
        }
        Ok(())
    }

    /// The costly, stateless half of [`GpuProgressive::insert`](super::GpuProgressive::insert),
    /// which may run on any thread while frames are drawn: checks the points (colours and payloads
    /// as the renderer was made, index range, inside the frame), encodes their words, computes and
    /// sorts their slots. Duplicates are checked by
    /// [`GpuProgressive::insert_prepared`](super::GpuProgressive::insert_prepared).
    pub fn prepare(
        &self,
        first: u64,
        xyz: &[[i32; 3]],
        colors: Option<&[u32]>,
        payload: Option<&[u64]>,
    ) -> Result<PreparedInsert, ProgressiveGpuError> {
        self.check(first, xyz, colors, payload, true)?;
        let n = xyz.len();
        let (min, max) = (self.frame.min, self.frame_max);
        let stride = 3 + colors.is_some() as usize;
        // A buffer handed back by an earlier insert if there is one (its pages are mapped).
        let mut records = self.pool.lock().ok().and_then(|mut p| p.pop()).unwrap_or_default();
        records.resize(n * stride, 0);
        let frame = self.frame;
        const PIECE: usize = 1 << 14;
        records.par_chunks_mut(PIECE * stride).enumerate().for_each(|(j, out)| {
            let (a, b) = (j * PIECE, (j * PIECE + PIECE).min(n));
            encode_records(&frame, &xyz[a..b], colors.map(|c| &c[a..b]), out);
        });
        let shuffle = self.shuffle;
        Ok(PreparedInsert {
            of: (self.shuffle.len(), self.options.colors, self.options.payloads, min, max),
            first,
            n,
            stride,
            records,
            slots: SortedSlots::new(self.bit_words, first as u32, n, |i| shuffle.target(i)),
            payload: payload.map(<[u64]>::to_vec),
        })
    }
}

/// The slots `target(first + k)`, `k < n`, sorted by region of a bit array of `words` words, per
/// task (a counting sort), ready to set their bits. The slots are random: one atomic OR per slot
/// costs a locked cache miss each (55 M points/s on two cores); setting each region's bits from
/// one thread, which owns its words and keeps them in cache, is about twice as fast with the
/// sort included, and the sort can run on another thread than the one that owns the bits.
pub(super) struct SortedSlots {
    /// Regions of 2^shift slots (whole words: shift >= 6), at most about 4096 of them.
    shift: u32,
    /// Per task: its slots by region, and where each region starts.
    tasks: Vec<(Vec<u32>, Vec<u32>)>,
}

impl SortedSlots {
    pub(super) fn new(
        words: usize,
        first: u32,
        n: usize,
        target: impl Fn(u32) -> u32 + Sync,
    ) -> SortedSlots {
        const TASK: usize = 1 << 16;
        let slots = words as u64 * 64;
        let shift = (64 - slots.saturating_sub(1).leading_zeros()).saturating_sub(12).max(14);
        let regions = (slots >> shift) as usize + 1;
        let tasks = (0..n)
            .step_by(TASK)
            .collect::<Vec<_>>()
            .into_par_iter()
            .map(|s| {
                let m = (n - s).min(TASK);
                let targets: Vec<u32> = (0..m).map(|k| target(first + (s + k) as u32)).collect();
                let mut starts = vec![0u32; regions + 1];
                for &t in &targets {
                    starts[(t >> shift) as usize + 1] += 1;
                }
                for r in 0..regions {
                    starts[r + 1] += starts[r];
                }
                let mut next = starts.clone();
                let mut out = vec![0u32; m];
                for &t in &targets {
                    let r = (t >> shift) as usize;
                    out[next[r] as usize] = t;
                    next[r] += 1;
                }
                (out, starts)
            })
            .collect();
        SortedSlots { shift, tasks }
    }

    /// Sets the slots' bits in `bits` (the array of `words` words they were sorted for).
    pub(super) fn apply(&self, bits: &mut [AtomicU64]) {
        if self.tasks.is_empty() {
            return;
        }
        let words = 1usize << (self.shift - 6);
        bits.par_chunks_mut(words).enumerate().for_each(|(r, region)| {
            let base = r * words;
            for (out, starts) in &self.tasks {
                for &t in &out[starts[r] as usize..starts[r + 1] as usize] {
                    *region[t as usize / 64 - base].get_mut() |= 1 << (t % 64);
                }
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::Ordering;

    /// The bits sorted slots set equal one OR per slot, for one and many tasks and capacities
    /// that do and do not fill the last region.
    #[test]
    fn sorted_slots_set_the_same_bits_as_one_or_per_slot() {
        for (capacity, first, n) in [
            (3u32, 0u32, 0usize),
            (1000, 10, 900),
            (300_000, 0, 300_000),
            (1 << 20, 5, 600_000),
            ((1 << 22) + 77, 123_456, 2_000_000),
        ] {
            let shuffle = Shuffle::new(capacity);
            let words = (capacity as usize).div_ceil(64);
            let mut bits: Vec<AtomicU64> = (0..words).map(|_| AtomicU64::new(0)).collect();
            SortedSlots::new(words, first, n, |t| shuffle.target(t)).apply(&mut bits);
            let mut want = vec![0u64; words];
            for k in 0..n {
                let t = shuffle.target(first + k as u32);
                want[t as usize / 64] |= 1 << (t % 64);
            }
            let got: Vec<u64> = bits.iter().map(|w| w.load(Ordering::Relaxed)).collect();
            assert_eq!(got, want, "capacity {capacity}");
            assert_eq!(got.iter().map(|w| w.count_ones() as usize).sum::<usize>(), n);
        }
    }
}
