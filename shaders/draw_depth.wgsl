// Pass "draw batches", 32-bit path, step 1 of 2 (for devices without 64-bit atomics): the same
// workgroups, decode and projection as draw.wgsl, with atomicMin of the depth bits alone (f32
// bits of a positive depth order like the value). Step 2 is draw_index.wgsl.

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> depths: array<atomic<u32>>;

@compute @workgroup_size(128)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let r = workgroup_linear(wg, groups);
    if r >= arrayLength(&records) {
        return;
    }
    let rec = records[r];
    for (var i = lid; i < rec.count; i += 128u) {
        let pt = load_and_project(rec, i, frame);
        if pt.inside {
            let d = bitcast<u32>(pt.depth);
            if d < atomicLoad(&depths[pt.pixel]) {
                atomicMin(&depths[pt.pixel], d);
            }
        }
    }
}
