//! The byte layout of LAS point records (ASPRS LAS 1.4 R15, §2.6-2.16), point data record formats
//! (PDRF) 0 to 10, plus trailing extra bytes.
//!
//! mortar moves points as raw records: it reads X, Y, Z as `i32` at offsets 0, 4, 8 and treats
//! everything else as named byte ranges ([`Attribute`]). A record can therefore be taken apart into
//! columns and put back together bit for bit, whatever its format, and no per-point `las::Point` is
//! ever built.

/// Bytes of the X, Y, Z integers at the start of every record.
pub const XYZ_BYTES: usize = 12;

/// One named byte range of a record, other than X/Y/Z.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Attribute {
    /// Stable name, used on the command line (`--attributes`), in `info --json` and in batch files.
    pub name: String,
    /// Byte offset within the record.
    pub offset: usize,
    /// Width in bytes.
    pub width: usize,
}

/// Which family of point formats: the legacy formats 0-5 or the LAS 1.4 formats 6-10.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Family {
    Legacy,
    Extended,
}

/// The layout of one point data record format with its extra bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RecordLayout {
    /// Point data record format, 0-10.
    pub format: u8,
    /// Full record length including extra bytes.
    pub record_len: usize,
    /// The named byte ranges, in record order, covering every byte after X/Y/Z.
    pub attributes: Vec<Attribute>,
}

/// Error for a record format mortar cannot lay out.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum LayoutError {
    #[error("point data record format {0} is not defined (LAS knows 0 to 10)")]
    UnknownFormat(u8),
    #[error(
        "point record length {len} is shorter than the {min} bytes point format {format} needs"
    )]
    RecordTooShort { format: u8, len: usize, min: usize },
}

/// Base record length of each format, without extra bytes.
pub fn base_len(format: u8) -> Option<usize> {
    Some(match format {
        0 => 20,
        1 => 28,
        2 => 26,
        3 => 34,
        4 => 57,
        5 => 63,
        6 => 30,
        7 => 36,
        8 => 38,
        9 => 59,
        10 => 67,
        _ => return None,
    })
}

impl RecordLayout {
    /// The layout of `format` with records of `record_len` bytes (the rest are extra bytes).
    pub fn new(format: u8, record_len: usize) -> Result<RecordLayout, LayoutError> {
        let base = base_len(format).ok_or(LayoutError::UnknownFormat(format))?;
        if record_len < base {
            return Err(LayoutError::RecordTooShort { format, len: record_len, min: base });
        }
        let mut attrs: Vec<(&str, usize, usize)> = Vec::new();
        if format <= 5 {
            attrs.extend([
                ("intensity", 12, 2),
                ("flags", 14, 1),
                ("classification", 15, 1),
                ("scan_angle", 16, 1),
                ("user_data", 17, 1),
                ("point_source_id", 18, 2),
            ]);
            if matches!(format, 1 | 3 | 4 | 5) {
                attrs.push(("gps_time", 20, 8));
            }
            match format {
                2 => attrs.push(("rgb", 20, 6)),
                3 | 5 => attrs.push(("rgb", 28, 6)),
                _ => {}
            }
            match format {
                4 => attrs.push(("wave_packet", 28, 29)),
                5 => attrs.push(("wave_packet", 34, 29)),
                _ => {}
            }
        } else {
            attrs.extend([
                ("intensity", 12, 2),
                ("flags", 14, 2),
                ("classification", 16, 1),
                ("user_data", 17, 1),
                ("scan_angle", 18, 2),
                ("point_source_id", 20, 2),
                ("gps_time", 22, 8),
            ]);
            if matches!(format, 7 | 8 | 10) {
                attrs.push(("rgb", 30, 6));
            }
            if matches!(format, 8 | 10) {
                attrs.push(("nir", 36, 2));
            }
            match format {
                9 => attrs.push(("wave_packet", 30, 29)),
                10 => attrs.push(("wave_packet", 38, 29)),
                _ => {}
            }
        }
        if record_len > base {
            attrs.push(("extra_bytes", base, record_len - base));
        }
        let attributes = attrs
            .into_iter()
            .map(|(n, o, w)| Attribute { name: n.to_string(), offset: o, width: w })
            .collect();
        Ok(RecordLayout { format, record_len, attributes })
    }

    pub fn family(&self) -> Family {
        if self.format <= 5 {
            Family::Legacy
        } else {
            Family::Extended
        }
    }

    /// The attribute of this name, if the format has it.
    pub fn attribute(&self, name: &str) -> Option<&Attribute> {
        self.attributes.iter().find(|a| a.name == name)
    }

    pub fn has_gps_time(&self) -> bool {
        self.attribute("gps_time").is_some()
    }

    pub fn has_rgb(&self) -> bool {
        self.attribute("rgb").is_some()
    }

