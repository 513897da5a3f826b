//! The WGSL passes of the GPU rasterizer and of the GPU progressive renderer, assembled from
//! `shaders/` exactly as the pipelines and the validation test use them: WGSL has no `#include`,
//! so each pass is the shared files of `shaders/common/` (and, for the progressive passes,
//! `shaders/progressive_types.wgsl`) followed by the pass's own file.
//!
//! The bind groups of every pass are defined here once ([`binding`], [`Pass::bindings`],
//! [`PRESENT_BINDINGS`]): the pipelines build their bind-group layouts from these tables and the
//! bind groups name the same constants, and mortar-render's shader test checks that each WGSL
//! module declares exactly these `@group`/`@binding`s with the same kind and name.

/// The shared types and the split-dispatch helper (every pass).
const TYPES: &str = include_str!("../../../shaders/common/types.wgsl");
/// The one position decode and projection (draw passes).
const DECODE: &str = include_str!("../../../shaders/common/decode.wgsl");
/// The batch bindings and the per-point load-decode-project step (draw passes).
const BATCHES: &str = include_str!("../../../shaders/common/batches.wgsl");
/// The drawn-point counter (draw passes that count).
const COUNTERS: &str = include_str!("../../../shaders/common/counters.wgsl");
/// The GPU octree builder's structs, bindings and tree walk (its passes, after `TYPES`).
const OCTREE: &str = include_str!("../../../shaders/octree_common.wgsl");
/// The GPU radix sort's uniforms, bindings and digit (its passes, after `TYPES`).
const SORT: &str = include_str!("../../../shaders/sort_common.wgsl");
/// The progressive renderer's constants and uniform structs (its passes, after `TYPES`).
const PROGRESSIVE: &str = include_str!("../../../shaders/progressive_types.wgsl");

/// The window's present pass (`shaders/present.wgsl`: a vertex and a fragment entry point, no
/// shared files), used by [`crate::present::WindowSurface`].
pub const PRESENT: &str = include_str!("../../../shaders/present.wgsl");

/// What a binding holds, as the bind-group layout gives it and the WGSL must declare it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BindingKind {
    /// `var<uniform>`.
    Uniform,
    /// `var<storage, read>`.
    StorageRead,
    /// `var<storage, read_write>`.
    StorageReadWrite,
}

/// One `@group(g) @binding(b)` of a pass: where it is, what it holds, and the name of its WGSL
/// variable.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Binding {
    /// The bind group (`@group`).
    pub group: u32,
    /// The slot in the group (`@binding`).
    pub binding: u32,
    /// Uniform or storage, read-only or not.
    pub kind: BindingKind,
    /// The WGSL variable's name.
    pub name: &'static str,
}

const fn bind(group: u32, binding: u32, kind: BindingKind, name: &'static str) -> Binding {
    Binding { group, binding, kind, name }
}

/// The bindings of every pass, each defined once; the tables of [`Pass::bindings`] and
/// [`PRESENT_BINDINGS`] list them per pass and the bind groups use them by name.
pub mod binding {
    use super::{bind, Binding, BindingKind::*};

    /// `clear.wgsl`: the framebuffer words to clear.
    pub const CLEAR_WORDS: Binding = bind(0, 0, StorageReadWrite, "words");

    /// Draw passes (`common/decode.wgsl` users): the per-frame camera constants (`FrameUniforms`).
    pub const FRAME: Binding = bind(0, 0, Uniform, "frame");
    /// `draw.wgsl`, `progressive_reproject.wgsl`, `progressive_fill.wgsl`: the 64-bit keys.
    pub const KEYS: Binding = bind(0, 1, StorageReadWrite, "keys");
    /// `draw_depth.wgsl`, `draw_index.wgsl`: the 32-bit path's depths.
    pub const DEPTHS: Binding = bind(0, 1, StorageReadWrite, "depths");
    /// `common/counters.wgsl`: the drawn-point counter (two words).
    pub const COUNTERS: Binding = bind(0, 2, StorageReadWrite, "counters");
    /// `draw_index.wgsl`: the 32-bit path's point indices.
    pub const INDICES: Binding = bind(0, 3, StorageReadWrite, "indices");
    /// `draw.wgsl`: the 64-bit keys again, as plain words (bound to the same buffer as [`KEYS`];
    /// read by the diagnostic kernel 1 of [`crate::DrawTuning`]).
    pub const KEY_WORDS: Binding = bind(0, 3, StorageReadWrite, "key_words");
    /// `progressive_reproject.wgsl`: one chunk's visible list.
    pub const VISIBLE: Binding = bind(0, 3, StorageRead, "visible");

