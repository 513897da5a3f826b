//! The 64-bit depth|index framebuffer of the visibility buffer (paper 003 §3.2, Listing 1, and
//! §3.3: "we render point indices rather than colors into the framebuffer").
//!
//! Each pixel holds one `u64` key: the f32 bits of the point's view depth in the high 32 bits and
//! the point's global index in the low 32. For non-negative floats the bit pattern orders like the
//! value, so the smallest key is the nearest point, and among points at the same depth the one with
//! the smallest index. `fetch_min` therefore gives the same image whatever order the points arrive
//! in. An empty pixel holds [`EMPTY_KEY`].

use std::sync::atomic::{AtomicU64, Ordering};

/// The key of an empty pixel (the clear value).
pub const EMPTY_KEY: u64 = u64::MAX;

/// The key of a point at view depth `depth` (`>= 0`, not NaN) with global index `index`.
#[inline(always)]
pub fn pack_key(depth: f32, index: u32) -> u64 {
    debug_assert!(depth >= 0.0, "depth {depth}");
    ((depth.to_bits() as u64) << 32) | index as u64
}

/// The view depth stored in a key (meaningless for [`EMPTY_KEY`]).
#[inline]
pub fn key_depth(key: u64) -> f32 {
    f32::from_bits((key >> 32) as u32)
}

/// The point index stored in a key (meaningless for [`EMPTY_KEY`]).
#[inline]
pub fn key_index(key: u64) -> u32 {
    key as u32
}

/// Depth and index of a key, `None` for an empty pixel.
#[inline]
pub fn unpack_key(key: u64) -> Option<(f32, u32)> {
    (key != EMPTY_KEY).then(|| (key_depth(key), key_index(key)))
}

/// A framebuffer of atomic 64-bit keys, row-major, row 0 at the top.
#[derive(Debug)]
pub struct Framebuffer {
    width: u32,
    height: u32,
    keys: Vec<AtomicU64>,
}

impl Framebuffer {
    /// A cleared framebuffer of `width x height` pixels.
    pub fn new(width: u32, height: u32) -> Framebuffer {
        let n = width as usize * height as usize;
        Framebuffer { width, height, keys: (0..n).map(|_| AtomicU64::new(EMPTY_KEY)).collect() }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Sets every pixel to [`EMPTY_KEY`].
    pub fn clear(&mut self) {
        for k in &mut self.keys {
            *k.get_mut() = EMPTY_KEY;
        }
    }

    /// The key of pixel `(x, y)`.
    pub fn key(&self, x: u32, y: u32) -> u64 {
        assert!(
            x < self.width && y < self.height,
            "pixel ({x}, {y}) outside {}x{}",
            self.width,
            self.height
        );
        self.keys[y as usize * self.width as usize + x as usize].load(Ordering::Relaxed)
    }

    /// Depth test and write of one point: keeps the smaller key. An early test (a plain load)
    /// skips the atomic read-modify-write when the pixel already holds a nearer point, as in
    /// paper 003 Listing 1. Returns whether the key was smaller than the value loaded.
    #[inline(always)]
    pub fn depth_test(&self, pixel: usize, key: u64) -> bool {
        let slot = &self.keys[pixel];
        if key < slot.load(Ordering::Relaxed) {
            slot.fetch_min(key, Ordering::Relaxed);
            true
        } else {
            false
        }
    }

    /// A copy of all keys, row-major.
    pub fn keys(&self) -> Vec<u64> {
        self.keys.iter().map(|k| k.load(Ordering::Relaxed)).collect()
    }

    /// The keys, row-major, read in place: exclusive access means no draw is running.
    pub fn keys_slice(&mut self) -> &[u64] {
        // SAFETY: `AtomicU64` has the same size, alignment and bit validity as `u64` (std
        // documents this), and `&mut self` rules out any concurrent access while the slice lives.
        unsafe { std::slice::from_raw_parts(self.keys.as_ptr() as *const u64, self.keys.len()) }
    }

    /// The keys, row-major, without copying.
    pub fn into_keys(self) -> Vec<u64> {
        self.keys.into_iter().map(AtomicU64::into_inner).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_order_by_depth_then_index() {
        assert!(pack_key(1.0, 5) < pack_key(1.0, 6));
        assert!(pack_key(1.0, u32::MAX) < pack_key(1.0000001, 0));
        assert!(pack_key(0.0, 0) < pack_key(f32::MIN_POSITIVE, 0));
        assert!(pack_key(3.0e38, u32::MAX) < EMPTY_KEY);
        assert!(pack_key(f32::INFINITY, u32::MAX - 1) < EMPTY_KEY);
        let mut prev = 0u64;
        for d in [0.001f32, 0.5, 1.0, 2.0, 1e3, 1e7, 6.4e6] {
            let k = pack_key(d, 0);
            assert_eq!(unpack_key(k), Some((d, 0)));
            if d != 6.4e6 {
                assert!(k > prev);
                prev = k;
            }
        }
        assert_eq!(unpack_key(EMPTY_KEY), None);
    }

    #[test]
    fn nearest_wins_in_any_order() {
        let mut fb = Framebuffer::new(4, 2);
        let keys = [pack_key(5.0, 1), pack_key(2.0, 9), pack_key(2.0, 3), pack_key(7.0, 0)];
        for k in keys {
            fb.depth_test(6, k);
        }
        assert_eq!(fb.key(2, 1), pack_key(2.0, 3));
        assert_eq!(fb.keys_slice()[6], pack_key(2.0, 3));
        let copy = fb.keys();
        assert_eq!(fb.keys_slice(), &copy[..]);
        assert!(!fb.depth_test(6, pack_key(2.5, 0)));
        assert_eq!(fb.key(0, 0), EMPTY_KEY);
        fb.clear();
        assert!(fb.into_keys().iter().all(|&k| k == EMPTY_KEY));
    }
}
