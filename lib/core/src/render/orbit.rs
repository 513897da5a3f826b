//! The orbit camera of `mortar view` and `build --preview`: a target, a distance and a direction
//! (azimuth and elevation, z up) that mouse drags turn, pan and zoom, turned into a [`Camera`]
//! per frame. Pure maths, no window: the viewer (mortar-app) feeds it the mouse's motion.
//!
//! ```
//! use mortar_core::render::{Aabb, Camera, Orbit, ViewPreset};
//! let bounds = Aabb::new([0.0, 0.0, 0.0], [100.0, 50.0, 20.0]);
//! let start = Camera::frame_perspective(&bounds, ViewPreset::Iso, 0.8, 640, 480).unwrap();
//! let mut orbit = Orbit::from_camera(&start);
//! orbit.rotate(40.0, 0.0); // a drag of 40 pixels to the right
//! orbit.zoom(1.0, &bounds); // one wheel line in
//! let camera = orbit.camera(0.8, false, &bounds, 640, 480).unwrap();
//! assert!(camera.project(bounds.center()).is_some());
//! ```

use super::camera::{Camera, CameraError, Projection};
use super::math::Aabb;

/// The camera as the mouse moves it: a target, a distance, and the direction from the target to
/// the eye as azimuth (`yaw`, from +x towards +y) and elevation (`pitch`), with z up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Orbit {
    pub target: [f64; 3],
    pub distance: f64,
    pub yaw: f64,
    pub pitch: f64,
}

/// The elevation stops short of the poles, where the view direction would be parallel to up.
pub const MAX_PITCH: f64 = 89.5 * std::f64::consts::PI / 180.0;

/// Radians of turn per pixel of drag.
const TURN_PER_PIXEL: f64 = 0.005;

