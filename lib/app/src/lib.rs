//! mortar's application layer, between the libraries (mortar-core, mortar-io, mortar-render) and
//! the thin binaries in `bins/`.
//!
//! - [`viewer`]: the viewer as a library. [`viewer::Content`] is what a window shows (bounds,
//!   colour modes, polling for new data, drawing on the CPU or GPU backend), with one
//!   implementation per kind of input: a batch file, an octree store, raw LAS/LAZ drawn
//!   progressively. The window, the build preview's threads and the frame statistics sit beside it.
//! - [`render`]: one view to PNG (`mortar render`) of a batch file, a store (LOD) or raw LAS/LAZ
//!   (progressive), on the CPU or GPU rasterizer.
//! - [`frames`]: PNG frames of a growing store (`mortar build --frames`).
//! - [`build`]: `mortar build` (options and the whole command: builds, `--append`, `--compact`,
//!   plan jobs, with `--preview` and `--frames`).
//! - [`gpu_build`]: the GPU octree builder for `mortar build --engine gpu`.
//! - [`bench`]: the render benchmarks' procedures (`mortar-bench-*`).
//! - [`cli`]: what every command shares: warnings, progress bars, sizes, the sort and CRS option
//!   sets.
//!
//! The option sets here derive `clap::Args`: `mortar render`, `mortar view`, `build --preview`
//! and `build --frames` and the benchmark binaries share them, so each is defined once (as
//! rerun's `RerunArgs` is defined in its library); the binaries parse them and make one call.

#![forbid(unsafe_code)]

pub mod bench;
pub mod build;
pub mod cli;
pub mod draw;
pub mod frames;
pub mod gpu_build;
pub mod render;
pub mod viewer;
