//! A colour chart in a camera file: the camera's mean colour over each
//! patch, found from the chart's four outer corners in the image, and the
//! colour calibration fitted on them ([`rigd_process::colour::chart_fit`]),
//! as `rigd camera colour` reports it and saves it.
//!
//! The corners are the outer corners of the patch grid, in pixels of the
//! decoded image, in the order the chart is read (legend below): the top
//! left (the first patch's, dark skin on the ColorChecker), top right,
//! bottom right (the last patch's) and bottom left. The grid is mapped
//! through their homography, so any view of the flat chart will do. Each
//! patch is averaged over the middle half of its cell (a quarter of the
//! cell's side in from every edge), clear of its edges and the black gaps
//! between patches, per colour channel: a Bayer mosaic's photosites by
//! their filter colour (no demosaicing, so no colour bleeds in from the
//! neighbours), an RGB file's pixels per channel. Values are the sample's
//! level above black over the white level's (`(s − black) / (white −
//! black)`, sRGB-decoded for rendered files), not clipped at 0, so that the
//! noise around black averages out.

use std::path::Path;

use rigd_core::chart::Chart;
use rigd_process::colour::chart_fit::{
    ChartFit, ChartReading, Correction, CorrectionFit, CorrectionKind,
};
use rigd_process::rectify::{fit_homography, project};

use crate::rig::camera_file::{CameraImage, Encoding};

/// Where each corner is, in the order they are given.
pub const CORNER_POSITIONS: [&str; 4] = ["top left", "top right", "bottom right", "bottom left"];

/// The fraction of a patch cell's side that is averaged, centred.
pub const INNER_FRACTION: f64 = 0.5;

/// The channel names, red green blue.
const CHANNELS: [&str; 3] = ["red", "green", "blue"];

/// Why a chart could not be read from an image.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ChartReadError {
    /// A corner off the image.
    #[error(
        "corner {number} ({position}, {patch}) at {x},{y} is outside the {width}x{height} image"
    )]
    CornerOutside {
        /// 1 to 4, as given.
        number: usize,
        /// `top left`, ….
        position: &'static str,
        /// The patch at that corner.
        patch: &'static str,
        /// The corner, pixels.
        x: f64,
        /// The corner, pixels.
        y: f64,
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
    },
    /// Corners that do not outline a chart.
    #[error("the corners do not outline a chart: {0}")]
    Corners(String),
    /// A patch with a clipped channel: its mean is not the patch's colour.
    #[error(
        "patch `{patch}` is saturated: some of its {channel} samples reach the white level \
         ({white}); photograph the chart with less exposure"
    )]
    Saturated {
        /// The patch.
        patch: &'static str,
        /// `red`, `green` or `blue`.
        channel: &'static str,
        /// The image's white level.
        white: f32,
    },
    /// A patch too small in the image to hold a sample of every colour.
    #[error(
        "patch `{patch}` has no {channel} sample in its middle: the chart is too small in the image"
    )]
    TooSmall {
        /// The patch.
        patch: &'static str,
        /// `red`, `green` or `blue`.
        channel: &'static str,
    },
    /// An image without colour, or whose samples do not fill it.
    #[error("{0}")]
    NoColour(String),
}

