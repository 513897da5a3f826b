//! Naming the coordinate reference system of a LAS file from its VLRs: OGC WKT (LASF_Projection
//! 2112) or GeoTIFF keys (LASF_Projection 34735, with 34736 doubles and 34737 ASCII citations).

use crate::las::Vlr;
use serde::Serialize;

/// What the CRS records say.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct CrsInfo {
    /// `wkt`, `geotiff`, `wkt+geotiff` or `none`.
    pub kind: String,
    /// A name for people: the WKT's name, the GeoTIFF citation, or a known EPSG name.
    pub name: Option<String>,
    /// Horizontal EPSG code (projected or geographic) when the records give one.
    pub epsg: Option<u32>,
    /// Vertical EPSG code when given.
    pub vertical_epsg: Option<u32>,
    pub wkt: Option<String>,
    /// GeoTIFF keys as (key id, name, value).
    pub geokeys: Vec<GeoKey>,
    /// Problems with the records (the file is still read).
    pub problems: Vec<String>,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GeoKey {
    pub id: u16,
    pub name: String,
    pub value: String,
}

fn geokey_name(id: u16) -> &'static str {
    match id {
        1024 => "GTModelTypeGeoKey",
        1025 => "GTRasterTypeGeoKey",
        1026 => "GTCitationGeoKey",
        2048 => "GeographicTypeGeoKey",
        2049 => "GeogCitationGeoKey",
        2050 => "GeogGeodeticDatumGeoKey",
        2052 => "GeogLinearUnitsGeoKey",
        2054 => "GeogAngularUnitsGeoKey",
        3072 => "ProjectedCSTypeGeoKey",
        3073 => "PCSCitationGeoKey",
        3074 => "ProjectionGeoKey",
        3076 => "ProjLinearUnitsGeoKey",
        4096 => "VerticalCSTypeGeoKey",
        4097 => "VerticalCitationGeoKey",
        4098 => "VerticalDatumGeoKey",
        4099 => "VerticalUnitsGeoKey",
        _ => "unknown",
    }
}

/// Names of a few EPSG codes that LAS files use most.
pub fn epsg_name(code: u32) -> Option<String> {
    Some(match code {
        4326 => "WGS 84".into(),
        4269 => "NAD83".into(),
        4267 => "NAD27".into(),
        3857 => "WGS 84 / Pseudo-Mercator".into(),
        4978 => "WGS 84 (geocentric)".into(),
        32601..=32660 => format!("WGS 84 / UTM zone {}N", code - 32600),
        32701..=32760 => format!("WGS 84 / UTM zone {}S", code - 32700),
        26901..=26923 => format!("NAD83 / UTM zone {}N", code - 26900),
        25828..=25838 => format!("ETRS89 / UTM zone {}N", code - 25800),
        28992 => "Amersfoort / RD New".into(),
        2056 => "CH1903+ / LV95".into(),
        5703 => "NAVD88 height".into(),
        _ => return None,
    })
}

