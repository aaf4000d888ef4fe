//! Mesostructure distance function (MDF) measurement by laser scanning
//! (seed 002 §3.2): laser line detection in a flat reference region, laser
//! plane calibration from two heights, space-time analysis of a scan
//! sequence into a displacement image, and the weighted merge of the
//! displacement images of several laser source positions.
//!
//! # Conventions
//! - **World frame** = the sample frame of the simulator: metres, the
//!   turntable (reference plane of the calibration) is `z = 0`, `+z` the
//!   sample normal, origin at the turntable centre.
//! - **Pixels**: continuous coordinates, `x` right and `y` down; pixel
//!   `(i, j)` spans `[i, i+1) × [j, j+1)`, its centre is `(i+0.5, j+0.5)`
//!   (as `rectify` and the simulator's camera).
//! - **Camera**: [`PinholeCamera`], the simulator's pinhole: the ray of the
//!   continuous pixel `(x, y)` has direction
//!   `f·forward + (x − W/2)·right + (H/2 − y)·up` from `centre`.
//!   [`PinholeCamera::looking_at_origin`] builds the simulator's camera
//!   (at `distance · view`, image up = the sample normal projected).
//! - **Laser plane**: [`LaserPlane`] `n·x = offset`, `n` unit; the sign of
//!   `n` is arbitrary (the simulator's `LaserLine { emitter, normal }` is
//!   `LaserPlane::through(emitter, normal)`).
//! - **MDF** (seed §3, Fig. 2): the MDF is defined on a reference plane
//!   `z = reference_height` *above* the mesostructure. For a camera pixel,
//!   whose ray meets the reference plane at `p` and the mesostructure first
//!   at `p'`, the displacement is `D = |p − p'|`, the distance along the
//!   view ray. A [`DisplacementImage`] is indexed by camera pixel; the
//!   reference-plane coordinates of a pixel are where its ray meets
//!   `z = reference_height` (a homography of the pixel, so `rectify` can
//!   resample it to texture coordinates). `−1` marks "no measurement"
//!   ([`NO_DEPTH`]): occluded from the laser or the camera, no peak above
//!   the threshold, or a rejected (grazing / out-of-range) triangulation.
//! - Lengths are metres; depths are `f32` metres.
//!
//! # Pipeline
//! 1. [`detect_line`] on each frame's reference region (turntable only):
//!    Gaussian filter, per row or column the brightest sample above the
//!    threshold refined to sub-pixel (3-point Gaussian fit), a total
//!    least-squares line with outlier rejection.
//! 2. [`calibrate_plane`]: the line seen on `z = 0` and on a raised plane
//!    `z = h` back-project to two 3-D lines; the laser plane is the
//!    least-squares plane through both (its tilt to the turntable is the
//!    seed's "angle between the laser plane and the reference plane").
//!    [`plane_from_line`] then turns each scan frame's reference line into
//!    that frame's plane (with the calibrated tilt, or through a known
//!    emitter position).
//! 3. [`space_time`]: per pixel the brightest frame above the threshold,
//!    sub-frame refinement of the peak time, triangulation of the pixel ray
//!    with the (interpolated) plane, the displacement from the reference
//!    plane along the ray, and a confidence weight (see [`space_time`] for
//!    the grazing-plane rule).
//! 4. [`merge`]: the seed's weighted mean over laser source positions with
//!    tetrahedron-volume weights, ignoring `−1` entries.
//! 5. [`quantise_depth`] / [`write_displacement`]: 8-bit codes (255 = no
//!    measurement) and `.npy` float output.
//!
//! Nothing on an input-reachable path panics; every output value is finite.

use std::path::Path;

use rayon::prelude::*;

use crate::image_io::{write_png, Image, ImageError, PngDepth};
use crate::npy::{write_f32, NpyError};
use rigd_core::geometry::{add, cross, dot, norm, scale, sub, unit};

/// Depth value of a pixel without a measurement (the seed's `−1`).
pub const NO_DEPTH: f32 = -1.0;
/// 8-bit code of a pixel without a measurement in [`quantise_depth`].
pub const NO_DEPTH_CODE: u8 = 255;
/// Largest 8-bit code of a measured depth (`max_depth` maps to it).
pub const MAX_DEPTH_CODE: u8 = 254;
/// [`calibrate_plane`] rejects line pairs whose 3-D directions differ by
/// more than this (lines cut from one plane by two parallel planes are
/// parallel): the two captures do not show the same laser plane.
pub const MAX_CALIBRATION_LINE_ANGLE_DEG: f64 = 2.0;
/// Fewest inlier points of a detected line.
pub const MIN_LINE_POINTS: usize = 5;

#[derive(Debug, thiserror::Error)]
pub enum MdfError {
    #[error("invalid input: {0}")]
    InvalidInput(String),
    #[error("invalid camera: {0}")]
    InvalidCamera(String),
    #[error("{frames} frames but {planes} laser planes (one plane per frame expected)")]
    FrameCount { frames: usize, planes: usize },
    #[error("frame {index} is {got:?} (width, height, channels) but {expected:?} was expected")]
    FrameSize {
        index: usize,
        expected: (usize, usize),
        got: (usize, usize, usize),
    },
    #[error("{count} displacement images but {sources} source positions / weights")]
    SourceCount { count: usize, sources: usize },
    #[error("displacement image {index} is {got:?} (width, height) but {expected:?} was expected, or its buffers have the wrong length")]
    DisplacementSize {
        index: usize,
        expected: (usize, usize),
        got: (usize, usize),
    },
    #[error("laser plane {index} is invalid: {reason}")]
    InvalidPlane { index: usize, reason: String },
    #[error("no laser line in region {region:?}: {reason}")]
    NoLine { region: [usize; 4], reason: String },
    #[error("degenerate calibration: {0}")]
    DegenerateCalibration(String),
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error(transparent)]
    Image(#[from] ImageError),
}

// ------------------------------------------------------------- 3-vectors

/// `a > b`, false when either is NaN (so `!gt(a, b)` reads "not clearly
/// above", NaN included).
fn gt(a: f64, b: f64) -> bool {
    a > b
}
fn finite3(a: [f64; 3]) -> bool {
    a.iter().all(|v| v.is_finite())
}

// ----------------------------------------------------------------- camera

