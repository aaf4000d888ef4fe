//! Pure wire codecs for the devices rigd talks to: text in, values out, and
//! back. No device I/O and no clocks (only the in-memory USB link of
//! `ptp::link` uses tokio channels), so the daemon's drivers and the simulated
//! firmware in `rigd-sim` share one definition of each protocol (and neither
//! crate has to depend on the other).
#![warn(missing_docs)]

pub mod acl;
pub mod grbl;
pub mod modbus;
pub mod ptp;
