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
    pub robust: bool,
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub images: Vec<String>,
    pub lights: Vec<[f64; 3]>,
    pub intensities: Option<Vec<[f64; 3]>>,
    pub condition_number: f64,
    pub mean_residual: f64,
    pub pixels_total: usize,
    pub pixels_valid: usize,
    pub pixels_masked: usize,
    pub pixels_dark: usize,
    pub pixels_saturated: usize,
    pub pixels_facing_away: usize,
    pub pixels_fallback: usize,
    pub samples_rejected_shadow: u64,
    pub samples_rejected_specular: u64,
    pub samples_rejected_saturated: u64,
}

/// Solver output; all arrays are row-major, `width × height` pixels.
#[derive(Debug, Clone)]
pub struct PsResult {
    pub width: usize,
    pub height: usize,
    /// Unit normals (module-doc frame).
    pub normals: Vec<[f32; 3]>,
    /// `albedo_channels` values per pixel (1 for grey input, 3 for RGB).
    pub albedo: Vec<f32>,
    pub albedo_channels: usize,
    pub p: Vec<f32>,
    pub q: Vec<f32>,
    /// Frankot–Chellappa height, zero mean, in pixel units.
    pub height_map: Vec<f32>,
    pub valid: Vec<bool>,
    pub report: PsReport,
}

#[derive(Debug, thiserror::Error)]
pub enum PsError {
    #[error("cannot read {}: {source}", path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}:{line}: {reason}", path.display())]
    Parse {
        path: PathBuf,
        line: usize,
        reason: String,
    },
    #[error("{}: no .png images found", path.display())]
    NoImages { path: PathBuf },
    #[error("{} has {found} {what} but there are {expected} images ({images})", path.display())]
    CountMismatch {
        path: PathBuf,
        what: &'static str,
        found: usize,
        expected: usize,
        images: String,
    },
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error("{image}: {found} does not match the first image's {expected}")]
    ImageMismatch {
        image: String,
        expected: String,
        found: String,
    },
    #[error("mask {mask}: {found} does not match the images' {expected}")]
    MaskMismatch {
        mask: String,
        expected: String,
        found: String,
    },
    #[error("{origin}: {count} light directions; photometric stereo needs at least 3")]
    TooFewLights { origin: String, count: usize },
    #[error("{origin}: light directions are near-coplanar or repeated: condition number {condition:.3e} exceeds the limit {max:.1e}")]
    IllConditioned {
        origin: String,
        condition: f64,
        max: f64,
    },
    #[error("{origin}: SVD of the light matrix failed: {reason}")]
    Svd { origin: String, reason: String },
    #[error("{origin}: {reason}")]
    InvalidInput { origin: String, reason: String },
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error("cannot create {}: {source}", path.display())]
    CreateDir {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write {}: {source}", path.display())]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
}

// ---------------------------------------------------------------- loading

/// Reads the light table, image list, images, intensities and mask.
pub fn load_inputs(inputs: &PsInputs) -> Result<PsDataset, PsError> {
    let lights = read_table(&inputs.lights_file, &[3], true)?;
    let (paths, listing) = match &inputs.names_file {
        Some(names) => (read_names(names, &inputs.images_dir)?, names.clone()),
        None => (
            list_pngs(&inputs.images_dir, inputs.mask_file.as_deref())?,
            inputs.images_dir.clone(),
        ),
    };
    let images_origin = listing.display().to_string();
    if lights.len() != paths.len() {
        return Err(PsError::CountMismatch {
            path: inputs.lights_file.clone(),
            what: "light directions",
            found: lights.len(),
            expected: paths.len(),
            images: images_origin,
        });
    }
    let intensities = match &inputs.intensities_file {
        Some(file) => {
            let table = read_table(file, &[1, 3], false)?;
            if table.len() != paths.len() {
                return Err(PsError::CountMismatch {
                    path: file.clone(),
                    what: "intensities",
                    found: table.len(),
                    expected: paths.len(),
                    images: images_origin,
                });
            }
            Some(table)
        }
        None => None,
    };
    let images: Vec<Image> = paths
        .par_iter()
        .map(|p| image_io::load_png(p))
        .collect::<Result<_, _>>()?;
    let image_names: Vec<String> = paths.iter().map(|p| p.display().to_string()).collect();
    check_images(&images, &image_names)?;
    let mask = match &inputs.mask_file {
        Some(file) => {
            let m = image_io::load_png(file)?;
            let first = &images[0];
            if (m.width, m.height) != (first.width, first.height) {
                return Err(PsError::MaskMismatch {
                    mask: file.display().to_string(),
                    expected: format!("{}x{}", first.width, first.height),
                    found: format!("{}x{}", m.width, m.height),
                });
            }
            Some(
                m.data
                    .chunks(m.channels)
                    .map(|px| px.iter().any(|&v| v > 0.0))
                    .collect(),
            )
        }
        None => None,
    };
    Ok(PsDataset {
        image_names,
        images,
        lights,
        intensities,
        mask,
        lights_origin: inputs.lights_file.display().to_string(),
    })
}

