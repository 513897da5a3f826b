//! The `#[repr(C)]` records the GPU passes (mortar-render, `shaders/`) read, defined once here:
//! the rasterizer's [`DrawRecord`], [`FrameUniforms`] and [`ResolveUniforms`] next to the CPU twin
//! that fills the same fields, its post-processing passes' [`HoleFillUniforms`] and
//! [`EyeDomeUniforms`], the progressive renderer's [`ScatterUniforms`], [`PrepareUniforms`] and
//! [`ReframeUniforms`], and the window's [`PresentUniforms`]. [`BatchProjection`] (inside
//! [`DrawRecord`]) lives with the camera maths that computes it and is re-exported here.
//!
//! Every struct has a WGSL mirror (keep both in sync: mortar-render's layout tests compare the
//! offsets and sizes naga computes for the WGSL structs with these):
//! - `shaders/common/types.wgsl`: `BatchProjection`, `DrawRecord`, `FrameUniforms`, `ResolveUniforms`,
//!   `HoleFillUniforms`, `EyeDomeUniforms`;
//! - `shaders/progressive_types.wgsl`: `ScatterUniforms`, `PrepareUniforms`, `ReframeUniforms`;
//! - `shaders/present.wgsl`: `PresentUniforms`.
//!
//! Only bytemuck layouts here: no GPU API (the crate graph keeps core free of wgpu).

pub use super::camera::BatchProjection;
use super::camera::Camera;
use super::resolve::{EyeDome, HoleFill, EDL_EXP2_COEFFS, EDL_LOG2_COEFFS};

/// One batch to draw in one frame: its projection and where its points are in the chunk's
/// word buffers. 128 bytes; WGSL `DrawRecord`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct DrawRecord {
    /// The per-batch transform, precision (`words`) and pixel origin (see [`BatchProjection`]).
    pub projection: BatchProjection,
    /// Position of the batch's first point in its chunk's word buffers.
    pub offset: u32,
    /// Number of points (0 for a padding record, which draws nothing).
    pub count: u32,
    /// Index of the batch's first point, written to the framebuffer's low 32 bits.
    pub first_index: u32,
    /// Padding to a multiple of 16 bytes.
    pub _pad: u32,
}

const _: () = assert!(std::mem::size_of::<DrawRecord>() == 128);

/// Per-frame constants of the draw passes. 32 bytes; WGSL `FrameUniforms`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct FrameUniforms {
    /// Viewport width in pixels.
    pub width: u32,
    /// Viewport height in pixels.
    pub height: u32,
    /// Near plane (view depth).
    pub near: f32,
    /// Far plane (view depth).
    pub far: f32,
    /// 1 for a perspective camera (pixel = X / W), 0 for orthographic (pixel = X).
    pub perspective: u32,
    /// Always 0. The shader xors the bits of every intermediate result of the projection with
    /// it: the compiler cannot see that this changes nothing, so it can neither fuse `a * b + c`
    /// into one rounding (an FMA) nor reorder operations, and the GPU rounds each operation as
    /// the CPU rasterizer does.
    pub zero: u32,
    /// How the perspective division is done: [`DIVISION_PLAIN`] (WGSL `/`) or
    /// [`DIVISION_REFINED`] (refined to the correctly rounded quotient with `fma`).
    pub division: u32,
    /// Padding to 32 bytes.
    pub _pad: u32,
}

/// WGSL's `/`: correctly rounded on lavapipe (a CPU), up to 2.5 ULP off elsewhere.
pub const DIVISION_PLAIN: u32 = 0;
/// `div_rn` of `shaders/common/decode.wgsl`: WGSL's reciprocal refined by a Newton step and
/// corrected by an `fma` remainder; correctly rounded where `fma` is fused (measured on an H100).
pub const DIVISION_REFINED: u32 = 1;

const _: () = assert!(std::mem::size_of::<FrameUniforms>() == 32);

impl FrameUniforms {
    /// The uniforms of a camera, dividing as `division` says.
    pub fn new(camera: &Camera, division: u32) -> FrameUniforms {
        FrameUniforms {
            width: camera.width,
            height: camera.height,
            near: camera.near as f32,
            far: camera.far as f32,
            perspective: camera.is_perspective() as u32,
            zero: 0,
            division,
            _pad: 0,
        }
    }
}

