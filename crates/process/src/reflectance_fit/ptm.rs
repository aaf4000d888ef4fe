//! PTM.

use super::*;

/// Biquadratic PTM coefficients `[a0..a5]` of
/// `L(lu, lv) = a0 lu² + a1 lv² + a2 lu lv + a3 lu + a4 lv + a5`, where
/// `(lu, lv)` are the x, y components of the unit light direction.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PtmFit {
    /// `[a0, …, a5]` of the polynomial above, in input units.
    pub coefficients: [f64; PTM_COEFFICIENTS],
    /// RMS over lights of model − value, in input units.
    pub rms_error: f64,
    /// Mean over lights of |model − value|.
    pub mean_abs_error: f64,
}

impl PtmFit {
    /// The PTM's value for the unit light direction `light` (only its x and
    /// y components enter).
    pub fn evaluate(&self, light: [f64; 3]) -> f64 {
        ptm_row(light)
            .iter()
            .zip(&self.coefficients)
            .map(|(b, a)| b * a)
            .sum()
    }
}

/// The PTM least-squares operator for one set of lights: the pseudo-inverse
/// of the `lights × 6` design matrix, computed once per slot. With fewer
/// than six independent lights it gives the minimum-norm solution.
#[derive(Debug, Clone)]
pub struct PtmBasis {
    lights: Vec<[f64; 3]>,
    /// Row-major `6 × lights`.
    pseudo_inverse: Vec<f64>,
}

impl PtmBasis {
    /// The pseudo-inverse for `lights` (normalised here); errors on no
    /// lights, an invalid light or a failed SVD.
    pub fn new(lights: &[[f64; 3]]) -> Result<Self, FitError> {
        let lights = unit_lights(lights)?;
        let design =
            Mat::<f64>::from_fn(lights.len(), PTM_COEFFICIENTS, |i, j| ptm_row(lights[i])[j]);
        let svd = design.thin_svd().map_err(|_| FitError::PtmSvd)?;
        let pinv = svd.pseudoinverse();
        let mut pseudo_inverse = Vec::with_capacity(PTM_COEFFICIENTS * lights.len());
        for i in 0..PTM_COEFFICIENTS {
            for j in 0..lights.len() {
                pseudo_inverse.push(pinv[(i, j)]);
            }
        }
        if pseudo_inverse.iter().any(|x| !x.is_finite()) {
            return Err(FitError::PtmSvd);
        }
        Ok(Self {
            lights,
            pseudo_inverse,
        })
    }

    /// The unit light directions the basis was built for.
    pub fn lights(&self) -> &[[f64; 3]] {
        &self.lights
    }

    /// Fits one texel: `values` holds one value per light, in
    /// [`PtmBasis::lights`] order.
    pub fn fit(&self, values: &[f32]) -> Result<PtmFit, FitError> {
        check_values(values, self.lights.len())?;
        Ok(self.fit_checked(values))
    }

    pub(super) fn fit_checked(&self, values: &[f32]) -> PtmFit {
        let m = self.lights.len();
        let mut coefficients = [0.0; PTM_COEFFICIENTS];
        for (i, a) in coefficients.iter_mut().enumerate() {
            let row = &self.pseudo_inverse[i * m..(i + 1) * m];
            *a = row.iter().zip(values).map(|(p, &v)| p * f64::from(v)).sum();
        }
        let mut fit = PtmFit {
            coefficients,
            rms_error: 0.0,
            mean_abs_error: 0.0,
        };
        let (rms, mae) = errors(&self.lights, values, |l| fit.evaluate(l));
        fit.rms_error = rms;
        fit.mean_abs_error = mae;
        fit
    }
}

/// PTM results for all texels of one view slot, texel-major.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PtmSlotFit {
    /// One fit per texel, texel-major.
    pub texels: Vec<PtmFit>,
}

impl PtmSlotFit {
    /// Mean over texels and lights of |model − value|.
    pub fn mean_abs_error(&self) -> f64 {
        mean(self.texels.iter().map(|t| t.mean_abs_error))
    }

    /// RMS over texels and lights of model − value.
    pub fn rms_error(&self) -> f64 {
        mean(self.texels.iter().map(|t| t.rms_error * t.rms_error)).sqrt()
    }
}

/// Fits the biquadratic PTM to one texel by linear least squares.
pub fn fit_ptm(lights: &[[f64; 3]], values: &[f32]) -> Result<PtmFit, FitError> {
    PtmBasis::new(lights)?.fit(values)
}

/// [`fit_ptm`] for every texel of a view slot (texel-major, as
/// [`fit_slot`]), sharing one pseudo-inverse.
pub fn fit_ptm_slot(lights: &[[f64; 3]], values: &[f32]) -> Result<PtmSlotFit, FitError> {
    let basis = PtmBasis::new(lights)?;
    check_slot_values(values, basis.lights.len())?;
    let texels = values
        .par_chunks_exact(basis.lights.len())
        .map(|texel| basis.fit_checked(texel))
        .collect();
    Ok(PtmSlotFit { texels })
}

pub(super) fn ptm_row(light: [f64; 3]) -> [f64; PTM_COEFFICIENTS] {
    let (u, v) = (light[0], light[1]);
    [u * u, v * v, u * v, u, v, 1.0]
}
