//! Visibility-buffer resolve (paper 003 §3.3: "we render point indices rather than colors into
//! the framebuffer during the geometry pass, and transform the point indices to vertex colors in a
//! post-processing step"), with the post-processing passes of paper 003 §3.5 and DESIGN.md:
//! depth-aware hole filling and eye-dome lighting, both off by default.
//!
//! Also the attribute colour modes ([`ColorMode`]): pure functions from a raw attribute value and
//! a range to RGBA8 (packed `r | g << 8 | b << 16 | a << 24`, as in [`crate::color`]). The reading
//! side feeds them attribute values; the resolve only sees a colour per point index.

use super::framebuffer::{key_depth, key_index, EMPTY_KEY};
use crate::color::RgbDepth;
use rayon::prelude::*;

/// Opaque black.
pub const BLACK: u32 = 0xff00_0000;

/// Packs RGBA8 as `r | g << 8 | b << 16 | a << 24`.
#[inline]
pub fn rgba(r: u8, g: u8, b: u8, a: u8) -> u32 {
    r as u32 | (g as u32) << 8 | (b as u32) << 16 | (a as u32) << 24
}

/// Unpacks RGBA8.
#[inline]
pub fn unpack_rgba(c: u32) -> [u8; 4] {
    c.to_le_bytes()
}

/// Depth-aware hole filling: an empty pixel takes the nearest point among its 8 neighbours.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct HoleFill {
    /// Fill only where at least this many of the 8 neighbours hold a point (1: plain depth-aware
    /// dilation by one pixel; higher values fill holes inside surfaces but keep silhouettes).
    pub min_neighbors: u32,
}

impl Default for HoleFill {
    fn default() -> Self {
        HoleFill { min_neighbors: 1 }
    }
}

/// Eye-dome lighting: darkens pixels that lie behind their neighbours in log depth, which outlines
/// silhouettes and shows shape without normals.
///
/// The shading is defined so that the GPU pass (`shaders/eye_dome.wgsl`) computes it bit for bit:
/// the neighbours' offsets are integers computed here ([`offsets`](Self::offsets)), the exponent's
/// scale is one `f32` computed here ([`scale`](Self::scale)), and the logarithm and the exponential
/// are [`edl_log2`] and [`edl_exp2`] (exponent bits and a fixed polynomial, every operation
/// rounded on its own) instead of the platform's `log2`/`exp`, which GPUs round differently.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EyeDome {
    /// Strength of the darkening (1 is the usual value).
    pub strength: f32,
    /// Distance in pixels of the 8 neighbours looked at.
    pub radius: f32,
}

impl Default for EyeDome {
    fn default() -> Self {
        EyeDome { strength: 1.0, radius: 1.4 }
    }
}

impl EyeDome {
    /// The 8 neighbours looked at, `(dx, dy)` in pixels: at 0, 45, ..., 315 degrees, `radius`
    /// away, rounded to whole pixels (computed in f64 on the host; the GPU gets these integers).
    pub fn offsets(&self) -> [[i32; 2]; 8] {
        std::array::from_fn(|i| {
            let angle = i as f64 * std::f64::consts::FRAC_PI_4;
            let r = self.radius as f64;
            [(r * angle.cos()).round() as i32, (r * angle.sin()).round() as i32]
        })
    }

    /// The factor of the mean log-depth difference in the exponent of 2:
    /// `300 * strength * log2(e)` (the shading is `exp(-300 strength mean)`), once, in f32.
    pub fn scale(&self) -> f32 {
        (300.0 * self.strength as f64 * std::f64::consts::LOG2_E) as f32
    }
}

/// Coefficients of `q(t) = log2(1 + t) / t` on `[sqrt(1/2) - 1, sqrt(2) - 1]` (degree 8,
/// interpolated at Chebyshev nodes, rounded to f32; `t q(t)` is within 6e-8 of `log2(1 + t)`;
/// the constant term rounds to the f32 of `log2(e)`).
/// The GPU gets them in [`crate::render::gpu::EyeDomeUniforms`].
pub const EDL_LOG2_COEFFS: [f32; 9] = [
    std::f32::consts::LOG2_E,
    -0.721_347_45,
    0.480_910_75,
    -0.360_693_28,
    0.287_903_25,
    -0.239_169_88,
    0.216_078_22,
    -0.205_861_88,
    0.123_109_68,
];

