//! Per view reflectance-field fit of seed 001 (Meseth, Müller, Klein,
//! "Preserving Realism in real-time Rendering of BTFs", §4.2), and the
//! polynomial texture map (PTM, Malzbender et al. 2001) it is compared with.
//!
//! For one view slot `v` and one texel `x` the measured reflectance field
//! `RF_v(x, l)` (one value per light direction `l`) is approximated by
//! seed 001 equation (1):
//!
//! ```text
//! RF_v(x, l) ≈ Σ_{i=1..k} ⟨(a_i, b_i, c_i), l⟩^{n_i}
//! ```
//!
//! a sum of `k` Lafortune-like lobes without the exitant direction. The
//! paper has no separate diffuse term: a Lambertian `ρ_d cos θ_l` is exactly
//! a lobe with axis = surface normal and `n = 1`, so equation (1) subsumes
//! it, and with `k = 2` one lobe usually settles as the broad "directional
//! diffuse" lobe. Like Lafortune, a negative scalar product contributes 0.
//!
//! # Reparametrisation (seed 001 §7: overflows with high exponents)
//!
//! In the paper's form the lobe height is `|C|^n`: with `n = 10⁴` a 1 %
//! change of `|C|` (one ordinary Levenberg–Marquardt step) multiplies the
//! lobe by `e^{99}`, which overflows f32 at once and f64 from `n ≈ 7·10⁴`;
//! and a spatially restricted lobe whose axis falls between samples can
//! fit the data with a peak of `10¹⁶` or more, which overflows at render
//! time. The paper reports exactly those overflows. Here each lobe is
//!
//! ```text
//! s_i(l) = ρ_i · max(ĉ_i · l, 0)^{n_i},   evaluated as ρ_i · exp(n_i · ln(ĉ_i · l))
//! ```
//!
//! with a unit axis `ĉ_i`, an amplitude `ρ_i = |C_i|^{n_i}` and the exponent
//! fitted as `η_i = ln n_i`. The power term is in `[0, 1]` for any `n`, so
//! nothing can overflow; `n` is clamped to `[MIN_EXPONENT, max_exponent]`
//! (at most [`MAX_EXPONENT`]) and `ρ` to `[0, max_amplitude_ratio · max
//! value]`, which bounds every fitted lobe's peak, even between samples.
//! [`Lobe::to_paper_coefficients`] converts back to `(a, b, c, n)`.
//!
//! # Fitting
//!
//! Each texel is fitted independently ([`fit_slot`] runs texels in parallel
//! with rayon) by a hand-written dense Levenberg–Marquardt over the `4k`
//! parameters `(ρ, u, v, ln n)` per lobe, with the analytic Jacobian
//! ([`LobeModel::jacobian_row`]), Marquardt scaling, Nielsen's damping
//! update, bounds by projection and at most [`FitOptions::max_iterations`]
//! solves. It starts from principal directions (the paper's "detecting
//! principal directions with a high-pass filter", §4.2; see
//! `principal_direction_lobes`). Degenerate texels get a documented
//! [`Fallback`]: all values ≤ 0 → zero lobes; fewer than 4 lights → one
//! Lambertian lobe; fewer than `4k` lights → fewer lobes. Invalid input
//! (no lights, mismatched lengths, non-finite lights or values) is a
//! [`FitError`]; nothing on an input path panics.
//!
//! # Error measure (seed 001 Table 1)
//!
//! Table 1 gives the "average luminance difference between data and
//! model" without defining it further. [`error_table`] reports the mean
//! absolute difference over all texels and lights of the slot (our reading
//! of "average difference", the column to compare with the paper) and the
//! RMS difference, both in the input's units, plus the fit's wall time.
//!
//! # Units
//!
//! Values are luminance, in whatever linear units the caller uses (f32);
//! all errors are reported in the same units. [`fit_texel_rgb`] fits the
//! luminance and a per-texel colour scale, as the paper does ("the fit is
//! performed on the luminance data, the final color is computed as in
//! [PTM]", §4.2 and §5.3).

use std::fmt;
use std::time::{Duration, Instant};

use faer::Mat;
use rayon::prelude::*;
use rigd_core::geometry::{cross, dot};
use serde::{Deserialize, Serialize};

/// Smallest lobe exponent. With `n ≥ 1` the lobe and its derivative stay
/// bounded at the lobe's horizon (`ĉ · l → 0`), where `n cos^{n-1}` would
/// blow up for `n < 1`.
pub const MIN_EXPONENT: f64 = 1.0;
/// Largest lobe exponent (half width 0.2°). Above it the paper coefficients
/// `(a, b, c, n)` stored as f32 lose the amplitude (`|C|^n` carries a
/// relative error `n · 2⁻²⁴ ≈ 0.6 %` here), and no rig samples lights
/// densely enough to tell such lobes apart. For f16 export lower
/// [`FitOptions::max_exponent`] to about 100.
pub const MAX_EXPONENT: f64 = 1.0e5;
/// Largest lobe amplitude accepted by [`Lobe::new`] and produced by
/// [`Lobe::from_paper_coefficients`]; far above any reflectance, far below
/// f32 overflow even summed over [`MAX_LOBES`] lobes.
pub const MAX_AMPLITUDE: f64 = 1.0e30;
/// Default of [`FitOptions::max_amplitude_ratio`].
pub const DEFAULT_MAX_AMPLITUDE_RATIO: f64 = 10.0;
/// Most lobes per texel.
pub const MAX_LOBES: usize = 8;
/// Fitted parameters per lobe: amplitude ρ, two tangent rotations of the
/// axis (u, v), and η = ln n.
pub const PARAMS_PER_LOBE: usize = 4;
/// Coefficients of the biquadratic PTM.
pub const PTM_COEFFICIENTS: usize = 6;
/// Rec. 709 / sRGB luminance weights for linear RGB.
pub const LUMINANCE_WEIGHTS: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// Invalid input to a fit.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitError {
    #[error("no light directions")]
    NoLights,
    #[error("light {index} is not a finite non-zero vector: {direction:?}")]
    InvalidLight { index: usize, direction: [f64; 3] },
    #[error("expected {expected} values, got {got}")]
    LengthMismatch { expected: usize, got: usize },
    #[error("value {index} is not finite ({value})")]
    NonFiniteValue { index: usize, value: f32 },
    #[error("lobe count {0} outside 1..={MAX_LOBES}")]
    InvalidLobeCount(usize),
    #[error("invalid fit option: {0}")]
    InvalidOptions(&'static str),
    #[error("invalid lobe: {0}")]
    InvalidLobe(&'static str),
    #[error("PTM pseudo-inverse: the SVD did not converge")]
    PtmSvd,
}

/// Levenberg–Marquardt settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FitOptions {
    /// Most LM iterations (linear solves) per texel.
    pub max_iterations: usize,
    /// Exponent clamp, in `[MIN_EXPONENT, MAX_EXPONENT]`.
    pub max_exponent: f64,
    /// A fitted lobe's amplitude is at most this times the texel's largest
    /// value (≥ 1). A sharp lobe whose axis falls between lights is seen by
    /// none of them at its peak, so the data cannot bound its height: LM
    /// would otherwise slide along a flat valley of ever higher, narrower
    /// peaks, which render as the black or white pixels of seed 001 §7. The
    /// default 10 still admits a lobe whose axis is up to `√(2 ln 10 / n)`
    /// from the nearest light.
    pub max_amplitude_ratio: f64,
    /// Stop when an accepted step lowers the cost, and was predicted to
    /// lower it, by less than this fraction (default 1e-8, as MINPACK's and
    /// SciPy's `ftol`: sharp lobes seen by one or two lights leave flat
    /// valleys LM would otherwise crawl along for thousands of steps).
    pub cost_tolerance: f64,
    /// Stop when no parameter moves more than this (amplitudes relative to
    /// the texel's largest value, angles in radians, `ln n` absolute).
    pub step_tolerance: f64,
    /// Initial damping, relative to the largest diagonal entry of `JᵀJ`.
    pub initial_damping: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            max_iterations: 200,
            max_exponent: MAX_EXPONENT,
            max_amplitude_ratio: DEFAULT_MAX_AMPLITUDE_RATIO,
            cost_tolerance: 1e-8,
            step_tolerance: 1e-10,
            initial_damping: 1e-3,
        }
    }
}