    /// Offset of the byte that holds the return number.
    pub fn return_number(&self, record: &[u8]) -> u8 {
        match self.family() {
            Family::Legacy => record[14] & 0x07,
            Family::Extended => record[14] & 0x0f,
        }
    }

    /// The classification code (without the legacy flag bits).
    pub fn classification(&self, record: &[u8]) -> u8 {
        match self.family() {
            Family::Legacy => record[15] & 0x1f,
            Family::Extended => record[16],
        }
    }
}

/// X, Y, Z integers of a record.
#[inline]
pub fn read_xyz(record: &[u8]) -> [i32; 3] {
    [
        i32::from_le_bytes([record[0], record[1], record[2], record[3]]),
        i32::from_le_bytes([record[4], record[5], record[6], record[7]]),
        i32::from_le_bytes([record[8], record[9], record[10], record[11]]),
    ]
}

/// Overwrites X, Y, Z of a record.
#[inline]
pub fn write_xyz(record: &mut [u8], xyz: [i32; 3]) {
    record[0..4].copy_from_slice(&xyz[0].to_le_bytes());
    record[4..8].copy_from_slice(&xyz[1].to_le_bytes());
    record[8..12].copy_from_slice(&xyz[2].to_le_bytes());
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn attributes_cover_every_byte_once() {
        for format in 0..=10u8 {
            let base = base_len(format).unwrap();
            for extra in [0usize, 3] {
                let l = RecordLayout::new(format, base + extra).unwrap();
                let mut covered = vec![0u8; base + extra];
                covered[..XYZ_BYTES].iter_mut().for_each(|c| *c += 1);
                for a in &l.attributes {
                    for c in &mut covered[a.offset..a.offset + a.width] {
                        *c += 1;
                    }
                }
                assert!(
                    covered.iter().all(|&c| c == 1),
                    "format {format} extra {extra}: {covered:?}"
                );
            }
        }
    }

    #[test]
    fn rejects_bad_formats() {
        assert_eq!(RecordLayout::new(11, 40), Err(LayoutError::UnknownFormat(11)));
        assert!(matches!(RecordLayout::new(3, 20), Err(LayoutError::RecordTooShort { .. })));
    }
}

/// Copies `n`-byte fields: `dst[i] = src[i * stride + offset .. + width]` for every record, with
/// fixed-size copies for the common widths (a hot path of batching and gathering).
pub fn copy_column(src: &[u8], stride: usize, offset: usize, width: usize, dst: &mut Vec<u8>) {
    fn fixed<const W: usize>(src: &[u8], stride: usize, offset: usize, dst: &mut Vec<u8>) {
        let n = src.len() / stride;
        let start = dst.len();
        dst.resize(start + n * W, 0);
        for (d, r) in dst[start..].chunks_exact_mut(W).zip(src.chunks_exact(stride)) {
            let s: &[u8; W] = r[offset..offset + W].try_into().unwrap();
            let d: &mut [u8; W] = d.try_into().unwrap();
            *d = *s;
        }
    }
    match width {
        1 => fixed::<1>(src, stride, offset, dst),
        2 => fixed::<2>(src, stride, offset, dst),
        4 => fixed::<4>(src, stride, offset, dst),
        6 => fixed::<6>(src, stride, offset, dst),
        8 => fixed::<8>(src, stride, offset, dst),
        _ => {
            for r in src.chunks_exact(stride) {
                dst.extend_from_slice(&r[offset..offset + width]);
            }
        }
    }
}

/// Copies whole records of `record_len` bytes, record `i` of `dst` from `src(i)`, with
/// fixed-size copies for every standard record length.
pub fn gather_records<'a>(
    record_len: usize,
    n: usize,
    src: impl Fn(usize) -> &'a [u8],
    dst: &mut Vec<u8>,
) {
    fn fixed<'a, const W: usize>(n: usize, src: impl Fn(usize) -> &'a [u8], dst: &mut Vec<u8>) {
        let start = dst.len();
        dst.resize(start + n * W, 0);
        for (i, d) in dst[start..].chunks_exact_mut(W).enumerate() {
            let s: &[u8; W] = src(i)[..W].try_into().unwrap();
            let d: &mut [u8; W] = d.try_into().unwrap();
            *d = *s;
        }
    }
    match record_len {
        20 => fixed::<20>(n, src, dst),
        26 => fixed::<26>(n, src, dst),
        28 => fixed::<28>(n, src, dst),
        30 => fixed::<30>(n, src, dst),
        34 => fixed::<34>(n, src, dst),
        36 => fixed::<36>(n, src, dst),
        38 => fixed::<38>(n, src, dst),
        _ => {
            for i in 0..n {
                dst.extend_from_slice(&src(i)[..record_len]);
            }
        }
    }
}

