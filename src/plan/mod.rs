//! Sampling plans: which (light, view) pairs to capture.
//!
//! The built-in plans are the hemisphere samplings H1 and H2 of Sattler et al.
//! (Table 1), the 12 × 8 grid of Wang et al., and one image per lamp for
//! photometric stereo (Spence et al.). Plans can also come from a JSON or TOML file.

pub mod laser;

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::model::profile::{Profile, ProfileError};
use crate::plan::laser::{LaserPlan, LaserRig};
use rigd_core::geometry::Direction;

/// Names accepted for `PLAN` besides a file path.
pub const BUILTIN_PLANS: &[&str] = &["h1", "h2", "grid12x8", "lamps", "laser"];

/// Largest plan accepted, in images; a typo in a generated file should not
/// start a capture of a billion frames.
pub const MAX_PAIRS: usize = 1_000_000;

/// Ring sizes of H1 and H2 (Sattler et al., Table 1): 1 + 6 + 12 + 18 + 20 + 24 = 81.
pub const HEMISPHERE_RING_COUNTS: [usize; 6] = [1, 6, 12, 18, 20, 24];
/// Elevations of H1, degrees.
pub const H1_THETAS: [f64; 6] = [0.0, 17.0, 34.0, 51.0, 68.0, 85.0];
/// Elevations of H2, degrees.
pub const H2_THETAS: [f64; 6] = [0.0, 15.0, 30.0, 45.0, 60.0, 75.0];

/// One image to take: light and view directions in the sample frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Pair {
    /// Direction towards the light, in the sample frame.
    pub light: Direction,
    /// Direction towards the camera, in the sample frame.
    pub view: Direction,
}

/// A named list of pairs, in the order a naive nested loop visits them
/// (view-major: all lights of one view slot, then the next view).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    /// The plan as named (`h1`, `laser:turns=4`), or a plan file's `name`
    /// (its file stem if it has none).
    pub name: String,
    /// The images to take, view-major; empty for a laser scan.
    pub pairs: Vec<Pair>,
    /// A laser scan (Wang et al., §3.2) instead of pairs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub laser: Option<LaserPlan>,
    /// The order the engine takes the triggers in. Runs recorded before
    /// orders existed read as `naive`, the order they were taken in.
    #[serde(default)]
    pub order: Order,
}

/// Why a plan could not be resolved for a rig.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    /// The name is no built-in plan and does not look like a plan file.
    #[error(
        "unknown plan `{0}` (expected one of h1, h2, grid12x8, lamps, laser[:key=value,…], or a .json/.toml plan file)"
    )]
    Unknown(String),
    /// A built-in plan the rig cannot take (grid12x8 without arcs, `lamps`
    /// without fixed lamps, a laser scan without a laser or with bad
    /// settings).
    #[error("plan `{plan}` does not fit profile `{profile}`: {why}")]
    NotForRig {
        /// The plan as named.
        plan: String,
        /// The profile's name.
        profile: String,
        /// What the plan needs that the rig lacks.
        why: String,
    },
    /// A plan file (or inline plan) that cannot be read or parsed, or whose
    /// images are not a usable list (none, too many, wrong shape).
    #[error("plan file {file}: {why}")]
    File {
        /// The file's path, or what names an inline plan.
        file: String,
        /// What is wrong with it.
        why: String,
    },
}

/// Rings of directions: `counts[i]` directions at elevation `thetas[i]`,
/// evenly spaced in φ from 0 (a single direction at θ = 0 is the pole).
pub fn rings(thetas: &[f64], counts: &[usize]) -> Vec<Direction> {
    let mut out = Vec::new();
    for (&theta, &n) in thetas.iter().zip(counts) {
        for k in 0..n {
            out.push(Direction::new(theta, 360.0 * k as f64 / n as f64));
        }
    }
    out
}

/// The 81 directions of H1.
pub fn h1() -> Vec<Direction> {
    rings(&H1_THETAS, &HEMISPHERE_RING_COUNTS)
}

/// The 81 directions of H2.
pub fn h2() -> Vec<Direction> {
    rings(&H2_THETAS, &HEMISPHERE_RING_COUNTS)
}

/// 12 azimuths 30° apart at each of the given elevations.
pub fn grid12(elevations: &[f64]) -> Vec<Direction> {
    let mut out = Vec::new();
    for &theta in elevations {
        for k in 0..12 {
            out.push(Direction::new(theta, 30.0 * k as f64));
        }
    }
    out
}