    /// `common/batches.wgsl` (group 1 of every draw pass, one bind group per chunk): the draw
    /// records.
    pub const RECORDS: Binding = bind(1, 0, StorageRead, "records");
    /// `common/batches.wgsl`: the chunk's coarse words.
    pub const COARSE: Binding = bind(1, 1, StorageRead, "coarse");
    /// `common/batches.wgsl`: the chunk's medium words.
    pub const MEDIUM: Binding = bind(1, 2, StorageRead, "medium");
    /// `common/batches.wgsl`: the chunk's fine words.
    pub const FINE: Binding = bind(1, 3, StorageRead, "fine");
    /// Group 1 of every draw pass.
    pub const BATCHES: [Binding; 4] = [RECORDS, COARSE, MEDIUM, FINE];

    /// `resolve.wgsl`: the dispatch's constants (`ResolveUniforms`).
    pub const RESOLVE_PARAMS: Binding = bind(0, 0, Uniform, "params");
    /// `resolve.wgsl`: the words holding the point indices.
    pub const RESOLVE_INDEX_WORDS: Binding = bind(0, 1, StorageRead, "index_words");
    /// `resolve.wgsl`: the words holding the depth bits.
    pub const RESOLVE_DEPTH_WORDS: Binding = bind(0, 2, StorageRead, "depth_words");
    /// `resolve.wgsl`: the chunk's colours.
    pub const RESOLVE_COLORS: Binding = bind(0, 3, StorageRead, "colors");
    /// `resolve.wgsl`: the RGBA8 image.
    pub const RESOLVE_IMAGE: Binding = bind(0, 4, StorageReadWrite, "image");

    /// `plan.wgsl`: the frame's plan constants (`PlanUniforms`).
    pub const PLAN_PARAMS: Binding = bind(0, 0, Uniform, "u");
    /// `plan.wgsl`: the batches to plan (`PlanBatch`, written when they were uploaded).
    pub const PLAN_BATCHES: Binding = bind(0, 1, StorageRead, "plan_batches");
    /// `plan.wgsl`: the draw records it writes.
    pub const PLAN_RECORDS: Binding = bind(0, 2, StorageReadWrite, "out_records");
    /// `plan.wgsl`: culled and drawn batches, points per number of words.
    pub const PLAN_COUNTERS: Binding = bind(0, 3, StorageReadWrite, "plan_counters");
    /// `hole_fill.wgsl`: the pass's constants (`HoleFillUniforms`).
    pub const FILL_PARAMS: Binding = bind(0, 0, Uniform, "params");
    /// `hole_fill.wgsl`: the framebuffer's words holding the point indices.
    pub const FILL_INDEX_WORDS: Binding = bind(0, 1, StorageRead, "index_words");
    /// `hole_fill.wgsl`: the framebuffer's words holding the depth bits.
    pub const FILL_DEPTH_WORDS: Binding = bind(0, 2, StorageRead, "depth_words");
    /// `hole_fill.wgsl`: the filled keys, two words per pixel (index, depth).
    pub const FILL_FILLED: Binding = bind(0, 3, StorageReadWrite, "filled");

    /// `eye_dome.wgsl`: the pass's constants (`EyeDomeUniforms`).
    pub const EYE_DOME_PARAMS: Binding = bind(0, 0, Uniform, "params");
    /// `eye_dome.wgsl`: the words holding the depth bits (framebuffer or filled keys).
    pub const EYE_DOME_DEPTH_WORDS: Binding = bind(0, 1, StorageRead, "depth_words");
    /// `eye_dome.wgsl`: the resolved image, shaded in place.
    pub const EYE_DOME_IMAGE: Binding = bind(0, 2, StorageReadWrite, "image");

    /// `progressive_unload.wgsl`: a chunk's coarse words.
    pub const UNLOAD_COARSE: Binding = bind(0, 0, StorageReadWrite, "coarse_words");