/// Coefficients of `r(f) = (2^f - 1) / f` on `[0, 1]` (degree 6, Chebyshev nodes, f32;
/// `1 + f r(f)` is within 8e-8 of `2^f`, relative; the constant term rounds to the f32 of
/// `ln 2`). The GPU gets them in
/// [`crate::render::gpu::EyeDomeUniforms`].
pub const EDL_EXP2_COEFFS: [f32; 7] = [
    std::f32::consts::LN_2,
    0.240_226_49,
    0.055_504_44,
    0.009_616_16,
    0.001_338_905_3,
    0.000_146_096_32,
    0.000_020_731_864,
];

/// `p(t)` of the coefficients `c` (lowest first) by Horner's rule, every multiplication and
/// addition rounded on its own (no fused multiply-add), as the GPU evaluates it.
#[inline]
fn horner(c: &[f32], t: f32) -> f32 {
    let mut p = c[c.len() - 1];
    for &a in c[..c.len() - 1].iter().rev() {
        p = p * t + a;
    }
    p
}

/// Base-2 logarithm of a positive depth given by its bits, the one definition of the eye-dome
/// lighting and its WGSL twin (`edl_log2` in `shaders/eye_dome.wgsl`): the exponent from the
/// bits, the mantissa brought into `[sqrt(1/2), sqrt(2))` and `t q(t)` of [`EDL_LOG2_COEFFS`]
/// with `t = m - 1` (exact). Bits outside the positive normal floats are clamped to them (zero
/// and subnormals to the smallest, negative values and NaN to the largest). Exact at powers of 2;
/// within 2e-7 of `log2` elsewhere.
pub fn edl_log2(depth_bits: u32) -> f32 {
    let b = depth_bits.clamp(0x0080_0000, 0x7f7f_ffff);
    let mut e = (b >> 23) as i32 - 127;
    let mant = b & 0x007f_ffff;
    // Above sqrt(2) (the mantissa bits of 0x3fb504f3): halve, one more in the exponent.
    let m = if mant > 0x0035_04f3 {
        e += 1;
        f32::from_bits(mant | 0x3f00_0000)
    } else {
        f32::from_bits(mant | 0x3f80_0000)
    };
    let t = m - 1.0;
    t * horner(&EDL_LOG2_COEFFS, t) + e as f32
}

/// `2^y`, the one definition of the eye-dome lighting and its WGSL twin (`edl_exp2` in
/// `shaders/eye_dome.wgsl`): `y = n + f` with `n = floor(y)`, `2^f = 1 + f r(f)` of
/// [`EDL_EXP2_COEFFS`], times `2^n` built from exponent bits. 0 at or below -64 (and for NaN),
/// `y` above 64 taken as 64.
pub fn edl_exp2(y: f32) -> f32 {
    if !(y > -64.0) {
        return 0.0;
    }
    let y = y.min(64.0);
    let n = y.floor();
    let f = y - n;
    let p = f * horner(&EDL_EXP2_COEFFS, f) + 1.0;
    p * f32::from_bits(((n as i32 + 127) as u32) << 23)
}

/// Choices of the resolve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ResolveOptions {
    /// Colour of empty pixels.
    pub background: u32,
    /// Hole filling, off when `None`.
    pub hole_fill: Option<HoleFill>,
    /// Eye-dome lighting, off when `None`.
    pub eye_dome: Option<EyeDome>,
}

impl Default for ResolveOptions {
    fn default() -> Self {
        ResolveOptions { background: BLACK, hole_fill: None, eye_dome: None }
    }
}

/// The keys with empty pixels filled from their nearest neighbour (smallest key in the 3x3
/// window), where at least `fill.min_neighbors` neighbours hold a point. Reads only the input, so
/// filling does not spread further than one pixel.
pub fn fill_holes(keys: &[u64], width: u32, height: u32, fill: &HoleFill) -> Vec<u64> {
    let (w, h) = (width as usize, height as usize);
    assert_eq!(keys.len(), w * h, "keys do not match {width}x{height}");
    let mut out = keys.to_vec();
    out.par_chunks_mut(w.max(1)).enumerate().for_each(|(y, row)| {
        for (x, slot) in row.iter_mut().enumerate() {
            if *slot != EMPTY_KEY {
                continue;
            }
            let mut best = EMPTY_KEY;
            let mut count = 0;
            for ny in y.saturating_sub(1)..(y + 2).min(h) {
                for nx in x.saturating_sub(1)..(x + 2).min(w) {
                    let k = keys[ny * w + nx];
                    if k != EMPTY_KEY {
                        count += 1;
                        best = best.min(k);
                    }
                }
            }
            if count >= fill.min_neighbors.max(1) {
                *slot = best;
            }
        }
    });
    out
}

