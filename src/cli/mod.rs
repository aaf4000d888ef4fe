//! One module per command of the `rigd` binary; `main.rs` only parses and
//! dispatches. Each command validates its own arguments (bad input exits 2,
//! see [`exit`]) and prints its own report.

pub mod camera;
pub mod dataset;
pub mod exit;
pub mod frame;
pub mod holder;
pub mod internal;
pub mod plan;
pub mod process;
pub mod profile;
pub mod progress;
pub mod rig;
pub mod run;
pub mod serve;
pub mod signal;
#[cfg(feature = "sim")]
pub mod sim;
#[cfg(feature = "sim")]
pub mod tradeoff;
