//! Colour corrections fitted on a photographed colour chart: camera linear
//! RGB (black level off, any exposure) to linear sRGB (D65 white), judged by
//! the CIEDE2000 difference between each corrected patch and its published
//! L\*a\*b\* (D50).
//!
//! Two corrections are fitted by least squares in linear sRGB:
//! - [`CorrectionKind::Matrix`]: a 3×3 matrix, `srgb = M · rgb`;
//! - [`CorrectionKind::RootPolynomial`]: the degree-2 root-polynomial
//!   correction of Finlayson, Mackiewicz & Hurlbert, "Color Correction
//!   Using Root-Polynomial Regression" (IEEE Transactions on Image
//!   Processing 24(5), 2015): a 3×6 matrix over the terms `r, g, b, √(rg),
//!   √(gb), √(rb)`.
//!
//! White balance is part of both fits (a diagonal gain is a special
//! matrix), so no separate balancing step comes first; [`ChartFit`] reports
//! the balance the neutral patches imply, for reference.
//!
//! Each correction is judged in the fit and left out of it: for every patch
//! the correction is fitted again without it and evaluated on it
//! (leave-one-out), which is what a correction does on colours that were
//! not on the chart. [`fit_chart`] keeps the correction whose mean
//! left-out ΔE2000 is lower: the root-polynomial has twice the unknowns and
//! can fit the chart's noise as well as its colours.

use std::fmt;

use faer::Mat;
use rigd_core::chart::{lab_d50_to_linear_srgb, linear_srgb_to_lab_d50};

use super::ciede2000::delta_e2000;

/// Smallest ratio of the design matrix's least to largest singular value
/// accepted: below it the readings do not determine the correction (all
/// patches the same colour, or greys only), and the fit would be noise.
pub const MIN_SINGULAR_RATIO: f64 = 1e-6;

/// Chroma C\*ab below which a reference patch counts as neutral for the
/// implied white balance (the ColorChecker's greys are within 3.1).
pub const NEUTRAL_CHROMA: f64 = 4.0;

/// One chart patch as the camera saw it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ChartReading {
    /// The chart maker's name for the patch.
    pub name: String,
    /// Its published CIE L\*a\*b\* (D50).
    pub lab_d50: [f64; 3],
    /// The camera's mean linear RGB over the patch: black level off, in
    /// any scale common to all patches (e.g. divided by the white level).
    pub camera_rgb: [f64; 3],
}

/// Which correction.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CorrectionKind {
    /// 3×3 matrix over `r, g, b`.
    Matrix,
    /// Degree-2 root-polynomial: 3×6 over `r, g, b, √(rg), √(gb), √(rb)`.
    RootPolynomial,
}

impl CorrectionKind {
    /// Both kinds, in the order [`fit_chart`] reports them.
    pub const ALL: [CorrectionKind; 2] = [CorrectionKind::Matrix, CorrectionKind::RootPolynomial];

    /// The terms a camera colour is expanded into, by name.
    pub fn term_names(self) -> &'static [&'static str] {
        match self {
            CorrectionKind::Matrix => &["r", "g", "b"],
            CorrectionKind::RootPolynomial => &["r", "g", "b", "sqrt(rg)", "sqrt(gb)", "sqrt(rb)"],
        }
    }

    /// How many terms (columns of the correction).
    pub fn terms(self) -> usize {
        self.term_names().len()
    }

    /// The camera colour expanded into this kind's terms.
    ///
    /// The root-polynomial terms are each of degree 1 in the camera's
    /// signal: scaling `rgb` by an exposure `k` scales every term, and so
    /// the corrected colour, by exactly `k`. A correction fitted at one
    /// exposure therefore holds at any other (a plain polynomial's `r²`
    /// would scale by `k²` and bend the colours of a brighter frame). A
    /// product below 0 (noise around black) counts as 0.
    pub fn expand(self, rgb: [f64; 3]) -> Vec<f64> {
        let [r, g, b] = rgb;
        match self {
            CorrectionKind::Matrix => vec![r, g, b],
            CorrectionKind::RootPolynomial => {
                let root = |x: f64, y: f64| (x * y).max(0.0).sqrt();
                vec![r, g, b, root(r, g), root(g, b), root(r, b)]
            }
        }
    }
}

