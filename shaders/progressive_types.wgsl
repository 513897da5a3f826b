// Shared by the passes of the GPU progressive renderer (paper 000 §3.3-3.4;
// lib/render/src/progressive.rs), after common/types.wgsl.
//
// KEEP IN SYNC with their Rust twins (mortar-render's shader test compares the offsets, sizes and
// values naga computes here with the Rust ones):
//   UNLOADED           mortar_core::render::progressive::UNLOADED
//   SLOTS_PER_THREAD   mortar_render::progressive::SLOTS_PER_THREAD
//   ScatterUniforms    mortar_core::render::gpu::ScatterUniforms  (32 bytes)
//   PrepareUniforms    mortar_core::render::gpu::PrepareUniforms  (16 bytes)
//   ReframeUniforms    mortar_core::render::gpu::ReframeUniforms  (64 bytes)

// The coarse word of a slot whose point has not arrived (bit 31: no real coarse word has it).
const UNLOADED: u32 = 0x80000000u;

// Slots (Fill) or visible-list entries (Reproject) per thread; a workgroup of 128 threads covers
// 128 * SLOTS_PER_THREAD of them, thread `lid` taking every 128th from the group's first.
const SLOTS_PER_THREAD: u32 = 8u;

// The constants of one scatter dispatch: staged points first..first + count of the input, in
// input order; the dispatch writes those whose shuffled slot falls in its chunk.
struct ScatterUniforms {
    // 1 when the staged records carry an RGBA8 colour (4 words per point), 0 when not (3 words).
    colors: u32,
    // 1: the records are one colour each and only the colours are written (a colour switch
    // streamed in, paper 000 §3.5).
    colors_only: u32,
    // The shuffle's prime P (eq. 1; 0 below 3 points: nothing moves).
    prime: u32,
    // Input index of the first staged record.
    first: u32,
    // The chunk's first slot and its number of slots.
    chunk_first: u32,
    chunk_len: u32,
    // Staged records.
    count: u32,
    _pad: u32,
}

// The constants of the Prepare pass.
struct PrepareUniforms {
    // Pixels of the framebuffer.
    pixels: u32,
    // Slots per chunk of the shuffled buffer: a slot's visible list is slot / chunk_slots.
    chunk_slots: u32,
    // Entries between the starts of two chunks' visible lists.
    list_stride: u32,
    // Number of chunks.
    chunks: u32,
}

// The constants of the reframe pass: one chunk's loaded slots from frame `from` to frame `to`.
struct ReframeUniforms {
    from_min: vec3<i32>,
    // Slots of the chunk.
    count: u32,
    to_min: vec3<i32>,
    _pad0: u32,
    // 30 - bits per axis of the old and the new frame.
    from_shift: vec3<u32>,
    _pad1: u32,
    to_shift: vec3<u32>,
    _pad2: u32,
}