fn read_text(path: &Path) -> Result<String, PsError> {
    std::fs::read_to_string(path).map_err(|source| PsError::Read {
        path: path.to_path_buf(),
        source,
    })
}

/// Non-blank, non-comment lines with their 1-based line numbers.
fn content_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().filter_map(|(i, line)| {
        let line = line.split('#').next().unwrap_or("").trim();
        (!line.is_empty()).then_some((i + 1, line))
    })
}

/// Reads one vector per line with one of `arities` components. Lights
/// (`directions`) must be non-zero and are normalised; intensities must be
/// positive. A single intensity applies to all three channels.
fn read_table(path: &Path, arities: &[usize], directions: bool) -> Result<Vec<[f64; 3]>, PsError> {
    let text = read_text(path)?;
    let parse_err = |line: usize, reason: String| PsError::Parse {
        path: path.to_path_buf(),
        line,
        reason,
    };
    let expected = if directions {
        "`x y z`"
    } else {
        "`r g b` or a single intensity"
    };
    let mut rows = Vec::new();
    for (line_no, line) in content_lines(&text) {
        let fields: Vec<&str> = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|f| !f.is_empty())
            .collect();
        if !arities.contains(&fields.len()) {
            return Err(parse_err(
                line_no,
                format!("expected {expected}, found {} values", fields.len()),
            ));
        }
        let mut values = Vec::with_capacity(3);
        for f in &fields {
            let v: f64 = f
                .parse()
                .map_err(|_| parse_err(line_no, format!("'{f}' is not a number")))?;
            if !v.is_finite() {
                return Err(parse_err(line_no, format!("'{f}' is not finite")));
            }
            values.push(v);
        }
        let v = if values.len() == 1 {
            [values[0]; 3]
        } else {
            [values[0], values[1], values[2]]
        };
        if directions {
            let norm = dot(v, v).sqrt();
            if !(norm > 0.0 && norm.is_finite()) {
                return Err(parse_err(line_no, "light direction has zero length".into()));
            }
            rows.push([v[0] / norm, v[1] / norm, v[2] / norm]);
        } else {
            if v.iter().any(|&x| x <= 0.0) {
                return Err(parse_err(line_no, "intensities must be positive".into()));
            }
            rows.push(v);
        }
    }
    Ok(rows)
}

fn read_names(names_file: &Path, dir: &Path) -> Result<Vec<PathBuf>, PsError> {
    let text = read_text(names_file)?;
    let names: Vec<PathBuf> = content_lines(&text)
        .map(|(_, name)| dir.join(name))
        .collect();
    if names.is_empty() {
        return Err(PsError::NoImages {
            path: names_file.to_path_buf(),
        });
    }
    Ok(names)
}

fn list_pngs(dir: &Path, exclude: Option<&Path>) -> Result<Vec<PathBuf>, PsError> {
    let read_err = |source| PsError::Read {
        path: dir.to_path_buf(),
        source,
    };
    // The mask may live next to the images; it is not one of them.
    let exclude = exclude.and_then(|p| p.canonicalize().ok());
    let mut paths = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(read_err)? {
        let path = entry.map_err(read_err)?.path();
        let is_png = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("png"));
        if is_png && path.is_file() && (exclude.is_none() || path.canonicalize().ok() != exclude) {
            paths.push(path);
        }
    }
    paths.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    if paths.is_empty() {
        return Err(PsError::NoImages {
            path: dir.to_path_buf(),
        });
    }
    Ok(paths)
}

fn describe(image: &Image) -> String {
    let kind = match image.channels {
        1 => "grey",
        3 => "RGB",
        _ => "?",
    };
    format!("{}x{} {kind}", image.width, image.height)
}

fn check_images(images: &[Image], names: &[String]) -> Result<(), PsError> {
    let Some(first) = images.first() else {
        return Err(PsError::InvalidInput {
            origin: "images".into(),
            reason: "no images".into(),
        });
    };
    for (image, name) in images.iter().zip(names) {
        let consistent = image.channels == first.channels
            && image.width == first.width
            && image.height == first.height;
        if !consistent {
            return Err(PsError::ImageMismatch {
                image: name.clone(),
                expected: describe(first),
                found: describe(image),
            });
        }
        if !(image.channels == 1 || image.channels == 3)
            || image.data.len() != image.width * image.height * image.channels
        {
            return Err(PsError::InvalidInput {
                origin: name.clone(),
                reason: format!(
                    "{} samples for {} channels of {}x{} (expected 1 or 3 channels)",
                    image.data.len(),
                    image.channels,
                    image.width,
                    image.height
                ),
            });
        }
        if image.width == 0 || image.height == 0 {
            return Err(PsError::InvalidInput {
                origin: name.clone(),
                reason: "empty image".into(),
            });
        }
    }
    Ok(())
}

// ---------------------------------------------------------------- solving

