//! The progressive renderer of paper 000 on the CPU ([`ProgressiveRenderer`], §3.4): the shuffled
//! buffer in memory (three 10-bit coordinate words per point in one quantization frame over the
//! whole data set, plus a 64-bit payload the caller turns into colours) and, per frame,
//! **Reproject** (draw the points that were visible at the end of the previous frame, from their
//! original coordinates and with their shuffled index), **Fill** (draw the next `budget` slots of
//! the shuffled buffer, wrapping around; slots whose point has not arrived yet are skipped, as the
//! paper discards default-initialized vertices) and **Prepare** (collect the indices of the points
//! that won a pixel: the next frame's Reproject buffer).

use super::budget::{FillBudget, ProbeTimings};
use super::error::ProgressiveError;
use super::frame::ProgressiveFrame;
use super::shuffle::Shuffle;
use super::state::ProgressiveState;
use super::stats::FrameStats;
use crate::grid::Grid;
use crate::par::SendPtr;
use crate::quantize::BatchGrid;
use crate::render::camera::Camera;
use crate::render::error::RasterError;
use crate::render::framebuffer::{key_index, Framebuffer, EMPTY_KEY};
use crate::render::math::Aabb;
use crate::render::plan::RasterOptions;
use crate::render::raster::{
    count_depth_ties, rasterize, rasterize_gathered, BatchRef, GatheredRef, RasterStats,
};
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// The coarse word of a slot whose point has not arrived: bit 31, which no real coarse word uses
/// (three 10-bit fields). The GPU progressive renderer (mortar-render) uses the same sentinel;
/// its WGSL mirror is `UNLOADED` in `shaders/progressive_fill.wgsl` and
/// `shaders/progressive_unload.wgsl` (checked against this one by mortar-render's shader test).
pub const UNLOADED: u32 = 1 << 31;

