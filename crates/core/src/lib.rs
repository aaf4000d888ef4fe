//! What every part of rigd shares, and nothing else: the one clock every
//! wait goes through ([`clock`]), the trapezoidal motion model of a stepper
//! axis or robot joint ([`motion`]), and directions on the hemisphere with
//! the vector and rotation helpers around them ([`geometry`]).
//!
//! The drivers and the run engine depend on this crate, not on `rigd-sim`,
//! so the hardware path builds without the simulator.
#![warn(missing_docs)]

pub mod clock;
pub mod geometry;
pub mod motion;

pub use clock::{Clock, DeadlineElapsed};
pub use geometry::Direction;
pub use motion::Trapezoid;
