// expand, counting (paper 004 §5.1): each point of the dispatch descends to its leaf, which
// counts it. Mode 0: a new batch, from the root; mode 1: points whose leaf split, from it.

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let t = item(wg, lid);
    if t >= params.count {
        return;
    }
    let i = params.first + t;
    var n = 0u;
    if params.mode == 1u {
        n = leaf[i];
        if nodes[n].child == 0u {
            return;
        }
    }
    n = descend(n, point_of(i));
    leaf[i] = n;
    atomicAdd(&nodes[n].count, 1u);
}
