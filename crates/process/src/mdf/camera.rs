//! Camera.

use super::*;

/// A pinhole camera (see the module doc for the pixel convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PinholeCamera {
    /// Pinhole position, metres.
    pub centre: [f64; 3],
    /// Unit image axes: `right` = `+x`, `up` = `−y` (image rows grow down).
    pub right: [f64; 3],
    /// Unit image up axis, `−y` (image rows grow down).
    pub up: [f64; 3],
    /// Unit optical axis (the way the camera looks).
    pub forward: [f64; 3],
    /// Focal length, pixels.
    pub focal_px: f64,
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
}

impl PinholeCamera {
    /// The simulator's camera for `view` (towards the camera, any length):
    /// the pinhole at `distance_m · unit(view)` looking at the origin, image
    /// up = the sample normal projected into the image plane (the sample's
    /// `+y` when `view` is the pole).
    pub fn looking_at_origin(
        view: [f64; 3],
        distance_m: f64,
        focal_px: f64,
        width: usize,
        height: usize,
    ) -> Result<PinholeCamera, MdfError> {
        let v = unit(view)
            .filter(|v| finite3(*v))
            .ok_or_else(|| MdfError::InvalidCamera(format!("view direction {view:?}")))?;
        let (right, up) = if v[0].hypot(v[1]) < 1e-9 {
            ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        } else {
            let up = unit([-v[2] * v[0], -v[2] * v[1], 1.0 - v[2] * v[2]])
                .ok_or_else(|| MdfError::InvalidCamera(format!("view direction {view:?}")))?;
            (cross(up, v), up)
        };
        let camera = PinholeCamera {
            centre: scale(v, distance_m),
            right,
            up,
            forward: scale(v, -1.0),
            focal_px,
            width,
            height,
        };
        camera.validate()?;
        Ok(camera)
    }

    /// Checks finite values, a positive focal length and size, and unit,
    /// mutually orthogonal axes (to 1e-6).
    pub fn validate(&self) -> Result<(), MdfError> {
        let bad = |r: String| Err(MdfError::InvalidCamera(r));
        if !finite3(self.centre) {
            return bad(format!("centre {:?}", self.centre));
        }
        if !(self.focal_px.is_finite() && self.focal_px > 0.0) {
            return bad(format!("focal length {} px", self.focal_px));
        }
        if self.width == 0 || self.height == 0 {
            return bad(format!("size {}x{}", self.width, self.height));
        }
        let axes = [self.right, self.up, self.forward];
        for (name, a) in ["right", "up", "forward"].iter().zip(axes) {
            if !finite3(a) || (norm(a) - 1.0).abs() > 1e-6 {
                return bad(format!("{name} axis {a:?} is not a unit vector"));
            }
        }
        for (i, j) in [(0, 1), (0, 2), (1, 2)] {
            if dot(axes[i], axes[j]).abs() > 1e-6 {
                return bad("axes are not orthogonal".into());
            }
        }
        Ok(())
    }

    /// The ray through continuous pixel `(x, y)`: origin (the pinhole) and
    /// unit direction.
    pub fn ray_at(&self, x: f64, y: f64) -> ([f64; 3], [f64; 3]) {
        let s = x - self.width as f64 / 2.0;
        let t = self.height as f64 / 2.0 - y;
        let d = add(
            scale(self.forward, self.focal_px),
            add(scale(self.right, s), scale(self.up, t)),
        );
        (self.centre, unit(d).unwrap_or(self.forward))
    }

    /// The ray through the centre of pixel `(i, j)`.
    pub fn ray(&self, i: usize, j: usize) -> ([f64; 3], [f64; 3]) {
        self.ray_at(i as f64 + 0.5, j as f64 + 0.5)
    }

    /// Continuous pixel coordinates of `p`; `None` at or behind the camera
    /// or when not finite. The result may lie outside the image.
    pub fn project(&self, p: [f64; 3]) -> Option<[f64; 2]> {
        let rel = sub(p, self.centre);
        let z = dot(rel, self.forward);
        if !gt(z, 0.0) {
            return None;
        }
        let s = self.focal_px * dot(rel, self.right) / z;
        let t = self.focal_px * dot(rel, self.up) / z;
        let out = [s + self.width as f64 / 2.0, self.height as f64 / 2.0 - t];
        (out[0].is_finite() && out[1].is_finite()).then_some(out)
    }

    /// Where the ray of continuous pixel `(x, y)` meets the plane
    /// `z = height`; `None` if it does not (parallel or behind the camera).
    pub fn back_project_to_height(&self, x: f64, y: f64, height: f64) -> Option<[f64; 3]> {
        let (o, d) = self.ray_at(x, y);
        if d[2].abs() < 1e-12 {
            return None;
        }
        let t = (height - o[2]) / d[2];
        let p = add(o, scale(d, t));
        (t > 0.0 && finite3(p)).then_some(p)
    }
}
