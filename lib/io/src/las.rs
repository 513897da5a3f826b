//! LAS headers, VLRs and EVLRs (ASPRS LAS 1.0-1.4): parsing from bytes and writing.
//!
//! Everything is read from a byte slice (a memory map or a buffer) with bounds checks, never by
//! allocating what a header claims: a VLR count is followed only as far as the VLRs fit before the
//! point data, and every length is checked against the bytes that exist.

/// Size of the standard header of each minor version.
pub fn standard_header_size(minor: u8) -> usize {
    match minor {
        0..=2 => 227,
        3 => 235,
        _ => 375,
    }
}

/// A variable length record (VLR) or extended VLR (EVLR), kept byte for byte.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Vlr {
    pub reserved: u16,
    pub user_id: [u8; 16],
    pub record_id: u16,
    pub description: [u8; 32],
    pub data: Vec<u8>,
}

impl Vlr {
    /// The user id without trailing NULs, lossily as text.
    pub fn user_id_str(&self) -> String {
        c_str(&self.user_id)
    }
    pub fn description_str(&self) -> String {
        c_str(&self.description)
    }
    pub fn is_laszip(&self) -> bool {
        self.user_id_str() == "laszip encoded" && self.record_id == 22204
    }
    pub fn is_copc(&self) -> bool {
        self.user_id_str() == "copc"
    }
}

/// Text of a fixed-size NUL-padded field.
pub fn c_str(b: &[u8]) -> String {
    let end = b.iter().position(|&c| c == 0).unwrap_or(b.len());
    String::from_utf8_lossy(&b[..end]).trim_end().to_string()
}

/// The public header block, every field kept.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    pub version: (u8, u8),
    pub file_source_id: u16,
    pub global_encoding: u16,
    pub guid: [u8; 16],
    pub system_identifier: [u8; 32],
    pub generating_software: [u8; 32],
    pub creation_day: u16,
    pub creation_year: u16,
    pub header_size: u16,
    pub offset_to_point_data: u32,
    pub number_of_vlrs: u32,
    /// Point data record format, 0-10, without the LAZ compression bits.
    pub point_format: u8,
    /// Whether the format byte carried the LAZ compression bit.
    pub compressed: bool,
    pub record_len: u16,
    pub point_count: u64,
    pub points_by_return: [u64; 15],
    pub scale: [f64; 3],
    pub offset: [f64; 3],
    pub min: [f64; 3],
    pub max: [f64; 3],
    pub waveform_start: u64,
    pub evlr_start: u64,
    pub evlr_count: u32,
    /// Bytes between the standard header and `header_size` (user-defined header data).
    pub extra_header: Vec<u8>,
}

fn u16_at(b: &[u8], o: usize) -> u16 {
    u16::from_le_bytes([b[o], b[o + 1]])
}
fn u32_at(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes(b[o..o + 4].try_into().unwrap())
}
fn u64_at(b: &[u8], o: usize) -> u64 {
    u64::from_le_bytes(b[o..o + 8].try_into().unwrap())
}
fn f64_at(b: &[u8], o: usize) -> f64 {
    f64::from_le_bytes(b[o..o + 8].try_into().unwrap())
}

