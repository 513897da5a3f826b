//! The camera and the per-batch f32 projection (paper 003 §3.2, Listing 1: `worldViewProj *
//! position`, then the pixel; §3.3: the batch-relative quantized position it is applied to).
//!
//! The camera lives in f64 world coordinates, which may be georeferenced (ECEF ~6.4e6 m), so no
//! absolute world coordinate ever reaches f32. For each batch, [`Camera::batch_projection`] builds
//! in f64 the transform from the batch's quantized integer offsets to pixels, relative to the eye,
//! and rounds only that transform to f32 ([`BatchProjection`]); per point the rasterizer then does
//! only integer and f32 math. Two choices keep the f32 error small and the result independent of
//! the batch a point is stored in:
//!
//! - an integer `anchor`, the eye's position on the grid, is subtracted from each point's integer
//!   offset before it becomes an f32 (in i32, exact), so the f32 values are the point's distance
//!   from the eye and never suffer from the batch's absolute position or size; being the same for
//!   every batch, it also makes a point's projection independent of the batch that holds it
//!   (the progressive renderer's one frame and the batch file's many give the same keys);
//! - the pixel coordinate is computed relative to an integer `pixel_origin`, the viewport's
//!   centre (for the same reason the same for every batch), so its f32 spacing is that of half
//!   the viewport (6e-5 px at 960 px).
//!
//! A batch reaching 2^30 grid units from the eye keeps the batch-local numerics (anchor at its
//! point nearest to the eye, pixel origin at its projected centre): `p - eye` must stay in i32.
//!
//! Conventions: right-handed world with z up (LAS); the view looks down its -z axis; view depth is
//! the distance along the viewing direction, positive in front; pixel (0, 0) is the top-left pixel,
//! pixel `(i, j)` covers `[i, i+1) x [j, j+1)`; clip space follows wgpu (z in `[0, 1]`).

use super::math::{cross, dot, length, normalize, scale, sub, Aabb, DMat4, DVec3};
use crate::grid::Grid;
use crate::quantize::{BatchGrid, Precision, MAX_BITS};

/// Largest viewport side: pixel bounds stay exact in f32 and `width * height` fits easily.
pub const MAX_VIEWPORT: u32 = 1 << 15;

/// The lens of a camera.
/// Grid units from the eye beyond which a batch is anchored at its own point nearest to the eye
/// rather than at the eye (`p - eye` must stay far inside i32 for the per-point local coordinate).
pub const FAR_UNITS: f32 = (1u32 << 30) as f32;

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Projection {
    /// Perspective with the vertical field of view `fov_y` in radians, `0 < fov_y < pi`.
    Perspective {
        /// Vertical field of view in radians.
        fov_y: f64,
    },
    /// Orthographic, showing `height` world units vertically.
    Orthographic {
        /// Visible height in world units.
        height: f64,
    },
}

/// Standard views for [`Camera::frame_perspective`] and [`Camera::frame_orthographic`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ViewPreset {
    /// From above, looking down -z, north (+y) up.
    Top,
    /// From the south, looking north (+y), z up.
    Front,
    /// From the east, looking west (-x), z up.
    Side,
    /// From the south-west and above, looking along (1, 1, -1), z up.
    Iso,
}

impl ViewPreset {
    /// All presets, in a stable order.
    pub const ALL: [ViewPreset; 4] =
        [ViewPreset::Top, ViewPreset::Front, ViewPreset::Side, ViewPreset::Iso];

    /// The viewing direction and up vector of the preset.
    pub fn direction_and_up(self) -> (DVec3, DVec3) {
        match self {
            ViewPreset::Top => ([0.0, 0.0, -1.0], [0.0, 1.0, 0.0]),
            ViewPreset::Front => ([0.0, 1.0, 0.0], [0.0, 0.0, 1.0]),
            ViewPreset::Side => ([-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
            ViewPreset::Iso => {
                let s = 1.0 / 3f64.sqrt();
                ([s, s, -s], [0.0, 0.0, 1.0])
            }
        }
    }

    /// The preset's name as used on the command line (`top`, `front`, `side`, `iso`).
    pub fn name(self) -> &'static str {
        match self {
            ViewPreset::Top => "top",
            ViewPreset::Front => "front",
            ViewPreset::Side => "side",
            ViewPreset::Iso => "iso",
        }
    }

    /// The preset of a name given by [`name`](Self::name).
    pub fn from_name(name: &str) -> Option<ViewPreset> {
        ViewPreset::ALL.into_iter().find(|p| p.name() == name)
    }
}

/// Why a camera cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// Width or height is 0 or larger than [`MAX_VIEWPORT`].
    #[error("viewport {width}x{height} is not supported (each side must be 1 to {max} pixels)", max = MAX_VIEWPORT)]
    Viewport {
        /// Requested width.
        width: u32,
        /// Requested height.
        height: u32,
    },
    /// Near or far plane out of order or not finite.
    #[error("clip planes near {near} and far {far} must satisfy 0 < near < far < infinity")]
    ClipPlanes {
        /// Near plane.
        near: f64,
        /// Far plane.
        far: f64,
    },
    /// A field of view outside `(0, pi)` or an orthographic height that is not positive.
    #[error("projection {0:?} is not valid (fov must be in (0, pi) radians, height positive)")]
    Projection(Projection),
    /// Eye, target and up do not define a view (coincident, parallel or not finite).
    #[error("eye {eye:?}, target {target:?} and up {up:?} do not define a view direction")]
    Orientation {
        /// Eye position.
        eye: DVec3,
        /// Target position.
        target: DVec3,
        /// Up vector.
        up: DVec3,
    },
    /// The bounds to frame are empty or not finite.
    #[error("cannot frame the bounds {min:?}..{max:?}: empty or not finite")]
    Bounds {
        /// Smallest corner.
        min: DVec3,
        /// Largest corner.
        max: DVec3,
    },
}

