// Each tile's count of every digit, into the histogram (digit-major: entry digit * tiles + tile).

var<workgroup> counts: array<atomic<u32>, 16>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let tile = group_index(wg);
    if lid.x < 16u {
        atomicStore(&counts[lid.x], 0u);
    }
    workgroupBarrier();
    if tile < params.tiles {
        for (var k = 0u; k < ITEMS; k++) {
            let i = tile * TILE + k * 256u + lid.x;
            if i < params.count {
                atomicAdd(&counts[digit(src[i])], 1u);
            }
        }
    }
    workgroupBarrier();
    if tile < params.tiles && lid.x < 16u {
        hist[lid.x * params.tiles + tile] = atomicLoad(&counts[lid.x]);
    }
}
