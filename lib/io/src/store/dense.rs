//! Partition cells denser than a unit of the partitioned engine may hold (`--memory` on hostile
//! density: points at one position, a cluster of exact duplicates, a terrestrial scan's
//! scanner position), shared by `mortar build` (`partitioned.rs`) and the export of inputs
//! larger than the budget (`export/stream.rs`).
//!
//! A cell of the partition whose points do not fit one unit is never read into memory whole:
//!
//! - **It may split** (more points than a leaf, a cube at least 2^7 units wide, above the depth
//!   limit): it is an inner node. When all its points lie in one octant (known from their
//!   bounds), its other seven children are empty and the one child is treated the same way, with
//!   no I/O: points at one position walk down the tree at no cost. Otherwise its points are
//!   partitioned again ([`split`]), in blocks of at most a quarter of the budget, into the cells
//!   up to five levels below it, written as run files in arrival order, and the walk goes on over
//!   that finer partition ([`Level`]).
//! - **It may not split** (a leaf beyond the depth limit, or narrower than 2^7 units): a leaf
//!   larger than a unit ([`big_leaf`]). Its points are put in the sorted engine's order (Morton
//!   order at full resolution, ties by arrival) without holding them all: points at one position
//!   are already in that order (arrival) and are read straight from the runs; otherwise the leaf's
//!   cube is split again by Morton order, down to parts that fit a unit (sorted in memory) or hold
//!   one position. The leaf is then read back in slices for its payload or its exported node.
//!
//! The nodes are those the sorted engine makes in memory (`tests/memory_budget.rs` compares the
//! stores node by node; `tests/export.rs` the exports). An exported leaf larger than a unit is
//! ordered by GPS time (the default `--order`) by an external merge sort ([`TimeOrder`]).

use super::runs::{Cands, Run};
use crate::cleanup::TempPath;
use crate::error::{Error, Result};
use mortar_core::layout::read_xyz;
use mortar_core::octree::{Cube, NodeKey, GRID_LOG2, MIN_INNER_SIZE_LOG2};
use rayon::prelude::*;
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The smallest and largest position of some points (empty: `[i32::MAX; 3]`, `[i32::MIN; 3]`).
pub(crate) type Bounds = ([i32; 3], [i32; 3]);

const EMPTY: Bounds = ([i32::MAX; 3], [i32::MIN; 3]);

fn grow(b: &mut Bounds, p: [i32; 3]) {
    for a in 0..3 {
        b.0[a] = b.0[a].min(p[a]);
        b.1[a] = b.1[a].max(p[a]);
    }
}

fn union(a: Bounds, b: Bounds) -> Bounds {
    ([0, 1, 2].map(|k| a.0[k].min(b.0[k])), [0, 1, 2].map(|k| a.1[k].max(b.1[k])))
}

/// A partition a walk reads: run files, the count of each cell, the level of the cells, and,
/// for a partition made here, each cell's bounds. A finer partition's run files are removed
/// when it is dropped.
pub(crate) struct Level {
    pub runs: Vec<Run>,
    pub hist: Vec<u64>,
    /// The tree level of the cells.
    pub depth: u8,
    bounds: Option<Vec<Bounds>>,
    _dir: Option<TempPath>,
}

impl Level {
    /// The partition of pass 1.
    pub(crate) fn new(runs: Vec<Run>, hist: Vec<u64>, depth: u8) -> Level {
        Level { runs, hist, depth, bounds: None, _dir: None }
    }

    /// The bounds of the points of `cells` if this partition knows them.
    fn known_bounds(&self, cells: &Range<usize>) -> Option<Bounds> {
        self.bounds.as_ref().map(|b| b[cells.clone()].iter().fold(EMPTY, |a, x| union(a, *x)))
    }

    /// The bounds of the points of `cells`: known, or read from the runs.
    pub(crate) fn bounds(&self, cells: &Range<usize>, rl: usize, block: usize) -> Result<Bounds> {
        if let Some(b) = self.known_bounds(cells) {
            return Ok(b);
        }
        let mut b = EMPTY;
        stream(&self.runs, cells.clone(), rl, block, |recs, _| {
            let part = recs
                .par_chunks(rl)
                .fold(
                    || EMPTY,
                    |mut x, r| {
                        grow(&mut x, read_xyz(r));
                        x
                    },
                )
                .reduce(|| EMPTY, union);
            b = union(b, part);
            Ok(())
        })?;
        Ok(b)
    }
}

