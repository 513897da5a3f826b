// expand, splitting (paper 004 §5.1): a leaf holding more than the capacity that may split
// (at least 128 units wide, above the level limit) gets 8 children, consecutive ids from a
// counter. One thread per node that existed before the dispatch.

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let n = item(wg, lid);
    if n >= params.count || nodes[n].child != 0u {
        return;
    }
    let s = size_log2_of(n);
    let level = nodes[n].size_level >> 8u;
    if atomicLoad(&nodes[n].count) <= params.capacity || s < 7u || level >= params.max_level {
        return;
    }
    let c = atomicAdd(&state[0], 8u);
    if c + 8u > params.node_capacity {
        // The host grows the buffer and runs this pass again; the node stays a leaf.
        atomicMax(&state[2], 1u);
        return;
    }
    let h = 1u << (s - 1u);
    let m = corner(n);
    for (var o = 0u; o < 8u; o++) {
        let k = c + o;
        atomicStore(&nodes[k].count, 0u);
        nodes[k].child = 0u;
        nodes[k].min[0] = m.x + select(0u, h, (o & 1u) != 0u);
        nodes[k].min[1] = m.y + select(0u, h, (o & 2u) != 0u);
        nodes[k].min[2] = m.z + select(0u, h, (o & 4u) != 0u);
        nodes[k].size_level = (s - 1u) | ((level + 1u) << 8u);
        nodes[k].grid = 0u;
        atomicStore(&nodes[k].cursor, 0u);
    }
    nodes[n].child = c;
    atomicMax(&state[1], 1u);
}
