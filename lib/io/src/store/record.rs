//! `build.json`: what a build needs to continue after a kill, a power loss or a full disk
//! (`mortar build --resume`): the engine, the settings that shape the tree, a fingerprint of
//! every input (path, size, modification time), and whether the build finished. How far it got
//! is the hierarchy's last commit. Written atomically (temporary name, then rename).

use crate::dataset::Dataset;
use crate::error::{Error, Result, StoreError};
use mortar_core::octree::{BuilderConfig, ColorMode};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The name of the build record in a store directory.
pub const RECORD_FILE: &str = "build.json";

pub use crate::dataset::InputPrint;

/// The build record.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct BuildRecord {
    /// `sorted` or `incremental`.
    pub engine: String,
    /// Leaf capacity.
    pub leaf_capacity: u32,
    /// Deepest level that may split.
    pub max_level: u8,
    /// `first-come` or `averaged`.
    pub colors: String,
    /// Points the headers declare.
    pub points: u64,
    /// The inputs, in order.
    pub inputs: Vec<InputPrint>,
    /// Whether the build finished.
    pub complete: bool,
}

impl BuildRecord {
    /// The record of a build of `ds` with `config` by `engine`, not finished.
    pub fn of(ds: &Dataset, config: &BuilderConfig, engine: &str) -> BuildRecord {
        let inputs = ds
            .inputs
            .iter()
            .flat_map(|i| -> Vec<InputPrint> {
                if let Some(s) = i.stands_for() {
                    return s.to_vec();
                }
                let p = i.path();
                let meta = std::fs::metadata(p).ok();
                vec![InputPrint {
                    path: std::fs::canonicalize(p)
                        .unwrap_or_else(|_| p.to_path_buf())
                        .display()
                        .to_string(),
                    bytes: meta.as_ref().map_or(0, |m| m.len()),
                    modified_ns: meta
                        .and_then(|m| m.modified().ok())
                        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                        .map_or(0, |d| d.as_nanos()),
                }]
            })
            .collect();
        BuildRecord {
            engine: engine.into(),
            leaf_capacity: config.leaf_capacity,
            max_level: config.max_level,
            colors: match config.color_mode {
                ColorMode::FirstCome => "first-come".into(),
                ColorMode::Averaged => "averaged".into(),
            },
            points: ds.declared_points(),
            inputs,
            complete: false,
        }
    }

    /// Writes the record into the store `dir` atomically.
    pub fn write(&self, dir: &Path) -> Result<()> {
        let p = dir.join(RECORD_FILE);
        let tmp = dir.join(format!("{RECORD_FILE}.tmp"));
        let bytes = serde_json::to_vec_pretty(self)
            .map_err(|error| Error::JsonFile { path: p.clone(), error })?;
        std::fs::write(&tmp, bytes).map_err(|e| Error::io(&tmp, e))?;
        std::fs::rename(&tmp, &p).map_err(|e| Error::io(&p, e))
    }

    /// The record of the store `dir`, if it has one that parses.
    pub fn read(dir: &Path) -> Result<Option<BuildRecord>> {
        let p = dir.join(RECORD_FILE);
        match std::fs::read(&p) {
            Ok(b) => serde_json::from_slice(&b).map(Some).map_err(|error| Error::Store {
                path: p.clone(),
                error: StoreError::BadBuildRecord { error },
            }),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(Error::io(&p, e)),
        }
    }

    /// Why a build described by `self` cannot continue the store recorded as `old`, if it cannot.
    pub fn mismatch(&self, old: &BuildRecord) -> Option<String> {
        if self.leaf_capacity != old.leaf_capacity
            || self.max_level != old.max_level
            || self.colors != old.colors
        {
            return Some(format!(
                "was built with other settings (leaf capacity {}, colours {}; now {}, {})",
                old.leaf_capacity, old.colors, self.leaf_capacity, self.colors
            ));
        }
        if self.inputs.len() != old.inputs.len() {
            return Some(format!(
                "was built from {} inputs, {} are given now",
                old.inputs.len(),
                self.inputs.len()
            ));
        }
        for (a, b) in self.inputs.iter().zip(&old.inputs) {
            if a.path != b.path {
                return Some(format!("was built from {}, not {}", b.path, a.path));
            }
            if a.bytes != b.bytes || a.modified_ns != b.modified_ns {
                return Some(format!(
                    "{} changed since the store was begun (size or modification time)",
                    a.path
                ));
            }
        }
        None
    }
}