/// Signed area of the triangle (a, b, c), twice over.
fn cross(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> f64 {
    (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
}

/// The camera's mean colour over each patch of `chart` in `image`, the
/// grid's outer corners at `corners` (see the module's documentation for
/// their order), in the chart's patch order.
pub fn read_chart(
    image: &CameraImage,
    chart: &Chart,
    corners: [[f64; 2]; 4],
) -> Result<Vec<ChartReading>, ChartReadError> {
    let (rows, cols) = (chart.rows, chart.columns);
    let patch_at_corner = [0, cols - 1, rows * cols - 1, (rows - 1) * cols];
    let (width, height) = (image.width, image.height);
    for (i, &[x, y]) in corners.iter().enumerate() {
        let inside = x.is_finite()
            && y.is_finite()
            && (0.0..=f64::from(width)).contains(&x)
            && (0.0..=f64::from(height)).contains(&y);
        if !inside {
            return Err(ChartReadError::CornerOutside {
                number: i + 1,
                position: CORNER_POSITIONS[i],
                patch: chart.patches[patch_at_corner[i]].name,
                x,
                y,
                width,
                height,
            });
        }
    }
    // The outline must turn the same way at every corner: corners given
    // out of order cross over, and their homography folds the grid.
    let turns: Vec<f64> = (0..4)
        .map(|i| cross(corners[i], corners[(i + 1) % 4], corners[(i + 2) % 4]))
        .collect();
    if !(turns.iter().all(|t| *t > 0.0) || turns.iter().all(|t| *t < 0.0)) {
        return Err(ChartReadError::Corners(format!(
            "{corners:?} is not a convex outline; give the corners in the order {}",
            CORNER_POSITIONS.join(", ")
        )));
    }
    let (c, r) = (cols as f64, rows as f64);
    let grid = [[0.0, 0.0], [c, 0.0], [c, r], [0.0, r]];
    let to_image = fit_homography(&grid, &corners, false)
        .map_err(|e| ChartReadError::Corners(e.to_string()))?;
    let to_grid = fit_homography(&corners, &grid, false)
        .map_err(|e| ChartReadError::Corners(e.to_string()))?;

    let channels = match (image.channels, image.cfa) {
        (1, Some(_)) | (3, None) => image.channels,
        _ => {
            return Err(ChartReadError::NoColour(format!(
                "the image has {} sample(s) per pixel and no colour filter array: a grey camera \
                 cannot be colour-calibrated",
                image.channels
            )))
        }
    };
    let expected = width as usize * height as usize * channels;
    if image.samples.len() != expected {
        return Err(ChartReadError::NoColour(format!(
            "the image holds {} samples, not the {expected} of {width}x{height} pixels of {channels}",
            image.samples.len()
        )));
    }
    let decoded = (image.encoding == Encoding::Srgb).then(|| image.linear());
    let span = f64::from((image.white - image.black).max(1.0));
    let value = |i: usize| match &decoded {
        Some(v) => f64::from(v[i]),
        None => (f64::from(image.samples[i]) - f64::from(image.black)) / span,
    };
    let w = width as usize;
    let lo = (1.0 - INNER_FRACTION) / 2.0;
    let hi = 1.0 - lo;

    let mut readings = Vec::with_capacity(chart.patches.len());
    for (k, patch) in chart.patches.iter().enumerate() {
        let (pr, pc) = ((k / cols) as f64, (k % cols) as f64);
        let inner = [
            [pc + lo, pr + lo],
            [pc + hi, pr + lo],
            [pc + hi, pr + hi],
            [pc + lo, pr + hi],
        ];
        let projected: Option<Vec<[f64; 2]>> =
            inner.iter().map(|&p| project(&to_image, p)).collect();
        let projected = projected.ok_or_else(|| {
            ChartReadError::Corners(format!("patch `{}` maps behind the camera", patch.name))
        })?;
        let x0 = projected.iter().map(|p| p[0]).fold(f64::INFINITY, f64::min);
        let x1 = projected
            .iter()
            .map(|p| p[0])
            .fold(f64::NEG_INFINITY, f64::max);
        let y0 = projected.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min);
        let y1 = projected
            .iter()
            .map(|p| p[1])
            .fold(f64::NEG_INFINITY, f64::max);
        let clamp_x = |v: f64| (v.max(0.0) as usize).min(w);
        let clamp_y = |v: f64| (v.max(0.0) as usize).min(height as usize);
        let mut sum = [0.0f64; 3];
        let mut count = [0usize; 3];
        for py in clamp_y(y0.floor())..clamp_y(y1.ceil()) {
            for px in clamp_x(x0.floor())..clamp_x(x1.ceil()) {
                let Some([u, v]) = project(&to_grid, [px as f64 + 0.5, py as f64 + 0.5]) else {
                    continue;
                };
                if !(pc + lo..=pc + hi).contains(&u) || !(pr + lo..=pr + hi).contains(&v) {
                    continue;
                }
                let pixel = py * w + px;
                let samples: &[(usize, usize)] = &match image.cfa {
                    Some(cfa) => [(cfa.channel_at(px, py), pixel); 3],
                    None => [(0, 3 * pixel), (1, 3 * pixel + 1), (2, 3 * pixel + 2)],
                };
                let used = if image.cfa.is_some() { 1 } else { channels };
                for &(ch, i) in &samples[..used] {
                    if f32::from(image.samples[i]) >= image.white {
                        return Err(ChartReadError::Saturated {
                            patch: patch.name,
                            channel: CHANNELS[ch],
                            white: image.white,
                        });
                    }
                    sum[ch] += value(i);
                    count[ch] += 1;
                }
            }
        }
        if let Some(ch) = (0..3).find(|&ch| count[ch] == 0) {
            return Err(ChartReadError::TooSmall {
                patch: patch.name,
                channel: CHANNELS[ch],
            });
        }
        readings.push(ChartReading {
            name: patch.name.to_string(),
            lab_d50: patch.lab_d50,
            camera_rgb: [0, 1, 2].map(|ch| sum[ch] / count[ch] as f64),
        });
    }
    Ok(readings)
}

/// One patch as `rigd camera colour --json` reports it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PatchReport {
    /// The chart maker's name.
    pub name: String,
    /// The published L\*a\*b\* (D50).
    pub reference_lab_d50: [f64; 3],
    /// The camera's mean linear RGB over the patch (see [`read_chart`]).
    pub camera_rgb: [f64; 3],
    /// The camera's colour after the chosen correction, L\*a\*b\* (D50).
    pub lab_d50: [f64; 3],
    /// ΔE2000 between the two, the patch in the fit.
    pub delta_e2000: f64,
    /// ΔE2000 with the patch left out of the fit.
    pub delta_e2000_left_out: Option<f64>,
}

