// Pass "Fill" of the progressive renderer (paper 000 §3.4): draws a run of consecutive slots of
// one chunk of the shuffled buffer (records[0]: offset = first slot in the chunk, count = slots,
// first_index = the global slot of `offset`, projection = the one plan of every slot), skipping
// slots whose point has not arrived (coarse word UNLOADED). Per point the one decode and
// projection of common/decode.wgsl, an early depth test and atomicMin of depth_bits << 32 | slot,
// as in draw.wgsl. Needs SHADER_INT64 + SHADER_INT64_ATOMIC_MIN_MAX.

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> keys: array<atomic<u64>>;

@compute @workgroup_size(128)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let rec = records[0];
    let first = workgroup_linear(wg, groups) * (128u * SLOTS_PER_THREAD);
    var drawn = 0u;
    for (var k = 0u; k < SLOTS_PER_THREAD; k += 1u) {
        let i = first + k * 128u + lid;
        if i < rec.count && coarse[rec.offset + i] != UNLOADED {
            let pt = load_and_project(rec, i, frame);
            if pt.inside {
                drawn += 1u;
                let key = (u64(bitcast<u32>(pt.depth)) << 32u) | u64(rec.first_index + i);
                if key < atomicLoad(&keys[pt.pixel]) {
                    atomicMin(&keys[pt.pixel], key);
                }
            }
        }
    }
    count_drawn(drawn, lid);
}