/// The eye-dome shading factor (0-1; above 1 for a negative strength) of the non-empty pixel
/// `(x, y)`: `2^(-scale * mean)` where `mean` sums, over the neighbours at `offsets` that lie in
/// the image and hold a point, how far the pixel lies behind each in log2 depth, divided by 8.
/// The WGSL twin is `shaders/eye_dome.wgsl`, operation for operation.
fn eye_dome_factor(
    keys: &[u64],
    w: usize,
    h: usize,
    x: usize,
    y: usize,
    offsets: &[[i32; 2]; 8],
    scale: f32,
) -> f32 {
    let d = edl_log2(key_depth(keys[y * w + x]).to_bits());
    let mut sum = 0.0f32;
    for &[dx, dy] in offsets {
        let nx = x as i64 + dx as i64;
        let ny = y as i64 + dy as i64;
        if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
            continue;
        }
        let k = keys[ny as usize * w + nx as usize];
        if k != EMPTY_KEY {
            sum += (d - edl_log2(key_depth(k).to_bits())).max(0.0);
        }
    }
    edl_exp2(-((sum * 0.125) * scale))
}

/// Scales the RGB of a colour by `f`, keeping alpha: each channel `floor(v f + 0.5)` (the
/// product rounded first), at most 255. The WGSL twin is `shade` in `shaders/eye_dome.wgsl`.
#[inline]
pub fn shade(c: u32, f: f32) -> u32 {
    let [r, g, b, a] = unpack_rgba(c);
    let s = |v: u8| ((v as f32 * f) + 0.5).floor().min(255.0) as u8;
    rgba(s(r), s(g), s(b), a)
}

/// Maps a framebuffer of keys to RGBA8: each covered pixel gets `color(point index)`, empty pixels
/// the background; hole filling and eye-dome lighting as the options say. `color` is called once
/// per covered pixel; pass a closure, a `&dyn Fn(u32) -> u32 + Sync`, or use
/// [`resolve_with_colors`] for a slice of per-point colours.
pub fn resolve<F: Fn(u32) -> u32 + Sync>(
    keys: &[u64],
    width: u32,
    height: u32,
    color: F,
    options: &ResolveOptions,
) -> Vec<u32> {
    let (w, h) = (width as usize, height as usize);
    assert_eq!(keys.len(), w * h, "keys do not match {width}x{height}");
    let filled;
    let keys = match &options.hole_fill {
        Some(fill) => {
            filled = fill_holes(keys, width, height, fill);
            &filled[..]
        }
        None => keys,
    };
    let eye_dome = options.eye_dome.map(|e| (e.offsets(), e.scale()));
    let mut out = vec![options.background; w * h];
    out.par_chunks_mut(w.max(1)).enumerate().for_each(|(y, row)| {
        for (x, px) in row.iter_mut().enumerate() {
            let k = keys[y * w + x];
            if k == EMPTY_KEY {
                continue;
            }
            let c = color(key_index(k));
            *px = match &eye_dome {
                Some((offsets, scale)) => {
                    shade(c, eye_dome_factor(keys, w, h, x, y, offsets, *scale))
                }
                None => c,
            };
        }
    });
    out
}

/// [`resolve`] with a slice of colours indexed by point index; an index beyond the slice gets the
/// background colour.
pub fn resolve_with_colors(
    keys: &[u64],
    width: u32,
    height: u32,
    colors: &[u32],
    options: &ResolveOptions,
) -> Vec<u32> {
    let bg = options.background;
    resolve(keys, width, height, |i| colors.get(i as usize).copied().unwrap_or(bg), options)
}