/// Points a block of a dense cell holds at once under the budget `memory` (a quarter of it for
/// the block as read, as much again for its scattered copy).
pub(crate) fn block_points(memory: u64, rl: usize) -> usize {
    ((memory / 4) / (rl as u64 + 12)).max(4096) as usize
}

/// The one octant of `cube` that holds every point of `b`, if there is one.
pub(crate) fn one_octant(cube: Cube, b: Bounds) -> Option<usize> {
    if cube.size_log2 == 0 {
        return None;
    }
    let (lo, hi) = (cube.octant_of(b.0), cube.octant_of(b.1));
    (lo == hi).then_some(lo)
}

/// The cell at `d` levels below `cube` that holds `p`, numbered in Morton order (octant order).
#[inline]
fn cell_below(cube: Cube, d: u8, p: [i32; 3]) -> usize {
    let o = [0, 1, 2].map(|a| (p[a] as i64 - cube.min[a]) as u64);
    let mut c = 0usize;
    for k in 0..d as u32 {
        let bit = cube.size_log2 as u32 - 1 - k;
        c = c << 3
            | ((o[0] >> bit) & 1 | ((o[1] >> bit) & 1) << 1 | ((o[2] >> bit) & 1) << 2) as usize;
    }
    c
}

/// The cube of cell `c` at `d` levels below `cube`.
fn cube_below(cube: Cube, d: u8, c: usize) -> Cube {
    let mut q = cube;
    for k in (0..d as u32).rev() {
        q = q.child(c >> (3 * k) & 7);
    }
    q
}

/// Calls `f` with the records and arrival numbers of the cells `cells` of `runs` in arrival
/// order (run after run), at most `block` points at a time.
fn stream(
    runs: &[Run],
    cells: Range<usize>,
    rl: usize,
    block: usize,
    mut f: impl FnMut(&[u8], &[u64]) -> Result<()>,
) -> Result<()> {
    let (mut recs, mut arr) = (Vec::new(), Vec::new());
    for run in runs {
        let (a, b) = (run.starts[cells.start], run.starts[cells.end]);
        if a == b {
            continue;
        }
        let total = *run.starts.last().expect("a run has an end");
        let file = std::fs::File::open(&run.path).map_err(|e| Error::io(&run.path, e))?;
        let mut at = a;
        while at < b {
            crate::cleanup::check_interrupted()?;
            let m = (b - at).min(block as u64) as usize;
            recs.resize(m * rl, 0);
            arr.resize(m, 0u64);
            file.read_exact_at(&mut recs, at * rl as u64).map_err(|e| Error::io(&run.path, e))?;
            file.read_exact_at(bytemuck::cast_slice_mut(&mut arr), total * rl as u64 + at * 8)
                .map_err(|e| Error::io(&run.path, e))?;
            f(&recs, &arr)?;
            at += m as u64;
        }
    }
    Ok(())
}

/// Partitions the points of `cells` of `runs` (in `cube`) again, by their cell `d` levels below
/// `cube` (`d` at most 5), into run files in a new directory in `dir`: a block of points at a
/// time, each block one run, so that arrival order is kept. The new partition's cells are at
/// level `level + d`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn split(
    runs: &[Run],
    cells: Range<usize>,
    rl: usize,
    cube: Cube,
    level: u8,
    d: u8,
    block: usize,
    dir: &Path,
) -> Result<Level> {
    debug_assert!((1..=5).contains(&d) && d <= cube.size_log2);
    let tmp = TempPath::dir_in(dir, "dense").map_err(|e| Error::io(dir, e))?;
    let nb = 1usize << (3 * d as u32);
    let mut hist = vec![0u64; nb];
    let mut bounds = vec![EMPTY; nb];
    let mut out = Vec::new();
    let mut buf: Vec<u8> = Vec::new();
    stream(runs, cells, rl, block, |recs, arr| {
        let m = arr.len();
        let which: Vec<u32> =
            recs.par_chunks(rl).map(|r| cell_below(cube, d, read_xyz(r)) as u32).collect();
        let mut starts = vec![0u64; nb + 1];
        for &c in &which {
            starts[c as usize + 1] += 1;
        }
        for c in 0..nb {
            starts[c + 1] += starts[c];
        }
        let mut cur: Vec<usize> = starts[..nb].iter().map(|&s| s as usize).collect();
        buf.resize(m * (rl + 8), 0);
        for (i, &c) in which.iter().enumerate() {
            let c = c as usize;
            let at = cur[c];
            cur[c] += 1;
            let r = &recs[i * rl..(i + 1) * rl];
            buf[at * rl..(at + 1) * rl].copy_from_slice(r);
            buf[m * rl + at * 8..m * rl + at * 8 + 8].copy_from_slice(&arr[i].to_ne_bytes());
            grow(&mut bounds[c], read_xyz(r));
            hist[c] += 1;
        }
        let path = tmp.path().join(format!("run-{}.bin", out.len()));
        std::fs::write(&path, &buf).map_err(|e| Error::io(&path, e))?;
        out.push(Run::new(path, starts));
        Ok(())
    })?;
    Ok(Level { runs: out, hist, depth: level + d, bounds: Some(bounds), _dir: Some(tmp) })
}

