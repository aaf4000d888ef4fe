//! `rigd profile check` and `rigd profile list`.

use std::process::ExitCode;

use anyhow::Result;
use clap::Subcommand;

#[derive(Subcommand)]
pub enum ProfileCmd {
    /// Parse and validate a profile; print a one-line summary.
    Check {
        /// A TOML file or an embedded profile name.
        profile: String,
    },
    /// List the embedded profiles.
    List,
}

/// Runs a `rigd profile` command.
pub fn run(cmd: ProfileCmd) -> Result<ExitCode> {
    match cmd {
        ProfileCmd::Check { profile } => {
            let p = rigd::rig::load_profile(&profile)?;
            println!(
                "{}: ok: profile `{}`, {} devices, default plan {}",
                profile,
                p.name,
                p.devices.len(),
                p.default_plan
            );
        }
        ProfileCmd::List => {
            for (name, _) in rigd::model::profile::EMBEDDED {
                let p = rigd::rig::load_profile(name)?;
                println!("{name}\t{}", p.description);
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}