/// A camera in f64 world coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position (world).
    pub eye: DVec3,
    /// The point looked at (world); only its direction from the eye matters.
    pub target: DVec3,
    /// Approximate up direction; must not be parallel to `target - eye`.
    pub up: DVec3,
    /// The lens.
    pub projection: Projection,
    /// Near clip distance along the view direction, `> 0`.
    pub near: f64,
    /// Far clip distance along the view direction, `> near`.
    pub far: f64,
    /// Viewport width in pixels.
    pub width: u32,
    /// Viewport height in pixels.
    pub height: u32,
}

/// The orthonormal axes of a view in world coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewAxes {
    /// Screen right.
    pub right: DVec3,
    /// Screen up.
    pub up: DVec3,
    /// Viewing direction (into the screen).
    pub forward: DVec3,
}

/// A point projected in f64: continuous pixel coordinates and view depth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectedPoint {
    /// Horizontal pixel coordinate; pixel column `floor(x)`.
    pub x: f64,
    /// Vertical pixel coordinate, downwards; pixel row `floor(y)`.
    pub y: f64,
    /// Distance along the viewing direction.
    pub depth: f64,
}

/// The f32 transform of one batch: from a point's quantized integer offset to pixel coordinates.
///
/// This is the batch's `clip_from_batch` of paper 003 §3.2 with the viewport transform folded in.
/// For a point with packed words `w` (only the first `words` read):
///
/// ```text
/// q      = join_words(w)                           // 30-bit numbers, crate::quantize
/// local  = f32((q >> shift) as i32 - anchor)       // integer-grid units, exact integer subtraction
/// (X, Y, D, W) = pixel_from_local * (local, 1)     // rows, f32
/// depth  = D                                       // view depth, drawn if near <= D <= far
/// pixel  = pixel_origin + floor((X / W, Y / W))    // drawn if inside the viewport
/// ```
///
/// The centre of the unloaded low bits (see [`BatchGrid::decode_relative`]) is part of the
/// translation, so the result equals projecting `decode_relative(w, precision)`.
///
/// `#[repr(C)]` and Pod: the per-batch projection the GPU passes read inside a
/// [`DrawRecord`](super::gpu::DrawRecord) (112 bytes; WGSL mirror `BatchProjection` in
/// `shaders/common/types.wgsl`, keep in sync: mortar-render's layout test compares them).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct BatchProjection {
    /// Rows X, Y, D, W: homogeneous pixel coordinates relative to `pixel_origin`, view depth, and w.
    pub pixel_from_local: [[f32; 4]; 4],
    /// Integer offset subtracted from each point's decoded integer offset.
    pub anchor: [i32; 3],
    /// Number of packed words to read per point (1-3).
    pub words: u32,
    /// Right shift from a 30-bit number to the integer offset, `30 - bits`, per axis.
    pub shift: [u32; 3],
    /// Padding (WGSL aligns vec3 to 16 bytes).
    pub _pad0: u32,
    /// Integer pixel added to the projected pixel offsets.
    pub pixel_origin: [i32; 2],
    /// Padding to a multiple of 16 bytes.
    pub _pad1: [u32; 2],
}

const _: () = assert!(std::mem::size_of::<BatchProjection>() == 112);

impl BatchProjection {
    /// The f32 local coordinate of a point from its 30-bit numbers `q` (see [`crate::quantize::join_words`]).
    #[inline(always)]
    pub fn local(&self, q: [u32; 3]) -> [f32; 3] {
        [
            ((q[0] >> self.shift[0]) as i32 - self.anchor[0]) as f32,
            ((q[1] >> self.shift[1]) as i32 - self.anchor[1]) as f32,
            ((q[2] >> self.shift[2]) as i32 - self.anchor[2]) as f32,
        ]
    }

    /// `pixel_from_local * (l, 1)`: `[X, Y, D, W]`.
    #[inline(always)]
    pub fn transform(&self, l: [f32; 3]) -> [f32; 4] {
        let m = &self.pixel_from_local;
        let row = |r: usize| m[r][0] * l[0] + m[r][1] * l[1] + m[r][2] * l[2] + m[r][3];
        [row(0), row(1), row(2), row(3)]
    }
}

impl Camera {
    /// Checks that the camera defines a view.
    pub fn validate(&self) -> Result<(), CameraError> {
        if self.width == 0
            || self.height == 0
            || self.width > MAX_VIEWPORT
            || self.height > MAX_VIEWPORT
        {
            return Err(CameraError::Viewport { width: self.width, height: self.height });
        }
        if !(self.near > 0.0 && self.far > self.near && self.far.is_finite()) {
            return Err(CameraError::ClipPlanes { near: self.near, far: self.far });
        }
        let ok = match self.projection {
            Projection::Perspective { fov_y } => fov_y > 0.0 && fov_y < std::f64::consts::PI,
            Projection::Orthographic { height } => height > 0.0 && height.is_finite(),
        };
        if !ok {
            return Err(CameraError::Projection(self.projection));
        }
        if self.axes().is_none() || !self.eye.iter().all(|v| v.is_finite()) {
            return Err(CameraError::Orientation {
                eye: self.eye,
                target: self.target,
                up: self.up,
            });
        }
        Ok(())
    }

    /// Width over height.
    pub fn aspect(&self) -> f64 {
        self.width as f64 / self.height as f64
    }

    /// The view's axes, or `None` if eye, target and up are degenerate.
    pub fn axes(&self) -> Option<ViewAxes> {
        let forward = normalize(sub(self.target, self.eye))?;
        let right = normalize(cross(forward, self.up))?;
        let up = cross(right, forward);
        Some(ViewAxes { right, up, forward })
    }

    fn axes_or_panic(&self) -> ViewAxes {
        self.axes().expect("camera orientation is degenerate; call Camera::validate first")
    }

    /// Half the visible extent on x and y: tangents of the half angles (perspective) or world
    /// units (orthographic).
    pub(crate) fn half_extent(&self) -> [f64; 2] {
        match self.projection {
            Projection::Perspective { fov_y } => {
                let ty = (fov_y * 0.5).tan();
                [ty * self.aspect(), ty]
            }
            Projection::Orthographic { height } => [height * 0.5 * self.aspect(), height * 0.5],
        }
    }

