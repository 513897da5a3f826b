//! Placing points on the Earth: the CRS of a dataset (its WKT or GeoTIFF keys) to WGS 84 Earth-
//! centred, Earth-fixed coordinates (ECEF, EPSG:4978), and a local east-north-up frame at the
//! data's centre, for the 3D Tiles export.
//!
//! The projection library is `proj4rs`, a pure-Rust port of PROJ.4 (projections, ellipsoids,
//! `+towgs84` datum shifts), with the EPSG definitions of `crs-definitions`: no C library to
//! build or ship, the same code on every platform and in CI. What it does not do, and PROJ
//! would: grid-based datum shifts (NADCON, NTv2, geoid models) and time-dependent frames. Datums
//! that PROJ without grids treats as WGS 84 (NAD83, ETRS89, GDA) are taken as WGS 84 here too,
//! which is within about a metre; heights are taken as ellipsoidal (an orthometric height
//! lands off the ellipsoid by the geoid undulation, as in PROJ without a geoid grid).
//!
//! Heights: the z unit is the vertical CRS's unit where the CRS names one (a `VERT_CS` of a
//! compound WKT, a vertical EPSG code, the GeoTIFF vertical units key), else the horizontal
//! unit (the LAS convention: a file in feet has its heights in feet). Heights pass a datum shift
//! unchanged and only latitude and longitude move, as in PROJ for CRSs without a vertical part.

use crate::crs::{CrsInfo, CrsRecords};
use crate::wkt;
use proj4rs::proj::Proj;

/// WGS 84's semi-major axis and first eccentricity squared.
const WGS84_A: f64 = 6_378_137.0;
const WGS84_F: f64 = 1.0 / 298.257_223_563;
const WGS84_E2: f64 = WGS84_F * (2.0 - WGS84_F);

/// A dataset's CRS, ready to transform its world coordinates to ECEF.
pub struct Globe {
    src: Proj,
    dst: Proj,
    geographic: bool,
    xy_to_radians: f64,
    z_to_meter: f64,
    /// The CRS's name, for messages and reports.
    pub name: String,
    /// The PROJ.4 definition used.
    pub proj4: String,
}

/// Metres per unit of a GeoTIFF linear unit code.
fn geotiff_unit(code: u32) -> Option<f64> {
    Some(match code {
        9001 => 1.0,
        9002 => 0.3048,
        9003 => 1200.0 / 3937.0,
        _ => return None,
    })
}

/// Metres per unit of the UNIT of an EPSG code's WKT.
fn epsg_unit(code: u32) -> Option<f64> {
    let def = crs_definitions::from_code(u16::try_from(code).ok()?)?;
    let node = wkt::parse(def.wkt).ok()?;
    node.child("UNIT").and_then(|u| u.nums().first().copied()).filter(|f| *f > 0.0)
}

fn epsg_proj4(code: u32) -> Option<String> {
    u16::try_from(code).ok().and_then(crs_definitions::from_code).map(|d| d.proj4.to_string())
}