    /// `progressive_scatter.wgsl`: the pass's constants (`ScatterUniforms`).
    pub const SCATTER_PARAMS: Binding = bind(0, 0, Uniform, "params");
    /// `progressive_scatter.wgsl`: the staged records.
    pub const SCATTER_STAGED: Binding = bind(0, 1, StorageRead, "staged");
    /// `progressive_scatter.wgsl`: the chunk's coarse words.
    pub const SCATTER_COARSE: Binding = bind(0, 2, StorageReadWrite, "coarse_out");
    /// `progressive_scatter.wgsl`: the chunk's medium words.
    pub const SCATTER_MEDIUM: Binding = bind(0, 3, StorageReadWrite, "medium_out");
    /// `progressive_scatter.wgsl`: the chunk's fine words.
    pub const SCATTER_FINE: Binding = bind(0, 4, StorageReadWrite, "fine_out");
    /// `progressive_scatter.wgsl`: the chunk's colours.
    pub const SCATTER_COLORS: Binding = bind(0, 5, StorageReadWrite, "colors_out");

    /// `progressive_reframe.wgsl`: the pass's constants (`ReframeUniforms`).
    pub const REFRAME_PARAMS: Binding = bind(0, 0, Uniform, "params");
    /// `progressive_reframe.wgsl`: a chunk's coarse words.
    pub const REFRAME_COARSE: Binding = bind(0, 1, StorageReadWrite, "coarse_words");
    /// `progressive_reframe.wgsl`: a chunk's medium words.
    pub const REFRAME_MEDIUM: Binding = bind(0, 2, StorageReadWrite, "medium_words");
    /// `progressive_reframe.wgsl`: a chunk's fine words.
    pub const REFRAME_FINE: Binding = bind(0, 3, StorageReadWrite, "fine_words");

    /// `progressive_ties.wgsl`: the framebuffer's keys as words.
    pub const TIES_KEY_WORDS: Binding = bind(0, 1, StorageRead, "key_words");
    /// `progressive_ties.wgsl`: a flag per pixel, set where the winner ties in depth.
    pub const TIES_FLAGS: Binding = bind(0, 2, StorageReadWrite, "ties");

    /// `progressive_prepare.wgsl`: the pass's constants (`PrepareUniforms`).
    pub const PREPARE_PARAMS: Binding = bind(0, 0, Uniform, "params");
    /// `progressive_prepare.wgsl`: the 64-bit keys read as words.
    pub const PREPARE_KEY_WORDS: Binding = bind(0, 1, StorageRead, "key_words");
    /// `progressive_prepare.wgsl`: the entries of each chunk's visible list.
    pub const PREPARE_LIST_COUNTS: Binding = bind(0, 2, StorageReadWrite, "list_counts");
    /// `progressive_prepare.wgsl`: the visible lists.
    pub const PREPARE_LISTS: Binding = bind(0, 3, StorageReadWrite, "lists");

    /// `present.wgsl`: the pass's constants (`PresentUniforms`).
    pub const OCTREE_PARAMS: Binding = bind(0, 0, Uniform, "params");
    pub const OCTREE_NODES: Binding = bind(0, 1, StorageReadWrite, "nodes");
    pub const OCTREE_STATE: Binding = bind(0, 2, StorageReadWrite, "state");
    pub const OCTREE_POS: Binding = bind(0, 3, StorageRead, "pos");
    pub const OCTREE_LEAF: Binding = bind(0, 4, StorageReadWrite, "leaf");
    pub const OCTREE_GRIDS: Binding = bind(0, 5, StorageReadWrite, "grids");
    pub const OCTREE_BLOCKS: Binding = bind(0, 6, StorageReadWrite, "blocks");
    pub const OCTREE_OUT: Binding = bind(0, 7, StorageReadWrite, "cells_out");
    /// Every octree pass binds the same group (`shaders/octree_common.wgsl`).
    pub const OCTREE: [Binding; 8] = [
        OCTREE_PARAMS,
        OCTREE_NODES,
        OCTREE_STATE,
        OCTREE_POS,
        OCTREE_LEAF,
        OCTREE_GRIDS,
        OCTREE_BLOCKS,
        OCTREE_OUT,
    ];

