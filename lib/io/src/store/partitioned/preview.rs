//! What readers of a partitioned build see before its final commit (issue 28 item 4): a coarse
//! picture of the whole cloud while pass 1 reads it, then the units filling in as they finish.
//!
//! - [`RootSample`]: pass 1 keeps the first point (in arrival order) of every cell of the root's
//!   128³ grid, the voxels the root will have, within a 32nd of `--memory` (cells beyond that
//!   are left out of the picture, never out of the store).
//! - Provisional commits ([`Preview::commit`]): the nodes the walk has finished (whole subtrees,
//!   real payloads in `nodes.bin`), and above them provisional inner nodes for their unfinished
//!   ancestors and the ancestors' other children, each holding the sample's points in its cube.
//!   An unfinished child has no children of its own: readers draw it as a frontier (its voxels,
//!   `LodIndex::new_partial`), so the tree is one octree at every commit. Provisional payloads
//!   are written once per node into a scratch segment ([`SCRATCH_SEGMENT`]), which the final
//!   commit drops and the build then removes: the finished store is the one an uncommitted build
//!   gives, byte for byte.
//!
//! Commits are at most `--commit-every` seconds apart (one per unit when it is 0).

use crate::error::{Error, Result};
use crate::store::format::*;
use crate::store::writer::StoreWriter;
use mortar_core::color::{ColorSource, RgbDepth};
use mortar_core::layout::{read_xyz, RecordLayout};
use mortar_core::octree::{Cube, NodeKey};
use std::collections::{HashMap, HashSet};
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

/// The segment provisional payloads go to while a partitioned build runs.
pub(crate) const SCRATCH_SEGMENT: u32 = 1;

/// Cells per axis of the root's grid (paper 004's 128³).
const GRID: i64 = 128;

/// The first point of every cell of the root's 128³ grid, in arrival order (pass 1).
pub(crate) struct RootSample {
    pub root: Cube,
    shift: u32,
    taken: Vec<u64>,
    pub pos: Vec<[i32; 3]>,
    pub records: Vec<u8>,
    rl: usize,
    cap: usize,
}

impl RootSample {
    /// An empty sample of `root`'s grid for records of `rl` bytes, holding at most a 32nd of
    /// `memory` (its commit codes it once more, beside it).
    pub(crate) fn new(root: Cube, rl: usize, memory: u64) -> RootSample {
        let cap = ((memory / 32) / (rl as u64 + 12)).min((GRID * GRID * GRID) as u64) as usize;
        RootSample {
            root,
            shift: (root.size_log2 as u32).saturating_sub(7),
            taken: vec![0; (GRID * GRID * GRID) as usize / 64],
            pos: Vec::new(),
            records: Vec::new(),
            rl,
            cap,
        }
    }

    #[inline]
    fn cell(&self, q: [i32; 3]) -> usize {
        let c = |a: usize| ((q[a] as i64 - self.root.min[a]) >> self.shift).clamp(0, GRID - 1);
        (c(0) | c(1) << 7 | c(2) << 14) as usize
    }

    #[inline]
    fn is_taken(&self, c: usize) -> bool {
        self.taken[c / 64] >> (c % 64) & 1 == 1
    }

    /// The records of `slab` (in arrival order) that are the first of a cell not taken yet:
    /// their indices. Run on pieces in parallel; [`absorb`](Self::absorb) them in arrival order.
    pub(crate) fn firsts(&self, slab: &[u8]) -> Vec<u32> {
        if self.pos.len() >= self.cap {
            return Vec::new();
        }
        // Cells seen in this piece: a bitmap (256 KiB), a few nanoseconds a point.
        let mut seen = vec![0u64; self.taken.len()];
        let mut out = Vec::new();
        for (i, r) in slab.chunks_exact(self.rl).enumerate() {
            let c = self.cell(read_xyz(r));
            let (w, b) = (c / 64, 1u64 << (c % 64));
            if (self.taken[w] | seen[w]) & b == 0 {
                seen[w] |= b;
                out.push(i as u32);
            }
        }
        out
    }

    /// Takes the cells of `firsts` (from [`firsts`](Self::firsts) of `slab`) still free.
    pub(crate) fn absorb(&mut self, slab: &[u8], firsts: &[u32]) {
        for &i in firsts {
            if self.pos.len() >= self.cap {
                return;
            }
            let r = &slab[i as usize * self.rl..(i as usize + 1) * self.rl];
            let q = read_xyz(r);
            let c = self.cell(q);
            if !self.is_taken(c) {
                self.taken[c / 64] |= 1 << (c % 64);
                self.pos.push(q);
                self.records.extend_from_slice(r);
            }
        }
    }

