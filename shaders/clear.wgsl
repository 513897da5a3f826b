// Pass "clear": every 32-bit word of a framebuffer buffer to 0xffffffff (an empty pixel: the
// 64-bit key u64::MAX, or depth and index both all ones in the 32-bit path).

@group(0) @binding(0) var<storage, read_write> words: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = workgroup_linear(wg, groups) * 256u + lid;
    if i < arrayLength(&words) {
        words[i] = 0xffffffffu;
    }
}
