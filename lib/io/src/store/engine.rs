//! The sorted engine of `mortar build` (ARCHITECTURE.md, "The build engine"): every piece read
//! once in parallel (LAZ chunks decoded once, mapped LAS read in place) with a Morton key per
//! point made while the piece is in cache; the keys sorted by the parallel radix sort of
//! `mortar sort`; the tree made in one pass over the sorted points
//! ([`mortar_core::octree::build_sorted`], sibling subtrees in parallel); then the nodes encoded in
//! parallel and written level by level from the root down, with a commit after each level, so a
//! reader (the preview, `render`, `view`) sees the whole cloud coarse first and finer with each
//! commit.
//!
//! It builds the tree the incremental engine builds (same nodes, same points per leaf, same
//! voxel points), and writes each node once: `nodes.bin` holds exactly the live payloads.
//! Used when the input fits the memory budget ([`in_memory_need`]) and voxels take the first
//! point's colour; otherwise the incremental engine runs.

use super::format::*;
use super::options::{BuildOptions, BuildProgress, BuildReport, BuiltBy};
use super::writer::*;
use crate::dataset::Dataset;
use crate::error::{Error, Result, StoreError};
use crate::progress::Progress;
use crate::sort::{self, Key, PieceStats};
use mortar_core::color::{ColorSource, RgbDepth};
use mortar_core::layout::read_xyz;
use mortar_core::morton::MortonGrid;
use mortar_core::octree::{build_sorted, ColorMode, Cube, SortedContent, SortedNode};
use mortar_core::par::SendPtr;
use rayon::prelude::*;
use std::time::Instant;

/// Bytes per point the sorted engine holds besides the records: the arrival number (8) and the
/// per-bucket sorting work (8).
const PER_POINT: u64 = 16;

/// Bits of the Morton code by which records are scattered into buckets, sorted one at a time in
/// cache. 8192 buckets: airborne clouds fill few of the cells in height, so 2048 (11 bits) left
/// about 300 k points in a bucket at 100 M points (10 MB of records, gathered out of cache); 13
/// bits cut the per-bucket sorts by a fifth on 2 cores at 20 M points (BENCHMARKS.md, "Store v3
/// on 16 cores"). Each piece keeps a count and a cursor per bucket (12 bytes each: 96 KiB a piece).
pub(super) const BUCKET_BITS: u32 = 13;

/// Memory the sorted engine needs for `ds` under the budget `memory`, as the OS counts it
/// (resident pages): the records as read (decoded LAZ, converted records, or the pages of a
/// mapped LAS file, resident once read), the records sorted, 16 bytes per point, and two
/// groups of encoded payloads ([`group_bytes`]).
pub fn in_memory_need(ds: &Dataset, memory: u64) -> u64 {
    held_in_memory(ds, PER_POINT).saturating_add(2 * group_bytes(memory))
}

/// The records as read and as sorted, and `per_point` bytes more per point.
pub(crate) fn held_in_memory(ds: &Dataset, per_point: u64) -> u64 {
    let rl = ds.layout.record_len as u64;
    let points = ds.declared_points();
    let read: u64 = ds
        .inputs
        .iter()
        .map(|s| s.point_count().saturating_mul(s.layout().record_len as u64))
        .sum();
    // a mapped LAS file whose records are converted is held mapped and converted
    let converted: u64 = ds
        .inputs
        .iter()
        .enumerate()
        .filter(|(i, s)| ds.needs_buffer(*i) && !s.is_compressed())
        .map(|(_, s)| s.point_count().saturating_mul(rl))
        .sum();
    read.saturating_add(converted).saturating_add(points.saturating_mul(rl + per_point))
}

/// Writes the payload of node `n` (of the records `sorted`) at `off` in slices of about the
/// writer's group: a node larger than a group (points at one position, beyond the depth limit)
/// is never encoded whole in memory. The same bytes as [`encode_payload`].
pub(crate) fn write_sliced(
    w: &StoreWriter,
    off: u64,
    n: &SortedNode,
    attr_len: usize,
    sorted: &Sorted,
    color: &ColorSource,
) -> Result<NodeEntry> {
    let (kind, idx): (u32, Box<dyn Fn(usize) -> usize + Sync>) = match &n.content {
        SortedContent::Leaf(r) => {
            let s = r.start;
            (LEAF, Box::new(move |i| s + i))
        }
        SortedContent::Inner(v) => (INNER, Box::new(move |i| v[i] as usize)),
    };
    let slice = (w.group_bytes / (16 + attr_len as u64)).max(1) as usize;
    let r = write_payload_sliced(
        n.key,
        kind,
        n.count(),
        attr_len,
        slice,
        |i| read_xyz(sorted.record(idx(i))),
        |i| color.rgba(sorted.record(idx(i))),
        |i| &sorted.record(idx(i))[12..],
        |at, b| w.write_at(off + at, b),
    )?;
    r.map_err(|error| Error::Payload { path: w.dir.clone(), error })
}