/// How many levels a dense inner node at `key` (cube `cube`) is partitioned again by: at most
/// five, and no deeper than the cells that may still be nodes of the tree (the children of the
/// deepest nodes that may split).
pub(crate) fn tree_split_depth(key: NodeKey, cube: Cube, max_level: u8) -> u8 {
    5u8.min(cube.size_log2 + 1 - MIN_INNER_SIZE_LOG2).min(max_level - key.level).max(1)
}

/// A run of a leaf's points in its order: records at `rec_at` and arrival numbers at `arr_at`
/// of one file.
struct Seg {
    path: Arc<PathBuf>,
    rec_at: u64,
    arr_at: u64,
    count: u64,
}

/// A leaf larger than a unit, in the sorted engine's order, on disk; its bounds, and its
/// candidates for its parent with their places in it.
pub(crate) struct Leaf {
    pub bounds: Bounds,
    /// The earliest point in each cell of the parent's grid, in Morton order (none for the root).
    pub cands: Cands,
    /// Where each candidate is in the leaf (increasing).
    pub cand_index: Vec<u64>,
    segs: Vec<Seg>,
    /// Where each segment starts in the leaf.
    seg_start: Vec<u64>,
    rl: usize,
    _temps: Vec<Level>,
    _file: Option<TempPath>,
}

/// The earliest point of a cell of the parent's grid so far: the cell, its place in the leaf,
/// its arrival number, its position and its record.
type Earliest = ([u64; 3], u64, u64, [i32; 3], Vec<u8>);

/// What [`big_leaf`] needs while it orders a leaf.
struct Order<'a> {
    rl: usize,
    unit_points: u64,
    block: usize,
    dir: &'a Path,
    segs: Vec<Seg>,
    temps: Vec<Level>,
    /// The file the parts sorted in memory are appended to (created at the first).
    file: Option<(TempPath, Arc<PathBuf>, std::fs::File, u64)>,
}

/// The leaf `key` (cube `cube`) of the `count` points of `cells` of `lv` (bounds `bounds`) in
/// the sorted engine's order, with no more than a unit of them in memory at once.
#[allow(clippy::too_many_arguments)]
pub(crate) fn big_leaf(
    lv: &Level,
    cells: Range<usize>,
    count: u64,
    key: NodeKey,
    cube: Cube,
    bounds: Bounds,
    rl: usize,
    unit_points: u64,
    block: usize,
    dir: &Path,
) -> Result<Leaf> {
    let mut o =
        Order { rl, unit_points, block, dir, segs: Vec::new(), temps: Vec::new(), file: None };
    o.order(&lv.runs, cells, count, cube, bounds)?;
    let Order { segs, temps, file, .. } = o;
    let mut seg_start = Vec::with_capacity(segs.len());
    let mut n = 0;
    for s in &segs {
        seg_start.push(n);
        n += s.count;
    }
    if n != count {
        return Err(Error::Internal {
            path: dir.to_path_buf(),
            what: "a dense leaf's parts hold another count of points",
        });
    }
    let mut leaf = Leaf {
        bounds,
        cands: Cands::default(),
        cand_index: Vec::new(),
        segs,
        seg_start,
        rl,
        _temps: temps,
        _file: file.map(|f| f.0),
    };
    if key.level > 0 {
        // The earliest point in each cell of the parent's grid: cells are ranges of the order.
        let cell_log2 = cube.size_log2 - (GRID_LOG2 - 1);
        let cell =
            |p: [i32; 3]| [0, 1, 2].map(|a| ((p[a] as i64 - cube.min[a]) as u64) >> cell_log2);
        // (cell, place in the leaf, arrival, position, record) of the earliest point so far
        let mut current: Option<Earliest> = None;
        let mut at = 0u64;
        let mut cands = Cands::default();
        let mut index = Vec::new();
        while at < count {
            let m = (count - at).min(block as u64);
            let (recs, arr) = leaf.read(at..at + m, true)?;
            for (i, r) in recs.chunks_exact(rl).enumerate() {
                let p = read_xyz(r);
                let c = cell(p);
                match &mut current {
                    Some((cc, bi, bt, bp, br)) if *cc == c => {
                        if arr[i] < *bt {
                            (*bi, *bt, *bp) = (at + i as u64, arr[i], p);
                            br.copy_from_slice(r);
                        }
                    }
                    _ => {
                        if let Some((_, bi, bt, bp, br)) = current.take() {
                            cands.push(bp, bt, &br);
                            index.push(bi);
                        }
                        current = Some((c, at + i as u64, arr[i], p, r.to_vec()));
                    }
                }
            }
            at += m;
        }
        if let Some((_, bi, bt, bp, br)) = current {
            cands.push(bp, bt, &br);
            index.push(bi);
        }
        leaf.cands = cands;
        leaf.cand_index = index;
    }
    Ok(leaf)
}