/// Constants of one resolve dispatch (one per chunk of points). 32 bytes; WGSL `ResolveUniforms`.
///
/// The framebuffer is read as 32-bit words: the point index of pixel `p` at
/// `index_words[p * key_stride]` and its depth bits at `depth_words[p * key_stride + depth_offset]`
/// (the 64-bit path binds the key buffer twice with stride 2 and offset 1, the 32-bit path its
/// index and depth buffers with stride 1 and offset 0).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct ResolveUniforms {
    /// Viewport width in pixels.
    pub width: u32,
    /// Viewport height in pixels.
    pub height: u32,
    /// Words per pixel in the key buffers (2 or 1).
    pub key_stride: u32,
    /// Offset of the depth word within a pixel's words.
    pub depth_offset: u32,
    /// First point index whose colour this dispatch's colour buffer holds.
    pub first_index: u32,
    /// Number of points in this dispatch's colour buffer.
    pub count: u32,
    /// RGBA8 of empty pixels.
    pub background: u32,
    /// 1 if this dispatch writes the background into empty pixels (the first one only).
    pub write_background: u32,
}

const _: () = assert!(std::mem::size_of::<ResolveUniforms>() == 32);

/// One batch as the plan pass reads it (`shaders/plan.wgsl`; [`super::plan`]): where its points
/// are, its quantization frame and the integer bounds of its points. Written once when the batch
/// is uploaded; 64 bytes; WGSL `PlanBatch`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct PlanBatch {
    /// The batch's smallest integer coordinate per axis ([`crate::quantize::BatchGrid::min`]).
    pub min: [i32; 3],
    /// Position of the batch's draw record in the records buffer.
    pub record: u32,
    /// Smallest integer offset of its points from `min`, per axis.
    pub lo: [u32; 3],
    /// Position of the batch's first point in its chunk's word buffers.
    pub offset: u32,
    /// Largest integer offset of its points from `min`, per axis.
    pub hi: [u32; 3],
    /// Number of points.
    pub count: u32,
    /// Bits per axis of the batch's integer offsets ([`crate::quantize::BatchGrid::bits`]).
    pub bits: [u32; 3],
    /// Index of the batch's first point.
    pub first_index: u32,
}

const _: () = assert!(std::mem::size_of::<PlanBatch>() == 64);

/// The per-frame constants of the plan pass and of its CPU twin ([`super::plan`]): the camera
/// relative to the points' integer grid, in f32; only the split of the eye into an integer and a
/// fractional part is made in f64 on the host. 160 bytes; WGSL `PlanUniforms`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct PlanUniforms {
    /// The eye in grid units, rounded down (clamped to ±(2^31 - 2)).
    pub eye_int: [i32; 3],
    /// 1 for a perspective camera, 0 for orthographic.
    pub perspective: u32,
    /// The eye's grid units minus `eye_int`, in [0, 1).
    pub eye_frac: [f32; 3],
    /// Number of batches the pass plans.
    pub batches: u32,
    /// The view's right axis times the grid scale per axis (world metres of view x per unit).
    pub right: [f32; 4],
    /// The view's up axis times the grid scale.
    pub up: [f32; 4],
    /// The view's forward (depth) axis times the grid scale.
    pub forward: [f32; 4],
    /// |scale| per axis (world units per grid unit).
    pub scale: [f32; 4],
    /// Pixels per unit of `x / depth` (perspective) or of world x (orthographic).
    pub sx: f32,
    /// The same for y.
    pub sy: f32,
    /// Half the viewport width (the principal point's x).
    pub cx: f32,
    /// Half the viewport height.
    pub cy: f32,
    /// Near plane (view depth).
    pub near: f32,
    /// Far plane.
    pub far: f32,
    /// Viewport width in pixels.
    pub width: f32,
    /// Viewport height in pixels.
    pub height: f32,
    /// 0: adaptive precision; 1-3: that many words for every batch (never more than it needs).
    pub words: u32,
    /// 1: frustum culling on.
    pub cull: u32,
    /// How the divisions are made ([`DIVISION_PLAIN`] or [`DIVISION_REFINED`]).
    pub division: u32,
    /// Always 0 (see [`FrameUniforms::zero`]).
    pub zero: u32,
    /// Pixels by which the culling frustum is wider than the viewport.
    pub margin_px: f32,
    /// Relative slack of culling in units of (distance + batch size), for f32 rounding.
    pub slack: f32,
    /// The largest displacement on screen, in pixels, the precision rule accepts.
    pub max_error_px: f32,
    /// Padding.
    pub _pad: u32,
}

