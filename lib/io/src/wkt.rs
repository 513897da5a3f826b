//! OGC WKT 1 (the CRS text of LAS files, record 2112) read as a tree, and the PROJ.4 string of
//! the CRSs it describes, for [`crate::globe`] to place points on the Earth.
//!
//! A WKT is turned into a PROJ.4 string by its outermost EPSG code where it names one (the
//! EPSG definitions of `crs-definitions`), else from its parameters: the projections that LAS
//! files use (Lambert conformal conic 1SP/2SP, transverse Mercator, Mercator, Albers, oblique and
//! polar stereographic, Lambert azimuthal equal area, equirectangular) on any ellipsoid, with
//! `TOWGS84` when given, the prime meridian and the linear unit. Anything else is refused with
//! the projection's name (`--assign-crs EPSG:code` gives such an input a CRS mortar can place).

/// A value of a WKT node.
#[derive(Clone, Debug, PartialEq)]
pub enum Val {
    Str(String),
    Num(f64),
    /// A bare word (`EAST`, `NORTH`).
    Word(String),
    Node(Node),
}

/// `NAME[values...]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Node {
    pub name: String,
    pub args: Vec<Val>,
}

/// Nesting deeper than this is refused (untrusted text; real CRSs nest five or six deep).
const MAX_DEPTH: usize = 32;

/// Parses one WKT node.
///
/// The text ends at its first NUL (a C string, as LAS writers store it). Text after the first
/// complete node is ignored, as GDAL does: some writers close the outer node early (a
/// `COMPD_CS` whose `VERT_CS` follows its closing bracket, lasR's example data).
pub fn parse(s: &str) -> Result<Node, String> {
    let s = s.split('\0').next().unwrap_or("");
    let b = s.trim().as_bytes();
    let mut i = 0;
    node(b, &mut i, 0)
}

fn skip_ws(b: &[u8], i: &mut usize) {
    while *i < b.len() && b[*i].is_ascii_whitespace() {
        *i += 1;
    }
}

fn word(b: &[u8], i: &mut usize) -> String {
    let s = *i;
    while *i < b.len() && (b[*i].is_ascii_alphanumeric() || b[*i] == b'_') {
        *i += 1;
    }
    String::from_utf8_lossy(&b[s..*i]).into_owned()
}

fn node(b: &[u8], i: &mut usize, depth: usize) -> Result<Node, String> {
    if depth > MAX_DEPTH {
        return Err(format!("nested deeper than {MAX_DEPTH} levels"));
    }
    skip_ws(b, i);
    let name = word(b, i);
    if name.is_empty() {
        return Err(format!("expected a keyword at byte {i}"));
    }
    skip_ws(b, i);
    let close = match b.get(*i) {
        Some(b'[') => b']',
        Some(b'(') => b')',
        _ => return Err(format!("expected '[' after {name}")),
    };
    *i += 1;
    let mut args = Vec::new();
    loop {
        skip_ws(b, i);
        match b.get(*i) {
            None => return Err(format!("{name}[ is not closed")),
            Some(&c) if c == close && args.is_empty() => {
                *i += 1;
                return Ok(Node { name, args });
            }
            Some(b'"') => {
                *i += 1;
                let s = *i;
                // "" inside a string is a quote (WKT 2); WKT 1 files have none.
                while *i < b.len() && b[*i] != b'"' {
                    *i += 1;
                }
                if *i >= b.len() {
                    return Err("a string is not closed".into());
                }
                args.push(Val::Str(String::from_utf8_lossy(&b[s..*i]).into_owned()));
                *i += 1;
            }
            Some(c) if c.is_ascii_digit() || *c == b'-' || *c == b'+' || *c == b'.' => {
                let s = *i;
                *i += 1;
                while *i < b.len()
                    && (b[*i].is_ascii_digit() || matches!(b[*i], b'.' | b'e' | b'E' | b'-' | b'+'))
                {
                    *i += 1;
                }
                let t = std::str::from_utf8(&b[s..*i]).unwrap_or("");
                args.push(Val::Num(t.parse().map_err(|_| format!("bad number {t:?}"))?));
            }
            Some(c) if c.is_ascii_alphabetic() => {
                let save = *i;
                let w = word(b, i);
                skip_ws(b, i);
                if matches!(b.get(*i), Some(b'[') | Some(b'(')) {
                    *i = save;
                    args.push(Val::Node(node(b, i, depth + 1)?));
                } else {
                    args.push(Val::Word(w));
                }
            }
            Some(c) => return Err(format!("unexpected {:?} in {name}[", *c as char)),
        }
        skip_ws(b, i);
        match b.get(*i) {
            Some(b',') => *i += 1,
            Some(&c) if c == close => {
                *i += 1;
                return Ok(Node { name, args });
            }
            _ => return Err(format!("expected ',' or the end of {name}[")),
        }
    }
}

