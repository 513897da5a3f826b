//! View frustum and box tests for per-batch culling (paper 003 §3.2: "we first load the bounding
//! box of the workgroup's batch and immediately abort if it lies outside the view frustum").
//!
//! The planes are built directly from the camera's axes, relative to the eye, so georeferenced
//! coordinates keep their precision: a box is moved to the eye-relative frame in f64 before it is
//! tested. A margin in pixels widens the side planes, which makes culling conservative against the
//! f32 rounding of the per-point projection (a culled batch never had a visible point).

use super::camera::{Camera, Projection};
use super::math::{dot, length, sub, Aabb, DVec3};

/// A plane `dot(normal, p) + offset = 0` in eye-relative world coordinates; the inside is where
/// the expression is `>= 0`. `normal` has unit length.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plane {
    /// Unit normal pointing inside.
    pub normal: DVec3,
    /// Signed offset.
    pub offset: f64,
}

impl Plane {
    fn new(normal: DVec3, offset: f64) -> Plane {
        let l = length(normal);
        Plane { normal: normal.map(|v| v / l), offset: offset / l }
    }

    /// Signed distance of an eye-relative point (positive inside).
    #[inline]
    pub fn distance(&self, p: DVec3) -> f64 {
        dot(self.normal, p) + self.offset
    }
}

/// Where a box lies with respect to the frustum.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Containment {
    /// Entirely outside: nothing of it can be seen.
    Outside,
    /// Crosses at least one plane.
    Intersecting,
    /// Entirely inside.
    Inside,
}

/// The six planes of a camera's view volume: left, right, bottom, top, near, far.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frustum {
    /// World position the planes are relative to (the camera's eye).
    pub origin: DVec3,
    /// Left, right, bottom, top, near, far.
    pub planes: [Plane; 6],
}

impl Frustum {
    /// The frustum of `camera`, its side planes moved outwards by `margin_px` pixels on each side of
    /// the viewport. The camera must be valid ([`Camera::validate`]).
    pub fn new(camera: &Camera, margin_px: f64) -> Frustum {
        let axes =
            camera.axes().expect("camera orientation is degenerate; call Camera::validate first");
        let grow_x = (camera.width as f64 + 2.0 * margin_px) / camera.width as f64;
        let grow_y = (camera.height as f64 + 2.0 * margin_px) / camera.height as f64;
        // Planes in view coordinates (x right, y up, d = depth along the view direction).
        let view_planes: [([f64; 3], f64); 6] = match camera.projection {
            Projection::Perspective { fov_y } => {
                let ty = (fov_y * 0.5).tan() * grow_y;
                let tx = (fov_y * 0.5).tan() * camera.aspect() * grow_x;
                [
                    ([1.0, 0.0, tx], 0.0),
                    ([-1.0, 0.0, tx], 0.0),
                    ([0.0, 1.0, ty], 0.0),
                    ([0.0, -1.0, ty], 0.0),
                    ([0.0, 0.0, 1.0], -camera.near),
                    ([0.0, 0.0, -1.0], camera.far),
                ]
            }
            Projection::Orthographic { height } => {
                let hy = height * 0.5 * grow_y;
                let hx = height * 0.5 * camera.aspect() * grow_x;
                [
                    ([1.0, 0.0, 0.0], hx),
                    ([-1.0, 0.0, 0.0], hx),
                    ([0.0, 1.0, 0.0], hy),
                    ([0.0, -1.0, 0.0], hy),
                    ([0.0, 0.0, 1.0], -camera.near),
                    ([0.0, 0.0, -1.0], camera.far),
                ]
            }
        };
        let planes = view_planes.map(|(n, offset)| {
            let w = [0, 1, 2]
                .map(|a| n[0] * axes.right[a] + n[1] * axes.up[a] + n[2] * axes.forward[a]);
            Plane::new(w, offset)
        });
        Frustum { origin: camera.eye, planes }
    }

    /// Whether a world point lies inside (or on) every plane.
    pub fn contains_point(&self, p: DVec3) -> bool {
        let r = sub(p, self.origin);
        self.planes.iter().all(|pl| pl.distance(r) >= 0.0)
    }

