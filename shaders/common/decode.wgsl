// The one position decode and projection of the GPU rasterizer: the WGSL twin of
// mortar_core::quantize::join_words + BatchProjection::local + ::transform and the pixel/inside
// test of the CPU loop (lib/core/src/render/raster.rs, project_block). Same operations in the
// same order, each rounded on its own (see opaque).

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

// The value of v, its bits xor-ed with `zero` (frame.zero, always 0): a barrier the shader
// compiler cannot see through, so it can neither fuse the product before it with a following
// addition (an FMA rounds once where the CPU rounds twice) nor reassociate across it.
fn opaque(v: f32, zero: u32) -> f32 {
    return bitcast<f32>(bitcast<u32>(v) ^ zero);
}

// One row of pixel_from_local applied to l: ((m.x l.x + m.y l.y) + m.z l.z) + m.w, every
// operation rounded on its own, as in the CPU loop.
fn row(m: vec4<f32>, l: vec3<f32>, zero: u32) -> f32 {
    let a = opaque(m.x * l.x, zero);
    let b = opaque(m.y * l.y, zero);
    let c = opaque(m.z * l.z, zero);
    return opaque(opaque(a + b, zero) + c, zero) + m.w;
}

// x / d correctly rounded, as the CPU divides, on GPUs whose division is not: a Newton step on
// the reciprocal, then one correction by the remainder r = x - q d from a fused multiply-add
// (Markstein; the sequence of CUDA's div.rn). Valid for the normal, finite values of the points
// kept (d >= near > 0) where fma is fused. Chosen by FrameUniforms.division (see gpu.rs).
fn div_rn(x: f32, d: f32, zero: u32) -> f32 {
    let y0 = opaque(1.0 / d, zero);
    let y = opaque(fma(opaque(fma(-d, y0, 1.0), zero), y0, y0), zero);
    let q0 = opaque(x * y, zero);
    let r = opaque(fma(-q0, d, x), zero);
    return opaque(fma(r, y, q0), zero);
}

fn divide(x: f32, d: f32, frame: FrameUniforms) -> f32 {
    if frame.division == 1u {
        return div_rn(x, d, frame.zero);
    }
    return opaque(x / d, frame.zero);
}

fn project(p: BatchProjection, q: vec3<u32>, frame: FrameUniforms) -> Projected {
    // Integer offset minus anchor (wrapping i32), then to f32: BatchProjection::local.
    let l = vec3<f32>(bitcast<vec3<i32>>(q >> p.shift) - p.anchor);
    let x = row(p.pixel_from_local[0], l, frame.zero);
    let y = row(p.pixel_from_local[1], l, frame.zero);
    let depth = row(p.pixel_from_local[2], l, frame.zero);
    var fx = x;
    var fy = y;
    if frame.perspective != 0u {
        fx = divide(x, depth, frame);
        fy = divide(y, depth, frame);
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