/// The PROJ.4 definition of user-defined GeoTIFF keys (`ProjectedCSTypeGeoKey` 32767 with the
/// projection's parameters, or a `ProjectionGeoKey` of UTM), `None` where the keys describe no
/// projection this reads.
fn geotiff_projection(info: &CrsInfo) -> Option<Result<wkt::Proj4Crs, String>> {
    let num = |id: u16| {
        info.geokeys.iter().find(|k| k.id == id).and_then(|k| k.value.parse::<f64>().ok())
    };
    let code = |id: u16| num(id).map(|v| v as u32).filter(|&c| c != 32767 && c != 0);
    let name = info.name.clone().unwrap_or_else(|| "GeoTIFF keys".into());
    let model = code(1024).unwrap_or(1);
    // The ellipsoid and datum shift: the geographic CRS's EPSG definition, else the datum's,
    // else the ellipsoid's code or its axes.
    let datum_of_geog = code(2048).and_then(epsg_proj4).map(|p| {
        p.split_whitespace()
            .filter(|t| {
                ["+ellps=", "+a=", "+b=", "+rf=", "+towgs84=", "+datum="]
                    .iter()
                    .any(|k| t.starts_with(k))
            })
            .collect::<Vec<_>>()
            .join(" ")
    });
    let datum = datum_of_geog.or_else(|| {
        Some(match code(2050)? {
            6326 => "+datum=WGS84".into(),
            6269 | 6152 | 6759 | 1116 | 6140 => "+ellps=GRS80 +towgs84=0,0,0".into(),
            6258 | 6283 | 6167 | 6171 => "+ellps=GRS80 +towgs84=0,0,0".into(),
            6267 => "+ellps=clrk66".into(),
            _ => return None,
        })
    });
    let datum = datum.or_else(|| {
        Some(match code(2056) {
            Some(7030) => "+ellps=WGS84 +towgs84=0,0,0".into(),
            Some(7019) => "+ellps=GRS80 +towgs84=0,0,0".into(),
            Some(7008) => "+ellps=clrk66".into(),
            Some(7004) => "+ellps=bessel".into(),
            Some(7022) => "+ellps=intl".into(),
            Some(_) => return None,
            None => {
                let a = num(2057)?;
                match (num(2059), num(2058)) {
                    (Some(rf), _) if rf > 0.0 => format!("+a={a} +rf={rf}"),
                    (_, Some(b)) => format!("+a={a} +b={b}"),
                    _ => format!("+a={a} +b={a}"),
                }
            }
        })
    })?;
    let to_m = code(3076).and_then(geotiff_unit).or_else(|| num(3077)).unwrap_or(1.0);
    let z = code(4099).and_then(geotiff_unit).unwrap_or(if model == 2 { 1.0 } else { to_m });
    if model == 2 {
        return Some(Ok(wkt::Proj4Crs {
            proj4: format!("+proj=longlat {datum} +no_defs"),
            z_to_meter: z,
            geographic: true,
            name,
        }));
    }
    if model != 1 {
        return None;
    }
    let proj = match code(3074) {
        Some(c @ 16001..=16060) => format!("+proj=utm +zone={}", c - 16000),
        Some(c @ 16101..=16160) => format!("+proj=utm +zone={} +south", c - 16100),
        Some(_) => return None,
        None => {
            let p = |id: u16| num(id).unwrap_or(0.0);
            let (fe, fn_) =
                (num(3082).or(num(3086)).unwrap_or(0.0), num(3083).or(num(3087)).unwrap_or(0.0));
            // False easting and northing are in the linear unit (GeoTIFF 1.1). Some writers
            // (older libgeotiff, PDAL 1.x: the Autzen files) put metres there whatever the unit,
            // as GDAL's GTIFF_LINEAR_UNITS=BROKEN reads them: a value that is a whole number of
            // kilometres (to a micrometre) but no whole number of the unit is taken as metres.
            let whole = |v: f64| (v - v.round()).abs() < 1e-6;
            let in_metres = |v: f64| {
                v != 0.0 && whole(v / 1000.0 * 1000.0) && whole(v / 1000.0) && !whole(v / to_m)
            };
            let metres = to_m != 1.0 && (in_metres(fe) || in_metres(fn_));
            let (fe, fn_) = if metres { (fe, fn_) } else { (fe * to_m, fn_ * to_m) };
            let lon0 = num(3080).or(num(3084)).or(num(3088)).unwrap_or(0.0);
            let lat0 = num(3081).or(num(3085)).or(num(3089)).unwrap_or(0.0);
            let k = num(3092).or(num(3093)).unwrap_or(1.0);
            let body = match code(3075)? {
                1 => format!("+proj=tmerc +lat_0={lat0} +lon_0={lon0} +k={k}"),
                8 => format!(
                    "+proj=lcc +lat_1={} +lat_2={} +lat_0={lat0} +lon_0={lon0}",
                    p(3078),
                    num(3079).unwrap_or(p(3078))
                ),
                9 => format!("+proj=lcc +lat_1={lat0} +lat_0={lat0} +lon_0={lon0} +k={k}"),
                7 => match num(3078) {
                    Some(ts) => format!("+proj=merc +lat_ts={ts} +lon_0={lon0}"),
                    None => format!("+proj=merc +lon_0={lon0} +k={k}"),
                },
                11 => format!(
                    "+proj=aea +lat_1={} +lat_2={} +lat_0={lat0} +lon_0={lon0}",
                    p(3078),
                    num(3079).unwrap_or(p(3078))
                ),
                16 => format!("+proj=sterea +lat_0={lat0} +lon_0={lon0} +k={k}"),
                10 => format!("+proj=laea +lat_0={lat0} +lon_0={lon0}"),
                _ => return None,
            };
            format!("{body} +x_0={fe} +y_0={fn_}")
        }
    };
    Some(Ok(wkt::Proj4Crs {
        proj4: format!("{proj} +to_meter={to_m} {datum} +no_defs"),
        z_to_meter: z,
        geographic: false,
        name,
    }))
}

