// Pass "Prepare" of the progressive renderer (paper 000 §3.4): appends the slot of every pixel's
// winning point to the visible list of the slot's chunk (an atomic counter per chunk), the next
// frame's Reproject input. The 64-bit keys are read as two 32-bit words (index low, depth high);
// an empty pixel has depth bits 0xffffffff, which no drawn point has. Each slot wins at most one
// pixel, so a list never holds more entries than there are pixels.

@group(0) @binding(0) var<uniform> params: PrepareUniforms;
@group(0) @binding(1) var<storage, read> key_words: array<u32>;
@group(0) @binding(2) var<storage, read_write> list_counts: array<atomic<u32>>;
@group(0) @binding(3) var<storage, read_write> lists: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let p = workgroup_linear(wg, groups) * 256u + lid;
    if p >= params.pixels {
        return;
    }
    if key_words[2u * p + 1u] == 0xffffffffu {
        return;
    }
    let slot = key_words[2u * p];
    let c = slot / params.chunk_slots;
    let j = atomicAdd(&list_counts[c], 1u);
    lists[c * params.list_stride + j] = slot;
}
