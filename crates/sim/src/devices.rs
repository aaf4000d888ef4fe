//! What every simulated device shares: the clock all its waits go through,
//! and the fault injector it asks before answering a command. Device
//! physics live with each firmware in [`crate::firmware`].

use std::sync::Arc;

use crate::faults::FaultInjector;
use rigd_core::clock::Clock;

/// Shared wiring of every simulated device.
#[derive(Debug, Clone)]
pub struct SimContext {
    pub clock: Clock,
    pub faults: Arc<FaultInjector>,
}

impl SimContext {
    pub fn new(clock: Clock, faults: Arc<FaultInjector>) -> SimContext {
        SimContext { clock, faults }
    }
}

/// Camera timing: exposure and readout keep the sensor busy; the transfer
/// delivers the frame afterwards.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraTimes {
    pub exposure_s: f64,
    pub readout_s: f64,
    pub transfer_s: f64,
}