/// How the engine orders a plan's triggers.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    Serialize,
    Deserialize,
    clap::ValueEnum,
    utoipa::ToSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Order {
    /// The plan's nested-loop order (view-major).
    #[default]
    Naive,
    /// Minimal physical time under the motion model.
    Optimised,
    /// Minimal physical time with the triggers of each view taken one after
    /// another, so each view slot's lights are all in as early as they can
    /// be (a run processed during its capture compresses a slot then).
    Slots,
}

/// Loads a profile ([`Profile::load`]) and checks what only the plans can
/// check: that its `default_plan` names a built-in plan. Everything that
/// loads a profile to plan or run with it comes through here.
pub fn load_profile(spec: &str) -> Result<Profile, ProfileError> {
    let profile = Profile::load(spec)?;
    check_default_plan(&profile, spec)?;
    Ok(profile)
}

/// The profile's `default_plan` is a built-in plan; `origin` names where
/// the profile came from in the error.
pub fn check_default_plan(profile: &Profile, origin: &str) -> Result<(), ProfileError> {
    if BUILTIN_PLANS.contains(&profile.default_plan.as_str()) {
        return Ok(());
    }
    Err(ProfileError {
        file: origin.to_string(),
        key: "default_plan".into(),
        message: format!(
            "unknown plan `{}` (expected one of: {})",
            profile.default_plan,
            BUILTIN_PLANS.join(", ")
        ),
    })
}

/// Every light with every view, view-major.
pub fn btf(lights: &[Direction], views: &[Direction]) -> Vec<Pair> {
    let mut out = Vec::with_capacity(lights.len() * views.len());
    for &view in views {
        for &light in lights {
            out.push(Pair { light, view });
        }
    }
    out
}

/// What the rig offers a plan: its arcs' elevations (turntable rigs), its
/// fixed lamps and camera (photometric-stereo rigs).
#[derive(Debug, Clone, Default)]
pub struct RigOffer {
    /// The profile's name, for messages.
    pub profile: String,
    /// Elevations (θ, degrees) of the lamps and of the cameras on the arcs,
    /// each in arc order; None for rigs without arcs.
    pub arc_elevations: Option<(Vec<f64>, Vec<f64>)>,
    /// The fixed lamps' directions in rig order and the camera's direction;
    /// None for rigs without fixed lamps.
    pub fixed_lamps: Option<(Vec<Direction>, Direction)>,
    /// The laser unit, on rigs that have one.
    pub laser: Option<LaserRig>,
}

/// Resolves a plan name or file for a rig.
pub fn resolve(spec: &str, rig: &RigOffer) -> Result<Plan, PlanError> {
    let named = |pairs: Vec<Pair>| Plan {
        name: spec.to_string(),
        pairs,
        laser: None,
        order: Order::Optimised,
    };
    match spec {
        "h1" => Ok(named(btf(&h1(), &h1()))),
        "h2" => Ok(named(btf(&h2(), &h2()))),
        "grid12x8" => {
            let (lamps, cams) = rig.arc_elevations.clone().ok_or_else(|| PlanError::NotForRig {
                plan: spec.into(),
                profile: rig.profile.clone(),
                why: "grid12x8 takes its 8 elevations from a rig's lamp and camera arcs, and this rig has none".into(),
            })?;
            Ok(named(btf(&grid12(&lamps), &grid12(&cams))))
        }
        "lamps" => {
            let (lamps, camera) = rig
                .fixed_lamps
                .clone()
                .ok_or_else(|| PlanError::NotForRig {
                    plan: spec.into(),
                    profile: rig.profile.clone(),
                    why: "`lamps` takes one image per fixed lamp, and this rig has no fixed lamps"
                        .into(),
                })?;
            Ok(named(btf(&lamps, &[camera])))
        }
        _ if spec == "laser" || spec.starts_with("laser:") => {
            let not_for_rig = |why: String| PlanError::NotForRig {
                plan: spec.into(),
                profile: rig.profile.clone(),
                why,
            };
            let laser = LaserPlan::parse(spec).map_err(&not_for_rig)?;
            let rig_laser = rig.laser.as_ref().ok_or_else(|| {
                not_for_rig(
                    "a laser scan needs a turntable rig with a laser, its tilt axis and the laser's `elevation_deg`"
                        .into(),
                )
            })?;
            rig_laser.check(&laser).map_err(not_for_rig)?;
            Ok(Plan {
                name: spec.to_string(),
                pairs: Vec::new(),
                laser: Some(laser),
                order: Order::Naive,
            })
        }
        _ if looks_like_file(spec) => from_file(Path::new(spec)),
        _ => Err(PlanError::Unknown(spec.to_string())),
    }
}

fn looks_like_file(spec: &str) -> bool {
    spec.contains('/') || spec.ends_with(".json") || spec.ends_with(".toml")
}

