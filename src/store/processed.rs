//! Where a run's processed results live: `RUN/processed/`, one folder per
//! step. Every path into it is built here, so the steps, the viewer and the
//! daemon agree on the layout.
//!
//! | path | written by |
//! |---|---|
//! | `processed/normtextures/` (+ `index.json`) | `rigd process rectify`, `rigd import` |
//! | `processed/btf/` | `rigd process btf` |
//! | `processed/fit/` | `rigd process fit` |
//! | `processed/mdf/` | `rigd process mdf` |
//! | `processed/ps/` | `rigd process photometric-stereo RUN` |

use std::path::{Path, PathBuf};

/// The folder of a run's processed results.
pub const PROCESSED_DIR: &str = "processed";
/// The registered textures, one per frame, and their index.
pub const NORMTEXTURES_DIR: &str = "normtextures";
/// The normtextures' index file.
pub const NORMTEXTURE_INDEX: &str = "index.json";

/// `RUN/processed/`.
pub fn processed_dir(run: &Path) -> PathBuf {
    run.join(PROCESSED_DIR)
}

/// `RUN/processed/normtextures/`.
pub fn normtextures_dir(run: &Path) -> PathBuf {
    processed_dir(run).join(NORMTEXTURES_DIR)
}

/// `RUN/processed/btf/`: the compressed BTF.
pub fn btf_dir(run: &Path) -> PathBuf {
    processed_dir(run).join("btf")
}

/// `RUN/processed/fit/`: the reflectance-field fit's report.
pub fn fit_dir(run: &Path) -> PathBuf {
    processed_dir(run).join("fit")
}

/// `RUN/processed/mdf/`: the mesostructure distance function.
pub fn mdf_dir(run: &Path) -> PathBuf {
    processed_dir(run).join("mdf")
}

/// `RUN/processed/mdf-texture/`: a laser run's MDF resampled to this
/// run's texture space (`rigd process mdf-texture`), for the renderers.
pub fn mdf_texture_dir(run: &Path) -> PathBuf {
    processed_dir(run).join("mdf-texture")
}

/// `RUN/processed/ps/`: a photometric-stereo result.
pub fn ps_dir(run: &Path) -> PathBuf {
    processed_dir(run).join("ps")
}