/// Whether the sorted engine builds `ds` with `opts`.
pub fn applies(ds: &Dataset, opts: &BuildOptions) -> bool {
    opts.config.color_mode == ColorMode::FirstCome
        && in_memory_need(ds, opts.memory) <= opts.memory
        && ds.declared_points() < u32::MAX as u64
}

/// The Morton grid whose codes order points as the octree over `root` needs: origin at the
/// root's corner, one shift so that the root fits 21 bits per axis (ties of a shifted code are
/// ordered by the bits the shift dropped).
pub(crate) fn grid_of(root: Cube) -> MortonGrid {
    MortonGrid {
        origin: root.min,
        shift: (root.size_log2 as u32).saturating_sub(mortar_core::morton::BITS_PER_AXIS),
    }
}

/// The shift that gives a code's bucket.
pub(crate) fn bucket_shift(root: Cube) -> u32 {
    let high = 3 * (root.size_log2 as u32).min(mortar_core::morton::BITS_PER_AXIS);
    high.saturating_sub(BUCKET_BITS)
}

#[inline]
pub(crate) fn code_of(r: &[u8], g: &MortonGrid) -> u64 {
    let q = read_xyz(r);
    g.code([q[0] as i64, q[1] as i64, q[2] as i64])
}

/// How many picks ahead [`write_tree`] asks for an inner node's records.
const PREFETCH_AHEAD: usize = 16;

