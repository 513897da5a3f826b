//! The progressive renderer of paper 000 (Schütz et al., "Progressive Real-Time Rendering of One
//! Billion Points Without Hierarchical Acceleration Structures"), on the CPU rasterizer.
//!
//! - [`Shuffle`]: the incremental shuffle of §3.3. A point's index `i` in the input becomes its
//!   position `targetIndex(i) = permute(permute(i))` in the shuffled buffer (eq. 2), where
//!   `permute` is Preshing's quadratic-residue permutation modulo the largest prime
//!   `P ≡ 3 (mod 4)` with `P <= N` (eq. 1); the points `i >= P` past that prime keep their
//!   position, as the paper does ("shuffle all the points in that range, and leave the remaining
//!   points unshuffled"). Each point's position depends on its index alone, so points are placed
//!   as they arrive, in any order.
//! - [`ProgressiveRenderer`]: the shuffled buffer in memory (three 10-bit coordinate words per
//!   point in one quantization frame over the whole data set, plus a 64-bit payload the caller
//!   turns into colours) and, per frame (§3.4), **Reproject** (draw the points that were visible at
//!   the end of the previous frame, from their original coordinates and with their shuffled
//!   index), **Fill** (draw the next `budget` slots of the shuffled buffer, wrapping around; slots
//!   whose point has not arrived yet are skipped, as the paper discards default-initialized
//!   vertices) and **Prepare** (collect the indices of the points that won a pixel: the next
//!   frame's Reproject buffer).
//! - [`ProgressiveFrame`]: the one quantization frame of the shuffled buffer, which grows when
//!   points arrive outside it (headers lie) instead of refusing them.
//! - [`AdaptiveBudget`]: the adaptive fill budget of §3.4.1: fill a fixed number of points first,
//!   measure how long that took, and fill as many more as fit in the time left in the frame. The
//!   timings are plain numbers ([`ProbeTimings`]), so a GPU renderer can feed it timestamp-query
//!   deltas; the CPU renderer here feeds it wall-clock time.
//!
//! Exactness: every draw (Fill through [`rasterize`], Reproject through [`rasterize_gathered`])
//! uses the same quantization frame and bounds, so the [`Planner`](super::Planner) makes the same
//! decisions and the per-point loop produces the same 64-bit depth|index key for a point
//! whichever pass draws it. With a still camera, each pixel therefore holds the minimum key over
//! every point drawn since the camera stopped, and once every slot was filled the framebuffer
//! equals the brute-force [`rasterize`] of all points in this frame, key for key
//! ([`ProgressiveRenderer::all_points`] gives that reference). [`FrameStats::converged`] says when
//! that is the case (a bitmap of the slots drawn since the view last changed). Since a point's key
//! depends on the point and the camera alone (`plan::plan_batch` anchors every batch at the eye),
//! it is also the brute force of a batch file of the same points, but where two points tie in
//! depth and the two numberings pick differently ([`ProgressiveRenderer::depth_ties`] counts the
//! pixels with a tie).
//!
//! The GPU twin is `mortar_render::progressive::GpuProgressive` (the same passes as compute
//! shaders, the same [`Shuffle`] and [`UNLOADED`] sentinel, one plan for all slots, GPU timestamps
//! feeding [`AdaptiveBudget`]); its keys equal this renderer's frame by frame for the same budgets.
//!
//! The interactive window (`mortar view` on raw LAS/LAZ) drives this renderer or its GPU twin
//! (mortar-app's `viewer::progressive`). Not implemented: MSAA (paper §3.4: it acts as
//! supersampling).

use super::camera::Camera;
use super::error::RasterError;
use super::framebuffer::{key_index, Framebuffer, EMPTY_KEY};
use super::framing::IntBox;
use super::math::Aabb;
use super::plan::RasterOptions;
use super::raster::{
    count_depth_ties, rasterize, rasterize_gathered, BatchRef, GatheredRef, RasterStats,
};
use crate::grid::Grid;
use crate::par::SendPtr;
use crate::quantize::BatchGrid;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

// ---------------------------------------------------------------------------------------------
// The shuffle (§3.3, eq. 1-2)
// ---------------------------------------------------------------------------------------------

/// `a * b mod m` without overflow.
#[inline]
fn mul_mod(a: u64, b: u64, m: u64) -> u64 {
    ((a as u128 * b as u128) % m as u128) as u64
}

fn pow_mod(mut b: u64, mut e: u64, m: u64) -> u64 {
    let mut r = 1 % m;
    b %= m;
    while e > 0 {
        if e & 1 == 1 {
            r = mul_mod(r, b, m);
        }
        b = mul_mod(b, b, m);
        e >>= 1;
    }
    r
}

/// Whether `n` is prime: deterministic Miller-Rabin for every `u64` (the seven bases of Jim
/// Sinclair are a certificate below 2^64).
// `is_multiple_of` needs Rust 1.87; the workspace supports 1.85.
#[allow(clippy::manual_is_multiple_of)]
pub fn is_prime(n: u64) -> bool {
    if n < 2 {
        return false;
    }
    for p in [2u64, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37] {
        if n % p == 0 {
            return n == p;
        }
    }
    let mut d = n - 1;
    let mut s = 0;
    while d % 2 == 0 {
        d /= 2;
        s += 1;
    }
    'bases: for a in [2u64, 325, 9375, 28178, 450775, 9780504, 1795265022] {
        let a = a % n;
        if a == 0 {
            continue;
        }
        let mut x = pow_mod(a, d, n);
        if x == 1 || x == n - 1 {
            continue;
        }
        for _ in 1..s {
            x = mul_mod(x, x, n);
            if x == n - 1 {
                continue 'bases;
            }
        }
        return false;
    }
    true
}

/// The largest prime `P <= n` with `P ≡ 3 (mod 4)` (the primes eq. 1 permutes over), `None` for
/// `n < 3`.
pub fn largest_prime_3_mod_4(n: u64) -> Option<u64> {
    if n < 3 {
        return None;
    }
    // The largest candidate <= n that is 3 mod 4, then every fourth number below it.
    let mut p = n - (n + 1) % 4;
    loop {
        if is_prime(p) {
            return Some(p);
        }
        p -= 4; // p >= 3 always: 3 is prime and ends the loop.
    }
}

/// The incremental shuffle of paper 000 §3.3 over `0..len`: a bijection computed per index, with
/// no state shared between indices.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shuffle {
    len: u32,
    /// The prime `P ≡ 3 (mod 4)`, `P <= len`, or 0 when there is none (`len < 3`).
    prime: u32,
}

impl Shuffle {
    /// The shuffle of `len` points (indices are 32-bit, as in the framebuffer's keys).
    pub fn new(len: u32) -> Shuffle {
        let prime = largest_prime_3_mod_4(len as u64).unwrap_or(0) as u32;
        Shuffle { len, prime }
    }

    /// Number of points.
    pub fn len(&self) -> u32 {
        self.len
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The prime of eq. 1, `None` below 3 points.
    pub fn prime(&self) -> Option<u32> {
        (self.prime != 0).then_some(self.prime)
    }

    /// Points past the prime, which keep their position (at most 532 below 500 M points, §3.3).
    pub fn unshuffled(&self) -> u32 {
        self.len - self.prime
    }

    /// Eq. 1: `i^2 mod P` for `i <= P/2`, `P - (i^2 mod P)` for `P/2 < i < P`, `i` otherwise.
    #[inline]
    pub fn permute(&self, i: u32) -> u32 {
        let p = self.prime as u64;
        let i = i as u64;
        if i >= p {
            return i as u32;
        }
        // i < P < 2^32, so i^2 < 2^64.
        let residue = (i * i) % p;
        (if 2 * i <= p { residue } else { p - residue }) as u32
    }

    /// Eq. 2: the position of point `i` in the shuffled buffer, `permute(permute(i))`.
    #[inline]
    pub fn target(&self, i: u32) -> u32 {
        self.permute(self.permute(i))
    }
}

// ---------------------------------------------------------------------------------------------
// The adaptive fill budget (§3.4.1)
// ---------------------------------------------------------------------------------------------

/// What the adaptive budget is computed from, measured in the frame being drawn: on the CPU with
/// a wall clock, on a GPU from timestamp queries (the hook for a GPU renderer: fill these from
/// the timestamps and call [`AdaptiveBudget::extra_points`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProbeTimings {
    /// Slots filled in the first, fixed step.
    pub probe_points: u64,
    /// Time the first step took, ms.
    pub probe_ms: f64,
    /// Time since the frame began, the first step included, ms.
    pub elapsed_ms: f64,
    /// Time expected after the fill (Prepare and what follows), ms: the last frame's.
    pub after_fill_ms: f64,
}

/// The adaptive fill budget of paper 000 §3.4.1: "we measure the time since the beginning of the
/// frame, and the time it took to render the first 1 million points. From this, we compute the
/// number of rendered points per millisecond, which we then multiply by the milliseconds we have
/// left to finish the frame."
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdaptiveBudget {
    /// The frame time to stay within, ms (16.6 for 60 frames per second).
    pub target_ms: f64,
    /// Slots filled first to measure the rate (the paper: 1 M points on a GPU).
    pub probe_points: u64,
    /// Share of `target_ms` planned for, for the estimate's error and work outside the passes
    /// (the paper suggests planning with about 10 of 16.6 ms on a GPU).
    pub usable: f64,
}

