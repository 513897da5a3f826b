//! The progressive state that the CPU renderer and its GPU twin share ([`ProgressiveState`]): the
//! shuffle, the quantization frame and how often it grew, the points loaded, Fill's cursor, the
//! view of the last frame, a bit per slot drawn since that view last changed (the convergence
//! test), the frame count and the time the last frame spent after its Fill. Both renderers keep
//! their buffers (the CPU's words and payloads in memory, the GPU's chunks and its own bit per
//! slot of what arrived) and drive this state the same way, so that they sweep, mark and converge
//! alike: the same keys frame by frame for the same budgets.

use super::budget::{AdaptiveBudget, FillBudget};
use super::error::ProgressiveError;
use super::frame::{piece_box, ProgressiveFrame};
use super::shuffle::Shuffle;
use super::stats::FrameStats;
use crate::render::camera::Camera;
use crate::render::plan::RasterOptions;
use rayon::prelude::*;

/// What a progressive renderer of paper 000 knows besides its point buffer: see the module
/// documentation.
#[derive(Clone, Debug)]
pub struct ProgressiveState {
    frame: ProgressiveFrame,
    /// Times the frame grew.
    grown: u32,
    shuffle: Shuffle,
    /// Points inserted so far.
    loaded: u64,
    /// Next slot Fill draws.
    cursor: u64,
    /// The camera and options of the last frame (`None` before the first and after the frame
    /// grew).
    view: Option<(Camera, RasterOptions)>,
    /// Slots drawn since the view last changed (bit per slot), and how many.
    done: Vec<u64>,
    done_count: u64,
    frames: u64,
    /// Time of the last frame's work after Fill (Prepare, and the resolve where drawn), ms: the
    /// adaptive budget's `after_fill_ms`.
    after_fill_ms: f64,
}

impl ProgressiveState {
    /// The state of a renderer for `capacity` points in `frame`: nothing loaded or drawn yet.
    /// Refuses more points than 32-bit indices address.
    pub fn new(
        frame: ProgressiveFrame,
        capacity: u64,
    ) -> Result<ProgressiveState, ProgressiveError> {
        let len = u32::try_from(capacity).map_err(|_| ProgressiveError::TooManyPoints(capacity))?;
        Ok(ProgressiveState {
            frame,
            grown: 0,
            shuffle: Shuffle::new(len),
            loaded: 0,
            cursor: 0,
            view: None,
            done: vec![0; (len as usize).div_ceil(64)],
            done_count: 0,
            frames: 0,
            after_fill_ms: 0.0,
        })
    }

    /// Number of points the renderer holds once everything arrived.
    pub fn capacity(&self) -> u64 {
        self.shuffle.len() as u64
    }

    /// Points inserted so far.
    pub fn loaded(&self) -> u64 {
        self.loaded
    }

    /// Whether every point arrived.
    pub fn all_loaded(&self) -> bool {
        self.loaded == self.capacity()
    }

    /// The shuffle placing input index `i` at slot `shuffle().target(i)`.
    pub fn shuffle(&self) -> &Shuffle {
        &self.shuffle
    }

    /// The frame: quantization, bounds, and the box of the points expected and arrived.
    pub fn frame(&self) -> &ProgressiveFrame {
        &self.frame
    }

    /// How often the frame grew to hold points outside it.
    pub fn growths(&self) -> u32 {
        self.grown
    }

    /// Frames drawn so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// The camera and options of the last frame, if one was drawn since the frame last grew.
    pub fn view(&self) -> Option<(Camera, RasterOptions)> {
        self.view
    }

    /// Next slot Fill draws.
    pub fn cursor(&self) -> u64 {
        self.cursor
    }

    /// Slots drawn since the view last changed.
    pub fn drawn(&self) -> u64 {
        self.done_count
    }

    /// Whether slot `slot` was drawn since the view last changed.
    pub fn is_drawn(&self, slot: u32) -> bool {
        self.done.get(slot as usize / 64).is_some_and(|w| w >> (slot % 64) & 1 == 1)
    }

