//! The host's bookkeeping of the GPU progressive renderer's slots ([`SlotBook`]), besides the
//! state it shares with the CPU renderer ([`ProgressiveState`]: points loaded, Fill's cursor, the
//! slots drawn since the view changed): a bit per slot of what arrived (the CPU renderer reads it
//! from its words), the ranges of input indices that arrived ([`Ranges`]: duplicates and
//! recolouring are checked there), and Fill's runs split at the chunks of the shuffled buffer.

use super::insert::SortedSlots;
use mortar_core::render::progressive::ProgressiveState;
use std::sync::atomic::{AtomicU64, Ordering};

/// The host's bookkeeping of the slots that only the GPU renderer needs.
pub(super) struct SlotBook {
    /// A bit per slot: its point arrived.
    pub(super) loaded_bits: Vec<AtomicU64>,
    /// The input indices that arrived, as ranges (duplicates and recolouring are checked here).
    pub(super) arrived: Ranges,
}

/// A set of `u64` indices kept as disjoint, non-adjacent ranges `[start, end)`.
#[derive(Default)]
pub(super) struct Ranges(std::collections::BTreeMap<u64, u64>);

impl Ranges {
    /// The smallest index of `[s, e)` in the set.
    pub(super) fn first_in(&self, s: u64, e: u64) -> Option<u64> {
        if let Some((_, &end)) = self.0.range(..=s).next_back() {
            if end > s && s < e {
                return Some(s);
            }
        }
        self.0.range(s..e).next().map(|(&start, _)| start)
    }

    /// The smallest index of `[s, e)` not in the set.
    pub(super) fn first_missing(&self, s: u64, e: u64) -> Option<u64> {
        if s >= e {
            return None;
        }
        match self.0.range(..=s).next_back() {
            Some((_, &end)) if end > s => (end < e).then_some(end),
            _ => Some(s),
        }
    }

    /// Adds `[s, e)` (disjoint from the set), merging with the ranges it touches.
    pub(super) fn insert(&mut self, mut s: u64, mut e: u64) {
        if s >= e {
            return;
        }
        if let Some((&start, &end)) = self.0.range(..=s).next_back() {
            if end == s {
                self.0.remove(&start);
                s = start;
            }
        }
        if let Some(end) = self.0.remove(&e) {
            e = end;
        }
        self.0.insert(s, e);
    }
}

impl SlotBook {
    /// The bookkeeping of `slots` slots, none loaded.
    pub(super) fn new(slots: usize) -> SlotBook {
        SlotBook {
            loaded_bits: (0..slots.div_ceil(64)).map(|_| AtomicU64::new(0)).collect(),
            arrived: Ranges::default(),
        }
    }

    /// Whether slot `slot` holds a point.
    pub(super) fn is_loaded(&self, slot: u32) -> bool {
        self.loaded_bits
            .get(slot as usize / 64)
            .is_some_and(|w| w.load(Ordering::Relaxed) >> (slot % 64) & 1 == 1)
    }

    /// Records that input points `first..first + n`, whose slots are `slots`, arrived: their
    /// loaded bits and the range of input indices (the state counts them).
    pub(super) fn arrive(&mut self, first: u64, n: usize, slots: &SortedSlots) {
        slots.apply(&mut self.loaded_bits);
        self.arrived.insert(first, first + n as u64);
    }

