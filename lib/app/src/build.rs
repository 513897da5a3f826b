//! `mortar build`: its options and the whole command (a build, `--append`, `--compact`, a job of
//! a plan; with `--preview` and `--frames`), so that the binary parses and makes one call.
//! Nothing is printed here but warnings and progress; the caller prints the [`Outcome`].

use crate::cli as common;
use anyhow::Result;
use mortar_core::octree::{BuilderConfig, ColorMode, DEFAULT_LEAF_CAPACITY};
use mortar_io::store::{build, BuildOptions, BuildProgress, BuildReport, Engine};
use std::path::PathBuf;

/// `--engine`, parsed apart from the library's [`Engine`] (which knows no command line).
#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum EngineArg {
    Auto,
    Sorted,
    Partitioned,
    Incremental,
    Gpu,
}

impl From<EngineArg> for Engine {
    fn from(e: EngineArg) -> Engine {
        match e {
            EngineArg::Auto => Engine::Auto,
            EngineArg::Sorted => Engine::Sorted,
            EngineArg::Partitioned => Engine::Partitioned,
            EngineArg::Incremental => Engine::Incremental,
            EngineArg::Gpu => Engine::Gpu,
        }
    }
}

/// `mortar build`'s options.
#[derive(clap::Args)]
pub struct Args {
    /// LAS/LAZ files, batch files, stores, directories, glob patterns, or - for stdin.
    #[arg(required_unless_present_any = ["compact", "plan"])]
    pub inputs: Vec<String>,
    /// The store directory to create (must not exist, or be empty).
    #[arg(short, long, required_unless_present_any = ["compact", "append"])]
    pub output: Option<PathBuf>,
    /// Add the inputs to this existing store: its points come first, the new ones after, and the
    /// result is the store a build of all of them in that order gives (with the store's leaf
    /// capacity and colours), built into STORE.append and swapped in atomically at the end
    /// (--resume continues a stopped append). A store of the sorted, partitioned or GPU engine
    /// keeps its points' arrival order (arrival.bin) and needs no original input; others are
    /// built again from their recorded inputs, which must still be there, unchanged. Where the new points
    /// stay inside the store's root cube (and change neither its grid, record layout nor colour
    /// scale), the nodes they do not reach are kept and only those they reach are coded again;
    /// otherwise the report says why everything is built again. Give the --crs options the
    /// store was built with.
    #[arg(long, value_name = "STORE", conflicts_with_all = ["output", "compact", "plan"])]
    pub append: Option<PathBuf>,
    /// Compact an existing store instead of building one: rewrite it so that `nodes.bin` holds
    /// only the payloads of its last commit (stores of the incremental engine keep superseded
    /// node versions). Run it when no build writes the store.
    #[arg(long, value_name = "STORE", conflicts_with_all = ["inputs", "resume"])]
    pub compact: Option<PathBuf>,
    /// Build one job of a plan (`mortar plan`) into a part for `mortar merge`: its inputs and
    /// tree come from the plan; -o names the part's directory (an earlier attempt is replaced).
    #[arg(long, requires = "job", conflicts_with_all = ["inputs", "compact", "resume"])]
    pub plan: Option<PathBuf>,
    /// The job of --plan to build (0 to jobs - 1).
    #[arg(long, requires = "plan")]
    pub job: Option<usize>,
    /// Most points per leaf.
    #[arg(long, default_value_t = DEFAULT_LEAF_CAPACITY)]
    pub leaf_capacity: u32,
    /// Voxel colours as the average of their points instead of the first point's (paper 004's
    /// future work; slower, more memory).
    #[arg(long)]
    pub averaged_colors: bool,
    /// Seconds between commits of the store while it is built (readers see each commit).
    #[arg(long, default_value_t = 5.0)]
    pub commit_every: f64,
    /// Points per octree update.
    #[arg(long, default_value_t = 1_000_000)]
    pub batch_points: usize,
    /// Memory budget, e.g. 8G (default: half the machine's memory, at most 16G, at least 256M,
    /// as for `sort`). An input that fits it is sorted in memory and the tree made in one pass
    /// (the sorted engine); a larger one is partitioned by Morton cell into run files in the
    /// store and built one unit of the budget's size at a time (the partitioned engine; a cell
    /// denser than a unit is partitioned again).
    #[arg(long, value_parser = common::parse_size)]
    pub memory: Option<u64>,
    /// The build engine: auto (sorted when the input fits --memory, else partitioned; incremental
    /// for --averaged-colors), sorted, partitioned, incremental, or gpu (SimLOD's passes on the
    /// GPU, a software Vulkan such as lavapipe where there is no GPU; the same store as sorted;
    /// the input must fit the GPU's memory and --memory). All build the same tree; auto never
    /// picks gpu.
    #[arg(long, value_enum, default_value_t = EngineArg::Auto)]
    pub engine: EngineArg,
    /// GPU memory --engine gpu may use, e.g. 8G (at least 32M; default: three quarters of the
    /// device memory the adapter reports, or without a report what the points, the nodes and
    /// the voxel grids need). Segments of points beyond half of it are paged out to host
    /// memory and back.
    #[arg(long, value_parser = common::parse_size)]
    pub gpu_memory: Option<u64>,
    /// Continue the store at --output from its last commit, if a build of the same inputs and
    /// settings began it and was stopped (kill -9, power loss, full disk); a complete store is
    /// left as it is.
    #[arg(long)]
    pub resume: bool,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub crs: common::CrsArgs,
    #[command(flatten)]
    pub frames: crate::frames::FramesArgs,
    #[command(flatten)]
    pub preview: crate::viewer::PreviewArgs,
}

