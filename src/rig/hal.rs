//! The hardware-abstraction layer ([`rigd_hal`]): the capability traits,
//! the common error kinds and the frame, under the path the drivers and the
//! engine name them by.

pub use rigd_hal::*;
