//! COPC files read as LOD sources (issue 30 §1): the info VLR and the hierarchy pages
//! ([`CopcHierarchy`]), the tree they describe as a [`LodIndex`] the store's node selection walks
//! ([`CopcLod`]), and an input that decodes only the chunks of chosen nodes
//! ([`CopcLod::open_nodes`]).
//!
//! COPC (copc.io, 1.0) is a LAZ 1.4 file whose variable-size chunks are the nodes of an octree: a
//! node `(d, x, y, z)` of the cube of half-size `halfsize` around `center` holds its points in one
//! chunk (offset, byte size, point count in the hierarchy), and every point is in exactly one
//! node: an additive tree ([`crate::additive`]), selected by the store's rule.
//!
//! Everything read from the file is checked before it is trusted: pages and chunks inside the
//! file, page sizes in whole entries, each page read once (no loop), levels below
//! [`MAX_LEVEL`](crate::additive::MAX_LEVEL), keys inside their level, at most one entry per key. A hierarchy that fails is
//! reported ([`CopcError`]) and the caller reads the file flat.

use crate::additive::{node_key, AdditiveTree};
use crate::dataset::{Dataset, OpenOptions, RecordSource};
pub use crate::error::CopcError;
use crate::error::{Error, Result};
use crate::source::LasInput;
use mortar_core::octree::{LodOptions, LodSelection, NodeKey};
use mortar_core::render::{Aabb, Camera, CameraError};
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// Bytes of one hierarchy entry: key (4 x i32), offset (u64), byte size (i32), point count
/// (i32).
const ENTRY: usize = 32;

/// The COPC info VLR (user `copc`, record 1, 160 bytes).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CopcInfo {
    /// Centre of the root cube (world units).
    pub center: [f64; 3],
    /// Half the root cube's edge.
    pub halfsize: f64,
    /// Distance between points at the root.
    pub spacing: f64,
    /// File offset of the root hierarchy page.
    pub root_hier_offset: u64,
    /// Its size in bytes.
    pub root_hier_size: u64,
}

/// One node of a COPC file with its chunk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CopcNode {
    /// Level and cell.
    pub key: NodeKey,
    /// File offset of the node's LAZ chunk.
    pub offset: u64,
    /// Bytes of the chunk.
    pub bytes: u64,
    /// Points in the chunk.
    pub points: u64,
}

/// Whether `path` is a COPC file: a LAS file whose first VLR (at byte 375) is the COPC info
/// VLR, as the COPC specification places it. Reads 400 bytes; any failure is "no".
pub fn is_copc_path(path: &Path) -> bool {
    use std::io::Read;
    let mut head = [0u8; 400];
    let ok = std::fs::File::open(path).and_then(|mut f| f.read_exact(&mut head)).is_ok();
    ok && &head[..4] == b"LASF"
        && &head[377..381] == b"copc"
        && u16::from_le_bytes([head[393], head[394]]) == 1
}

/// The info VLR of a file's VLRs, if it has one (`None`: not COPC).
pub fn info_of(vlrs: &[crate::las::Vlr]) -> Option<std::result::Result<CopcInfo, CopcError>> {
    let v = vlrs.iter().find(|v| v.is_copc() && v.record_id == 1)?;
    Some(parse_info(&v.data))
}

fn parse_info(d: &[u8]) -> std::result::Result<CopcInfo, CopcError> {
    if d.len() < 160 {
        return Err(CopcError::Info(format!("{} bytes, 160 expected", d.len())));
    }
    let f = |i: usize| f64::from_le_bytes(d[8 * i..8 * i + 8].try_into().unwrap());
    let u = |i: usize| u64::from_le_bytes(d[8 * i..8 * i + 8].try_into().unwrap());
    let info = CopcInfo {
        center: [f(0), f(1), f(2)],
        halfsize: f(3),
        spacing: f(4),
        root_hier_offset: u(5),
        root_hier_size: u(6),
    };
    if !(info.center.iter().all(|c| c.is_finite()) && info.halfsize > 0.0 && info.halfsize < 1e12) {
        return Err(CopcError::Info(format!(
            "centre {:?}, half-size {}",
            info.center, info.halfsize
        )));
    }
    Ok(info)
}

/// A COPC file's hierarchy: every node with points, read from all pages.
#[derive(Clone, Debug)]
pub struct CopcHierarchy {
    /// The info VLR.
    pub info: CopcInfo,
    /// Nodes with points, in the order the pages list them.
    pub nodes: Vec<CopcNode>,
    /// Hierarchy pages read.
    pub pages: u64,
    /// Bytes of the hierarchy pages read.
    pub page_bytes: u64,
}

