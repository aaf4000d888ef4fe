//! Colour calibration from reference patches of known reflectance: white
//! balance from the white patch, then a 3×3 colour correction matrix fitted
//! by least squares over all patches, and the CIE 1976 colour difference
//! ΔE*ab of every patch, in the fit and held out of it.
//!
//! Conventions: reflectances and corrected values are linear sRGB (D65
//! white); raw values are a camera's demosaiced channel means with the
//! black level off, in any common scale (the fit absorbs the exposure).
//! Lab is computed against the reflectance of a perfect white diffuser, so
//! `L* = 100` is a reflectance of 1; the conversions are
//! [`rigd_core::chart`]'s (sRGB through XYZ, Bradford-adapted to D50).
//!
//! [`ciede2000`] is the CIE's current colour difference, and [`chart_fit`]
//! the corrections fitted on a photographed colour chart (3×3 matrix and
//! root-polynomial) with their ΔE2000 in and out of the fit.

pub mod chart_fit;
pub mod ciede2000;

pub use ciede2000::delta_e2000;

use faer::Mat;
use rigd_core::chart::linear_srgb_to_lab_d50;

/// Why patches could not calibrate colour.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ColourError {
    /// Fewer patches than a 3×3 matrix needs, or no white patch.
    #[error("{0}")]
    TooFewPatches(String),
    /// A raw value that is not finite and positive.
    #[error("patch `{name}` reads {raw:?}: every channel must be finite and above 0")]
    BadReading {
        /// The patch.
        name: String,
        /// What was read.
        raw: [f64; 3],
    },
    /// The patches' colours do not span three dimensions (all grey, say).
    #[error("the patches' raw colours are nearly coplanar (singular values {0:?}); the colour correction is not determined")]
    Degenerate([f64; 3]),
}

/// One reference patch as a frame saw it.
#[derive(Debug, Clone, PartialEq)]
pub struct PatchReading {
    /// The patch's name (`white`, `red`, …).
    pub name: String,
    /// Its known reflectance, linear sRGB.
    pub reference: [f64; 3],
    /// The camera's raw channel means over it.
    pub raw: [f64; 3],
}

/// A camera's colour calibration: `corrected = matrix · (white_balance ⊙
/// raw)`, or, where a root-polynomial correction fits better, `corrected =
/// root_polynomial · terms(white_balance ⊙ raw)`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ColourCalibration {
    /// Per-channel gains that make the white patch neutral, green 1.
    pub white_balance: [f64; 3],
    /// Row-major 3×3 colour correction from balanced raw to linear sRGB.
    pub matrix: [[f64; 3]; 3],
    /// A root-polynomial correction (Finlayson, Mackiewicz & Hurlbert) from
    /// balanced raw to linear sRGB: a row per output channel, a column per
    /// term `r g b √(rg) √(gb) √(rb)`
    /// ([`chart_fit::CorrectionKind::RootPolynomial`]). When set it is
    /// applied instead of `matrix`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub root_polynomial: Option<[[f64; 6]; 3]>,
}

impl ColourCalibration {
    /// Balanced and corrected: raw camera values to linear sRGB.
    pub fn apply(&self, raw: [f64; 3]) -> [f64; 3] {
        let b = [0, 1, 2].map(|c| raw[c] * self.white_balance[c]);
        match &self.root_polynomial {
            Some(rows) => {
                let terms = chart_fit::CorrectionKind::RootPolynomial.expand(b);
                rows.map(|row| row.iter().zip(&terms).map(|(c, t)| c * t).sum())
            }
            None => self
                .matrix
                .map(|row| row[0] * b[0] + row[1] * b[1] + row[2] * b[2]),
        }
    }