/// A pinhole camera (see the module doc for the pixel convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PinholeCamera {
    /// Pinhole position, metres.
    pub centre: [f64; 3],
    /// Unit image axes: `right` = `+x`, `up` = `−y` (image rows grow down).
    pub right: [f64; 3],
    pub up: [f64; 3],
    /// Unit optical axis (the way the camera looks).
    pub forward: [f64; 3],
    /// Focal length, pixels.
    pub focal_px: f64,
    pub width: usize,
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

// ------------------------------------------------------------ laser plane

/// A laser plane `normal · x = offset` (`normal` unit; its sign is
/// arbitrary).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LaserPlane {
    pub normal: [f64; 3],
    pub offset: f64,
}

impl LaserPlane {
    /// The plane through `point` with normal `normal` (any length), e.g.
    /// the simulator's `LaserLine { emitter, normal }`.
    pub fn through(point: [f64; 3], normal: [f64; 3]) -> Result<LaserPlane, MdfError> {
        let n = unit(normal)
            .filter(|_| finite3(point))
            .ok_or_else(|| MdfError::InvalidPlane {
                index: 0,
                reason: format!("normal {normal:?} through {point:?}"),
            })?;
        Ok(LaserPlane {
            normal: n,
            offset: dot(n, point),
        })
    }

    /// Signed distance of `p` from the plane.
    pub fn distance(&self, p: [f64; 3]) -> f64 {
        dot(self.normal, p) - self.offset
    }

    /// Ray parameter `t` (so the point is `origin + t·dir`) where the ray
    /// meets the plane, with `|n·dir|/|dir|` (the sine of the angle between
    /// ray and plane). `None` when the ray is parallel to the plane or the
    /// values are not finite; `t` may be negative.
    pub fn intersect(&self, origin: [f64; 3], dir: [f64; 3]) -> Option<(f64, f64)> {
        let len = norm(dir);
        let nd = dot(self.normal, dir);
        if !gt(len, 0.0) || !gt(nd.abs(), 1e-15 * len) {
            return None;
        }
        let t = (self.offset - dot(self.normal, origin)) / nd;
        t.is_finite().then_some((t, (nd / len).abs()))
    }

    fn normalised(self, index: usize) -> Result<LaserPlane, MdfError> {
        let n = norm(self.normal);
        if !(finite3(self.normal) && self.offset.is_finite() && n > 1e-12) {
            return Err(MdfError::InvalidPlane {
                index,
                reason: format!("normal {:?}, offset {}", self.normal, self.offset),
            });
        }
        Ok(LaserPlane {
            normal: scale(self.normal, 1.0 / n),
            offset: self.offset / n,
        })
    }
}

// ---------------------------------------------------------- line detection

/// Along which image axis [`detect_line`] searched for the peaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScanAxis {
    /// One peak per row (a steep line).
    Rows,
    /// One peak per column (a flat line).
    Columns,
}

/// A straight laser line in an image.
///
/// Parametrisation: the line through `point` with unit `direction`
/// (total least squares, so any orientation is represented equally well);
/// [`LineFit::x_at_y`] / [`LineFit::y_at_x`] give the `x = a·y + b` form.
#[derive(Debug, Clone, PartialEq)]
pub struct LineFit {
    /// The inlier candidate points (continuous pixel coordinates).
    pub points: Vec<[f64; 2]>,
    /// Centroid of the inliers, on the line.
    pub point: [f64; 2],
    /// Unit direction, `direction[1] ≥ 0` (pointing down the image).
    pub direction: [f64; 2],
    /// RMS perpendicular distance of the inliers, pixels.
    pub rms_px: f64,
    /// Candidates rejected as outliers.
    pub rejected: usize,
    pub scan: ScanAxis,
}

impl LineFit {
    /// Signed perpendicular distance of `p` from the line, pixels.
    pub fn distance(&self, p: [f64; 2]) -> f64 {
        let (dx, dy) = (p[0] - self.point[0], p[1] - self.point[1]);
        dx * self.direction[1] - dy * self.direction[0]
    }

    /// `x` on the line at row `y` (`None` for a horizontal line).
    pub fn x_at_y(&self, y: f64) -> Option<f64> {
        (self.direction[1].abs() > 1e-12)
            .then(|| self.point[0] + (y - self.point[1]) * self.direction[0] / self.direction[1])
    }

    /// `y` on the line at column `x` (`None` for a vertical line).
    pub fn y_at_x(&self, x: f64) -> Option<f64> {
        (self.direction[0].abs() > 1e-12)
            .then(|| self.point[1] + (x - self.point[0]) * self.direction[1] / self.direction[0])
    }

    /// The two extreme inliers' feet on the fitted line.
    pub fn endpoints(&self) -> ([f64; 2], [f64; 2]) {
        let along = |p: &[f64; 2]| {
            (p[0] - self.point[0]) * self.direction[0] + (p[1] - self.point[1]) * self.direction[1]
        };
        let (mut lo, mut hi) = (0.0f64, 0.0f64);
        for p in &self.points {
            let s = along(p);
            lo = lo.min(s);
            hi = hi.max(s);
        }
        let at = |s: f64| {
            [
                self.point[0] + s * self.direction[0],
                self.point[1] + s * self.direction[1],
            ]
        };
        (at(lo), at(hi))
    }
}