/// Why LAS front matter (header, VLRs, EVLRs) cannot be read or written.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LasError {
    /// The file does not start with `LASF`.
    #[error("not a LAS/LAZ file (no LASF signature)")]
    NoSignature,
    /// The file is shorter than the smallest LAS header.
    #[error("file is {len} bytes, shorter than a LAS header (227)")]
    TooShort { len: usize },
    /// A version other than LAS 1.0 to 1.4.
    #[error("unsupported LAS version {major}.{minor}")]
    Version { major: u8, minor: u8 },
    /// The header size is below the standard header of its version.
    #[error("header size {header_size} is smaller than the {standard} bytes of LAS 1.{minor}")]
    HeaderTooSmall { header_size: u16, standard: usize, minor: u8 },
    /// The header size is beyond the end of the file.
    #[error("header size {header_size} is larger than the file ({len} bytes)")]
    HeaderTooLarge { header_size: u16, len: usize },
    /// The offset to the point data lies inside the header.
    #[error("offset to point data {offset} lies inside the header ({header_size} bytes)")]
    PointDataInHeader { offset: u32, header_size: u16 },
    /// The offset to the point data is beyond the end of the file.
    #[error("offset to point data {offset} is beyond the end of the file ({len} bytes)")]
    PointDataBeyondEnd { offset: u32, len: usize },
    /// A scale factor is zero, negative or not finite.
    #[error("scale factor {scale} on axis {axis} is not a positive number")]
    BadScale { scale: f64, axis: char },
    /// An offset is not finite.
    #[error("offset {offset} on axis {axis} is not a finite number")]
    BadOffset { offset: f64, axis: char },
    /// The EVLRs start outside the file's data.
    #[error("EVLRs start at byte {start}, outside the file's data ({len} bytes)")]
    EvlrsOutside { start: u64, len: usize },
    /// The file ends before the EVLRs the header declares.
    #[error("header says {declared} EVLRs but the file ends after {found}")]
    EvlrCount { declared: u32, found: u32 },
    /// One EVLR is damaged.
    #[error("EVLR {index}: {error}")]
    Evlr { index: u32, error: Box<LasError> },
    /// An EVLR's header is cut off.
    #[error("truncated EVLR header")]
    EvlrHeaderTruncated,
    /// An EVLR claims more bytes than the file holds.
    #[error("claims {len} bytes, more than the file holds")]
    EvlrTooLong { len: u64 },
    /// The VLRs do not fit the 32-bit offset to the point data.
    #[error("VLRs too large for a LAS header")]
    VlrsTooLarge,
    /// More points than a LAS 1.0-1.3 header can count.
    #[error("{count} points do not fit a LAS 1.{minor} header (at most 4,294,967,295)")]
    TooManyPoints { count: u64, minor: u8 },
    /// A point format of LAS 1.4 in an older header.
    #[error("point format {format} needs LAS 1.4")]
    FormatNeedsLas14 { format: u8 },
    /// A VLR payload larger than a VLR (65,535 bytes) can hold.
    #[error("VLR {user_id} {record_id} is too large for a LAS VLR")]
    VlrTooLarge { user_id: String, record_id: u16 },
}

/// The parsed front matter of a LAS/LAZ file.
#[derive(Clone, Debug)]
pub struct LasMeta {
    pub header: Header,
    pub vlrs: Vec<Vlr>,
    pub evlrs: Vec<Vlr>,
    /// Problems that did not stop reading (printed as warnings by the binary).
    pub warnings: Vec<String>,
}

const VLR_HEADER: usize = 54;
const EVLR_HEADER: usize = 60;

