//! A COPC file or an EPT directory opened as a LOD source (issue 30 §1): one interface over both
//! for `mortar render` (the nodes of one view, decoded at once) and `mortar view` (nodes decoded
//! one by one as the camera moves).
//!
//! Both are additive trees ([`crate::additive`]) selected by the store's rule. The *read order*
//! of the nodes is the order a flat read meets their points: a COPC file's chunks by file
//! offset, an EPT directory's files by path; numbering points in that order gives a view of
//! every node the point indices (and so the depth-tie order) of the flat read.

use crate::additive::AdditiveTree;
use crate::copc::{is_copc_path, CopcFile};
use crate::dataset::{Dataset, OpenOptions};
use crate::ept::{ept_dir, EptSource};
use crate::error::{Error, Result};
use crate::remote::{is_url, Remote};
use crate::source::LasInput;
use mortar_core::layout::RecordLayout;
use mortar_core::octree::{LodOptions, LodSelection, NodeKey};
use mortar_core::render::framing::ViewBox;
use mortar_core::render::{Aabb, Camera, CameraError};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A COPC file or an EPT directory with a usable hierarchy.
#[derive(Debug)]
pub enum LodSource {
    /// A COPC file (over HTTP: its local sparse copy, and the remote file that fills it).
    Copc(Box<CopcFile>, Option<Arc<Remote>>),
    /// An EPT directory.
    Ept(Box<EptSource>),
}

/// Whether `path` names a COPC file (a cheap look at its VLRs) or an EPT directory; a URL is
/// asked for whether it is COPC by [`LodSource::open_url`].
pub fn is_lod_source_path(path: &Path) -> bool {
    path.to_str().is_some_and(is_url) || is_copc_path(path) || ept_dir(path).is_some()
}

impl LodSource {
    /// Opens `path` as a LOD source: `Ok((None, None))` when it is neither a COPC file nor an
    /// EPT directory, `Ok((None, Some(warning)))` when its hierarchy cannot be used (the caller
    /// reads it flat and says the warning); an error only where the file cannot be opened.
    pub fn open(path: &Path) -> Result<(Option<LodSource>, Option<String>)> {
        if let Some(url) = path.to_str().filter(|s| is_url(s)) {
            return Self::open_url(url);
        }
        if let Some(dir) = ept_dir(path) {
            return Ok(match EptSource::open(&dir) {
                Ok(e) => (Some(LodSource::Ept(Box::new(e))), None),
                Err(e) => {
                    (None, Some(format!("{}: EPT: {e}; reading its LAZ files flat", dir.display())))
                }
            });
        }
        let (file, warning) = CopcFile::open(path)?;
        Ok((file.map(|f| LodSource::Copc(Box::new(f), None)), warning))
    }

    /// [`open`](Self::open) for a URL: a COPC file read with range requests (its header, VLRs,
    /// chunk table and EVLRs now, its nodes' chunks as they are asked for); `Ok((None, None))`
    /// for anything else (read whole as a LAS/LAZ input).
    pub fn open_url(url: &str) -> Result<(Option<LodSource>, Option<String>)> {
        if url.ends_with('/') || url.ends_with("/ept.json") {
            let base = url.strip_suffix("ept.json").unwrap_or(url);
            return Ok(match EptSource::open_url(base) {
                Ok(e) => (Some(LodSource::Ept(Box::new(e))), None),
                Err(e) => return Err(Error::Ept { path: PathBuf::from(base), error: e }),
            });
        }
        let remote = Remote::open(url)?;
        remote.fetch_las_index()?;
        if !is_copc_path(remote.path()) {
            return Ok((None, None));
        }
        let (file, warning) = CopcFile::open(remote.path())?;
        let warning = warning.map(|w| w.replace(&remote.path().display().to_string(), url));
        let Some(mut file) = file else { return Ok((None, warning)) };
        file.path = PathBuf::from(url);
        file.local = Some(remote.path().to_path_buf());
        // The first chunk: what the framing rule checks the header's box against.
        let first = file.lod.hierarchy.nodes.iter().min_by_key(|n| n.offset).copied();
        if let Some(n) = first {
            remote.fetch(n.offset, n.bytes)?;
        }
        Ok((Some(LodSource::Copc(Box::new(file), Some(remote))), warning))
    }

    /// Bytes fetched over HTTP so far (0 for a local source).
    pub fn bytes_fetched(&self) -> u64 {
        match self {
            LodSource::Copc(_, Some(r)) => r.bytes_fetched(),
            LodSource::Ept(e) if e.remote.is_some() => crate::remote::fetched_under(&e.dir),
            _ => 0,
        }
    }