/// Grey value of pixel `idx` (Rec. 709 luminance for RGB, the mean of the
/// channels otherwise; non-finite samples read as 0).
fn grey(image: &Image, idx: usize) -> f32 {
    let c = image.channels;
    let px = image.data.get(idx * c..(idx + 1) * c).unwrap_or(&[]);
    let v = if let [r, g, b] = *px {
        0.2126 * r + 0.7152 * g + 0.0722 * b
    } else if c > 0 {
        px.iter().sum::<f32>() / c as f32
    } else {
        0.0
    };
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

fn check_image(image: &Image, what: &str) -> Result<(), MdfError> {
    let len = image
        .width
        .checked_mul(image.height)
        .and_then(|n| n.checked_mul(image.channels));
    if image.width == 0 || image.height == 0 || image.channels == 0 || len != Some(image.data.len())
    {
        return Err(MdfError::InvalidInput(format!(
            "{what}: {}x{}x{} with {} samples",
            image.width,
            image.height,
            image.channels,
            image.data.len()
        )));
    }
    Ok(())
}

/// Separable Gaussian filter of the grey values of `[x0, x1) × [y0, y1)`,
/// reading up to `3σ` beyond the window where the image has pixels (edges
/// clamped). Returns the filtered window, row-major.
fn gaussian_window(image: &Image, win: [usize; 4], sigma: f64) -> Vec<f64> {
    let [x0, y0, x1, y1] = win;
    let r = if sigma > 0.0 {
        (3.0 * sigma).ceil() as usize
    } else {
        0
    };
    let kernel: Vec<f64> = {
        let k: Vec<f64> = (0..=2 * r)
            .map(|i| {
                let d = i as f64 - r as f64;
                if r == 0 {
                    1.0
                } else {
                    (-0.5 * (d / sigma).powi(2)).exp()
                }
            })
            .collect();
        let s: f64 = k.iter().sum();
        k.into_iter().map(|v| v / s).collect()
    };
    let (w, h) = (image.width, image.height);
    // Rows ey0..ey1 of the horizontally filtered image, columns x0..x1.
    let ey0 = y0.saturating_sub(r);
    let ey1 = (y1 + r).min(h);
    let clamp_x = |x: isize| x.clamp(0, w as isize - 1) as usize;
    let clamp_y = |y: isize| y.clamp(ey0 as isize, ey1 as isize - 1) as usize;
    let ww = x1 - x0;
    let horiz: Vec<f64> = (ey0..ey1)
        .into_par_iter()
        .flat_map_iter(|y| {
            let kernel = &kernel;
            (x0..x1).map(move |x| {
                kernel
                    .iter()
                    .enumerate()
                    .map(|(k, kv)| {
                        let xx = clamp_x(x as isize + k as isize - r as isize);
                        kv * f64::from(grey(image, y * w + xx))
                    })
                    .sum::<f64>()
            })
        })
        .collect();
    (y0..y1)
        .into_par_iter()
        .flat_map_iter(|y| {
            let (kernel, horiz) = (&kernel, &horiz);
            (0..ww).map(move |xi| {
                kernel
                    .iter()
                    .enumerate()
                    .map(|(k, kv)| {
                        let yy = clamp_y(y as isize + k as isize - r as isize);
                        kv * horiz[(yy - ey0) * ww + xi]
                    })
                    .sum::<f64>()
            })
        })
        .collect()
}

/// Sub-sample offset in `[−0.5, 0.5]` of the peak of three samples
/// `a, b, c` around a maximum `b` (background already removed): the
/// 3-point Gaussian fit when all three are positive (exact for a sampled
/// Gaussian), else the parabola.
fn peak_offset(a: f64, b: f64, c: f64) -> f64 {
    let d = if a > 0.0 && b > 0.0 && c > 0.0 {
        let (la, lb, lc) = (a.ln(), b.ln(), c.ln());
        let den = la - 2.0 * lb + lc;
        if den < -1e-12 {
            0.5 * (la - lc) / den
        } else {
            0.0
        }
    } else {
        let den = a - 2.0 * b + c;
        if den < -1e-12 {
            0.5 * (a - c) / den
        } else {
            0.0
        }
    };
    if d.is_finite() {
        d.clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let m = v.len() / 2;
    let (_, x, _) = v.select_nth_unstable_by(m, f64::total_cmp);
    *x
}

/// Candidate points scanning `lines` (each a sequence of filtered samples
/// along the scan direction).
fn candidates(
    filt: &[f64],
    w: usize,
    h: usize,
    axis: ScanAxis,
    origin: [usize; 2],
    threshold: f64,
) -> Vec<[f64; 2]> {
    let (n_lines, len) = match axis {
        ScanAxis::Rows => (h, w),
        ScanAxis::Columns => (w, h),
    };
    let at = |line: usize, k: usize| match axis {
        ScanAxis::Rows => filt[line * w + k],
        ScanAxis::Columns => filt[k * w + line],
    };
    (0..n_lines)
        .filter_map(|line| {
            if len < 3 {
                return None;
            }
            let (mut best, mut kmax) = (f64::NEG_INFINITY, 0);
            for k in 0..len {
                let v = at(line, k);
                if v > best {
                    best = v;
                    kmax = k;
                }
            }
            if !gt(best, threshold) || kmax == 0 || kmax + 1 == len {
                return None;
            }
            let mut all: Vec<f64> = (0..len).map(|k| at(line, k)).collect();
            let bg = median(&mut all);
            let d = peak_offset(at(line, kmax - 1) - bg, best - bg, at(line, kmax + 1) - bg);
            let along = kmax as f64 + 0.5 + d;
            let across = line as f64 + 0.5;
            Some(match axis {
                ScanAxis::Rows => [origin[0] as f64 + along, origin[1] as f64 + across],
                ScanAxis::Columns => [origin[0] as f64 + across, origin[1] as f64 + along],
            })
        })
        .collect()
}

/// Total least-squares line through `pts`: centroid, unit direction
/// (`dir[1] ≥ 0`), `None` if the points do not define a direction.
fn tls(pts: &[[f64; 2]]) -> Option<([f64; 2], [f64; 2])> {
    let n = pts.len() as f64;
    if pts.len() < 2 {
        return None;
    }
    let cx = pts.iter().map(|p| p[0]).sum::<f64>() / n;
    let cy = pts.iter().map(|p| p[1]).sum::<f64>() / n;
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in pts {
        let (dx, dy) = (p[0] - cx, p[1] - cy);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
    }
    // Principal axis of [[sxx, sxy], [sxy, syy]].
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let spread = sxx + syy;
    if !gt(spread, 1e-18) || !angle.is_finite() {
        return None;
    }
    let mut d = [angle.cos(), angle.sin()];
    if d[1] < 0.0 || (d[1] == 0.0 && d[0] < 0.0) {
        d = [-d[0], -d[1]];
    }
    Some(([cx, cy], d))
}

fn fit_robust(cands: &[[f64; 2]], axis: ScanAxis) -> Option<LineFit> {
    let mut inliers: Vec<[f64; 2]> = cands.to_vec();
    let mut fit = None;
    for _ in 0..10 {
        let (c, d) = tls(&inliers)?;
        let dist = |p: &[f64; 2]| (p[0] - c[0]) * d[1] - (p[1] - c[1]) * d[0];
        let mut abs: Vec<f64> = cands.iter().map(|p| dist(p).abs()).collect();
        let mad = median(&mut abs);
        let limit = (3.0 * 1.4826 * mad).max(0.5);
        let next: Vec<[f64; 2]> = cands
            .iter()
            .copied()
            .filter(|p| dist(p).abs() <= limit)
            .collect();
        let done = next.len() == inliers.len();
        fit = Some((c, d));
        inliers = next;
        if done || inliers.len() < MIN_LINE_POINTS {
            break;
        }
    }
    let (c, d) = tls(&inliers).or(fit)?;
    if inliers.len() < MIN_LINE_POINTS {
        return None;
    }
    let rms = (inliers
        .iter()
        .map(|p| ((p[0] - c[0]) * d[1] - (p[1] - c[1]) * d[0]).powi(2))
        .sum::<f64>()
        / inliers.len() as f64)
        .sqrt();
    Some(LineFit {
        rejected: cands.len() - inliers.len(),
        points: inliers,
        point: c,
        direction: d,
        rms_px: rms,
        scan: axis,
    })
}

/// Detects the laser line in the reference region `[x0, y0, x1, y1)`
/// (pixels, end exclusive) of `image` (seed §3.2, Fig. 5a).
///
/// The grey image is Gaussian-filtered (`sigma_px`, 0 = none); then both
/// per row and per column the brightest filtered sample is taken as a
/// candidate if it exceeds `threshold` (in filtered grey units) and is not
/// on the region's border, refined to sub-pixel by a 3-point Gaussian fit
/// after subtracting that row's (column's) median as background. The scan
/// axis giving more candidates wins (a steep line gives one per row, a
/// flat one one per column). A total least-squares line is fitted with
/// iterative rejection of candidates farther than
/// `max(3 · 1.4826 · MAD, 0.5 px)` from it.
pub fn detect_line(
    image: &Image,
    region: [usize; 4],
    sigma_px: f64,
    threshold: f64,
) -> Result<LineFit, MdfError> {
    detect_line_in_regions(image, &[region], sigma_px, threshold)
}

/// [`detect_line`] over several reference regions at once (the reference
/// region of the seed is the image minus the sample's bounding box, which
/// is rarely one rectangle): candidates of all regions are pooled per scan
/// axis before the fit, so a line crossing two bands is fitted over its
/// whole span.
pub fn detect_line_in_regions(
    image: &Image,
    regions: &[[usize; 4]],
    sigma_px: f64,
    threshold: f64,
) -> Result<LineFit, MdfError> {
    check_image(image, "line image")?;
    let first = *regions
        .first()
        .ok_or_else(|| MdfError::InvalidInput("no reference region".into()))?;
    for &region in regions {
        let [x0, y0, x1, y1] = region;
        if !(x0 < x1 && y0 < y1 && x1 <= image.width && y1 <= image.height) {
            return Err(MdfError::InvalidInput(format!(
                "region {region:?} is empty or outside the {}x{} image",
                image.width, image.height
            )));
        }
    }
    if !(sigma_px.is_finite() && (0.0..=100.0).contains(&sigma_px) && threshold.is_finite()) {
        return Err(MdfError::InvalidInput(format!(
            "sigma {sigma_px} px (0..=100), threshold {threshold}"
        )));
    }
    let filtered: Vec<Vec<f64>> = regions
        .iter()
        .map(|&r| gaussian_window(image, r, sigma_px))
        .collect();
    let mut best: Option<LineFit> = None;
    let mut counts = Vec::new();
    for axis in [ScanAxis::Rows, ScanAxis::Columns] {
        let mut c = Vec::new();
        for (&[x0, y0, x1, y1], filt) in regions.iter().zip(&filtered) {
            c.extend(candidates(
                filt,
                x1 - x0,
                y1 - y0,
                axis,
                [x0, y0],
                threshold,
            ));
        }
        counts.push(c.len());
        if let Some(fit) = fit_robust(&c, axis) {
            let better = match &best {
                None => true,
                Some(b) => fit.points.len() > b.points.len(),
            };
            if better {
                best = Some(fit);
            }
        }
    }
    best.ok_or_else(|| MdfError::NoLine {
        region: first,
        reason: format!(
            "{} row and {} column candidates above threshold {threshold} in {} region(s); at least {MIN_LINE_POINTS} collinear needed",
            counts.first().copied().unwrap_or(0),
            counts.get(1).copied().unwrap_or(0),
            regions.len()
        ),
    })
}

// ------------------------------------------------------------ calibration

/// The result of [`calibrate_plane`].
#[derive(Debug, Clone, PartialEq)]
pub struct PlaneCalibration {
    pub plane: LaserPlane,
    /// Angle between the laser plane and the reference plane `z = 0`,
    /// degrees (the seed's calibrated quantity).
    pub tilt_deg: f64,
    /// RMS distance of the back-projected line points from the fitted
    /// plane, metres (coplanarity residual).
    pub residual_m: f64,
    /// Angle between the two 3-D lines, degrees (0 for a consistent pair).
    pub line_angle_deg: f64,
}

/// Smallest-eigenvalue eigenvector of a symmetric 3×3 matrix (cyclic
/// Jacobi) and the eigenvalues ascending.
fn smallest_eigenvector(mut a: [[f64; 3]; 3]) -> ([f64; 3], [f64; 3]) {
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _ in 0..50 {
        let off = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
        if off < 1e-30 {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q].abs() < 1e-300 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for row in a.iter_mut() {
                let (akp, akq) = (row[p], row[q]);
                row[p] = c * akp - s * akq;
                row[q] = s * akp + c * akq;
            }
            let (rp, rq) = (a[p], a[q]);
            for k in 0..3 {
                a[p][k] = c * rp[k] - s * rq[k];
                a[q][k] = s * rp[k] + c * rq[k];
            }
            for row in v.iter_mut() {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&i, &j| a[i][i].total_cmp(&a[j][j]));
    let k = idx[0];
    (
        [v[0][k], v[1][k], v[2][k]],
        [a[idx[0]][idx[0]], a[idx[1]][idx[1]], a[idx[2]][idx[2]]],
    )
}

/// Back-projects the inliers' feet on the fitted line to `z = height`.
fn line_points_3d(
    camera: &PinholeCamera,
    line: &LineFit,
    height: f64,
    which: &str,
) -> Result<Vec<[f64; 3]>, MdfError> {
    let (a, b) = line.endpoints();
    let len = (b[0] - a[0]).hypot(b[1] - a[1]);
    if !gt(len, 2.0) {
        return Err(MdfError::DegenerateCalibration(format!(
            "{which} line spans only {len:.2} px"
        )));
    }
    let n = 16;
    (0..=n)
        .map(|k| {
            let s = k as f64 / n as f64;
            let (x, y) = (a[0] + s * (b[0] - a[0]), a[1] + s * (b[1] - a[1]));
            camera.back_project_to_height(x, y, height).ok_or_else(|| {
                MdfError::DegenerateCalibration(format!(
                    "{which} line pixel ({x:.1}, {y:.1}) does not see the plane z = {height}"
                ))
            })
        })
        .collect()
}

/// The laser plane from its line seen on the reference plane `z = 0`
/// (`line_at_0`) and on a raised plane `z = height` (`line_at_h`), seed
/// §3.2 ("project the laser strip onto two planes with different
/// heights"): both image lines back-project to 3-D lines; the plane is
/// the least-squares plane through points sampled along both. Errors when
/// a line is too short, does not back-project, `height` is not positive,
/// or the two 3-D lines are not parallel within
/// [`MAX_CALIBRATION_LINE_ANGLE_DEG`] (they cannot lie in one plane cut by
/// two parallel planes).
pub fn calibrate_plane(
    camera: &PinholeCamera,
    line_at_0: &LineFit,
    line_at_h: &LineFit,
    height: f64,
) -> Result<PlaneCalibration, MdfError> {
    camera.validate()?;
    if !(height.is_finite() && height > 0.0) {
        return Err(MdfError::DegenerateCalibration(format!(
            "raised plane height {height} m (must be > 0)"
        )));
    }
    let p0 = line_points_3d(camera, line_at_0, 0.0, "reference")?;
    let p1 = line_points_3d(camera, line_at_h, height, "raised")?;
    let dir = |p: &[[f64; 3]]| unit(sub(p[p.len() - 1], p[0]));
    let (d0, d1) = match (dir(&p0), dir(&p1)) {
        (Some(a), Some(b)) => (a, b),
        _ => {
            return Err(MdfError::DegenerateCalibration(
                "a 3-D line has no direction".into(),
            ))
        }
    };
    let line_angle_deg = dot(d0, d1).abs().min(1.0).acos().to_degrees();
    if line_angle_deg > MAX_CALIBRATION_LINE_ANGLE_DEG {
        return Err(MdfError::DegenerateCalibration(format!(
            "the two 3-D lines differ in direction by {line_angle_deg:.2}° (> {MAX_CALIBRATION_LINE_ANGLE_DEG}°): not one laser plane"
        )));
    }
    let all: Vec<[f64; 3]> = p0.iter().chain(&p1).copied().collect();
    let n = all.len() as f64;
    let c = scale(all.iter().fold([0.0; 3], |s, p| add(s, *p)), 1.0 / n);
    let mut cov = [[0.0; 3]; 3];
    for p in &all {
        let d = sub(*p, c);
        for (i, row) in cov.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v += d[i] * d[j];
            }
        }
    }
    let (normal, eig) = smallest_eigenvector(cov);
    let normal =
        unit(normal).ok_or_else(|| MdfError::DegenerateCalibration("no plane normal".into()))?;
    if !gt(eig[1], 1e-6 * eig[2].max(1e-300)) {
        return Err(MdfError::DegenerateCalibration(
            "the two 3-D lines coincide".into(),
        ));
    }
    let plane = LaserPlane {
        normal,
        offset: dot(normal, c),
    };
    let residual_m = (all.iter().map(|p| plane.distance(*p).powi(2)).sum::<f64>() / n).sqrt();
    let tilt_deg = normal[2].abs().min(1.0).acos().to_degrees();
    Ok(PlaneCalibration {
        plane,
        tilt_deg,
        residual_m,
        line_angle_deg,
    })
}

/// What fixes a scan frame's laser plane besides its line on the
/// reference plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PlaneConstraint {
    /// The seed's model (laser far away, planes of one scan parallel): the
    /// plane makes the calibrated plane's angle with `z = 0` (its normal's
    /// `z` component and side are taken from this calibrated plane).
    CalibratedTilt(LaserPlane),
    /// The plane passes through the emitter at this position (a near
    /// rotating emitter, e.g. the simulator's `LaserLine::emitter`).
    ThroughEmitter([f64; 3]),
}

