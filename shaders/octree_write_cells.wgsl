// Compaction of the voxel grids, second half: each block writes the arrivals of its occupied
// cells, in Morton order, from the place the host gave it (the blocks' exclusive prefix sum).

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let b = item(wg, lid);
    if b >= params.count {
        return;
    }
    var k = blocks[b];
    for (var j = 0u; j < BLOCK; j++) {
        let v = atomicLoad(&grids[b * BLOCK + j]);
        if v != 0u {
            cells_out[k] = ~v;
            k++;
        }
    }
}
