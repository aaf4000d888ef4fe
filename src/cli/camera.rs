//! `rigd camera colour`: a camera's colour calibration from a photograph of
//! a colour chart (see `docs/colour.md`).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::{Args, Subcommand};
use rigd::postprocess::chart::{read_chart, ChartReport, ColourCalibrationFile, CORNER_POSITIONS};
use rigd_process::colour::chart_fit::fit_chart;

use super::exit::bad_input;

#[derive(Subcommand)]
pub enum CameraCmd {
    /// Fit a camera's colour correction on a photographed colour chart: a
    /// 3x3 matrix and a root-polynomial, each patch's CIEDE2000 difference
    /// in the fit and left out of it, the better correction chosen.
    Colour(ColourArgs),
}

#[derive(Args)]
pub struct ColourArgs {
    /// The camera file (DNG, vendor raw, TIFF or JPEG).
    file: PathBuf,
    /// The chart in the photograph.
    #[arg(long, default_value = "colorchecker24")]
    chart: String,
    /// The patch grid's outer corners in pixels of the decoded image, as
    /// X,Y: top left (dark skin's), top right (bluish green's), bottom
    /// right (black 2's), bottom left (white 9.5's).
    // A negative X is a corner (refused as off the image), not an option.
    #[arg(
        long,
        num_args = 4,
        value_names = ["X,Y", "X,Y", "X,Y", "X,Y"],
        required = true,
        allow_hyphen_values = true
    )]
    corners: Vec<String>,
    /// Print the result as JSON instead of a table.
    #[arg(long)]
    json: bool,
    /// Also write the chosen calibration to this file (JSON).
    #[arg(long)]
    save: Option<PathBuf>,
}

/// Runs a `rigd camera` command.
pub fn run(cmd: CameraCmd) -> Result<ExitCode> {
    match cmd {
        CameraCmd::Colour(args) => colour(args)?,
    }
    Ok(ExitCode::SUCCESS)
}

/// `X,Y` as two finite numbers; which corner it is in the message.
fn parse_corner(number: usize, text: &str) -> Result<[f64; 2]> {
    let position = CORNER_POSITIONS[number - 1];
    let malformed = || {
        bad_input(format!(
            "--corners: corner {number} ({position}) `{text}` is not X,Y in pixels (two numbers, \
             e.g. 120.5,80)"
        ))
    };
    let (x, y) = text.split_once(',').ok_or_else(malformed)?;
    let x: f64 = x.trim().parse().map_err(|_| malformed())?;
    let y: f64 = y.trim().parse().map_err(|_| malformed())?;
    if !(x.is_finite() && y.is_finite()) {
        return Err(malformed());
    }
    Ok([x, y])
}

fn colour(args: ColourArgs) -> Result<()> {
    let Some(chart) = rigd_core::chart::chart(&args.chart) else {
        let known: Vec<&str> = rigd_core::chart::CHARTS.iter().map(|c| c.name).collect();
        return Err(bad_input(format!(
            "--chart: unknown chart `{}`; known: {}",
            args.chart,
            known.join(", ")
        )));
    };
    if args.corners.len() != 4 {
        return Err(bad_input(format!(
            "--corners: {} given, 4 needed ({})",
            args.corners.len(),
            CORNER_POSITIONS.join(", ")
        )));
    }
    let mut corners = [[0.0; 2]; 4];
    for (i, text) in args.corners.iter().enumerate() {
        corners[i] = parse_corner(i + 1, text)?;
    }
    let name = args.file.display().to_string();
    // A path that is no readable camera file is the caller's input.
    let bytes = rigd_core::read::read_bounded(&args.file, rigd_core::read::IMAGE_LIMIT)
        .map_err(|e| bad_input(format!("cannot read {e}")))?;
    let image =
        rigd::rig::camera_file::decode(&bytes).map_err(|e| bad_input(format!("{name}: {e}")))?;
    let readings =
        read_chart(&image, chart, corners).map_err(|e| bad_input(format!("{name}: {e}")))?;
    let fit = fit_chart(&readings).map_err(|e| bad_input(format!("{name}: {e}")))?;
    let report = ChartReport::new(chart, &readings, &fit);
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", table(&report));
    }
    if let Some(path) = &args.save {
        ColourCalibrationFile::new(chart, &name, &image, &fit).write(path)?;
        if !args.json {
            println!("-> {}", path.display());
        }
    }
    Ok(())
}

fn table(r: &ChartReport) -> String {
    let lab = |v: [f64; 3]| format!("{:6.2} {:7.2} {:7.2}", v[0], v[1], v[2]);
    let opt = |v: Option<f64>| v.map_or("     -".into(), |v| format!("{v:6.2}"));
    let mut out = format!(
        "{:<14} {:>22}   {:>22}   {:>6} {:>8}\n",
        "patch", "reference L*a*b*", "corrected L*a*b*", "dE00", "left out"
    );
    for p in &r.patches {
        out.push_str(&format!(
            "{:<14} {}   {}   {:6.2} {:>8}\n",
            p.name,
            lab(p.reference_lab_d50),
            lab(p.lab_d50),
            p.delta_e2000,
            opt(p.delta_e2000_left_out)
        ));
    }
    for (name, f) in [
        ("3x3 matrix", &r.fits.matrix),
        ("root-polynomial", &r.fits.root_polynomial),
    ] {
        out.push_str(&format!(
            "{name:<16} dE00 mean {:.2} max {:.2}; left out mean {} max {}\n",
            f.mean_delta_e2000,
            f.max_delta_e2000,
            opt(f.mean_delta_e2000_left_out).trim(),
            opt(f.max_delta_e2000_left_out).trim()
        ));
    }
    let chosen = match r.correction {
        rigd_process::colour::chart_fit::CorrectionKind::Matrix => "3x3 matrix",
        rigd_process::colour::chart_fit::CorrectionKind::RootPolynomial => "root-polynomial",
    };
    out.push_str(&format!("chosen: {chosen} (lower mean dE00 left out)\n"));
    if let Some(wb) = r.white_balance {
        out.push_str(&format!(
            "white balance (neutral patches): {:.3} {:.3} {:.3}\n",
            wb[0], wb[1], wb[2]
        ));
    }
    out
}
