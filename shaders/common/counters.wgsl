// The count of drawn points (points inside the viewport and depth range that were depth-tested),
// as a 64-bit number in two words; the twin of RasterStats::points_drawn.

@group(0) @binding(2) var<storage, read_write> counters: array<atomic<u32>, 2>;

var<workgroup> drawn_in_group: atomic<u32>;

// Sums every thread's count in the workgroup, then adds it once to the global count (low word,
// carry into the high word). Call from uniform control flow.
fn count_drawn(drawn: u32, lid: u32) {
    // Workgroup memory is not zeroed for us (the pipelines switch that off).
    if lid == 0u {
        atomicStore(&drawn_in_group, 0u);
    }
    workgroupBarrier();
    atomicAdd(&drawn_in_group, drawn);
    workgroupBarrier();
    if lid == 0u {
        let n = atomicLoad(&drawn_in_group);
        let before = atomicAdd(&counters[0], n);
        if before + n < before {
            atomicAdd(&counters[1], 1u);
        }
    }
}
