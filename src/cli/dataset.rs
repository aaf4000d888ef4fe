//! `rigd export` and `rigd import`: a rectified run's textures in the
//! formats existing BTF tools read, and back.

use std::path::PathBuf;

use std::process::ExitCode;

use anyhow::Result;
use clap::Args;

use super::exit::bad_input;

#[derive(Args)]
pub struct ExportArgs {
    /// The run directory (after `rigd process rectify`).
    pub run: PathBuf,
    /// utia or ubo2003.
    #[arg(long)]
    pub format: rigd_process::export::Format,
    /// A folder (utia) or a .zip file (ubo2003).
    #[arg(long)]
    pub out: PathBuf,
    /// JPEG quality for ubo2003, 1 ..= 100.
    #[arg(long, default_value_t = 95)]
    pub quality: u8,
}

#[derive(Args)]
pub struct ImportArgs {
    /// A utia folder or a ubo2003 zip.
    pub path: PathBuf,
    /// utia or ubo2003.
    #[arg(long)]
    pub format: rigd_process::export::Format,
    /// Directory to create the normtextures in.
    #[arg(long)]
    pub out: PathBuf,
}

/// Runs `rigd export`.
pub fn export(args: ExportArgs) -> Result<ExitCode> {
    if !(1..=100).contains(&args.quality) {
        return Err(bad_input(format!(
            "--quality {}: expected 1 ..= 100",
            args.quality
        )));
    }
    let n =
        rigd::postprocess::dataset::export_run(&args.run, args.format, &args.out, args.quality)?;
    println!("{n} textures written to {}", args.out.display());
    Ok(ExitCode::SUCCESS)
}

/// Runs `rigd import`.
pub fn import(args: ImportArgs) -> Result<ExitCode> {
    let index = rigd::postprocess::dataset::import_textures(args.format, &args.path, &args.out)?;
    println!(
        "{} textures ({} views × {} lights, {}²) in {}",
        index.frames.len(),
        index.views.len(),
        index.lights.len(),
        index.size,
        args.out.join("processed/normtextures").display()
    );
    Ok(ExitCode::SUCCESS)
}
