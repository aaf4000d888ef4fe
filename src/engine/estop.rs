//! The emergency stop: every device's out-of-band stop at once, timed on
//! the run's clock, then the run pauses and must re-home before it goes on.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use futures::future::join_all;
use rigd_core::Clock;
use serde::{Deserialize, Serialize};

use crate::rig::hal::EmergencyStop;

/// How long one device may take to acknowledge its stop (physical time).
pub const STOP_DEADLINE_S: f64 = 2.0;

/// One device's answer to the emergency stop.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StopAck {
    /// The device (or shared bus) that was stopped, named as in the rig profile.
    pub device: String,
    /// Physical seconds from the request to this device's acknowledgement
    /// (or to its failure).
    pub after_s: f64,
    /// Why the device did not acknowledge, if it did not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// What an emergency stop did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StopReport {
    /// Physical seconds from the request to the last device acknowledging.
    pub latency_s: f64,
    /// Every device's answer, in name order.
    pub devices: Vec<StopAck>,
}

impl StopReport {
    /// True when every device acknowledged.
    pub fn all_stopped(&self) -> bool {
        self.devices.iter().all(|d| d.error.is_none())
    }
}

/// The stop button of one rig. Cheap to clone; shared by the engine (which
/// reads whether it tripped) and whoever may press it.
#[derive(Clone)]
pub struct EStop {
    stops: Arc<BTreeMap<String, Arc<dyn EmergencyStop>>>,
    clock: Clock,
    tripped: Arc<AtomicBool>,
}

impl std::fmt::Debug for EStop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EStop")
            .field("devices", &self.stops.keys().collect::<Vec<_>>())
            .field("tripped", &self.is_tripped())
            .finish()
    }
}

impl EStop {
    /// A stop button over these devices' out-of-band stops (by device name),
    /// not tripped; `clock` times their acknowledgements.
    pub fn new(stops: BTreeMap<String, Arc<dyn EmergencyStop>>, clock: Clock) -> EStop {
        EStop {
            stops: Arc::new(stops),
            clock,
            tripped: Arc::new(AtomicBool::new(false)),
        }
    }

    /// Stops every device at once and reports when each acknowledged.
    pub async fn trigger(&self) -> StopReport {
        self.tripped.store(true, Ordering::SeqCst);
        let start = self.clock.now_s();
        let calls = self.stops.iter().map(|(name, stop)| async move {
            let r = self
                .clock
                .deadline(
                    Duration::from_secs_f64(STOP_DEADLINE_S),
                    stop.emergency_stop(),
                )
                .await;
            let error = match r {
                Ok(Ok(())) => None,
                Ok(Err(e)) => Some(e.to_string()),
                Err(_) => Some(format!("no acknowledgement within {STOP_DEADLINE_S} s")),
            };
            StopAck {
                device: name.clone(),
                after_s: self.clock.now_s() - start,
                error,
            }
        });
        let devices = join_all(calls).await;
        let latency_s = devices.iter().map(|d| d.after_s).fold(0.0, f64::max);
        for d in &devices {
            match &d.error {
                None => {
                    tracing::warn!(device = %d.device, after_s = d.after_s, "emergency stop acknowledged")
                }
                Some(e) => {
                    tracing::error!(device = %d.device, "emergency stop not acknowledged: {e}")
                }
            }
        }
        StopReport { latency_s, devices }
    }

    /// True from a trigger until the run has re-homed.
    pub fn is_tripped(&self) -> bool {
        self.tripped.load(Ordering::SeqCst)
    }

    pub(crate) fn rearm(&self) {
        self.tripped.store(false, Ordering::SeqCst);
    }
}
