//! `mortar`: the command line. Thin: arguments -> configuration -> one library call -> output.
//! One file per subcommand.

mod batch;
mod build;
mod export;
mod info;
mod merge;
mod plan;
mod sort;

use clap::{Parser, Subcommand};
use mortar_app::{cli as common, render, viewer as view};

#[derive(Parser)]
#[command(
    name = "mortar",
    version,
    about = "LAS/LAZ to GPU-ready Morton-sorted batch files, sorted LAS/LAZ, and more"
)]
struct Cli {
    /// Worker threads (default: all cores).
    #[arg(long, global = true)]
    threads: Option<usize>,
    /// No warnings on stderr.
    #[arg(long, short, global = true)]
    quiet: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Describe LAS/LAZ files and batch files.
    Info(info::Args),
    /// Write every point in Morton order as LAS/LAZ (to a file or stdout).
    Sort(sort::Args),
    /// Convert to a Morton-sorted, quantized batch file (paper 003).
    Batch(batch::Args),
    /// Draw a view of a batch file, an octree store (LOD) or LAS/LAZ to PNG (CPU or GPU rasterizer).
    Render(render::Args),
    /// Build an octree LOD store (paper 004) from LAS/LAZ or batch files.
    Build(build::Args),
    /// Split a build into independent jobs (for a cluster): a plan for `build --plan --job`.
    Plan(plan::Args),
    /// Join the parts of a planned build into one store.
    Merge(merge::Args),
    /// Export the octree for other tools: one COPC 1.0 file or a Potree 2.0 directory.
    Export(export::Args),
    /// Show a batch file, a store (LOD) or raw LAS/LAZ (progressive) in a window (orbit, pan, zoom).
    View(view::Args),
}

fn main() {
    common::since_start_ms();
    let cli = Cli::parse();
    if let Some(t) = cli.threads {
        if let Err(e) = rayon::ThreadPoolBuilder::new().num_threads(t.max(1)).build_global() {
            eprintln!("mortar: error: cannot set up {t} threads: {e}");
            std::process::exit(1);
        }
    }
    common::set_quiet(cli.quiet);
    // A file that grows past `ulimit -f` raises SIGXFSZ, which kills by default: ignored, the
    // write fails with EFBIG and mortar reports it (a build keeps its last commit).
    // SAFETY: setting a signal's disposition to SIG_IGN before any other thread exists.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
    }
    // Ctrl-C: the temporary paths are removed at once, and again a moment later (the work may
    // have made one between the flag and its next check, which would stay); work that sees the
    // flag first returns an error, and main exits 130 below.
    let _ = ctrlc::set_handler(|| {
        mortar_io::cleanup::INTERRUPTED.store(true, std::sync::atomic::Ordering::Relaxed);
        mortar_io::cleanup::remove_all();
        std::thread::sleep(std::time::Duration::from_millis(300));
        mortar_io::cleanup::remove_all();
        eprintln!("mortar: interrupted");
        std::process::exit(130);
    });
    let r = match cli.cmd {
        Cmd::Info(a) => info::run(a),
        Cmd::Sort(a) => sort::run(a),
        Cmd::Batch(a) => batch::run(a),
        Cmd::Render(a) => render::run(a),
        Cmd::Build(a) => build::run(a),
        Cmd::Export(a) => export::run(a),
        Cmd::Plan(a) => plan::run(a),
        Cmd::Merge(a) => merge::run(a),
        Cmd::View(a) => view::run(a),
    };
    // Local copies of HTTP inputs.
    mortar_io::remote::remove_copies();
    if let Err(e) = r {
        mortar_io::cleanup::remove_all();
        if mortar_io::cleanup::INTERRUPTED.load(std::sync::atomic::Ordering::Relaxed) {
            eprintln!("mortar: interrupted");
            std::process::exit(130);
        }
        if common::is_broken_pipe(&e) {
            std::process::exit(0);
        }
        eprintln!("mortar: error: {}", mortar_io::remote::with_urls(&format!("{e:#}")));
        std::process::exit(1);
    }
}