const _: () = assert!(std::mem::size_of::<PlanUniforms>() == 160);

/// Counters the plan pass adds to (eight words; WGSL `plan_counters`).
pub mod plan_counter {
    /// Batches culled.
    pub const CULLED: usize = 0;
    /// Batches drawn.
    pub const DRAWN: usize = 1;
    /// Points drawn from 1, 2 and 3 words (three words from here).
    pub const POINTS_BY_WORDS: usize = 2;
    /// Number of words.
    pub const WORDS: usize = 8;
}

/// Constants of the hole-filling pass (`shaders/hole_fill.wgsl`, the twin of
/// [`crate::render::resolve::fill_holes`]). 32 bytes; WGSL `HoleFillUniforms`.
///
/// Reads the framebuffer as [`ResolveUniforms`] does (`key_stride`, `depth_offset`) and writes
/// the filled keys as two words per pixel (point index, then depth bits: a 64-bit key's
/// little-endian words), whatever the atomic path.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct HoleFillUniforms {
    /// Viewport width in pixels.
    pub width: u32,
    /// Viewport height in pixels.
    pub height: u32,
    /// Words per pixel in the key buffers read (2 or 1).
    pub key_stride: u32,
    /// Offset of the depth word within a pixel's words.
    pub depth_offset: u32,
    /// An empty pixel is filled where at least this many of its 8 neighbours hold a point
    /// ([`HoleFill::min_neighbors`], at least 1).
    pub min_neighbors: u32,
    /// Padding.
    pub _pad0: u32,
    /// Padding.
    pub _pad1: u32,
    /// Padding.
    pub _pad2: u32,
}

const _: () = assert!(std::mem::size_of::<HoleFillUniforms>() == 32);

impl HoleFillUniforms {
    /// The uniforms of `fill` over a framebuffer read with `key_stride` and `depth_offset`.
    pub fn new(
        fill: &HoleFill,
        width: u32,
        height: u32,
        key_stride: u32,
        depth_offset: u32,
    ) -> HoleFillUniforms {
        HoleFillUniforms {
            width,
            height,
            key_stride,
            depth_offset,
            min_neighbors: fill.min_neighbors.max(1),
            _pad0: 0,
            _pad1: 0,
            _pad2: 0,
        }
    }
}

/// Constants of the eye-dome lighting pass (`shaders/eye_dome.wgsl`, the twin of the CPU
/// resolve's eye-dome lighting). 176 bytes; WGSL `EyeDomeUniforms`.
///
/// Everything the CPU computes with functions a GPU rounds differently comes from here: the
/// neighbours' integer offsets ([`EyeDome::offsets`]), the exponent's scale ([`EyeDome::scale`])
/// and the polynomial coefficients of `edl_log2` and `edl_exp2` ([`EDL_LOG2_COEFFS`],
/// [`EDL_EXP2_COEFFS`]), so that each is defined once, in Rust.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct EyeDomeUniforms {
    /// Viewport width in pixels.
    pub width: u32,
    /// Viewport height in pixels.
    pub height: u32,
    /// Words per pixel in the key buffer read (2 or 1).
    pub key_stride: u32,
    /// Offset of the depth word within a pixel's words.
    pub depth_offset: u32,
    /// [`EyeDome::scale`].
    pub scale: f32,
    /// Always 0: the rounding barrier of [`FrameUniforms::zero`].
    pub zero: u32,
    /// Padding.
    pub _pad0: u32,
    /// Padding.
    pub _pad1: u32,
    /// The 8 offsets `(dx, dy)`, two per vector: `[dx0, dy0, dx1, dy1]`, ... (a uniform array's
    /// elements are 16 bytes apart).
    pub offsets: [[i32; 4]; 4],
    /// [`EDL_LOG2_COEFFS`], four per vector, the last three 0.
    pub log2_coeffs: [[f32; 4]; 3],
    /// [`EDL_EXP2_COEFFS`], four per vector, the last one 0.
    pub exp2_coeffs: [[f32; 4]; 2],
}

