//! The vocabulary of `mortar export`: the format, the order of points in a node, the options
//! and the report.

use mortar_core::octree::BuilderConfig;
use serde::Serialize;

/// The output format.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExportFormat {
    /// One COPC 1.0 file (`.copc.laz`).
    Copc,
    /// A Potree 2.0 directory (`metadata.json`, `hierarchy.bin`, `octree.bin`).
    Potree,
    /// A 3D Tiles 1.1 directory (`tileset.json`, `tiles/*.glb`).
    Tiles3d,
}

/// The order of the points inside a node.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PointOrder {
    /// Morton order (leaves) and the Morton order of the voxel cells (inner nodes).
    Morton,
    /// By GPS time (ties in Morton order); Morton order where the records have no GPS time.
    GpsTime,
}

/// What an export is asked to do.
#[derive(Clone, Debug)]
pub struct ExportOptions {
    pub format: ExportFormat,
    /// Memory budget in bytes: an input that needs more is exported through run files on
    /// disk, unit by unit (module docs).
    pub memory: u64,
    /// Most points per leaf and the deepest level (the tree of `mortar build`).
    pub config: BuilderConfig,
    pub order: PointOrder,
}

/// What an export did.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ExportReport {
    pub format: &'static str,
    pub output: String,
    pub points: u64,
    /// Nodes written (with points or with nodes below).
    pub nodes: u64,
    /// Deepest level.
    pub depth: u32,
    /// Point data record format written (COPC) or of the records the attributes come from.
    pub point_format: u8,
    /// Bytes of the output (all files).
    pub bytes: u64,
    pub seconds: f64,
    pub read_seconds: f64,
    pub sort_seconds: f64,
    pub tree_seconds: f64,
    pub write_seconds: f64,
    /// "memory" (read, sorted and assigned in memory) or "partitioned" (larger than
    /// `--memory`: through run files on disk, one unit at a time).
    pub engine: &'static str,
    pub warnings: Vec<String>,
    /// Partition cells denser than a unit that were partitioned again on disk.
    pub dense_cells: u64,
    /// Leaves larger than a unit, ordered on disk and written in slices.
    pub large_leaves: u64,
    /// 3D Tiles: the CRS the points were placed on the globe from (name and PROJ.4), `None`
    /// for a local frame.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tiles_crs: Option<String>,
    /// 3D Tiles: the centre of the root tile's bounding box in ECEF (EPSG:4978) metres.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ecef_center: Option<[f64; 3]>,
    /// 3D Tiles: the largest distance between a point and its position in a tile (metres on
    /// the globe), from the 16-bit or 32-bit float storage.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub position_error_bound: Option<f64>,
}
