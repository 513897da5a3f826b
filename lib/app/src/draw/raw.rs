//! Raw LAS/LAZ points for the progressive renderers of paper 000 ([`mortar_core::render::progressive`]):
//! parallel loading that hands over points as they are decoded
//! (§3.2: "files are loaded and transformed to GPU-ready buffers in parallel, and the task of the
//! main thread is simplified to sending batches that are ready"), and the colours of the visible
//! points.
//!
//! Each point carries one 64-bit payload: the raw value the colour mode needs, kept in its
//! original form as the paper keeps attributes (§3.1, §3.5), and turned into a colour only for the
//! points that won a pixel, with the same rules as [`super::batch::colors_for_keys`] (so a
//! converged progressive image is coloured like `mortar render`'s): RGB with the dataset's 8/16-bit
//! decision, scalar modes over the 1st to 99th percentile of the visible points.

use super::color::{quantile, ColorChoice};
use mortar_core::color::RgbDepth;
use mortar_core::grid::Grid;
use mortar_core::layout::{read_xyz, Family, RecordLayout};
use mortar_core::render::resolve::{
    classification_color, elevation_color, gps_time_color, intensity_color, return_number_color,
    rgb_color, ColorMode,
};
use mortar_io::dataset::Dataset;
use mortar_io::error::{Error, RenderError, Result};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// Points of all pieces of all inputs (what the progressive renderers allocate for).
pub fn point_count(ds: &Dataset) -> u64 {
    ds.inputs.iter().flat_map(|s| s.pieces()).map(|p| p.points).sum()
}

/// What each point's payload holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Payload {
    /// The 16-bit RGB in bits 0-47 and the intensity in bits 48-63 (`auto`, `stored`, `rgb`).
    RgbIntensity {
        /// Record offset of the RGB field.
        offset: usize,
    },
    /// The intensity.
    Intensity,
    /// The classification code.
    Classification,
    /// Return number in bits 0-7, number of returns in bits 8-15.
    ReturnNumber,
    /// The GPS time's f64 bits.
    GpsTime {
        /// Record offset of the GPS time.
        offset: usize,
    },
    /// The integer z (as `i32` bits).
    Elevation,
}

/// The payload a colour choice needs from records of `layout`; an error (naming `path`) when the
/// point format lacks the field.
pub fn payload_for(
    layout: &RecordLayout,
    choice: ColorChoice,
    path: &std::path::Path,
) -> Result<Payload> {
    let rgb = layout.attribute("rgb").map(|a| a.offset);
    Ok(match choice {
        ColorChoice::Auto | ColorChoice::Stored => match rgb {
            Some(offset) => Payload::RgbIntensity { offset },
            None => Payload::Intensity,
        },
        ColorChoice::Mode(ColorMode::Rgb) => match rgb {
            Some(offset) => Payload::RgbIntensity { offset },
            None => {
                return Err(Error::Render {
                    path: path.to_path_buf(),
                    error: RenderError::NoColour { format: layout.format, has_rgb: false },
                })
            }
        },
        ColorChoice::Mode(ColorMode::Intensity) => Payload::Intensity,
        ColorChoice::Mode(ColorMode::Classification) => Payload::Classification,
        ColorChoice::Mode(ColorMode::ReturnNumber) => Payload::ReturnNumber,
        ColorChoice::Mode(ColorMode::Elevation) => Payload::Elevation,
        ColorChoice::Mode(ColorMode::GpsTime) => match layout.attribute("gps_time") {
            Some(a) => Payload::GpsTime { offset: a.offset },
            None => {
                return Err(Error::Render {
                    path: path.to_path_buf(),
                    error: RenderError::MissingAttribute {
                        mode: "gps-time",
                        attribute: "gps_time",
                        format: layout.format,
                        not_kept: false,
                    },
                })
            }
        },
    })
}

/// The points of one piece, decoded.
#[derive(Clone, Debug, Default)]
pub struct LoadedPiece {
    /// Index of the first point among all points of the dataset.
    pub first: u64,
    /// Integer coordinates on the merged grid.
    pub xyz: Vec<[i32; 3]>,
    /// One payload per point.
    pub payload: Vec<u64>,
    /// Largest RGB component (0 without RGB).
    pub max_rgb: u16,
    /// Largest intensity.
    pub max_intensity: u16,
    /// Seconds spent reading and decoding the piece.
    pub seconds: f64,
}

