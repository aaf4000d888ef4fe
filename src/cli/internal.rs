//! `rigd internal …`: what rigd runs of itself, hidden from `--help`. A
//! camera file is decoded in a child process (`rigd internal
//! decode-frame`), so a file that makes a decoder abort or hang takes
//! only that child down (`rigd::rig::camera_file`).

use std::process::ExitCode;

use clap::Subcommand;

use rigd::rig::camera_file::{self, DEFAULT_MEMORY};

/// The internal commands.
#[derive(Subcommand)]
pub enum InternalCmd {
    /// Decode the camera file on stdin and write the image to stdout in
    /// rigd's record form (a JSON header, then the samples).
    DecodeFrame {
        /// Address-space limit in bytes, set before anything is read.
        #[arg(long, default_value_t = DEFAULT_MEMORY)]
        memory: u64,
        /// Decode file after file, each prefixed by its length, until
        /// stdin ends.
        #[arg(long)]
        batch: bool,
        /// The file's length in bytes, when the parent knows it.
        #[arg(long)]
        size: Option<u64>,
    },
}

/// Runs an internal command.
pub fn run(cmd: InternalCmd) -> anyhow::Result<ExitCode> {
    match cmd {
        InternalCmd::DecodeFrame {
            memory,
            batch,
            size,
        } => {
            camera_file::serve(memory, batch, size)?;
            Ok(ExitCode::SUCCESS)
        }
    }
}
