//! `mortar merge`: joins the parts of a planned build into one store
//! (`lib/io/src/store/distributed.rs`).

use anyhow::Result;
use mortar_io::store::distributed::merge;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// The parts (`mortar build --plan P --job I -o part_I`), every job of one plan once.
    #[arg(required = true)]
    pub parts: Vec<PathBuf>,
    /// The store directory to create (must not exist, or be empty).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let r = merge(&a.parts, &a.output)?;
    if a.json {
        let mut j = serde_json::to_value(&r)?;
        j["output"] = serde_json::json!(a.output);
        println!("{}", serde_json::to_string_pretty(&j)?);
    }
    Ok(())
}
