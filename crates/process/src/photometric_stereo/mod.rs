//! Photometric stereo (Woodham 1980): per-pixel surface normals and albedo
//! from images lit from known directions, gradients, and a height map by
//! Frankot–Chellappa integration.
//!
//! # Conventions
//! - **Frame.** Lights and normals share one right-handed frame: `+x` to
//!   the right (column increasing), `+y` up (row *decreasing*; row 0 is the
//!   top of the image), `+z` out of the surface towards the camera. This is
//!   the frame of the common photometric-stereo light tables and of
//!   OpenGL-style normal maps (green = up).
//! - **Images.** Linear intensities in `[0, 1]` (see [`crate::image_io`]).
//!   With an intensities table each channel of image `i` is divided by that
//!   light's intensity for the channel; a single value per line applies to
//!   every channel, and grey images use the Rec. 709 luminance of an `r g b`
//!   triple.
//! - **Model.** Lambertian: `I_i = ρ (l_i · n)`. With exactly 3 lights the
//!   light matrix is inverted; with more, its pseudo-inverse (from the SVD)
//!   is computed once and applied per pixel.
//! - **Colour.** Normals are solved on the Rec. 709 luminance
//!   `0.2126 R + 0.7152 G + 0.0722 B`; the albedo is then fitted per channel
//!   by least squares along that normal, `ρ_c = Σ s_i I_ci / Σ s_i²` with
//!   `s_i = l_i · n` over the samples used for the normal (clamped at 0).
//!   For grey images this equals `|L⁺ I|`.
//! - **Gradients.** `p = ∂z/∂x = -n_x/n_z`, `q = ∂z/∂y = -n_y/n_z`, in
//!   height units per pixel, with `n_z` floored at [`MIN_NZ`] so steep
//!   pixels yield large but finite slopes. Because `y` is up, `q` is minus
//!   the derivative along increasing rows.
//! - **Height.** Frankot–Chellappa: the least-squares integrable surface in
//!   the Fourier basis, `Z = -j(ω_x P + ω_y Q) / (ω_x² + ω_y²)` with
//!   spectral (not finite-difference) derivatives, any image size
//!   (rustfft handles non-powers of two), mean removed. The surface is
//!   treated as periodic, so a non-periodic sample shows some edge bending.
//!   Height is in pixel units (1 = one pixel pitch).
//! - **Invalid pixels.** Masked-out pixels, dark pixels (every sample 0, or
//!   a zero solution), saturated pixels (every sample at or above
//!   [`PsOptions::saturation_level`] in some channel) and pixels whose
//!   solution faces away from the camera (`n_z ≤ 0`) get `n = (0, 0, 1)`,
//!   `p = q = 0` and albedo 0, are `false` in [`PsResult::valid`] and are
//!   counted in the report. No output ever holds NaN or infinity
//!   (non-finite input samples are read as 0).
//! - **Ill-conditioned lights.** The condition number `σ_max/σ_min` of the
//!   N×3 light matrix is computed with faer's SVD; above
//!   [`PsOptions::max_condition`] (default 1e6) — near-coplanar or repeated
//!   lights — solving fails with [`PsError::IllConditioned`].
//!
//! # Robust mode
//! Per pixel, on the luminance:
//! 1. Reject **saturated** samples (raw value ≥ `saturation_level` in any
//!    channel) and **shadowed** ones (raw luminance ≤ `dark_absolute`, or
//!    intensity-corrected luminance < `dark_relative` × the median of the
//!    pixel's non-saturated samples).
//! 2. Fit by least squares on the remaining lights. While more than 3
//!    remain, compute studentised residuals `r_i / √(1 - h_ii)` (`h` the
//!    hat matrix); the threshold is `max(residual_sigmas · 1.4826 ·
//!    median|r|, residual_tolerance · ρ)`. Remove the sample with the
//!    largest studentised residual above it (ties — with 4 lights a single
//!    outlier cannot be located by residuals — go to the brighter sample,
//!    assuming specular highlights as Coleman & Jain 1982 do) and refit. A
//!    sample is only removed if the remaining lights keep a condition number
//!    ≤ `max_pixel_condition`. Positive residuals count as specular
//!    rejections, negative ones as shadow rejections.
//! 3. If step 1 leaves fewer than 3 lights or an ill-conditioned set, it is
//!    retried without the relative dark test; if that still fails the pixel
//!    falls back to the plain solution from all lights (counted as
//!    `pixels_fallback`).
//!
//! The reported residual is the RMS luminance residual over the samples
//! used, averaged over valid pixels (0 with exactly 3 lights).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;
use rigd_core::geometry::dot;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;