impl FitOptions {
    fn validate(&self) -> Result<(), FitError> {
        if !(MIN_EXPONENT..=MAX_EXPONENT).contains(&self.max_exponent) {
            return Err(FitError::InvalidOptions(
                "max_exponent outside [MIN_EXPONENT, MAX_EXPONENT]",
            ));
        }
        if !(self.max_amplitude_ratio.is_finite() && self.max_amplitude_ratio >= 1.0) {
            return Err(FitError::InvalidOptions(
                "max_amplitude_ratio must be finite and at least 1",
            ));
        }
        let tolerances = [self.cost_tolerance, self.step_tolerance];
        if tolerances.iter().any(|t| !t.is_finite() || *t < 0.0) {
            return Err(FitError::InvalidOptions(
                "tolerances must be finite and non-negative",
            ));
        }
        if !(self.initial_damping.is_finite() && self.initial_damping > 0.0) {
            return Err(FitError::InvalidOptions(
                "initial_damping must be finite and positive",
            ));
        }
        Ok(())
    }
}

/// One lobe `ρ · max(ĉ · l, 0)^n` (seed 001 eq. 1 with `C = ρ^{1/n} ĉ`).
/// Deserialising goes through [`Lobe::new`], so stored lobes keep the
/// bounds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RawLobe")]
pub struct Lobe {
    axis: [f64; 3],
    amplitude: f64,
    exponent: f64,
}

impl Lobe {
    /// A lobe; the axis is normalised, the exponent clamped to
    /// `[MIN_EXPONENT, MAX_EXPONENT]`.
    pub fn new(axis: [f64; 3], amplitude: f64, exponent: f64) -> Result<Self, FitError> {
        let axis =
            normalized(axis).ok_or(FitError::InvalidLobe("axis must be finite, non-zero"))?;
        if !(amplitude.is_finite() && (0.0..=MAX_AMPLITUDE).contains(&amplitude)) {
            return Err(FitError::InvalidLobe(
                "amplitude outside [0, MAX_AMPLITUDE]",
            ));
        }
        if exponent.is_nan() {
            return Err(FitError::InvalidLobe("exponent is NaN"));
        }
        Ok(Self {
            axis,
            amplitude,
            exponent: clamp_exponent(exponent, MAX_EXPONENT),
        })
    }

    /// Unit lobe axis `ĉ`.
    pub fn axis(&self) -> [f64; 3] {
        self.axis
    }

    /// Amplitude `ρ = |C|^n`: the lobe's value on its axis.
    pub fn amplitude(&self) -> f64 {
        self.amplitude
    }

    /// Exponent `n`.
    pub fn exponent(&self) -> f64 {
        self.exponent
    }

    /// `ρ · max(ĉ · l, 0)^n` for a unit light `l` (the fit functions
    /// normalise their lights; here `ĉ · l` is capped at 1); finite for
    /// every finite light.
    pub fn evaluate(&self, light: [f64; 3]) -> f64 {
        self.amplitude * power(dot(self.axis, light), self.exponent)
    }

    /// The paper's `(a, b, c, n)` with `(a, b, c) = ρ^{1/n} ĉ`.
    pub fn to_paper_coefficients(&self) -> [f64; 4] {
        let scale = if self.amplitude > 0.0 {
            (self.amplitude.ln() / self.exponent).exp()
        } else {
            0.0
        };
        [
            scale * self.axis[0],
            scale * self.axis[1],
            scale * self.axis[2],
            self.exponent,
        ]
    }

    /// From the paper's `(a, b, c, n)`. The amplitude `|C|^n` is computed
    /// in the log domain and clamped to [`MAX_AMPLITUDE`], the exponent to
    /// `[MIN_EXPONENT, MAX_EXPONENT]`; `C = 0` gives a zero lobe on the
    /// normal.
    pub fn from_paper_coefficients(abcn: [f64; 4]) -> Result<Self, FitError> {
        let [a, b, c, n] = abcn;
        if !abcn.iter().all(|x| x.is_finite()) {
            return Err(FitError::InvalidLobe("coefficients must be finite"));
        }
        let exponent = clamp_exponent(n, MAX_EXPONENT);
        let length = (a * a + b * b + c * c).sqrt();
        if length == 0.0 {
            return Self::new([0.0, 0.0, 1.0], 0.0, exponent);
        }
        let ln_amplitude = (exponent * length.ln()).min(MAX_AMPLITUDE.ln());
        Self::new([a, b, c], ln_amplitude.exp(), exponent)
    }

    fn zero() -> Self {
        Self {
            axis: [0.0, 0.0, 1.0],
            amplitude: 0.0,
            exponent: MIN_EXPONENT,
        }
    }

    /// Applies `[Δρ, u, v, Δη]`: the axis turns to `normalize(ĉ + u e₁ + v e₂)`
    /// with `(e₁, e₂)` = [`tangent_basis`] of the axis, `ln n` moves by `Δη`,
    /// and the result is clamped to `bounds`.
    fn retract(&self, step: &[f64], bounds: &Bounds) -> Self {
        let (e1, e2) = tangent_basis(self.axis);
        let (u, v) = (step[1], step[2]);
        let moved = [
            self.axis[0] + u * e1[0] + v * e2[0],
            self.axis[1] + u * e1[1] + v * e2[1],
            self.axis[2] + u * e1[2] + v * e2[2],
        ];
        let amplitude = self.amplitude + step[0];
        let amplitude = if amplitude.is_finite() {
            amplitude.clamp(0.0, bounds.max_amplitude)
        } else {
            self.amplitude
        };
        Self {
            axis: normalized(moved).unwrap_or(self.axis),
            amplitude,
            exponent: clamp_exponent((self.exponent.ln() + step[3]).exp(), bounds.max_exponent),
        }
    }
}

