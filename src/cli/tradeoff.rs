//! `rigd tradeoff`: what accuracy costs in time on a rig and material.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use rigd::model::profile::DEFAULT_PROFILE;

use super::exit::bad_input;
use super::progress::hms;

#[derive(Args)]
pub struct TradeoffArgs {
    /// Rig profile: a TOML file or an embedded profile name.
    #[arg(long, default_value = DEFAULT_PROFILE)]
    pub profile: String,
    /// The material: a built-in scene or a scene file.
    #[arg(long, default_value = "corduroy")]
    pub scene: String,
    /// Where to write tradeoff.csv, .json and .svg.
    #[arg(long, default_value = ".")]
    pub out: PathBuf,
    /// Side of the normtextures, texels.
    #[arg(long, default_value_t = 16)]
    pub texture: usize,
    /// Held-out (light, view) pairs.
    #[arg(long, default_value_t = 24)]
    pub held_out: usize,
    /// PCA components for the plan rows.
    #[arg(long, default_value_t = 16)]
    pub components: usize,
    /// Frame size of the fidelity renders, WIDTHxHEIGHT.
    #[arg(long, default_value = "256x192", value_parser = rigd::model::text::parse_frame_size)]
    pub render_size: [u32; 2],
    /// Answer with the most accurate measured plan whose physical capture
    /// time fits this budget (3h, 90m, 2h30m): prints that plan and the
    /// frontier instead of the table.
    #[arg(long, conflicts_with = "target")]
    pub budget: Option<String>,
    /// Answer with the fastest measured plan whose held-out error is at
    /// most this (15% or 0.15).
    #[arg(long)]
    pub target: Option<String>,
    /// Use a report already written (its tradeoff.json, or the folder
    /// holding it) instead of computing one: answer --budget or --target
    /// from it, or, with neither, draw its tradeoff.svg again (with the
    /// default plan of the report's profile ringed).
    #[arg(long)]
    pub from: Option<PathBuf>,
}

/// Runs `rigd tradeoff`.
pub fn run(args: TradeoffArgs) -> Result<ExitCode> {
    use rigd::tradeoff::choice::Goal;
    let goal = match (&args.budget, &args.target) {
        (Some(b), _) => Some(Goal::budget(b).map_err(bad_input)?),
        (None, Some(t)) => Some(Goal::target(t).map_err(bad_input)?),
        (None, None) => None,
    };
    if let Some(from) = &args.from {
        let path = if from.is_dir() {
            from.join("tradeoff.json")
        } else {
            from.clone()
        };
        let bytes = rigd_core::read::read_bounded(&path, rigd::tradeoff::REPORT_LIMIT)
            .map_err(std::io::Error::from)
            .context("cannot read the report")?;
        let report = rigd::tradeoff::read_report(&bytes)
            .map_err(|e| bad_input(format!("{}: {e}", path.display())))?;
        let Some(goal) = goal else {
            let folder = path.parent().unwrap_or(std::path::Path::new("."));
            let marked = rigd::rig::load_profile(&report.profile)
                .ok()
                .map(|p| p.default_plan);
            rigd::tradeoff::redraw(folder, &report, marked.as_deref())?;
            println!("wrote {}", folder.join("tradeoff.svg").display());
            return Ok(ExitCode::SUCCESS);
        };
        return answer(&report.rows, goal);
    }
    let profile = rigd::rig::load_profile(&args.profile)?;
    let cfg = rigd::tradeoff::TradeoffConfig {
        texture: args.texture,
        held_out: args.held_out,
        components: args.components,
        render_size: args.render_size,
    };
    let started = Instant::now();
    let report = rigd::tradeoff::run(&profile, &args.scene, &cfg, &args.out, &|what| {
        eprintln!(
            "tradeoff: {what} ({:.0} s)",
            started.elapsed().as_secs_f64()
        );
    })?;
    if let Some(goal) = goal {
        eprintln!("wrote {}/tradeoff.{{csv,json,svg}}", args.out.display());
        println!(
            "{} on {}, {}² textures, {} held-out pairs",
            report.scene, report.profile, report.texture, report.held_out
        );
        return answer(&report.rows, goal);
    }
    println!(
        "{} on {}, {}² textures, {} held-out pairs",
        report.scene, report.profile, report.texture, report.held_out
    );
    println!("family\tsetting\timages\tphysical time\tbytes\terror\tcompute\tdetail");
    for r in &report.rows {
        println!(
            "{}\t{}\t{}\t{}\t{}\t{}\t{}\t{}",
            r.family,
            r.setting,
            r.images
                .map(|x| x.to_string())
                .unwrap_or_else(|| "-".into()),
            r.physical_s.map(hms).unwrap_or_else(|| "-".into()),
            r.bytes
                .map(|b| format!("{:.1} MB", b as f64 / 1e6))
                .unwrap_or_else(|| "-".into()),
            error_text(r),
            r.compute_s
                .map(|t| format!("{t:.2} s"))
                .unwrap_or_else(|| "-".into()),
            r.detail.as_deref().unwrap_or(""),
        );
    }
    for m in &report.method {
        println!("note: {m}");
    }
    for line in &report.summary {
        println!("summary: {line}");
    }
    println!("wrote {}/tradeoff.{{csv,json,svg}}", args.out.display());
    Ok(ExitCode::SUCCESS)
}

/// A row's error with its standard error, in the row's unit.
fn error_text(r: &rigd::tradeoff::Row) -> String {
    let Some(e) = r.error else {
        return "-".into();
    };
    let (scale, digits, unit) = match r.unit.as_str() {
        "relative" => (100.0, 2, " %".to_string()),
        "degrees" => (1.0, 2, "°".to_string()),
        other => (1.0, 3, format!(" {other}")),
    };
    match r.spread {
        Some(s) => format!("{:.digits$} ± {:.digits$}{unit}", e * scale, s * scale),
        None => format!("{:.digits$}{unit}", e * scale),
    }
}

/// Prints the plan that answers `goal` among the report's plans, and the
/// frontier it was chosen from.
fn answer(rows: &[rigd::tradeoff::Row], goal: rigd::tradeoff::choice::Goal) -> Result<ExitCode> {
    use rigd::tradeoff::choice::{choose, ChoiceError};
    match choose(&rigd::tradeoff::plan_points(rows), goal) {
        Ok(c) => {
            println!("{}", c.answer);
            println!("frontier (no measured plan is both faster and more accurate):");
            for p in &c.frontier {
                println!(
                    "  {}{}\t{}\t{:.2} %",
                    p.setting,
                    if *p == c.plan { " (chosen)" } else { "" },
                    hms(p.physical_s),
                    100.0 * p.error
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        Err(e @ ChoiceError::NoPlans) => Err(bad_input(e.to_string())),
        Err(e @ ChoiceError::NoneFits(_)) => {
            println!("{e}");
            Ok(ExitCode::from(1))
        }
    }
}
