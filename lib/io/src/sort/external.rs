//! The external Morton sort, for datasets larger than the memory budget.
//!
//! Pass 1 reads the dataset in blocks of about a quarter of the budget and partitions each block
//! by the top 10 bits of the Morton code (a stable counting sort) into one run file per block.
//! Pass 2 takes the buckets in code order: a bucket that fits the budget is read from every run,
//! sorted in memory ([`super::memory`]) and emitted; a larger one (skewed data) is partitioned again
//! on the next 10 bits. Ties keep input order (runs are read in order, partitions are stable), so
//! the output equals the in-memory sort's. Temporary files live in one directory that is removed
//! on success, on error and on Ctrl-C ([`crate::cleanup`]).
//!
//! The Morton grid is defined by the points' actual bounds. Pass 1 uses the bounds the headers
//! declare; if the points disagree with them, pass 1 runs again with the real ones.

use super::memory::{
    declared_grid, emit, in_memory_need, make_keys, refine_ties, sort_keys, OrderedSink,
    PieceStats, SortOptions, SortReport,
};
use crate::cleanup::{check_interrupted, TempPath};
use crate::dataset::Dataset;
use crate::error::{Error, Result};
use mortar_core::layout::read_xyz;
use mortar_core::morton::MortonGrid;
use rayon::prelude::*;
use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

const BUCKET_BITS: u32 = 10;
const BUCKETS: usize = 1 << BUCKET_BITS;
const CODE_BITS: u32 = 63;
const MAX_LEVEL: u32 = CODE_BITS / BUCKET_BITS;

/// One run file: its records grouped by bucket.
struct Run {
    path: PathBuf,
    /// (byte offset, record count) per bucket.
    segments: Vec<(u64, u64)>,
}

fn bucket_of(code: u64, level: u32) -> usize {
    let top = CODE_BITS as i64 - (BUCKET_BITS * (level + 1)) as i64;
    if top >= 0 {
        ((code >> top) as usize) & (BUCKETS - 1)
    } else {
        ((code << (-top)) as usize) & (BUCKETS - 1)
    }
}

/// Partitions one block of records into a new run file.
fn write_run(
    block: &[u8],
    record_len: usize,
    level: u32,
    morton: &MortonGrid,
    dir: &Path,
    n: usize,
) -> Result<Run> {
    let count = block.len() / record_len;
    let buckets: Vec<u16> = block
        .par_chunks_exact(record_len)
        .map(|r| {
            let p = read_xyz(r);
            bucket_of(morton.code([p[0] as i64, p[1] as i64, p[2] as i64]), level) as u16
        })
        .collect();
    let mut starts = vec![0usize; BUCKETS + 1];
    for &b in &buckets {
        starts[b as usize + 1] += 1;
    }
    for b in 0..BUCKETS {
        starts[b + 1] += starts[b];
    }
    let mut out = vec![0u8; block.len()];
    let mut cur = starts.clone();
    for (i, &b) in buckets.iter().enumerate() {
        let d = cur[b as usize];
        out[d * record_len..(d + 1) * record_len]
            .copy_from_slice(&block[i * record_len..(i + 1) * record_len]);
        cur[b as usize] += 1;
    }
    debug_assert_eq!(cur[BUCKETS - 1], count);
    let path = dir.join(format!("run-{level}-{n}.bin"));
    let mut f =
        std::io::BufWriter::new(std::fs::File::create(&path).map_err(|e| Error::io(&path, e))?);
    f.write_all(&out).map_err(|e| Error::io(&path, e))?;
    f.flush().map_err(|e| Error::io(&path, e))?;
    let segments = (0..BUCKETS)
        .map(|b| ((starts[b] * record_len) as u64, (starts[b + 1] - starts[b]) as u64))
        .collect();
    Ok(Run { path, segments })
}

fn read_segment(
    run: &Run,
    bucket: usize,
    record_len: usize,
    from: u64,
    count: u64,
) -> Result<Vec<u8>> {
    let (off, _) = run.segments[bucket];
    let mut buf = vec![0u8; (count as usize) * record_len];
    let f = std::fs::File::open(&run.path).map_err(|e| Error::io(&run.path, e))?;
    f.read_exact_at(&mut buf, off + from * record_len as u64)
        .map_err(|e| Error::io(&run.path, e))?;
    Ok(buf)
}

