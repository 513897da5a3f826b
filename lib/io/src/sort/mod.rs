//! The Morton sort: every point of a dataset, in Morton order (paper 003 §3.1), handed to a sink
//! as ordered chunks of records.
//!
//! In memory when the dataset fits the memory budget: pieces are read (LAZ decoded) in parallel,
//! a key `(morton code, piece, index)` is made per point, the keys are sorted by a parallel
//! radix partition on the top code bits followed by a sort of each bucket, and records are
//! gathered in key order. Otherwise an external sort ([`external`]): points are bucketed
//! by Morton prefix into temporary files, and each bucket is sorted in memory in turn.
//!
//! The Morton grid is defined by the actual integer bounds of the points, and ties are broken by
//! input order, so the output is the same on every path and on every run.

use crate::dataset::Dataset;
use crate::error::Result;

mod external;
mod memory;

pub use memory::*;

/// Sorts every point of `ds` into `sink`: in memory when the dataset fits `opts.memory`
/// ([`in_memory_need`]), else by the external sort.
pub fn sort(ds: &Dataset, opts: &SortOptions, sink: &mut dyn OrderedSink) -> Result<SortReport> {
    let need = in_memory_need(ds.declared_points(), ds.layout.record_len, opts.chunk_points);
    if need > opts.memory {
        return external::sort_external(ds, opts, sink);
    }
    memory::sort_in_memory(ds, opts, sink)
}
