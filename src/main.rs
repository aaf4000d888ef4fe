//! The `rigd` command line: parses the arguments and hands each command to
//! its module in `src/cli/`; an error ends the process with the exit code
//! of its class (`cli::exit`).
#![warn(missing_docs)]

mod cli;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

use cli::{
    camera, dataset, exit, frame, holder, internal, plan, process, profile, rig, run, serve,
};
#[cfg(feature = "sim")]
use cli::{sim, tradeoff};

#[derive(Parser)]
#[command(
    name = "rigd",
    version,
    about = "Control daemon for BTF measurement rigs",
    long_about = "Control daemon for BTF (bidirectional texture function) measurement rigs: \
plans captures over the hemisphere, drives the rig (or its simulation), and writes datasets that lose nothing.",
    after_help = exit::exit_codes_help()
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Show sampling plans.
    Plan {
        #[command(subcommand)]
        command: plan::PlanCmd,
    },
    /// Check rig profiles.
    Profile {
        #[command(subcommand)]
        command: profile::ProfileCmd,
    },
    /// Bring up a rig: check every device without moving anything.
    Rig {
        #[command(subcommand)]
        command: rig::RigCmd,
    },
    /// The sample holder plate: print its template, check it in a frame.
    Holder {
        #[command(subcommand)]
        command: holder::HolderCmd,
    },
    /// Calibrate a camera: its colour from a photographed colour chart.
    Camera {
        #[command(subcommand)]
        command: camera::CameraCmd,
    },
    /// Capture a BTF: run a plan on a rig into a run directory, or resume one.
    Run(run::RunArgs),
    /// Run the daemon: the HTTP API (/api/v1, docs at /api/docs) driving one
    /// run at a time, with a queue. SIGINT/SIGTERM pause the active run
    /// (resumable after restart) and stop.
    Serve(serve::ServeArgs),
    /// Write a rectified run's textures for existing BTF tools: `utia` (a
    /// folder per view of tl…_pl…_tv…_pv….png) or `ubo2003` (a zip of
    /// `tl… pl… tv… pv….jpg`, integer degrees, as the Bonn 2003 database).
    Export(dataset::ExportArgs),
    /// What accuracy costs in time on this rig and material: sampling plans
    /// (H2, H1, ring subsets, grids, a dense reference) against held-out BTF
    /// error, PCA components, the simulator's effects against render time,
    /// the laser's sources, photometric stereo's lights, and the exposure
    /// policies against held-out error near the mirror direction; prints
    /// the table and writes tradeoff.csv, tradeoff.json and tradeoff.svg (a
    /// panel per family) into --out.
    #[cfg(feature = "sim")]
    Tradeoff(tradeoff::TradeoffArgs),
    /// Read textures in an export format (ours or a database's) into
    /// OUT/processed/normtextures/, ready for `rigd process btf OUT`.
    Import(dataset::ImportArgs),
    /// Turn captured frames into results: photometric stereo,
    /// rectification, BTF compression, reflectance fits, the MDF.
    Process {
        #[command(subcommand)]
        command: process::ProcessCmd,
    },
    /// Camera files: what rigd makes of one (DNG, vendor raw, TIFF, JPEG).
    Frame {
        #[command(subcommand)]
        command: frame::FrameCmd,
    },
    /// What rigd runs of itself (the camera-file decoder child).
    #[command(hide = true)]
    Internal {
        #[command(subcommand)]
        command: internal::InternalCmd,
    },
    /// The simulated rig's firmware, for tools outside rigd.
    #[cfg(feature = "sim")]
    Sim {
        #[command(subcommand)]
        command: sim::SimCmd,
    },
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    // Simulated runs' results are measured against their scene.
    #[cfg(feature = "sim")]
    rigd::truth::install();
    let result = match Cli::parse().command {
        Cmd::Plan { command } => plan::run(command),
        Cmd::Profile { command } => profile::run(command),
        Cmd::Rig { command } => rig::run(command),
        Cmd::Holder { command } => holder::run(command),
        Cmd::Camera { command } => camera::run(command),
        Cmd::Run(args) => run::run(args),
        Cmd::Serve(args) => serve::run(args),
        Cmd::Export(args) => dataset::export(args),
        Cmd::Import(args) => dataset::import(args),
        #[cfg(feature = "sim")]
        Cmd::Tradeoff(args) => tradeoff::run(args),
        Cmd::Process { command } => process::run(command),
        Cmd::Frame { command } => frame::run(command),
        Cmd::Internal { command } => internal::run(command),
        #[cfg(feature = "sim")]
        Cmd::Sim { command } => sim::run(command),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {}", exit::describe(&e));
            ExitCode::from(exit::exit_code_of(&e))
        }
    }
}
