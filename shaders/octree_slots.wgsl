// Slots: each point takes the next slot of its leaf's range (the host set each leaf's cursor to
// the start of its range, leaves depth first); the order within a leaf is the host's sort.

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let t = item(wg, lid);
    if t >= params.count {
        return;
    }
    let i = params.first + t;
    leaf[i] = atomicAdd(&nodes[leaf[i]].cursor, 1u);
}