/// Asks the processor to bring `r`'s cache lines in (a hint: nothing on other targets).
#[inline]
pub(crate) fn prefetch(r: &[u8]) {
    #[cfg(target_arch = "x86_64")]
    if let (Some(a), Some(b)) = (r.first(), r.last()) {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: a prefetch is a hint that never faults; SSE is part of x86_64.
        unsafe {
            _mm_prefetch::<_MM_HINT_T0>(a as *const u8 as *const i8);
            _mm_prefetch::<_MM_HINT_T0>(b as *const u8 as *const i8);
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = r;
}

/// Points in Morton order: whole records and their arrival numbers (`piece << 32 | index`).
pub(crate) struct Sorted {
    pub(crate) records: Vec<u8>,
    pub(crate) arrival: Vec<u64>,
    pub(crate) rl: usize,
}

impl Sorted {
    #[inline]
    pub(crate) fn record(&self, i: usize) -> &[u8] {
        &self.records[i * self.rl..(i + 1) * self.rl]
    }
}

/// Sorts the records of `slabs` (pieces in input order) by Morton code on `g`, ties by the bits
/// the shift dropped, then by arrival: a parallel scatter of whole records into buckets by the
/// code's top bits (sequential reads, one write stream per bucket), then each bucket sorted in
/// cache. `hist[p]` is piece `p`'s count per bucket.
///
/// Buckets are the `BUCKET_BITS` code bits from `shift` up (the bits above are shared, as in a
/// unit of the partitioned engine); `arrival_of(slab, index)` numbers each record.
pub(crate) fn sort_records(
    slabs: &[&[u8]],
    hist: &[Vec<u32>],
    rl: usize,
    g: &MortonGrid,
    shift: u32,
    prog: &Progress,
    arrival_of: impl Fn(usize, usize) -> u64 + Sync,
) -> Sorted {
    let nb = 1usize << BUCKET_BITS;
    let n: usize = slabs.iter().map(|s| s.len() / rl).sum();
    let mut starts = vec![0usize; nb + 1];
    for b in 0..nb {
        starts[b + 1] = starts[b] + hist.iter().map(|h| h[b] as usize).sum::<usize>();
    }
    let mut cursors: Vec<Vec<usize>> = Vec::with_capacity(hist.len());
    let mut running = starts[..nb].to_vec();
    for h in hist {
        cursors.push(running.clone());
        for b in 0..nb {
            running[b] += h[b] as usize;
        }
    }
    let t = Instant::now();
    let mut records = sort::zeroed_huge::<u8>(n * rl);
    let mut arrival = sort::zeroed_huge::<u64>(n);
    crate::cleanup::trace("  sort: allocated", t);
    {
        let rp = SendPtr(records.as_mut_ptr());
        let ap = SendPtr(arrival.as_mut_ptr());
        slabs.par_iter().zip(cursors.into_par_iter()).enumerate().for_each(
            |(p, (slab, mut cur))| {
                let (rp, ap) = (&rp, &ap);
                prog.add((slab.len() / rl) as u64);
                for (i, r) in slab.chunks_exact(rl).enumerate() {
                    let b = ((code_of(r, g) >> shift) as usize) & (nb - 1);
                    let at = cur[b];
                    cur[b] += 1;
                    // SAFETY: the cursors of all pieces partition 0..n; each slot is written once.
                    unsafe {
                        std::ptr::copy_nonoverlapping(r.as_ptr(), rp.0.add(at * rl), rl);
                        ap.write(at, arrival_of(p, i));
                    }
                }
            },
        );
    }
    crate::cleanup::trace("  sort: scattered", t);
    // Each bucket: keys (code, local index) sorted stably by code, then the bucket permuted.
    let mask = (1i64 << g.shift) - 1;
    let mut rb: Vec<&mut [u8]> = Vec::with_capacity(nb);
    let mut ab: Vec<&mut [u64]> = Vec::with_capacity(nb);
    {
        let (mut rr, mut ar): (&mut [u8], &mut [u64]) = (&mut records, &mut arrival);
        for b in 0..nb {
            let len = starts[b + 1] - starts[b];
            let (x, y) = rr.split_at_mut(len * rl);
            let (u, v) = ar.split_at_mut(len);
            rb.push(x);
            ab.push(u);
            rr = y;
            ar = v;
        }
    }
    rb.into_par_iter().zip(ab.into_par_iter()).for_each_init(
        || (Vec::<Key>::new(), Vec::<Key>::new(), Vec::<u8>::new(), Vec::<u64>::new()),
        |(keys, scratch, tmp, tarr), (recs, arr)| {
            let m = arr.len();
            prog.add(m as u64);
            if m < 2 {
                return;
            }
            // Every point at one position (a dense bucket of coincident points): the bucket is
            // already in its order (arrival), and the keys and copies below would cost 74
            // bytes per point of it.
            let first = read_xyz(recs);
            if recs.chunks_exact(rl).all(|r| read_xyz(r) == first) {
                return;
            }
            keys.clear();
            keys.extend(recs.chunks_exact(rl).enumerate().map(|(i, r)| Key {
                code: code_of(r, g),
                slab: i as u32,
                idx: 0,
            }));
            sort::sort_bucket(keys, shift, scratch);
            if g.shift > 0 {
                // Ties of the shifted code: by the dropped bits, then arrival (local order).
                let residual = |i: u32| {
                    let q = read_xyz(&recs[i as usize * rl..]);
                    let low = |a: usize| ((q[a] as i64 - g.origin[a]) & mask) as u32;
                    mortar_core::morton::encode(low(0), low(1), low(2))
                };
                let mut s = 0;
                while s < m {
                    let mut e = s + 1;
                    while e < m && keys[e].code == keys[s].code {
                        e += 1;
                    }
                    if e - s > 1 {
                        keys[s..e].sort_by_key(|k| (residual(k.slab), k.slab));
                    }
                    s = e;
                }
            }
            tmp.clear();
            tmp.extend_from_slice(recs);
            tarr.clear();
            tarr.extend_from_slice(arr);
            for (d, k) in keys.iter().enumerate() {
                let j = k.slab as usize;
                recs[d * rl..(d + 1) * rl].copy_from_slice(&tmp[j * rl..(j + 1) * rl]);
                arr[d] = tarr[j];
            }
        },
    );
    crate::cleanup::trace("  sort: buckets sorted", t);
    Sorted { records, arrival, rl }
}

/// Where each piece's records begin among all (`starts[p]`; the last entry is the count).
pub(crate) fn piece_starts(records: &[&[u8]], rl: usize) -> Vec<usize> {
    let mut starts = vec![0usize; records.len() + 1];
    for (k, r) in records.iter().enumerate() {
        starts[k + 1] = starts[k] + r.len() / rl;
    }
    starts
}

/// Writes the store's `arrival.bin` ([`super::arrival`]): the arrival numbers
/// (`piece << 32 | index`) of the leaves' points in their coded order ([`write_tree`] puts them
/// so) as ranks among all records (`starts` from [`piece_starts`]); `header` is the box the
/// inputs' headers declared.
pub(crate) fn write_arrival(
    writer: &StoreWriter,
    arrival: &[u64],
    starts: &[usize],
    header: Option<([i32; 3], [i32; 3])>,
    all: &PieceStats,
) -> Result<()> {
    let rank = |i: usize| {
        let a = arrival[i];
        (starts[(a >> 32) as usize] + (a & 0xffff_ffff) as usize) as u64
    };
    let colors =
        super::arrival::ColorMaxima { max_rgb: all.max_rgb, max_intensity: all.max_intensity };
    super::arrival::write(&writer.dir, arrival.len(), rank, header, colors)
}

/// Builds the store in `writer` from `ds` with the sorted engine; `header` is the headers' box
/// (see [`super::build`]).
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
    let mut report = BuildReport { engine: BuiltBy::Sorted, ..BuildReport::default() };
    let Input { slabs, mut hist, all, root, promised, bounds: (lo, hi) } =
        read_input(ds, header, &mut report, t0)?;
    let records: Vec<&[u8]> = slabs.iter().map(|(r, _)| &**r).collect();
    let starts = piece_starts(&records, rl);
    let g = grid_of(root);
    let shift = bucket_shift(root);
    if root != promised {
        hist = records.par_iter().map(|s| histogram(s, rl, &g, shift)).collect();
        crate::cleanup::trace("histograms again (header bounds differ from the points)", t0);
    }
    let ts = Instant::now();
    // Counted twice: once scattered into buckets, once sorted in its bucket.
    ds.progress.stage("sorting", 2 * all.count, "points");
    let mut sorted = sort_records(&records, &hist, rl, &g, shift, &ds.progress, |p, i| {
        (p as u64) << 32 | i as u64
    });
    drop(records);
    drop(slabs);
    report.sort_seconds = ts.elapsed().as_secs_f64();
    crate::cleanup::trace("sort", t0);
    crate::cleanup::check_interrupted()?;
    let color = color_of(ds, &all);
    let tt = Instant::now();
    ds.progress.stage("indexing", 0, "");
    let n = sorted.arrival.len();
    let pos = |i: usize| read_xyz(sorted.record(i));
    let arrival = |i: usize| sorted.arrival[i];
    let tree = build_sorted(root, n, &pos, &arrival, opts.config)
        .map_err(|error| Error::Octree { error })?;
    report.tree_seconds = tt.elapsed().as_secs_f64();
    report.batch_seconds.push(report.tree_seconds);
    crate::cleanup::trace("tree", t0);
    ds.progress.stage("writing", tree.nodes.len() as u64, "nodes");
    let mut arrival = std::mem::take(&mut sorted.arrival);
    write_tree(
        writer,
        &tree,
        root,
        opts,
        &sorted,
        &mut arrival,
        &color,
        (lo, hi),
        &mut report,
        progress,
        &ds.progress,
        total,
        t0,
    )?;
    write_arrival(writer, &arrival, &starts, header, &all)?;
    crate::cleanup::trace("arrival ranks written", t0);
    crate::cleanup::trace("written", t0);
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(report)
}

/// The input as the sorted engines begin: every piece read, the points' statistics, and the
/// root cube.
pub(crate) struct Input<'a> {
    /// The pieces' records (in input order) and statistics.
    pub(crate) slabs: Vec<(std::borrow::Cow<'a, [u8]>, PieceStats)>,
    /// Per piece, its count per sort bucket on the grid of `promised`.
    pub(crate) hist: Vec<Vec<u32>>,
    /// All the points' statistics.
    pub(crate) all: PieceStats,
    /// The root cube.
    pub(crate) root: Cube,
    /// The root the headers promised (`hist` is on its grid).
    pub(crate) promised: Cube,
    /// The points' box.
    pub(crate) bounds: ([i32; 3], [i32; 3]),
}

/// Reads every piece ([`read_pieces`]), warns about headers that lie, and chooses the root:
/// the headers' box when it holds every point, otherwise the points' own box (the incremental
/// engine grows its root instead). `header` is the headers' box (see [`super::build`]).
pub(crate) fn read_input<'a>(
    ds: &'a Dataset,
    header: Option<([i32; 3], [i32; 3])>,
    report: &mut BuildReport,
    t0: Instant,
) -> Result<Input<'a>> {
    let total = ds.declared_points();
    // The root the headers promise; checked against the points once they are read.
    let promised =
        header.map(|(l, h)| Cube::covering(l, h)).unwrap_or(Cube { min: [0; 3], size_log2: 32 });
    let tr = Instant::now();
    ds.progress.stage("reading", total, "points");
    let (slabs, hist) = read_pieces(ds, promised)?;
    let pieces = ds.pieces();
    let mut all = PieceStats::default();
    let mut real = vec![PieceStats::default(); ds.inputs.len()];
    for (p, (_, st)) in pieces.iter().zip(&slabs) {
        all.merge(st);
        real[p.input].merge(st);
    }
    // Headers that lie: the points' real range, per file.
    for (src, st) in ds.inputs.iter().zip(&real) {
        if let Some(w) = super::bounds::bounds_warning(ds, src.as_ref(), st) {
            report.warnings.push(w);
        }
    }
    report.read_seconds = tr.elapsed().as_secs_f64();
    crate::cleanup::trace("read", t0);
    let (lo, hi) = if all.count == 0 { ([0; 3], [0; 3]) } else { (all.min, all.max) };
    let root = match header {
        Some((l, h)) if all.count > 0 && (0..3).all(|a| l[a] <= lo[a] && hi[a] <= h[a]) => {
            Cube::covering(l, h)
        }
        _ => Cube::covering(lo, hi),
    };
    Ok(Input { slabs, hist, all, root, promised, bounds: (lo, hi) })
}

