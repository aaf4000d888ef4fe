//! rigd: control daemon for BTF (bidirectional texture function) measurement
//! rigs. See the README for the commands and `docs/architecture.md` for the
//! layers and the rule of what may depend on what.
//!
//! The layers, lowest first; a module uses only those above it in this list:
//! [`model`] (profile, geometry, run state) → [`plan`] and [`kinematics`] →
//! [`schedule`] (ordered triggers, timing) → [`rig`] (device traits,
//! drivers, rig assembly) → [`store`] (the dataset on disk) → [`engine`]
//! (drives the rig through a schedule into the store) → [`postprocess`] →
//! [`tradeoff`] → [`server`]. The command line (`src/cli/`) sits on top.
#![warn(missing_docs)]

pub mod engine;
pub mod kinematics;
pub mod model;
pub mod plan;
pub mod postprocess;
pub mod rig;
pub mod schedule;
pub mod server;
pub mod store;
#[cfg(feature = "sim")]
pub mod tradeoff;
#[cfg(feature = "sim")]
pub mod truth;