/// Takes a piece's records apart into coordinates and payloads.
fn split(records: &[u8], layout: &RecordLayout, payload: Payload, out: &mut LoadedPiece) {
    let family = layout.family();
    let n = records.len() / layout.record_len;
    out.xyz.reserve(n);
    out.payload.reserve(n);
    for r in records.chunks_exact(layout.record_len) {
        let xyz = read_xyz(r);
        out.xyz.push(xyz);
        let u16_at = |o: usize| u16::from_le_bytes([r[o], r[o + 1]]);
        let intensity = u16_at(12);
        out.max_intensity = out.max_intensity.max(intensity);
        let v = match payload {
            Payload::RgbIntensity { offset } => {
                let c = [u16_at(offset), u16_at(offset + 2), u16_at(offset + 4)];
                out.max_rgb = out.max_rgb.max(c[0]).max(c[1]).max(c[2]);
                c[0] as u64 | (c[1] as u64) << 16 | (c[2] as u64) << 32 | (intensity as u64) << 48
            }
            Payload::Intensity => intensity as u64,
            Payload::Classification => layout.classification(r) as u64,
            Payload::ReturnNumber => {
                let (rn, n) = match family {
                    Family::Legacy => (r[14] & 0x07, (r[14] >> 3) & 0x07),
                    Family::Extended => (r[14] & 0x0f, r[14] >> 4),
                };
                rn as u64 | (n as u64) << 8
            }
            Payload::GpsTime { offset } => {
                u64::from_le_bytes(r[offset..offset + 8].try_into().expect("8 bytes"))
            }
            Payload::Elevation => xyz[2] as u32 as u64,
        };
        out.payload.push(v);
    }
}

/// Decodes every piece of `ds` on the calling thread, in order, into one [`LoadedPiece`] whose
/// first point is `first` (a viewer's node: one COPC chunk or EPT file).
pub fn load_all(ds: &Dataset, payload: Payload, first: u64) -> Result<LoadedPiece> {
    let t = Instant::now();
    let mut out = LoadedPiece { first, ..LoadedPiece::default() };
    for p in ds.pieces() {
        let records = ds.read_piece(&p)?;
        split(&records, &ds.layout, payload, &mut out);
    }
    out.seconds = t.elapsed().as_secs_f64();
    Ok(out)
}

/// Decodes every piece of `ds` on a pool of `threads` threads of its own (so that decoding does
/// not queue behind the renderer's work on the global pool, nor the renderer behind it) and hands
/// each to `deliver` as soon as it is ready, in no particular order. Stops early when `cancel` is
/// set or `deliver` returns `false`; a piece that fails is delivered as an error, and no further
/// pieces are started after it.
pub fn load_pieces(
    ds: &Dataset,
    payload: Payload,
    threads: usize,
    cancel: &AtomicBool,
    deliver: impl Fn(Result<LoadedPiece>) -> bool + Sync,
) -> Result<()> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads.max(1))
        .thread_name(|i| format!("mortar-load-{i}"))
        .build()
        .map_err(|error| Error::ThreadPool { threads, error })?;
    let mut firsts = Vec::with_capacity(ds.inputs.len());
    let mut first = 0u64;
    for src in &ds.inputs {
        firsts.push(first);
        first += src.pieces().iter().map(|p| p.points).sum::<u64>();
    }
    let pieces = ds.pieces();
    let layout = &ds.layout;
    pool.install(|| {
        pieces.par_iter().with_max_len(1).for_each(|p| {
            if cancel.load(Ordering::Relaxed) {
                return;
            }
            let t = Instant::now();
            let result = ds.read_piece(p).map(|records| {
                let mut out = LoadedPiece {
                    first: firsts[p.input] + p.piece.first_point,
                    ..LoadedPiece::default()
                };
                split(&records, layout, payload, &mut out);
                out.seconds = t.elapsed().as_secs_f64();
                out
            });
            let failed = result.is_err();
            if !deliver(result) || failed {
                cancel.store(true, Ordering::Relaxed);
            }
        })
    });
    Ok(())
}

/// The dataset-level colour decisions, from what was loaded so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ColorStats {
    /// Largest RGB component.
    pub max_rgb: u16,
    /// Largest intensity.
    pub max_intensity: u16,
}

impl ColorStats {
    /// Adds a piece's maxima.
    pub fn add(&mut self, p: &LoadedPiece) {
        self.max_rgb = self.max_rgb.max(p.max_rgb);
        self.max_intensity = self.max_intensity.max(p.max_intensity);
    }
}

/// The colour mode `choice` stands for with these statistics (`Auto`: RGB when some RGB value is
/// not zero, else intensity; `Stored` stays `Stored`), as [`ColorChoice::resolved`] decides for a
/// batch file.
pub fn resolve_choice(choice: ColorChoice, payload: Payload, stats: &ColorStats) -> ColorChoice {
    match choice {
        ColorChoice::Auto
            if matches!(payload, Payload::RgbIntensity { .. }) && stats.max_rgb > 0 =>
        {
            ColorChoice::Mode(ColorMode::Rgb)
        }
        ColorChoice::Auto => ColorChoice::Mode(ColorMode::Intensity),
        c => c,
    }
}

