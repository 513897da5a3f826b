//! A part of a distributed build: the directory a job writes (its subtrees' payloads in
//! `nodes.bin`, their entries in `entries.bin`, each subtree's candidates in `candidates.bin`
//! and `part.json`, which describes them with the plan and the statistics of the points read),
//! and the part read back, its sizes checked, as the merge takes it.

use super::plan::Plan;
use crate::error::{Error, PartError, Result};
use crate::store::format::*;
use mortar_core::color::{ColorSource, RgbDepth};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A part's description inside its directory.
pub const PART_FILE: &str = "part.json";
pub(super) const ENTRIES_FILE: &str = "entries.bin";
pub(super) const CANDIDATES_FILE: &str = "candidates.bin";

/// One subtree of a part as `part.json` lists it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub(super) struct PartNode {
    pub(super) key: [u32; 4],
    /// Points of its subtree.
    pub(super) points: u64,
    pub(super) candidates: u64,
}

/// `part.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub(super) struct PartFile {
    pub(super) format: String,
    pub(super) plan: Plan,
    pub(super) job: usize,
    pub(super) nodes: Vec<PartNode>,
    pub(super) entries: u64,
    pub(super) nodes_len: u64,
    pub(super) record_len: usize,
    /// Points kept and the statistics of every piece the job read.
    pub(super) points: u64,
    pub(super) min: [i32; 3],
    pub(super) max: [i32; 3],
    pub(super) max_rgb: u16,
    pub(super) max_intensity: u16,
    /// The RGB field's offset, where the records have one.
    pub(super) rgb_offset: Option<usize>,
}

pub(super) fn color_of(rgb_offset: Option<usize>, max_rgb: u16, max_intensity: u16) -> ColorSource {
    match rgb_offset {
        Some(offset) if max_rgb > 0 => {
            ColorSource::Rgb { offset, depth: RgbDepth::detect(max_rgb) }
        }
        _ => ColorSource::Intensity { max_intensity },
    }
}

/// A part as the merge reads it.
pub(super) struct Part {
    pub(super) dir: PathBuf,
    pub(super) file: PartFile,
    pub(super) entries: Vec<NodeEntry>,
}

pub(super) fn read_part(dir: &Path) -> Result<Part> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::distributed::testing::{
        part_file, plan_of, scratch, two_entries, write_part,
    };

    #[test]
    fn a_part_takes_rgb_at_its_depth_or_else_intensity() {
        let rgb = |depth| ColorSource::Rgb { offset: 28, depth };
        assert_eq!(color_of(Some(28), 255, 9), rgb(RgbDepth::Eight));
        assert_eq!(color_of(Some(28), 4000, 9), rgb(RgbDepth::Sixteen));
        // No colour in the points read, or no RGB field: grey from intensity.
        assert_eq!(color_of(Some(28), 0, 9), ColorSource::Intensity { max_intensity: 9 });
        assert_eq!(color_of(None, 4000, 700), ColorSource::Intensity { max_intensity: 700 });
    }

    #[test]
    fn a_part_is_read_back_and_one_whose_files_disagree_is_refused() {
        let dir = scratch("part");
        let plan = plan_of(2, "p");
        let entries = two_entries();
        let part = dir.join("a");
        write_part(&part, &part_file(&plan, 1, 2, 100), &entries, b"LASF");
        let p = read_part(&part).unwrap();
        assert_eq!((&p.dir, p.file.job, &p.file.plan, &p.entries), (&part, 1, &plan, &entries));
        let damaged = |what: &str| -> PartError {
            match read_part(&part) {
                Err(Error::Part { error, .. }) => error,
                Err(e) => panic!("{what}: another error: {e}"),
                Ok(_) => panic!("{what}: read"),
            }
        };
        let is_damaged = |e: PartError, says: &str| match e {
            PartError::Damaged { what } => what.contains(says),
            _ => false,
        };
        // entries.bin of another size than part.json says.
        write_part(&part, &part_file(&plan, 1, 3, 100), &entries, b"LASF");
        assert!(is_damaged(damaged("3 entries"), "another size"));
        let mut eb = bytemuck::cast_slice::<NodeEntry, u8>(&entries).to_vec();
        eb.push(0);
        write_part(&part, &part_file(&plan, 1, 2, 100), &entries, b"LASF");
        std::fs::write(part.join(ENTRIES_FILE), &eb).unwrap();
        assert!(is_damaged(damaged("a byte more"), "another size"));
        // nodes.bin of another length, or an entry past its end (or past u64).
        write_part(&part, &part_file(&plan, 1, 2, 99), &entries, b"LASF");
        assert!(is_damaged(damaged("an entry past the end"), "nodes.bin"));
        write_part(&part, &part_file(&plan, 1, 2, 100), &entries, b"LASF");
        std::fs::write(part.join(NODES_FILE), [0u8; 101]).unwrap();
        assert!(is_damaged(damaged("nodes.bin longer"), "nodes.bin"));
        let mut far = entries.clone();
        far[1].offset = u64::MAX - 10;
        write_part(&part, &part_file(&plan, 1, 2, 100), &far, b"LASF");
        assert!(is_damaged(damaged("an offset near u64::MAX"), "nodes.bin"));
        std::fs::remove_file(part.join(NODES_FILE)).unwrap();
        assert!(is_damaged(damaged("no nodes.bin"), "nodes.bin"));
        // entries.bin missing: the file named.
        write_part(&part, &part_file(&plan, 1, 2, 100), &entries, b"LASF");
        std::fs::remove_file(part.join(ENTRIES_FILE)).unwrap();
        assert!(matches!(read_part(&part), Err(Error::Io { ref path, .. })
                if path.ends_with(ENTRIES_FILE)));
        // part.json that does not parse, or none.
        std::fs::write(part.join(PART_FILE), b"{\"format\": 1}").unwrap();
        assert!(matches!(
            read_part(&part),
            Err(Error::Part { ref path, error: PartError::BadDescription { .. } })
                if path.ends_with(PART_FILE)
        ));
        std::fs::remove_file(part.join(PART_FILE)).unwrap();
        assert!(matches!(
            read_part(&part),
            Err(Error::Part { ref path, error: PartError::NotPart }) if *path == part
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