    /// The calibration of a chart's fitted `correction` (which takes raw
    /// values as they are: no separate white balance), its output scaled
    /// by `scale`. `None` when the correction's shape is not its kind's.
    pub fn from_correction(correction: &chart_fit::Correction, scale: f64) -> Option<Self> {
        let row = |c: usize| correction.coefficients[c].iter().map(|v| v * scale);
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        match correction.kind {
            chart_fit::CorrectionKind::Matrix => {
                let matrix = [0, 1, 2].map(|c| <[f64; 3]>::try_from(row(c).collect::<Vec<_>>()));
                let [Ok(r), Ok(g), Ok(b)] = matrix else {
                    return None;
                };
                Some(ColourCalibration {
                    white_balance: [1.0; 3],
                    matrix: [r, g, b],
                    root_polynomial: None,
                })
            }
            chart_fit::CorrectionKind::RootPolynomial => {
                let rows = [0, 1, 2].map(|c| <[f64; 6]>::try_from(row(c).collect::<Vec<_>>()));
                let [Ok(r), Ok(g), Ok(b)] = rows else {
                    return None;
                };
                Some(ColourCalibration {
                    white_balance: [1.0; 3],
                    matrix: identity,
                    root_polynomial: Some([r, g, b]),
                })
            }
        }
    }
}

/// Smallest ratio of the balanced patches' least to largest singular
/// value accepted: below it the matrix would amplify noise without bound.
pub const MIN_SPREAD: f64 = 1e-3;

/// The patch white balance is set on: the one with the brightest
/// reference (the standard row's `white`, a ColorChecker's `white 9.5`).
pub fn white_patch(patches: &[PatchReading]) -> Option<usize> {
    let sum = |p: &PatchReading| p.reference.iter().sum::<f64>();
    (0..patches.len()).max_by(|&a, &b| sum(&patches[a]).total_cmp(&sum(&patches[b])))
}

/// White balance from the brightest patch ([`white_patch`]), then the least-squares
/// colour correction over all `patches` (at least 4, so that the 9
/// unknowns are over-determined).
pub fn calibrate(patches: &[PatchReading]) -> Result<ColourCalibration, ColourError> {
    for p in patches {
        if !p.raw.iter().all(|v| v.is_finite() && *v > 0.0) {
            return Err(ColourError::BadReading {
                name: p.name.clone(),
                raw: p.raw,
            });
        }
    }
    let Some(white) = white_patch(patches).map(|k| &patches[k]) else {
        return Err(ColourError::TooFewPatches("no patch to balance on".into()));
    };
    if patches.len() < 4 {
        return Err(ColourError::TooFewPatches(format!(
            "{} patches; a 3x3 colour correction needs at least 4",
            patches.len()
        )));
    }
    let white_balance = [
        white.raw[1] / white.raw[0],
        1.0,
        white.raw[1] / white.raw[2],
    ];
    let balanced = |raw: [f64; 3]| [0, 1, 2].map(|c| raw[c] * white_balance[c]);
    // matrix · b_p ≈ reference_p for every patch: B Mᵀ ≈ R, one least-
    // squares problem per output channel sharing B's pseudo-inverse.
    let b = Mat::<f64>::from_fn(patches.len(), 3, |i, j| balanced(patches[i].raw)[j]);
    let svd = b
        .thin_svd()
        .map_err(|_| ColourError::Degenerate([0.0; 3]))?;
    let s = svd.S().column_vector();
    let values = [s[0], s[1], s[2]];
    // NaN fails the comparison and is refused with the rest.
    if values[2].partial_cmp(&(MIN_SPREAD * values[0])) != Some(std::cmp::Ordering::Greater) {
        return Err(ColourError::Degenerate(values));
    }
    let pinv = svd.pseudoinverse();
    let mut matrix = [[0.0; 3]; 3];
    for (out, row) in matrix.iter_mut().enumerate() {
        for (k, m) in row.iter_mut().enumerate() {
            *m = (0..patches.len())
                .map(|i| pinv[(k, i)] * patches[i].reference[out])
                .sum();
        }
    }
    Ok(ColourCalibration {
        white_balance,
        matrix,
        root_polynomial: None,
    })
}