/// Reads the CRS records among `vlrs` (VLRs and EVLRs alike).
pub fn describe(vlrs: &[&Vlr]) -> CrsInfo {
    let mut info = CrsInfo::default();
    let proj =
        |id: u16| vlrs.iter().find(|v| v.user_id_str() == "LASF_Projection" && v.record_id == id);
    if let Some(w) = proj(2112) {
        let text = String::from_utf8_lossy(&w.data).trim_end_matches('\0').trim().to_string();
        if text.is_empty() {
            info.problems.push("WKT record is empty".into());
        } else {
            info.name = wkt_name(&text);
            info.epsg = wkt_epsg(&text);
            info.wkt = Some(text);
        }
    }
    let ascii = proj(34737).map(|v| String::from_utf8_lossy(&v.data).into_owned());
    let doubles: Vec<f64> = proj(34736)
        .map(|v| {
            v.data.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().unwrap())).collect()
        })
        .unwrap_or_default();
    if let Some(k) = proj(34735) {
        let words: Vec<u16> =
            k.data.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect();
        if words.len() < 4 {
            info.problems.push("GeoTIFF key directory is shorter than its header".into());
        } else {
            let n = words[3] as usize;
            if 4 + 4 * n > words.len() {
                info.problems.push(format!(
                    "GeoTIFF key directory claims {n} keys but holds {}",
                    (words.len() - 4) / 4
                ));
            }
            for e in words[4..].chunks_exact(4).take(n) {
                let (id, loc, count, val) = (e[0], e[1], e[2] as usize, e[3] as usize);
                let value = match loc {
                    0 => val.to_string(),
                    34736 => doubles.get(val).map(|d| d.to_string()).unwrap_or_else(|| {
                        info.problems
                            .push(format!("GeoTIFF key {id} points past the double parameters"));
                        "?".into()
                    }),
                    34737 => ascii
                        .as_deref()
                        .and_then(|a| a.get(val..(val + count).min(a.len())))
                        .map(|s| s.trim_end_matches(['|', '\0']).to_string())
                        .unwrap_or_else(|| {
                            info.problems
                                .push(format!("GeoTIFF key {id} points past the ASCII parameters"));
                            "?".into()
                        }),
                    _ => {
                        info.problems
                            .push(format!("GeoTIFF key {id} has an unknown location {loc}"));
                        "?".into()
                    }
                };
                if loc == 0 {
                    let code = val as u32;
                    match id {
                        3072 | 2048
                            if code != 32767
                                && code != 0
                                && (id == 3072 || info.epsg.is_none()) =>
                        {
                            info.epsg = Some(code)
                        }
                        4096 if code != 32767 && code != 0 => info.vertical_epsg = Some(code),
                        _ => {}
                    }
                }
                if (id == 1026 || id == 3073)
                    && info.name.is_none()
                    && value != "?"
                    && !value.is_empty()
                {
                    info.name = Some(value.clone());
                }
                info.geokeys.push(GeoKey { id, name: geokey_name(id).into(), value });
            }
        }
    }
    if info.name.is_none() {
        info.name = info.epsg.and_then(epsg_name);
    }
    info.kind = match (info.wkt.is_some(), !info.geokeys.is_empty()) {
        (true, true) => "wkt+geotiff",
        (true, false) => "wkt",
        (false, true) => "geotiff",
        (false, false) => "none",
    }
    .into();
    info
}

impl CrsInfo {
    /// One line for people, as `mortar info` prints it: `NAD83 / UTM zone 10N (EPSG:26910, wkt)`.
    pub fn summary(&self) -> String {
        let vertical = self.vertical_epsg.map(|v| format!(" + EPSG:{v}")).unwrap_or_default();
        match (&self.name, self.epsg) {
            (Some(n), Some(e)) => format!("{n} (EPSG:{e}{vertical}, {})", self.kind),
            (Some(n), None) => format!("{n} ({})", self.kind),
            (None, Some(e)) => format!("EPSG:{e}{vertical} ({})", self.kind),
            (None, None) => self.kind.clone(),
        }
    }
}

/// Whether a VLR or EVLR describes the coordinate reference system (`LASF_Projection`).
pub fn is_crs_record(v: &Vlr) -> bool {
    v.user_id_str() == "LASF_Projection"
}

/// The CRS records of one input (VLRs and EVLRs), as they will be written.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CrsRecords {
    pub vlrs: Vec<Vlr>,
    pub evlrs: Vec<Vlr>,
}

