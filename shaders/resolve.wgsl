// Pass "resolve" (paper 003 §3.3, visibility buffer): maps each pixel's winning point index to
// the point's colour. One dispatch per chunk of points; a dispatch colours the pixels whose
// index falls in its chunk (and, the first one, the empty pixels with the background).
// With hole filling it reads the filled keys of hole_fill.wgsl (stride 2, depth offset 1);
// eye_dome.wgsl shades its image afterwards.

@group(0) @binding(0) var<uniform> params: ResolveUniforms;
@group(0) @binding(1) var<storage, read> index_words: array<u32>;
@group(0) @binding(2) var<storage, read> depth_words: array<u32>;
@group(0) @binding(3) var<storage, read> colors: array<u32>;
@group(0) @binding(4) var<storage, read_write> image: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let p = workgroup_linear(wg, groups) * 256u + lid;
    if p >= params.width * params.height {
        return;
    }
    let index = index_words[p * params.key_stride];
    let depth = depth_words[p * params.key_stride + params.depth_offset];
    if depth == 0xffffffffu {
        if params.write_background != 0u {
            image[p] = params.background;
        }
        return;
    }
    if index >= params.first_index && index - params.first_index < params.count {
        image[p] = colors[index - params.first_index];
    }
}
