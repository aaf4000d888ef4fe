//! `rigd rig check`: bring-up without moving anything.

use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use rigd::model::profile::DEFAULT_PROFILE;
use rigd_core::Clock;

/// `rigd rig …`.
#[derive(Subcommand)]
pub enum RigCmd {
    /// Bring-up without moving anything: connect every device of the
    /// profile through the same drivers and deadlines as a run and print
    /// one line per device: identity, firmware, controller settings
    /// compared with the profile, homing mode, position or state; OK, or
    /// what is wrong and the fix. Nothing is homed, moved or switched (an
    /// axis with `configure = true` gets its GRBL settings written). Exit
    /// status 0 only when every device is usable, 1 when one is not.
    Check(CheckArgs),
}

/// Arguments of `rigd rig check`.
#[derive(Args)]
pub struct CheckArgs {
    /// Rig profile: a TOML file or an embedded name. Without it, the
    /// embedded default profile's simulated rig.
    #[arg(long)]
    pub profile: Option<String>,
    /// Check the profile's simulated rig instead of its hardware.
    #[arg(long)]
    pub sim: bool,
    /// Print the report as JSON (the same as GET /api/v1/rig/check).
    #[arg(long)]
    pub json: bool,
}

/// Runs a `rigd rig` command.
pub fn run(cmd: RigCmd) -> Result<ExitCode> {
    match cmd {
        RigCmd::Check(args) => check(args),
    }
}

fn check(args: CheckArgs) -> Result<ExitCode> {
    let simulated = args.sim || args.profile.is_none();
    let source = args
        .profile
        .clone()
        .unwrap_or_else(|| DEFAULT_PROFILE.to_string());
    let profile = rigd::rig::load_profile(&source)?;
    // As for a run: the simulated rig in virtual time, hardware on the wall
    // clock.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .start_paused(simulated)
        .build()
        .context("cannot start the runtime")?;
    let report = runtime.block_on(async {
        if simulated {
            simulated_check(&profile).await
        } else {
            Ok(rigd::rig::hardware::check(&profile, &Clock::real()).await)
        }
    })?;
    super::exit::print_check(&report, report.lines(), args.json, report.usable)
}

#[cfg(feature = "sim")]
async fn simulated_check(
    profile: &rigd::model::profile::Profile,
) -> Result<rigd::rig::check::RigCheck> {
    let solver = rigd::kinematics::Solver::new(profile)?;
    rigd::rig::sim::check(profile, std::sync::Arc::new(solver), &Clock::virtual_time())
        .await
        .context("cannot set up the simulated rig")
}

#[cfg(not(feature = "sim"))]
async fn simulated_check(_: &rigd::model::profile::Profile) -> Result<rigd::rig::check::RigCheck> {
    Err(super::exit::bad_input(
        "this rigd was built without the simulator: give --profile FILE for hardware",
    ))
}
