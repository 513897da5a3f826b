//! Test support shared by mortar-render's tests and mortar's end-to-end tests (not a stable API).

use crate::context::{AtomicPath, GpuContext, GpuError, GpuOptions};

/// A context on any adapter (software ones included) with the given atomic path, or `None` with
/// a printed reason where no adapter exists at all (or, for the 64-bit path, where it lacks 64-bit
/// atomics). With `MORTAR_REQUIRE_GPU` set (CI), a missing adapter fails instead.
pub fn context_or_skip(
    atomics: AtomicPath,
    max_workgroups_per_dimension: Option<u32>,
) -> Option<GpuContext> {
    let opts =
        GpuOptions { atomics: Some(atomics), allow_software: true, max_workgroups_per_dimension };
    let required = std::env::var_os("MORTAR_REQUIRE_GPU").is_some();
    match GpuContext::new(&opts) {
        Ok(c) => Some(c),
        Err(GpuError::NoAdapter(why)) if !required => {
            eprintln!("SKIPPED: no GPU adapter at all{why}");
            None
        }
        Err(GpuError::NoInt64Atomics { adapter }) if !required => {
            eprintln!("SKIPPED (64-bit path): {adapter} has no 64-bit atomics");
            None
        }
        Err(e) => panic!("GPU context: {e}"),
    }
}