impl CrsRecords {
    /// The `LASF_Projection` records among an input's VLRs and EVLRs.
    pub fn of(vlrs: &[Vlr], evlrs: &[Vlr]) -> CrsRecords {
        CrsRecords {
            vlrs: vlrs.iter().filter(|v| is_crs_record(v)).cloned().collect(),
            evlrs: evlrs.iter().filter(|v| is_crs_record(v)).cloned().collect(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.vlrs.is_empty() && self.evlrs.is_empty()
    }
    pub fn describe(&self) -> CrsInfo {
        let all: Vec<&Vlr> = self.vlrs.iter().chain(&self.evlrs).collect();
        describe(&all)
    }
    /// Whether a WKT record (2112) is among them.
    pub fn has_wkt(&self) -> bool {
        self.vlrs.iter().chain(&self.evlrs).any(|v| v.record_id == 2112)
    }
    /// Whether two inputs' records say the same: the same bytes (record ids and payloads,
    /// descriptions aside), or the same horizontal and vertical EPSG codes.
    pub fn agrees_with(&self, o: &CrsRecords) -> bool {
        let key = |r: &CrsRecords| {
            let mut k: Vec<(u16, Vec<u8>)> =
                r.vlrs.iter().chain(&r.evlrs).map(|v| (v.record_id, v.data.clone())).collect();
            k.sort();
            k
        };
        if key(self) == key(o) {
            return true;
        }
        let (a, b) = (self.describe(), o.describe());
        if let (Some(x), Some(y)) = (&a.wkt, &b.wkt) {
            if canonical_wkt(x) == canonical_wkt(y) {
                return true;
            }
        }
        a.epsg.is_some() && a.epsg == b.epsg && a.vertical_epsg == b.vertical_epsg
    }
}

/// WKT without whitespace and without `AUTHORITY[...]`/`ID[...]` nodes, so that the same CRS
/// written with and without authority codes compares equal.
fn canonical_wkt(w: &str) -> String {
    let mut out = String::with_capacity(w.len());
    let b = w.as_bytes();
    let mut i = 0;
    while i < b.len() {
        let rest = &w[i..];
        if rest.starts_with(",AUTHORITY[") || rest.starts_with(",ID[") {
            let mut depth = 0;
            while i < b.len() {
                match b[i] {
                    b'[' => depth += 1,
                    b']' => {
                        depth -= 1;
                        if depth == 0 {
                            i += 1;
                            break;
                        }
                    }
                    _ => {}
                }
                i += 1;
            }
            continue;
        }
        if !b[i].is_ascii_whitespace() {
            out.push(b[i] as char);
        }
        i += 1;
    }
    out
}

/// What `--assign-crs` gives: the CRS records of a LAS/LAZ file, or an EPSG code (with an
/// optional vertical code: `EPSG:26910+5703`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum AssignCrs {
    File(std::path::PathBuf),
    Epsg { horizontal: u32, vertical: Option<u32> },
}

impl AssignCrs {
    /// `EPSG:n`, `EPSG:n+v` (any case), or a path.
    pub fn parse(s: &str) -> Result<AssignCrs, String> {
        let t = s.trim();
        if t.len() > 5 && t[..5].eq_ignore_ascii_case("epsg:") {
            let code = |c: &str| c.trim().parse::<u32>().ok().filter(|&c| c > 0 && c < 32767);
            let mut parts = t[5..].splitn(2, '+');
            let h = parts
                .next()
                .and_then(code)
                .ok_or_else(|| format!("'{s}': not an EPSG code (try EPSG:26910)"))?;
            let v = match parts.next() {
                Some(v) => Some(code(v).ok_or_else(|| {
                    format!("'{s}': not a vertical EPSG code (try EPSG:26910+5703)")
                })?),
                None => None,
            };
            return Ok(AssignCrs::Epsg { horizontal: h, vertical: v });
        }
        if t.is_empty() {
            return Err("--assign-crs needs a LAS/LAZ file or EPSG:CODE".into());
        }
        Ok(AssignCrs::File(t.into()))
    }
}

/// Why CRS records cannot be made for an EPSG code.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum CrsError {
    /// A geocentric CRS, which GeoTIFF 1.0 keys cannot express.
    #[error("EPSG:{code} is geocentric, which GeoTIFF keys cannot name; give --assign-crs a LAS file that carries it as WKT")]
    Geocentric { code: u32 },
}