#[derive(Deserialize)]
struct RawLobe {
    axis: [f64; 3],
    amplitude: f64,
    exponent: f64,
}

impl TryFrom<RawLobe> for Lobe {
    type Error = FitError;
    fn try_from(raw: RawLobe) -> Result<Self, FitError> {
        Lobe::new(raw.axis, raw.amplitude, raw.exponent)
    }
}

/// `k` lobes of seed 001 equation (1) for one texel and view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RawLobeModel")]
pub struct LobeModel {
    lobes: Vec<Lobe>,
}

impl LobeModel {
    /// A model of `1..=MAX_LOBES` lobes.
    pub fn new(lobes: Vec<Lobe>) -> Result<Self, FitError> {
        if lobes.is_empty() || lobes.len() > MAX_LOBES {
            return Err(FitError::InvalidLobeCount(lobes.len()));
        }
        Ok(Self { lobes })
    }

    /// Number of lobes `k` (unused lobes have amplitude 0).
    pub fn k(&self) -> usize {
        self.lobes.len()
    }

    pub fn lobes(&self) -> &[Lobe] {
        &self.lobes
    }

    /// Model value for one light direction (unit vector, z = normal).
    pub fn evaluate(&self, light: [f64; 3]) -> f64 {
        self.lobes.iter().map(|lobe| lobe.evaluate(light)).sum()
    }

    /// `k · PARAMS_PER_LOBE`.
    pub fn parameter_count(&self) -> usize {
        self.lobes.len() * PARAMS_PER_LOBE
    }

    /// Analytic gradient of [`LobeModel::evaluate`] with respect to the
    /// fitted parameters, per lobe `[∂/∂ρ, ∂/∂u, ∂/∂v, ∂/∂ln n]`, where
    /// `(u, v)` turn the axis along [`tangent_basis`] (see
    /// [`LobeModel::retract`]). Every entry is finite.
    pub fn jacobian_row(&self, light: [f64; 3]) -> Vec<f64> {
        let mut row = vec![0.0; self.parameter_count()];
        let bases: Vec<_> = self.lobes.iter().map(|l| tangent_basis(l.axis)).collect();
        lobes_jacobian_row(&self.lobes, &bases, light, &mut row);
        row
    }

    /// The model moved by `step` (length [`LobeModel::parameter_count`],
    /// same order as [`LobeModel::jacobian_row`]), clamped to
    /// `[0, MAX_AMPLITUDE]` and `[MIN_EXPONENT, MAX_EXPONENT]`.
    pub fn retract(&self, step: &[f64]) -> Result<Self, FitError> {
        if step.len() != self.parameter_count() {
            return Err(FitError::LengthMismatch {
                expected: self.parameter_count(),
                got: step.len(),
            });
        }
        let bounds = Bounds {
            max_amplitude: MAX_AMPLITUDE,
            max_exponent: MAX_EXPONENT,
        };
        let lobes = self
            .lobes
            .iter()
            .zip(step.chunks_exact(PARAMS_PER_LOBE))
            .map(|(lobe, s)| lobe.retract(s, &bounds))
            .collect();
        Ok(Self { lobes })
    }

    /// `(a, b, c, n)` per lobe, as stored by the paper's renderer.
    pub fn to_paper_coefficients(&self) -> Vec<[f64; 4]> {
        self.lobes.iter().map(Lobe::to_paper_coefficients).collect()
    }
}

#[derive(Deserialize)]
struct RawLobeModel {
    lobes: Vec<Lobe>,
}

impl TryFrom<RawLobeModel> for LobeModel {
    type Error = FitError;
    fn try_from(raw: RawLobeModel) -> Result<Self, FitError> {
        LobeModel::new(raw.lobes)
    }
}

/// `(e₁, e₂)`: a deterministic orthonormal basis of the plane normal to
/// `axis` (a unit vector). The helper vector switches away from the normal
/// near the pole so the basis never degenerates.
pub fn tangent_basis(axis: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    let helper = if axis[2].abs() < 0.9 {
        [0.0, 0.0, 1.0]
    } else {
        [1.0, 0.0, 0.0]
    };
    let e1 = normalized(cross(helper, axis)).unwrap_or([1.0, 0.0, 0.0]);
    let e2 = cross(axis, e1);
    (e1, e2)
}

/// Why a texel was not fitted with the full model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Fallback {
    /// No positive value: every lobe has amplitude 0 (the best non-negative
    /// fit), no iteration is run.
    Dark,
    /// Fewer lights than one lobe's parameters: a Lambertian lobe (axis =
    /// normal, `n = 1`) with a least-squares amplitude.
    DiffuseOnly,
    /// Fewer lights than `k · PARAMS_PER_LOBE`: only `lights /
    /// PARAMS_PER_LOBE` lobes are fitted, the others have amplitude 0.
    ReducedLobes { active: usize },
}

/// Result of one texel's fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TexelFit {
    /// Always `k` lobes; lobes not fitted have amplitude 0.
    pub model: LobeModel,
    /// RMS over lights of model − value, in input units.
    pub rms_error: f64,
    /// Mean over lights of |model − value|, in input units.
    pub mean_abs_error: f64,
    /// RMS error of the principal-direction initialisation.
    pub initial_rms_error: f64,
    /// LM iterations (linear solves) run, including those refining the
    /// first lobes during the initialisation.
    pub iterations: usize,
    /// True when LM stopped on a tolerance or could not lower the cost any
    /// further (and for the closed-form `Dark` and `DiffuseOnly`
    /// fallbacks), false when it ran out of iterations.
    pub converged: bool,
    /// Lobes that were fitted (0 for a dark texel); the rest of the `k`
    /// lobes are zero.
    pub active_lobes: usize,
    pub fallback: Option<Fallback>,
}

/// Results for all texels of one view slot, texel-major.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlotFit {
    pub k: usize,
    pub texels: Vec<TexelFit>,
}

impl SlotFit {
    /// Mean over texels and lights of |model − value|.
    pub fn mean_abs_error(&self) -> f64 {
        mean(self.texels.iter().map(|t| t.mean_abs_error))
    }

    /// RMS over texels and lights of model − value.
    pub fn rms_error(&self) -> f64 {
        mean(self.texels.iter().map(|t| t.rms_error * t.rms_error)).sqrt()
    }

