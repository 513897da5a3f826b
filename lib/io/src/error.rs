//! Errors of mortar-io, typed in the manner of las-rs: one documented variant per kind of
//! failure, with the file it concerns (`path`) and the numbers that describe it as fields.
//!
//! Lower layers have their own enums ([`LasError`] for the LAS header parser, [`LazError`] for
//! LAZ data, [`BatchError`], [`StoreError`], [`PayloadError`], [`PlanError`], [`PartError`],
//! [`ExportError`], [`RenderError`], [`CrsError`], and mortar-core's errors); [`Error`] wraps
//! them with the path. The messages are what mortar has always printed (`path: problem`).
//!
//! A wrapped error is kept in a field named `error` and is part of the message, not returned by
//! [`std::error::Error::source`]: the binary prints errors with their whole chain (`{:#}`), which
//! would print it twice. [`Error::Io`] keeps its `source` as it always has.

use std::path::{Path, PathBuf};

pub use crate::crs::CrsError;
pub use crate::las::LasError;
use mortar_core::grid::GridError;
use mortar_core::layout::LayoutError;
use mortar_core::octree::{LodIndexError, OctreeError};
use mortar_core::render::{CameraError, RasterError};

/// An error of mortar-io; every one that concerns a file names it.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    // ---- inputs as given on the command line
    /// An input path names nothing (and is not a glob pattern).
    #[error("{path}: no such file or directory")]
    NotFound { path: PathBuf },
    /// A directory given as input holds no `.las` or `.laz` file.
    #[error("{path}: directory holds no .las or .laz files")]
    NoLasInDirectory { path: PathBuf },
    /// A glob pattern does not parse.
    #[error("{pattern}: bad pattern: {error}")]
    BadPattern { pattern: String, error: glob::PatternError },
    /// A glob pattern matches no file.
    #[error("{pattern}: no file matches this pattern")]
    NoMatch { pattern: String },
    /// No input was given at all.
    #[error("no input given")]
    NoInput,
    /// An attribute named in a selection (`--attributes`) is not in the point format.
    #[error("{0}")]
    UnknownAttribute(#[from] UnknownAttribute),

    // ---- reading and writing files
    /// Reading, writing, creating or renaming a file failed (out of disk, permissions, a closed
    /// pipe, ...).
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// An HTTP input failed (`path` is its URL): a status, a short body, a changed file
    /// (`crate::remote`).
    #[error("{path}: {why}")]
    Http { path: PathBuf, why: String },
    /// A LAS/LAZ header, its VLRs or EVLRs are malformed (bad signature, unsupported version,
    /// truncated header, offsets that lie), or a header cannot be written for these points.
    #[error("{path}: {error}")]
    Las { path: PathBuf, error: LasError },
    /// A COPC file's hierarchy cannot be used (read as a LOD source).
    #[error("{path}: COPC: {error}")]
    Copc { path: PathBuf, error: CopcError },
    /// An EPT directory's node cannot be read.
    #[error("{path}: EPT: {error}")]
    Ept { path: PathBuf, error: EptError },
    /// The point format and record length of a file cannot be laid out.
    #[error("{path}: {error}")]
    Layout { path: PathBuf, error: LayoutError },
    /// LAZ data cannot be read: the LASzip VLR, the chunk table or a chunk is damaged or
    /// unsupported.
    #[error("{path}: {error}")]
    Laz { path: PathBuf, error: LazError },
    /// A LAS file's header declares more points than its point data holds.
    #[error("{path}: header says {declared} points but the file holds only {available} ({bytes} bytes of point data, {record_len} per point): truncated or damaged")]
    Truncated { path: PathBuf, declared: u64, available: u64, bytes: u64, record_len: u64 },
    /// A piece of an input decoded to another number of bytes than its points need.
    #[error("{path}: piece {piece} holds {got} bytes, expected {expected}")]
    PieceSize { path: PathBuf, piece: usize, got: usize, expected: usize },
    /// A piece of an input holds another number of points than it declared.
    #[error("{path}: piece {piece} holds another number of points than declared")]
    PieceCount { path: PathBuf, piece: usize },
    /// A mortar batch file is malformed or of another version.
    #[error("{path}: {error}")]
    Batch { path: PathBuf, error: BatchError },
    /// A batch section could not be compressed.
    #[error("zstd: {error}")]
    Compress { error: std::io::Error },
    /// The LAZ writer cannot be set up for a point format.
    #[error("cannot write LAZ for point format {format}: {error}")]
    LazFormat { format: u8, error: laz::LasZipError },
    /// The LAZ writer failed while being set up (its VLR or compressor).
    #[error("{error}")]
    LazSetup { error: std::io::Error },
    /// Finishing the LAZ compression of a file failed.
    #[error("{path}: LAZ compression failed: {error}")]
    LazCompress { path: PathBuf, error: laz::LasZipError },
    /// A LAS sink was given another number of points than it announced.
    #[error("{path}: wrote {written} of {expected} points")]
    ShortWrite { path: PathBuf, written: u64, expected: u64 },
    /// A sink was used out of order (finished before it began, written before it began): a bug
    /// of its caller.
    #[error("{what}")]
    SinkOrder { what: &'static str },
    /// Metadata could not be serialized as JSON.
    #[error("{error}")]
    Json { error: serde_json::Error },
    /// Metadata for a file could not be serialized as JSON.
    #[error("{path}: {error}")]
    JsonFile { path: PathBuf, error: serde_json::Error },
    /// An inconsistency mortar checks for and never expects (a bug, or a file changed under it).
    #[error("{path}: internal: {what}")]
    Internal { path: PathBuf, what: &'static str },

    // ---- merging inputs
    /// The inputs' point formats cannot be merged into one record layout.
    #[error("{path}: {problem} (this file has point format {format}, {first} has {first_format})")]
    FormatsDiffer { path: PathBuf, problem: String, format: u8, first: PathBuf, first_format: u8 },
    /// An input's scales or offsets do not put its points on the merged grid (incompatible
    /// scales).
    #[error("{path}: {error}")]
    IncompatibleGrid { path: PathBuf, error: GridError },
    /// The inputs together do not fit one grid (their extent).
    #[error("{error}")]
    Grid { error: GridError },
    /// An input's extra bytes are described differently from the first input's.
    #[error("{path}: its {extra} extra bytes per point are described differently from those of {first}; they cannot be merged")]
    ExtraBytesDiffer { path: PathBuf, extra: usize, first: PathBuf },
    /// A point lies outside its header's bounds, beyond what the merged grid can hold.
    #[error("{path}: a point lies outside the bounds its header declares, beyond what the merged grid can hold")]
    OutsideGrid { path: PathBuf },
    /// Two inputs carry different CRSs.
    #[error("{path}: its CRS, {crs}, differs from that of {first}, {first_crs}; refusing to merge them (reproject one, or choose with --assign-crs FILE|EPSG:CODE)")]
    CrsConflict { path: PathBuf, crs: String, first: PathBuf, first_crs: String },
    /// The file given to `--assign-crs` cannot be read (anything but an I/O error).
    #[error("{}: --assign-crs: {}", error.path().unwrap_or(Path::new("")).display(), error.problem())]
    AssignCrsFile { error: Box<Error> },
    /// The file given to `--assign-crs` has no CRS records.
    #[error("{path}: --assign-crs: this file has no CRS records (LASF_Projection VLRs)")]
    AssignCrsNoRecords { path: PathBuf },
    /// The EPSG code given to `--assign-crs` cannot be written as GeoTIFF keys.
    #[error("--assign-crs: {error}")]
    AssignCrsCode { error: CrsError },

    // ---- sorting and building
    /// More points than one in-memory sort or build can index.
    #[error("too many points for one in-memory {what}")]
    TooManyPoints { what: &'static str },
    /// A piece of an input is too large to hold in memory.
    #[error("a piece of {points} points does not fit in memory")]
    PieceTooLarge { points: u64 },
    /// An engine that holds the whole input in memory was asked for an input larger than
    /// `--memory`.
    #[error("{what} needs about {needed} bytes of memory for this input, above --memory ({budget} bytes); raise --memory, or leave --engine to auto (the partitioned engine builds the same store within the budget)")]
    OverBudget { what: &'static str, needed: u64, budget: u64 },
    /// An input's axes have different scales and its extent on the finest does not fit the
    /// octree's grid.
    #[error("{path}: its axes' scales {scale:?} differ, and its extent on axis {axis} on the finest of them does not fit the octree's grid (2^31 units); re-scale it to one scale on all axes (e.g. `las2las -rescale`)")]
    ScalesDiffer { path: PathBuf, scale: [f64; 3], axis: usize },
    /// The octree builder refused (root, depth or bounds out of range).
    #[error("octree: {error}")]
    Octree { error: OctreeError },
    /// Reading a node's points back from the store failed while the octree grew.
    #[error("{path}: reading a node back: {problem}")]
    PageIn { path: PathBuf, problem: String },
    /// A worker thread panicked.
    #[error("{thread} thread panicked")]
    ThreadPanicked { thread: &'static str },
    /// The loader threads could not be started.
    #[error("cannot start {threads} loader threads: {error}")]
    ThreadPool { threads: usize, error: rayon::ThreadPoolBuildError },
    /// Averaged voxel colours were asked of an engine that makes first-come colours only.
    #[error("the sorted engines make first-come voxel colours only; averaged colours need the incremental engine")]
    AveragedColours,
    /// There are no points to build or export.
    #[error("{path}: no points to {action}")]
    NoPoints { path: PathBuf, action: &'static str },
    /// A store or part directory could not be written into.
    #[error("{path}: its directory {parent} does not exist")]
    NoParentDirectory { path: PathBuf, parent: PathBuf },
    /// A store cannot be read, built, continued or compacted.
    #[error("{path}: {error}")]
    Store { path: PathBuf, error: StoreError },
    /// A node payload is damaged or cannot be encoded.
    #[error("{path}: {error}")]
    Payload { path: PathBuf, error: PayloadError },
    /// A node payload of a merged store cannot be encoded.
    #[error("{error}")]
    MergePayload { error: PayloadError },
    /// A build failed (out of disk, ...) after a commit: the store keeps that commit.
    #[error("{error}; the store {store} keeps its last commit (commit {commit}), readable; `mortar build --resume` continues it")]
    KeptCommit { error: Box<Error>, store: PathBuf, commit: u64 },
    /// An export cannot be made of these points.
    #[error("{path}: {error}")]
    Export { path: PathBuf, error: ExportError },

    // ---- distributed builds
    /// A plan cannot be read or does not fit the inputs (checksum mismatch, other files).
    #[error("{path}: {error}")]
    Plan { path: PathBuf, error: PlanError },
    /// A plan or job asked for does not exist, or the parts do not make up the plan.
    #[error("{error}")]
    Job { error: JobError },
    /// A part of a distributed build is refused (damaged, of another plan, repeated).
    #[error("{path}: {error}")]
    Part { path: PathBuf, error: PartError },

    // ---- rendering
    /// The points cannot be drawn or coloured as asked.
    #[error("{path}: {error}")]
    Render { path: PathBuf, error: RenderError },

    /// The work stopped because of Ctrl-C.
    #[error("interrupted")]
    Interrupted,
}

/// Why a COPC hierarchy is not used (`mortar_io::copc`; the file is then read flat).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CopcError {
    /// The info VLR is not 160 bytes or holds a non-finite or non-positive cube.
    #[error("the COPC info VLR is damaged ({0})")]
    Info(String),
    /// A hierarchy page outside the file or not a whole number of entries.
    #[error("hierarchy page at byte {offset} ({size} bytes) {why}")]
    Page {
        /// Offset of the page.
        offset: u64,
        /// Its size.
        size: u64,
        /// What is wrong.
        why: &'static str,
    },
    /// An entry that cannot be a node of the cube.
    #[error("hierarchy entry {key:?} {why}")]
    Entry {
        /// Level, x, y, z as recorded.
        key: [i32; 4],
        /// What is wrong.
        why: String,
    },
    /// No root node.
    #[error("the hierarchy has no root node (0-0-0-0)")]
    NoRoot,
    /// A node that no walk from the root reaches.
    #[error("node {0} has no parent in the hierarchy")]
    Orphan(String),
}

/// Why an EPT directory is not used as a LOD source (`mortar_io::ept`; its LAZ files are then
/// read flat).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum EptError {
    /// A file cannot be read.
    #[error("{file}: {error}")]
    Read {
        /// The file.
        file: String,
        /// The system's message.
        error: String,
    },
    /// `ept.json` is not usable.
    #[error("{0}")]
    Meta(String),
    /// The hierarchy is damaged.
    #[error("{0}")]
    Hierarchy(String),
}

/// Why LAZ data cannot be read (the LASzip VLR, the chunk table, a chunk).
#[derive(Debug, thiserror::Error)]
pub enum LazError {
    /// The point format has the compression bit but there is no LASzip VLR.
    #[error("point format is marked compressed but the file has no LASzip VLR")]
    NoLaszipVlr,
    /// The LASzip VLR does not parse.
    #[error("LASzip VLR is invalid: {error}")]
    BadVlr { error: laz::LasZipError },
    /// The LASzip VLR's items describe another record length than the header.
    #[error("LASzip VLR describes {items_size}-byte points but the header says {record_len}")]
    ItemSizes { items_size: u64, record_len: u16 },
    /// A LASzip item (type, version) that mortar does not decode.
    #[error("LASzip item {item} version {version} is not supported")]
    UnsupportedItem { item: String, version: u16 },
    /// Variable-size chunks without a chunk table.
    #[error("LAZ file uses variable-size chunks but has no chunk table")]
    NoChunkTable,
    /// The header's point count is implausible for the bytes of LAZ data (no chunk table).
    #[error("header claims {points} points, implausible for {bytes} bytes of LAZ data")]
    Implausible { points: u64, bytes: usize },
    /// The header declares points but there is no point data.
    #[error("LAZ point data is missing")]
    NoPointData,
    /// The chunk table lies past the end of the file.
    #[error("the LAZ chunk table should be at byte {at} but the file ends at byte {file_len}: truncated (the header says {points} points)")]
    TableTruncated { at: i64, file_len: usize, points: u64 },
    /// The chunk table claims more chunks than its data can hold.
    #[error("LAZ chunk table claims {chunks} chunks, impossible in {bytes} bytes of data")]
    TooManyChunks { chunks: u64, bytes: u64 },
    /// The sequential decoder's chunk table claims more chunks than follow it.
    #[error("LAZ chunk table claims {chunks} chunks in {bytes} bytes (corrupt chunk table)")]
    SequentialTable { chunks: u64, bytes: u64 },
    /// The chunk table does not parse (or its reader gave up: `error` is `None`).
    #[error("LAZ chunk table is corrupt{}", error.as_ref().map(|e| format!(": {e}")).unwrap_or_default())]
    BadTable { error: Option<std::io::Error> },
    /// A chunk claims more points than its bytes can hold.
    #[error("LAZ chunk {chunk} claims {points} points in {bytes} bytes (corrupt chunk table)")]
    ChunkPoints { chunk: usize, points: u64, bytes: u64 },
    /// A chunk's bytes run past the chunk table.
    #[error("LAZ chunk {chunk} runs past the chunk table (corrupt chunk table)")]
    ChunkPastTable { chunk: usize },
    /// The chunk table's points disagree with the header's count (header lies about counts).
    #[error("header says {declared} points but the LAZ chunk table holds {table}")]
    CountMismatch { declared: u64, table: u64 },
    /// A layered chunk's layer sizes claim more bytes than the chunk holds.
    #[error("LAZ chunk {chunk} is corrupt: its layers claim {total} bytes but {room} follow")]
    ChunkLayers { chunk: usize, total: u64, room: u64 },
    /// The decoder failed on a chunk.
    #[error("LAZ chunk {chunk} is corrupt: {error}")]
    ChunkCorrupt { chunk: usize, error: laz::LasZipError },
    /// The decoder panicked on a chunk.
    #[error("LAZ chunk {chunk} is corrupt (the decoder gave up)")]
    ChunkGaveUp { chunk: usize },
    /// Fewer points decoded than the piece holds.
    #[error("LAZ data ends early: {got} of {expected} points")]
    EndsEarly { got: usize, expected: u64 },
    /// The sequential decoder failed.
    #[error("LAZ data is corrupt: {error}")]
    DataCorrupt { error: std::io::Error },
    /// The sequential decoder panicked.
    #[error("LAZ data is corrupt (the decoder gave up)")]
    DataGaveUp,
}

/// Why a mortar batch file cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum BatchError {
    /// The file does not start with the batch file magic.
    #[error("not a mortar batch file")]
    NotBatchFile,
    /// Another version of the batch format.
    #[error("batch file version {found} is not supported (this mortar reads {supported})")]
    Version { found: u32, supported: u32 },
    /// The metadata lies outside the file.
    #[error("metadata lies outside the file (truncated?)")]
    MetaOutside,
    /// The metadata does not parse.
    #[error("metadata is not valid: {error}")]
    BadMeta { error: serde_json::Error },
    /// The header's section count disagrees with the metadata.
    #[error("section count disagrees with the metadata")]
    SectionCount,
    /// The batch table lies outside the file.
    #[error("batch table lies outside the file (truncated?)")]
    TableOutside,
    /// The stored LAS header or EVLRs lie outside the file.
    #[error("LAS header record lies outside the file")]
    LasHeaderOutside,
    /// The stored LAS header does not parse.
    #[error("stored LAS header is invalid: {error}")]
    BadLasHeader { error: LasError },
    /// The stored EVLRs do not parse.
    #[error("stored EVLRs are invalid: {error}")]
    BadEvlrs { error: LasError },
    /// The stored point format cannot be laid out.
    #[error("{error}")]
    Layout { error: LayoutError },
    /// The record length is more than a LAS record holds.
    #[error("record length {record_len} is more than a LAS record can hold")]
    RecordTooLong { record_len: usize },
    /// An attribute column lies outside the record.
    #[error(
        "attribute {name} (bytes {offset}..+{width}) lies outside the {record_len}-byte record"
    )]
    AttributeOutside { name: String, offset: usize, width: usize, record_len: usize },
    /// A batch table entry is out of range.
    #[error("batch {batch} has an invalid entry")]
    BadEntry { batch: usize },
    /// A batch does not start where the ones before it end.
    #[error("batch {batch} starts at point {first} but {preceding} points precede it")]
    BatchStart { batch: usize, first: u64, preceding: u64 },
    /// A section lies outside the file.
    #[error("batch {batch} section {section} lies outside the file (truncated?)")]
    SectionOutside { batch: usize, section: usize },
    /// An uncompressed section has another size than its points need.
    #[error("batch {batch} section {section} has {len} bytes, expected {expected}")]
    SectionLen { batch: usize, section: usize, len: u64, expected: u64 },
    /// The batches hold another number of points than the header says.
    #[error("batches hold {total} points but the header says {declared}")]
    PointCount { total: u64, declared: u64 },
    /// A compressed section does not decompress.
    #[error("batch {batch} section {section} is corrupt: {error}")]
    SectionCorrupt { batch: usize, section: usize, error: std::io::Error },
    /// A compressed section decompresses to another size than its points need.
    #[error("batch {batch} section {section} decompresses to {len} bytes, expected {expected}")]
    SectionSize { batch: usize, section: usize, len: usize, expected: usize },
}

/// Why a store cannot be read, built into, continued or compacted.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// `hierarchy.bin` is shorter than its header.
    #[error("hierarchy.bin is truncated")]
    HierarchyTruncated,
    /// `hierarchy.bin` does not start with the hierarchy magic.
    #[error("hierarchy.bin is not a mortar store hierarchy")]
    NotHierarchy,
    /// Another store format version.
    #[error("store version {version} (entry size {entry_size}) is not supported")]
    Version { version: u32, entry_size: u32 },
    /// The hierarchy holds another number of entries than it declares.
    #[error("hierarchy.bin declares {declared} nodes but holds {held}")]
    NodeCount { declared: u64, held: u64 },
    /// A payload segment (`nodes.bin`, `nodes-<s>.bin`) is shorter than the hierarchy covers.
    #[error("{file} holds {held} bytes, fewer than the {covered} the hierarchy covers")]
    NodesShort { file: String, held: u64, covered: u64 },
    /// The bytes after the entries are no segment table.
    #[error("hierarchy.bin: the bytes after the node entries are no segment table")]
    SegmentTable,
    /// A hierarchy entry is out of range.
    #[error(
        "node entry {node} is damaged (kind {kind}, {count} points, {length} bytes at {offset})"
    )]
    EntryDamaged { node: usize, kind: u32, count: u64, length: u64, offset: u64 },
    /// A payload's header disagrees with its hierarchy entry.
    #[error("node payload {node} does not match its hierarchy entry")]
    PayloadMismatch { node: usize },
    /// The leaves hold another number of points than the hierarchy says.
    #[error("the leaves hold {leaves} points, the hierarchy says {declared}")]
    LeafPoints { leaves: u64, declared: u64 },
    /// The root cube is larger than mortar supports.
    #[error("hierarchy.bin: root cube of 2^{size_log2} grid units; at most 2^32 is supported")]
    RootTooLarge { size_log2: u32 },
    /// The root cube does not overlap the 32-bit grid.
    #[error("hierarchy.bin: root cube corner {min:?} lies outside the 32-bit grid")]
    RootOutside { min: [i64; 3] },
    /// A node's level does not fit a byte.
    #[error("hierarchy.bin: node {node} has level {level}")]
    NodeLevel { node: usize, level: u32 },
    /// The hierarchy is not a tree mortar can select from.
    #[error("hierarchy.bin: {error}")]
    Index { error: LodIndexError },
    /// A node asked for is not in the store.
    #[error("node {node} is not in the store")]
    NoSuchNode { node: u32 },
    /// A piece of a store holds another number of points than its leaves declare.
    #[error("piece {piece} holds another number of points than its leaves declare")]
    PieceCount { piece: usize },
    /// The directory is not empty (a new store is built into an empty one).
    #[error("exists and is not an empty directory; give a new directory for the store")]
    NotEmpty,
    /// The store was built from other inputs than those given.
    #[error("was built from other inputs (its source header, VLRs or CRS differ); give a new directory or remove it")]
    OtherInputs,
    /// The store has no build record, so it cannot be continued.
    #[error("has no build record (build.json): not a store that `mortar build` began, or one begun by an older mortar; give a new directory")]
    NoBuildRecord,
    /// The build record does not parse.
    #[error("not a build record: {error}")]
    BadBuildRecord { error: serde_json::Error },
    /// The store was built with other settings than the build that would continue it.
    #[error("{mismatch}; give a new directory, or remove it to start over")]
    Settings { mismatch: String },
    /// The store cannot be extended by `mortar build --append` (why, in words).
    #[error("{why}")]
    Append { why: String },
    /// `arrival.bin` is damaged or does not belong to the store (why, in words).
    #[error("{why}")]
    Arrival { why: String },
    /// The committed nodes are not those the inputs give.
    #[error("its committed nodes are not those the inputs give (the store was changed, or built by another mortar); give a new directory")]
    CommittedNodes,
    /// A node has saved points but no payload.
    #[error("node {node} has saved points but no payload")]
    NoPayload { node: usize },
    /// A node's last payload holds another number of points than were saved.
    #[error("node {node}: the last payload holds {held} points, {saved:?} were saved")]
    PayloadCount { node: usize, held: u64, saved: Option<u64> },
}

