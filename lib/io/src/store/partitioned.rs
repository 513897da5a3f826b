//! The partitioned engine of `mortar build`: the sorted engine for inputs larger than
//! `--memory` (ARCHITECTURE.md, "The build engine").
//!
//! 1. Partition: every piece is read once (LAZ decoded once, groups of pieces in parallel) and
//!    its records, each with its arrival number, are scattered by the Morton cell that holds
//!    them at depth `D` of the root (at most 8^5 cells) into run files, one per group of about a
//!    quarter of the budget, each with a table of where every cell begins. The cells' counts
//!    make a histogram of the whole input.
//! 2. Build: the tree's top is walked depth first from the root. A node whose points fit the
//!    budget for one unit (or a cell of depth `D`) is a unit: its cells are read back from
//!    every run (one contiguous range per run), sorted as the sorted engine sorts, and built by
//!    [`build_subtree`]; its nodes are written at once, and it hands its parent the earliest
//!    point per cell of the parent's grid. A node above the units is inner (it holds more
//!    points than a unit, hence more than a leaf), and its voxels are its children's candidates
//!    end to end, reduced by eight for its own parent ([`earliest_in_parent_cells`]).
//! 3. The entries are put in the sorted engine's order (level by level, Morton order in a
//!    level) and committed once.
//!
//! The tree is the one the sorted engine makes (a subtree depends on the points in its cube
//! alone; `tests/build_engine.rs` compares them node by node). A cell of depth `D` holding more
//! points than a unit may is partitioned again, or is a leaf read in slices (`dense.rs`).
//!
//! Resume: the run files, a manifest of the partition (with a checksum of every run) and a log
//! of finished visits (each node's entry and payload checksum, the points it added and its
//! candidates, each record checksummed) live in `.partition/` inside the store until the build
//! ends. Nothing is synced before the final commit: after kill -9 the page cache holds it all;
//! after a power loss whatever did not reach the disk fails its checksum. `--resume` skips pass 1
//! when the manifest and every run check out, keeps the log's records up to the first one whose
//! record or payloads do not, cuts `nodes.bin` after them and walks again, taking logged visits
//! from the log: the store is the uninterrupted one byte for byte. Not done yet:
//! commits while it builds (a reader sees the store at the end only), and units built in
//! parallel with one another (each unit's tree and encoding are parallel inside).

use super::dense::{self, Level};
use super::engine::{grid_of, histogram, sort_records, Sorted, BUCKET_BITS};
use super::format::*;
use super::options::{BuildOptions, BuildProgress, BuildReport, BuiltBy};
use super::runs::{Cands, Run};
use super::writer::*;
use crate::dataset::Dataset;
use crate::error::{Error, Result};
use crate::sort::{self, PieceStats};
use mortar_core::color::{ColorSource, RgbDepth};
use mortar_core::layout::read_xyz;
use mortar_core::morton::MortonGrid;
use mortar_core::octree::{
    build_subtree, splits, Cube, NodeKey, SortedContent, MIN_INNER_SIZE_LOG2,
};
use rayon::prelude::*;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Deepest level of the cells the records are partitioned by (8^5 = 32,768 cells).
const MAX_CELL_DEPTH: u8 = 5;

/// The directory inside the store that holds the partition until the build ends.
pub(crate) const STATE_DIR: &str = ".partition";
const MANIFEST: &str = "manifest.json";
const TABLES: &str = "tables.bin";
const LOG: &str = "done.bin";
const LOG_MAGIC: u32 = 0x4d50_4c47;

/// Whether the store `dir` holds the state a partitioned build can resume from.
pub(crate) fn has_state(dir: &Path) -> bool {
    dir.join(STATE_DIR).join(MANIFEST).is_file()
}

/// What pass 1 found, kept in the manifest for `--resume`.
pub(crate) struct Partition {
    pub root: Cube,
    pub runs: Vec<Run>,
    pub hist: Vec<u64>,
    pub all: PieceStats,
    pub warnings: Vec<String>,
    /// The `base` of a stretched grid ([`partition_all`]); zeros for builds.
    pub base: [i64; 3],
}

/// Writes the manifest (the tables first, then the JSON by rename) once the runs are synced.
fn write_manifest(state: &Path, p: &Partition) -> Result<()> {
    let tp = state.join(TABLES);
    let mut t: Vec<u64> = p.hist.clone();
    for r in &p.runs {
        t.extend_from_slice(&r.starts);
    }
    let tables = bytemuck::cast_slice::<u64, u8>(&t);
    std::fs::write(&tp, tables).map_err(|e| Error::io(&tp, e))?;
    let j = serde_json::json!({
        "root_min": p.root.min,
        "root_size_log2": p.root.size_log2,
        "cells": p.hist.len(),
        "runs": p.runs.iter().map(|r| r.path.file_name().map(|n| n.to_string_lossy().to_string())).collect::<Vec<_>>(),
        "run_checksums": p.runs.iter().map(|r| r.hash).collect::<Vec<_>>(),
        "tables_checksum": checksum(tables),
        "checksum": manifest_sum(p, checksum(tables)),
        "count": p.all.count,
        "min": p.all.min,
        "max": p.all.max,
        "max_rgb": p.all.max_rgb,
        "max_intensity": p.all.max_intensity,
        "warnings": p.warnings,
    });
    let mp = state.join(MANIFEST);
    let tmp = state.join(format!("{MANIFEST}.tmp"));
    std::fs::write(&tmp, serde_json::to_vec_pretty(&j).unwrap_or_default())
        .map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, &mp).map_err(|e| Error::io(&mp, e))?;
    Ok(())
}

/// A checksum of what the manifest says (its JSON is checked field by field against it).
fn manifest_sum(p: &Partition, tables: u64) -> u64 {
    let names: Vec<String> = p
        .runs
        .iter()
        .map(|r| r.path.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default())
        .collect();
    let hashes: Vec<u64> = p.runs.iter().map(|r| r.hash).collect();
    let a = &p.all;
    let text = format!(
        "{:?} {} {} {names:?} {hashes:?} {} {:?} {:?} {} {} {tables} {:?}",
        p.root.min,
        p.root.size_log2,
        p.hist.len(),
        a.count,
        a.min,
        a.max,
        a.max_rgb,
        a.max_intensity,
        p.warnings
    );
    checksum(text.as_bytes())
}