    /// The runs of Fill for `count` slots from `state`'s cursor (wrapping around), split at chunk
    /// boundaries, as `(chunk, offset in chunk, slots)`; advances the cursor and marks the loaded
    /// slots drawn. Returns the runs and the points (loaded slots) among them. The chunks are
    /// those of the renderer: `chunk_slots` slots each, the last one the rest of the capacity.
    pub(super) fn sweep(
        &self,
        state: &mut ProgressiveState,
        count: u64,
        chunk_slots: u32,
    ) -> (Vec<(usize, u32, u32)>, u64) {
        let mut left = count.min(state.capacity());
        let mut runs = Vec::new();
        let mut points = 0;
        let bits = &self.loaded_bits;
        while left > 0 {
            let c = (state.cursor() / chunk_slots as u64) as usize;
            let chunk_first = c as u64 * chunk_slots as u64;
            let (s, e) = state.next_run(left, chunk_first + chunk_slots as u64);
            runs.push((c, (s - chunk_first) as u32, (e - s) as u32));
            points += state.mark_drawn(s as usize, e as usize, |w| bits[w].load(Ordering::Relaxed));
            left -= e - s;
            state.advance(e);
        }
        (runs, points)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mortar_core::grid::Grid;
    use mortar_core::render::progressive::{ProgressiveFrame, Shuffle};
    use mortar_core::render::{Aabb, Camera, RasterOptions, ViewPreset};

    /// The shared state of `capacity` slots.
    fn state(capacity: u64) -> ProgressiveState {
        let grid = Grid { scale: [0.01; 3], offset: [0.0; 3] };
        ProgressiveState::new(ProgressiveFrame::exact(grid, [0; 3], [100; 3]).unwrap(), capacity)
            .unwrap()
    }

    /// Input points `first..first + n` arrive at the slots `target` gives them.
    fn arrived(
        book: &mut SlotBook,
        state: &mut ProgressiveState,
        first: u32,
        n: usize,
        target: impl Fn(u32) -> u32 + Sync,
    ) {
        let slots = SortedSlots::new(book.loaded_bits.len(), first, n, target);
        book.arrive(first as u64, n, &slots);
        state.add_loaded(n);
    }

    fn drawn(state: &ProgressiveState) -> Vec<u32> {
        (0..state.capacity() as u32).filter(|&s| state.is_drawn(s)).collect()
    }

    #[test]
    fn ranges_merge_and_answer_first_in_and_first_missing() {
        let mut r = Ranges::default();
        assert_eq!(r.first_in(0, 10), None);
        assert_eq!(r.first_missing(0, 10), Some(0));
        assert_eq!(r.first_missing(5, 5), None);
        r.insert(10, 20);
        r.insert(30, 40);
        assert_eq!(r.first_in(0, 10), None);
        assert_eq!(r.first_in(0, 11), Some(10));
        assert_eq!(r.first_in(15, 16), Some(15));
        assert_eq!(r.first_in(20, 30), None);
        assert_eq!(r.first_in(25, 100), Some(30));
        assert_eq!(r.first_missing(10, 20), None);
        assert_eq!(r.first_missing(12, 25), Some(20));
        assert_eq!(r.first_missing(9, 12), Some(9));
        r.insert(20, 30);
        assert_eq!(r.0.len(), 1, "touching ranges merge: {:?}", r.0);
        assert_eq!(r.first_missing(10, 40), None);
        assert_eq!(r.first_missing(10, 41), Some(40));
        r.insert(0, 10);
        r.insert(40, 41);
        assert_eq!(r.0.iter().map(|(&a, &b)| (a, b)).collect::<Vec<_>>(), vec![(0, 41)]);
        // Empty ranges add nothing and hold nothing.
        r.insert(50, 50);
        assert_eq!(r.0.len(), 1);
        assert_eq!(r.first_in(7, 7), None);
    }

    /// Random disjoint pieces in a random order, against a bit per index: `first_in` and
    /// `first_missing` answer as a scan would, and the ranges stay disjoint and non-adjacent
    /// (as few as the pieces allow).
    #[test]
    fn ranges_answer_as_a_scan_of_the_indices() {
        let mut rng = mortar_core::render::testutil::Rng(7);
        for _ in 0..20 {
            let len = 1 + rng.next_u64() % 300;
            let mut cuts: Vec<u64> =
                (0..rng.next_u64() % 20).map(|_| rng.next_u64() % len).collect();
            cuts.extend([0, len]);
            cuts.sort_unstable();
            cuts.dedup();
            let mut pieces: Vec<(u64, u64)> = cuts.windows(2).map(|w| (w[0], w[1])).collect();
            for i in (1..pieces.len()).rev() {
                pieces.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
            }
            let mut r = Ranges::default();
            let mut held = vec![false; len as usize];
            for (k, &(a, b)) in pieces.iter().enumerate() {
                // Only some pieces arrive.
                if k % 3 == 2 {
                    continue;
                }
                r.insert(a, b);
                held[a as usize..b as usize].iter_mut().for_each(|h| *h = true);
                for _ in 0..30 {
                    let s = rng.next_u64() % (len + 1);
                    let e = s + rng.next_u64() % (len + 1 - s);
                    let scan_in = (s..e).find(|&i| held[i as usize]);
                    let scan_missing = (s..e).find(|&i| !held[i as usize]);
                    assert_eq!(r.first_in(s, e), scan_in, "[{s}, {e}) of {:?}", r.0);
                    assert_eq!(r.first_missing(s, e), scan_missing, "[{s}, {e}) of {:?}", r.0);
                }
                let ranges: Vec<(u64, u64)> = r.0.iter().map(|(&a, &b)| (a, b)).collect();
                assert!(ranges.iter().all(|(a, b)| a < b), "{ranges:?}");
                assert!(ranges.windows(2).all(|w| w[0].1 < w[1].0), "{ranges:?}");
                let runs = held.windows(2).filter(|w| w[1] && !w[0]).count() + held[0] as usize;
                assert_eq!(ranges.len(), runs, "{ranges:?}");
            }
        }
    }

    #[test]
    fn arrivals_set_loaded_bits_and_ranges() {
        let capacity = 1000u32;
        let shuffle = Shuffle::new(capacity);
        let mut book = SlotBook::new(capacity as usize);
        let mut st = state(capacity as u64);
        assert_eq!(book.loaded_bits.len(), 16);
        assert!((0..capacity).all(|s| !book.is_loaded(s)));
        arrived(&mut book, &mut st, 100, 250, |i| shuffle.target(i));
        arrived(&mut book, &mut st, 350, 50, |i| shuffle.target(i));
        assert_eq!(st.loaded(), 300);
        for i in 0..capacity {
            assert_eq!(book.is_loaded(shuffle.target(i)), (100..400).contains(&i), "point {i}");
        }
        // Past the last slot: not loaded (no panic).
        assert!(!book.is_loaded(capacity) && !book.is_loaded(u32::MAX));
        // The input indices that arrived: duplicates and what may be recoloured.
        assert_eq!(book.arrived.0.iter().map(|(&a, &b)| (a, b)).collect::<Vec<_>>(), [(100, 400)]);
        assert_eq!(book.arrived.first_in(0, 100), None);
        assert_eq!(book.arrived.first_in(0, 101), Some(100));
        assert_eq!(book.arrived.first_in(399, 500), Some(399));
        assert_eq!(book.arrived.first_missing(100, 400), None);
        assert_eq!(book.arrived.first_missing(150, 401), Some(400));
    }

    #[test]
    fn fill_runs_split_at_chunks_and_wrap_around() {
        // 10 slots in chunks of 4: [0, 4), [4, 8), [8, 10).
        let mut book = SlotBook::new(10);
        let mut st = state(10);
        arrived(&mut book, &mut st, 0, 10, |i| i);
        assert_eq!(book.sweep(&mut st, 6, 4), (vec![(0, 0, 4), (1, 0, 2)], 6));
        assert_eq!(st.cursor(), 6);
        assert!(!st.converged());
        // Through the end of the buffer and around.
        assert_eq!(book.sweep(&mut st, 6, 4), (vec![(1, 2, 2), (2, 0, 2), (0, 0, 2)], 6));
        assert_eq!(st.cursor(), 2);
        assert!(st.converged());
        // A budget past the capacity sweeps the buffer once.
        assert_eq!(
            book.sweep(&mut st, 25, 4),
            (vec![(0, 2, 2), (1, 0, 4), (2, 0, 2), (0, 0, 2)], 10)
        );
        assert_eq!(st.cursor(), 2);
        // Ending exactly at the end puts the cursor back at 0; a budget of 0 draws nothing.
        assert_eq!(book.sweep(&mut st, 8, 4), (vec![(0, 2, 2), (1, 0, 4), (2, 0, 2)], 8));
        assert_eq!(st.cursor(), 0);
        assert_eq!(book.sweep(&mut st, 0, 4), (vec![], 0));
        assert_eq!(st.cursor(), 0);
        // One chunk of every slot.
        let mut one = SlotBook::new(10);
        let mut st = state(10);
        arrived(&mut one, &mut st, 0, 10, |i| i);
        assert_eq!(one.sweep(&mut st, 7, 16), (vec![(0, 0, 7)], 7));
        assert_eq!(one.sweep(&mut st, 7, 16), (vec![(0, 7, 3), (0, 0, 4)], 7));
    }

    #[test]
    fn converges_once_every_slot_is_loaded_and_drawn_since_the_view_changed() {
        // Half the points arrived: Fill draws (and counts) only those, and a whole sweep does not
        // converge.
        let capacity = 300u32;
        let shuffle = Shuffle::new(capacity);
        let mut book = SlotBook::new(capacity as usize);
        let mut st = state(capacity as u64);
        let view = |w| {
            Camera::frame_orthographic(&Aabb::new([0.0; 3], [1.0; 3]), ViewPreset::Top, w, 16)
                .unwrap()
        };
        let options = RasterOptions::default();
        st.begin_frame(&view(16), &options);
        arrived(&mut book, &mut st, 0, 150, |i| shuffle.target(i));
        let (runs, points) = book.sweep(&mut st, capacity as u64, 128);
        assert_eq!(runs, vec![(0, 0, 128), (1, 0, 128), (2, 0, 44)]);
        assert_eq!(points, 150);
        assert_eq!(st.drawn(), 150);
        let d = drawn(&st);
        assert!(d.iter().all(|&s| book.is_loaded(s)) && d.len() == 150);
        assert!(!st.converged());
        // The rest arrives: the slots drawn stay drawn, the new ones are not yet, so no
        // convergence until Fill swept them.
        arrived(&mut book, &mut st, 150, 150, |i| shuffle.target(i));
        assert_eq!(st.loaded(), capacity as u64);
        st.begin_frame(&view(16), &options);
        assert!(!st.converged());
        let (_, points) = book.sweep(&mut st, 100, 128);
        assert_eq!(points, 100, "every slot holds a point now");
        assert!(!st.converged());
        book.sweep(&mut st, 200, 128);
        assert!(st.converged());
        // A new view starts over: nothing drawn since, the cursor stays where it was.
        let cursor = st.cursor();
        st.begin_frame(&view(32), &options);
        assert_eq!((st.drawn(), st.cursor()), (0, cursor));
        assert!(drawn(&st).is_empty() && !st.converged());
        book.sweep(&mut st, capacity as u64, 128);
        assert!(st.converged());
        // No slots: converged from the start, Fill draws nothing.
        let empty = SlotBook::new(0);
        let mut st = state(0);
        assert!(st.converged());
        assert_eq!(empty.sweep(&mut st, 10, 128), (vec![], 0));
    }
}