/// Why an export cannot be made.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum ExportError {
    /// The point format carries waveforms, which COPC does not hold.
    #[error("point format {format} carries waveforms; COPC holds point formats 6, 7 and 8 only (give the points without waveforms, e.g. `pdal translate` to format {instead})")]
    Waveforms { format: u8, instead: u8 },
    /// The output record layout cannot be made.
    #[error("{error}")]
    Layout { error: LayoutError },
    /// The points cannot be converted into the output layout (mortar-core's message).
    #[error("{problem}")]
    Convert { problem: String },
    /// The scales are not all positive.
    #[error("the scales {scale:?} are not all positive; the export needs positive scales (a reader's octree grows with the world coordinates)")]
    ScalesNotPositive { scale: [f64; 3] },
    /// The scales are not whole multiples of one another.
    #[error("the scales {scale:?} are not whole multiples of one another, so no octree cube has whole cells on every axis (re-scale the input, e.g. with `las2las -rescale`)")]
    ScalesNotMultiples { scale: [f64; 3] },
    /// The points cannot be placed on the globe (3D Tiles).
    #[error("{why}")]
    Globe { why: String },
}

/// Why a plan cannot be read, or does not fit the inputs it is run on.
#[derive(Debug, thiserror::Error)]
pub enum PlanError {
    /// The file is not JSON of a plan.
    #[error("not a plan of `mortar plan`: {error}")]
    NotPlan { error: serde_json::Error },
    /// Another plan format.
    #[error("a plan of format {found:?}; this mortar reads {supported}")]
    Format { found: String, supported: &'static str },
    /// The plan's checksum does not match its contents: it was edited.
    #[error("the plan was changed after `mortar plan` wrote it (its checksum does not match); plan again")]
    Checksum,
    /// An index of the plan is out of range.
    #[error("not a plan this mortar can run (a root, depth, node or input index out of range); plan again")]
    OutOfRange,
    /// An input's header bounds cannot be used for planning.
    #[error("{error}; plan with --scan (which reads the points for their box)")]
    HeaderBox { error: BoundsError },
    /// An input is not the file the plan was made from.
    #[error("is not the file the plan was made from ({bytes} bytes and {points} points now, {plan_bytes} and {plan_points} in the plan); plan again")]
    OtherFile { bytes: u64, points: u64, plan_bytes: u64, plan_points: u64 },
    /// An input's points reach outside the box the plan took for it.
    #[error("its points reach outside the box the plan took for it ({min:?} .. {max:?} against {lo:?} .. {hi:?} on the grid){}; plan again with --scan", if *scanned { " (the file changed since)" } else { " (its header's bounds are wrong)" })]
    OutsideBox { min: [i32; 3], max: [i32; 3], lo: [i32; 3], hi: [i32; 3], scanned: bool },
}

/// Why a header's bounds cannot frame its points.
#[derive(Debug, thiserror::Error)]
pub enum BoundsError {
    /// All bounds are zero: the writer did not set them.
    #[error("the header's bounds are all zero (not set by the writer)")]
    AllZero,
    /// An axis's bounds are not finite or are reversed.
    #[error("the header's bounds on axis {axis} are not usable ({min} .. {max})")]
    Unusable { axis: char, min: f64, max: f64 },
}

/// Why a job cannot run or the parts cannot be merged (the plan and the parts as a whole).
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// `--jobs 0`.
    #[error("--jobs must be at least 1")]
    NoJobs,
    /// `--job` names a job the plan does not have.
    #[error("--job {job}: the plan has jobs 0 to {last}")]
    NoSuchJob { job: usize, last: usize },
    /// Another number of inputs than the plan names.
    #[error("the plan names {planned} inputs, {opened} were opened")]
    Inputs { planned: usize, opened: usize },
    /// The plan's cells are at another depth than this mortar makes them.
    #[error(
        "the plan's cells are at depth {planned}, this mortar makes them at {ours}; plan again"
    )]
    CellDepth { planned: u8, ours: u8 },
    /// A node of the plan is not in its tree.
    #[error("the plan's node {node:?} is not in its tree")]
    NodeOutside { node: [u32; 4] },
    /// No parts were given to merge.
    #[error("give the parts to merge")]
    NoParts,
    /// A job's part is missing from the merge.
    #[error("the plan has {jobs} jobs and part {first} is missing (missing: {missing:?}); run those jobs and merge all parts")]
    MissingParts { jobs: usize, first: usize, missing: Vec<usize> },
    /// The plan's nodes do not cover the tree.
    #[error("the plan's nodes do not cover node {node} of the tree")]
    Uncovered { node: String },
    /// The plan split a node that cannot split.
    #[error("node {node} holds {count} points and cannot split, but the plan split it")]
    CannotSplit { node: String, count: u64 },
}

