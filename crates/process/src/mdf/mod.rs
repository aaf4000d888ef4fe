//! Mesostructure distance function (MDF) measurement by laser scanning
//! (Wang et al., §3.2): laser line detection in a flat reference region, laser
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
//! - **MDF** (Wang et al., §3, Fig. 2): the MDF is defined on a reference plane
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
//!    least-squares plane through both (its tilt to the turntable is Wang
//!    et al.'s "angle between the laser plane and the reference plane").
//!    [`plane_from_line`] then turns each scan frame's reference line into
//!    that frame's plane (with the calibrated tilt, or through a known
//!    emitter position).
//! 3. [`space_time`]: per pixel the brightest frame above the threshold,
//!    sub-frame refinement of the peak time, triangulation of the pixel ray
//!    with the (interpolated) plane, the displacement from the reference
//!    plane along the ray, and a confidence weight (see [`space_time`] for
//!    the grazing-plane rule).
//! 4. [`merge`]: Wang et al.'s weighted mean over laser source positions with
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

/// Depth value of a pixel without a measurement (Wang et al.'s `−1`).
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

/// Errors of the MDF pipeline.
#[derive(Debug, thiserror::Error)]
pub enum MdfError {
    /// An argument is empty, out of range or inconsistent (no frames, a region
    /// outside the image, a non-finite option, a negative weight, …); the
    /// text says which.
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// A [`PinholeCamera`] has non-finite values, a non-positive focal length
    /// or size, or axes that are not unit and orthogonal, or a view direction
    /// gives no camera; the text says which.
    #[error("invalid camera: {0}")]
    InvalidCamera(String),
    /// [`space_time`] got a different number of frames and laser planes.
    #[error("{frames} frames but {planes} laser planes (one plane per frame expected)")]
    FrameCount {
        /// Frames given.
        frames: usize,
        /// Laser planes given.
        planes: usize,
    },
    /// A scan frame's size differs from the camera's.
    #[error("frame {index} is {got:?} (width, height, channels) but {expected:?} was expected")]
    FrameSize {
        /// Index of the frame in the scan.
        index: usize,
        /// The camera's (width, height), pixels.
        expected: (usize, usize),
        /// The frame's (width, height, channels).
        got: (usize, usize, usize),
    },
    /// [`merge`] or [`merge_weighted`] got a different number of displacement
    /// images and source positions or weights.
    #[error("{count} displacement images but {sources} source positions / weights")]
    SourceCount {
        /// Displacement images given.
        count: usize,
        /// Source positions or weights given.
        sources: usize,
    },
    /// A displacement image's size differs from the others', or its depth or
    /// weight buffer does not hold width · height values.
    #[error("displacement image {index} is {got:?} (width, height) but {expected:?} was expected, or its buffers have the wrong length")]
    DisplacementSize {
        /// Index of the displacement image.
        index: usize,
        /// The expected (width, height), pixels.
        expected: (usize, usize),
        /// Its (width, height), pixels.
        got: (usize, usize),
    },
    /// A laser plane has a zero or non-finite normal or a non-finite offset.
    #[error("laser plane {index} is invalid: {reason}")]
    InvalidPlane {
        /// Index of the plane (its frame); 0 from [`LaserPlane::through`].
        index: usize,
        /// The offending values.
        reason: String,
    },
    /// [`detect_line`] found too few collinear peaks above the threshold in
    /// the reference region(s).
    #[error("no laser line in region {region:?}: {reason}")]
    NoLine {
        /// The first region searched, `[x0, y0, x1, y1]` in pixels (ends
        /// exclusive).
        region: [usize; 4],
        /// How many candidates there were and how many are needed.
        reason: String,
    },
    /// The laser plane cannot be calibrated or built from the lines: a line
    /// too short or not seeing its plane, a non-positive height, 3-D lines
    /// that are not parallel, or an emitter on the line; the text says which.
    #[error("degenerate calibration: {0}")]
    DegenerateCalibration(String),
    /// Writing a float displacement `.npy` file failed.
    #[error(transparent)]
    Npy(#[from] NpyError),
    /// Writing an 8-bit displacement PNG failed.
    #[error(transparent)]
    Image(#[from] ImageError),
}

// ------------------------------------------------------------- comparisons

/// `a > b`, false when either is NaN (so `!gt(a, b)` reads "not clearly
/// above", NaN included).
fn gt(a: f64, b: f64) -> bool {
    a > b
}
fn finite3(a: [f64; 3]) -> bool {
    a.iter().all(|v| v.is_finite())
}

mod calibration;
mod camera;
mod laser_plane;
mod line_detection;
mod merge;
mod output;
mod space_time;
mod texture;
pub use calibration::*;
pub use camera::*;
pub use laser_plane::*;
pub use line_detection::*;
pub use merge::*;
pub use output::*;
pub use space_time::*;
pub use texture::*;

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
