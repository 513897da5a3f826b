// Each block of BLOCK histogram entries made the exclusive prefix sum of all entries: where the
// elements of a digit of a tile go. Each thread scans ITEMS consecutive entries.

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let b = group_index(wg);
    let live = b < params.blocks;
    let start = b * BLOCK + lid.x * ITEMS;
    var before: array<u32, ITEMS>;
    var s = 0u;
    for (var k = 0u; k < ITEMS; k++) {
        let i = start + k;
        before[k] = s;
        if live && i < params.entries {
            s += hist[i];
        }
    }
    let upto = workgroup_scan(lid.x, s);
    if live {
        let base = sums[b] + upto - s;
        for (var k = 0u; k < ITEMS; k++) {
            let i = start + k;
            if i < params.entries {
                hist[i] = base + before[k];
            }
        }
    }
}