impl fmt::Display for CorrectionKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            CorrectionKind::Matrix => "3x3 matrix",
            CorrectionKind::RootPolynomial => "root-polynomial",
        })
    }
}

/// A fitted correction: `srgb[c] = Σ_k coefficients[c][k] · term_k(rgb)`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Correction {
    /// Which correction.
    pub kind: CorrectionKind,
    /// One row per sRGB output channel (red, green, blue), one column per
    /// term of [`CorrectionKind::term_names`].
    pub coefficients: [Vec<f64>; 3],
}

impl Correction {
    /// Camera linear RGB (in the scale the correction was fitted in) to
    /// linear sRGB.
    pub fn apply(&self, rgb: [f64; 3]) -> [f64; 3] {
        let terms = self.kind.expand(rgb);
        self.coefficients
            .each_ref()
            .map(|row| row.iter().zip(&terms).map(|(c, t)| c * t).sum())
    }

    /// Camera linear RGB to L\*a\*b\* (D50).
    pub fn apply_lab_d50(&self, rgb: [f64; 3]) -> [f64; 3] {
        linear_srgb_to_lab_d50(self.apply(rgb))
    }

    /// Whether the correction can be applied: one finite coefficient per
    /// term in each row (for one read back from a file).
    pub fn check(&self) -> Result<(), ChartFitError> {
        let terms = self.kind.terms();
        for (c, row) in self.coefficients.iter().enumerate() {
            if row.len() != terms || !row.iter().all(|v| v.is_finite()) {
                return Err(ChartFitError::BadCorrection(format!(
                    "row {c} of the {} correction has {} coefficients ({terms} finite ones needed)",
                    self.kind,
                    row.len()
                )));
            }
        }
        Ok(())
    }
}

/// One patch under a correction.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PatchFit {
    /// The chart maker's name for the patch.
    pub name: String,
    /// Its published L\*a\*b\* (D50).
    pub reference_lab_d50: [f64; 3],
    /// The camera's colour corrected by the correction fitted on all
    /// patches, L\*a\*b\* (D50).
    pub lab_d50: [f64; 3],
    /// ΔE2000 between the two.
    pub delta_e2000: f64,
    /// ΔE2000 of the patch corrected by the correction fitted without it;
    /// `None` if the other patches do not determine a correction.
    pub delta_e2000_left_out: Option<f64>,
}

/// A correction fitted on a chart, and how well it does.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CorrectionFit {
    /// The correction fitted on all patches.
    pub correction: Correction,
    /// Every patch, in the readings' order.
    pub patches: Vec<PatchFit>,
    /// Mean ΔE2000 over the patches, in the fit.
    pub mean_delta_e2000: f64,
    /// Largest ΔE2000, in the fit.
    pub max_delta_e2000: f64,
    /// Mean ΔE2000 with each patch left out of the fit; `None` if some
    /// patch's could not be computed.
    pub mean_delta_e2000_left_out: Option<f64>,
    /// Largest left-out ΔE2000; `None` as the mean.
    pub max_delta_e2000_left_out: Option<f64>,
}

/// Both corrections fitted on a chart, and the one to use.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ChartFit {
    /// The correction with the lower mean left-out ΔE2000 (the matrix on a
    /// tie or when the root-polynomial's cannot be computed).
    pub chosen: CorrectionKind,
    /// The 3×3 matrix.
    pub matrix: CorrectionFit,
    /// The degree-2 root-polynomial.
    pub root_polynomial: CorrectionFit,
    /// Per-channel gains (green 1) that make the neutral patches (chroma
    /// below [`NEUTRAL_CHROMA`]) grey in the camera's raw colours: the
    /// white balance the fit holds. `None` without neutral patches.
    pub white_balance: Option<[f64; 3]>,
}

impl ChartFit {
    /// The chosen correction's fit.
    pub fn chosen_fit(&self) -> &CorrectionFit {
        self.fit_of(self.chosen)
    }