/// Solves a loaded dataset.
pub fn solve(dataset: &PsDataset, opts: &PsOptions) -> Result<PsResult, PsError> {
    if dataset.image_names.len() != dataset.images.len() {
        return Err(PsError::InvalidInput {
            origin: dataset.lights_origin.clone(),
            reason: format!(
                "{} image names for {} images",
                dataset.image_names.len(),
                dataset.images.len()
            ),
        });
    }
    solve_core(
        &dataset.images,
        &dataset.image_names,
        &dataset.lights,
        dataset.intensities.as_deref(),
        dataset.mask.as_deref(),
        &dataset.lights_origin,
        opts,
    )
}

/// Solves images already in memory (e.g. frames of a rigd run). `lights`
/// need not be unit length; `mask` is row-major, `true` = solve.
pub fn solve_images(
    images: &[Image],
    lights: &[[f64; 3]],
    mask: Option<&[bool]>,
    opts: &PsOptions,
) -> Result<PsResult, PsError> {
    let names: Vec<String> = (0..images.len()).map(|i| format!("image #{i}")).collect();
    solve_core(images, &names, lights, None, mask, "light directions", opts)
}

/// Per-pixel outcome before assembly.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Status {
    Valid,
    Masked,
    Dark,
    Saturated,
    FacingAway,
}

#[derive(Clone, Copy)]
struct PixelOut {
    normal: [f64; 3],
    albedo: [f32; 3],
    status: Status,
    residual: f64,
    fallback: bool,
    rejected: Rejections,
}

#[derive(Clone, Copy, Default)]
struct Rejections {
    shadow: u32,
    specular: u32,
    saturated: u32,
}

/// Everything a pixel solve needs that does not change between pixels.
struct Solver<'a> {
    images: &'a [Image],
    lights: Vec<[f64; 3]>,
    /// 3×N: pseudo-inverse (or inverse for N = 3) of the light matrix.
    pinv: Vec<[f64; 3]>,
    /// Per image, the reciprocal intensity of each channel.
    inv_intensity: Vec<[f64; 3]>,
    channels: usize,
    opts: PsOptions<'a>,
}

/// Scratch buffers reused across the pixels of a row.
struct Scratch {
    raw: Vec<f64>,
    corrected: Vec<f64>,
    lum: Vec<f64>,
    raw_lum: Vec<f64>,
    raw_max: Vec<f32>,
    used: Vec<bool>,
    sort: Vec<f64>,
    ranked: Vec<(f64, f64, usize)>,
}