    /// `copc` or `ept`.
    pub fn format(&self) -> &'static str {
        match self {
            LodSource::Copc(..) => "copc",
            LodSource::Ept(_) => "ept",
        }
    }

    /// The file or directory.
    pub fn path(&self) -> &Path {
        match self {
            LodSource::Copc(f, _) => &f.path,
            LodSource::Ept(e) => &e.dir,
        }
    }

    /// The tree the selection walks.
    pub fn tree(&self) -> &AdditiveTree {
        match self {
            LodSource::Copc(f, _) => &f.lod.tree,
            LodSource::Ept(e) => &e.tree,
        }
    }

    /// Nodes with points.
    pub fn node_count(&self) -> usize {
        match self {
            LodSource::Copc(f, _) => f.lod.hierarchy.nodes.len(),
            LodSource::Ept(e) => e.nodes.len(),
        }
    }

    /// Node `i`'s key.
    pub fn node_key(&self, i: usize) -> NodeKey {
        match self {
            LodSource::Copc(f, _) => f.lod.hierarchy.nodes[i].key,
            LodSource::Ept(e) => e.nodes[i].key,
        }
    }

    /// Points the hierarchy gives node `i`.
    pub fn node_points(&self, i: usize) -> u64 {
        match self {
            LodSource::Copc(f, _) => f.lod.hierarchy.nodes[i].points,
            LodSource::Ept(e) => e.nodes[i].points,
        }
    }

    /// Bytes read to decode nodes `nodes`: their chunks, or their files.
    pub fn node_bytes(&self, nodes: &[usize]) -> u64 {
        match self {
            LodSource::Copc(f, _) => nodes.iter().map(|&i| f.lod.hierarchy.nodes[i].bytes).sum(),
            LodSource::Ept(e) => e.node_bytes(nodes),
        }
    }

    /// Points in all nodes.
    pub fn points(&self) -> u64 {
        match self {
            LodSource::Copc(f, _) => f.lod.hierarchy.points(),
            LodSource::Ept(e) => e.points,
        }
    }

    /// Bytes read before any node: COPC's header, VLRs and hierarchy pages; EPT's `ept.json`
    /// and hierarchy files.
    pub fn index_bytes(&self) -> u64 {
        match self {
            LodSource::Copc(f, _) => f.index_bytes(),
            LodSource::Ept(e) => e.meta_bytes + e.hierarchy_bytes,
        }
    }

    /// Bytes of the whole source (`None` for an EPT directory over HTTP: not known without a
    /// request per file).
    pub fn total_bytes(&self) -> Option<u64> {
        match self {
            LodSource::Copc(f, _) => Some(f.file_len()),
            LodSource::Ept(e) => e.total_bytes().map(|b| b + e.meta_bytes + e.hierarchy_bytes),
        }
    }

    /// Hierarchy pages (COPC) or files (EPT) read.
    pub fn pages(&self) -> u64 {
        match self {
            LodSource::Copc(f, _) => f.lod.hierarchy.pages,
            LodSource::Ept(e) => e.hierarchy_files,
        }
    }

    /// The nodes to read for `camera` ([`AdditiveTree::select`]) in read order (see the module
    /// docs); with the selection itself.
    pub fn select(
        &self,
        camera: &Camera,
        options: &LodOptions,
    ) -> std::result::Result<(Vec<usize>, LodSelection), CameraError> {
        match self {
            LodSource::Copc(f, _) => f.lod.select(camera, options),
            LodSource::Ept(e) => e.select(camera, options),
        }
    }

    /// Every node in read order.
    pub fn read_order(&self) -> Vec<usize> {
        let mut all: Vec<usize> = (0..self.node_count()).collect();
        match self {
            LodSource::Copc(f, _) => all.sort_unstable_by_key(|&i| f.lod.hierarchy.nodes[i].offset),
            LodSource::Ept(e) => all.sort_by_cached_key(|&i| e.node_path(i)),
        }
        all
    }

    /// The points of `nodes` (in the order given) as a dataset that decodes only them, and of
    /// their records only the `attributes` named (positions always).
    pub fn dataset(
        &self,
        nodes: &[usize],
        opts: &OpenOptions,
        attributes: &[&str],
    ) -> Result<Dataset> {
        match self {
            LodSource::Copc(f, remote) => {
                if let Some(r) = remote {
                    crate::remote::in_parallel(nodes, |&i| {
                        let n = f.lod.hierarchy.nodes[i];
                        r.fetch(n.offset, n.bytes)
                    })?;
                }
                f.nodes(nodes, opts, attributes)
            }
            LodSource::Ept(e) => e.dataset(nodes, opts, attributes),
        }
    }

    /// The record layout of the points (an EPT directory's: its first node file's in read
    /// order).
    pub fn layout(&self) -> Result<RecordLayout> {
        match self {
            LodSource::Copc(f, _) => Ok(f.layout().clone()),
            LodSource::Ept(e) => {
                let first = self.read_order().first().copied().unwrap_or(0);
                Ok(LasInput::open(&e.node_file(first)?)?.layout)
            }
        }
    }

    /// The box a view of the whole source frames: a COPC file's what a flat read frames (the
    /// header's box, checked against the root chunk), an EPT directory's `boundsConforming`
    /// (the points' box), else the tree's cube.
    pub fn bounds(&self, opts: &OpenOptions) -> Result<Aabb> {
        Ok(match self {
            LodSource::Copc(f, _) => {
                let whole = f.whole(opts)?;
                match crate::framing::view_box(&whole)? {
                    ViewBox::Header(h) => h.world(&whole.grid),
                    ViewBox::Points => f.lod.cube_bounds(),
                }
            }
            LodSource::Ept(e) => e.conforming.unwrap_or_else(|| e.tree.cube_bounds()),
        })
    }
}
