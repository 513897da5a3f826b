//! The merge of a distributed build (`mortar merge`): the parts checked to be every job of one
//! plan once, each part's `nodes.bin` linked into the store as a payload segment of its own (a
//! hard link: no byte copied, the part stays intact until it is removed; copied where the part
//! lies on another file system), or its payloads coded again into the store's `nodes.bin` where
//! its colour scale is not the whole input's or a leaf above the cut absorbs some of its nodes;
//! the nodes above the cut made from the subtrees' candidates, and the entries committed in the
//! one-machine order.

use super::cut::morton;
use super::part::{color_of, read_part, Part, CANDIDATES_FILE};
use super::plan::Plan;
use crate::cleanup::TempPath;
use crate::error::{Error, JobError, PartError, Result};
use crate::store::arrival::{
    self, BlockCache, ColorMaxima, DeclaredBox, RankCheck, RankFault, RankFile, SharedBlocks,
};
use crate::store::codec::Order;
use crate::store::format::*;
use crate::store::runs::Cands;
use crate::store::writer::StoreWriter;
use mortar_core::color::ColorSource;
use mortar_core::layout::read_xyz;
use mortar_core::octree::{splits, Cube, NodeKey};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What a merge reports.
#[derive(Clone, Debug, Default, Serialize)]
pub struct MergeReport {
    pub parts: usize,
    pub points: u64,
    pub nodes: u64,
    /// Nodes above the cut, made by the merge.
    pub top_nodes: u64,
    /// Parts whose payloads were recoloured (coded again into the store's `nodes.bin`).
    pub recoloured_parts: usize,
    /// Parts whose `nodes.bin` was linked into the store as a segment, no byte copied.
    pub linked_parts: usize,
    /// Bytes of parts' payloads copied (parts on another file system than the store, where a
    /// link cannot be made, and parts with recoloured or absorbed nodes).
    pub copied_bytes: u64,
    pub seconds: f64,
}