    /// Whether the last frame's image is final (see [`FrameStats::converged`]): every slot loaded
    /// and drawn since the view last changed.
    pub fn converged(&self) -> bool {
        self.loaded == self.capacity() && self.done_count == self.capacity()
    }

    /// Time of the last frame's work after Fill, ms (the adaptive budget's `after_fill_ms`).
    pub fn after_fill_ms(&self) -> f64 {
        self.after_fill_ms
    }

    /// Sets the time of this frame's work after Fill, ms, for the next frame's budget.
    pub fn set_after_fill_ms(&mut self, ms: f64) {
        self.after_fill_ms = ms;
    }

    /// Refuses input points `first..first + n` past the capacity; returns one past the last.
    pub fn check_range(&self, first: u64, n: usize) -> Result<u64, ProgressiveError> {
        let end = first.saturating_add(n as u64);
        if end > self.capacity() {
            return Err(ProgressiveError::IndexRange { first, end, capacity: self.capacity() });
        }
        Ok(end)
    }

    /// Grows the frame to hold the points `xyz` about to be inserted, as [`ProgressiveFrame`]
    /// grows: when they lie outside it, `reencode(from, to)` moves the words held into the
    /// larger frame (if it fails, nothing changed), then the view is forgotten (the planner's
    /// bounds changed, so convergence starts over); the box of the points arrived takes theirs
    /// in. Fails unchanged when the frame would need more than 30 bits on an axis.
    pub fn grow_for<E: From<ProgressiveError>>(
        &mut self,
        xyz: &[[i32; 3]],
        reencode: impl FnOnce(&ProgressiveFrame, &ProgressiveFrame) -> Result<(), E>,
    ) -> Result<(), E> {
        if let Some(b) = piece_box(xyz) {
            if let Some(grown) = self.frame.grown(b)? {
                reencode(&self.frame, &grown)?;
                self.frame = grown;
                self.view = None;
                self.grown += 1;
            }
            self.frame.data = self.frame.data.union(b);
        }
        Ok(())
    }

    /// Counts `n` points inserted (their slots were free).
    pub fn add_loaded(&mut self, n: usize) {
        self.loaded += n as u64;
    }

    /// Begins a frame for `camera` and `options`: a change of view starts convergence over (no
    /// slot drawn since); returns the frame's statistics so far (its number, the points loaded).
    pub fn begin_frame(&mut self, camera: &Camera, options: &RasterOptions) -> FrameStats {
        if self.view != Some((*camera, *options)) {
            self.view = Some((*camera, *options));
            self.done.par_iter_mut().with_min_len(1 << 14).for_each(|w| *w = 0);
            self.done_count = 0;
        }
        self.frames += 1;
        FrameStats { frame: self.frames, loaded: self.loaded, ..FrameStats::default() }
    }

    /// The slots Fill draws first with `budget` (at most the capacity) and, for the adaptive
    /// budget, the budget that decides how many more.
    pub fn first_fill(&self, budget: &FillBudget) -> (u64, Option<AdaptiveBudget>) {
        match budget {
            FillBudget::Fixed(b) => (*b, None),
            FillBudget::Adaptive(a) => (a.probe_points.min(self.capacity()), Some(*a)),
        }
    }

    /// The next run of Fill for `left` more slots: `[cursor, e)`, `e` the first of
    /// `cursor + left`, `limit` (a boundary the caller splits at) and the end of the buffer.
    /// [`advance`](Self::advance) moves the cursor past it once drawn.
    pub fn next_run(&self, left: u64, limit: u64) -> (u64, u64) {
        let s = self.cursor;
        (s, (s + left).min(limit).min(self.capacity()))
    }

    /// Moves Fill's cursor to `e`, the end of the run just drawn (back to slot 0 at the end of
    /// the buffer).
    pub fn advance(&mut self, e: u64) {
        self.cursor = if e == self.capacity() { 0 } else { e };
    }