impl Order<'_> {
    /// Appends the points of `cells` of `runs` (in `cube`, bounds `b`) in order.
    fn order(
        &mut self,
        runs: &[Run],
        cells: Range<usize>,
        count: u64,
        cube: Cube,
        b: Bounds,
    ) -> Result<()> {
        if count == 0 {
            return Ok(());
        }
        if b.0 == b.1 {
            // One position: arrival order is the order; read where they are.
            for r in runs {
                let (a, e) = (r.starts[cells.start], r.starts[cells.end]);
                if a < e {
                    let total = *r.starts.last().expect("a run has an end");
                    self.segs.push(Seg {
                        path: Arc::new(r.path.clone()),
                        rec_at: a * self.rl as u64,
                        arr_at: total * self.rl as u64 + a * 8,
                        count: e - a,
                    });
                }
            }
            return Ok(());
        }
        if count <= self.unit_points {
            return self.sorted_part(runs, cells, count, cube);
        }
        if let Some(o) = one_octant(cube, b) {
            return self.order(runs, cells, count, cube.child(o), b);
        }
        let d = 5u8.min(cube.size_log2);
        let sub = split(runs, cells, self.rl, cube, 0, d, self.block, self.dir)?;
        let bounds = sub.bounds.clone().expect("a split knows its cells' bounds");
        for (c, &n) in sub.hist.iter().enumerate() {
            if n > 0 {
                self.order(&sub.runs, c..c + 1, n, cube_below(cube, d, c), bounds[c])?;
            }
        }
        self.temps.push(sub);
        Ok(())
    }

    /// Reads a part that fits a unit, sorts it by full-resolution Morton order in `cube` (ties by
    /// arrival) and appends it to the leaf's file.
    fn sorted_part(
        &mut self,
        runs: &[Run],
        cells: Range<usize>,
        count: u64,
        cube: Cube,
    ) -> Result<()> {
        let rl = self.rl;
        let n = count as usize;
        let mut recs = Vec::with_capacity(n * rl);
        let mut arr = Vec::with_capacity(n);
        stream(runs, cells, rl, self.block, |r, a| {
            recs.extend_from_slice(r);
            arr.extend_from_slice(a);
            Ok(())
        })?;
        let key = |r: &[u8]| -> u128 {
            let p = read_xyz(r);
            let o = [0, 1, 2].map(|a| (p[a] as i64 - cube.min[a]) as u32);
            let hi = mortar_core::morton::encode(o[0] >> 11, o[1] >> 11, o[2] >> 11) as u128;
            let lo = mortar_core::morton::encode(o[0] & 0x7ff, o[1] & 0x7ff, o[2] & 0x7ff) as u128;
            hi << 33 | lo
        };
        let mut keys: Vec<(u128, u64, u32)> =
            recs.par_chunks(rl).enumerate().map(|(i, r)| (key(r), arr[i], i as u32)).collect();
        keys.par_sort_unstable();
        let mut out = vec![0u8; n * (rl + 8)];
        {
            let (o_rec, o_arr) = out.split_at_mut(n * rl);
            o_rec.par_chunks_mut(rl).zip(o_arr.par_chunks_mut(8)).zip(keys.par_iter()).for_each(
                |((d, da), k)| {
                    let i = k.2 as usize;
                    d.copy_from_slice(&recs[i * rl..(i + 1) * rl]);
                    da.copy_from_slice(&k.1.to_ne_bytes());
                },
            );
        }
        drop((recs, arr, keys));
        if self.file.is_none() {
            let t = TempPath::dir_in(self.dir, "leaf").map_err(|e| Error::io(self.dir, e))?;
            let p = t.path().join("leaf.bin");
            let f = std::fs::File::create(&p).map_err(|e| Error::io(&p, e))?;
            self.file = Some((t, Arc::new(p), f, 0));
        }
        let (_, path, f, end) = self.file.as_mut().expect("created above");
        f.write_all_at(&out, *end).map_err(|e| Error::io(path.as_path(), e))?;
        self.segs.push(Seg {
            path: path.clone(),
            rec_at: *end,
            arr_at: *end + (n * rl) as u64,
            count,
        });
        *end += out.len() as u64;
        Ok(())
    }
}

