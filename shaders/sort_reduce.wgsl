// The sum of each block of BLOCK histogram entries.

var<workgroup> part: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let b = group_index(wg);
    var s = 0u;
    if b < params.blocks {
        for (var k = 0u; k < BLOCK / 256u; k++) {
            let i = b * BLOCK + k * 256u + lid.x;
            if i < params.entries {
                s += hist[i];
            }
        }
    }
    part[lid.x] = s;
    workgroupBarrier();
    for (var off = 128u; off > 0u; off >>= 1u) {
        if lid.x < off {
            part[lid.x] += part[lid.x + off];
        }
        workgroupBarrier();
    }
    if lid.x == 0u && b < params.blocks {
        sums[b] = part[0];
    }
}
