//! `rigd plan show`: every image of a plan with its directions,
//! feasibility and set-points, the estimated physical capture time and
//! the raw data volume.

use std::process::ExitCode;

use anyhow::Result;
use clap::Subcommand;
use rigd::model::exposure::ExposurePolicy;
use rigd::model::profile::DEFAULT_PROFILE;
use rigd::plan::Order;
use rigd::schedule::timing::{parse_exposure_s, Timing};
use rigd::store::human_bytes;

use super::progress::hms;

#[derive(Subcommand)]
pub enum PlanCmd {
    /// List every image of a plan with its directions, feasibility and set-points,
    /// and the totals: image count, estimated physical capture time and raw
    /// data volume.
    Show {
        /// h1, h2, grid12x8, lamps, or a plan file (.json/.toml)
        plan: String,
        /// Rig profile: a TOML file or an embedded profile name.
        #[arg(long, default_value = DEFAULT_PROFILE)]
        profile: String,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
        /// Exposure time for every camera, seconds, up to 3600 and within
        /// each camera's `timing.exposure_range_s` (default: the profile's).
        #[arg(long, allow_negative_numbers = true, value_parser = parse_exposure_s)]
        exposure: Option<f64>,
        /// Trigger order: optimised (the shortest physical time under the
        /// motion model), slots (the shortest with each view's triggers
        /// together, so view slots complete early) or naive (the plan's
        /// nested loops).
        #[arg(long, value_enum, default_value_t = Order::Optimised)]
        order: Order,
        /// Exposures per step, as `rigd run --exposure-policy` takes them
        /// (default: the profile's `[exposure_policy]`): `brackets:…`
        /// multiplies the time and data of every step; `auto` is estimated
        /// as if nothing clipped, or with `--scene` from what that scene is
        /// expected to clip.
        #[arg(long, value_name = "POLICY")]
        exposure_policy: Option<ExposurePolicy>,
        /// With `auto`: the simulated scene (`rigd sim scenes`) whose
        /// expected clipping the estimate counts, by the trade-off report's
        /// texture-space model (8² texels; docs/tradeoff.md, exposure).
        #[cfg(feature = "sim")]
        #[arg(long, value_name = "NAME")]
        scene: Option<String>,
    },
}

