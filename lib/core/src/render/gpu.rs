//! The `#[repr(C)]` records the GPU rasterizer (mortar-render, `shaders/`) reads, defined once
//! here next to the CPU twin that fills the same fields. Every struct has a WGSL mirror in
//! `shaders/common/types.wgsl` (keep both in sync: mortar-render's layout test compares the
//! offsets and sizes naga computes for the WGSL structs with these).

use super::camera::{BatchProjection, Camera};

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
