//! The binary layouts of a batch file that renderers read directly (memory-mapped on the CPU,
//! uploaded as-is to the GPU): the file header, one [`BatchEntry`] per batch and one
//! [`SectionEntry`] per batch and section. The file around them (metadata, writing, checks) is
//! `mortar_io::batchfile`; the format is described in `lib/io/BATCH_FORMAT.md`.
//!
//! Keep in sync: `lib/io/BATCH_FORMAT.md`, and the WGSL mirror of [`BatchEntry`] once the GPU
//! renderer reads it.

use crate::quantize::BatchGrid;
use bytemuck::{Pod, Zeroable};

/// File magic, first 8 bytes.
pub const MAGIC: [u8; 8] = *b"MORTBAT\0";
/// Format version written by this build.
pub const VERSION: u32 = 1;
/// Header flag: sections are zstd-compressed.
pub const FLAG_ZSTD: u32 = 1;
/// Section alignment in the file, bytes.
pub const SECTION_ALIGN: u64 = 16;

/// Section indices: the three coordinate words, the render colour, then the kept attributes.
pub const SECTION_COARSE: usize = 0;
pub const SECTION_MEDIUM: usize = 1;
pub const SECTION_FINE: usize = 2;
pub const SECTION_COLOR: usize = 3;
pub const FIRST_ATTRIBUTE_SECTION: usize = 4;

/// The fixed header at byte 0 of a batch file.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable, PartialEq, Eq)]
pub struct FileHeader {
    pub magic: [u8; 8],
    pub version: u32,
    pub flags: u32,
    pub point_count: u64,
    pub batch_count: u64,
    pub section_count: u32,
    pub _pad: u32,
    /// Byte range of the JSON metadata.
    pub meta_offset: u64,
    pub meta_len: u64,
    /// Start of the batch table: `batch_count` [`BatchEntry`], then
    /// `batch_count * section_count` [`SectionEntry`].
    pub table_offset: u64,
}
const _: () = assert!(std::mem::size_of::<FileHeader>() == 64);

/// One batch: point count, quantization frame and bounds.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable, PartialEq)]
pub struct BatchEntry {
    pub count: u32,
    pub flags: u32,
    /// Bits per axis of the quantization frame (x, y, z, unused).
    pub bits: [u8; 4],
    /// Integer bounds (inclusive) on the dataset's LAS grid.
    pub min: [i32; 3],
    pub max: [i32; 3],
    pub _pad: u32,
    /// Index of the batch's first point in the file.
    pub first_point: u64,
    /// World bounds (scale and offset applied).
    pub world_min: [f64; 3],
    pub world_max: [f64; 3],
}
const _: () = assert!(std::mem::size_of::<BatchEntry>() == 96);

impl BatchEntry {
    pub fn grid(&self) -> BatchGrid {
        BatchGrid { min: self.min, bits: [self.bits[0], self.bits[1], self.bits[2]] }
    }
}

/// Where one section of one batch is stored.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable, PartialEq, Eq)]
pub struct SectionEntry {
    pub offset: u64,
    /// Bytes stored (compressed size when the file is compressed).
    pub stored_len: u64,
}
const _: () = assert!(std::mem::size_of::<SectionEntry>() == 16);