impl Globe {
    /// The globe of the CRS records `crs`: `Ok(None)` when there are none, an error naming
    /// the CRS when it cannot be transformed.
    pub fn of_records(crs: &CrsRecords) -> Result<Option<Globe>, String> {
        if crs.is_empty() {
            return Ok(None);
        }
        let info = crs.describe();
        // Records that name no CRS (no key directory entries, or only units: PDAL's
        // 1.2-empty-geotiff-vlrs.las): no CRS.
        let names_one = info.geokeys.iter().any(|k| {
            matches!(k.id, 1024 | 2048 | 2050 | 2056 | 2057 | 3072 | 3074 | 3075) && k.value != "0"
        });
        if info.wkt.is_none() && info.epsg.is_none() && !names_one {
            return Ok(None);
        }
        Globe::of_info(&info).map(Some)
    }

    fn of_info(info: &CrsInfo) -> Result<Globe, String> {
        let name = info.name.clone().unwrap_or_else(|| info.summary());
        let node = info.wkt.as_deref().map(wkt::parse);
        // The WKT's parameters first (its EPSG code where it names one); else the EPSG code of
        // the records (GeoTIFF keys, or a WKT 2 that names its code).
        let from_wkt = match &node {
            Some(Ok(n)) => Some(wkt::to_proj4(n, &epsg_proj4)),
            Some(Err(e)) => {
                Some(Err(wkt::unsupported(&name, format_args!("its WKT does not parse ({e})"))))
            }
            None => None,
        };
        let def = match (from_wkt, info.epsg) {
            (Some(Ok(def)), _) => def,
            (from_wkt, Some(code)) if epsg_proj4(code).is_some() => {
                let proj4 = epsg_proj4(code).unwrap_or_default();
                let geographic = proj4.contains("+proj=longlat") || proj4.contains("+proj=latlong");
                let h_unit = if geographic { 1.0 } else { epsg_unit(code).unwrap_or(1.0) };
                let key = |id: u16| {
                    info.geokeys.iter().find(|k| k.id == id).and_then(|k| k.value.parse::<u32>().ok())
                };
                let wkt_vertical = match (&node, from_wkt) {
                    (Some(Ok(n)), _) => wkt::vertical_unit(n),
                    _ => None,
                };
                let z = wkt_vertical
                    .or_else(|| info.vertical_epsg.and_then(epsg_unit))
                    .or_else(|| key(4099).and_then(geotiff_unit))
                    .unwrap_or(h_unit);
                wkt::Proj4Crs { proj4, z_to_meter: z, geographic, name: name.clone() }
            }
            (from_wkt, epsg) => match (geotiff_projection(info), from_wkt, epsg) {
                (Some(g), _, _) => g?,
                (None, Some(Err(e)), _) => return Err(e),
                (None, _, Some(code)) => {
                    return Err(wkt::unsupported(
                        &name,
                        format_args!("EPSG:{code} is not in the EPSG definitions mortar carries (give another with --assign-crs EPSG:code)"),
                    ))
                }
                (None, _, None) => {
                    return Err(wkt::unsupported(
                        &name,
                        "its GeoTIFF keys give no EPSG code and no projection mortar reads (give it one with --assign-crs EPSG:code)",
                    ))
                }
            },
        };
        Globe::from_proj4(def)
    }

    /// The globe of a PROJ.4 definition.
    pub fn from_proj4(def: wkt::Proj4Crs) -> Result<Globe, String> {
        let src = Proj::from_proj_string(&def.proj4).map_err(|e| {
            wkt::unsupported(&def.name, format_args!("{e} (PROJ.4: {})", def.proj4))
        })?;
        let dst = Proj::from_proj_string("+proj=longlat +datum=WGS84 +no_defs").expect("WGS 84");
        if src.is_geocent() {
            return Err(wkt::unsupported(
                &def.name,
                "it is geocentric; give its points as ECEF are not supported",
            ));
        }
        Ok(Globe {
            src,
            dst,
            geographic: def.geographic,
            xy_to_radians: if def.geographic { std::f64::consts::PI / 180.0 } else { 1.0 },
            z_to_meter: def.z_to_meter,
            name: def.name,
            proj4: def.proj4,
        })
    }

