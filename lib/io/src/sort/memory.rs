//! The in-memory Morton sort and what every sort shares: keys `(morton code, piece, index)`,
//! the parallel radix partition and per-bucket sort, the refinement of ties of a shifted code,
//! piece statistics, and the sinks the ordered records go to. The external sort
//! ([`super::external`]) sorts each of its buckets with these.
use crate::cleanup::{check_interrupted, trace};
use crate::dataset::{Dataset, DatasetPiece};
use crate::error::{Error, Result};
use crate::progress::Progress;
use mortar_core::layout::{read_xyz, RecordLayout};
use mortar_core::morton::MortonGrid;
use mortar_core::par::SendPtr;
use rayon::prelude::*;
use std::borrow::Cow;
use std::path::PathBuf;

/// Sort key of one point. Ordering: code, then input order (ties of a shifted code are refined
/// by [`refine_ties`] after sorting).
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, bytemuck::Zeroable, bytemuck::Pod,
)]
#[repr(C)]
pub struct Key {
    pub code: u64,
    pub slab: u32,
    pub idx: u32,
}

/// Facts about the whole dataset, known before the first record is emitted.
#[derive(Clone, Debug, PartialEq)]
pub struct Summary {
    pub count: u64,
    /// Integer bounds (inclusive) on the merged grid; meaningless when `count == 0`.
    pub min: [i32; 3],
    pub max: [i32; 3],
    pub points_by_return: [u64; 15],
    /// Largest RGB component (0 without RGB).
    pub max_rgb: u16,
    pub max_intensity: u16,
    pub morton: MortonGrid,
}

/// Per-piece statistics, merged into a [`Summary`].
#[derive(Clone, Debug)]
pub struct PieceStats {
    pub count: u64,
    pub min: [i32; 3],
    pub max: [i32; 3],
    pub by_return: [u64; 15],
    pub max_rgb: u16,
    pub max_intensity: u16,
}

impl Default for PieceStats {
    fn default() -> Self {
        PieceStats {
            count: 0,
            min: [i32::MAX; 3],
            max: [i32::MIN; 3],
            by_return: [0; 15],
            max_rgb: 0,
            max_intensity: 0,
        }
    }
}

impl PieceStats {
    pub fn of(records: &[u8], layout: &RecordLayout) -> PieceStats {
        Self::of_with(records, layout, |_, _| {})
    }

    /// The statistics of `records`, calling `each(i, xyz)` for every record in the same pass
    /// (the sort makes its keys there while the record is in cache).
    #[inline]
    pub fn of_with(
        records: &[u8],
        layout: &RecordLayout,
        mut each: impl FnMut(usize, [i32; 3]),
    ) -> PieceStats {
        let mut s = PieceStats::default();
        let rgb = layout.attribute("rgb").map(|a| a.offset);
        for (i, r) in records.chunks_exact(layout.record_len).enumerate() {
            let p = read_xyz(r);
            each(i, p);
            for a in 0..3 {
                s.min[a] = s.min[a].min(p[a]);
                s.max[a] = s.max[a].max(p[a]);
            }
            let rn = layout.return_number(r) as usize;
            if (1..=15).contains(&rn) {
                s.by_return[rn - 1] += 1;
            }
            s.max_intensity = s.max_intensity.max(u16::from_le_bytes([r[12], r[13]]));
            if let Some(o) = rgb {
                for c in 0..3 {
                    s.max_rgb = s.max_rgb.max(u16::from_le_bytes([r[o + 2 * c], r[o + 2 * c + 1]]));
                }
            }
        }
        s.count = (records.len() / layout.record_len) as u64;
        s
    }

    pub fn merge(&mut self, o: &PieceStats) {
        self.count += o.count;
        for a in 0..3 {
            self.min[a] = self.min[a].min(o.min[a]);
            self.max[a] = self.max[a].max(o.max[a]);
        }
        for i in 0..15 {
            self.by_return[i] += o.by_return[i];
        }
        self.max_rgb = self.max_rgb.max(o.max_rgb);
        self.max_intensity = self.max_intensity.max(o.max_intensity);
    }

