//! Builds beyond one machine (ARCHITECTURE.md, "The distributed build"): `mortar plan` splits
//! the tree into subtrees and the subtrees into jobs, `mortar build --plan --job` builds one
//! job's subtrees into a part, and `mortar merge` joins the parts into the store that one
//! machine builds from the same inputs (same nodes, same payloads, same entry order).
//!
//! The unit of work is the partitioned engine's (`partitioned.rs`): a subtree under a node of
//! the tree's top is built from the points of its cube alone, and hands its parent the earliest
//! point of each cell of the parent's grid (its candidates). A plan is a cut of the tree: nodes
//! (at most at the partition cells' depth) that tile the root's cube; every node above the cut
//! is an inner node of the one-machine tree when it has more points than a leaf may. The plan
//! splits only nodes its estimate puts well above that (four leaves' worth); where the true
//! count is smaller (the estimate is a guess), the merge makes the node the leaf one machine
//! makes: the leaves of the subtrees below it concatenated in octant (= Morton) order, their
//! entries dropped.
//!
//! - Plan: the root is the one the one-machine build takes (the headers' box; with `--scan`
//!   the points' own box where the headers lie), each input's box comes from its header (or
//!   from its points with `--scan`), and the points of the inputs are spread over their boxes
//!   to estimate the nodes' counts. The cut splits the largest node until nodes are small
//!   enough for the jobs to be balanced; jobs take runs of nodes in Morton order of about the
//!   same estimated count, and each job the inputs whose box meets one of its nodes.
//! - Job: opens every input (so that pieces have the numbers, and points the arrival numbers,
//!   of a one-machine build), reads only its inputs' pieces and keeps the points of its nodes
//!   (partition pass of the partitioned engine with a filter), checks that each input's points
//!   lie in the box the plan took for it (else a file the job skipped could hold some of its
//!   points: refused, plan again with `--scan`), and builds its subtrees within `--memory`.
//!   The part (its nodes' payloads, entries and candidates, `part.json`) is written under a
//!   temporary name and renamed over any earlier attempt: a job that failed or ran twice is
//!   simply run again.
//! - Merge: checks that the parts are every job of one plan exactly once, then copies the
//!   payloads, makes the nodes above the cut from the candidates (as the partitioned engine
//!   makes its nodes above the units), recolours payloads of parts whose colour scale differs
//!   from the whole input's (intensity grey scaled to the largest intensity of all points, or
//!   8- against 16-bit RGB), commits the entries in the one-machine order, and lists the
//!   parts' arrival ranks (each part's `arrival.bin`) as one machine lists them, so that the
//!   store is extended in place by `--append` without its inputs.
//!
//! Not done: skipping LAZ chunks (a job reads every chunk of the files it needs; their chunk
//! tables hold no bounds) and `--scan` counting the cells exactly (it takes each input's own
//! box and spreads its points over it).
//!
//! The files, one concept each:
//!
//! - [`plan`](mod@plan): the plan, its cut and jobs ([`Plan`], [`plan()`]);
//! - [`cut`]: the geometry of the cut (nodes' cubes, partition cells, Morton order);
//! - [`job`]: one job built into a part ([`build_job`]);
//! - [`part`]: a part's files, written by a job and read back by the merge;
//! - [`merge`](mod@merge): the parts joined into the store ([`merge()`]).

mod cut;
mod job;
mod merge;
mod part;
mod plan;
#[cfg(test)]
mod testing;

pub use job::{build_job, JobReport};
pub use merge::{merge, MergeReport};
pub use part::PART_FILE;
pub use plan::{plan, Plan, PlanInput, PlanJob, PlanOptions, PLAN_FORMAT};