/// How records of one layout become records of another: byte ranges to copy, the rest zero,
/// and for legacy records (PDRF 0-5) put into a LAS 1.4 format (6-10) the fields whose encoding
/// differs (`docs/formats.md`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Conversion {
    pub target_len: usize,
    /// (source offset, target offset, length)
    pub copies: Vec<(usize, usize, usize)>,
    /// Whether the source is a legacy record and the target a LAS 1.4 one: return numbers,
    /// flags, classification and scan angle are mapped by [`legacy_to_extended`].
    pub legacy_to_extended: bool,
}

impl Conversion {
    /// Converts `src` records (source layout) into `dst` (target layout, zeroed or not).
    pub fn apply(&self, src: &[u8], source_len: usize, dst: &mut [u8]) {
        for (s, d) in src.chunks_exact(source_len).zip(dst.chunks_exact_mut(self.target_len)) {
            d.fill(0);
            for &(so, to, n) in &self.copies {
                d[to..to + n].copy_from_slice(&s[so..so + n]);
            }
            if self.legacy_to_extended {
                legacy_to_extended(s, d);
            }
        }
    }
}

/// A legacy scan angle rank (whole degrees) in LAS 1.4 units of 0.006 degrees, rounded to the
/// nearest unit (never a tie: `1000 * rank` is 0, 2 or 4 modulo 6); rounding the result times
/// 0.006 gives the rank back.
pub fn scan_angle_rank_to_extended(rank: i8) -> i16 {
    let v = rank as i32 * 1000;
    let q = if v >= 0 { (v + 3) / 6 } else { (v - 3) / 6 };
    q as i16
}

/// The fields of a legacy record (PDRF 0-5) whose encoding differs in LAS 1.4 (PDRF 6-10),
/// written into an extended record: return number (3 -> 4 bits) and number of returns, the
/// synthetic/key-point/withheld bits (classification byte bits 5-7 -> classification flags
/// bits 0-2), scan direction and edge of flight line (same bits 6 and 7, next byte), the
/// 5-bit classification (-> a whole byte) and the scan angle rank.
#[inline]
pub fn legacy_to_extended(src: &[u8], dst: &mut [u8]) {
    let returns = src[14];
    let class = src[15];
    dst[14] = (returns & 0x07) | (((returns >> 3) & 0x07) << 4);
    dst[15] = ((class >> 5) & 0x07) | (returns & 0xc0);
    dst[16] = class & 0x1f;
    dst[18..20].copy_from_slice(&scan_angle_rank_to_extended(src[16] as i8).to_le_bytes());
}

/// The smallest layout that holds every field of every input layout, and the conversion of each
/// input into it (`None` where an input already has it). Formats of one family merge into that
/// family: 0-3 (adding GPS time and RGB as needed) or 6-8 (adding RGB and NIR). Legacy and
/// LAS 1.4 formats together merge into the smallest of 6-8 that holds every field (legacy
/// records mapped by [`legacy_to_extended`]). Waveform formats merge only with themselves, and
/// the extra bytes must be the same size everywhere.
pub fn merge_layouts(
    layouts: &[RecordLayout],
) -> Result<(RecordLayout, Vec<Option<Conversion>>), String> {
    let first = &layouts[0];
    if layouts.iter().all(|l| l == first) {
        return Ok((first.clone(), vec![None; layouts.len()]));
    }
    let extra = |l: &RecordLayout| l.record_len - base_len(l.format).unwrap();
    if layouts.iter().any(|l| matches!(l.format, 4 | 5 | 9 | 10)) {
        return Err("inputs with waveform point formats (4, 5, 9, 10) can only be merged with the same format".into());
    }
    if layouts.iter().any(|l| extra(l) != extra(first)) {
        return Err("inputs have different numbers of extra bytes per point".into());
    }
    let any = |name: &str| layouts.iter().any(|l| l.attribute(name).is_some());
    let family = if layouts.iter().all(|l| l.family() == Family::Legacy) {
        Family::Legacy
    } else {
        Family::Extended
    };
    let target_format = match family {
        Family::Legacy => match (any("gps_time"), any("rgb")) {
            (false, false) => 0,
            (true, false) => 1,
            (false, true) => 2,
            (true, true) => 3,
        },
        Family::Extended => {
            if any("nir") {
                8
            } else if any("rgb") {
                7
            } else {
                6
            }
        }
    };
    let target = RecordLayout::new(target_format, base_len(target_format).unwrap() + extra(first))
        .map_err(|e| e.to_string())?;
    let convs = layouts
        .iter()
        .map(|l| {
            if *l == target {
                return None;
            }
            let mapped = l.family() == Family::Legacy && target.family() == Family::Extended;
            let mut copies = vec![(0, 0, XYZ_BYTES)];
            for a in &l.attributes {
                if mapped && matches!(a.name.as_str(), "flags" | "classification" | "scan_angle") {
                    continue;
                }
                let t = target.attribute(&a.name).expect("target holds every field");
                copies.push((a.offset, t.offset, a.width));
            }
            Some(Conversion { target_len: target.record_len, copies, legacy_to_extended: mapped })
        })
        .collect();
    Ok((target, convs))
}