    /// The integer bounds of the sample's points.
    fn bounds(&self) -> ([i32; 3], [i32; 3]) {
        let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
        for p in &self.pos {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        if self.pos.is_empty() {
            ([0; 3], [0; 3])
        } else {
            (lo, hi)
        }
    }
}

/// The provisional commits of one partitioned build.
pub(crate) struct Preview {
    pub sample: Option<RootSample>,
    color: Option<ColorSource>,
    layout: RecordLayout,
    scratch: std::fs::File,
    scratch_path: PathBuf,
    scratch_len: u64,
    /// Provisional payloads written, by key.
    made: HashMap<NodeKey, NodeEntry>,
    every: f64,
    last: Option<Instant>,
    leaf_capacity: u32,
    /// Commits made.
    pub commits: u64,
}

impl Preview {
    /// Starts the scratch segment of `writer`'s store (commits at most `every` seconds apart).
    pub(crate) fn new(
        writer: &StoreWriter,
        layout: RecordLayout,
        every: f64,
        leaf_capacity: u32,
    ) -> Result<Preview> {
        let scratch_path = writer.dir.join(segment_file(SCRATCH_SEGMENT));
        let scratch =
            std::fs::File::create(&scratch_path).map_err(|e| Error::io(&scratch_path, e))?;
        Ok(Preview {
            sample: None,
            color: None,
            layout,
            scratch,
            scratch_path,
            scratch_len: 0,
            made: HashMap::new(),
            every,
            last: None,
            leaf_capacity,
            commits: 0,
        })
    }

    /// Whether a commit is due.
    pub(crate) fn due(&self) -> bool {
        self.every.is_finite() && self.last.is_none_or(|t| t.elapsed().as_secs_f64() >= self.every)
    }

    /// Takes a new sample (pass 1 read more, or made its partition again): what was drawn from
    /// the old one is written again.
    pub(crate) fn set_sample(&mut self, s: RootSample) {
        self.made.clear();
        self.color = None;
        self.sample = Some(s);
    }

    fn color(&mut self) -> ColorSource {
        if let Some(c) = self.color {
            return c;
        }
        let rec = self.sample.as_ref().map_or(&[][..], |s| &s.records[..]);
        let c = color_of(rec, &self.layout);
        self.color = Some(c);
        c
    }

    /// The provisional inner node `key` (the sample's points in its cube), written once.
    fn provisional(&mut self, key: NodeKey) -> Result<NodeEntry> {
        if let Some(e) = self.made.get(&key) {
            return Ok(*e);
        }
        let color = self.color();
        let sample = self.sample.take();
        let e = self.write_node(key, sample.as_ref(), color);
        self.sample = sample;
        let e = e?;
        self.made.insert(key, e);
        Ok(e)
    }

    /// Writes the provisional inner node `key` of `sample`'s points in its cube.
    fn write_node(
        &mut self,
        key: NodeKey,
        sample: Option<&RootSample>,
        color: ColorSource,
    ) -> Result<NodeEntry> {
        let (inside, rl, al) = match sample {
            Some(s) => {
                let cube = key.cube_in(s.root);
                let edge = 1i64 << cube.size_log2;
                let inside: Vec<usize> = (0..s.pos.len())
                    .filter(|&i| {
                        (0..3).all(|a| {
                            let v = s.pos[i][a] as i64 - cube.min[a];
                            (0..edge).contains(&v)
                        })
                    })
                    .collect();
                (inside, s.rl, s.rl - 12)
            }
            None => (Vec::new(), self.layout.record_len, self.layout.record_len - 12),
        };
        let empty: &[u8] = &[];
        let s = sample;
        let rec = |i: usize| s.map_or(empty, |s| &s.records[inside[i] * rl..(inside[i] + 1) * rl]);
        let (mut e, b) = crate::store::codec::encode_payload(
            key,
            INNER,
            inside.len(),
            al,
            |i| read_xyz(rec(i)),
            |i| color.rgba(rec(i)),
            |i| &rec(i)[12..],
            None,
        )
        .map_err(|error| Error::Payload { path: self.scratch_path.clone(), error })?;
        self.scratch.write_all(&b).map_err(|err| Error::io(&self.scratch_path, err))?;
        e.segment = SCRATCH_SEGMENT;
        e.offset = self.scratch_len;
        self.scratch_len += b.len() as u64;
        Ok(e)
    }

