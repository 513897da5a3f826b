//! A seeded generator of synthetic airborne-like scans, for benchmarks at sizes no fixture has
//! (the fixtures stop near 1 M points). Deterministic: the same seed and size give the same file.
//!
//! The scene: rolling terrain (sum of sines) with blocky buildings and round tree crowns, sampled
//! along zig-zag scan lines like an airborne strip, with GPS time increasing along the scan,
//! intensity and RGB derived from height and class. Points are LAS point format 3 records.
//!
//! Hostile shapes for the memory budget's tests and benchmarks (the stress cases of
//! copc_converter's CI): every point at one position ([`Shape::Coincident`]), a uniform cube
//! ([`Shape::Cube`]), every record eight times ([`Shape::Duplicates`]), wide extra bytes
//! ([`SynthOptions::extra_bytes`], described by an Extra Bytes VLR) and LAZ chunks of any size
//! ([`write_file`]'s `laz_chunk`, e.g. one chunk for the whole file).

use crate::dataset::SourceMeta;
use crate::error::Result;
use crate::las::{Header, Vlr};
use crate::sink_las::{LasSink, Target};
use crate::sort::{OrderedSink, PieceStats};
use mortar_core::layout::RecordLayout;
use rayon::prelude::*;

/// Where the points are.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Shape {
    /// The airborne-like scene (terrain, buildings, trees along scan lines).
    #[default]
    Airborne,
    /// Every point at the scene's centre (attributes still differ from point to point).
    Coincident,
    /// Uniform in a cube of the extent's side.
    Cube,
    /// The airborne scene with every record written eight times in a row, byte for byte.
    Duplicates,
}

/// What to generate.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    pub points: u64,
    pub seed: u64,
    /// Side of the square scene in metres.
    pub extent: f64,
    pub scale: f64,
    /// World position of the scene's corner (e.g. 6.4e6 for ECEF-scale coordinates).
    pub origin: [f64; 3],
    pub shape: Shape,
    /// Extra bytes per record (after the 34 of point format 3), at most 255: one undocumented
    /// extra-bytes field, filled with bytes that differ from point to point.
    pub extra_bytes: usize,
}

impl Default for SynthOptions {
    fn default() -> Self {
        SynthOptions {
            points: 1_000_000,
            seed: 1,
            extent: 1000.0,
            scale: 0.001,
            origin: [500_000.0, 5_000_000.0, 0.0],
            shape: Shape::Airborne,
            extra_bytes: 0,
        }
    }
}

impl SynthOptions {
    /// The record layout of the generated points.
    pub fn layout(&self) -> RecordLayout {
        RecordLayout::new(3, 34 + self.extra_bytes).expect("point format 3 with extra bytes")
    }
}

/// The Extra Bytes VLR (LAS 1.4 R15 §2.5) of `n` undocumented bytes (data type 0, options: size).
fn extra_bytes_vlr(n: usize) -> Vlr {
    let mut d = vec![0u8; 192];
    d[2] = 0;
    d[3] = n as u8;
    d[4..4 + 5].copy_from_slice(b"synth");
    d[160..160 + 17].copy_from_slice(b"mortar-gen filler");
    let mut user_id = [0u8; 16];
    user_id[..9].copy_from_slice(b"LASF_Spec");
    Vlr { reserved: 0, user_id, record_id: 4, description: [0; 32], data: d }
}

/// Writes the generated points to `output` (LAS, or LAZ by the extension; `laz_chunk` points
/// per LAZ chunk, default 50,000), through the LAS writer (temporary name, then rename).
pub fn write_file(o: &SynthOptions, output: &str, laz_chunk: Option<u32>) -> Result<()> {
    let mut header = header(o);
    let layout = o.layout();
    header.record_len = layout.record_len as u16;
    let grid = mortar_core::grid::Grid { scale: header.scale, offset: header.offset };
    let vlrs = if o.extra_bytes > 0 { vec![extra_bytes_vlr(o.extra_bytes)] } else { Vec::new() };
    let template = SourceMeta { header, vlrs, evlrs: Vec::new(), layout, grid };
    let compressed = output.to_ascii_lowercase().ends_with(".laz");
    let mut sink =
        LasSink::new(Target::parse(output), compressed, template, &std::env::temp_dir())?;
    if let Some(n) = laz_chunk {
        sink.laz_chunk_size(n);
    }
    // statistics first (the header needs bounds), then the points
    let step = 1u64 << 22;
    let mut total = PieceStats::default();
    let mut first = 0;
    while first < o.points {
        let n = step.min(o.points - first);
        total.merge(&records(o, first, n).1);
        first += n;
    }
    sink.begin(&total.summary())?;
    let mut first = 0;
    while first < o.points {
        let n = step.min(o.points - first);
        sink.write(&records(o, first, n).0)?;
        first += n;
    }
    sink.finish()?;
    Ok(())
}

fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

