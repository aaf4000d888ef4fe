//! Marker-based registration and rectification of rig frames onto the
//! frontal plane (Sattler et al., §3.2): find the holder plate's point markers in
//! a frame, estimate the plate→image homography, and resample the sample
//! region to a frontal "normtexture".
//!
//! # Conventions
//! - **Plate coordinates** are metres in the holder plane (z = 0), origin at
//!   the sample centre, `+x` right and `+y` up when seen from the front
//!   (θ = 0, φ = 0) — the sample frame of the simulator.
//! - **Pixel coordinates** are continuous, `x` right and `y` down; pixel
//!   `(i, j)` spans `[i, i+1) × [j, j+1)`, so its centre is `(i+0.5, j+0.5)`.
//! - **Homographies** are row-major 3×3 matrices mapping plate `(x, y, 1)`
//!   to pixel `(u w, v w, w)`; they are scaled to unit Frobenius norm with
//!   `w > 0` over the plate.
//! - **Textures** (output of [`rectify`]): row 0 is the `+y` edge of the
//!   region, column 0 its `−x` edge, i.e. the frontal view as the camera at
//!   θ = 0, φ = 0 sees it.
//!
//! # Pipeline
//! 1. [`detect_markers`]: for each marker whose position the rig predicts
//!    (from the commanded pose; tens of pixels off is fine), the bright blob
//!    nearest the prediction within a search radius. Candidate blobs come
//!    from connected components at a few global levels of the search window
//!    (so a bright sample nearby cannot mask a dimmer marker); each is then
//!    regrown from its peak at the *local* threshold midway between its
//!    surround's median (the dark plate) and its peak, and accepted only if
//!    it does not touch the window or image border, its area is within
//!    [`DetectOptions::min_area_px`]..[`DetectOptions::max_area_px`], it is
//!    not too elongated (second moments), fills its moment ellipse like a
//!    disc does, and is isolated (its surround is dark: a speck of a bright
//!    textured sample is not). The centre is the centroid of the blob
//!    dilated by one pixel, weighted by intensity above the local
//!    background, so partially covered edge pixels count by their coverage.
//!    Under perspective the centroid of a projected disc is not exactly the
//!    projection of its centre; for the holder's 6 mm discs at rig
//!    distances the difference is of the order of 0.01 px.
//! 2. [`detect_border_corners`] (optional, needs a homography good to
//!    about a pixel, e.g. from the point markers): the border lines'
//!    centrelines from cross profiles, fitted as straight image lines, and
//!    their 4 intersections as extra markers
//!    ([`MarkerLayout::with_border_corners`]).
//! 3. [`register`]: normalised DLT (Hartley) over all found markers by
//!    faer's SVD, Levenberg–Marquardt refinement of the reprojection error,
//!    and outlier rejection (see [`register`]); a typed [`RectifyError`]
//!    when fewer than 4 markers are usable, the set is degenerate, the
//!    residual stays too large, or the mapping folds over the plate.
//! 4. [`rectify`]: anisotropic area filtering through the homography's
//!    Jacobian (see [`Filter::Area`]), then [`roi_cut`] and [`quantise`].
//!
//! Every function validates its input and returns finite values; nothing on
//! an input-reachable path panics.

use rayon::prelude::*;

use crate::image_io::Image;

/// Size of a normtexture in Sattler et al. (1024²).
pub const NORMTEXTURE_SIZE: usize = 1024;
/// Size of the final textures after the ROI cut in Sattler et al. (256²).
pub const FINAL_TEXTURE_SIZE: usize = 256;
/// Sattler et al.'s ROI: about 550 of 1024 texels, centred.
pub const SATTLER_ROI_FRACTION: f64 = 550.0 / 1024.0;
/// Largest output side accepted by [`rectify`] and [`roi_cut`].
pub const MAX_OUTPUT_SIDE: usize = 16384;

/// A 3×3 homography, row-major, plate metres → pixels.
pub type Homography = [[f64; 3]; 3];

