// Pass "draw batches", 64-bit path (paper 003 §3.2, Listing 1): one workgroup of 128 threads per
// batch, each thread looping over every 128th point of it; per point the one decode and
// projection of common/decode.wgsl, then an early depth test (atomicLoad) and atomicMin of the
// key depth_bits << 32 | index on the pixel. Needs SHADER_INT64 + SHADER_INT64_ATOMIC_MIN_MAX.

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> keys: array<atomic<u64>>;

@compute @workgroup_size(128)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let r = workgroup_linear(wg, groups);
    if r >= arrayLength(&records) {
        return;
    }
    let rec = records[r];
    var drawn = 0u;
    for (var i = lid; i < rec.count; i += 128u) {
        let pt = load_and_project(rec, i, frame);
        if pt.inside {
            drawn += 1u;
            let key = (u64(bitcast<u32>(pt.depth)) << 32u) | u64(rec.first_index + i);
            if key < atomicLoad(&keys[pt.pixel]) {
                atomicMin(&keys[pt.pixel], key);
            }
        }
    }
    count_drawn(drawn, lid);
}
