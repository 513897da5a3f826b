//! One build by the partitioned engine: pass 1 (or, with `--resume`, the manifest it left and
//! the log of finished visits), the walk, and the one commit of the entries in the sorted
//! engine's order.

use super::log::{read_log, LOG};
use super::manifest::{read_manifest, write_manifest, STATE_DIR};
use super::partition::{cell_depth, partition_all, Partition};
use super::preview::{Preview, RootSample};
use super::ranks::{RankLog, RANKS};
use super::unit::unit_bytes_per_point;
use super::walk::Walk;
use crate::dataset::Dataset;
use crate::error::{Error, Result};
use crate::store::arrival::ColorMaxima;
use crate::store::dense::Level;
use crate::store::format::*;
use crate::store::options::{BuildOptions, BuildProgress, BuildReport, BuiltBy};
use crate::store::writer::*;
use mortar_core::color::{ColorSource, RgbDepth};
use mortar_core::octree::NodeKey;
use std::time::Instant;

/// Builds the store in `writer` from `ds` (a cell denser than a unit: [`dense`]).
///
/// [`dense`]: crate::store::dense
pub(crate) fn build_into(
    ds: &Dataset,
    writer: &mut StoreWriter,
    opts: &BuildOptions,
    progress: &mut dyn FnMut(&BuildProgress),
    header: Option<([i32; 3], [i32; 3])>,
    t0: Instant,
) -> Result<BuildReport> {
    let rl = ds.layout.record_len;
    let total = ds.declared_points();
    let mut report = BuildReport { engine: BuiltBy::Partitioned, ..BuildReport::default() };
    let state = writer.dir.join(STATE_DIR);
    let tr = Instant::now();
    let kept = if opts.resume { read_manifest(&state, rl) } else { None };
    // A partition made for another tree shape (another --max-level) is not used.
    let kept = kept.filter(|p| {
        p.hist.len() == 1usize << (3 * cell_depth(p.root, opts.config.max_level) as u32)
    });
    let resumed = kept.is_some();
    // Provisional commits while the build runs (readers and --preview see it grow).
    let mut preview = if opts.commit_every.is_finite() {
        Some(Preview::new(writer, ds.layout.clone(), opts.commit_every, opts.config.leaf_capacity)?)
    } else {
        None
    };
    let part = match kept {
        Some(p) => p,
        None => {
            let _ = std::fs::remove_dir_all(&state);
            std::fs::create_dir_all(&state).map_err(|e| Error::io(&state, e))?;
            let previewed = preview.is_some();
            let mut commit = |s: &RootSample| -> Result<()> {
                match preview.as_mut() {
                    Some(pv) if pv.due() => pv.commit_sample(writer, s),
                    _ => Ok(()),
                }
            };
            let on_group = previewed
                .then_some((&mut commit as &mut dyn FnMut(&RootSample) -> Result<()>, opts.memory));
            let p = partition_all(
                ds,
                opts.memory,
                opts.config.max_level,
                [1; 3],
                header,
                &state,
                on_group,
            )?;
            write_manifest(&state, &p)?;
            p
        }
    };
    let Partition { root, runs, hist, all, warnings, sample, .. } = part;
    if let (Some(pv), Some(s)) = (preview.as_mut(), sample) {
        pv.set_sample(s);
    }
    report.warnings = warnings;
    report.read_seconds = tr.elapsed().as_secs_f64();
    crate::cleanup::trace("partitioned", t0);
    let (lo, hi) = if all.count == 0 { ([0; 3], [0; 3]) } else { (all.min, all.max) };
    let unit_points = ((opts.memory / 2) / unit_bytes_per_point(rl as u64))
        .max(opts.config.leaf_capacity as u64 + 1);
    // A resumed walk: what the log holds is taken as it is; nodes.bin is cut after it.
    let log_path = state.join(LOG);
    let ranks_path = state.join(RANKS);
    let (replay, logged, logged_hashes, logged_points, nodes_end) = if resumed {
        read_log(&log_path, &writer.dir.join(NODES_FILE), rl, Some(&ranks_path))?
    } else {
        Default::default()
    };
    // The leaves' arrival ranks, kept for `arrival.bin` as the visits finish (those of the
    // visits a resumed build keeps are in the file already).
    let ranks = RankLog::open(&state, ds.pieces().iter().map(|p| p.piece.points), logged_points)?;
    writer.cut_nodes(nodes_end)?;
    report.kept_nodes = logged.len() as u64;
    ds.progress.stage("building", all.count, "points");
    ds.progress.add(logged_points);
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .map_err(|e| Error::io(&log_path, e))?;
    let color = match ds.layout.attribute("rgb") {
        Some(a) if all.max_rgb > 0 => {
            ColorSource::Rgb { offset: a.offset, depth: RgbDepth::detect(all.max_rgb) }
        }
        _ => ColorSource::Intensity { max_intensity: all.max_intensity },
    };
    ds.progress.stage("building", all.count, "points");
    let depth = cell_depth(root, opts.config.max_level);
    let cells = hist.len();
    let lv = Level::new(runs, hist, depth);
    let mut w = Walk {
        ds,
        writer,
        opts,
        root,
        unit_points,
        color,
        rl,
        entries: logged,
        hashes: logged_hashes,
        seq: 0,
        points: logged_points,
        report: &mut report,
        replay,
        log,
        log_path,
        state: state.clone(),
        preview,
        bounds: (lo, hi),
        ranks: Some(ranks),
    };
    w.visit(&lv, NodeKey::ROOT, root, 0, 0..cells)?;
    let Walk { mut entries, points, preview, ranks, .. } = w;
    // The sorted engine's order: level by level, depth-first (= Morton) order in a level.
    entries.sort_by_key(|&(level, seq, _)| (level, seq));
    // The final commit names no provisional node and no scratch segment.
    writer.entries.clear();
    writer.segments.clear();
    for (i, (_, _, e)) in entries.iter().enumerate() {
        writer.set_entry(i, *e);
    }
    let tc = Instant::now();
    writer.write_hierarchy(root, points, opts.config.leaf_capacity, (lo, hi))?;
    report.commit_seconds += tc.elapsed().as_secs_f64();
    // The ranks after the last commit and before the build record says the build finished,
    // as the sorted engine writes them.
    let colors = ColorMaxima { max_rgb: all.max_rgb, max_intensity: all.max_intensity };
    ranks.expect("the walk keeps ranks").write_arrival(
        &writer.dir,
        points,
        header,
        colors,
        opts.memory,
    )?;
    if let Some(pv) = preview {
        pv.remove();
    }
    progress(&BuildProgress { points, total, nodes: entries.len(), commits: writer.commits() });
    report.points = points;
    report.nodes = entries.len() as u64;
    report.leaves = entries.iter().filter(|(_, _, e)| e.kind == LEAF).count() as u64;
    report.voxels =
        entries.iter().filter(|(_, _, e)| e.kind != LEAF).map(|(_, _, e)| e.count).sum();
    report.commits = writer.commits();
    report.nodes_bytes = writer.nodes_len;
    report.resumed = resumed;
    let _ = std::fs::remove_dir_all(&state);
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(report)
}