impl Default for AdaptiveBudget {
    fn default() -> Self {
        AdaptiveBudget { target_ms: 16.6, probe_points: 100_000, usable: 0.9 }
    }
}

impl AdaptiveBudget {
    /// Points to fill after the first step: the measured rate times the time left, 0 when no time
    /// is left, `u64::MAX` (fill everything) when the first step was too fast to measure.
    pub fn extra_points(&self, t: &ProbeTimings) -> u64 {
        let left = self.target_ms * self.usable - t.elapsed_ms - t.after_fill_ms;
        if t.probe_points == 0 || left.is_nan() || left <= 0.0 {
            return 0;
        }
        if t.probe_ms.is_nan() || t.probe_ms <= 0.0 {
            return u64::MAX;
        }
        let extra = t.probe_points as f64 / t.probe_ms * left;
        if extra >= u64::MAX as f64 {
            u64::MAX
        } else {
            extra as u64
        }
    }
}

/// How many slots the Fill pass draws per frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FillBudget {
    /// A fixed number of slots (at most the whole buffer).
    Fixed(u64),
    /// The adaptive budget of §3.4.1.
    Adaptive(AdaptiveBudget),
}

// ---------------------------------------------------------------------------------------------
// The quantization frame, which grows (the Distribute step's frame, shared by the CPU and GPU)
// ---------------------------------------------------------------------------------------------

/// The one quantization frame of a progressive renderer's shuffled buffer and the bounds its
/// planner sees, the same for every slot; the CPU renderer and its GPU twin hold one each and
/// grow it alike.
///
/// The paper allocates from the header before any point arrives; headers lie, so the frame is
/// the box the points are expected in (`data`: the headers' box) grown by its largest extent on
/// every side ([`around`](Self::around)), and when a point arrives outside it the frame grows
/// again ([`grown`](Self::grown): the box of everything expected and arrived, plus its extent),
/// as the octree builder grows its root: each growth more than doubles the frame, so it happens
/// a few times at most; the words already held are re-encoded in the new frame (exactly: every
/// frame holds every bit), and since a point's key depends on the point and the camera alone
/// (`plan::plan_batch`), nothing drawn moves. Refused only past 2^30 grid units on an axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProgressiveFrame {
    /// The integer grid of the points.
    pub grid: Grid,
    /// The box of the points expected (the headers') and of those that arrived.
    pub data: IntBox,
    /// Integer minimum and bits per axis of the words.
    pub quant: BatchGrid,
    /// Largest integer coordinate the frame holds per axis.
    pub max: [i32; 3],
    /// World bounds of the frame (what the planner culls and chooses precision with).
    pub bounds: Aabb,
}

impl ProgressiveFrame {
    /// The frame `min..=max` exactly, with no margin.
    pub fn exact(
        grid: Grid,
        min: [i32; 3],
        max: [i32; 3],
    ) -> Result<ProgressiveFrame, ProgressiveError> {
        if (0..3).any(|a| min[a] > max[a]) {
            return Err(ProgressiveError::Frame { min, max });
        }
        let quant = BatchGrid::for_bounds(min, max).ok_or(ProgressiveError::Frame { min, max })?;
        let b = IntBox { min, max };
        Ok(ProgressiveFrame { grid, data: b, quant, max, bounds: b.world(&grid) })
    }

    /// The frame of points expected in `data`: `data` grown by its largest extent (and one grid
    /// step) on every side, less where the frame would need more than 30 bits on an axis.
    pub fn around(grid: Grid, data: IntBox) -> Result<ProgressiveFrame, ProgressiveError> {
        let extent = data.extent();
        let room = ((1i64 << 30) - 1 - (extent + 2)).max(0) / 2;
        let margin = (extent + 1).min(room);
        let clamp = |v: i64| v.clamp(i32::MIN as i64, i32::MAX as i64) as i32;
        let min = data.min.map(|v| clamp(v as i64 - 1 - margin));
        let max = data.max.map(|v| clamp(v as i64 + 1 + margin));
        let mut f = ProgressiveFrame::exact(grid, min, max)
            .map_err(|_| ProgressiveError::Frame { min: data.min, max: data.max })?;
        f.data = data;
        Ok(f)
    }

    /// Whether the frame holds `p`.
    #[inline]
    pub fn holds(&self, p: &[i32; 3]) -> bool {
        (0..3).all(|a| p[a] >= self.quant.min[a] && p[a] <= self.max[a])
    }

    /// The frame grown to hold the points of `b` too ([`around`](Self::around) the box of
    /// everything expected and arrived), or `None` when it holds them already. Fails (the frame
    /// unchanged) when that needs more than 30 bits on an axis.
    pub fn grown(&self, b: IntBox) -> Result<Option<ProgressiveFrame>, ProgressiveError> {
        if self.holds(&b.min) && self.holds(&b.max) {
            return Ok(None);
        }
        ProgressiveFrame::around(self.grid, self.data.union(b)).map(Some)
    }

    /// The words of `words` (encoded in `from`) in this frame.
    #[inline]
    pub fn reencode(&self, from: &BatchGrid, words: [u32; 3]) -> [u32; 3] {
        self.quant.encode(from.decode_exact(words))
    }
}

// ---------------------------------------------------------------------------------------------
// The renderer (§3.4)
// ---------------------------------------------------------------------------------------------

/// The coarse word of a slot whose point has not arrived: bit 31, which no real coarse word uses
/// (three 10-bit fields). The GPU progressive renderer (mortar-render) uses the same sentinel;
/// its WGSL mirror is `UNLOADED` in `shaders/progressive_fill.wgsl` and
/// `shaders/progressive_unload.wgsl` (checked against this one by mortar-render's shader test).
pub const UNLOADED: u32 = 1 << 31;

/// Points per [`BatchRef`] / [`GatheredRef`] handed to the rasterizer (its unit of parallelism).
const CHUNK: usize = 1 << 15;

/// Why the progressive renderer refused something (nothing was changed).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProgressiveError {
    /// More points than 32-bit indices can address.
    #[error("{0} points: the progressive renderer holds at most {max} points (32-bit indices)", max = u32::MAX)]
    TooManyPoints(u64),
    /// The frame's bounds are empty or need more than 30 bits on an axis.
    #[error("bounds {min:?}..{max:?} on the integer grid are empty or span more than 2^30 steps on an axis")]
    Frame {
        /// Smallest integer coordinate.
        min: [i32; 3],
        /// Largest integer coordinate.
        max: [i32; 3],
    },
    /// A point lies outside the frame given to [`ProgressiveRenderer::new`].
    #[error("point {index} at {point:?} lies outside the bounds {min:?}..{max:?} (integer grid) the renderer was made for")]
    OutsideFrame {
        /// The point's input index.
        index: u64,
        /// Its integer coordinates.
        point: [i32; 3],
        /// Smallest integer coordinate of the frame.
        min: [i32; 3],
        /// Largest integer coordinate of the frame.
        max: [i32; 3],
    },
    /// Indices past the capacity.
    #[error("points {first}..{end} do not fit in a renderer of {capacity} points")]
    IndexRange {
        /// First index inserted.
        first: u64,
        /// One past the last.
        end: u64,
        /// The capacity.
        capacity: u64,
    },
    /// A point was inserted twice.
    #[error("point {0} was inserted twice")]
    Duplicate(u64),
    /// A payload was replaced for a point not inserted yet.
    #[error("point {0} has no payload to replace: it was not inserted")]
    NotLoaded(u64),
    /// Coordinates and payloads of different lengths.
    #[error("{points} points but {payloads} payloads")]
    PayloadCount {
        /// Number of points.
        points: usize,
        /// Number of payloads.
        payloads: usize,
    },
    /// The rasterizer refused the view.
    #[error(transparent)]
    Raster(#[from] RasterError),
}

/// What one frame did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameStats {
    /// Frame number, from 1.
    pub frame: u64,
    /// Points loaded when the frame was drawn.
    pub loaded: u64,
    /// Points drawn by Reproject (those visible at the end of the previous frame).
    pub reprojected: u64,
    /// Slots of the shuffled buffer swept by Fill (the budget spent; unloaded slots included).
    pub filled: u64,
    /// Of those, slots holding a point (the points Fill drew).
    pub fill_points: u64,
    /// With the adaptive budget: slots of the first, fixed step (included in `filled`).
    pub probe: u64,
    /// Points visible at the end of the frame (the next frame's Reproject buffer).
    pub visible: u64,
    /// What the rasterizer did, both passes together.
    pub raster: RasterStats,
    /// Time of the Reproject pass (framebuffer clear included), ms.
    pub reproject_ms: f64,
    /// Time of the Fill pass, ms.
    pub fill_ms: f64,
    /// Time of the Prepare pass, ms.
    pub prepare_ms: f64,
    /// Time of the whole frame, ms.
    pub total_ms: f64,
    /// Whether the image is final: every point loaded and drawn since the view last changed, so
    /// the keys equal the brute-force render of all points.
    pub converged: bool,
}