/// Pass 1 over the dataset: statistics and level-0 runs.
fn pass1(
    ds: &Dataset,
    opts: &SortOptions,
    morton: &MortonGrid,
    dir: &Path,
) -> Result<(Vec<Run>, PieceStats)> {
    let rl = ds.layout.record_len;
    let block_bytes = (opts.memory / 4).max(rl as u64) as usize;
    let pieces = ds.pieces();
    let mut runs = Vec::new();
    let mut stats = PieceStats::default();
    let mut i = 0;
    while i < pieces.len() {
        check_interrupted()?;
        let mut j = i;
        let mut bytes = 0usize;
        while j < pieces.len()
            && (j == i || bytes + pieces[j].piece.points as usize * rl <= block_bytes)
        {
            bytes += pieces[j].piece.points as usize * rl;
            j += 1;
        }
        let group = &pieces[i..j];
        let decoded: Vec<(Vec<u8>, PieceStats)> = group
            .par_iter()
            .map(|p| {
                let r = ds.read_piece(p)?;
                let s = PieceStats::of(&r, &ds.layout);
                let v = r.into_owned();
                ds.inputs[p.input].release_piece(&p.piece);
                Ok((v, s))
            })
            .collect::<Result<Vec<_>>>()?;
        let mut block = Vec::with_capacity(decoded.iter().map(|d| d.0.len()).sum());
        for (v, s) in decoded {
            block.extend_from_slice(&v);
            stats.merge(&s);
        }
        runs.push(write_run(&block, rl, 0, morton, dir, runs.len())?);
        i = j;
    }
    Ok((runs, stats))
}

/// Sorts a dataset larger than the memory budget.
pub fn sort_external(
    ds: &Dataset,
    opts: &SortOptions,
    sink: &mut dyn OrderedSink,
) -> Result<SortReport> {
    let rl = ds.layout.record_len;
    std::fs::create_dir_all(&opts.tmp_dir).map_err(|e| Error::io(&opts.tmp_dir, e))?;
    let tmp = TempPath::dir_in(&opts.tmp_dir, "sort").map_err(|e| Error::io(&opts.tmp_dir, e))?;
    let guess = declared_grid(ds);
    ds.progress.stage("reading", ds.declared_points(), "points");
    let (mut runs, stats) = pass1(ds, opts, &guess, tmp.path())?;
    let summary = stats.summary();
    if summary.morton != guess && summary.count > 0 {
        // The headers' bounds were not the points' bounds: partition again on the real grid.
        for r in &runs {
            let _ = std::fs::remove_file(&r.path);
        }
        ds.progress.stage(
            "reading again (the headers' bounds are wrong)",
            ds.declared_points(),
            "points",
        );
        runs = pass1(ds, opts, &summary.morton, tmp.path())?.0;
    }
    ds.progress.stage("writing", summary.count, "points");
    let mut sink = super::memory::Counted { sink, progress: &ds.progress, record_len: rl };
    sink.begin(&summary)?;
    let mut buckets = 0;
    drain(&runs, 0, &summary.morton, rl, opts, tmp.path(), &mut sink, &mut buckets)?;
    drop(tmp);
    Ok(SortReport { summary, external: true, buckets })
}

#[allow(clippy::too_many_arguments)]
fn drain(
    runs: &[Run],
    level: u32,
    morton: &MortonGrid,
    rl: usize,
    opts: &SortOptions,
    dir: &Path,
    sink: &mut dyn OrderedSink,
    buckets_done: &mut usize,
) -> Result<()> {
    for b in 0..BUCKETS {
        check_interrupted()?;
        let total: u64 = runs.iter().map(|r| r.segments[b].1).sum();
        if total == 0 {
            continue;
        }
        if in_memory_need(total, rl, opts.chunk_points) <= opts.memory || level >= MAX_LEVEL {
            let slabs: Vec<Vec<u8>> = runs
                .iter()
                .filter(|r| r.segments[b].1 > 0)
                .map(|r| read_segment(r, b, rl, 0, r.segments[b].1))
                .collect::<Result<Vec<_>>>()?;
            let refs: Vec<&[u8]> = slabs.iter().map(|s| s.as_slice()).collect();
            let mut keys = sort_keys(make_keys(&refs, rl, morton)?);
            refine_ties(&mut keys, &refs, rl, morton);
            emit(&refs, &keys, rl, opts.chunk_points, sink)?;
            *buckets_done += 1;
        } else {
            // Skewed bucket: partition it again on the next bits, block by block.
            let block_points = ((opts.memory / 4) as usize / rl).max(1) as u64;
            let mut sub = Vec::new();
            for r in runs {
                let (_, n) = r.segments[b];
                let mut from = 0;
                while from < n {
                    let take = block_points.min(n - from);
                    let block = read_segment(r, b, rl, from, take)?;
                    sub.push(write_run(
                        &block,
                        rl,
                        level + 1,
                        morton,
                        dir,
                        *buckets_done * 1_000_000 + sub.len(),
                    )?);
                    from += take;
                }
            }
            drain(&sub, level + 1, morton, rl, opts, dir, sink, buckets_done)?;
            for s in &sub {
                let _ = std::fs::remove_file(&s.path);
            }
        }
    }
    Ok(())
}
