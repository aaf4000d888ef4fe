//! Pure wire codecs for the devices rigd talks to: text in, values out, and
//! back. No I/O and no clocks, so the daemon's drivers and the simulated
//! firmware in `rigd-sim` share one definition of each protocol (and neither
//! crate has to depend on the other).

pub mod grbl;
