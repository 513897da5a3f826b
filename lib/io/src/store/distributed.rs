//! Builds beyond one machine (ARCHITECTURE.md, "The distributed build"): `mortar plan` splits
//! the tree into subtrees and the subtrees into jobs, `mortar build --plan --job` builds one
//! job's subtrees into a part, and `mortar merge` joins the parts into the store that one
//! machine builds from the same inputs (same nodes, same payloads, same entry order).
//!
//! The unit of work is the partitioned engine's (`partitioned.rs`): a subtree under a node of
//! the tree's top is built from the points of its cube alone, and hands its parent the earliest
//! point of each cell of the parent's grid (its candidates). A plan is a cut of the tree: nodes
//! (at most at the partition cells' depth) that tile the root's cube; every node above the cut
//! is an inner node of the one-machine tree when it has more points than a leaf may. The plan
//! splits only nodes its estimate puts well above that (four leaves' worth); where the true
//! count is smaller (the estimate is a guess), the merge makes the node the leaf one machine
//! makes: the leaves of the subtrees below it concatenated in octant (= Morton) order, their
//! entries dropped.
//!
//! - Plan: the root is the one the one-machine build takes (the headers' box; with `--scan`
//!   the points' own box where the headers lie), each input's box comes from its header (or
//!   from its points with `--scan`), and the points of the inputs are spread over their boxes
//!   to estimate the nodes' counts. The cut splits the largest node until nodes are small
//!   enough for the jobs to be balanced; jobs take runs of nodes in Morton order of about the
//!   same estimated count, and each job the inputs whose box meets one of its nodes.
//! - Job: opens every input (so that pieces have the numbers, and points the arrival numbers,
//!   of a one-machine build), reads only its inputs' pieces and keeps the points of its nodes
//!   (partition pass of the partitioned engine with a filter), checks that each input's points
//!   lie in the box the plan took for it (else a file the job skipped could hold some of its
//!   points: refused, plan again with `--scan`), and builds its subtrees within `--memory`.
//!   The part (its nodes' payloads, entries and candidates, `part.json`) is written under a
//!   temporary name and renamed over any earlier attempt: a job that failed or ran twice is
//!   simply run again.
//! - Merge: checks that the parts are every job of one plan exactly once, then copies the
//!   payloads, makes the nodes above the cut from the candidates (as the partitioned engine
//!   makes its nodes above the units), recolours payloads of parts whose colour scale differs
//!   from the whole input's (intensity grey scaled to the largest intensity of all points, or
//!   8- against 16-bit RGB), and commits the entries in the one-machine order.
//!
//! Not done: skipping LAZ chunks (a job reads every chunk of the files it needs; their chunk
//! tables hold no bounds) and `--scan` counting the cells exactly (it takes each input's own
//! box and spreads its points over it).

use super::bounds::header_box;
use super::format::*;
use super::partitioned::{build_units, cell_depth, partition_fixed, Filter};
use super::record::BuildRecord;
use super::runs::Cands;
use super::writer::StoreWriter;
use crate::cleanup::TempPath;
use crate::dataset::Dataset;
use crate::error::{Error, JobError, PartError, PlanError, Result};
use crate::sort::PieceStats;
use mortar_core::color::{ColorSource, RgbDepth};
use mortar_core::layout::read_xyz;
use mortar_core::octree::{splits, BuilderConfig, Cube, NodeKey};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The plan's format name.
pub const PLAN_FORMAT: &str = "mortar-plan/1";
/// A part's description inside its directory.
pub const PART_FILE: &str = "part.json";
const ENTRIES_FILE: &str = "entries.bin";
const CANDIDATES_FILE: &str = "candidates.bin";

/// One input as the plan takes it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PlanInput {
    /// Its path, absolute where it can be made so (jobs open it there: a shared filesystem).
    pub path: String,
    pub bytes: u64,
    /// Points its header declares.
    pub points: u64,
    /// The box its points lie in, on the merged grid (its header's, or its points' with
    /// `--scan`); `None` for an input without points.
    pub bounds: Option<([i32; 3], [i32; 3])>,
}

/// One job: its subtrees (as `[level, x, y, z]`, in Morton order) and the inputs it reads.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PlanJob {
    pub nodes: Vec<[u32; 4]>,
    pub inputs: Vec<usize>,
    pub estimated_points: u64,
}

/// What `mortar plan` writes.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Plan {
    pub format: String,
    /// A checksum of everything else: parts name the plan they were built from by it.
    pub id: String,
    /// Whether the inputs' boxes come from their points (`--scan`) rather than their headers.
    pub scanned: bool,
    pub root_min: [i64; 3],
    pub root_size_log2: u8,
    /// Depth of the partition cells below the root (the cut's deepest level).
    pub cell_depth: u8,
    pub leaf_capacity: u32,
    pub max_level: u8,
    pub points: u64,
    pub inputs: Vec<PlanInput>,
    pub jobs: Vec<PlanJob>,
    pub warnings: Vec<String>,
}

