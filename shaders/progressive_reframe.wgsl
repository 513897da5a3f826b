// Pass "reframe" of the progressive renderer: when points arrive outside the quantization frame,
// the frame grows (mortar_core::render::progressive::ProgressiveFrame::grown) and every loaded
// slot of one chunk is re-encoded from the old frame to the new one, exactly (both hold every
// bit): the 30-bit numbers of the three words, the integer offset in the old frame, the integer
// position, the offset in the new frame, its 30-bit numbers, the three words. Unloaded slots
// (coarse word UNLOADED) stay as they are. The twin of ProgressiveFrame::reencode
// (BatchGrid::decode_exact, then BatchGrid::encode).

@group(0) @binding(0) var<uniform> params: ReframeUniforms;
@group(0) @binding(1) var<storage, read_write> coarse_words: array<u32>;
@group(0) @binding(2) var<storage, read_write> medium_words: array<u32>;
@group(0) @binding(3) var<storage, read_write> fine_words: array<u32>;

// Bits [10 a + lane, ..) of the three words of a point as one 10-bit field per axis, placed at
// `shift` of the 30-bit numbers.
fn field(w: u32, shift: u32) -> vec3<u32> {
    return ((vec3<u32>(w) >> vec3<u32>(0u, 10u, 20u)) & vec3<u32>(0x3ffu)) << vec3<u32>(shift);
}

// One word of split_words: bits [shift, shift + 10) of each axis' 30-bit number.
fn word(q: vec3<u32>, shift: u32) -> u32 {
    let f = (q >> vec3<u32>(shift)) & vec3<u32>(0x3ffu);
    return f.x | (f.y << 10u) | (f.z << 20u);
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = workgroup_linear(wg, groups) * 256u + lid;
    if i >= params.count {
        return;
    }
    let c = coarse_words[i];
    if c == UNLOADED {
        return;
    }
    let q = field(c, 20u) | field(medium_words[i], 10u) | field(fine_words[i], 0u);
    // Integer position, then its offset in the new frame (both fit: the new frame holds the old).
    let p = params.from_min + bitcast<vec3<i32>>(q >> params.from_shift);
    let n = bitcast<vec3<u32>>(p - params.to_min) << params.to_shift;
    coarse_words[i] = word(n, 20u);
    medium_words[i] = word(n, 10u);
    fine_words[i] = word(n, 0u);
}