    pub fn converged_texels(&self) -> usize {
        self.texels.iter().filter(|t| t.converged).count()
    }
}

/// Fits seed 001 equation (1) with `k` lobes to one texel by
/// Levenberg–Marquardt from a principal-direction initialisation.
///
/// `lights` are directions in the sample frame (z = normal; normalised
/// here), `values` one luminance per light.
pub fn fit_texel(
    lights: &[[f64; 3]],
    values: &[f32],
    k: usize,
    opts: &FitOptions,
) -> Result<TexelFit, FitError> {
    let lights = unit_lights(lights)?;
    check_values(values, lights.len())?;
    check_k(k)?;
    opts.validate()?;
    Ok(fit_checked(&lights, values, k, opts))
}

/// [`fit_texel`] for every texel of a view slot in parallel. `values` is
/// texel-major: texel `t`'s value under light `j` is `values[t · lights + j]`.
pub fn fit_slot(
    lights: &[[f64; 3]],
    values: &[f32],
    k: usize,
    opts: &FitOptions,
) -> Result<SlotFit, FitError> {
    let lights = unit_lights(lights)?;
    check_slot_values(values, lights.len())?;
    check_k(k)?;
    opts.validate()?;
    let texels = values
        .par_chunks_exact(lights.len())
        .map(|texel| fit_checked(&lights, texel, k, opts))
        .collect();
    Ok(SlotFit { k, texels })
}

/// The principal-direction initialisation [`fit_texel`] starts from (with
/// its fallbacks), for inspection and tests.
pub fn initial_model(
    lights: &[[f64; 3]],
    values: &[f32],
    k: usize,
    opts: &FitOptions,
) -> Result<LobeModel, FitError> {
    let lights = unit_lights(lights)?;
    check_values(values, lights.len())?;
    check_k(k)?;
    opts.validate()?;
    let values: Vec<f64> = values.iter().map(|&v| f64::from(v)).collect();
    let plan = plan_texel(&lights, &values, k, opts);
    Ok(LobeModel {
        lobes: padded(plan.lobes, k),
    })
}

/// A luminance fit plus the per-texel colour: reconstruct RGB as
/// `colour_scale · model`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RgbTexelFit {
    pub luminance: TexelFit,
    pub colour_scale: [f64; 3],
}

/// Luminance of a linear RGB value ([`LUMINANCE_WEIGHTS`]).
pub fn luminance(rgb: [f32; 3]) -> f32 {
    (0..3)
        .map(|c| LUMINANCE_WEIGHTS[c] * f64::from(rgb[c]))
        .sum::<f64>() as f32
}

/// Per-texel colour `Σ rgb / Σ luminance` over the lights: the average
/// colour normalised to unit luminance, so `colour_scale · L` has
/// luminance `L` (the paper's "average color", §5.3). Grey when the texel
/// is dark.
pub fn colour_scale(rgb: &[[f32; 3]]) -> [f64; 3] {
    let mut sum = [0.0f64; 3];
    for value in rgb {
        for c in 0..3 {
            sum[c] += f64::from(value[c]);
        }
    }
    let total: f64 = (0..3).map(|c| LUMINANCE_WEIGHTS[c] * sum[c]).sum();
    if total > 0.0 && total.is_finite() {
        sum.map(|s| s / total)
    } else {
        [1.0; 3]
    }
}

/// Fits the luminance of linear RGB values and the per-texel colour scale.
pub fn fit_texel_rgb(
    lights: &[[f64; 3]],
    rgb: &[[f32; 3]],
    k: usize,
    opts: &FitOptions,
) -> Result<RgbTexelFit, FitError> {
    let values: Vec<f32> = rgb.iter().map(|&c| luminance(c)).collect();
    let luminance = fit_texel(lights, &values, k, opts)?;
    Ok(RgbTexelFit {
        luminance,
        colour_scale: colour_scale(rgb),
    })
}

// ---------------------------------------------------------------------------
// PTM

/// Biquadratic PTM coefficients `[a0..a5]` of
/// `L(lu, lv) = a0 lu² + a1 lv² + a2 lu lv + a3 lu + a4 lv + a5`, where
/// `(lu, lv)` are the x, y components of the unit light direction.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PtmFit {
    pub coefficients: [f64; PTM_COEFFICIENTS],
    /// RMS over lights of model − value, in input units.
    pub rms_error: f64,
    /// Mean over lights of |model − value|.
    pub mean_abs_error: f64,
}

impl PtmFit {
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

    pub fn lights(&self) -> &[[f64; 3]] {
        &self.lights
    }

    pub fn fit(&self, values: &[f32]) -> Result<PtmFit, FitError> {
        check_values(values, self.lights.len())?;
        Ok(self.fit_checked(values))
    }

    fn fit_checked(&self, values: &[f32]) -> PtmFit {
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
    pub texels: Vec<PtmFit>,
}

impl PtmSlotFit {
    pub fn mean_abs_error(&self) -> f64 {
        mean(self.texels.iter().map(|t| t.mean_abs_error))
    }

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

fn ptm_row(light: [f64; 3]) -> [f64; PTM_COEFFICIENTS] {
    let (u, v) = (light[0], light[1]);
    [u * u, v * v, u * v, u, v, 1.0]
}

// ---------------------------------------------------------------------------
// Error table (seed 001 Table 1)

/// A row label of the error table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum FitMethod {
    Ptm,
    Lobes(usize),
}

impl fmt::Display for FitMethod {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FitMethod::Ptm => write!(f, "PTM"),
            FitMethod::Lobes(k) => write!(f, "non-linear K={k}"),
        }
    }
}

/// One row of seed 001 Table 1 for one view slot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorRow {
    pub method: FitMethod,
    /// Mean over texels and lights of |model − value|, input units: the
    /// paper's "average luminance difference between data and model" (the
    /// paper does not define it further; we read "average difference" as
    /// the mean absolute difference).
    pub mean_abs_error: f64,
    /// RMS over texels and lights of model − value, input units.
    pub rms_error: f64,
    /// Wall time of the whole slot fit on the rayon pool.
    pub fit_time: Duration,
    /// Texels whose LM converged (all of them for PTM).
    pub converged_texels: usize,
}

/// Seed 001 Table 1 for one view slot: one row per method.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorTable {
    pub texels: usize,
    pub lights: usize,
    pub threads: usize,
    pub rows: Vec<ErrorRow>,
}

impl fmt::Display for ErrorTable {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "{} texels x {} lights, {} threads",
            self.texels, self.lights, self.threads
        )?;
        writeln!(
            f,
            "{:<16} {:>12} {:>12} {:>12} {:>10}",
            "method", "mean |err|", "rms err", "fit time ms", "converged"
        )?;
        for row in &self.rows {
            writeln!(
                f,
                "{:<16} {:>12.6} {:>12.6} {:>12.1} {:>10}",
                row.method.to_string(),
                row.mean_abs_error,
                row.rms_error,
                row.fit_time.as_secs_f64() * 1e3,
                row.converged_texels
            )?;
        }
        Ok(())
    }
}

