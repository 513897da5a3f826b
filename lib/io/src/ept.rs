//! EPT directories (Entwine Point Tile 1.x: `ept.json`, `ept-hierarchy/`, `ept-data/`) read as
//! LOD sources (issue 30 §1): the hierarchy's JSON files give each node's key and point count,
//! each node's points are one LAZ file (`ept-data/D-X-Y-Z.laz`), and every point is in exactly
//! one node: an additive tree ([`crate::additive`]) selected by the store's rule, of which only
//! the chosen nodes' files are opened.
//!
//! What is checked before it is trusted: `ept.json` parses, its `bounds` are six finite numbers
//! with a positive extent, its `dataType` is `laszip` (the others, `binary` and `zstandard`, are
//! refused by name) and its `hierarchyType` `json`; every hierarchy file is read once (a subtree
//! named twice is a loop) from inside `ept-hierarchy/`, keys parse and lie in their level, counts
//! are -1 (a subtree file) or at least 0. A directory that fails is reported ([`EptError`]) and
//! the caller reads its LAZ files flat.

use crate::additive::{node_key, AdditiveTree};
use crate::dataset::{Dataset, OpenOptions, RecordSource};
pub use crate::error::EptError;
use crate::error::{Error, Result};
use crate::remote::Remote;
use crate::source::LasInput;
use mortar_core::octree::{LodOptions, LodSelection, NodeKey};
use mortar_core::render::{Aabb, Camera, CameraError};
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// One node of an EPT directory.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct EptNode {
    /// Level and cell.
    pub key: NodeKey,
    /// Points the hierarchy gives it.
    pub points: u64,
}

/// An EPT directory opened as a LOD source.
#[derive(Clone, Debug)]
pub struct EptSource {
    /// The directory (holding `ept.json`).
    pub dir: PathBuf,
    /// Nodes with points.
    pub nodes: Vec<EptNode>,
    /// The tree the selection walks (positions in `nodes`).
    pub tree: AdditiveTree,
    /// `points` of `ept.json`.
    pub points: u64,
    /// `boundsConforming` of `ept.json` (the points' box), where given.
    pub conforming: Option<Aabb>,
    /// Hierarchy files read, and their bytes.
    pub hierarchy_files: u64,
    pub hierarchy_bytes: u64,
    /// Bytes of `ept.json`.
    pub meta_bytes: u64,
    /// `span` of `ept.json` (cells per node edge), where given.
    pub span: Option<u64>,
    /// The base URL (ending in `/`) of an EPT directory read over HTTP ([`crate::remote`]);
    /// `dir` is then that URL too.
    pub remote: Option<String>,
}

/// The directory of an EPT input: `path` itself when it holds `ept.json`, or the directory of
/// a path naming `ept.json`; `None` for anything else.
pub fn ept_dir(path: &Path) -> Option<PathBuf> {
    if path.file_name().is_some_and(|n| n == "ept.json") && path.is_file() {
        return Some(path.parent().unwrap_or(Path::new(".")).to_path_buf());
    }
    (path.is_dir() && path.join("ept.json").is_file()).then(|| path.to_path_buf())
}

fn numbers(v: &serde_json::Value, n: usize) -> Option<Vec<f64>> {
    let a = v.as_array()?;
    let x: Vec<f64> = a.iter().filter_map(|v| v.as_f64()).collect();
    (a.len() == n && x.len() == n && x.iter().all(|v| v.is_finite())).then_some(x)
}

impl EptSource {
    /// Reads `dir/ept.json` and the hierarchy (see the module docs).
    pub fn open(dir: &Path) -> std::result::Result<EptSource, EptError> {
        Self::open_with(dir, None, |p: &Path| {
            std::fs::read(p)
                .map_err(|e| EptError::Read { file: p.display().to_string(), error: e.to_string() })
        })
    }