    /// Longitude and latitude (radians, WGS 84) and ellipsoidal height (metres) of `p`.
    pub fn geodetic(&self, p: [f64; 3]) -> Result<[f64; 3], String> {
        if self.geographic && !(p[1].abs() <= 90.0 && p[0].abs() <= 540.0) {
            return Err(format!(
                "({}, {}) is not a longitude and latitude in degrees, which the CRS {} says the points are (is the CRS wrong? give the right one with --assign-crs EPSG:code)",
                p[0], p[1], self.name
            ));
        }
        let mut t = (p[0] * self.xy_to_radians, p[1] * self.xy_to_radians, p[2] * self.z_to_meter);
        proj4rs::transform::transform(&self.src, &self.dst, &mut t).map_err(|e| {
            format!("({}, {}, {}) cannot be transformed from {}: {e}", p[0], p[1], p[2], self.name)
        })?;
        // The height passes the datum shift unchanged, as in PROJ for CRSs without a vertical
        // part (its pipelines `push v_3` around the Helmert): only latitude and longitude move.
        t.2 = p[2] * self.z_to_meter;
        if !(t.0.is_finite() && t.1.is_finite() && t.2.is_finite()) {
            return Err(format!(
                "({}, {}, {}) has no place on the globe in {}",
                p[0], p[1], p[2], self.name
            ));
        }
        Ok([t.0, t.1, t.2])
    }

    /// ECEF (EPSG:4978, metres) of world coordinates `p` in the dataset's CRS.
    pub fn ecef(&self, p: [f64; 3]) -> Result<[f64; 3], String> {
        Ok(ecef_of_geodetic(self.geodetic(p)?))
    }

    /// Whether x and y are degrees.
    pub fn is_geographic(&self) -> bool {
        self.geographic
    }
}

/// ECEF of WGS 84 longitude, latitude (radians) and ellipsoidal height (metres).
pub fn ecef_of_geodetic(g: [f64; 3]) -> [f64; 3] {
    let (lon, lat, h) = (g[0], g[1], g[2]);
    let (sl, cl) = lat.sin_cos();
    let n = WGS84_A / (1.0 - WGS84_E2 * sl * sl).sqrt();
    [(n + h) * cl * lon.cos(), (n + h) * cl * lon.sin(), (n * (1.0 - WGS84_E2) + h) * sl]
}

/// A local east-north-up frame: its origin in ECEF and its axes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Enu {
    pub origin: [f64; 3],
    /// East, north and up as unit vectors in ECEF.
    pub axes: [[f64; 3]; 3],
}