/// A scan frame's laser plane from its line detected in the reference
/// region (on the plane `z = reference_z`, normally the turntable, 0), seed
/// §3.2 "projecting the laser line … to the 3D reference plane".
pub fn plane_from_line(
    camera: &PinholeCamera,
    line: &LineFit,
    reference_z: f64,
    constraint: PlaneConstraint,
) -> Result<LaserPlane, MdfError> {
    camera.validate()?;
    let pts = line_points_3d(camera, line, reference_z, "reference")?;
    let q = pts[pts.len() / 2];
    let u = unit(sub(pts[pts.len() - 1], pts[0]))
        .ok_or_else(|| MdfError::DegenerateCalibration("the 3-D line has no direction".into()))?;
    let normal = match constraint {
        PlaneConstraint::ThroughEmitter(e) => {
            if !finite3(e) {
                return Err(MdfError::InvalidInput(format!("emitter {e:?}")));
            }
            unit(cross(u, sub(e, q))).ok_or_else(|| {
                MdfError::DegenerateCalibration("the emitter lies on the laser line".into())
            })?
        }
        PlaneConstraint::CalibratedTilt(cal) => {
            let cal = cal.normalised(0)?;
            // Normals ⟂ u: n = nz·ẑ' + r·m with m horizontal ⟂ u; ẑ' = the
            // part of ẑ ⟂ u (u is horizontal on z = const, so ẑ itself).
            let m = unit(cross([0.0, 0.0, 1.0], u))
                .ok_or_else(|| MdfError::DegenerateCalibration("vertical 3-D line".into()))?;
            let nz = cal.normal[2];
            let r = (1.0 - nz * nz).max(0.0).sqrt();
            let side = if dot(m, cal.normal) < 0.0 { -1.0 } else { 1.0 };
            add([0.0, 0.0, nz], scale(m, side * r))
        }
    };
    Ok(LaserPlane {
        normal,
        offset: dot(normal, q),
    })
}

