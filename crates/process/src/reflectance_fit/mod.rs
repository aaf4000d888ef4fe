//! Per view reflectance-field fit of Meseth et al. (Meseth, Müller, Klein,
//! "Preserving Realism in real-time Rendering of BTFs", §4.2), and the
//! polynomial texture map (PTM, Malzbender et al. 2001) it is compared with.
//!
//! For one view slot `v` and one texel `x` the measured reflectance field
//! `RF_v(x, l)` (one value per light direction `l`) is approximated by
//! Meseth et al. equation (1):
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
//! # Reparametrisation (Meseth et al., §7: overflows with high exponents)
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
//! # Error measure (Meseth et al. Table 1)
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
    /// The light list is empty.
    #[error("no light directions")]
    NoLights,
    /// A light direction is zero or not finite.
    #[error("light {index} is not a finite non-zero vector: {direction:?}")]
    InvalidLight {
        /// Index of the light.
        index: usize,
        /// The direction as given.
        direction: [f64; 3],
    },
    /// The values (or an LM step) do not have the length the lights (or the
    /// model's parameters) need; for a slot, they are not a whole number of
    /// texels.
    #[error("expected {expected} values, got {got}")]
    LengthMismatch {
        /// The length needed (for a slot, the next whole number of texels).
        expected: usize,
        /// The length given.
        got: usize,
    },
    /// A measured value is NaN or infinite.
    #[error("value {index} is not finite ({value})")]
    NonFiniteValue {
        /// Index of the value.
        index: usize,
        /// The value.
        value: f32,
    },
    /// A lobe count outside 1 ..= [`MAX_LOBES`].
    #[error("lobe count {0} outside 1..={MAX_LOBES}")]
    InvalidLobeCount(usize),
    /// A [`FitOptions`] field is out of range; the text says which.
    #[error("invalid fit option: {0}")]
    InvalidOptions(&'static str),
    /// [`Lobe::new`] or [`Lobe::from_paper_coefficients`] got a zero or
    /// non-finite axis, an amplitude outside `[0, MAX_AMPLITUDE]`, a NaN
    /// exponent or non-finite coefficients; the text says which.
    #[error("invalid lobe: {0}")]
    InvalidLobe(&'static str),
    /// The SVD of the PTM design matrix did not converge or gave a
    /// non-finite pseudo-inverse.
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
    /// peaks, which render as the black or white pixels of Meseth et al., §7. The
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

/// One lobe `ρ · max(ĉ · l, 0)^n` (Meseth et al. eq. 1 with `C = ρ^{1/n} ĉ`).
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

/// `k` lobes of Meseth et al. equation (1) for one texel and view.
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

    /// The `k` lobes (unused ones have amplitude 0).
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
    ReducedLobes {
        /// Lobes actually fitted.
        active: usize,
    },
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
    /// Why the texel was not fitted with the full model; `None` when it was.
    pub fallback: Option<Fallback>,
}

/// Results for all texels of one view slot, texel-major.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlotFit {
    /// Lobes per texel model.
    pub k: usize,
    /// One fit per texel, texel-major as the slot's values.
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

    /// Number of texels whose fit converged.
    pub fn converged_texels(&self) -> usize {
        self.texels.iter().filter(|t| t.converged).count()
    }
}

/// Fits Meseth et al. equation (1) with `k` lobes to one texel by
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
    /// The fit of the texel's luminance ([`LUMINANCE_WEIGHTS`]).
    pub luminance: TexelFit,
    /// Linear RGB factors of unit luminance that turn the luminance model
    /// into colour (the texel's average colour).
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

mod error_table;
mod fitting;
mod helpers;
mod ptm;
pub use error_table::*;
use fitting::*;
use helpers::*;
pub use ptm::*;
