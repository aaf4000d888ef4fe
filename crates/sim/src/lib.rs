//! The simulated BTF rig behind rigd: simulated firmware that speaks each device's real wire protocol
//! with its physics (motion, warm-up, exposure, readout, transfer), the
//! world they share, the scene renderer (`crates/sim/scenes/*.toml`) with its
//! ground truth, and fault injection.
//!
//! The crate depends on nothing of the daemon but the hardware-abstraction
//! layer, whose link openers it implements ([`links`]), so the daemon can
//! embed it as its default backend and tests can drive it directly. Its
//! waits go through `rigd_core::Clock`, the clock the drivers and the
//! engine use.
#![warn(missing_docs)]

pub mod devices;
pub mod faults;
pub mod firmware;
pub mod links;
pub mod scene;
pub mod settings;
pub mod world;

pub use faults::{FaultInjector, FaultKind, FaultRule};
pub use world::{SharedWorld, World};