/// Parses the header, VLRs and EVLRs of a LAS/LAZ file held in `b`.
pub fn parse(b: &[u8]) -> Result<LasMeta, LasError> {
    if b.len() < 4 || &b[0..4] != b"LASF" {
        return Err(LasError::NoSignature);
    }
    if b.len() < 227 {
        return Err(LasError::TooShort { len: b.len() });
    }
    let major = b[24];
    let minor = b[25];
    if major != 1 || minor > 4 {
        return Err(LasError::Version { major, minor });
    }
    let header_size = u16_at(b, 94);
    let std = standard_header_size(minor);
    if (header_size as usize) < std {
        return Err(LasError::HeaderTooSmall { header_size, standard: std, minor });
    }
    if header_size as usize > b.len() {
        return Err(LasError::HeaderTooLarge { header_size, len: b.len() });
    }
    let offset_to_point_data = u32_at(b, 96);
    if (offset_to_point_data as u64) < header_size as u64 {
        return Err(LasError::PointDataInHeader { offset: offset_to_point_data, header_size });
    }
    if offset_to_point_data as u64 > b.len() as u64 {
        return Err(LasError::PointDataBeyondEnd { offset: offset_to_point_data, len: b.len() });
    }
    let format_byte = b[104];
    let mut warnings = Vec::new();
    let mut points_by_return = [0u64; 15];
    for (i, p) in points_by_return.iter_mut().take(5).enumerate() {
        *p = u32_at(b, 111 + 4 * i) as u64;
    }
    let mut header = Header {
        version: (major, minor),
        file_source_id: u16_at(b, 4),
        global_encoding: u16_at(b, 6),
        guid: b[8..24].try_into().unwrap(),
        system_identifier: b[26..58].try_into().unwrap(),
        generating_software: b[58..90].try_into().unwrap(),
        creation_day: u16_at(b, 90),
        creation_year: u16_at(b, 92),
        header_size,
        offset_to_point_data,
        number_of_vlrs: u32_at(b, 100),
        point_format: format_byte & 0x3f,
        compressed: format_byte & 0x80 != 0,
        record_len: u16_at(b, 105),
        point_count: u32_at(b, 107) as u64,
        points_by_return,
        scale: [f64_at(b, 131), f64_at(b, 139), f64_at(b, 147)],
        offset: [f64_at(b, 155), f64_at(b, 163), f64_at(b, 171)],
        max: [f64_at(b, 179), f64_at(b, 195), f64_at(b, 211)],
        min: [f64_at(b, 187), f64_at(b, 203), f64_at(b, 219)],
        waveform_start: 0,
        evlr_start: 0,
        evlr_count: 0,
        extra_header: b[std..header_size as usize].to_vec(),
    };
    if minor >= 3 {
        header.waveform_start = u64_at(b, 227);
    }
    if minor >= 4 {
        header.evlr_start = u64_at(b, 235);
        header.evlr_count = u32_at(b, 243);
        let count14 = u64_at(b, 247);
        if count14 != 0 || header.point_format >= 6 {
            if header.point_count != 0 && header.point_count != count14 {
                warnings.push(format!(
                    "legacy point count {} disagrees with the LAS 1.4 count {count14}; using the latter",
                    header.point_count
                ));
            }
            header.point_count = count14;
        }
        for (i, p) in header.points_by_return.iter_mut().enumerate() {
            *p = u64_at(b, 255 + 8 * i);
        }
    }
    for a in 0..3 {
        let s = header.scale[a];
        if !(s.is_finite() && s > 0.0) {
            return Err(LasError::BadScale { scale: s, axis: ['x', 'y', 'z'][a] });
        }
        if !header.offset[a].is_finite() {
            return Err(LasError::BadOffset { offset: header.offset[a], axis: ['x', 'y', 'z'][a] });
        }
    }

    // VLRs: follow the count only while whole VLRs fit before the point data.
    let mut vlrs = Vec::new();
    let mut pos = header_size as usize;
    let end = offset_to_point_data as usize;
    for i in 0..header.number_of_vlrs {
        if pos + VLR_HEADER > end {
            warnings.push(format!(
                "header says {} VLRs but only {i} fit before the point data; ignoring the rest",
                header.number_of_vlrs
            ));
            break;
        }
        let len = u16_at(b, pos + 20) as usize;
        if pos + VLR_HEADER + len > end {
            warnings.push(format!(
                "VLR {i} claims {len} bytes, more than remain before the point data; ignoring it and any after it"
            ));
            break;
        }
        vlrs.push(Vlr {
            reserved: u16_at(b, pos),
            user_id: b[pos + 2..pos + 18].try_into().unwrap(),
            record_id: u16_at(b, pos + 18),
            description: b[pos + 22..pos + 54].try_into().unwrap(),
            data: b[pos + VLR_HEADER..pos + VLR_HEADER + len].to_vec(),
        });
        pos += VLR_HEADER + len;
    }

    let mut evlrs = Vec::new();
    if header.evlr_count > 0 && header.evlr_start > 0 {
        let mut pos = header.evlr_start;
        if pos < offset_to_point_data as u64 || pos > b.len() as u64 {
            return Err(LasError::EvlrsOutside { start: pos, len: b.len() });
        }
        for i in 0..header.evlr_count {
            if pos + EVLR_HEADER as u64 > b.len() as u64 {
                return Err(LasError::EvlrCount { declared: header.evlr_count, found: i });
            }
            let (v, next) = parse_evlr(b, pos as usize)
                .map_err(|e| LasError::Evlr { index: i, error: Box::new(e) })?;
            evlrs.push(v);
            pos = next as u64;
        }
    }
    Ok(LasMeta { header, vlrs, evlrs, warnings })
}

/// Parses the EVLR starting at byte `at` of `b`; returns it and the position after it.
pub fn parse_evlr(b: &[u8], at: usize) -> Result<(Vlr, usize), LasError> {
    if at.checked_add(EVLR_HEADER).is_none_or(|e| e > b.len()) {
        return Err(LasError::EvlrHeaderTruncated);
    }
    let len = u64_at(b, at + 20);
    let end = (at as u64 + EVLR_HEADER as u64)
        .checked_add(len)
        .filter(|&e| e <= b.len() as u64)
        .ok_or(LasError::EvlrTooLong { len })? as usize;
    let v = Vlr {
        reserved: u16_at(b, at),
        user_id: b[at + 2..at + 18].try_into().unwrap(),
        record_id: u16_at(b, at + 18),
        description: b[at + 28..at + 60].try_into().unwrap(),
        data: b[at + EVLR_HEADER..end].to_vec(),
    };
    Ok((v, end))
}

/// What a writer needs to put a header in front of points.
#[derive(Clone, Debug)]
pub struct HeaderOut<'a> {
    pub template: &'a Header,
    pub point_format: u8,
    pub compressed: bool,
    pub record_len: u16,
    pub point_count: u64,
    pub points_by_return: [u64; 15],
    pub scale: [f64; 3],
    pub offset: [f64; 3],
    pub min: [f64; 3],
    pub max: [f64; 3],
    pub vlrs: &'a [Vlr],
    /// Start of the EVLRs (0 if none), known only after the points are written.
    pub evlr_start: u64,
    pub evlr_count: u32,
}

