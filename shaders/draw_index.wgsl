// Pass "draw batches", 32-bit path, step 2 of 2: every point projects again exactly as in step 1
// (draw_depth.wgsl); where its depth equals the pixel's winning depth, atomicMin of its index.
// The pixel ends with the nearest depth and, among points at that depth, the smallest index: the
// same winner as the 64-bit key of draw.wgsl.

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> depths: array<u32>;
@group(0) @binding(3) var<storage, read_write> indices: array<atomic<u32>>;
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
    var drawn = 0u;
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