// --------------------------------------------------------- space-time

/// A displacement image `D_{v,l}(x, y)` (or the merged `D_v`), indexed by
/// camera pixel, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct DisplacementImage {
    pub width: usize,
    pub height: usize,
    /// Distance along the view ray from the reference plane to the
    /// surface, metres; [`NO_DEPTH`] (−1) where there is no measurement.
    pub depth: Vec<f32>,
    /// Confidence, ≥ 0; 0 exactly where `depth` is −1.
    pub weight: Vec<f32>,
}

impl DisplacementImage {
    /// Fraction of pixels with a measurement.
    pub fn valid_fraction(&self) -> f64 {
        if self.depth.is_empty() {
            return 0.0;
        }
        self.depth.iter().filter(|&&d| d >= 0.0).count() as f64 / self.depth.len() as f64
    }

    fn check(&self, index: usize, expected: (usize, usize)) -> Result<(), MdfError> {
        let n = self.width.checked_mul(self.height);
        if (self.width, self.height) != expected
            || n != Some(self.depth.len())
            || n != Some(self.weight.len())
        {
            return Err(MdfError::DisplacementSize {
                index,
                expected,
                got: (self.width, self.height),
            });
        }
        Ok(())
    }
}

/// Parameters of [`space_time`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpaceTimeOptions {
    /// A pixel's brightest frame must exceed this grey value (seed: "the
    /// prescribed threshold"); otherwise the pixel is occluded → −1.
    pub threshold: f64,
    /// Height of the MDF reference plane, metres (above the mesostructure).
    pub reference_height: f64,
    /// Sine of the smallest accepted angle between camera ray and laser
    /// plane; below it the pixel is "grazing" → −1, weight 0.
    pub min_sin_angle: f64,
    /// Largest accepted displacement, metres; a triangulation farther below
    /// the reference plane (or more than `depth_tolerance` above it) is
    /// rejected → −1.
    pub max_depth: f64,
    /// Triangulated points up to this far above the reference plane are
    /// kept (as depth 0); farther ones are rejected.
    pub depth_tolerance: f64,
    /// Refine the peak time between frames and interpolate the plane.
    pub subframe: bool,
}

