//! `rigd holder`: the sample holder plate a profile describes: its
//! printable template, and the check of a frame of it on the rig.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::{Args, Subcommand};
use rigd::model::profile::DEFAULT_PROFILE;
use rigd::postprocess::holder_check::{check_frame, read_frame};
use rigd::postprocess::holder_template::{write_template, TemplateError, TemplateFormat};
use rigd_core::geometry::Direction;

use super::exit::bad_input;

/// `rigd holder …`.
#[derive(Subcommand)]
pub enum HolderCmd {
    /// Draw the profile's holder plate to scale, to print: the plate in its
    /// grey, the point markers, the border lines, the sample window, the
    /// colour patches and white areas, and a 100 mm line to check the
    /// print's scale. The format is the extension of --out: .svg or .pdf.
    Template(TemplateArgs),
    /// Find the holder in one frame (a camera file, or a PNG test frame as
    /// `rigd sim render` writes it): every marker where the profile's
    /// camera model predicts it, the registration's residual, and each
    /// colour patch's and white area's mean. Exit 0 when every marker is
    /// found and nothing is clipped, 1 naming what is missing or clipped.
    Check(CheckArgs),
}

/// Arguments of `rigd holder template`.
#[derive(Args)]
pub struct TemplateArgs {
    /// Rig profile: a TOML file or an embedded name [default: the embedded
    /// default profile].
    #[arg(long)]
    pub profile: Option<String>,
    /// Output file: FILE.svg or FILE.pdf.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

/// Arguments of `rigd holder check`.
#[derive(Args)]
pub struct CheckArgs {
    /// The frame: a camera file (DNG, raw, JPEG, TIFF) or a PNG.
    pub frame: PathBuf,
    /// Rig profile: a TOML file or an embedded name [default: the embedded
    /// default profile].
    #[arg(long)]
    pub profile: Option<String>,
    /// View direction θ,φ in degrees, sample frame [default: the test
    /// frame's, else frontal 0,0].
    #[arg(long, value_parser = rigd::model::text::parse_direction)]
    pub view: Option<Direction>,
    /// Camera of the profile [default: the test frame's, else the
    /// profile's first].
    #[arg(long)]
    pub camera: Option<String>,
    /// Print the report as one JSON object.
    #[arg(long)]
    pub json: bool,
}

/// Runs a `rigd holder` command.
pub fn run(cmd: HolderCmd) -> Result<ExitCode> {
    match cmd {
        HolderCmd::Template(args) => template(args),
        HolderCmd::Check(args) => check(args),
    }
}

fn profile_source(profile: &Option<String>) -> String {
    profile
        .clone()
        .unwrap_or_else(|| DEFAULT_PROFILE.to_string())
}

fn template(args: TemplateArgs) -> Result<ExitCode> {
    // Refused before the profile is read: nothing else can be wrong first.
    if TemplateFormat::of_path(&args.out).is_none() {
        return Err(bad_input(format!(
            "--out {}: expected a file name ending in .svg or .pdf",
            args.out.display()
        )));
    }
    let profile = rigd::rig::load_profile(&profile_source(&args.profile))?;
    let drawing =
        write_template(&profile.name, &profile.holder, &args.out).map_err(|e| match e {
            TemplateError::Holder(_) | TemplateError::Format(_) => bad_input(e.to_string()),
            e => anyhow::Error::new(e).context(format!("cannot write {}", args.out.display())),
        })?;
    println!(
        "{}: holder `{}` of profile `{}`, page {:.0} × {:.0} mm; print at 100 % and check the 100 mm line",
        args.out.display(),
        profile.holder.name,
        profile.name,
        drawing.page_mm[0],
        drawing.page_mm[1]
    );
    Ok(ExitCode::SUCCESS)
}

fn check(args: CheckArgs) -> Result<ExitCode> {
    let profile = rigd::rig::load_profile(&profile_source(&args.profile))?;
    let frame = read_frame(&args.frame, &profile, args.camera.as_deref())
        .map_err(|e| bad_input(e.to_string()))?;
    let mut pose = frame.pose;
    if let Some(view) = args.view {
        pose.view = view;
    }
    if let Some(camera) = args.camera {
        // A test frame's focal length is its own camera's.
        if pose.camera.as_deref() != Some(camera.as_str()) {
            pose.focal_px = None;
        }
        pose.camera = Some(camera);
    }
    let report =
        check_frame(&profile, &frame.image, &pose).map_err(|e| bad_input(e.to_string()))?;
    super::exit::print_check(&report, report.lines(), args.json, report.ok)
}
