//! The sensor's noise source: a standard normal deviate per (seed, pixel)
//! from a counter-based hash (splitmix64) and Box–Muller, so a pixel's
//! noise never depends on which thread renders it or in what order.
//!
//! [`Deviate::exact`] is the deviate, with libm's `ln` and `cos`.
//! [`Deviate::estimate`] is the same deviate computed without libm (a
//! reduced atanh series for the logarithm, quadrant reduction and Taylor
//! series for the cosine) to within [`Deviate::ESTIMATE_ERROR`]: the sensor
//! reads a pixel from the estimate only when that error cannot change the
//! pixel's code, and asks for the exact deviate otherwise.

use std::f64::consts::{FRAC_2_PI, LN_2, SQRT_2, TAU};

/// The two uniforms Box–Muller turns into pixel `k`'s deviate.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Deviate {
    /// In (0, 1): sets the deviate's size, √(−2 ln u1).
    u1: f64,
    /// In [0, 1): sets its sign and phase, cos(τ·phase).
    phase: f64,
}

impl Deviate {
    /// A bound on `|estimate − exact|` relative to `|estimate|`, and
    /// absolute: with a hundredfold margin over the series' truncation
    /// and the rounding of both computations (libm's `ln` and `cos` are
    /// within an ulp).
    pub(crate) const ESTIMATE_ERROR: (f64, f64) = (1e-9, 1e-12);

