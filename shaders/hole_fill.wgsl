// Pass "hole fill" (depth-aware hole filling, paper 003 §3.5): the twin of
// mortar_core::render::resolve::fill_holes. An empty pixel takes the smallest key among the
// non-empty pixels of its 3x3 window where at least min_neighbors of them hold a point; a
// covered pixel keeps its key. Reads only the framebuffer and writes a second buffer, so filling
// never spreads further than one pixel.
//
// The framebuffer is read as 32-bit words as resolve.wgsl reads it (index_words/depth_words with
// key_stride and depth_offset: the 64-bit keys, or the 32-bit path's indices and depths); a
// pixel is empty where its depth word is all ones. Keys compare as (depth word, index word)
// lexicographically, which is the 64-bit key order, with u32 operations only (no SHADER_INT64).
// The output holds two words per pixel, index then depth (a 64-bit key's little-endian words).

@group(0) @binding(0) var<uniform> params: HoleFillUniforms;
@group(0) @binding(1) var<storage, read> index_words: array<u32>;
@group(0) @binding(2) var<storage, read> depth_words: array<u32>;
@group(0) @binding(3) var<storage, read_write> filled: array<u32>;

const EMPTY: u32 = 0xffffffffu;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let p = workgroup_linear(wg, groups) * 256u + lid;
    let w = params.width;
    let h = params.height;
    if p >= w * h {
        return;
    }
    let stride = params.key_stride;
    let depth = depth_words[p * stride + params.depth_offset];
    if depth != EMPTY {
        filled[2u * p] = index_words[p * stride];
        filled[2u * p + 1u] = depth;
        return;
    }
    let x = p % w;
    let y = p / w;
    var best_depth = EMPTY;
    var best_index = EMPTY;
    var count = 0u;
    for (var ny = max(y, 1u) - 1u; ny <= min(y + 1u, h - 1u); ny++) {
        for (var nx = max(x, 1u) - 1u; nx <= min(x + 1u, w - 1u); nx++) {
            let q = ny * w + nx;
            let d = depth_words[q * stride + params.depth_offset];
            if d == EMPTY {
                continue;
            }
            count += 1u;
            let i = index_words[q * stride];
            if d < best_depth || (d == best_depth && i < best_index) {
                best_depth = d;
                best_index = i;
            }
        }
    }
    if count >= max(params.min_neighbors, 1u) {
        filled[2u * p] = best_index;
        filled[2u * p + 1u] = best_depth;
    } else {
        filled[2u * p] = EMPTY;
        filled[2u * p + 1u] = EMPTY;
    }
}