/// Which attribute points are coloured by.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum ColorMode {
    /// The source's RGB ([`rgb_color`]).
    #[default]
    Rgb,
    /// Grey from intensity over a range ([`intensity_color`]).
    Intensity,
    /// ASPRS classification palette ([`classification_color`]).
    Classification,
    /// Colour ramp over an elevation range ([`elevation_color`]).
    Elevation,
    /// Return number within the pulse's returns ([`return_number_color`]).
    ReturnNumber,
    /// Colour ramp over a GPS time range ([`gps_time_color`]).
    GpsTime,
}

impl ColorMode {
    /// All modes, in a stable order.
    pub const ALL: [ColorMode; 6] = [
        ColorMode::Rgb,
        ColorMode::Intensity,
        ColorMode::Classification,
        ColorMode::Elevation,
        ColorMode::ReturnNumber,
        ColorMode::GpsTime,
    ];

    /// The mode's name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            ColorMode::Rgb => "rgb",
            ColorMode::Intensity => "intensity",
            ColorMode::Classification => "classification",
            ColorMode::Elevation => "elevation",
            ColorMode::ReturnNumber => "return-number",
            ColorMode::GpsTime => "gps-time",
        }
    }

    /// The mode of a name given by [`name`](Self::name).
    pub fn from_name(name: &str) -> Option<ColorMode> {
        ColorMode::ALL.into_iter().find(|m| m.name() == name)
    }

    /// The record attribute the mode reads (names of [`crate::layout`]; `z` is the coordinate).
    pub fn attribute(self) -> &'static str {
        match self {
            ColorMode::Rgb => "rgb",
            ColorMode::Intensity => "intensity",
            ColorMode::Classification => "classification",
            ColorMode::Elevation => "z",
            ColorMode::ReturnNumber => "flags",
            ColorMode::GpsTime => "gps_time",
        }
    }
}

/// `(v - lo) / (hi - lo)` clamped to `[0, 1]`; 0.5 for an empty or reversed range, 0 for NaN.
#[inline]
pub fn normalized(v: f64, range: [f64; 2]) -> f64 {
    let [lo, hi] = range;
    if !(hi > lo) {
        return 0.5;
    }
    let t = (v - lo) / (hi - lo);
    if t.is_nan() {
        0.0
    } else {
        t.clamp(0.0, 1.0)
    }
}

/// Stops of the scalar ramp (viridis, sampled at 9 points).
const RAMP: [[u8; 3]; 9] = [
    [68, 1, 84],
    [71, 44, 122],
    [59, 81, 139],
    [44, 113, 142],
    [33, 144, 141],
    [39, 173, 129],
    [92, 200, 99],
    [170, 220, 50],
    [253, 231, 37],
];

/// The scalar colour ramp at `t` in `[0, 1]` (clamped), dark blue-violet to yellow, opaque.
pub fn ramp(t: f64) -> u32 {
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
    let f = t * (RAMP.len() - 1) as f64;
    let i = (f.floor() as usize).min(RAMP.len() - 2);
    let u = f - i as f64;
    let mix = |a: usize| (RAMP[i][a] as f64 * (1.0 - u) + RAMP[i + 1][a] as f64 * u).round() as u8;
    rgba(mix(0), mix(1), mix(2), 255)
}

/// The source's 16-bit RGB as RGBA8, with the dataset's [`RgbDepth`].
pub fn rgb_color(rgb: [u16; 3], depth: RgbDepth) -> u32 {
    rgba(depth.to8(rgb[0]), depth.to8(rgb[1]), depth.to8(rgb[2]), 255)
}

/// Grey from an intensity over `range` (black at the low end, white at the high end).
pub fn intensity_color(intensity: u16, range: [f64; 2]) -> u32 {
    let g = (normalized(intensity as f64, range) * 255.0).round() as u8;
    rgba(g, g, g, 255)
}