/// A plan file: a list of directions (paired all with all), separate light
/// and view lists (paired all with all), or explicit pairs.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PlanFile {
    #[serde(default)]
    name: Option<String>,
    #[serde(default)]
    directions: Option<Vec<Direction>>,
    #[serde(default)]
    lights: Option<Vec<Direction>>,
    #[serde(default)]
    views: Option<Vec<Direction>>,
    #[serde(default)]
    pairs: Option<Vec<Pair>>,
}

/// Reads a plan file (`.json` or `.toml`).
pub fn from_file(path: &Path) -> Result<Plan, PlanError> {
    let file = path.display().to_string();
    let err = |why: String| PlanError::File {
        file: file.clone(),
        why,
    };
    // A plan is JSON unless its name ends in `.toml`.
    let format = if file.ends_with(".toml") {
        rigd_core::config::Format::Toml
    } else {
        rigd_core::config::Format::Json
    };
    let parsed: PlanFile = rigd_core::config::load(path, rigd_core::read::PLAN_LIMIT, format)
        .map_err(|e| err(e.detail()))?;
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| file.clone());
    from_parsed(parsed, &file, stem)
}

/// A plan given inline as JSON (the API's `plan` object): the same shapes
/// as a plan file. `what` names it in messages; `default_name` is used when
/// the plan has no `name`.
pub fn from_json_value(
    value: serde_json::Value,
    what: &str,
    default_name: &str,
) -> Result<Plan, PlanError> {
    let parsed: PlanFile = serde_json::from_value(value).map_err(|e| PlanError::File {
        file: what.to_string(),
        why: e.to_string(),
    })?;
    from_parsed(parsed, what, default_name.to_string())
}

/// The θ a plan may ask for, degrees: from the normal up to, not
/// including, the horizon, where light and view graze the sample and no
/// rig's limits reach (the Bonn arm's pitch stops at 89°).
pub const PLAN_THETA_DEG: std::ops::Range<f64> = 0.0..90.0;

/// A plan's direction checked ([`PLAN_THETA_DEG`], φ finite and sane) and
/// with φ normalised into [0, 360), so capture, index and export see one
/// value; `key` names it in the file (`directions[3]`, `pairs[0].light`).
fn plan_direction(d: Direction, key: &str) -> Result<Direction, String> {
    crate::model::text::check_direction(d, PLAN_THETA_DEG).map_err(|why| format!("{key}: {why}"))
}

/// [`plan_direction`] of every direction of a list named `key`.
fn plan_directions(list: Vec<Direction>, key: &str) -> Result<Vec<Direction>, String> {
    list.into_iter()
        .enumerate()
        .map(|(i, d)| plan_direction(d, &format!("{key}[{i}]")))
        .collect()
}