    /// Commits the root alone, a frontier of `sample`'s points: what pass 1 has read so far.
    pub(crate) fn commit_sample(
        &mut self,
        writer: &mut StoreWriter,
        sample: &RootSample,
    ) -> Result<()> {
        let color = color_of(&sample.records, &self.layout);
        let e = self.write_node(NodeKey::ROOT, Some(sample), color)?;
        self.finish(writer, sample.root, vec![e], 0, sample.bounds())
    }

    fn finish(
        &mut self,
        writer: &mut StoreWriter,
        root: Cube,
        entries: Vec<NodeEntry>,
        points: u64,
        bounds: ([i32; 3], [i32; 3]),
    ) -> Result<()> {
        self.scratch.sync_data().map_err(|e| Error::io(&self.scratch_path, e))?;
        writer.entries = entries.into_iter().map(Some).collect();
        writer.segments = vec![self.scratch_len];
        writer.write_hierarchy(root, points, self.leaf_capacity, bounds)?;
        self.last = Some(Instant::now());
        self.commits += 1;
        Ok(())
    }

    /// Commits the finished nodes `done` (whole subtrees, in `writer`'s `nodes.bin`, holding
    /// `points` points in their leaves; `bounds` of every point where known) under provisional
    /// nodes for everything not finished, in `root`.
    pub(crate) fn commit(
        &mut self,
        writer: &mut StoreWriter,
        root: Cube,
        done: &[NodeEntry],
        points: u64,
        bounds: Option<([i32; 3], [i32; 3])>,
    ) -> Result<()> {
        let finished: HashSet<NodeKey> = done.iter().map(key_of).collect();
        if finished.contains(&NodeKey::ROOT) {
            return Ok(());
        }
        // The unfinished ancestors of finished subtrees, and their unfinished children.
        let mut above: HashSet<NodeKey> = HashSet::from([NodeKey::ROOT]);
        for k in &finished {
            let mut k = *k;
            while let Some(p) = k.parent() {
                if !above.insert(p) {
                    break;
                }
                k = p;
            }
        }
        let mut keys: Vec<NodeKey> = above.iter().copied().collect();
        for a in &above {
            for o in 0..8 {
                let c = a.child(o);
                if !finished.contains(&c) && !above.contains(&c) {
                    keys.push(c);
                }
            }
        }
        keys.sort_by_key(|k| (k.level, k.index));
        let mut entries = Vec::with_capacity(keys.len() + done.len());
        for k in keys {
            entries.push(self.provisional(k)?);
        }
        entries.extend_from_slice(done);
        // The root first; the rest in any order a reader accepts.
        entries.sort_by_key(|e| e.level);
        let bounds =
            bounds.unwrap_or_else(|| self.sample.as_ref().map_or(([0; 3], [0; 3]), |s| s.bounds()));
        self.finish(writer, root, entries, points, bounds)
    }

    /// Drops the scratch segment: after the final commit (which names no provisional node).
    pub(crate) fn remove(self) {
        drop(self.scratch);
        let _ = std::fs::remove_file(&self.scratch_path);
    }
}

/// The colours of provisional nodes: the build's rule over the sample's records.
fn color_of(records: &[u8], layout: &RecordLayout) -> ColorSource {
    let st = crate::sort::PieceStats::of(records, layout);
    match layout.attribute("rgb") {
        Some(a) if st.max_rgb > 0 => {
            ColorSource::Rgb { offset: a.offset, depth: RgbDepth::detect(st.max_rgb) }
        }
        _ => ColorSource::Intensity { max_intensity: st.max_intensity },
    }
}

fn key_of(e: &NodeEntry) -> NodeKey {
    NodeKey { level: e.level as u8, index: e.index }
}

/// Removes what the provisional commits of a stopped build left in the store `dir` (its
/// hierarchy and scratch segment), so that `--resume` continues from the build's state alone.
pub(crate) fn drop_provisional(dir: &std::path::Path) -> Result<()> {
    for f in [HIERARCHY_FILE.to_string(), segment_file(SCRATCH_SEGMENT)] {
        let p = dir.join(f);
        match std::fs::remove_file(&p) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(Error::io(&p, e)),
            _ => {}
        }
    }
    Ok(())
}