impl Enu {
    /// The frame at geodetic position `g` (longitude, latitude in radians, height in metres).
    pub fn at(g: [f64; 3]) -> Enu {
        let (so, co) = g[0].sin_cos();
        let (sa, ca) = g[1].sin_cos();
        Enu {
            origin: ecef_of_geodetic(g),
            axes: [[-so, co, 0.0], [-sa * co, -sa * so, ca], [ca * co, ca * so, sa]],
        }
    }
    /// Local coordinates of an ECEF position.
    #[inline]
    pub fn local(&self, e: [f64; 3]) -> [f64; 3] {
        let d = [e[0] - self.origin[0], e[1] - self.origin[1], e[2] - self.origin[2]];
        self.axes.map(|a| a[0] * d[0] + a[1] * d[1] + a[2] * d[2])
    }
    /// The 4x4 matrix from the local frame to ECEF, column-major (3D Tiles' `transform`).
    pub fn to_ecef_matrix(&self) -> [f64; 16] {
        let [e, n, u] = self.axes;
        let o = self.origin;
        [e[0], e[1], e[2], 0.0, n[0], n[1], n[2], 0.0, u[0], u[1], u[2], 0.0, o[0], o[1], o[2], 1.0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn globe(proj4: &str, z: f64, geographic: bool) -> Globe {
        Globe::from_proj4(wkt::Proj4Crs {
            proj4: proj4.into(),
            z_to_meter: z,
            geographic,
            name: "t".into(),
        })
        .unwrap()
    }

    #[test]
    fn utm_and_geographic_agree_with_proj() {
        let g = globe("+proj=utm +zone=10 +datum=WGS84 +units=m +no_defs", 1.0, false);
        let e = g.ecef([500000.0, 4000000.0, 100.0]).unwrap();
        // lon -123, lat from the inverse: the point lies on the central meridian.
        let geo = g.geodetic([500000.0, 4000000.0, 100.0]).unwrap();
        assert!((geo[0].to_degrees() + 123.0).abs() < 1e-9);
        assert!((geo[2] - 100.0).abs() < 1e-6);
        let r = (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt();
        assert!((6_360_000.0..6_380_000.0).contains(&r), "{r}");
        // Degrees in, the same place.
        let d = globe("+proj=longlat +datum=WGS84 +no_defs", 1.0, true);
        let e2 = d.ecef([geo[0].to_degrees(), geo[1].to_degrees(), 100.0]).unwrap();
        for a in 0..3 {
            assert!((e[a] - e2[a]).abs() < 1e-6, "{e:?} {e2:?}");
        }
    }

    fn near(a: [f64; 3], b: [f64; 3], tol: f64) {
        let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
        assert!(d <= tol, "{a:?} vs {b:?}: {d} m");
    }

    /// Against pyproj 3.8 (PROJ 9.x, no grids), `Transformer.from_crs(crs, 4978, always_xy=True)`.
    #[test]
    fn real_crss_agree_with_pyproj() {
        let w = r#"PROJCS["NAD_1983_HARN_Lambert_Conformal_Conic",GEOGCS["GCS_North_American_1983_HARN",DATUM["NAD83_High_Accuracy_Regional_Network",SPHEROID["GRS_1980",6378137,298.257222101,AUTHORITY["EPSG","7019"]],AUTHORITY["EPSG","6152"]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Lambert_Conformal_Conic_2SP"],PARAMETER["standard_parallel_1",43],PARAMETER["standard_parallel_2",45.5],PARAMETER["latitude_of_origin",41.75],PARAMETER["central_meridian",-120.5],PARAMETER["false_easting",1312335.958005249],PARAMETER["false_northing",0],UNIT["foot",0.3048,AUTHORITY["EPSG","9002"]]]"#;
        let info =
            CrsInfo { wkt: Some(w.into()), name: Some("autzen".into()), ..CrsInfo::default() };
        let g = Globe::of_info(&info).unwrap();
        // z is in feet here (the horizontal unit), pyproj was given 400 ft as metres. PROJ's
        // default is "NAD83(HARN) to WGS 84 (3)" (a Helmert, 1 m accuracy); mortar takes the
        // null transformation "NAD83(HARN) to WGS 84 (1)" (2 m accuracy), equal to the mm.
        let p = g.ecef([637000.0, 849000.0, 400.0]).unwrap();
        near(p, [-2505489.341525898, -3847875.101867256, 4412184.205149691], 0.001);
        near(p, [-2505490.067513772, -3847874.1320473496, 4412184.635772115], 2.0);
        let utm = CrsInfo { epsg: Some(32605), ..CrsInfo::default() };
        near(
            Globe::of_info(&utm).unwrap().ecef([200000.0, 2200000.0, 10.0]).unwrap(),
            [-5476072.307521426, -2453613.9952781145, 2154503.5796139333],
            0.001,
        );
        // Amersfoort / RD New: PROJ picks another Helmert ("Amersfoort to WGS 84 (9)") than the
        // +towgs84 of the EPSG PROJ.4 string; they differ by decimetres.
        let rd = CrsInfo { epsg: Some(28992), ..CrsInfo::default() };
        near(
            Globe::of_info(&rd).unwrap().ecef([85000.0, 446000.0, 10.0]).unwrap(),
            [3923716.0429577995, 299701.4688492099, 5002671.620536937],
            1.0,
        );
        let none = CrsInfo { kind: "geotiff".into(), ..CrsInfo::default() };
        assert!(Globe::of_info(&none).err().unwrap().contains("--assign-crs"));
    }

    #[test]
    fn enu_is_orthonormal_and_inverts() {
        let f = Enu::at([(-123.0f64).to_radians(), 44.0f64.to_radians(), 120.0]);
        for i in 0..3 {
            for j in 0..3 {
                let d: f64 = (0..3).map(|k| f.axes[i][k] * f.axes[j][k]).sum();
                assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        assert_eq!(f.local(f.origin), [0.0, 0.0, 0.0]);
        let up = ecef_of_geodetic([(-123.0f64).to_radians(), 44.0f64.to_radians(), 220.0]);
        let l = f.local(up);
        assert!(l[0].abs() < 1e-6 && l[1].abs() < 1e-6 && (l[2] - 100.0).abs() < 1e-6, "{l:?}");
    }
}
