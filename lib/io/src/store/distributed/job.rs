//! One job of a distributed build (`mortar build --plan --job`): its subtrees built from the
//! points of its inputs (the partitioned engine's partition pass with a filter, then its walk
//! over the subtrees) into a part, written under a temporary name and renamed over any earlier
//! attempt.

use super::cut::{cells_of, cube_of};
use super::part::{color_of, PartFile, PartNode, CANDIDATES_FILE, ENTRIES_FILE, PART_FILE};
use super::plan::Plan;
use crate::cleanup::TempPath;
use crate::dataset::Dataset;
use crate::error::{Error, JobError, PartError, PlanError, Result};
use crate::store::arrival::ColorMaxima;
use crate::store::format::*;
use crate::store::partitioned::{build_units, cell_depth, partition_fixed, Filter};
use crate::store::record::BuildRecord;
use crate::store::writer::StoreWriter;
use mortar_core::octree::{Cube, NodeKey};
use serde::Serialize;
use std::io::Write;
use std::path::Path;
use std::time::Instant;

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
    writer.group_bytes = crate::store::writer::group_bytes(memory);
    let state = tmp.path().join(".partition");
    std::fs::create_dir_all(&state).map_err(|e| Error::io(&state, e))?;
    ds.progress.stage("reading", pj.inputs.iter().map(|&i| plan.inputs[i].points).sum(), "points");
    let (runs, hist, all, real, _) =
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
    // The leaves' arrival ranks among all inputs (the one-machine build's), in the part's
    // `arrival.bin`, with the box the inputs' headers declare: the merge lists them for the
    // store (`merge::Ranks`).
    let declared = crate::store::bounds::header_bounds(ds, &mut Vec::new());
    let maxima = ColorMaxima { max_rgb: all.max_rgb, max_intensity: all.max_intensity };
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
        Some((tmp.path(), declared, maxima)),
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
        if let Some(w) = crate::store::bounds::bounds_warning(ds, ds.inputs[i].as_ref(), &real[i]) {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::distributed::testing::scratch;

    #[test]
    fn a_rerun_job_removes_only_the_attempts_of_dead_processes_at_its_part() {
        let dir = scratch("stale");
        let out = dir.join("part-3");
        // Above the kernel's largest pid (PID_MAX_LIMIT, 2^22): no such process ever runs.
        let dead = 4_194_305u32;
        let names = [
            format!(".part-3.mortar-tmp-{dead}"),
            format!(".part-3.mortar-tmp-{}", std::process::id()),
            ".part-3.mortar-tmp-1".to_string(),
            ".part-3.mortar-tmp-x".to_string(),
            format!(".part-30.mortar-tmp-{dead}"),
            format!("part-3.mortar-tmp-{dead}"),
        ];
        for n in &names {
            std::fs::create_dir_all(dir.join(n).join("inner")).unwrap();
        }
        remove_stale_attempts(&out);
        let left: Vec<bool> = names.iter().map(|n| dir.join(n).exists()).collect();
        assert_eq!(left, [false, true, true, true, true, true], "{names:?}");
        // No directory beside it at all: nothing to do, no error.
        remove_stale_attempts(&dir.join("missing").join("part"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