/// Fits a view slot with PTM and with each `k` in `ks` and tabulates the
/// average luminance errors and fit times (seed 001 Table 1; its
/// "Lafortune (2 lobes)" column fits one model to all views and is not a
/// per-slot method, so it has no row here).
pub fn error_table(
    lights: &[[f64; 3]],
    values: &[f32],
    ks: &[usize],
    opts: &FitOptions,
) -> Result<ErrorTable, FitError> {
    let unit = unit_lights(lights)?;
    check_slot_values(values, unit.len())?;
    let texels = values.len() / unit.len();
    let mut rows = Vec::with_capacity(ks.len() + 1);
    let start = Instant::now();
    let ptm = fit_ptm_slot(&unit, values)?;
    rows.push(ErrorRow {
        method: FitMethod::Ptm,
        mean_abs_error: ptm.mean_abs_error(),
        rms_error: ptm.rms_error(),
        fit_time: start.elapsed(),
        converged_texels: texels,
    });
    for &k in ks {
        let start = Instant::now();
        let fit = fit_slot(&unit, values, k, opts)?;
        rows.push(ErrorRow {
            method: FitMethod::Lobes(k),
            mean_abs_error: fit.mean_abs_error(),
            rms_error: fit.rms_error(),
            fit_time: start.elapsed(),
            converged_texels: fit.converged_texels(),
        });
    }
    Ok(ErrorTable {
        texels,
        lights: unit.len(),
        threads: rayon::current_num_threads(),
        rows,
    })
}

// ---------------------------------------------------------------------------
// Fitting

#[derive(Debug, Clone, Copy)]
struct Bounds {
    max_amplitude: f64,
    max_exponent: f64,
}

struct TexelPlan {
    lobes: Vec<Lobe>,
    /// LM iterations spent refining the first lobes during initialisation.
    iterations: usize,
    fallback: Option<Fallback>,
    bounds: Bounds,
}

/// Fallbacks and principal-direction initialisation for one texel.
fn plan_texel(lights: &[[f64; 3]], values: &[f64], k: usize, opts: &FitOptions) -> TexelPlan {
    let peak = values.iter().fold(0.0f64, |acc, &v| acc.max(v));
    let bounds = Bounds {
        max_amplitude: (opts.max_amplitude_ratio * peak).min(MAX_AMPLITUDE),
        max_exponent: opts.max_exponent,
    };
    if peak <= 0.0 {
        return TexelPlan {
            lobes: Vec::new(),
            iterations: 0,
            fallback: Some(Fallback::Dark),
            bounds,
        };
    }
    let active = k.min(lights.len() / PARAMS_PER_LOBE);
    if active == 0 {
        let mut lobes = vec![Lobe::zero()];
        fit_amplitudes(lights, values, &mut lobes, &bounds);
        return TexelPlan {
            lobes,
            iterations: 0,
            fallback: Some(Fallback::DiffuseOnly),
            bounds,
        };
    }
    let (lobes, iterations) = principal_direction_lobes(lights, values, active, &bounds, opts);
    TexelPlan {
        lobes,
        iterations,
        fallback: (active < k).then_some(Fallback::ReducedLobes { active }),
        bounds,
    }
}

/// Lights within this angle of a residual peak take part in estimating
/// the peak's lobe (wide enough to reach the next ring of a 15° sampling).
const NEIGHBOUR_COS: f64 = 0.906; // cos 25°

/// Initial lobes from principal directions (seed 001 §4.2: "detecting
/// principal directions with a high-pass filter").
///
/// Lobe 1 is the low-pass part: its axis is the value-weighted mean light
/// direction (first moment of the reflected energy; unlike the dominant
/// eigenvector of the second moment it has no sign ambiguity) and its
/// exponent comes from the weighted mean cosine, `E[cos] = (n+1)/(n+2)` for
/// a `cos^n` lobe under lights spread evenly over the hemisphere. The lobes
/// so far are then refined by LM, and the next lobe sits at the peak of the
/// high-pass residual (data minus those lobes): its axis is the peak light
/// or the residual-weighted mean of the peak's neighbours, its exponent the
/// neighbours' falloff or one of a ladder, whichever fits best with
/// non-negative least-squares amplitudes. Returns the lobes and the LM
/// iterations spent.
fn principal_direction_lobes(
    lights: &[[f64; 3]],
    values: &[f64],
    count: usize,
    bounds: &Bounds,
    opts: &FitOptions,
) -> (Vec<Lobe>, usize) {
    let broad_limit = bounds.max_exponent.min(1.0e3);
    let mut total = 0.0;
    let mut moment = [0.0; 3];
    for (light, &v) in lights.iter().zip(values) {
        let w = v.max(0.0);
        total += w;
        moment = add_scaled(moment, *light, w);
    }
    let axis = normalized(moment).unwrap_or([0.0, 0.0, 1.0]);
    let mean_cos = lights
        .iter()
        .zip(values)
        .map(|(l, &v)| v.max(0.0) * dot(axis, *l).max(0.0))
        .sum::<f64>()
        / total;
    let exponent = clamp_exponent((2.0 * mean_cos - 1.0) / (1.0 - mean_cos), broad_limit);
    let mut lobes = vec![Lobe {
        axis,
        amplitude: 0.0,
        exponent,
    }];
    fit_amplitudes(lights, values, &mut lobes, bounds);

    // Each stage's lobes are fitted before the next peak is sought, so the
    // high-pass residual is measured against the best low-pass model, not
    // against the moment estimate (whose misfit at grazing lights would
    // otherwise outshine a specular peak).
    let stage_opts = FitOptions {
        max_iterations: opts.max_iterations / 2,
        ..*opts
    };
    let mut iterations = 0;
    while lobes.len() < count {
        iterations += levenberg_marquardt(lights, values, &mut lobes, bounds, &stage_opts).0;
        let residual: Vec<f64> = lights
            .iter()
            .zip(values)
            .map(|(l, v)| v - lobes.iter().map(|lobe| lobe.evaluate(*l)).sum::<f64>())
            .collect();
        let (peak_index, peak) =
            residual
                .iter()
                .copied()
                .enumerate()
                .fold((0, f64::NEG_INFINITY), |best, (i, r)| {
                    if r > best.1 {
                        (i, r)
                    } else {
                        best
                    }
                });
        let scale = values.iter().fold(0.0f64, |acc, v| acc.max(v.abs()));
        if peak <= 1e-9 * scale {
            // Nothing left to explain: an idle lobe LM may still pick up.
            lobes.push(Lobe {
                axis: lobes[0].axis,
                amplitude: 0.0,
                exponent: MIN_EXPONENT,
            });
            continue;
        }
        let peak_light = lights[peak_index];
        let mut weighted = [0.0; 3];
        for (light, &r) in lights.iter().zip(&residual) {
            if r > 0.0 && dot(*light, peak_light) >= NEIGHBOUR_COS {
                weighted = add_scaled(weighted, *light, r);
            }
        }
        let axis = normalized(weighted).unwrap_or(peak_light);
        // Geometric mean of the exponents implied by each neighbour's
        // falloff r_j / r_peak = cos(angle)^n.
        let mut log_sum = 0.0;
        let mut count_estimates = 0usize;
        let mut nearest_cos = -1.0f64;
        for (j, (light, &r)) in lights.iter().zip(&residual).enumerate() {
            let c = dot(*light, peak_light);
            if j == peak_index || c >= 1.0 - 1e-12 {
                continue;
            }
            nearest_cos = nearest_cos.max(c);
            if c >= NEIGHBOUR_COS && r > 0.0 && r < peak {
                let n = (r / peak).ln() / c.ln();
                if n.is_finite() && n > 0.0 {
                    log_sum += n.ln();
                    count_estimates += 1;
                }
            }
        }
        // Sharper than a lobe that is down to 1 % at the nearest light, a
        // lobe sees one light only; LM cannot widen it again (its gradient
        // in n vanishes), so the start is never sharper than that.
        let sharpest = if nearest_cos > 0.0 {
            100f64.ln() / -nearest_cos.ln()
        } else {
            MIN_EXPONENT
        };
        let mut exponents = vec![sharpest];
        if count_estimates > 0 {
            exponents.push((log_sum / count_estimates as f64).exp().min(sharpest));
        }
        // The falloff estimate is fooled when the low-pass misfit around the
        // peak is as large as the peak itself: also try a fixed ladder and
        // keep whichever (axis, exponent) fits best after the amplitudes.
        exponents.extend(EXPONENT_LADDER.iter().filter(|&&n| n < sharpest));
        let mut best: Option<(f64, Vec<Lobe>)> = None;
        for candidate_axis in [axis, peak_light] {
            for &exponent in &exponents {
                let mut candidate = lobes.clone();
                candidate.push(Lobe {
                    axis: candidate_axis,
                    amplitude: 0.0,
                    exponent: clamp_exponent(exponent, bounds.max_exponent),
                });
                fit_amplitudes(lights, values, &mut candidate, bounds);
                let cost = cost_of(lights, values, &candidate);
                if best.as_ref().is_none_or(|(best_cost, _)| cost < *best_cost) {
                    best = Some((cost, candidate));
                }
            }
        }
        if let Some((_, candidate)) = best {
            lobes = candidate;
        }
    }
    (lobes, iterations)
}