impl Plan {
    pub fn root(&self) -> Cube {
        Cube { min: self.root_min, size_log2: self.root_size_log2 }
    }

    pub fn config(&self) -> BuilderConfig {
        BuilderConfig {
            leaf_capacity: self.leaf_capacity,
            max_level: self.max_level,
            ..BuilderConfig::default()
        }
    }

    fn checksum(&self) -> String {
        let mut p = self.clone();
        p.id = String::new();
        let text = serde_json::to_vec(&p).unwrap_or_default();
        format!(
            "{:016x}",
            text.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &x| (h ^ x as u64)
                .wrapping_mul(0x100_0000_01b3))
        )
    }

    /// Reads a plan and checks its checksum.
    pub fn read(path: &Path) -> Result<Plan> {
        let b = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let p: Plan = serde_json::from_slice(&b).map_err(|error| Error::Plan {
            path: path.to_path_buf(),
            error: PlanError::NotPlan { error },
        })?;
        if p.format != PLAN_FORMAT {
            return Err(Error::Plan {
                path: path.to_path_buf(),
                error: PlanError::Format { found: p.format, supported: PLAN_FORMAT },
            });
        }
        if p.checksum() != p.id {
            return Err(Error::Plan { path: path.to_path_buf(), error: PlanError::Checksum });
        }
        // A checksum is no proof: everything the jobs index with is checked.
        let ok = p.root_size_log2 <= mortar_core::octree::MAX_ROOT_SIZE_LOG2
            && p.cell_depth <= p.root_size_log2
            && p.cell_depth <= 8
            && p.leaf_capacity > 0
            && !p.jobs.is_empty()
            && p.jobs.iter().all(|j| {
                j.inputs.iter().all(|&i| i < p.inputs.len())
                    && j.nodes.iter().all(|n| {
                        n[0] <= p.cell_depth as u32
                            && n[1..].iter().all(|&x| (x as u64) < 1u64 << n[0])
                    })
            });
        if !ok {
            return Err(Error::Plan { path: path.to_path_buf(), error: PlanError::OutOfRange });
        }
        Ok(p)
    }

    /// Writes the plan (temporary name, then rename).
    pub fn write(&self, path: &Path) -> Result<()> {
        let tmp = TempPath::beside(path);
        std::fs::write(tmp.path(), serde_json::to_vec_pretty(self).unwrap_or_default())
            .map_err(|e| Error::io(tmp.path(), e))?;
        tmp.persist(path).map_err(|e| Error::io(path, e))
    }
}

/// The cube of `key` in `root`.
fn cube_of(root: Cube, key: NodeKey) -> Cube {
    let size = 1i64 << (root.size_log2 - key.level);
    Cube {
        min: [0, 1, 2].map(|a| root.min[a] + key.index[a] as i64 * size),
        size_log2: root.size_log2 - key.level,
    }
}

/// The partition cells (at `depth`) under `key`.
fn cells_of(key: NodeKey, depth: u8) -> std::ops::Range<usize> {
    let below = 3 * (depth - key.level) as u32;
    let start = (morton(key.index, key.level) as usize) << below;
    start..start + (1usize << below)
}

/// The Morton code of a node's index at `level` (x in the lowest bit of each triple: octant
/// order, so codes sort a level depth first).
fn morton(index: [u32; 3], level: u8) -> u128 {
    let mut c = 0u128;
    for b in (0..level as u32).rev() {
        for a in 0..3 {
            c = c << 1 | ((index[2 - a] >> b) & 1) as u128;
        }
    }
    c
}

/// Whether the inclusive box `[lo, hi]` meets `cube`.
fn meets(b: &([i32; 3], [i32; 3]), cube: Cube) -> bool {
    (0..3).all(|a| {
        (b.1[a] as i64) >= cube.min[a] && (b.0[a] as i64) < cube.min[a] + cube.size() as i64
    })
}

/// Points of `inputs` estimated in `cube`: each input's points spread evenly over its box.
fn estimate(inputs: &[PlanInput], cube: Cube) -> f64 {
    inputs
        .iter()
        .filter_map(|i| i.bounds.map(|b| (i.points, b)))
        .map(|(n, (lo, hi))| {
            let mut f = 1.0;
            for a in 0..3 {
                let (l, h) = (lo[a] as i64, hi[a] as i64 + 1);
                let (cl, ch) = (cube.min[a], cube.min[a] + cube.size() as i64);
                let o = (h.min(ch) - l.max(cl)).max(0) as f64;
                f *= o / (h - l).max(1) as f64;
            }
            n as f64 * f
        })
        .sum()
}

/// What `mortar plan` is asked.
#[derive(Clone, Debug)]
pub struct PlanOptions {
    pub jobs: usize,
    pub config: BuilderConfig,
    /// Read every point for the inputs' true boxes (headers that lie).
    pub scan: bool,
}

