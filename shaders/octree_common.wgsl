// The GPU octree builder (mortar_render::octree, issue 29): SimLOD's expand, voxel and slot
// passes over points in arrival order. The CPU twin is mortar_core::octree::arrival (the
// reference the GPU is tested against; keep in sync).
//
// KEEP IN SYNC with their #[repr(C)] twins in mortar_core::render::gpu:
//   OctreeUniforms (48 bytes)
//   OctreeNode     (32 bytes; `Node` here, with atomics)

struct OctreeUniforms {
    first: u32,
    count: u32,
    capacity: u32,
    max_level: u32,
    node_capacity: u32,
    grid_first: u32,
    grid_count: u32,
    groups_x: u32,
    mode: u32,
    base: u32,
    _pad: vec2<u32>,
}

struct Node {
    count: atomic<u32>,
    child: u32,
    min: array<u32, 3>,
    // size_log2 | level << 8
    size_level: u32,
    grid: u32,
    cursor: atomic<u32>,
}

@group(0) @binding(0) var<uniform> params: OctreeUniforms;
@group(0) @binding(1) var<storage, read_write> nodes: array<Node>;
// [0] nodes allocated, [1] a leaf split, [2] the node buffer overflowed.
@group(0) @binding(2) var<storage, read_write> state: array<atomic<u32>>;
// The bound segment's points: 3 words each, relative to the root's corner.
@group(0) @binding(3) var<storage, read> pos: array<u32>;
// Per point of the segment: its leaf; after the slot pass, its slot.
@group(0) @binding(4) var<storage, read_write> leaf: array<u32>;
// The voxel grids are sparse: a grid of 128^3 cells is 16^3 bricks of 8^3 cells, each brick
// allocated on first touch from this pool (512 cells, in Morton order); a cell holds the bitwise
// NOT of the earliest arrival (0: empty), so that atomicMax keeps the earliest.
@group(0) @binding(5) var<storage, read_write> grids: array<atomic<u32>>;
// Two halves of `params.count` words (the bound group's grids times 4096 bricks, in Morton order
// of the bricks): the brick table (0: none, 1: touched, b + 2: pool brick b), then per brick its
// occupied cells and, from the host, where its voxels go.
@group(0) @binding(6) var<storage, read_write> blocks: array<atomic<u32>>;
// The voxels of the bound grids, grid by grid, cells in Morton order.
@group(0) @binding(7) var<storage, read_write> cells_out: array<u32>;

const BRICKS_LOG2: u32 = 12u;
const BRICK_CELLS_LOG2: u32 = 9u;
const BRICK_CELLS: u32 = 512u;

// The dispatch's item of this thread (workgroups of 256, split over x and y).
fn item(wg: vec3<u32>, lid: vec3<u32>) -> u32 {
    return (wg.y * params.groups_x + wg.x) * 256u + lid.x;
}

fn point_of(i: u32) -> vec3<u32> {
    return vec3<u32>(pos[3u * i], pos[3u * i + 1u], pos[3u * i + 2u]);
}

fn size_log2_of(n: u32) -> u32 {
    return nodes[n].size_level & 0xffu;
}

fn corner(n: u32) -> vec3<u32> {
    return vec3<u32>(nodes[n].min[0], nodes[n].min[1], nodes[n].min[2]);
}

// The octant of p in node n (x | y << 1 | z << 2).
fn octant(n: u32, p: vec3<u32>) -> u32 {
    let d = (p - corner(n)) >> vec3<u32>(size_log2_of(n) - 1u);
    return (d.x & 1u) | ((d.y & 1u) << 1u) | ((d.z & 1u) << 2u);
}

// From node n down to the leaf holding p.
fn descend(n0: u32, p: vec3<u32>) -> u32 {
    var n = n0;
    loop {
        let c = nodes[n].child;
        if c == 0u {
            break;
        }
        n = c + octant(n, p);
    }
    return n;
}

fn spread7(v: u32) -> u32 {
    var x = v & 0x7fu;
    x = (x | (x << 8u)) & 0x0300f00fu;
    x = (x | (x << 4u)) & 0x030c30c3u;
    x = (x | (x << 2u)) & 0x09249249u;
    return x;
}

// The Morton index of p's cell in the 128^3 grid of inner node n.
fn cell_of(n: u32, p: vec3<u32>) -> u32 {
    let c = (p - corner(n)) >> vec3<u32>(size_log2_of(n) - 7u);
    return spread7(c.x) | (spread7(c.y) << 1u) | (spread7(c.z) << 2u);
}

// The brick-table entry of p's cell in inner node n, if n's grid is in the bound group.
fn brick_entry(n: u32, m: u32) -> u32 {
    return ((nodes[n].grid - params.grid_first) << BRICKS_LOG2) | (m >> BRICK_CELLS_LOG2);
}

fn in_group(n: u32) -> bool {
    let g = nodes[n].grid;
    return g >= params.grid_first && g - params.grid_first < params.grid_count;
}
