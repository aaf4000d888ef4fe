//! Camera rays and vignetting for a whole frame, with what is constant
//! along a row or a column worked out once: the same numbers, bit for bit,
//! as [`Camera::ray`] and [`Camera::vignetting`] give pixel by pixel, at a
//! fraction of the cost (those are calls into `rigd-core` the compiler
//! cannot inline, each with a square root and a division on its critical
//! path, and they were a third of a flat frame's time).
//!
//! The fan takes the camera's own numbers ([`Camera::parts`]) and checks
//! itself against the camera at the frame's corners and centre. Should the
//! camera's arithmetic ever change, the check fails and the renderer asks
//! the camera for every pixel, as before: slower, never different.

use rigd_core::camera::{Camera, CameraParts};
use rigd_core::geometry::{add, normalize, scale};

/// Rays [`RayFan::rays`] computes at a time.
const RUN: usize = 64;

/// Per-row set-up of a frame's rays.
#[derive(Debug, Clone)]
pub(crate) struct RayFan {
    camera: Camera,
    model: Option<Model>,
}

/// The camera model, rebuilt.
#[derive(Debug, Clone)]
struct Model {
    projection: Projection,
    right: [f64; 3],
    up: [f64; 3],
    forward: [f64; 3],
    origin: [f64; 3],
    half_w: f64,
    half_h: f64,
    vignette_focal: f64,
}

#[derive(Debug, Clone, Copy)]
enum Projection {
    /// A pinhole camera with this focal length, pixels.
    Pinhole(f64),
    /// An orthographic view, metres per pixel.
    Orthographic(f64),
}

/// The parts of a row's rays that are the same for every pixel in it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Row {
    j: usize,
    /// Pinhole: `up · t`; orthographic: `up · (t · scale)`.
    along_up: [f64; 3],
    /// `t²`, for the vignetting.
    t2: f64,
}

impl RayFan {
    /// The fan of `camera`.
    pub(crate) fn new(camera: Camera) -> RayFan {
        RayFan::checked(camera, camera.parts())
    }

    /// The fan made of `parts`, used only if it gives what `camera` gives.
    fn checked(camera: Camera, parts: CameraParts) -> RayFan {
        let model = Model::from(parts);
        // The camera's frame, whose halves it keeps (exact for integers).
        let size = |half: f64| ((2.0 * half) as usize).max(1);
        let (w, h) = (size(parts.half_w), size(parts.half_h));
        let probes = [
            (0, 0),
            (w - 1, 0),
            (0, h - 1),
            (w - 1, h - 1),
            (w / 2, h / 2),
        ];
        let agrees = probes.iter().all(|&(i, j)| {
            let fan = model.ray(i, &model.row(j));
            let cam = camera.ray(i, j);
            let vignette_agrees = [0.0, 0.3, 1.0].iter().all(|&s| {
                model.vignetting(i, &model.row(j), s).to_bits()
                    == camera.vignetting(i, j, s).to_bits()
            });
            same_bits(fan.0, cam.0) && same_bits(fan.1, cam.1) && vignette_agrees
        });
        RayFan {
            camera,
            model: agrees.then_some(model),
        }
    }

    /// The camera the fan stands for.
    pub(crate) fn camera(&self) -> &Camera {
        &self.camera
    }

    /// Whether the fan computes rays itself (else it asks the camera).
    #[cfg(test)]
    pub(crate) fn is_fast(&self) -> bool {
        self.model.is_some()
    }

    /// Row `j`'s shared parts.
    #[inline]
    pub(crate) fn row(&self, j: usize) -> Row {
        match &self.model {
            Some(m) => m.row(j),
            None => Row {
                j,
                along_up: [0.0; 3],
                t2: 0.0,
            },
        }
    }

    /// The ray through the centre of pixel (i, row.j), as [`Camera::ray`].
    #[inline]
    pub(crate) fn ray(&self, i: usize, row: &Row) -> ([f64; 3], [f64; 3]) {
        match &self.model {
            Some(m) => m.ray(i, row),
            None => self.camera.ray(i, row.j),
        }
    }

    /// The rays through pixels `first ..` of a row into `origins` and
    /// `dirs` (as many as both hold), as [`RayFan::ray`] gives them one by
    /// one; for a pinhole in straight loops over arrays, which the compiler
    /// vectorises (two square roots or divisions to an instruction).
    pub(crate) fn rays(
        &self,
        first: usize,
        row: &Row,
        origins: &mut [[f64; 3]],
        dirs: &mut [[f64; 3]],
    ) {
        let Some(
            m @ Model {
                projection: Projection::Pinhole(f),
                ..
            },
        ) = &self.model
        else {
            for (k, (o, d)) in origins.iter_mut().zip(dirs.iter_mut()).enumerate() {
                (*o, *d) = self.ray(first + k, row);
            }
            return;
        };
        let along_forward = scale(m.forward, *f);
        let runs = origins.chunks_mut(RUN).zip(dirs.chunks_mut(RUN));
        for (c, (origins, dirs)) in runs.enumerate() {
            let first = first + c * RUN;
            let n = dirs.len().min(origins.len());
            // Pixel columns as floats (exact), converted on their own:
            // packed 64-bit integer to float conversion needs more than
            // SSE2, and would keep the loop below scalar.
            let mut column = [0.0; RUN];
            for (k, c) in column.iter_mut().enumerate().take(n) {
                *c = (first + k) as f64;
            }
            let (mut x, mut y, mut z) = ([0.0; RUN], [0.0; RUN], [0.0; RUN]);
            for k in 0..n {
                let s = column[k] + 0.5 - m.half_w;
                let v = add(along_forward, add(scale(m.right, s), row.along_up));
                // `normalize`, branch-free.
                let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                let inv = 1.0 / len;
                let ok = len != 0.0 && len.is_finite();
                x[k] = if ok { v[0] * inv } else { 0.0 };
                y[k] = if ok { v[1] * inv } else { 0.0 };
                z[k] = if ok { v[2] * inv } else { 1.0 };
            }
            for k in 0..n {
                dirs[k] = [x[k], y[k], z[k]];
                origins[k] = m.origin;
            }
        }
    }

