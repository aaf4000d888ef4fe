//! `rigd tradeoff`: what accuracy costs in time on a rig and material.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Result;
use clap::Args;
use rigd::model::profile::DEFAULT_PROFILE;

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
}

/// Runs `rigd tradeoff`.
pub fn run(args: TradeoffArgs) -> Result<ExitCode> {
    let profile = rigd::plan::load_profile(&args.profile)?;
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
            r.error
                .map(|e| match r.unit.as_str() {
                    "relative" => format!("{:.2} %", 100.0 * e),
                    "degrees" => format!("{e:.2}°"),
                    unit => format!("{e:.3} {unit}"),
                })
                .unwrap_or_else(|| "-".into()),
            r.compute_s
                .map(|t| format!("{t:.2} s"))
                .unwrap_or_else(|| "-".into()),
            r.detail.as_deref().unwrap_or(""),
        );
    }
    for m in &report.method {
        println!("note: {m}");
    }
    println!("wrote {}/tradeoff.{{csv,json,svg}}", args.out.display());
    Ok(ExitCode::SUCCESS)
}