impl Node {
    /// The first string argument (the object's name).
    pub fn title(&self) -> Option<&str> {
        self.args.iter().find_map(|a| match a {
            Val::Str(s) => Some(s.as_str()),
            _ => None,
        })
    }
    /// The child nodes called `name` (any case).
    pub fn children<'a>(&'a self, name: &'a str) -> impl Iterator<Item = &'a Node> + 'a {
        self.args.iter().filter_map(move |a| match a {
            Val::Node(n) if n.name.eq_ignore_ascii_case(name) => Some(n),
            _ => None,
        })
    }
    pub fn child(&self, name: &str) -> Option<&Node> {
        self.args.iter().find_map(|a| match a {
            Val::Node(n) if n.name.eq_ignore_ascii_case(name) => Some(n),
            _ => None,
        })
    }
    /// The numbers among the arguments, in order.
    pub fn nums(&self) -> Vec<f64> {
        self.args
            .iter()
            .filter_map(|a| match a {
                Val::Num(x) => Some(*x),
                _ => None,
            })
            .collect()
    }
    /// The EPSG code of this object's own `AUTHORITY["EPSG","n"]` or `ID["EPSG",n]`.
    pub fn epsg(&self) -> Option<u32> {
        let a = self.child("AUTHORITY").or_else(|| self.child("ID"))?;
        match (a.args.first(), a.args.get(1)) {
            (Some(Val::Str(auth)), Some(Val::Str(code))) if auth.eq_ignore_ascii_case("EPSG") => {
                code.trim().parse().ok()
            }
            (Some(Val::Str(auth)), Some(Val::Num(code))) if auth.eq_ignore_ascii_case("EPSG") => {
                Some(*code as u32)
            }
            _ => None,
        }
    }
    /// `PARAMETER["name", value]` of this object, names compared without case and separators.
    fn param(&self, names: &[&str]) -> Option<f64> {
        let norm = |s: &str| s.chars().filter(|c| c.is_ascii_alphanumeric()).collect::<String>();
        self.children("PARAMETER").find_map(|p| {
            let t = norm(&p.title()?.to_ascii_lowercase());
            names.iter().any(|n| norm(n) == t).then(|| p.nums().first().copied()).flatten()
        })
    }
    /// The factor of this object's `UNIT` (to metres, or to radians for angles).
    fn unit_factor(&self) -> Option<f64> {
        self.child("UNIT").and_then(|u| u.nums().first().copied()).filter(|f| *f > 0.0)
    }
}

/// A CRS as PROJ.4 wants it, and the unit of its heights.
#[derive(Clone, Debug, PartialEq)]
pub struct Proj4Crs {
    pub proj4: String,
    /// Metres per unit of the z coordinate.
    pub z_to_meter: f64,
    /// Whether x and y are longitude and latitude in degrees.
    pub geographic: bool,
    pub name: String,
}

/// Why a CRS cannot be given as PROJ.4.
pub fn unsupported(name: &str, why: impl std::fmt::Display) -> String {
    format!("the CRS {name:?} cannot be placed on the globe: {why}")
}

