// Pass "scatter" of the progressive renderer (paper 000 §3.3, the Distribute step): moves points
// that arrived into their shuffled slots of one chunk. The host computed each point's slot with
// mortar_core's Shuffle::target and staged one record per point: the slot relative to the chunk,
// the coarse, medium and fine words and, with colours, the RGBA8 colour. Slots are distinct, so
// threads need no synchronisation. With `colors_only` the records are (slot, colour) and only the
// colours are written: a colour-mode switch streamed in piece by piece (§3.5).

@group(0) @binding(0) var<uniform> params: ScatterUniforms;
@group(0) @binding(1) var<storage, read> staged: array<u32>;
@group(0) @binding(2) var<storage, read_write> coarse_out: array<u32>;
@group(0) @binding(3) var<storage, read_write> medium_out: array<u32>;
@group(0) @binding(4) var<storage, read_write> fine_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> colors_out: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = workgroup_linear(wg, groups) * 256u + lid;
    if params.colors_only != 0u {
        if i >= arrayLength(&staged) / 2u {
            return;
        }
        colors_out[staged[2u * i]] = staged[2u * i + 1u];
        return;
    }
    let stride = 4u + params.colors;
    if i >= arrayLength(&staged) / stride {
        return;
    }
    let r = i * stride;
    let slot = staged[r];
    coarse_out[slot] = staged[r + 1u];
    medium_out[slot] = staged[r + 2u];
    fine_out[slot] = staged[r + 3u];
    if params.colors != 0u {
        colors_out[slot] = staged[r + 4u];
    }
}
