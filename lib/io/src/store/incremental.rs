//! The incremental engine: paper 004's batch updates with leaves paged out after each commit
//! (bounded memory for any input; ARCHITECTURE.md, "Paging the octree's leaves").

use crate::dataset::Dataset;
use crate::error::{Error, Result};
use mortar_core::color::{ColorSource, RgbDepth};
use mortar_core::octree::{Builder, NodeId, OctreeError, Point};
use rayon::prelude::*;
use std::time::Instant;

use super::bounds::bounds_warning;
use super::format::*;
use super::options::{BuildOptions, BuildProgress, BuildReport, BuiltBy};
use super::writer::*;

pub(crate) fn build_into(
    ds: &Dataset,
    writer: &mut StoreWriter,
    opts: &BuildOptions,
    progress: &mut dyn FnMut(&BuildProgress),
    header: Option<([i32; 3], [i32; 3])>,
    t0: Instant,
) -> Result<BuildReport> {
    let rl = ds.layout.record_len;
    let pieces = ds.pieces();
    let total: u64 = pieces.iter().map(|p| p.piece.points).sum();
    let batch = opts.batch_points.max(1);
    // Bytes held per point between commits: its record, its Point in a leaf, the batch's work.
    let per_point = rl as u64 + 24 + 48;
    let interval_points = ((opts.memory / 3) / per_point).max(batch as u64);
    let mut report = BuildReport { engine: BuiltBy::Incremental, ..BuildReport::default() };
    ds.progress.stage("building", total, "points");
    // Made with the first points: its root covers the headers' bounds and those points.
    let mut builder: Option<Builder> = None;
    // The real bounds of each input's points, for the warnings about headers that lie.
    let mut real: Vec<crate::sort::PieceStats> =
        vec![crate::sort::PieceStats::default(); ds.inputs.len()];
    // Records of the points added since the last commit (index = Point::record) and of points
    // paged back in (PAGED | index).
    let mut records: Vec<u8> = Vec::with_capacity(
        (interval_points.min(total) as usize + batch).saturating_mul(rl).min(1 << 30),
    );
    let paged = std::sync::Mutex::new(Vec::<u8>::new());
    let mut color: Option<ColorSource> = None;
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    let mut last_commit = Instant::now();
    let mut points: Vec<Point> = Vec::new();
    let mut done = 0u64;
    let mut next = 0usize;
    while next < pieces.len() {
        crate::cleanup::check_interrupted()?;
        // The next pieces, up to about one batch of points.
        let first = next;
        let mut n = 0u64;
        while next < pieces.len()
            && (next == first || n + pieces[next].piece.points <= batch as u64)
        {
            n += pieces[next].piece.points;
            next += 1;
        }
        let tr = Instant::now();
        let base = records.len();
        let bytes = usize::try_from(n)
            .ok()
            .and_then(|n| n.checked_mul(rl))
            .ok_or(Error::PieceTooLarge { points: n })?;
        records.resize(base + bytes, 0);
        {
            let mut slices = Vec::with_capacity(next - first);
            let mut rest = &mut records[base..];
            for p in &pieces[first..next] {
                let (head, tail) = rest.split_at_mut(p.piece.points as usize * rl);
                slices.push((p, head));
                rest = tail;
            }
            let stats: Vec<(usize, crate::sort::PieceStats)> = slices
                .into_par_iter()
                .map(|(p, out)| {
                    crate::cleanup::check_interrupted()?;
                    ds.read_piece_into(p, out)?;
                    // Read once: a mapped input's pages leave this process's memory.
                    ds.inputs[p.input].release_piece(&p.piece);
                    Ok((p.input, crate::sort::PieceStats::of(out, &ds.layout)))
                })
                .collect::<Result<_>>()?;
            for (i, st) in stats {
                real[i].merge(&st);
            }
        }
        let recs = &records[base..];
        let st = recs
            .par_chunks(rl * 65_536)
            .map(|c| crate::sort::PieceStats::of(c, &ds.layout))
            .reduce(crate::sort::PieceStats::default, |mut a, b| {
                a.merge(&b);
                a
            });
        report.read_seconds += tr.elapsed().as_secs_f64();
        if builder.is_none() && st.count > 0 {
            // The headers' box when it holds the first points; otherwise the headers lie, and
            // the root starts from the first points alone (it grows for the rest).
            let (l, h) = match header {
                Some((l, h)) if (0..3).all(|a| l[a] <= st.min[a] && st.max[a] <= h[a]) => (l, h),
                _ => (st.min, st.max),
            };
            builder = Some(
                Builder::for_bounds(l, h, opts.config).map_err(|error| Error::Octree { error })?,
            );
        }
        let Some(builder) = builder.as_mut() else { continue };
        if st.count > 0 {
            for a in 0..3 {
                lo[a] = lo[a].min(st.min[a]);
                hi[a] = hi[a].max(st.max[a]);
            }
        }
        // The colour source is chosen once, from the first batch (as batch files choose it from
        // the whole input).
        let color = *color.get_or_insert_with(|| match ds.layout.attribute("rgb") {
            Some(a) if st.max_rgb > 0 => {
                ColorSource::Rgb { offset: a.offset, depth: RgbDepth::detect(st.max_rgb) }
            }
            _ => ColorSource::Intensity { max_intensity: st.max_intensity },
        });
        // Updates of about `batch` points each; a commit may come between two of them.
        let mut cursor = base;
        while cursor < records.len() {
            crate::cleanup::check_interrupted()?;
            let end = (cursor + batch * rl).min(records.len());
            let first_index = (cursor / rl) as u64;
            points.clear();
            points.par_extend(records[cursor..end].par_chunks_exact(rl).enumerate().map(
                |(i, r)| Point {
                    pos: read_xyz(r),
                    color: color.rgba(r),
                    record: first_index + i as u64,
                },
            ));
            let tb = Instant::now();
            let paged_in = std::sync::atomic::AtomicU64::new(0);
            {
                let w = &*writer;
                let page_in = |id: NodeId| -> std::result::Result<Vec<Point>, String> {
                    paged_in.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    w.page_in(id.index(), None, &paged).map_err(|e| e.to_string())
                };
                let st = builder.add_batch_paged(&points, &page_in).map_err(|e| match e {
                    OctreeError::PageIn(problem) => Error::PageIn { path: w.dir.clone(), problem },
                    error => Error::Octree { error },
                })?;
                report.root_growths += st.growths as u64;
            }
            report.paged_in_leaves += paged_in.into_inner();
            report.batch_seconds.push(tb.elapsed().as_secs_f64());
            done += points.len() as u64;
            cursor = end;
            let held = records.len() as u64
                + paged.lock().map_or(0, |p| p.len() as u64)
                + builder.resident_points() * 24;
            report.peak_interval_bytes = report.peak_interval_bytes.max(held);
            let since = last_commit.elapsed().as_secs_f64();
            let first_due =
                writer.commits() == 0 && opts.first_commit_after.is_some_and(|f| since >= f);
            let due = since >= opts.commit_every
                || first_due
                || builder.resident_points() >= interval_points;
            let last = next == pieces.len() && cursor == records.len();
            if due && !last {
                commit_and_page_out(
                    writer,
                    builder,
                    (lo, hi),
                    &mut records,
                    cursor,
                    &paged,
                    rl,
                    &mut report,
                )?;
                cursor = 0;
                last_commit = Instant::now();
            }
            progress(&BuildProgress {
                points: done,
                total,
                nodes: builder.node_count(),
                commits: writer.commits(),
            });
        }
    }
    if done == 0 {
        (lo, hi) = ([0; 3], [0; 3]);
    }
    let builder = match builder.as_mut() {
        Some(b) => b,
        None => builder.insert(
            Builder::for_bounds([0; 3], [0; 3], opts.config)
                .map_err(|error| Error::Octree { error })?,
        ),
    };
    let all = records.len();
    commit_and_page_out(writer, builder, (lo, hi), &mut records, all, &paged, rl, &mut report)?;
    // Headers that lie: the points' real range, per file.
    for (src, st) in ds.inputs.iter().zip(&real) {
        if let Some(w) = bounds_warning(ds, src.as_ref(), st) {
            report.warnings.push(w);
        }
    }
    let snap = builder.snapshot();
    report.points = snap.total_points();
    report.nodes = snap.node_count() as u64;
    report.leaves = snap.leaves().count() as u64;
    report.voxels = snap.voxel_count();
    report.commits = writer.commits();
    report.nodes_bytes = writer.nodes_len;
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(report)
}