    /// The vignetting of pixel (i, row.j), as [`Camera::vignetting`].
    #[inline]
    pub(crate) fn vignetting(&self, i: usize, row: &Row, strength: f64) -> f64 {
        match &self.model {
            Some(m) => m.vignetting(i, row, strength),
            None => self.camera.vignetting(i, row.j, strength),
        }
    }
}

impl From<CameraParts> for Model {
    fn from(parts: CameraParts) -> Model {
        Model {
            projection: match parts.focal {
                Some(f) => Projection::Pinhole(f),
                None => Projection::Orthographic(parts.metres_per_px),
            },
            right: parts.right,
            up: parts.up,
            forward: parts.forward,
            origin: parts.origin,
            half_w: parts.half_w,
            half_h: parts.half_h,
            vignette_focal: parts.vignette_focal,
        }
    }
}

impl Model {
    #[inline]
    fn row(&self, j: usize) -> Row {
        let t = self.half_h - j as f64 - 0.5;
        let along_up = match self.projection {
            Projection::Pinhole(_) => scale(self.up, t),
            Projection::Orthographic(metres_per_px) => scale(self.up, t * metres_per_px),
        };
        Row {
            j,
            along_up,
            t2: t * t,
        }
    }

    #[inline]
    fn ray(&self, i: usize, row: &Row) -> ([f64; 3], [f64; 3]) {
        let s = i as f64 + 0.5 - self.half_w;
        match self.projection {
            Projection::Pinhole(f) => {
                let d = add(
                    scale(self.forward, f),
                    add(scale(self.right, s), row.along_up),
                );
                (self.origin, normalize(d))
            }
            Projection::Orthographic(metres_per_px) => {
                let o = add(
                    self.origin,
                    add(scale(self.right, s * metres_per_px), row.along_up),
                );
                (o, self.forward)
            }
        }
    }

    #[inline]
    fn vignetting(&self, i: usize, row: &Row, strength: f64) -> f64 {
        let s = i as f64 + 0.5 - self.half_w;
        let cos2 = 1.0 / (1.0 + (s * s + row.t2) / (self.vignette_focal * self.vignette_focal));
        1.0 - strength * (1.0 - cos2 * cos2)
    }
}

fn same_bits(a: [f64; 3], b: [f64; 3]) -> bool {
    a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(theta_deg: f64, phi_deg: f64) -> [f64; 3] {
        let (t, p) = (theta_deg.to_radians(), phi_deg.to_radians());
        [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
    }

    #[test]
    fn the_fan_is_the_camera_bit_for_bit() {
        let views = [
            dir(0.0, 0.0),
            dir(30.0, 200.0),
            dir(75.0, 10.0),
            dir(89.0, 300.0),
        ];
        let optics = [
            (Some(1393.0), Some(1.6)),
            (None, None),
            (Some(-1.0), Some(1.0)),
        ];
        for view in views {
            for (focal, distance) in optics {
                let size = [97, 61];
                let camera = Camera::new(view, size, focal, distance, 0.088);
                let fan = RayFan::new(camera);
                assert!(fan.is_fast(), "{view:?} {focal:?}");
                for j in 0..61 {
                    let row = fan.row(j);
                    for i in 0..97 {
                        let (a, b) = (fan.ray(i, &row), camera.ray(i, j));
                        assert!(same_bits(a.0, b.0) && same_bits(a.1, b.1), "({i}, {j})");
                        assert_eq!(
                            fan.vignetting(i, &row, 0.3).to_bits(),
                            camera.vignetting(i, j, 0.3).to_bits()
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn a_row_of_rays_is_the_camera_bit_for_bit() {
        for (focal, distance) in [(Some(1393.0), Some(1.6)), (None, None)] {
            let (view, size) = (dir(30.0, 200.0), [150, 20]);
            let camera = Camera::new(view, size, focal, distance, 0.088);
            let fan = RayFan::new(camera);
            let row = fan.row(7);
            let (mut origins, mut dirs) = ([[0.0; 3]; 143], [[0.0; 3]; 143]);
            fan.rays(5, &row, &mut origins, &mut dirs);
            for k in 0..143 {
                let (o, d) = camera.ray(5 + k, 7);
                assert!(same_bits(origins[k], o) && same_bits(dirs[k], d), "{k}");
            }
        }
    }

    #[test]
    fn a_fan_that_disagrees_with_its_camera_asks_the_camera() {
        let camera = Camera::new(dir(30.0, 200.0), [32, 24], Some(100.0), Some(1.0), 0.088);
        // Made of another view's camera.
        let other = Camera::new(dir(31.0, 200.0), [32, 24], Some(100.0), Some(1.0), 0.088);
        let fan = RayFan::checked(camera, other.parts());
        assert!(!fan.is_fast());
        let row = fan.row(5);
        assert!(same_bits(fan.ray(7, &row).1, camera.ray(7, 5).1));
    }
}