impl Orbit {
    /// The orbit through `c`'s eye around its target.
    pub fn from_camera(c: &Camera) -> Orbit {
        let d = [0, 1, 2].map(|i| c.eye[i] - c.target[i]);
        let distance = d.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-12);
        let dir = d.map(|v| v / distance);
        // Straight down (or up): the azimuth from the camera's up vector, so a top view keeps north
        // up.
        let yaw =
            if dir[2].abs() > 0.9999 { (-c.up[1]).atan2(-c.up[0]) } else { dir[1].atan2(dir[0]) };
        Orbit {
            target: c.target,
            distance,
            yaw,
            pitch: dir[2].clamp(-1.0, 1.0).asin().clamp(-MAX_PITCH, MAX_PITCH),
        }
    }

    /// Where the eye is.
    pub fn eye(&self) -> [f64; 3] {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        let d = [cp * cy, cp * sy, sp];
        [0, 1, 2].map(|i| self.target[i] + self.distance * d[i])
    }

    /// The camera of this orbit: perspective with vertical field of view `fov_y`, or
    /// orthographic with the height that field of view sees at the target's distance.
    pub fn camera(
        &self,
        fov_y: f64,
        ortho: bool,
        bounds: &Aabb,
        width: u32,
        height: u32,
    ) -> Result<Camera, CameraError> {
        let projection = if ortho {
            Projection::Orthographic { height: 2.0 * self.distance * (0.5 * fov_y).tan() }
        } else {
            Projection::Perspective { fov_y }
        };
        Camera::look_at(self.eye(), self.target, [0.0, 0.0, 1.0], projection, bounds, width, height)
    }

    /// A drag of `(dx, dy)` pixels turns the eye around the target (right: the view turns left;
    /// down: the eye rises).
    pub fn rotate(&mut self, dx: f64, dy: f64) {
        self.yaw -= dx * TURN_PER_PIXEL;
        self.pitch = (self.pitch + dy * TURN_PER_PIXEL).clamp(-MAX_PITCH, MAX_PITCH);
    }

    /// A drag of `(dx, dy)` pixels moves the target with the cursor in the plane of the view, at
    /// the target's distance; `camera` is this orbit's camera (vertical field of view `fov_y`)
    /// for the window. `None` where the camera has no axes (degenerate).
    pub fn pan(&mut self, dx: f64, dy: f64, fov_y: f64, camera: &Camera) -> Option<()> {
        let axes = camera.axes()?;
        // World units per pixel at the target's distance.
        let per_px = 2.0 * self.distance * (0.5 * fov_y).tan() / camera.height.max(1) as f64;
        for i in 0..3 {
            self.target[i] += (-dx * axes.right[i] + dy * axes.up[i]) * per_px;
        }
        Some(())
    }

    /// `lines` wheel lines in (negative: out): 15 % closer per line, within 1e-6 and 100 times
    /// the extent of `bounds`.
    pub fn zoom(&mut self, lines: f64, bounds: &Aabb) {
        let extent = bounds.diagonal().max(1e-9);
        self.distance = (self.distance * 0.85f64.powf(lines)).clamp(extent * 1e-6, extent * 100.0);
    }

    /// Looks at the centre of `bounds` from the current direction, from the distance at which every
    /// corner of the bounds is in view with a small margin (as `Camera::frame_perspective` does
    /// for its preset directions).
    pub fn fit(&mut self, bounds: &Aabb, fov_y: f64, width: u32, height: u32) {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        let forward = [-cp * cy, -cp * sy, -sp];
        // right = forward x z (the pitch stops short of the poles, so it is not zero), up = right x forward.
        let n = (forward[0] * forward[0] + forward[1] * forward[1]).sqrt().max(1e-12);
        let right = [forward[1] / n, -forward[0] / n, 0.0];
        let up = [
            right[1] * forward[2],
            -right[0] * forward[2],
            right[0] * forward[1] - right[1] * forward[0],
        ];
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let ty = (0.5 * fov_y).tan() / 1.05;
        let tx = ty * width.max(1) as f64 / height.max(1) as f64;
        let c = bounds.center();
        let extent = bounds.diagonal().max(1e-9);
        let (mut dist, mut min_f) = (0.0f64, f64::INFINITY);
        for k in bounds.corners() {
            let d = [k[0] - c[0], k[1] - c[1], k[2] - c[2]];
            let (x, y, f) = (dot(right, d), dot(up, d), dot(forward, d));
            dist = dist.max(x.abs() / tx - f).max(y.abs() / ty - f);
            min_f = min_f.min(f);
        }
        self.target = c;
        self.distance = dist.max(-min_f + 0.05 * extent).max(0.5 * extent);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::ViewPreset;

    #[test]
    fn orbit_round_trips_a_camera() {
        let bounds = Aabb::new([0.0, 0.0, 0.0], [100.0, 50.0, 20.0]);
        let cam = Camera::frame_perspective(&bounds, ViewPreset::Iso, 0.8, 640, 480).unwrap();
        let o = Orbit::from_camera(&cam);
        let back = o.camera(0.8, false, &bounds, 640, 480).unwrap();
        for i in 0..3 {
            assert!(
                (back.eye[i] - cam.eye[i]).abs() < 1e-6 * o.distance,
                "{:?} vs {:?}",
                back.eye,
                cam.eye
            );
        }
        // A top view keeps north up: the eye is displaced south of the target.
        let top = Camera::frame_perspective(&bounds, ViewPreset::Top, 0.8, 640, 480).unwrap();
        let o = Orbit::from_camera(&top);
        assert!(o.eye()[1] < o.target[1] && (o.eye()[0] - o.target[0]).abs() < 1e-6 * o.distance);
        assert!(o.camera(0.8, false, &bounds, 640, 480).is_ok());
    }

    #[test]
    fn fit_shows_every_corner() {
        let bounds = Aabb::new([1000.0, 2000.0, 0.0], [1100.0, 2300.0, 40.0]);
        for (w, h) in [(640, 480), (300, 900)] {
            let mut o = Orbit { target: [0.0; 3], distance: 1.0, yaw: 0.7, pitch: 0.4 };
            o.fit(&bounds, 0.9, w, h);
            let cam = o.camera(0.9, false, &bounds, w, h).unwrap();
            let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
            for k in bounds.corners() {
                let p = cam.project(k).expect("in front of the eye");
                assert!(
                    p.x >= 0.0 && p.x <= w as f64 && p.y >= 0.0 && p.y <= h as f64,
                    "{k:?} at {p:?} outside {w}x{h}"
                );
                lo = [lo[0].min(p.x), lo[1].min(p.y)];
                hi = [hi[0].max(p.x), hi[1].max(p.y)];
            }
            // Tight: the box spans most of the window in one direction.
            assert!(
                (hi[0] - lo[0]) / w as f64 > 0.8 || (hi[1] - lo[1]) / h as f64 > 0.8,
                "{lo:?}..{hi:?} in {w}x{h}"
            );
        }
    }

    #[test]
    fn drags_turn_pan_and_zoom_within_limits() {
        let bounds = Aabb::new([0.0, 0.0, 0.0], [100.0, 100.0, 10.0]);
        let cam = Camera::frame_perspective(&bounds, ViewPreset::Iso, 0.8, 640, 480).unwrap();
        let mut o = Orbit::from_camera(&cam);
        let before = o;
        o.rotate(0.0, 1e6);
        assert_eq!(o.pitch, MAX_PITCH);
        o.rotate(100.0, 0.0);
        assert!((o.yaw - (before.yaw - 0.5)).abs() < 1e-12);
        for _ in 0..1000 {
            o.zoom(1.0, &bounds);
        }
        assert!((o.distance - bounds.diagonal() * 1e-6).abs() < 1e-12);
        let mut p = before;
        let cam = p.camera(0.8, false, &bounds, 640, 480).unwrap();
        p.pan(10.0, 0.0, 0.8, &cam).unwrap();
        // Dragging right moves the target left on screen's right axis: its distance is unchanged.
        assert_ne!(p.target, before.target);
        assert!((p.distance - before.distance).abs() < 1e-12);
    }
}
