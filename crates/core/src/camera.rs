//! The camera model the simulator renders with and the rectification
//! predicts marker positions with: a pinhole (or, without a focal length,
//! orthographic) camera looking at the sample centre from a view direction.
//! Image axes: up is the sample normal projected into the image; at the
//! pole, where that is undefined, the sample's +y.

use crate::geometry::{add, cross, dot, normalize, scale, sub, Vec3};

/// How pixels map to rays, and back: the one camera model of rigd.
#[derive(Debug, Clone, Copy)]
pub struct Camera {
    right: [f64; 3],
    up: [f64; 3],
    forward: [f64; 3],
    /// Pinhole position, or the view direction's far point for orthographic.
    origin: [f64; 3],
    focal: Option<f64>,
    /// Metres per pixel for an orthographic view.
    scale: f64,
    half_w: f64,
    half_h: f64,
    /// Focal length that sets the vignetting's fall-off.
    vignette_focal: f64,
}

/// The numbers [`Camera::ray`] and [`Camera::vignetting`] are made of, for
/// code that sets up many rays at once and must give the same bits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraParts {
    /// Image +x, sample frame.
    pub right: [f64; 3],
    /// Image +y, sample frame.
    pub up: [f64; 3],
    /// The viewing direction, from the camera towards the sample.
    pub forward: [f64; 3],
    /// Pinhole position, or the view direction's far point for orthographic.
    pub origin: [f64; 3],
    /// Focal length, pixels; `None` for an orthographic view.
    pub focal: Option<f64>,
    /// Metres per pixel of an orthographic view.
    pub metres_per_px: f64,
    /// Half the frame's width, pixels.
    pub half_w: f64,
    /// Half the frame's height, pixels.
    pub half_h: f64,
    /// Focal length that sets the vignetting's fall-off, pixels.
    pub vignette_focal: f64,
}

impl Camera {
    /// A camera looking at the sample centre along `view` (towards the
    /// camera, z the sample normal), for frames of `size` pixels: a pinhole
    /// with `focal_px` at `distance_m` when both are known and positive,
    /// else orthographic with a field `field_half` metres either side.
    pub fn new(
        view: Vec3,
        size: [u32; 2],
        focal_px: Option<f64>,
        distance_m: Option<f64>,
        field_half: f64,
    ) -> Camera {
        let v = normalize(view);
        // Image axes: `up` is the sample normal projected into the image
        // plane; at the pole that is undefined and the sample's +y is used.
        let (right, up) = if v[0].hypot(v[1]) < 1e-9 {
            ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        } else {
            let up = normalize([-v[2] * v[0], -v[2] * v[1], 1.0 - v[2] * v[2]]);
            (cross(up, v), up)
        };
        let (w, h) = (size[0].max(1) as f64, size[1].max(1) as f64);
        let (focal, origin) = match (focal_px, distance_m) {
            (Some(f), Some(d)) if f > 0.0 && d > 0.0 => (Some(f), scale(v, d)),
            _ => (None, scale(v, 10.0)),
        };
        Camera {
            right,
            up,
            forward: scale(v, -1.0),
            origin,
            focal,
            scale: 2.0 * field_half / w.min(h),
            half_w: w / 2.0,
            half_h: h / 2.0,
            vignette_focal: focal.unwrap_or(w.max(h)),
        }
    }

    /// The same camera moved by `offset` metres (sample frame), keeping its
    /// orientation: how a rig whose holder sits `-offset` away from the
    /// sample centre its kinematics assume sees the plate.
    pub fn translated(mut self, offset: Vec3) -> Camera {
        self.origin = add(self.origin, offset);
        self
    }

    /// What the camera is made of (see [`CameraParts`]).
    pub fn parts(&self) -> CameraParts {
        CameraParts {
            right: self.right,
            up: self.up,
            forward: self.forward,
            origin: self.origin,
            focal: self.focal,
            metres_per_px: self.scale,
            half_w: self.half_w,
            half_h: self.half_h,
            vignette_focal: self.vignette_focal,
        }
    }

    /// The ray through the centre of pixel (i, j).
    pub fn ray(&self, i: usize, j: usize) -> ([f64; 3], [f64; 3]) {
        let s = i as f64 + 0.5 - self.half_w;
        let t = self.half_h - j as f64 - 0.5;
        match self.focal {
            Some(f) => {
                let d = add(
                    scale(self.forward, f),
                    add(scale(self.right, s), scale(self.up, t)),
                );
                (self.origin, normalize(d))
            }
            None => {
                let o = add(
                    self.origin,
                    add(
                        scale(self.right, s * self.scale),
                        scale(self.up, t * self.scale),
                    ),
                );
                (o, self.forward)
            }
        }
    }

    /// Continuous pixel coordinates (x right, y down; pixel i spans
    /// [i, i+1)) of a point, or None behind the camera.
    pub fn project(&self, p: [f64; 3]) -> Option<[f64; 2]> {
        let rel = sub(p, self.origin);
        let (s, t) = match self.focal {
            Some(f) => {
                let z = dot(rel, self.forward);
                if z <= 0.0 {
                    return None;
                }
                (f * dot(rel, self.right) / z, f * dot(rel, self.up) / z)
            }
            None => (
                dot(rel, self.right) / self.scale,
                dot(rel, self.up) / self.scale,
            ),
        };
        Some([s + self.half_w, self.half_h - t])
    }

    /// The brightness fall-off towards the frame's corners (cos⁴ of the
    /// angle off axis), at `strength` 0 (none) … 1.
    pub fn vignetting(&self, i: usize, j: usize, strength: f64) -> f64 {
        let s = i as f64 + 0.5 - self.half_w;
        let t = self.half_h - j as f64 - 0.5;
        let cos2 = 1.0 / (1.0 + (s * s + t * t) / (self.vignette_focal * self.vignette_focal));
        1.0 - strength * (1.0 - cos2 * cos2)
    }
}
