//! `mortar info`: what a LAS/LAZ file or a batch file holds. The JSON form ([`FileInfo`]) is
//! stable: fields are only ever added (documented in `docs/info-json.md`).

use crate::batchfile::BatchFile;
use crate::cleanup::check_interrupted;
use crate::crs::{self, CrsInfo};
use crate::dataset::RecordSource;
use crate::error::Result;
use crate::las::{c_str, Vlr};
use mortar_core::layout::{read_xyz, Family, RecordLayout};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::BTreeMap;

#[derive(Clone, Debug, Serialize)]
pub struct Bounds {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

#[derive(Clone, Debug, Serialize)]
pub struct VlrInfo {
    pub user_id: String,
    pub record_id: u16,
    pub description: String,
    pub length: usize,
}

#[derive(Clone, Debug, Serialize)]
pub struct ExtraBytesInfo {
    pub name: String,
    pub data_type: String,
    pub description: String,
}

#[derive(Clone, Debug, Serialize)]
pub struct AttributeInfo {
    pub name: String,
    pub offset: usize,
    pub width: usize,
}

/// One level of a COPC or EPT hierarchy.
#[derive(Clone, Debug, Serialize)]
pub struct HierarchyLevel {
    pub level: u32,
    /// Nodes with points.
    pub nodes: u64,
    pub points: u64,
}

/// What a COPC file's or an EPT directory's hierarchy holds, or why it cannot be used.
#[derive(Clone, Debug, Serialize)]
pub struct HierarchySummary {
    /// `copc` or `ept`.
    pub format: &'static str,
    pub center: [f64; 3],
    pub halfsize: f64,
    pub spacing: f64,
    pub hierarchy_pages: u64,
    pub hierarchy_bytes: u64,
    /// Nodes with points.
    pub nodes: u64,
    /// Points in the nodes (the header's point count for a sound file).
    pub points: u64,
    pub levels: Vec<HierarchyLevel>,
    /// Why the hierarchy cannot be used (mortar then reads the file flat); the other fields
    /// are then zero, or the info VLR's where it parsed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// The COPC hierarchy of `input`, or `None` when it is not a COPC file.
pub fn copc_summary(input: &crate::source::LasInput) -> Option<HierarchySummary> {
    use crate::copc::{info_of, CopcHierarchy};
    let empty = |error: String| HierarchySummary {
        format: "copc",
        center: [0.0; 3],
        halfsize: 0.0,
        spacing: 0.0,
        hierarchy_pages: 0,
        hierarchy_bytes: 0,
        nodes: 0,
        points: 0,
        levels: Vec::new(),
        error: Some(error),
    };
    let info = match info_of(&input.meta.vlrs)? {
        Ok(i) => i,
        Err(e) => return Some(empty(e.to_string())),
    };
    let h = match CopcHierarchy::read(input.file_bytes(), info) {
        Ok(h) => h,
        Err(e) => {
            let mut s = empty(e.to_string());
            (s.center, s.halfsize, s.spacing) = (info.center, info.halfsize, info.spacing);
            return Some(s);
        }
    };
    let levels = levels_of(h.nodes.iter().map(|n| (n.key.level, n.points)));
    let mut s = HierarchySummary {
        format: "copc",
        center: info.center,
        halfsize: info.halfsize,
        spacing: info.spacing,
        hierarchy_pages: h.pages,
        hierarchy_bytes: h.page_bytes,
        nodes: h.nodes.len() as u64,
        points: h.points(),
        levels,
        error: None,
    };
    let usable = crate::copc::CopcLod::new(h).and_then(|l| l.check_chunks(input));
    if let Err(e) = usable {
        s.error = Some(e.to_string());
    } else if s.points != input.meta.header.point_count {
        s.error = Some(format!(
            "the hierarchy's nodes hold {} points, the header says {}",
            s.points, input.meta.header.point_count
        ));
    }
    Some(s)
}

/// Levels of `nodes` (key, points): per level, nodes and points.
fn levels_of(nodes: impl Iterator<Item = (u8, u64)>) -> Vec<HierarchyLevel> {
    let mut v: Vec<HierarchyLevel> = Vec::new();
    for (l, p) in nodes {
        while v.len() <= l as usize {
            v.push(HierarchyLevel { level: v.len() as u32, nodes: 0, points: 0 });
        }
        v[l as usize].nodes += 1;
        v[l as usize].points += p;
    }
    v
}

/// `mortar info` of an EPT directory: its root node's file described (format, attributes,
/// CRS), with the points and bounds of `ept.json` and the hierarchy; `Ok(None)` with a warning
/// where the directory is not a usable EPT source (its files are then described one by one).
pub fn ept_info(dir: &std::path::Path) -> Result<(Option<FileInfo>, Option<String>)> {
    let e = match crate::ept::EptSource::open(dir) {
        Ok(e) => e,
        Err(err) => {
            return Ok((
                None,
                Some(format!("{}: EPT: {err}; describing its LAZ files", dir.display())),
            ))
        }
    };
    let Some(root) = (0..e.nodes.len()).find(|&i| e.nodes[i].key.level == 0) else {
        return Ok((
            None,
            Some(format!("{}: EPT: no root node; describing its LAZ files", dir.display())),
        ));
    };
    let input = crate::source::LasInput::open(&e.node_path(root))?;
    let mut info = describe(&input, "ept", false, None)?;
    info.path = dir.display().to_string();
    info.point_count = e.points;
    info.points_by_return = vec![0; info.points_by_return.len()];
    if let Some(c) = e.conforming {
        info.header_bounds = on_grid(c.min, c.max, info.scale);
    }
    let cube = e.tree.cube_bounds();
    let halfsize = (cube.max[0] - cube.min[0]) / 2.0;
    let points = e.node_points();
    info.hierarchy = Some(HierarchySummary {
        format: "ept",
        center: [0, 1, 2].map(|a| (cube.min[a] + cube.max[a]) / 2.0),
        halfsize,
        spacing: e.span.map_or(0.0, |s| 2.0 * halfsize / s as f64),
        hierarchy_pages: e.hierarchy_files,
        hierarchy_bytes: e.hierarchy_bytes,
        nodes: e.nodes.len() as u64,
        points,
        levels: levels_of(e.nodes.iter().map(|n| (n.key.level, n.points))),
        error: (points != e.points).then(|| {
            format!("the hierarchy's nodes hold {points} points, ept.json says {}", e.points)
        }),
    });
    Ok((Some(info), None))
}

/// What an octree store holds (its last commit).
#[derive(Clone, Debug, Serialize)]
pub struct StoreInfo {
    pub commit: u64,
    pub nodes: u64,
    pub leaves: u64,
    pub inner_nodes: u64,
    /// Leaves without points (the empty octants of split nodes).
    pub empty_leaves: u64,
    pub voxels: u64,
    pub depth: u32,
    pub leaf_capacity: u32,
    pub largest_leaf: u64,
    pub nodes_bytes: u64,
    /// Bytes of `arrival.bin` (0 without one): the store can be appended to without its original
    /// inputs where it has one.
    pub arrival_bytes: u64,
    pub root_min: [i64; 3],
    pub root_size_log2: u32,
}

/// The store section of `mortar info` for a store.
pub fn store_info(s: &crate::store::Store) -> StoreInfo {
    let leaves: Vec<&crate::store::NodeEntry> =
        s.entries.iter().filter(|e| e.kind == crate::store::LEAF).collect();
    StoreInfo {
        commit: s.header.commit,
        nodes: s.entries.len() as u64,
        leaves: leaves.len() as u64,
        inner_nodes: (s.entries.len() - leaves.len()) as u64,
        empty_leaves: leaves.iter().filter(|e| e.count == 0).count() as u64,
        voxels: s.entries.iter().filter(|e| e.kind == crate::store::INNER).map(|e| e.count).sum(),
        depth: s.entries.iter().map(|e| e.level).max().unwrap_or(0),
        leaf_capacity: s.header.leaf_capacity,
        largest_leaf: leaves.iter().map(|e| e.count).max().unwrap_or(0),
        nodes_bytes: s.covered.iter().sum(),
        arrival_bytes: std::fs::metadata(s.path.join(crate::store::arrival::ARRIVAL_FILE))
            .map_or(0, |m| m.len()),
        root_min: s.header.root_min,
        root_size_log2: s.header.root_size_log2,
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct BatchInfo {
    pub batch_count: u64,
    pub compression: String,
    /// Largest per-axis bit count of each batch, histogram: bits -> batches.
    pub bits_histogram: BTreeMap<u8, u64>,
    pub smallest_batch: u32,
    pub largest_batch: u32,
    pub kept_attributes: Vec<String>,
    pub dropped_attributes: Vec<String>,
    pub color_source: String,
    pub rgb_bits: Option<u8>,
}

#[derive(Clone, Debug, Default, Serialize)]
pub struct Range {
    pub min: f64,
    pub max: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct Stats {
    pub point_count: u64,
    pub bounds: Bounds,
    /// Ranges of the numeric attributes present (rgb per channel, gps_time in seconds).
    pub ranges: BTreeMap<String, Range>,
    /// Points per classification code.
    pub classification_counts: BTreeMap<u8, u64>,
    /// Points per return number.
    pub return_counts: BTreeMap<u8, u64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct FileInfo {
    pub path: String,
    /// `las`, `laz` or `batch`.
    pub kind: String,
    pub version: String,
    pub point_format: u8,
    pub record_length: usize,
    pub point_count: u64,
    pub points_by_return: Vec<u64>,
    pub scale: [f64; 3],
    pub offset: [f64; 3],
    pub header_bounds: Bounds,
    pub system_identifier: String,
    pub generating_software: String,
    pub creation_day: u16,
    pub creation_year: u16,
    pub crs: CrsInfo,
    pub attributes: Vec<AttributeInfo>,
    pub extra_bytes: Vec<ExtraBytesInfo>,
    pub vlrs: Vec<VlrInfo>,
    pub evlrs: Vec<VlrInfo>,
    pub batch: Option<BatchInfo>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub store: Option<StoreInfo>,
    /// A COPC file's or an EPT directory's hierarchy (absent for other inputs).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hierarchy: Option<HierarchySummary>,
    pub stats: Option<Stats>,
    /// Disagreements found (header against points, broken records).
    pub warnings: Vec<String>,
}

/// Decimals of a coordinate on a grid of step `scale`: the fewest (at most 12) that write every
/// multiple of it exactly, e.g. 2 for 0.01, 3 for 0.025, 0 for 1.
pub fn grid_decimals(scale: f64) -> usize {
    (0..12)
        .find(|&d| {
            let m = scale * 10f64.powi(d as i32);
            (m - m.round()).abs() <= 1e-9 * m.abs().max(1.0)
        })
        .unwrap_or(12)
}

/// `v` rounded to `decimals` decimals (the nearest f64, which prints with at most that many).
pub fn round_to(v: f64, decimals: usize) -> f64 {
    if !v.is_finite() {
        return v;
    }
    let r: f64 = format!("{v:.decimals$}").parse().unwrap_or(v);
    r
}

/// Bounds with each axis rounded to the decimals of its scale.
fn on_grid(min: [f64; 3], max: [f64; 3], scale: [f64; 3]) -> Bounds {
    let d = |a: usize| grid_decimals(scale[a]);
    Bounds {
        min: [round_to(min[0], d(0)), round_to(min[1], d(1)), round_to(min[2], d(2))],
        max: [round_to(max[0], d(0)), round_to(max[1], d(1)), round_to(max[2], d(2))],
    }
}

fn vlr_info(v: &Vlr) -> VlrInfo {
    VlrInfo {
        user_id: v.user_id_str(),
        record_id: v.record_id,
        description: v.description_str(),
        length: v.data.len(),
    }
}

/// The extra-bytes descriptors (LASF_Spec record 4) among `vlrs`.
pub fn extra_bytes(vlrs: &[Vlr]) -> Vec<ExtraBytesInfo> {
    const TYPES: [&str; 11] =
        ["undocumented", "u8", "i8", "u16", "i16", "u32", "i32", "u64", "i64", "f32", "f64"];
    let mut out = Vec::new();
    for v in vlrs.iter().filter(|v| v.user_id_str() == "LASF_Spec" && v.record_id == 4) {
        for d in v.data.chunks_exact(192) {
            let t = d[2] as usize;
            let data_type = if t < TYPES.len() {
                TYPES[t].to_string()
            } else if t <= 30 {
                format!("{}[{}]", TYPES[(t - 1) % 10 + 1], (t - 1) / 10 + 1)
            } else {
                format!("type {t}")
            };
            out.push(ExtraBytesInfo {
                name: c_str(&d[4..36]),
                data_type,
                description: c_str(&d[160..192]),
            });
        }
    }
    out
}

/// Describes one input; `stats` adds a full pass over the points.
pub fn describe(
    src: &dyn RecordSource,
    kind: &str,
    stats: bool,
    batch: Option<&BatchFile>,
) -> Result<FileInfo> {
    let h = src.header();
    let all: Vec<&Vlr> = src.vlrs().iter().chain(src.evlrs()).collect();
    let mut warnings = Vec::new();
    let crs = crs::describe(&all);
    warnings.extend(crs.problems.iter().cloned());
    let layout = src.layout();
    let mut info = FileInfo {
        path: crate::remote::with_urls(&src.path().display().to_string()),
        kind: kind.into(),
        version: format!("{}.{}", h.version.0, h.version.1),
        point_format: layout.format,
        record_length: layout.record_len,
        point_count: src.point_count(),
        points_by_return: h.points_by_return.to_vec(),
        scale: h.scale,
        offset: h.offset,
        header_bounds: on_grid(h.min, h.max, h.scale),
        system_identifier: c_str(&h.system_identifier),
        generating_software: c_str(&h.generating_software),
        creation_day: h.creation_day,
        creation_year: h.creation_year,
        crs,
        attributes: layout
            .attributes
            .iter()
            .map(|a| AttributeInfo { name: a.name.clone(), offset: a.offset, width: a.width })
            .collect(),
        extra_bytes: extra_bytes(src.vlrs()),
        vlrs: src.vlrs().iter().map(vlr_info).collect(),
        evlrs: src.evlrs().iter().map(vlr_info).collect(),
        batch: batch.map(batch_info),
        store: None,
        hierarchy: None,
        stats: None,
        warnings,
    };
    if stats {
        let s = full_stats(src)?;
        let tol = |a: usize| h.scale[a] * 0.5 + 1e-9;
        for a in 0..3 {
            if s.point_count > 0
                && ((s.bounds.min[a] - h.min[a]).abs() > tol(a)
                    || (s.bounds.max[a] - h.max[a]).abs() > tol(a))
            {
                let d = grid_decimals(h.scale[a]);
                info.warnings.push(format!(
                    "header bounds on {} are [{:.d$}, {:.d$}] but the points span [{:.d$}, {:.d$}]",
                    ["x", "y", "z"][a],
                    h.min[a],
                    h.max[a],
                    s.bounds.min[a],
                    s.bounds.max[a]
                ));
            }
        }
        info.stats = Some(s);
    }
    Ok(info)
}

fn batch_info(b: &BatchFile) -> BatchInfo {
    let mut hist = BTreeMap::new();
    let mut smallest = u32::MAX;
    let mut largest = 0;
    for e in b.entries() {
        *hist.entry(e.bits[0].max(e.bits[1]).max(e.bits[2])).or_insert(0) += 1;
        smallest = smallest.min(e.count);
        largest = largest.max(e.count);
    }
    BatchInfo {
        batch_count: b.header.batch_count,
        compression: format!("{:?}", b.meta.compression).to_lowercase(),
        bits_histogram: hist,
        smallest_batch: if b.entries().is_empty() { 0 } else { smallest },
        largest_batch: largest,
        kept_attributes: b.meta.attributes.iter().map(|a| a.name.clone()).collect(),
        dropped_attributes: b.meta.dropped.clone(),
        color_source: b.meta.color.source.clone(),
        rgb_bits: b.meta.color.rgb_bits,
    }
}

#[cfg(test)]
mod grid_tests {
    use super::*;

    #[test]
    fn coordinates_print_on_the_grid() {
        assert_eq!(grid_decimals(0.01), 2);
        assert_eq!(grid_decimals(0.001), 3);
        assert_eq!(grid_decimals(0.025), 3);
        assert_eq!(grid_decimals(1.0), 0);
        assert_eq!(grid_decimals(1e-7), 7);
        assert_eq!(round_to(848935.2000000001, 2), 848935.2);
        assert_eq!(round_to(848935.2000000001, 2).to_string(), "848935.2");
        assert_eq!(round_to(-0.004, 2), -0.0);
    }
}

#[derive(Clone)]
struct Acc {
    n: u64,
    min: [i32; 3],
    max: [i32; 3],
    ranges: BTreeMap<String, (f64, f64)>,
    class: [u64; 256],
    ret: [u64; 16],
}

impl Acc {
    fn new() -> Acc {
        Acc {
            n: 0,
            min: [i32::MAX; 3],
            max: [i32::MIN; 3],
            ranges: BTreeMap::new(),
            class: [0; 256],
            ret: [0; 16],
        }
    }
    fn merge(mut self, o: Acc) -> Acc {
        self.n += o.n;
        for a in 0..3 {
            self.min[a] = self.min[a].min(o.min[a]);
            self.max[a] = self.max[a].max(o.max[a]);
        }
        for (k, (lo, hi)) in o.ranges {
            let e = self.ranges.entry(k).or_insert((f64::INFINITY, f64::NEG_INFINITY));
            e.0 = e.0.min(lo);
            e.1 = e.1.max(hi);
        }
        for i in 0..256 {
            self.class[i] += o.class[i];
        }
        for i in 0..16 {
            self.ret[i] += o.ret[i];
        }
        self
    }
}

/// A field's value read from a record.
type FieldReader = Box<dyn Fn(&[u8]) -> f64 + Sync>;

/// Numeric fields for ranges: (name, fn(record) -> value).
fn numeric_fields(layout: &RecordLayout) -> Vec<(&'static str, FieldReader)> {
    let u16_at = |o: usize| move |r: &[u8]| u16::from_le_bytes([r[o], r[o + 1]]) as f64;
    let mut f: Vec<(&'static str, FieldReader)> = vec![("intensity", Box::new(u16_at(12)))];
    match layout.family() {
        Family::Legacy => {
            f.push(("number_of_returns", Box::new(|r: &[u8]| ((r[14] >> 3) & 7) as f64)));
            f.push(("scan_angle", Box::new(|r: &[u8]| r[16] as i8 as f64)));
            f.push(("user_data", Box::new(|r: &[u8]| r[17] as f64)));
            f.push(("point_source_id", Box::new(u16_at(18))));
        }
        Family::Extended => {
            f.push(("number_of_returns", Box::new(|r: &[u8]| (r[14] >> 4) as f64)));
            f.push(("scanner_channel", Box::new(|r: &[u8]| ((r[15] >> 4) & 3) as f64)));
            f.push(("user_data", Box::new(|r: &[u8]| r[17] as f64)));
            f.push((
                "scan_angle",
                Box::new(|r: &[u8]| i16::from_le_bytes([r[18], r[19]]) as f64 * 0.006),
            ));
            f.push(("point_source_id", Box::new(u16_at(20))));
        }
    }
    if let Some(a) = layout.attribute("gps_time") {
        let o = a.offset;
        f.push((
            "gps_time",
            Box::new(move |r: &[u8]| f64::from_le_bytes(r[o..o + 8].try_into().unwrap())),
        ));
    }
    if let Some(a) = layout.attribute("rgb") {
        let o = a.offset;
        f.push(("red", Box::new(u16_at(o))));
        f.push(("green", Box::new(u16_at(o + 2))));
        f.push(("blue", Box::new(u16_at(o + 4))));
    }
    if let Some(a) = layout.attribute("nir") {
        f.push(("nir", Box::new(u16_at(a.offset))));
    }
    f
}

fn full_stats(src: &dyn RecordSource) -> Result<Stats> {
    let layout = src.layout();
    let fields = numeric_fields(layout);
    let acc = src
        .pieces()
        .par_iter()
        .map(|p| -> Result<Acc> {
            check_interrupted()?;
            let recs = src.read_piece(p)?;
            let mut acc = Acc::new();
            let mut lo = vec![f64::INFINITY; fields.len()];
            let mut hi = vec![f64::NEG_INFINITY; fields.len()];
            for r in recs.chunks_exact(layout.record_len) {
                let xyz = read_xyz(r);
                for a in 0..3 {
                    acc.min[a] = acc.min[a].min(xyz[a]);
                    acc.max[a] = acc.max[a].max(xyz[a]);
                }
                for (i, (_, f)) in fields.iter().enumerate() {
                    let v = f(r);
                    if v < lo[i] {
                        lo[i] = v;
                    }
                    if v > hi[i] {
                        hi[i] = v;
                    }
                }
                acc.class[layout.classification(r) as usize] += 1;
                acc.ret[layout.return_number(r) as usize] += 1;
                acc.n += 1;
            }
            for (i, (name, _)) in fields.iter().enumerate() {
                if acc.n > 0 {
                    acc.ranges.insert(name.to_string(), (lo[i], hi[i]));
                }
            }
            Ok(acc)
        })
        .try_reduce(Acc::new, |a, b| Ok(a.merge(b)))?;
    let h = src.header();
    let w = |a: usize, v: i32| h.offset[a] + h.scale[a] * v as f64;
    let bounds = if acc.n == 0 {
        Bounds { min: [0.0; 3], max: [0.0; 3] }
    } else {
        on_grid(
            [w(0, acc.min[0]), w(1, acc.min[1]), w(2, acc.min[2])],
            [w(0, acc.max[0]), w(1, acc.max[1]), w(2, acc.max[2])],
            h.scale,
        )
    };
    Ok(Stats {
        point_count: acc.n,
        bounds,
        ranges: acc.ranges.into_iter().map(|(k, (min, max))| (k, Range { min, max })).collect(),
        classification_counts: acc
            .class
            .iter()
            .enumerate()
            .filter(|(_, &c)| c > 0)
            .map(|(i, &c)| (i as u8, c))
            .collect(),
        return_counts: acc
            .ret
            .iter()
            .enumerate()
            .filter(|(_, &c)| c > 0)
            .map(|(i, &c)| (i as u8, c))
            .collect(),
    })
}