/// The Reproject buffer: the words and shuffled indices of the points visible in the last frame.
#[derive(Debug, Default)]
struct Gathered {
    words: [Vec<u32>; 3],
    indices: Vec<u32>,
}

impl Gathered {
    fn push(&mut self, words: &[Vec<u32>; 3], slot: usize) {
        for (dst, src) in self.words.iter_mut().zip(words) {
            dst.push(src[slot]);
        }
        self.indices.push(slot as u32);
    }

    fn refs<'a>(&'a self, r: &ProgressiveRenderer) -> Vec<GatheredRef<'a>> {
        (0..self.indices.len())
            .step_by(CHUNK)
            .map(|s| {
                let e = (s + CHUNK).min(self.indices.len());
                GatheredRef {
                    grid: r.frame.quant,
                    bounds_min: r.frame.bounds.min,
                    bounds_max: r.frame.bounds.max,
                    words: [0, 1, 2].map(|k| &self.words[k][s..e]),
                    indices: &self.indices[s..e],
                }
            })
            .collect()
    }
}

/// Raw pointers into the slot arrays for the parallel scatter of [`ProgressiveRenderer::insert`].
struct Slots {
    words: [SendPtr<u32>; 3],
    payload: SendPtr<u64>,
    len: usize,
}

impl Slots {
    /// Writes one slot.
    ///
    /// # Safety
    /// `slot < len`, and no other thread writes or reads the same slot meanwhile.
    #[inline]
    unsafe fn write(&self, slot: usize, w: [u32; 3], v: u64) {
        debug_assert!(slot < self.len);
        // SAFETY: the caller's promise above.
        unsafe {
            for (dst, v) in self.words.iter().zip(w) {
                dst.write(slot, v);
            }
            self.payload.write(slot, v);
        }
    }
}

/// The progressive renderer of paper 000 on the CPU: a shuffled point buffer that fills as points
/// arrive, and per frame Reproject, Fill and Prepare into a 64-bit visibility buffer (the same
/// keys and resolve as the batch rasterizer). See the module documentation.
#[derive(Debug)]
pub struct ProgressiveRenderer {
    frame: ProgressiveFrame,
    shuffle: Shuffle,
    /// Coarse, medium, fine words in shuffled order; an empty slot's coarse word is [`UNLOADED`].
    words: [Vec<u32>; 3],
    payload: Vec<u64>,
    loaded: u64,
    /// The Reproject buffer, in parts made in parallel (slot order).
    reproject: Vec<Gathered>,
    /// Next slot Fill draws.
    cursor: u64,
    fb: Option<Framebuffer>,
    view: Option<(Camera, RasterOptions)>,
    /// Slots drawn since the view last changed (bit per slot), and how many.
    done: Vec<u64>,
    /// Scratch bitmap of the visible slots for Prepare (all zero between frames).
    visible_bits: Vec<AtomicU64>,
    done_count: u64,
    frames: u64,
    last_prepare_ms: f64,
    /// Times the frame grew.
    grown: u32,
}

/// The integer box of a piece's points (`None` for none), computed in parallel.
pub fn piece_box(xyz: &[[i32; 3]]) -> Option<IntBox> {
    xyz.par_chunks(1 << 16).filter_map(IntBox::of).reduce_with(IntBox::union)
}

impl ProgressiveRenderer {
    /// A renderer for `capacity` points whose integer coordinates (on `grid`) lie in
    /// `[min, max]`: the quantization frame of every point and the bounds the rasterizer's
    /// planner sees, exactly (points outside grow it, see [`ProgressiveFrame`]).
    pub fn new(
        grid: Grid,
        min: [i32; 3],
        max: [i32; 3],
        capacity: u64,
    ) -> Result<ProgressiveRenderer, ProgressiveError> {
        ProgressiveRenderer::with_frame(ProgressiveFrame::exact(grid, min, max)?, capacity)
    }