/// The manifest of a stopped build, if it is whole and its run files are all there.
fn read_manifest(state: &Path, rl: usize) -> Option<Partition> {
    let j: serde_json::Value =
        serde_json::from_slice(&std::fs::read(state.join(MANIFEST)).ok()?).ok()?;
    let arr3 = |v: &serde_json::Value| -> Option<[i64; 3]> {
        Some([v.get(0)?.as_i64()?, v.get(1)?.as_i64()?, v.get(2)?.as_i64()?])
    };
    let root = Cube { min: arr3(&j["root_min"])?, size_log2: j["root_size_log2"].as_u64()? as u8 };
    let cells = j["cells"].as_u64()? as usize;
    let names: Vec<String> = j["runs"]
        .as_array()?
        .iter()
        .map(|v| v.as_str().map(str::to_string))
        .collect::<Option<_>>()?;
    let hashes: Vec<u64> =
        j["run_checksums"].as_array()?.iter().map(|v| v.as_u64()).collect::<Option<_>>()?;
    if hashes.len() != names.len() {
        return None;
    }
    let t = std::fs::read(state.join(TABLES)).ok()?;
    let want =
        cells.checked_add(names.len().checked_mul(cells.checked_add(1)?)?)?.checked_mul(8)?;
    if t.len() != want
        || checksum(&t) != j["tables_checksum"].as_u64()?
        || cells == 0
        || !cells.is_power_of_two()
    {
        return None;
    }
    let t: Vec<u64> =
        t.chunks_exact(8).map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes"))).collect();
    let hist = t[..cells].to_vec();
    let mut runs = Vec::new();
    if names.iter().any(|n| !(n.starts_with("run-") && n.ends_with(".bin")) || n.contains('/')) {
        return None;
    }
    for (k, name) in names.iter().enumerate() {
        let starts = t[cells + k * (cells + 1)..cells + (k + 1) * (cells + 1)].to_vec();
        if starts[0] != 0 || starts.windows(2).any(|w| w[0] > w[1]) {
            return None;
        }
        let path = state.join(name);
        let len = std::fs::metadata(&path).ok()?.len();
        if len != *starts.last()? * (rl as u64 + 8) {
            return None;
        }
        runs.push(Run { path, starts, hash: hashes[k] });
    }
    // The cells' counts are the runs' counts summed.
    if (0..cells)
        .any(|c| runs.iter().map(|r| r.starts[c + 1] - r.starts[c]).sum::<u64>() != hist[c])
    {
        return None;
    }
    // Every run as it was written (a power loss may have kept the sizes but not the bytes).
    let whole =
        runs.par_iter().all(|r| std::fs::read(&r.path).is_ok_and(|b| checksum(&b) == r.hash));
    if !whole {
        return None;
    }
    let i32x3 =
        |v: &serde_json::Value| -> Option<[i32; 3]> { arr3(v).map(|a| a.map(|x| x as i32)) };
    let all = PieceStats {
        count: j["count"].as_u64()?,
        min: i32x3(&j["min"])?,
        max: i32x3(&j["max"])?,
        max_rgb: j["max_rgb"].as_u64()? as u16,
        max_intensity: j["max_intensity"].as_u64()? as u16,
        ..PieceStats::default()
    };
    let warnings =
        j["warnings"].as_array()?.iter().filter_map(|w| w.as_str().map(str::to_string)).collect();
    let p = Partition { root, runs, hist, all, warnings, base: [0; 3] };
    (manifest_sum(&p, j["tables_checksum"].as_u64()?) == j["checksum"].as_u64()?).then_some(p)
}

/// A finished visit as the log keeps it.
struct Logged {
    seq_after: u64,
    cands: Cands,
}

fn fnv(b: &[u8]) -> u64 {
    b.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &x| (h ^ x as u64).wrapping_mul(0x100_0000_01b3))
}

/// One log record: the visit's key, where the walk stood after it, its nodes and candidates.
#[allow(clippy::too_many_arguments)]
fn log_record(
    key: NodeKey,
    seq_after: u64,
    points: u64,
    nodes_end: u64,
    entries: &[(u32, u64, NodeEntry)],
    hashes: &[u64],
    cands: &Cands,
    rl: usize,
) -> Vec<u8> {
    let mut b = Vec::new();
    for v in [
        LOG_MAGIC,
        key.level as u32,
        key.index[0],
        key.index[1],
        key.index[2],
        entries.len() as u32,
        cands.pos.len() as u32,
    ] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    for v in [seq_after, points, nodes_end] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    for ((_, seq, e), h) in entries.iter().zip(hashes) {
        b.extend_from_slice(&seq.to_le_bytes());
        b.extend_from_slice(&h.to_le_bytes());
        b.extend_from_slice(bytemuck::bytes_of(e));
    }
    for i in 0..cands.pos.len() {
        for a in cands.pos[i] {
            b.extend_from_slice(&a.to_le_bytes());
        }
        b.extend_from_slice(&cands.arrival[i].to_le_bytes());
        b.extend_from_slice(&cands.records[i * rl..(i + 1) * rl]);
    }
    let h = fnv(&b);
    b.extend_from_slice(&h.to_le_bytes());
    b
}

/// What a stopped walk left: the visits by key, every logged entry with its payload checksum,
/// the points they added, and where `nodes.bin` ended after the last one.
type LogState = (
    std::collections::HashMap<(u32, [u32; 3]), Logged>,
    Vec<(u32, u64, NodeEntry)>,
    Vec<u64>,
    u64,
    u64,
);

/// The log's records up to the first that is not whole or whose payloads in `nodes` are not
/// what it wrote; the log is cut after them.
fn read_log(path: &Path, nodes: &Path, rl: usize) -> Result<LogState> {
    let b = std::fs::read(path).unwrap_or_default();
    let mut visits = std::collections::HashMap::new();
    let (mut entries, mut hashes, mut points, mut end, mut at) =
        (Vec::new(), Vec::new(), 0u64, 0u64, 0usize);
    let nf = std::fs::File::open(nodes).ok();
    let payload_ok = |e: &NodeEntry, h: u64| -> bool {
        use std::os::unix::fs::FileExt;
        let Some(f) = &nf else { return false };
        let mut buf = vec![0u8; e.length as usize];
        f.read_exact_at(&mut buf, e.offset).is_ok() && checksum(&buf) == h
    };
    let es = std::mem::size_of::<NodeEntry>();
    let u32_at = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().expect("4 bytes"));
    let u64_at = |o: usize| u64::from_le_bytes(b[o..o + 8].try_into().expect("8 bytes"));
    while b.len() >= at + 52 {
        if u32_at(at) != LOG_MAGIC {
            break;
        }
        let (ne, nc) = (u32_at(at + 20) as usize, u32_at(at + 24) as usize);
        let len = 52 + ne * (16 + es) + nc * (20 + rl);
        if b.len() < at + len + 8 || fnv(&b[at..at + len]) != u64_at(at + len) {
            break;
        }
        let key = (u32_at(at + 4), [u32_at(at + 8), u32_at(at + 12), u32_at(at + 16)]);
        let (seq_after, p, nodes_end) = (u64_at(at + 28), u64_at(at + 36), u64_at(at + 44));
        let mut o = at + 52;
        let mut these = Vec::with_capacity(ne);
        for _ in 0..ne {
            let (seq, h) = (u64_at(o), u64_at(o + 8));
            let e: NodeEntry = bytemuck::pod_read_unaligned(&b[o + 16..o + 16 + es]);
            these.push((e.level, seq, e, h));
            o += 16 + es;
        }
        if !these.par_iter().all(|(_, _, e, h)| payload_ok(e, *h)) {
            break;
        }
        for (l, seq, e, h) in these {
            entries.push((l, seq, e));
            hashes.push(h);
        }
        let mut cands = Cands::default();
        for _ in 0..nc {
            let q = [0, 1, 2].map(|a| {
                i32::from_le_bytes(b[o + 4 * a..o + 4 * a + 4].try_into().expect("4 bytes"))
            });
            cands.push(q, u64_at(o + 12), &b[o + 20..o + 20 + rl]);
            o += 20 + rl;
        }
        visits.insert(key, Logged { seq_after, cands });
        points += p;
        end = nodes_end;
        at += len + 8;
    }
    if at < b.len() {
        let f =
            std::fs::OpenOptions::new().write(true).open(path).map_err(|e| Error::io(path, e))?;
        f.set_len(at as u64).map_err(|e| Error::io(path, e))?;
    }
    Ok((visits, entries, hashes, points, end))
}

