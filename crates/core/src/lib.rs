//! What every part of rigd shares, and nothing else: the one clock every
//! wait goes through ([`clock`]), the trapezoidal motion model of a stepper
//! axis or robot joint ([`motion`]), directions on the hemisphere with the
//! vector and rotation helpers around them ([`geometry`]), and the physical
//! things both the simulator and the processing model: the camera
//! ([`camera`]) and the sample holder with its markers ([`holder`]); and
//! the pixel formats of raw frames ([`pixel_format`]); bounded reads of
//! files named from outside and of hand-written text ([`read`]), one
//! loader for configuration files ([`config`]),
//! whole-or-nothing writes ([`atomic`]) and locks that outlive a panic
//! ([`sync`]); and virtual time paced to the wall clock for sped-up demos
//! ([`pace`]).
//!
//! The drivers and the run engine depend on this crate, not on `rigd-sim`,
//! so the hardware path builds without the simulator.
#![warn(missing_docs)]

pub mod atomic;
pub mod camera;
pub mod chart;
pub mod clock;
pub mod config;
pub mod geometry;
pub mod holder;
pub mod lamp_drift;
pub mod motion;
pub mod pace;
pub mod pixel_format;
pub mod read;
pub mod sync;

pub use clock::{Clock, DeadlineElapsed};
pub use geometry::Direction;
pub use motion::Trapezoid;
pub use pixel_format::{Cfa, PixelFormat};