    /// Marks the loaded slots of `[s, e)` drawn since the view changed; returns how many there
    /// are. Before every point arrived, word `w` of the slots' loaded bits is `loaded(w)`; after,
    /// every slot is loaded and `loaded` is not called.
    pub fn mark_drawn(&mut self, s: usize, e: usize, loaded: impl Fn(usize) -> u64 + Sync) -> u64 {
        let all = self.loaded == self.capacity();
        let (ws, we) = (s / 64, e.div_ceil(64));
        let (points, new): (u64, u64) = self.done[ws..we]
            .par_iter_mut()
            .enumerate()
            .with_min_len(1024)
            .map(|(k, d)| {
                let w = ws + k;
                let lo = s.max(w * 64) - w * 64;
                let hi = e.min(w * 64 + 64) - w * 64;
                let range = if hi - lo == 64 { u64::MAX } else { ((1u64 << (hi - lo)) - 1) << lo };
                let mask = if all { range } else { range & loaded(w) };
                let new = (mask & !*d).count_ones() as u64;
                *d |= mask;
                (mask.count_ones() as u64, new)
            })
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        self.done_count += new;
        points
    }

    /// Marks one slot drawn since the view changed.
    pub fn mark_slot(&mut self, slot: u32) {
        let (w, b) = (slot as usize / 64, slot % 64);
        if self.done[w] & (1 << b) == 0 {
            self.done[w] |= 1 << b;
            self.done_count += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;
    use crate::render::camera::ViewPreset;
    use crate::render::framing::IntBox;
    use crate::render::math::Aabb;

    const GRID: Grid = Grid { scale: [0.01; 3], offset: [0.0; 3] };

    fn state(capacity: u64) -> ProgressiveState {
        ProgressiveState::new(ProgressiveFrame::exact(GRID, [0; 3], [100; 3]).unwrap(), capacity)
            .unwrap()
    }

    fn camera(width: u32) -> Camera {
        Camera::frame_orthographic(&Aabb::new([0.0; 3], [1.0; 3]), ViewPreset::Top, width, 16)
            .unwrap()
    }

    fn drawn_slots(st: &ProgressiveState) -> Vec<u32> {
        (0..st.capacity() as u32).filter(|&s| st.is_drawn(s)).collect()
    }

    /// The runs of Fill for `count` slots, as a renderer sweeps them (every slot loaded).
    fn sweep(st: &mut ProgressiveState, count: u64) -> Vec<(u64, u64)> {
        let mut left = count.min(st.capacity());
        let mut runs = Vec::new();
        while left > 0 {
            let (s, e) = st.next_run(left, u64::MAX);
            st.mark_drawn(s as usize, e as usize, |_| u64::MAX);
            runs.push((s, e));
            left -= e - s;
            st.advance(e);
        }
        runs
    }

    #[test]
    fn a_new_state_holds_nothing_and_refuses_too_many_points() {
        let st = state(1000);
        assert_eq!((st.capacity(), st.loaded(), st.cursor(), st.drawn()), (1000, 0, 0, 0));
        assert_eq!((st.frames(), st.growths(), st.view()), (0, 0, None));
        assert_eq!(*st.shuffle(), Shuffle::new(1000));
        assert_eq!(st.frame().max, [100; 3]);
        assert!(!st.converged() && !st.all_loaded());
        assert!(matches!(
            ProgressiveState::new(*st.frame(), 1 << 32),
            Err(ProgressiveError::TooManyPoints(_))
        ));
        // No points: converged from the start.
        assert!(state(0).converged());
    }

    #[test]
    fn index_ranges_past_the_capacity_are_refused() {
        let st = state(10);
        assert_eq!(st.check_range(0, 10), Ok(10));
        assert_eq!(st.check_range(4, 3), Ok(7));
        assert_eq!(st.check_range(10, 0), Ok(10));
        assert_eq!(
            st.check_range(9, 2),
            Err(ProgressiveError::IndexRange { first: 9, end: 11, capacity: 10 })
        );
        assert!(matches!(st.check_range(u64::MAX, 2), Err(ProgressiveError::IndexRange { .. })));
    }

    #[test]
    fn runs_wrap_around_and_split_at_the_limit() {
        let mut st = state(10);
        assert_eq!(sweep(&mut st, 6), [(0, 6)]);
        assert_eq!(st.cursor(), 6);
        assert_eq!(sweep(&mut st, 6), [(6, 10), (0, 2)]);
        assert_eq!(st.cursor(), 2);
        // More than the capacity: the buffer once.
        assert_eq!(sweep(&mut st, 25), [(2, 10), (0, 2)]);
        // Ending at the end of the buffer puts the cursor back at 0.
        assert_eq!(sweep(&mut st, 8), [(2, 10)]);
        assert_eq!(st.cursor(), 0);
        // A limit (a chunk boundary) ends a run early.
        assert_eq!(st.next_run(8, 4), (0, 4));
        assert_eq!(st.next_run(3, 4), (0, 3));
        st.advance(4);
        assert_eq!(st.next_run(100, 8), (4, 8));
        assert_eq!(st.next_run(100, 20), (4, 10));
    }

    #[test]
    fn marks_count_the_loaded_slots_and_the_new_ones() {
        let mut st = state(200);
        // Before every point arrived, only the slots with a loaded bit are drawn.
        st.add_loaded(100);
        let loaded = |w: usize| [0x5555_5555_5555_5555u64, u64::MAX, 0, 0xff][w];
        assert_eq!(st.mark_drawn(60, 130, loaded), 2 + 64);
        assert_eq!(st.drawn(), 66);
        assert_eq!(st.mark_drawn(0, 200, loaded), 32 + 64 + 8);
        assert_eq!(st.drawn(), 32 + 64 + 8, "slots 60 and 62 were drawn already");
        let want: Vec<u32> = (0..64).step_by(2).chain(64..128).chain(192..200).collect();
        assert_eq!(drawn_slots(&st), want);
        // Once every point arrived, every slot of a run counts (the bits are not read).
        st.add_loaded(100);
        assert!(st.all_loaded());
        let mut st2 = state(200);
        st2.add_loaded(200);
        assert_eq!(st2.mark_drawn(60, 130, |_| unreachable!()), 70);
        assert_eq!(st2.mark_drawn(100, 140, |_| unreachable!()), 40);
        assert_eq!(st2.drawn(), 80, "only the new slots are counted");
        assert_eq!(drawn_slots(&st2), (60..140).collect::<Vec<_>>());
        assert_eq!(st2.mark_drawn(64, 64, |_| unreachable!()), 0);
        // One slot at a time, once each.
        st2.mark_slot(0);
        st2.mark_slot(0);
        st2.mark_slot(199);
        assert_eq!(st2.drawn(), 82);
        assert!(st2.is_drawn(0) && st2.is_drawn(199) && !st2.is_drawn(1) && !st2.is_drawn(200));
    }

    #[test]
    fn converges_once_every_slot_is_loaded_and_drawn_since_the_view_changed() {
        let mut st = state(300);
        let (a, b) = (camera(16), camera(32));
        let options = RasterOptions::default();
        // Half loaded (slots 0..150): a whole sweep draws that half and does not converge.
        st.add_loaded(150);
        let f = st.begin_frame(&a, &options);
        assert_eq!((f.frame, f.loaded, f.converged), (1, 150, false));
        assert_eq!(st.view(), Some((a, options)));
        let half = |w: usize| [u64::MAX, u64::MAX, (1 << 22) - 1, 0, 0][w];
        assert_eq!(st.mark_drawn(0, 300, half), 150);
        assert_eq!(drawn_slots(&st), (0..150).collect::<Vec<_>>());
        assert!(!st.converged());
        // Everything arrived; the same view keeps what was drawn, and one more sweep of the
        // other half converges.
        st.add_loaded(150);
        let f = st.begin_frame(&a, &options);
        assert_eq!((f.frame, f.loaded), (2, 300));
        assert_eq!(st.drawn(), 150, "the same view keeps what was drawn");
        assert!(!st.converged());
        assert_eq!(st.mark_drawn(150, 300, |_| unreachable!()), 150);
        assert!(st.converged());
        // A new view starts over (Fill's cursor stays), then converges after one sweep.
        st.advance(123);
        st.begin_frame(&b, &options);
        assert_eq!((st.drawn(), st.cursor(), st.frames()), (0, 123, 3));
        assert!(!st.converged() && drawn_slots(&st).is_empty());
        sweep(&mut st, 299);
        assert!(!st.converged());
        sweep(&mut st, 1);
        assert!(st.converged());
        // Other options are another view too.
        let cull = RasterOptions { cull: !options.cull, ..options };
        st.begin_frame(&b, &cull);
        assert!(!st.converged());
    }

    #[test]
    fn the_frame_grows_for_points_outside_it_and_forgets_the_view() {
        let mut st = state(10);
        let options = RasterOptions::default();
        st.begin_frame(&camera(16), &options);
        // Inside: no re-encoding, the box of the arrived points takes theirs in.
        let mut calls = 0;
        st.grow_for(&[[1, 2, 3], [4, 5, 6]], |_, _| {
            calls += 1;
            Ok::<(), ProgressiveError>(())
        })
        .unwrap();
        assert_eq!((calls, st.growths()), (0, 0));
        assert!(st.view().is_some());
        assert_eq!(st.frame().data, IntBox { min: [0; 3], max: [100; 3] });
        // No points: nothing happens.
        st.grow_for(&[], |_, _| -> Result<(), ProgressiveError> { unreachable!() }).unwrap();
        // Outside: re-encoded from the old frame into the new one, which holds the points; the
        // view is forgotten (convergence starts over).
        let before = *st.frame();
        let mut seen = None;
        st.grow_for(&[[-50, 0, 0], [300, 0, 0]], |from, to| {
            seen = Some((*from, *to));
            Ok::<(), ProgressiveError>(())
        })
        .unwrap();
        let (from, to) = seen.unwrap();
        assert_eq!(from, before);
        assert_eq!(*st.frame(), to);
        assert!(to.holds(&[-50, 0, 0]) && to.holds(&[300, 0, 0]));
        assert_eq!(st.frame().data, IntBox { min: [-50, 0, 0], max: [300, 100, 100] });
        assert_eq!((st.growths(), st.view()), (1, None));
        // A failed re-encoding, or a frame past 30 bits, leaves everything as it was.
        let before = st.clone();
        let failed = st.grow_for(&[[5000, 0, 0]], |_, _| Err(ProgressiveError::Duplicate(7)));
        assert_eq!(failed, Err(ProgressiveError::Duplicate(7)));
        let wide = st.grow_for(&[[1 << 30, 0, 0]], |_, _| -> Result<(), ProgressiveError> {
            unreachable!()
        });
        assert!(matches!(wide, Err(ProgressiveError::Frame { .. })));
        assert_eq!(
            (*st.frame(), st.growths(), st.view()),
            (*before.frame(), before.growths(), before.view())
        );
    }

    #[test]
    fn the_first_fill_is_the_fixed_budget_or_the_probe() {
        let st = state(1000);
        assert_eq!(st.first_fill(&FillBudget::Fixed(5000)), (5000, None));
        let a = AdaptiveBudget { target_ms: 10.0, probe_points: 300, usable: 0.5 };
        assert_eq!(st.first_fill(&FillBudget::Adaptive(a)), (300, Some(a)));
        let big = AdaptiveBudget { probe_points: 1 << 40, ..a };
        assert_eq!(st.first_fill(&FillBudget::Adaptive(big)), (1000, Some(big)));
        let mut st = st;
        assert_eq!(st.after_fill_ms(), 0.0);
        st.set_after_fill_ms(2.5);
        assert_eq!(st.after_fill_ms(), 2.5);
    }
}
