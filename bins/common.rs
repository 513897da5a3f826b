//! Helpers shared by the subcommands: warnings, sizes, inputs.

use std::sync::atomic::{AtomicBool, Ordering};

static QUIET: AtomicBool = AtomicBool::new(false);

pub fn set_quiet(q: bool) {
    QUIET.store(q, Ordering::Relaxed);
}

pub fn warn(msg: &str) {
    if !QUIET.load(Ordering::Relaxed) {
        eprintln!("mortar: warning: {msg}");
    }
}

/// Whether an error is a closed stdout pipe (which ends mortar quietly with status 0).
pub fn is_broken_pipe(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        if let Some(io) = c.downcast_ref::<std::io::Error>() {
            return io.kind() == std::io::ErrorKind::BrokenPipe;
        }
        if let Some(mortar_io::Error::Io { source, .. }) = c.downcast_ref::<mortar_io::Error>() {
            return source.kind() == std::io::ErrorKind::BrokenPipe;
        }
        false
    })
}

/// Parses sizes like `512M`, `4G`, `1.5GiB`, `100000` (bytes).
pub fn parse_size(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let split = t.find(|c: char| !(c.is_ascii_digit() || c == '.')).unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let v: f64 = num.parse().map_err(|_| format!("'{s}' is not a size (try 512M or 4G)"))?;
    let mult = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1u64,
        "k" | "kb" | "kib" => 1 << 10,
        "m" | "mb" | "mib" => 1 << 20,
        "g" | "gb" | "gib" => 1 << 30,
        "t" | "tb" | "tib" => 1 << 40,
        _ => return Err(format!("'{s}': unknown unit (use K, M, G or T)")),
    };
    Ok((v * mult as f64) as u64)
}

/// Where temporary files go: `--tmp-dir`, else `$TMPDIR`, else `/tmp`.
pub fn tmp_dir(arg: &Option<std::path::PathBuf>) -> std::path::PathBuf {
    arg.clone().unwrap_or_else(std::env::temp_dir)
}

pub fn print_warnings(ws: &[String]) {
    for w in ws {
        warn(w);
    }
}

/// Opens the inputs of a command as one dataset.
pub fn open_dataset(inputs: &[String], crs: &CrsArgs) -> anyhow::Result<mortar_io::dataset::Dataset> {
    let paths = mortar_io::source::expand_inputs(inputs)?;
    Ok(mortar_io::dataset::Dataset::open_with(&paths, &crs.options())?)
}

/// How merged inputs get their CRS, shared by every command that merges inputs.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct CrsArgs {
    /// The output's CRS, whatever the inputs say: the CRS records of a LAS/LAZ FILE, or
    /// EPSG:CODE (GeoTIFF keys; EPSG:CODE+VERTICAL adds a vertical CRS). Without it, inputs
    /// whose CRSs disagree are refused.
    #[arg(long, value_name = "FILE|EPSG:CODE", value_parser = parse_assign_crs)]
    pub assign_crs: Option<mortar_io::crs::AssignCrs>,
}

fn parse_assign_crs(s: &str) -> Result<mortar_io::crs::AssignCrs, String> {
    mortar_io::crs::AssignCrs::parse(s)
}

impl CrsArgs {
    pub fn options(&self) -> mortar_io::dataset::OpenOptions {
        mortar_io::dataset::OpenOptions { assign_crs: self.assign_crs.clone() }
    }
}

/// Warns when the points' return counts differ from what the inputs' headers declare (the
/// output's header has the counted ones).
pub fn warn_points_by_return(ds: &mortar_io::dataset::Dataset, counted: &[u64; 15]) {
    if let Some(w) = ds.points_by_return_disagreement(counted) {
        warn(&w);
    }
}

/// Peak resident memory of this process so far (Linux `VmHWM`), in bytes.
pub fn peak_rss_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse::<u64>().ok().map(|kb| kb * 1024)
}

/// The sort's settings, shared by every command that sorts (`sort`, `batch`, `render`).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct SortArgs {
    /// Memory budget for sorting (e.g. 2G); larger inputs use an external sort.
    #[arg(long, value_parser = parse_size)]
    pub memory: Option<u64>,
    /// Directory for temporary files (external sort buckets, temporary batch files).
    #[arg(long)]
    pub tmp_dir: Option<std::path::PathBuf>,
    #[command(flatten)]
    pub crs: CrsArgs,
}

impl SortArgs {
    pub fn tmp_dir(&self) -> std::path::PathBuf {
        tmp_dir(&self.tmp_dir)
    }
    pub fn options(&self) -> mortar_io::sort::SortOptions {
        mortar_io::sort::SortOptions::with_memory(self.memory.unwrap_or_else(mortar_io::sort::default_memory), self.tmp_dir())
    }
}

/// Milliseconds since the process started (the first call, made first thing in `main`).
pub fn since_start_ms() -> f64 {
    static START: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
    START.get_or_init(std::time::Instant::now).elapsed().as_secs_f64() * 1e3
}