    /// A renderer for `capacity` points in `frame` (e.g. [`ProgressiveFrame::around`] the
    /// headers' box).
    pub fn with_frame(
        frame: ProgressiveFrame,
        capacity: u64,
    ) -> Result<ProgressiveRenderer, ProgressiveError> {
        let len = u32::try_from(capacity).map_err(|_| ProgressiveError::TooManyPoints(capacity))?;
        let n = len as usize;
        let mut coarse = Vec::with_capacity(n);
        coarse.resize(n, UNLOADED);
        Ok(ProgressiveRenderer {
            frame,
            shuffle: Shuffle::new(len),
            words: [coarse, vec![0; n], vec![0; n]],
            payload: vec![0; n],
            loaded: 0,
            reproject: Vec::new(),
            cursor: 0,
            fb: None,
            view: None,
            done: vec![0; n.div_ceil(64)],
            visible_bits: (0..n.div_ceil(64)).map(|_| AtomicU64::new(0)).collect(),
            done_count: 0,
            frames: 0,
            last_prepare_ms: 0.0,
            grown: 0,
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

    /// The shuffle placing input index `i` at slot `shuffle().target(i)`.
    pub fn shuffle(&self) -> &Shuffle {
        &self.shuffle
    }

    /// The quantization frame of the words.
    pub fn quantization(&self) -> &BatchGrid {
        &self.frame.quant
    }

    /// The frame: quantization, bounds, and the box of the points expected and arrived.
    pub fn frame_state(&self) -> &ProgressiveFrame {
        &self.frame
    }

    /// World bounds of the frame.
    pub fn bounds(&self) -> &Aabb {
        &self.frame.bounds
    }

    /// The integer grid of the points.
    pub fn grid(&self) -> &Grid {
        &self.frame.grid
    }

    /// Frames drawn so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Inserts points `first..first + xyz.len()` of the input (integer coordinates on the grid)
    /// with one payload each, at their shuffled slots (the Distribute step of §3.1-3.2). Checks
    /// everything before changing anything.
    pub fn insert(
        &mut self,
        first: u64,
        xyz: &[[i32; 3]],
        payload: &[u64],
    ) -> Result<(), ProgressiveError> {
        if xyz.len() != payload.len() {
            return Err(ProgressiveError::PayloadCount {
                points: xyz.len(),
                payloads: payload.len(),
            });
        }
        let end = first.saturating_add(xyz.len() as u64);
        if end > self.capacity() {
            return Err(ProgressiveError::IndexRange { first, end, capacity: self.capacity() });
        }
        let shuffle = self.shuffle;
        let targets: Vec<u32> = (0..xyz.len())
            .into_par_iter()
            .with_min_len(4096)
            .map(|k| shuffle.target((first + k as u64) as u32))
            .collect();
        if let Some(k) = targets.iter().position(|&t| self.words[0][t as usize] != UNLOADED) {
            return Err(ProgressiveError::Duplicate(first + k as u64));
        }
        // Points outside the frame grow it (the words held are re-encoded; fails unchanged past
        // 30 bits).
        if let Some(b) = piece_box(xyz) {
            if let Some(grown) = self.frame.grown(b)? {
                self.reframe(grown);
            }
            self.frame.data = self.frame.data.union(b);
        }
        let frame = self.frame.quant;
        let [c, m, f] = &mut self.words;
        let out = Slots {
            words: [SendPtr(c.as_mut_ptr()), SendPtr(m.as_mut_ptr()), SendPtr(f.as_mut_ptr())],
            payload: SendPtr(self.payload.as_mut_ptr()),
            len: c.len(),
        };
        (0..xyz.len()).into_par_iter().with_min_len(4096).for_each(|k| {
            let out = &out;
            // SAFETY: every target is below `len` (the shuffle is a bijection on 0..len), and the
            // targets are distinct (a bijection of distinct indices), so no two iterations write
            // the same slot; the buffers are borrowed mutably for the whole loop.
            unsafe { out.write(targets[k] as usize, frame.encode(xyz[k]), payload[k]) };
        });
        self.loaded += xyz.len() as u64;
        Ok(())
    }

    /// Moves every word held into the frame `to` (exactly) and starts convergence over (the
    /// planner's bounds changed, so its precision choices may have).
    fn reframe(&mut self, to: ProgressiveFrame) {
        let from = self.frame.quant;
        let [c, m, f] = &mut self.words;
        c.par_iter_mut().zip(m.par_iter_mut()).zip(f.par_iter_mut()).with_min_len(4096).for_each(
            |((c, m), f)| {
                if *c != UNLOADED {
                    [*c, *m, *f] = to.reencode(&from, [*c, *m, *f]);
                }
            },
        );
        for g in &mut self.reproject {
            let [c, m, f] = &mut g.words;
            for i in 0..c.len() {
                [c[i], m[i], f[i]] = to.reencode(&from, [c[i], m[i], f[i]]);
            }
        }
        self.frame = to;
        self.view = None;
        self.grown += 1;
    }

    /// How often the frame grew to hold points outside it.
    pub fn growths(&self) -> u32 {
        self.grown
    }

    /// Replaces the payloads of points `first..first + payload.len()` of the input (already
    /// inserted) with new ones, leaving their positions and the frame's state alone: attribute
    /// switching streamed batch by batch (§3.5), as a loader delivers the new attribute. Checks
    /// everything before changing anything.
    pub fn replace_payloads(
        &mut self,
        first: u64,
        payload: &[u64],
    ) -> Result<(), ProgressiveError> {
        let end = first.saturating_add(payload.len() as u64);
        if end > self.capacity() {
            return Err(ProgressiveError::IndexRange { first, end, capacity: self.capacity() });
        }
        let shuffle = self.shuffle;
        let targets: Vec<u32> = (0..payload.len())
            .into_par_iter()
            .with_min_len(4096)
            .map(|k| shuffle.target((first + k as u64) as u32))
            .collect();
        if let Some(k) = targets.iter().position(|&t| self.words[0][t as usize] == UNLOADED) {
            return Err(ProgressiveError::NotLoaded(first + k as u64));
        }
        for (&t, &v) in targets.iter().zip(payload) {
            self.payload[t as usize] = v;
        }
        Ok(())
    }

    /// Whether slot `slot` holds a point.
    pub fn is_loaded(&self, slot: u32) -> bool {
        self.words[0].get(slot as usize).is_some_and(|&c| c != UNLOADED)
    }

    /// The payload of the point in slot `slot` (a shuffled index, as in the keys), if loaded.
    pub fn payload(&self, slot: u32) -> Option<u64> {
        self.is_loaded(slot).then(|| self.payload[slot as usize])
    }

    /// The payloads of every point inserted so far, in slot order (for view-independent colour
    /// ranges over all the points).
    pub fn loaded_payloads(&self) -> Vec<u64> {
        self.words[0]
            .par_iter()
            .zip(&self.payload)
            .filter(|(c, _)| **c != UNLOADED)
            .map(|(_, &v)| v)
            .collect()
    }

    /// The integer coordinates of the point in slot `slot`, if loaded.
    pub fn position(&self, slot: u32) -> Option<[i32; 3]> {
        let s = slot as usize;
        self.is_loaded(slot).then(|| {
            self.frame.quant.decode_exact([self.words[0][s], self.words[1][s], self.words[2][s]])
        })
    }

    /// Every point as [`BatchRef`]s over the shuffled buffer, for the brute-force [`rasterize`] of
    /// all points in this renderer's frame; `None` until every point arrived.
    pub fn all_points(&self) -> Option<Vec<BatchRef<'_>>> {
        (self.loaded == self.capacity()).then(|| self.slot_refs(0, self.capacity() as usize))
    }

    /// The visibility buffer of the last frame (row-major depth|index keys; indices are slots),
    /// empty before the first frame.
    pub fn keys(&self) -> Vec<u64> {
        self.fb.as_ref().map(Framebuffer::keys).unwrap_or_default()
    }

    /// The slots of the points visible at the end of the last frame, in increasing order.
    pub fn visible(&self) -> Vec<u32> {
        self.reproject.iter().flat_map(|g| g.indices.iter().copied()).collect()
    }

    /// The pixels of the last frame in which another point has exactly the winner's depth
    /// ([`count_depth_ties`] over every point, with the last frame's camera and options): where
    /// a renderer that numbers the points otherwise may show another of them. `None` until every
    /// point arrived and a frame was drawn.
    pub fn depth_ties(&self) -> Result<Option<u64>, ProgressiveError> {
        let (Some(all), Some((camera, options)), Some(fb)) =
            (self.all_points(), self.view, &self.fb)
        else {
            return Ok(None);
        };
        Ok(Some(count_depth_ties(&fb.keys(), &all, &self.frame.grid, &camera, &options)?))
    }

    /// Whether the last frame's image is final (see [`FrameStats::converged`]).
    pub fn converged(&self) -> bool {
        self.loaded == self.capacity() && self.done_count == self.capacity()
    }

    fn slot_refs(&self, s: usize, e: usize) -> Vec<BatchRef<'_>> {
        (s..e)
            .step_by(CHUNK)
            .map(|a| {
                let b = (a + CHUNK).min(e);
                BatchRef {
                    grid: self.frame.quant,
                    bounds_min: self.frame.bounds.min,
                    bounds_max: self.frame.bounds.max,
                    words: [0, 1, 2].map(|k| &self.words[k][a..b]),
                    first_index: a as u32,
                }
            })
            .collect()
    }

    /// Marks slots `[s, e)` drawn since the view changed.
    fn mark_range(&mut self, s: usize, e: usize) {
        let mut i = s;
        while i < e {
            let w = i / 64;
            let lo = i % 64;
            let hi = (e - w * 64).min(64);
            let mask = if hi - lo == 64 { u64::MAX } else { ((1u64 << (hi - lo)) - 1) << lo };
            self.done_count += (mask & !self.done[w]).count_ones() as u64;
            self.done[w] |= mask;
            i = w * 64 + hi;
        }
    }

    /// Marks one slot drawn since the view changed.
    fn mark(&mut self, slot: u32) {
        let (w, b) = (slot as usize / 64, slot % 64);
        if self.done[w] & (1 << b) == 0 {
            self.done[w] |= 1 << b;
            self.done_count += 1;
        }
    }

    /// Fill: draws slots `[cursor, cursor + count)` (wrapping) into the framebuffer. Returns the
    /// points drawn (loaded slots) and the rasterizer's statistics.
    fn sweep(
        &mut self,
        count: u64,
        camera: &Camera,
        options: &RasterOptions,
    ) -> Result<(u64, RasterStats), ProgressiveError> {
        let n = self.capacity();
        let count = count.min(n);
        let mut points = 0;
        let mut stats = RasterStats::default();
        let mut left = count;
        while left > 0 {
            let s = self.cursor as usize;
            let e = (self.cursor + left).min(n) as usize;
            let fb = self.fb.as_ref().expect("framebuffer made before the passes");
            if self.loaded == n {
                let st = rasterize(fb, &self.slot_refs(s, e), &self.frame.grid, camera, options)?;
                stats = stats.merge(st);
                points += (e - s) as u64;
                self.mark_range(s, e);
            } else {
                // Loading in progress: draw the slots whose point arrived (the paper discards the
                // others in the vertex shader).
                let coarse = &self.words[0];
                let parts: Vec<Gathered> = (s..e)
                    .into_par_iter()
                    .step_by(CHUNK)
                    .map(|a| {
                        let b = (a + CHUNK).min(e);
                        let mut g = Gathered {
                            words: [0; 3].map(|_| Vec::with_capacity(b - a)),
                            indices: Vec::with_capacity(b - a),
                        };
                        for (i, &c) in coarse[a..b].iter().enumerate() {
                            if c != UNLOADED {
                                g.push(&self.words, a + i);
                            }
                        }
                        g
                    })
                    .collect();
                let refs: Vec<GatheredRef<'_>> = parts.iter().flat_map(|g| g.refs(self)).collect();
                let st = rasterize_gathered(fb, &refs, &self.frame.grid, camera, options)?;
                stats = stats.merge(st);
                for g in &parts {
                    points += g.indices.len() as u64;
                    for &slot in &g.indices {
                        self.mark(slot);
                    }
                }
            }
            left -= (e - s) as u64;
            self.cursor = if e as u64 == n { 0 } else { e as u64 };
        }
        Ok((points, stats))
    }

    /// Draws one frame for `camera`: Reproject, Fill with `budget`, Prepare (paper 000 §3.4).
    /// The keys are then in [`keys`](Self::keys). A change of camera or options keeps the
    /// Reproject buffer (that is what it is for) but starts convergence over.
    pub fn frame(
        &mut self,
        camera: &Camera,
        options: &RasterOptions,
        budget: &FillBudget,
    ) -> Result<FrameStats, ProgressiveError> {
        let start = Instant::now();
        camera.validate().map_err(RasterError::from)?;
        let n = self.capacity();
        match &mut self.fb {
            Some(fb) if fb.width() == camera.width && fb.height() == camera.height => fb.clear(),
            fb => *fb = Some(Framebuffer::new(camera.width, camera.height)),
        }
        if self.view != Some((*camera, *options)) {
            self.view = Some((*camera, *options));
            self.done.iter_mut().for_each(|w| *w = 0);
            self.done_count = 0;
        }
        self.frames += 1;
        let mut st =
            FrameStats { frame: self.frames, loaded: self.loaded, ..FrameStats::default() };

        // Reproject: the points visible at the end of the last frame, from their coordinates.
        let fb = self.fb.as_ref().expect("made above");
        let refs: Vec<GatheredRef<'_>> = self.reproject.iter().flat_map(|g| g.refs(self)).collect();
        st.raster = rasterize_gathered(fb, &refs, &self.frame.grid, camera, options)?;
        st.reprojected = refs.iter().map(|g| g.len() as u64).sum();
        let t_reproject = start.elapsed();
        st.reproject_ms = t_reproject.as_secs_f64() * 1e3;

        // Fill: the next slots of the shuffled buffer.
        let t = Instant::now();
        let (first, extra) = match budget {
            FillBudget::Fixed(b) => (*b, None),
            FillBudget::Adaptive(a) => (a.probe_points.min(n), Some(a)),
        };
        let (points, stats) = self.sweep(first, camera, options)?;
        st.filled = first.min(n);
        st.fill_points = points;
        st.raster = st.raster.merge(stats);
        if let Some(a) = extra {
            st.probe = st.filled;
            let timings = ProbeTimings {
                probe_points: st.probe,
                probe_ms: t.elapsed().as_secs_f64() * 1e3,
                elapsed_ms: start.elapsed().as_secs_f64() * 1e3,
                after_fill_ms: self.last_prepare_ms,
            };
            let more = a.extra_points(&timings).min(n - st.filled);
            let (points, stats) = self.sweep(more, camera, options)?;
            st.filled += more;
            st.fill_points += points;
            st.raster = st.raster.merge(stats);
        }
        st.fill_ms = t.elapsed().as_secs_f64() * 1e3;

        // Prepare: the points that won a pixel, with their words, for the next Reproject.
        let t = Instant::now();
        // The visible slots are marked in a bitmap and read back in slot order, so that the
        // gather streams through the word arrays instead of missing the cache three times per
        // point (a bitmap of the slots is small, and cheaper than sorting the slots).
        let keys = self.fb.as_mut().expect("made above").keys_slice();
        let bits = &self.visible_bits;
        keys.par_chunks(1 << 16).for_each(|chunk| {
            for &k in chunk.iter().filter(|&&k| k != EMPTY_KEY) {
                let s = key_index(k) as usize;
                bits[s / 64].fetch_or(1 << (s % 64), Ordering::Relaxed);
            }
        });
        let words = &self.words;
        self.reproject = bits
            .par_chunks(CHUNK / 16)
            .enumerate()
            .map(|(c, chunk)| {
                let mut g = Gathered::default();
                for (i, w) in chunk.iter().enumerate() {
                    let mut v = w.swap(0, Ordering::Relaxed);
                    while v != 0 {
                        g.push(words, (c * (CHUNK / 16) + i) * 64 + v.trailing_zeros() as usize);
                        v &= v - 1;
                    }
                }
                g
            })
            .filter(|g| !g.indices.is_empty())
            .collect();
        st.visible = self.reproject.iter().map(|g| g.indices.len() as u64).sum();
        st.prepare_ms = t.elapsed().as_secs_f64() * 1e3;
        self.last_prepare_ms = st.prepare_ms;

        st.total_ms = start.elapsed().as_secs_f64() * 1e3;
        st.converged = self.converged();
        Ok(st)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera::{Projection, ViewPreset};
    use crate::render::framebuffer::key_depth;
    use crate::render::testutil::{Rng, Scene};
    use proptest::prelude::*;

    // --- shuffle ------------------------------------------------------------------------------

    fn trial_division(n: u64) -> bool {
        n >= 2 && (2..).take_while(|d| d * d <= n).all(|d| !n.is_multiple_of(d))
    }

    /// Asserts that `target` is a bijection on `0..n`, that `permute` is one on `0..P` and the
    /// identity past it.
    fn check_bijection(n: u32) {
        let s = Shuffle::new(n);
        let mut seen = vec![false; n as usize];
        for i in 0..n {
            let t = s.target(i);
            assert!(t < n, "n {n}: target({i}) = {t}");
            assert!(!seen[t as usize], "n {n}: target {t} twice");
            seen[t as usize] = true;
            assert_eq!(t, s.permute(s.permute(i)));
            if i >= s.prime().unwrap_or(0) {
                assert_eq!(s.permute(i), i, "n {n}: past the prime stays");
            }
        }
        if let Some(p) = s.prime() {
            let mut seen = vec![false; p as usize];
            for i in 0..p {
                let t = s.permute(i);
                assert!(t < p && !seen[t as usize], "n {n}: permute not a bijection on 0..{p}");
                seen[t as usize] = true;
            }
        }
    }

    #[test]
    fn primality_matches_trial_division() {
        for n in 0..20_000u64 {
            assert_eq!(is_prime(n), trial_division(n), "{n}");
        }
        for n in
            [4_294_967_291u64, 4_294_967_279, 2_147_483_647, 184_007_671, 184_008_203, 1_000_003]
        {
            assert!(is_prime(n), "{n}");
        }
        for n in
            [4_294_967_295u64, 4_294_967_293, 2_147_483_649, 1_000_001, 561, 1_105, 3_215_031_751]
        {
            assert_eq!(is_prime(n), trial_division(n), "{n}");
        }
    }

    #[test]
    fn the_prime_is_the_largest_3_mod_4_at_most_n() {
        assert_eq!(largest_prime_3_mod_4(0), None);
        assert_eq!(largest_prime_3_mod_4(2), None);
        assert_eq!(largest_prime_3_mod_4(3), Some(3));
        assert_eq!(largest_prime_3_mod_4(6), Some(3));
        assert_eq!(largest_prime_3_mod_4(7), Some(7));
        assert_eq!(largest_prime_3_mod_4(18), Some(11));
        assert_eq!(largest_prime_3_mod_4(19), Some(19));
        for n in 3..5_000u64 {
            let p = largest_prime_3_mod_4(n).unwrap();
            assert!(p <= n && p % 4 == 3 && trial_division(p), "{n}: {p}");
            assert!(
                (p + 1..=n).all(|q| q % 4 != 3 || !trial_division(q)),
                "{n}: a larger one exists"
            );
        }
        // The paper's largest gap below 500 M points: 532 between 184007671 and 184008203.
        assert_eq!(largest_prime_3_mod_4(184_008_202), Some(184_007_671));
        assert_eq!(largest_prime_3_mod_4(184_008_203), Some(184_008_203));
        assert_eq!(Shuffle::new(184_008_202).unshuffled(), 531);
        // The largest prime below 2^32 is 3 mod 4, and eq. 1 does not overflow there.
        let s = Shuffle::new(u32::MAX);
        assert_eq!(s.prime(), Some(4_294_967_291));
        assert_eq!(s.unshuffled(), 4);
        let p = 4_294_967_291u64;
        let i = (p - 1) as u32;
        assert_eq!(s.permute(i) as u64, p - ((p - 1) * (p - 1)) % p);
        assert_eq!(s.permute(u32::MAX), u32::MAX);
    }

    #[test]
    fn eq_1_by_hand() {
        // P = 7: i <= 3 -> i^2 mod 7 = 0, 1, 4, 2; i = 4..6 -> 7 - (16, 25, 36 mod 7) = 5, 3, 6.
        let s = Shuffle::new(9);
        assert_eq!(s.prime(), Some(7));
        let one: Vec<u32> = (0..9).map(|i| s.permute(i)).collect();
        assert_eq!(one, [0, 1, 4, 2, 5, 3, 6, 7, 8]);
        let two: Vec<u32> = (0..9).map(|i| s.target(i)).collect();
        assert_eq!(two, [0, 1, 5, 4, 3, 2, 6, 7, 8]);
        assert_eq!(Shuffle::new(2).target(1), 1);
        assert!(Shuffle::new(0).is_empty());
    }

    #[test]
    fn bijection_for_every_small_n() {
        for n in 0..3_000 {
            check_bijection(n);
        }
    }

    #[test]
    fn bijection_at_primes_and_just_above() {
        // 3 mod 4 primes (the whole range shuffled), 1 mod 4 primes, n just above a prime, powers of two.
        for n in [
            1_000_003u32,
            1_000_004,
            1_000_005,
            1_000_033,
            1_000_034,
            65_521,
            65_536,
            1 << 20,
            (1 << 20) + 1,
            999_983,
            999_984,
        ] {
            check_bijection(n);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]
        #[test]
        fn bijection_for_random_n(n in 0u32..1_500_000) {
            check_bijection(n);
        }
    }

    #[test]
    fn shuffled_prefixes_spread_over_the_buffer() {
        // The Fill pass relies on any run of slots being a random subset: the points of a run of
        // 1 % of the slots come from all over the input (here: each tenth of the input holds
        // 5-15 % of them), with eq. 2; eq. 1 alone keeps visible patterns (the paper's Fig. 4).
        let n = 1_000_000u32;
        let s = Shuffle::new(n);
        let mut inverse = vec![0u32; n as usize];
        for i in 0..n {
            inverse[s.target(i) as usize] = i;
        }
        for start in [0u32, 123_457, 500_000, 989_000] {
            let mut tenths = [0u32; 10];
            for slot in start..start + 10_000 {
                tenths[(inverse[slot as usize] as u64 * 10 / n as u64) as usize] += 1;
            }
            assert!(
                tenths.iter().all(|&c| (500..=1500).contains(&c)),
                "slots {start}..: {tenths:?}"
            );
        }
    }

    // --- adaptive budget -----------------------------------------------------------------------

    #[test]
    fn adaptive_budget_fills_the_time_left() {
        let a = AdaptiveBudget { target_ms: 16.0, probe_points: 1_000_000, usable: 1.0 };
        // 1 M points in 2 ms, 4 ms into the frame, 2 ms expected after: 10 ms left at 0.5 M/ms.
        let t = ProbeTimings {
            probe_points: 1_000_000,
            probe_ms: 2.0,
            elapsed_ms: 4.0,
            after_fill_ms: 2.0,
        };
        assert_eq!(a.extra_points(&t), 5_000_000);
        // Twice as fast (e.g. half the points outside the frustum): twice the budget.
        assert_eq!(
            a.extra_points(&ProbeTimings { probe_ms: 1.0, elapsed_ms: 3.0, ..t }),
            11_000_000
        );
        // Planning with 10 of 16 ms (the paper's advice) leaves 4 ms.
        let careful = AdaptiveBudget { usable: 10.0 / 16.0, ..a };
        assert_eq!(careful.extra_points(&t), 2_000_000);
        // Over time already: nothing more; too fast to measure: everything; no probe: nothing.
        assert_eq!(a.extra_points(&ProbeTimings { elapsed_ms: 15.0, ..t }), 0);
        assert_eq!(a.extra_points(&ProbeTimings { elapsed_ms: f64::NAN, ..t }), 0);
        assert_eq!(a.extra_points(&ProbeTimings { probe_ms: 0.0, ..t }), u64::MAX);
        assert_eq!(a.extra_points(&ProbeTimings { probe_points: 0, ..t }), 0);
        // A closed loop against a synthetic machine (fixed cost per point, reprojection and
        // prepare costs): frames stay within the target and the budget settles where the fill
        // takes the time left.
        let (per_point_ms, reproject_ms, prepare_ms) = (2e-6, 1.0, 1.5);
        let a = AdaptiveBudget { target_ms: 16.6, probe_points: 100_000, usable: 0.9 };
        let mut after = 0.0;
        for frame in 0..5 {
            let probe_ms = a.probe_points as f64 * per_point_ms;
            let t = ProbeTimings {
                probe_points: a.probe_points,
                probe_ms,
                elapsed_ms: reproject_ms + probe_ms,
                after_fill_ms: after,
            };
            let extra = a.extra_points(&t);
            let total = reproject_ms + (a.probe_points + extra) as f64 * per_point_ms + prepare_ms;
            after = prepare_ms;
            if frame > 0 {
                assert!(
                    total <= 16.6 * 0.9 + 1e-6 && total > 16.6 * 0.9 - 1e-3,
                    "frame {frame}: {total} ms"
                );
                let fill = ((16.6 * 0.9 - reproject_ms - prepare_ms) / per_point_ms) as u64;
                assert!(
                    (a.probe_points + extra).abs_diff(fill) <= 1,
                    "frame {frame}: {} points, {fill} fit",
                    a.probe_points + extra
                );
            }
        }
    }

    // --- renderer ------------------------------------------------------------------------------

    /// A renderer holding every point of `scene` (input index = scene index; payload = the
    /// index), in the scene's integer bounds.
    fn renderer_for(scene: &Scene) -> ProgressiveRenderer {
        let (lo, hi) = int_bounds(&scene.points);
        let mut r =
            ProgressiveRenderer::new(scene.grid, lo, hi, scene.points.len() as u64).unwrap();
        let payload: Vec<u64> = (0..scene.points.len() as u64).collect();
        r.insert(0, &scene.points, &payload).unwrap();
        r
    }

    fn int_bounds(points: &[[i32; 3]]) -> ([i32; 3], [i32; 3]) {
        crate::batching::int_bounds(points)
    }

    /// The brute-force keys of all points in the renderer's frame.
    fn brute_force(r: &ProgressiveRenderer, cam: &Camera, options: &RasterOptions) -> Vec<u64> {
        let fb = Framebuffer::new(cam.width, cam.height);
        rasterize(&fb, &r.all_points().unwrap(), r.grid(), cam, options).unwrap();
        fb.into_keys()
    }

    fn covered(keys: &[u64]) -> usize {
        keys.iter().filter(|&&k| k != EMPTY_KEY).count()
    }

    fn cameras(scene: &Scene) -> Vec<Camera> {
        let c = scene.bounds.center();
        vec![
            Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 320, 200).unwrap(),
            Camera::frame_orthographic(&scene.bounds, ViewPreset::Top, 256, 192).unwrap(),
            Camera::close_up(&scene.bounds, 0.8, 300, 200).unwrap(),
            Camera {
                eye: [c[0] - 30.0, c[1], c[2] + 5.0],
                target: [c[0] + 10.0, c[1] + 25.0, c[2]],
                up: [0.0, 0.0, 1.0],
                projection: Projection::Perspective { fov_y: 0.9 },
                near: 0.1,
                far: 1e4,
                width: 240,
                height: 160,
            },
        ]
    }

    #[test]
    fn converges_to_the_brute_force_render_after_points_over_budget_frames() {
        let scene = Scene::terrain(
            150_000,
            31,
            Grid { scale: [0.001; 3], offset: [500_000.0, 5_400_000.0, 0.0] },
        );
        let n = scene.points.len() as u64;
        let options = RasterOptions::default();
        for (ci, cam) in cameras(&scene).iter().enumerate() {
            let want = brute_force(&renderer_for(&scene), cam, &options);
            assert!(covered(&want) > 2_000, "camera {ci}: {}", covered(&want));
            for budget in [40_000u64, 33_333, 150_000, 1_000_000] {
                let mut r = renderer_for(&scene);
                let frames = n.div_ceil(budget);
                let mut prev: Option<Vec<u64>> = None;
                for f in 1..=frames {
                    let st = r.frame(cam, &options, &FillBudget::Fixed(budget)).unwrap();
                    let keys = r.keys();
                    assert_eq!(st.filled, budget.min(n));
                    assert_eq!(st.fill_points, budget.min(n));
                    assert_eq!(
                        st.visible as usize,
                        covered(&keys),
                        "camera {ci}: one visible point per covered pixel"
                    );
                    assert_eq!(st.converged, f == frames, "camera {ci} budget {budget} frame {f}");
                    if let Some(p) = &prev {
                        assert_eq!(st.reprojected as usize, covered(p));
                        // Still camera: every pixel keeps its point or gets a nearer one, so the
                        // covered pixels of a frame are a subset of the next frame's.
                        for (a, b) in p.iter().zip(&keys) {
                            assert!(
                                b <= a,
                                "camera {ci} budget {budget} frame {f}: a pixel got farther"
                            );
                        }
                    }
                    if f < frames {
                        assert_ne!(
                            keys, want,
                            "camera {ci} budget {budget}: converged early at frame {f}"
                        );
                    }
                    prev = Some(keys);
                }
                let keys = prev.unwrap();
                let differ = keys.iter().zip(&want).filter(|(a, b)| a != b).count();
                assert_eq!(
                    differ, 0,
                    "camera {ci} budget {budget}: {differ} pixels differ after {frames} frames"
                );
                // One more frame changes nothing.
                r.frame(cam, &options, &FillBudget::Fixed(budget)).unwrap();
                assert_eq!(r.keys(), want);
            }
        }
    }

    #[test]
    fn early_frames_show_a_random_subset_everywhere() {
        // Frame 1 of 10 draws a tenth of the points spread over the whole image (the shuffle), so it
        // already covers a large part of what the final image covers, and coverage only grows.
        let scene = Scene::terrain(200_000, 5, Grid { scale: [0.001; 3], offset: [0.0; 3] });
        let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Top, 0.8, 400, 300).unwrap();
        let mut r = renderer_for(&scene);
        let mut cover = Vec::new();
        for _ in 0..10 {
            r.frame(&cam, &RasterOptions::default(), &FillBudget::Fixed(20_000)).unwrap();
            cover.push(covered(&r.keys()));
        }
        assert!(cover.windows(2).all(|w| w[0] <= w[1]), "{cover:?}");
        let last = *cover.last().unwrap();
        assert!(cover[0] * 100 > last * 5 && cover[0] < last, "{cover:?}");
        // Every quarter of the final image gets points in frame 1.
        let mut r = renderer_for(&scene);
        r.frame(&cam, &RasterOptions::default(), &FillBudget::Fixed(20_000)).unwrap();
        let keys = r.keys();
        for q in 0..4 {
            let (x0, y0) = ((q % 2) * 200, (q / 2) * 150);
            let n = (y0..y0 + 150)
                .flat_map(|y| (x0..x0 + 200).map(move |x| (x, y)))
                .filter(|&(x, y)| keys[y * 400 + x] != EMPTY_KEY)
                .count();
            assert!(n > 500, "quarter {q}: {n}");
        }
    }