#[cfg(test)]
mod merge_tests {
    use super::*;

    #[test]
    fn legacy_formats_merge_to_their_union() {
        let a = RecordLayout::new(1, 28).unwrap();
        let b = RecordLayout::new(2, 26).unwrap();
        let (t, c) = merge_layouts(&[a.clone(), b.clone()]).unwrap();
        assert_eq!(t.format, 3);
        let mut src = vec![0u8; 26];
        src[20..26].copy_from_slice(&[1, 2, 3, 4, 5, 6]);
        src[0] = 9;
        let mut dst = vec![0xffu8; 34];
        c[1].as_ref().unwrap().apply(&src, 26, &mut dst);
        assert_eq!(dst[0], 9);
        assert_eq!(&dst[28..34], &[1, 2, 3, 4, 5, 6]);
        assert_eq!(&dst[20..28], &[0; 8], "no gps time in the source: zero");
    }

    #[test]
    fn legacy_and_extended_merge_into_the_smallest_extended_format() {
        let l = |f: u8| RecordLayout::new(f, base_len(f).unwrap()).unwrap();
        assert_eq!(merge_layouts(&[l(1), l(6)]).unwrap().0.format, 6);
        assert_eq!(merge_layouts(&[l(0), l(6)]).unwrap().0.format, 6);
        assert_eq!(merge_layouts(&[l(2), l(6)]).unwrap().0.format, 7);
        assert_eq!(merge_layouts(&[l(3), l(7)]).unwrap().0.format, 7);
        assert_eq!(merge_layouts(&[l(3), l(8)]).unwrap().0.format, 8);
        assert!(merge_layouts(&[l(4), l(6)]).is_err());
        assert!(
            merge_layouts(&[RecordLayout::new(1, 30).unwrap(), l(6)]).is_err(),
            "extra bytes differ"
        );
    }

    #[test]
    fn legacy_fields_are_mapped() {
        let (t, c) =
            merge_layouts(&[RecordLayout::new(3, 34).unwrap(), RecordLayout::new(7, 36).unwrap()])
                .unwrap();
        assert_eq!(t.format, 7);
        let c = c[0].as_ref().unwrap();
        let mut src = vec![0u8; 34];
        src[0..12].copy_from_slice(&[1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0]);
        src[12..14].copy_from_slice(&500u16.to_le_bytes());
        src[14] = 0b1101_0011; // return 3 of 2 (sic), scan direction, edge
        src[15] = 0b1010_1100; // class 12, synthetic, withheld
        src[16] = (-7i8) as u8;
        src[17] = 42;
        src[18..20].copy_from_slice(&777u16.to_le_bytes());
        src[20..28].copy_from_slice(&1.5f64.to_le_bytes());
        src[28..34].copy_from_slice(&[1, 2, 3, 4, 5, 6]);
        let mut dst = vec![0xffu8; 36];
        c.apply(&src, 34, &mut dst);
        assert_eq!(&dst[0..14], &src[0..14]);
        assert_eq!(dst[14], 3 | (2 << 4));
        assert_eq!(dst[15], 0b1100_0101);
        assert_eq!(dst[16], 12);
        assert_eq!(dst[17], 42);
        assert_eq!(i16::from_le_bytes([dst[18], dst[19]]), -1167);
        assert_eq!(u16::from_le_bytes([dst[20], dst[21]]), 777);
        assert_eq!(f64::from_le_bytes(dst[22..30].try_into().unwrap()), 1.5);
        assert_eq!(&dst[30..36], &[1, 2, 3, 4, 5, 6]);
    }

    #[test]
    fn scan_angle_ranks_round_trip() {
        for r in -128i8..=127 {
            let e = scan_angle_rank_to_extended(r);
            assert_eq!((e as f64 * 0.006).round() as i32, r as i32, "rank {r}");
            assert!((e as f64 * 0.006 - r as f64).abs() <= 0.003 + 1e-12);
        }
        assert_eq!(scan_angle_rank_to_extended(90), 15000);
        assert_eq!(scan_angle_rank_to_extended(1), 167);
        assert_eq!(scan_angle_rank_to_extended(-1), -167);
    }

    #[test]
    fn families_and_extra_bytes() {
        assert!(merge_layouts(&[
            RecordLayout::new(1, 30).unwrap(),
            RecordLayout::new(1, 28).unwrap()
        ])
        .is_err());
        assert_eq!(
            merge_layouts(&[RecordLayout::new(6, 30).unwrap(), RecordLayout::new(8, 38).unwrap()])
                .unwrap()
                .0
                .format,
            8
        );
    }
}
