// Sparse voxel grids, second step: each marked brick-table entry takes a brick of the pool from a
// counter (state[3]); the host sizes the pool from the count. One thread per entry.

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let e = item(wg, lid);
    if e >= params.count {
        return;
    }
    if atomicLoad(&blocks[e]) == 1u {
        atomicStore(&blocks[e], atomicAdd(&state[3], 1u) + 2u);
    }
}
