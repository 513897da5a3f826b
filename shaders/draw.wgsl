// Pass "draw batches", 64-bit path (paper 003 §3.2, Listing 1): one workgroup of WG (128) threads
// per batch, each thread looping over every WG-th point of it; per point the one decode and
// projection of common/decode.wgsl, then an early depth test and atomicMin of the key
// depth_bits << 32 | index on the pixel. Needs SHADER_INT64 + SHADER_INT64_ATOMIC_MIN_MAX.
//
// KERNEL and WG are pipeline-overridable for the measurements of issue 17
// (mortar_render::DrawTuning); the renderer uses the defaults:
//   0: early depth test with atomicLoad of the 64-bit key, then atomicMin (the renderer);
//   1: early depth test with a plain load of the key's depth word (key_words aliases keys; a
//      stale value is never smaller than the current one, so the test only lets more through);
//   2: no early depth test: atomicMin for every point inside;
//   3: no framebuffer access at all (load, decode, project, count): the floor of the pass;
//   4: kernel 0 with the words of four points loaded before any of them is projected (the
//      paper's prefetch, §3.4), so that four loads are in flight per thread.

override KERNEL: u32 = 0u;
override WG: u32 = 128u;

@group(0) @binding(0) var<uniform> frame: FrameUniforms;
@group(0) @binding(1) var<storage, read_write> keys: array<atomic<u64>>;
@group(0) @binding(3) var<storage, read_write> key_words: array<u32>;

@compute @workgroup_size(WG)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let r = workgroup_linear(wg, groups);
    if r >= arrayLength(&records) {
        return;
    }
    let rec = records[r];
    var drawn = 0u;
    if KERNEL == 4u {
        for (var base = lid; base < rec.count; base += 4u * WG) {
            var w: array<vec3<u32>, 4>;
            for (var k = 0u; k < 4u; k++) {
                let i = base + k * WG;
                if i < rec.count {
                    w[k] = load_words(rec, i);
                }
            }
            for (var k = 0u; k < 4u; k++) {
                let i = base + k * WG;
                if i < rec.count {
                    let pt = project_words(rec, w[k], frame);
                    if pt.inside {
                        drawn += 1u;
                        let key = (u64(bitcast<u32>(pt.depth)) << 32u) | u64(rec.first_index + i);
                        if key < atomicLoad(&keys[pt.pixel]) {
                            atomicMin(&keys[pt.pixel], key);
                        }
                    }
                }
            }
        }
        count_drawn(drawn, lid);
        return;
    }
    for (var i = lid; i < rec.count; i += WG) {
        let pt = load_and_project(rec, i, frame);
        if pt.inside {
            drawn += 1u;
            let key = (u64(bitcast<u32>(pt.depth)) << 32u) | u64(rec.first_index + i);
            if KERNEL == 0u {
                if key < atomicLoad(&keys[pt.pixel]) {
                    atomicMin(&keys[pt.pixel], key);
                }
            } else if KERNEL == 1u {
                if bitcast<u32>(pt.depth) <= key_words[pt.pixel * 2u + 1u] {
                    atomicMin(&keys[pt.pixel], key);
                }
            } else if KERNEL == 2u {
                atomicMin(&keys[pt.pixel], key);
            }
        }
    }
    count_drawn(drawn, lid);
}
