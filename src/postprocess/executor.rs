//! Where a run's processing steps run: here (`local`, rayon over this
//! machine's cores) or as job arrays on a Slurm cluster (`slurm`,
//! [`super::slurm`]). The result is the same files either way.

use std::path::Path;

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::pipeline::{ProcessOptions, ProcessStep, StepProgress};
use super::slurm::{Cancel, Notes, SlurmConfig, SlurmError};

/// Which executor runs the steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum ExecutorKind {
    /// On this machine.
    #[default]
    Local,
    /// As Slurm job arrays, on the shared filesystem.
    Slurm,
}

/// The daemon's `[processing]` table, and the options of `rigd process …
/// --executor`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct ProcessingConfig {
    /// `local` or `slurm`.
    pub executor: ExecutorKind,
    /// The cluster's settings, used with `executor = "slurm"`.
    pub slurm: SlurmConfig,
}

impl ProcessingConfig {
    /// Checks what can be checked before anything runs on the run at
    /// `root` (nothing for `local`).
    pub fn check(&self, root: &Path) -> Result<(), SlurmError> {
        match self.executor {
            ExecutorKind::Local => Ok(()),
            ExecutorKind::Slurm => self.slurm.check(root),
        }
    }

    /// Runs one step with this executor; returns its one-line summary.
    pub fn run_step(
        &self,
        root: &Path,
        step: ProcessStep,
        opts: &ProcessOptions,
        progress: StepProgress<'_>,
        notes: Notes<'_>,
        cancel: Cancel<'_>,
    ) -> Result<String, SlurmError> {
        match self.executor {
            ExecutorKind::Local => Ok(super::pipeline::run_step(root, step, opts, progress)?),
            ExecutorKind::Slurm => self
                .slurm
                .run_step(root, step, opts, progress, notes, cancel),
        }
    }
}
