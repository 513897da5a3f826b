//! `mortar sort`: Morton-ordered LAS/LAZ.

use anyhow::Result;
use mortar_app::cli as common;
use mortar_io::sink_las::{LasSink, Target};
use mortar_io::sort::sort;

#[derive(clap::Args)]
pub struct Args {
    /// LAS/LAZ files, directories, glob patterns, batch files, or - for stdin.
    #[arg(required = true)]
    pub inputs: Vec<String>,
    /// Output .las or .laz file, or - for stdout (LAS unless --laz).
    #[arg(short, long)]
    pub output: String,
    /// Write LAZ (the default for a .laz output file).
    #[arg(long)]
    pub laz: bool,
    #[command(flatten)]
    pub sort: common::SortArgs,
}

pub fn run(a: Args) -> Result<()> {
    let ds = common::open_dataset(&a.inputs, &a.sort.crs)?;
    common::print_warnings(&ds.warnings);
    let target = Target::parse(&a.output);
    let compressed = a.laz || a.output.to_ascii_lowercase().ends_with(".laz");
    let tmp = a.sort.tmp_dir();
    let template = ds.source_meta();
    let mut sink = LasSink::new(target, compressed, template, &tmp)?;
    let opts = a.sort.options();
    let bar = common::progress_bar("mortar sort", &ds.progress);
    let report = sort(&ds, &opts, &mut sink)?;
    drop(bar);
    sink.finish()?;
    common::warn_points_by_return(&ds, &report.summary.points_by_return);
    Ok(())
}