/// How well a correction fits, in short.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FitSummary {
    /// Mean ΔE2000 over the patches, in the fit.
    pub mean_delta_e2000: f64,
    /// Largest ΔE2000, in the fit.
    pub max_delta_e2000: f64,
    /// Mean ΔE2000, each patch left out of the fit.
    pub mean_delta_e2000_left_out: Option<f64>,
    /// Largest ΔE2000 left out.
    pub max_delta_e2000_left_out: Option<f64>,
}

impl From<&CorrectionFit> for FitSummary {
    fn from(f: &CorrectionFit) -> FitSummary {
        FitSummary {
            mean_delta_e2000: f.mean_delta_e2000,
            max_delta_e2000: f.max_delta_e2000,
            mean_delta_e2000_left_out: f.mean_delta_e2000_left_out,
            max_delta_e2000_left_out: f.max_delta_e2000_left_out,
        }
    }
}

/// Both corrections' summaries.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FitSummaries {
    /// The 3×3 matrix's.
    pub matrix: FitSummary,
    /// The root-polynomial's.
    pub root_polynomial: FitSummary,
}

/// What `rigd camera colour --json` prints: the chosen correction's patches
/// and figures, its coefficients, and both corrections' summaries.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ChartReport {
    /// The chart's name.
    pub chart: String,
    /// Every patch in the chart maker's order.
    pub patches: Vec<PatchReport>,
    /// Mean ΔE2000 of the chosen correction, in the fit.
    pub mean_delta_e2000: f64,
    /// Largest ΔE2000 of the chosen correction, in the fit.
    pub max_delta_e2000: f64,
    /// Mean ΔE2000 of the chosen correction, each patch left out.
    pub mean_delta_e2000_left_out: Option<f64>,
    /// Largest ΔE2000 of the chosen correction, left out.
    pub max_delta_e2000_left_out: Option<f64>,
    /// The chosen correction: `matrix` or `root_polynomial`.
    pub correction: CorrectionKind,
    /// The chosen correction's terms, in the order of `matrix`'s columns.
    pub terms: Vec<String>,
    /// The chosen correction's coefficients: a row per sRGB channel, a
    /// column per term (3×3 for the matrix, 3×6 for the root-polynomial).
    pub matrix: [Vec<f64>; 3],
    /// The white balance the neutral patches imply (gains, green 1).
    pub white_balance: Option<[f64; 3]>,
    /// Both corrections' summaries.
    pub fits: FitSummaries,
}

impl ChartReport {
    /// The report of `fit` on `readings` of `chart`.
    pub fn new(chart: &Chart, readings: &[ChartReading], fit: &ChartFit) -> ChartReport {
        let chosen = fit.chosen_fit();
        ChartReport {
            chart: chart.name.to_string(),
            patches: chosen
                .patches
                .iter()
                .zip(readings)
                .map(|(p, r)| PatchReport {
                    name: p.name.clone(),
                    reference_lab_d50: p.reference_lab_d50,
                    camera_rgb: r.camera_rgb,
                    lab_d50: p.lab_d50,
                    delta_e2000: p.delta_e2000,
                    delta_e2000_left_out: p.delta_e2000_left_out,
                })
                .collect(),
            mean_delta_e2000: chosen.mean_delta_e2000,
            max_delta_e2000: chosen.max_delta_e2000,
            mean_delta_e2000_left_out: chosen.mean_delta_e2000_left_out,
            max_delta_e2000_left_out: chosen.max_delta_e2000_left_out,
            correction: fit.chosen,
            terms: fit
                .chosen
                .term_names()
                .iter()
                .map(|t| t.to_string())
                .collect(),
            matrix: chosen.correction.coefficients.clone(),
            white_balance: fit.white_balance,
            fits: FitSummaries {
                matrix: (&fit.matrix).into(),
                root_polynomial: (&fit.root_polynomial).into(),
            },
        }
    }
}