use crate::image_io::{self, Image, ImageError, PngDepth};
use crate::npy::{self, NpyError};

/// Default limit on the light matrix's condition number.
pub const DEFAULT_MAX_CONDITION: f64 = 1e6;
/// Smallest `n_z` used when converting normals to gradients.
pub const MIN_NZ: f64 = 1e-3;
const LUMA: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// Where `rigd process photometric-stereo` finds its inputs.
#[derive(Debug, Clone, Default)]
pub struct PsInputs {
    /// Folder holding the images; without `names_file` every `.png` in it
    /// (except the mask) is one.
    pub images_dir: PathBuf,
    /// One `x y z` direction per line, in image order.
    pub lights_file: PathBuf,
    /// One image file name (relative to `images_dir`) per line; without it,
    /// the `.png` files of `images_dir` sorted by name.
    pub names_file: Option<PathBuf>,
    /// One `r g b` (or single) intensity per line, in image order.
    pub intensities_file: Option<PathBuf>,
    /// PNG, non-zero = valid.
    pub mask_file: Option<PathBuf>,
}

/// Loaded inputs; all fields are public so callers can build one directly.
#[derive(Debug, Clone)]
pub struct PsDataset {
    /// Names used in errors and the report (file paths when loaded).
    pub image_names: Vec<String>,
    /// The images, in light order: all the same size, 1 or 3 channels,
    /// linear values in `[0, 1]`.
    pub images: Vec<Image>,
    /// Unit light directions (see the module doc for the frame).
    pub lights: Vec<[f64; 3]>,
    /// Per-image `[r, g, b]` light intensities, divided out of the samples.
    pub intensities: Option<Vec<[f64; 3]>>,
    /// Row-major, `true` = solve this pixel.
    pub mask: Option<Vec<bool>>,
    /// Named in light-matrix errors (the lights file when loaded).
    pub lights_origin: String,
}

/// Progress callback: `(rows_done, total_rows)`, called from worker threads.
pub type Progress<'a> = &'a (dyn Fn(usize, usize) + Sync);

/// Solver settings; [`Default`] gives plain mode with the documented limits.
#[derive(Clone, Copy)]
pub struct PsOptions<'a> {
    /// Use the robust mode of the module doc (per-pixel rejection of
    /// saturated, shadowed and outlying samples) instead of plain least
    /// squares.
    pub robust: bool,
    /// Largest accepted condition number of the whole light matrix.
    pub max_condition: f64,
    /// Robust mode: largest condition number of a pixel's remaining lights.
    pub max_pixel_condition: f64,
    /// Raw sample value (in `[0, 1]`) from which a sample is saturated.
    pub saturation_level: f32,
    /// Robust mode: raw luminance at or below which a sample is shadowed.
    pub dark_absolute: f64,
    /// Robust mode: fraction of the pixel's median below which a sample is shadowed.
    pub dark_relative: f64,
    /// Robust mode: residual (relative to the albedo) always tolerated.
    pub residual_tolerance: f64,
    /// Robust mode: residual threshold in robust standard deviations.
    pub residual_sigmas: f64,
    /// Called with `(rows_done, total_rows)` while solving.
    pub progress: Option<Progress<'a>>,
}

impl Default for PsOptions<'_> {
    fn default() -> Self {
        PsOptions {
            robust: false,
            max_condition: DEFAULT_MAX_CONDITION,
            max_pixel_condition: 100.0,
            saturation_level: 0.998,
            dark_absolute: 0.5 / 255.0,
            dark_relative: 0.1,
            residual_tolerance: 0.02,
            residual_sigmas: 3.0,
            progress: None,
        }
    }
}

/// What was solved and how; written as `report.json`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PsReport {
    /// Whether the robust mode was used.
    pub robust: bool,
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Channels of the input images: 1 (grey) or 3 (RGB).
    pub channels: usize,
    /// Image names, in light order.
    pub images: Vec<String>,
    /// Unit light directions (module-doc frame), in image order.
    pub lights: Vec<[f64; 3]>,
    /// Per-image `[r, g, b]` light intensities, when a table was given.
    pub intensities: Option<Vec<[f64; 3]>>,
    /// Condition number `σ_max/σ_min` of the N×3 light matrix.
    pub condition_number: f64,
    /// RMS luminance residual over the samples used, averaged over the valid
    /// pixels (0 with exactly 3 lights).
    pub mean_residual: f64,
    /// Pixels in the image: width · height.
    pub pixels_total: usize,
    /// Pixels with a solved normal.
    pub pixels_valid: usize,
    /// Pixels the mask excludes.
    pub pixels_masked: usize,
    /// Pixels with every sample 0, or a zero solution.
    pub pixels_dark: usize,
    /// Pixels with every sample saturated in some channel.
    pub pixels_saturated: usize,
    /// Pixels whose solution faces away from the camera (`n_z ≤ 0`).
    pub pixels_facing_away: usize,
    /// Robust mode: pixels that fell back to the plain solution from all
    /// lights.
    pub pixels_fallback: usize,
    /// Robust mode: samples rejected as shadowed (dark, or an outlier
    /// below the fit).
    pub samples_rejected_shadow: u64,
    /// Robust mode: samples rejected as specular (an outlier above the fit).
    pub samples_rejected_specular: u64,
    /// Robust mode: samples rejected as saturated.
    pub samples_rejected_saturated: u64,
}