impl SpaceTimeOptions {
    /// Defaults: `min_sin_angle = sin 3°`, `depth_tolerance = 2 % of
    /// max_depth`, sub-frame refinement on.
    pub fn new(threshold: f64, reference_height: f64, max_depth: f64) -> SpaceTimeOptions {
        SpaceTimeOptions {
            threshold,
            reference_height,
            min_sin_angle: 3f64.to_radians().sin(),
            max_depth,
            depth_tolerance: 0.02 * max_depth,
            subframe: true,
        }
    }
}

/// What happened to the pixels in [`space_time`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SpaceTimeStats {
    pub measured: usize,
    /// No frame above the threshold (occluded or outside the scan).
    pub dark: usize,
    /// Ray nearly parallel to the laser plane (`|n·d| < min_sin_angle`).
    pub grazing: usize,
    /// Triangulation behind the camera, not reaching the reference plane,
    /// or outside `[−depth_tolerance, max_depth]`.
    pub out_of_range: usize,
}

enum PixelOutcome {
    Measured(f32, f32),
    Dark,
    Grazing,
    OutOfRange,
}

/// Space-time analysis of one scan sequence (seed §3.2, Fig. 5b; [4]):
/// per pixel, the frame `i0` with the brightest grey value; if it does not
/// exceed `opts.threshold` the pixel is occluded (−1). Otherwise, with
/// `opts.subframe`, the peak time is refined by a 3-point Gaussian fit of
/// frames `i0−1, i0, i0+1` (temporal median removed as background) and
/// the plane interpolated linearly (normal and offset, signs aligned)
/// between frame `i0` and its neighbour toward the peak; then the pixel
/// ray is intersected with that plane and the displacement measured from
/// the reference plane along the ray.
///
/// **Grazing rule.** With `s = |n·d|` the sine of the angle between the
/// (unit) ray `d` and the plane: `s < min_sin_angle` → −1 and weight 0
/// (counted as `grazing`); otherwise the geometric weight is
/// `g = s · clamp((s − s_min)/s_min, 0, 1)`, rising continuously from 0 at
/// `s_min` and ∝ `s` above `2·s_min` (depth errors scale as `1/s`). The
/// confidence weight is `g · c` with the peak contrast
/// `c = clamp((peak − median)/peak, 0, 1)` (temporal median of the
/// pixel; 0 with fewer than 3 frames). A triangulation is further
/// rejected (−1) when the point is behind the camera or outside
/// `[−depth_tolerance, max_depth]` from the reference plane, so no huge
/// depth is ever produced; depths in `[−depth_tolerance, 0)` read as 0.
///
/// Frames must be in scan order (for the sub-frame interpolation), all of
/// the camera's size; `planes[i]` is frame `i`'s laser plane.
pub fn space_time(
    frames: &[Image],
    planes: &[LaserPlane],
    camera: &PinholeCamera,
    opts: &SpaceTimeOptions,
) -> Result<(DisplacementImage, SpaceTimeStats), MdfError> {
    camera.validate()?;
    if frames.len() != planes.len() {
        return Err(MdfError::FrameCount {
            frames: frames.len(),
            planes: planes.len(),
        });
    }
    if frames.is_empty() {
        return Err(MdfError::InvalidInput("no frames".into()));
    }
    let ok = |v: f64| v.is_finite();
    if !(ok(opts.threshold)
        && ok(opts.reference_height)
        && ok(opts.min_sin_angle)
        && opts.min_sin_angle > 0.0
        && opts.min_sin_angle < 1.0
        && ok(opts.max_depth)
        && opts.max_depth > 0.0
        && ok(opts.depth_tolerance)
        && opts.depth_tolerance >= 0.0)
    {
        return Err(MdfError::InvalidInput(format!(
            "space-time options {opts:?}"
        )));
    }
    let (w, h) = (camera.width, camera.height);
    for (index, f) in frames.iter().enumerate() {
        check_image(f, "frame")?;
        if (f.width, f.height) != (w, h) {
            return Err(MdfError::FrameSize {
                index,
                expected: (w, h),
                got: (f.width, f.height, f.channels),
            });
        }
    }
    let planes: Vec<LaserPlane> = planes
        .iter()
        .enumerate()
        .map(|(i, p)| p.normalised(i))
        .collect::<Result<_, _>>()?;

    let outcomes: Vec<PixelOutcome> = (0..w * h)
        .into_par_iter()
        .map(|idx| {
            let values: Vec<f64> = frames.iter().map(|f| f64::from(grey(f, idx))).collect();
            pixel(idx % w, idx / w, &values, &planes, camera, opts)
        })
        .collect();
    let mut stats = SpaceTimeStats::default();
    let mut depth = Vec::with_capacity(w * h);
    let mut weight = Vec::with_capacity(w * h);
    for o in outcomes {
        let (d, wt) = match o {
            PixelOutcome::Measured(d, wt) => {
                stats.measured += 1;
                (d, wt)
            }
            PixelOutcome::Dark => {
                stats.dark += 1;
                (NO_DEPTH, 0.0)
            }
            PixelOutcome::Grazing => {
                stats.grazing += 1;
                (NO_DEPTH, 0.0)
            }
            PixelOutcome::OutOfRange => {
                stats.out_of_range += 1;
                (NO_DEPTH, 0.0)
            }
        };
        depth.push(d);
        weight.push(wt);
    }
    Ok((
        DisplacementImage {
            width: w,
            height: h,
            depth,
            weight,
        },
        stats,
    ))
}

