//! Per-run processing: what `rigd process`, the daemon and the trade-off
//! report do with a run directory. Each step reads what `rigd_process`
//! needs from the run (frames, directions, the holder), runs it, and
//! writes into `RUN/processed/` ([`crate::store::processed`]).

pub mod accuracy;
pub mod btf;
pub mod chart;
pub mod dataset;
pub mod executor;
pub mod fit;
pub mod frames;
pub mod holder_check;
pub mod holder_template;
pub mod job;
pub mod mdf;
pub mod mdf_texture;
pub mod parts;
pub mod pipeline;
pub mod ps;
pub mod rectify;
pub mod slot_textures;
pub mod slurm;
pub mod viewer;

/// The colour calibration is rectification's: re-exported where the
/// commands look for it.
pub use rectify::colour;

use std::path::PathBuf;

/// Why a processing step failed.
#[derive(Debug, thiserror::Error)]
pub enum ProcessError {
    /// The run directory could not be read or written.
    #[error("{0}")]
    Store(#[from] crate::store::StoreError),
    /// A frame that cannot be read or decoded.
    #[error("{path}: {message}")]
    Frame {
        /// The frame's file.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// A frame whose bytes are not those its journal line vouches for: its
    /// SHA-256 differs (bits damaged on disk, or another frame's file). It
    /// is never used as measured.
    #[error("{path}: image {index} is damaged: the file's SHA-256 is {found:.16}…, its journal line recorded {expected:.16}…")]
    Damaged {
        /// The frame's file.
        path: PathBuf,
        /// The image's index in the run.
        index: usize,
        /// The SHA-256 the journal recorded, lowercase hex.
        expected: String,
        /// The SHA-256 of the file as read, lowercase hex.
        found: String,
    },
    /// Options or data the step cannot work with.
    #[error("{0}")]
    Invalid(String),
}

impl ProcessError {
    /// A step's write into the run failed in the system: the system's
    /// error is kept, so a read-only or full disk is classed as the
    /// failure it is, not as bad input.
    pub fn io(path: &std::path::Path, op: &'static str, error: std::io::Error) -> ProcessError {
        ProcessError::Store(crate::store::StoreError::Io {
            path: path.to_path_buf(),
            op,
            error,
        })
    }
}

/// Creates a folder a step writes into (and its parents), as
/// [`ProcessError::io`] reports a failure.
pub fn create_dir(dir: &std::path::Path) -> Result<(), ProcessError> {
    std::fs::create_dir_all(dir).map_err(|e| ProcessError::io(dir, "create directory", e))
}
