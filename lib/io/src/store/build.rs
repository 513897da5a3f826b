//! `mortar build`: the choice of engine, and the start, resumption and end of a build (the
//! options and the report are in [`super::options`]).

use crate::dataset::Dataset;
use crate::error::{Error, Result, StoreError};
use std::path::Path;
use std::time::Instant;

use super::bounds::header_bounds;
use super::incremental::build_into;
use super::options::{BuildOptions, BuildProgress, BuildReport, BuiltBy, Engine};
use super::record::BuildRecord;
use super::writer::*;

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
    if engine == Engine::Gpu && !first_come {
        return Err(Error::AveragedColours);
    }
    let built_by = match engine {
        Engine::Sorted => BuiltBy::Sorted,
        Engine::Gpu => BuiltBy::Gpu,
        Engine::Partitioned => BuiltBy::Partitioned,
        _ => BuiltBy::Incremental,
    };
    let mut record = BuildRecord::of(ds, &opts.config, built_by.name());
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
            Engine::Gpu => super::gpu::build_into(ds, writer, opts, progress, bounds, t0),
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
            engine: BuiltBy::None,
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
    if old.engine == BuiltBy::Partitioned.name() && record.engine == BuiltBy::Partitioned.name() {
        if super::partitioned::has_state(dir) {
            // Its provisional commits: the build goes on from its state, not from them.
            super::partitioned::drop_provisional(dir)?;
        }
        return match StoreWriter::reopen_uncommitted(dir, meta)? {
            Some(w) if super::partitioned::has_state(dir) => Ok(Continue::Writer(w)),
            _ => start_over("nothing of its partition was kept".into(), warnings),
        };
    }
    // The sorted and the GPU engines write the same nodes level by level: either continues
    // the other's commits.
    let levelled = |e: &str| e == BuiltBy::Sorted.name() || e == BuiltBy::Gpu.name();
    if !levelled(&old.engine) || !levelled(&record.engine) {
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