const _: () = assert!(std::mem::size_of::<EyeDomeUniforms>() == 176);

impl EyeDomeUniforms {
    /// The uniforms of `edl` over a framebuffer (or filled keys) read with `key_stride` and
    /// `depth_offset`.
    pub fn new(
        edl: &EyeDome,
        width: u32,
        height: u32,
        key_stride: u32,
        depth_offset: u32,
    ) -> EyeDomeUniforms {
        let o = edl.offsets();
        let offsets =
            std::array::from_fn(|i| [o[2 * i][0], o[2 * i][1], o[2 * i + 1][0], o[2 * i + 1][1]]);
        let mut log2_coeffs = [[0.0; 4]; 3];
        for (i, c) in EDL_LOG2_COEFFS.iter().enumerate() {
            log2_coeffs[i / 4][i % 4] = *c;
        }
        let mut exp2_coeffs = [[0.0; 4]; 2];
        for (i, c) in EDL_EXP2_COEFFS.iter().enumerate() {
            exp2_coeffs[i / 4][i % 4] = *c;
        }
        EyeDomeUniforms {
            width,
            height,
            key_stride,
            depth_offset,
            scale: edl.scale(),
            zero: 0,
            _pad0: 0,
            _pad1: 0,
            offsets,
            log2_coeffs,
            exp2_coeffs,
        }
    }
}

/// Constants of one dispatch of the progressive renderer's scatter pass: staged points
/// `first..first + count` of the input (in input order), of which the pass writes those whose
/// shuffled slot (eq. 1-2 of paper 000, computed in the shader with `prime`) falls in the chunk
/// `[chunk_first, chunk_first + chunk_len)`. 32 bytes; WGSL `ScatterUniforms` in
/// `shaders/progressive_types.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct ScatterUniforms {
    /// 1 when the staged records carry a colour (4 words per point), 0 when not (3 words).
    pub colors: u32,
    /// 1 when the records are one colour each and only colours are written (a colour switch).
    pub colors_only: u32,
    /// The shuffle's prime `P` ([`Shuffle::prime`](super::progressive::Shuffle::prime); 0 below
    /// 3 points: nothing moves).
    pub prime: u32,
    /// Input index of the first staged record.
    pub first: u32,
    /// First slot of the chunk this dispatch writes.
    pub chunk_first: u32,
    /// Slots of the chunk.
    pub chunk_len: u32,
    /// Staged records.
    pub count: u32,
    /// Padding.
    pub _pad: u32,
}

const _: () = assert!(std::mem::size_of::<ScatterUniforms>() == 32);

/// Constants of the progressive renderer's Prepare pass. 16 bytes; WGSL `PrepareUniforms` in
/// `shaders/progressive_types.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct PrepareUniforms {
    /// Pixels of the framebuffer.
    pub pixels: u32,
    /// Slots per chunk (a slot's list is `slot / chunk_slots`).
    pub chunk_slots: u32,
    /// Entries between the starts of two chunks' visible lists.
    pub list_stride: u32,
    /// Number of chunks.
    pub chunks: u32,
}

const _: () = assert!(std::mem::size_of::<PrepareUniforms>() == 16);

/// Constants of the progressive renderer's reframe pass: every loaded slot of a chunk (`count`
/// slots) re-encoded from the quantization frame `from` to `to` when the frame grows
/// ([`ProgressiveFrame::grown`](super::progressive::ProgressiveFrame::grown)). 64 bytes; WGSL
/// `ReframeUniforms` in `shaders/progressive_types.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct ReframeUniforms {
    /// Integer minimum of the old frame.
    pub from_min: [i32; 3],
    /// Slots of the chunk.
    pub count: u32,
    /// Integer minimum of the new frame.
    pub to_min: [i32; 3],
    /// Padding (WGSL aligns vec3 to 16 bytes).
    pub _pad0: u32,
    /// `30 - bits` per axis of the old frame: the right shift from a 30-bit number to the offset.
    pub from_shift: [u32; 3],
    /// Padding.
    pub _pad1: u32,
    /// `30 - bits` per axis of the new frame: the left shift from the offset to a 30-bit number.
    pub to_shift: [u32; 3],
    /// Padding.
    pub _pad2: u32,
}

