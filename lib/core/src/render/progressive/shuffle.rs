//! The incremental shuffle of paper 000 §3.3 (eq. 1-2): a point's index `i` in the input becomes
//! its position `targetIndex(i) = permute(permute(i))` in the shuffled buffer, where `permute` is
//! Preshing's quadratic-residue permutation modulo the largest prime `P ≡ 3 (mod 4)` with
//! `P <= N`; the points past that prime keep their position. Each point's position depends on its
//! index alone, so points are placed as they arrive, in any order.

/// `a * b mod m` without overflow.
#[inline]
fn mul_mod(a: u64, b: u64, m: u64) -> u64 {
    ((a as u128 * b as u128) % m as u128) as u64
}

fn pow_mod(mut b: u64, mut e: u64, m: u64) -> u64 {
    let mut r = 1 % m;
    b %= m;
    while e > 0 {
        if e & 1 == 1 {
            r = mul_mod(r, b, m);
        }
        b = mul_mod(b, b, m);
        e >>= 1;
    }
    r
}

/// Whether `n` is prime: deterministic Miller-Rabin for every `u64` (the seven bases of Jim
/// Sinclair are a certificate below 2^64).
// `is_multiple_of` needs Rust 1.87; the workspace supports 1.85.
#[allow(clippy::manual_is_multiple_of)]
pub fn is_prime(n: u64) -> bool {
    if n < 2 {
        return false;
    }
    for p in [2u64, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37] {
        if n % p == 0 {
            return n == p;
        }
    }
    let mut d = n - 1;
    let mut s = 0;
    while d % 2 == 0 {
        d /= 2;
        s += 1;
    }
    'bases: for a in [2u64, 325, 9375, 28178, 450775, 9780504, 1795265022] {
        let a = a % n;
        if a == 0 {
            continue;
        }
        let mut x = pow_mod(a, d, n);
        if x == 1 || x == n - 1 {
            continue;
        }
        for _ in 1..s {
            x = mul_mod(x, x, n);
            if x == n - 1 {
                continue 'bases;
            }
        }
        return false;
    }
    true
}

/// The largest prime `P <= n` with `P ≡ 3 (mod 4)` (the primes eq. 1 permutes over), `None` for
/// `n < 3`.
pub fn largest_prime_3_mod_4(n: u64) -> Option<u64> {
    if n < 3 {
        return None;
    }
    // The largest candidate <= n that is 3 mod 4, then every fourth number below it.
    let mut p = n - (n + 1) % 4;
    loop {
        if is_prime(p) {
            return Some(p);
        }
        p -= 4; // p >= 3 always: 3 is prime and ends the loop.
    }
}

/// The incremental shuffle of paper 000 §3.3 over `0..len`: a bijection computed per index, with
/// no state shared between indices.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shuffle {
    len: u32,
    /// The prime `P ≡ 3 (mod 4)`, `P <= len`, or 0 when there is none (`len < 3`).
    prime: u32,
}

impl Shuffle {
    /// The shuffle of `len` points (indices are 32-bit, as in the framebuffer's keys).
    pub fn new(len: u32) -> Shuffle {
        let prime = largest_prime_3_mod_4(len as u64).unwrap_or(0) as u32;
        Shuffle { len, prime }
    }

