// The GPU radix sort (mortar_render::radix, issue 29): the points of a build in the order of the
// full-resolution Morton code of their position relative to the root's corner, ties in arrival
// order, which is the sorted engine's order (ARCHITECTURE.md, "Who orders the records"). A stable
// least-significant-digit sort of 4-bit digits in the portable three-kernel form: a digit
// histogram per tile (sort_count), an exclusive scan of the histograms in digit-major order
// (sort_reduce, sort_scan_sums, sort_scan) and a scatter that ranks each element within its tile
// (sort_scatter: each thread takes ITEMS consecutive elements, so the tile's order is kept).
// The CPU twin is mortar_core::octree::arrival::morton_order.
//
// KEEP IN SYNC with its #[repr(C)] twin in mortar_core::render::gpu: SortUniforms (32 bytes).

struct SortUniforms {
    // Elements (points) of the dispatch: all of them, or the bound segment's (sort_init).
    count: u32,
    // The first Morton bit of this pass's digit.
    bit: u32,
    // Tiles of TILE elements.
    tiles: u32,
    // Workgroups in x of a dispatch split over x and y.
    groups_x: u32,
    // sort_init: the arrival number of the segment's first point.
    base: u32,
    // Blocks of BLOCK histogram entries.
    blocks: u32,
    // Histogram entries: 16 a tile.
    entries: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: SortUniforms;
// The elements as the last pass left them: x, y, z (relative to the root's corner) and arrival.
@group(0) @binding(1) var<storage, read> src: array<vec4<u32>>;
// The elements after this pass.
@group(0) @binding(2) var<storage, read_write> dst: array<vec4<u32>>;
// Per digit, per tile (digit-major): the tile's elements of that digit; after the scan, where
// they go.
@group(0) @binding(3) var<storage, read_write> hist: array<u32>;
// Per block of BLOCK histogram entries: their sum; after sort_scan_sums, the sum before it.
@group(0) @binding(4) var<storage, read_write> sums: array<u32>;
// sort_init: a segment's points, 3 words each.
@group(0) @binding(5) var<storage, read> pos: array<u32>;
// sort_extract: the arrival number of each element, in order.
@group(0) @binding(6) var<storage, read_write> order: array<u32>;

// Elements a thread of sort_scatter ranks; a tile is 256 threads of them.
const ITEMS: u32 = 8u;
const TILE: u32 = 2048u;
// Histogram entries a workgroup of the scan sums or scans.
const BLOCK: u32 = 2048u;

// The workgroup's index in a dispatch split over x and y.
fn group_index(wg: vec3<u32>) -> u32 {
    return wg.y * params.groups_x + wg.x;
}

// The element's 4-bit digit from Morton bit params.bit: Morton bit k is bit k / 3 of axis k % 3
// (x the lowest, as mortar_core::morton::encode).
fn digit(e: vec4<u32>) -> u32 {
    var d = 0u;
    for (var j = 0u; j < 4u; j++) {
        let k = params.bit + j;
        let level = k / 3u;
        if level < 32u {
            d |= ((e[k % 3u] >> level) & 1u) << j;
        }
    }
    return d;
}

// The inclusive prefix sum of `v` over the 256 threads of the workgroup (Hillis-Steele, in
// `scan_part`; its last entry is then the workgroup's total). Every thread calls it: it has
// barriers.
var<workgroup> scan_part: array<u32, 256>;

fn workgroup_scan(lane: u32, v: u32) -> u32 {
    scan_part[lane] = v;
    workgroupBarrier();
    for (var off = 1u; off < 256u; off <<= 1u) {
        var t = 0u;
        if lane >= off {
            t = scan_part[lane - off];
        }
        workgroupBarrier();
        scan_part[lane] += t;
        workgroupBarrier();
    }
    return scan_part[lane];
}
