// Pass "unload" of the progressive renderer: every coarse word of one chunk of the shuffled buffer
// to UNLOADED, once, when the buffer is made (the slots whose point has not arrived yet, which
// Fill skips as the paper discards default-initialized vertices, §3.2).

@group(0) @binding(0) var<storage, read_write> coarse_words: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = workgroup_linear(wg, groups) * 256u + lid;
    if i < arrayLength(&coarse_words) {
        coarse_words[i] = UNLOADED;
    }
}
