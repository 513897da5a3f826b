// sample voxels (paper 004 §5.2): each point offers itself to its cell in every inner node on
// its path whose grid is bound; the earliest arrival wins (atomicMax of its bitwise NOT), the
// point the CPU engines pick, whatever the order the threads run in (or the points are walked
// in: mode 2 walks a paged build's points in leaf order, each point's arrival number in `leaf`).

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let t = item(wg, lid);
    if t >= params.count {
        return;
    }
    let i = params.first + t;
    let p = point_of(i);
    var arrival = params.base + i;
    if params.mode == 2u {
        arrival = leaf[i];
    }
    let mark = ~arrival;
    var n = 0u;
    loop {
        let c = nodes[n].child;
        if c == 0u {
            break;
        }
        if in_group(n) {
            let m = cell_of(n, p);
            let b = atomicLoad(&blocks[brick_entry(n, m)]) - 2u;
            atomicMax(&grids[(b << BRICK_CELLS_LOG2) | (m & (BRICK_CELLS - 1u))], mark);
        }
        n = c + octant(n, p);
    }
}