    /// Classifies a world box against the frustum. Conservative: `Outside` only when the box lies
    /// entirely on the outer side of one plane (a box near a frustum corner may be reported
    /// `Intersecting` although it is outside).
    pub fn test_aabb(&self, b: &Aabb) -> Containment {
        let lo = sub(b.min, self.origin);
        let hi = sub(b.max, self.origin);
        let mut inside = true;
        for pl in &self.planes {
            // The corner farthest along the normal, and the one farthest against it.
            let mut far = [0.0; 3];
            let mut near = [0.0; 3];
            for a in 0..3 {
                if pl.normal[a] >= 0.0 {
                    far[a] = hi[a];
                    near[a] = lo[a];
                } else {
                    far[a] = lo[a];
                    near[a] = hi[a];
                }
            }
            if pl.distance(far) < 0.0 {
                return Containment::Outside;
            }
            if pl.distance(near) < 0.0 {
                inside = false;
            }
        }
        if inside {
            Containment::Inside
        } else {
            Containment::Intersecting
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera::ViewPreset;

    fn cam(projection: Projection) -> Camera {
        Camera {
            eye: [0.0, 0.0, 0.0],
            target: [0.0, 10.0, 0.0],
            up: [0.0, 0.0, 1.0],
            projection,
            near: 1.0,
            far: 100.0,
            width: 200,
            height: 100,
        }
    }

    fn cube(c: DVec3, r: f64) -> Aabb {
        Aabb::new(c.map(|v| v - r), c.map(|v| v + r))
    }

    #[test]
    fn perspective_boxes() {
        // fov 90 degrees: at depth 10 the view spans z in [-10, 10] and x in [-20, 20].
        let f =
            Frustum::new(&cam(Projection::Perspective { fov_y: std::f64::consts::FRAC_PI_2 }), 0.0);
        assert_eq!(f.test_aabb(&cube([0.0, 10.0, 0.0], 1.0)), Containment::Inside);
        assert_eq!(f.test_aabb(&cube([0.0, -10.0, 0.0], 1.0)), Containment::Outside); // behind
        assert_eq!(f.test_aabb(&cube([0.0, 10.0, 15.0], 2.0)), Containment::Outside); // above
        assert_eq!(f.test_aabb(&cube([0.0, 10.0, 11.0], 2.0)), Containment::Intersecting); // top edge
        assert_eq!(f.test_aabb(&cube([-30.0, 10.0, 0.0], 2.0)), Containment::Outside); // left
        assert_eq!(f.test_aabb(&cube([19.0, 10.0, 0.0], 2.0)), Containment::Intersecting); // right edge
        assert_eq!(f.test_aabb(&cube([0.0, 150.0, 0.0], 10.0)), Containment::Outside); // beyond far
        assert_eq!(f.test_aabb(&cube([0.0, 0.5, 0.0], 0.2)), Containment::Outside); // before near
        assert_eq!(f.test_aabb(&cube([0.0, 1.0, 0.0], 0.2)), Containment::Intersecting); // across near
        assert_eq!(f.test_aabb(&cube([0.0, 0.0, 0.0], 1000.0)), Containment::Intersecting); // around all
        assert!(f.contains_point([0.0, 10.0, 9.9]));
        assert!(!f.contains_point([0.0, 10.0, 10.1]));
    }

    #[test]
    fn orthographic_boxes_and_margin() {
        // Height 20: z in [-10, 10], x in [-20, 20] at every depth.
        let c = cam(Projection::Orthographic { height: 20.0 });
        let f = Frustum::new(&c, 0.0);
        assert_eq!(f.test_aabb(&cube([0.0, 50.0, 0.0], 1.0)), Containment::Inside);
        assert_eq!(f.test_aabb(&cube([0.0, 50.0, 10.5], 0.4)), Containment::Outside);
        assert_eq!(f.test_aabb(&cube([20.5, 50.0, 0.0], 0.4)), Containment::Outside);
        // A margin of 10 px (of 100) widens the view by 10 % of the height on each side (2 units).
        let wide = Frustum::new(&c, 10.0);
        assert_eq!(wide.test_aabb(&cube([0.0, 50.0, 10.5], 0.4)), Containment::Inside);
        assert_eq!(wide.test_aabb(&cube([0.0, 50.0, 12.0], 0.4)), Containment::Intersecting);
        assert_eq!(wide.test_aabb(&cube([0.0, 50.0, 12.5], 0.4)), Containment::Outside);
    }

    #[test]
    fn agrees_with_projection_of_points() {
        // Every point the frustum contains projects inside the viewport and depth range, and
        // points it excludes do not, for framed cameras at georeferenced coordinates.
        let region = Aabb::new([6_400_000.0, 100_000.0, 0.0], [6_400_300.0, 100_200.0, 40.0]);
        let mut rng = crate::render::testutil::Rng(3);
        for preset in ViewPreset::ALL {
            for camera in [
                Camera::frame_perspective(&region, preset, 0.7, 640, 480).unwrap(),
                Camera::frame_orthographic(&region, preset, 640, 480).unwrap(),
            ] {
                let f = Frustum::new(&camera, 0.0);
                let big = region.expanded([300.0; 3]);
                for _ in 0..2000 {
                    let p = [0, 1, 2].map(|a| big.min[a] + rng.unit() * (big.max[a] - big.min[a]));
                    let visible = camera
                        .project(p)
                        .is_some_and(|q| q.x >= 0.0 && q.x <= 640.0 && q.y >= 0.0 && q.y <= 480.0);
                    let inside = f.contains_point(p);
                    // Allow disagreement only within a hair of a plane.
                    let margin = f
                        .planes
                        .iter()
                        .map(|pl| pl.distance(sub(p, f.origin)).abs())
                        .fold(f64::INFINITY, f64::min);
                    if margin > 1e-6 {
                        assert_eq!(visible, inside, "{preset:?} {p:?}");
                    }
                    let b = Aabb::new(p, p);
                    assert_eq!(f.test_aabb(&b) == Containment::Outside, !inside);
                }
            }
        }
    }
}
