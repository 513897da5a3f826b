// Pass "eye-dome lighting" (paper 003 §3.5): shades the resolved image in place from the depths
// of the keys it was resolved from (the framebuffer, or the hole-filled keys), the twin of the
// eye-dome lighting of mortar_core::render::resolve::resolve operation for operation: the
// neighbours' integer offsets, the exponent's scale and the polynomial coefficients come from
// the host (EyeDomeUniforms), log2 and exp2 are built from exponent bits and those polynomials
// (edl_log2, edl_exp2 in Rust), and every floating-point operation is rounded on its own (see
// opaque), so that the image equals the CPU's byte for byte. Empty pixels keep the background.

@group(0) @binding(0) var<uniform> params: EyeDomeUniforms;
@group(0) @binding(1) var<storage, read> depth_words: array<u32>;
@group(0) @binding(2) var<storage, read_write> image: array<u32>;

const EMPTY: u32 = 0xffffffffu;
// Coefficients in params.log2_coeffs and params.exp2_coeffs (EDL_LOG2_COEFFS, EDL_EXP2_COEFFS).
const LOG2_TERMS: u32 = 9u;
const EXP2_TERMS: u32 = 7u;

// The value of v, its bits xor-ed with params.zero (always 0): the compiler can neither fuse a
// product with a following addition (an FMA rounds once where the CPU rounds twice) nor
// reassociate across it (as opaque() in common/decode.wgsl).
fn opaque(v: f32) -> f32 {
    return bitcast<f32>(bitcast<u32>(v) ^ params.zero);
}

fn log2_coeff(i: u32) -> f32 {
    return params.log2_coeffs[i / 4u][i % 4u];
}

fn exp2_coeff(i: u32) -> f32 {
    return params.exp2_coeffs[i / 4u][i % 4u];
}

// mortar_core::render::resolve::edl_log2.
fn edl_log2(depth_bits: u32) -> f32 {
    let b = clamp(depth_bits, 0x00800000u, 0x7f7fffffu);
    var e = i32(b >> 23u) - 127;
    let mant = b & 0x007fffffu;
    var m: f32;
    if mant > 0x003504f3u {
        e += 1;
        m = bitcast<f32>(mant | 0x3f000000u);
    } else {
        m = bitcast<f32>(mant | 0x3f800000u);
    }
    let t = opaque(m - 1.0);
    var p = log2_coeff(LOG2_TERMS - 1u);
    for (var i = LOG2_TERMS - 1u; i > 0u; i--) {
        p = opaque(opaque(p * t) + log2_coeff(i - 1u));
    }
    return opaque(opaque(t * p) + f32(e));
}

// mortar_core::render::resolve::edl_exp2.
fn edl_exp2(y_in: f32) -> f32 {
    if !(y_in > -64.0) {
        return 0.0;
    }
    let y = min(y_in, 64.0);
    let n = floor(y);
    let f = opaque(y - n);
    var p = exp2_coeff(EXP2_TERMS - 1u);
    for (var i = EXP2_TERMS - 1u; i > 0u; i--) {
        p = opaque(opaque(p * f) + exp2_coeff(i - 1u));
    }
    let q = opaque(opaque(f * p) + 1.0);
    return opaque(q * bitcast<f32>(u32(i32(n) + 127) << 23u));
}

// mortar_core::render::resolve::shade: each channel floor(v f + 0.5), at most 255; alpha kept.
fn shade(c: u32, f: f32) -> u32 {
    var out = c & 0xff000000u;
    for (var s = 0u; s < 24u; s += 8u) {
        let v = f32((c >> s) & 0xffu);
        let r = min(floor(opaque(opaque(v * f) + 0.5)), 255.0);
        out |= u32(r) << s;
    }
    return out;
}

fn depth_at(q: u32) -> u32 {
    return depth_words[q * params.key_stride + params.depth_offset];
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let p = workgroup_linear(wg, groups) * 256u + lid;
    let w = params.width;
    let h = params.height;
    if p >= w * h {
        return;
    }
    let depth = depth_at(p);
    if depth == EMPTY {
        return;
    }
    let d = edl_log2(depth);
    let x = i32(p % w);
    let y = i32(p / w);
    var sum = 0.0;
    for (var i = 0u; i < 8u; i++) {
        let pair = params.offsets[i / 2u];
        var o = pair.xy;
        if (i & 1u) == 1u {
            o = pair.zw;
        }
        let nx = x + o.x;
        let ny = y + o.y;
        if nx < 0 || ny < 0 || nx >= i32(w) || ny >= i32(h) {
            continue;
        }
        let nd = depth_at(u32(ny) * w + u32(nx));
        if nd != EMPTY {
            sum = opaque(sum + max(opaque(d - edl_log2(nd)), 0.0));
        }
    }
    let factor = edl_exp2(-opaque(opaque(sum * 0.125) * params.scale));
    image[p] = shade(image[p], factor);
}