/// Runs a `rigd plan` command.
pub fn run(cmd: PlanCmd) -> Result<ExitCode> {
    match cmd {
        PlanCmd::Show {
            plan,
            profile,
            json,
            exposure,
            order,
            exposure_policy,
            #[cfg(feature = "sim")]
            scene,
        } => {
            #[cfg(not(feature = "sim"))]
            let scene = None;
            show(
                &plan,
                &profile,
                json,
                exposure,
                order,
                exposure_policy,
                scene,
            )?
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn show(
    plan: &str,
    profile: &str,
    json: bool,
    exposure: Option<f64>,
    order: Order,
    policy: Option<ExposurePolicy>,
    scene: Option<String>,
) -> Result<()> {
    let profile = rigd::rig::load_profile(profile)?;
    if let Some(e) = exposure {
        profile
            .check_exposure_override(e)
            .map_err(|why| super::exit::bad_input(format!("--exposure {why}")))?;
    }
    let policy = policy.unwrap_or_else(|| profile.exposure_policy.clone());
    profile
        .check_exposure_policy(&policy, exposure)
        .map_err(|(key, why)| super::exit::bad_input(format!("exposure_policy.{key}: {why}")))?;
    let solver = rigd::kinematics::Solver::new(&profile)?;
    let offer = rigd::schedule::rig_offer(&profile, &solver);
    let mut resolved = rigd::plan::resolve(plan, &offer)?;
    if resolved.laser.is_none() {
        resolved.order = order;
    }
    let (schedule, report) = rigd::schedule::build_with_report(&profile, &solver, &resolved);
    let timing = Timing::new(&profile, exposure).with_exposure_policy(&policy);
    let retakes = match (policy.auto(), scene) {
        (Some(auto), Some(scene)) => Some(expected_retakes(
            &profile, &schedule, auto, exposure, &scene,
        )?),
        (None, Some(_)) => {
            return Err(super::exit::bad_input(
                "--scene: only an `auto` exposure policy depends on the scene",
            ))
        }
        _ => None,
    };
    let estimate = match &retakes {
        Some(r) => {
            timing.estimate_with_retakes_s(&schedule, |_| false, |t| r.get(t).copied().unwrap_or(0))
        }
        None => timing.estimate_s(&schedule, |_| false),
    };
    let retaken = retakes
        .as_ref()
        .map(|r| r.iter().filter(|&&k| k > 0).count());
    let infeasible = schedule.infeasible().count();
    let volume = rigd::schedule::volume::data_volume(&profile, &schedule, &policy);
    if json {
        let steps: Vec<_> = schedule.steps().collect();
        let out = serde_json::json!({
            "plan": schedule.plan,
            "profile": schedule.profile,
            "steps_total": schedule.images.len(),
            "triggers_total": schedule.triggers.len(),
            "infeasible_total": infeasible,
            "estimated_physical_s": estimate,
            "expected_retaken_triggers": retaken,
            "raw_bytes": volume.raw_bytes,
            "image_bytes": volume.largest_image_bytes,
            "order": resolved.order,
            "order_report": report,
            "steps": steps,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!(
        "{:>6} {:>6} {:<8} {:>14} {:>14} {:<8} set-points",
        "image", "trig", "camera", "light θ/φ", "view θ/φ", "feasible"
    );
    for img in &schedule.images {
        let sp = &schedule.triggers[img.trigger].setpoints;
        let mut points: Vec<String> = sp.axes.iter().map(|(k, v)| format!("{k}={v:.3}")).collect();
        if let Some(arm) = &sp.arm {
            points.push(format!(
                "arm=[{}]",
                arm.iter()
                    .map(|q| format!("{q:.3}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
        points.push(format!("lamp={}", sp.lamp));
        println!(
            "{:>6} {:>6} {:<8} {:>6.2}/{:>6.2} {:>6.2}/{:>6.2} {:<8} {}{}",
            img.index,
            img.trigger,
            img.camera,
            img.light.theta_deg,
            img.light.phi_deg,
            img.view.theta_deg,
            img.view.phi_deg,
            if img.feasible { "yes" } else { "NO" },
            points.join(" "),
            img.reason
                .as_ref()
                .map(|r| format!("  ({r})"))
                .unwrap_or_default()
        );
    }
    match &report.kept {
        Some(why) => println!("order: as planned ({why})"),
        None => println!(
            "order: {:?}; physical time (motion-model estimate, profile exposures): naive {}, optimised {} ({:.1} % shorter), lower bound {} ({}; optimised is within {:.3}×)",
            resolved.order,
            hms(report.naive_s),
            hms(report.optimised_s),
            100.0 * (1.0 - report.optimised_s / report.naive_s.max(1e-9)),
            hms(report.lower_bound_s),
            report.bound,
            report.gap()
        ),
    }
    if let (None, Some(slots_s)) = (&report.kept, report.slots_s) {
        println!(
            "order slots (each view's triggers together, so each view slot completes early for processing during the capture): {} ({:+.1} % against optimised)",
            hms(slots_s),
            100.0 * (slots_s / report.optimised_s.max(1e-9) - 1.0)
        );
    }
    println!(
        "plan {} on {}: {} images in {} triggers, {} infeasible (substituted), estimated physical capture time {}",
        schedule.plan,
        schedule.profile,
        schedule.images.len(),
        schedule.triggers.len(),
        infeasible,
        hms(estimate)
    );
    println!(
        "raw data: {} ({} an image at the cameras' resolution and bit depth, before the store's compression)",
        human_bytes(volume.raw_bytes),
        human_bytes(volume.largest_image_bytes)
    );
    if !policy.is_single() {
        let assumed = match (policy.auto(), retaken) {
            (Some(_), Some(n)) => format!(
                "; the scene is expected to clip at {n} of {} triggers, each taken again shorter (counted in the time; the data counts first exposures only)",
                schedule.triggers.len()
            ),
            (Some(_), None) => "; time and data as if no step clipped (each that does is taken again shorter, up to max_extra times; --scene counts what a simulated scene clips)".into(),
            (None, _) => String::new(),
        };
        println!("exposure policy: {policy}{assumed}");
    }
    Ok(())
}

/// The further exposures `auto` is expected to take at each trigger on the
/// simulated `scene`, at the run's exposure.
#[cfg(feature = "sim")]
fn expected_retakes(
    profile: &rigd::model::profile::Profile,
    schedule: &rigd::schedule::Schedule,
    auto: rigd::model::exposure::AutoExposure,
    exposure: Option<f64>,
    scene: &str,
) -> Result<Vec<u32>> {
    let loaded = rigd::rig::sim::Scene::load_on(scene, &profile.holder)
        .map_err(|e| super::exit::bad_input(format!("--scene {scene}: {e}")))?;
    let nominal = schedule.images.first().map_or(0.0, |img| {
        Timing::new(profile, None).exposure_s(&img.camera)
    });
    let relative = match exposure {
        Some(e) if nominal > 0.0 => e / nominal,
        _ => 1.0,
    };
    Ok(rigd::tradeoff::exposure::expected_retakes(
        &loaded, schedule, auto, relative, 8,
    ))
}

/// Without the simulator there is no scene to clip.
#[cfg(not(feature = "sim"))]
fn expected_retakes(
    _: &rigd::model::profile::Profile,
    _: &rigd::schedule::Schedule,
    _: rigd::model::exposure::AutoExposure,
    _: Option<f64>,
    scene: &str,
) -> Result<Vec<u32>> {
    Err(super::exit::bad_input(format!(
        "--scene {scene}: this rigd was built without the simulator"
    )))
}