    #[test]
    fn equals_the_one_batch_brute_force_up_to_counted_depth_ties() {
        // The brute-force rasterize of the scene as one batch with the same frame and bounds: the
        // projection is the same, only the indices differ (Morton order there, shuffled slots
        // here), so a pixel may differ only where two points have the very same f32 depth and the
        // smaller index wins on each side.
        let scene = Scene::terrain(
            120_000,
            77,
            Grid { scale: [0.01; 3], offset: [684_000.0, 5_017_000.0, 0.0] },
        );
        let one = Scene::from_points(scene.grid, scene.points.clone(), scene.points.len());
        assert_eq!(one.batches.len(), 1);
        for (ci, cam) in cameras(&scene).iter().enumerate() {
            let fb = Framebuffer::new(cam.width, cam.height);
            rasterize(&fb, &one.refs(), &one.grid, cam, &RasterOptions::default()).unwrap();
            let want = fb.into_keys();
            // Points in the one-batch scene's order, so that its index is the input index.
            let mut r = renderer_for(&one);
            let st: Vec<FrameStats> = (0..4)
                .map(|_| {
                    r.frame(cam, &RasterOptions::default(), &FillBudget::Fixed(30_000)).unwrap()
                })
                .collect();
            assert!(
                !st[2].converged && st[3].converged,
                "camera {ci}: 4 x 30000 slots cover 120000 points"
            );
            let keys = r.keys();
            let mut table = vec![0u32; one.points.len()];
            for i in 0..one.points.len() as u32 {
                table[r.shuffle().target(i) as usize] = i;
            }
            let inverse = |slot: u32| table[slot as usize];
            let (mut ties, mut other) = (0, 0);
            for (k, w) in keys.iter().zip(&want) {
                if (*k == EMPTY_KEY) != (*w == EMPTY_KEY) {
                    other += 1;
                } else if *k != EMPTY_KEY && inverse(key_index(*k)) != key_index(*w) {
                    if key_depth(*k) == key_depth(*w) {
                        ties += 1;
                    } else {
                        other += 1;
                    }
                }
            }
            let n = covered(&want);
            eprintln!("camera {ci}: {ties} depth ties in {n} pixels");
            // The tie pass counts every pixel where the winner has a twin in depth, which holds
            // the pixels where the two numberings chose differently.
            let counted = r.depth_ties().unwrap().unwrap();
            assert!(counted >= ties as u64, "camera {ci}: {counted} ties counted, {ties} seen");
            assert!(counted > 0 || ci == 2, "camera {ci}: no ties at all?");
            assert_eq!(other, 0, "camera {ci}: {other} pixels differ beyond depth ties");
            // Few, but not none: several points share a pixel, and their f32 depths (24-bit
            // mantissa, ~3 mm at 300 m) are often equal; heights on a 1 cm grid make equal depths
            // more common in the orthographic top view (camera 1: ~3 % of the pixels).
            assert!(ties * 20 <= n, "camera {ci}: {ties} depth ties in {n} pixels");
            if ci != 1 {
                assert!(ties * 50 <= n, "camera {ci}: {ties} depth ties in {n} pixels");
            }
        }
    }