/// Seconds between commits while a preview window shows the store.
const PREVIEW_COMMIT_EVERY: f64 = 1.0;
/// Seconds to the first commit while a preview window shows the store (so that points appear
/// early).
const PREVIEW_FIRST_COMMIT: f64 = 0.25;

/// What `mortar build` did: the JSON summary (`--json`) and, where the command has one, the line
/// it says on stderr without `--json`.
pub struct Outcome {
    /// The summary `--json` prints.
    pub json: serde_json::Value,
    /// A one-line summary for stderr, when not `--json`.
    pub line: Option<String>,
}

/// Runs `mortar build` as `a` says.
pub fn run(a: &Args) -> Result<Outcome> {
    let memory = a.memory.unwrap_or_else(mortar_io::sort::default_memory);
    if let Some(dir) = &a.compact {
        let r = mortar_io::store::compact(dir)?;
        return Ok(Outcome {
            json: serde_json::json!({"store": dir, "nodes": r.nodes, "bytes_before": r.before, "bytes_after": r.after, "segments_rewritten": r.segments}),
            line: Some(format!(
                "mortar: {}: payloads {} -> {} bytes ({} nodes, {} segments rewritten)",
                dir.display(),
                r.before,
                r.after,
                r.nodes,
                r.segments
            )),
        });
    }
    // --append: the store's inputs, then the new ones, built beside it and swapped in at the end.
    let append = match &a.append {
        Some(store) => {
            let ask = mortar_io::store::append::AppendAsk {
                leaf_capacity: (a.leaf_capacity != DEFAULT_LEAF_CAPACITY)
                    .then_some(a.leaf_capacity),
                averaged_colors: a.averaged_colors,
                resume: a.resume,
            };
            let plan = mortar_io::store::append::plan_append(store, &a.inputs, ask)?;
            Some(plan)
        }
        None => None,
    };
    let Some(output) = append.as_ref().map(|p| p.work.clone()).or_else(|| a.output.clone()) else {
        anyhow::bail!("give the store directory with -o")
    };
    if let (Some(plan), Some(job)) = (&a.plan, a.job) {
        let plan = mortar_io::store::distributed::Plan::read(plan)?;
        let paths: Vec<String> = plan.inputs.iter().map(|i| i.path.clone()).collect();
        let ds = common::open_dataset(&paths, &common::CrsArgs::default())?;
        let bar = common::progress_bar("mortar build (job)", &ds.progress);
        let r = mortar_io::store::distributed::build_job(&ds, &plan, job, &output, memory)?;
        drop(bar);
        common::print_warnings(&r.warnings);
        let mut j = serde_json::to_value(&r)?;
        j["output"] = serde_json::json!(output);
        j["peak_rss_bytes"] = serde_json::json!(common::peak_rss_bytes());
        return Ok(Outcome { json: j, line: None });
    }
    if a.leaf_capacity == 0 {
        anyhow::bail!("--leaf-capacity must be at least 1");
    }
    // --append keeps the store's nodes that no new point reaches where it can (not while a
    // preview or frames watch the build's commits; MORTAR_APPEND_REBUILD=1 builds everything,
    // for comparisons), else builds everything again.
    let mut rebuild_note = None;
    if let Some(plan) = &append {
        let watched = a.preview.preview || a.frames.frames.is_some();
        if !watched && std::env::var_os("MORTAR_APPEND_REBUILD").is_none() {
            use mortar_io::store::patch::{append_in_place, InPlace};
            match append_in_place(plan, &a.crs.options(), memory)
                .map_err(|e| anyhow::Error::from(e).context(plan.failure(false)))?
            {
                InPlace::Done(r) => {
                    mortar_io::store::append::replace_store(plan)?;
                    common::print_warnings(&r.warnings);
                    return report(
                        &r,
                        &plan.store,
                        serde_json::Value::Null,
                        serde_json::Value::Null,
                    );
                }
                InPlace::Rebuild(why) => {
                    rebuild_note =
                        Some(format!("{}: every node is built again ({why})", plan.store.display()))
                }
            }
        }
    }
    let ds = match &append {
        Some(plan) => plan.open_inputs(&a.crs.options(), memory)?,
        None => common::open_dataset(&a.inputs, &a.crs)?,
    };
    common::print_warnings(&ds.warnings);
    let opts = BuildOptions {
        config: append.as_ref().map_or(
            BuilderConfig {
                leaf_capacity: a.leaf_capacity,
                color_mode: if a.averaged_colors {
                    ColorMode::Averaged
                } else {
                    ColorMode::FirstCome
                },
                ..BuilderConfig::default()
            },
            |p| p.config,
        ),
        batch_points: a.batch_points.max(1),
        first_commit_after: None,
        commit_every: a.commit_every.max(0.0),
        memory,
        engine: a.engine.into(),
        resume: a.resume,
        tree: None,
    };
    let mut recorder = crate::frames::FrameRecorder::new(&a.frames, &ds, &output)?;
    let mut opts = opts;
    if opts.engine == Engine::Gpu {
        opts.tree = Some(crate::gpu_build::tree_backend(a.gpu_memory)?);
    }
    if let Some(r) = &recorder {
        opts.commit_every = opts.commit_every.min(r.every());
    }
    if a.preview.preview {
        opts.commit_every = opts.commit_every.min(PREVIEW_COMMIT_EVERY);
        opts.first_commit_after = Some(PREVIEW_FIRST_COMMIT);
    }
    let bar = common::progress_bar("mortar build", &ds.progress);
    let mut frame_error: Option<anyhow::Error> = None;
    let mut progress = |p: &BuildProgress| {
        if let (Some(rec), None) = (recorder.as_mut(), frame_error.as_ref()) {
            if let Err(e) = rec.on_commit(p.commits, false) {
                frame_error = Some(e);
            }
        }
    };
    let built = if a.preview.preview {
        let view = a.preview.view_args(&output, &a.frames.camera);
        let bounds = crate::frames::header_bounds(&ds);
        let (ds, output, opts) = (&ds, &output, &opts);
        let job = move |report: &mut dyn FnMut(&BuildProgress)| {
            // The build's threads (this one and rayon's, for the rest of the command) give way
            // to the preview's frame thread (mortar_io::threads).
            mortar_io::threads::lower_priority();
            rayon::broadcast(|_| mortar_io::threads::lower_priority());
            build(ds, output, opts, &mut |p| {
                progress(p);
                report(p);
            })
            .map_err(anyhow::Error::from)
        };
        if a.preview.preview_offscreen {
            crate::viewer::run_preview_offscreen(&view, output, bounds, &ds.layout, job)
        } else {
            crate::viewer::run_preview(&view, output, bounds, &ds.layout, job)
        }
    } else {
        build(&ds, &output, &opts, &mut progress)
            .map(|r| (r, serde_json::Value::Null))
            .map_err(anyhow::Error::from)
    };
    // A stopped append is continued by --append, not by a build of the working directory.
    let (r, preview_json) = built.map_err(|e| match &append {
        Some(plan) => {
            let kept = matches!(
                e.downcast_ref::<mortar_io::error::Error>(),
                Some(mortar_io::error::Error::KeptCommit { .. })
            );
            e.context(plan.failure(kept))
        }
        None => e,
    })?;
    drop(bar);
    let mut r = r;
    r.warnings.splice(0..0, rebuild_note);
    let output = match &append {
        Some(plan) => {
            mortar_io::store::append::replace_store(plan)?;
            plan.store.clone()
        }
        None => output,
    };
    common::print_warnings(&r.warnings);
    if let Some(e) = frame_error {
        return Err(e.context("drawing a frame of the growing store (the store itself was built)"));
    }
    let mut frames_json = serde_json::Value::Null;
    if let Some(rec) = recorder.as_mut() {
        rec.on_commit(r.commits, true)?;
        let sheet = rec.finish()?;
        frames_json = crate::frames::frames_json(rec, &sheet);
    }
    report(&r, &output, frames_json, preview_json)
}

/// The build's report as it is, and the figures derived from it (the per-batch times summed up).
fn report(
    r: &BuildReport,
    output: &std::path::Path,
    frames_json: serde_json::Value,
    preview_json: serde_json::Value,
) -> Result<Outcome> {
    let n = r.batch_seconds.len().max(1) as f64;
    let mut j = serde_json::to_value(r)?;
    let derived = serde_json::json!({
        "output": output,
        "build_seconds": r.batch_seconds.iter().sum::<f64>(),
        "points_per_second": r.points as f64 / r.seconds.max(1e-9),
        "batches": r.batch_seconds.len(),
        "batch_seconds_mean": r.batch_seconds.iter().sum::<f64>() / n,
        "batch_seconds_max": r.batch_seconds.iter().cloned().fold(0.0, f64::max),
        "peak_rss_bytes": common::peak_rss_bytes(),
        "threads": rayon::current_num_threads(),
        "frames": frames_json,
        "preview": preview_json,
    });
    if let (Some(j), serde_json::Value::Object(d)) = (j.as_object_mut(), derived) {
        j.extend(d);
    }
    Ok(Outcome { json: j, line: None })
}