fn pixel(
    i: usize,
    j: usize,
    values: &[f64],
    planes: &[LaserPlane],
    camera: &PinholeCamera,
    opts: &SpaceTimeOptions,
) -> PixelOutcome {
    let mut i0 = 0;
    for (k, &v) in values.iter().enumerate() {
        if v > values[i0] {
            i0 = k;
        }
    }
    let peak = values[i0];
    if !gt(peak, opts.threshold) {
        return PixelOutcome::Dark;
    }
    // Background: the temporal median (0 with fewer than 3 frames, where a
    // median would be the peak itself).
    let bg = if values.len() >= 3 {
        let mut sorted = values.to_vec();
        median(&mut sorted)
    } else {
        0.0
    };
    let mut plane = planes[i0];
    if opts.subframe && i0 > 0 && i0 + 1 < values.len() {
        let d = peak_offset(values[i0 - 1] - bg, peak - bg, values[i0 + 1] - bg);
        let nb = if d < 0.0 { i0 - 1 } else { i0 + 1 };
        let other = planes[nb];
        let sign = if dot(plane.normal, other.normal) < 0.0 {
            -1.0
        } else {
            1.0
        };
        // Interpolate only between similar planes (same scan).
        if dot(plane.normal, other.normal).abs() > 0.9 && d != 0.0 {
            let f = d.abs();
            let n = add(scale(plane.normal, 1.0 - f), scale(other.normal, f * sign));
            let o = (1.0 - f) * plane.offset + f * sign * other.offset;
            let len = norm(n);
            if len > 1e-9 {
                plane = LaserPlane {
                    normal: scale(n, 1.0 / len),
                    offset: o / len,
                };
            }
        }
    }
    let (origin, dir) = camera.ray(i, j);
    let s = dot(plane.normal, dir).abs();
    if !gt(s, opts.min_sin_angle) {
        return PixelOutcome::Grazing;
    }
    let Some((t, _)) = plane.intersect(origin, dir) else {
        return PixelOutcome::Grazing;
    };
    // The reference plane along the same ray.
    if !gt(-dir[2], 1e-12) {
        return PixelOutcome::OutOfRange;
    }
    let t_ref = (opts.reference_height - origin[2]) / dir[2];
    let depth = t - t_ref;
    if !(t > 0.0 && t_ref > 0.0 && depth.is_finite())
        || depth > opts.max_depth
        || depth < -opts.depth_tolerance
    {
        return PixelOutcome::OutOfRange;
    }
    let s_min = opts.min_sin_angle;
    let g = s * ((s - s_min) / s_min).clamp(0.0, 1.0);
    let c = ((peak - bg) / peak).clamp(0.0, 1.0);
    let wt = (g * c) as f32;
    PixelOutcome::Measured(depth.max(0.0) as f32, if wt.is_finite() { wt } else { 0.0 })
}

// ----------------------------------------------------------------- merge