impl Leaf {
    /// The records (and with `arrival` their arrival numbers) of the points `range` of the leaf.
    pub(crate) fn read(&self, range: Range<u64>, arrival: bool) -> Result<(Vec<u8>, Vec<u64>)> {
        let rl = self.rl as u64;
        let n = (range.end - range.start) as usize;
        let mut recs = vec![0u8; n * self.rl];
        let mut arr = if arrival { vec![0u64; n] } else { Vec::new() };
        let first = self.seg_start.partition_point(|&s| s <= range.start).saturating_sub(1);
        let mut k = first;
        let mut at = range.start;
        while at < range.end {
            let s = self.segs.get(k).ok_or(Error::Internal {
                path: PathBuf::new(),
                what: "a read past a dense leaf's end",
            })?;
            let off = at - self.seg_start[k];
            let m = (s.count - off).min(range.end - at);
            let f = std::fs::File::open(s.path.as_path())
                .map_err(|e| Error::io(s.path.as_path(), e))?;
            let d = (at - range.start) as usize;
            f.read_exact_at(
                &mut recs[d * self.rl..(d + m as usize) * self.rl],
                s.rec_at + off * rl,
            )
            .map_err(|e| Error::io(s.path.as_path(), e))?;
            if arrival {
                f.read_exact_at(
                    bytemuck::cast_slice_mut(&mut arr[d..d + m as usize]),
                    s.arr_at + off * 8,
                )
                .map_err(|e| Error::io(s.path.as_path(), e))?;
            }
            at += m;
            k += 1;
        }
        Ok((recs, arr))
    }

    /// The records of the points `range` of the leaf less its candidates (what an exported leaf
    /// holds: the candidates are held above it).
    pub(crate) fn read_kept(&self, range: Range<u64>) -> Result<Vec<u8>> {
        if range.is_empty() {
            return Ok(Vec::new());
        }
        let c = &self.cand_index;
        // The leaf index of kept point j: j plus the candidates before it.
        // (`c[i] - i` kept points come before candidate `i`, and it grows with `i`.)
        let place = |j: u64| {
            let (mut lo, mut hi) = (0usize, c.len());
            while lo < hi {
                let m = (lo + hi) / 2;
                if c[m] - m as u64 <= j {
                    lo = m + 1;
                } else {
                    hi = m;
                }
            }
            j + lo as u64
        };
        let (a, b) = (place(range.start), place(range.end - 1) + 1);
        let (recs, _) = self.read(a..b, false)?;
        let lo = c.partition_point(|&x| x < a);
        let hi = c.partition_point(|&x| x < b);
        let skip = &c[lo..hi];
        let rl = self.rl;
        let mut out = Vec::with_capacity((range.end - range.start) as usize * rl);
        let mut s = 0;
        for (i, r) in recs.chunks_exact(rl).enumerate() {
            if s < skip.len() && skip[s] == a + i as u64 {
                s += 1;
                continue;
            }
            out.extend_from_slice(r);
        }
        Ok(out)
    }
}

/// The total order of `f64::total_cmp` as an unsigned key.
fn time_key(t: f64) -> u64 {
    let b = t.to_bits();
    if b >> 63 == 1 {
        !b
    } else {
        b | 1 << 63
    }
}

