//! A dataset: the inputs of one command, merged onto one integer grid and one record layout.

use crate::error::{Error, Result};
use crate::las::{Header, Vlr};
use crate::source::{LasInput, Piece};
use mortar_core::grid::{self, Grid, GridInput, GridMap};
use mortar_core::layout::{merge_layouts, read_xyz, write_xyz, Conversion, RecordLayout};
use std::borrow::Cow;
use std::path::{Path, PathBuf};

/// Something that yields LAS records in pieces: a LAS/LAZ file, or a batch file read back.
pub trait RecordSource: Send + Sync {
    fn path(&self) -> &Path;
    fn header(&self) -> &Header;
    fn vlrs(&self) -> &[Vlr];
    fn evlrs(&self) -> &[Vlr];
    fn layout(&self) -> &RecordLayout;
    fn point_count(&self) -> u64;
    fn pieces(&self) -> Vec<Piece>;
    fn read_piece(&self, piece: &Piece) -> Result<Cow<'_, [u8]>>;
    /// Whether decoding a piece costs real work (LAZ, compressed batches), for progress and planning.
    fn is_compressed(&self) -> bool;
    /// Lets go of a piece's memory once it was processed (external sort).
    fn release_piece(&self, _piece: &Piece) {}
    /// Whether [`read_piece`](Self::read_piece) borrows without work (LAS in a memory map).
    fn borrows_pieces(&self) -> bool {
        false
    }
    /// Prepares to read everything soon (the in-memory sort).
    fn prefetch(&self) {}
    /// Reads a piece into `out`, which holds exactly `piece.points` records.
    fn read_piece_into(&self, piece: &Piece, out: &mut [u8]) -> Result<()> {
        let r = self.read_piece(piece)?;
        if r.len() != out.len() {
            return Err(Error::input(self.path(), format!("piece {} holds {} bytes, expected {}", piece.index, r.len(), out.len())));
        }
        out.copy_from_slice(&r);
        Ok(())
    }
}

impl RecordSource for LasInput {
    fn path(&self) -> &Path {
        &self.path
    }
    fn header(&self) -> &Header {
        &self.meta.header
    }
    fn vlrs(&self) -> &[Vlr] {
        &self.meta.vlrs
    }
    fn evlrs(&self) -> &[Vlr] {
        &self.meta.evlrs
    }
    fn layout(&self) -> &RecordLayout {
        &self.layout
    }
    fn point_count(&self) -> u64 {
        self.point_count
    }
    fn pieces(&self) -> Vec<Piece> {
        LasInput::pieces(self).to_vec()
    }
    fn read_piece(&self, piece: &Piece) -> Result<Cow<'_, [u8]>> {
        LasInput::read_piece(self, piece)
    }
    fn is_compressed(&self) -> bool {
        self.is_laz()
    }
    fn release_piece(&self, piece: &Piece) {
        LasInput::release_piece(self, piece)
    }
    fn borrows_pieces(&self) -> bool {
        !self.is_laz()
    }
    fn prefetch(&self) {
        LasInput::prefetch(self)
    }
    fn read_piece_into(&self, piece: &Piece, out: &mut [u8]) -> Result<()> {
        LasInput::read_piece_into(self, piece, out)
    }
}

/// What a writer needs of a dataset besides its points: the header fields to keep, the (E)VLRs,
/// the record layout and the integer grid. Both the LAS/LAZ writer and the batch writer take it.
#[derive(Clone, Debug)]
pub struct SourceMeta {
    pub header: Header,
    pub vlrs: Vec<Vlr>,
    pub evlrs: Vec<Vlr>,
    pub layout: RecordLayout,
    pub grid: Grid,
}

/// A piece of one input of a dataset.
#[derive(Clone, Copy, Debug)]
pub struct DatasetPiece {
    pub input: usize,
    pub piece: Piece,
}