const _: () = assert!(std::mem::size_of::<ReframeUniforms>() == 64);

impl ReframeUniforms {
    /// The constants of a chunk of `count` slots moving from frame `from` to `to`.
    pub fn new(
        from: &crate::quantize::BatchGrid,
        to: &crate::quantize::BatchGrid,
        count: u32,
    ) -> ReframeUniforms {
        let shift = |g: &crate::quantize::BatchGrid| {
            g.bits.map(|b| crate::quantize::MAX_BITS - (b as u32).min(crate::quantize::MAX_BITS))
        };
        ReframeUniforms {
            from_min: from.min,
            count,
            to_min: to.min,
            _pad0: 0,
            from_shift: shift(from),
            _pad1: 0,
            to_shift: shift(to),
            _pad2: 0,
        }
    }
}

/// Constants of the window's present pass. 32 bytes; WGSL `PresentUniforms` in
/// `shaders/present.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct PresentUniforms {
    /// Image width in pixels (the surface's).
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Overlay width in pixels (0: no overlay).
    pub overlay_width: u32,
    /// Overlay height in pixels.
    pub overlay_height: u32,
    /// 1 when the surface format is sRGB (the shader decodes the image's sRGB bytes to linear).
    pub srgb_target: u32,
    /// Padding.
    pub _pad0: u32,
    /// Padding.
    pub _pad1: u32,
    /// Padding.
    pub _pad2: u32,
}

const _: () = assert!(std::mem::size_of::<PresentUniforms>() == 32);

/// Uniforms of the GPU octree builder's passes (`shaders/octree_common.wgsl`,
/// `mortar_render::octree`; the CPU twin is [`crate::octree::arrival`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct OctreeUniforms {
    /// The first item (point of the bound segment, node, or block of cells) of the dispatch.
    pub first: u32,
    /// Items of the dispatch.
    pub count: u32,
    /// The leaf capacity.
    pub capacity: u32,
    /// Nodes at this level never split.
    pub max_level: u32,
    /// Nodes the node buffer holds.
    pub node_capacity: u32,
    /// The first grid of the bound group of voxel grids.
    pub grid_first: u32,
    /// Grids in the bound group.
    pub grid_count: u32,
    /// Workgroups in x of a dispatch split over x and y.
    pub groups_x: u32,
    /// The insert pass: 0 descends from the root (a new batch), 1 again from a leaf that split;
    /// the voxel pass: 0 numbers the points from `base`, 2 reads each point's arrival number
    /// from the leaf buffer (a paged build's points in leaf order).
    pub mode: u32,
    /// The arrival number of the bound segment's first point.
    pub base: u32,
    /// Unused (16-byte size).
    pub _pad: [u32; 2],
}

/// The constants of a GPU radix sort pass (`SortUniforms` in `shaders/sort_common.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct SortUniforms {
    /// Elements of the dispatch: all of them, or the bound segment's points (`sort_init`).
    pub count: u32,
    /// The first Morton bit of the pass's 4-bit digit.
    pub bit: u32,
    /// Tiles of 2048 elements.
    pub tiles: u32,
    /// Workgroups in x of a dispatch split over x and y.
    pub groups_x: u32,
    /// `sort_init`: the arrival number of the segment's first point.
    pub base: u32,
    /// Blocks of 2048 histogram entries.
    pub blocks: u32,
    /// Histogram entries (16 a tile).
    pub entries: u32,
    /// Unused (16-byte size).
    pub _pad: u32,
}

/// One node of the GPU octree builder's node buffer (`Node` in `shaders/octree_common.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct OctreeNode {
    /// Points in its cube.
    pub count: u32,
    /// Its first child (8 consecutive), or 0 for a leaf.
    pub child: u32,
    /// Its corner relative to the root's.
    pub min: [u32; 3],
    /// `size_log2 | level << 8`.
    pub size_level: u32,
    /// An inner node's voxel grid (the voxel pass).
    pub grid: u32,
    /// A leaf's next slot (the slot pass).
    pub cursor: u32,
}