fn solve_core(
    images: &[Image],
    names: &[String],
    lights: &[[f64; 3]],
    intensities: Option<&[[f64; 3]]>,
    mask: Option<&[bool]>,
    lights_origin: &str,
    opts: &PsOptions,
) -> Result<PsResult, PsError> {
    check_images(images, names)?;
    let invalid = |reason: String| PsError::InvalidInput {
        origin: lights_origin.to_string(),
        reason,
    };
    if lights.len() != images.len() {
        return Err(invalid(format!(
            "{} light directions for {} images",
            lights.len(),
            images.len()
        )));
    }
    if lights.len() < 3 {
        return Err(PsError::TooFewLights {
            origin: lights_origin.to_string(),
            count: lights.len(),
        });
    }
    let mut unit = Vec::with_capacity(lights.len());
    for (i, l) in lights.iter().enumerate() {
        let norm = dot(*l, *l).sqrt();
        if !(norm.is_finite() && norm > 0.0) {
            return Err(invalid(format!(
                "light {} ({}) is zero or not finite",
                i + 1,
                names[i]
            )));
        }
        unit.push([l[0] / norm, l[1] / norm, l[2] / norm]);
    }
    let (width, height, channels) = (images[0].width, images[0].height, images[0].channels);
    if let Some(m) = mask {
        if m.len() != width * height {
            return Err(PsError::MaskMismatch {
                mask: "mask".into(),
                expected: format!("{} pixels", width * height),
                found: format!("{} values", m.len()),
            });
        }
    }
    let inv_intensity = match intensities {
        Some(table) => {
            if table.len() != images.len() {
                return Err(invalid(format!(
                    "{} intensities for {} images",
                    table.len(),
                    images.len()
                )));
            }
            let mut inv = Vec::with_capacity(table.len());
            for (i, t) in table.iter().enumerate() {
                if t.iter().any(|&v| !(v.is_finite() && v > 0.0)) {
                    return Err(invalid(format!(
                        "intensity of {} is not positive",
                        names[i]
                    )));
                }
                inv.push(if channels == 1 {
                    [1.0 / dot(*t, LUMA); 3]
                } else {
                    [1.0 / t[0], 1.0 / t[1], 1.0 / t[2]]
                });
            }
            inv
        }
        None => vec![[1.0; 3]; images.len()],
    };

    let (condition, pinv) = light_matrix_inverse(&unit, lights_origin)?;
    if condition.is_nan() || condition > opts.max_condition {
        return Err(PsError::IllConditioned {
            origin: lights_origin.to_string(),
            condition,
            max: opts.max_condition,
        });
    }

    let solver = Solver {
        images,
        lights: unit,
        pinv,
        inv_intensity,
        channels,
        opts: *opts,
    };
    let rows_done = AtomicUsize::new(0);
    let rows: Vec<Vec<PixelOut>> = (0..height)
        .into_par_iter()
        .map(|y| {
            let mut scratch = Scratch::new(images.len(), channels);
            let row = (0..width)
                .map(|x| {
                    let index = y * width + x;
                    let enabled = mask.is_none_or(|m| m[index]);
                    solver.pixel(index, enabled, &mut scratch)
                })
                .collect();
            let done = rows_done.fetch_add(1, Ordering::Relaxed) + 1;
            if let Some(progress) = opts.progress {
                progress(done, height);
            }
            row
        })
        .collect();

    let n_pixels = width * height;
    let albedo_channels = channels;
    let mut result = PsResult {
        width,
        height,
        normals: Vec::with_capacity(n_pixels),
        albedo: Vec::with_capacity(n_pixels * albedo_channels),
        albedo_channels,
        p: Vec::with_capacity(n_pixels),
        q: Vec::with_capacity(n_pixels),
        height_map: Vec::new(),
        valid: Vec::with_capacity(n_pixels),
        report: PsReport {
            robust: opts.robust,
            width,
            height,
            channels,
            images: names.to_vec(),
            lights: solver.lights.clone(),
            intensities: intensities.map(<[_]>::to_vec),
            condition_number: condition,
            mean_residual: 0.0,
            pixels_total: n_pixels,
            pixels_valid: 0,
            pixels_masked: 0,
            pixels_dark: 0,
            pixels_saturated: 0,
            pixels_facing_away: 0,
            pixels_fallback: 0,
            samples_rejected_shadow: 0,
            samples_rejected_specular: 0,
            samples_rejected_saturated: 0,
        },
    };
    let mut residual_sum = 0.0;
    for px in rows.iter().flatten() {
        let report = &mut result.report;
        match px.status {
            Status::Valid => {
                report.pixels_valid += 1;
                residual_sum += px.residual;
            }
            Status::Masked => report.pixels_masked += 1,
            Status::Dark => report.pixels_dark += 1,
            Status::Saturated => report.pixels_saturated += 1,
            Status::FacingAway => report.pixels_facing_away += 1,
        }
        report.pixels_fallback += usize::from(px.fallback);
        report.samples_rejected_shadow += u64::from(px.rejected.shadow);
        report.samples_rejected_specular += u64::from(px.rejected.specular);
        report.samples_rejected_saturated += u64::from(px.rejected.saturated);
        let n = px.normal;
        let nz = n[2].max(MIN_NZ);
        result.normals.push([n[0] as f32, n[1] as f32, n[2] as f32]);
        result.p.push((-n[0] / nz) as f32);
        result.q.push((-n[1] / nz) as f32);
        result
            .albedo
            .extend_from_slice(&px.albedo[..albedo_channels]);
        result.valid.push(px.status == Status::Valid);
    }
    if result.report.pixels_valid > 0 {
        result.report.mean_residual = residual_sum / result.report.pixels_valid as f64;
    }
    result.height_map = integrate_frankot_chellappa(&result.p, &result.q, width, height)?;
    Ok(result)
}

impl Scratch {
    fn new(n: usize, channels: usize) -> Self {
        Scratch {
            raw: vec![0.0; n * channels],
            corrected: vec![0.0; n * channels],
            lum: vec![0.0; n],
            raw_lum: vec![0.0; n],
            raw_max: vec![0.0; n],
            used: vec![false; n],
            sort: Vec::with_capacity(n),
            ranked: Vec::with_capacity(n),
        }
    }
}

const INVALID_NORMAL: [f64; 3] = [0.0, 0.0, 1.0];

