// Pass "scatter" of the progressive renderer (paper 000 §3.3, the Distribute step): moves points
// that arrived into their shuffled slots of one chunk. The host staged the points in input order,
// one record each: the coarse, medium and fine words and, with colours, the RGBA8 colour; or, with
// `colors_only`, the colour alone (a colour-mode switch streamed in piece by piece, §3.5). Each
// thread computes its point's slot, `target(first + i)` (eq. 1-2: twice `i^2 mod P`, mirrored
// above P/2), the twin of mortar_core's Shuffle::target, and writes the record when that slot is
// in this dispatch's chunk (one dispatch per chunk). Slots are distinct, so threads need no
// synchronisation. Needs SHADER_INT64 (the 64-bit square and remainder).

@group(0) @binding(0) var<uniform> params: ScatterUniforms;
@group(0) @binding(1) var<storage, read> staged: array<u32>;
@group(0) @binding(2) var<storage, read_write> coarse_out: array<u32>;
@group(0) @binding(3) var<storage, read_write> medium_out: array<u32>;
@group(0) @binding(4) var<storage, read_write> fine_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> colors_out: array<u32>;

// Eq. 1: i^2 mod P for i <= P/2, P - (i^2 mod P) for P/2 < i < P, i from P on.
fn permute(i: u32) -> u32 {
    let p = params.prime;
    if i >= p {
        return i;
    }
    let r = u32((u64(i) * u64(i)) % u64(p));
    if i <= p / 2u {
        return r;
    }
    return p - r;
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = workgroup_linear(wg, groups) * 256u + lid;
    if i >= params.count {
        return;
    }
    // Unsigned: slots below the chunk wrap to large values and fail the test too.
    let slot = permute(permute(params.first + i)) - params.chunk_first;
    if slot >= params.chunk_len {
        return;
    }
    if params.colors_only != 0u {
        colors_out[slot] = staged[i];
        return;
    }
    let r = i * (3u + params.colors);
    coarse_out[slot] = staged[r];
    medium_out[slot] = staged[r + 1u];
    fine_out[slot] = staged[r + 2u];
    if params.colors != 0u {
        colors_out[slot] = staged[r + 3u];
    }
}
