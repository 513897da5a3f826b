//! The plan of a distributed build (`mortar plan`): the root, each input's box, the cut of the
//! tree's top into subtrees by an estimate of their points, and the jobs (runs of the cut in
//! Morton order, about the same estimate each, with the inputs they read); written as JSON with
//! a checksum, read back with everything the jobs index with checked.

use super::cut::{cells_of, cube_of};
use crate::cleanup::TempPath;
use crate::dataset::Dataset;
use crate::error::{Error, JobError, PlanError, Result};
use crate::sort::PieceStats;
use crate::store::bounds::header_box;
use crate::store::partitioned::cell_depth;
use mortar_core::octree::{BuilderConfig, Cube, NodeKey};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The plan's format name.
pub const PLAN_FORMAT: &str = "mortar-plan/1";

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
        match crate::store::header_bounds_of(ds, &mut warnings) {
            Some((l, h)) if (0..3).all(|a| l[a] <= lo[a] && hi[a] <= h[a]) => Cube::covering(l, h),
            _ => Cube::covering(lo, hi),
        }
    } else {
        let (l, h) = crate::store::header_bounds_of(ds, &mut warnings).unwrap_or((lo, hi));
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

#[cfg(test)]
mod tests {
    use super::*;

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