impl CopcHierarchy {
    /// Reads the hierarchy of the COPC file `bytes` (the whole file) from its root page on.
    pub fn read(bytes: &[u8], info: CopcInfo) -> std::result::Result<CopcHierarchy, CopcError> {
        let len = bytes.len() as u64;
        let mut todo = vec![(info.root_hier_offset, info.root_hier_size)];
        let mut seen: HashSet<u64> = HashSet::new();
        let mut keys: HashSet<NodeKey> = HashSet::new();
        let mut nodes = Vec::new();
        let (mut pages, mut page_bytes) = (0u64, 0u64);
        while let Some((offset, size)) = todo.pop() {
            let bad = |why| CopcError::Page { offset, size, why };
            if size % ENTRY as u64 != 0 {
                return Err(bad("is not a whole number of 32-byte entries"));
            }
            if offset.checked_add(size).is_none_or(|e| e > len) {
                return Err(bad("lies outside the file"));
            }
            if !seen.insert(offset) {
                return Err(bad("is listed twice (a loop)"));
            }
            pages += 1;
            page_bytes += size;
            let page = &bytes[offset as usize..(offset + size) as usize];
            for e in page.chunks_exact(ENTRY) {
                let i = |k: usize| i32::from_le_bytes(e[4 * k..4 * k + 4].try_into().unwrap());
                let raw = [i(0), i(1), i(2), i(3)];
                let at = u64::from_le_bytes(e[16..24].try_into().unwrap());
                let byte_size = i32::from_le_bytes(e[24..28].try_into().unwrap());
                let count = i32::from_le_bytes(e[28..32].try_into().unwrap());
                let wrong = |why: String| CopcError::Entry { key: raw, why };
                let key = node_key(raw).map_err(wrong)?;
                if count == -1 {
                    // A child page.
                    todo.push((
                        at,
                        u64::try_from(byte_size)
                            .map_err(|_| wrong(format!("names a page of {byte_size} bytes")))?,
                    ));
                    continue;
                }
                if count < -1 || byte_size < 0 {
                    return Err(wrong(format!("has {count} points in {byte_size} bytes")));
                }
                if !keys.insert(key) {
                    return Err(wrong("is listed twice".into()));
                }
                if count == 0 {
                    continue;
                }
                if byte_size == 0 || at.checked_add(byte_size as u64).is_none_or(|e| e > len) {
                    return Err(wrong(format!(
                        "names a chunk at byte {at} of {byte_size} bytes outside the file"
                    )));
                }
                nodes.push(CopcNode {
                    key,
                    offset: at,
                    bytes: byte_size as u64,
                    points: count as u64,
                });
            }
        }
        Ok(CopcHierarchy { info, nodes, pages, page_bytes })
    }

    /// Points in all nodes.
    pub fn points(&self) -> u64 {
        self.nodes.iter().map(|n| n.points).sum()
    }

    /// Per level: nodes and points (index = level).
    pub fn levels(&self) -> Vec<(u64, u64)> {
        let depth = self.nodes.iter().map(|n| n.key.level as usize + 1).max().unwrap_or(0);
        let mut v = vec![(0u64, 0u64); depth];
        for n in &self.nodes {
            let l = &mut v[n.key.level as usize];
            l.0 += 1;
            l.1 += n.points;
        }
        v
    }
}

/// A COPC file's tree ready for node selection: its hierarchy and the [`AdditiveTree`] of its
/// nodes (positions in `hierarchy.nodes`).
#[derive(Clone, Debug)]
pub struct CopcLod {
    /// The hierarchy.
    pub hierarchy: CopcHierarchy,
    /// The tree the selection walks.
    pub tree: AdditiveTree,
}

impl CopcLod {
    /// The tree of `hierarchy` (see the module docs).
    pub fn new(hierarchy: CopcHierarchy) -> std::result::Result<CopcLod, CopcError> {
        let nodes: Vec<(NodeKey, u64)> =
            hierarchy.nodes.iter().map(|n| (n.key, n.points)).collect();
        let info = hierarchy.info;
        let tree =
            AdditiveTree::new(info.center, info.halfsize, &nodes).map_err(CopcError::Orphan)?;
        Ok(CopcLod { hierarchy, tree })
    }

    /// Reads the hierarchy of an opened COPC input; `None` when it is not COPC.
    pub fn of_input(input: &LasInput) -> Option<std::result::Result<CopcLod, CopcError>> {
        let info = match info_of(&input.meta.vlrs)? {
            Ok(i) => i,
            Err(e) => return Some(Err(e)),
        };
        let lod = CopcHierarchy::read(input.file_bytes(), info).and_then(CopcLod::new);
        Some(lod.and_then(|l| l.check_chunks(input).map(|_| l)))
    }

    /// The COPC cube's world box.
    pub fn cube_bounds(&self) -> Aabb {
        self.tree.cube_bounds()
    }

