//! A batch file as the rasterizers' input (paper 003 §3.2): its batches as [`BatchRef`]s, and
//! LAS/LAZ inputs batched on the fly into a temporary batch file ([`RenderSource`]). What colours
//! and draws them is mortar-app's (`draw::batch`).
//!
//! Uncompressed batch files are used in place: the rasterizer reads the memory map, so the pages of
//! a word array a batch does not need (its medium and fine words at 10-bit precision, every word of
//! a culled batch) are never read from disk. zstd files are decompressed (the three word sections
//! of every batch) before drawing.

use crate::batchfile::{AttributeSelection, BatchFile, BatchSink, BatchView, Compression};
use crate::cleanup::TempPath;
use crate::dataset::Dataset;
use crate::error::{Error, RenderError, Result};
use crate::sort::{sort, SortOptions};
use mortar_core::render::{Aabb, BatchRef};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Sections of a batch holding the coarse, medium and fine words.
pub const WORD_SECTIONS: [usize; 3] = [0, 1, 2];
/// Section of the stored RGBA8 render colour.
pub const COLOR_SECTION: usize = 3;
/// Section of the first kept attribute.
pub const FIRST_ATTRIBUTE_SECTION: usize = 4;

/// A batch file to draw: opened as given, or made from LAS/LAZ inputs in a temporary directory
/// that is removed when this is dropped (and on Ctrl-C, through [`crate::cleanup`]).
#[derive(Debug)]
pub struct RenderSource {
    /// The batch file.
    pub file: BatchFile,
    /// What the user gave: the batch file's path, or the LAS/LAZ inputs.
    pub name: PathBuf,
    // Dropped after `file` (declaration order): the map is closed before the directory goes.
    temp: Option<TempPath>,
}

impl RenderSource {
    /// Opens an existing batch file.
    pub fn open_batch_file(path: &Path) -> Result<RenderSource> {
        Ok(RenderSource { file: BatchFile::open(path)?, name: path.to_path_buf(), temp: None })
    }

    /// Morton-sorts and batches `ds` exactly as `mortar batch --attributes ...` does (no
    /// compression) into a temporary batch file under `opts.tmp_dir`, and opens it.
    pub fn batch_dataset(
        ds: &Dataset,
        opts: &SortOptions,
        attributes: &AttributeSelection,
    ) -> Result<RenderSource> {
        let names: Vec<String> = ds.inputs.iter().map(|i| i.path().display().to_string()).collect();
        let dir =
            TempPath::dir_in(&opts.tmp_dir, "render").map_err(|e| Error::io(&opts.tmp_dir, e))?;
        let path = dir.path().join("input.mbat");
        let attributes = attributes.resolve(&ds.layout)?;
        let template = ds.source_meta();
        let mut sink = BatchSink::new(&path, template, attributes, Compression::None);
        sort(ds, opts, &mut sink)?;
        sink.finish()?;
        Ok(RenderSource {
            file: BatchFile::open(&path)?,
            name: PathBuf::from(names.join(" ")),
            temp: Some(dir),
        })
    }

    /// `e` with the temporary batch file's path replaced by the inputs' names, so that messages
    /// name what the user gave.
    pub fn own_error(&self, e: Error) -> Error {
        e.renamed(&self.file.path, &self.name)
    }

    /// Whether the batch file is a temporary one made from LAS/LAZ.
    pub fn is_temporary(&self) -> bool {
        self.temp.is_some()
    }
}

/// World bounds of every point of the file.
pub fn file_bounds(file: &BatchFile) -> Aabb {
    let (a, b) = (file.meta.world_min, file.meta.world_max);
    Aabb::new([0, 1, 2].map(|i| a[i].min(b[i])), [0, 1, 2].map(|i| a[i].max(b[i])))
}

/// The coordinate words of every batch: borrowed from the map for uncompressed files,
/// decompressed (in parallel) for zstd files.
pub fn load_words(file: &BatchFile) -> Result<Vec<BatchView<'_>>> {
    (0..file.batch_count())
        .into_par_iter()
        .map(|i| file.batch_sections(i, &WORD_SECTIONS))
        .collect()
}

/// The rasterizer's view of the batches in `views` (from [`load_words`] on `file`). Fails when the
/// file holds more than 2^32 points (point indices are 32-bit in the framebuffer).
pub fn batch_refs<'a>(file: &BatchFile, views: &'a [BatchView<'_>]) -> Result<Vec<BatchRef<'a>>> {
    if file.header.point_count > 1u64 << 32 {
        return Err(Error::Render {
            path: file.path.clone(),
            error: RenderError::TooManyToDraw { points: file.header.point_count },
        });
    }
    Ok(views
        .iter()
        .map(|v| {
            let e = v.entry;
            BatchRef {
                grid: e.grid(),
                bounds_min: [0, 1, 2].map(|a| e.world_min[a].min(e.world_max[a])),
                bounds_max: [0, 1, 2].map(|a| e.world_min[a].max(e.world_max[a])),
                words: [v.words(0), v.words(1), v.words(2)],
                first_index: e.first_point as u32,
            }
        })
        .collect())
}