    /// `sort_common.wgsl`: the pass's constants (`SortUniforms`).
    pub const SORT_PARAMS: Binding = bind(0, 0, Uniform, "params");
    pub const SORT_SRC: Binding = bind(0, 1, StorageRead, "src");
    pub const SORT_DST: Binding = bind(0, 2, StorageReadWrite, "dst");
    pub const SORT_HIST: Binding = bind(0, 3, StorageReadWrite, "hist");
    pub const SORT_SUMS: Binding = bind(0, 4, StorageReadWrite, "sums");
    pub const SORT_POS: Binding = bind(0, 5, StorageRead, "pos");
    pub const SORT_ORDER: Binding = bind(0, 6, StorageReadWrite, "order");
    /// Every radix sort pass binds the same group (`shaders/sort_common.wgsl`).
    pub const SORT: [Binding; 7] =
        [SORT_PARAMS, SORT_SRC, SORT_DST, SORT_HIST, SORT_SUMS, SORT_POS, SORT_ORDER];

    pub const PRESENT_PARAMS: Binding = bind(0, 0, Uniform, "params");
    /// `present.wgsl`: the resolved image.
    pub const PRESENT_IMAGE: Binding = bind(0, 1, StorageRead, "image");
    /// `present.wgsl`: the overlay.
    pub const PRESENT_OVERLAY: Binding = bind(0, 2, StorageRead, "overlay");
}

/// The bindings of the present pass (`shaders/present.wgsl`, fragment stage).
pub const PRESENT_BINDINGS: &[Binding] =
    &[binding::PRESENT_PARAMS, binding::PRESENT_IMAGE, binding::PRESENT_OVERLAY];

/// A compute pass of the rasterizer; one WGSL file each.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Pass {
    /// Sets framebuffer words to all ones (`shaders/clear.wgsl`).
    Clear,
    /// Draws batches with 64-bit `atomicMin` on depth|index keys (`shaders/draw.wgsl`).
    Draw64,
    /// 32-bit path, step 1: `atomicMin` of the depth (`shaders/draw_depth.wgsl`).
    DrawDepth32,
    /// 32-bit path, step 2: `atomicMin` of the index among the nearest (`shaders/draw_index.wgsl`).
    DrawIndex32,
    /// Point index to colour (`shaders/resolve.wgsl`).
    Resolve,
    /// Culling, precision and projection of every batch on the GPU (`shaders/plan.wgsl`).
    Plan,
    /// Depth-aware hole filling of the framebuffer into a second key buffer
    /// (`shaders/hole_fill.wgsl`).
    HoleFill,
    /// Eye-dome lighting of the resolved image from the keys' depths (`shaders/eye_dome.wgsl`).
    EyeDome,
    /// Progressive renderer: marks a chunk's slots unloaded (`shaders/progressive_unload.wgsl`).
    ProgressiveUnload,
    /// Progressive renderer: staged points into their shuffled slots
    /// (`shaders/progressive_scatter.wgsl`).
    ProgressiveScatter,
    /// Progressive renderer: draws the last frame's visible slots
    /// (`shaders/progressive_reproject.wgsl`).
    ProgressiveReproject,
    /// Progressive renderer: draws a run of slots, skipping unloaded ones
    /// (`shaders/progressive_fill.wgsl`).
    ProgressiveFill,
    /// Progressive renderer: the visible slots into the next Reproject lists
    /// (`shaders/progressive_prepare.wgsl`).
    ProgressivePrepare,
    /// Progressive renderer: a chunk's loaded slots re-encoded in a grown frame
    /// (`shaders/progressive_reframe.wgsl`).
    ProgressiveReframe,
    /// Progressive renderer: marks the pixels whose winner ties in depth with another point
    /// (`shaders/progressive_ties.wgsl`).
    ProgressiveTies,
    OctreeInsert,
    OctreeSplit,
    OctreeMarkBricks,
    OctreeAllocBricks,
    OctreeVoxels,
    OctreeCountCells,
    OctreeWriteCells,
    OctreeSlots,
    /// GPU radix sort: a segment's points into elements (`shaders/sort_init.wgsl`).
    SortInit,
    /// GPU radix sort: a digit histogram per tile (`shaders/sort_count.wgsl`).
    SortCount,
    /// GPU radix sort: sums of blocks of the histogram (`shaders/sort_reduce.wgsl`).
    SortReduce,
    /// GPU radix sort: the blocks' sums scanned (`shaders/sort_scan_sums.wgsl`).
    SortScanSums,
    /// GPU radix sort: the histogram scanned (`shaders/sort_scan.wgsl`).
    SortScan,
    /// GPU radix sort: elements to their places (`shaders/sort_scatter.wgsl`).
    SortScatter,
    /// GPU radix sort: the arrival numbers in order (`shaders/sort_extract.wgsl`).
    SortExtract,
}