/// Why a part of a distributed build is refused.
#[derive(Debug, thiserror::Error)]
pub enum PartError {
    /// The output directory is neither a part nor empty.
    #[error("exists and is neither a part nor empty; give a new directory for the part")]
    NotEmpty,
    /// The directory has no `part.json`.
    #[error("is not a part of `mortar build --plan` (no part.json): its job did not finish, or it is another directory")]
    NotPart,
    /// `part.json` does not parse.
    #[error("not a part description: {error}")]
    BadDescription { error: serde_json::Error },
    /// A file of the part has another size than `part.json` says.
    #[error("damaged: {what}; run its job again")]
    Damaged { what: &'static str },
    /// The part has no leaf for one of its subtrees.
    #[error("damaged: no leaf for its subtree {subtree}; run its job again")]
    NoLeaf { subtree: String },
    /// The part was built from another plan than the first part.
    #[error("was built from another plan (id {id}) than {first} (id {first_id}); merge the parts of one plan")]
    OtherPlan { id: String, first: PathBuf, first_id: String },
    /// The same job was given twice.
    #[error("is job {job} again (as {first}); give each part once")]
    Repeated { job: usize, first: PathBuf },
    /// The part's job is not in the plan.
    #[error("is job {job}, the plan has {jobs}")]
    NoSuchJob { job: usize, jobs: usize },
    /// The part was built from other inputs than the first part.
    #[error("its source.las differs from {first}'s: built from other inputs")]
    OtherInputs { first: PathBuf },
    /// The parts' arrival ranks are not a permutation of the inputs' points, found in this
    /// part's.
    #[error("damaged arrival.bin: {why}; run its job again")]
    Ranks { why: String },
}

/// Why points cannot be drawn or coloured as asked.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// More points than 32-bit indices can draw.
    #[error(
        "{points} points: at most 2^32 points can be drawn at once (point indices are 32-bit)"
    )]
    TooManyToDraw { points: u64 },
    /// More points than 32-bit indices can colour.
    #[error("{points} points: at most 2^32 points can be coloured at once")]
    TooManyToColour { points: u64 },
    /// A selection of more samples than 32-bit indices can draw.
    #[error("{samples} samples selected: at most 2^32 can be drawn at once (point indices are 32-bit); set a --point-budget")]
    TooManySamples { samples: u64 },
    /// `--color rgb` on points without colour.
    #[error("--color rgb: the points have no colour ({}, point format {format}); try --color intensity", if *has_rgb { "every RGB value is zero" } else { "the point format has no RGB" })]
    NoColour { format: u8, has_rgb: bool },
    /// A colour mode needs an attribute the points do not have.
    #[error("--color {mode}: needs the attribute '{attribute}', but {}", if *not_kept { "it was not kept when the batch file was written (batch again with --attributes all)".to_string() } else { format!("point format {format} has no such field") })]
    MissingAttribute { mode: &'static str, attribute: &'static str, format: u8, not_kept: bool },
    /// A framebuffer holds a point index beyond what was drawn.
    #[error("framebuffer holds a point index beyond {beyond}")]
    StrayIndex { beyond: &'static str },
    /// The rasterizer refused.
    #[error("{error}")]
    Raster { error: RasterError },
    /// The camera cannot select nodes.
    #[error("{error}")]
    Camera { error: CameraError },
}

