//! Shared types that depend on nothing else in the crate: rig profiles and
//! where a run stands. Directions and vectors are `rigd_core::geometry`,
//! shared with the simulator and the processing crate.

pub mod device;
pub mod exposure;
pub mod profile;
pub mod run_state;
pub mod text;
pub mod whole_value;
