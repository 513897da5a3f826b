//! The vocabulary of `mortar build`: which engine, the options, the progress it reports and
//! the report it ends with. Apart from the dispatcher ([`super::build`]) and the engines, which
//! all import it, so that no engine imports the module that imports the engines.

use mortar_core::octree::BuilderConfig;
use serde::Serialize;

/// Which engine builds the store (`mortar build --engine`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Engine {
    /// The sorted engine when the input fits the memory budget and voxels take the first
    /// point's colour, the partitioned one when it does not, the incremental one for averaged
    /// colours.
    #[default]
    Auto,
    /// Sort, then make the tree in one pass (ARCHITECTURE.md, "The build engine").
    Sorted,
    /// The sorted engine over a partition of the input into cells written to run files: for
    /// inputs larger than the memory budget.
    Partitioned,
    /// Paper 004's batch updates with paged leaves (bounded memory for any input).
    Incremental,
    /// SimLOD's passes on the GPU ([`BuildOptions::tree`]), then the sorted engine's writing:
    /// the same store as [`Engine::Sorted`].
    Gpu,
}

/// Choices of `mortar build`.
#[derive(Clone, Debug)]
pub struct BuildOptions {
    /// The builder's configuration (leaf capacity, colour mode).
    pub config: BuilderConfig,
    /// Points per `add_batch`.
    pub batch_points: usize,
    /// Seconds between commits (the last one is always made).
    pub commit_every: f64,
    /// Seconds after the start at which the first commit is made, when sooner than
    /// `commit_every` (a preview shows the store from its first commit on).
    pub first_commit_after: Option<f64>,
    /// Memory budget in bytes: a commit (after which the builder pages out every leaf's points)
    /// is also made when the points and records held since the last one exceed a third of it.
    pub memory: u64,
    /// The engine.
    pub engine: Engine,
    /// Continue the store the output names, if a build of the same inputs and settings began
    /// it and did not finish (killed, power loss, disk full): from its last commit.
    pub resume: bool,
    /// What builds the tree for [`Engine::Gpu`] (`mortar_render::octree::GpuTreeBuilder` from
    /// the command line; this crate knows no GPU).
    pub tree: Option<std::sync::Arc<dyn mortar_core::octree::arrival::TreeBackend>>,
}

/// Progress of a build, reported after every batch.
#[derive(Clone, Copy, Debug, Default)]
pub struct BuildProgress {
    /// Points added so far.
    pub points: u64,
    /// Points in all (as the headers declare).
    pub total: u64,
    /// Nodes so far.
    pub nodes: usize,
    /// Commits so far.
    pub commits: u64,
}

/// What a build did (`mortar build --json` prints it, with a few figures derived from it).
#[derive(Clone, Debug, Default, Serialize)]
pub struct BuildReport {
    /// Points in the store.
    pub points: u64,
    /// Nodes, leaves.
    pub nodes: u64,
    /// Leaves.
    pub leaves: u64,
    /// Voxels of the inner nodes.
    pub voxels: u64,
    /// Commits.
    pub commits: u64,
    /// Bytes of `nodes.bin`.
    pub nodes_bytes: u64,
    /// Seconds reading (decoding) the input.
    pub read_seconds: f64,
    /// Seconds in `add_batch`, per batch (the JSON report gives their sum, count, mean and
    /// maximum instead).
    #[serde(skip)]
    pub batch_seconds: Vec<f64>,
    /// Seconds committing.
    pub commit_seconds: f64,
    /// Leaves paged back in for splits.
    pub paged_in_leaves: u64,
    /// Most bytes of points and records held between two commits.
    pub peak_interval_bytes: u64,
    /// Seconds in all.
    pub seconds: f64,
    /// Times the octree's root grew for points outside it.
    pub root_growths: u64,
    /// Problems that did not stop the build (headers that lie about the bounds).
    pub warnings: Vec<String>,
    /// The engine that built the store.
    pub engine: BuiltBy,
    /// Seconds sorting the keys (sorted engine; the GPU engine: placing the records and sorting
    /// each leaf).
    pub sort_seconds: f64,
    /// The GPU engine's adapter.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu: Option<String>,
    /// The GPU engine's steps and their seconds (setup, expand, number, voxels, slots), the
    /// rounds of expand and the voxel walks, and the transfers inside those steps: bytes and
    /// seconds uploaded and read back (`upload bytes`, `upload seconds`, `read-back bytes`,
    /// `read-back seconds`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub gpu_steps: Vec<(String, f64)>,
    /// Seconds gathering positions and colours and making the tree (sorted engine).
    pub tree_seconds: f64,
    /// Seconds encoding and appending payloads (sorted engine).
    pub write_seconds: f64,
    /// Of those, seconds encoding.
    pub encode_seconds: f64,
    /// Whether the build continued a store begun before (`--resume`).
    pub resumed: bool,
    /// Nodes the resumed build found committed and kept.
    pub kept_nodes: u64,
    /// Partition cells denser than a unit that were partitioned again on disk (partitioned
    /// engine).
    pub dense_cells: u64,
    /// Leaves larger than a unit, ordered on disk and written in slices (partitioned engine).
    pub large_leaves: u64,
}

/// The engine that built a store, as the report and the build record (`build.json`) name it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BuiltBy {
    /// Nothing was built: `--resume` found the store complete.
    #[default]
    None,
    /// The sorted engine (the input fit `--memory`).
    Sorted,
    /// The partitioned engine (the input is larger than `--memory`).
    Partitioned,
    /// The incremental engine (averaged colours, or `--engine incremental`).
    Incremental,
    /// The GPU engine (`--engine gpu`).
    Gpu,
}

impl BuiltBy {
    /// The name the report and `build.json` use.
    pub fn name(self) -> &'static str {
        match self {
            BuiltBy::None => "none",
            BuiltBy::Sorted => "sorted",
            BuiltBy::Partitioned => "partitioned",
            BuiltBy::Incremental => "incremental",
            BuiltBy::Gpu => "gpu",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_report_names_its_engine_as_build_json_does() {
        for b in [
            BuiltBy::None,
            BuiltBy::Sorted,
            BuiltBy::Partitioned,
            BuiltBy::Incremental,
            BuiltBy::Gpu,
        ] {
            assert_eq!(serde_json::to_value(b).unwrap(), serde_json::json!(b.name()));
        }
        let r = BuildReport { batch_seconds: vec![1.0], ..BuildReport::default() };
        let j = serde_json::to_value(&r).unwrap();
        assert!(j.get("batch_seconds").is_none() && j["engine"] == "none", "{j}");
    }
}
