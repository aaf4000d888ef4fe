//! Drivers for real device protocols. Each speaks its wire protocol (codecs
//! in `rigd-proto`) over a stream it is handed, never opening ports itself,
//! so tests can connect it to the simulated firmware in `rigd-sim`.

pub mod acl;
pub mod grbl;
pub mod modbus;
pub mod ptp;
pub mod usb;