/// A leaf's kept points ([`Leaf::read_kept`]) by GPS time, ties in the leaf's order (what the
/// in-memory export's stable sort gives): parts of at most a unit sorted in memory and written
/// to run files (each record followed by its place in the leaf), then merged as they are read.
pub(crate) struct TimeOrder {
    runs: Vec<TimeRun>,
    heap: std::collections::BinaryHeap<std::cmp::Reverse<(u64, u64, usize)>>,
    rl: usize,
    gps: usize,
    _dir: TempPath,
}

/// One sorted run of a [`TimeOrder`]: its file, where the next block starts, its end, and the
/// block read (entries of `rl + 8` bytes) with how much of it is taken.
struct TimeRun {
    file: std::fs::File,
    path: PathBuf,
    next: u64,
    end: u64,
    buf: Vec<u8>,
    at: usize,
    per_block: u64,
}

impl TimeRun {
    /// The entry at the front (reading the next block when the one read is taken).
    fn front(&mut self, el: usize) -> Result<Option<&[u8]>> {
        if self.at * el >= self.buf.len() {
            if self.next >= self.end {
                return Ok(None);
            }
            let m = (self.end - self.next).min(self.per_block);
            self.buf.resize(m as usize * el, 0);
            self.file
                .read_exact_at(&mut self.buf, self.next * el as u64)
                .map_err(|e| Error::io(&self.path, e))?;
            self.next += m;
            self.at = 0;
        }
        Ok(Some(&self.buf[self.at * el..(self.at + 1) * el]))
    }
}

impl Leaf {
    /// The `kept` points [`read_kept`](Self::read_kept) gives, ordered by the GPS time at byte
    /// `gps` of each record: at most `unit_points` sorted at once, merged `block` entries at a
    /// time.
    pub(crate) fn time_order(
        &self,
        kept: u64,
        gps: usize,
        unit_points: u64,
        block: usize,
        dir: &Path,
    ) -> Result<TimeOrder> {
        let rl = self.rl;
        let el = rl + 8;
        let tmp = TempPath::dir_in(dir, "leaf-time").map_err(|e| Error::io(dir, e))?;
        let time =
            |r: &[u8]| time_key(f64::from_le_bytes(r[gps..gps + 8].try_into().expect("8 bytes")));
        let part = unit_points.max(1);
        let mut runs = Vec::new();
        let mut s = 0u64;
        while s < kept {
            crate::cleanup::check_interrupted()?;
            let e = (s + part).min(kept);
            let recs = self.read_kept(s..e)?;
            let mut keys: Vec<(u64, u64)> =
                recs.par_chunks(rl).enumerate().map(|(i, r)| (time(r), s + i as u64)).collect();
            keys.par_sort_unstable();
            let mut out = vec![0u8; keys.len() * el];
            out.par_chunks_mut(el).zip(keys.par_iter()).for_each(|(d, &(_, j))| {
                let i = (j - s) as usize;
                d[..rl].copy_from_slice(&recs[i * rl..(i + 1) * rl]);
                d[rl..].copy_from_slice(&j.to_le_bytes());
            });
            let path = tmp.path().join(format!("time-{}.bin", runs.len()));
            std::fs::write(&path, &out).map_err(|e| Error::io(&path, e))?;
            let file = std::fs::File::open(&path).map_err(|e| Error::io(&path, e))?;
            runs.push(TimeRun {
                file,
                path,
                next: 0,
                end: e - s,
                buf: Vec::new(),
                at: 0,
                per_block: 0,
            });
            s = e;
        }
        let per_block = (block / runs.len().max(1)).max(1024) as u64;
        let mut heap = std::collections::BinaryHeap::new();
        for (k, r) in runs.iter_mut().enumerate() {
            r.per_block = per_block;
            if let Some(x) = r.front(el)? {
                heap.push(std::cmp::Reverse((
                    time(x),
                    u64::from_le_bytes(x[rl..].try_into().expect("8 bytes")),
                    k,
                )));
            }
        }
        Ok(TimeOrder { runs, heap, rl, gps, _dir: tmp })
    }
}

