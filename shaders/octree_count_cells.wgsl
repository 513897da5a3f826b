// Compaction of the voxel grids, first half: the occupied cells of each block of 256.

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let b = item(wg, lid);
    if b >= params.count {
        return;
    }
    var k = 0u;
    for (var j = 0u; j < BLOCK; j++) {
        if atomicLoad(&grids[b * BLOCK + j]) != 0u {
            k++;
        }
    }
    blocks[b] = k;
}
