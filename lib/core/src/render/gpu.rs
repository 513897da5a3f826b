//! The `#[repr(C)]` records the GPU passes (mortar-render, `shaders/`) read, defined once here:
//! the rasterizer's [`DrawRecord`], [`FrameUniforms`] and [`ResolveUniforms`] next to the CPU twin
//! that fills the same fields, the progressive renderer's [`ScatterUniforms`] and
//! [`PrepareUniforms`], and the window's [`PresentUniforms`]. [`BatchProjection`] (inside
//! [`DrawRecord`]) lives with the camera maths that computes it and is re-exported here.
//!
//! Every struct has a WGSL mirror (keep both in sync: mortar-render's layout tests compare the
//! offsets and sizes naga computes for the WGSL structs with these):
//! - `shaders/common/types.wgsl`: `BatchProjection`, `DrawRecord`, `FrameUniforms`, `ResolveUniforms`;
//! - `shaders/progressive_types.wgsl`: `ScatterUniforms`, `PrepareUniforms`;
//! - `shaders/present.wgsl`: `PresentUniforms`.
//!
//! Only bytemuck layouts here: no GPU API (the crate graph keeps core free of wgpu).

pub use super::camera::BatchProjection;
use super::camera::Camera;

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

/// Constants of the progressive renderer's scatter pass. 16 bytes; WGSL `ScatterUniforms` in
/// `shaders/progressive_types.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct ScatterUniforms {
    /// 1 when the staged records carry a colour (5 words per point), 0 when not (4 words).
    pub colors: u32,
    /// 1 when the records are (slot, colour) and only colours are written (a colour switch).
    pub colors_only: u32,
    /// Padding.
    pub _pad1: u32,
    /// Padding.
    pub _pad2: u32,
}

const _: () = assert!(std::mem::size_of::<ScatterUniforms>() == 16);

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