/// Why a frame could not be registered or rectified.
#[derive(Debug, thiserror::Error)]
pub enum RectifyError {
    /// Fewer than four markers were found.
    #[error(
        "only {found} of {total} markers found (at least 4 needed); missing markers {missing:?}"
    )]
    TooFewMarkers {
        /// Markers found.
        found: usize,
        /// Markers in the layout.
        total: usize,
        /// Layout indices of the markers not found.
        missing: Vec<usize>,
    },
    /// No four of the markers are in general position (near-collinear), so
    /// they determine no homography.
    #[error("the {found} markers found ({used:?}) are degenerate: no 4 of them are in general position (near-collinear)")]
    Degenerate {
        /// Markers found.
        found: usize,
        /// Layout indices of the markers the fit tried.
        used: Vec<usize>,
    },
    /// After outlier rejection the worst reprojection residual still exceeds
    /// [`RegisterOptions::max_residual_px`].
    #[error("markers inconsistent: worst residual {max_px:.2} px exceeds {limit_px:.2} px with {used} markers used ({found} found, rejected {rejected:?})")]
    Inconsistent {
        /// Markers found.
        found: usize,
        /// Markers used in the final fit.
        used: usize,
        /// Layout indices of the markers rejected as outliers.
        rejected: Vec<usize>,
        /// Worst residual of the final fit, pixels.
        max_px: f64,
        /// The limit it exceeds, pixels.
        limit_px: f64,
    },
    /// The fitted homography folds over the plate: the plate reaches (or
    /// comes too near) the camera's horizon, `w ≤ 0`.
    #[error("the homography from {found} markers folds over the plate (the plate reaches the camera's horizon)")]
    Folded {
        /// Markers found.
        found: usize,
    },
    /// faer's SVD in the DLT failed.
    #[error("SVD failed: {0}")]
    Svd(String),
    /// An argument is invalid (sizes, non-finite values, an ROI outside the
    /// texture, a bad bit depth, …); the text says which.
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// [`require_all`]: some frames of a set could not be registered.
    #[error("{} of {total} frames could not be registered: {}", failures.len(), failures.iter().map(|(n, e)| format!("{n}: {e}")).collect::<Vec<_>>().join("; "))]
    Frames {
        /// Frames checked.
        total: usize,
        /// (frame name, reason) of each frame that failed.
        failures: Vec<(String, String)>,
    },
}

mod border_lines;
mod detection;
mod layout;
mod pose;
mod rectification;
mod registration;
mod roi_and_bits;
mod texture_alignment;
pub use border_lines::*;
pub use detection::*;
pub use layout::*;
pub use pose::*;
pub use rectification::*;
pub use registration::*;
pub use roi_and_bits::*;
pub use texture_alignment::*;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resample_weights_sum_to_one() {
        for (n_in, n_out) in [(1024, 256), (550, 256), (10, 4), (2, 7), (5, 5)] {
            for taps in resample_weights(n_in, n_out) {
                let s: f64 = taps.iter().map(|t| t.1).sum();
                assert!((s - 1.0).abs() < 1e-12, "{n_in}->{n_out}: {s}");
                assert!(taps.iter().all(|&(i, w)| i < n_in && w > 0.0));
            }
        }
    }

    #[test]
    fn general_position_needs_four_points_without_collinear_triples() {
        let square = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        assert!(general_position(&square));
        assert!(!general_position(&square[..3]));
        let line_plus_one = [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 1.0]];
        assert!(!general_position(&line_plus_one));
        let mut more = line_plus_one.to_vec();
        more.push([2.0, 1.0]);
        assert!(general_position(&more));
    }

    #[test]
    fn solve8_solves_and_refuses_singular_systems() {
        let mut m = [[0.0; 8]; 8];
        for (i, row) in m.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = 1.0 / (1.0 + i as f64 + j as f64) + if i == j { 1.0 } else { 0.0 };
            }
        }
        let x: [f64; 8] = std::array::from_fn(|i| i as f64 - 3.5);
        let b: [f64; 8] = std::array::from_fn(|i| (0..8).map(|j| m[i][j] * x[j]).sum());
        let got = solve8(m, b).unwrap();
        for (g, w) in got.iter().zip(x) {
            assert!((g - w).abs() < 1e-9);
        }
        assert!(solve8([[0.0; 8]; 8], b).is_none());
    }

    #[test]
    fn disc_centroid_is_subpixel_accurate() {
        // A supersampled disc of radius 5 px at sub-pixel offsets.
        for (cx, cy) in [(30.0, 30.0), (30.3, 29.7), (31.77, 28.21)] {
            let (w, h) = (64, 60);
            let mut img = Image::new(w, h, 1);
            for y in 0..h {
                for x in 0..w {
                    let mut s = 0.0;
                    for a in 0..8 {
                        for b in 0..8 {
                            let px = x as f64 + (a as f64 + 0.5) / 8.0;
                            let py = y as f64 + (b as f64 + 0.5) / 8.0;
                            if (px - cx).hypot(py - cy) <= 5.0 {
                                s += 1.0;
                            }
                        }
                    }
                    img.set(x, y, 0, (0.05 + 0.7 * s / 64.0) as f32);
                }
            }
            let found = detect_markers(
                &img,
                &[Some([cx + 6.0, cy - 4.0])],
                10.0,
                &DetectOptions::default(),
            )
            .unwrap();
            let d = found[0].unwrap();
            let e = (d.centre_px[0] - cx).hypot(d.centre_px[1] - cy);
            assert!(e < 0.02, "({cx}, {cy}): {:?} error {e}", d.centre_px);
            assert!(
                (d.area_px - 78.5).abs() < 8.0 && d.elongation < 1.1,
                "{d:?}"
            );
        }
    }
}