/// The PROJ.4 string of a WKT 1 CRS (`PROJCS`, `GEOGCS`, `COMPD_CS` of one of them and a
/// `VERT_CS`); `epsg_proj4` gives an EPSG code's PROJ.4 string where the WKT names one.
pub fn to_proj4(
    root: &Node,
    epsg_proj4: &dyn Fn(u32) -> Option<String>,
) -> Result<Proj4Crs, String> {
    let name = root.title().unwrap_or("unnamed").to_string();
    let (horizontal, vertical) = match root.name.to_ascii_uppercase().as_str() {
        "COMPD_CS" | "COMPOUNDCRS" => {
            let h = root
                .args
                .iter()
                .find_map(|a| match a {
                    Val::Node(n)
                        if matches!(n.name.to_ascii_uppercase().as_str(), "PROJCS" | "GEOGCS") =>
                    {
                        Some(n)
                    }
                    _ => None,
                })
                .ok_or_else(|| unsupported(&name, "a compound CRS without PROJCS or GEOGCS"))?;
            (h, root.child("VERT_CS"))
        }
        "PROJCS" | "GEOGCS" => (root, None),
        other => {
            return Err(unsupported(
                &name,
                format_args!("{other} is not a projected or geographic CRS of WKT 1"),
            ))
        }
    };
    let geographic = horizontal.name.eq_ignore_ascii_case("GEOGCS");
    let h_unit = if geographic { 1.0 } else { horizontal.unit_factor().unwrap_or(1.0) };
    let z_to_meter = vertical.and_then(|v| v.unit_factor()).unwrap_or(h_unit);
    if let Some(p) = horizontal.epsg().and_then(epsg_proj4) {
        return Ok(Proj4Crs { proj4: p, z_to_meter, geographic, name });
    }
    let gcs = if geographic {
        horizontal
    } else {
        horizontal.child("GEOGCS").ok_or_else(|| unsupported(&name, "a PROJCS without GEOGCS"))?
    };
    let mut s = String::new();
    if geographic {
        s.push_str("+proj=longlat");
    } else {
        let proj = horizontal
            .child("PROJECTION")
            .and_then(|p| p.title())
            .ok_or_else(|| unsupported(&name, "no PROJECTION"))?;
        s.push_str(&projection(horizontal, proj).map_err(|why| unsupported(&name, why))?);
        let to_m = h_unit;
        let fe = horizontal.param(&["false_easting"]).unwrap_or(0.0) * to_m;
        let fn_ = horizontal.param(&["false_northing"]).unwrap_or(0.0) * to_m;
        s.push_str(&format!(" +x_0={fe} +y_0={fn_} +to_meter={to_m}"));
    }
    s.push_str(&datum(gcs).map_err(|why| unsupported(&name, why))?);
    if let Some(pm) = gcs.child("PRIMEM").and_then(|p| p.nums().first().copied()) {
        if pm != 0.0 {
            s.push_str(&format!(" +pm={pm}"));
        }
    }
    s.push_str(" +no_defs");
    Ok(Proj4Crs { proj4: s, z_to_meter, geographic, name })
}

/// ` +ellps/+a +rf [+towgs84]` of a `GEOGCS`.
fn datum(gcs: &Node) -> Result<String, String> {
    let d = gcs.child("DATUM").ok_or("a GEOGCS without DATUM")?;
    let sph =
        d.child("SPHEROID").or_else(|| d.child("ELLIPSOID")).ok_or("a DATUM without SPHEROID")?;
    let v = sph.nums();
    let (a, rf) = match v[..] {
        [a, rf, ..] if a > 0.0 && rf >= 0.0 => (a, rf),
        _ => return Err("a SPHEROID without its axis and flattening".into()),
    };
    let mut s = if rf == 0.0 { format!(" +a={a} +b={a}") } else { format!(" +a={a} +rf={rf}") };
    if let Some(t) = d.child("TOWGS84") {
        let p = t.nums();
        if p.len() == 3 || p.len() == 7 {
            let list: Vec<String> = p.iter().map(|x| x.to_string()).collect();
            s.push_str(&format!(" +towgs84={}", list.join(",")));
        }
    } else {
        let n = d.title().unwrap_or("").to_ascii_uppercase().replace([' ', '-'], "_");
        // Datums that PROJ takes as WGS 84 within a metre when it has no grid (its ballpark).
        if n.contains("WGS_1984")
            || n.contains("WGS84")
            || n.contains("NORTH_AMERICAN_1983")
            || n.contains("NAD83")
            || n.contains("ETRS")
            || n.contains("EUROPEAN_TERRESTRIAL")
            || n.contains("GDA")
        {
            s.push_str(" +towgs84=0,0,0");
        }
    }
    Ok(s)
}