    /// The fit of `kind`.
    pub fn fit_of(&self, kind: CorrectionKind) -> &CorrectionFit {
        match kind {
            CorrectionKind::Matrix => &self.matrix,
            CorrectionKind::RootPolynomial => &self.root_polynomial,
        }
    }
}

/// Why readings could not be fitted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ChartFitError {
    /// Fewer readings than the fit needs.
    #[error("{readings} chart readings; {needed} are needed ({what})")]
    TooFewReadings {
        /// Readings given.
        readings: usize,
        /// Readings needed.
        needed: usize,
        /// Why that many.
        what: String,
    },
    /// A reading with a value that is not a number.
    #[error("patch `{name}`: its {what} {value:?} is not finite")]
    NotFinite {
        /// The patch.
        name: String,
        /// `camera RGB` or `reference L*a*b*`.
        what: &'static str,
        /// The value.
        value: [f64; 3],
    },
    /// The readings' camera colours do not determine the correction.
    #[error(
        "the patches' camera colours do not determine the {kind} correction (least to largest \
         singular value {ratio:.1e}, at least {MIN_SINGULAR_RATIO:.0e} needed): are the patches \
         all the same colour, or all grey?"
    )]
    Degenerate {
        /// Which correction.
        kind: CorrectionKind,
        /// The design matrix's least to largest singular value.
        ratio: f64,
    },
    /// The least-squares solver failed.
    #[error("the least-squares fit failed: {0}")]
    Solver(String),
    /// A correction that cannot be applied (read from a file).
    #[error("{0}")]
    BadCorrection(String),
}

fn check_readings(readings: &[ChartReading]) -> Result<(), ChartFitError> {
    for r in readings {
        if !r.camera_rgb.iter().all(|v| v.is_finite()) {
            return Err(ChartFitError::NotFinite {
                name: r.name.clone(),
                what: "camera RGB",
                value: r.camera_rgb,
            });
        }
        if !r.lab_d50.iter().all(|v| v.is_finite()) {
            return Err(ChartFitError::NotFinite {
                name: r.name.clone(),
                what: "reference L*a*b*",
                value: r.lab_d50,
            });
        }
    }
    Ok(())
}

/// Fits a correction of `kind` on `readings` by least squares in linear
/// sRGB (at least as many readings as the kind has terms).
pub fn fit_correction(
    kind: CorrectionKind,
    readings: &[ChartReading],
) -> Result<Correction, ChartFitError> {
    check_readings(readings)?;
    let (n, k) = (readings.len(), kind.terms());
    if n < k {
        return Err(ChartFitError::TooFewReadings {
            readings: n,
            needed: k,
            what: format!("the {kind} correction has {k} terms per channel"),
        });
    }
    let rows: Vec<Vec<f64>> = readings.iter().map(|r| kind.expand(r.camera_rgb)).collect();
    let targets: Vec<[f64; 3]> = readings
        .iter()
        .map(|r| lab_d50_to_linear_srgb(r.lab_d50))
        .collect();
    let x = Mat::<f64>::from_fn(n, k, |i, j| rows[i][j]);
    let svd = x
        .thin_svd()
        .map_err(|e| ChartFitError::Solver(format!("{e:?}")))?;
    let s = svd.S().column_vector();
    let (largest, least) = (s[0], s[k - 1]);
    let ratio = least / largest;
    // NaN (all-zero readings) fails the comparison and is refused too.
    if ratio.partial_cmp(&MIN_SINGULAR_RATIO) != Some(std::cmp::Ordering::Greater) {
        return Err(ChartFitError::Degenerate {
            kind,
            ratio: if ratio.is_finite() { ratio } else { 0.0 },
        });
    }
    let pinv = svd.pseudoinverse();
    let coefficients = [0, 1, 2].map(|c| {
        (0..k)
            .map(|j| (0..n).map(|i| pinv[(j, i)] * targets[i][c]).sum())
            .collect::<Vec<f64>>()
    });
    let correction = Correction { kind, coefficients };
    correction.check()?;
    Ok(correction)
}

fn mean_max(values: &[f64]) -> (f64, f64) {
    let mean = values.iter().sum::<f64>() / values.len().max(1) as f64;
    let max = values.iter().copied().fold(0.0, f64::max);
    (mean, max)
}

