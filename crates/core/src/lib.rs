//! What rigd's hardware path and its simulator share, and nothing else: the
//! one clock every wait goes through ([`clock`]) and the trapezoidal motion
//! model of a stepper axis or robot joint ([`motion`]).
//!
//! The drivers and the run engine depend on this crate, not on `rigd-sim`,
//! so the hardware path builds without the simulator.
#![warn(missing_docs)]

pub mod clock;
pub mod motion;

pub use clock::{Clock, DeadlineElapsed};
pub use motion::Trapezoid;
