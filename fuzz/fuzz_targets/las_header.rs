#![no_main]
//! Fuzz target `las_header`: see `mortar_fuzz::las_header` and FUZZING.md.

#[global_allocator]
static ALLOC: mortar_fuzz::LimitAlloc = mortar_fuzz::LimitAlloc;

libfuzzer_sys::fuzz_target!(init: mortar_fuzz::init(), |data: &[u8]| mortar_fuzz::las_header(data));
