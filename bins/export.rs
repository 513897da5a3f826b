//! `mortar export`: the octree as COPC 1.0, Potree 2.0 or 3D Tiles 1.1 for other tools
//! (`lib/io/src/export`).

use anyhow::Result;
use mortar_app::cli as common;
use mortar_core::octree::{BuilderConfig, DEFAULT_LEAF_CAPACITY};
use mortar_io::export::{export, ExportFormat, ExportOptions, PointOrder};
use std::path::{Path, PathBuf};

#[derive(clap::Args)]
pub struct Args {
    /// LAS/LAZ files, batch files, stores, directories, glob patterns, or - for stdin.
    #[arg(required = true)]
    pub inputs: Vec<String>,
    /// The output: a COPC file (`.copc.laz`), or a Potree 2.0 or 3D Tiles directory (must not
    /// exist, or be empty).
    #[arg(short, long)]
    pub output: PathBuf,
    /// copc, potree, 3dtiles, or auto: copc for an output ending in .laz, else potree.
    #[arg(long, default_value = "auto")]
    pub format: String,
    /// Memory budget, e.g. 8G (default: half the machine's memory, at most 16G, at least 256M,
    /// as for `sort`). A larger input is exported through run files on disk (beside the output),
    /// one subtree at a time.
    #[arg(long, value_parser = common::parse_size)]
    pub memory: Option<u64>,
    /// Most points per leaf (default: 200,000 for COPC, where larger LAZ chunks compress
    /// better, 20 % smaller than at 50,000 (BENCHMARKS.md); 50,000 for Potree and 3D Tiles,
    /// whose viewers load nodes one request each).
    #[arg(long)]
    pub leaf_capacity: Option<u32>,
    /// Order of the points inside a node: gps-time (the default; Morton order where the records
    /// have no GPS time) or morton. By GPS time LAZ compresses the scanner's fields far better:
    /// COPC files 1.5x smaller than in Morton order (BENCHMARKS.md).
    #[arg(long, default_value = "gps-time")]
    pub order: String,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub crs: common::CrsArgs,
}

/// Leaf capacity of COPC exports.
const COPC_LEAF_CAPACITY: u32 = 200_000;

fn format_of(a: &Args) -> Result<ExportFormat> {
    Ok(match a.format.as_str() {
        "copc" => ExportFormat::Copc,
        "potree" => ExportFormat::Potree,
        "3dtiles" | "3d-tiles" => ExportFormat::Tiles3d,
        "auto" if a.output.to_string_lossy().to_ascii_lowercase().ends_with(".laz") => {
            ExportFormat::Copc
        }
        "auto" => ExportFormat::Potree,
        f => anyhow::bail!("--format {f}: give copc, potree, 3dtiles or auto"),
    })
}

/// Refuses an output that cannot be written, before any point is read.
fn check_output(out: &Path, format: ExportFormat) -> Result<()> {
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if !parent.is_dir() {
        anyhow::bail!("{}: its directory {} does not exist", out.display(), parent.display());
    }
    match format {
        ExportFormat::Copc if out.is_dir() => {
            anyhow::bail!("{}: is a directory; a COPC output is a file", out.display())
        }
        ExportFormat::Potree | ExportFormat::Tiles3d if out.exists() && !out.is_dir() => {
            anyhow::bail!("{}: exists and is not a directory", out.display())
        }
        ExportFormat::Potree | ExportFormat::Tiles3d
            if out.is_dir() && std::fs::read_dir(out)?.next().is_some() =>
        {
            anyhow::bail!("{}: the directory is not empty; give a new or empty one", out.display())
        }
        _ => Ok(()),
    }
}

pub fn run(a: Args) -> Result<()> {
    let format = format_of(&a)?;
    let leaf_capacity = a.leaf_capacity.unwrap_or(match format {
        ExportFormat::Copc => COPC_LEAF_CAPACITY,
        ExportFormat::Potree | ExportFormat::Tiles3d => DEFAULT_LEAF_CAPACITY,
    });
    if leaf_capacity == 0 {
        anyhow::bail!("--leaf-capacity must be at least 1");
    }
    let order = match a.order.as_str() {
        "morton" => PointOrder::Morton,
        "gps-time" => PointOrder::GpsTime,
        o => anyhow::bail!("--order {o}: give morton or gps-time"),
    };
    check_output(&a.output, format)?;
    let ds = common::open_dataset(&a.inputs, &a.crs)?;
    common::print_warnings(&ds.warnings);
    let opts = ExportOptions {
        format,
        memory: a.memory.unwrap_or_else(mortar_io::sort::default_memory),
        config: BuilderConfig { leaf_capacity, ..BuilderConfig::default() },
        order,
    };
    let bar = common::progress_bar("mortar export", &ds.progress);
    let r = export(&ds, &a.output, &opts)?;
    drop(bar);
    common::print_warnings(&r.warnings);
    if a.json {
        let mut j = serde_json::to_value(&r)?;
        j["peak_rss_bytes"] = serde_json::json!(common::peak_rss_bytes());
        j["threads"] = serde_json::json!(rayon::current_num_threads());
        j["points_per_second"] = serde_json::json!(r.points as f64 / r.seconds.max(1e-9));
        println!("{}", serde_json::to_string_pretty(&j)?);
    }
    Ok(())
}