/// Points per [`BatchRef`] / [`GatheredRef`] handed to the rasterizer (its unit of parallelism).
const CHUNK: usize = 1 << 15;

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
                let frame = r.state.frame();
                GatheredRef {
                    grid: frame.quant,
                    bounds_min: frame.bounds.min,
                    bounds_max: frame.bounds.max,
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
/// keys and resolve as the batch rasterizer). See the documentation of [`progressive`](super).
#[derive(Debug)]
pub struct ProgressiveRenderer {
    /// The shuffle, the frame, the points loaded, Fill's cursor, the view and the slots drawn
    /// since it changed: the state the GPU twin shares.
    state: ProgressiveState,
    /// Coarse, medium, fine words in shuffled order; an empty slot's coarse word is [`UNLOADED`].
    words: [Vec<u32>; 3],
    payload: Vec<u64>,
    /// The Reproject buffer, in parts made in parallel (slot order).
    reproject: Vec<Gathered>,
    fb: Option<Framebuffer>,
    /// Scratch bitmap of the visible slots for Prepare (all zero between frames).
    visible_bits: Vec<AtomicU64>,
}

/// Moves every word held (the shuffled buffer's and the Reproject buffer's) from the frame
/// `from` into the frame `to`, exactly (what the renderer does when its frame grows; the state
/// then starts convergence over, as the planner's bounds changed, so its precision choices may
/// have).
fn reencode(
    words: &mut [Vec<u32>; 3],
    reproject: &mut [Gathered],
    from: &BatchGrid,
    to: &ProgressiveFrame,
) {
    let [c, m, f] = words;
    c.par_iter_mut().zip(m.par_iter_mut()).zip(f.par_iter_mut()).with_min_len(4096).for_each(
        |((c, m), f)| {
            if *c != UNLOADED {
                [*c, *m, *f] = to.reencode(from, [*c, *m, *f]);
            }
        },
    );
    for g in reproject {
        let [c, m, f] = &mut g.words;
        for i in 0..c.len() {
            [c[i], m[i], f[i]] = to.reencode(from, [c[i], m[i], f[i]]);
        }
    }
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
        let state = ProgressiveState::new(frame, capacity)?;
        let n = state.capacity() as usize;
        let mut coarse = Vec::with_capacity(n);
        coarse.resize(n, UNLOADED);
        Ok(ProgressiveRenderer {
            state,
            words: [coarse, vec![0; n], vec![0; n]],
            payload: vec![0; n],
            reproject: Vec::new(),
            fb: None,
            visible_bits: (0..n.div_ceil(64)).map(|_| AtomicU64::new(0)).collect(),
        })
    }

    /// The state the renderer shares with its GPU twin: shuffle, frame, points loaded, Fill's
    /// cursor, view, slots drawn since it changed.
    pub fn state(&self) -> &ProgressiveState {
        &self.state
    }

    /// Number of points the renderer holds once everything arrived.
    pub fn capacity(&self) -> u64 {
        self.state.capacity()
    }

    /// Points inserted so far.
    pub fn loaded(&self) -> u64 {
        self.state.loaded()
    }

    /// The shuffle placing input index `i` at slot `shuffle().target(i)`.
    pub fn shuffle(&self) -> &Shuffle {
        self.state.shuffle()
    }

    /// The quantization frame of the words.
    pub fn quantization(&self) -> &BatchGrid {
        &self.state.frame().quant
    }

    /// The frame: quantization, bounds, and the box of the points expected and arrived.
    pub fn frame_state(&self) -> &ProgressiveFrame {
        self.state.frame()
    }

    /// World bounds of the frame.
    pub fn bounds(&self) -> &Aabb {
        &self.state.frame().bounds
    }

    /// The integer grid of the points.
    pub fn grid(&self) -> &Grid {
        &self.state.frame().grid
    }

    /// Frames drawn so far.
    pub fn frames(&self) -> u64 {
        self.state.frames()
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
        self.state.check_range(first, xyz.len())?;
        let shuffle = *self.state.shuffle();
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
        let (words, reproject) = (&mut self.words, &mut self.reproject);
        self.state.grow_for(xyz, |from, to| {
            reencode(words, reproject, &from.quant, to);
            Ok::<(), ProgressiveError>(())
        })?;
        let frame = self.state.frame().quant;
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
        self.state.add_loaded(xyz.len());
        Ok(())
    }

    /// How often the frame grew to hold points outside it.
    pub fn growths(&self) -> u32 {
        self.state.growths()
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
        self.state.check_range(first, payload.len())?;
        let shuffle = *self.state.shuffle();
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
            let quant = &self.state.frame().quant;
            quant.decode_exact([self.words[0][s], self.words[1][s], self.words[2][s]])
        })
    }

    /// Every point as [`BatchRef`]s over the shuffled buffer, for the brute-force [`rasterize`] of
    /// all points in this renderer's frame; `None` until every point arrived.
    pub fn all_points(&self) -> Option<Vec<BatchRef<'_>>> {
        self.state.all_loaded().then(|| self.slot_refs(0, self.capacity() as usize))
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
            (self.all_points(), self.state.view(), &self.fb)
        else {
            return Ok(None);
        };
        let grid = &self.state.frame().grid;
        Ok(Some(count_depth_ties(&fb.keys(), &all, grid, &camera, &options)?))
    }

    /// Whether the last frame's image is final (see [`FrameStats::converged`]).
    pub fn converged(&self) -> bool {
        self.state.converged()
    }

    fn slot_refs(&self, s: usize, e: usize) -> Vec<BatchRef<'_>> {
        (s..e)
            .step_by(CHUNK)
            .map(|a| {
                let b = (a + CHUNK).min(e);
                let frame = self.state.frame();
                BatchRef {
                    grid: frame.quant,
                    bounds_min: frame.bounds.min,
                    bounds_max: frame.bounds.max,
                    words: [0, 1, 2].map(|k| &self.words[k][a..b]),
                    first_index: a as u32,
                }
            })
            .collect()
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
            let (s, e) = self.state.next_run(left, n);
            let (s, e) = (s as usize, e as usize);
            let fb = self.fb.as_ref().expect("framebuffer made before the passes");
            let grid = &self.state.frame().grid;
            if self.state.all_loaded() {
                let st = rasterize(fb, &self.slot_refs(s, e), grid, camera, options)?;
                stats = stats.merge(st);
                points += (e - s) as u64;
                self.state.mark_drawn(s, e, |_| u64::MAX);
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
                let st = rasterize_gathered(fb, &refs, grid, camera, options)?;
                stats = stats.merge(st);
                for g in &parts {
                    points += g.indices.len() as u64;
                    for &slot in &g.indices {
                        self.state.mark_slot(slot);
                    }
                }
            }
            left -= (e - s) as u64;
            self.state.advance(e as u64);
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
        let mut st = self.state.begin_frame(camera, options);

        // Reproject: the points visible at the end of the last frame, from their coordinates.
        let fb = self.fb.as_ref().expect("made above");
        let refs: Vec<GatheredRef<'_>> = self.reproject.iter().flat_map(|g| g.refs(self)).collect();
        st.raster = rasterize_gathered(fb, &refs, &self.state.frame().grid, camera, options)?;
        st.reprojected = refs.iter().map(|g| g.len() as u64).sum();
        let t_reproject = start.elapsed();
        st.reproject_ms = t_reproject.as_secs_f64() * 1e3;

        // Fill: the next slots of the shuffled buffer.
        let t = Instant::now();
        let (first, extra) = self.state.first_fill(budget);
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
                after_fill_ms: self.state.after_fill_ms(),
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
        self.state.set_after_fill_ms(st.prepare_ms);

        st.total_ms = start.elapsed().as_secs_f64() * 1e3;
        st.converged = self.state.converged();
        Ok(st)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera::{Projection, ViewPreset};
    use crate::render::framebuffer::key_depth;
    use crate::render::framing::IntBox;
    use crate::render::progressive::AdaptiveBudget;
    use crate::render::testutil::{Rng, Scene};

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
        // Frame 1 of 10 draws a tenth of the points spread over the whole image (the shuffle), so
        // it already covers a large part of what the final image covers, and coverage only grows.
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
