// Types shared by the passes of the GPU rasterizer.
//
// KEEP IN SYNC with their #[repr(C)] twins in Rust, all in mortar_core::render::gpu
// (lib/core/src/render/gpu.rs; one definition per layout; mortar-render's layout test compares
// the offsets and sizes naga computes here with the Rust ones):
//   BatchProjection  (112 bytes; defined in lib/core/src/render/camera.rs, re-exported by gpu.rs)
//   DrawRecord       (128 bytes)
//   FrameUniforms    (32 bytes)
//   ResolveUniforms  (32 bytes)
//   PlanBatch        (64 bytes)
//   PlanUniforms     (160 bytes)
//   HoleFillUniforms (32 bytes)
//   EyeDomeUniforms  (176 bytes)

struct BatchProjection {
    // Rows X, Y, D, W of pixel_from_local (row-major, as in Rust; not a WGSL matrix).
    pixel_from_local: array<vec4<f32>, 4>,
    anchor: vec3<i32>,
    words: u32,
    shift: vec3<u32>,
    _pad0: u32,
    pixel_origin: vec2<i32>,
    _pad1: vec2<u32>,
}

struct DrawRecord {
    projection: BatchProjection,
    offset: u32,
    count: u32,
    first_index: u32,
    _pad: u32,
}

struct FrameUniforms {
    width: u32,
    height: u32,
    near: f32,
    far: f32,
    perspective: u32,
    zero: u32,
    division: u32,
    _pad: u32,
}

struct ResolveUniforms {
    width: u32,
    height: u32,
    key_stride: u32,
    depth_offset: u32,
    first_index: u32,
    count: u32,
    background: u32,
    write_background: u32,
}

struct PlanBatch {
    min: vec3<i32>,
    record: u32,
    lo: vec3<u32>,
    offset: u32,
    hi: vec3<u32>,
    count: u32,
    bits: vec3<u32>,
    first_index: u32,
}

struct PlanUniforms {
    eye_int: vec3<i32>,
    perspective: u32,
    eye_frac: vec3<f32>,
    batches: u32,
    right: vec4<f32>,
    up: vec4<f32>,
    forward: vec4<f32>,
    scale: vec4<f32>,
    sx: f32,
    sy: f32,
    cx: f32,
    cy: f32,
    near: f32,
    far: f32,
    width: f32,
    height: f32,
    words: u32,
    cull: u32,
    division: u32,
    zero: u32,
    margin_px: f32,
    slack: f32,
    max_error_px: f32,
    _pad: u32,
}

struct HoleFillUniforms {
    width: u32,
    height: u32,
    key_stride: u32,
    depth_offset: u32,
    min_neighbors: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

struct EyeDomeUniforms {
    width: u32,
    height: u32,
    key_stride: u32,
    depth_offset: u32,
    scale: f32,
    zero: u32,
    _pad0: u32,
    _pad1: u32,
    // The 8 neighbour offsets, two (dx, dy) per vector.
    offsets: array<vec4<i32>, 4>,
    // The polynomial coefficients of edl_log2 (9) and edl_exp2 (7), lowest first, four per vector.
    log2_coeffs: array<vec4<f32>, 3>,
    exp2_coeffs: array<vec4<f32>, 2>,
}

// The linear index of a workgroup in a dispatch split over x and y (at most 65,535 per dimension).
fn workgroup_linear(wg: vec3<u32>, groups: vec3<u32>) -> u32 {
    return wg.y * groups.x + wg.x;
}
