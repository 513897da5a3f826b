// Pass "Reproject" of the progressive renderer (paper 000 §3.4): draws the points that were
// visible at the end of the last frame, from their words in the shuffled buffer and with their
// slot as the index ("we identify the original point projected to a pixel and reproject it from
// its original coordinates"). One dispatch per chunk: `visible` is that chunk's list of slots
// (global), records[0] has offset 0, count = entries, first_index = the chunk's first slot.
// Needs SHADER_INT64 + SHADER_INT64_ATOMIC_MIN_MAX.

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> keys: array<atomic<u64>>;
@group(0) @binding(3) var<storage, read> visible: array<u32>;

@compute @workgroup_size(128)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let rec = records[0];
    let first = workgroup_linear(wg, groups) * (128u * SLOTS_PER_THREAD);
    var drawn = 0u;
    for (var k = 0u; k < SLOTS_PER_THREAD; k += 1u) {
        let j = first + k * 128u + lid;
        if j < rec.count {
            let slot = visible[j];
            let pt = load_and_project(rec, slot - rec.first_index, frame);
            if pt.inside {
                drawn += 1u;
                let key = (u64(bitcast<u32>(pt.depth)) << 32u) | u64(slot);
                if key < atomicLoad(&keys[pt.pixel]) {
                    atomicMin(&keys[pt.pixel], key);
                }
            }
        }
    }
    count_drawn(drawn, lid);
}
