//! The octree's vocabulary, which every part of it shares: the grid's constants, a point and a
//! voxel as the builders hold them, the colour mode, the builder's settings, node ids and the
//! error.

/// Cells per axis of an inner node's voxel grid (paper 004 §3.3).
pub const GRID_SIZE: u32 = 128;
/// `log2(GRID_SIZE)`.
pub const GRID_LOG2: u8 = 7;

/// Widest root cube: `2^32` grid units cover any set of `i32` coordinates.
pub const MAX_ROOT_SIZE_LOG2: u8 = 32;
/// Cubes narrower than `2^MIN_INNER_SIZE_LOG2` grid units never split: their voxels would be
/// smaller than one grid unit.
pub const MIN_INNER_SIZE_LOG2: u8 = GRID_LOG2;
/// Default leaf capacity (paper 004 §3.1).
pub const DEFAULT_LEAF_CAPACITY: u32 = 50_000;
/// Default [`BuilderConfig::max_level`]: deep enough that the size rule binds first for any root.
pub const DEFAULT_MAX_LEVEL: u8 = 32;
/// Largest chunk of points a leaf's payload is built from.
pub const POINT_CHUNK_MAX: usize = 1 << 16;
/// Largest chunk of voxels an inner node's payload is built from in [`ColorMode::FirstCome`].
pub const VOXEL_CHUNK_MAX: usize = 1 << 16;

/// One input point: integer LAS-grid coordinates, RGBA colour, and the caller's index of the
/// record it came from (opaque to the octree).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Point {
    /// Integer coordinates in the LAS grid.
    pub pos: [i32; 3],
    /// RGBA8 colour, `r | g << 8 | b << 16 | a << 24`.
    pub color: u32,
    /// Index of the point's record in the caller's storage.
    pub record: u64,
}

const _: () = assert!(std::mem::size_of::<Point>() == 24);

/// One voxel of an inner node: an occupied cell of its 128³ grid, represented by a real source
/// point, the first that claimed the cell in arrival order (its position and record), so that a
/// level of detail can be coloured by any attribute of the source and exported as real points.
/// Its colour is that point's ([`ColorMode::FirstCome`]) or the mean of the cell's points
/// ([`ColorMode::Averaged`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Voxel {
    /// Integer coordinates of the representative point (inside the node's cube and the cell).
    pub pos: [i32; 3],
    /// RGBA8 colour, `r | g << 8 | b << 16 | a << 24`.
    pub color: u32,
    /// The caller's index of the representative point's record ([`Point::record`]).
    pub record: u64,
}

const _: () = assert!(std::mem::size_of::<Voxel>() == 24);

impl Voxel {
    /// The voxel of point `p` with colour `color`.
    #[inline]
    pub fn of(p: &Point, color: u32) -> Voxel {
        Voxel { pos: p.pos, color, record: p.record }
    }

    /// The representative as a point (position, the voxel's colour, record).
    #[inline]
    pub fn point(&self) -> Point {
        Point { pos: self.pos, color: self.color, record: self.record }
    }
}

/// How inner-node voxels get their colour.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum ColorMode {
    /// The colour of the first point that fell into the cell (paper 004 §5.2).
    #[default]
    FirstCome,
    /// The rounded mean colour of the points that fell into the cell (paper 004 §8, future work).
    Averaged,
}

/// Settings of a [`Builder`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BuilderConfig {
    /// Most points a leaf holds before it splits (at least 1). Leaves that may not split (see the
    /// module docs) hold more.
    pub leaf_capacity: u32,
    /// How voxels get their colour.
    pub color_mode: ColorMode,
    /// Nodes at this level never split (the root is level 0).
    pub max_level: u8,
}

impl Default for BuilderConfig {
    fn default() -> Self {
        BuilderConfig {
            leaf_capacity: DEFAULT_LEAF_CAPACITY,
            color_mode: ColorMode::FirstCome,
            max_level: DEFAULT_MAX_LEVEL,
        }
    }
}

/// Index of a node in a [`Snapshot`] (and in the builder); stable for the builder's lifetime.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct NodeId(pub u32);

impl NodeId {
    /// The root.
    pub const ROOT: NodeId = NodeId(0);

    /// The id as an index into [`Snapshot::nodes`].
    #[inline]
    pub fn index(self) -> usize {
        self.0 as usize
    }
}

/// Errors of the octree builder. A failed call leaves the builder as it was.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum OctreeError {
    /// The configured leaf capacity is 0.
    #[error("the leaf capacity must be at least 1")]
    ZeroCapacity,
    /// The root cube is wider than the i32 grid needs.
    #[error("the root cube is 2^{size_log2} grid units wide; at most 2^{MAX_ROOT_SIZE_LOG2} is supported")]
    RootTooLarge {
        /// The requested `size_log2`.
        size_log2: u8,
    },
    /// A point of the batch lies outside the root cube.
    #[error("point {index} of the batch at {pos:?} lies outside the octree's root cube (min {min:?}, size {size})")]
    PointOutsideRoot {
        /// Index of the first such point in the batch.
        index: usize,
        /// Its coordinates.
        pos: [i32; 3],
        /// Root cube minimum.
        min: [i64; 3],
        /// Root cube size in grid units.
        size: u64,
    },
    /// The page-in callback failed or returned another number of points than were paged out.
    #[error("paging points back in: {0}")]
    PageIn(String),
    /// The batch plus the points it would spill do not fit the update's 32-bit ids.
    #[error("a batch of {points} points that spills {spilled} stored points exceeds 2^32 - 1 points per update; add smaller batches")]
    BatchTooLarge {
        /// Points in the batch.
        points: usize,
        /// Stored points the batch would spill.
        spilled: u64,
    },
    /// A setting the chosen builder does not implement.
    #[error("{0}")]
    Unsupported(String),
}