/// A fast 64-bit checksum (8 bytes per step), in parallel over 1 MiB blocks for large inputs.
/// [`checksum`] of the `len` bytes of `nodes.bin` at `off` (a payload written in slices), read
/// back a block at a time.
fn checksum_at(w: &StoreWriter, off: u64, len: u64) -> Result<u64> {
    use std::os::unix::fs::FileExt;
    let path = w.dir.join(NODES_FILE);
    let read = |at: u64, n: usize| -> Result<Vec<u8>> {
        let mut b = vec![0u8; n];
        w.reader.read_exact_at(&mut b, off + at).map_err(|e| Error::io(&path, e))?;
        Ok(b)
    };
    if len <= 1 << 20 {
        return Ok(checksum(&read(0, len as usize)?));
    }
    let parts: Vec<u64> = (0..len.div_ceil(1 << 20))
        .into_par_iter()
        .map(|k| Ok(checksum_block(&read(k << 20, ((len - (k << 20)).min(1 << 20)) as usize)?)))
        .collect::<Result<_>>()?;
    Ok(checksum_block(bytemuck::cast_slice(&parts)))
}

fn checksum_block(b: &[u8]) -> u64 {
    let mut h = 0x243f_6a88_85a3_08d3u64 ^ b.len() as u64;
    let mut words = b.chunks_exact(8);
    for w in &mut words {
        h = (h ^ u64::from_le_bytes(w.try_into().expect("8 bytes")))
            .wrapping_mul(0x9e37_79b9_7f4a_7c15)
            .rotate_left(29);
    }
    for &x in words.remainder() {
        h = (h ^ x as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15).rotate_left(29);
    }
    h
}

fn checksum(b: &[u8]) -> u64 {
    if b.len() <= 1 << 20 {
        return checksum_block(b);
    }
    let parts: Vec<u64> = b.par_chunks(1 << 20).map(checksum_block).collect();
    checksum_block(bytemuck::cast_slice(&parts))
}

/// Bytes per point of a unit held in memory: the entry read back (record + 8), the sorted copy
/// (record + 8), and the sort's keys and scratch (32).
pub(crate) fn unit_bytes_per_point(rl: u64) -> u64 {
    2 * (rl + 8) + 32
}

/// The depth of the partition cells for `root`: cells must still be able to split (so that
/// every node above them is inner when it holds more than a unit).
pub(crate) fn cell_depth(root: Cube, max_level: u8) -> u8 {
    let room = root.size_log2.saturating_sub(MIN_INNER_SIZE_LOG2);
    MAX_CELL_DEPTH.min(room).min(max_level).min(mortar_core::morton::BITS_PER_AXIS as u8)
}

/// Builds the store in `writer` from `ds` (a cell denser than a unit: [`dense`]).
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
    let part = match kept {
        Some(p) => p,
        None => {
            let _ = std::fs::remove_dir_all(&state);
            std::fs::create_dir_all(&state).map_err(|e| Error::io(&state, e))?;
            let p = partition_all(ds, opts.memory, opts.config.max_level, [1; 3], header, &state)?;
            write_manifest(&state, &p)?;
            p
        }
    };
    let Partition { root, runs, hist, all, warnings, .. } = part;
    report.warnings = warnings;
    report.read_seconds = tr.elapsed().as_secs_f64();
    crate::cleanup::trace("partitioned", t0);
    let (lo, hi) = if all.count == 0 { ([0; 3], [0; 3]) } else { (all.min, all.max) };
    let unit_points = ((opts.memory / 2) / unit_bytes_per_point(rl as u64))
        .max(opts.config.leaf_capacity as u64 + 1);
    // A resumed walk: what the log holds is taken as it is; nodes.bin is cut after it.
    let log_path = state.join(LOG);
    let (replay, logged, logged_hashes, logged_points, nodes_end) = if resumed {
        read_log(&log_path, &writer.dir.join(NODES_FILE), rl)?
    } else {
        Default::default()
    };
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
    };
    w.visit(&lv, NodeKey::ROOT, root, 0, 0..cells)?;
    let Walk { mut entries, points, .. } = w;
    // The sorted engine's order: level by level, depth-first (= Morton) order in a level.
    entries.sort_by_key(|&(level, seq, _)| (level, seq));
    for (i, (_, _, e)) in entries.iter().enumerate() {
        writer.set_entry(i, *e);
    }
    let tc = Instant::now();
    writer.write_hierarchy(root, points, opts.config.leaf_capacity, (lo, hi))?;
    report.commit_seconds += tc.elapsed().as_secs_f64();
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

