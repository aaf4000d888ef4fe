//! An HMI lamp's slow drift, as the simulated rig models it: its output
//! wanders by a few per cent over the hours of a capture (arc wander,
//! electrode wear, the ballast warming).
//! Modelled as two slow sinusoids of incommensurate periods, so the level
//! never repeats within a capture and stays within ±`amplitude`.

use serde::{Deserialize, Serialize};

/// How a simulated lamp's output drifts over physical time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LampDrift {
    /// Largest relative departure from the nominal level (0.05: ±5 %).
    pub amplitude: f64,
    /// Period of the slower wander, physical seconds.
    #[serde(default = "default_period_s")]
    pub period_s: f64,
}

fn default_period_s() -> f64 {
    4.0 * 3600.0
}

/// Ratio of the faster wander's period to the slower one's: irrational,
/// so the two never fall into step.
const FAST_RATIO: f64 = 0.381_966_011_250_105;

impl LampDrift {
    /// Checks the amplitude (0 ..= 0.5) and the period (1 s ..= 1000 h);
    /// the message names the key under `sim.lamp_drift`.
    pub fn check(&self) -> Result<(), (String, String)> {
        if !(self.amplitude.is_finite() && (0.0..=0.5).contains(&self.amplitude)) {
            return Err((
                "sim.lamp_drift.amplitude".into(),
                format!("expected 0 ..= 0.5 (a fraction), got {}", self.amplitude),
            ));
        }
        if !(self.period_s.is_finite() && (1.0..=3.6e6).contains(&self.period_s)) {
            return Err((
                "sim.lamp_drift.period_s".into(),
                format!("expected 1 ..= 3600000 s, got {}", self.period_s),
            ));
        }
        Ok(())
    }

    /// The lamp's level relative to nominal at physical time `t_s`: 1 at
    /// t = 0, within 1 ± `amplitude` always.
    pub fn level(&self, t_s: f64) -> f64 {
        let slow = (std::f64::consts::TAU * t_s / self.period_s).sin();
        let fast = (std::f64::consts::TAU * t_s / (FAST_RATIO * self.period_s)).sin();
        1.0 + self.amplitude * (0.7 * slow + 0.3 * fast)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_level_starts_nominal_wanders_slowly_and_stays_in_bounds() {
        let d = LampDrift {
            amplitude: 0.05,
            period_s: 3600.0,
        };
        assert_eq!(d.level(0.0), 1.0);
        let levels: Vec<f64> = (0..10_000).map(|k| d.level(k as f64 * 3.6)).collect();
        assert!(levels.iter().all(|l| (0.95..=1.05).contains(l)));
        let (lo, hi) = levels
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), &l| (a.min(l), b.max(l)));
        assert!(hi - lo > 0.06, "it wanders: {lo} … {hi}");
        // Slow: under 0.1 % between frames 10 s apart.
        assert!((d.level(1000.0) - d.level(1010.0)).abs() < 1e-3);
        assert!(LampDrift {
            amplitude: 0.6,
            ..d
        }
        .check()
        .is_err());
        assert!(LampDrift {
            period_s: f64::NAN,
            ..d
        }
        .check()
        .is_err());
    }
}
