//! The status line drawn into the image: 8x8 glyphs, wrapped to the width.

/// The status line as an RGBA8 overlay (white 8x8 glyphs, doubled on wide windows, on a
/// translucent black bar) at most `max_width` pixels wide: `(width, height, pixels)`.
pub(super) fn status_overlay(text: &str, max_width: u32) -> (u32, u32, Vec<u32>) {
    use font8x8::UnicodeFonts;
    let scale: u32 = if max_width >= 1600 { 2 } else { 1 };
    let pad = 3 * scale;
    let glyph = 8 * scale;
    let chars: Vec<char> = text.chars().collect();
    let width = (chars.len() as u32 * glyph + 2 * pad).min(max_width.max(1));
    let height = glyph + 2 * pad;
    let bar = 0xb000_0000u32;
    let mut px = vec![bar; width as usize * height as usize];
    for (k, ch) in chars.iter().enumerate() {
        let rows = font8x8::BASIC_FONTS.get(*ch).unwrap_or([0; 8]);
        for (gy, row) in rows.iter().enumerate() {
            for gx in 0..8u32 {
                if row & (1 << gx) == 0 {
                    continue;
                }
                for sy in 0..scale {
                    for sx in 0..scale {
                        let x = pad + k as u32 * glyph + gx * scale + sx;
                        let y = pad + gy as u32 * scale + sy;
                        if x < width {
                            px[(y * width + x) as usize] = 0xffff_ffff;
                        }
                    }
                }
            }
        }
    }
    (width, height, px)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_overlay_draws_text_within_the_width() {
        let (w, h, px) = status_overlay("110,000 points | 1.0 ms", 120);
        assert_eq!((w, h), (120, 14));
        assert_eq!(px.len(), (w * h) as usize);
        let lit = px.iter().filter(|&&c| c == 0xffff_ffff).count();
        assert!(lit > 50, "{lit} text pixels");
        let (w2, _, _) = status_overlay("ab", 1000);
        assert_eq!(w2, 2 * 8 + 6);
    }
}
