//! The RGBA8 render colour of a batch file, derived from the source's own fields (which stay as
//! attributes, so nothing is lost).
//!
//! LAS stores RGB as 16-bit values, but many writers put 8-bit values in them. The choice is made
//! once per dataset ([`RgbDepth::detect`]), never per point: if every component is at most 255 the
//! values are taken as 8-bit, otherwise the high byte of each 16-bit value is used. Without RGB the
//! colour is a grey ramp of intensity over the dataset's intensity range.

/// How the source's 16-bit RGB fields map to 8 bits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RgbDepth {
    /// Values are 0-255: taken as they are.
    Eight,
    /// Values use 16 bits: the high byte is taken.
    Sixteen,
}

impl RgbDepth {
    /// The depth of a dataset whose largest RGB component is `max_component`.
    pub fn detect(max_component: u16) -> RgbDepth {
        if max_component <= 255 {
            RgbDepth::Eight
        } else {
            RgbDepth::Sixteen
        }
    }

    #[inline]
    pub fn to8(self, v: u16) -> u8 {
        match self {
            RgbDepth::Eight => v as u8,
            RgbDepth::Sixteen => (v >> 8) as u8,
        }
    }
}

/// Where the render colour comes from, decided once per dataset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColorSource {
    /// The RGB field at this record offset.
    Rgb { offset: usize, depth: RgbDepth },
    /// Grey from intensity, scaled so that `max_intensity` is white.
    Intensity { max_intensity: u16 },
}

impl ColorSource {
    /// The RGBA8 colour of one record, packed as `r | g << 8 | b << 16 | a << 24`.
    #[inline]
    pub fn rgba(&self, record: &[u8]) -> u32 {
        match *self {
            ColorSource::Rgb { offset, depth } => {
                let c = |i: usize| {
                    depth.to8(u16::from_le_bytes([
                        record[offset + 2 * i],
                        record[offset + 2 * i + 1],
                    ])) as u32
                };
                c(0) | (c(1) << 8) | (c(2) << 16) | (255 << 24)
            }
            ColorSource::Intensity { max_intensity } => {
                let i = u16::from_le_bytes([record[12], record[13]]) as u32;
                let g = if max_intensity == 0 {
                    255
                } else {
                    (i * 255 / max_intensity as u32).min(255)
                };
                g | (g << 8) | (g << 16) | (255 << 24)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_is_per_dataset() {
        assert_eq!(RgbDepth::detect(255), RgbDepth::Eight);
        assert_eq!(RgbDepth::detect(256), RgbDepth::Sixteen);
        assert_eq!(RgbDepth::Sixteen.to8(0xff00), 255);
        assert_eq!(RgbDepth::Eight.to8(200), 200);
    }

    #[test]
    fn rgba_from_record() {
        let mut rec = vec![0u8; 34];
        rec[28..34].copy_from_slice(&[0x00, 0x10, 0x00, 0x20, 0x00, 0xff]);
        let c = ColorSource::Rgb { offset: 28, depth: RgbDepth::Sixteen }.rgba(&rec);
        assert_eq!(c, 0x10 | (0x20 << 8) | (0xff << 16) | (0xff << 24));
        rec[12..14].copy_from_slice(&100u16.to_le_bytes());
        let g = ColorSource::Intensity { max_intensity: 200 }.rgba(&rec);
        assert_eq!(g & 0xff, 127);
    }
}
