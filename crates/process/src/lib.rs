//! Post-processing of captured datasets. Pure numerics over images and
//! direction tables: nothing here knows about devices, runs or the daemon,
//! so each step is testable on analytic data and reusable by the CLI, the
//! daemon and the trade-off report.
#![warn(missing_docs)]

pub mod btf;
pub mod colour;
pub mod demosaic;
pub mod directions;
pub mod export;
pub mod hdr;
pub mod image_io;
pub mod mdf;
pub mod mesh;
pub mod npy;
pub mod photometric_stereo;
pub mod rectify;
pub mod reflectance_fit;
pub mod relight;
pub mod silhouette;
pub mod webgl;