/// Fits a correction of `kind` on all `readings` and judges it on every
/// patch, in the fit and left out of it.
pub fn evaluate(
    kind: CorrectionKind,
    readings: &[ChartReading],
) -> Result<CorrectionFit, ChartFitError> {
    let correction = fit_correction(kind, readings)?;
    let patches: Vec<PatchFit> = readings
        .iter()
        .enumerate()
        .map(|(i, r)| {
            let lab = correction.apply_lab_d50(r.camera_rgb);
            let rest: Vec<ChartReading> = readings
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, r)| r.clone())
                .collect();
            let left_out = fit_correction(kind, &rest)
                .ok()
                .map(|c| delta_e2000(c.apply_lab_d50(r.camera_rgb), r.lab_d50))
                .filter(|d| d.is_finite());
            PatchFit {
                name: r.name.clone(),
                reference_lab_d50: r.lab_d50,
                lab_d50: lab,
                delta_e2000: delta_e2000(lab, r.lab_d50),
                delta_e2000_left_out: left_out,
            }
        })
        .collect();
    let in_fit: Vec<f64> = patches.iter().map(|p| p.delta_e2000).collect();
    let (mean, max) = mean_max(&in_fit);
    let left_out: Option<Vec<f64>> = patches.iter().map(|p| p.delta_e2000_left_out).collect();
    let (mean_out, max_out) = match left_out {
        Some(v) => {
            let (m, x) = mean_max(&v);
            (Some(m), Some(x))
        }
        None => (None, None),
    };
    Ok(CorrectionFit {
        correction,
        patches,
        mean_delta_e2000: mean,
        max_delta_e2000: max,
        mean_delta_e2000_left_out: mean_out,
        max_delta_e2000_left_out: max_out,
    })
}

/// The white balance the neutral patches imply: gains that make their
/// summed camera colour grey, green 1.
pub fn implied_white_balance(readings: &[ChartReading]) -> Option<[f64; 3]> {
    let mut sum = [0.0; 3];
    for r in readings {
        if r.lab_d50[1].hypot(r.lab_d50[2]) < NEUTRAL_CHROMA {
            for (total, v) in sum.iter_mut().zip(r.camera_rgb) {
                *total += v;
            }
        }
    }
    let gains = [sum[1] / sum[0], 1.0, sum[1] / sum[2]];
    (gains.iter().all(|g| g.is_finite() && *g > 0.0)).then_some(gains)
}

