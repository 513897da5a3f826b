// Pass "present" (the window of `mortar view`): copies the resolved image (the RGBA8 words the
// resolve pass wrote, one per pixel, row-major from the top-left) into the window's surface
// texture, with the status line's overlay blended over its top-left corner. A render pass, not a
// compute pass, so that any surface format works (Bgra8 or Rgba8, sRGB or not) without storage
// texture support: the fragment output is converted by the hardware.
//
// KEEP IN SYNC with mortar_core::render::gpu::PresentUniforms (lib/core/src/render/gpu.rs,
// 32 bytes; mortar-render's layout test compares them).

struct PresentUniforms {
    // Size of the image (equal to the surface's).
    width: u32,
    height: u32,
    // Size of the overlay (0 x 0: none); its words are RGBA8 with alpha as coverage.
    overlay_width: u32,
    overlay_height: u32,
    // 1 when the surface format is sRGB: the image's sRGB bytes are decoded to linear first, so
    // that the hardware's encoding gives them back.
    srgb_target: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: PresentUniforms;
@group(0) @binding(1) var<storage, read> image: array<u32>;
@group(0) @binding(2) var<storage, read> overlay: array<u32>;

// One triangle covering the viewport: (-1, -1), (3, -1), (-1, 3).
@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let x = f32((i & 1u) << 2u) - 1.0;
    let y = f32((i & 2u) << 1u) - 1.0;
    return vec4<f32>(x, y, 0.0, 1.0);
}

fn srgb_to_linear(c: vec3<f32>) -> vec3<f32> {
    let lo = c / 12.92;
    let hi = pow((c + vec3<f32>(0.055)) / 1.055, vec3<f32>(2.4));
    return select(hi, lo, c <= vec3<f32>(0.04045));
}

@fragment
fn fs_main(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
    // Framebuffer coordinates: the pixel centre, y down from the top-left corner.
    let x = u32(pos.x);
    let y = u32(pos.y);
    var c = vec3<f32>(0.0);
    if x < params.width && y < params.height {
        c = unpack4x8unorm(image[y * params.width + x]).rgb;
    }
    if x < params.overlay_width && y < params.overlay_height {
        let o = unpack4x8unorm(overlay[y * params.overlay_width + x]);
        c = mix(c, o.rgb, o.a);
    }
    if params.srgb_target != 0u {
        c = srgb_to_linear(c);
    }
    return vec4<f32>(c, 1.0);
}