impl Solver<'_> {
    fn invalid(status: Status) -> PixelOut {
        PixelOut {
            normal: INVALID_NORMAL,
            albedo: [0.0; 3],
            status,
            residual: 0.0,
            fallback: false,
            rejected: Rejections::default(),
        }
    }

    fn pixel(&self, index: usize, enabled: bool, s: &mut Scratch) -> PixelOut {
        if !enabled {
            return Self::invalid(Status::Masked);
        }
        let ch = self.channels;
        let n = self.lights.len();
        for (i, image) in self.images.iter().enumerate() {
            let mut raw_max = 0.0f32;
            for c in 0..ch {
                let v = image.data[index * ch + c];
                let v = if v.is_finite() { v } else { 0.0 };
                raw_max = raw_max.max(v);
                s.raw[i * ch + c] = f64::from(v);
                s.corrected[i * ch + c] = f64::from(v) * self.inv_intensity[i][c];
            }
            s.raw_max[i] = raw_max;
            if ch == 1 {
                s.lum[i] = s.corrected[i];
                s.raw_lum[i] = s.raw[i];
            } else {
                s.lum[i] = dot(
                    [
                        s.corrected[3 * i],
                        s.corrected[3 * i + 1],
                        s.corrected[3 * i + 2],
                    ],
                    LUMA,
                );
                s.raw_lum[i] = dot([s.raw[3 * i], s.raw[3 * i + 1], s.raw[3 * i + 2]], LUMA);
            }
        }
        if s.raw_max.iter().all(|&v| v <= 0.0) {
            return Self::invalid(Status::Dark);
        }
        if s.raw_max.iter().all(|&v| v >= self.opts.saturation_level) {
            return Self::invalid(Status::Saturated);
        }

        let mut rejected = Rejections::default();
        let mut fallback = false;
        let robust = if self.opts.robust {
            self.robust_fit(s, &mut rejected)
        } else {
            None
        };
        let t = match robust {
            Some(t) => t,
            None => {
                fallback = self.opts.robust;
                rejected = Rejections::default();
                s.used.iter_mut().for_each(|u| *u = true);
                let mut t = [0.0; 3];
                for (row, lum) in self.pinv.iter().zip(&s.lum) {
                    for k in 0..3 {
                        t[k] += row[k] * lum;
                    }
                }
                t
            }
        };
        let rho = dot(t, t).sqrt();
        if !(rho > 1e-12 && rho.is_finite()) {
            return Self::invalid(Status::Dark);
        }
        if t[2] <= 0.0 {
            return Self::invalid(Status::FacingAway);
        }
        let normal = [t[0] / rho, t[1] / rho, t[2] / rho];

        let (mut ss, mut res2, mut used) = (0.0, 0.0, 0usize);
        let mut sc = [0.0f64; 3];
        for i in (0..n).filter(|&i| s.used[i]) {
            let shading = dot(self.lights[i], normal);
            ss += shading * shading;
            for (c, acc) in sc.iter_mut().enumerate().take(ch) {
                *acc += shading * s.corrected[i * ch + c];
            }
            let r = s.lum[i] - rho * shading;
            res2 += r * r;
            used += 1;
        }
        let mut albedo = [0.0f32; 3];
        if ss > 0.0 {
            for c in 0..ch {
                albedo[c] = (sc[c] / ss).max(0.0) as f32;
            }
        }
        PixelOut {
            normal,
            albedo,
            status: Status::Valid,
            residual: (res2 / used.max(1) as f64).sqrt(),
            fallback,
            rejected,
        }
    }

    /// Robust fit (module doc); `None` means "use the plain solution".
    /// Leaves the chosen samples in `s.used`.
    fn robust_fit(&self, s: &mut Scratch, rejected: &mut Rejections) -> Option<[f64; 3]> {
        let n = self.lights.len();
        let opts = &self.opts;
        for use_relative in [true, false] {
            let mut r = Rejections::default();
            for i in 0..n {
                s.used[i] = s.raw_max[i] < opts.saturation_level;
                r.saturated += u32::from(!s.used[i]);
            }
            s.sort.clear();
            s.sort
                .extend((0..n).filter(|&i| s.used[i]).map(|i| s.lum[i]));
            let median = median(&mut s.sort);
            for i in 0..n {
                let dark = s.raw_lum[i] <= opts.dark_absolute
                    || (use_relative && s.lum[i] < opts.dark_relative * median);
                if s.used[i] && dark {
                    s.used[i] = false;
                    r.shadow += 1;
                }
            }
            let count = s.used.iter().filter(|&&u| u).count();
            if count < 3 || self.subset_condition(&s.used, None) > opts.max_pixel_condition {
                continue;
            }
            let t = self.refit_loop(s, &mut r)?;
            *rejected = r;
            return Some(t);
        }
        None
    }

    fn refit_loop(&self, s: &mut Scratch, r: &mut Rejections) -> Option<[f64; 3]> {
        let n = self.lights.len();
        let opts = &self.opts;
        loop {
            let mut gram = [[0.0; 3]; 3];
            let mut rhs = [0.0; 3];
            let mut count = 0;
            for i in (0..n).filter(|&i| s.used[i]) {
                let l = self.lights[i];
                add_outer(&mut gram, l, 1.0);
                for k in 0..3 {
                    rhs[k] += l[k] * s.lum[i];
                }
                count += 1;
            }
            let inverse = invert3(&gram)?;
            let t = mat_vec(&inverse, rhs);
            if count <= 3 {
                return Some(t);
            }
            s.sort.clear();
            s.ranked.clear();
            for i in (0..n).filter(|&i| s.used[i]) {
                let l = self.lights[i];
                let residual = s.lum[i] - dot(l, t);
                let leverage = dot(l, mat_vec(&inverse, l));
                let studentised = residual / (1.0 - leverage).max(1e-12).sqrt();
                s.sort.push(residual.abs());
                s.ranked.push((studentised, s.lum[i], i));
            }
            let scale = (opts.residual_sigmas * 1.4826 * median(&mut s.sort))
                .max(opts.residual_tolerance * dot(t, t).sqrt());
            let largest = s.ranked.iter().map(|e| e.0.abs()).fold(0.0, f64::max);
            let tie = 1e-9 * largest;
            // Largest |studentised residual| first; near-ties to the brighter sample.
            // Comparators must be total orders (sort may panic otherwise), so
            // the near-tie group is re-sorted separately rather than with a
            // tolerance inside one comparator.
            s.ranked.sort_by(|a, b| b.0.abs().total_cmp(&a.0.abs()));
            let tied = s
                .ranked
                .iter()
                .take_while(|e| e.0.abs() >= largest - tie)
                .count();
            s.ranked[..tied].sort_by(|a, b| b.1.total_cmp(&a.1));
            let mut removed = false;
            for k in 0..s.ranked.len() {
                let (studentised, _, i) = s.ranked[k];
                if studentised.abs() <= scale {
                    break;
                }
                if self.subset_condition(&s.used, Some(i)) <= opts.max_pixel_condition {
                    s.used[i] = false;
                    if studentised > 0.0 {
                        r.specular += 1;
                    } else {
                        r.shadow += 1;
                    }
                    removed = true;
                    break;
                }
            }
            if !removed {
                return Some(t);
            }
        }
    }

    /// Condition number of the used lights, optionally without `skip`.
    fn subset_condition(&self, used: &[bool], skip: Option<usize>) -> f64 {
        let mut gram = [[0.0; 3]; 3];
        let mut count = 0;
        for (i, l) in self.lights.iter().enumerate() {
            if used[i] && skip != Some(i) {
                add_outer(&mut gram, *l, 1.0);
                count += 1;
            }
        }
        if count < 3 {
            return f64::INFINITY;
        }
        let eig = symmetric_eigenvalues(gram);
        let (min, max) = eig.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &e| {
            (lo.min(e), hi.max(e))
        });
        if min <= 0.0 {
            f64::INFINITY
        } else {
            (max / min).sqrt()
        }
    }
}