/// Plans a build of `ds` in `opts.jobs` jobs.
pub fn plan(ds: &Dataset, opts: &PlanOptions) -> Result<Plan> {
    if opts.jobs == 0 {
        return Err(Error::Job { error: JobError::NoJobs });
    }
    let mut warnings = Vec::new();
    let mut inputs = Vec::with_capacity(ds.inputs.len());
    let real: Vec<PieceStats> = if opts.scan { scan(ds)? } else { Vec::new() };
    for (i, src) in ds.inputs.iter().enumerate() {
        let path = std::fs::canonicalize(src.path()).unwrap_or_else(|_| src.path().to_path_buf());
        let bytes = std::fs::metadata(src.path()).map(|m| m.len()).unwrap_or(0);
        let bounds = if opts.scan {
            (real[i].count > 0).then_some((real[i].min, real[i].max))
        } else if src.point_count() == 0 {
            None
        } else {
            Some(header_box(ds, src.as_ref()).map_err(|error| Error::Plan {
                path: src.path().to_path_buf(),
                error: PlanError::HeaderBox { error },
            })?)
        };
        let points = if opts.scan { real[i].count } else { src.point_count() };
        inputs.push(PlanInput { path: path.display().to_string(), bytes, points, bounds });
    }
    let boxes: Vec<_> = inputs.iter().filter_map(|i| i.bounds).collect();
    if boxes.is_empty() {
        return Err(Error::NoPoints { path: ds.inputs[0].path().to_path_buf(), action: "build" });
    }
    let lo = [0, 1, 2].map(|a| boxes.iter().map(|b| b.0[a]).min().unwrap_or(0));
    let hi = [0, 1, 2].map(|a| boxes.iter().map(|b| b.1[a]).max().unwrap_or(0));
    // The one-machine root: the headers' box when it holds every point, else the points' box.
    let root = if opts.scan {
        match super::header_bounds_of(ds, &mut warnings) {
            Some((l, h)) if (0..3).all(|a| l[a] <= lo[a] && hi[a] <= h[a]) => Cube::covering(l, h),
            _ => Cube::covering(lo, hi),
        }
    } else {
        let (l, h) = super::header_bounds_of(ds, &mut warnings).unwrap_or((lo, hi));
        Cube::covering(l, h)
    };
    let depth = cell_depth(root, opts.config.max_level);
    let total: u64 = inputs.iter().map(|i| i.points).sum();
    // The cut: split the largest node while it is large against the jobs' share and surely inner.
    let fine = total as f64 / (4 * opts.jobs) as f64;
    let mut cut: Vec<(NodeKey, f64)> = vec![(NodeKey::ROOT, total as f64)];
    while let Some((i, &(k, e))) = cut
        .iter()
        .enumerate()
        .filter(|(_, (k, _))| k.level < depth)
        .max_by(|a, b| a.1 .1.total_cmp(&b.1 .1))
    {
        if e <= fine
            || e <= 4.0 * opts.config.leaf_capacity as f64
            || cut.len() > 64 * opts.jobs + 4096
        {
            break;
        }
        cut.swap_remove(i);
        for o in 0..8 {
            let c = k.child(o);
            cut.push((c, estimate(&inputs, cube_of(root, c))));
        }
    }
    cut.sort_by_key(|(k, _)| cells_of(*k, depth).start);
    // Runs of the cut to jobs, about the same estimate each.
    let mut jobs: Vec<PlanJob> = (0..opts.jobs)
        .map(|_| PlanJob { nodes: Vec::new(), inputs: Vec::new(), estimated_points: 0 })
        .collect();
    let mut acc = 0.0;
    let mut j = 0;
    for (k, e) in &cut {
        while j + 1 < opts.jobs && acc >= (j + 1) as f64 * total as f64 / opts.jobs as f64 {
            j += 1;
        }
        jobs[j].nodes.push([k.level as u32, k.index[0], k.index[1], k.index[2]]);
        jobs[j].estimated_points += e.round() as u64;
        acc += e;
    }
    for job in &mut jobs {
        let cubes: Vec<Cube> = job
            .nodes
            .iter()
            .map(|n| cube_of(root, NodeKey { level: n[0] as u8, index: [n[1], n[2], n[3]] }))
            .collect();
        job.inputs = inputs
            .iter()
            .enumerate()
            .filter(|(_, i)| i.bounds.is_some_and(|b| cubes.iter().any(|c| meets(&b, *c))))
            .map(|(k, _)| k)
            .collect();
    }
    let mut p = Plan {
        format: PLAN_FORMAT.into(),
        id: String::new(),
        scanned: opts.scan,
        root_min: root.min,
        root_size_log2: root.size_log2,
        cell_depth: depth,
        leaf_capacity: opts.config.leaf_capacity,
        max_level: opts.config.max_level,
        points: total,
        inputs,
        jobs,
        warnings,
    };
    p.id = p.checksum();
    Ok(p)
}

