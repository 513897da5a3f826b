#![no_main]
//! Fuzz target `vlr_records`: see `mortar_fuzz::vlr_records` and FUZZING.md.

#[global_allocator]
static ALLOC: mortar_fuzz::LimitAlloc = mortar_fuzz::LimitAlloc;

libfuzzer_sys::fuzz_target!(init: mortar_fuzz::init(), |data: &[u8]| mortar_fuzz::vlr_records(data));
