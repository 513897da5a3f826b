//! Pass 1 of the partitioned engine, the partition: every piece read once and its records, each
//! with its arrival number, scattered by the Morton cell (at depth `D` of the root) that holds
//! them into run files, with the cells' counts; on the headers' root, or again on the points'
//! own root where the headers lie, or on a plan's fixed root for a distributed job.

use super::checksum::checksum;
use super::preview::RootSample;
use crate::dataset::Dataset;
use crate::error::{Error, Result};
use crate::sort::{self, PieceStats};
use crate::store::engine::grid_of;
use crate::store::runs::Run;
use mortar_core::layout::read_xyz;
use mortar_core::morton::MortonGrid;
use mortar_core::octree::{Cube, MIN_INNER_SIZE_LOG2};
use rayon::prelude::*;
use std::io::Write;
use std::path::Path;

/// Deepest level of the cells the records are partitioned by (8^5 = 32,768 cells).
const MAX_CELL_DEPTH: u8 = 5;

/// What pass 1 found, kept in the manifest for `--resume`.
pub(crate) struct Partition {
    pub root: Cube,
    pub runs: Vec<Run>,
    pub hist: Vec<u64>,
    pub all: PieceStats,
    pub warnings: Vec<String>,
    /// The `base` of a stretched grid ([`partition_all`]); zeros for builds.
    pub base: [i64; 3],
    /// The first point of each cell of the root's grid (when asked for: a build's preview).
    pub sample: Option<RootSample>,
}

/// What pass 1 reports after each group of pieces, with the memory its sample may take: the
/// root's sample so far (a build's provisional commits, [`super::preview`]).
pub(crate) type OnGroup<'a, 'b> = (&'a mut (dyn FnMut(&RootSample) -> Result<()> + 'b), u64);

/// The depth of the partition cells for `root`: cells must still be able to split (so that
/// every node above them is inner when it holds more than a unit).
pub(crate) fn cell_depth(root: Cube, max_level: u8) -> u8 {
    let room = root.size_log2.saturating_sub(MIN_INNER_SIZE_LOG2);
    MAX_CELL_DEPTH.min(room).min(max_level).min(mortar_core::morton::BITS_PER_AXIS as u8)
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
    mut on_group: Option<OnGroup<'_, '_>>,
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
    // Every point read into runs of cells of `root`'s grid (and `root`'s sample, when asked).
    let mut pass = |root: Cube, grid: Grid| {
        let g = on_group.as_mut().map(|(f, m)| (&mut **f, *m));
        partition(ds, root, grid, max_level, block_bytes, state, None, g)
    };
    let (mut runs, mut hist, all, real, mut sample) = pass(guess.1, guess.0)?;
    let mut warnings = Vec::new();
    for (src, st) in ds.inputs.iter().zip(&real) {
        if let Some(w) = crate::store::bounds::bounds_warning(ds, src.as_ref(), st) {
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
        (runs, hist, _, _, sample) = pass(root, grid)?;
    }
    Ok(Partition { root, runs, hist, all, warnings, base: grid.base, sample })
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
/// of all points and of each input, and with `on_group` the root's sample (reported after each
/// group of pieces).
#[allow(clippy::too_many_arguments)]
fn partition(
    ds: &Dataset,
    root: Cube,
    grid: Grid,
    max_level: u8,
    block_bytes: usize,
    dir: &Path,
    filter: Option<&Filter>,
    mut on_group: Option<OnGroup<'_, '_>>,
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
    let mut sample = on_group.as_ref().map(|(_, m)| RootSample::new(root, rl, *m));
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
        let sampled = sample.as_ref();
        let group: Vec<ReadPiece<'_>> = (i..j)
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
                let firsts = sampled.map(|s| s.firsts(&slab)).unwrap_or_default();
                Ok((slab, st, h, firsts))
            })
            .collect::<Result<_>>()?;
        let mut starts = vec![0u64; cells + 1];
        for c in 0..cells {
            starts[c + 1] = starts[c] + group.iter().map(|(_, _, h, _)| h[c] as u64).sum::<u64>();
        }
        let n = starts[cells] as usize;
        let mut cursors: Vec<Vec<usize>> = Vec::with_capacity(group.len());
        let mut running: Vec<usize> = starts[..cells].iter().map(|&s| s as usize).collect();
        for (_, _, h, _) in &group {
            cursors.push(running.clone());
            for c in 0..cells {
                running[c] += h[c] as usize;
            }
        }
        let mut buf = sort::zeroed_huge::<u8>(n * el);
        {
            let bp = mortar_core::par::SendPtr(buf.as_mut_ptr());
            group.par_iter().zip(cursors.into_par_iter()).enumerate().for_each(
                |(k, ((slab, _, _, _), mut cur))| {
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
        if let Some(s) = sample.as_mut() {
            // In arrival order: the first point of a cell wins.
            for (slab, _, _, firsts) in &group {
                s.absorb(slab, firsts);
            }
        }
        for (k, (_, st, h, _)) in group.iter().enumerate() {
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
        // The group's records are written: their memory is free before a commit codes the
        // sample.
        drop(buf);
        drop(f);
        if let (Some((f, _)), Some(s)) = (on_group.as_mut(), sample.as_ref()) {
            f(s)?;
        }
        i = j;
    }
    Ok((runs, hist, all, real, sample))
}

/// A piece read in pass 1: its records, statistics, counts per cell and the records that are
/// the first of a root cell ([`RootSample::firsts`]).
type ReadPiece<'a> = (std::borrow::Cow<'a, [u8]>, PieceStats, Vec<u32>, Vec<u32>);

/// What a job of a distributed build reads ([`crate::store::distributed`]): the dataset's pieces
/// (by number) and the partition cells it keeps.
pub(crate) struct Filter {
    pub pieces: Vec<bool>,
    pub cells: Vec<bool>,
}

/// What pass 1 gives: the runs, the cells' counts, the statistics of every point read and of
/// each input's, and the root's sample where one was asked for.
pub(crate) type Partitioned = (Vec<Run>, Vec<u64>, PieceStats, Vec<PieceStats>, Option<RootSample>);

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
    partition(ds, root, Grid::IDENTITY, max_level, block_bytes, dir, Some(filter), None)
}
