#![no_main]
//! Fuzz target `batch_file`: see `mortar_fuzz::batch_file` and FUZZING.md.

#[global_allocator]
static ALLOC: mortar_fuzz::LimitAlloc = mortar_fuzz::LimitAlloc;

libfuzzer_sys::fuzz_target!(init: mortar_fuzz::init(), |data: &[u8]| mortar_fuzz::batch_file(data));
