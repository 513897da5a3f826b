//! A dataset: the inputs of one command, merged onto one integer grid and one record layout.

use crate::crs::{epsg_records, AssignCrs, CrsRecords};
use crate::error::{Error, Result};
use crate::las::{Header, Vlr};
use crate::progress::Progress;
use crate::source::{LasInput, Piece};
use mortar_core::grid::{self, Grid, GridInput, GridMap};
use mortar_core::layout::{base_len, merge_layouts, read_xyz, write_xyz, Conversion, RecordLayout};
use std::borrow::Cow;
use std::path::Path;

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
    /// The inputs this source stands for in a store's build record, where it is not a file of
    /// its own: a store read in arrival order for `--append` stands for the inputs it was built
    /// from ([`crate::store::append`]).
    fn stands_for(&self) -> Option<&[InputPrint]> {
        None
    }
    /// The box the headers of the inputs this source stands for declared, on its own grid
    /// (`Some(None)`: none was usable), where it knows it better than its header: a store read
    /// for `--append` ([`crate::store::append`]).
    fn declared_box(&self) -> Option<Option<([i32; 3], [i32; 3])>> {
        None
    }
    /// Lets go of a piece's memory once it was processed (external sort).
    fn release_piece(&self, _piece: &Piece) {}
    /// Whether [`read_piece`](Self::read_piece) borrows without work (LAS in a memory map).
    fn borrows_pieces(&self) -> bool {
        false
    }
    /// Prepares to read everything soon (the in-memory sort).
    fn prefetch(&self) {}
    /// Reads a piece into `out`, which holds exactly `piece.points` records.
    /// Decodes only the named attributes of the source's layout (positions always); the bytes
    /// of the others read as zero. Sources that cannot skip fields decode everything.
    fn decode_only(&mut self, _attributes: &[&str]) {}
    fn read_piece_into(&self, piece: &Piece, out: &mut [u8]) -> Result<()> {
        let r = self.read_piece(piece)?;
        if r.len() != out.len() {
            return Err(Error::PieceSize {
                path: self.path().to_path_buf(),
                piece: piece.index,
                got: r.len(),
                expected: out.len(),
            });
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
    fn decode_only(&mut self, attributes: &[&str]) {
        LasInput::decode_only(self, attributes)
    }
}

/// One input as a store's build record knows it (`build.json`), and as a source that stands for
/// other inputs names them ([`RecordSource::stands_for`]).
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct InputPrint {
    /// Its path, absolute where it can be made so.
    pub path: String,
    /// Its size in bytes.
    pub bytes: u64,
    /// Its modification time, nanoseconds since the epoch.
    pub modified_ns: u128,
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
    /// Counts the points read (every `read_piece*` adds its piece); jobs name the stages.
    pub progress: Progress,
}

impl Dataset {
    /// Merges opened inputs. Fails before any point is read when they cannot be merged exactly.
    pub fn new(inputs: Vec<Box<dyn RecordSource>>) -> Result<Dataset> {
        Self::with_options(inputs, &OpenOptions::default())
    }

    /// [`new`](Self::new) with the user's choices (the CRS to assign).
    pub fn with_options(inputs: Vec<Box<dyn RecordSource>>, opts: &OpenOptions) -> Result<Dataset> {
        if inputs.is_empty() {
            return Err(Error::NoInput);
        }
        let first = &inputs[0];
        let mut warnings = Vec::new();
        let layouts: Vec<RecordLayout> = inputs.iter().map(|i| i.layout().clone()).collect();
        let (layout, conversions) = merge_layouts(&layouts).map_err(|e| {
            let odd = inputs.iter().find(|i| i.layout() != first.layout()).unwrap_or(first);
            Error::FormatsDiffer {
                path: odd.path().to_path_buf(),
                problem: e,
                format: odd.layout().format,
                first: first.path().to_path_buf(),
                first_format: first.layout().format,
            }
        })?;
        if conversions.iter().any(|c| c.is_some()) {
            warnings.push(format!(
                "inputs have point formats {}; merged into point format {} (missing fields are zero; legacy fields mapped as docs/formats.md says)",
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
                Some(i) => {
                    Error::IncompatibleGrid { path: inputs[i].path().to_path_buf(), error: e }
                }
                None => Error::Grid { error: e },
            }
        })?;
        if maps.iter().any(|m| !m.is_identity()) {
            warnings.push(format!(
                "inputs have different scales or offsets; merged exactly onto scale {:?}, offset {:?}",
                grid.scale, grid.offset
            ));
        }
        // The template header (version, ids, software, non-CRS VLRs): the first input whose
        // format family the merged layout has, so that a LAS 1.4 result gets a LAS 1.4 header.
        let t = inputs.iter().position(|i| i.layout().family() == layout.family()).unwrap_or(0);
        let tin = &inputs[t];
        let mut template = tin.header().clone();
        template.point_format = layout.format;
        template.record_len = layout.record_len as u16;
        check_extra_bytes(
            &inputs,
            layout.record_len - base_len(layout.format).unwrap_or(layout.record_len),
        )?;
        check_gps_time_kind(&inputs, &layout, &mut warnings);
        let crs = choose_crs(&inputs, opts, &mut warnings)?;
        let (mut vlrs, mut evlrs) = (tin.vlrs().to_vec(), tin.evlrs().to_vec());
        let mut dropped = Vec::new();
        for i in &inputs {
            for (v, ext) in
                i.vlrs().iter().map(|v| (v, false)).chain(i.evlrs().iter().map(|v| (v, true)))
            {
                if let Some(why) = offset_dependent(v) {
                    let d = format!(
                        "{}{} {} ({why})",
                        if ext { "EVLR " } else { "VLR " },
                        v.user_id_str(),
                        v.record_id
                    );
                    if !dropped.contains(&d) {
                        dropped.push(d);
                    }
                }
            }
        }
        // The template input's own CRS records stay where they are; others replace them.
        let own = crs.as_ref().is_some_and(|c| *c == CrsRecords::of(tin.vlrs(), tin.evlrs()));
        vlrs.retain(|v| offset_dependent(v).is_none() && (own || !crate::crs::is_crs_record(v)));
        evlrs.retain(|v| offset_dependent(v).is_none() && (own || !crate::crs::is_crs_record(v)));
        if !dropped.is_empty() {
            warnings.push(format!(
                "dropped records that point into the input's byte layout and would be wrong in the output (docs/formats.md): {}",
                dropped.join(", ")
            ));
        }
        // The header's waveform pointer is a byte offset: writers set it where they put the
        // waveform data EVLR; internal waveform data that is not an EVLR (LAS 1.3) is not carried.
        template.waveform_start = 0;
        if template.global_encoding & 0x2 != 0 && !evlrs.iter().any(is_waveform_data) {
            template.global_encoding &= !0x2;
            warnings.push(format!(
                "{}: its waveform data is internal but not an EVLR mortar can carry; the output's waveform packets point nowhere",
                tin.path().display()
            ));
        }
        match &crs {
            Some(c) if !own => {
                vlrs.extend(c.vlrs.iter().cloned());
                if template.version.1 >= 4 {
                    evlrs.extend(c.evlrs.iter().cloned());
                } else {
                    vlrs.extend(
                        c.evlrs.iter().filter(|v| v.data.len() <= u16::MAX as usize).cloned(),
                    );
                }
                if c.has_wkt() {
                    template.global_encoding |= 0x10;
                } else {
                    template.global_encoding &= !0x10;
                }
            }
            _ => {}
        }
        let converted = conversions.iter().flatten().any(|c| c.legacy_to_extended);
        if layout.format >= 6 && crs.as_ref().is_some_and(|c| !c.has_wkt()) && (converted || !own) {
            warnings.push(
                "the output's CRS is GeoTIFF keys, but LAS 1.4 point formats 6-10 ask for WKT (readers may ignore the keys; give --assign-crs a LAS file with WKT)".into(),
            );
        }
        Ok(Dataset {
            inputs,
            grid,
            maps,
            layout,
            conversions,
            template,
            vlrs,
            evlrs,
            warnings,
            progress: Progress::new(),
        })
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

    /// A warning when the points' return counts (`counted`, return 1 first) differ from the sum
    /// of what the inputs' headers declare; `None` when they agree or no header declares any.
    /// Headers before LAS 1.4 declare returns 1-5 only, so only those are compared then.
    pub fn points_by_return_disagreement(&self, counted: &[u64; 15]) -> Option<String> {
        let mut declared = [0u64; 15];
        for i in &self.inputs {
            for (d, c) in declared.iter_mut().zip(i.header().points_by_return) {
                *d += c;
            }
        }
        if declared.iter().all(|&d| d == 0) {
            return None;
        }
        let n = if self.inputs.iter().any(|i| i.header().version.1 < 4) { 5 } else { 15 };
        if declared[..n] == counted[..n] {
            return None;
        }
        let show = |v: &[u64]| {
            let last = v.iter().rposition(|&c| c > 0).map_or(1, |p| p + 1);
            v[..last].iter().map(|c| c.to_string()).collect::<Vec<_>>().join(" ")
        };
        Some(format!(
            "the input header{} declare{} points by return {} but the points have {}; the output's header has the counted ones",
            if self.inputs.len() > 1 { "s" } else { "" },
            if self.inputs.len() > 1 { "" } else { "s" },
            show(&declared[..n]),
            show(&counted[..n])
        ))
    }

    /// Decodes only these attributes of the merged layout (names as in
    /// [`RecordLayout::attributes`]; positions always), for jobs that use only some of them:
    /// LAS 1.4 layered LAZ (point formats 6 to 10) then skips the other layers, whose bytes read
    /// as zero. Other inputs still deliver every byte (a mapped LAS file is not copied to clear
    /// them), so a job that calls this must not look at the other attributes. Call it before
    /// reading.
    pub fn decode_only(&mut self, attributes: &[&str]) {
        for s in &mut self.inputs {
            s.decode_only(attributes);
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
            .flat_map(|(i, s)| {
                s.pieces().into_iter().map(move |p| DatasetPiece { input: i, piece: p })
            })
            .collect()
    }

    /// Whether reading a piece of input `i` needs a buffer (decoding, conversion or regridding).
    pub fn needs_buffer(&self, i: usize) -> bool {
        !self.inputs[i].borrows_pieces()
            || !self.maps[i].is_identity()
            || self.conversions[i].is_some()
    }

    fn regrid(&self, input: usize, records: &mut [u8]) -> Result<()> {
        let map = self.maps[input];
        if map.is_identity() {
            return Ok(());
        }
        for r in records.chunks_exact_mut(self.layout.record_len) {
            let xyz = map.apply(read_xyz(r)).ok_or_else(|| Error::OutsideGrid {
                path: self.inputs[input].path().to_path_buf(),
            })?;
            write_xyz(r, xyz);
        }
        Ok(())
    }

    /// Reads a piece into `out` (exactly its size in merged records), on the merged grid.
    pub fn read_piece_into(&self, p: &DatasetPiece, out: &mut [u8]) -> Result<()> {
        self.progress.add(p.piece.points);
        let src = &self.inputs[p.input];
        match &self.conversions[p.input] {
            None => src.read_piece_into(&p.piece, out)?,
            Some(c) => {
                let r = src.read_piece(&p.piece)?;
                let srl = src.layout().record_len;
                if r.len() / srl * c.target_len != out.len() {
                    return Err(Error::PieceCount {
                        path: src.path().to_path_buf(),
                        piece: p.piece.index,
                    });
                }
                c.apply(&r, srl, out);
            }
        }
        self.regrid(p.input, out)
    }

    /// The records of a piece, converted to the merged layout and grid.
    pub fn read_piece(&self, p: &DatasetPiece) -> Result<Cow<'_, [u8]>> {
        self.progress.add(p.piece.points);
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
    crate::crs::is_crs_record(v)
}

/// The user's choices when inputs are merged.
#[derive(Clone, Debug, Default)]
pub struct OpenOptions {
    /// The CRS of the output whatever the inputs say (`--assign-crs`).
    pub assign_crs: Option<AssignCrs>,
}

/// Whether a VLR/EVLR is the waveform data packets record (`LASF_Spec` 65535).
pub fn is_waveform_data(v: &Vlr) -> bool {
    v.user_id_str() == "LASF_Spec" && v.record_id == 65535
}

/// Why a VLR/EVLR cannot be copied into an output that mortar writes (its points reordered and
/// re-encoded, its records at other byte offsets), or `None` if it can (docs/formats.md):
/// - `copc` (every record id: 1 info, 1000 hierarchy, ...): byte offsets and point counts of
///   the COPC chunks; a copy would make the output claim to be COPC with a hierarchy pointing
///   into the middle of its point data;
/// - `LAStools` 30 (the spatial index of a `.lax` file stored in the LAS file): intervals of
///   point indices in the original point order;
/// - `laszip encoded` 22204: describes the input's compression (writers add their own).
///
/// Kept: CRS records, extra bytes descriptions, LAStools' tiling (10) and original-header (20)
/// records (no offsets), waveform packet descriptors (`LASF_Spec`
/// 100-354: sampling parameters), and the waveform data EVLR (`LASF_Spec` 65535): the points'
/// waveform offsets are relative to that record, so a byte-for-byte copy stays valid and the
/// writers point the header at it.
pub fn offset_dependent(v: &Vlr) -> Option<&'static str> {
    match (v.user_id_str().as_str(), v.record_id) {
        ("copc", 1) => Some("COPC info"),
        ("copc", 1000) => Some("COPC hierarchy"),
        ("copc", _) => Some("COPC"),
        ("LAStools", 30) => Some("LAStools spatial index"),
        ("laszip encoded", 22204) => Some("LASzip compression of the input"),
        _ => None,
    }
}

/// Refuses inputs whose extra bytes are described differently (the merged records keep one
/// description: the extra bytes VLR `LASF_Spec` 4 of the first input that has one).
fn check_extra_bytes(inputs: &[Box<dyn RecordSource>], extra: usize) -> Result<()> {
    if extra == 0 || inputs.len() < 2 {
        return Ok(());
    }
    let desc = |i: &dyn RecordSource| {
        i.vlrs()
            .iter()
            .find(|v| v.user_id_str() == "LASF_Spec" && v.record_id == 4)
            .map(|v| v.data.clone())
    };
    let first = desc(inputs[0].as_ref());
    for i in &inputs[1..] {
        if desc(i.as_ref()) != first {
            return Err(Error::ExtraBytesDiffer {
                path: i.path().to_path_buf(),
                extra,
                first: inputs[0].path().to_path_buf(),
            });
        }
    }
    Ok(())
}

/// Warns when inputs with GPS time disagree on its kind (global encoding bit 0: GPS week time
/// or adjusted standard GPS time): the merged values are then not comparable.
fn check_gps_time_kind(
    inputs: &[Box<dyn RecordSource>],
    layout: &RecordLayout,
    warnings: &mut Vec<String>,
) {
    if !layout.has_gps_time() {
        return;
    }
    let with: Vec<&Box<dyn RecordSource>> =
        inputs.iter().filter(|i| i.layout().has_gps_time()).collect();
    if let Some(odd) = with
        .iter()
        .find(|i| (i.header().global_encoding & 1) != (with[0].header().global_encoding & 1))
    {
        warnings.push(format!(
            "{} has {} but {} has {}; the merged GPS times mix both",
            with[0].path().display(),
            gps_kind(with[0].header().global_encoding),
            odd.path().display(),
            gps_kind(odd.header().global_encoding)
        ));
    }
}

fn gps_kind(global_encoding: u16) -> &'static str {
    if global_encoding & 1 != 0 {
        "adjusted standard GPS time"
    } else {
        "GPS week time"
    }
}

/// The CRS records of the output: the assigned one, else the one CRS the inputs agree on.
/// Inputs whose CRSs disagree are refused (naming two of them); inputs without a CRS beside
/// inputs with one take that CRS with a warning.
fn choose_crs(
    inputs: &[Box<dyn RecordSource>],
    opts: &OpenOptions,
    warnings: &mut Vec<String>,
) -> Result<Option<CrsRecords>> {
    match &opts.assign_crs {
        Some(AssignCrs::File(p)) => {
            let f = LasInput::open(p).map_err(|e| match e {
                e @ Error::Io { .. } => e,
                e => Error::AssignCrsFile { error: Box::new(e) },
            })?;
            let c = CrsRecords::of(&f.meta.vlrs, &f.meta.evlrs);
            if c.is_empty() {
                return Err(Error::AssignCrsNoRecords { path: p.clone() });
            }
            return Ok(Some(c));
        }
        Some(AssignCrs::Epsg { horizontal, vertical }) => {
            return epsg_records(*horizontal, *vertical)
                .map(Some)
                .map_err(|error| Error::AssignCrsCode { error });
        }
        None => {}
    }
    let all: Vec<CrsRecords> = inputs.iter().map(|i| CrsRecords::of(i.vlrs(), i.evlrs())).collect();
    let Some(k) = all.iter().position(|c| !c.is_empty()) else {
        return Ok(None);
    };
    for (j, c) in all.iter().enumerate() {
        if !c.is_empty() && !c.agrees_with(&all[k]) {
            return Err(Error::CrsConflict {
                path: inputs[j].path().to_path_buf(),
                crs: c.describe().summary(),
                first: inputs[k].path().to_path_buf(),
                first_crs: all[k].describe().summary(),
            });
        }
    }
    let without: Vec<usize> = (0..inputs.len()).filter(|&j| all[j].is_empty()).collect();
    if let Some(&j) = without.first() {
        warnings.push(format!(
            "{}{} no CRS; the output takes that of {}, {}",
            inputs[j].path().display(),
            if without.len() > 1 {
                format!(" and {} other inputs have", without.len() - 1)
            } else {
                " has".into()
            },
            inputs[k].path().display(),
            all[k].describe().summary()
        ));
    }
    Ok(Some(all[k].clone()))
}