/// Solver output; all arrays are row-major, `width × height` pixels.
#[derive(Debug, Clone)]
pub struct PsResult {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Unit normals (module-doc frame).
    pub normals: Vec<[f32; 3]>,
    /// `albedo_channels` values per pixel (1 for grey input, 3 for RGB).
    pub albedo: Vec<f32>,
    /// Albedo values per pixel: 1 for grey input, 3 for RGB.
    pub albedo_channels: usize,
    /// Gradient `∂z/∂x = −n_x/n_z` per pixel, height units per pixel.
    pub p: Vec<f32>,
    /// Gradient `∂z/∂y = −n_y/n_z` per pixel (`y` up, so minus the slope
    /// along increasing rows).
    pub q: Vec<f32>,
    /// Frankot–Chellappa height, zero mean, in pixel units.
    pub height_map: Vec<f32>,
    /// Per pixel: `true` where a normal was solved (not masked, dark,
    /// saturated or facing away).
    pub valid: Vec<bool>,
    /// Counts and diagnostics, as written to `report.json`.
    pub report: PsReport,
}

/// Why photometric stereo could not load its inputs, solve or write.
#[derive(Debug, thiserror::Error)]
pub enum PsError {
    /// A text file or the images folder could not be read.
    #[error("cannot read {}: {source}", path.display())]
    Read {
        /// The file or folder.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A line of the lights or intensities table is malformed: the wrong
    /// number of values, not a number, a zero-length light or a non-positive
    /// intensity.
    #[error("{}:{line}: {reason}", path.display())]
    Parse {
        /// The table file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong with the line.
        reason: String,
    },
    /// The images folder holds no `.png`, or the names file lists no image.
    #[error("{}: no .png images found", path.display())]
    NoImages {
        /// The folder or names file.
        path: PathBuf,
    },
    /// The lights or intensities table has a different number of entries than
    /// there are images.
    #[error("{} has {found} {what} but there are {expected} images ({images})", path.display())]
    CountMismatch {
        /// The table file.
        path: PathBuf,
        /// Which table: `light directions` or `intensities`.
        what: &'static str,
        /// Entries in the table.
        found: usize,
        /// Images listed.
        expected: usize,
        /// Where the images were listed: the names file or the images folder.
        images: String,
    },
    /// An image or the mask could not be loaded, or an output PNG could not
    /// be written.
    #[error(transparent)]
    Image(#[from] ImageError),
    /// An image differs in size or channel count from the first image.
    #[error("{image}: {found} does not match the first image's {expected}")]
    ImageMismatch {
        /// Name of the image.
        image: String,
        /// Size and kind of the first image, e.g. `640x480 RGB`.
        expected: String,
        /// Size and kind of this image.
        found: String,
    },
    /// The mask's size differs from the images'.
    #[error("mask {mask}: {found} does not match the images' {expected}")]
    MaskMismatch {
        /// The mask file (`mask` for a dataset built in code).
        mask: String,
        /// The images' size.
        expected: String,
        /// The mask's size.
        found: String,
    },
    /// Fewer than three light directions were given.
    #[error("{origin}: {count} light directions; photometric stereo needs at least 3")]
    TooFewLights {
        /// Where the lights came from (the lights file when loaded).
        origin: String,
        /// Light directions given.
        count: usize,
    },
    /// The light matrix's condition number exceeds
    /// [`PsOptions::max_condition`]: near-coplanar or repeated lights.
    #[error("{origin}: light directions are near-coplanar or repeated: condition number {condition:.3e} exceeds the limit {max:.1e}")]
    IllConditioned {
        /// Where the lights came from (the lights file when loaded).
        origin: String,
        /// The condition number `σ_max/σ_min`.
        condition: f64,
        /// The limit it exceeds.
        max: f64,
    },
    /// faer's SVD of the light matrix failed.
    #[error("{origin}: SVD of the light matrix failed: {reason}")]
    Svd {
        /// Where the lights came from (the lights file when loaded).
        origin: String,
        /// faer's error.
        reason: String,
    },
    /// A dataset is inconsistent (names, lights or intensities not matching
    /// the images, a zero light, a non-positive intensity, no or empty images)
    /// or the gradients to integrate do not fit the grid.
    #[error("{origin}: {reason}")]
    InvalidInput {
        /// Which input is wrong: the lights' origin, an image name, `images` or
        /// `Frankot–Chellappa`.
        origin: String,
        /// What is wrong with it.
        reason: String,
    },
    /// Writing an output `.npy` array failed.
    #[error(transparent)]
    Npy(#[from] NpyError),
    /// The output folder could not be created.
    #[error("cannot create {}: {source}", path.display())]
    CreateDir {
        /// The folder.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// `report.json` could not be written.
    #[error("cannot write {}: {source}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
}

mod integration;
mod loading;
mod output;
mod solving;
pub use integration::*;
pub use loading::*;
pub use output::*;
pub use solving::*;

#[cfg(test)]
// Index loops read like the matrix algebra they check.
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    #[test]
    fn jacobi_eigenvalues_match_faer_singular_values() {
        let lights = [
            [0.3, -0.2, 0.9],
            [0.1, 0.5, 0.7],
            [-0.6, 0.1, 0.8],
            [0.2, 0.2, 0.1],
        ];
        let mut gram = [[0.0; 3]; 3];
        for l in lights {
            add_outer(&mut gram, l, 1.0);
        }
        let mut eig = symmetric_eigenvalues(gram);
        eig.sort_by(|a, b| b.total_cmp(a));
        let m = faer::Mat::<f64>::from_fn(4, 3, |i, j| lights[i][j]);
        let sv = m.singular_values().unwrap();
        for k in 0..3 {
            assert!((eig[k].sqrt() - sv[k]).abs() < 1e-12, "{eig:?} vs {sv:?}");
        }
    }

    #[test]
    fn invert3_inverts_and_rejects_singular() {
        let m = [[2.0, 1.0, 0.0], [0.5, 3.0, 1.0], [0.0, 1.0, 4.0]];
        let inv = invert3(&m).unwrap();
        for r in 0..3 {
            for c in 0..3 {
                let v: f64 = (0..3).map(|k| m[r][k] * inv[k][c]).sum();
                assert!((v - f64::from(u8::from(r == c))).abs() < 1e-12);
            }
        }
        assert!(invert3(&[[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 1.0, 1.0]]).is_none());
    }

    #[test]
    fn pseudo_inverse_is_a_left_inverse() {
        let lights: Vec<[f64; 3]> = (0..5)
            .map(|i| {
                let a = i as f64 * 1.3;
                [a.cos() * 0.6, a.sin() * 0.6, 0.8]
            })
            .collect();
        let (cond, pinv) = light_matrix_inverse(&lights, "test").unwrap();
        assert!(cond.is_finite() && cond > 1.0);
        for r in 0..3 {
            for c in 0..3 {
                let v: f64 = (0..5).map(|i| pinv[i][r] * lights[i][c]).sum();
                assert!((v - f64::from(u8::from(r == c))).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn table_parsing_skips_comments_and_reports_lines() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("lights.txt");
        std::fs::write(&path, "# header\n\n0 0 2\n1, 0, 1 # trailing\n").unwrap();
        let lights = read_table(&path, &[3], true).unwrap();
        assert_eq!(lights[0], [0.0, 0.0, 1.0]);
        assert!((lights[1][0] - std::f64::consts::FRAC_1_SQRT_2).abs() < 1e-15);
        std::fs::write(&path, "0 0 1\n\n0 0 0\n").unwrap();
        let err = read_table(&path, &[3], true).unwrap_err().to_string();
        assert!(
            err.contains("lights.txt:3") && err.contains("zero"),
            "{err}"
        );
        std::fs::write(&path, "0 0 1\n0 nan 1\n").unwrap();
        let err = read_table(&path, &[3], true).unwrap_err().to_string();
        assert!(err.contains("lights.txt:2"), "{err}");
        std::fs::write(&path, "0 0\n").unwrap();
        assert!(read_table(&path, &[3], true)
            .unwrap_err()
            .to_string()
            .contains(":1:"));
    }

    #[test]
    fn report_json_escapes_names_and_nulls_non_finite() {
        assert_eq!(json_string("a\"b\\c\n"), "\"a\\\"b\\\\c\\u000a\"");
        assert_eq!(json_number(f64::NAN), "null");
        assert_eq!(json_number(1e-7), "1e-7");
    }
}