/// Whether an EPSG code is a geographic 2D/3D CRS (degrees) rather than a projected one, as far
/// as mortar can tell without the EPSG database: the 4000-4999 block is geographic, except the
/// geocentric codes in it, which GeoTIFF 1.0 keys cannot express.
fn epsg_kind(code: u32) -> Result<bool, CrsError> {
    const GEOCENTRIC: [u32; 6] = [4328, 4330, 4338, 4340, 4936, 4978];
    if GEOCENTRIC.contains(&code) {
        return Err(CrsError::Geocentric { code });
    }
    Ok((4000..5000).contains(&code))
}

/// GeoTIFF key directory records (LASF_Projection 34735, and 34737 with a citation) for an EPSG
/// code: GTModelTypeGeoKey (1 projected, 2 geographic), GTRasterTypeGeoKey (1, pixel is area),
/// ProjectedCSTypeGeoKey or GeographicTypeGeoKey, VerticalCSTypeGeoKey when given. mortar has
/// no EPSG database, so it cannot write the WKT that LAS 1.4 formats 6-10 ask for.
pub fn epsg_records(horizontal: u32, vertical: Option<u32>) -> Result<CrsRecords, CrsError> {
    let geographic = epsg_kind(horizontal)?;
    // a citation only where mortar knows the name (readers show it; a bare code says nothing new)
    let citation = epsg_name(horizontal).map(|n| format!("{n}|"));
    let mut keys: Vec<[u16; 4]> =
        vec![[1024, 0, 1, if geographic { 2 } else { 1 }], [1025, 0, 1, 1]];
    if let Some(c) = &citation {
        keys.push([1026, 34737, c.len() as u16, 0]);
    }
    keys.push([if geographic { 2048 } else { 3072 }, 0, 1, horizontal as u16]);
    if let Some(v) = vertical {
        keys.push([4096, 0, 1, v as u16]);
    }
    let mut words: Vec<u16> = vec![1, 1, 0, keys.len() as u16];
    for k in &keys {
        words.extend_from_slice(k);
    }
    let rec = |id: u16, data: Vec<u8>, desc: &str| {
        let mut user_id = [0u8; 16];
        user_id[..15].copy_from_slice(b"LASF_Projection");
        let mut description = [0u8; 32];
        description[..desc.len()].copy_from_slice(desc.as_bytes());
        Vlr { reserved: 0, user_id, record_id: id, description, data }
    };
    let mut vlrs = vec![rec(
        34735,
        words.iter().flat_map(|w| w.to_le_bytes()).collect(),
        "GeoTIFF GeoKeyDirectoryTag",
    )];
    if let Some(c) = citation {
        let mut ascii = c.into_bytes();
        ascii.push(0);
        vlrs.push(rec(34737, ascii, "GeoTIFF GeoAsciiParamsTag"));
    }
    Ok(CrsRecords { vlrs, evlrs: Vec::new() })
}

fn wkt_name(w: &str) -> Option<String> {
    let s = w.find('"')?;
    let e = w[s + 1..].find('"')?;
    Some(w[s + 1..s + 1 + e].to_string())
}

