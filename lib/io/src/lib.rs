//! mortar-io: everything that touches files. LAS/LAZ sources and sinks, the Morton sort (in
//! memory or external), the batch file format and its memory-mapped reader.
//!
//! The main entry points, on the shipped sample (110,000 points of LAZ): open inputs through the
//! front door ([`inputs`]: what kind each path is, directories and globs) as one
//! [`Dataset`](dataset::Dataset), write them Morton-sorted as LAZ ([`sort::sort`] into a
//! [`LasSink`](sink_las::LasSink)) or as a batch file ([`BatchSink`](batchfile::BatchSink), read
//! back with [`BatchFile`](batchfile::BatchFile)), build the octree store
//! ([`store::build`], read back with [`Store`](store::Store)) and export it as COPC
//! ([`export::export`]).
//!
//! ```
//! use mortar_io::batchfile::{AttributeSelection, BatchFile, BatchSink, Compression};
//! use mortar_io::inputs;
//! use mortar_io::export::{export, ExportFormat, ExportOptions, PointOrder};
//! use mortar_io::sink_las::{LasSink, Target};
//! use mortar_io::sort::{sort, SortOptions};
//! use mortar_io::store::{build, BuildOptions, Engine, Store};
//! # let out = std::env::temp_dir().join(format!("mortar-io-doctest-{}", std::process::id()));
//! # std::fs::create_dir_all(&out)?;
//! let ds = inputs::open(&["../../data-samples/autzen_trim.laz".into()])?;
//! assert_eq!(ds.declared_points(), 110_000);
//! let opts = SortOptions::with_memory(1 << 30, out.clone());
//!
//! let mut laz = LasSink::new(Target::File(out.join("sorted.laz")), true, ds.source_meta(), &out)?;
//! sort(&ds, &opts, &mut laz)?;
//! assert_eq!(laz.finish()?, 110_000);
//!
//! let attributes = AttributeSelection::All.resolve(&ds.layout)?;
//! let mut batches = BatchSink::new(&out.join("sample.mbat"), ds.source_meta(), attributes, Compression::None);
//! sort(&ds, &opts, &mut batches)?;
//! batches.finish()?;
//! let file = BatchFile::open(&out.join("sample.mbat"))?;
//! assert_eq!(file.header.point_count, 110_000);
//!
//! let store = BuildOptions { config: Default::default(), batch_points: 100_000, commit_every: 0.0, first_commit_after: None, memory: 1 << 30, engine: Engine::Auto, resume: false, tree: None };
//! let report = build(&ds, &out.join("store"), &store, &mut |_| {})?;
//! assert_eq!(report.points, 110_000);
//! assert_eq!(Store::open(&out.join("store"))?.header.points, 110_000);
//!
//! let copc = ExportOptions { format: ExportFormat::Copc, memory: 1 << 30, config: Default::default(), order: PointOrder::Morton };
//! export(&ds, &out.join("sample.copc.laz"), &copc)?;
//! assert!(out.join("sample.copc.laz").is_file());
//! # std::fs::remove_dir_all(&out)?;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![deny(unsafe_op_in_unsafe_fn)]

pub mod cleanup;
pub mod error;
pub mod las;
pub mod source;

pub use error::{Error, Result};
pub mod additive;
pub mod batch_input;
pub mod batchfile;
pub mod copc;
pub mod crs;
pub mod dataset;
pub mod ept;
pub mod export;
pub mod framing;
pub mod globe;
pub mod info;
pub mod inputs;
pub mod lod_source;
pub mod progress;
pub mod remote;
pub mod sink_las;
pub mod sort;
pub mod store;
pub mod synth;
pub mod threads;
pub mod wkt;