/// Colour of an ASPRS classification code (LAS 1.4 R15 table 17): standard codes 0-22 get fixed
/// colours, reserved and user-defined codes a stable colour derived from the code.
pub fn classification_color(code: u8) -> u32 {
    let [r, g, b] = match code {
        0 => [160, 160, 160],  // created, never classified
        1 => [200, 200, 200],  // unclassified
        2 => [170, 120, 60],   // ground
        3 => [150, 220, 110],  // low vegetation
        4 => [70, 180, 60],    // medium vegetation
        5 => [20, 110, 30],    // high vegetation
        6 => [230, 90, 50],    // building
        7 => [255, 0, 255],    // low point (noise)
        8 => [255, 255, 0],    // reserved (model key-point in LAS 1.0-1.3)
        9 => [40, 110, 230],   // water
        10 => [130, 80, 40],   // rail
        11 => [90, 90, 90],    // road surface
        12 => [255, 200, 120], // reserved (overlap in LAS 1.0-1.3)
        13 => [255, 255, 140], // wire - guard (shield)
        14 => [255, 190, 0],   // wire - conductor (phase)
        15 => [190, 120, 255], // transmission tower
        16 => [255, 140, 200], // wire-structure connector (insulator)
        17 => [140, 140, 255], // bridge deck
        18 => [200, 0, 100],   // high noise
        19 => [0, 200, 200],   // overhead structure
        20 => [210, 180, 130], // ignored ground
        21 => [235, 245, 255], // snow
        22 => [110, 0, 130],   // temporal exclusion
        _ => {
            // Reserved (23-63) and user-defined (64-255): a fixed hash, bright enough to see.
            let h = (code as u32).wrapping_mul(0x9e37_79b1).rotate_left(7);
            [64 + (h & 0xbf) as u8, 64 + (h >> 8 & 0xbf) as u8, 64 + (h >> 16 & 0xbf) as u8]
        }
    };
    rgba(r, g, b, 255)
}

/// Colour ramp over an elevation range.
pub fn elevation_color(z: f64, range: [f64; 2]) -> u32 {
    ramp(normalized(z, range))
}

/// Colour of a return within its pulse: a single return yellow, the first of several red, the
/// last of several blue, an intermediate one green; invalid numbers (0, or beyond the count) grey.
pub fn return_number_color(return_number: u8, number_of_returns: u8) -> u32 {
    let [r, g, b] = if return_number == 0 || return_number > number_of_returns {
        [128, 128, 128]
    } else if number_of_returns == 1 {
        [255, 220, 0]
    } else if return_number == 1 {
        [230, 40, 40]
    } else if return_number == number_of_returns {
        [40, 90, 240]
    } else {
        [40, 200, 80]
    };
    rgba(r, g, b, 255)
}