/// ΔE*ab of every patch corrected by a calibration fitted without it
/// (leave-one-out): how well the correction does on a colour it was not
/// fitted to. The white patch is never left out (it sets the balance);
/// its entry is its in-fit ΔE. `None` where the remaining patches do not
/// determine a matrix.
pub fn held_out_delta_e(patches: &[PatchReading]) -> Vec<Option<f64>> {
    let white = white_patch(patches);
    (0..patches.len())
        .map(|k| {
            if Some(k) == white {
                let cal = calibrate(patches).ok()?;
                return Some(delta_e(cal.apply(patches[k].raw), patches[k].reference));
            }
            let rest: Vec<PatchReading> = patches
                .iter()
                .enumerate()
                .filter(|(i, _)| *i != k)
                .map(|(_, p)| p.clone())
                .collect();
            let cal = calibrate(&rest).ok()?;
            Some(delta_e(cal.apply(patches[k].raw), patches[k].reference))
        })
        .collect()
}

/// CIE 1976 colour difference ΔE*ab between two linear sRGB colours, in
/// L\*a\*b\* under D50 as the chart makers publish it
/// ([`rigd_core::chart::linear_srgb_to_lab_d50`]: sRGB white is `L* = 100`).
pub fn delta_e(a: [f64; 3], b: [f64; 3]) -> f64 {
    let (la, lb) = (linear_srgb_to_lab_d50(a), linear_srgb_to_lab_d50(b));
    ((la[0] - lb[0]).powi(2) + (la[1] - lb[1]).powi(2) + (la[2] - lb[2]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// ColorChecker-like reflectances, linear sRGB.
    const PATCHES: [(&str, [f64; 3]); 6] = [
        ("white", [0.896, 0.896, 0.888]),
        ("red", [0.429, 0.037, 0.045]),
        ("green", [0.061, 0.296, 0.067]),
        ("grey", [0.195, 0.195, 0.191]),
        ("blue", [0.040, 0.047, 0.305]),
        ("yellow", [0.799, 0.571, 0.014]),
    ];

    fn seen_through(response: [[f64; 3]; 3], exposure: f64) -> Vec<PatchReading> {
        PATCHES
            .iter()
            .map(|(name, r)| PatchReading {
                name: name.to_string(),
                reference: *r,
                raw: response.map(|row| exposure * (row[0] * r[0] + row[1] * r[1] + row[2] * r[2])),
            })
            .collect()
    }

    #[test]
    fn a_chart_fits_correction_becomes_a_calibration_that_applies_it() {
        let kinds = [
            chart_fit::Correction {
                kind: chart_fit::CorrectionKind::Matrix,
                coefficients: [
                    vec![1.5, -0.3, -0.1],
                    vec![-0.2, 1.3, -0.1],
                    vec![0.0, -0.4, 1.6],
                ],
            },
            chart_fit::Correction {
                kind: chart_fit::CorrectionKind::RootPolynomial,
                coefficients: [
                    vec![1.4, -0.2, -0.1, 0.05, -0.02, 0.1],
                    vec![-0.2, 1.2, -0.1, 0.1, 0.03, -0.04],
                    vec![0.0, -0.3, 1.5, -0.05, 0.08, 0.0],
                ],
            },
        ];
        for correction in kinds {
            let cal = ColourCalibration::from_correction(&correction, 0.5).expect("its shape");
            assert_eq!(cal.white_balance, [1.0; 3]);
            for raw in [[0.2, 0.4, 0.1], [0.9, 0.8, 0.7], [0.0, 0.3, 0.0]] {
                let want = correction.apply(raw).map(|v| 0.5 * v);
                let got = cal.apply(raw);
                for c in 0..3 {
                    assert!((got[c] - want[c]).abs() < 1e-12, "{:?}", correction.kind);
                }
            }
            // Kept in colour.json and read back, the same calibration.
            let json = serde_json::to_string(&cal).expect("json");
            let back: ColourCalibration = serde_json::from_str(&json).expect("reads back");
            assert_eq!(back, cal);
        }
        // A calibration written before root-polynomials is still read.
        let old = r#"{"white_balance":[2.0,1.0,1.5],"matrix":[[1,0,0],[0,1,0],[0,0,1]]}"#;
        let cal: ColourCalibration = serde_json::from_str(old).expect("reads");
        assert_eq!(cal.root_polynomial, None);
        let applied = cal.apply([0.1, 0.2, 0.3]);
        for (got, want) in applied.iter().zip([0.2, 0.2, 0.45]) {
            assert!((got - want).abs() < 1e-12, "{applied:?}");
        }
        // A correction whose rows do not have its kind's terms is refused.
        let short = chart_fit::Correction {
            kind: chart_fit::CorrectionKind::RootPolynomial,
            coefficients: [vec![1.0; 3], vec![1.0; 3], vec![1.0; 3]],
        };
        assert_eq!(ColourCalibration::from_correction(&short, 1.0), None);
    }

    #[test]
    fn delta_e_is_lab_distance_from_white_to_black() {
        assert_eq!(delta_e([0.3, 0.2, 0.1], [0.3, 0.2, 0.1]), 0.0);
        // sRGB white is L* 100, black L* 0, both neutral.
        assert!((delta_e([1.0; 3], [0.0; 3]) - 100.0).abs() < 1e-3);
        // Mid grey 0.18: L* 49.5.
        assert!((delta_e([0.18; 3], [0.0; 3]) - 49.50).abs() < 0.01);
    }

    #[test]
    fn a_linear_camera_is_corrected_exactly_in_and_out_of_the_fit() {
        let response = [[0.50, 0.12, 0.02], [0.10, 0.80, 0.10], [0.02, 0.12, 0.55]];
        let readings = seen_through(response, 0.37);
        let cal = calibrate(&readings).expect("calibrates");
        assert!((cal.white_balance[0] - readings[0].raw[1] / readings[0].raw[0]).abs() < 1e-12);
        for p in &readings {
            assert!(delta_e(cal.apply(p.raw), p.reference) < 1e-6, "{}", p.name);
        }
        for e in held_out_delta_e(&readings) {
            assert!(e.expect("determined") < 1e-6);
        }
        // White balance alone leaves the overlap of the passbands: the red
        // patch is visibly off.
        let wb_only = ColourCalibration {
            matrix: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            ..cal
        };
        let red = &readings[1];
        let white_scale = readings[0].reference[1] / readings[0].raw[1];
        let balanced = wb_only.apply(red.raw).map(|v| v * white_scale);
        assert!(delta_e(balanced, red.reference) > 5.0);
    }

    #[test]
    fn grey_patches_alone_do_not_determine_a_matrix() {
        let greys: Vec<PatchReading> = [0.9, 0.6, 0.3, 0.1]
            .iter()
            .enumerate()
            .map(|(i, v)| PatchReading {
                name: if i == 0 {
                    "white".into()
                } else {
                    format!("grey{i}")
                },
                reference: [*v; 3],
                raw: [0.5 * v, *v, 0.6 * v],
            })
            .collect();
        assert!(matches!(calibrate(&greys), Err(ColourError::Degenerate(_))));
    }

    #[test]
    fn bad_readings_and_too_few_patches_are_named() {
        let mut readings = seen_through([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], 1.0);
        readings[4].raw[2] = 0.0;
        assert!(
            matches!(calibrate(&readings), Err(ColourError::BadReading { name, .. }) if name == "blue")
        );
        readings[4].raw[2] = f64::NAN;
        assert!(calibrate(&readings).is_err());
        readings.remove(4);
        readings.remove(0);
        // Without `white` the brightest patch left balances.
        calibrate(&readings).expect("four patches calibrate");
        readings.remove(0);
        assert!(matches!(
            calibrate(&readings),
            Err(ColourError::TooFewPatches(_))
        ));
        assert!(matches!(calibrate(&[]), Err(ColourError::TooFewPatches(_))));
    }
}