/// The range scalar colour modes map over when none is given, for points with payloads
/// `payloads` (all the points: the rule of every renderer, view-independent, as
/// [`super::batch::color_range`] takes it for a batch file): the 1st to 99th percentile
/// of their values; `None` for modes without a range.
pub fn payload_range(
    payloads: &[u64],
    choice: ColorChoice,
    payload: Payload,
    stats: &ColorStats,
    grid: &Grid,
) -> Option<[f64; 2]> {
    let choice = resolve_choice(choice, payload, stats);
    if !matches!(
        choice,
        ColorChoice::Mode(ColorMode::Intensity | ColorMode::Elevation | ColorMode::GpsTime)
    ) {
        return None;
    }
    let mut v: Vec<f64> = payloads
        .par_iter()
        .map(|&p| scalar_value(p, choice, payload, grid))
        .filter(|x| x.is_finite())
        .collect();
    Some([quantile(&mut v, 0.01).unwrap_or(0.0), quantile(&mut v, 0.99).unwrap_or(1.0)])
}

/// The scalar a payload stands for in a scalar colour mode (intensity, elevation, GPS time).
fn scalar_value(v: u64, choice: ColorChoice, payload: Payload, grid: &Grid) -> f64 {
    match choice {
        ColorChoice::Mode(ColorMode::Intensity) => match payload {
            Payload::RgbIntensity { .. } => (v >> 48) as u16 as f64,
            _ => v as u16 as f64,
        },
        ColorChoice::Mode(ColorMode::Elevation) => grid.world(2, v as u32 as i32 as i64),
        _ => f64::from_bits(v),
    }
}

