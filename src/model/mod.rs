//! Shared types that depend on nothing else in the crate: rig profiles,
//! directions and vectors, and where a run stands.

pub mod geometry;
pub mod profile;
pub mod run_state;