/// The version of [`ColourCalibrationFile`] written.
pub const CALIBRATION_VERSION: u32 = 1;

/// A camera's colour calibration saved from a chart photograph
/// (`rigd camera colour --save`), for frames of the same camera and light
/// that have no chart in view. Apply it to a camera's mean linear RGB as
/// [`read_chart`] measures it (`(sample − black) / (white − black)` per
/// channel); the result is linear sRGB (D65 white), scaled as the chart's
/// reflectances at the chart photograph's exposure: a frame exposed `k`
/// times longer comes out `k` times brighter.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ColourCalibrationFile {
    /// [`CALIBRATION_VERSION`].
    pub version: u32,
    /// The chart it was fitted on (`colorchecker24`).
    pub chart: String,
    /// The photograph it was fitted on, as named on the command line.
    pub source: String,
    /// The photograph's size, pixels.
    pub width: u32,
    /// The photograph's size, pixels.
    pub height: u32,
    /// The chosen correction: its kind and coefficients (a row per sRGB
    /// channel, a column per term of the kind).
    pub correction: Correction,
    /// The chosen correction's terms, by name.
    pub terms: Vec<String>,
    /// The white balance the neutral patches imply (gains, green 1).
    pub white_balance: Option<[f64; 3]>,
    /// Mean ΔE2000 over the chart, in the fit.
    pub mean_delta_e2000: f64,
    /// Mean ΔE2000 with each patch left out of the fit: what to expect on
    /// colours not on the chart.
    pub mean_delta_e2000_left_out: Option<f64>,
    /// Largest ΔE2000 left out.
    pub max_delta_e2000_left_out: Option<f64>,
}

/// Why a calibration file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationFileError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Read {
        /// The file.
        path: String,
        /// Why.
        source: rigd_core::read::ReadError,
    },
    /// The file is not a calibration rigd can apply.
    #[error("{path} is not a colour calibration rigd can apply: {why}")]
    Invalid {
        /// The file.
        path: String,
        /// Why.
        why: String,
    },
    /// The file could not be written.
    #[error(transparent)]
    Write(#[from] rigd_core::atomic::WriteError),
}

impl ColourCalibrationFile {
    /// The calibration of `fit`.
    pub fn new(chart: &Chart, source: &str, image: &CameraImage, fit: &ChartFit) -> Self {
        let chosen = fit.chosen_fit();
        ColourCalibrationFile {
            version: CALIBRATION_VERSION,
            chart: chart.name.to_string(),
            source: source.to_string(),
            width: image.width,
            height: image.height,
            correction: chosen.correction.clone(),
            terms: fit
                .chosen
                .term_names()
                .iter()
                .map(|t| t.to_string())
                .collect(),
            white_balance: fit.white_balance,
            mean_delta_e2000: chosen.mean_delta_e2000,
            mean_delta_e2000_left_out: chosen.mean_delta_e2000_left_out,
            max_delta_e2000_left_out: chosen.max_delta_e2000_left_out,
        }
    }

    /// Writes the calibration as JSON, atomically.
    pub fn write(&self, path: &Path) -> Result<(), CalibrationFileError> {
        let mut json =
            serde_json::to_vec_pretty(self).map_err(|e| CalibrationFileError::Invalid {
                path: path.display().to_string(),
                why: e.to_string(),
            })?;
        json.push(b'\n');
        rigd_core::atomic::write(path, &json)?;
        Ok(())
    }

    /// Reads a calibration written by [`ColourCalibrationFile::write`],
    /// checking that it can be applied.
    pub fn read(path: &Path) -> Result<Self, CalibrationFileError> {
        let name = path.display().to_string();
        let bytes =
            rigd_core::read::read_bounded(path, rigd_core::read::TEXT_LIMIT).map_err(|source| {
                CalibrationFileError::Read {
                    path: name.clone(),
                    source,
                }
            })?;
        let invalid = |why: String| CalibrationFileError::Invalid {
            path: name.clone(),
            why,
        };
        let file: ColourCalibrationFile =
            serde_json::from_slice(&bytes).map_err(|e| invalid(e.to_string()))?;
        if file.version != CALIBRATION_VERSION {
            return Err(invalid(format!(
                "version {} (this rigd reads {CALIBRATION_VERSION})",
                file.version
            )));
        }
        file.correction
            .check()
            .map_err(|e| invalid(e.to_string()))?;
        Ok(file)
    }
}
