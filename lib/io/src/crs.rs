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
    let proj = |id: u16| vlrs.iter().find(|v| v.user_id_str() == "LASF_Projection" && v.record_id == id);
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
        .map(|v| v.data.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().unwrap())).collect())
        .unwrap_or_default();
    if let Some(k) = proj(34735) {
        let words: Vec<u16> = k.data.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect();
        if words.len() < 4 {
            info.problems.push("GeoTIFF key directory is shorter than its header".into());
        } else {
            let n = words[3] as usize;
            if 4 + 4 * n > words.len() {
                info.problems.push(format!("GeoTIFF key directory claims {n} keys but holds {}", (words.len() - 4) / 4));
            }
            for e in words[4..].chunks_exact(4).take(n) {
                let (id, loc, count, val) = (e[0], e[1], e[2] as usize, e[3] as usize);
                let value = match loc {
                    0 => val.to_string(),
                    34736 => doubles.get(val).map(|d| d.to_string()).unwrap_or_else(|| {
                        info.problems.push(format!("GeoTIFF key {id} points past the double parameters"));
                        "?".into()
                    }),
                    34737 => ascii
                        .as_deref()
                        .and_then(|a| a.get(val..(val + count).min(a.len())))
                        .map(|s| s.trim_end_matches(['|', '\0']).to_string())
                        .unwrap_or_else(|| {
                            info.problems.push(format!("GeoTIFF key {id} points past the ASCII parameters"));
                            "?".into()
                        }),
                    _ => {
                        info.problems.push(format!("GeoTIFF key {id} has an unknown location {loc}"));
                        "?".into()
                    }
                };
                if loc == 0 {
                    let code = val as u32;
                    match id {
                        3072 | 2048 if code != 32767 && code != 0 => {
                            if id == 3072 || info.epsg.is_none() {
                                info.epsg = Some(code)
                            }
                        }
                        4096 if code != 32767 && code != 0 => info.vertical_epsg = Some(code),
                        _ => {}
                    }
                }
                if (id == 1026 || id == 3073) && info.name.is_none() && value != "?" && !value.is_empty() {
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
    fn broken_key_directory_is_reported_not_fatal() {
        let words: [u16; 8] = [1, 1, 0, 5, 3072, 0, 1, 32610];
        let i = describe(&[&vlr(34735, words.iter().flat_map(|w| w.to_le_bytes()).collect())]);
        assert!(!i.problems.is_empty());
        assert_eq!(i.epsg, Some(32610));
    }
}
