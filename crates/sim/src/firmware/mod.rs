//! Simulated device firmware: the same physics as [`crate::devices`], but
//! spoken byte for byte over a stream, so the daemon's real protocol
//! drivers can be tested against it without hardware.

pub mod acl;
pub mod dng;
pub mod grbl;
pub mod modbus;
pub mod ptp;