impl Pass {
    /// Every pass.
    pub const ALL: [Pass; 30] = [
        Pass::Clear,
        Pass::Plan,
        Pass::Draw64,
        Pass::DrawDepth32,
        Pass::DrawIndex32,
        Pass::Resolve,
        Pass::HoleFill,
        Pass::EyeDome,
        Pass::ProgressiveUnload,
        Pass::ProgressiveScatter,
        Pass::ProgressiveReproject,
        Pass::ProgressiveFill,
        Pass::ProgressivePrepare,
        Pass::ProgressiveReframe,
        Pass::ProgressiveTies,
        Pass::OctreeInsert,
        Pass::OctreeSplit,
        Pass::OctreeMarkBricks,
        Pass::OctreeAllocBricks,
        Pass::OctreeVoxels,
        Pass::OctreeCountCells,
        Pass::OctreeWriteCells,
        Pass::OctreeSlots,
        Pass::SortInit,
        Pass::SortCount,
        Pass::SortReduce,
        Pass::SortScanSums,
        Pass::SortScan,
        Pass::SortScatter,
        Pass::SortExtract,
    ];

    /// The pass's file under `shaders/`.
    pub fn file(self) -> &'static str {
        match self {
            Pass::Clear => "clear.wgsl",
            Pass::Draw64 => "draw.wgsl",
            Pass::DrawDepth32 => "draw_depth.wgsl",
            Pass::DrawIndex32 => "draw_index.wgsl",
            Pass::Resolve => "resolve.wgsl",
            Pass::Plan => "plan.wgsl",
            Pass::HoleFill => "hole_fill.wgsl",
            Pass::EyeDome => "eye_dome.wgsl",
            Pass::ProgressiveUnload => "progressive_unload.wgsl",
            Pass::ProgressiveScatter => "progressive_scatter.wgsl",
            Pass::ProgressiveReproject => "progressive_reproject.wgsl",
            Pass::ProgressiveFill => "progressive_fill.wgsl",
            Pass::ProgressivePrepare => "progressive_prepare.wgsl",
            Pass::ProgressiveReframe => "progressive_reframe.wgsl",
            Pass::ProgressiveTies => "progressive_ties.wgsl",
            Pass::OctreeInsert => "octree_insert.wgsl",
            Pass::OctreeSplit => "octree_split.wgsl",
            Pass::OctreeMarkBricks => "octree_mark_bricks.wgsl",
            Pass::OctreeAllocBricks => "octree_alloc_bricks.wgsl",
            Pass::OctreeVoxels => "octree_voxels.wgsl",
            Pass::OctreeCountCells => "octree_count_cells.wgsl",
            Pass::OctreeWriteCells => "octree_write_cells.wgsl",
            Pass::OctreeSlots => "octree_slots.wgsl",
            Pass::SortInit => "sort_init.wgsl",
            Pass::SortCount => "sort_count.wgsl",
            Pass::SortReduce => "sort_reduce.wgsl",
            Pass::SortScanSums => "sort_scan_sums.wgsl",
            Pass::SortScan => "sort_scan.wgsl",
            Pass::SortScatter => "sort_scatter.wgsl",
            Pass::SortExtract => "sort_extract.wgsl",
        }
    }

    fn own_source(self) -> &'static str {
        match self {
            Pass::Clear => include_str!("../../../shaders/clear.wgsl"),
            Pass::Draw64 => include_str!("../../../shaders/draw.wgsl"),
            Pass::DrawDepth32 => include_str!("../../../shaders/draw_depth.wgsl"),
            Pass::DrawIndex32 => include_str!("../../../shaders/draw_index.wgsl"),
            Pass::Resolve => include_str!("../../../shaders/resolve.wgsl"),
            Pass::Plan => include_str!("../../../shaders/plan.wgsl"),
            Pass::HoleFill => include_str!("../../../shaders/hole_fill.wgsl"),
            Pass::EyeDome => include_str!("../../../shaders/eye_dome.wgsl"),
            Pass::ProgressiveUnload => include_str!("../../../shaders/progressive_unload.wgsl"),
            Pass::ProgressiveScatter => include_str!("../../../shaders/progressive_scatter.wgsl"),
            Pass::ProgressiveReproject => {
                include_str!("../../../shaders/progressive_reproject.wgsl")
            }
            Pass::ProgressiveFill => include_str!("../../../shaders/progressive_fill.wgsl"),
            Pass::ProgressivePrepare => include_str!("../../../shaders/progressive_prepare.wgsl"),
            Pass::ProgressiveReframe => include_str!("../../../shaders/progressive_reframe.wgsl"),
            Pass::ProgressiveTies => include_str!("../../../shaders/progressive_ties.wgsl"),
            Pass::OctreeInsert => include_str!("../../../shaders/octree_insert.wgsl"),
            Pass::OctreeSplit => include_str!("../../../shaders/octree_split.wgsl"),
            Pass::OctreeMarkBricks => include_str!("../../../shaders/octree_mark_bricks.wgsl"),
            Pass::OctreeAllocBricks => include_str!("../../../shaders/octree_alloc_bricks.wgsl"),
            Pass::OctreeVoxels => include_str!("../../../shaders/octree_voxels.wgsl"),
            Pass::OctreeCountCells => include_str!("../../../shaders/octree_count_cells.wgsl"),
            Pass::OctreeWriteCells => include_str!("../../../shaders/octree_write_cells.wgsl"),
            Pass::OctreeSlots => include_str!("../../../shaders/octree_slots.wgsl"),
            Pass::SortInit => include_str!("../../../shaders/sort_init.wgsl"),
            Pass::SortCount => include_str!("../../../shaders/sort_count.wgsl"),
            Pass::SortReduce => include_str!("../../../shaders/sort_reduce.wgsl"),
            Pass::SortScanSums => include_str!("../../../shaders/sort_scan_sums.wgsl"),
            Pass::SortScan => include_str!("../../../shaders/sort_scan.wgsl"),
            Pass::SortScatter => include_str!("../../../shaders/sort_scatter.wgsl"),
            Pass::SortExtract => include_str!("../../../shaders/sort_extract.wgsl"),
        }
    }

    /// Every binding the pass's WGSL module declares, in groups 0 and (draw passes) 1.
    pub fn bindings(self) -> &'static [Binding] {
        use binding::*;
        match self {
            Pass::Clear => &[CLEAR_WORDS],
            Pass::Draw64 => &[FRAME, KEYS, COUNTERS, KEY_WORDS, RECORDS, COARSE, MEDIUM, FINE],
            Pass::DrawDepth32 => &[FRAME, DEPTHS, RECORDS, COARSE, MEDIUM, FINE],
            Pass::DrawIndex32 => &[FRAME, DEPTHS, COUNTERS, INDICES, RECORDS, COARSE, MEDIUM, FINE],
            Pass::Resolve => &[
                RESOLVE_PARAMS,
                RESOLVE_INDEX_WORDS,
                RESOLVE_DEPTH_WORDS,
                RESOLVE_COLORS,
                RESOLVE_IMAGE,
            ],
            Pass::Plan => &[PLAN_PARAMS, PLAN_BATCHES, PLAN_RECORDS, PLAN_COUNTERS],
            Pass::HoleFill => &[FILL_PARAMS, FILL_INDEX_WORDS, FILL_DEPTH_WORDS, FILL_FILLED],
            Pass::EyeDome => &[EYE_DOME_PARAMS, EYE_DOME_DEPTH_WORDS, EYE_DOME_IMAGE],
            Pass::ProgressiveUnload => &[UNLOAD_COARSE],
            Pass::ProgressiveScatter => &[
                SCATTER_PARAMS,
                SCATTER_STAGED,
                SCATTER_COARSE,
                SCATTER_MEDIUM,
                SCATTER_FINE,
                SCATTER_COLORS,
            ],
            Pass::ProgressiveReproject => {
                &[FRAME, KEYS, COUNTERS, VISIBLE, RECORDS, COARSE, MEDIUM, FINE]
            }
            Pass::ProgressiveFill => &[FRAME, KEYS, COUNTERS, RECORDS, COARSE, MEDIUM, FINE],
            Pass::ProgressivePrepare => {
                &[PREPARE_PARAMS, PREPARE_KEY_WORDS, PREPARE_LIST_COUNTS, PREPARE_LISTS]
            }
            Pass::ProgressiveReframe => {
                &[REFRAME_PARAMS, REFRAME_COARSE, REFRAME_MEDIUM, REFRAME_FINE]
            }
            Pass::ProgressiveTies => {
                &[FRAME, TIES_KEY_WORDS, TIES_FLAGS, RECORDS, COARSE, MEDIUM, FINE]
            }
            p if p.builds_octree() => &OCTREE,
            p if p.sorts() => &SORT,
            _ => unreachable!("every other pass builds the octree or sorts"),
        }
    }

    /// Whether the pass is one of the GPU radix sort's (`shaders/sort_*.wgsl`; they share
    /// [`binding::SORT`] and `sort_common.wgsl`).
    pub fn sorts(self) -> bool {
        matches!(
            self,
            Pass::SortInit
                | Pass::SortCount
                | Pass::SortReduce
                | Pass::SortScanSums
                | Pass::SortScan
                | Pass::SortScatter
                | Pass::SortExtract
        )
    }

    /// Whether the pass is one of the GPU octree builder's (`shaders/octree_*.wgsl`; they share
    /// [`binding::OCTREE`] and `octree_common.wgsl`).
    pub fn builds_octree(self) -> bool {
        matches!(
            self,
            Pass::OctreeInsert
                | Pass::OctreeSplit
                | Pass::OctreeMarkBricks
                | Pass::OctreeAllocBricks
                | Pass::OctreeVoxels
                | Pass::OctreeCountCells
                | Pass::OctreeWriteCells
                | Pass::OctreeSlots
        )
    }

    /// Whether the pass draws batches: its group 1 is [`binding::BATCHES`] (`common/batches.wgsl`).
    pub fn draws_batches(self) -> bool {
        matches!(
            self,
            Pass::Draw64
                | Pass::DrawDepth32
                | Pass::DrawIndex32
                | Pass::ProgressiveReproject
                | Pass::ProgressiveFill
                | Pass::ProgressiveTies
        )
    }

    /// Whether the pass uses 64-bit integers and atomics (SHADER_INT64 +
    /// SHADER_INT64_ATOMIC_MIN_MAX).
    pub fn needs_int64(self) -> bool {
        matches!(
            self,
            Pass::Draw64
                | Pass::ProgressiveReproject
                | Pass::ProgressiveFill
                | Pass::ProgressiveScatter
        )
    }

    /// The complete WGSL module of the pass, as the pipeline compiles it.
    pub fn source(self) -> String {
        let mut parts = vec![TYPES];
        match self {
            Pass::Clear | Pass::Resolve | Pass::HoleFill | Pass::EyeDome => {}
            // div_rn and opaque of the decode.
            Pass::Plan => parts.push(DECODE),
            Pass::Draw64 | Pass::DrawIndex32 => parts.extend([DECODE, BATCHES, COUNTERS]),
            Pass::DrawDepth32 => parts.extend([DECODE, BATCHES]),
            Pass::ProgressiveUnload
            | Pass::ProgressiveScatter
            | Pass::ProgressivePrepare
            | Pass::ProgressiveReframe => parts.push(PROGRESSIVE),
            Pass::ProgressiveReproject | Pass::ProgressiveFill => {
                parts.extend([PROGRESSIVE, DECODE, BATCHES, COUNTERS])
            }
            Pass::ProgressiveTies => parts.extend([PROGRESSIVE, DECODE, BATCHES]),
            p if p.builds_octree() => parts.push(OCTREE),
            p if p.sorts() => parts.push(SORT),
            _ => unreachable!("every other pass builds the octree or sorts"),
        }
        parts.push(self.own_source());
        parts.join("\n")
    }
}
