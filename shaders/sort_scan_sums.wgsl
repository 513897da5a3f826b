// One workgroup: the blocks' sums made the sum of the blocks before each (exclusive scan), 256 at
// a time.

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
        let upto = workgroup_scan(lid.x, v);
        if i < params.blocks {
            sums[i] = carry + upto - v;
        }
        carry += scan_part[255];
        workgroupBarrier();
    }
}