    #[test]
    fn matches_the_morton_batched_render_but_for_exact_depth_ties() {
        // Against the scene's own Morton batches (other quantization frames; a point's key does
        // not depend on them), at full precision on both sides, every pixel has the same depth,
        // and where the winners differ their depths are equal: ties, which the smaller index
        // decides and the two number points differently. (At adaptive precision the small Morton
        // batches load 10 bits in this overview and move points by up to half a pixel, which
        // changes which of the points sharing a pixel wins in ~1/3 of the pixels, as raster.rs's
        // tests describe.)
        let scene = Scene::terrain(
            150_000,
            41,
            Grid { scale: [0.001; 3], offset: [6_400_000.0, 0.0, 0.0] },
        );
        let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 480, 320).unwrap();
        let options = RasterOptions {
            precision: crate::render::PrecisionMode::Fixed(crate::quantize::Precision::Bits30),
            cull: true,
        };
        let fb = Framebuffer::new(cam.width, cam.height);
        rasterize(&fb, &scene.refs(), &scene.grid, &cam, &options).unwrap();
        let want = fb.into_keys();
        let mut r = renderer_for(&scene);
        while !r.frame(&cam, &options, &FillBudget::Fixed(50_000)).unwrap().converged {}
        let mut inverse = vec![0u32; scene.points.len()];
        for i in 0..scene.points.len() as u32 {
            inverse[r.shuffle().target(i) as usize] = i;
        }
        let (mut ties, mut other) = (0usize, 0usize);
        for (k, w) in r.keys().iter().zip(&want) {
            if (*k == EMPTY_KEY) != (*w == EMPTY_KEY)
                || (*k != EMPTY_KEY && key_depth(*k) != key_depth(*w))
            {
                other += 1;
            } else if *k != EMPTY_KEY && inverse[key_index(*k) as usize] != key_index(*w) {
                ties += 1;
            }
        }
        let n = covered(&want);
        eprintln!("{other} pixels differ, {ties} exact depth ties, of {n}");
        assert!(n > 20_000, "{n}");
        assert_eq!(other, 0, "{other} of {n} pixels differ beyond ties ({ties} ties)");
        assert!(ties as f64 <= 1e-2 * n as f64, "{ties} ties in {n} pixels");
    }

    #[test]
    fn points_arriving_while_rendering_are_shown_and_converge() {
        // Pieces arrive between frames in a scrambled order; every frame shows what arrived, and
        // the image converges once everything arrived and every slot was swept since.
        let scene = Scene::terrain(100_000, 13, Grid { scale: [0.001; 3], offset: [0.0; 3] });
        let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 320, 240).unwrap();
        let (lo, hi) = int_bounds(&scene.points);
        let mut r =
            ProgressiveRenderer::new(scene.grid, lo, hi, scene.points.len() as u64).unwrap();
        let pieces: Vec<(usize, usize)> = (0..scene.points.len())
            .step_by(7_000)
            .map(|s| (s, (s + 7_000).min(scene.points.len())))
            .collect();
        let mut order: Vec<usize> = (0..pieces.len()).collect();
        let mut rng = Rng(3);
        for i in (1..order.len()).rev() {
            order.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
        }
        let budget = FillBudget::Fixed(12_000);
        let mut frames = 0;
        for (k, &p) in order.iter().enumerate() {
            let (s, e) = pieces[p];
            let payload: Vec<u64> = (s as u64..e as u64).collect();
            r.insert(s as u64, &scene.points[s..e], &payload).unwrap();
            let st = r.frame(&cam, &RasterOptions::default(), &budget).unwrap();
            frames += 1;
            assert_eq!(st.loaded, r.loaded());
            assert!(st.fill_points <= st.filled && st.filled == 12_000);
            assert!(!st.converged || k + 1 == order.len());
            // Every visible point is a loaded one.
            assert!(r.visible().iter().all(|&slot| r.is_loaded(slot)));
        }
        assert!(frames > 0 && r.loaded() == scene.points.len() as u64);
        let want = brute_force(&r, &cam, &RasterOptions::default());
        let mut extra = 0;
        while !r.frame(&cam, &RasterOptions::default(), &budget).unwrap().converged {
            extra += 1;
            assert!(extra <= 10, "no convergence 10 frames after loading ended");
        }
        assert_eq!(r.keys(), want);
        // The payload travels with the point.
        for &slot in r.visible().iter().take(1000) {
            let i = r.payload(slot).unwrap() as usize;
            assert_eq!(r.position(slot), Some(scene.points[i]));
        }
    }

    #[test]
    fn a_moved_camera_reprojects_and_converges_again() {
        let scene = Scene::terrain(120_000, 17, Grid { scale: [0.001; 3], offset: [0.0; 3] });
        let cams = cameras(&scene);
        let mut r = renderer_for(&scene);
        let budget = FillBudget::Fixed(25_000);
        for _ in 0..5 {
            r.frame(&cams[0], &RasterOptions::default(), &budget).unwrap();
        }
        assert!(r.converged());
        // Move to a camera of another size: the visible points of the old view are drawn in the
        // new one first (reprojected from their coordinates), then the fill completes the image.
        let moved = Camera { width: 200, height: 150, ..cams[3] };
        let st = r.frame(&moved, &RasterOptions::default(), &budget).unwrap();
        assert!(st.reprojected > 10_000 && !st.converged);
        let want = brute_force(&r, &moved, &RasterOptions::default());
        let mut frames = 1;
        while !r.frame(&moved, &RasterOptions::default(), &budget).unwrap().converged {
            frames += 1;
        }
        assert_eq!(frames + 1, 5, "ceil(120000 / 25000) frames after the move");
        assert_eq!(r.keys(), want);
    }

    #[test]
    fn adaptive_budget_in_the_renderer() {
        let scene = Scene::terrain(80_000, 23, Grid { scale: [0.001; 3], offset: [0.0; 3] });
        let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 200, 150).unwrap();
        // No time at all: only the probe is filled, so it converges after ceil(n / probe) frames.
        let mut r = renderer_for(&scene);
        let none = FillBudget::Adaptive(AdaptiveBudget {
            target_ms: 0.0,
            probe_points: 30_000,
            usable: 0.9,
        });
        let st: Vec<FrameStats> =
            (0..3).map(|_| r.frame(&cam, &RasterOptions::default(), &none).unwrap()).collect();
        assert!(st.iter().all(|s| s.probe == 30_000 && s.filled == 30_000));
        assert!(!st[1].converged && st[2].converged);
        assert_eq!(r.keys(), brute_force(&r, &cam, &RasterOptions::default()));
        // A generous target: the whole buffer in the first frame.
        let mut r = renderer_for(&scene);
        let lots = FillBudget::Adaptive(AdaptiveBudget {
            target_ms: 1e6,
            probe_points: 1_000,
            usable: 0.9,
        });
        let s = r.frame(&cam, &RasterOptions::default(), &lots).unwrap();
        assert_eq!((s.probe, s.filled, s.fill_points), (1_000, 80_000, 80_000));
        assert!(s.converged);
    }

    #[test]
    fn bad_input_is_refused_without_changes() {
        let grid = Grid { scale: [0.01; 3], offset: [0.0; 3] };
        assert!(matches!(
            ProgressiveRenderer::new(grid, [0; 3], [10; 3], 1 << 32),
            Err(ProgressiveError::TooManyPoints(_))
        ));
        assert!(matches!(
            ProgressiveRenderer::new(grid, [0; 3], [-1, 5, 5], 10),
            Err(ProgressiveError::Frame { .. })
        ));
        assert!(matches!(
            ProgressiveRenderer::new(grid, [i32::MIN, 0, 0], [i32::MAX, 0, 0], 10),
            Err(ProgressiveError::Frame { .. })
        ));
        let mut r = ProgressiveRenderer::new(grid, [0; 3], [100; 3], 10).unwrap();
        let p = [[1, 2, 3], [4, 5, 6]];
        assert!(matches!(r.insert(0, &p, &[0]), Err(ProgressiveError::PayloadCount { .. })));
        assert!(matches!(r.insert(9, &p, &[0, 0]), Err(ProgressiveError::IndexRange { .. })));
        // A point that would need more than 30 bits on an axis cannot be framed: refused, nothing
        // changed. (Points outside the frame otherwise grow it: `a_frame_grows_to_hold_...`.)
        assert!(matches!(
            r.insert(0, &[[1, 2, 3], [4, 1 << 30, 6]], &[0, 0]),
            Err(ProgressiveError::Frame { .. })
        ));
        assert_eq!(r.loaded(), 0);
        assert_eq!(r.frame_state().max, [100; 3]);
        r.insert(3, &p, &[7, 8]).unwrap();
        assert!(matches!(r.insert(4, &p, &[0, 0]), Err(ProgressiveError::Duplicate(4))));
        assert_eq!(r.loaded(), 2);
        assert_eq!(r.payload(r.shuffle().target(4)), Some(8));
        assert_eq!(r.position(r.shuffle().target(3)), Some([1, 2, 3]));
        // Attribute switching (§3.5): payloads replaced in place, positions kept; points not
        // inserted or past the end are refused without changes.
        assert_eq!(r.replace_payloads(3, &[70, 80, 90]), Err(ProgressiveError::NotLoaded(5)));
        assert!(matches!(r.replace_payloads(9, &[1, 2]), Err(ProgressiveError::IndexRange { .. })));
        assert_eq!(r.payload(r.shuffle().target(3)), Some(7));
        r.replace_payloads(3, &[70, 80]).unwrap();
        assert_eq!(r.payload(r.shuffle().target(3)), Some(70));
        assert_eq!(r.payload(r.shuffle().target(4)), Some(80));
        assert_eq!(r.position(r.shuffle().target(4)), Some([4, 5, 6]));
        assert_eq!(r.loaded(), 2);
        assert!(r.all_points().is_none() && !r.converged());
        let mut cam =
            Camera::frame_orthographic(&Aabb::new([0.0; 3], [1.0; 3]), ViewPreset::Top, 16, 16)
                .unwrap();
        cam.far = cam.near;
        assert!(matches!(
            r.frame(&cam, &RasterOptions::default(), &FillBudget::Fixed(4)),
            Err(ProgressiveError::Raster(_))
        ));
        // An empty renderer draws empty frames and is converged.
        let mut e = ProgressiveRenderer::new(grid, [0; 3], [0; 3], 0).unwrap();
        let cam =
            Camera::frame_orthographic(&Aabb::new([0.0; 3], [1.0; 3]), ViewPreset::Top, 16, 16)
                .unwrap();
        let s = e.frame(&cam, &RasterOptions::default(), &FillBudget::Fixed(100)).unwrap();
        assert!(s.converged && s.visible == 0 && covered(&e.keys()) == 0);
    }

    #[test]
    fn a_frame_grows_to_hold_points_outside_it_and_nothing_drawn_moves() {
        // The renderer is framed for a tenth of the scene (as a lying header would frame it);
        // pieces arrive between frames, most of them outside: the frame grows a few times, the
        // words held are re-encoded, and the converged keys are those of a renderer framed for
        // the final box from the start (any precision: same frame, same plan) and, at 30 bits,
        // of the brute force in the scene's own tight frame (keys do not depend on the frame).
        let scene = Scene::terrain(
            60_000,
            29,
            Grid { scale: [0.001; 3], offset: [500_000.0, 5_400_000.0, 0.0] },
        );
        let (lo, hi) = int_bounds(&scene.points);
        let small = IntBox { min: lo, max: [0, 1, 2].map(|a| lo[a] + (hi[a] - lo[a]) / 10) };
        let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 320, 240).unwrap();
        let full = RasterOptions {
            precision: crate::render::PrecisionMode::Fixed(crate::quantize::Precision::Bits30),
            cull: true,
        };
        for options in [RasterOptions::default(), full] {
            let frame = ProgressiveFrame::around(scene.grid, small).unwrap();
            let mut r = ProgressiveRenderer::with_frame(frame, scene.points.len() as u64).unwrap();
            let budget = FillBudget::Fixed(7_000);
            for s in (0..scene.points.len()).step_by(6_000) {
                let e = (s + 6_000).min(scene.points.len());
                let payload: Vec<u64> = (s as u64..e as u64).collect();
                r.insert(s as u64, &scene.points[s..e], &payload).unwrap();
                r.frame(&cam, &options, &budget).unwrap();
                assert!(r.visible().iter().all(|&slot| r.is_loaded(slot)));
            }
            assert!((1..=4).contains(&r.growths()), "{} growths", r.growths());
            assert!(r.frame_state().holds(&lo) && r.frame_state().holds(&hi));
            assert_eq!(r.frame_state().data, IntBox { min: lo, max: hi });
            while !r.frame(&cam, &options, &budget).unwrap().converged {}
            // Every point kept its exact position through the re-encodings.
            for i in (0..scene.points.len() as u32).step_by(97) {
                assert_eq!(r.position(r.shuffle().target(i)), Some(scene.points[i as usize]));
            }
            let mut same =
                ProgressiveRenderer::with_frame(*r.frame_state(), scene.points.len() as u64)
                    .unwrap();
            let payload: Vec<u64> = (0..scene.points.len() as u64).collect();
            same.insert(0, &scene.points, &payload).unwrap();
            while !same.frame(&cam, &options, &budget).unwrap().converged {}
            assert_eq!(r.keys(), same.keys(), "{options:?}");
            if options == full {
                assert_eq!(r.keys(), brute_force(&renderer_for(&scene), &cam, &full));
            }
        }
        // Past 30 bits: refused, the renderer unchanged.
        let mut r = ProgressiveRenderer::with_frame(
            ProgressiveFrame::around(scene.grid, small).unwrap(),
            10,
        )
        .unwrap();
        let before = *r.frame_state();
        assert!(matches!(
            r.insert(0, &[[0, 0, 0], [1 << 30, 0, 0]], &[0, 0]),
            Err(ProgressiveError::Frame { .. })
        ));
        assert_eq!((*r.frame_state(), r.loaded(), r.growths()), (before, 0, 0));
    }

    #[test]
    fn gathered_points_leave_the_same_keys_as_batches() {
        // rasterize_gathered with each batch's points listed in reverse order (and their indices)
        // gives the keys of rasterize.
        let scene =
            Scene::terrain(60_000, 9, Grid { scale: [0.001; 3], offset: [300_000.0, 0.0, 0.0] });
        for cam in cameras(&scene) {
            let fb = Framebuffer::new(cam.width, cam.height);
            rasterize(&fb, &scene.refs(), &scene.grid, &cam, &RasterOptions::default()).unwrap();
            let want = fb.into_keys();
            let mut owned = Vec::new();
            for b in scene.refs() {
                let words: [Vec<u32>; 3] =
                    [0, 1, 2].map(|k| b.words[k].iter().rev().copied().collect());
                let indices: Vec<u32> =
                    (0..b.len() as u32).rev().map(|i| b.first_index + i).collect();
                owned.push((b, words, indices));
            }
            let refs: Vec<GatheredRef<'_>> = owned
                .iter()
                .map(|(b, w, i)| GatheredRef {
                    grid: b.grid,
                    bounds_min: b.bounds_min,
                    bounds_max: b.bounds_max,
                    words: [&w[0], &w[1], &w[2]],
                    indices: i,
                })
                .collect();
            let fb = Framebuffer::new(cam.width, cam.height);
            rasterize_gathered(&fb, &refs, &scene.grid, &cam, &RasterOptions::default()).unwrap();
            assert_eq!(fb.into_keys(), want);
        }
        let mut bad = scene
            .refs()
            .iter()
            .map(|b| GatheredRef {
                grid: b.grid,
                bounds_min: b.bounds_min,
                bounds_max: b.bounds_max,
                words: b.words,
                indices: &[],
            })
            .collect::<Vec<_>>();
        bad.truncate(1);
        let cam = cameras(&scene)[0];
        let fb = Framebuffer::new(cam.width, cam.height);
        assert!(matches!(
            rasterize_gathered(&fb, &bad, &scene.grid, &cam, &RasterOptions::default()),
            Err(RasterError::IndexCount { batch: 0, .. })
        ));
    }
}
