//! What every simulated device shares: the clock all its waits go through,
//! and the fault injector it asks before answering a command. Device
//! physics live with each firmware in [`crate::firmware`].

use std::sync::Arc;

use crate::faults::FaultInjector;
use rigd_core::clock::Clock;

/// Shared wiring of every simulated device.
#[derive(Debug, Clone)]
pub struct SimContext {
    /// The clock every simulated wait goes through, in physical time.
    pub clock: Clock,
    /// The rig's fault injector, asked before each command is answered.
    pub faults: Arc<FaultInjector>,
}

impl SimContext {
    /// Wiring from a clock and a shared fault injector.
    pub fn new(clock: Clock, faults: Arc<FaultInjector>) -> SimContext {
        SimContext { clock, faults }
    }
}

/// Camera timing: exposure and readout keep the sensor busy; the transfer
/// delivers the frame afterwards.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraTimes {
    /// Nominal exposure in seconds: the initial exposure setting, against
    /// which a frame's brightness is scaled.
    pub exposure_s: f64,
    /// Sensor readout after the exposure, in seconds.
    pub readout_s: f64,
    /// Transfer of a frame to the host, in seconds.
    pub transfer_s: f64,
}