    /// Whether the projection is perspective.
    pub fn is_perspective(&self) -> bool {
        matches!(self.projection, Projection::Perspective { .. })
    }

    /// The view transform: world to a right-handed view space looking down -z.
    ///
    /// Its translation holds the absolute eye position, so apply it in f64 only; the rasterizer
    /// works eye-relative ([`batch_projection`](Self::batch_projection)).
    pub fn view_from_world(&self) -> DMat4 {
        let ViewAxes { right: r, up: u, forward: f } = self.axes_or_panic();
        let e = self.eye;
        DMat4 {
            rows: [
                [r[0], r[1], r[2], -dot(r, e)],
                [u[0], u[1], u[2], -dot(u, e)],
                [-f[0], -f[1], -f[2], dot(f, e)],
                [0.0, 0.0, 0.0, 1.0],
            ],
        }
    }

    /// The projection: view space to clip space (wgpu conventions, z in `[0, 1]`).
    pub fn clip_from_view(&self) -> DMat4 {
        let [hx, hy] = self.half_extent();
        let (n, f) = (self.near, self.far);
        match self.projection {
            Projection::Perspective { .. } => DMat4 {
                rows: [
                    [1.0 / hx, 0.0, 0.0, 0.0],
                    [0.0, 1.0 / hy, 0.0, 0.0],
                    [0.0, 0.0, f / (n - f), n * f / (n - f)],
                    [0.0, 0.0, -1.0, 0.0],
                ],
            },
            Projection::Orthographic { .. } => DMat4 {
                rows: [
                    [1.0 / hx, 0.0, 0.0, 0.0],
                    [0.0, 1.0 / hy, 0.0, 0.0],
                    [0.0, 0.0, 1.0 / (n - f), n / (n - f)],
                    [0.0, 0.0, 0.0, 1.0],
                ],
            },
        }
    }

    /// `clip_from_view * view_from_world`, in f64.
    pub fn clip_from_world(&self) -> DMat4 {
        self.clip_from_view().mul(&self.view_from_world())
    }

    /// Eye-relative view coordinates `(x, y, depth)` of a world point, in f64.
    #[inline]
    fn view_of(&self, axes: &ViewAxes, world: DVec3) -> DVec3 {
        let v = sub(world, self.eye);
        [dot(axes.right, v), dot(axes.up, v), dot(axes.forward, v)]
    }

    /// Continuous pixel coordinates of view coordinates (depth must be positive for perspective).
    #[inline]
    fn pixel_of_view(&self, v: DVec3) -> [f64; 2] {
        self.pixel_of_view_with(self.half_extent(), v)
    }

    /// [`Camera::pixel_of_view`] with the half extent computed once by the caller (a `tan`).
    #[inline]
    fn pixel_of_view_with(&self, [hx, hy]: [f64; 2], v: DVec3) -> [f64; 2] {
        let (nx, ny) = match self.projection {
            Projection::Perspective { .. } => (v[0] / (v[2] * hx), v[1] / (v[2] * hy)),
            Projection::Orthographic { .. } => (v[0] / hx, v[1] / hy),
        };
        [(nx + 1.0) * 0.5 * self.width as f64, (1.0 - ny) * 0.5 * self.height as f64]
    }

    /// The f64 reference projection of a world point: pixel coordinates and view depth, or `None`
    /// when the point lies outside `[near, far]` in depth. Points outside the viewport are returned
    /// too (their pixel lies outside `[0, width) x [0, height)`).
    pub fn project(&self, world: DVec3) -> Option<ProjectedPoint> {
        let axes = self.axes_or_panic();
        let v = self.view_of(&axes, world);
        if !(v[2] >= self.near && v[2] <= self.far) {
            return None;
        }
        let [x, y] = self.pixel_of_view(v);
        Some(ProjectedPoint { x, y, depth: v[2] })
    }

    /// The screen rectangle `(lo, hi)` in continuous pixel coordinates around the part of the box
    /// in front of the near plane (the box is clipped there, so a box around the eye gives a finite
    /// rectangle); `None` when the box lies entirely behind the near plane.
    pub fn screen_rect(&self, bounds: &Aabb) -> Option<([f64; 2], [f64; 2])> {
        let axes = self.axes_or_panic();
        let corners = bounds.corners().map(|c| self.view_of(&axes, c));
        let half = self.half_extent();
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        let mut add = |v: DVec3| {
            let p = self.pixel_of_view_with(half, v);
            for a in 0..2 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        };
        let near = self.near;
        for (i, c) in corners.iter().enumerate() {
            if c[2] >= near {
                add(*c);
            }
            // The 12 edges: from corner i to the corner with one more bit set.
            for a in 0..3 {
                if i >> a & 1 == 0 {
                    let d = corners[i | 1 << a];
                    if (c[2] < near) != (d[2] < near) {
                        let t = (near - c[2]) / (d[2] - c[2]);
                        add([c[0] + t * (d[0] - c[0]), c[1] + t * (d[1] - c[1]), near]);
                    }
                }
            }
        }
        (lo[0] <= hi[0]).then_some((lo, hi))
    }

