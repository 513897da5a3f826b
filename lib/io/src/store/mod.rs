//! The octree LOD store (paper 004 on disk): `mortar build` writes it, `info`, `sort` and `batch`
//! read it. Layout in `lib/io/STORE_FORMAT.md`.
//!
//! A directory that can be read while it grows:
//!
//! - `source.las`: the LAS header, VLRs and EVLRs of the source (no points), written once, so the
//!   points go back to LAS with every field and record;
//! - `nodes.bin`: node payloads, append-only. A payload is a variable-size batch in the quantized
//!   layout of the batch file (paper 003 §3.5): coarse, medium and fine words relative to the
//!   node's integer bounds, RGBA8 colours, and for leaves the rest of every original record
//!   (all bytes after X, Y, Z), so leaves keep every attribute exactly. A node that changes is
//!   appended again; the hierarchy points at its newest version;
//! - `hierarchy.bin`: one entry per node (key, kind, count, payload offset and length) and the
//!   length of `nodes.bin` it covers, replaced atomically at each commit (payloads written and
//!   synced first, then a new hierarchy written, synced and renamed over the old one). A reader
//!   that opens the directory at any moment sees the last commit; a crash or Ctrl-C leaves it.
//!
//! Memory: the input is read piece by piece, never whole. After each commit the builder pages
//! out the points of every leaf (they are in `nodes.bin` now) and the records of the points added
//! since the last commit are dropped; a leaf that must split later gets its points back from its
//! last payload. So what is held is the inner nodes' voxels, the hierarchy and the points of one
//! commit interval: a commit is also made when those exceed a third of `--memory`.
//!
//! The incremental engine leaves old versions of changed nodes in `nodes.bin`: a leaf that
//! receives points in many commit intervals is rewritten whole each time, so `nodes.bin` grows
//! with input order as much as with input size (measured in BENCHMARKS.md); `mortar build
//! --compact` ([`compact`]) rewrites it with only the live payloads. The sorted and partitioned
//! engines write each node once.

pub mod append;
pub mod arrival;
mod bounds;
mod build;
pub(crate) mod codec;
mod compact;
pub(crate) mod dense;
pub mod distributed;
pub(crate) mod engine;
mod format;
mod gpu;
mod incremental;
pub mod lod;
mod options;
pub(crate) mod partitioned;
pub mod patch;
mod reader;
mod record;
pub(crate) mod runs;
mod writer;

pub(crate) use bounds::header_bounds as header_bounds_of;
pub use build::build;
pub use compact::{compact, CompactReport};
pub use engine::in_memory_need;
pub use format::{
    segment_file, HierarchyHeader, NodeEntry, NodeHeader, PayloadError, HIERARCHY_FILE, INNER,
    LEAF, NODES_FILE, SOURCE_FILE,
};
pub use lod::{LodBatches, PayloadPlace, StoreLod};
pub use options::{BuildOptions, BuildProgress, BuildReport, BuiltBy, Engine};
pub use reader::{is_store, NodeData, Store};
pub use record::{BuildRecord, InputPrint, RECORD_FILE};
pub use writer::{CommitStats, StoreWriter, COMMIT_GROUP_BYTES, PAGED};
