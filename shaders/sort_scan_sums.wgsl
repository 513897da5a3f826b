// One workgroup: the blocks' sums made the sum of the blocks before each (exclusive scan), 256 at
// a time.

var<workgroup> part: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_id) lid: vec3<u32>) {
    var carry = 0u;
    let chunks = (params.blocks + 255u) / 256u;
    for (var c = 0u; c < chunks; c++) {
        let i = c * 256u + lid.x;
        var v = 0u;
        if i < params.blocks {
            v = sums[i];
        }
        part[lid.x] = v;
        workgroupBarrier();
        for (var off = 1u; off < 256u; off <<= 1u) {
            var t = 0u;
            if lid.x >= off {
                t = part[lid.x - off];
            }
            workgroupBarrier();
            part[lid.x] += t;
            workgroupBarrier();
        }
        if i < params.blocks {
            sums[i] = carry + part[lid.x] - v;
        }
        carry += part[255];
        workgroupBarrier();
    }
}