    /// An upper bound, in pixels (Euclidean), of how far any point of `bounds` moves on screen when
    /// it is displaced by at most `err[a]` world units along each axis `a`, over the displaced
    /// points that are drawn (depth at least `near`). The precision rule's guarantee
    /// ([`crate::render::precision`]): `err` is a decode's error bound, so no point of a batch lands
    /// farther than this from where its exact position projects.
    ///
    /// With view coordinates `(x, y, z)` of the exact point and a displacement `d` whose view
    /// components obey `|dx| <= Ex = sum |right_a| err_a` (likewise `Ey`, `Ez` with the up and
    /// forward axes), the perspective pixel moves by
    /// `sx * (dx - (x / z) dz) / (z + dz)` horizontally (`sx` pixels per unit of `x / z`), so
    /// `|Δpx| <= sx * (Ex + Tx * Ez) / D` with `Tx` the largest `|x / z|` over the box and `D` the
    /// smallest depth a drawn displaced point can have: `max(near, zmin - Ez)`. Both come from the
    /// box's corners (and its edges' crossings of the plane `z = near - Ez`, below which no point
    /// can reach the near plane): perspective depth across the batch (a near end much closer than
    /// the far end) and grazing views (a depth error seen far off-axis) are both in it. An
    /// orthographic pixel moves by `sx * dx` exactly. Infinite when the box reaches the eye's plane.
    pub fn displacement_bound_px(&self, bounds: &Aabb, err: [f64; 3]) -> f64 {
        let axes = self.axes_or_panic();
        let reach = |axis: DVec3| (0..3).map(|a| axis[a].abs() * err[a]).sum::<f64>();
        let (ex, ey, ez) = (reach(axes.right), reach(axes.up), reach(axes.forward));
        let [hx, hy] = self.half_extent();
        let (sx, sy) = (0.5 * self.width as f64 / hx, 0.5 * self.height as f64 / hy);
        let (bx, by) = match self.projection {
            Projection::Orthographic { .. } => (sx * ex, sy * ey),
            Projection::Perspective { .. } => {
                if bounds.is_empty() {
                    return 0.0;
                }
                // Points nearer than `clip` cannot be displaced onto the near plane; where the
                // error reaches past the eye's plane, the box must lie wholly in front of it.
                let corners = bounds.corners().map(|c| self.view_of(&axes, c));
                let mut clip = self.near - ez;
                if clip.is_nan() || clip <= 0.0 {
                    if corners.iter().any(|c| c[2].is_nan() || c[2] <= 0.0) {
                        return f64::INFINITY;
                    }
                    clip = 0.0;
                }
                let (mut tx, mut ty, mut zmin) = (0f64, 0f64, f64::INFINITY);
                let mut any = false;
                let mut add = |v: DVec3| {
                    tx = tx.max((v[0] / v[2]).abs());
                    ty = ty.max((v[1] / v[2]).abs());
                    zmin = zmin.min(v[2]);
                    any = true;
                };
                for (i, c) in corners.iter().enumerate() {
                    if c[2] >= clip {
                        add(*c);
                    }
                    for a in 0..3 {
                        if i >> a & 1 == 0 {
                            let d = corners[i | 1 << a];
                            if (c[2] < clip) != (d[2] < clip) {
                                let t = (clip - c[2]) / (d[2] - c[2]);
                                add([c[0] + t * (d[0] - c[0]), c[1] + t * (d[1] - c[1]), clip]);
                            }
                        }
                    }
                }
                if !any {
                    return 0.0;
                }
                let depth = self.near.max(zmin - ez);
                (sx * (ex + tx * ez) / depth, sy * (ey + ty * ez) / depth)
            }
        };
        let b = (bx * bx + by * by).sqrt();
        if b.is_nan() {
            f64::INFINITY
        } else {
            b
        }
    }

    /// Size in pixels of the box's projection: the larger side of its [`screen_rect`](Self::screen_rect);
    /// 0 when the box lies entirely behind the near plane.
    pub fn projected_size(&self, bounds: &Aabb) -> f64 {
        match self.screen_rect(bounds) {
            Some((lo, hi)) => (hi[0] - lo[0]).max(hi[1] - lo[1]),
            None => 0.0,
        }
    }

    /// A perspective camera showing all of `bounds` from the preset's direction, with a small margin.
    pub fn frame_perspective(
        bounds: &Aabb,
        preset: ViewPreset,
        fov_y: f64,
        width: u32,
        height: u32,
    ) -> Result<Camera, CameraError> {
        let projection = Projection::Perspective { fov_y };
        let mut cam = Camera::framing_start(bounds, preset, projection, width, height)?;
        let axes = cam.axes_or_panic();
        let [hx, hy] = cam.half_extent();
        let (hx, hy) = (hx / 1.05, hy / 1.05);
        let c = bounds.center();
        let extent = bounds.diagonal().max(1e-6 * length(c)).max(1e-9);
        // Distance from the centre such that every corner lies inside the (shrunk) view.
        let mut dist: f64 = 0.0;
        let mut min_f = f64::INFINITY;
        let mut max_f = f64::NEG_INFINITY;
        for k in bounds.corners() {
            let d = sub(k, c);
            let (x, y, f) = (dot(axes.right, d), dot(axes.up, d), dot(axes.forward, d));
            dist = dist.max(x.abs() / hx - f).max(y.abs() / hy - f);
            min_f = min_f.min(f);
            max_f = max_f.max(f);
        }
        dist = dist.max(-min_f + 0.05 * extent).max(extent * 0.5);
        cam.eye = sub(c, scale(axes.forward, dist));
        cam.target = c;
        cam.near = ((dist + min_f) * 0.5).max(dist * 1e-6);
        cam.far = (dist + max_f) * 2.0 + extent;
        Ok(cam)
    }

    /// An orthographic camera showing all of `bounds` from the preset's direction, with a small margin.
    pub fn frame_orthographic(
        bounds: &Aabb,
        preset: ViewPreset,
        width: u32,
        height: u32,
    ) -> Result<Camera, CameraError> {
        let mut cam = Camera::framing_start(
            bounds,
            preset,
            Projection::Orthographic { height: 1.0 },
            width,
            height,
        )?;
        let axes = cam.axes_or_panic();
        let c = bounds.center();
        let extent = bounds.diagonal().max(1e-6 * length(c)).max(1e-9);
        let (mut half_h, mut back, mut front) = (0.0f64, 0.0f64, 0.0f64);
        for k in bounds.corners() {
            let d = sub(k, c);
            half_h = half_h.max(dot(axes.up, d).abs()).max(dot(axes.right, d).abs() / cam.aspect());
            back = back.max(-dot(axes.forward, d));
            front = front.max(dot(axes.forward, d));
        }
        let h = (2.0 * half_h * 1.05).max(extent * 1e-3);
        let dist = back + 0.5 * extent;
        cam.projection = Projection::Orthographic { height: h };
        cam.eye = sub(c, scale(axes.forward, dist));
        cam.target = c;
        cam.near = 0.25 * extent;
        cam.far = dist + front + 0.25 * extent;
        Ok(cam)
    }

