// Pass "ties" of the progressive renderer: after a frame, every slot of a run of one chunk
// (records[0], as Fill draws them) is projected again, and the pixel it lands in is marked when
// the point has exactly the depth of the pixel's winner but is another point: a tie that the
// smaller index decided, so a renderer that numbers points otherwise may show another of them
// (the twin of mortar_core::render::count_depth_ties). Reads the keys as words (index at 2p,
// depth bits at 2p + 1), so it needs no 64-bit integers.

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read> key_words: array<u32>;
@group(0) @binding(2) var<storage, read_write> ties: array<u32>;

@compute @workgroup_size(128)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let rec = records[0];
    let first = workgroup_linear(wg, groups) * (128u * SLOTS_PER_THREAD);
    for (var k = 0u; k < SLOTS_PER_THREAD; k += 1u) {
        let i = first + k * 128u + lid;
        if i < rec.count && coarse[rec.offset + i] != UNLOADED {
            let pt = load_and_project(rec, i, frame);
            if pt.inside {
                let slot = rec.first_index + i;
                let p = pt.pixel;
                if bitcast<u32>(pt.depth) == key_words[2u * p + 1u] && slot != key_words[2u * p] {
                    ties[p] = 1u;
                }
            }
        }
    }
}