/// Pass 1 with the root the sorted engine takes (the headers' box when it holds every point,
/// else the points' own box: then a second pass). With `stretch` other than `[1; 3]` (the
/// export of axes with different scales) the records in the runs are on the stretched grid
/// `(p - base) * stretch` with `base` the points' smallest position, and the root is the
/// points' own box on it.
pub(crate) fn partition_all(
    ds: &Dataset,
    memory: u64,
    max_level: u8,
    stretch: [i64; 3],
    header: Option<([i32; 3], [i32; 3])>,
    state: &Path,
) -> Result<Partition> {
    let rl = ds.layout.record_len;
    let total = ds.declared_points();
    let stretched = stretch != [1; 3];
    let guess = match header {
        Some((l, h)) if stretched => (
            Grid { base: l.map(|v| v as i64), m: stretch },
            Cube::covering(
                [0; 3],
                [0, 1, 2].map(|a| Grid::clamp((h[a] as i64 - l[a] as i64) * stretch[a])),
            ),
        ),
        Some((l, h)) => (Grid::IDENTITY, Cube::covering(l, h)),
        None if stretched => {
            (Grid { base: [0; 3], m: stretch }, Cube { min: [0; 3], size_log2: 32 })
        }
        None => (Grid::IDENTITY, Cube { min: [0; 3], size_log2: 32 }),
    };
    let block_bytes = ((memory / 4).max(rl as u64 * 4096)) as usize;
    ds.progress.stage("partitioning", total, "points");
    let (mut runs, mut hist, all, real) =
        partition(ds, guess.1, guess.0, max_level, block_bytes, state, None)?;
    let mut warnings = Vec::new();
    for (src, st) in ds.inputs.iter().zip(&real) {
        if let Some(w) = super::bounds::bounds_warning(ds, src.as_ref(), st) {
            warnings.push(w);
        }
    }
    let (lo, hi) = if all.count == 0 { ([0; 3], [0; 3]) } else { (all.min, all.max) };
    let (grid, root) = if stretched {
        let mut t = [0i32; 3];
        for a in 0..3 {
            let v = (hi[a] as i64 - lo[a] as i64) * stretch[a];
            if v >= i32::MAX as i64 {
                return Err(Error::ScalesDiffer {
                    path: ds.inputs[0].path().to_path_buf(),
                    scale: ds.grid.scale,
                    axis: a,
                });
            }
            t[a] = v as i32;
        }
        (Grid { base: lo.map(|v| v as i64), m: stretch }, Cube::covering([0; 3], t))
    } else {
        let root = match header {
            Some((l, h)) if all.count > 0 && (0..3).all(|a| l[a] <= lo[a] && hi[a] <= h[a]) => {
                Cube::covering(l, h)
            }
            _ => Cube::covering(lo, hi),
        };
        (Grid::IDENTITY, root)
    };
    if root != guess.1 || grid != guess.0 {
        // The headers lie (or say nothing): partition again on the points' own root.
        for r in &runs {
            let _ = std::fs::remove_file(&r.path);
        }
        ds.progress.stage("partitioning again (the headers' bounds are wrong)", total, "points");
        (runs, hist, _, _) = partition(ds, root, grid, max_level, block_bytes, state, None)?;
    }
    Ok(Partition { root, runs, hist, all, warnings, base: grid.base })
}

/// The integer grid the runs hold positions on: `(p - base) * m` per axis (the identity for
/// builds; exports of axes with different scales stretch them to cubic cells).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Grid {
    base: [i64; 3],
    m: [i64; 3],
}

impl Grid {
    const IDENTITY: Grid = Grid { base: [0; 3], m: [1; 3] };
    fn is_identity(&self) -> bool {
        *self == Self::IDENTITY
    }
    fn clamp(v: i64) -> i32 {
        v.clamp(i32::MIN as i64, i32::MAX as i64) as i32
    }
    #[inline]
    fn apply(&self, p: [i32; 3]) -> [i32; 3] {
        if self.is_identity() {
            return p;
        }
        [0, 1, 2].map(|a| Self::clamp((p[a] as i64 - self.base[a]) * self.m[a]))
    }
}

/// The cell (at depth `depth` of `root`) of a record, from its code on the root's grid.
#[inline]
fn cell_of(q: [i32; 3], g: &MortonGrid, root: Cube, depth: u8) -> usize {
    let high = 3 * (root.size_log2 as u32).min(mortar_core::morton::BITS_PER_AXIS);
    let code = g.code([q[0] as i64, q[1] as i64, q[2] as i64]);
    ((code >> (high - 3 * depth as u32)) as usize).min((1usize << (3 * depth as u32)) - 1)
}