/// `Some(path)` for the variants whose message begins with the file they concern (`path: ...`),
/// by reference or by mutable reference as `$e` is.
macro_rules! leading_path {
    ($e:expr) => {
        match $e {
            Error::NotFound { path }
            | Error::NoLasInDirectory { path }
            | Error::Io { path, .. }
            | Error::Http { path, .. }
            | Error::Las { path, .. }
            | Error::Copc { path, .. }
            | Error::Ept { path, .. }
            | Error::Layout { path, .. }
            | Error::Laz { path, .. }
            | Error::Truncated { path, .. }
            | Error::PieceSize { path, .. }
            | Error::PieceCount { path, .. }
            | Error::Batch { path, .. }
            | Error::LazCompress { path, .. }
            | Error::ShortWrite { path, .. }
            | Error::JsonFile { path, .. }
            | Error::Internal { path, .. }
            | Error::FormatsDiffer { path, .. }
            | Error::IncompatibleGrid { path, .. }
            | Error::ExtraBytesDiffer { path, .. }
            | Error::OutsideGrid { path }
            | Error::CrsConflict { path, .. }
            | Error::AssignCrsNoRecords { path }
            | Error::ScalesDiffer { path, .. }
            | Error::PageIn { path, .. }
            | Error::NoPoints { path, .. }
            | Error::NoParentDirectory { path, .. }
            | Error::Store { path, .. }
            | Error::Payload { path, .. }
            | Error::Export { path, .. }
            | Error::Plan { path, .. }
            | Error::Part { path, .. }
            | Error::Render { path, .. } => Some(path),
            Error::AssignCrsFile { .. }
            | Error::KeptCommit { .. }
            | Error::BadPattern { .. }
            | Error::NoMatch { .. }
            | Error::NoInput
            | Error::UnknownAttribute(_)
            | Error::Compress { .. }
            | Error::LazFormat { .. }
            | Error::LazSetup { .. }
            | Error::SinkOrder { .. }
            | Error::Json { .. }
            | Error::Grid { .. }
            | Error::AssignCrsCode { .. }
            | Error::TooManyPoints { .. }
            | Error::OverBudget { .. }
            | Error::PieceTooLarge { .. }
            | Error::Octree { .. }
            | Error::ThreadPanicked { .. }
            | Error::ThreadPool { .. }
            | Error::AveragedColours
            | Error::MergePayload { .. }
            | Error::Job { .. }
            | Error::Interrupted => None,
        }
    };
}

