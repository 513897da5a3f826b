//! What points are coloured by ([`ColorChoice`]) and the colour rules every renderer shares:
//! attribute values from record bytes, scalar modes mapped over the 1st to 99th percentile of
//! their values unless a range is given (paper 003 §3.3: "transform the point indices to vertex
//! colors in a post-processing step").

use mortar_core::layout::{Family, RecordLayout};
use mortar_core::render::resolve::{
    classification_color, elevation_color, gps_time_color, intensity_color, return_number_color,
    ColorMode,
};
use mortar_io::batchfile::BatchFile;
use rayon::prelude::*;

/// What the points are coloured by.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum ColorChoice {
    /// RGB when the source has colours, else intensity over the visible points' range, else the
    /// stored colour ([`resolved`](Self::resolved) says which).
    #[default]
    Auto,
    /// The batch file's stored render colour: RGB when the source has it, else a grey ramp of
    /// intensity over the dataset's whole intensity range.
    Stored,
    /// An attribute colour mode.
    Mode(ColorMode),
}

impl ColorChoice {
    /// Names accepted on the command line: `auto`, `stored` and the names of [`ColorMode`].
    pub fn names() -> Vec<&'static str> {
        let mut v = vec!["auto", "stored"];
        v.extend(ColorMode::ALL.iter().map(|m| m.name()));
        v
    }

    /// The choice of a name from [`names`](Self::names).
    pub fn from_name(name: &str) -> Option<ColorChoice> {
        match name {
            "auto" => Some(ColorChoice::Auto),
            "stored" => Some(ColorChoice::Stored),
            _ => ColorMode::from_name(name).map(ColorChoice::Mode),
        }
    }

    /// The name of the choice.
    pub fn name(self) -> &'static str {
        match self {
            ColorChoice::Auto => "auto",
            ColorChoice::Stored => "stored",
            ColorChoice::Mode(m) => m.name(),
        }
    }

    /// The choice `Auto` stands for in `file`; other choices unchanged.
    pub fn resolved(self, file: &BatchFile) -> ColorChoice {
        match self {
            ColorChoice::Auto if file.meta.color.source == "rgb" => {
                ColorChoice::Mode(ColorMode::Rgb)
            }
            ColorChoice::Auto if file.meta.attributes.iter().any(|a| a.name == "intensity") => {
                ColorChoice::Mode(ColorMode::Intensity)
            }
            ColorChoice::Auto => ColorChoice::Stored,
            c => c,
        }
    }

    /// The attributes of `layout` that drawing with this choice reads: the mode's attribute, and
    /// RGB and intensity, from which the stored colour is chosen (positions are always read).
    /// For [`Dataset::decode_only`] and the attributes of a batch file made only to be drawn.
    pub fn attributes(self, layout: &RecordLayout) -> Vec<&'static str> {
        let mut v = vec!["rgb", "intensity"];
        if let ColorChoice::Mode(m) = self {
            v.push(m.attribute());
        }
        v.retain(|n| layout.attribute(n).is_some());
        v.dedup();
        v
    }

    /// Whether the choice maps a scalar over a range (intensity, elevation, GPS time).
    pub fn uses_range(self) -> bool {
        matches!(
            self,
            ColorChoice::Mode(ColorMode::Intensity | ColorMode::Elevation | ColorMode::GpsTime)
        )
    }
}

/// The value at quantile `q` (0-1) of `v` (finite values only; reorders `v`).
pub fn quantile(v: &mut [f64], q: f64) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let k = ((v.len() - 1) as f64 * q).round() as usize;
    Some(*v.select_nth_unstable_by(k, f64::total_cmp).1)
}

/// The value of attribute colour mode `mode` from the bytes `v` of its field (as
/// [`ColorMode::attribute`] names it) in a record of `family`: the colour for classification and
/// return number, the `f64` bits of the value for intensity and GPS time.
#[inline]
pub fn attribute_value(mode: ColorMode, family: Family, v: &[u8]) -> u64 {
    match mode {
        ColorMode::Intensity => (u16::from_le_bytes([v[0], v[1]]) as f64).to_bits(),
        ColorMode::GpsTime => f64::from_le_bytes(v[..8].try_into().expect("8 bytes")).to_bits(),
        ColorMode::Classification => {
            let code = if family == Family::Legacy { v[0] & 0x1f } else { v[0] };
            classification_color(code) as u64
        }
        ColorMode::ReturnNumber => {
            let (r, n) = match family {
                Family::Legacy => (v[0] & 0x07, (v[0] >> 3) & 0x07),
                Family::Extended => (v[0] & 0x0f, v[0] >> 4),
            };
            return_number_color(r, n) as u64
        }
        ColorMode::Rgb | ColorMode::Elevation => unreachable!("not read from an attribute"),
    }
}

/// The range a scalar colour mode maps over when none is given: the 1st to 99th percentile of
/// the finite `values` (`f64` bits), robust against outliers.
pub fn percentile_range(values: &[u64]) -> [f64; 2] {
    let mut v: Vec<f64> =
        values.iter().map(|&b| f64::from_bits(b)).filter(|x| x.is_finite()).collect();
    let lo = quantile(&mut v, 0.01).unwrap_or(0.0);
    let hi = quantile(&mut v, 0.99).unwrap_or(1.0);
    [lo, hi]
}

/// Colours of scalar values (`f64` bits) in `mode` (intensity, elevation, GPS time) over
/// `range`, or when it is `None` over [`percentile_range`]; and the range used.
pub fn scalar_colors(
    mode: ColorMode,
    values: &[u64],
    range: Option<[f64; 2]>,
) -> (Vec<u32>, [f64; 2]) {
    let range = range.unwrap_or_else(|| percentile_range(values));
    let color = |v: f64| match mode {
        ColorMode::Intensity => intensity_color(v as u16, range),
        ColorMode::Elevation => elevation_color(v, range),
        _ => gps_time_color(v, range),
    };
    (values.par_iter().map(|&b| color(f64::from_bits(b))).collect(), range)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_choice_names_round_trip() {
        for name in ColorChoice::names() {
            assert_eq!(ColorChoice::from_name(name).map(ColorChoice::name), Some(name));
        }
        assert_eq!(ColorChoice::from_name("height"), None);
        assert!(ColorChoice::Mode(ColorMode::GpsTime).uses_range());
        assert!(!ColorChoice::Mode(ColorMode::Classification).uses_range());
    }

    #[test]
    fn percentile_range_skips_non_finite_values() {
        let mut v: Vec<u64> = (0..=100).map(|i| f64::from(i).to_bits()).collect();
        v.push(f64::NAN.to_bits());
        v.push(f64::INFINITY.to_bits());
        assert_eq!(percentile_range(&v), [1.0, 99.0]);
        assert_eq!(percentile_range(&[]), [0.0, 1.0]);
    }
}