/// Pass 1: reads every piece once and writes the run files; the cells' counts, the statistics
/// of all points and of each input.
fn partition(
    ds: &Dataset,
    root: Cube,
    grid: Grid,
    max_level: u8,
    block_bytes: usize,
    dir: &Path,
    filter: Option<&Filter>,
) -> Result<Partitioned> {
    let rl = ds.layout.record_len;
    let el = rl + 8;
    let depth = cell_depth(root, max_level);
    let cells = 1usize << (3 * depth as u32);
    let g = grid_of(root);
    // The pieces read (all, or those a filter keeps), each with its number in the dataset: the
    // arrival numbers are those of a build that reads every piece.
    let pieces: Vec<(usize, crate::dataset::DatasetPiece)> = ds
        .pieces()
        .into_iter()
        .enumerate()
        .filter(|(k, _)| filter.is_none_or(|f| f.pieces[*k]))
        .collect();
    let wanted = |c: usize| filter.is_none_or(|f| f.cells[c]);
    let mut runs = Vec::new();
    let mut hist = vec![0u64; cells];
    let mut all = PieceStats::default();
    let mut real = vec![PieceStats::default(); ds.inputs.len()];
    let mut i = 0;
    while i < pieces.len() {
        crate::cleanup::check_interrupted()?;
        let mut j = i;
        let mut bytes = 0usize;
        while j < pieces.len()
            && (j == i || bytes + pieces[j].1.piece.points as usize * rl <= block_bytes)
        {
            bytes += pieces[j].1.piece.points as usize * rl;
            j += 1;
        }
        // Decoded (or borrowed) in parallel, with the counts per cell made while in cache.
        let group: Vec<(std::borrow::Cow<'_, [u8]>, PieceStats, Vec<u32>)> = (i..j)
            .into_par_iter()
            .map(|k| {
                let p = &pieces[k].1;
                let slab = ds.read_piece(p)?;
                if slab.len() as u64 != p.piece.points * rl as u64 {
                    return Err(Error::PieceCount {
                        path: ds.inputs[p.input].path().to_path_buf(),
                        piece: p.piece.index,
                    });
                }
                let mut h = vec![0u32; cells];
                for r in slab.chunks_exact(rl) {
                    let c = cell_of(grid.apply(read_xyz(r)), &g, root, depth);
                    if wanted(c) {
                        h[c] += 1;
                    }
                }
                let st = PieceStats::of(&slab, &ds.layout);
                Ok((slab, st, h))
            })
            .collect::<Result<_>>()?;
        let mut starts = vec![0u64; cells + 1];
        for c in 0..cells {
            starts[c + 1] = starts[c] + group.iter().map(|(_, _, h)| h[c] as u64).sum::<u64>();
        }
        let n = starts[cells] as usize;
        let mut cursors: Vec<Vec<usize>> = Vec::with_capacity(group.len());
        let mut running: Vec<usize> = starts[..cells].iter().map(|&s| s as usize).collect();
        for (_, _, h) in &group {
            cursors.push(running.clone());
            for c in 0..cells {
                running[c] += h[c] as usize;
            }
        }
        let mut buf = sort::zeroed_huge::<u8>(n * el);
        {
            let bp = mortar_core::par::SendPtr(buf.as_mut_ptr());
            group.par_iter().zip(cursors.into_par_iter()).enumerate().for_each(
                |(k, ((slab, _, _), mut cur))| {
                    let bp = &bp;
                    let piece = pieces[i + k].0 as u64;
                    for (x, r) in slab.chunks_exact(rl).enumerate() {
                        let q = grid.apply(read_xyz(r));
                        let c = cell_of(q, &g, root, depth);
                        if !wanted(c) {
                            continue;
                        }
                        let at = cur[c];
                        cur[c] += 1;
                        // SAFETY: the cursors of all pieces partition 0..n; each slot is written once.
                        unsafe {
                            std::ptr::copy_nonoverlapping(r.as_ptr(), bp.0.add(at * rl), rl);
                            if !grid.is_identity() {
                                let q = q.map(i32::to_le_bytes);
                                for (a, b) in q.iter().enumerate() {
                                    std::ptr::copy_nonoverlapping(
                                        b.as_ptr(),
                                        bp.0.add(at * rl + 4 * a),
                                        4,
                                    );
                                }
                            }
                            std::ptr::copy_nonoverlapping(
                                (piece << 32 | x as u64).to_ne_bytes().as_ptr(),
                                bp.0.add(n * rl + at * 8),
                                8,
                            );
                        }
                    }
                },
            );
        }
        for (k, (_, st, h)) in group.iter().enumerate() {
            all.merge(st);
            real[pieces[i + k].1.input].merge(st);
            for c in 0..cells {
                hist[c] += h[c] as u64;
            }
        }
        for (_, p) in &pieces[i..j] {
            ds.inputs[p.input].release_piece(&p.piece);
        }
        drop(group);
        let path = dir.join(format!("run-{}.bin", runs.len()));
        let mut f = std::io::BufWriter::with_capacity(
            8 << 20,
            std::fs::File::create(&path).map_err(|e| Error::io(&path, e))?,
        );
        f.write_all(&buf).map_err(|e| Error::io(&path, e))?;
        f.flush().map_err(|e| Error::io(&path, e))?;
        let hash = checksum(&buf);
        runs.push(Run { path, starts, hash });
        i = j;
    }
    Ok((runs, hist, all, real))
}

/// The depth-first walk over the tree's top (pass 2).
struct Walk<'a, 'w> {
    ds: &'a Dataset,
    writer: &'w mut StoreWriter,
    opts: &'a BuildOptions,
    root: Cube,
    unit_points: u64,
    color: ColorSource,
    rl: usize,
    /// (level, depth-first number, entry) of every node written.
    entries: Vec<(u32, u64, NodeEntry)>,
    seq: u64,
    points: u64,
    report: &'a mut BuildReport,
    /// Visits a stopped build finished, by key (`--resume`).
    replay: std::collections::HashMap<(u32, [u32; 3]), Logged>,
    /// The log of finished visits.
    log: std::fs::File,
    log_path: PathBuf,
    /// [`checksum`] of each payload in `entries`.
    hashes: Vec<u64>,
    /// Where finer partitions of dense cells go.
    state: PathBuf,
}

impl Walk<'_, '_> {
    /// Builds the node `key` (cube `cube`, at `depth`, over the cells `cells` of `lv`) and
    /// everything under it; returns its candidates for its parent.
    fn visit(
        &mut self,
        lv: &Level,
        key: NodeKey,
        cube: Cube,
        depth: u8,
        cells: std::ops::Range<usize>,
    ) -> Result<Cands> {
        crate::cleanup::check_interrupted()?;
        if let Some(l) = self.replay.remove(&(key.level as u32, key.index)) {
            self.seq = l.seq_after;
            return Ok(l.cands);
        }
        let count: u64 = lv.hist[cells.clone()].iter().sum();
        if depth == lv.depth || count <= self.unit_points {
            if count > self.unit_points {
                return self.dense(lv, key, cube, cells, count, None);
            }
            let before = self.entries.len();
            let points_before = self.points;
            let out = self.unit(lv, key, cube, cells, count)?;
            self.logged(key, before, self.points - points_before, &out)?;
            return Ok(out);
        }
        // More points than a unit, so more than a leaf, in a cube that may split: inner.
        let step = cells.len() / 8;
        self.inner(key, cube, |w, o| {
            w.visit(
                lv,
                key.child(o),
                cube.child(o),
                depth + 1,
                cells.start + o * step..cells.start + (o + 1) * step,
            )
        })
    }

    /// Builds the inner node `key` (cube `cube`) whose children `kid(o)` builds; returns its
    /// candidates for its parent.
    fn inner(
        &mut self,
        key: NodeKey,
        cube: Cube,
        mut kid: impl FnMut(&mut Self, usize) -> Result<Cands>,
    ) -> Result<Cands> {
        let seq = self.seq;
        self.seq += 1;
        let mut voxels = Cands::default();
        for o in 0..8 {
            let c = kid(self, o)?;
            voxels.append(c);
        }
        let rl = self.rl;
        let color = &self.color;
        let (e, b) = encode_payload(
            key,
            INNER,
            voxels.pos.len(),
            rl - 12,
            |i| voxels.pos[i],
            |i| color.rgba(&voxels.records[i * rl..(i + 1) * rl]),
            |i| &voxels.records[i * rl + 12..(i + 1) * rl],
        )
        .map_err(|error| Error::Payload { path: self.writer.dir.clone(), error })?;
        let before = self.entries.len();
        self.put(seq, e, &b)?;
        let out = voxels.pick(&voxels.for_parent(key, cube), rl);
        if key.level > 0 {
            self.logged(key, before, 0, &out)?;
        }
        Ok(out)
    }

    /// Builds the node `key` over the `count` points of `cells` of `lv`, more than a unit holds
    /// (bounds `known` where known): see [`dense`].
    fn dense(
        &mut self,
        lv: &Level,
        key: NodeKey,
        cube: Cube,
        cells: std::ops::Range<usize>,
        count: u64,
        known: Option<dense::Bounds>,
    ) -> Result<Cands> {
        let rl = self.rl;
        let block = dense::block_points(self.opts.memory, rl);
        let b = match known {
            Some(b) => b,
            None => lv.bounds(&cells, rl, block)?,
        };
        if splits(count, key, cube, &self.opts.config) {
            if let Some(o) = dense::one_octant(cube, b) {
                let c0 = cells.start;
                return self.inner(key, cube, |w, k| {
                    if k == o {
                        w.dense(lv, key.child(o), cube.child(o), cells.clone(), count, Some(b))
                    } else {
                        w.visit(lv, key.child(k), cube.child(k), key.level + 1, c0..c0)
                    }
                });
            }
            let d = dense::tree_split_depth(key, cube, self.opts.config.max_level);
            let sub = dense::split(&lv.runs, cells, rl, cube, key.level, d, block, &self.state)?;
            self.report.dense_cells += 1;
            let n = sub.hist.len();
            return self.visit(&sub, key, cube, key.level, 0..n);
        }
        // A leaf larger than a unit.
        let before = self.entries.len();
        let leaf = dense::big_leaf(
            lv,
            cells,
            count,
            key,
            cube,
            b,
            rl,
            self.unit_points,
            block,
            &self.state,
        )?;
        self.report.large_leaves += 1;
        let seq = self.seq;
        self.seq += 1;
        let tw = Instant::now();
        let attr_len = rl - 12;
        let off = self.writer.reserve(&[payload_len(count, attr_len as u64)])[0];
        let slice = (self.writer.group_bytes / (16 + attr_len as u64)).max(1) as usize;
        let (w, color) = (&*self.writer, &self.color);
        let r = write_payload_blocks(
            key,
            LEAF,
            count as usize,
            attr_len,
            leaf.bounds,
            slice,
            |r| leaf.read(r.start as u64..r.end as u64, false).map(|x| x.0),
            |rec| color.rgba(rec),
            |at, bytes| w.write_at(off + at, bytes),
        )?;
        let mut e = r.map_err(|error| Error::Payload { path: w.dir.clone(), error })?;
        e.offset = off;
        let h = checksum_at(w, off, e.length)?;
        self.entries.push((e.level, seq, e));
        self.hashes.push(h);
        self.points += count;
        self.ds.progress.add(count);
        self.report.write_seconds += tw.elapsed().as_secs_f64();
        let out = leaf.cands;
        self.logged(key, before, count, &out)?;
        Ok(out)
    }

    /// Logs a finished visit (its entries from `before` on). Not synced: see the module docs.
    fn logged(&mut self, key: NodeKey, before: usize, points: u64, out: &Cands) -> Result<()> {
        let rec = log_record(
            key,
            self.seq,
            points,
            self.writer.nodes_len,
            &self.entries[before..],
            &self.hashes[before..],
            out,
            self.rl,
        );
        self.log.write_all(&rec).map_err(|e| Error::io(&self.log_path, e))
    }

    /// Writes one payload at the end of `nodes.bin` and keeps its entry.
    fn put(&mut self, seq: u64, mut e: NodeEntry, bytes: &[u8]) -> Result<()> {
        let off = self.writer.reserve(&[bytes.len() as u64])[0];
        self.writer.write_at(off, bytes)?;
        e.offset = off;
        self.entries.push((e.level, seq, e));
        self.hashes.push(checksum(bytes));
        Ok(())
    }

    /// Reads the points of `cells` back, sorts them and builds their subtree.
    fn unit(
        &mut self,
        lv: &Level,
        key: NodeKey,
        cube: Cube,
        cells: std::ops::Range<usize>,
        count: u64,
    ) -> Result<Cands> {
        let rl = self.rl;
        let n = count as usize;
        let ts = Instant::now();
        let sorted = read_unit(&lv.runs, self.root, key, cells, count, rl, &self.writer.dir)?;
        self.ds.progress.add(count);
        self.report.sort_seconds += ts.elapsed().as_secs_f64();
        let tt = Instant::now();
        let pos = |i: usize| read_xyz(sorted.record(i));
        let arr = |i: usize| sorted.arrival[i];
        let sub = build_subtree(key, cube, n, &pos, &arr, self.opts.config)
            .map_err(|error| Error::Octree { error })?;
        self.report.tree_seconds += tt.elapsed().as_secs_f64();
        let tw = Instant::now();
        let base = self.seq;
        self.seq += sub.nodes.len() as u64;
        let attr_len = rl - 12;
        let dir = self.writer.dir.clone();
        let color = &self.color;
        let mut start = 0;
        while start < sub.nodes.len() {
            let mut end = start;
            let mut bytes = 0u64;
            while end < sub.nodes.len() && (end == start || bytes < self.writer.group_bytes) {
                bytes += payload_len(sub.nodes[end].count() as u64, attr_len as u64);
                end += 1;
            }
            let lens: Vec<u64> = (start..end)
                .map(|i| payload_len(sub.nodes[i].count() as u64, attr_len as u64))
                .collect();
            let offsets = self.writer.reserve(&lens);
            let w = &*self.writer;
            let done: Vec<(NodeEntry, u64)> = (start..end)
                .into_par_iter()
                .zip(offsets.into_par_iter())
                .map(|(i, off)| {
                    let nd = &sub.nodes[i];
                    if payload_len(nd.count() as u64, attr_len as u64) > w.group_bytes {
                        let mut e =
                            super::engine::write_sliced(w, off, nd, attr_len, &sorted, color)?;
                        e.offset = off;
                        return Ok((e, checksum_at(w, off, e.length)?));
                    }
                    let (kind, idx): (u32, Box<dyn Fn(usize) -> usize + Sync>) = match &nd.content {
                        SortedContent::Leaf(r) => {
                            let s = r.start;
                            (LEAF, Box::new(move |i| s + i))
                        }
                        SortedContent::Inner(v) => (INNER, Box::new(move |i| v[i] as usize)),
                    };
                    let (mut e, b) = encode_payload(
                        nd.key,
                        kind,
                        nd.count(),
                        attr_len,
                        |i| read_xyz(sorted.record(idx(i))),
                        |i| color.rgba(sorted.record(idx(i))),
                        |i| &sorted.record(idx(i))[12..],
                    )
                    .map_err(|error| Error::Payload { path: dir.clone(), error })?;
                    w.write_at(off, &b)?;
                    e.offset = off;
                    Ok((e, checksum(&b)))
                })
                .collect::<Result<_>>()?;
            for (i, (e, h)) in (start..end).zip(done) {
                self.entries.push((e.level, base + i as u64, e));
                self.hashes.push(h);
            }
            start = end;
        }
        self.points +=
            sub.nodes.iter().filter(|x| x.is_leaf()).map(|x| x.count() as u64).sum::<u64>();
        self.report.write_seconds += tw.elapsed().as_secs_f64();
        let mut out = Cands::default();
        for &i in &sub.candidates {
            let r = sorted.record(i as usize);
            out.push(read_xyz(r), sorted.arrival[i as usize], r);
        }
        Ok(out)
    }
}

/// The points of the partition cells `cells` (those of node `key`, `count` of them) read back
/// from every run and sorted as the sorted engine sorts: a unit's points, ready for
/// [`build_subtree`]. `dir` names the place in errors.
pub(crate) fn read_unit(
    runs: &[Run],
    root: Cube,
    key: NodeKey,
    cells: std::ops::Range<usize>,
    count: u64,
    rl: usize,
    dir: &Path,
) -> Result<Sorted> {
    let n = count as usize;
    let mut records = sort::zeroed_huge::<u8>(n * rl);
    let mut arrival = sort::zeroed_huge::<u64>(n);
    // Each run's share, read in parallel straight into place (runs in input order).
    let mut parts: Vec<(&Run, &mut [u8], &mut [u64])> = Vec::with_capacity(runs.len());
    {
        let (mut rr, mut ar): (&mut [u8], &mut [u64]) = (&mut records, &mut arrival);
        for run in runs {
            let m = (run.starts[cells.end] - run.starts[cells.start]) as usize;
            if m > ar.len() {
                return Err(Error::Internal {
                    path: dir.to_path_buf(),
                    what: "the run files hold more points than counted",
                });
            }
            let (x, y) = std::mem::take(&mut rr).split_at_mut(m * rl);
            let (u, v) = std::mem::take(&mut ar).split_at_mut(m);
            parts.push((run, x, u));
            rr = y;
            ar = v;
        }
        if !ar.is_empty() {
            return Err(Error::Internal {
                path: dir.to_path_buf(),
                what: "the run files hold fewer points than counted",
            });
        }
    }
    let cs = cells.start;
    parts.into_par_iter().try_for_each(|(run, recs, arr)| -> Result<()> {
        if arr.is_empty() {
            return Ok(());
        }
        let total = *run.starts.last().expect("a run has an end");
        let first = run.starts[cs];
        let mut f = std::fs::File::open(&run.path).map_err(|e| Error::io(&run.path, e))?;
        f.seek(SeekFrom::Start(first * rl as u64)).map_err(|e| Error::io(&run.path, e))?;
        f.read_exact(recs).map_err(|e| Error::io(&run.path, e))?;
        f.seek(SeekFrom::Start(total * rl as u64 + first * 8))
            .map_err(|e| Error::io(&run.path, e))?;
        f.read_exact(bytemuck::cast_slice_mut(arr)).map_err(|e| Error::io(&run.path, e))
    })?;
    // Sorted as the sorted engine sorts (buckets below the unit's own prefix): local order
    // is input order, so ties come out the same.
    let g = grid_of(root);
    let high = 3 * (root.size_log2 as u32).min(mortar_core::morton::BITS_PER_AXIS);
    let unit_level = key.level as u32;
    let shift = high.saturating_sub(3 * unit_level.min(high / 3)).saturating_sub(BUCKET_BITS);
    let sorted: Sorted = if n == 0 {
        Sorted { records: Vec::new(), arrival: Vec::new(), rl }
    } else {
        // Slabs of the unit, so that the histograms and the scatter run on every thread.
        const SLAB: usize = 1 << 16;
        let slabs: Vec<&[u8]> = records.chunks(SLAB * rl).collect();
        let hist: Vec<Vec<u32>> = slabs.par_iter().map(|s| histogram(s, rl, &g, shift)).collect();
        sort_records(&slabs, &hist, rl, &g, shift, &crate::progress::Progress::new(), |p, i| {
            arrival[p * SLAB + i]
        })
    };
    Ok(sorted)
}

/// What a job of a distributed build reads ([`super::distributed`]): the dataset's pieces
/// (by number) and the partition cells it keeps.
pub(crate) struct Filter {
    pub pieces: Vec<bool>,
    pub cells: Vec<bool>,
}

/// What pass 1 gives: the runs, the cells' counts, the statistics of every point read and of
/// each input's.
pub(crate) type Partitioned = (Vec<Run>, Vec<u64>, PieceStats, Vec<PieceStats>);

/// Pass 1 on a root fixed beforehand (a plan's), reading only what `filter` keeps: the runs,
/// the cells' counts of the points kept, their statistics and those of every piece read, per
/// input (to check the files against the bounds the plan took for them).
pub(crate) fn partition_fixed(
    ds: &Dataset,
    root: Cube,
    max_level: u8,
    memory: u64,
    filter: &Filter,
    dir: &Path,
) -> Result<Partitioned> {
    let block_bytes = ((memory / 4).max(ds.layout.record_len as u64 * 4096)) as usize;
    partition(ds, root, Grid::IDENTITY, max_level, block_bytes, dir, Some(filter))
}

/// The nodes a distributed job wrote: (level, depth-first number, entry) of each, the
/// candidates of each unit for its parent, and the points in the leaves.
pub(crate) type Units = (Vec<(u32, u64, NodeEntry)>, Vec<Cands>, u64);

/// Builds the subtrees `units` (key, cube, partition cells) from the runs into `writer`, each
/// as the partitioned engine builds a node and everything under it, with `color` for the
/// payloads.
#[allow(clippy::too_many_arguments)]
pub(crate) fn build_units(
    ds: &Dataset,
    writer: &mut StoreWriter,
    config: mortar_core::octree::BuilderConfig,
    memory: u64,
    root: Cube,
    runs: &[Run],
    hist: &[u64],
    units: &[(NodeKey, Cube, std::ops::Range<usize>)],
    color: ColorSource,
    state: &Path,
) -> Result<Units> {
    let rl = ds.layout.record_len;
    let opts = BuildOptions {
        config,
        batch_points: 0,
        commit_every: f64::INFINITY,
        first_commit_after: None,
        memory,
        engine: super::options::Engine::Partitioned,
        resume: false,
    };
    let unit_points =
        ((memory / 2) / unit_bytes_per_point(rl as u64)).max(config.leaf_capacity as u64 + 1);
    let log_path = state.join(LOG);
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .map_err(|e| Error::io(&log_path, e))?;
    let mut report = BuildReport::default();
    let depth = cell_depth(root, config.max_level);
    let lv = Level::new(runs.to_vec(), hist.to_vec(), depth);
    let mut w = Walk {
        ds,
        writer,
        opts: &opts,
        root,
        unit_points,
        color,
        rl,
        entries: Vec::new(),
        hashes: Vec::new(),
        seq: 0,
        points: 0,
        report: &mut report,
        replay: Default::default(),
        log,
        log_path,
        state: state.to_path_buf(),
    };
    let mut cands = Vec::with_capacity(units.len());
    for (key, cube, cells) in units {
        // An empty subtree too: it is an empty leaf where its parent is inner.
        cands.push(w.visit(&lv, *key, *cube, key.level, cells.clone())?);
    }
    let Walk { entries, points, .. } = w;
    Ok((entries, cands, points))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh directory under the system's temporary directory.
    fn scratch(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("mortar-part-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// Bytes that differ from run to run of the generator but not between runs of the test.
    fn bytes(n: usize, seed: u64) -> Vec<u8> {
        let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..n)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                x as u8
            })
            .collect()
    }

    /// A partition of two runs over 8 cells, as pass 1 leaves it, with its run files.
    fn partition(state: &Path, rl: usize) -> Partition {
        let starts = [vec![0u64, 3, 3, 5, 9, 9, 9, 10, 12], vec![0u64, 0, 1, 1, 1, 4, 6, 6, 6]];
        let mut runs = Vec::new();
        for (k, s) in starts.iter().enumerate() {
            let path = state.join(format!("run-{k}.bin"));
            let b = bytes(*s.last().unwrap() as usize * (rl + 8), k as u64 + 1);
            std::fs::write(&path, &b).unwrap();
            runs.push(Run { path, starts: s.clone(), hash: checksum(&b) });
        }
        let hist =
            (0..8).map(|c| runs.iter().map(|r| r.starts[c + 1] - r.starts[c]).sum()).collect();
        let all = PieceStats {
            count: 18,
            min: [-5, 0, 7],
            max: [900, 1000, 70],
            max_rgb: 65535,
            max_intensity: 4000,
            ..PieceStats::default()
        };
        let root = Cube { min: [-8, -8, -8], size_log2: 11 };
        Partition { root, runs, hist, all, warnings: vec!["a.las: lies".into()], base: [0; 3] }
    }

    #[test]
    fn a_manifest_is_read_back_as_written_and_any_damage_refuses_it() {
        let (state, rl) = (scratch("manifest"), 26);
        let p = partition(&state, rl);
        write_manifest(&state, &p).unwrap();
        let q = read_manifest(&state, rl).expect("a whole manifest is read back");
        assert_eq!((q.root, &q.hist, q.all.count, &q.warnings), (p.root, &p.hist, 18, &p.warnings));
        assert_eq!(
            (q.all.min, q.all.max, q.all.max_rgb, q.all.max_intensity),
            ([-5, 0, 7], [900, 1000, 70], 65535, 4000)
        );
        for (a, b) in q.runs.iter().zip(&p.runs) {
            assert_eq!((&a.path, &a.starts, a.hash), (&b.path, &b.starts, b.hash));
        }
        // Another record length: the run files' sizes do not match.
        assert!(read_manifest(&state, rl + 1).is_none());
        // A run file whose bytes changed but not its size (a power loss after the rename).
        let run0 = state.join("run-0.bin");
        let good = std::fs::read(&run0).unwrap();
        let mut bad = good.clone();
        bad[7] ^= 1;
        std::fs::write(&run0, &bad).unwrap();
        assert!(read_manifest(&state, rl).is_none(), "a changed run is refused");
        std::fs::write(&run0, &good).unwrap();
        // The tables cut short.
        let tables = state.join(TABLES);
        let t = std::fs::read(&tables).unwrap();
        std::fs::write(&tables, &t[..t.len() - 8]).unwrap();
        assert!(read_manifest(&state, rl).is_none(), "short tables are refused");
        std::fs::write(&tables, &t).unwrap();
        // A field of the JSON edited: the manifest's own checksum no longer matches.
        let mp = state.join(MANIFEST);
        let text = std::fs::read_to_string(&mp).unwrap();
        std::fs::write(&mp, text.replace("\"count\": 18", "\"count\": 19")).unwrap();
        assert!(read_manifest(&state, rl).is_none(), "an edited manifest is refused");
        std::fs::write(&mp, &text).unwrap();
        // A run file gone.
        std::fs::remove_file(state.join("run-1.bin")).unwrap();
        assert!(read_manifest(&state, rl).is_none(), "a missing run is refused");
        std::fs::remove_dir_all(&state).unwrap();
    }

    #[test]
    fn the_log_keeps_whole_records_whose_payloads_are_there_and_cuts_the_rest() {
        let (dir, rl) = (scratch("log"), 20);
        let nodes = dir.join("nodes.bin");
        let payloads = [bytes(96, 5), bytes(40, 6), bytes(64, 7)];
        std::fs::write(&nodes, payloads.concat()).unwrap();
        let entry = |i: usize, off: u64| NodeEntry {
            level: 3,
            kind: LEAF,
            index: [i as u32, 1, 2],
            _pad: 0,
            count: 4,
            offset: off,
            length: payloads[i].len() as u64,
        };
        let mut cands = Cands::default();
        cands.push([1, 2, 3], 77, &bytes(rl, 8));
        cands.push([-4, 5, 6], 78, &bytes(rl, 9));
        let key = |i: u32| NodeKey { level: 3, index: [i, 1, 2] };
        let r0 = log_record(
            key(0),
            1,
            10,
            96,
            &[(3, 0, entry(0, 0))],
            &[checksum(&payloads[0])],
            &cands,
            rl,
        );
        let r1 = log_record(
            key(1),
            2,
            20,
            136,
            &[(3, 1, entry(1, 96))],
            &[checksum(&payloads[1])],
            &Cands::default(),
            rl,
        );
        let log = dir.join(LOG);
        std::fs::write(&log, [r0.clone(), r1.clone()].concat()).unwrap();
        let (visits, entries, hashes, points, end) = read_log(&log, &nodes, rl).unwrap();
        assert_eq!((visits.len(), entries.len(), hashes.len(), points, end), (2, 2, 2, 30, 136));
        let v = &visits[&(3, [0, 1, 2])];
        assert_eq!((v.seq_after, &v.cands.pos, &v.cands.arrival), (1, &cands.pos, &cands.arrival));
        assert_eq!(v.cands.records, cands.records);
        // A record torn by a kill: the whole records before it are kept, the log is cut there.
        let r2 = log_record(
            key(2),
            3,
            5,
            200,
            &[(3, 2, entry(2, 136))],
            &[checksum(&payloads[2])],
            &Cands::default(),
            rl,
        );
        std::fs::write(&log, [r0.clone(), r1.clone(), r2[..r2.len() - 3].to_vec()].concat())
            .unwrap();
        let (visits, _, _, points, end) = read_log(&log, &nodes, rl).unwrap();
        assert_eq!((visits.len(), points, end), (2, 30, 136));
        assert_eq!(std::fs::metadata(&log).unwrap().len(), (r0.len() + r1.len()) as u64);
        // A record whose payload in nodes.bin is not what it logged (written, not synced).
        let mut nb = std::fs::read(&nodes).unwrap();
        nb[100] ^= 0xff;
        std::fs::write(&nodes, &nb).unwrap();
        let (visits, _, _, points, _) = read_log(&log, &nodes, rl).unwrap();
        assert_eq!((visits.len(), points), (1, 10), "the second visit's payload changed");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