/// Exponents tried for each new lobe of the initialisation.
const EXPONENT_LADDER: [f64; 6] = [2.0, 5.0, 10.0, 20.0, 50.0, 100.0];

/// Non-negative least squares for the amplitudes with axes and exponents
/// fixed, by cyclic coordinate descent (a convex problem of ≤ MAX_LOBES
/// unknowns).
fn fit_amplitudes(lights: &[[f64; 3]], values: &[f64], lobes: &mut [Lobe], bounds: &Bounds) {
    let k = lobes.len();
    let shapes: Vec<Vec<f64>> = lobes
        .iter()
        .map(|lobe| {
            lights
                .iter()
                .map(|l| power(dot(lobe.axis, *l), lobe.exponent))
                .collect()
        })
        .collect();
    let mut gram = vec![0.0; k * k];
    let mut rhs = vec![0.0; k];
    for i in 0..k {
        rhs[i] = shapes[i].iter().zip(values).map(|(s, v)| s * v).sum();
        for j in 0..k {
            gram[i * k + j] = shapes[i].iter().zip(&shapes[j]).map(|(a, b)| a * b).sum();
        }
    }
    for lobe in lobes.iter_mut() {
        lobe.amplitude = 0.0;
    }
    for _ in 0..100 {
        let mut change = 0.0f64;
        for i in 0..k {
            if gram[i * k + i] <= 0.0 {
                continue;
            }
            let others: f64 = (0..k)
                .filter(|&j| j != i)
                .map(|j| gram[i * k + j] * lobes[j].amplitude)
                .sum();
            let updated = ((rhs[i] - others) / gram[i * k + i]).clamp(0.0, bounds.max_amplitude);
            if updated.is_finite() {
                change = change.max((updated - lobes[i].amplitude).abs());
                lobes[i].amplitude = updated;
            }
        }
        if change <= 1e-14 * bounds.max_amplitude {
            break;
        }
    }
}

fn fit_checked(lights: &[[f64; 3]], values: &[f32], k: usize, opts: &FitOptions) -> TexelFit {
    let values: Vec<f64> = values.iter().map(|&v| f64::from(v)).collect();
    let plan = plan_texel(lights, &values, k, opts);
    let mut lobes = plan.lobes;
    let initial_rms_error = errors64(lights, &values, &lobes).0;
    let (iterations, converged) = match plan.fallback {
        Some(Fallback::Dark) | Some(Fallback::DiffuseOnly) => (0, true),
        _ => levenberg_marquardt(lights, &values, &mut lobes, &plan.bounds, opts),
    };
    let iterations = iterations + plan.iterations;
    let (rms_error, mean_abs_error) = errors64(lights, &values, &lobes);
    let active_lobes = lobes.len();
    TexelFit {
        model: LobeModel {
            lobes: padded(lobes, k),
        },
        rms_error,
        mean_abs_error,
        initial_rms_error,
        iterations,
        converged,
        active_lobes,
        fallback: plan.fallback,
    }
}

