// The one position decode and projection of the GPU rasterizer: the WGSL twin of
// mortar_core::quantize::join_words + BatchProjection::local + ::transform and the pixel/inside
// test of the CPU loop (lib/core/src/render/raster.rs, project_block). Same operations in the
// same order; every product is multiplied by frame.one (1.0, unknown to the compiler) so that no
// product can be fused into an FMA with the following addition.

// The 30-bit numbers of a point from its first `words` words (coarse bits [20, 30), medium
// [10, 20), fine [0, 10) per axis; axis a in bits [10a, 10a + 10) of each word).
fn join_words(coarse: u32, medium: u32, fine: u32, words: u32) -> vec3<u32> {
    let lane = vec3<u32>(0u, 10u, 20u);
    var q = ((vec3<u32>(coarse) >> lane) & vec3<u32>(0x3ffu)) << vec3<u32>(20u);
    if words >= 2u {
        q = q | (((vec3<u32>(medium) >> lane) & vec3<u32>(0x3ffu)) << vec3<u32>(10u));
    }
    if words >= 3u {
        q = q | ((vec3<u32>(fine) >> lane) & vec3<u32>(0x3ffu));
    }
    return q;
}

struct Projected {
    // Row-major pixel index, valid where inside is true.
    pixel: u32,
    // View depth (positive where inside).
    depth: f32,
    inside: bool,
}

// One row of pixel_from_local applied to l: ((m.x l.x + m.y l.y) + m.z l.z) + m.w, each product
// rounded on its own.
fn row(m: vec4<f32>, l: vec3<f32>, one: f32) -> f32 {
    let a = (m.x * l.x) * one;
    let b = (m.y * l.y) * one;
    let c = (m.z * l.z) * one;
    return ((a + b) + c) + m.w;
}

fn project(p: BatchProjection, q: vec3<u32>, frame: FrameUniforms) -> Projected {
    // Integer offset minus anchor (wrapping i32), then to f32: BatchProjection::local.
    let l = vec3<f32>(bitcast<vec3<i32>>(q >> p.shift) - p.anchor);
    let x = row(p.pixel_from_local[0], l, frame.one);
    let y = row(p.pixel_from_local[1], l, frame.one);
    let depth = row(p.pixel_from_local[2], l, frame.one);
    var fx = x;
    var fy = y;
    if frame.perspective != 0u {
        fx = x / depth;
        fy = y / depth;
    }
    let ox = p.pixel_origin.x;
    let oy = p.pixel_origin.y;
    let x_lo = f32(-ox);
    let x_hi = f32(i32(frame.width) - ox);
    let y_lo = f32(-oy);
    let y_hi = f32(i32(frame.height) - oy);
    var out: Projected;
    // Also false for NaN. Inside [near, far] the perspective divisor is positive.
    out.inside = depth >= frame.near && depth <= frame.far && fx >= x_lo && fx < x_hi && fy >= y_lo && fy < y_hi;
    // Inside the viewport |fx|, |fy| < 32768, so floor and the conversion are exact.
    let px = i32(floor(fx)) + ox;
    let py = i32(floor(fy)) + oy;
    out.pixel = u32(py * i32(frame.width) + px);
    out.depth = depth;
    return out;
}