fn from_parsed(parsed: PlanFile, file: &str, default_name: String) -> Result<Plan, PlanError> {
    let err = |why: String| PlanError::File {
        file: file.to_string(),
        why,
    };
    let too_many = |n: usize| {
        err(format!(
            "{n} images is more than the {MAX_PAIRS} a plan may hold"
        ))
    };
    // Counted before pairing: a long list paired with itself must not
    // allocate its square first.
    let paired = |l: &[Direction], v: &[Direction]| match l.len().checked_mul(v.len()) {
        Some(n) if n <= MAX_PAIRS => Ok(btf(l, v)),
        n => Err(too_many(n.unwrap_or(usize::MAX))),
    };
    let pairs = match (parsed.directions, parsed.lights, parsed.views, parsed.pairs) {
        (Some(d), None, None, None) => {
            let d = plan_directions(d, "directions").map_err(err)?;
            paired(&d, &d)?
        }
        (None, Some(l), Some(v), None) => paired(
            &plan_directions(l, "lights").map_err(err)?,
            &plan_directions(v, "views").map_err(err)?,
        )?,
        (None, None, None, Some(p)) => p
            .into_iter()
            .enumerate()
            .map(|(i, p)| {
                Ok(Pair {
                    light: plan_direction(p.light, &format!("pairs[{i}].light"))?,
                    view: plan_direction(p.view, &format!("pairs[{i}].view"))?,
                })
            })
            .collect::<Result<Vec<_>, String>>()
            .map_err(err)?,
        _ => {
            return Err(err(
                "expected exactly one of: `directions`, `lights` with `views`, or `pairs`".into(),
            ))
        }
    };
    if pairs.is_empty() {
        return Err(err("the plan has no images".into()));
    }
    if pairs.len() > MAX_PAIRS {
        return Err(too_many(pairs.len()));
    }
    let name = parsed.name.unwrap_or(default_name);
    Ok(Plan {
        name,
        pairs,
        laser: None,
        order: Order::Optimised,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn h1_has_81_directions_in_the_table_1_rings() {
        let d = h1();
        assert_eq!(d.len(), 81);
        for (theta, n) in H1_THETAS.iter().zip(HEMISPHERE_RING_COUNTS) {
            let ring: Vec<_> = d.iter().filter(|x| x.theta_deg == *theta).collect();
            assert_eq!(ring.len(), n, "ring θ = {theta}");
        }
        // Δφ of the 68° ring is 18°.
        let r68: Vec<f64> = d
            .iter()
            .filter(|x| x.theta_deg == 68.0)
            .map(|x| x.phi_deg)
            .collect();
        assert!((r68[1] - r68[0] - 18.0).abs() < 1e-12);
    }

    /// An inline plan (the API's) follows the plan files' rules: φ kept in
    /// [0, 360), garbage and the horizon refused with the key.
    #[test]
    fn inline_plans_have_their_azimuths_normalised_and_checked() {
        let plan = from_json_value(
            serde_json::json!({"pairs": [{"light": {"theta_deg": 30, "phi_deg": -30},
                                           "view": {"theta_deg": 0, "phi_deg": 720}}]}),
            "inline plan",
            "custom",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(plan.pairs[0].light.phi_deg, 330.0);
        assert_eq!(plan.pairs[0].view.phi_deg, 0.0);
        for (value, says) in [
            (
                serde_json::json!({"directions": [{"theta_deg": 10, "phi_deg": 1e300}]}),
                "directions[0]: φ = 1e300",
            ),
            (
                serde_json::json!({"lights": [{"theta_deg": 10, "phi_deg": 0}],
                                   "views": [{"theta_deg": 95, "phi_deg": 0}]}),
                "views[0]: θ = 95",
            ),
        ] {
            let e = from_json_value(value, "inline plan", "custom")
                .err()
                .map(|e| e.to_string())
                .unwrap_or_default();
            assert!(e.contains(says), "{e}");
        }
    }

    #[test]
    fn a_long_list_is_refused_before_it_is_paired() {
        let d: Vec<serde_json::Value> = (0..1001)
            .map(|i| serde_json::json!({"theta_deg": 10, "phi_deg": i % 360}))
            .collect();
        let e = from_json_value(serde_json::json!({ "directions": d }), "inline plan", "x")
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("1002001 images is more than"), "{e}");
    }

    #[test]
    fn btf_pairs_all_with_all() {
        assert_eq!(btf(&h2(), &h2()).len(), 6561);
        assert_eq!(btf(&grid12(&[10.0; 8]), &grid12(&[10.0; 8])).len(), 9216);
    }

    #[test]
    fn grid_needs_arcs() {
        let r = resolve("grid12x8", &RigOffer::default());
        assert!(matches!(r, Err(PlanError::NotForRig { .. })));
        assert!(matches!(
            resolve("h3", &RigOffer::default()),
            Err(PlanError::Unknown(_))
        ));
    }

    #[test]
    fn plan_files_in_all_three_shapes() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let p = dir.path().join("dirs.json");
        std::fs::write(
            &p,
            r#"{"directions":[{"theta_deg":0,"phi_deg":0},{"theta_deg":45,"phi_deg":90}]}"#,
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(from_file(&p).map(|x| x.pairs.len()), Ok(4));
        let p = dir.path().join("pairs.toml");
        std::fs::write(&p, "name = \"one\"\n[[pairs]]\nlight = { theta_deg = 10.0, phi_deg = 0.0 }\nview = { theta_deg = 20.0, phi_deg = 5.0 }\n")
            .unwrap_or_else(|e| panic!("{e}"));
        let plan = from_file(&p).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((plan.name.as_str(), plan.pairs.len()), ("one", 1));
        let p = dir.path().join("bad.json");
        std::fs::write(&p, r#"{"directions":[{"theta_deg":95,"phi_deg":0}]}"#)
            .unwrap_or_else(|e| panic!("{e}"));
        let e = from_file(&p)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("θ = 95"), "{e}");
        let p = dir.path().join("horizon.json");
        std::fs::write(&p, r#"{"directions":[{"theta_deg":90,"phi_deg":0}]}"#)
            .unwrap_or_else(|e| panic!("{e}"));
        let e = from_file(&p)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("directions[0]: θ = 90"), "{e}");
        let p = dir.path().join("both.json");
        std::fs::write(&p, r#"{"directions":[],"pairs":[]}"#).unwrap_or_else(|e| panic!("{e}"));
        assert!(from_file(&p).is_err());
    }
}
