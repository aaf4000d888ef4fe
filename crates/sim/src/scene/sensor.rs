//! The sensor: shot and read noise ([`super::noise`]: a pixel's noise
//! depends on (seed, pixel index) only, whatever thread renders it) and
//! quantisation to the frame's bit depth. The renderer reads out each run
//! of pixels as soon as it is shaded.

use super::effects::{Effect, EffectPlan};
use super::noise::Deviate;
use super::shot::Shot;
use super::spec::SensorSpec;

/// The sensor as one frame sets it up.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Sensor {
    /// The largest code: `2^bit_depth − 1`.
    max_value: f64,
    noise: Option<Noise>,
}

/// Shot and read noise, when live.
#[derive(Debug, Clone, Copy)]
struct Noise {
    /// The scene's seed with the frame's mixed in.
    seed: u64,
    read_dn: f64,
    electrons_per_dn: f64,
}

impl Sensor {
    pub(crate) fn new(spec: &SensorSpec, shot: &Shot, plan: &EffectPlan) -> Sensor {
        Sensor {
            max_value: max_code(shot),
            noise: plan.has(Effect::Noise).then_some(Noise {
                seed: spec.seed ^ shot.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15),
                read_dn: spec.read_noise_dn,
                electrons_per_dn: spec.electrons_per_dn,
            }),
        }
    }

    /// The codes of a run of pixels from their linear values in digital
    /// numbers; `first` is the row-major index of the first.
    pub(crate) fn read_out(&self, linear: &[f32], first: u64, codes: &mut [u16]) {
        let Some(n) = &self.noise else {
            for (code, &v) in codes.iter_mut().zip(linear) {
                *code = quantise(v as f64, self.max_value);
            }
            return;
        };
        for (c, (linear, codes)) in linear.chunks(RUN).zip(codes.chunks_mut(RUN)).enumerate() {
            let first = first + (c * RUN) as u64;
            // The phase of every pixel's deviate first: a pixel that reads 0
            // whatever its deviate's size is done without the rest, and the
            // others are listed rather than branched to (the test goes
            // either way at random, and a mispredicted branch per pixel
            // would serialise the work).
            let mut phase = [0.0; RUN];
            let mut noisy = [0u8; RUN];
            let mut count = 0;
            for (k, (&v, code)) in linear.iter().zip(codes.iter_mut()).enumerate() {
                phase[k] = Deviate::phase(n.seed, first + k as u64);
                // cos(τ·phase) < 0: the deviate is negative and only
                // darkens a pixel that already reads 0.
                let reads_zero = (v as f64) < 0.5 && (0.2501..=0.7499).contains(&phase[k]);
                *code = 0;
                noisy[count] = k as u8;
                count += usize::from(!reads_zero);
            }
            // The listed pixels' values, spreads and uniforms side by side,
            // then their deviates' estimates in one straight loop, which
            // the compiler vectorises.
            let mut value = [0.0; RUN];
            let mut spread = [0.0; RUN];
            let mut deviate = [Deviate::default(); RUN];
            for (m, &k) in noisy[..count].iter().enumerate() {
                let k = usize::from(k);
                let v = linear[k] as f64;
                let mut var = n.read_dn * n.read_dn;
                if n.electrons_per_dn > 0.0 {
                    var += v.max(0.0) / n.electrons_per_dn;
                }
                value[m] = v;
                spread[m] = var.sqrt();
                deviate[m] = Deviate::new(n.seed, first + k as u64, phase[k]);
            }
            let mut estimate = [0.0; RUN];
            for (g, d) in estimate.iter_mut().zip(&deviate).take(count) {
                *g = d.estimate();
            }
            for (m, &k) in noisy[..count].iter().enumerate() {
                codes[usize::from(k)] = noisy_code(
                    value[m],
                    spread[m],
                    estimate[m],
                    &deviate[m],
                    self.max_value,
                );
            }
        }
    }
}