/// Commits, then pages out every leaf's points and drops the records they needed: the first
/// `added` bytes of `records` (the rest, not added yet, moves to the front).
#[allow(clippy::too_many_arguments)]
pub(crate) fn commit_and_page_out(
    writer: &mut StoreWriter,
    builder: &mut Builder,
    bounds: ([i32; 3], [i32; 3]),
    records: &mut Vec<u8>,
    added: usize,
    paged: &std::sync::Mutex<Vec<u8>>,
    rl: usize,
    report: &mut BuildReport,
) -> Result<()> {
    let tc = Instant::now();
    {
        let paged = paged.lock().map_err(|_| Error::ThreadPanicked { thread: "a page-in" })?;
        let recs: &[u8] = records;
        let pg: &[u8] = &paged;
        let record = |h: u64| -> &[u8] {
            if h & PAGED != 0 {
                let i = (h & !PAGED) as usize;
                &pg[i * rl..(i + 1) * rl]
            } else {
                &recs[h as usize * rl..(h as usize + 1) * rl]
            }
        };
        writer.commit(&builder.snapshot(), bounds, &record)?;
    }
    builder.page_out();
    records.drain(..added);
    if let Ok(mut p) = paged.lock() {
        p.clear();
        p.shrink_to_fit();
    }
    report.commit_seconds += tc.elapsed().as_secs_f64();
    Ok(())
}