/// The colour source from the whole input, as batch files choose it.
pub(crate) fn color_of(ds: &Dataset, all: &PieceStats) -> ColorSource {
    color_source(&ds.layout, all.max_rgb, all.max_intensity)
}

/// The colour source of records of `layout` whose largest RGB component and intensity are
/// `max_rgb` and `max_intensity`.
pub(crate) fn color_source(
    layout: &mortar_core::layout::RecordLayout,
    max_rgb: u16,
    max_intensity: u16,
) -> ColorSource {
    match layout.attribute("rgb") {
        Some(a) if max_rgb > 0 => {
            ColorSource::Rgb { offset: a.offset, depth: RgbDepth::detect(max_rgb) }
        }
        _ => ColorSource::Intensity { max_intensity },
    }
}

/// Counts per bucket of the records of one piece.
pub(crate) fn histogram(slab: &[u8], rl: usize, g: &MortonGrid, shift: u32) -> Vec<u32> {
    let mut h = vec![0u32; 1 << BUCKET_BITS];
    for r in slab.chunks_exact(rl) {
        h[((code_of(r, g) >> shift) as usize) & ((1 << BUCKET_BITS) - 1)] += 1;
    }
    h
}

/// Reads every piece in parallel (LAZ decoded once, mapped LAS borrowed in place), with its
/// statistics and its bucket counts on the grid of `root` made while it is in cache.
#[allow(clippy::type_complexity)]
pub(crate) fn read_pieces(
    ds: &Dataset,
    root: Cube,
) -> Result<(Vec<(std::borrow::Cow<'_, [u8]>, PieceStats)>, Vec<Vec<u32>>)> {
    let rl = ds.layout.record_len;
    let g = grid_of(root);
    let shift = bucket_shift(root);
    ds.inputs.par_iter().for_each(|i| i.prefetch());
    let pieces = ds.pieces();
    if pieces.len() > u32::MAX as usize || pieces.iter().any(|p| p.piece.points > u32::MAX as u64) {
        return Err(Error::TooManyPoints { what: "build" });
    }
    let out: Vec<((std::borrow::Cow<'_, [u8]>, PieceStats), Vec<u32>)> = pieces
        .par_iter()
        .map(|p| {
            crate::cleanup::check_interrupted()?;
            let slab = ds.read_piece(p)?;
            if slab.len() as u64 != p.piece.points * rl as u64 {
                return Err(Error::PieceCount {
                    path: ds.inputs[p.input].path().to_path_buf(),
                    piece: p.piece.index,
                });
            }
            let mut h = vec![0u32; 1 << BUCKET_BITS];
            let st = PieceStats::of_with(&slab, &ds.layout, |_, q| {
                // Points outside the promised root land in the last bucket: the histograms are made again
                // on the real root when the headers lie.
                h[((g.code([q[0] as i64, q[1] as i64, q[2] as i64]) >> shift) as usize)
                    .min((1 << BUCKET_BITS) - 1)] += 1;
            });
            Ok(((slab, st), h))
        })
        .collect::<Result<_>>()?;
    Ok(out.into_iter().unzip())
}

/// Encodes and appends the nodes of `tree` level by level, committing after each level.
#[allow(clippy::too_many_arguments)]
pub(crate) fn write_tree(
    writer: &mut StoreWriter,
    tree: &mortar_core::octree::SortedTree,
    root: Cube,
    opts: &BuildOptions,
    sorted: &Sorted,
    arrival: &mut [u64],
    color: &ColorSource,
    bounds: ([i32; 3], [i32; 3]),
    report: &mut BuildReport,
    progress: &mut dyn FnMut(&BuildProgress),
    prog: &Progress,
    total: u64,
    t0: Instant,
) -> Result<()> {
    let rl = writer.record_len;
    let attr_len = rl - 12;
    let levels = tree.levels();
    let mut points = 0u64;
    // A resumed build: the committed nodes must be whole levels of this tree, the same nodes.
    let kept: Vec<NodeEntry> = writer.entries().copied().collect();
    if !kept.is_empty() {
        let whole = levels.iter().any(|l| l.end == kept.len());
        let same = kept.len() <= tree.nodes.len()
            && kept.iter().zip(&tree.nodes).all(|(e, n)| {
                e.level == n.key.level as u32
                    && e.index == n.key.index
                    && (e.kind == LEAF) == n.is_leaf()
                    && e.count == n.count() as u64
            });
        if !whole || !same {
            return Err(Error::Store {
                path: writer.dir.clone(),
                error: StoreError::CommittedNodes,
            });
        }
        report.kept_nodes = kept.len() as u64;
        prog.add(kept.len() as u64);
    }
    let dir = writer.dir.clone();
    let layout = writer.layout.clone();
    let order = |key| crate::store::codec::Order::of(root, key, &layout);
    // Each leaf's arrival numbers put in its coded order as it is encoded (`arrival.bin` lists
    // them so: [`super::arrival`]); the kept leaves' (a resumed build) from their stored
    // payloads' order.
    let ap = SendPtr(arrival.as_mut_ptr());
    (0..kept.len()).into_par_iter().try_for_each(|id| -> Result<()> {
        let SortedContent::Leaf(run) = &tree.nodes[id].content else { return Ok(()) };
        let b = writer.read_payload(id, None)?;
        let (_, seq) = crate::store::codec::decode_ordered(&b).map_err(|m| Error::Payload {
            path: writer.dir.join(NODES_FILE),
            error: m.in_node(id),
        })?;
        if let Some(seq) = seq {
            let ap = &ap;
            // SAFETY: leaves' runs are disjoint ranges of `arrival` (held mutably here).
            unsafe {
                let tmp: Vec<u64> = (0..seq.len()).map(|i| *ap.0.add(run.start + i)).collect();
                for (i, &t) in seq.iter().enumerate() {
                    ap.0.add(run.start + t as usize).write(tmp[i]);
                }
            }
        }
        Ok(())
    })?;
    let encode = |id: usize, n: &SortedNode| -> Result<(usize, NodeEntry, Vec<u8>)> {
        // The record of the node's point i: a run of the sorted records, or the voxels' picks
        // (a branch the predictor learns per node, and inlined, unlike a boxed closure).
        let (kind, run, picks): (u32, usize, &[u32]) = match &n.content {
            SortedContent::Leaf(r) => (LEAF, r.start, &[]),
            SortedContent::Inner(v) => (INNER, 0, v),
        };
        let idx = |i: usize| if kind == LEAF { run + i } else { picks[i] as usize };
        let (e, b, seq) = crate::store::codec::encode_payload_ordered(
            n.key,
            kind,
            n.count(),
            attr_len,
            |i| {
                // An inner node's records lie far apart in the sorted input (a cache and TLB
                // miss each; the coder gathers them first): the one PREFETCH_AHEAD picks on is
                // asked for while this one is read.
                if let Some(&p) = picks.get(i + PREFETCH_AHEAD) {
                    prefetch(sorted.record(p as usize));
                }
                read_xyz(sorted.record(idx(i)))
            },
            |i| color.rgba(sorted.record(idx(i))),
            |i| &sorted.record(idx(i))[12..],
            order(n.key),
        )
        .map_err(|error| Error::Payload { path: dir.clone(), error })?;
        if let (LEAF, Some(seq)) = (kind, seq) {
            let ap = &ap;
            // SAFETY: leaves' runs are disjoint ranges of `arrival` (which this function holds
            // mutably), each leaf encoded once, by one thread.
            unsafe {
                let tmp: Vec<u64> = seq.iter().map(|&i| *ap.0.add(run + i as usize)).collect();
                std::ptr::copy_nonoverlapping(tmp.as_ptr(), ap.0.add(run), tmp.len());
            }
        }
        Ok((id, e, b))
    };
    for level in &levels {
        if level.end <= kept.len() {
            points += tree.nodes[level.clone()]
                .iter()
                .filter(|n| n.is_leaf())
                .map(|n| n.count() as u64)
                .sum::<u64>();
            continue;
        }
        let tw = Instant::now();
        let mut start = level.start;
        while start < level.end {
            crate::cleanup::check_interrupted()?;
            let mut end = start;
            let mut bytes = 0u64;
            while end < level.end && (end == start || bytes < writer.group_bytes) {
                bytes += payload_len(tree.nodes[end].count() as u64, attr_len as u64);
                end += 1;
            }
            // Coded lengths are known once encoded: encode (in parallel), place, then write
            // (nodes too large to encode in memory are written raw, in slices, in place).
            let big = |i: usize| {
                payload_len(tree.nodes[i].count() as u64, attr_len as u64)
                    > writer.group_bytes.max(super::codec::CODE_LIMIT)
            };
            let coded: Vec<Option<(usize, NodeEntry, Vec<u8>)>> = (start..end)
                .into_par_iter()
                .map(|i| if big(i) { Ok(None) } else { encode(i, &tree.nodes[i]).map(Some) })
                .collect::<Result<_>>()?;
            let lens: Vec<u64> = (start..end)
                .zip(&coded)
                .map(|(i, c)| match c {
                    Some((_, _, b)) => b.len() as u64,
                    None => payload_len(tree.nodes[i].count() as u64, attr_len as u64),
                })
                .collect();
            let offsets = writer.reserve(&lens);
            let w = &*writer;
            let entries: Vec<NodeEntry> = (start..end)
                .into_par_iter()
                .zip(coded.into_par_iter())
                .zip(offsets.into_par_iter())
                .map(|((i, c), off)| {
                    let mut e = match c {
                        None => write_sliced(w, off, &tree.nodes[i], attr_len, sorted, color)?,
                        Some((_, e, b)) => {
                            w.write_at(off, &b)?;
                            e
                        }
                    };
                    prog.add(1);
                    e.offset = off;
                    Ok(e)
                })
                .collect::<Result<_>>()?;
            for (i, e) in (start..end).zip(entries) {
                writer.set_entry(i, e);
            }
            start = end;
        }
        points += tree.nodes[level.clone()]
            .iter()
            .filter(|n| n.is_leaf())
            .map(|n| n.count() as u64)
            .sum::<u64>();
        report.write_seconds += tw.elapsed().as_secs_f64();
        let tc = Instant::now();
        writer.write_hierarchy(root, points, opts.config.leaf_capacity, bounds)?;
        report.commit_seconds += tc.elapsed().as_secs_f64();
        progress(&BuildProgress { points, total, nodes: level.end, commits: writer.commits() });
        crate::cleanup::trace("level committed", t0);
    }
    report.points = points;
    report.nodes = tree.nodes.len() as u64;
    report.leaves = tree.nodes.iter().filter(|n| n.is_leaf()).count() as u64;
    report.voxels = tree.nodes.iter().filter(|n| !n.is_leaf()).map(|n| n.count() as u64).sum();
    report.commits = writer.commits();
    report.nodes_bytes = writer.nodes_len;
    Ok(())
}
