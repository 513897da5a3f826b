// Pass "draw batches", 32-bit path, step 1 of 2 (for devices without 64-bit atomics): the same
// workgroups, decode and projection as draw.wgsl, with atomicMin of the depth bits alone (f32
// bits of a positive depth order like the value). Step 2 is draw_index.wgsl.

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> depths: array<atomic<u32>>;
@group(1) @binding(0) var<storage, read> records: array<DrawRecord>;
@group(1) @binding(1) var<storage, read> coarse: array<u32>;
@group(1) @binding(2) var<storage, read> medium: array<u32>;
@group(1) @binding(3) var<storage, read> fine: array<u32>;

@compute @workgroup_size(128)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let r = workgroup_linear(wg, groups);
    if r >= arrayLength(&records) {
        return;
    }
    let rec = records[r];
    let p = rec.projection;
    for (var i = lid; i < rec.count; i += 128u) {
        let s = rec.offset + i;
        var m = 0u;
        var f = 0u;
        if p.words >= 2u {
            m = medium[s];
        }
        if p.words >= 3u {
            f = fine[s];
        }
        let pt = project(p, join_words(coarse[s], m, f, p.words), frame);
        if pt.inside {
            let d = bitcast<u32>(pt.depth);
            if d < atomicLoad(&depths[pt.pixel]) {
                atomicMin(&depths[pt.pixel], d);
            }
        }
    }
}