/// Minimises `½ Σ (model − value)²` over all lobe parameters. Damping
/// follows Marquardt (scaled by diag JᵀJ) with Nielsen's update; only
/// steps that lower the cost are taken, so the result is never worse than
/// the start. Axes move on the sphere: each step is expressed in the
/// tangent basis of the current axis, which is re-centred after every
/// accepted step, so the poles need no special case.
fn levenberg_marquardt(
    lights: &[[f64; 3]],
    values: &[f64],
    lobes: &mut Vec<Lobe>,
    bounds: &Bounds,
    opts: &FitOptions,
) -> (usize, bool) {
    let m = lights.len();
    let p = lobes.len() * PARAMS_PER_LOBE;
    let scale = values.iter().fold(0.0f64, |acc, v| acc.max(v.abs()));
    // The values are f32 (relative precision 6e-8): once the RMS residual is
    // a few f32 ulps of the largest value, further steps only fit rounding.
    let cost_floor = 0.5 * m as f64 * (4.0 * f64::from(f32::EPSILON) * scale).powi(2);
    let mut jac = vec![0.0; m * p];
    let mut residual = vec![0.0; m];
    let mut normal = vec![0.0; p * p];
    let mut gradient = vec![0.0; p];
    let mut system = vec![0.0; p * p];
    let mut step = vec![0.0; p];

    let mut cost = linearise(lights, values, lobes, &mut jac, &mut residual);
    normal_equations(&jac, &residual, p, &mut normal, &mut gradient);
    let max_diag = (0..p).map(|i| normal[i * p + i]).fold(0.0f64, f64::max);
    let mut damping = opts.initial_damping * if max_diag > 0.0 { max_diag } else { 1.0 };
    let mut growth = 2.0;

    for iteration in 1..=opts.max_iterations {
        if cost <= cost_floor {
            return (iteration - 1, true);
        }
        let max_diag = (0..p).map(|i| normal[i * p + i]).fold(0.0f64, f64::max);
        let diag_floor = 1e-12 * max_diag + f64::MIN_POSITIVE;
        system.copy_from_slice(&normal);
        for i in 0..p {
            system[i * p + i] += damping * normal[i * p + i].max(diag_floor);
            step[i] = -gradient[i];
        }
        pin_active_bounds(lobes, &gradient, bounds, &mut system, &mut step);
        if !cholesky_solve(&mut system, p, &mut step) {
            damping *= growth;
            growth *= 2.0;
            continue;
        }
        // Predicted decrease of the linear model: ½ δᵀ(λDδ − g).
        let predicted: f64 = (0..p)
            .map(|i| {
                0.5 * step[i]
                    * (damping * normal[i * p + i].max(diag_floor) * step[i] - gradient[i])
            })
            .sum();
        let trial: Vec<Lobe> = lobes
            .iter()
            .zip(step.chunks_exact(PARAMS_PER_LOBE))
            .map(|(lobe, s)| lobe.retract(s, bounds))
            .collect();
        let trial_cost = cost_of(lights, values, &trial);
        let actual = cost - trial_cost;
        if actual > 0.0 && trial_cost.is_finite() {
            let gain = if predicted > 0.0 {
                actual / predicted
            } else {
                1.0
            };
            damping *= (1.0 - (2.0 * gain - 1.0).powi(3)).max(1.0 / 3.0);
            growth = 2.0;
            let moved = largest_move(&step, scale);
            *lobes = trial;
            let previous = cost;
            cost = linearise(lights, values, lobes, &mut jac, &mut residual);
            normal_equations(&jac, &residual, p, &mut normal, &mut gradient);
            let small_decrease = actual <= opts.cost_tolerance * previous
                && predicted <= opts.cost_tolerance * previous;
            if small_decrease || moved <= opts.step_tolerance {
                return (iteration, true);
            }
        } else {
            damping *= growth;
            growth *= 2.0;
            // Damping this large means no step lowers the cost at f64
            // precision: a (possibly bound-constrained) minimum.
            if damping > 1e16 * (max_diag + f64::MIN_POSITIVE) || !damping.is_finite() {
                return (iteration, true);
            }
        }
    }
    (opts.max_iterations, false)
}

/// Projected LM: a parameter sitting on a bound whose descent direction
/// points out of the box is held fixed for this solve, so the clamp cannot
/// swallow the whole step (the other parameters still move).
fn pin_active_bounds(
    lobes: &[Lobe],
    gradient: &[f64],
    bounds: &Bounds,
    system: &mut [f64],
    rhs: &mut [f64],
) {
    let p = rhs.len();
    for (index, lobe) in lobes.iter().enumerate() {
        let amplitude = index * PARAMS_PER_LOBE;
        let exponent = amplitude + 3;
        let pin_amplitude = (lobe.amplitude <= 0.0 && gradient[amplitude] > 0.0)
            || (lobe.amplitude >= bounds.max_amplitude && gradient[amplitude] < 0.0);
        let pin_exponent = (lobe.exponent <= MIN_EXPONENT && gradient[exponent] > 0.0)
            || (lobe.exponent >= bounds.max_exponent && gradient[exponent] < 0.0);
        for (pinned, i) in [(pin_amplitude, amplitude), (pin_exponent, exponent)] {
            if pinned {
                for j in 0..p {
                    system[i * p + j] = 0.0;
                    system[j * p + i] = 0.0;
                }
                system[i * p + i] = 1.0;
                rhs[i] = 0.0;
            }
        }
    }
}

/// Largest parameter change of a step: amplitudes relative to the data
/// scale, angles and `ln n` as they are.
fn largest_move(step: &[f64], scale: f64) -> f64 {
    step.chunks_exact(PARAMS_PER_LOBE)
        .map(|s| {
            let amplitude = if scale > 0.0 {
                s[0].abs() / scale
            } else {
                s[0].abs()
            };
            amplitude.max(s[1].abs()).max(s[2].abs()).max(s[3].abs())
        })
        .fold(0.0, f64::max)
}

/// Fills the Jacobian (row-major lights × params) and residuals
/// (model − value); returns the cost ½ Σ r².
fn linearise(
    lights: &[[f64; 3]],
    values: &[f64],
    lobes: &[Lobe],
    jac: &mut [f64],
    residual: &mut [f64],
) -> f64 {
    let p = lobes.len() * PARAMS_PER_LOBE;
    let bases: Vec<_> = lobes.iter().map(|l| tangent_basis(l.axis)).collect();
    let mut cost = 0.0;
    for (j, (light, value)) in lights.iter().zip(values).enumerate() {
        let model = lobes_jacobian_row(lobes, &bases, *light, &mut jac[j * p..(j + 1) * p]);
        let r = model - value;
        residual[j] = r;
        cost += 0.5 * r * r;
    }
    cost
}

/// `∂s/∂ρ = cos^n`, `∂s/∂u = ρ n cos^{n-1} (e₁·l)`, `∂s/∂v` likewise with
/// e₂, `∂s/∂ln n = ρ cos^n · n ln cos`; 0 where `cos ≤ 0`. All bounded:
/// `cos^{n-1} ≤ 1` as `n ≥ 1`, and `|x eˣ| ≤ 1/e` for `x = n ln cos ≤ 0`.
/// `bases` holds each lobe's [`tangent_basis`]. Returns the model value.
fn lobes_jacobian_row(
    lobes: &[Lobe],
    bases: &[([f64; 3], [f64; 3])],
    light: [f64; 3],
    row: &mut [f64],
) -> f64 {
    let mut model = 0.0;
    for ((lobe, (e1, e2)), out) in lobes
        .iter()
        .zip(bases)
        .zip(row.chunks_exact_mut(PARAMS_PER_LOBE))
    {
        let c = dot(lobe.axis, light).min(1.0);
        if c <= 0.0 {
            out.fill(0.0);
            continue;
        }
        let n = lobe.exponent;
        let ln_c = c.ln();
        let shape = (n * ln_c).exp();
        // cos^{n-1} = cos^n / cos, at most 1 for n ≥ 1 (saves an exp).
        let slope = lobe.amplitude * n * (shape / c).min(1.0);
        model += lobe.amplitude * shape;
        out[0] = shape;
        out[1] = slope * dot(*e1, light);
        out[2] = slope * dot(*e2, light);
        out[3] = lobe.amplitude * shape * n * ln_c;
    }
    model
}

