//! `mortar batch`: the batch file of paper 003.

use anyhow::{bail, Result};
use mortar_app::cli as common;
use mortar_io::batchfile::{AttributeSelection, BatchSink, Compression};
use mortar_io::sort::sort;
use std::path::PathBuf;

#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum Compress {
    None,
    Zstd,
}

#[derive(clap::Args)]
pub struct Args {
    /// LAS/LAZ files, directories, glob patterns, or - for stdin.
    #[arg(required = true)]
    pub inputs: Vec<String>,
    /// Output batch file (.mbat).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Attributes to keep besides coordinates and colour: all, none, or a list such as
    /// intensity,classification,gps_time (see `mortar info` for a file's attributes).
    #[arg(long, default_value = "all")]
    pub attributes: String,
    /// Compress each section with zstd (smaller; not memory-mappable without copying).
    #[arg(long, value_enum, default_value = "none")]
    pub compress: Compress,
    #[command(flatten)]
    pub sort: common::SortArgs,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    if a.output.as_os_str() == "-" {
        bail!("batch files are written to a file (they are not streamable); give -o FILE.mbat");
    }
    let mut ds = common::open_dataset(&a.inputs, &a.sort.crs)?;
    common::print_warnings(&ds.warnings);
    let selection = AttributeSelection::parse(&a.attributes);
    let attributes =
        selection.resolve(&ds.layout).map_err(|e| anyhow::anyhow!("--attributes: {e}"))?;
    if let AttributeSelection::Only(_) = selection {
        // The stored colour is RGB, or intensity where RGB is zero: both are read whatever is kept.
        let mut keep: Vec<&str> = attributes.iter().map(|a| a.name.as_str()).collect();
        keep.extend(["rgb", "intensity"]);
        let keep: Vec<String> = keep.into_iter().map(str::to_string).collect();
        ds.decode_only(&keep.iter().map(String::as_str).collect::<Vec<_>>());
    }
    let template = ds.source_meta();
    let compression = match a.compress {
        Compress::None => Compression::None,
        Compress::Zstd => Compression::Zstd,
    };
    let start = std::time::Instant::now();
    let mut sink = BatchSink::new(&a.output, template, attributes, compression);
    let opts = a.sort.options();
    let bar = common::progress_bar("mortar batch", &ds.progress);
    let report = sort(&ds, &opts, &mut sink)?;
    drop(bar);
    mortar_io::cleanup::trace("sorted", start);
    let points = sink.finish()?;
    common::warn_points_by_return(&ds, &report.summary.points_by_return);
    mortar_io::cleanup::trace("finished", start);
    let secs = start.elapsed().as_secs_f64();
    if a.json {
        let j = serde_json::json!({
            "output": a.output,
            "points": points,
            "seconds": secs,
            "points_per_second": points as f64 / secs.max(1e-9),
            "external_sort": report.external,
            "peak_rss_bytes": common::peak_rss_bytes(),
            "threads": rayon::current_num_threads(),
            "buckets": report.buckets,
        });
        println!("{}", serde_json::to_string_pretty(&j)?);
    }
    Ok(())
}