/// Bytes of all VLRs as written.
pub fn vlrs_len(vlrs: &[Vlr]) -> usize {
    vlrs.iter().map(|v| VLR_HEADER + v.data.len()).sum()
}

/// Serializes header and VLRs; the point data starts right after the returned bytes.
pub fn write_header(h: &HeaderOut) -> Result<Vec<u8>, LasError> {
    let t = h.template;
    let minor = t.version.1;
    let std = standard_header_size(minor);
    let header_size = std + t.extra_header.len();
    let offset_to_point_data = header_size + vlrs_len(h.vlrs);
    if offset_to_point_data > u32::MAX as usize {
        return Err(LasError::VlrsTooLarge);
    }
    if minor < 4 && (h.point_count > u32::MAX as u64) {
        return Err(LasError::TooManyPoints { count: h.point_count, minor });
    }
    if minor < 4 && h.point_format > 5 {
        return Err(LasError::FormatNeedsLas14 { format: h.point_format });
    }
    let mut b = Vec::with_capacity(offset_to_point_data);
    b.extend_from_slice(b"LASF");
    b.extend_from_slice(&t.file_source_id.to_le_bytes());
    b.extend_from_slice(&t.global_encoding.to_le_bytes());
    b.extend_from_slice(&t.guid);
    b.push(t.version.0);
    b.push(minor);
    b.extend_from_slice(&t.system_identifier);
    b.extend_from_slice(&t.generating_software);
    b.extend_from_slice(&t.creation_day.to_le_bytes());
    b.extend_from_slice(&t.creation_year.to_le_bytes());
    b.extend_from_slice(&(header_size as u16).to_le_bytes());
    b.extend_from_slice(&(offset_to_point_data as u32).to_le_bytes());
    b.extend_from_slice(&(h.vlrs.len() as u32).to_le_bytes());
    let mut fmt = h.point_format;
    if h.compressed {
        fmt |= 0x80;
    }
    b.push(fmt);
    b.extend_from_slice(&h.record_len.to_le_bytes());
    let legacy_ok = h.point_format < 6 && h.point_count <= u32::MAX as u64;
    let legacy_count = if legacy_ok { h.point_count as u32 } else { 0 };
    b.extend_from_slice(&legacy_count.to_le_bytes());
    for i in 0..5 {
        let v = h.points_by_return[i];
        let v = if legacy_ok && v <= u32::MAX as u64 { v as u32 } else { 0 };
        b.extend_from_slice(&v.to_le_bytes());
    }
    for v in h.scale.iter().chain(&h.offset) {
        b.extend_from_slice(&v.to_le_bytes());
    }
    for a in 0..3 {
        b.extend_from_slice(&h.max[a].to_le_bytes());
        b.extend_from_slice(&h.min[a].to_le_bytes());
    }
    if minor >= 3 {
        b.extend_from_slice(&t.waveform_start.to_le_bytes());
    }
    if minor >= 4 {
        b.extend_from_slice(&h.evlr_start.to_le_bytes());
        b.extend_from_slice(&h.evlr_count.to_le_bytes());
        b.extend_from_slice(&h.point_count.to_le_bytes());
        for v in h.points_by_return {
            b.extend_from_slice(&v.to_le_bytes());
        }
    }
    debug_assert_eq!(b.len(), std);
    b.extend_from_slice(&t.extra_header);
    for v in h.vlrs {
        if v.data.len() > u16::MAX as usize {
            return Err(LasError::VlrTooLarge { user_id: v.user_id_str(), record_id: v.record_id });
        }
        b.extend_from_slice(&v.reserved.to_le_bytes());
        b.extend_from_slice(&v.user_id);
        b.extend_from_slice(&v.record_id.to_le_bytes());
        b.extend_from_slice(&(v.data.len() as u16).to_le_bytes());
        b.extend_from_slice(&v.description);
        b.extend_from_slice(&v.data);
    }
    Ok(b)
}

/// Serializes EVLRs.
pub fn write_evlrs(evlrs: &[Vlr]) -> Vec<u8> {
    let mut b = Vec::new();
    for v in evlrs {
        b.extend_from_slice(&v.reserved.to_le_bytes());
        b.extend_from_slice(&v.user_id);
        b.extend_from_slice(&v.record_id.to_le_bytes());
        b.extend_from_slice(&(v.data.len() as u64).to_le_bytes());
        b.extend_from_slice(&v.description);
        b.extend_from_slice(&v.data);
    }
    b
}