/// Unsigned volume of the tetrahedron `a, b, c, d`.
pub fn tetrahedron_volume(a: [f64; 3], b: [f64; 3], c: [f64; 3], d: [f64; 3]) -> f64 {
    let v = dot(sub(b, a), cross(sub(c, a), sub(d, a))).abs() / 6.0;
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// The seed's merge weight of a scan (§3.2, after the error analysis of
/// [2]): the volume of the tetrahedron formed by the laser source position,
/// the camera location, and two points on the laser line passing through
/// the turntable centre. The laser strip on the turntable is orthogonal to
/// the scan direction (§3.1), which is the source's horizontal direction,
/// so the line through the centre runs along `unit(ẑ × source)`; the two
/// points are `±half_length` along it (any fixed length: only ratios of
/// weights matter). The volume vanishes when the camera lies in that laser
/// plane (triangulation ill-conditioned).
pub fn seed_source_weight(
    source: [f64; 3],
    camera_centre: [f64; 3],
    half_length: f64,
) -> Result<f64, MdfError> {
    if !(finite3(source) && finite3(camera_centre) && half_length.is_finite() && half_length > 0.0)
    {
        return Err(MdfError::InvalidInput(format!(
            "source {source:?}, camera {camera_centre:?}, half length {half_length}"
        )));
    }
    let u = unit(cross([0.0, 0.0, 1.0], source)).ok_or_else(|| {
        MdfError::InvalidInput(format!(
            "source {source:?} is above the turntable centre: no scan direction"
        ))
    })?;
    Ok(tetrahedron_volume(
        source,
        camera_centre,
        scale(u, half_length),
        scale(u, -half_length),
    ))
}

/// Merges the displacement images of several laser source positions with
/// the seed's tetrahedron weights ([`seed_source_weight`] with
/// `half_length` metres); see [`merge_weighted`].
pub fn merge(
    displacements: &[DisplacementImage],
    source_positions: &[[f64; 3]],
    camera: &PinholeCamera,
    half_length: f64,
    use_pixel_confidence: bool,
) -> Result<DisplacementImage, MdfError> {
    camera.validate()?;
    if displacements.len() != source_positions.len() {
        return Err(MdfError::SourceCount {
            count: displacements.len(),
            sources: source_positions.len(),
        });
    }
    let weights: Vec<f64> = source_positions
        .iter()
        .map(|&s| seed_source_weight(s, camera.centre, half_length))
        .collect::<Result<_, _>>()?;
    merge_weighted(displacements, &weights, use_pixel_confidence)
}

/// `D_v(x,y) = Σ w_i D_{v,l_i}(x,y) / Σ w_i` over the scans with
/// `D_{v,l_i}(x,y) ≠ −1` (seed §3.2). With `use_pixel_confidence` each
/// term's weight is `w_i` times the pixel's [`space_time`] confidence
/// (the seed's formula is `false`). A pixel with no valid scan, or whose
/// weights sum to 0, stays −1. The output weight is the sum of the weights
/// used.
pub fn merge_weighted(
    displacements: &[DisplacementImage],
    weights: &[f64],
    use_pixel_confidence: bool,
) -> Result<DisplacementImage, MdfError> {
    if displacements.len() != weights.len() {
        return Err(MdfError::SourceCount {
            count: displacements.len(),
            sources: weights.len(),
        });
    }
    let first = displacements
        .first()
        .ok_or_else(|| MdfError::InvalidInput("no displacement images to merge".into()))?;
    let size = (first.width, first.height);
    for (i, d) in displacements.iter().enumerate() {
        d.check(i, size)?;
    }
    if let Some(w) = weights.iter().find(|w| !(w.is_finite() && **w >= 0.0)) {
        return Err(MdfError::InvalidInput(format!("scan weight {w}")));
    }
    let n = size.0 * size.1;
    let (depth, weight): (Vec<f32>, Vec<f32>) = (0..n)
        .into_par_iter()
        .map(|p| {
            let (mut sw, mut swd) = (0.0f64, 0.0f64);
            for (d, &wi) in displacements.iter().zip(weights) {
                let v = d.depth[p];
                if !(v >= 0.0 && v.is_finite()) {
                    continue;
                }
                let c = if use_pixel_confidence {
                    f64::from(d.weight[p]).max(0.0)
                } else {
                    1.0
                };
                let wt = wi * c;
                if wt.is_finite() {
                    sw += wt;
                    swd += wt * f64::from(v);
                }
            }
            if sw > 0.0 && (swd / sw).is_finite() {
                ((swd / sw) as f32, sw as f32)
            } else {
                (NO_DEPTH, 0.0)
            }
        })
        .unzip();
    Ok(DisplacementImage {
        width: size.0,
        height: size.1,
        depth,
        weight,
    })
}

// ------------------------------------------------------------ output

/// 8-bit codes of the depths (the seed stores MDFs quantised to 8 bits):
/// `round(clamp(depth / max_depth, 0, 1) · 254)`; 255 ([`NO_DEPTH_CODE`])
/// for −1 (any negative or non-finite depth).
pub fn quantise_depth(d: &DisplacementImage, max_depth: f64) -> Result<Vec<u8>, MdfError> {
    if !(max_depth.is_finite() && max_depth > 0.0) {
        return Err(MdfError::InvalidInput(format!("max depth {max_depth}")));
    }
    Ok(d.depth
        .iter()
        .map(|&v| {
            if !(v >= 0.0 && v.is_finite()) {
                NO_DEPTH_CODE
            } else {
                let q = (f64::from(v) / max_depth).clamp(0.0, 1.0) * f64::from(MAX_DEPTH_CODE);
                q.round() as u8
            }
        })
        .collect())
}

/// Inverse of [`quantise_depth`]: code 255 → −1.
pub fn dequantise_depth(codes: &[u8], max_depth: f64) -> Vec<f32> {
    codes
        .iter()
        .map(|&c| {
            if c == NO_DEPTH_CODE {
                NO_DEPTH
            } else {
                (f64::from(c) / f64::from(MAX_DEPTH_CODE) * max_depth) as f32
            }
        })
        .collect()
}

/// Writes a displacement image as `float32` `.npy` of shape `(H, W)`
/// (metres, −1 = none) to `npy_path` and its [`quantise_depth`] codes as
/// an 8-bit grey PNG to `png_path` (both atomically).
pub fn write_displacement(
    d: &DisplacementImage,
    npy_path: &Path,
    png_path: &Path,
    max_depth: f64,
) -> Result<(), MdfError> {
    d.check(0, (d.width, d.height))?;
    write_f32(npy_path, &[d.height, d.width], &d.depth)?;
    let codes = quantise_depth(d, max_depth)?;
    let image = Image {
        width: d.width,
        height: d.height,
        channels: 1,
        data: codes.iter().map(|&c| f32::from(c) / 255.0).collect(),
    };
    write_png(png_path, &image, PngDepth::Eight)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn three_point_gaussian_peak_is_exact_for_a_sampled_gaussian() {
        for &(mu, sigma) in &[(0.3, 1.0), (-0.45, 0.7), (0.0, 2.5), (0.1, 0.4)] {
            let g = |x: f64| 0.8 * (-0.5 * ((x - mu) / sigma).powi(2)).exp();
            let d = peak_offset(g(-1.0), g(0.0), g(1.0));
            assert!((d - mu).abs() < 1e-9, "{d} vs {mu}");
        }
        // Flat or non-finite input: no offset, never NaN.
        assert_eq!(peak_offset(1.0, 1.0, 1.0), 0.0);
        assert_eq!(peak_offset(f64::NAN, 1.0, 0.5), 0.0);
    }

    #[test]
    fn jacobi_finds_the_smallest_eigenvector() {
        // R diag(3, 0.5, 2) Rᵀ with R a rotation about (1, 2, 2)/3.
        let axis = [1.0 / 3.0, 2.0 / 3.0, 2.0 / 3.0];
        let (s, c) = 0.7f64.sin_cos();
        // Rodrigues: R = I + s K + (1 − c) K², K the cross-product matrix.
        let k = [
            [0.0, -axis[2], axis[1]],
            [axis[2], 0.0, -axis[0]],
            [-axis[1], axis[0], 0.0],
        ];
        let mut r = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                let k2: f64 = (0..3).map(|m| k[i][m] * k[m][j]).sum();
                r[i][j] = f64::from(u8::from(i == j)) + s * k[i][j] + (1.0 - c) * k2;
            }
        }
        let lam = [3.0, 0.5, 2.0];
        let mut a = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] = (0..3).map(|k| r[i][k] * lam[k] * r[j][k]).sum();
            }
        }
        let (v, eig) = smallest_eigenvector(a);
        let expected = [r[0][1], r[1][1], r[2][1]];
        assert!(
            (dot(v, expected).abs() - 1.0).abs() < 1e-12,
            "{v:?} vs {expected:?}"
        );
        assert!((eig[0] - 0.5).abs() < 1e-12 && (eig[2] - 3.0).abs() < 1e-12);
    }
}