/// The code of `v + sd·g`, g the pixel's deviate: read from `g`, the
/// deviate's estimate, when the estimate's error bound and the rounding of
/// the sum leave only one possible code (the code is monotone in the
/// value), else from the exact deviate. Either way it is the exact code.
#[inline]
fn noisy_code(v: f64, sd: f64, g: f64, deviate: &Deviate, max: f64) -> u16 {
    let value = v + sd * g;
    let (relative, absolute) = Deviate::ESTIMATE_ERROR;
    // The deviate's error scaled by sd, and a bound (with a wide margin) on
    // how differently the two sums can round.
    let slack = sd * (relative * g.abs() + absolute) + 1e-12 * (1.0 + v.abs() + value.abs());
    let low = quantise(value - slack, max);
    if low == quantise(value + slack, max) {
        low
    } else {
        quantise(v + sd * deviate.exact(), max)
    }
}

/// Pixels whose noise is worked out together.
const RUN: usize = 64;

/// `2^bit_depth − 1` for the shot's bit depth (1 ..= 16 bits).
pub(crate) fn max_code(shot: &Shot) -> f64 {
    ((1u32 << shot.bit_depth.clamp(1, 16)) - 1) as f64
}

/// `v.round().clamp(0.0, max) as u16`, code for code, without the libm
/// `round` call baseline x86-64 makes: clamping first rounds to the same
/// code (`max` is an integer), and on [0, max] rounding half away from zero
/// is truncation plus one when the exact remainder is at least ½. NaN
/// reads 0, as the cast made it.
#[inline]
fn quantise(v: f64, max: f64) -> u16 {
    let c = v.max(0.0).min(max);
    let whole = c as u32;
    let up = c - whole as f64 >= 0.5;
    (whole + u32::from(up)) as u16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantise_is_round_then_clamp() {
        let max = 4095.0;
        let mut values = vec![
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            -0.0,
            0.0,
            0.5,
            0.499_999_999_999_999_94,
            -0.5,
            -0.499_999_999_999_999_94,
            1.5,
            2.5,
            4094.5,
            4_094.499_999_999_999,
            4095.0,
            4095.5,
            1e300,
            -1e300,
        ];
        let mut x = 0.37_f64;
        for _ in 0..100_000 {
            x = (x * 7919.0 + 0.731).rem_euclid(5000.0);
            values.push(x - 400.0);
            values.push((x - 400.0).floor() + 0.5);
        }
        for v in values {
            assert_eq!(quantise(v, max), v.round().clamp(0.0, max) as u16, "{v}");
        }
    }

    #[test]
    fn read_out_is_noise_then_round_and_clamp_pixel_by_pixel() {
        let shot = Shot {
            bit_depth: 12,
            ..Shot::default()
        };
        let n = Noise {
            seed: 11,
            read_dn: 2.0,
            electrons_per_dn: 4.0,
        };
        let sensor = Sensor {
            max_value: max_code(&shot),
            noise: Some(n),
        };
        // Dark pixels (where the shortcut applies), mid-grey and clipped.
        let linear: Vec<f32> = (0..20_000)
            .map(|k| [0.0, 0.3, 0.49, -1.0, 2.0, 700.0, 4094.7, 5000.0][k % 8])
            .collect();
        let first = 123_456;
        let mut codes = vec![0; linear.len()];
        sensor.read_out(&linear, first, &mut codes);
        for (k, (&v, &code)) in linear.iter().zip(&codes).enumerate() {
            let index = first + k as u64;
            let v = v as f64;
            let var = n.read_dn * n.read_dn + v.max(0.0) / n.electrons_per_dn;
            let g = Deviate::new(n.seed, index, Deviate::phase(n.seed, index)).exact();
            let expected = (v + var.sqrt() * g).round().clamp(0.0, sensor.max_value) as u16;
            assert_eq!(code, expected, "pixel {index}, value {v}");
        }
    }

    #[test]
    fn values_at_a_rounding_boundary_are_read_exactly() {
        let max = 4095.0;
        let sd = 2.0;
        for k in 0..20_000u64 {
            let d = Deviate::new(7, k, Deviate::phase(7, k));
            let exact_noise = sd * d.exact();
            // v + sd·g lands on (or a hair either side of) a half-integer,
            // where the estimate cannot decide.
            for boundary in [0.5, 1.5, 700.5, 4094.5] {
                for hair in [-1e-12, 0.0, 1e-12] {
                    let v = boundary + hair - exact_noise;
                    let expected = (v + exact_noise).round().clamp(0.0, max) as u16;
                    let code = noisy_code(v, sd, d.estimate(), &d, max);
                    assert_eq!(code, expected, "pixel {k}, v {v}");
                }
            }
        }
    }
}