    /// The nodes to read for `camera` ([`AdditiveTree::select`]) as positions in
    /// `hierarchy.nodes` by ascending file offset; with the selection itself.
    pub fn select(
        &self,
        camera: &Camera,
        options: &LodOptions,
    ) -> std::result::Result<(Vec<usize>, LodSelection), CameraError> {
        let (mut nodes, sel) = self.tree.select(camera, options)?;
        nodes.sort_unstable_by_key(|&i| self.hierarchy.nodes[i].offset);
        Ok((nodes, sel))
    }

    /// `input` (this file, opened) reduced to the chunks of `nodes` (positions in
    /// `hierarchy.nodes`): only they are decoded when it is read. An error names a node whose
    /// chunk is not one of the file's chunks (the hierarchy and the chunk table disagree).
    pub fn open_nodes(
        &self,
        input: &mut LasInput,
        nodes: &[usize],
    ) -> std::result::Result<(), CopcError> {
        let offsets: Vec<(u64, u64)> = nodes
            .iter()
            .map(|&i| (self.hierarchy.nodes[i].offset, self.hierarchy.nodes[i].points))
            .collect();
        input.keep_chunks(&offsets).map_err(|e| self.chunk_error(e))
    }

    /// Checks every node against `input`'s chunk table (offsets and point counts agree).
    pub fn check_chunks(&self, input: &LasInput) -> std::result::Result<(), CopcError> {
        let all: Vec<(u64, u64)> =
            self.hierarchy.nodes.iter().map(|n| (n.offset, n.points)).collect();
        input.find_chunks(&all).map(|_| ()).map_err(|e| self.chunk_error(e))
    }

    fn chunk_error(&self, (offset, why): (u64, String)) -> CopcError {
        CopcError::Entry {
            key: self.hierarchy.nodes.iter().find(|n| n.offset == offset).map_or([-1; 4], |n| {
                [
                    n.key.level as i32,
                    n.key.index[0] as i32,
                    n.key.index[1] as i32,
                    n.key.index[2] as i32,
                ]
            }),
            why,
        }
    }
}

/// A COPC file opened as a LOD source: its input (not yet reduced) and its tree.
#[derive(Debug)]
pub struct CopcFile {
    /// The file (or the URL it came from, which names it in messages).
    pub path: PathBuf,
    /// Where its bytes are read when not at `path`: the local copy of a URL
    /// ([`crate::remote`]).
    pub local: Option<PathBuf>,
    /// Its tree.
    pub lod: CopcLod,
    input: LasInput,
}

impl CopcFile {
    /// Opens `path` as a LOD source: `Ok(None)` when it is not a COPC file (no info VLR) or
    /// when its hierarchy cannot be used, which is then said in the returned warning (the caller
    /// reads it flat); an error only where the file itself cannot be opened.
    pub fn open(path: &Path) -> Result<(Option<CopcFile>, Option<String>)> {
        let input = LasInput::open(path)?;
        match CopcLod::of_input(&input) {
            None => Ok((None, None)),
            Some(Err(e)) => Ok((
                None,
                Some(format!("{}: COPC: {e}; reading it as a flat LAZ file", path.display())),
            )),
            Some(Ok(lod)) => {
                Ok((Some(CopcFile { path: path.to_path_buf(), local: None, lod, input }), None))
            }
        }
    }

    /// Where the file's bytes are read.
    fn bytes_path(&self) -> &Path {
        self.local.as_deref().unwrap_or(&self.path)
    }

    /// The file's record layout.
    pub fn layout(&self) -> &mortar_core::layout::RecordLayout {
        &self.input.layout
    }

    /// Bytes of the file.
    pub fn file_len(&self) -> u64 {
        self.input.file_bytes().len() as u64
    }

    /// Bytes read before any node: the header and VLRs (up to the point data) and the
    /// hierarchy pages.
    pub fn index_bytes(&self) -> u64 {
        self.input.meta.header.offset_to_point_data as u64 + self.lod.hierarchy.page_bytes
    }

    /// The whole file as a dataset (every chunk), e.g. for the framing of a view.
    pub fn whole(&self, opts: &OpenOptions) -> Result<Dataset> {
        Dataset::with_options(vec![Box::new(LasInput::open(self.bytes_path())?)], opts)
    }

    /// The points of `nodes` (positions in the hierarchy's nodes) as a dataset that decodes
    /// only their chunks, and of those only the `attributes` named (positions always; see
    /// [`LasInput::decode_only`]). The file is opened again (a map, the chunk table): a viewer
    /// asks for nodes one by one.
    pub fn nodes(
        &self,
        nodes: &[usize],
        opts: &OpenOptions,
        attributes: &[&str],
    ) -> Result<Dataset> {
        let mut input = LasInput::open(self.bytes_path())?;
        input.decode_only(attributes);
        self.lod
            .open_nodes(&mut input, nodes)
            .map_err(|error| Error::Copc { path: self.path.clone(), error })?;
        let sources: Vec<Box<dyn RecordSource>> = vec![Box::new(input)];
        Dataset::with_options(sources, opts)
    }
}