    /// [`open`](Self::open) for the EPT directory at URL `base` (ending in `/`): `ept.json` and
    /// the hierarchy files are fetched whole; node files when a dataset asks for them.
    pub fn open_url(base: &str) -> std::result::Result<EptSource, EptError> {
        Self::open_with(Path::new(base), Some(base.to_string()), |p: &Path| {
            let url = p.to_string_lossy().to_string();
            let err = |e: Error| EptError::Read { file: url.clone(), error: e.problem() };
            let r = Remote::open(&url).map_err(err)?;
            r.fetch_all().map_err(err)?;
            std::fs::read(r.path())
                .map_err(|e| EptError::Read { file: url.clone(), error: e.to_string() })
        })
    }

    fn open_with(
        dir: &Path,
        remote: Option<String>,
        read: impl Fn(&Path) -> std::result::Result<Vec<u8>, EptError>,
    ) -> std::result::Result<EptSource, EptError> {
        let meta_path = dir.join("ept.json");
        let meta_raw = read(&meta_path)?;
        let meta: serde_json::Value = serde_json::from_slice(&meta_raw)
            .map_err(|e| EptError::Meta(format!("ept.json does not parse: {e}")))?;
        let b = numbers(&meta["bounds"], 6)
            .ok_or_else(|| EptError::Meta("ept.json's bounds are not six numbers".into()))?;
        let half = (0..3).map(|a| (b[a + 3] - b[a]) / 2.0).fold(0.0f64, f64::max);
        if !(half > 0.0 && half < 1e12) {
            return Err(EptError::Meta(format!("ept.json's bounds {b:?} hold no cube")));
        }
        let center = [0, 1, 2].map(|a| (b[a] + b[a + 3]) / 2.0);
        match meta["dataType"].as_str() {
            Some("laszip") => {}
            other => {
                return Err(EptError::Meta(format!(
                    "dataType {} is not read (laszip only)",
                    other.unwrap_or("(none)")
                )))
            }
        }
        if let Some(h) = meta["hierarchyType"].as_str() {
            if h != "json" {
                return Err(EptError::Meta(format!("hierarchyType {h} is not read (json only)")));
            }
        }
        let conforming = numbers(&meta["boundsConforming"], 6)
            .map(|c| Aabb { min: [c[0], c[1], c[2]], max: [c[3], c[4], c[5]] });
        let mut todo = vec!["0-0-0-0".to_string()];
        let mut seen: HashSet<String> = HashSet::new();
        let mut keys: HashSet<NodeKey> = HashSet::new();
        let mut nodes = Vec::new();
        let (mut files, mut bytes) = (0u64, 0u64);
        while let Some(name) = todo.pop() {
            if !seen.insert(name.clone()) {
                return Err(EptError::Hierarchy(format!(
                    "ept-hierarchy/{name}.json is named twice (a loop)"
                )));
            }
            let raw = read(&dir.join("ept-hierarchy").join(format!("{name}.json")))?;
            files += 1;
            bytes += raw.len() as u64;
            let page: serde_json::Map<String, serde_json::Value> = serde_json::from_slice(&raw)
                .map_err(|e| {
                    EptError::Hierarchy(format!("ept-hierarchy/{name}.json does not parse: {e}"))
                })?;
            for (k, v) in page {
                let bad = |why: String| {
                    EptError::Hierarchy(format!("ept-hierarchy/{name}.json: node {k} {why}"))
                };
                let parts: Vec<i32> = k.split('-').filter_map(|p| p.parse().ok()).collect();
                let [d, x, y, z] = parts[..] else {
                    return Err(bad("is not a key D-X-Y-Z".into()));
                };
                let key = node_key([d, x, y, z]).map_err(bad)?;
                let count = v.as_i64().ok_or_else(|| bad(format!("has count {v}")))?;
                match count {
                    -1 => {
                        // A subtree file, named by a key made of parsed numbers (no path
                        // outside the directory).
                        todo.push(format!("{d}-{x}-{y}-{z}"));
                    }
                    0 => {}
                    c if c > 0 => {
                        if !keys.insert(key) {
                            return Err(bad("is listed twice".into()));
                        }
                        nodes.push(EptNode { key, points: c as u64 });
                    }
                    c => return Err(bad(format!("has count {c}"))),
                }
            }
        }
        // A deterministic order: by level and cell.
        nodes.sort_unstable_by_key(|n| (n.key.level, n.key.index));
        let pairs: Vec<(NodeKey, u64)> = nodes.iter().map(|n| (n.key, n.points)).collect();
        let tree = AdditiveTree::new(center, half, &pairs).map_err(EptError::Hierarchy)?;
        let points = meta["points"].as_u64().unwrap_or_else(|| pairs.iter().map(|p| p.1).sum());
        Ok(EptSource {
            dir: dir.to_path_buf(),
            nodes,
            tree,
            points,
            conforming,
            hierarchy_files: files,
            hierarchy_bytes: bytes,
            meta_bytes: meta_raw.len() as u64,
            span: meta["span"].as_u64(),
            remote,
        })
    }