/// Every input's points' statistics (`--scan`).
fn scan(ds: &Dataset) -> Result<Vec<PieceStats>> {
    let pieces = ds.pieces();
    let per: Vec<(usize, PieceStats)> = pieces
        .par_iter()
        .map(|p| {
            crate::cleanup::check_interrupted()?;
            let slab = ds.read_piece(p)?;
            let st = PieceStats::of(&slab, &ds.layout);
            ds.inputs[p.input].release_piece(&p.piece);
            Ok((p.input, st))
        })
        .collect::<Result<_>>()?;
    let mut out = vec![PieceStats::default(); ds.inputs.len()];
    for (i, st) in per {
        out[i].merge(&st);
    }
    Ok(out)
}

/// What a job reports.
#[derive(Clone, Debug, Default, Serialize)]
pub struct JobReport {
    pub job: usize,
    pub jobs: usize,
    pub points: u64,
    pub nodes: u64,
    pub inputs_read: usize,
    pub seconds: f64,
    pub warnings: Vec<String>,
}

/// One subtree of a part as `part.json` lists it.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct PartNode {
    key: [u32; 4],
    /// Points of its subtree.
    points: u64,
    candidates: u64,
}

/// `part.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct PartFile {
    format: String,
    plan: Plan,
    job: usize,
    nodes: Vec<PartNode>,
    entries: u64,
    nodes_len: u64,
    record_len: usize,
    /// Points kept and the statistics of every piece the job read.
    points: u64,
    min: [i32; 3],
    max: [i32; 3],
    max_rgb: u16,
    max_intensity: u16,
    /// The RGB field's offset, where the records have one.
    rgb_offset: Option<usize>,
}

fn color_of(rgb_offset: Option<usize>, max_rgb: u16, max_intensity: u16) -> ColorSource {
    match rgb_offset {
        Some(offset) if max_rgb > 0 => {
            ColorSource::Rgb { offset, depth: RgbDepth::detect(max_rgb) }
        }
        _ => ColorSource::Intensity { max_intensity },
    }
}

