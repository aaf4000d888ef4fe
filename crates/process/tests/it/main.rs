//! rigd-process's integration tests, one module per processing step, in one
//! binary so the crate is linked once.

mod btf;
mod mdf;
mod photometric_stereo;
mod rectify;
mod reflectance_fit;