/// Condition number of the N×3 light matrix and its (pseudo-)inverse as N
/// rows of 3 (row `i` holds column `i` of the 3×N inverse).
fn light_matrix_inverse(
    lights: &[[f64; 3]],
    origin: &str,
) -> Result<(f64, Vec<[f64; 3]>), PsError> {
    let matrix = faer::Mat::<f64>::from_fn(lights.len(), 3, |i, j| lights[i][j]);
    let svd_err = |e: faer::linalg::svd::SvdError| PsError::Svd {
        origin: origin.to_string(),
        reason: format!("{e:?}"),
    };
    let svd = matrix.thin_svd().map_err(svd_err)?;
    let sigma = svd.S().column_vector();
    let (max, min) = (sigma[0], sigma[2]);
    let condition = if min > 0.0 { max / min } else { f64::INFINITY };
    if !condition.is_finite() {
        return Ok((f64::INFINITY, Vec::new()));
    }
    let pinv: Vec<[f64; 3]> = if lights.len() == 3 {
        let m = [lights[0], lights[1], lights[2]];
        let Some(inv) = invert3(&m) else {
            return Ok((f64::INFINITY, Vec::new()));
        };
        (0..3).map(|i| [inv[0][i], inv[1][i], inv[2][i]]).collect()
    } else {
        let p = svd.pseudoinverse();
        (0..lights.len())
            .map(|i| [p[(0, i)], p[(1, i)], p[(2, i)]])
            .collect()
    };
    Ok((condition, pinv))
}

fn add_outer(m: &mut [[f64; 3]; 3], v: [f64; 3], w: f64) {
    for r in 0..3 {
        for c in 0..3 {
            m[r][c] += w * v[r] * v[c];
        }
    }
}

fn mat_vec(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [dot(m[0], v), dot(m[1], v), dot(m[2], v)]
}

/// Inverse by cofactors; `None` if singular.
fn invert3(m: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let c = |r: usize, k: usize| {
        let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
        let (k1, k2) = ((k + 1) % 3, (k + 2) % 3);
        m[r1][k1] * m[r2][k2] - m[r1][k2] * m[r2][k1]
    };
    let det = m[0][0] * c(0, 0) + m[0][1] * c(0, 1) + m[0][2] * c(0, 2);
    if !(det.abs() > f64::MIN_POSITIVE && det.is_finite()) {
        return None;
    }
    let mut inv = [[0.0; 3]; 3];
    for (r, row) in inv.iter_mut().enumerate() {
        for (k, v) in row.iter_mut().enumerate() {
            *v = c(k, r) / det;
        }
    }
    Some(inv)
}

/// Eigenvalues of a symmetric 3×3 matrix by cyclic Jacobi rotations.
fn symmetric_eigenvalues(mut a: [[f64; 3]; 3]) -> [f64; 3] {
    for _ in 0..50 {
        let off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
        let diag = a[0][0] * a[0][0] + a[1][1] * a[1][1] + a[2][2] * a[2][2];
        if off <= 1e-30 * diag || off == 0.0 {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for row in a.iter_mut() {
                let (kp, kq) = (row[p], row[q]);
                row[p] = c * kp - s * kq;
                row[q] = s * kp + c * kq;
            }
            let (row_p, row_q) = (a[p], a[q]);
            a[p] = std::array::from_fn(|k| c * row_p[k] - s * row_q[k]);
            a[q] = std::array::from_fn(|k| s * row_p[k] + c * row_q[k]);
        }
    }
    [a[0][0], a[1][1], a[2][2]]
}

