// Sparse voxel grids, first step: each point marks the brick of its cell in every inner node on
// its path whose grid is bound (the bricks a grid needs, before any is allocated).

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let t = item(wg, lid);
    if t >= params.count {
        return;
    }
    let p = point_of(params.first + t);
    var n = 0u;
    loop {
        let c = nodes[n].child;
        if c == 0u {
            break;
        }
        if in_group(n) {
            atomicOr(&blocks[brick_entry(n, cell_of(n, p))], 1u);
        }
        n = c + octant(n, p);
    }
}
