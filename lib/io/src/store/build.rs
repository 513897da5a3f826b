//! `mortar build`: options, report, and the choice of engine.

use crate::dataset::{Dataset, RecordSource};
use crate::error::{BoundsError, Error, Result, StoreError};
use mortar_core::octree::BuilderConfig;
use std::path::Path;
use std::time::Instant;

use super::incremental::build_into;
use super::record::BuildRecord;
use super::writer::*;

/// Choices of `mortar build`.
/// Which engine builds the store.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Engine {
    /// The sorted engine when the input fits the memory budget and voxels take the first
    /// point's colour, the partitioned one when it does not, the incremental one for averaged
    /// colours (and where one cell is denser than the budget allows).
    #[default]
    Auto,
    /// Sort, then make the tree in one pass (ARCHITECTURE.md, "The build engine").
    Sorted,
    /// The sorted engine over a partition of the input into cells written to run files: for
    /// inputs larger than the memory budget.
    Partitioned,
    /// Paper 004's batch updates with paged leaves (bounded memory for any input).
    Incremental,
}

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

/// What a build did.
#[derive(Clone, Debug, Default)]
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
    /// Seconds in `add_batch`, per batch.
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
    /// The engine that built the store: `sorted` (the input fits `--memory`) or `incremental`.
    pub engine: &'static str,
    /// Seconds sorting the keys (sorted engine).
    pub sort_seconds: f64,
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

/// The integer bounds the inputs' headers declare (one unit of margin), on the merged grid, with
/// a warning for each input whose header bounds are not usable; `None` when no header is.
pub(crate) fn header_bounds(
    ds: &Dataset,
    warnings: &mut Vec<String>,
) -> Option<([i32; 3], [i32; 3])> {
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    for src in &ds.inputs {
        if src.point_count() == 0 {
            continue;
        }
        match header_box(ds, src.as_ref()) {
            Ok((l, h)) => {
                for a in 0..3 {
                    lo[a] = lo[a].min(l[a]);
                    hi[a] = hi[a].max(h[a]);
                }
            }
            Err(why) => warnings.push(format!(
                "{}: {why}; the octree is placed from the points",
                src.path().display()
            )),
        }
    }
    (lo[0] <= hi[0]).then_some((lo, hi))
}

/// The integer box the header of `src` declares (one unit of margin), on the merged grid, or
/// why it is not usable.
pub(crate) fn header_box(
    ds: &Dataset,
    src: &dyn RecordSource,
) -> std::result::Result<([i32; 3], [i32; 3]), BoundsError> {
    let h = src.header();
    if src.point_count() > 1 && (0..3).all(|a| h.min[a] == 0.0 && h.max[a] == 0.0) {
        return Err(BoundsError::AllZero);
    }
    if let Some(a) =
        (0..3).find(|&a| !(h.min[a].is_finite() && h.max[a].is_finite()) || h.min[a] > h.max[a])
    {
        return Err(BoundsError::Unusable {
            axis: ['x', 'y', 'z'][a],
            min: h.min[a],
            max: h.max[a],
        });
    }
    let c = |v: i64| v.clamp(i32::MIN as i64, i32::MAX as i64) as i32;
    Ok((
        [0, 1, 2].map(|a| c(ds.grid.to_int(a, h.min[a]).saturating_sub(1))),
        [0, 1, 2].map(|a| c(ds.grid.to_int(a, h.max[a]).saturating_add(1))),
    ))
}

/// A warning when the points of `src` (`st`, on the merged grid) reach outside the bounds its
/// header declares, with both ranges in world coordinates on the file's grid.
pub(crate) fn bounds_warning(
    ds: &Dataset,
    src: &dyn RecordSource,
    st: &crate::sort::PieceStats,
) -> Option<String> {
    let h = src.header();
    if st.count == 0
        || (0..3).any(|a| !(h.min[a].is_finite() && h.max[a].is_finite()) || h.min[a] > h.max[a])
    {
        return None;
    }
    let g = &ds.grid;
    let outside = (0..3).any(|a| {
        (st.min[a] as i64) < g.to_int(a, h.min[a]) - 1
            || (st.max[a] as i64) > g.to_int(a, h.max[a]) + 1
    });
    if !outside {
        return None;
    }
    let digits = |a: usize| (-h.scale[a].log10()).ceil().clamp(0.0, 12.0) as usize;
    let range = |a: usize, lo: f64, hi: f64| {
        format!("{} [{:.*}, {:.*}]", ['x', 'y', 'z'][a], digits(a), lo, digits(a), hi)
    };
    let real: Vec<String> = (0..3)
        .map(|a| range(a, g.world(a, st.min[a] as i64), g.world(a, st.max[a] as i64)))
        .collect();
    let declared: Vec<String> = (0..3).map(|a| range(a, h.min[a], h.max[a])).collect();
    Some(format!(
        "{}: its points reach {}, outside the bounds its header declares ({}); the octree's root holds them (`mortar sort` writes the file with true bounds)",
        src.path().display(),
        real.join(", "),
        declared.join(", ")
    ))
}

