//! Where the simulated devices physically are, shared by every simulated
//! firmware of one rig, so a camera renders what the axes, the arm and the
//! lamps really did (not what a driver asked for).

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, MutexGuard};

/// A snapshot of the simulated world.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct World {
    /// Axis positions in degrees, by device name.
    pub axes: BTreeMap<String, f64>,
    /// Arm joint values in degrees, in profile order.
    pub arm: Option<Vec<f64>>,
    /// Lamp (and laser) relays, by device name.
    pub lamps_on: BTreeMap<String, bool>,
    /// The laser calibration plate's height over the turntable, mm, while
    /// it is in place.
    pub plate_mm: Option<f64>,
}

/// The world, written by the firmware simulators and read by the cameras
/// and status displays.
#[derive(Debug, Clone, Default)]
pub struct SharedWorld(Arc<Mutex<World>>);

impl SharedWorld {
    /// An empty world: no axis, arm, lamp or plate reported yet.
    pub fn new() -> SharedWorld {
        SharedWorld::default()
    }

    fn lock(&self) -> MutexGuard<'_, World> {
        // Plain numbers: a panic elsewhere cannot leave them inconsistent.
        rigd_core::sync::lock(&self.0)
    }

    /// A copy of the world as it is now.
    pub fn snapshot(&self) -> World {
        self.lock().clone()
    }

    /// Called after every exchange of a controller (every status poll), so
    /// it allocates only the first time an axis appears.
    pub fn set_axis(&self, name: &str, position: f64) {
        let mut w = self.lock();
        match w.axes.get_mut(name) {
            Some(p) => *p = position,
            None => {
                w.axes.insert(name.to_string(), position);
            }
        }
    }

    /// Records the arm's joint values in degrees, in profile order.
    pub fn set_arm(&self, joints: Vec<f64>) {
        self.lock().arm = Some(joints);
    }

    /// Puts the laser calibration plate in place at `height_mm` over the
    /// turntable, or takes it away (`None`).
    pub fn set_plate(&self, height_mm: Option<f64>) {
        self.lock().plate_mm = height_mm;
    }
}