/// Fits both corrections on a chart's `readings`, judges each in and out
/// of the fit, and chooses the one with the lower mean left-out ΔE2000.
/// Needs one reading more than the root-polynomial's 6 terms, so that
/// every patch can be left out.
pub fn fit_chart(readings: &[ChartReading]) -> Result<ChartFit, ChartFitError> {
    check_readings(readings)?;
    let needed = CorrectionKind::RootPolynomial.terms() + 1;
    if readings.len() < needed {
        return Err(ChartFitError::TooFewReadings {
            readings: readings.len(),
            needed,
            what: "the root-polynomial correction has 6 terms per channel, and each patch is \
                   also left out of a fit"
                .into(),
        });
    }
    let matrix = evaluate(CorrectionKind::Matrix, readings)?;
    let root_polynomial = evaluate(CorrectionKind::RootPolynomial, readings)?;
    let score = |f: &CorrectionFit| f.mean_delta_e2000_left_out.unwrap_or(f64::INFINITY);
    let chosen = if score(&root_polynomial) < score(&matrix) {
        CorrectionKind::RootPolynomial
    } else {
        CorrectionKind::Matrix
    };
    Ok(ChartFit {
        chosen,
        matrix,
        root_polynomial,
        white_balance: implied_white_balance(readings),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigd_core::chart::COLORCHECKER24;

    /// A camera's linear response to linear sRGB: channels overlap, as
    /// real filters do, and red is weak, so white is not neutral.
    const CAMERA: [[f64; 3]; 3] = [[0.45, 0.20, 0.03], [0.08, 0.85, 0.12], [0.02, 0.18, 0.70]];

    fn mul(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
        m.map(|row| row[0] * v[0] + row[1] * v[1] + row[2] * v[2])
    }

    /// Deterministic noise in [-1, 1] (xorshift).
    fn noise(state: &mut u64) -> f64 {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        (*state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }

    /// The ColorChecker seen through `camera` at `exposure`, each channel
    /// off by up to `noise_level` (relative).
    fn chart_through(
        camera: impl Fn([f64; 3]) -> [f64; 3],
        exposure: f64,
        noise_level: f64,
    ) -> Vec<ChartReading> {
        let mut state = 0x9E37_79B9_7F4A_7C15;
        COLORCHECKER24
            .patches
            .iter()
            .map(|p| {
                let raw = camera(lab_d50_to_linear_srgb(p.lab_d50));
                ChartReading {
                    name: p.name.into(),
                    lab_d50: p.lab_d50,
                    camera_rgb: raw.map(|v| exposure * v * (1.0 + noise_level * noise(&mut state))),
                }
            })
            .collect()
    }

    #[test]
    fn a_linear_camera_s_inverse_is_recovered_exactly() {
        let readings = chart_through(|s| mul(&CAMERA, s), 0.6, 0.0);
        let fit = fit_chart(&readings).expect("fits");
        let m = &fit.matrix.correction;
        // M · CAMERA · exposure is the identity.
        for j in 0..3 {
            let mut e = [0.0; 3];
            e[j] = 1.0;
            let back = m.apply(mul(&CAMERA, e).map(|v| 0.6 * v));
            for (i, v) in back.iter().enumerate() {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 1e-9, "{back:?}");
            }
        }
        // What is left is the rounding of the conversion matrices (7
        // digits) between L*a*b* and sRGB and back.
        assert!(fit.matrix.max_delta_e2000 < 1e-4, "{fit:?}");
        assert!(fit.matrix.max_delta_e2000_left_out.expect("every patch") < 1e-4);
        // The root-polynomial holds the matrix too (its root terms at 0).
        assert!(fit.root_polynomial.max_delta_e2000 < 1e-4);
        assert_eq!(fit.matrix.patches[0].name, "dark skin");
    }

    /// A camera whose channels are not a linear map of sRGB: each channel
    /// has a little of the geometric mean of the others.
    fn crosstalk_camera(s: [f64; 3]) -> [f64; 3] {
        let lin = mul(&CAMERA, s);
        let gm = |x: f64, y: f64| (x.max(0.0) * y.max(0.0)).sqrt();
        [
            lin[0] + 0.08 * gm(lin[1], lin[2]),
            lin[1] + 0.05 * gm(lin[0], lin[2]),
            lin[2] + 0.10 * gm(lin[0], lin[1]),
        ]
    }

    #[test]
    fn the_root_polynomial_is_invariant_to_exposure() {
        let dim = chart_through(crosstalk_camera, 0.3, 0.0);
        let bright = chart_through(crosstalk_camera, 0.3 * 2.5, 0.0);
        let a = fit_correction(CorrectionKind::RootPolynomial, &dim).expect("fits");
        let b = fit_correction(CorrectionKind::RootPolynomial, &bright).expect("fits");
        for (d, r) in dim.iter().zip(&bright) {
            // The same corrected colour from either fit...
            let (x, y) = (a.apply(d.camera_rgb), b.apply(r.camera_rgb));
            // ...and the dim fit scales with the exposure.
            let z = a.apply(r.camera_rgb);
            for c in 0..3 {
                assert!((x[c] - y[c]).abs() < 1e-9, "{}", d.name);
                assert!((z[c] - 2.5 * x[c]).abs() < 1e-9, "{}", d.name);
            }
        }
        // On this camera the root terms earn their keep.
        let fit = fit_chart(&dim).expect("fits");
        assert!(fit.root_polynomial.mean_delta_e2000 < fit.matrix.mean_delta_e2000);
    }

    #[test]
    fn left_out_patches_are_worse_than_fitted_ones_under_noise() {
        let readings = chart_through(crosstalk_camera, 0.5, 0.01);
        let fit = fit_chart(&readings).expect("fits");
        for f in [&fit.matrix, &fit.root_polynomial] {
            let out = f.mean_delta_e2000_left_out.expect("every patch");
            assert!(out > f.mean_delta_e2000, "{f:?}");
            assert!(f.max_delta_e2000_left_out.expect("every patch") >= out);
            for p in &f.patches {
                assert!(p.delta_e2000_left_out.expect("determined") >= 0.0);
            }
        }
        let chosen = fit.chosen_fit().mean_delta_e2000_left_out.expect("both");
        for kind in CorrectionKind::ALL {
            assert!(chosen <= fit.fit_of(kind).mean_delta_e2000_left_out.expect("both"));
        }
    }

    #[test]
    fn the_neutral_patches_give_the_camera_s_white_balance() {
        let gains = [2.0, 1.0, 1.5];
        let readings = chart_through(|s| [0, 1, 2].map(|c| gains[c] * s[c]), 1.0, 0.0);
        let wb = fit_chart(&readings)
            .expect("fits")
            .white_balance
            .expect("neutrals");
        // The chart's greys are within about 2% of neutral in sRGB.
        assert!((wb[0] - 0.5).abs() < 0.02 && wb[1] == 1.0 && (wb[2] - 2.0 / 3.0).abs() < 0.02);
    }

    #[test]
    fn unusable_readings_are_refused_by_name() {
        let good = chart_through(|s| mul(&CAMERA, s), 1.0, 0.0);
        // Fewer readings than terms, for either fit.
        assert!(matches!(
            fit_chart(&good[..5]),
            Err(ChartFitError::TooFewReadings {
                readings: 5,
                needed: 7,
                ..
            })
        ));
        assert!(matches!(
            fit_correction(CorrectionKind::Matrix, &good[..2]),
            Err(ChartFitError::TooFewReadings { needed: 3, .. })
        ));
        // Every patch the same colour.
        let same: Vec<ChartReading> = good
            .iter()
            .map(|r| ChartReading {
                camera_rgb: [0.2, 0.3, 0.1],
                ..r.clone()
            })
            .collect();
        assert!(matches!(
            fit_chart(&same),
            Err(ChartFitError::Degenerate {
                kind: CorrectionKind::Matrix,
                ..
            })
        ));
        // Greys only: the camera colours lie on one line.
        let greys: Vec<ChartReading> = good
            .iter()
            .map(|r| ChartReading {
                camera_rgb: [0.5, 1.0, 0.7].map(|v| v * r.lab_d50[0] / 100.0),
                ..r.clone()
            })
            .collect();
        assert!(matches!(
            fit_chart(&greys),
            Err(ChartFitError::Degenerate { .. })
        ));
        // All black.
        let black: Vec<ChartReading> = good
            .iter()
            .map(|r| ChartReading {
                camera_rgb: [0.0; 3],
                ..r.clone()
            })
            .collect();
        assert!(matches!(
            fit_chart(&black),
            Err(ChartFitError::Degenerate { .. })
        ));
        // NaN in a camera colour or a reference, named.
        let mut nan = good.clone();
        nan[7].camera_rgb[1] = f64::NAN;
        let err = fit_chart(&nan).expect_err("NaN");
        assert!(err.to_string().contains("purplish blue"), "{err}");
        let mut nan = good;
        nan[3].lab_d50[0] = f64::INFINITY;
        assert!(matches!(
            fit_chart(&nan),
            Err(ChartFitError::NotFinite {
                what: "reference L*a*b*",
                ..
            })
        ));
    }

    #[test]
    fn a_correction_read_back_is_checked_and_round_trips() {
        let readings = chart_through(crosstalk_camera, 0.5, 0.0);
        let fit = fit_chart(&readings).expect("fits");
        let json = serde_json::to_string(&fit).expect("serialises");
        let back: ChartFit = serde_json::from_str(&json).expect("reads back");
        assert_eq!(back.chosen, fit.chosen);
        back.root_polynomial.correction.check().expect("whole");
        let mut broken = back.root_polynomial.correction.clone();
        broken.coefficients[1].pop();
        assert!(matches!(
            broken.check(),
            Err(ChartFitError::BadCorrection(_))
        ));
        assert!(json.contains("\"root_polynomial\""));
    }
}