/// Median of `values` (reordered in place); 0 when empty.
fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    values.sort_by(f64::total_cmp);
    let mid = values.len() / 2;
    if values.len() % 2 == 1 {
        values[mid]
    } else {
        0.5 * (values[mid - 1] + values[mid])
    }
}

// ---------------------------------------------------------------- integration

/// Frankot–Chellappa integration of gradients `p = ∂z/∂x` (x = column) and
/// `q = ∂z/∂y` (y = up, i.e. row decreasing) on a `width × height` grid;
/// returns the zero-mean height, row-major. Non-finite gradients count as 0.
pub fn integrate_frankot_chellappa(
    p: &[f32],
    q: &[f32],
    width: usize,
    height: usize,
) -> Result<Vec<f32>, PsError> {
    let n = width * height;
    if p.len() != n || q.len() != n || n == 0 {
        return Err(PsError::InvalidInput {
            origin: "Frankot–Chellappa".into(),
            reason: format!(
                "{} p and {} q values for a {width}x{height} grid",
                p.len(),
                q.len()
            ),
        });
    }
    let finite = |v: f32| if v.is_finite() { f64::from(v) } else { 0.0 };
    // Work in (row, column): ∂z/∂column = p, ∂z/∂row = -q because y is up.
    let mut gc: Vec<Complex<f64>> = p.iter().map(|&v| Complex::new(finite(v), 0.0)).collect();
    let mut gr: Vec<Complex<f64>> = q.iter().map(|&v| Complex::new(-finite(v), 0.0)).collect();
    let mut planner = FftPlanner::new();
    fft2(&mut planner, &mut gc, width, height, false);
    fft2(&mut planner, &mut gr, width, height, false);
    let omega = |k: usize, len: usize| {
        let signed = if k <= len / 2 {
            k as f64
        } else {
            k as f64 - len as f64
        };
        2.0 * std::f64::consts::PI * signed / len as f64
    };
    let j = Complex::new(0.0, 1.0);
    let mut z = gc;
    for r in 0..height {
        let wr = omega(r, height);
        for c in 0..width {
            let wc = omega(c, width);
            let denom = wc * wc + wr * wr;
            let i = r * width + c;
            z[i] = if denom > 0.0 {
                -j * (z[i] * wc + gr[i] * wr) / denom
            } else {
                Complex::new(0.0, 0.0)
            };
        }
    }
    fft2(&mut planner, &mut z, width, height, true);
    let scale = 1.0 / n as f64;
    let mean = z.iter().map(|v| v.re).sum::<f64>() * scale * scale;
    Ok(z.iter().map(|v| (v.re * scale - mean) as f32).collect())
}

/// In-place unnormalised 2-D FFT of a row-major `width × height` grid.
fn fft2(
    planner: &mut FftPlanner<f64>,
    data: &mut [Complex<f64>],
    width: usize,
    height: usize,
    inverse: bool,
) {
    let plan = |planner: &mut FftPlanner<f64>, len| {
        if inverse {
            planner.plan_fft_inverse(len)
        } else {
            planner.plan_fft_forward(len)
        }
    };
    let row_fft = plan(planner, width);
    data.par_chunks_mut(width).for_each_init(
        || vec![Complex::new(0.0, 0.0); row_fft.get_inplace_scratch_len()],
        |scratch, row| row_fft.process_with_scratch(row, scratch),
    );
    let mut columns = vec![Complex::new(0.0, 0.0); data.len()];
    for r in 0..height {
        for c in 0..width {
            columns[c * height + r] = data[r * width + c];
        }
    }
    let col_fft = plan(planner, height);
    columns.par_chunks_mut(height).for_each_init(
        || vec![Complex::new(0.0, 0.0); col_fft.get_inplace_scratch_len()],
        |scratch, col| col_fft.process_with_scratch(col, scratch),
    );
    for r in 0..height {
        for c in 0..width {
            data[r * width + c] = columns[c * height + r];
        }
    }
}

// ---------------------------------------------------------------- output