impl TimeOrder {
    /// The records of the next `n` points.
    pub(crate) fn next(&mut self, n: usize) -> Result<Vec<u8>> {
        let (rl, el, gps) = (self.rl, self.rl + 8, self.gps);
        let mut out = Vec::with_capacity(n * rl);
        for _ in 0..n {
            let Some(std::cmp::Reverse((_, _, k))) = self.heap.pop() else {
                return Err(Error::Internal {
                    path: PathBuf::new(),
                    what: "a dense leaf's time order ended early",
                });
            };
            let r = &mut self.runs[k];
            let x = r.front(el)?.expect("a run in the heap has an entry");
            out.extend_from_slice(&x[..rl]);
            r.at += 1;
            if let Some(x) = r.front(el)? {
                let t = time_key(f64::from_le_bytes(x[gps..gps + 8].try_into().expect("8 bytes")));
                self.heap.push(std::cmp::Reverse((
                    t,
                    u64::from_le_bytes(x[rl..].try_into().expect("8 bytes")),
                    k,
                )));
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_below_are_the_octants_descended_in_order() {
        let cube = Cube { min: [-100, 50, 7], size_log2: 9 };
        let mut h = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..2000 {
            h = h.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let p = [0, 1, 2].map(|a| (cube.min[a] + ((h >> (20 * a)) & 511) as i64) as i32);
            for d in 1..=5 {
                let c = cell_below(cube, d, p);
                assert!(cube_below(cube, d, c).contains(p));
                let (mut q, mut i) = (cube, 0);
                for _ in 0..d {
                    let o = q.octant_of(p);
                    i = i * 8 + o;
                    q = q.child(o);
                }
                assert_eq!(i, c, "{p:?} at depth {d}");
            }
        }
        assert_eq!(one_octant(cube, ([-100, 50, 7], [-100 + 255, 50 + 255, 7 + 255])), Some(0));
        assert_eq!(one_octant(cube, ([-100, 50, 7], [-100 + 256, 50, 7])), None);
    }

    #[test]
    fn time_keys_order_as_total_cmp() {
        let mut v =
            [f64::NAN, f64::INFINITY, 2.0, 1e-300, 0.0, -0.0, -1.5, f64::NEG_INFINITY, -f64::NAN];
        v.sort_by(|a, b| a.total_cmp(b));
        for w in v.windows(2) {
            assert!(time_key(w[0]) < time_key(w[1]), "{} {}", w[0], w[1]);
        }
    }

    /// A leaf of `n` records (12 bytes: x is the point's place) in two segments of one file.
    fn leaf_of(dir: &Path, n: u64, cands: Vec<u64>) -> Leaf {
        let mut b = Vec::new();
        for i in 0..n {
            b.extend_from_slice(&(i as i32).to_le_bytes());
            b.extend_from_slice(&[0; 8]);
        }
        b.extend(std::iter::repeat_n(0u8, n as usize * 8));
        let p = Arc::new(dir.join("leaf.bin"));
        std::fs::write(p.as_path(), &b).unwrap();
        let h = n / 3;
        let segs = vec![
            Seg { path: p.clone(), rec_at: 0, arr_at: n * 12, count: h },
            Seg { path: p, rec_at: h * 12, arr_at: n * 12 + h * 8, count: n - h },
        ];
        Leaf {
            bounds: EMPTY,
            cands: Cands::default(),
            cand_index: cands,
            segs,
            seg_start: vec![0, h],
            rl: 12,
            _temps: Vec::new(),
            _file: None,
        }
    }

    #[test]
    fn kept_points_skip_the_candidates_in_every_range() {
        let dir = std::env::temp_dir().join(format!("mortar-dense-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let n = 1000u64;
        for cands in [
            vec![],
            vec![0],
            vec![999],
            vec![0, 1, 2, 500, 998, 999],
            (0..1000).step_by(7).collect(),
        ] {
            let leaf = leaf_of(&dir, n, cands.clone());
            let kept: Vec<i32> = (0..n as i32).filter(|i| !cands.contains(&(*i as u64))).collect();
            let k = kept.len() as u64;
            for (a, b) in
                [(0, k), (0, 1), (k - 1, k), (3, 17), (k / 2, k / 2 + 100), (k / 3 - 1, k / 3 + 1)]
            {
                let r = leaf.read_kept(a..b).unwrap();
                let got: Vec<i32> = r
                    .chunks_exact(12)
                    .map(|c| i32::from_le_bytes(c[..4].try_into().unwrap()))
                    .collect();
                assert_eq!(got, kept[a as usize..b as usize], "{cands:?} {a}..{b}");
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