/// The EPSG code of the outermost object: the last `AUTHORITY["EPSG","n"]` or `ID["EPSG",n]` at depth 1.
fn wkt_epsg(w: &str) -> Option<u32> {
    let mut depth = 0i32;
    let mut found = None;
    let b = w.as_bytes();
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'[' | b'(' => depth += 1,
            b']' | b')' => depth -= 1,
            _ => {
                // Bytes, not `&w[i..]`: `i` may fall inside a multi-byte character (fuzz
                // regression wkt-char-boundary). The object ends at its `]`: looking further
                // made many AUTHORITY objects quadratic.
                if depth == 1 && (b[i..].starts_with(b"AUTHORITY[") || b[i..].starts_with(b"ID[")) {
                    let rest = &w[i..];
                    let rest = &rest[..rest.find(']').unwrap_or(rest.len())];
                    let digits: String = rest
                        .split(',')
                        .nth(1)
                        .map(|s| s.chars().filter(|c| c.is_ascii_digit()).collect())
                        .unwrap_or_default();
                    if rest.to_ascii_uppercase().contains("EPSG") {
                        found = digits.parse().ok();
                    }
                }
            }
        }
        i += 1;
    }
    found
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vlr(id: u16, data: Vec<u8>) -> Vlr {
        let mut user_id = [0u8; 16];
        user_id[..15].copy_from_slice(b"LASF_Projection");
        Vlr { reserved: 0, user_id, record_id: id, description: [0; 32], data }
    }

    #[test]
    fn geotiff_projected_code() {
        let words: [u16; 12] = [1, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 26910];
        let v = vlr(34735, words.iter().flat_map(|w| w.to_le_bytes()).collect());
        let i = describe(&[&v]);
        assert_eq!(i.kind, "geotiff");
        assert_eq!(i.epsg, Some(26910));
        assert_eq!(i.name.as_deref(), Some("NAD83 / UTM zone 10N"));
    }

    #[test]
    fn wkt_name_and_code() {
        let w = r#"PROJCS["NAD83 / UTM zone 10N",GEOGCS["NAD83",AUTHORITY["EPSG","4269"]],AUTHORITY["EPSG","26910"]]"#;
        let i = describe(&[&vlr(2112, w.as_bytes().to_vec())]);
        assert_eq!(i.name.as_deref(), Some("NAD83 / UTM zone 10N"));
        assert_eq!(i.epsg, Some(26910));
    }

    #[test]
    fn epsg_records_describe_their_code() {
        let r = epsg_records(26910, Some(5703)).unwrap();
        let i = r.describe();
        assert_eq!(i.kind, "geotiff");
        assert_eq!(i.epsg, Some(26910));
        assert_eq!(i.vertical_epsg, Some(5703));
        assert!(i.problems.is_empty(), "{:?}", i.problems);
        let g = epsg_records(4326, None).unwrap().describe();
        assert_eq!(g.epsg, Some(4326));
        assert!(g.geokeys.iter().any(|k| k.id == 2048 && k.value == "4326"));
        assert!(g.geokeys.iter().any(|k| k.id == 1024 && k.value == "2"));
        assert!(epsg_records(4978, None).is_err());
        assert!(r.agrees_with(&r.clone()));
        assert!(!r.agrees_with(&epsg_records(26911, Some(5703)).unwrap()));
    }

    #[test]
    fn the_same_wkt_with_and_without_authorities_agrees() {
        let a = r#"PROJCS["X",GEOGCS["NAD83",SPHEROID["GRS 1980",6378137,298.257222101]],UNIT["metre",1]]"#;
        let b = r#"PROJCS["X", GEOGCS["NAD83",SPHEROID["GRS 1980",6378137,298.257222101,AUTHORITY["EPSG","7019"]]],UNIT["metre",1,AUTHORITY["EPSG","9001"]]]"#;
        let c = r#"PROJCS["X",GEOGCS["NAD83",SPHEROID["GRS 1980",6378137,298.3]],UNIT["metre",1]]"#;
        let r =
            |w: &str| CrsRecords { vlrs: vec![vlr(2112, w.as_bytes().to_vec())], evlrs: vec![] };
        assert!(r(a).agrees_with(&r(b)));
        assert!(!r(a).agrees_with(&r(c)));
    }

    #[test]
    fn assign_crs_parses() {
        assert_eq!(
            AssignCrs::parse("EPSG:26910"),
            Ok(AssignCrs::Epsg { horizontal: 26910, vertical: None })
        );
        assert_eq!(
            AssignCrs::parse("epsg:26910+5703"),
            Ok(AssignCrs::Epsg { horizontal: 26910, vertical: Some(5703) })
        );
        assert!(AssignCrs::parse("EPSG:x").is_err());
        assert_eq!(AssignCrs::parse("a.las"), Ok(AssignCrs::File("a.las".into())));
    }

    #[test]
    fn broken_key_directory_is_reported_not_fatal() {
        let words: [u16; 8] = [1, 1, 0, 5, 3072, 0, 1, 32610];
        let i = describe(&[&vlr(34735, words.iter().flat_map(|w| w.to_le_bytes()).collect())]);
        assert!(!i.problems.is_empty());
        assert_eq!(i.epsg, Some(32610));
    }
}