/// Builds job `job` of `plan` from `ds` (the plan's inputs, opened in its order) into the part
/// directory `out`, replacing an earlier attempt.
pub fn build_job(
    ds: &Dataset,
    plan: &Plan,
    job: usize,
    out: &Path,
    memory: u64,
) -> Result<JobReport> {
    let t0 = Instant::now();
    let Some(pj) = plan.jobs.get(job) else {
        return Err(Error::Job { error: JobError::NoSuchJob { job, last: plan.jobs.len() - 1 } });
    };
    if ds.inputs.len() != plan.inputs.len() {
        return Err(Error::Job {
            error: JobError::Inputs { planned: plan.inputs.len(), opened: ds.inputs.len() },
        });
    }
    for (src, pi) in ds.inputs.iter().zip(&plan.inputs) {
        let bytes = std::fs::metadata(src.path()).map(|m| m.len()).unwrap_or(0);
        if bytes != pi.bytes || (!plan.scanned && src.point_count() != pi.points) {
            return Err(Error::Plan {
                path: src.path().to_path_buf(),
                error: PlanError::OtherFile {
                    bytes,
                    points: src.point_count(),
                    plan_bytes: pi.bytes,
                    plan_points: pi.points,
                },
            });
        }
    }
    let root = plan.root();
    let depth = cell_depth(root, plan.max_level);
    if depth != plan.cell_depth {
        return Err(Error::Job {
            error: JobError::CellDepth { planned: plan.cell_depth, ours: depth },
        });
    }
    let units: Vec<(NodeKey, Cube, std::ops::Range<usize>)> = pj
        .nodes
        .iter()
        .map(|n| {
            let k = NodeKey { level: n[0] as u8, index: [n[1], n[2], n[3]] };
            if k.level > depth || (0..3).any(|a| k.index[a] as u64 >= 1u64 << k.level) {
                return Err(Error::Job { error: JobError::NodeOutside { node: *n } });
            }
            Ok((k, cube_of(root, k), cells_of(k, depth)))
        })
        .collect::<Result<_>>()?;
    let mut cells = vec![false; 1usize << (3 * depth as u32)];
    for (_, _, r) in &units {
        cells[r.clone()].iter_mut().for_each(|c| *c = true);
    }
    let read: Vec<bool> = (0..ds.inputs.len()).map(|i| pj.inputs.contains(&i)).collect();
    let filter = Filter { pieces: ds.pieces().iter().map(|p| read[p.input]).collect(), cells };
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if !parent.is_dir() {
        return Err(Error::NoParentDirectory {
            path: out.to_path_buf(),
            parent: parent.to_path_buf(),
        });
    }
    remove_stale_attempts(out);
    let tmp = TempPath::beside(out);
    let mut writer = StoreWriter::create(tmp.path(), &ds.source_meta())?;
    writer.group_bytes = super::writer::group_bytes(memory);
    let state = tmp.path().join(".partition");
    std::fs::create_dir_all(&state).map_err(|e| Error::io(&state, e))?;
    ds.progress.stage("reading", pj.inputs.iter().map(|&i| plan.inputs[i].points).sum(), "points");
    let (runs, hist, all, real) =
        partition_fixed(ds, root, plan.max_level, memory, &filter, &state)?;
    // Every input read lies in the box the plan took for it: a file the job skipped by its box
    // holds none of the job's points.
    for &i in &pj.inputs {
        let (st, b) = (&real[i], plan.inputs[i].bounds);
        if let Some((lo, hi)) = b.filter(|_| st.count > 0) {
            if (0..3).any(|a| st.min[a] < lo[a] || st.max[a] > hi[a]) {
                return Err(Error::Plan {
                    path: ds.inputs[i].path().to_path_buf(),
                    error: PlanError::OutsideBox {
                        min: st.min,
                        max: st.max,
                        lo,
                        hi,
                        scanned: plan.scanned,
                    },
                });
            }
        }
    }
    let rgb_offset = ds.layout.attribute("rgb").map(|a| a.offset);
    let color = color_of(rgb_offset, all.max_rgb, all.max_intensity);
    ds.progress.stage("building", hist.iter().sum(), "points");
    let (entries, cands, points) = build_units(
        ds,
        &mut writer,
        plan.config(),
        memory,
        root,
        &runs,
        &hist,
        &units,
        color,
        &state,
    )?;
    let _ = std::fs::remove_dir_all(&state);
    // entries.bin: the entries in the walk's order; candidates.bin: each subtree's candidates.
    let rl = ds.layout.record_len;
    let eb: Vec<NodeEntry> = entries.iter().map(|(_, _, e)| *e).collect();
    let ep = tmp.path().join(ENTRIES_FILE);
    std::fs::write(&ep, bytemuck::cast_slice::<NodeEntry, u8>(&eb))
        .map_err(|e| Error::io(&ep, e))?;
    let cp = tmp.path().join(CANDIDATES_FILE);
    let mut cf =
        std::io::BufWriter::new(std::fs::File::create(&cp).map_err(|e| Error::io(&cp, e))?);
    let mut nodes = Vec::with_capacity(units.len());
    for ((k, _, r), c) in units.iter().zip(&cands) {
        for i in 0..c.pos.len() {
            for v in c.pos[i] {
                cf.write_all(&v.to_le_bytes()).map_err(|e| Error::io(&cp, e))?;
            }
            cf.write_all(&c.arrival[i].to_le_bytes()).map_err(|e| Error::io(&cp, e))?;
            cf.write_all(&c.records[i * rl..(i + 1) * rl]).map_err(|e| Error::io(&cp, e))?;
        }
        nodes.push(PartNode {
            key: [k.level as u32, k.index[0], k.index[1], k.index[2]],
            points: hist[r.clone()].iter().sum(),
            candidates: c.pos.len() as u64,
        });
    }
    cf.flush().map_err(|e| Error::io(&cp, e))?;
    drop(cf);
    let part = PartFile {
        format: "mortar-part/1".into(),
        plan: plan.clone(),
        job,
        nodes,
        entries: eb.len() as u64,
        nodes_len: writer.nodes_len,
        record_len: rl,
        points,
        min: all.min,
        max: all.max,
        max_rgb: all.max_rgb,
        max_intensity: all.max_intensity,
        rgb_offset,
    };
    let mut record = BuildRecord::of(ds, &plan.config(), "distributed");
    record.complete = true;
    record.write(tmp.path())?;
    let pp = tmp.path().join(PART_FILE);
    std::fs::write(&pp, serde_json::to_vec_pretty(&part).unwrap_or_default())
        .map_err(|e| Error::io(&pp, e))?;
    // An earlier attempt is replaced whole.
    if out.exists() {
        if !out.join(PART_FILE).is_file()
            && std::fs::read_dir(out).map_err(|e| Error::io(out, e))?.next().is_some()
        {
            return Err(Error::Part { path: out.to_path_buf(), error: PartError::NotEmpty });
        }
        std::fs::remove_dir_all(out).map_err(|e| Error::io(out, e))?;
    }
    tmp.persist(out).map_err(|e| Error::io(out, e))?;
    drop(writer);
    let mut warnings = Vec::new();
    for &i in &pj.inputs {
        if let Some(w) = super::bounds::bounds_warning(ds, ds.inputs[i].as_ref(), &real[i]) {
            warnings.push(w);
        }
    }
    Ok(JobReport {
        job,
        jobs: plan.jobs.len(),
        points,
        nodes: eb.len() as u64,
        inputs_read: pj.inputs.len(),
        seconds: t0.elapsed().as_secs_f64(),
        warnings,
    })
}