/// Metres per unit of the vertical part of a compound CRS (WKT 1 `VERT_CS`, WKT 2 `VERTCRS`).
pub fn vertical_unit(root: &Node) -> Option<f64> {
    let v = root.child("VERT_CS").or_else(|| root.child("VERTCRS"))?;
    let unit = v
        .child("UNIT")
        .or_else(|| v.child("LENGTHUNIT"))
        .or_else(|| v.children("AXIS").find_map(|a| a.child("LENGTHUNIT")))?;
    unit.nums().first().copied().filter(|f| *f > 0.0)
}

/// `+proj=... ` and its parameters (angles in degrees) for a WKT `PROJECTION`.
fn projection(p: &Node, name: &str) -> Result<String, String> {
    let key: String =
        name.to_ascii_lowercase().chars().filter(|c| c.is_ascii_alphanumeric()).collect();
    let lat0 = p
        .param(&["latitude_of_origin", "latitude_of_center", "latitude_of_projection_centre"])
        .unwrap_or(0.0);
    let lon0 = p
        .param(&[
            "central_meridian",
            "longitude_of_center",
            "longitude_of_origin",
            "longitude_of_projection_centre",
        ])
        .unwrap_or(0.0);
    let k0 = p.param(&["scale_factor", "scale_factor_at_natural_origin"]).unwrap_or(1.0);
    let sp1 = p.param(&["standard_parallel_1"]);
    let sp2 = p.param(&["standard_parallel_2"]);
    Ok(match key.as_str() {
        "lambertconformalconic2sp" | "lambertconformalconic" | "lambertconformalconic2spbelgium" => {
            let lat1 = sp1.ok_or("Lambert conformal conic without standard_parallel_1")?;
            let lat2 = sp2.unwrap_or(lat1);
            format!("+proj=lcc +lat_1={lat1} +lat_2={lat2} +lat_0={lat0} +lon_0={lon0} +k={k0}")
        }
        "lambertconformalconic1sp" => {
            format!("+proj=lcc +lat_1={lat0} +lat_0={lat0} +lon_0={lon0} +k={k0}")
        }
        "transversemercator" | "gausskruger" => {
            format!("+proj=tmerc +lat_0={lat0} +lon_0={lon0} +k={k0}")
        }
        "mercator1sp" | "mercator" => match sp1 {
            Some(ts) => format!("+proj=merc +lat_ts={ts} +lon_0={lon0}"),
            None => format!("+proj=merc +lon_0={lon0} +k={k0}"),
        },
        "mercator2sp" => format!("+proj=merc +lat_ts={} +lon_0={lon0}", sp1.unwrap_or(0.0)),
        "albersconicequalarea" | "albers" => {
            let lat1 = sp1.ok_or("Albers without standard_parallel_1")?;
            format!("+proj=aea +lat_1={lat1} +lat_2={} +lat_0={lat0} +lon_0={lon0}", sp2.unwrap_or(lat1))
        }
        "obliquestereographic" | "doublestereographic" => {
            format!("+proj=sterea +lat_0={lat0} +lon_0={lon0} +k={k0}")
        }
        "polarstereographic" | "stereographicnorthpole" | "stereographicsouthpole" => {
            let ts = sp1.unwrap_or(lat0);
            let pole = if ts < 0.0 || lat0 < 0.0 || key.contains("south") { -90 } else { 90 };
            format!("+proj=stere +lat_0={pole} +lat_ts={ts} +lon_0={lon0} +k={k0}")
        }
        "lambertazimuthalequalarea" => format!("+proj=laea +lat_0={lat0} +lon_0={lon0}"),
        "equirectangular" | "equidistantcylindrical" | "platecarree" => {
            format!("+proj=eqc +lat_ts={} +lon_0={lon0}", sp1.unwrap_or(0.0))
        }
        _ => return Err(format!("the projection {name:?} is not one mortar can transform (give the input a CRS with --assign-crs EPSG:code)")),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const AUTZEN: &str = r#"PROJCS["NAD_1983_HARN_Lambert_Conformal_Conic",GEOGCS["GCS_North_American_1983_HARN",DATUM["NAD83_High_Accuracy_Regional_Network",SPHEROID["GRS_1980",6378137,298.257222101,AUTHORITY["EPSG","7019"]],AUTHORITY["EPSG","6152"]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Lambert_Conformal_Conic_2SP"],PARAMETER["standard_parallel_1",43],PARAMETER["standard_parallel_2",45.5],PARAMETER["latitude_of_origin",41.75],PARAMETER["central_meridian",-120.5],PARAMETER["false_easting",1312335.958005249],PARAMETER["false_northing",0],UNIT["foot",0.3048,AUTHORITY["EPSG","9002"]]]"#;

    #[test]
    fn autzen_lcc_in_feet() {
        let n = parse(AUTZEN).unwrap();
        let c = to_proj4(&n, &|_| None).unwrap();
        assert!(
            c.proj4.starts_with("+proj=lcc +lat_1=43 +lat_2=45.5 +lat_0=41.75 +lon_0=-120.5"),
            "{}",
            c.proj4
        );
        assert!(
            c.proj4.contains("+to_meter=0.3048") && c.proj4.contains("+towgs84=0,0,0"),
            "{}",
            c.proj4
        );
        assert!((c.z_to_meter - 0.3048).abs() < 1e-12);
        assert!(!c.geographic);
        // false easting in metres
        assert!(c.proj4.contains("+x_0=399999.99999"), "{}", c.proj4);
    }

    #[test]
    fn compound_takes_the_vertical_unit_and_the_epsg_code() {
        let w = r#"COMPD_CS["x",PROJCS["NAD83 / UTM zone 10N",GEOGCS["NAD83",DATUM["North_American_Datum_1983",SPHEROID["GRS 1980",6378137,298.257222101]]],PROJECTION["Transverse_Mercator"],UNIT["metre",1],AUTHORITY["EPSG","26910"]],VERT_CS["NAVD88 height (ftUS)",VERT_DATUM["North American Vertical Datum 1988",2005],UNIT["US survey foot",0.304800609601219],AXIS["Up",UP]]]"#;
        let n = parse(w).unwrap();
        let c = to_proj4(&n, &|code| (code == 26910).then(|| "+proj=utm +zone=10".to_string()))
            .unwrap();
        assert_eq!(c.proj4, "+proj=utm +zone=10");
        assert!((c.z_to_meter - 0.304800609601219).abs() < 1e-15);
    }

    #[test]
    fn unknown_projections_and_broken_text_are_refused() {
        let w = r#"PROJCS["odd",GEOGCS["g",DATUM["d",SPHEROID["s",6378137,298.257223563]]],PROJECTION["Bonne"],UNIT["metre",1]]"#;
        let e = to_proj4(&parse(w).unwrap(), &|_| None).unwrap_err();
        assert!(e.contains("\"odd\"") && e.contains("Bonne"), "{e}");
        for bad in ["", "PROJCS[", "PROJCS[\"a\",", "[1]", &"A[".repeat(100)] {
            assert!(parse(bad).is_err(), "{bad}");
        }
        // text after the first whole node is ignored (lasR's las14_pdrf6.laz closes its
        // COMPD_CS before the VERT_CS), a NUL ends the text
        assert_eq!(parse("PROJCS[\"a\"]], VERT_CS[\"b\"]]").unwrap().title(), Some("a"));
        assert_eq!(parse("PROJCS[\"a\"]\0garbage[").unwrap().title(), Some("a"));
        let e = to_proj4(&parse("LOCAL_CS[\"site\"]").unwrap(), &|_| None).unwrap_err();
        assert!(e.contains("site"), "{e}");
    }
}