    /// The LAZ file of node `i`.
    pub fn node_path(&self, i: usize) -> PathBuf {
        let k = self.nodes[i].key;
        let [x, y, z] = k.index;
        self.dir.join("ept-data").join(format!("{}-{x}-{y}-{z}.laz", k.level))
    }

    /// Where node `i`'s LAZ file is read: its path, or over HTTP its local copy (fetched whole
    /// now). An error names a node the hierarchy lists without a file.
    pub fn node_file(&self, i: usize) -> Result<PathBuf> {
        let path = self.node_path(i);
        if self.remote.is_some() {
            let r = Remote::open(&path.to_string_lossy())?;
            r.fetch_all()?;
            return Ok(r.path().to_path_buf());
        }
        if !path.is_file() {
            let k = self.nodes[i].key;
            let [x, y, z] = k.index;
            return Err(Error::Ept {
                path: self.dir.clone(),
                error: EptError::Hierarchy(format!(
                    "node {}-{x}-{y}-{z} is in the hierarchy but ept-data has no file for it",
                    k.level
                )),
            });
        }
        Ok(path)
    }

    /// Points in the hierarchy's nodes.
    pub fn node_points(&self) -> u64 {
        self.nodes.iter().map(|n| n.points).sum()
    }

    /// The nodes to read for `camera` ([`AdditiveTree::select`]), ordered by their files' paths
    /// (the order a directory's files are read in); with the selection itself.
    pub fn select(
        &self,
        camera: &Camera,
        options: &LodOptions,
    ) -> std::result::Result<(Vec<usize>, LodSelection), CameraError> {
        let (mut nodes, sel) = self.tree.select(camera, options)?;
        nodes.sort_by_cached_key(|&i| self.node_path(i));
        Ok((nodes, sel))
    }

    /// The points of `nodes` (positions in `nodes`) as a dataset of their LAZ files, decoding
    /// only the `attributes` named (positions always).
    pub fn dataset(
        &self,
        nodes: &[usize],
        opts: &OpenOptions,
        attributes: &[&str],
    ) -> Result<Dataset> {
        if self.remote.is_some() {
            crate::remote::in_parallel(nodes, |&i| self.node_file(i).map(|_| ()))?;
        }
        let mut inputs: Vec<Box<dyn RecordSource>> = Vec::with_capacity(nodes.len());
        for &i in nodes {
            let path = self.node_file(i)?;
            let mut input = LasInput::open(&path)?;
            input.decode_only(attributes);
            inputs.push(Box::new(input));
        }
        Dataset::with_options(inputs, opts)
    }

    /// Bytes of the files of `nodes` (over HTTP: of those fetched).
    pub fn node_bytes(&self, nodes: &[usize]) -> u64 {
        if self.remote.is_some() {
            return nodes
                .iter()
                .filter_map(|&i| Remote::opened(&self.node_path(i).to_string_lossy()))
                .map(|r| r.len())
                .sum();
        }
        nodes
            .iter()
            .filter_map(|&i| std::fs::metadata(self.node_path(i)).ok())
            .map(|m| m.len())
            .sum()
    }

    /// Bytes of every node file (over HTTP: not known without a request per file).
    pub fn total_bytes(&self) -> Option<u64> {
        if self.remote.is_some() {
            return None;
        }
        Some(self.whole_bytes())
    }

    fn whole_bytes(&self) -> u64 {
        self.node_bytes(&(0..self.nodes.len()).collect::<Vec<_>>())
    }
}