/// Removes what killed attempts at the part `out` left beside it (temporary directories of
/// processes that no longer run), so that re-running a job cleans up after the one it repeats.
fn remove_stale_attempts(out: &Path) {
    let (Some(parent), Some(name)) = (
        out.parent().map(|p| if p.as_os_str().is_empty() { Path::new(".") } else { p }),
        out.file_name(),
    ) else {
        return;
    };
    let prefix = format!(".{}.mortar-tmp-", name.to_string_lossy());
    let Ok(rd) = std::fs::read_dir(parent) else { return };
    for e in rd.flatten() {
        let n = e.file_name().to_string_lossy().to_string();
        if let Some(pid) = n.strip_prefix(&prefix).and_then(|p| p.parse::<u32>().ok()) {
            if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    }
}

/// What a merge reports.
#[derive(Clone, Debug, Default, Serialize)]
pub struct MergeReport {
    pub parts: usize,
    pub points: u64,
    pub nodes: u64,
    /// Nodes above the cut, made by the merge.
    pub top_nodes: u64,
    /// Parts whose payloads were recoloured.
    pub recoloured_parts: usize,
    pub seconds: f64,
}

/// A part as the merge reads it.
struct Part {
    dir: PathBuf,
    file: PartFile,
    entries: Vec<NodeEntry>,
}

fn read_part(dir: &Path) -> Result<Part> {
    let pp = dir.join(PART_FILE);
    let b = std::fs::read(&pp)
        .map_err(|_| Error::Part { path: dir.to_path_buf(), error: PartError::NotPart })?;
    let file: PartFile = serde_json::from_slice(&b).map_err(|error| Error::Part {
        path: pp.clone(),
        error: PartError::BadDescription { error },
    })?;
    let ep = dir.join(ENTRIES_FILE);
    let eb = std::fs::read(&ep).map_err(|e| Error::io(&ep, e))?;
    let es = std::mem::size_of::<NodeEntry>();
    if eb.len() as u64 != file.entries * es as u64 {
        return Err(Error::Part {
            path: ep,
            error: PartError::Damaged { what: "another size than part.json says" },
        });
    }
    let entries: Vec<NodeEntry> = eb.chunks_exact(es).map(bytemuck::pod_read_unaligned).collect();
    let nl = std::fs::metadata(dir.join(NODES_FILE)).map(|m| m.len()).unwrap_or(u64::MAX);
    if nl != file.nodes_len
        || entries.iter().any(|e| e.offset.checked_add(e.length).is_none_or(|end| end > nl))
    {
        return Err(Error::Part {
            path: dir.to_path_buf(),
            error: PartError::Damaged { what: "nodes.bin is not what part.json says" },
        });
    }
    Ok(Part { dir: dir.to_path_buf(), file, entries })
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
    // The store, in a temporary directory.
    let tmp = TempPath::beside(out);
    let dir = tmp.path().to_path_buf();
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    std::fs::write(dir.join(SOURCE_FILE), &source).map_err(|e| Error::io(&dir, e))?;
    std::fs::copy(
        parts[0].dir.join(super::record::RECORD_FILE),
        dir.join(super::record::RECORD_FILE),
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
        guard: None,
        group_bytes: super::writer::COMMIT_GROUP_BYTES,
    };
    // The subtrees' candidates and counts.
    let mut subtrees: HashMap<NodeKey, (u64, Cands, usize)> = HashMap::new();
    for (pi, p) in parts.iter().enumerate() {
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
                (n.points, c, pi),
            );
        }
    }
    // The nodes above the cut, from the subtrees' candidates; written after the parts' nodes.
    let mut top = Top {
        subtrees,
        parts: &parts,
        plan,
        color,
        rl,
        made: Vec::new(),
        absorbed: std::collections::HashSet::new(),
    };
    if let Visit::Small { records, unit: false, .. } = top.visit(NodeKey::ROOT, plan.root())? {
        // Few points in all: the root is a leaf (held as it is where the cut is the root).
        top.leaf(NodeKey::ROOT, &records)?;
    }
    let Top { made, absorbed, .. } = top;
    let mut all: Vec<NodeEntry> = Vec::new();
    let mut recoloured = 0;
    for p in &parts {
        let f = &p.file;
        let same_color = color_of(f.rgb_offset, f.max_rgb, f.max_intensity) == color;
        let src = p.dir.join(NODES_FILE);
        let base = writer.nodes_len;
        let absorbs = p.entries.iter().any(|e| absorbed.contains(&(e.level, e.index)));
        if same_color && !absorbs {
            // The payloads as they are, in one copy.
            let off = writer.reserve(&[f.nodes_len])[0];
            debug_assert_eq!(off, base);
            let mut from = std::fs::File::open(&src).map_err(|e| Error::io(&src, e))?;
            use std::io::Seek;
            writer.nodes.seek(std::io::SeekFrom::Start(off)).map_err(|e| Error::io(&np, e))?;
            std::io::copy(&mut from, &mut writer.nodes).map_err(|e| Error::io(&np, e))?;
            all.extend(p.entries.iter().map(|e| NodeEntry { offset: e.offset + base, ..*e }));
        } else {
            recoloured += !same_color as usize;
            let bytes = std::fs::read(&src).map_err(|e| Error::io(&src, e))?;
            let keep: Vec<&NodeEntry> =
                p.entries.iter().filter(|e| !absorbed.contains(&(e.level, e.index))).collect();
            let lens: Vec<u64> = keep.iter().map(|e| e.length).collect();
            let offs = writer.reserve(&lens);
            let w = &writer;
            let done: Vec<NodeEntry> = keep
                .par_iter()
                .zip(offs)
                .map(|(e, off)| {
                    let mut b = bytes[e.offset as usize..(e.offset + e.length) as usize].to_vec();
                    if !same_color {
                        recolour(&mut b, &color, rl)
                            .map_err(|error| Error::Payload { path: p.dir.clone(), error })?;
                    }
                    w.write_at(off, &b)?;
                    Ok(NodeEntry { offset: off, ..**e })
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
    tmp.persist(out).map_err(|e| Error::io(out, e))?;
    Ok(MergeReport {
        parts: parts.len(),
        points,
        nodes: all.len() as u64,
        top_nodes,
        recoloured_parts: recoloured,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Rewrites the colours of a payload with `color` (from its records: position and attributes).
fn recolour(b: &mut [u8], color: &ColorSource, rl: usize) -> std::result::Result<(), PayloadError> {
    let d = DecodedLeaf::parse(b)?;
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
    let at = 64 + 12 * n;
    for (i, c) in cols.iter().enumerate() {
        b[at + 4 * i..at + 4 * i + 4].copy_from_slice(&c.to_le_bytes());
    }
    Ok(())
}

/// What the walk above the cut gives a parent.
enum Visit {
    /// A node with more points than a leaf holds (inner, written): its candidates.
    Big { cands: Cands, count: u64 },
    /// A node with at most a leaf's points: a leaf, unless its parent is a leaf too. Its
    /// candidates and its records in Morton order (ties in arrival order); `unit` when it is a
    /// subtree of the cut whose part holds it as a leaf already.
    Small { cands: Cands, count: u64, records: Vec<u8>, unit: bool },
}

/// The walk over the nodes above the cut.
struct Top<'a> {
    subtrees: HashMap<NodeKey, (u64, Cands, usize)>,
    parts: &'a [Part],
    plan: &'a Plan,
    color: ColorSource,
    rl: usize,
    /// Payloads made here (offsets set when written).
    made: Vec<(NodeEntry, Vec<u8>)>,
    /// Nodes of the parts that a leaf above them holds: not copied.
    absorbed: std::collections::HashSet<(u32, [u32; 3])>,
}

impl Top<'_> {
    fn visit(&mut self, key: NodeKey, cube: Cube) -> Result<Visit> {
        if let Some((count, cands, pi)) = self.subtrees.remove(&key) {
            if count > self.plan.leaf_capacity as u64 {
                return Ok(Visit::Big { cands, count });
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
            let records = records_of(&b, self.rl)
                .map_err(|error| Error::Payload { path: p.dir.clone(), error })?;
            return Ok(Visit::Small { cands, count, records, unit: true });
        }
        if key.level >= self.plan.cell_depth {
            return Err(Error::Job { error: JobError::Uncovered { node: key.name() } });
        }
        let mut kids = Vec::with_capacity(8);
        let mut voxels = Cands::default();
        let mut count = 0;
        for o in 0..8 {
            match self.visit(key.child(o), cube.child(o))? {
                Visit::Big { cands, count: n } => {
                    voxels.append(cands);
                    count += n;
                    kids.push(None);
                }
                Visit::Small { cands, count: n, records, unit } => {
                    voxels.append(cands);
                    count += n;
                    kids.push(Some((records, unit)));
                }
            }
        }
        let rl = self.rl;
        let up = |voxels: &Cands| voxels.pick(&voxels.for_parent(key, cube), rl);
        if count <= self.plan.leaf_capacity as u64 {
            // A leaf of the one-machine tree (unless its parent is one too): the points below,
            // children in octant order, which is Morton order.
            let mut records = Vec::with_capacity(count as usize * rl);
            for (r, _) in kids.into_iter().flatten() {
                records.extend_from_slice(&r);
            }
            self.absorb_below(key);
            return Ok(Visit::Small { cands: up(&voxels), count, records, unit: false });
        }
        if !splits(count, key, cube, &self.plan.config()) {
            return Err(Error::Job { error: JobError::CannotSplit { node: key.name(), count } });
        }
        // Inner: small children are leaves; those the parts hold as leaves stay as they are.
        for (o, k) in kids.into_iter().enumerate() {
            if let Some((records, false)) = k {
                self.leaf(key.child(o), &records)?;
            }
        }
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
        .map_err(|m| Error::MergePayload { error: m.in_node(key.name()) })?;
        self.made.push((e, b));
        Ok(Visit::Big { cands: up(&voxels), count })
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

    /// Writes `records` as the leaf `key`.
    fn leaf(&mut self, key: NodeKey, records: &[u8]) -> Result<()> {
        let rl = self.rl;
        let n = records.len() / rl;
        let color = &self.color;
        let (e, b) = encode_payload(
            key,
            LEAF,
            n,
            rl - 12,
            |i| read_xyz(&records[i * rl..]),
            |i| color.rgba(&records[i * rl..(i + 1) * rl]),
            |i| &records[i * rl + 12..(i + 1) * rl],
        )
        .map_err(|m| Error::MergePayload { error: m.in_node(key.name()) })?;
        self.made.push((e, b));
        Ok(())
    }
}

/// The records (position and attributes) of a payload, in its order.
fn records_of(b: &[u8], rl: usize) -> std::result::Result<Vec<u8>, PayloadError> {
    let d = DecodedLeaf::parse(b)?;
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
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_orders_a_level_depth_first() {
        // children of the root in octant order
        let kids: Vec<u128> = (0..8)
            .map(|o| {
                let k = NodeKey::ROOT.child(o);
                morton(k.index, 1)
            })
            .collect();
        assert_eq!(kids, (0..8).collect::<Vec<u128>>());
        // grandchildren: all of child 0 before any of child 1
        let k = NodeKey::ROOT.child(1).child(0);
        assert_eq!(morton(k.index, 2), 8);
        assert_eq!(cells_of(NodeKey::ROOT.child(3), 2), 24..32);
    }

    fn a_plan() -> Plan {
        let mut p = Plan {
            format: PLAN_FORMAT.into(),
            id: String::new(),
            scanned: false,
            root_min: [-1024, 0, 0],
            root_size_log2: 11,
            cell_depth: 2,
            leaf_capacity: 5000,
            max_level: 32,
            points: 300,
            inputs: vec![PlanInput {
                path: "/data/a.las".into(),
                bytes: 10_000,
                points: 300,
                bounds: Some(([-1024, 0, 0], [1023, 2047, 2047])),
            }],
            jobs: vec![PlanJob {
                nodes: vec![[1, 0, 0, 0], [2, 3, 3, 3]],
                inputs: vec![0],
                estimated_points: 300,
            }],
            warnings: Vec::new(),
        };
        p.id = p.checksum();
        p
    }

    #[test]
    fn a_plan_is_read_back_and_an_edited_or_out_of_range_plan_is_refused() {
        let dir = std::env::temp_dir().join(format!("mortar-plan-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("plan.json");
        let p = a_plan();
        p.write(&path).unwrap();
        assert_eq!(Plan::read(&path).unwrap(), p);
        // An edit without a new id: the checksum names it.
        let text = std::fs::read_to_string(&path).unwrap();
        std::fs::write(&path, text.replace("\"leaf_capacity\": 5000", "\"leaf_capacity\": 6000"))
            .unwrap();
        assert!(matches!(Plan::read(&path), Err(Error::Plan { error: PlanError::Checksum, .. })));
        // Consistent checksums do not make indices safe: a node outside its level, an input
        // that does not exist, a cut deeper than the root.
        for edit in [
            (|p: &mut Plan| p.jobs[0].nodes[1] = [2, 4, 0, 0]) as fn(&mut Plan),
            |p: &mut Plan| p.jobs[0].inputs = vec![1],
            |p: &mut Plan| p.cell_depth = 12,
            |p: &mut Plan| p.jobs.clear(),
        ] {
            let mut q = a_plan();
            edit(&mut q);
            q.id = q.checksum();
            q.write(&path).unwrap();
            assert!(
                matches!(Plan::read(&path), Err(Error::Plan { error: PlanError::OutOfRange, .. })),
                "{:?}",
                q.jobs
            );
        }
        // Another format, and not a plan at all.
        let mut q = a_plan();
        q.format = "mortar-plan/0".into();
        q.id = q.checksum();
        q.write(&path).unwrap();
        assert!(matches!(
            Plan::read(&path),
            Err(Error::Plan { error: PlanError::Format { .. }, .. })
        ));
        std::fs::write(&path, b"{}").unwrap();
        assert!(matches!(
            Plan::read(&path),
            Err(Error::Plan { error: PlanError::NotPlan { .. }, .. })
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn cubes_cells_and_estimates_of_the_cut() {
        let root = Cube { min: [-1024, 0, 0], size_log2: 11 };
        let k = NodeKey::ROOT.child(7).child(0);
        let c = cube_of(root, k);
        assert_eq!((c.min, c.size_log2), ([0, 1024, 1024], 9));
        assert_eq!(cells_of(k, 2), 56..57);
        assert_eq!(cells_of(NodeKey::ROOT, 2), 0..64);
        // An inclusive box meets a cube it touches on its last unit, not one it stops short of.
        assert!(meets(&([-5, 0, 0], [0, 1024, 1024]), c));
        assert!(!meets(&([-5, 0, 0], [-1, 2000, 2000]), c));
        // Points spread evenly over their box: an eighth of the root's box in each child.
        let inputs = a_plan().inputs;
        let e: Vec<f64> =
            (0..8).map(|o| estimate(&inputs, cube_of(root, NodeKey::ROOT.child(o)))).collect();
        assert!(e.iter().all(|&x| (x - 37.5).abs() < 1e-9), "{e:?}");
        assert!((estimate(&inputs, root) - 300.0).abs() < 1e-9);
    }
}