impl Error {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Error {
        Error::Io { path: path.into(), source }
    }

    /// The file the error concerns, if it concerns one.
    pub fn path(&self) -> Option<&Path> {
        match self {
            Error::AssignCrsFile { error } | Error::KeptCommit { error, .. } => error.path(),
            e => leading_path!(e).map(PathBuf::as_path),
        }
    }

    /// `self` with the file its message begins with renamed from `from` to `to` (a temporary
    /// file named as what the user gave).
    pub fn renamed(mut self, from: &Path, to: &Path) -> Error {
        if let Some(p) = leading_path!(&mut self) {
            if p == from {
                *p = to.to_path_buf();
            }
        }
        self
    }

    /// The message without the `path: ` it begins with, if it begins with one.
    pub fn problem(&self) -> String {
        let s = self.to_string();
        match leading_path!(self) {
            Some(p) => {
                s.strip_prefix(&format!("{}: ", p.display())).map(str::to_string).unwrap_or(s)
            }
            None => s,
        }
    }
}

pub type Result<T> = std::result::Result<T, Error>;

/// An attribute named in an [`AttributeSelection`](crate::batchfile::AttributeSelection) that the point format does not have.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("point format {format} has no attribute '{name}' (it has: {})", have.join(", "))]
pub struct UnknownAttribute {
    pub format: u8,
    pub name: String,
    /// The attributes the point format has.
    pub have: Vec<String>,
}

