// Compaction of the voxel grids, second half: each brick writes the arrivals of its occupied
// cells, in Morton order, from the place the host gave it (the bricks' exclusive prefix sum, in
// the second half of `blocks`): bricks in Morton order, cells in Morton order within a brick, is
// the cells' Morton order in the grid.

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let e = item(wg, lid);
    if e >= params.count {
        return;
    }
    let v = atomicLoad(&blocks[e]);
    if v < 2u {
        return;
    }
    let b = (v - 2u) << BRICK_CELLS_LOG2;
    var k = atomicLoad(&blocks[params.count + e]);
    for (var j = 0u; j < BRICK_CELLS; j++) {
        let c = atomicLoad(&grids[b + j]);
        if c != 0u {
            cells_out[k] = ~c;
            k++;
        }
    }
}
