//! mortar-core: the pure logic of mortar.
//!
//! This crate knows no files and no GPU (see `ARCHITECTURE.md`). It holds the definitions that every
//! other part shares: Morton codes over the LAS integer grid ([`morton`]), the byte layout of LAS
//! point records ([`layout`]), merging the integer grids of several inputs ([`grid`]), the batch
//! quantization of paper 003 §3.3 ([`quantize`]), splitting sorted points into batches ([`batching`]),
//! the render colour derived from the source's fields ([`color`]), the incremental octree LOD builder
//! of paper 004 §3-5 with its snapshots ([`octree`]) and the rendering logic of paper 003 §3.2-3.4:
//! camera, culling, adaptive precision, the CPU rasterizer and the resolve ([`render`]); and the
//! statistics every benchmark and accuracy test reports: medians, percentiles, PSNR ([`metrics`]);
//! and the one pointer type the parallel scatters share ([`par`]).

#![deny(unsafe_op_in_unsafe_fn)]

pub mod batch;
pub mod batching;
pub mod color;
pub mod grid;
pub mod layout;
pub mod metrics;
pub mod morton;
pub mod octree;
pub mod par;
pub mod quantize;
pub mod render;

/// Points per full batch: 128 threads x 80 points (paper 003 §3.1).
pub const BATCH_SIZE: usize = 10_240;
