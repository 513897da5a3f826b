// Pass "draw batches", 32-bit path, step 2 of 2: every point projects again exactly as in step 1
// (draw_depth.wgsl); where its depth equals the pixel's winning depth, atomicMin of its index.
// The pixel ends with the nearest depth and, among points at that depth, the smallest index: the
// same winner as the 64-bit key of draw.wgsl.

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> depths: array<u32>;
@group(0) @binding(3) var<storage, read_write> indices: array<atomic<u32>>;

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
            if bitcast<u32>(pt.depth) == depths[pt.pixel] {
                let index = rec.first_index + i;
                if index < atomicLoad(&indices[pt.pixel]) {
                    atomicMin(&indices[pt.pixel], index);
                }
            }
        }
    }
    count_drawn(drawn, lid);
}