    pub fn summary(&self) -> Summary {
        let (min, max) = if self.count == 0 { ([0; 3], [0; 3]) } else { (self.min, self.max) };
        let morton = MortonGrid::for_bounds(min.map(|v| v as i64), max.map(|v| v as i64));
        Summary {
            count: self.count,
            min,
            max,
            points_by_return: self.by_return,
            max_rgb: self.max_rgb,
            max_intensity: self.max_intensity,
            morton,
        }
    }
}

/// A consumer of Morton-ordered records.
pub trait OrderedSink: Send {
    /// Called once, before any record.
    fn begin(&mut self, summary: &Summary) -> Result<()>;
    /// Called with consecutive runs of records in Morton order.
    fn write(&mut self, records: &[u8]) -> Result<()>;
    /// Called instead of [`write`](Self::write) by [`emit`] with the records given by
    /// keys into slabs; the default gathers them and calls `write`. Sinks that consume records
    /// in small groups override it to gather into cache-sized buffers instead.
    fn write_keyed(&mut self, slabs: &[&[u8]], keys: &[Key], record_len: usize) -> Result<()> {
        self.write(&gather(slabs, keys, record_len))
    }
    /// Whether [`write_keyed`](Self::write_keyed) is better than gathered chunks.
    fn prefers_keyed(&self) -> bool {
        false
    }
}

/// The records of `keys`, gathered in order.
pub fn gather(slabs: &[&[u8]], keys: &[Key], record_len: usize) -> Vec<u8> {
    let mut buf = Vec::with_capacity(keys.len() * record_len);
    mortar_core::layout::gather_records(
        record_len,
        keys.len(),
        |i| {
            let k = keys[i];
            &slabs[k.slab as usize][k.idx as usize * record_len..]
        },
        &mut buf,
    );
    buf
}

/// Sort settings.
#[derive(Clone, Debug)]
pub struct SortOptions {
    /// Memory budget in bytes for sorting; larger datasets go through the external sort.
    pub memory: u64,
    /// Where temporary bucket files go.
    pub tmp_dir: PathBuf,
    /// Records per emitted chunk.
    pub chunk_points: usize,
}

impl SortOptions {
    /// Options for a budget of `memory` bytes; emitted chunks shrink with small budgets.
    pub fn with_memory(memory: u64, tmp_dir: PathBuf) -> SortOptions {
        let chunk_points = ((memory / 64 / 64) as usize).clamp(10_240, 10_240 * 32);
        SortOptions { memory, tmp_dir, chunk_points }
    }
}

/// Default memory budget: half the machine's memory, at most 16 GiB, at least 256 MiB.
pub fn default_memory() -> u64 {
    let total = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("MemTotal:"))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<u64>().ok()))
        })
        .map(|kb| kb * 1024)
        .unwrap_or(8 << 30);
    (total / 2).clamp(256 << 20, 16 << 30)
}

/// Bytes the in-memory sort needs for `points` records of `record_len` bytes.
pub fn in_memory_need(points: u64, record_len: usize, chunk_points: usize) -> u64 {
    let chunk = points.min(chunk_points as u64);
    points * (record_len as u64 + 2 * std::mem::size_of::<Key>() as u64)
        + 4 * chunk * record_len as u64
}

/// What [`super::sort`] did.
#[derive(Clone, Debug)]
pub struct SortReport {
    pub summary: Summary,
    pub external: bool,
    pub buckets: usize,
}

/// Sorts the dataset in memory and feeds the sink (the dataset fits the budget).
pub(crate) fn sort_in_memory(
    ds: &Dataset,
    opts: &SortOptions,
    sink: &mut dyn OrderedSink,
) -> Result<SortReport> {
    let t0 = std::time::Instant::now();
    let rl = ds.layout.record_len;
    let guess = declared_grid(ds);
    ds.progress.stage("reading", ds.declared_points(), "points");
    let mut arena = Vec::new();
    let (slabs, mut keys) = read_all(ds, &guess, &mut arena)?;
    let mut total = PieceStats::default();
    for (_, s) in &slabs {
        total.merge(s);
    }
    let summary = total.summary();
    let records: Vec<&[u8]> = slabs.iter().map(|(r, _)| &**r).collect();
    trace("read", t0);
    if summary.morton != guess && summary.count > 0 {
        keys = make_keys(&records, rl, &summary.morton)?;
        trace("keys again (header bounds differ from the points)", t0);
    }
    let mut keys = sort_keys(keys);
    refine_ties(&mut keys, &records, rl, &summary.morton);
    trace("sort", t0);
    ds.progress.stage("writing", summary.count, "points");
    let mut sink = Counted { sink, progress: &ds.progress, record_len: rl };
    sink.begin(&summary)?;
    emit(&records, &keys, ds.layout.record_len, opts.chunk_points, &mut sink)?;
    trace("emit", t0);
    Ok(SortReport { summary, external: false, buckets: 1 })
}