    /// The phase of pixel `k`'s deviate: whether it is negative is known
    /// from this alone.
    #[inline]
    pub(crate) fn phase(seed: u64, k: u64) -> f64 {
        let b = splitmix(seed ^ splitmix(k.wrapping_mul(2) + 1));
        (b >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Pixel `k`'s uniforms, given its [`Deviate::phase`].
    #[inline]
    pub(crate) fn new(seed: u64, k: u64, phase: f64) -> Deviate {
        let a = splitmix(seed ^ splitmix(k.wrapping_mul(2)));
        Deviate {
            u1: ((a >> 11) as f64 + 0.5) / (1u64 << 53) as f64,
            phase,
        }
    }

    /// The deviate.
    #[inline]
    pub(crate) fn exact(&self) -> f64 {
        (-2.0 * self.u1.ln()).sqrt() * (TAU * self.phase).cos()
    }

    /// The deviate to within [`Deviate::ESTIMATE_ERROR`], without libm.
    #[inline]
    pub(crate) fn estimate(&self) -> f64 {
        (-2.0 * ln_estimate(self.u1)).sqrt() * cos_estimate(TAU * self.phase)
    }
}

/// ln u for a normal u in (0, 1], to about 1e-12 relative: u = 2^e·m with
/// m in [√½, √2), ln m = 2 atanh(s) with s = (m − 1)/(m + 1), |s| < 0.172,
/// summed to s¹³ (the rest is below s¹⁵/15 < 3e-13 relative to ln m; for
/// e ≠ 0, |ln u| > 0.34 outweighs it).
#[inline]
fn ln_estimate(u: f64) -> f64 {
    let bits = u.to_bits();
    // Branch-free (selects, 32-bit integers), so that a loop of these
    // vectorises.
    let e = ((bits >> 52) & 0x7ff) as i32 - 1023;
    let m = f64::from_bits((bits & ((1u64 << 52) - 1)) | (1023u64 << 52));
    let above = m > SQRT_2;
    let m = if above { m * 0.5 } else { m };
    let e = e + i32::from(above);
    let s = (m - 1.0) / (m + 1.0);
    let s2 = s * s;
    let series = 1.0
        + s2 * (1.0 / 3.0
            + s2 * (1.0 / 5.0
                + s2 * (1.0 / 7.0 + s2 * (1.0 / 9.0 + s2 * (1.0 / 11.0 + s2 * (1.0 / 13.0))))));
    f64::from(e) * LN_2 + 2.0 * s * series
}

/// cos x for x in [0, 2π], to about 1e-13: x = k·π/2 + r with |r| ≤ π/4
/// (π/2 in two parts, so r is exact to far below that), then ±cos r or
/// ±sin r by their Taylor series to r¹² and r¹³ (the rest is below
/// r¹⁴/14! < 4e-13, and relative to sin r where it is small).
#[inline]
fn cos_estimate(x: f64) -> f64 {
    // π/2 = PIO2_HI + PIO2_LO, PIO2_HI with 33 significant bits so that
    // k·PIO2_HI is exact for the k ≤ 4 this range needs.
    const PIO2_HI: f64 = 1.570_796_326_734_125_6;
    const PIO2_LO: f64 = 6.077_100_506_506_192e-11;
    let k = (x * FRAC_2_PI + 0.5) as i32;
    let kf = f64::from(k);
    let r = (x - kf * PIO2_HI) - kf * PIO2_LO;
    let r2 = r * r;
    // Coefficients 1/n! folded at compile time: multiplications only.
    let cos_r = 1.0
        + r2 * (-1.0 / 2.0
            + r2 * (1.0 / 24.0
                + r2 * (-1.0 / 720.0
                    + r2 * (1.0 / 40_320.0
                        + r2 * (-1.0 / 3_628_800.0 + r2 * (1.0 / 479_001_600.0))))));
    let sin_r = r
        * (1.0
            + r2 * (-1.0 / 6.0
                + r2 * (1.0 / 120.0
                    + r2 * (-1.0 / 5_040.0
                        + r2 * (1.0 / 362_880.0
                            + r2 * (-1.0 / 39_916_800.0 + r2 * (1.0 / 6_227_020_800.0)))))));
    // Quadrants 0 … 4: cos r, −sin r, −cos r, sin r, cos r.
    let value = if k & 1 == 0 { cos_r } else { sin_r };
    if (k + 1) & 2 == 0 {
        value
    } else {
        -value
    }
}

#[inline]
fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_1_SQRT_2;

    fn within_bound(estimate: f64, exact: f64) -> bool {
        let (relative, absolute) = Deviate::ESTIMATE_ERROR;
        // A hundredth of the bound: the margin the bound claims.
        (estimate - exact).abs() <= (relative * estimate.abs() + absolute) / 100.0
    }

    #[test]
    fn the_estimate_is_within_its_bound_with_margin() {
        for k in 0..2_000_000u64 {
            let seed = 0x5EED ^ (k >> 17);
            let d = Deviate::new(seed, k, Deviate::phase(seed, k));
            assert!(within_bound(d.estimate(), d.exact()), "pixel {k}: {d:?}");
        }
    }

    #[test]
    fn the_estimate_holds_at_the_extremes() {
        let smallest_u1 = 0.5 / (1u64 << 53) as f64;
        let largest_u1 = ((u64::MAX >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
        let largest_phase = (u64::MAX >> 11) as f64 / (1u64 << 53) as f64;
        let mut phases = vec![
            0.0,
            0.125,
            0.25,
            0.375,
            0.5,
            0.625,
            0.75,
            0.875,
            largest_phase,
        ];
        // Around the quadrant boundaries, where k changes.
        for q in 1..8 {
            for step in 1..40 {
                let d = f64::from(step) * 1e-16 * 2f64.powi(step / 4);
                phases.push(f64::from(q) / 8.0 - d);
                phases.push(f64::from(q) / 8.0 + d);
            }
        }
        for u1 in [
            smallest_u1,
            1e-10,
            0.25,
            0.5,
            // Where the reduction switches between m and m / 2.
            FRAC_1_SQRT_2,
            FRAC_1_SQRT_2 * (1.0 + 1e-15),
            0.999_999_9,
            largest_u1,
        ] {
            for &phase in &phases {
                let d = Deviate { u1, phase };
                assert!(within_bound(d.estimate(), d.exact()), "{d:?}");
            }
        }
    }
}
