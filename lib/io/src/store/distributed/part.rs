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
