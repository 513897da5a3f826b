// The sorted elements' arrival numbers: the points' order.

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = group_index(wg) * 256u + lid.x;
    if i >= params.count {
        return;
    }
    order[i] = src[i].w;
}
