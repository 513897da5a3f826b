//! 3D Tiles 1.1 (CesiumJS, deck.gl, game engines): a directory of
//!
//! - `tileset.json`: the tree of tiles, one per octree node with its points (every point in
//!   exactly one tile, `refine: ADD`, the assignment of the COPC export), each tile's bounding
//!   box the box of its points and of the tiles below it, in a local east-north-up frame whose
//!   root `transform` places it on the WGS 84 globe (ECEF, EPSG:4978);
//! - `tiles/<level>-<x>-<y>-<z>.glb`: a tile's points ([`super::glb`]);
//! - `tiles/<level>-<x>-<y>-<z>.json`: external tilesets, one for each subtree below a node at a
//!   level that is a multiple of [`SPLIT`] (explicit tiling in pieces, so a viewer reads the
//!   top of a deep tree first and each piece when it gets there).
//!
//! Geometric errors: a tile of level `l` holds points spaced about `s_l` apart (the root's
//! spacing, its edge over 128, halved per level); its error is `8 s_l`, so a viewer at its
//! default maximum screen-space error (16 pixels) loads the children when the tile's points
//! are more than 2 pixels apart. Leaves have error 0.
//!
//! Placement ([`crate::globe`]): each point is transformed from the input's CRS to ECEF and
//! then into the frame at the data's centre (doubles all the way), so that the tiles sit on
//! the globe with the curvature and convergence of the real projection. An input without a CRS
//! is written in its own coordinates (the root transform a translation to the data's centre)
//! with a warning; a CRS that cannot be transformed is refused with its name.

use super::glb::{self, Attrs, Bounds, Point};
use super::nodes::{Frame, NodeWriter, OutNode};
use super::options::ExportReport;
use crate::cleanup::TempPath;
use crate::crs::CrsRecords;
use crate::dataset::Dataset;
use crate::error::{Error, ExportError, Result};
use crate::globe::{Enu, Globe};
use crate::sort::PieceStats;
use mortar_core::color::RgbDepth;
use mortar_core::octree::NodeKey;
use rayon::prelude::*;
use serde_json::json;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Levels per tileset piece: the subtrees of nodes at levels that are multiples of this are
/// external tilesets.
pub const SPLIT: u8 = 4;

/// Where the points go: the globe, or a local frame.
enum Place {
    Globe { globe: Box<Globe>, enu: Enu },
    Local { origin: [f64; 3] },
}

impl Place {
    #[inline]
    fn local(&self, w: [f64; 3]) -> std::result::Result<[f64; 3], String> {
        match self {
            Place::Globe { globe, enu } => Ok(enu.local(globe.ecef(w)?)),
            Place::Local { origin } => Ok([w[0] - origin[0], w[1] - origin[1], w[2] - origin[2]]),
        }
    }
    fn transform(&self) -> [f64; 16] {
        match self {
            Place::Globe { enu, .. } => enu.to_ecef_matrix(),
            Place::Local { origin } => {
                let mut m = [0.0; 16];
                m[0] = 1.0;
                m[5] = 1.0;
                m[10] = 1.0;
                m[15] = 1.0;
                m[12..15].copy_from_slice(origin);
                m
            }
        }
    }
}

/// What a written tile was.
#[derive(Clone, Copy, Debug)]
struct Placed {
    points: u64,
    bounds: Bounds,
    bytes: u64,
}

/// The 3D Tiles directory being written: tiles as nodes come, the tilesets at the end.
pub(crate) struct Tiles3dWriter<'a> {
    ds: &'a Dataset,
    frame: Frame,
    out: PathBuf,
    tmp: TempPath,
    tiles: PathBuf,
    place: Place,
    attrs: Attrs,
    /// The input's resolution in the frame's units (its smallest LAS scale, in metres on the
    /// globe): positions are quantized to 16 bits where a step is no larger.
    resolution: f64,
    placed: HashMap<NodeKey, Placed>,
    max_error: f64,
    crs: Option<String>,
}

fn tile_name(k: &NodeKey) -> String {
    format!("{}-{}-{}-{}", k.level, k.index[0], k.index[1], k.index[2])
}