/// Why a node payload cannot be read or written.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum PayloadError {
    /// The payload is shorter than its header.
    #[error("payload shorter than its header")]
    Short,
    /// The payload's header is damaged (magic, kind, length or bit widths).
    #[error("damaged payload")]
    Damaged,
    /// The payload holds records of another length than the store's.
    #[error("damaged payload: another record length")]
    RecordLength,
    /// More points than a payload can count.
    #[error("node {node} holds {count} points, more than a payload can (2^32 - 1)")]
    TooManyPoints { node: String, count: usize },
    /// The node's points span more than a payload's grid.
    #[error("node {node} spans more than 2^30 grid units on an axis")]
    TooWide { node: String },
    /// A node's last payload does not hold the points the builder saved in it.
    #[error("node {node}: its last payload does not match the points saved")]
    Stale { node: String },
    /// The attributes gathered for a node are not those of its points.
    #[error("node {node}: {bytes} bytes of attributes for {count} points")]
    AttributeBytes { node: String, bytes: usize, count: usize },
    /// A payload error of node `node`.
    #[error("node {node}: {error}")]
    InNode { node: String, error: Box<PayloadError> },
}

impl From<mortar_core::octree::OctreeError> for Error {
    fn from(error: mortar_core::octree::OctreeError) -> Error {
        Error::Octree { error }
    }
}
