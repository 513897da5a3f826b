//! mortar-io: everything that touches files. LAS/LAZ sources and sinks, the Morton sort (in
//! memory or external), the batch file format and its memory-mapped reader.

pub mod cleanup;
pub mod error;
pub mod las;
pub mod source;

pub use error::{Error, Result};
pub mod dataset;
pub mod external;
pub mod sort;
pub mod sink_las;
pub mod batchfile;
pub mod crs;
pub mod info;
pub mod synth;
pub mod render_input;
pub mod progressive;
pub mod progress;
pub mod store;
pub mod export;
pub mod store_lod;