impl<'a> Tiles3dWriter<'a> {
    /// Places the data (its CRS, its centre from `stats`) and makes the temporary directory.
    pub(crate) fn create(
        ds: &'a Dataset,
        frame: Frame,
        out: &Path,
        stats: &PieceStats,
        warnings: &mut Vec<String>,
    ) -> Result<Tiles3dWriter<'a>> {
        let first = ds.inputs[0].path().to_path_buf();
        let g = &ds.grid;
        let centre = [0, 1, 2].map(|a| {
            g.offset[a] + g.scale[a] * ((stats.min[a] as f64 + stats.max[a] as f64) / 2.0)
        });
        let records = CrsRecords::of(&ds.vlrs, &ds.evlrs);
        let globe = Globe::of_records(&records).map_err(|why| Error::Export {
            path: first.clone(),
            error: ExportError::Globe { why },
        })?;
        let smin = g.scale.iter().cloned().fold(f64::INFINITY, f64::min);
        let (place, resolution, crs) = match globe {
            Some(globe) => {
                let geo = globe.geodetic(centre).map_err(|why| Error::Export {
                    path: first.clone(),
                    error: ExportError::Globe { why },
                })?;
                // The resolution in metres: one grid step near the centre.
                let e0 = globe.ecef(centre).ok();
                let e1 = globe.ecef([centre[0] + smin, centre[1], centre[2]]).ok();
                let res = match (e0, e1) {
                    (Some(a), Some(b)) => {
                        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2))
                            .sqrt()
                    }
                    _ => smin,
                };
                let name = format!("{} ({})", globe.name, globe.proj4);
                (Place::Globe { enu: Enu::at(geo), globe: Box::new(globe) }, res, Some(name))
            }
            None => {
                warnings.push(format!(
                    "{}: the input has no CRS; the 3D Tiles are in its own coordinates around ({:.3}, {:.3}, {:.3}), not on the globe (give it one with --assign-crs EPSG:code)",
                    first.display(),
                    centre[0],
                    centre[1],
                    centre[2]
                ));
                (Place::Local { origin: centre }, smin, None)
            }
        };
        let color = match frame.out.format {
            7 | 8 => {
                if RgbDepth::detect(stats.max_rgb) == RgbDepth::Eight {
                    1
                } else {
                    2
                }
            }
            _ => 0,
        };
        let attrs = Attrs { color, intensity: stats.max_intensity > 0, classification: true };
        let tmp = TempPath::beside(out);
        let dir = tmp.path().to_path_buf();
        let tiles = dir.join("tiles");
        std::fs::create_dir_all(&tiles).map_err(|e| Error::io(&tiles, e))?;
        Ok(Tiles3dWriter {
            ds,
            frame,
            out: out.to_path_buf(),
            tmp,
            tiles,
            place,
            attrs,
            resolution,
            placed: HashMap::new(),
            max_error: 0.0,
            crs,
        })
    }

    /// The points of LAS 1.4 records `recs`, placed.
    fn points(&self, recs: &[u8]) -> Result<Vec<Point>> {
        let rl = self.frame.out.record_len;
        let g = &self.ds.grid;
        let rgb_at = matches!(self.frame.out.format, 7 | 8);
        recs.chunks_exact(rl)
            .map(|r| {
                let i = |o: usize| i32::from_le_bytes(r[o..o + 4].try_into().unwrap()) as f64;
                let w = [
                    g.offset[0] + g.scale[0] * i(0),
                    g.offset[1] + g.scale[1] * i(4),
                    g.offset[2] + g.scale[2] * i(8),
                ];
                let p = self.place.local(w).map_err(|why| Error::Export {
                    path: self.ds.inputs[0].path().to_path_buf(),
                    error: ExportError::Globe { why },
                })?;
                let u = |o: usize| u16::from_le_bytes([r[o], r[o + 1]]);
                Ok(Point {
                    p,
                    rgb: if rgb_at { [u(30), u(32), u(34)] } else { [0; 3] },
                    intensity: u(12),
                    classification: r[16],
                })
            })
            .collect()
    }

    fn write_file(&self, key: &NodeKey, bytes: &[u8]) -> Result<()> {
        let p = self.tiles.join(format!("{}.glb", tile_name(key)));
        std::fs::write(&p, bytes).map_err(|e| Error::io(&p, e))
    }
}

