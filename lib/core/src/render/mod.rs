//! Rendering logic shared by the CPU reference rasterizer and the GPU one (paper 003 §3.2-3.4):
//! camera and per-batch f32 projection ([`camera`]), the one framing rule of every renderer ([`framing`]), frustum culling ([`frustum`]), adaptive
//! precision with the 500 px rule and a bound on the decode error on screen ([`precision`]), the 64-bit depth|index visibility buffer
//! ([`framebuffer`]), the records the GPU rasterizer reads ([`gpu`]), the CPU rasterizer ([`raster`]) and the resolve from point indices to colours
//! with hole filling, eye-dome lighting and attribute colour modes ([`resolve`]); the orbit camera
//! of the viewer ([`orbit`]); the progressive renderer of paper 000 on the CPU rasterizer, with its shuffle and adaptive fill budget ([`progressive`]).
//!
//! No files and no GPU here: the GPU crate uploads the `#[repr(C)]` records defined in these modules.

pub mod camera;
pub mod error;
pub mod framebuffer;
pub mod framing;
pub mod frustum;
pub mod gpu;
pub mod math;
pub mod orbit;
pub mod plan;
pub mod precision;
pub mod progressive;
pub mod raster;
pub mod resolve;
#[doc(hidden)]
pub mod testutil;

pub use camera::{
    BatchProjection, Camera, CameraError, ProjectedPoint, Projection, ViewAxes, ViewPreset,
};
pub use error::RasterError;
pub use framebuffer::{pack_key, unpack_key, Framebuffer, EMPTY_KEY};
pub use frustum::{Containment, Frustum, Plane};
pub use math::{Aabb, DMat4, DVec3};
pub use orbit::Orbit;
pub use plan::{BatchPlan, Planner, RasterOptions};
pub use precision::{choose_precision, precision_for_pixels, PrecisionMode};
pub use raster::{
    count_depth_ties, rasterize, rasterize_gathered, validate_batches, BatchRef, GatheredRef,
    RasterStats, RasterUniforms,
};