/// Colour ramp over a GPS time range.
pub fn gps_time_color(t: f64, range: [f64; 2]) -> u32 {
    ramp(normalized(t, range))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::framebuffer::{pack_key, unpack_key};

    const E: u64 = EMPTY_KEY;

    #[test]
    fn indices_become_colours_and_empty_pixels_background() {
        let keys = vec![pack_key(1.0, 2), E, pack_key(3.0, 0), pack_key(2.0, 7)];
        let colors = [rgba(1, 0, 0, 255), rgba(2, 0, 0, 255), rgba(3, 0, 0, 255)];
        let opts = ResolveOptions { background: rgba(9, 9, 9, 255), ..Default::default() };
        let out = resolve_with_colors(&keys, 2, 2, &colors, &opts);
        assert_eq!(out, vec![colors[2], rgba(9, 9, 9, 255), colors[0], rgba(9, 9, 9, 255)]);
        let f: &(dyn Fn(u32) -> u32 + Sync) = &|i| i * 10;
        assert_eq!(resolve(&keys, 2, 2, f, &opts), vec![20, rgba(9, 9, 9, 255), 0, 70]);
    }

    #[test]
    fn hole_filling_takes_the_nearest_neighbour() {
        // 3x3 with an empty centre: the nearest neighbour (depth 1.0, index 5) fills it.
        let mut keys = vec![pack_key(4.0, 0); 9];
        keys[4] = E;
        keys[6] = pack_key(1.0, 5);
        keys[2] = pack_key(1.0, 8);
        let filled = fill_holes(&keys, 3, 3, &HoleFill::default());
        assert_eq!(filled[4], pack_key(1.0, 5));
        assert_eq!(&filled[..4], &keys[..4]);
        // An isolated empty region stays empty beyond one pixel, and min_neighbors is honoured.
        let mut keys = vec![E; 25];
        keys[0] = pack_key(1.0, 1);
        let filled = fill_holes(&keys, 5, 5, &HoleFill::default());
        assert_eq!(filled.iter().filter(|&&k| k != E).count(), 4);
        let filled = fill_holes(&keys, 5, 5, &HoleFill { min_neighbors: 2 });
        assert_eq!(filled.iter().filter(|&&k| k != E).count(), 1);
        // Off by default.
        let out = resolve(&keys, 5, 5, |_| 7, &ResolveOptions::default());
        assert_eq!(out.iter().filter(|&&c| c == 7).count(), 1);
        let out = resolve(
            &keys,
            5,
            5,
            |_| 7,
            &ResolveOptions { hole_fill: Some(HoleFill::default()), ..Default::default() },
        );
        assert_eq!(out.iter().filter(|&&c| c == 7).count(), 4);
    }

    #[test]
    fn eye_dome_darkens_pixels_behind_their_neighbours() {
        // A near square (depth 10) in front of a far plane (depth 20).
        let (w, h) = (8u32, 8u32);
        let keys: Vec<u64> = (0..64)
            .map(|i| {
                let (x, y) = (i % 8, i / 8);
                if (2..6).contains(&x) && (2..6).contains(&y) {
                    pack_key(10.0, i)
                } else {
                    pack_key(20.0, i)
                }
            })
            .collect();
        let white = rgba(255, 255, 255, 255);
        let opts = ResolveOptions { eye_dome: Some(EyeDome::default()), ..Default::default() };
        let out = resolve(&keys, w, h, |_| white, &opts);
        let at = |x: usize, y: usize| unpack_rgba(out[y * 8 + x]);
        assert_eq!(at(3, 3), [255, 255, 255, 255], "inside the near square: flat, unshaded");
        assert_eq!(at(7, 7), [255, 255, 255, 255], "far plane away from the edge: unshaded");
        assert!(at(1, 3)[0] < 100, "far pixel next to the near square is darkened: {:?}", at(1, 3));
        assert_eq!(at(1, 3)[3], 255);
        assert_eq!(resolve(&keys, w, h, |_| white, &ResolveOptions::default()), vec![white; 64]);
    }

    #[test]
    fn edl_log2_and_exp2_are_close_to_the_real_functions() {
        // Exact at powers of two and 2^0 = 1 (a flat surface stays unshaded).
        for e in -126..=127 {
            assert_eq!(edl_log2(2f32.powi(e).to_bits()), e as f32);
        }
        assert_eq!(edl_exp2(0.0), 1.0);
        assert_eq!(edl_exp2(-0.0), 1.0);
        assert_eq!(edl_exp2(-64.0), 0.0);
        assert_eq!(edl_exp2(f32::NAN), 0.0);
        // Measured: log2 within 2.4e-7 absolute plus half an ulp of the result, exp2 within
        // 3e-7 relative, over the depths a camera sees and the exponents the shading uses.
        let (mut worst_log, mut worst_exp) = (0.0f64, 0.0f64);
        for i in 0..200_000u32 {
            let v = 1e-3f32 * (1.0 + i as f32 * 0.013).powf(1.7);
            let want = (v as f64).log2();
            let err = (edl_log2(v.to_bits()) as f64 - want).abs()
                - 0.5 * f64::from(want.abs() as f32 * f32::EPSILON);
            worst_log = worst_log.max(err);
            let y = -(i as f32) * 3.1e-4;
            let want = 2f64.powf(y as f64);
            worst_exp = worst_exp.max((edl_exp2(y) as f64 - want).abs() / want);
        }
        assert!(worst_log < 2.4e-7, "log2: {worst_log:e}");
        assert!(worst_exp < 3e-7, "exp2: {worst_exp:e}");
        // Out-of-range bits are clamped, not NaN.
        assert_eq!(edl_log2(0), -126.0);
        assert!(edl_log2(f32::NAN.to_bits()) > 127.9 && edl_log2((-1.0f32).to_bits()) > 127.9);
    }

    #[test]
    fn eye_dome_offsets_and_shading_are_integers_and_exact_rounding() {
        assert_eq!(
            EyeDome::default().offsets(),
            [[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1]]
        );
        assert_eq!(
            EyeDome { strength: 1.0, radius: 3.0 }.offsets(),
            [[3, 0], [2, 2], [0, 3], [-2, 2], [-3, 0], [-2, -2], [0, -3], [2, -2]]
        );
        let c = rgba(255, 128, 1, 77);
        assert_eq!(shade(c, 1.0), c);
        assert_eq!(shade(c, 0.5), rgba(128, 64, 1, 77));
        assert_eq!(shade(c, 0.0), rgba(0, 0, 0, 77));
        assert_eq!(shade(c, 4.0), rgba(255, 255, 4, 77));
    }

    #[test]
    fn resolves_a_rasterized_scene() {
        use crate::grid::Grid;
        use crate::render::camera::{Camera, ViewPreset};
        use crate::render::framebuffer::Framebuffer;
        use crate::render::plan::RasterOptions;
        use crate::render::raster::rasterize;
        use crate::render::testutil::Scene;
        // Sparse (~1 point per pixel), so plain resolve leaves holes that filling closes.
        let scene = Scene::terrain(40_000, 4, Grid { scale: [0.01; 3], offset: [0.0; 3] });
        let cam = Camera::frame_orthographic(&scene.bounds, ViewPreset::Top, 240, 180).unwrap();
        let fb = Framebuffer::new(240, 180);
        rasterize(&fb, &scene.refs(), &scene.grid, &cam, &RasterOptions::default()).unwrap();
        let keys = fb.into_keys();
        let bg = rgba(0, 0, 255, 255);
        let plain = resolve_with_colors(
            &keys,
            240,
            180,
            &scene.colors,
            &ResolveOptions { background: bg, ..Default::default() },
        );
        for (k, c) in keys.iter().zip(&plain) {
            match unpack_key(*k) {
                Some((_, i)) => assert_eq!(*c, scene.colors[i as usize]),
                None => assert_eq!(*c, bg),
            }
        }
        let holes = |img: &[u32]| img.iter().filter(|&&c| c == bg).count();
        let filled = resolve_with_colors(
            &keys,
            240,
            180,
            &scene.colors,
            &ResolveOptions {
                background: bg,
                hole_fill: Some(HoleFill { min_neighbors: 3 }),
                ..Default::default()
            },
        );
        assert!(holes(&plain) > 5_000, "{}", holes(&plain));
        assert!(holes(&filled) * 3 < holes(&plain), "{} -> {}", holes(&plain), holes(&filled));
    }

    #[test]
    fn colour_modes() {
        for m in ColorMode::ALL {
            assert_eq!(ColorMode::from_name(m.name()), Some(m));
        }
        assert_eq!(rgb_color([0xff00, 0x8000, 0], RgbDepth::Sixteen), rgba(255, 128, 0, 255));
        assert_eq!(rgb_color([200, 100, 0], RgbDepth::Eight), rgba(200, 100, 0, 255));
        assert_eq!(intensity_color(0, [0.0, 1000.0]), rgba(0, 0, 0, 255));
        assert_eq!(intensity_color(2000, [0.0, 1000.0]), rgba(255, 255, 255, 255));
        assert_eq!(intensity_color(500, [0.0, 1000.0]), rgba(128, 128, 128, 255));
        // Standard classes are distinct; ground is not vegetation; every code is opaque.
        let std: Vec<u32> = (0..=22).map(classification_color).collect();
        for i in 0..std.len() {
            for j in 0..i {
                assert_ne!(std[i], std[j], "classes {i} and {j} share a colour");
            }
        }
        assert!((0..=255).all(|c| classification_color(c) >> 24 == 255));
        // The ramp runs from the first to the last stop and is monotone in brightness.
        assert_eq!(elevation_color(-5.0, [0.0, 10.0]), rgba(68, 1, 84, 255));
        assert_eq!(elevation_color(10.0, [0.0, 10.0]), rgba(253, 231, 37, 255));
        let lum = |c: u32| {
            let [r, g, b, _] = unpack_rgba(c);
            0.3 * r as f64 + 0.59 * g as f64 + 0.11 * b as f64
        };
        let mut prev = -1.0;
        for i in 0..=100 {
            let l = lum(elevation_color(i as f64, [0.0, 100.0]));
            assert!(l >= prev - 1.0, "ramp not monotone at {i}");
            prev = l;
        }
        assert_eq!(gps_time_color(f64::NAN, [0.0, 1.0]), ramp(0.0));
        assert_eq!(normalized(3.0, [5.0, 5.0]), 0.5);
        assert_ne!(return_number_color(1, 1), return_number_color(1, 3));
        assert_ne!(return_number_color(3, 3), return_number_color(2, 3));
        assert_eq!(return_number_color(4, 3), return_number_color(0, 2));
    }
}
