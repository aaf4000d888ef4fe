//! Simulated device firmware: the same physics as [`crate::devices`], but
//! spoken byte for byte over a stream, so the daemon's real protocol
//! drivers can be tested against it without hardware.

pub mod acl;
pub mod dng;

/// How close to an operation's end (a move, a warm-up) an instant counts
/// as past it, seconds. Virtual time runs in whole milliseconds while the
/// ends are sums of floats, so a poll made exactly at the modelled end
/// could otherwise read a hair before it and wait a whole poll interval
/// more; a microsecond is far below anything a device or a poll resolves.
pub const END_TOLERANCE_S: f64 = 1e-6;

pub mod grbl;
pub mod modbus;
pub mod ptp;