    /// A camera at `eye` looking at `target`, with clip planes that hold all of `bounds`: the far
    /// plane just behind the box's farthest corner, the near plane just before its nearest corner
    /// in front of the eye, or a small fraction of the box's size when the eye is inside the box.
    /// For [`Projection::Orthographic`] the clip planes follow the same rule.
    pub fn look_at(
        eye: DVec3,
        target: DVec3,
        up: DVec3,
        projection: Projection,
        bounds: &Aabb,
        width: u32,
        height: u32,
    ) -> Result<Camera, CameraError> {
        if bounds.is_empty() || !bounds.min.iter().chain(&bounds.max).all(|v| v.is_finite()) {
            return Err(CameraError::Bounds { min: bounds.min, max: bounds.max });
        }
        let mut cam = Camera { eye, target, up, projection, near: 1.0, far: 2.0, width, height };
        cam.validate()?;
        let axes = cam.axes_or_panic();
        let extent = bounds.diagonal().max(1e-6 * length(bounds.center())).max(1e-9);
        let (mut min_d, mut max_d) = (f64::INFINITY, f64::NEG_INFINITY);
        for k in bounds.corners() {
            let d = dot(axes.forward, sub(k, eye));
            min_d = min_d.min(d);
            max_d = max_d.max(d);
        }
        let floor = extent * 1e-5;
        cam.far = (max_d + 0.01 * extent).max(2.0 * floor);
        cam.near = if min_d > floor { (min_d - 0.01 * extent).max(floor) } else { floor };
        if cam.near >= cam.far {
            cam.near = cam.far * 0.5;
        }
        cam.validate()?;
        Ok(cam)
    }

    /// A perspective close-up of the middle of `bounds`: looking down at 45 degrees from the
    /// south-west at the box's centre, from the distance at which the view shows, from top to
    /// bottom, about a tenth of the box's larger horizontal extent (a view in which most drawn
    /// batches are large on screen).
    pub fn close_up(
        bounds: &Aabb,
        fov_y: f64,
        width: u32,
        height: u32,
    ) -> Result<Camera, CameraError> {
        if bounds.is_empty() || !bounds.min.iter().chain(&bounds.max).all(|v| v.is_finite()) {
            return Err(CameraError::Bounds { min: bounds.min, max: bounds.max });
        }
        let c = bounds.center();
        let size = bounds.size();
        let across = (size[0].max(size[1]) * 0.1).max(bounds.diagonal() * 0.05).max(1e-9);
        let dist = 0.5 * across / (0.5 * fov_y).tan();
        let h = std::f64::consts::FRAC_1_SQRT_2;
        // Unit vector: horizontal part (1, 1) / sqrt(2) times cos 45, vertical -sin 45.
        let dir = [0.5, 0.5, -h];
        let eye = sub(c, scale(dir, dist));
        Camera::look_at(
            eye,
            c,
            [0.0, 0.0, 1.0],
            Projection::Perspective { fov_y },
            bounds,
            width,
            height,
        )
    }

    /// A perspective view from inside `bounds`: the eye above the centre of the box's footprint at
    /// 30 % of its height, looking horizontally north (+y). For a forest or a city this stands
    /// among the trees or buildings; for a scanned object it looks at its inner side.
    pub fn inside(
        bounds: &Aabb,
        fov_y: f64,
        width: u32,
        height: u32,
    ) -> Result<Camera, CameraError> {
        if bounds.is_empty() || !bounds.min.iter().chain(&bounds.max).all(|v| v.is_finite()) {
            return Err(CameraError::Bounds { min: bounds.min, max: bounds.max });
        }
        let c = bounds.center();
        let eye = [c[0], c[1], bounds.min[2] + 0.3 * bounds.size()[2]];
        let target = [eye[0], eye[1] + bounds.diagonal().max(1e-9), eye[2]];
        Camera::look_at(
            eye,
            target,
            [0.0, 0.0, 1.0],
            Projection::Perspective { fov_y },
            bounds,
            width,
            height,
        )
    }

    fn framing_start(
        bounds: &Aabb,
        preset: ViewPreset,
        projection: Projection,
        width: u32,
        height: u32,
    ) -> Result<Camera, CameraError> {
        if bounds.is_empty() || !bounds.min.iter().chain(&bounds.max).all(|v| v.is_finite()) {
            return Err(CameraError::Bounds { min: bounds.min, max: bounds.max });
        }
        let (dir, up) = preset.direction_and_up();
        let c = bounds.center();
        let cam = Camera {
            eye: sub(c, dir),
            target: c,
            up,
            projection,
            near: 1.0,
            far: 2.0,
            width,
            height,
        };
        cam.validate()?;
        Ok(cam)
    }