fn normal_equations(
    jac: &[f64],
    residual: &[f64],
    p: usize,
    normal: &mut [f64],
    gradient: &mut [f64],
) {
    normal.fill(0.0);
    gradient.fill(0.0);
    for (row, r) in jac.chunks_exact(p).zip(residual) {
        for i in 0..p {
            gradient[i] += row[i] * r;
            for j in 0..=i {
                normal[i * p + j] += row[i] * row[j];
            }
        }
    }
    for i in 0..p {
        for j in 0..i {
            normal[j * p + i] = normal[i * p + j];
        }
    }
}

/// Solves `a x = b` in place for symmetric positive definite `a` (p × p,
/// row-major); false if `a` is not numerically positive definite.
fn cholesky_solve(a: &mut [f64], p: usize, b: &mut [f64]) -> bool {
    for j in 0..p {
        let mut d = a[j * p + j];
        for k in 0..j {
            d -= a[j * p + k] * a[j * p + k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return false;
        }
        let d = d.sqrt();
        a[j * p + j] = d;
        for i in j + 1..p {
            let mut s = a[i * p + j];
            for k in 0..j {
                s -= a[i * p + k] * a[j * p + k];
            }
            a[i * p + j] = s / d;
        }
    }
    for i in 0..p {
        let mut s = b[i];
        for k in 0..i {
            s -= a[i * p + k] * b[k];
        }
        b[i] = s / a[i * p + i];
    }
    for i in (0..p).rev() {
        let mut s = b[i];
        for k in i + 1..p {
            s -= a[k * p + i] * b[k];
        }
        b[i] = s / a[i * p + i];
    }
    b.iter().all(|x| x.is_finite())
}

fn cost_of(lights: &[[f64; 3]], values: &[f64], lobes: &[Lobe]) -> f64 {
    lights
        .iter()
        .zip(values)
        .map(|(l, v)| {
            let r = lobes.iter().map(|lobe| lobe.evaluate(*l)).sum::<f64>() - v;
            0.5 * r * r
        })
        .sum()
}

/// (RMS, mean absolute) error of lobes against f64 values.
fn errors64(lights: &[[f64; 3]], values: &[f64], lobes: &[Lobe]) -> (f64, f64) {
    let mut sum_sq = 0.0;
    let mut sum_abs = 0.0;
    for (l, v) in lights.iter().zip(values) {
        let r = lobes.iter().map(|lobe| lobe.evaluate(*l)).sum::<f64>() - v;
        sum_sq += r * r;
        sum_abs += r.abs();
    }
    let m = lights.len().max(1) as f64;
    ((sum_sq / m).sqrt(), sum_abs / m)
}

/// (RMS, mean absolute) error of any model against f32 values.
fn errors(lights: &[[f64; 3]], values: &[f32], model: impl Fn([f64; 3]) -> f64) -> (f64, f64) {
    let mut sum_sq = 0.0;
    let mut sum_abs = 0.0;
    for (l, &v) in lights.iter().zip(values) {
        let r = model(*l) - f64::from(v);
        sum_sq += r * r;
        sum_abs += r.abs();
    }
    let m = lights.len().max(1) as f64;
    ((sum_sq / m).sqrt(), sum_abs / m)
}

// ---------------------------------------------------------------------------
// Small helpers

/// `max(c, 0)^n` as `exp(n ln c)`: in `[0, 1]` for every `n ≥ 0`, so it
/// cannot overflow; tiny results underflow harmlessly to 0.
fn power(c: f64, n: f64) -> f64 {
    if c > 0.0 {
        (n * c.min(1.0).ln()).exp()
    } else {
        0.0
    }
}

fn clamp_exponent(n: f64, max_exponent: f64) -> f64 {
    if n.is_nan() {
        MIN_EXPONENT
    } else {
        n.clamp(MIN_EXPONENT, max_exponent)
    }
}

fn padded(mut lobes: Vec<Lobe>, k: usize) -> Vec<Lobe> {
    lobes.truncate(k);
    while lobes.len() < k {
        lobes.push(Lobe::zero());
    }
    lobes
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, count) = values.fold((0.0, 0usize), |(s, c), v| (s + v, c + 1));
    if count == 0 {
        0.0
    } else {
        sum / count as f64
    }
}

fn unit_lights(lights: &[[f64; 3]]) -> Result<Vec<[f64; 3]>, FitError> {
    if lights.is_empty() {
        return Err(FitError::NoLights);
    }
    lights
        .iter()
        .enumerate()
        .map(|(index, &direction)| {
            normalized(direction).ok_or(FitError::InvalidLight { index, direction })
        })
        .collect()
}

fn check_values(values: &[f32], lights: usize) -> Result<(), FitError> {
    if values.len() != lights {
        return Err(FitError::LengthMismatch {
            expected: lights,
            got: values.len(),
        });
    }
    check_finite(values)
}

fn check_slot_values(values: &[f32], lights: usize) -> Result<(), FitError> {
    // Not `is_multiple_of`: the workspace still builds on Rust 1.85.
    if (values.len() / lights) * lights != values.len() {
        return Err(FitError::LengthMismatch {
            expected: (values.len() / lights + 1) * lights,
            got: values.len(),
        });
    }
    check_finite(values)
}

fn check_finite(values: &[f32]) -> Result<(), FitError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(FitError::NonFiniteValue {
            index,
            value: values[index],
        }),
        None => Ok(()),
    }
}

fn check_k(k: usize) -> Result<(), FitError> {
    if (1..=MAX_LOBES).contains(&k) {
        Ok(())
    } else {
        Err(FitError::InvalidLobeCount(k))
    }
}

fn add_scaled(a: [f64; 3], b: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}

/// The unit vector along `v`, or None if `v` is zero or not finite.
fn normalized(v: [f64; 3]) -> Option<[f64; 3]> {
    if !v.iter().all(|x| x.is_finite()) {
        return None;
    }
    // Scale first so huge or tiny components neither overflow nor vanish.
    let largest = v.iter().fold(0.0f64, |acc, x| acc.max(x.abs()));
    if largest == 0.0 {
        return None;
    }
    let s = v.map(|x| x / largest);
    let length = dot(s, s).sqrt();
    Some(s.map(|x| x / length))
}