/// The colours of the points with payloads `payloads` (the visible ones), in colour mode `choice`
/// (resolved with [`resolve_choice`]); scalar modes over `range` (the renderers pass
/// [`payload_range`] of all the points when none is given) or the 1st to 99th percentile of
/// these points. Returns the colours and the range used.
pub fn payload_colors(
    payloads: &[u64],
    choice: ColorChoice,
    payload: Payload,
    stats: &ColorStats,
    grid: &Grid,
    range: Option<[f64; 2]>,
) -> (Vec<u32>, Option<[f64; 2]>) {
    let choice = resolve_choice(choice, payload, stats);
    let depth = RgbDepth::detect(stats.max_rgb);
    let rgb = |v: u64| rgb_color([v as u16, (v >> 16) as u16, (v >> 32) as u16], depth);
    let intensity = |v: u64| match payload {
        Payload::RgbIntensity { .. } => (v >> 48) as u16,
        _ => v as u16,
    };
    let scalar = |v: u64| scalar_value(v, choice, payload, grid);
    match choice {
        ColorChoice::Mode(ColorMode::Intensity | ColorMode::Elevation | ColorMode::GpsTime) => {
            let range = range.unwrap_or_else(|| {
                let mut v: Vec<f64> =
                    payloads.iter().map(|&p| scalar(p)).filter(|x| x.is_finite()).collect();
                [quantile(&mut v, 0.01).unwrap_or(0.0), quantile(&mut v, 0.99).unwrap_or(1.0)]
            });
            let colors = payloads
                .par_iter()
                .map(|&p| match choice {
                    ColorChoice::Mode(ColorMode::Intensity) => intensity_color(intensity(p), range),
                    ColorChoice::Mode(ColorMode::Elevation) => elevation_color(scalar(p), range),
                    _ => gps_time_color(scalar(p), range),
                })
                .collect();
            (colors, Some(range))
        }
        _ => {
            let colors = payloads
                .par_iter()
                .map(|&p| match choice {
                    ColorChoice::Mode(ColorMode::Classification) => classification_color(p as u8),
                    ColorChoice::Mode(ColorMode::ReturnNumber) => {
                        return_number_color(p as u8, (p >> 8) as u8)
                    }
                    // Stored: RGB when some RGB value is not zero, else grey from intensity over
                    // the whole range (mortar_core::color::ColorSource).
                    ColorChoice::Stored
                        if !(matches!(payload, Payload::RgbIntensity { .. })
                            && stats.max_rgb > 0) =>
                    {
                        let i = intensity(p) as u32;
                        let g = if stats.max_intensity == 0 {
                            255
                        } else {
                            (i * 255 / stats.max_intensity as u32).min(255)
                        };
                        g | (g << 8) | (g << 16) | (255 << 24)
                    }
                    _ => rgb(p),
                })
                .collect();
            (colors, None)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mortar_core::color::ColorSource;

    fn record(
        layout: &RecordLayout,
        xyz: [i32; 3],
        intensity: u16,
        rgb: [u16; 3],
        flags: u8,
        class: u8,
    ) -> Vec<u8> {
        let mut r = vec![0u8; layout.record_len];
        for a in 0..3 {
            r[4 * a..4 * a + 4].copy_from_slice(&xyz[a].to_le_bytes());
        }
        r[12..14].copy_from_slice(&intensity.to_le_bytes());
        r[14] = flags;
        r[15] = class;
        if let Some(a) = layout.attribute("rgb") {
            for c in 0..3 {
                r[a.offset + 2 * c..a.offset + 2 * c + 2].copy_from_slice(&rgb[c].to_le_bytes());
            }
        }
        r
    }

    #[test]
    fn payloads_and_colours_follow_the_batch_file_rules() {
        let layout = RecordLayout::new(3, 34).unwrap();
        let recs: Vec<u8> = [
            record(&layout, [1, 2, 3], 100, [0x1000, 0x2000, 0xff00], 0b0001_0001, 2),
            record(&layout, [4, 5, -6], 300, [0x0100, 0, 0], 0b0001_0010, 6),
        ]
        .concat();
        let rgb = payload_for(&layout, ColorChoice::Auto, "x".as_ref()).unwrap();
        let mut p = LoadedPiece::default();
        split(&recs, &layout, rgb, &mut p);
        assert_eq!(p.xyz, [[1, 2, 3], [4, 5, -6]]);
        assert_eq!((p.max_rgb, p.max_intensity), (0xff00, 300));
        let mut stats = ColorStats::default();
        stats.add(&p);
        let grid = Grid { scale: [0.5; 3], offset: [0.0; 3] };
        // RGB: the stored colour of a batch file (ColorSource::rgba with the dataset's depth).
        let (c, range) = payload_colors(&p.payload, ColorChoice::Auto, rgb, &stats, &grid, None);
        let source = ColorSource::Rgb { offset: 28, depth: RgbDepth::detect(0xff00) };
        assert_eq!(c, [source.rgba(&recs[..34]), source.rgba(&recs[34..])]);
        assert_eq!(range, None);
        // All RGB zero: auto is intensity over the visible range, stored is grey over the max.
        let zero = ColorStats { max_rgb: 0, ..stats };
        assert_eq!(
            resolve_choice(ColorChoice::Auto, rgb, &zero),
            ColorChoice::Mode(ColorMode::Intensity)
        );
        let (c, range) = payload_colors(&p.payload, ColorChoice::Auto, rgb, &zero, &grid, None);
        assert_eq!(range, Some([100.0, 300.0]));
        assert_eq!(c, [intensity_color(100, [100.0, 300.0]), intensity_color(300, [100.0, 300.0])]);
        let (c, _) = payload_colors(&p.payload, ColorChoice::Stored, rgb, &zero, &grid, None);
        assert_eq!(c[1], ColorSource::Intensity { max_intensity: 300 }.rgba(&recs[34..]));
        // Elevation from the integer z on the grid, with a given range.
        let el =
            payload_for(&layout, ColorChoice::Mode(ColorMode::Elevation), "x".as_ref()).unwrap();
        let mut q = LoadedPiece::default();
        split(&recs, &layout, el, &mut q);
        let (c, _) = payload_colors(
            &q.payload,
            ColorChoice::Mode(ColorMode::Elevation),
            el,
            &stats,
            &grid,
            Some([-3.0, 1.5]),
        );
        assert_eq!(c, [elevation_color(1.5, [-3.0, 1.5]), elevation_color(-3.0, [-3.0, 1.5])]);
        // Return numbers and classes.
        let rn =
            payload_for(&layout, ColorChoice::Mode(ColorMode::ReturnNumber), "x".as_ref()).unwrap();
        let mut q = LoadedPiece::default();
        split(&recs, &layout, rn, &mut q);
        let (c, _) = payload_colors(
            &q.payload,
            ColorChoice::Mode(ColorMode::ReturnNumber),
            rn,
            &stats,
            &grid,
            None,
        );
        assert_eq!(c, [return_number_color(1, 2), return_number_color(2, 2)]);
        let cl = payload_for(&layout, ColorChoice::Mode(ColorMode::Classification), "x".as_ref())
            .unwrap();
        let mut q = LoadedPiece::default();
        split(&recs, &layout, cl, &mut q);
        assert_eq!(q.payload, [2, 6]);
        // Fields the format lacks are refused with the file's name.
        let plain = RecordLayout::new(0, 20).unwrap();
        let e = payload_for(&plain, ColorChoice::Mode(ColorMode::Rgb), "f.las".as_ref())
            .unwrap_err()
            .to_string();
        assert!(e.contains("f.las") && e.contains("no RGB"), "{e}");
        assert!(
            payload_for(&plain, ColorChoice::Mode(ColorMode::GpsTime), "f.las".as_ref()).is_err()
        );
        assert_eq!(
            payload_for(&plain, ColorChoice::Auto, "f.las".as_ref()).unwrap(),
            Payload::Intensity
        );
    }
}