/// Merges the parts `dirs` (every job of one plan, once each) into the store `out`.
pub fn merge(dirs: &[PathBuf], out: &Path) -> Result<MergeReport> {
    let t0 = Instant::now();
    if dirs.is_empty() {
        return Err(Error::Job { error: JobError::NoParts });
    }
    let parts: Vec<Part> = dirs.iter().map(|d| read_part(d)).collect::<Result<_>>()?;
    let plan = &parts[0].file.plan;
    let mut by_job: Vec<Option<usize>> = vec![None; plan.jobs.len()];
    for (i, p) in parts.iter().enumerate() {
        if p.file.plan.id != plan.id || p.file.plan != *plan {
            return Err(Error::Part {
                path: p.dir.clone(),
                error: PartError::OtherPlan {
                    id: p.file.plan.id.clone(),
                    first: parts[0].dir.clone(),
                    first_id: plan.id.clone(),
                },
            });
        }
        match by_job.get_mut(p.file.job) {
            Some(Some(o)) => {
                return Err(Error::Part {
                    path: p.dir.clone(),
                    error: PartError::Repeated { job: p.file.job, first: parts[*o].dir.clone() },
                })
            }
            Some(slot) => *slot = Some(i),
            None => {
                return Err(Error::Part {
                    path: p.dir.clone(),
                    error: PartError::NoSuchJob { job: p.file.job, jobs: plan.jobs.len() },
                })
            }
        }
    }
    if let Some(j) = by_job.iter().position(|s| s.is_none()) {
        let missing: Vec<usize> =
            by_job.iter().enumerate().filter(|(_, s)| s.is_none()).map(|(j, _)| j).collect();
        return Err(Error::Job {
            error: JobError::MissingParts { jobs: plan.jobs.len(), first: j, missing },
        });
    }
    let source =
        std::fs::read(parts[0].dir.join(SOURCE_FILE)).map_err(|e| Error::io(&parts[0].dir, e))?;
    for p in &parts[1..] {
        if std::fs::read(p.dir.join(SOURCE_FILE)).ok().as_deref() != Some(&source[..]) {
            return Err(Error::Part {
                path: p.dir.clone(),
                error: PartError::OtherInputs { first: parts[0].dir.clone() },
            });
        }
    }
    if out.exists()
        && !(out.is_dir()
            && std::fs::read_dir(out).map_err(|e| Error::io(out, e))?.next().is_none())
    {
        return Err(Error::Store {
            path: out.to_path_buf(),
            error: crate::error::StoreError::NotEmpty,
        });
    }
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if !parent.is_dir() {
        return Err(Error::NoParentDirectory {
            path: out.to_path_buf(),
            parent: parent.to_path_buf(),
        });
    }
    // The whole input's statistics and colours.
    let f0 = &parts[0].file;
    let rl = f0.record_len;
    let (mut lo, mut hi, mut max_rgb, mut max_int, mut points) =
        ([i32::MAX; 3], [i32::MIN; 3], 0u16, 0u16, 0u64);
    for p in &parts {
        let f = &p.file;
        if f.points > 0 || f.min[0] <= f.max[0] {
            for a in 0..3 {
                lo[a] = lo[a].min(f.min[a]);
                hi[a] = hi[a].max(f.max[a]);
            }
        }
        max_rgb = max_rgb.max(f.max_rgb);
        max_int = max_int.max(f.max_intensity);
        points += f.points;
    }
    if lo[0] > hi[0] {
        (lo, hi) = ([0; 3], [0; 3]);
    }
    let color = color_of(f0.rgb_offset, max_rgb, max_int);
    let layout = crate::source::LasInput::open(&parts[0].dir.join(SOURCE_FILE))?.layout.clone();
    // The store, in a temporary directory.
    let tmp = TempPath::beside(out);
    let dir = tmp.path().to_path_buf();
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    std::fs::write(dir.join(SOURCE_FILE), &source).map_err(|e| Error::io(&dir, e))?;
    std::fs::copy(
        parts[0].dir.join(crate::store::record::RECORD_FILE),
        dir.join(crate::store::record::RECORD_FILE),
    )
    .map_err(|e| Error::io(&parts[0].dir, e))?;
    let np = dir.join(NODES_FILE);
    let nodes_file = std::fs::File::create(&np).map_err(|e| Error::io(&np, e))?;
    let reader = std::fs::File::open(&np).map_err(|e| Error::io(&np, e))?;
    let mut writer = StoreWriter {
        dir: dir.clone(),
        nodes: nodes_file,
        reader,
        nodes_len: 0,
        entries: Vec::new(),
        commit: 0,
        last_revision: None,
        record_len: rl,
        layout: layout.clone(),
        guard: None,
        group_bytes: crate::store::writer::COMMIT_GROUP_BYTES,
        segments: Vec::new(),
    };
    // The parts' arrival ranks, where every part has them (a part of an older mortar has none:
    // the store then has none either, and is extended from its inputs).
    let ranks = part_ranks(&parts)?;
    // The subtrees' candidates, counts and places in their part's listing of ranks.
    let mut subtrees: HashMap<NodeKey, Subtree> = HashMap::new();
    for (pi, p) in parts.iter().enumerate() {
        let mut listed = 0usize;
        let cp = p.dir.join(CANDIDATES_FILE);
        let b = std::fs::read(&cp).map_err(|e| Error::io(&cp, e))?;
        let mut at = 0usize;
        let one = 20 + rl;
        for n in &p.file.nodes {
            let mut c = Cands::default();
            let end = at + n.candidates as usize * one;
            if end > b.len() {
                return Err(Error::Part {
                    path: cp.clone(),
                    error: PartError::Damaged { what: "shorter than part.json says" },
                });
            }
            while at < end {
                let q = [0, 1, 2].map(|a| {
                    i32::from_le_bytes(b[at + 4 * a..at + 4 * a + 4].try_into().expect("4 bytes"))
                });
                c.push(
                    q,
                    u64::from_le_bytes(b[at + 12..at + 20].try_into().expect("8 bytes")),
                    &b[at + 20..at + one],
                );
                at += one;
            }
            subtrees.insert(
                NodeKey { level: n.key[0] as u8, index: [n.key[1], n.key[2], n.key[3]] },
                Subtree {
                    count: n.points,
                    cands: c,
                    part: pi,
                    listed: listed..listed + n.points as usize,
                },
            );
            listed += n.points as usize;
        }
    }
    // The nodes above the cut, from the subtrees' candidates; written after the parts' nodes.
    let mut top = Top {
        subtrees,
        parts: &parts,
        plan,
        color,
        rl,
        layout: layout.clone(),
        made: Vec::new(),
        absorbed: std::collections::HashSet::new(),
        cache: None,
        ranks: ranks.as_ref(),
    };
    let listing = match top.visit(NodeKey::ROOT, plan.root())? {
        Visit::Big { ranks, .. } => ranks,
        // Few points in all: the root is a leaf (held as it is where the cut is the root).
        Visit::Small { records, ranks: SmallRanks::Gathered(r, from), .. } => {
            vec![top.leaf(NodeKey::ROOT, &records, r, from)?]
        }
        Visit::Small { ranks: SmallRanks::Kept { part, listed, .. }, .. } => {
            vec![RankRun::Part { part, listed }]
        }
    };
    let Top { made, absorbed, .. } = top;
    let mut all: Vec<NodeEntry> = Vec::new();
    let (mut recoloured, mut linked, mut copied_bytes) = (0, 0, 0u64);
    for p in &parts {
        let f = &p.file;
        let same_color = color_of(f.rgb_offset, f.max_rgb, f.max_intensity) == color;
        let src = p.dir.join(NODES_FILE);
        let absorbs = p.entries.iter().any(|e| absorbed.contains(&(e.level, e.index)));
        if same_color && !absorbs {
            // The part's payloads as they are: its nodes.bin becomes a segment of the store,
            // linked in (no byte copied; the part can be removed afterwards) or, across file
            // systems, copied whole.
            let seg = writer.segments.len() as u32 + 1;
            let to = dir.join(segment_file(seg));
            if std::fs::hard_link(&src, &to).is_ok() {
                linked += 1;
            } else {
                std::fs::copy(&src, &to).map_err(|e| Error::io(&src, e))?;
                std::fs::File::open(&to)
                    .and_then(|f| f.sync_all())
                    .map_err(|e| Error::io(&to, e))?;
                copied_bytes += f.nodes_len;
            }
            writer.segments.push(f.nodes_len);
            all.extend(p.entries.iter().map(|e| NodeEntry { segment: seg, ..*e }));
        } else {
            recoloured += !same_color as usize;
            let bytes = std::fs::read(&src).map_err(|e| Error::io(&src, e))?;
            let keep: Vec<&NodeEntry> =
                p.entries.iter().filter(|e| !absorbed.contains(&(e.level, e.index))).collect();
            // Recoloured payloads may code to other lengths: made first, then placed.
            let made: Vec<Vec<u8>> = keep
                .par_iter()
                .map(|e| {
                    let b = &bytes[e.offset as usize..(e.offset + e.length) as usize];
                    if same_color {
                        Ok(b.to_vec())
                    } else {
                        let key = NodeKey { level: e.level as u8, index: e.index };
                        recolour(b, &color, rl, Order::of(plan.root(), key, &layout))
                            .map_err(|error| Error::Payload { path: p.dir.clone(), error })
                    }
                })
                .collect::<Result<_>>()?;
            let lens: Vec<u64> = made.iter().map(|b| b.len() as u64).collect();
            copied_bytes += lens.iter().sum::<u64>();
            let offs = writer.reserve(&lens);
            let w = &writer;
            let done: Vec<NodeEntry> = keep
                .par_iter()
                .zip(made)
                .zip(offs)
                .map(|((e, b), off)| {
                    w.write_at(off, &b)?;
                    Ok(NodeEntry { offset: off, length: b.len() as u64, ..**e })
                })
                .collect::<Result<_>>()?;
            all.extend(done);
        }
    }
    let top_nodes = made.len() as u64;
    for (mut e, b) in made {
        let off = writer.reserve(&[b.len() as u64])[0];
        writer.write_at(off, &b)?;
        e.offset = off;
        all.push(e);
    }
    // The one-machine order: level by level, Morton order in a level.
    all.sort_by_key(|e| (e.level, morton(e.index, e.level as u8)));
    for (i, e) in all.iter().enumerate() {
        writer.set_entry(i, *e);
    }
    writer.write_hierarchy(plan.root(), points, plan.leaf_capacity, (lo, hi))?;
    drop(writer);
    if let Some(r) = &ranks {
        let colors = ColorMaxima { max_rgb, max_intensity: max_int };
        r.write(&dir, &listing, points, colors, dirs)?;
    }
    tmp.persist(out).map_err(|e| Error::io(out, e))?;
    Ok(MergeReport {
        parts: parts.len(),
        points,
        nodes: all.len() as u64,
        top_nodes,
        recoloured_parts: recoloured,
        linked_parts: linked,
        copied_bytes,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// The payload `b` (coded or raw) with its colours rewritten by `color` (from its records:
/// position and attributes), coded again.
fn recolour(
    b: &[u8],
    color: &ColorSource,
    rl: usize,
    order: Option<Order>,
) -> std::result::Result<Vec<u8>, PayloadError> {
    let raw = crate::store::codec::decode(b)?;
    let d = DecodedLeaf::parse(&raw)?;
    let n = d.count;
    if d.attr_len + 12 != rl {
        return Err(PayloadError::RecordLength);
    }
    let mut rec = vec![0u8; rl];
    let cols: Vec<u32> = (0..n)
        .map(|i| {
            let p = d.position(i);
            for a in 0..3 {
                rec[4 * a..4 * a + 4].copy_from_slice(&p[a].to_le_bytes());
            }
            rec[12..].copy_from_slice(d.attributes(i));
            color.rgba(&rec)
        })
        .collect();
    let mut out = raw.to_vec();
    let at = 64 + 12 * n;
    for (i, c) in cols.iter().enumerate() {
        out[at + 4 * i..at + 4 * i + 4].copy_from_slice(&c.to_le_bytes());
    }
    Ok(crate::store::codec::encode(out, order))
}

/// What the walk above the cut gives a parent.
enum Visit {
    /// A node with more points than a leaf holds (inner, written): its candidates, and where
    /// its leaves' arrival ranks come from (in the store's listing order).
    Big { cands: Cands, count: u64, ranks: Vec<RankRun> },
    /// A node with at most a leaf's points: a leaf, unless its parent is a leaf too. Its
    /// candidates, its records in Morton order (ties in arrival order) and their ranks
    /// ([`SmallRanks::Kept`] where it is a subtree of the cut whose part holds it as a leaf
    /// already).
    Small { cands: Cands, count: u64, records: Vec<u8>, ranks: SmallRanks },
}

/// A subtree of the cut as its part holds it.
struct Subtree {
    /// Its points.
    count: u64,
    /// Its candidates for its parent.
    cands: Cands,
    /// The part holding it.
    part: usize,
    /// Its leaves' places in the part's listing of arrival ranks.
    listed: std::ops::Range<usize>,
}

/// Where a run of the store's listing of arrival ranks (`arrival.bin`: leaves depth first, each
/// leaf's points in its coded order) comes from.
enum RankRun {
    /// Places of a part's listing: a subtree, or a leaf, kept as its part built it.
    Part { part: usize, listed: std::ops::Range<usize> },
    /// A leaf the merge made: its ranks in its coded order, and a part they came from (named
    /// where they are wrong).
    Made(Vec<u64>, usize),
}

/// The arrival ranks of a node small enough to be a leaf.
enum SmallRanks {
    /// A leaf its part holds: its places in the part's listing and its payload's coded order
    /// (`decode_ordered`'s: `coded[i]` is the coded place of payload point `i`).
    Kept { part: usize, listed: std::ops::Range<usize>, coded: Option<Vec<u32>> },
    /// The ranks of records gathered here, in their (Morton) order (none without ranks), and
    /// a part they came from.
    Gathered(Vec<u64>, usize),
}

/// The parts' arrival ranks (`arrival.bin` in each part: its leaves' ranks among all inputs,
/// its subtrees in the job's order, each as the partitioned engine lists it).
struct Ranks {
    files: Vec<RankFile>,
    /// The box the inputs' headers declare (every part's).
    declared: DeclaredBox,
}

/// Ranks decoded at once while the store's listing is coded (as `arrival::write_blocks`
/// codes them; with the blocks of the parts' listings kept, about 0.2 GiB at the peak).
const RANK_BLOCKS_AT_ONCE: usize = 8;

/// The parts' ranks where every part has them, their counts and declared boxes checked.
fn part_ranks(parts: &[Part]) -> Result<Option<Ranks>> {
    let mut files = Vec::with_capacity(parts.len());
    for p in parts {
        let Some(f) = RankFile::open(&p.dir, p.file.points)? else { return Ok(None) };
        if p.file.nodes.iter().map(|n| n.points).sum::<u64>() != p.file.points {
            return Err(Error::Part {
                path: p.dir.clone(),
                error: PartError::Damaged { what: "its subtrees' points are not its points" },
            });
        }
        if let Some(first) = files.first().map(|f: &RankFile| f.declared) {
            if f.declared != first {
                return Err(Error::Part {
                    path: p.dir.clone(),
                    error: PartError::OtherInputs { first: parts[0].dir.clone() },
                });
            }
        }
        files.push(f);
    }
    let declared = files.first().and_then(|f| f.declared);
    Ok(Some(Ranks { files, declared }))
}

impl Ranks {
    /// Appends the ranks of `part`'s listing places `listed` to `out`.
    fn copy(
        &self,
        part: usize,
        listed: std::ops::Range<usize>,
        cache: &mut BlockCache,
        out: &mut Vec<u64>,
    ) -> Result<()> {
        self.files[part].copy(listed, cache, out)
    }

    /// Writes the store's `arrival.bin` into `dir`: the `points` ranks of `listing`, with the
    /// inputs' colour maxima `colors`, a few blocks at a time; checked to be a permutation of
    /// `0..points` as they are listed (a bit a point), else a part whose listing holds the
    /// wrong rank is named (of a rank given twice, the one found second: blocks are listed in
    /// parallel). `parts` are the parts' directories.
    fn write(
        &self,
        dir: &Path,
        listing: &[RankRun],
        points: u64,
        colors: ColorMaxima,
        parts: &[PathBuf],
    ) -> Result<()> {
        let len = |r: &RankRun| match r {
            RankRun::Part { listed, .. } => listed.len(),
            RankRun::Made(v, _) => v.len(),
        };
        let mut starts = Vec::with_capacity(listing.len());
        let mut at = 0usize;
        for r in listing {
            starts.push(at);
            at += len(r);
        }
        if at as u64 != points {
            return Err(Error::Internal {
                path: dir.to_path_buf(),
                what: "the merge lists another count of arrival ranks than the store's points",
            });
        }
        let shared: Vec<SharedBlocks> =
            self.files.iter().map(|f| SharedBlocks::new(f, RANK_BLOCKS_AT_ONCE + 2)).collect();
        let check = RankCheck::of_len(points);
        let checked = |part: usize, ranks: &[u64]| -> Result<()> {
            check.mark_ranks(ranks).map_err(|f| Error::Part {
                path: parts[part].clone(),
                error: PartError::Ranks {
                    why: match f {
                        RankFault::Beyond(r) => {
                            format!("rank {r} is not below the inputs' {points} points")
                        }
                        RankFault::Twice(r) => format!("rank {r} is given twice"),
                    },
                },
            })
        };
        let fill = |r: std::ops::Range<usize>, out: &mut Vec<u64>| -> Result<()> {
            let first = starts.partition_point(|&s| s <= r.start).saturating_sub(1);
            for (run, &s) in listing[first..].iter().zip(&starts[first..]) {
                if s >= r.end {
                    break;
                }
                let (a, b) = (r.start.max(s) - s, r.end.min(s + len(run)) - s);
                if a >= b {
                    continue;
                }
                let at = out.len();
                match run {
                    RankRun::Part { part, listed } => {
                        shared[*part].copy(listed.start + a..listed.start + b, out)?;
                        checked(*part, &out[at..])?;
                        // The listing meets the parts one after another: once a part's last
                        // rank is read, its blocks are not kept (a reader still inside it
                        // holds what it took, or decodes it again).
                        if listed.start + b == self.files[*part].len() {
                            shared[*part].forget();
                        }
                    }
                    RankRun::Made(v, part) => {
                        out.extend_from_slice(&v[a..b]);
                        checked(*part, &out[at..])?;
                    }
                }
            }
            Ok(())
        };
        arrival::write_blocks(
            dir,
            points as usize,
            fill,
            self.declared,
            colors,
            RANK_BLOCKS_AT_ONCE,
        )
    }
}

/// The walk over the nodes above the cut.
struct Top<'a> {
    subtrees: HashMap<NodeKey, Subtree>,
    parts: &'a [Part],
    plan: &'a Plan,
    color: ColorSource,
    rl: usize,
    layout: mortar_core::layout::RecordLayout,
    /// Payloads made here (offsets set when written).
    made: Vec<(NodeEntry, Vec<u8>)>,
    /// Nodes of the parts that a leaf above them holds: not copied.
    absorbed: std::collections::HashSet<(u32, [u32; 3])>,
    /// The parts' ranks (`None`: the store gets none), and the part and block decoded last
    /// (one for all parts: the walk meets the parts one after another, and a block is 8 MiB).
    ranks: Option<&'a Ranks>,
    cache: Option<(usize, BlockCache)>,
}

impl Top<'_> {
    fn visit(&mut self, key: NodeKey, cube: Cube) -> Result<Visit> {
        if let Some(Subtree { count, cands, part: pi, listed }) = self.subtrees.remove(&key) {
            if count > self.plan.leaf_capacity as u64 {
                let ranks = vec![RankRun::Part { part: pi, listed }];
                return Ok(Visit::Big { cands, count, ranks });
            }
            // A leaf in its part: its records, in case the node above is a leaf too.
            let p = &self.parts[pi];
            let e = p
                .entries
                .iter()
                .find(|e| e.level == key.level as u32 && e.index == key.index && e.kind == LEAF)
                .ok_or_else(|| Error::Part {
                    path: p.dir.clone(),
                    error: PartError::NoLeaf { subtree: key.name() },
                })?;
            let src = p.dir.join(NODES_FILE);
            let mut b = vec![0u8; e.length as usize];
            {
                use std::os::unix::fs::FileExt;
                let f = std::fs::File::open(&src).map_err(|x| Error::io(&src, x))?;
                f.read_exact_at(&mut b, e.offset).map_err(|x| Error::io(&src, x))?;
            }
            let (records, coded) = records_of(&b, self.rl)
                .map_err(|error| Error::Payload { path: p.dir.clone(), error })?;
            let ranks = SmallRanks::Kept { part: pi, listed, coded };
            return Ok(Visit::Small { cands, count, records, ranks });
        }
        if key.level >= self.plan.cell_depth {
            return Err(Error::Job { error: JobError::Uncovered { node: key.name() } });
        }
        let mut kids = Vec::with_capacity(8);
        let mut voxels = Cands::default();
        let mut count = 0;
        for o in 0..8 {
            let mut v = self.visit(key.child(o), cube.child(o))?;
            let (Visit::Big { cands, count: n, .. } | Visit::Small { cands, count: n, .. }) =
                &mut v;
            voxels.append(std::mem::take(cands));
            count += *n;
            kids.push(v);
        }
        let rl = self.rl;
        let up = |voxels: &Cands| voxels.pick(&voxels.for_parent(key, cube), rl);
        if count <= self.plan.leaf_capacity as u64 {
            // A leaf of the one-machine tree (unless its parent is one too): the points below,
            // children in octant order, which is Morton order; their ranks in that order.
            let mut records = Vec::with_capacity(count as usize * rl);
            let mut gathered = Vec::new();
            let mut from = None;
            for k in kids {
                if let Visit::Small { records: r, ranks, .. } = k {
                    records.extend_from_slice(&r);
                    from = from.or(self.gather(ranks, &mut gathered)?);
                }
            }
            self.absorb_below(key);
            let ranks = SmallRanks::Gathered(gathered, from.unwrap_or(0));
            return Ok(Visit::Small { cands: up(&voxels), count, records, ranks });
        }
        if !splits(count, key, cube, &self.plan.config()) {
            return Err(Error::Job { error: JobError::CannotSplit { node: key.name(), count } });
        }
        // Inner: small children are leaves; those the parts hold as leaves stay as they are.
        let mut runs = Vec::new();
        for (o, k) in kids.into_iter().enumerate() {
            match k {
                Visit::Big { ranks, .. } => runs.extend(ranks),
                Visit::Small { ranks: SmallRanks::Kept { part, listed, .. }, .. } => {
                    runs.push(RankRun::Part { part, listed })
                }
                Visit::Small { records, ranks: SmallRanks::Gathered(r, from), .. } => {
                    runs.push(self.leaf(key.child(o), &records, r, from)?)
                }
            }
        }
        let color = &self.color;
        let (e, b) = crate::store::codec::encode_payload(
            key,
            INNER,
            voxels.pos.len(),
            rl - 12,
            |i| voxels.pos[i],
            |i| color.rgba(&voxels.records[i * rl..(i + 1) * rl]),
            |i| &voxels.records[i * rl + 12..(i + 1) * rl],
            Order::of(self.plan.root(), key, &self.layout),
        )
        .map_err(|m| Error::MergePayload { error: m.in_node(key.name()) })?;
        self.made.push((e, b));
        Ok(Visit::Big { cands: up(&voxels), count, ranks: runs })
    }

    /// Appends the ranks of a small node's records, in their order, to `out` (nothing without
    /// ranks); the part they came from, where any.
    fn gather(&mut self, ranks: SmallRanks, out: &mut Vec<u64>) -> Result<Option<usize>> {
        let Some(rk) = self.ranks else { return Ok(None) };
        Ok(Some(match ranks {
            SmallRanks::Gathered(r, from) => {
                out.extend_from_slice(&r);
                from
            }
            SmallRanks::Kept { part, listed, coded } => {
                let mut listed_ranks = Vec::with_capacity(listed.len());
                if self.cache.as_ref().is_none_or(|(p, _)| *p != part) {
                    self.cache = Some((part, None));
                }
                let (_, cache) = self.cache.as_mut().expect("just set");
                rk.copy(part, listed, cache, &mut listed_ranks)?;
                match coded {
                    // The part lists them in coded order: payload point i is coded at c[i].
                    Some(c) if c.len() == listed_ranks.len() => {
                        out.extend(c.iter().map(|&t| listed_ranks[t as usize]))
                    }
                    Some(_) => {
                        return Err(Error::Part {
                            path: self.parts[part].dir.clone(),
                            error: PartError::Damaged {
                                what: "a leaf's coded order and its ranks disagree",
                            },
                        })
                    }
                    None => out.extend_from_slice(&listed_ranks),
                }
                part
            }
        }))
    }

    /// Marks every subtree of the cut under `key` as held by a leaf above.
    fn absorb_below(&mut self, key: NodeKey) {
        for p in self.parts {
            for n in &p.file.nodes {
                let k = NodeKey { level: n.key[0] as u8, index: [n.key[1], n.key[2], n.key[3]] };
                if k.level >= key.level
                    && (0..3).all(|a| k.index[a] >> (k.level - key.level) == key.index[a])
                {
                    self.absorbed.insert((k.level as u32, k.index));
                }
            }
        }
    }

    /// Writes `records` (whose arrival ranks are `ranks`, in their order; none without ranks)
    /// as the leaf `key`; its ranks in its coded order.
    fn leaf(
        &mut self,
        key: NodeKey,
        records: &[u8],
        ranks: Vec<u64>,
        from: usize,
    ) -> Result<RankRun> {
        let rl = self.rl;
        let n = records.len() / rl;
        let color = &self.color;
        let (e, b, coded) = crate::store::codec::encode_payload_ordered(
            key,
            LEAF,
            n,
            rl - 12,
            |i| read_xyz(&records[i * rl..]),
            |i| color.rgba(&records[i * rl..(i + 1) * rl]),
            |i| &records[i * rl + 12..(i + 1) * rl],
            Order::of(self.plan.root(), key, &self.layout),
        )
        .map_err(|m| Error::MergePayload { error: m.in_node(key.name()) })?;
        self.made.push((e, b));
        // Coded point t is payload point seq[t].
        let ranks = match coded {
            Some(seq) if ranks.len() == n => seq.iter().map(|&i| ranks[i as usize]).collect(),
            _ => ranks,
        };
        Ok(RankRun::Made(ranks, from))
    }
}

/// The records (position and attributes) of a payload, in its order, and its coded order
/// where it is not the payload's (`decode_ordered`).
fn records_of(
    b: &[u8],
    rl: usize,
) -> std::result::Result<(Vec<u8>, Option<Vec<u32>>), PayloadError> {
    let (raw, coded) = crate::store::codec::decode_ordered(b)?;
    let d = DecodedLeaf::parse(&raw)?;
    if d.attr_len + 12 != rl {
        return Err(PayloadError::RecordLength);
    }
    let mut out = vec![0u8; d.count * rl];
    for (i, r) in out.chunks_exact_mut(rl).enumerate() {
        let p = d.position(i);
        for a in 0..3 {
            r[4 * a..4 * a + 4].copy_from_slice(&p[a].to_le_bytes());
        }
        r[12..].copy_from_slice(d.attributes(i));
    }
    Ok((out, coded))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::distributed::testing::{
        part_file, plan_of, scratch, two_entries, write_part,
    };

    /// The part error of merging `dirs` into `out`, with the directory it names.
    fn refusal(dirs: &[PathBuf], out: &Path) -> (PathBuf, PartError) {
        match merge(dirs, out) {
            Err(Error::Part { path, error }) => (path, error),
            Err(e) => panic!("another error: {e}"),
            Ok(_) => panic!("merged"),
        }
    }

    #[test]
    fn parts_that_are_not_every_job_of_one_plan_once_are_refused_before_anything_is_written() {
        let dir = scratch("merge");
        let out = dir.join("store");
        let (plan, entries) = (plan_of(3, "p"), two_entries());
        let part = |name: &str, plan: &Plan, job: usize, source: &[u8]| {
            let d = dir.join(name);
            write_part(&d, &part_file(plan, job, 2, 100), &entries, source);
            d
        };
        let (a, b, c) =
            (part("a", &plan, 0, b"S"), part("b", &plan, 1, b"S"), part("c", &plan, 2, b"S"));
        assert!(matches!(merge(&[], &out), Err(Error::Job { error: JobError::NoParts })));
        // A part of another plan (another id, or the same id on another plan).
        let other = part("other", &plan_of(3, "q"), 1, b"S");
        let (path, e) = refusal(&[a.clone(), other.clone()], &out);
        assert_eq!(path, other);
        assert!(matches!(e, PartError::OtherPlan { ref id, ref first, ref first_id }
            if id == "q" && *first == a && first_id == "p"));
        let mut edited = plan_of(3, "p");
        edited.leaf_capacity += 1;
        let forged = part("forged", &edited, 1, b"S");
        assert!(matches!(refusal(&[a.clone(), forged], &out).1, PartError::OtherPlan { .. }));
        // A job twice, a job the plan does not have, a job missing.
        let again = part("again", &plan, 0, b"S");
        let (path, e) = refusal(&[a.clone(), b.clone(), again.clone()], &out);
        assert_eq!(path, again);
        assert!(matches!(e, PartError::Repeated { job: 0, ref first } if *first == a));
        let beyond = part("beyond", &plan, 3, b"S");
        assert!(matches!(
            refusal(&[a.clone(), beyond], &out).1,
            PartError::NoSuchJob { job: 3, jobs: 3 }
        ));
        assert!(matches!(
            merge(std::slice::from_ref(&b), &out),
            Err(Error::Job { error: JobError::MissingParts { jobs: 3, first: 0, ref missing } })
                if *missing == [0, 2]
        ));
        // Every job once, but from other inputs.
        let d = part("d", &plan, 2, b"T");
        let (path, e) = refusal(&[a.clone(), b.clone(), d.clone()], &out);
        assert_eq!(path, d);
        assert!(matches!(e, PartError::OtherInputs { ref first } if *first == a));
        // Every job once, of one plan and one input, in any order: the output must be new.
        let all = [c.clone(), a.clone(), b.clone()];
        std::fs::create_dir_all(out.join("x")).unwrap();
        assert!(matches!(
            merge(&all, &out),
            Err(Error::Store { ref path, error: crate::error::StoreError::NotEmpty })
                if *path == out
        ));
        std::fs::remove_dir_all(&out).unwrap();
        let nowhere = dir.join("no").join("store");
        assert!(matches!(merge(&all, &nowhere), Err(Error::NoParentDirectory { .. })));
        // Nothing written by any refusal.
        assert!(!out.exists() && !dir.join("no").exists());
        let left: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
            .filter(|n| n.contains("mortar-tmp"))
            .collect();
        assert!(left.is_empty(), "{left:?}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Three records of 20 bytes (position, intensity, 6 more bytes) and their leaf payload.
    fn a_leaf() -> (Vec<u8>, Vec<u8>) {
        let rl = 20;
        let mut records = vec![0u8; 3 * rl];
        for (i, r) in records.chunks_exact_mut(rl).enumerate() {
            let p = [100 + i as i32, -7 * i as i32, 3];
            for a in 0..3 {
                r[4 * a..4 * a + 4].copy_from_slice(&p[a].to_le_bytes());
            }
            r[12..14].copy_from_slice(&(1000 * i as u16 + 10).to_le_bytes());
            r[14..].copy_from_slice(&[i as u8 + 1; 6]);
        }
        let key = NodeKey { level: 3, index: [1, 2, 3] };
        let (_, b) = crate::store::codec::encode_payload(
            key,
            LEAF,
            3,
            rl - 12,
            |i| read_xyz(&records[i * rl..]),
            |_| 0x1234_5678,
            |i| &records[i * rl + 12..(i + 1) * rl],
            None,
        )
        .unwrap();
        (records, b)
    }

    #[test]
    fn a_payload_gives_back_its_records_and_is_recoloured() {
        let (records, b) = a_leaf();
        assert_eq!(records_of(&b, 20).unwrap().0, records);
        assert!(matches!(records_of(&b, 21), Err(PayloadError::RecordLength)));
        assert!(matches!(records_of(&b[..40], 20), Err(PayloadError::Short)));
        // Recoloured: every colour from its record, nothing else changed.
        let color = ColorSource::Intensity { max_intensity: 2010 };
        let c = recolour(&b, &color, 20, None).unwrap();
        let raw_c = crate::store::codec::decode(&c).unwrap();
        let d = DecodedLeaf::parse(&raw_c).unwrap();
        for (i, r) in records.chunks_exact(20).enumerate() {
            assert_eq!(d.color(i), color.rgba(r), "point {i}");
            assert_ne!(d.color(i), 0x1234_5678);
        }
        let colours = 64 + 12 * 3..64 + 16 * 3;
        let raw_b = crate::store::codec::decode(&b).unwrap();
        assert_eq!(
            (&raw_c[..colours.start], &raw_c[colours.end..]),
            (&raw_b[..colours.start], &raw_b[colours.end..])
        );
        assert_eq!(records_of(&c, 20).unwrap().0, records);
        assert!(matches!(recolour(&b, &color, 26, None), Err(PayloadError::RecordLength)));
    }
}
