//! The one implementation of the statistics that mortar's benchmarks and accuracy tests report:
//! medians and percentiles of timings, and image error (PSNR, differing pixels). Every
//! `mortar-bench-*` binary, the `--json` statistics and the image-accuracy tests use these, so
//! that a headline figure means the same thing everywhere.
//!
//! ```
//! use mortar_core::metrics::{median, percentile, psnr};
//! assert_eq!(median(&[3.0, 1.0, 2.0, 10.0]), 2.5);
//! assert_eq!(percentile(&[1.0, 2.0, 3.0, 4.0, 5.0], 0.95), 5.0);
//! let a = [0xff00_0000u32; 4];
//! let mut b = a;
//! b[0] = 0xff00_00ff; // one red channel of twelve differs by 255
//! assert!((psnr(&a, &b) - 10.0 * 12f64.log10()).abs() < 1e-9);
//! assert_eq!(psnr(&a, &a), f64::INFINITY);
//! ```

/// The median of `v`: the middle value, the mean of the two middle ones for an even count; NaN
/// for none. NaNs sort last (`f64::total_cmp`).
pub fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    match n {
        0 => f64::NAN,
        _ if n % 2 == 1 => s[n / 2],
        _ => 0.5 * (s[n / 2 - 1] + s[n / 2]),
    }
}

/// The `q`-quantile of `v` (`q` in 0..=1) by nearest rank: the sorted value at index
/// `round((n - 1) q)`, so 0 is the minimum and 1 the maximum; NaN for none.
pub fn percentile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    if s.is_empty() {
        return f64::NAN;
    }
    let i = ((s.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize;
    s[i]
}

/// The squared error summed over the R, G and B channels of two RGBA8 pixels (packed
/// `r | g << 8 | b << 16 | a << 24`).
fn rgb_squared_error(x: u32, y: u32) -> f64 {
    let (x, y) = (x.to_le_bytes(), y.to_le_bytes());
    (0..3).map(|c| (x[c] as f64 - y[c] as f64).powi(2)).sum()
}

/// PSNR in dB of two RGBA8 images over their R, G and B channels (alpha ignored); infinite for
/// identical images. The images are compared pixel by pixel up to the shorter one.
pub fn psnr(a: &[u32], b: &[u32]) -> f64 {
    psnr_where(a, b, |_| true)
}

/// [`psnr`] over the pixels `i` for which `keep(i)` holds (e.g. those covered in either image);
/// infinite where they are identical or none is kept.
pub fn psnr_where(a: &[u32], b: &[u32], keep: impl Fn(usize) -> bool) -> f64 {
    let (mut se, mut channels) = (0f64, 0usize);
    for (i, (&x, &y)) in a.iter().zip(b).enumerate() {
        if keep(i) {
            se += rgb_squared_error(x, y);
            channels += 3;
        }
    }
    if se == 0.0 {
        return f64::INFINITY;
    }
    10.0 * (255.0 * 255.0 / (se / channels as f64)).log10()
}

/// Pixels whose RGBA8 values differ between two images of the same size.
pub fn differing_pixels(a: &[u32], b: &[u32]) -> usize {
    a.iter().zip(b).filter(|(x, y)| x != y).count()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians_of_odd_even_and_empty_inputs() {
        assert_eq!(median(&[5.0]), 5.0);
        assert_eq!(median(&[9.0, 1.0, 5.0]), 5.0);
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), 2.5);
        assert!(median(&[]).is_nan());
    }

    #[test]
    fn percentiles_by_nearest_rank() {
        let v: Vec<f64> = (1..=21).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.0), 1.0);
        assert_eq!(percentile(&v, 0.5), 11.0);
        assert_eq!(percentile(&v, 0.95), 20.0);
        assert_eq!(percentile(&v, 1.0), 21.0);
        assert!(percentile(&[], 0.5).is_nan());
    }

    #[test]
    fn psnr_matches_its_definition() {
        // Every channel off by 16: MSE 256 over R, G, B.
        let a = vec![0xff10_1010u32; 100];
        let b = vec![0xff20_2020u32; 100];
        let want = 10.0 * (255.0f64 * 255.0 / 256.0).log10();
        assert!((psnr(&a, &b) - want).abs() < 1e-12);
        // Alpha is ignored.
        assert_eq!(psnr(&[0x0010_1010], &[0xff10_1010]), f64::INFINITY);
        // Only the kept pixels count.
        let mut c = a.clone();
        c[7] = 0xffff_ffff;
        assert_eq!(psnr_where(&a, &c, |i| i != 7), f64::INFINITY);
        assert!(psnr_where(&a, &c, |i| i == 7) < psnr(&a, &c));
        assert_eq!(differing_pixels(&a, &c), 1);
    }
}
