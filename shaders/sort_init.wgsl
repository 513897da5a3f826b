// The elements of one segment of points: position and arrival number, at their arrival.

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = group_index(wg) * 256u + lid.x;
    if i >= params.count {
        return;
    }
    dst[params.base + i] = vec4<u32>(pos[3u * i], pos[3u * i + 1u], pos[3u * i + 2u], params.base + i);
}
