//! The laser calibration plate (Wang et al., §3.2): a flat plate an operator
//! lays over the turntable at a known height, so the strip falls on two
//! planes of different heights. On a real rig the run pauses with the
//! instruction and goes on when the operator resumes; the simulated rig
//! places the plate itself ([`crate::rig::sim::SimPlate`]).

use async_trait::async_trait;

use crate::rig::hal::{DeviceError, ErrorKind, Fixture};

/// Name the plate's messages and deadlines carry.
pub const PLATE_DEVICE: &str = "plate";

/// Asks the operator: the first call for a placement fails with the
/// instruction (the engine pauses with it as the reason, and never retries
/// it); the call after the operator's resume finds it done.
#[derive(Debug, Default)]
pub struct OperatorPlate {
    asked: Option<Option<f64>>,
}

#[async_trait]
impl Fixture for OperatorPlate {
    async fn place(&mut self, height_mm: Option<f64>) -> Result<(), DeviceError> {
        if self.asked == Some(height_mm) {
            self.asked = None;
            return Ok(());
        }
        self.asked = Some(height_mm);
        let what = match height_mm {
            Some(h) => format!("lay the {h} mm laser calibration plate over the turntable"),
            None => "take the laser calibration plate off the turntable".to_string(),
        };
        Err(DeviceError::new(
            PLATE_DEVICE,
            ErrorKind::NotReady,
            format!("operator: {what}, then resume the run"),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn the_operator_is_asked_once_per_placement() {
        let mut plate = OperatorPlate::default();
        let first = plate.place(Some(10.0)).await;
        let msg = first.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(msg.contains("10 mm") && msg.contains("resume"), "{msg}");
        assert!(plate.place(Some(10.0)).await.is_ok());
        // A new placement asks again.
        assert!(plate.place(None).await.is_err());
        assert!(plate.place(None).await.is_ok());
    }
}
