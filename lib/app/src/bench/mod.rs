//! The render benchmarks' procedures; each `mortar-bench-*` binary parses its [`Args`](render::Args)
//! and calls `run`.

pub mod gpu;
pub mod lod;
pub mod progressive_bench;
pub mod render;