/// The merged inputs.
pub struct Dataset {
    pub inputs: Vec<Box<dyn RecordSource>>,
    pub grid: Grid,
    pub maps: Vec<GridMap>,
    pub layout: RecordLayout,
    /// Per input, how its records become `layout` records (`None`: already are).
    pub conversions: Vec<Option<Conversion>>,
    /// Header fields (version, ids, software) taken from the first input.
    pub template: Header,
    pub vlrs: Vec<Vlr>,
    pub evlrs: Vec<Vlr>,
    /// Things the user should know (printed by the binary).
    pub warnings: Vec<String>,
}

impl Dataset {
    /// Merges opened inputs. Fails before any point is read when they cannot be merged exactly.
    pub fn new(inputs: Vec<Box<dyn RecordSource>>) -> Result<Dataset> {
        if inputs.is_empty() {
            return Err(Error::Usage("no input given".into()));
        }
        let first = &inputs[0];
        let mut warnings = Vec::new();
        let layouts: Vec<RecordLayout> = inputs.iter().map(|i| i.layout().clone()).collect();
        let (layout, conversions) = merge_layouts(&layouts).map_err(|e| {
            let odd = inputs.iter().find(|i| i.layout() != first.layout()).unwrap_or(first);
            Error::input(odd.path(), format!("{e} (this file has point format {}, {} has {})", odd.layout().format, first.path().display(), first.layout().format))
        })?;
        if conversions.iter().any(|c| c.is_some()) {
            warnings.push(format!(
                "inputs have point formats {}; merged into point format {} (missing fields are zero)",
                layouts.iter().map(|l| l.format.to_string()).collect::<Vec<_>>().join(", "),
                layout.format
            ));
        }
        let gin: Vec<GridInput> = inputs
            .iter()
            .map(|i| {
                let h = i.header();
                let g = Grid { scale: h.scale, offset: h.offset };
                let mut min = [0i64; 3];
                let mut max = [0i64; 3];
                for a in 0..3 {
                    let lo = g.to_int(a, h.min[a]);
                    let hi = g.to_int(a, h.max[a]);
                    // headers with garbage bounds: fall back to the whole i32 range for the check
                    let ok = h.min[a].is_finite() && h.max[a].is_finite() && lo <= hi;
                    min[a] = if ok { lo.clamp(i32::MIN as i64, i32::MAX as i64) } else { 0 };
                    max[a] = if ok { hi.clamp(i32::MIN as i64, i32::MAX as i64) } else { 0 };
                }
                GridInput { grid: g, min, max }
            })
            .collect();
        let (grid, maps) = grid::merge(&gin).map_err(|e| {
            let idx = match &e {
                grid::GridError::BadScale { index, .. }
                | grid::GridError::ScaleNotMultiple { index, .. }
                | grid::GridError::OffsetOffGrid { index, .. } => Some(*index),
                _ => None,
            };
            match idx {
                Some(i) => Error::input(inputs[i].path(), e.to_string()),
                None => Error::Usage(e.to_string()),
            }
        })?;
        if maps.iter().any(|m| !m.is_identity()) {
            warnings.push(format!(
                "inputs have different scales or offsets; merged exactly onto scale {:?}, offset {:?}",
                grid.scale, grid.offset
            ));
        }
        let template = first.header().clone();
        let vlrs = first.vlrs().to_vec();
        let evlrs = first.evlrs().to_vec();
        for i in &inputs[1..] {
            if i.vlrs().iter().filter(|v| is_crs(v)).ne(vlrs.iter().filter(|v| is_crs(v))) {
                warnings.push(format!(
                    "{}: its CRS records differ from those of {}; the output keeps the first input's",
                    i.path().display(),
                    first.path().display()
                ));
            }
        }
        Ok(Dataset { inputs, grid, maps, layout, conversions, template, vlrs, evlrs, warnings })
    }