impl NodeWriter for Tiles3dWriter<'_> {
    fn write_nodes(&mut self, nodes: Vec<(NodeKey, Vec<u8>)>) -> Result<()> {
        crate::cleanup::check_interrupted()?;
        let rl = self.frame.out.record_len;
        let this = &*self;
        let done: Vec<(NodeKey, Placed, f64)> = nodes
            .par_iter()
            .map(|(key, recs)| {
                let pts = this.points(recs)?;
                let mut b = Bounds::EMPTY;
                pts.iter().for_each(|p| b.add(p.p));
                let pos = glb::positions_for(&b, this.resolution);
                let bytes = glb::encode(&pts, &b, this.attrs, &pos);
                this.write_file(key, &bytes)?;
                this.ds.progress.add((recs.len() / rl) as u64);
                Ok((
                    *key,
                    Placed { points: pts.len() as u64, bounds: b, bytes: bytes.len() as u64 },
                    pos.error_bound(&b),
                ))
            })
            .collect::<Result<_>>()?;
        for (k, p, e) in done {
            self.placed.insert(k, p);
            self.max_error = self.max_error.max(e);
        }
        Ok(())
    }

    fn write_node_slices(
        &mut self,
        key: NodeKey,
        points: usize,
        slice: usize,
        records: &(dyn Fn(std::ops::Range<usize>) -> Vec<u8> + Sync),
    ) -> Result<()> {
        use std::io::Write;
        // Pass 1: the box. Pass 2: the vertices, streamed after the header.
        let mut b = Bounds::EMPTY;
        for s in (0..points).step_by(slice) {
            crate::cleanup::check_interrupted()?;
            for p in self.points(&records(s..(s + slice).min(points)))? {
                b.add(p.p);
            }
        }
        let pos = glb::positions_for(&b, self.resolution);
        let (head, pad) = glb::head(points, &b, self.attrs, &pos);
        let path = self.tiles.join(format!("{}.glb", tile_name(&key)));
        let mut w =
            std::io::BufWriter::new(std::fs::File::create(&path).map_err(|e| Error::io(&path, e))?);
        w.write_all(&head).map_err(|e| Error::io(&path, e))?;
        let mut bytes = head.len() as u64;
        for s in (0..points).step_by(slice) {
            crate::cleanup::check_interrupted()?;
            let recs = records(s..(s + slice).min(points));
            let v = glb::vertices(&self.points(&recs)?, self.attrs, &pos);
            w.write_all(&v).map_err(|e| Error::io(&path, e))?;
            bytes += v.len() as u64;
            self.ds.progress.add((recs.len() / self.frame.out.record_len) as u64);
        }
        w.write_all(&vec![0u8; pad]).map_err(|e| Error::io(&path, e))?;
        w.flush().map_err(|e| Error::io(&path, e))?;
        self.placed
            .insert(key, Placed { points: points as u64, bounds: b, bytes: bytes + pad as u64 });
        self.max_error = self.max_error.max(pos.error_bound(&b));
        Ok(())
    }

    fn finish(
        self: Box<Self>,
        tree: &[OutNode],
        _stats: &PieceStats,
        report: &mut ExportReport,
    ) -> Result<()> {
        let w = *self;
        let dir = w.tmp.path().to_path_buf();
        let at: HashMap<NodeKey, &OutNode> = tree.iter().map(|n| (n.key, n)).collect();
        // Boxes bottom-up: a tile's points and every tile below.
        let mut order: Vec<NodeKey> = tree.iter().map(|n| n.key).collect();
        order.sort_by_key(|k| std::cmp::Reverse(k.level));
        let mut boxes: HashMap<NodeKey, Bounds> = HashMap::new();
        for k in &order {
            let mut b = w.placed.get(k).map(|p| p.bounds).unwrap_or(Bounds::EMPTY);
            let n = at[k];
            for o in 0..8 {
                if n.children >> o & 1 == 1 {
                    if let Some(cb) = boxes.get(&k.child(o)) {
                        b.union(cb);
                    }
                }
            }
            boxes.insert(*k, b);
        }
        // Spacing in the frame's units: metres on the globe.
        let unit = if w.frame.halfsize > 0.0 {
            let s = w.ds.grid.scale.iter().cloned().fold(f64::INFINITY, f64::min);
            w.resolution / s
        } else {
            1.0
        };
        let spacing = w.frame.spacing() * unit;
        let error_of = |k: &NodeKey| {
            if at[k].children == 0 {
                0.0
            } else {
                8.0 * spacing / (1u64 << k.level.min(62)) as f64
            }
        };
        let pad = 1e-3 + w.max_error;
        let volume = |k: &NodeKey| {
            let b = boxes[k];
            let c = [0, 1, 2].map(|a| (b.lo[a] + b.hi[a]) / 2.0);
            let h = [0, 1, 2].map(|a| (b.hi[a] - b.lo[a]) / 2.0 + pad);
            json!({"box": [c[0], c[1], c[2], h[0], 0.0, 0.0, 0.0, h[1], 0.0, 0.0, 0.0, h[2]]})
        };
        let mut externals: Vec<NodeKey> = Vec::new();
        let asset =
            json!({"version": "1.1", "generator": concat!("mortar ", env!("CARGO_PKG_VERSION"))});
        let tree_json =
            TreeJson { at: &at, placed: &w.placed, volume: &volume, error_of: &error_of };
        let mut root = tree_json.tile(NodeKey::ROOT, true, "tiles/", &mut externals);
        root["transform"] = json!(w.place.transform().to_vec());
        let main = json!({"asset": asset, "geometricError": 2.0 * error_of(&NodeKey::ROOT).max(spacing), "root": root});
        let write_json = |p: &Path, v: &serde_json::Value| -> Result<u64> {
            let text = serde_json::to_vec(v)
                .map_err(|error| Error::JsonFile { path: p.to_path_buf(), error })?;
            std::fs::write(p, &text).map_err(|e| Error::io(p, e))?;
            Ok(text.len() as u64)
        };
        let mut bytes = write_json(&dir.join("tileset.json"), &main)?;
        while let Some(k) = externals.pop() {
            let r = tree_json.tile(k, true, "", &mut externals);
            let doc = json!({"asset": asset, "geometricError": error_of(&k), "root": r});
            bytes += write_json(&w.tiles.join(format!("{}.json", tile_name(&k))), &doc)?;
        }
        report.points = w.placed.values().map(|p| p.points).sum();
        report.bytes = bytes + w.placed.values().map(|p| p.bytes).sum::<u64>();
        report.tiles_crs = w.crs.clone();
        report.position_error_bound = Some(w.max_error);
        if let Place::Globe { enu, .. } = &w.place {
            let rb = boxes[&NodeKey::ROOT];
            let c = [0, 1, 2].map(|a| (rb.lo[a] + rb.hi[a]) / 2.0);
            let e = [0, 1, 2]
                .map(|i| enu.origin[i] + (0..3).map(|a| enu.axes[a][i] * c[a]).sum::<f64>());
            report.ecef_center = Some(e);
        }
        if w.out.is_dir() {
            std::fs::remove_dir(&w.out).map_err(|e| Error::io(&w.out, e))?;
        }
        w.tmp.persist(&w.out).map_err(|e| Error::io(&w.out, e))?;
        Ok(())
    }
}