/// Builds the store `dir` from `ds`: reads the input piece by piece (pieces of a batch in
/// parallel) and adds the points to the octree in batches of about `batch_points` in input order,
/// committing every `commit_every` seconds, whenever the points held since the last commit exceed
/// a third of the memory budget, and at the end; after each commit the leaves' points are paged
/// out (see the module docs). The octree's root cube comes from the headers' bounds and the first
/// points; where points fall outside it (headers lie), the root grows (a new root above the old
/// one) and the report warns about each such file with its points' real range. On an error the
/// directory is removed; on Ctrl-C the last commit stays readable.
pub fn build(
    ds: &Dataset,
    dir: &Path,
    opts: &BuildOptions,
    progress: &mut dyn FnMut(&BuildProgress),
) -> Result<BuildReport> {
    let t0 = Instant::now();
    let meta = ds.source_meta();
    let mut warnings = Vec::new();
    let bounds = header_bounds(ds, &mut warnings);
    let first_come = opts.config.color_mode == mortar_core::octree::ColorMode::FirstCome;
    let engine = match opts.engine {
        Engine::Auto if super::engine::applies(ds, opts) => Engine::Sorted,
        Engine::Auto if first_come => Engine::Partitioned,
        Engine::Auto => Engine::Incremental,
        Engine::Sorted | Engine::Partitioned if !first_come => {
            return Err(Error::AveragedColours);
        }
        e => e,
    };
    let name = match engine {
        Engine::Sorted => "sorted",
        Engine::Partitioned => "partitioned",
        _ => "incremental",
    };
    let mut record = BuildRecord::of(ds, &opts.config, name);
    let mut writer = match if opts.resume {
        continue_store(dir, &meta, &record, &mut warnings)?
    } else {
        Continue::Fresh
    } {
        Continue::Writer(w) => w,
        Continue::Complete(mut r) => {
            warnings.append(&mut r.warnings);
            r.warnings = warnings;
            r.seconds = t0.elapsed().as_secs_f64();
            return Ok(r);
        }
        Continue::Fresh => {
            let w = StoreWriter::create(dir, &meta)?;
            record.write(dir)?;
            w
        }
    };
    writer.group_bytes = super::writer::group_bytes(opts.memory);
    // Continued from a commit, or from a partitioned build's state (no commit yet).
    let resumed = writer.commits() > 0 || (opts.resume && writer.guard.is_none());
    let run = |writer: &mut StoreWriter,
               progress: &mut dyn FnMut(&BuildProgress)|
     -> Result<BuildReport> {
        match engine {
            Engine::Sorted => super::engine::build_into(ds, writer, opts, progress, bounds, t0),
            Engine::Partitioned => {
                super::partitioned::build_into(ds, writer, opts, progress, bounds, t0)
            }
            _ => build_into(ds, writer, opts, progress, bounds, t0),
        }
    };
    let result = run(&mut writer, progress).map(|mut r| {
        warnings.append(&mut r.warnings);
        r.warnings = warnings;
        r.resumed = resumed;
        r
    });
    match result {
        Ok(r) => {
            record.complete = true;
            record.write(dir)?;
            Ok(r)
        }
        Err(Error::Interrupted) => Err(Error::Interrupted),
        // Out of disk, or another failure of the file system, after a commit: the store keeps
        // its last commit, and `--resume` continues from it once there is room.
        Err(e @ Error::Io { .. }) if writer.commits() > 0 => Err(Error::KeptCommit {
            error: Box::new(e),
            store: dir.to_path_buf(),
            commit: writer.commits(),
        }),
        Err(e) if resumed => Err(e),
        Err(e) => {
            // Not a store the user asked for: remove what was written (also after commits).
            let _ = std::fs::remove_dir_all(dir);
            Err(e)
        }
    }
}

/// How a build with `--resume` begins.
enum Continue {
    /// From nothing (no store, or nothing committed yet).
    Fresh,
    /// From the last commit of the store.
    Writer(StoreWriter),
    /// The store is complete.
    Complete(BuildReport),
}

/// Checks that the store `dir` was begun by a build of the same inputs and settings (its
/// [`BuildRecord`]) and reopens it at its last commit.
fn continue_store(
    dir: &Path,
    meta: &crate::dataset::SourceMeta,
    record: &BuildRecord,
    warnings: &mut Vec<String>,
) -> Result<Continue> {
    let empty = !dir.exists()
        || (dir.is_dir()
            && std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?.next().is_none());
    if empty {
        return Ok(Continue::Fresh);
    }
    let Some(old) = BuildRecord::read(dir)? else {
        return Err(Error::Store { path: dir.to_path_buf(), error: StoreError::NoBuildRecord });
    };
    if let Some(m) = record.mismatch(&old) {
        return Err(Error::Store {
            path: dir.to_path_buf(),
            error: StoreError::Settings { mismatch: m },
        });
    }
    if old.complete {
        let s = super::reader::Store::open(dir)?;
        let r = BuildReport {
            engine: "none",
            points: s.header.points,
            nodes: s.entries.len() as u64,
            leaves: s.leaves().len() as u64,
            commits: s.header.commit,
            nodes_bytes: s.header.nodes_len,
            resumed: true,
            warnings: vec![format!("{}: the build is complete; nothing to resume", dir.display())],
            ..BuildReport::default()
        };
        return Ok(Continue::Complete(r));
    }
    let start_over = |why: String, warnings: &mut Vec<String>| -> Result<Continue> {
        warnings.push(format!("{}: {why}; building it again from the start", dir.display()));
        std::fs::remove_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        Ok(Continue::Fresh)
    };
    if old.engine == "partitioned" && record.engine == "partitioned" {
        return match StoreWriter::reopen_uncommitted(dir, meta)? {
            Some(w) if super::partitioned::has_state(dir) => Ok(Continue::Writer(w)),
            _ => start_over("nothing of its partition was kept".into(), warnings),
        };
    }
    if old.engine != "sorted" || record.engine != "sorted" {
        return start_over(
            "the incremental engine keeps its tree in memory and cannot continue a build".into(),
            warnings,
        );
    }
    match StoreWriter::reopen(dir, meta)? {
        Some((w, _)) => Ok(Continue::Writer(w)),
        None => start_over("nothing was committed".into(), warnings),
    }
}