    /// Opens LAS/LAZ files and batch files and merges them; warnings about each file come first.
    pub fn open(paths: &[PathBuf]) -> Result<Dataset> {
        let mut warnings = Vec::new();
        let mut inputs: Vec<Box<dyn RecordSource>> = Vec::new();
        for p in paths {
            if p != Path::new("-") && crate::store::is_store(p) {
                inputs.push(Box::new(crate::store::Store::open(p)?));
                continue;
            }
            if p != Path::new("-") && crate::batchfile::is_batch_file(p) {
                inputs.push(Box::new(crate::batchfile::BatchFile::open(p)?));
                continue;
            }
            let i = LasInput::open(p)?;
            warnings.extend(i.meta.warnings.iter().map(|w| format!("{}: {w}", p.display())));
            inputs.push(Box::new(i));
        }
        let mut ds = Dataset::new(inputs)?;
        warnings.append(&mut ds.warnings);
        ds.warnings = warnings;
        Ok(ds)
    }

    /// The metadata the writers need.
    pub fn source_meta(&self) -> SourceMeta {
        SourceMeta {
            header: self.template.clone(),
            vlrs: self.vlrs.clone(),
            evlrs: self.evlrs.clone(),
            layout: self.layout.clone(),
            grid: self.grid,
        }
    }

    /// Points the headers declare in total.
    pub fn declared_points(&self) -> u64 {
        self.inputs.iter().map(|i| i.point_count()).sum()
    }

    /// Every piece of every input, in input order.
    pub fn pieces(&self) -> Vec<DatasetPiece> {
        self.inputs
            .iter()
            .enumerate()
            .flat_map(|(i, s)| s.pieces().into_iter().map(move |p| DatasetPiece { input: i, piece: p }))
            .collect()
    }

    /// Whether reading a piece of input `i` needs a buffer (decoding, conversion or regridding).
    pub fn needs_buffer(&self, i: usize) -> bool {
        !self.inputs[i].borrows_pieces() || !self.maps[i].is_identity() || self.conversions[i].is_some()
    }

    fn regrid(&self, input: usize, records: &mut [u8]) -> Result<()> {
        let map = self.maps[input];
        if map.is_identity() {
            return Ok(());
        }
        for r in records.chunks_exact_mut(self.layout.record_len) {
            let xyz = map.apply(read_xyz(r)).ok_or_else(|| {
                Error::input(
                    self.inputs[input].path(),
                    "a point lies outside the bounds its header declares, beyond what the merged grid can hold",
                )
            })?;
            write_xyz(r, xyz);
        }
        Ok(())
    }

    /// Reads a piece into `out` (exactly its size in merged records), on the merged grid.
    pub fn read_piece_into(&self, p: &DatasetPiece, out: &mut [u8]) -> Result<()> {
        let src = &self.inputs[p.input];
        match &self.conversions[p.input] {
            None => src.read_piece_into(&p.piece, out)?,
            Some(c) => {
                let r = src.read_piece(&p.piece)?;
                let srl = src.layout().record_len;
                if r.len() / srl * c.target_len != out.len() {
                    return Err(Error::input(src.path(), format!("piece {} holds another number of points than declared", p.piece.index)));
                }
                c.apply(&r, srl, out);
            }
        }
        self.regrid(p.input, out)
    }

    /// The records of a piece, converted to the merged layout and grid.
    pub fn read_piece(&self, p: &DatasetPiece) -> Result<Cow<'_, [u8]>> {
        let src = &self.inputs[p.input];
        let records = src.read_piece(&p.piece)?;
        let mut owned = match &self.conversions[p.input] {
            None if self.maps[p.input].is_identity() => return Ok(records),
            None => records.into_owned(),
            Some(c) => {
                let srl = src.layout().record_len;
                let mut out = vec![0u8; records.len() / srl * c.target_len];
                c.apply(&records, srl, &mut out);
                out
            }
        };
        self.regrid(p.input, &mut owned)?;
        Ok(Cow::Owned(owned))
    }
}

/// Whether a VLR describes the coordinate reference system.
pub fn is_crs(v: &Vlr) -> bool {
    v.user_id_str() == "LASF_Projection"
}