/// What the tileset files are made from.
struct TreeJson<'t> {
    at: &'t HashMap<NodeKey, &'t OutNode>,
    placed: &'t HashMap<NodeKey, Placed>,
    volume: &'t dyn Fn(&NodeKey) -> serde_json::Value,
    error_of: &'t dyn Fn(&NodeKey) -> f64,
}

impl TreeJson<'_> {
    /// A tile and its children down to the next split (`top`: the root of a tileset file);
    /// `prefix` is the path from the tileset file to `tiles/`. Nodes below a split go to
    /// `externals`.
    fn tile(
        &self,
        k: NodeKey,
        top: bool,
        prefix: &str,
        externals: &mut Vec<NodeKey>,
    ) -> serde_json::Value {
        let n = self.at[&k];
        let mut t = json!({"boundingVolume": (self.volume)(&k), "geometricError": (self.error_of)(&k), "refine": "ADD"});
        if !top && k.level.is_multiple_of(SPLIT) && n.children != 0 {
            externals.push(k);
            t["content"] = json!({"uri": format!("{prefix}{}.json", tile_name(&k))});
            return t;
        }
        if self.placed.contains_key(&k) {
            t["content"] = json!({"uri": format!("{prefix}{}.glb", tile_name(&k))});
        }
        let kids: Vec<serde_json::Value> = (0..8)
            .filter(|o| n.children >> o & 1 == 1)
            .map(|o| self.tile(k.child(o), false, prefix, externals))
            .collect();
        if !kids.is_empty() {
            t["children"] = json!(kids);
        }
        t
    }
}
