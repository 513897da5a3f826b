//! `mortar plan`: splits a build into independent jobs (`lib/io/src/store/distributed.rs`).

use anyhow::Result;
use mortar_app::cli as common;
use mortar_core::octree::{BuilderConfig, DEFAULT_LEAF_CAPACITY};
use mortar_io::store::distributed::{plan, PlanOptions};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// LAS/LAZ files, directories or glob patterns (on a filesystem every job can read).
    #[arg(required = true)]
    pub inputs: Vec<String>,
    /// Jobs to split the build into.
    #[arg(long)]
    pub jobs: usize,
    /// The plan to write (JSON).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Most points per leaf (as for `mortar build`).
    #[arg(long, default_value_t = DEFAULT_LEAF_CAPACITY)]
    pub leaf_capacity: u32,
    /// Read every point for each input's true box and count, instead of trusting the headers
    /// (a job refuses a file whose points leave its header's box).
    #[arg(long)]
    pub scan: bool,
    /// Print the plan's summary as JSON on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    if a.leaf_capacity == 0 {
        anyhow::bail!("--leaf-capacity must be at least 1");
    }
    let ds = common::open_dataset(&a.inputs, &common::CrsArgs::default())?;
    common::print_warnings(&ds.warnings);
    let p = plan(
        &ds,
        &PlanOptions {
            jobs: a.jobs,
            config: BuilderConfig { leaf_capacity: a.leaf_capacity, ..BuilderConfig::default() },
            scan: a.scan,
        },
    )?;
    common::print_warnings(&p.warnings);
    p.write(&a.output)?;
    if a.json {
        let j = serde_json::json!({
            "plan": a.output, "id": p.id, "jobs": p.jobs.len(), "points": p.points, "inputs": p.inputs.len(),
            "subtrees": p.jobs.iter().map(|j| j.nodes.len()).sum::<usize>(),
            "estimated_points": p.jobs.iter().map(|j| j.estimated_points).collect::<Vec<_>>(),
            "inputs_per_job": p.jobs.iter().map(|j| j.inputs.len()).collect::<Vec<_>>(),
        });
        println!("{}", serde_json::to_string_pretty(&j)?);
    }
    Ok(())
}