    /// Number of points.
    pub fn len(&self) -> u32 {
        self.len
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The prime of eq. 1, `None` below 3 points.
    pub fn prime(&self) -> Option<u32> {
        (self.prime != 0).then_some(self.prime)
    }

    /// Points past the prime, which keep their position (at most 532 below 500 M points, §3.3).
    pub fn unshuffled(&self) -> u32 {
        self.len - self.prime
    }

    /// Eq. 1: `i^2 mod P` for `i <= P/2`, `P - (i^2 mod P)` for `P/2 < i < P`, `i` otherwise.
    #[inline]
    pub fn permute(&self, i: u32) -> u32 {
        let p = self.prime as u64;
        let i = i as u64;
        if i >= p {
            return i as u32;
        }
        // i < P < 2^32, so i^2 < 2^64.
        let residue = (i * i) % p;
        (if 2 * i <= p { residue } else { p - residue }) as u32
    }

    /// Eq. 2: the position of point `i` in the shuffled buffer, `permute(permute(i))`.
    #[inline]
    pub fn target(&self, i: u32) -> u32 {
        self.permute(self.permute(i))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn trial_division(n: u64) -> bool {
        n >= 2 && (2..).take_while(|d| d * d <= n).all(|d| !n.is_multiple_of(d))
    }

    /// Asserts that `target` is a bijection on `0..n`, that `permute` is one on `0..P` and the
    /// identity past it.
    fn check_bijection(n: u32) {
        let s = Shuffle::new(n);
        let mut seen = vec![false; n as usize];
        for i in 0..n {
            let t = s.target(i);
            assert!(t < n, "n {n}: target({i}) = {t}");
            assert!(!seen[t as usize], "n {n}: target {t} twice");
            seen[t as usize] = true;
            assert_eq!(t, s.permute(s.permute(i)));
            if i >= s.prime().unwrap_or(0) {
                assert_eq!(s.permute(i), i, "n {n}: past the prime stays");
            }
        }
        if let Some(p) = s.prime() {
            let mut seen = vec![false; p as usize];
            for i in 0..p {
                let t = s.permute(i);
                assert!(t < p && !seen[t as usize], "n {n}: permute not a bijection on 0..{p}");
                seen[t as usize] = true;
            }
        }
    }

    #[test]
    fn primality_matches_trial_division() {
        for n in 0..20_000u64 {
            assert_eq!(is_prime(n), trial_division(n), "{n}");
        }
        for n in
            [4_294_967_291u64, 4_294_967_279, 2_147_483_647, 184_007_671, 184_008_203, 1_000_003]
        {
            assert!(is_prime(n), "{n}");
        }
        for n in
            [4_294_967_295u64, 4_294_967_293, 2_147_483_649, 1_000_001, 561, 1_105, 3_215_031_751]
        {
            assert_eq!(is_prime(n), trial_division(n), "{n}");
        }
    }

    #[test]
    fn the_prime_is_the_largest_3_mod_4_at_most_n() {
        assert_eq!(largest_prime_3_mod_4(0), None);
        assert_eq!(largest_prime_3_mod_4(2), None);
        assert_eq!(largest_prime_3_mod_4(3), Some(3));
        assert_eq!(largest_prime_3_mod_4(6), Some(3));
        assert_eq!(largest_prime_3_mod_4(7), Some(7));
        assert_eq!(largest_prime_3_mod_4(18), Some(11));
        assert_eq!(largest_prime_3_mod_4(19), Some(19));
        for n in 3..5_000u64 {
            let p = largest_prime_3_mod_4(n).unwrap();
            assert!(p <= n && p % 4 == 3 && trial_division(p), "{n}: {p}");
            assert!(
                (p + 1..=n).all(|q| q % 4 != 3 || !trial_division(q)),
                "{n}: a larger one exists"
            );
        }
        // The paper's largest gap below 500 M points: 532 between 184007671 and 184008203.
        assert_eq!(largest_prime_3_mod_4(184_008_202), Some(184_007_671));
        assert_eq!(largest_prime_3_mod_4(184_008_203), Some(184_008_203));
        assert_eq!(Shuffle::new(184_008_202).unshuffled(), 531);
        // The largest prime below 2^32 is 3 mod 4, and eq. 1 does not overflow there.
        let s = Shuffle::new(u32::MAX);
        assert_eq!(s.prime(), Some(4_294_967_291));
        assert_eq!(s.unshuffled(), 4);
        let p = 4_294_967_291u64;
        let i = (p - 1) as u32;
        assert_eq!(s.permute(i) as u64, p - ((p - 1) * (p - 1)) % p);
        assert_eq!(s.permute(u32::MAX), u32::MAX);
    }

    #[test]
    fn eq_1_by_hand() {
        // P = 7: i <= 3 -> i^2 mod 7 = 0, 1, 4, 2; i = 4..6 -> 7 - (16, 25, 36 mod 7) = 5, 3, 6.
        let s = Shuffle::new(9);
        assert_eq!(s.prime(), Some(7));
        let one: Vec<u32> = (0..9).map(|i| s.permute(i)).collect();
        assert_eq!(one, [0, 1, 4, 2, 5, 3, 6, 7, 8]);
        let two: Vec<u32> = (0..9).map(|i| s.target(i)).collect();
        assert_eq!(two, [0, 1, 5, 4, 3, 2, 6, 7, 8]);
        assert_eq!(Shuffle::new(2).target(1), 1);
        assert!(Shuffle::new(0).is_empty());
    }

    #[test]
    fn bijection_for_every_small_n() {
        for n in 0..3_000 {
            check_bijection(n);
        }
    }

    #[test]
    fn bijection_at_primes_and_just_above() {
        // 3 mod 4 primes (the whole range shuffled), 1 mod 4 primes, n just above a prime, powers
        // of two.
        for n in [
            1_000_003u32,
            1_000_004,
            1_000_005,
            1_000_033,
            1_000_034,
            65_521,
            65_536,
            1 << 20,
            (1 << 20) + 1,
            999_983,
            999_984,
        ] {
            check_bijection(n);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]
        #[test]
        fn bijection_for_random_n(n in 0u32..1_500_000) {
            check_bijection(n);
        }
    }

    #[test]
    fn shuffled_prefixes_spread_over_the_buffer() {
        // The Fill pass relies on any run of slots being a random subset: the points of a run of
        // 1 % of the slots come from all over the input (here: each tenth of the input holds
        // 5-15 % of them), with eq. 2; eq. 1 alone keeps visible patterns (the paper's Fig. 4).
        let n = 1_000_000u32;
        let s = Shuffle::new(n);
        let mut inverse = vec![0u32; n as usize];
        for i in 0..n {
            inverse[s.target(i) as usize] = i;
        }
        for start in [0u32, 123_457, 500_000, 989_000] {
            let mut tenths = [0u32; 10];
            for slot in start..start + 10_000 {
                tenths[(inverse[slot as usize] as u64 * 10 / n as u64) as usize] += 1;
            }
            assert!(
                tenths.iter().all(|&c| (500..=1500).contains(&c)),
                "slots {start}..: {tenths:?}"
            );
        }
    }
}