/// Writes the arrays, renderings and `report.json` into `out_dir` (created
/// if missing), each atomically; returns the written paths.
pub fn write_outputs(result: &PsResult, out_dir: &Path) -> Result<Vec<PathBuf>, PsError> {
    std::fs::create_dir_all(out_dir).map_err(|source| PsError::CreateDir {
        path: out_dir.to_path_buf(),
        source,
    })?;
    let (w, h) = (result.width, result.height);
    let mut written = Vec::new();
    let mut npy_out = |name: &str, shape: &[usize], data: &[f32]| -> Result<(), PsError> {
        let path = out_dir.join(name);
        npy::write_f32(&path, shape, data)?;
        written.push(path);
        Ok(())
    };
    let normals_flat: Vec<f32> = result.normals.iter().flatten().copied().collect();
    npy_out("normals.npy", &[h, w, 3], &normals_flat)?;
    if result.albedo_channels == 1 {
        npy_out("albedo.npy", &[h, w], &result.albedo)?;
    } else {
        npy_out(
            "albedo.npy",
            &[h, w, result.albedo_channels],
            &result.albedo,
        )?;
    }
    npy_out("height.npy", &[h, w], &result.height_map)?;
    npy_out("p.npy", &[h, w], &result.p)?;
    npy_out("q.npy", &[h, w], &result.q)?;

    let mut png_out = |name: &str, image: Image, depth: PngDepth| -> Result<(), PsError> {
        let path = out_dir.join(name);
        image_io::write_png(&path, &image, depth)?;
        written.push(path);
        Ok(())
    };
    png_out(
        "normals.png",
        Image {
            width: w,
            height: h,
            channels: 3,
            data: normals_flat.iter().map(|v| 0.5 * (v + 1.0)).collect(),
        },
        PngDepth::Eight,
    )?;
    // Albedo above 1 (possible after intensity division) is scaled down to fit.
    let albedo_max = result.albedo.iter().copied().fold(0.0f32, f32::max);
    let albedo_scale = if albedo_max > 1.0 {
        1.0 / albedo_max
    } else {
        1.0
    };
    png_out(
        "albedo.png",
        Image {
            width: w,
            height: h,
            channels: result.albedo_channels,
            data: result.albedo.iter().map(|v| v * albedo_scale).collect(),
        },
        PngDepth::Sixteen,
    )?;
    let (lo, hi) = result
        .height_map
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    let span = hi - lo;
    png_out(
        "height.png",
        Image {
            width: w,
            height: h,
            channels: 1,
            data: result
                .height_map
                .iter()
                .map(|&v| if span > 0.0 { (v - lo) / span } else { 0.5 })
                .collect(),
        },
        PngDepth::Sixteen,
    )?;

    let path = out_dir.join("report.json");
    crate::atomic::write(&path, report_json(&result.report).as_bytes()).map_err(|source| {
        PsError::Write {
            path: path.clone(),
            source,
        }
    })?;
    written.push(path);
    Ok(written)
}

fn json_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for ch in s.chars() {
        match ch {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => out.push_str(&format!("\\u{:04x}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

fn json_number(v: f64) -> String {
    if v.is_finite() {
        format!("{v:?}")
    } else {
        "null".into()
    }
}

fn json_vec3(v: &[f64; 3]) -> String {
    format!(
        "[{}, {}, {}]",
        json_number(v[0]),
        json_number(v[1]),
        json_number(v[2])
    )
}

/// `report.json`: hand-written to keep the crate free of a JSON dependency.
fn report_json(r: &PsReport) -> String {
    let images: Vec<String> = r
        .images
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let intensity = r
                .intensities
                .as_ref()
                .and_then(|t| t.get(i))
                .map_or_else(|| "null".to_string(), json_vec3);
            format!(
                "    {{\"name\": {}, \"light\": {}, \"intensity\": {intensity}}}",
                json_string(name),
                r.lights
                    .get(i)
                    .map_or_else(|| "null".to_string(), json_vec3)
            )
        })
        .collect();
    format!(
        "{{\n  \"method\": \"photometric-stereo\",\n  \"mode\": \"{mode}\",\n  \
         \"frame\": \"x right (column), y up (row decreasing), z towards the camera\",\n  \
         \"width\": {w},\n  \"height\": {h},\n  \"channels\": {c},\n  \
         \"lights_used\": {nl},\n  \"condition_number\": {cond},\n  \"mean_residual\": {res},\n  \
         \"pixels_total\": {pt},\n  \"pixels_valid\": {pv},\n  \"pixels_masked\": {pm},\n  \
         \"pixels_dark\": {pd},\n  \"pixels_saturated\": {ps},\n  \"pixels_facing_away\": {pf},\n  \
         \"pixels_fallback\": {pfb},\n  \"samples_rejected_shadow\": {rs},\n  \
         \"samples_rejected_specular\": {rsp},\n  \"samples_rejected_saturated\": {rsat},\n  \
         \"images\": [\n{images}\n  ]\n}}\n",
        mode = if r.robust { "robust" } else { "plain" },
        w = r.width,
        h = r.height,
        c = r.channels,
        nl = r.lights.len(),
        cond = json_number(r.condition_number),
        res = json_number(r.mean_residual),
        pt = r.pixels_total,
        pv = r.pixels_valid,
        pm = r.pixels_masked,
        pd = r.pixels_dark,
        ps = r.pixels_saturated,
        pf = r.pixels_facing_away,
        pfb = r.pixels_fallback,
        rs = r.samples_rejected_shadow,
        rsp = r.samples_rejected_specular,
        rsat = r.samples_rejected_saturated,
        images = images.join(",\n"),
    )
}

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