/// A sink that counts the records it passes on in a job's [`Progress`].
pub(crate) struct Counted<'a> {
    pub sink: &'a mut dyn OrderedSink,
    pub progress: &'a Progress,
    pub record_len: usize,
}

impl OrderedSink for Counted<'_> {
    fn begin(&mut self, summary: &Summary) -> Result<()> {
        self.sink.begin(summary)
    }
    fn write(&mut self, records: &[u8]) -> Result<()> {
        self.sink.write(records)?;
        self.progress.add((records.len() / self.record_len.max(1)) as u64);
        Ok(())
    }
    fn write_keyed(&mut self, slabs: &[&[u8]], keys: &[Key], record_len: usize) -> Result<()> {
        self.sink.write_keyed(slabs, keys, record_len)?;
        self.progress.add(keys.len() as u64);
        Ok(())
    }
    fn prefers_keyed(&self) -> bool {
        self.sink.prefers_keyed()
    }
}

/// The records of every piece, in input order, with their statistics.
pub type Slabs<'a> = Vec<(Cow<'a, [u8]>, PieceStats)>;

/// Reads every piece of `ds` in parallel (LAZ decoded into `arena`, mapped LAS borrowed in
/// place) and makes one key per point on the Morton grid `guess` while the piece is hot in
/// cache: the pieces' records (in input order) with their statistics, and the keys in input
/// order (`slab` = piece, `idx` = record in it).
pub fn read_all<'a>(
    ds: &'a Dataset,
    guess: &MortonGrid,
    arena: &'a mut Vec<u8>,
) -> Result<(Slabs<'a>, Vec<Key>)> {
    let pieces = ds.pieces();
    ds.inputs.par_iter().for_each(|i| i.prefetch());
    let rl = ds.layout.record_len;
    let n: usize = pieces.iter().map(|p| p.piece.points as usize).sum();
    if pieces.len() > u32::MAX as usize || pieces.iter().any(|p| p.piece.points > u32::MAX as u64) {
        return Err(Error::TooManyPoints { what: "sort" });
    }
    let buffered = |p: &DatasetPiece| ds.needs_buffer(p.input);
    let arena_len: usize =
        pieces.iter().filter(|p| buffered(p)).map(|p| p.piece.points as usize * rl).sum();
    *arena = zeroed_huge::<u8>(arena_len);
    let mut keys = zeroed_huge::<Key>(n);
    let mut work = Vec::with_capacity(pieces.len());
    {
        let mut rest_a: &mut [u8] = arena;
        let mut rest_k: &mut [Key] = &mut keys;
        for (i, p) in pieces.iter().enumerate() {
            let np = p.piece.points as usize;
            let (k, rk) = rest_k.split_at_mut(np);
            rest_k = rk;
            let buf = if buffered(p) {
                let (b, ra) = rest_a.split_at_mut(np * rl);
                rest_a = ra;
                Some(b)
            } else {
                None
            };
            work.push((i, *p, buf, k));
        }
    }
    let slabs: Vec<(Cow<[u8]>, PieceStats)> = work
        .into_par_iter()
        .map(|(i, p, buf, ks)| {
            check_interrupted()?;
            let slab: Cow<[u8]> = match buf {
                Some(b) => {
                    ds.read_piece_into(&p, b)?;
                    Cow::Borrowed(&*b)
                }
                None => ds.read_piece(&p)?,
            };
            if slab.len() != ks.len() * rl {
                return Err(Error::PieceCount {
                    path: ds.inputs[p.input].path().to_path_buf(),
                    piece: p.piece.index,
                });
            }
            let s = PieceStats::of_with(&slab, &ds.layout, |idx, q| {
                ks[idx] = Key {
                    code: guess.code([q[0] as i64, q[1] as i64, q[2] as i64]),
                    slab: i as u32,
                    idx: idx as u32,
                };
            });
            Ok((slab, s))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok((slabs, keys))
}

/// The Morton grid from the bounds the headers declare.
pub fn declared_grid(ds: &Dataset) -> MortonGrid {
    let mut min = [i64::MAX; 3];
    let mut max = [i64::MIN; 3];
    for (i, m) in ds.inputs.iter().zip(&ds.maps) {
        let h = i.header();
        for a in 0..3 {
            let g = mortar_core::grid::Grid { scale: h.scale, offset: h.offset };
            let lo = g.to_int(a, h.min[a]) * m.factor[a] + m.shift[a];
            let hi = g.to_int(a, h.max[a]) * m.factor[a] + m.shift[a];
            min[a] = min[a].min(lo.clamp(i32::MIN as i64, i32::MAX as i64));
            max[a] = max[a].max(hi.clamp(i32::MIN as i64, i32::MAX as i64));
        }
    }
    MortonGrid::for_bounds(min, max)
}

/// One key per record, slab by slab, in parallel.
pub fn make_keys(slabs: &[&[u8]], record_len: usize, morton: &MortonGrid) -> Result<Vec<Key>> {
    let n: usize = slabs.iter().map(|s| s.len() / record_len).sum();
    if slabs.len() > u32::MAX as usize
        || slabs.iter().any(|s| s.len() / record_len > u32::MAX as usize)
    {
        return Err(Error::TooManyPoints { what: "sort" });
    }
    let mut keys = key_buffer(n);
    let mut starts = Vec::with_capacity(slabs.len());
    let mut at = 0usize;
    for s in slabs {
        starts.push(at);
        at += s.len() / record_len;
    }
    let ptr = SendPtr(keys.as_mut_ptr());
    slabs.par_iter().zip(starts.par_iter()).enumerate().for_each(|(slab, (records, &start))| {
        let p = &ptr;
        for (idx, r) in records.chunks_exact(record_len).enumerate() {
            let q = read_xyz(r);
            let k = Key {
                code: morton.code([q[0] as i64, q[1] as i64, q[2] as i64]),
                slab: slab as u32,
                idx: idx as u32,
            };
            // SAFETY: slab ranges [start, start + len) partition 0..n; each slot written once.
            unsafe { p.write(start + idx, k) };
        }
    });
    // SAFETY: all n keys were written above.
    unsafe { keys.set_len(n) };
    Ok(keys)
}

/// A zeroed vector of `n` elements whose pages are backed by transparent huge pages where the
/// kernel offers them. The zero pages come from the allocator untouched, so the advice applies
/// before the first write.
pub(crate) fn zeroed_huge<T: bytemuck::Zeroable + Copy>(n: usize) -> Vec<T> {
    let v: Vec<T> = bytemuck::zeroed_vec(n);
    advise_huge(v.as_ptr() as usize, n * std::mem::size_of::<T>());
    v
}

fn advise_huge(addr: usize, bytes: usize) {
    let huge = 2usize << 20;
    if bytes >= 8 << 20 {
        let start = addr.next_multiple_of(huge);
        let end = (addr + bytes) / huge * huge;
        if end > start {
            // SAFETY: advice on memory the caller owns; it changes no contents.
            unsafe { libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE) };
        }
    }
}

/// A vector of `n` uninitialised keys whose pages are backed by transparent huge pages where
/// the kernel offers them (fewer page faults on the hundreds of MiB a large sort needs).
fn key_buffer(n: usize) -> Vec<Key> {
    let v: Vec<Key> = Vec::with_capacity(n);
    advise_huge(v.as_ptr() as usize, n * std::mem::size_of::<Key>());
    v
}

/// Orders the runs of keys that share a Morton code by the bits the code's shift dropped (the
/// full-resolution Morton order of their integer coordinates), then by input order.
///
/// With a shift of `s`, points up to `2^s - 1` grid units apart share a code. Input order alone
/// would break those ties, and an octree store cannot give input order back across leaves (two
/// such points may end in different leaves). With this refinement the order depends only on the
/// coordinates, except between points at the same position, which always share a leaf, where the
/// leaf's arrival order is the input order: so `sort store/` gives the bytes of `sort input`.
/// Without a shift, equal codes mean equal coordinates and nothing is done.
pub fn refine_ties(keys: &mut [Key], slabs: &[&[u8]], record_len: usize, morton: &MortonGrid) {
    if morton.shift == 0 || keys.len() < 2 {
        return;
    }
    let mask = (1i64 << morton.shift) - 1;
    let residual = |k: &Key| -> u64 {
        let r = &slabs[k.slab as usize][k.idx as usize * record_len..];
        let q = read_xyz(r);
        let low = |a: usize| ((q[a] as i64 - morton.origin[a]) & mask) as u32;
        mortar_core::morton::encode(low(0), low(1), low(2))
    };
    // Parts that never cut a run of equal codes, sorted in parallel.
    let parts = rayon::current_num_threads() * 8;
    let step = keys.len().div_ceil(parts).max(1);
    let mut cuts = vec![0usize];
    let mut at = step;
    while at < keys.len() {
        while at < keys.len() && keys[at].code == keys[at - 1].code {
            at += 1;
        }
        if at < keys.len() {
            cuts.push(at);
        }
        at += step;
    }
    cuts.push(keys.len());
    let mut pieces = Vec::with_capacity(cuts.len());
    let mut rest = keys;
    for w in cuts.windows(2) {
        let (a, r) = rest.split_at_mut(w[1] - w[0]);
        pieces.push(a);
        rest = r;
    }
    pieces.into_par_iter().for_each_init(Vec::new, |scratch: &mut Vec<(u64, Key)>, part| {
        let mut s = 0;
        while s < part.len() {
            let mut e = s + 1;
            while e < part.len() && part[e].code == part[s].code {
                e += 1;
            }
            if e - s > 1 {
                scratch.clear();
                scratch.extend(part[s..e].iter().map(|k| (residual(k), *k)));
                // Keys of one run are in input order; (slab, idx) keeps it among equal residuals.
                scratch.sort_unstable_by_key(|&(r, k)| (r, k.slab, k.idx));
                for (d, (_, k)) in part[s..e].iter_mut().zip(scratch.iter()) {
                    *d = *k;
                }
            }
            s = e;
        }
    });
}

/// Sorts keys: a parallel radix partition on the top 16 used bits of the code, then each bucket
/// sorted on its own (in cache).
pub fn sort_keys(mut keys: Vec<Key>) -> Vec<Key> {
    let n = keys.len();
    if n < (1 << 16) {
        keys.par_sort_unstable();
        return keys;
    }
    let max = keys.par_iter().map(|k| k.code).max().unwrap_or(0);
    let high = 64 - max.leading_zeros();
    let bits = high.min(16);
    let shift = high - bits;
    let nb = 1usize << bits;
    let parts = rayon::current_num_threads() * 4;
    let part_len = n.div_ceil(parts);
    let hists: Vec<Vec<u32>> = keys
        .par_chunks(part_len)
        .map(|c| {
            let mut h = vec![0u32; nb];
            for k in c {
                h[(k.code >> shift) as usize] += 1;
            }
            h
        })
        .collect();
    // bucket starts, and per-part write cursors
    let mut starts = vec![0usize; nb + 1];
    for b in 0..nb {
        starts[b + 1] = starts[b] + hists.iter().map(|h| h[b] as usize).sum::<usize>();
    }
    let mut cursors: Vec<Vec<usize>> = Vec::with_capacity(hists.len());
    let mut running = starts[..nb].to_vec();
    for h in &hists {
        cursors.push(running.clone());
        for b in 0..nb {
            running[b] += h[b] as usize;
        }
    }
    let mut out = key_buffer(n);
    let ptr = SendPtr(out.as_mut_ptr());
    keys.par_chunks(part_len).zip(cursors.into_par_iter()).for_each(|(c, mut cur)| {
        let p = &ptr;
        for k in c {
            let b = (k.code >> shift) as usize;
            // SAFETY: the cursors of all parts partition 0..n, each position is written once.
            unsafe { p.write(cur[b], *k) };
            cur[b] += 1;
        }
    });
    // SAFETY: every one of the n positions was written above.
    unsafe { out.set_len(n) };
    drop(keys);
    let mut slices = Vec::with_capacity(nb);
    let mut rest: &mut [Key] = &mut out;
    for b in 0..nb {
        let (a, r) = rest.split_at_mut(starts[b + 1] - starts[b]);
        if a.len() > 1 {
            slices.push(a);
        }
        rest = r;
    }
    slices.into_par_iter().for_each_init(Vec::new, |scratch, s| sort_bucket(s, shift, scratch));
    out
}

/// Sorts one bucket whose keys are in input order and share the code bits from `bits` up: a
/// stable LSD radix sort on the lower code bits (8 bits per pass, passes where every key has the
/// same digit skipped), so ties keep input order without comparing it.
pub(crate) fn sort_bucket(s: &mut [Key], bits: u32, scratch: &mut Vec<Key>) {
    if s.len() <= 32 {
        // insertion sort, stable
        for i in 1..s.len() {
            let k = s[i];
            let mut j = i;
            while j > 0 && s[j - 1].code > k.code {
                s[j] = s[j - 1];
                j -= 1;
            }
            s[j] = k;
        }
        return;
    }
    scratch.clear();
    scratch.extend_from_slice(s);
    let mut src_is_s = true;
    let mut shift = 0;
    while shift < bits {
        let mut count = [0usize; 256];
        {
            let src: &[Key] = if src_is_s { s } else { scratch };
            for k in src {
                count[((k.code >> shift) & 0xff) as usize] += 1;
            }
        }
        if count.contains(&s.len()) {
            shift += 8;
            continue;
        }
        let mut pos = [0usize; 256];
        let mut sum = 0;
        for d in 0..256 {
            pos[d] = sum;
            sum += count[d];
        }
        if src_is_s {
            for k in s.iter() {
                let d = ((k.code >> shift) & 0xff) as usize;
                scratch[pos[d]] = *k;
                pos[d] += 1;
            }
        } else {
            for k in scratch.iter() {
                let d = ((k.code >> shift) & 0xff) as usize;
                s[pos[d]] = *k;
                pos[d] += 1;
            }
        }
        src_is_s = !src_is_s;
        shift += 8;
    }
    if !src_is_s {
        s.copy_from_slice(scratch);
    }
}

/// Gathers records in key order, in chunks, and writes them to the sink. Gathering (parallel)
/// overlaps with the sink's work on the previous chunks.
pub fn emit(
    slabs: &[&[u8]],
    keys: &[Key],
    record_len: usize,
    chunk_points: usize,
    sink: &mut dyn OrderedSink,
) -> Result<()> {
    if sink.prefers_keyed() {
        for ks in keys.chunks(chunk_points.max(1)) {
            check_interrupted()?;
            sink.write_keyed(slabs, ks, record_len)?;
        }
        return Ok(());
    }
    let gather = |ks: &[Key]| gather(slabs, ks, record_len);
    let group = rayon::current_num_threads().max(2);
    let chunks: Vec<&[Key]> = keys.chunks(chunk_points.max(1)).collect();
    std::thread::scope(|scope| -> Result<()> {
        let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<u8>>(group);
        let writer = scope.spawn(move || -> Result<()> {
            for buf in rx {
                sink.write(&buf)?;
            }
            Ok(())
        });
        let mut send_failed = false;
        for g in chunks.chunks(group) {
            if check_interrupted().is_err() {
                break;
            }
            let bufs: Vec<Vec<u8>> = g.par_iter().map(|ks| gather(ks)).collect();
            for b in bufs {
                if tx.send(b).is_err() {
                    send_failed = true;
                    break;
                }
            }
            if send_failed {
                break;
            }
        }
        drop(tx);
        writer.join().map_err(|_| Error::ThreadPanicked { thread: "writer" })??;
        check_interrupted()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radix_sort_matches_std_sort() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        // keys come in input order (slab, idx); codes with many ties and with wide ranges
        for mask in [0x00ff_ffff_ffff_u64, 0x3ff, (1 << 62) - 1] {
            let keys: Vec<Key> = (0..300_000u32)
                .map(|i| Key { code: next() & mask, slab: i / 40_000, idx: i % 40_000 })
                .collect();
            let mut expect = keys.clone();
            expect.sort();
            assert_eq!(sort_keys(keys), expect, "mask {mask:x}");
        }
    }

    #[test]
    fn radix_sort_small_inputs() {
        let keys: Vec<Key> =
            (0..1000u32).map(|i| Key { code: (i as u64 * 7919) % 13, slab: 0, idx: i }).collect();
        let mut expect = keys.clone();
        expect.sort();
        assert_eq!(sort_keys(keys), expect);
    }
}
