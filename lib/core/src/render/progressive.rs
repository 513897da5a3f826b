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
//! Exactness: every draw (Fill through [`rasterize`](super::rasterize), Reproject through
//! [`rasterize_gathered`](super::raster::rasterize_gathered))
//! uses the same quantization frame and bounds, so the [`Planner`](super::Planner) makes the same
//! decisions and the per-point loop produces the same 64-bit depth|index key for a point
//! whichever pass draws it. With a still camera, each pixel therefore holds the minimum key over
//! every point drawn since the camera stopped, and once every slot was filled the framebuffer
//! equals the brute-force [`rasterize`](super::rasterize) of all points in this frame, key for key
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
//! (mortar-app's `viewer::progressive_view`). Not implemented: MSAA (paper §3.4: it acts as
//! supersampling).
//!
//! The files, one concept each:
//! - `shuffle`: the incremental shuffle ([`Shuffle`], [`is_prime`], [`largest_prime_3_mod_4`]).
//! - `budget`: the fill budget ([`FillBudget`], [`AdaptiveBudget`], [`ProbeTimings`]).
//! - `frame`: the quantization frame that grows ([`ProgressiveFrame`], [`piece_box`]).
//! - `error`: why a renderer refused something ([`ProgressiveError`]).
//! - `stats`: what one frame did ([`FrameStats`]).
//! - `state`: the state the CPU renderer and its GPU twin share ([`ProgressiveState`]: shuffle,
//!   frame, points loaded, Fill's cursor, view, slots drawn since it changed).
//! - `cpu`: the CPU renderer ([`ProgressiveRenderer`]) and the [`UNLOADED`] sentinel.

mod budget;
mod cpu;
mod error;
mod frame;
mod shuffle;
mod state;
mod stats;

pub use budget::{AdaptiveBudget, FillBudget, ProbeTimings};
pub use cpu::{ProgressiveRenderer, UNLOADED};
pub use error::ProgressiveError;
pub use frame::{piece_box, ProgressiveFrame};
pub use shuffle::{is_prime, largest_prime_3_mod_4, Shuffle};
pub use state::ProgressiveState;
pub use stats::FrameStats;
