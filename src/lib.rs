//! rigd: control daemon for BTF (bidirectional texture function) measurement
//! rigs. See the README for the commands and `../DESIGN.md`-style notes in
//! `docs/` for the architecture.
//!
//! Data flows: [`profile`] → [`kinematics`] (poses) and [`plan`] (pairs) →
//! [`schedule`] (ordered triggers) → [`engine`] (drives the [`hal`] rig) →
//! [`store`] (the dataset on disk).

pub mod connect;
pub mod drivers;
pub mod engine;
pub mod geometry;
pub mod hal;
pub mod kinematics;
pub mod laser;
pub mod mdf_run;
pub mod ordering;
pub mod plan;
pub mod postprocess;
pub mod profile;
pub mod relight;
pub mod runner;
pub mod schedule;
pub mod server;
pub mod sim_render;
pub mod store;
pub mod tradeoff;

pub use rigd_sim as sim;