fn unit(h: u64) -> f64 {
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Height and class at (x, y) in scene metres.
fn surface(x: f64, y: f64, seed: u64) -> (f64, u8) {
    let ground =
        30.0 + 8.0 * (x / 97.0).sin() * (y / 131.0).cos() + 3.0 * (x / 23.0 + y / 41.0).sin();
    let cell = 40.0;
    let (cx, cy) = ((x / cell).floor() as i64, (y / cell).floor() as i64);
    let h =
        mix(seed ^ (cx as u64).wrapping_mul(0x9e37_79b9) ^ (cy as u64).wrapping_mul(0x85eb_ca6b));
    let (fx, fy) = (x / cell - cx as f64, y / cell - cy as f64);
    match h % 5 {
        0 if (0.2..0.8).contains(&fx) && (0.25..0.75).contains(&fy) => {
            (ground + 6.0 + (h >> 8) as f64 % 15.0, 6)
        }
        1 | 2 => {
            let (tx, ty) = (0.3 + 0.4 * unit(h >> 3), 0.3 + 0.4 * unit(h >> 7));
            let r = ((fx - tx).powi(2) + (fy - ty).powi(2)).sqrt() * cell;
            let crown = 5.0 + (h >> 12) as f64 % 4.0;
            if r < crown {
                (ground + 12.0 + (crown * crown - r * r).sqrt(), 5)
            } else {
                (ground, 2)
            }
        }
        _ => (ground, 2),
    }
}

/// The header of a generated file (LAS 1.2, point format 3).
pub fn header(o: &SynthOptions) -> Header {
    let mut sw = [0u8; 32];
    sw[..13].copy_from_slice(b"mortar-synth ");
    Header {
        version: (1, 2),
        file_source_id: 0,
        global_encoding: 0,
        guid: [0; 16],
        system_identifier: [0; 32],
        generating_software: sw,
        creation_day: 1,
        creation_year: 2026,
        header_size: 227,
        offset_to_point_data: 227,
        number_of_vlrs: 0,
        point_format: 3,
        compressed: false,
        record_len: 34,
        point_count: o.points,
        points_by_return: [0; 15],
        scale: [o.scale; 3],
        offset: o.origin,
        min: o.origin,
        max: [o.origin[0] + o.extent, o.origin[1] + o.extent, o.origin[2] + 100.0],
        waveform_start: 0,
        evlr_start: 0,
        evlr_count: 0,
        extra_header: Vec::new(),
    }
}

/// Points per scan line.
fn line_len(o: &SynthOptions) -> u64 {
    ((o.points as f64).sqrt() as u64).max(1)
}

/// Generates points `first..first + n` as point format 3 records (in scan order), with
/// [`SynthOptions::extra_bytes`] after each.
pub fn records(o: &SynthOptions, first: u64, n: u64) -> (Vec<u8>, PieceStats) {
    let rl = 34 + o.extra_bytes;
    let mut out = vec![0u8; n as usize * rl];
    let per_line = line_len(o);
    let lines = o.points.div_ceil(per_line).max(1);
    out.par_chunks_mut(rl * 4096).enumerate().for_each(|(c, chunk)| {
        for (k, r) in chunk.chunks_exact_mut(rl).enumerate() {
            let at = first + (c * 4096 + k) as u64;
            let i = if o.shape == Shape::Duplicates { at / 8 } else { at };
            let h = mix(o.seed.wrapping_mul(0x2545_f491_4f6c_dd1d) ^ i);
            let line = i / per_line;
            let mut t = (i % per_line) as f64 / per_line as f64;
            if line % 2 == 1 {
                t = 1.0 - t;
            }
            let x = (line as f64 + unit(h)) / lines as f64 * o.extent;
            let y = (t + 0.5 * unit(h >> 9) / per_line as f64) * o.extent;
            let (mut z, class) = surface(x, y, o.seed);
            z += 0.05 * (unit(h >> 17) - 0.5);
            let (x, y, z) = match o.shape {
                Shape::Airborne | Shape::Duplicates => (x, y, z),
                Shape::Coincident => (o.extent / 2.0, o.extent / 2.0, 50.0),
                Shape::Cube => (
                    unit(mix(h ^ 0x1b87_3593)) * o.extent,
                    unit(mix(h ^ 0xcc9e_2d51)) * o.extent,
                    unit(mix(h ^ 0x5bd1_e995)) * o.extent,
                ),
            };
            let xi = (x / o.scale).round() as i32;
            let yi = (y / o.scale).round() as i32;
            let zi = (z / o.scale).round() as i32;
            r[0..4].copy_from_slice(&xi.to_le_bytes());
            r[4..8].copy_from_slice(&yi.to_le_bytes());
            r[8..12].copy_from_slice(&zi.to_le_bytes());
            let intensity = (z * 500.0) as u16 ^ (h >> 40) as u16 & 0xff;
            r[12..14].copy_from_slice(&intensity.to_le_bytes());
            let returns = if class == 5 { 1 + (h >> 50) % 3 } else { 1 } as u8;
            r[14] = returns | (returns << 3);
            r[15] = class;
            r[16] = ((t - 0.5) * 40.0) as i8 as u8;
            r[17] = 0;
            r[18..20].copy_from_slice(&((line % 7) as u16).to_le_bytes());
            r[20..28].copy_from_slice(&(i as f64 * 1e-5).to_le_bytes());
            let (cr, cg, cb): (u16, u16, u16) = match class {
                6 => (180, 90, 70),
                5 => (40, 120 + (z as u16 % 60), 40),
                _ => (120 + (z as u16 % 40), 110, 80),
            };
            for (j, c) in [cr, cg, cb].iter().enumerate() {
                r[28 + 2 * j..30 + 2 * j].copy_from_slice(&(c * 256).to_le_bytes());
            }
            let mut e = h;
            for b in r[34..].iter_mut() {
                e = e.rotate_left(8);
                *b = e as u8;
            }
        }
    });
    let s = PieceStats::of(&out, &o.layout());
    (out, s)
}
