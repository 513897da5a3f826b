//! The partitioned engine of `mortar build`: the sorted engine for inputs larger than
//! `--memory` (ARCHITECTURE.md, "The build engine").
//!
//! 1. Partition: every piece is read once (LAZ decoded once, groups of pieces in parallel) and
//!    its records, each with its arrival number, are scattered by the Morton cell that holds
//!    them at depth `D` of the root (at most 8^5 cells) into run files, one per group of about a
//!    quarter of the budget, each with a table of where every cell begins. The cells' counts
//!    make a histogram of the whole input.
//! 2. Build: the tree's top is walked depth first from the root. A node whose points fit the
//!    budget for one unit (or a cell of depth `D`) is a unit: its cells are read back from
//!    every run (one contiguous range per run), sorted as the sorted engine sorts, and built by
//!    [`build_subtree`]; its nodes are written at once, and it hands its parent the earliest
//!    point per cell of the parent's grid. A node above the units is inner (it holds more
//!    points than a unit, hence more than a leaf), and its voxels are its children's candidates
//!    end to end, reduced by eight for its own parent ([`earliest_in_parent_cells`]).
//! 3. The entries are put in the sorted engine's order (level by level, Morton order in a
//!    level) and committed once.
//!
//! The tree is the one the sorted engine makes (a subtree depends on the points in its cube
//! alone; `tests/build_engine.rs` compares them node by node). A cell of depth `D` holding more
//! points than a unit may is partitioned again, or is a leaf read in slices (`dense.rs`).
//!
//! Resume: the run files, a manifest of the partition (with a checksum of every run) and a log
//! of finished visits (each node's entry and payload checksum, the points it added and its
//! candidates, each record checksummed) live in `.partition/` inside the store until the build
//! ends. Nothing is synced before the final commit: after kill -9 the page cache holds it all;
//! after a power loss whatever did not reach the disk fails its checksum. `--resume` skips pass 1
//! when the manifest and every run check out, keeps the log's records up to the first one whose
//! record or payloads do not, cuts `nodes.bin` after them and walks again, taking logged visits
//! from the log: the store is the uninterrupted one byte for byte. Not done yet:
//! commits while it builds (a reader sees the store at the end only), and units built in
//! parallel with one another (each unit's tree and encoding are parallel inside).
//!
//! The files, one concept each:
//!
//! - [`partition`]: pass 1, the run files and the cells' counts ([`partition_all`],
//!   [`partition_fixed`] for a distributed job);
//! - [`unit`]: a unit's memory per point and its points read back and sorted ([`read_unit`]);
//! - [`walk`]: pass 2, the depth-first walk over the tree's top ([`build_units`] for a job);
//! - [`build`]: one build: pass 1 or what `--resume` keeps, the walk, the commit ([`build_into`]);
//! - [`manifest`]: what pass 1 found, kept for `--resume` in `.partition/`;
//! - [`log`]: the log of finished visits;
//! - [`ranks`]: the leaves' arrival ranks as visits finish, coded into `arrival.bin` at the end;
//! - [`checksum`]: the checksums of runs, tables and payloads.
//!
//! [`build_subtree`]: mortar_core::octree::build_subtree
//! [`earliest_in_parent_cells`]: mortar_core::octree::earliest_in_parent_cells

mod build;
mod checksum;
mod log;
mod manifest;
mod partition;
mod preview;
mod ranks;
#[cfg(test)]
mod testing;
mod unit;
mod walk;

pub(crate) use build::build_into;
pub(crate) use manifest::has_state;
pub(crate) use partition::{cell_depth, partition_all, partition_fixed, Filter};
pub(crate) use preview::drop_provisional;
pub(crate) use unit::{read_unit, unit_bytes_per_point};
pub(crate) use walk::build_units;
