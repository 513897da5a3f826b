// Every element to its place: its tile's start for its digit (the scanned histogram), plus the
// elements of that digit before it in the tile. Thread t takes the tile's elements t * ITEMS ..
// (t + 1) * ITEMS, so "before" is: in earlier threads (a scan of per-thread counts), then earlier
// in the thread. The 16 counts of a thread are packed two to a word (16 bits each: a tile holds
// 2048 elements).

var<workgroup> part: array<array<u32, 8>, 256>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let tile = group_index(wg);
    let live = tile < params.tiles;
    let start = tile * TILE + lid.x * ITEMS;
    var e: array<vec4<u32>, ITEMS>;
    var d: array<u32, ITEMS>;
    var c: array<u32, 8>;
    for (var w = 0u; w < 8u; w++) {
        c[w] = 0u;
    }
    for (var k = 0u; k < ITEMS; k++) {
        let i = start + k;
        d[k] = 16u;
        if live && i < params.count {
            e[k] = src[i];
            let q = digit(e[k]);
            d[k] = q;
            c[q >> 1u] += 1u << (16u * (q & 1u));
        }
    }
    part[lid.x] = c;
    workgroupBarrier();
    for (var off = 1u; off < 256u; off <<= 1u) {
        var t: array<u32, 8>;
        if lid.x >= off {
            t = part[lid.x - off];
        }
        workgroupBarrier();
        for (var w = 0u; w < 8u; w++) {
            part[lid.x][w] += t[w];
        }
        workgroupBarrier();
    }
    var run: array<u32, 8>;
    for (var w = 0u; w < 8u; w++) {
        run[w] = part[lid.x][w] - c[w];
    }
    for (var k = 0u; k < ITEMS; k++) {
        let q = d[k];
        if q < 16u {
            let w = q >> 1u;
            let sh = 16u * (q & 1u);
            let rank = (run[w] >> sh) & 0xffffu;
            run[w] += 1u << sh;
            dst[hist[q * params.tiles + tile] + rank] = e[k];
        }
    }
}
