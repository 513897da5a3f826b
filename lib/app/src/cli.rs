//! Helpers shared by the subcommands: warnings, sizes, inputs.

use std::sync::atomic::{AtomicBool, Ordering};

static QUIET: AtomicBool = AtomicBool::new(false);

pub fn set_quiet(q: bool) {
    QUIET.store(q, Ordering::Relaxed);
}

pub fn warn(msg: &str) {
    if !QUIET.load(Ordering::Relaxed) {
        eprintln!("mortar: warning: {}", mortar_io::remote::with_urls(msg));
    }
}

/// A progress bar on stderr while a job runs: percent, count, rate and time left, drawn from
/// the job's [`Progress`](mortar_io::progress::Progress) by a thread of its own ten times a
/// second, one bar per stage. Nothing is drawn when stderr is not a terminal or with `--quiet`.
/// Dropping it stops the thread and clears the line.
pub struct ProgressBar {
    stop: std::sync::Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

pub fn progress_bar(
    command: &'static str,
    progress: &mortar_io::progress::Progress,
) -> ProgressBar {
    use std::io::IsTerminal;
    let stop = std::sync::Arc::new(AtomicBool::new(false));
    if QUIET.load(Ordering::Relaxed) || !std::io::stderr().is_terminal() {
        return ProgressBar { stop, thread: None };
    }
    let (p, s) = (progress.clone(), stop.clone());
    let thread = std::thread::Builder::new()
        .name("mortar-progress".into())
        .spawn(move || {
            let rate = |st: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
                let r = st.per_sec();
                let _ = match r {
                    r if r >= 1e6 => write!(w, "{:.1} M/s", r / 1e6),
                    r if r >= 1e3 => write!(w, "{:.1} k/s", r / 1e3),
                    r => write!(w, "{r:.0}/s"),
                };
            };
            let known = indicatif::ProgressStyle::with_template("{prefix}: {msg} [{bar:30}] {percent:>3}% {human_pos}/{human_len} ({rate}, {eta} left)")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .with_key("rate", rate)
                .progress_chars("=> ");
            let unknown = indicatif::ProgressStyle::with_template("{prefix}: {msg} {spinner} {elapsed}").unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner());
            let mut bar: Option<indicatif::ProgressBar> = None;
            let mut number = 0;
            while !s.load(Ordering::Relaxed) {
                let (stage, done) = p.snapshot();
                if stage.number != number && stage.number > 0 {
                    number = stage.number;
                    if let Some(b) = bar.take() {
                        b.finish_and_clear();
                    }
                    // A bar per stage, made whole before it is first drawn.
                    let target = indicatif::ProgressDrawTarget::stderr_with_hz(10);
                    let b = if stage.total > 0 {
                        indicatif::ProgressBar::with_draw_target(Some(stage.total), target).with_style(known.clone()).with_message(format!("{} ({})", stage.name, stage.unit))
                    } else {
                        indicatif::ProgressBar::with_draw_target(None, target).with_style(unknown.clone()).with_message(stage.name)
                    };
                    bar = Some(b.with_prefix(command));
                }
                if let Some(b) = &bar {
                    if stage.total > 0 {
                        b.set_position(done.min(stage.total));
                    } else {
                        b.tick();
                    }
                }
                std::thread::sleep(std::time::Duration::from_millis(100));
            }
            if let Some(b) = bar {
                b.finish_and_clear();
            }
        })
        .ok();
    ProgressBar { stop, thread }
}

impl Drop for ProgressBar {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
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
pub fn open_dataset(
    inputs: &[String],
    crs: &CrsArgs,
) -> anyhow::Result<mortar_io::dataset::Dataset> {
    let paths = mortar_io::inputs::expand(inputs)?;
    Ok(mortar_io::inputs::open_with(&paths, &crs.options())?)
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
        mortar_io::sort::SortOptions::with_memory(
            self.memory.unwrap_or_else(mortar_io::sort::default_memory),
            self.tmp_dir(),
        )
    }
}

/// Milliseconds since the process started (the first call, made first thing in `main`).
pub fn since_start_ms() -> f64 {
    static START: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
    START.get_or_init(std::time::Instant::now).elapsed().as_secs_f64() * 1e3
}
