#![no_main]
//! Fuzz target `laz_pointwise`: see `mortar_fuzz::laz_pointwise` and FUZZING.md.

#[global_allocator]
static ALLOC: mortar_fuzz::LimitAlloc = mortar_fuzz::LimitAlloc;

libfuzzer_sys::fuzz_target!(init: mortar_fuzz::init(), |data: &[u8]| mortar_fuzz::laz_pointwise(data));
