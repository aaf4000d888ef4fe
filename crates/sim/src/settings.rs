//! The simulator's own keys of a profile's `[sim]` table: what the
//! simulated firmware does (faults, controllers' quirks, the lamps' drift)
//! and what its cameras look at (the scene, where the holder really sits).
//! The table's other keys, the simulated frames' size and lens, belong to
//! the profile, since processing models those frames.

use rigd_core::lamp_drift::LampDrift;
use serde::{Deserialize, Serialize};

/// The simulator's keys of the `[sim]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimSettings {
    /// Faults the simulated firmware inject, in `--sim-fault` syntax
    /// (`DEVICE:OP:N:KIND[:sticky]`), on top of those given on the command
    /// line.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub faults: Vec<String>,
    /// What the simulated cameras look at: a built-in scene's name or a
    /// path to a scene file (`crates/sim/scenes/*.toml`); `flat-calibration`
    /// if absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene: Option<String>,
    /// Whether the simulated GRBL boards reset when their port opens and
    /// greet with the banner (an Arduino, through DTR), or keep running and
    /// stay silent until asked (a board without that reset). Default `true`.
    #[serde(default = "default_true")]
    pub grbl_reset_on_open: bool,
    /// The simulated GRBL boards' settings at power-up: `configured` (set
    /// up for their axes: rates, travel and `$22` from the profile) or
    /// `factory` (as GRBL ships: `$22=0`, `$110=500`, `$120=10`).
    #[serde(default)]
    pub grbl_settings: SimGrblSettings,
    /// Seconds every answer of a simulated GRBL board waits before it goes
    /// out: a slow controller (one was observed answering each line in
    /// about 150 ms). Default 0.
    #[serde(default)]
    pub grbl_answer_delay_s: f64,
    /// Where the holder really sits in the plate plane, millimetres from
    /// the sample centre the kinematics assume: the placement error a real
    /// rig has. The markers see it; registration from the rig's pose must
    /// calibrate it away. Default `[0, 0]`.
    #[serde(default, skip_serializing_if = "is_zero_offset")]
    pub holder_offset_mm: [f64; 2],
    /// How the simulated lamps' output drifts over the capture's physical
    /// time (`{ amplitude = 0.05, period_s = 14400 }`), as an HMI lamp's
    /// does; none if absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lamp_drift: Option<LampDrift>,
}

fn is_zero_offset(o: &[f64; 2]) -> bool {
    o == &[0.0, 0.0]
}

fn default_true() -> bool {
    true
}

/// What the simulated GRBL boards have in their EEPROM at power-up.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SimGrblSettings {
    /// Set up for their axes, from the profile.
    #[default]
    Configured,
    /// GRBL's factory defaults.
    Factory,
}

impl Default for SimSettings {
    fn default() -> Self {
        SimSettings {
            faults: Vec::new(),
            scene: None,
            grbl_reset_on_open: true,
            grbl_settings: SimGrblSettings::Configured,
            grbl_answer_delay_s: 0.0,
            holder_offset_mm: [0.0, 0.0],
            lamp_drift: None,
        }
    }
}

impl SimSettings {
    /// Checks the values each key holds on its own; `Err` names the key
    /// under `sim.` and says what was expected. Whether the scene exists and
    /// the faults name the profile's devices is the caller's to check.
    pub fn check(&self) -> Result<(), (String, String)> {
        if !self
            .holder_offset_mm
            .iter()
            .all(|v| v.is_finite() && v.abs() <= 10.0)
        {
            return Err((
                "sim.holder_offset_mm".into(),
                format!(
                    "expected [x, y] within ±10 mm (a holder that far off leaves the camera's field), got {:?}",
                    self.holder_offset_mm
                ),
            ));
        }
        if let Some(drift) = &self.lamp_drift {
            drift.check()?;
        }
        let delay = self.grbl_answer_delay_s;
        if !(delay.is_finite() && (0.0..=1.0).contains(&delay)) {
            return Err((
                "sim.grbl_answer_delay_s".into(),
                format!("expected 0 ..= 1 second (the driver allows 2 s per line), got {delay}"),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn out_of_range_values_name_their_key() {
        let ok = SimSettings::default();
        assert_eq!(ok.check(), Ok(()));
        let far = SimSettings {
            holder_offset_mm: [0.0, f64::NAN],
            ..SimSettings::default()
        };
        assert_eq!(
            far.check().map_err(|e| e.0),
            Err("sim.holder_offset_mm".into())
        );
        let slow = SimSettings {
            grbl_answer_delay_s: 1.5,
            ..SimSettings::default()
        };
        assert_eq!(
            slow.check().map_err(|e| e.0),
            Err("sim.grbl_answer_delay_s".into())
        );
    }
}
