// Compaction of the voxel grids, first half: the occupied cells of each brick (0 for a brick
// never touched), into the second half of `blocks`. One thread per brick-table entry.

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let e = item(wg, lid);
    if e >= params.count {
        return;
    }
    let v = atomicLoad(&blocks[e]);
    var k = 0u;
    if v >= 2u {
        let b = (v - 2u) << BRICK_CELLS_LOG2;
        for (var j = 0u; j < BRICK_CELLS; j++) {
            if atomicLoad(&grids[b + j]) != 0u {
                k++;
            }
        }
    }
    atomicStore(&blocks[params.count + e], k);
}
