//! Small f64 vector and matrix helpers for the camera (paper 003 §3.2: the view-projection
//! transform), and the axis-aligned box the camera frames and the frustum tests.
//!
//! World coordinates may be georeferenced (UTM ~1e6 m, ECEF ~6.4e6 m), so everything here is f64;
//! the f32 transforms of the rasterizer are derived per batch, relative to the eye
//! ([`crate::render::camera::BatchProjection`]).

/// A 3-vector in f64.
pub type DVec3 = [f64; 3];

#[inline]
pub(crate) fn add(a: DVec3, b: DVec3) -> DVec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

#[inline]
pub(crate) fn sub(a: DVec3, b: DVec3) -> DVec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
pub(crate) fn scale(a: DVec3, s: f64) -> DVec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

#[inline]
pub(crate) fn dot(a: DVec3, b: DVec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
pub(crate) fn cross(a: DVec3, b: DVec3) -> DVec3 {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

#[inline]
pub(crate) fn length(a: DVec3) -> f64 {
    dot(a, a).sqrt()
}

/// `a / |a|`, or `None` for a zero or non-finite vector.
#[inline]
pub(crate) fn normalize(a: DVec3) -> Option<DVec3> {
    let l = length(a);
    if l > 0.0 && l.is_finite() {
        Some(scale(a, 1.0 / l))
    } else {
        None
    }
}

/// A 4x4 f64 matrix, stored as rows: `m.rows[r][c]`, applied to column vectors (`m * v`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DMat4 {
    /// The four rows.
    pub rows: [[f64; 4]; 4],
}

impl DMat4 {
    /// The identity.
    pub const IDENTITY: DMat4 = DMat4 {
        rows: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ],
    };

    /// The product `self * rhs` (apply `rhs` first).
    pub fn mul(&self, rhs: &DMat4) -> DMat4 {
        let mut rows = [[0.0; 4]; 4];
        for (r, row) in rows.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = (0..4).map(|k| self.rows[r][k] * rhs.rows[k][c]).sum();
            }
        }
        DMat4 { rows }
    }

    /// `self * v` for a homogeneous vector.
    #[inline]
    pub fn mul_vec4(&self, v: [f64; 4]) -> [f64; 4] {
        let mut out = [0.0; 4];
        for (o, row) in out.iter_mut().zip(&self.rows) {
            *o = row[0] * v[0] + row[1] * v[1] + row[2] * v[2] + row[3] * v[3];
        }
        out
    }

    /// `self * (p, 1)`.
    #[inline]
    pub fn mul_point(&self, p: DVec3) -> [f64; 4] {
        self.mul_vec4([p[0], p[1], p[2], 1.0])
    }
}

/// An axis-aligned box in world coordinates (f64), `min <= max` on every axis for a non-empty box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Smallest corner.
    pub min: DVec3,
    /// Largest corner.
    pub max: DVec3,
}

impl Aabb {
    /// The empty box: growing it by a point gives that point.
    pub const EMPTY: Aabb = Aabb { min: [f64::INFINITY; 3], max: [f64::NEG_INFINITY; 3] };

    /// The box with corners `min` and `max`.
    pub fn new(min: DVec3, max: DVec3) -> Aabb {
        Aabb { min, max }
    }

    /// Whether the box holds no point (some `min > max`, or NaN).
    pub fn is_empty(&self) -> bool {
        !(0..3).all(|a| self.min[a] <= self.max[a])
    }

    /// The box grown to hold `p`.
    pub fn grow(&mut self, p: DVec3) {
        for a in 0..3 {
            self.min[a] = self.min[a].min(p[a]);
            self.max[a] = self.max[a].max(p[a]);
        }
    }

    /// The box grown by `margin[a]` on both sides of axis `a`.
    pub fn expanded(&self, margin: DVec3) -> Aabb {
        Aabb { min: sub(self.min, margin), max: add(self.max, margin) }
    }

    /// The centre.
    pub fn center(&self) -> DVec3 {
        scale(add(self.min, self.max), 0.5)
    }

    /// The extent `max - min`.
    pub fn size(&self) -> DVec3 {
        sub(self.max, self.min)
    }

    /// Length of the diagonal.
    pub fn diagonal(&self) -> f64 {
        length(self.size())
    }

    /// The eight corners; bit `a` of the index picks `max` on axis `a`.
    pub fn corners(&self) -> [DVec3; 8] {
        let mut c = [[0.0; 3]; 8];
        for (i, corner) in c.iter_mut().enumerate() {
            for a in 0..3 {
                corner[a] = if i >> a & 1 == 1 { self.max[a] } else { self.min[a] };
            }
        }
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matrix_product_applies_right_first() {
        let mut t = DMat4::IDENTITY;
        t.rows[0][3] = 5.0; // translate x by 5
        let mut s = DMat4::IDENTITY;
        s.rows[0][0] = 2.0; // scale x by 2
        assert_eq!(s.mul(&t).mul_point([1.0, 0.0, 0.0])[0], 12.0);
        assert_eq!(t.mul(&s).mul_point([1.0, 0.0, 0.0])[0], 7.0);
    }

    #[test]
    fn box_basics() {
        let mut b = Aabb::EMPTY;
        assert!(b.is_empty());
        b.grow([1.0, 2.0, 3.0]);
        b.grow([-1.0, 4.0, 3.0]);
        assert!(!b.is_empty());
        assert_eq!(b.center(), [0.0, 3.0, 3.0]);
        assert_eq!(b.corners()[0], [-1.0, 2.0, 3.0]);
        assert_eq!(b.corners()[7], [1.0, 4.0, 3.0]);
        assert_eq!(cross([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), [0.0, 0.0, 1.0]);
    }
}