    /// The f32 transform of one batch for points decoded at `precision` (paper 003 §3.2-3.3),
    /// built relative to the eye in f64; see [`BatchProjection`]. The anchor is the eye's grid
    /// position and the pixel origin the viewport's centre, whatever the batch, so a point's
    /// local coordinate is `p - eye` in integers and its projection does not depend on the batch
    /// holding it; only a batch whose `bounds` (the world bounds of its points) reach
    /// [`FAR_UNITS`] grid units from the eye is anchored at its point
    /// nearest to the eye, with the pixel origin at the centre of its on-screen rectangle. The
    /// f32 twin the rasterizers run is [`super::plan::plan_batch`].
    pub fn batch_projection(
        &self,
        grid: &Grid,
        batch: &BatchGrid,
        bounds: &Aabb,
        precision: Precision,
    ) -> BatchProjection {
        let axes = self.axes_or_panic();
        let mut anchor = [0i32; 3];
        let mut shift = [0u32; 3];
        let eye_units = |a: usize| (self.eye[a] - grid.offset[a]) / grid.scale[a];
        let limit = FAR_UNITS as f64;
        let far = bounds.is_empty()
            || (0..3).any(|a| {
                let e = eye_units(a);
                let (lo, hi) = (
                    (bounds.min[a] - grid.offset[a]) / grid.scale[a],
                    (bounds.max[a] - grid.offset[a]) / grid.scale[a],
                );
                !((e - lo).abs() < limit && (e - hi).abs() < limit)
            });
        // Eye-relative world position of the local origin (anchor plus the centre of the unloaded bits).
        let mut rel = [0f64; 3];
        for a in 0..3 {
            let bits = batch.bits[a] as u32;
            shift[a] = MAX_BITS - bits;
            let an = if far {
                let span = ((1u64 << bits) - 1) as f64;
                let nearest = if bounds.is_empty() {
                    self.eye[a]
                } else {
                    self.eye[a].clamp(bounds.min[a], bounds.max[a])
                };
                let units = (nearest - grid.offset[a]) / grid.scale[a] - batch.min[a] as f64;
                if units.is_nan() {
                    0.0
                } else {
                    units.round().clamp(0.0, span)
                }
            } else {
                (eye_units(a) + 0.5).floor() - batch.min[a] as f64
            };
            anchor[a] = an as i32;
            let missing = bits.saturating_sub(precision.bits());
            let mid = ((1u64 << missing) - 1) as f64 * 0.5;
            let origin = grid.offset[a] + grid.scale[a] * batch.min[a] as f64;
            rel[a] = (origin - self.eye[a]) + grid.scale[a] * (an + mid);
        }
        // view_from_local: rows right, up, forward (depth), applied to scale * local + rel.
        let s = grid.scale;
        let row = |ax: DVec3| [ax[0] * s[0], ax[1] * s[1], ax[2] * s[2], dot(ax, rel)];
        let view_from_local = DMat4 {
            rows: [row(axes.right), row(axes.up), row(axes.forward), [0.0, 0.0, 0.0, 1.0]],
        };

        // Pixel origin: the viewport's centre; for a far batch the centre of its on-screen
        // rectangle, so that |pixel - origin| of every drawn point is at most half its visible size.
        let (w, h) = (self.width as f64, self.height as f64);
        let centre = ((w * 0.5 + 0.5).floor(), (h * 0.5 + 0.5).floor());
        let (ox, oy) = match self.screen_rect(bounds) {
            Some((lo, hi)) if far => {
                let cx = 0.5 * (lo[0].clamp(0.0, w) + hi[0].clamp(0.0, w));
                let cy = 0.5 * (lo[1].clamp(0.0, h) + hi[1].clamp(0.0, h));
                (cx.round(), cy.round())
            }
            _ => centre,
        };

        // pixel_from_view on (x, y, depth, 1): rows X, Y, D, W.
        let [hx, hy] = self.half_extent();
        let pixel_from_view = match self.projection {
            Projection::Perspective { .. } => DMat4 {
                rows: [
                    [0.5 * w / hx, 0.0, 0.5 * w - ox, 0.0],
                    [0.0, -0.5 * h / hy, 0.5 * h - oy, 0.0],
                    [0.0, 0.0, 1.0, 0.0],
                    [0.0, 0.0, 1.0, 0.0],
                ],
            },
            Projection::Orthographic { .. } => DMat4 {
                rows: [
                    [0.5 * w / hx, 0.0, 0.0, 0.5 * w - ox],
                    [0.0, -0.5 * h / hy, 0.0, 0.5 * h - oy],
                    [0.0, 0.0, 1.0, 0.0],
                    [0.0, 0.0, 0.0, 1.0],
                ],
            },
        };
        let m = pixel_from_view.mul(&view_from_local);
        BatchProjection {
            pixel_from_local: m.rows.map(|r| r.map(|v| v as f32)),
            anchor,
            words: precision.words() as u32,
            shift,
            _pad0: 0,
            pixel_origin: [ox as i32, oy as i32],
            _pad1: [0; 2],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::quantize::join_words;
    use crate::render::precision::PrecisionMode;
    use crate::render::testutil::{Rng, Scene};

    fn world_of(grid: &Grid, batch: &BatchGrid, rel: [f64; 3]) -> DVec3 {
        [0, 1, 2].map(|a| grid.offset[a] + grid.scale[a] * (batch.min[a] as f64 + rel[a]))
    }

    /// The rasterizer's f32 projection against the f64 reference on a Morton-batched terrain
    /// placed at `offset`, for overviews and close-ups: over all views, the same pixel for at
    /// least 99.99 % of points, and with adaptive precision every point within half a pixel of its
    /// exact projection (the 500 px rule).
    ///
    /// f32 pixel coordinates carry errors of a few 2^-24 of the batch's extent on screen (here up
    /// to ~1e-4 px in overviews, ~4e-4 px in close-ups where one batch spans the screen), so a
    /// point that close to a pixel edge may fall on the other side: about 1 point in 10^4 in a
    /// close-up, which is why a single view is allowed 2e-4.
    fn check_scene(scale: f64, offset: DVec3, label: &str) {
        let scene = Scene::terrain(200_000, 17, Grid { scale: [scale; 3], offset });
        let (mut total, mut other) = (0usize, 0usize);
        for (i, cam) in scene.cameras().iter().enumerate() {
            for mode in [PrecisionMode::Adaptive, PrecisionMode::Fixed(Precision::Bits30)] {
                let c = scene.check_projection(cam, mode);
                assert!(
                    c.on_screen > 20_000,
                    "{label} camera {i}: only {} points on screen",
                    c.on_screen
                );
                assert!(c.on_edge * 20 < c.on_screen, "{label} camera {i} {mode:?}: {c:?}");
                assert!(
                    c.other_pixel as f64 <= 2e-4 * c.on_screen as f64,
                    "{label} camera {i} {mode:?}: {c:?}"
                );
                assert!(c.worst_f32_px < 1e-3, "{label} camera {i} {mode:?}: {c:?}");
                assert!(c.worst_decode_px < 0.5, "{label} camera {i} {mode:?}: {c:?}");
                total += c.on_screen;
                other += c.other_pixel;
            }
        }
        assert!(
            other as f64 <= 1e-4 * total as f64,
            "{label}: {other} of {total} points in another pixel"
        );
    }

    #[test]
    fn f32_projection_matches_f64_reference_local() {
        check_scene(0.01, [0.0; 3], "local");
    }

    #[test]
    fn f32_projection_matches_f64_reference_utm() {
        check_scene(0.001, [500_000.0, 5_400_000.0, 0.0], "utm");
    }

    #[test]
    fn f32_projection_matches_f64_reference_ecef() {
        check_scene(0.0001, [6_400_000.0, 6_400_000.0, 6_400_000.0], "ecef");
    }

    #[test]
    fn huge_batches_stay_sub_pixel() {
        // Batches of random extent up to the whole region (far larger than Morton batches), at ECEF
        // coordinates: the f32 error grows with the batch's size on screen but stays far below a pixel.
        let grid = Grid { scale: [0.0001; 3], offset: [6_400_000.0; 3] };
        let region = Aabb::new(
            [6_400_000.0, 6_400_000.0, 6_400_000.0],
            [6_400_200.0, 6_400_150.0, 6_400_030.0],
        );
        let mut rng = Rng(99);
        let mut cams: Vec<Camera> = ViewPreset::ALL
            .iter()
            .map(|&p| Camera::frame_perspective(&region, p, 0.8, 1920, 1080).unwrap())
            .collect();
        cams.push(Camera {
            eye: [6_400_050.0, 6_400_010.0, 6_400_032.0],
            target: [6_400_100.0, 6_400_060.0, 6_400_015.0],
            ..cams[0]
        });
        cams[4].near = 0.05;
        let (mut total, mut differ, mut worst) = (0usize, 0usize, 0f64);
        for cam in &cams {
            for _ in 0..300 {
                let ext_bits = 1 + (rng.next_u64() % 21) as u32;
                let mut min = [0i32; 3];
                let mut max = [0i32; 3];
                for a in 0..3 {
                    let lo = grid.to_int(a, region.min[a]);
                    let hi = grid.to_int(a, region.max[a]);
                    min[a] = (lo + (rng.unit() * (hi - lo) as f64) as i64) as i32;
                    max[a] = min[a] + (rng.next_u64() % (1u64 << ext_bits)) as i32;
                }
                let batch = BatchGrid::for_bounds(min, max).unwrap();
                let world = |v: [i32; 3]| [0, 1, 2].map(|a| grid.world(a, v[a] as i64));
                let bounds = Aabb::new(world(min), world(max));
                for precision in [Precision::Bits10, Precision::Bits20, Precision::Bits30] {
                    let bp = cam.batch_projection(&grid, &batch, &bounds, precision);
                    for _ in 0..50 {
                        let p: [i32; 3] = [0, 1, 2]
                            .map(|a| min[a] + (rng.unit() * (max[a] - min[a] + 1) as f64) as i32);
                        let words = batch.encode(p);
                        let Some(r) = cam.project(world_of(
                            &grid,
                            &batch,
                            batch.decode_relative(words, precision),
                        )) else {
                            continue;
                        };
                        if !(r.x >= 0.0 && r.x < 1920.0 && r.y >= 0.0 && r.y < 1080.0) {
                            continue;
                        }
                        total += 1;
                        let [x, y, _, wc] = bp.transform(bp.local(join_words(words, precision)));
                        let fx = bp.pixel_origin[0] as f64 + (x / wc) as f64;
                        let fy = bp.pixel_origin[1] as f64 + (y / wc) as f64;
                        worst = worst.max((fx - r.x).abs()).max((fy - r.y).abs());
                        if fx.floor() != r.x.floor() || fy.floor() != r.y.floor() {
                            differ += 1;
                        }
                    }
                }
            }
        }
        assert!(total > 50_000, "{total}");
        assert!(worst < 2e-3, "worst {worst} px");
        assert!(differ as f64 <= 1e-3 * total as f64, "{differ} of {total}");
    }

    #[test]
    fn naive_f32_world_projection_would_fail_at_ecef() {
        // Regression guard for the design: projecting absolute ECEF coordinates in f32 is off by
        // many pixels, which is why the transform is built per batch relative to the eye.
        let region = Aabb::new([6_400_000.0; 3], [6_400_010.0; 3]);
        let cam = Camera::frame_perspective(&region, ViewPreset::Iso, 0.8, 1920, 1080).unwrap();
        let m = cam.clip_from_world();
        let m32 = m.rows.map(|r| r.map(|v| v as f32));
        let p = [6_400_003.3, 6_400_007.1, 6_400_001.9];
        let r = cam.project(p).unwrap();
        let p32 = p.map(|v| v as f32);
        let c: Vec<f32> = (0..4)
            .map(|i| m32[i][0] * p32[0] + m32[i][1] * p32[1] + m32[i][2] * p32[2] + m32[i][3])
            .collect();
        let x = (c[0] / c[3] + 1.0) * 0.5 * 1920.0;
        assert!(
            (x as f64 - r.x).abs() > 2.0,
            "f32 world projection unexpectedly accurate: {x} vs {}",
            r.x
        );
    }

    #[test]
    fn clip_from_world_agrees_with_reference() {
        let region = Aabb::new([10.0, 20.0, 0.0], [110.0, 70.0, 15.0]);
        for preset in ViewPreset::ALL {
            for cam in [
                Camera::frame_perspective(&region, preset, 1.0, 800, 600).unwrap(),
                Camera::frame_orthographic(&region, preset, 800, 600).unwrap(),
            ] {
                let m = cam.clip_from_world();
                for k in region.corners() {
                    let c = m.mul_point(k);
                    let r = cam.project(k).expect("framed corner must be between near and far");
                    let x = (c[0] / c[3] + 1.0) * 400.0;
                    let y = (1.0 - c[1] / c[3]) * 300.0;
                    assert!((x - r.x).abs() < 1e-6 && (y - r.y).abs() < 1e-6);
                    let z = c[2] / c[3];
                    assert!((0.0..=1.0).contains(&z), "clip z {z}");
                }
            }
        }
    }

    #[test]
    fn framing_shows_every_corner_with_a_margin() {
        let region = Aabb::new([1000.0, 2000.0, 10.0], [1400.0, 2100.0, 60.0]);
        for preset in ViewPreset::ALL {
            for cam in [
                Camera::frame_perspective(&region, preset, 0.9, 1000, 500).unwrap(),
                Camera::frame_orthographic(&region, preset, 1000, 500).unwrap(),
            ] {
                cam.validate().unwrap();
                let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
                for k in region.corners() {
                    let p = cam.project(k).unwrap();
                    assert!(
                        p.x > 0.0 && p.x < 1000.0 && p.y > 0.0 && p.y < 500.0,
                        "{preset:?} {p:?}"
                    );
                    lo = [lo[0].min(p.x), lo[1].min(p.y)];
                    hi = [hi[0].max(p.x), hi[1].max(p.y)];
                }
                // Tight: the box fills most of the viewport in one direction.
                let fill = ((hi[0] - lo[0]) / 1000.0).max((hi[1] - lo[1]) / 500.0);
                assert!(fill > 0.65, "{preset:?} fills only {fill}");
            }
        }
        assert_eq!(ViewPreset::from_name("iso"), Some(ViewPreset::Iso));
        assert!(Camera::frame_orthographic(&Aabb::EMPTY, ViewPreset::Top, 10, 10).is_err());
    }

    #[test]
    fn look_at_close_up_and_inside_hold_the_data_between_their_clip_planes() {
        let region = Aabb::new([684_700.0, 5_017_700.0, 0.0], [685_500.0, 5_018_200.0, 30.0]);
        let depth = |cam: &Camera, p: DVec3| dot(cam.axes().unwrap().forward, sub(p, cam.eye));
        let eye = [684_600.0, 5_017_600.0, 400.0];
        let cam = Camera::look_at(
            eye,
            region.center(),
            [0.0, 0.0, 1.0],
            Projection::Perspective { fov_y: 0.9 },
            &region,
            640,
            480,
        )
        .unwrap();
        for k in region.corners() {
            let d = depth(&cam, k);
            assert!(
                d > cam.near && d < cam.far,
                "corner depth {d} outside [{}, {}]",
                cam.near,
                cam.far
            );
        }
        // The centre is looked at: it projects to the middle of the image.
        let c = cam.project(region.center()).unwrap();
        assert!((c.x - 320.0).abs() < 1e-6 && (c.y - 240.0).abs() < 1e-6, "{c:?}");

        let close = Camera::close_up(&region, 0.9, 640, 480).unwrap();
        // About a tenth of the 800 m extent is visible from top to bottom at the target.
        let visible = 2.0 * length(sub(close.target, close.eye)) * (0.45f64).tan();
        assert!((visible - 80.0).abs() < 1.0, "{visible}");
        assert!(
            close.projected_size(&region) > 5000.0,
            "a close-up is much larger than the viewport"
        );
        let d = close.axes().unwrap().forward;
        assert!(
            (d[2] + std::f64::consts::FRAC_1_SQRT_2).abs() < 1e-9 && (d[0] - d[1]).abs() < 1e-9,
            "{d:?}"
        );

        let inside = Camera::inside(&region, 1.2, 640, 480).unwrap();
        let e = inside.eye;
        assert!(
            (0..3).all(|a| e[a] > region.min[a] && e[a] < region.max[a]),
            "eye {e:?} not inside"
        );
        assert!((e[2] - 9.0).abs() < 1e-9);
        assert!(inside.near < 0.1 && inside.far > region.size()[1] * 0.5);
        // Looking north along the ground: a point ahead at eye height projects to the image centre row.
        let ahead = inside.project([e[0], e[1] + 50.0, e[2]]).unwrap();
        assert!((ahead.y - 240.0).abs() < 1e-6 && (ahead.x - 320.0).abs() < 1e-6);
        assert!(Camera::inside(&Aabb::EMPTY, 1.0, 10, 10).is_err());
        assert!(Camera::close_up(&Aabb::EMPTY, 1.0, 10, 10).is_err());
    }

    #[test]
    fn invalid_cameras_are_rejected() {
        let region = Aabb::new([0.0; 3], [1.0; 3]);
        let good = Camera::frame_perspective(&region, ViewPreset::Front, 1.0, 64, 64).unwrap();
        let mut c = good;
        c.near = 0.0;
        assert!(matches!(c.validate(), Err(CameraError::ClipPlanes { .. })));
        let mut c = good;
        c.width = 0;
        assert!(matches!(c.validate(), Err(CameraError::Viewport { .. })));
        let mut c = good;
        c.up = sub(c.target, c.eye);
        assert!(matches!(c.validate(), Err(CameraError::Orientation { .. })));
        let mut c = good;
        c.projection = Projection::Perspective { fov_y: 4.0 };
        assert!(matches!(c.validate(), Err(CameraError::Projection(_))));
    }

    #[test]
    fn projected_size_clips_at_the_near_plane() {
        let cam = Camera {
            eye: [0.0, 0.0, 0.0],
            target: [0.0, 1.0, 0.0],
            up: [0.0, 0.0, 1.0],
            projection: Projection::Perspective { fov_y: std::f64::consts::FRAC_PI_2 },
            near: 0.1,
            far: 1000.0,
            width: 1000,
            height: 1000,
        };
        // A 2 m box 99-101 m ahead; 90 degrees: 500 px per 99 m at its front face: 10.1 px.
        let b = Aabb::new([-1.0, 99.0, -1.0], [1.0, 101.0, 1.0]);
        let s = cam.projected_size(&b);
        assert!((s - 1000.0 / 99.0).abs() < 1e-9, "{s}");
        // Entirely behind: 0. Around the eye: finite but large.
        assert_eq!(cam.projected_size(&Aabb::new([-1.0, -10.0, -1.0], [1.0, -5.0, 1.0])), 0.0);
        let around = cam.projected_size(&Aabb::new([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]));
        assert!(around.is_finite() && around > 1000.0, "{around}");
    }
}
