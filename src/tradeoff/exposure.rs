//! The exposure family of `rigd tradeoff`: what each exposure policy an
//! operator chooses among (`single`, `auto`, brackets of two and three
//! exposures) costs in physical time and data, and what it buys: texels
//! still clipped, and the held-out BTF error overall and within 10° of the
//! mirror direction, where a glossy material's highlights clip.
//!
//! Like the plans family it works in texture space: each image is the
//! scene's true texture at the achieved directions, each of its samples
//! held at the sensor's full scale ([`crate::truth::exposed_textures`]).
//! Merged, a series of exposures reads each sample from the longest one
//! that did not clip, which without noise is its true value; so a step's
//! merged texture is the true one clipped at the full scale of its
//! shortest exposure. `auto`'s further exposures are the ones the engine
//! would take: a step is taken again while more than `threshold` of its
//! samples clip, up to `max_extra` times, and its time follows the
//! engine's order ([`Timing::estimate_with_retakes_s`]).

use rayon::prelude::*;
use rigd_core::geometry::{add, cross, normalize, scale, Direction};
use rigd_sim::scene::Scene;

use super::{compress, held_out_error, Measured, Row, TradeoffConfig};
use crate::kinematics::Solver;
use crate::model::exposure::{AutoExposure, ExposurePolicy};
use crate::model::profile::Profile;
use crate::postprocess::ProcessError;
use crate::schedule::timing::Timing;
use crate::schedule::volume::image_bytes;
use crate::schedule::{self, Schedule};
use crate::truth::{exposed_textures, true_texture, ExposedTexture};

/// The family's name in the report.
pub const FAMILY: &str = "exposure";

/// How far from the mirror direction a held-out view of the near-mirror
/// set lies at most, degrees.
pub const NEAR_MIRROR_DEG: f64 = 10.0;

/// The exposure family on `profile`'s default plan (H1 where that is not
/// every light with every view): one row per policy of
/// [`ExposurePolicy::choices`] at the plan's first camera's exposure.
/// `built` holds plans already solved for the rig, by name.
pub(super) fn family(
    profile: &Profile,
    scene: &Scene,
    solver: &Solver,
    cfg: &TradeoffConfig,
    truths: &[(Direction, Direction, Vec<f32>)],
    built: &[(&str, &Schedule)],
    progress: &dyn Fn(&str),
) -> Result<Vec<Row>, ProcessError> {
    let offer = schedule::rig_offer(profile, solver);
    let mut tried = Vec::new();
    for spec in [profile.default_plan.as_str(), "h1"] {
        let s = match built.iter().find(|(name, _)| *name == spec) {
            Some((_, s)) => (*s).clone(),
            None => match crate::plan::resolve(spec, &offer) {
                Ok(plan) => schedule::build(profile, solver, &plan),
                Err(_) => {
                    tried.push(spec);
                    continue;
                }
            },
        };
        if super::grid(&s).is_ok() {
            progress(&format!("exposure policies on {spec}"));
            return rows(profile, scene, &s, spec, cfg, truths);
        }
        tried.push(spec);
    }
    Err(ProcessError::Invalid(format!(
        "exposure family: neither of {tried:?} pairs every light with every view on this rig"
    )))
}

/// The family's rows on schedule `s` (named `plan`).
pub(super) fn rows(
    profile: &Profile,
    scene: &Scene,
    s: &Schedule,
    plan: &str,
    cfg: &TradeoffConfig,
    truths: &[(Direction, Direction, Vec<f32>)],
) -> Result<Vec<Row>, ProcessError> {
    let g = super::grid(s)?;
    let timing = Timing::new(profile, None);
    let base_s = s
        .images
        .first()
        .map_or(0.0, |img| timing.exposure_s(&img.camera));
    if base_s.is_nan() || base_s <= 0.0 {
        return Err(ProcessError::Invalid(format!(
            "exposure family: the camera of plan `{plan}` has no exposure time"
        )));
    }
    let policies = ExposurePolicy::choices(base_s);
    let scales = full_scales(&policies, base_s);
    let near = near_mirror_pairs(cfg.held_out);
    let near_truths: Vec<(Direction, Direction, Vec<f32>)> = near
        .par_iter()
        .map(|&(l, v)| (l, v, true_texture(scene, cfg.texture, l, v)))
        .collect();
    let exposed = exposed_images(scene, s, cfg.texture, &scales);
    let cell = |img: &crate::schedule::ImageStep| -> Option<(usize, usize)> {
        Some((
            g.views.iter().position(|d| *d == img.view)?,
            g.lights.iter().position(|d| *d == img.light)?,
        ))
    };
    let texels = (cfg.texture * cfg.texture) as f64;
    let mut out = Vec::with_capacity(policies.len());
    for policy in &policies {
        // Per image, which full scale its merged texture is clipped at;
        // per trigger, how many further exposures `auto` took.
        let (levels, retakes) = levels_of(policy, s, &exposed, &scales, base_s);
        let mut textures = vec![vec![Vec::new(); g.lights.len()]; g.views.len()];
        let mut clipped = 0usize;
        for (img, &level) in s.images.iter().zip(&levels) {
            let e = &exposed[img.index][level];
            clipped += e.clipped_texels;
            if let Some((v, l)) = cell(img) {
                textures[v][l] = e.texels.clone();
            }
        }
        let (store, _, compress_s) = compress(&textures, &g, cfg.texture, cfg.components)?;
        let overall = held_out_error(&store, truths)?;
        let mirror = held_out_error(&store, &near_truths)?;
        let timing = Timing::new(profile, None).with_exposure_policy(policy);
        let physical_s =
            timing.estimate_with_retakes_s(s, |_| false, |t| retakes.get(t).copied().unwrap_or(0));
        let bytes: u64 = s
            .images
            .iter()
            .map(|img| {
                let n = match policy {
                    ExposurePolicy::Brackets { exposures_s } => exposures_s.len() as u64,
                    _ => 1 + u64::from(retakes.get(img.trigger).copied().unwrap_or(0)),
                };
                n * image_bytes(profile, &img.camera)
            })
            .sum();
        let retaken = retakes.iter().filter(|&&k| k > 0).count();
        let detail = match policy {
            ExposurePolicy::Auto { .. } => format!(
                "{plan}: {retaken} of {} steps took further exposures; {clipped} texels still clipped",
                s.triggers.len()
            ),
            _ => format!("{plan}: {clipped} texels clipped"),
        };
        out.push(Row {
            family: FAMILY.into(),
            setting: setting_of(policy),
            images: Some(s.images.len()),
            physical_s: Some(physical_s),
            bytes: Some(bytes),
            error: Some(overall.error),
            spread: overall.spread,
            compute_s: Some(compress_s),
            unit: "relative".into(),
            near_mirror: Some(NearMirror::from(mirror)),
            clipped_share: Some(clipped as f64 / (texels * s.images.len().max(1) as f64)),
            detail: Some(detail),
            ..Row::default()
        });
    }
    Ok(out)
}

/// The further exposures `auto` is expected to take at each trigger of
/// `s` on `scene`, by the family's texture-space model at `size`² texels:
/// a step is taken again while more than the threshold of its samples
/// clip. `relative_exposure` is the run's exposure over the profile's (1
/// at the profile's): a longer exposure clips sooner.
pub fn expected_retakes(
    scene: &Scene,
    s: &Schedule,
    auto: AutoExposure,
    relative_exposure: f64,
    size: usize,
) -> Vec<u32> {
    let policy = ExposurePolicy::from(auto);
    let scales = full_scales(std::slice::from_ref(&policy), 1.0);
    let relative = if relative_exposure > 0.0 && relative_exposure.is_finite() {
        relative_exposure
    } else {
        1.0
    };
    let recorded: Vec<f64> = scales.iter().map(|f| f / relative).collect();
    let exposed = exposed_images(scene, s, size, &recorded);
    levels_of(&policy, s, &exposed, &scales, 1.0).1
}

/// Each image of `s` as recorded at every one of `full_scales`
/// ([`exposed_textures`]), in capture order.
fn exposed_images(
    scene: &Scene,
    s: &Schedule,
    size: usize,
    full_scales: &[f64],
) -> Vec<Vec<ExposedTexture>> {
    s.images
        .par_iter()
        .map(|img| {
            exposed_textures(
                scene,
                size,
                img.achieved_light,
                img.achieved_view,
                full_scales,
            )
        })
        .collect()
}

/// A policy as `rigd run --exposure-policy` takes it, `auto` with its
/// defaults as plain `auto`.
fn setting_of(policy: &ExposurePolicy) -> String {
    match policy.auto() {
        Some(a) if a == AutoExposure::default() => "auto".into(),
        _ => policy.to_string(),
    }
}

/// The held-out error within [`NEAR_MIRROR_DEG`] of the mirror direction.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NearMirror {
    /// RMS error relative to the truth's RMS, over held-out pairs whose
    /// view lies within 10° of the light's mirror direction.
    pub error: f64,
    /// One standard error of `error`: the jackknife over those pairs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spread: Option<f64>,
}

impl From<Measured> for NearMirror {
    fn from(m: Measured) -> Self {
        NearMirror {
            error: m.error,
            spread: m.spread,
        }
    }
}

/// The full scales (1 at the base exposure) the policies' merged textures
/// are clipped at: 1, each series' base over its shortest exposure, and
/// `auto`'s `factor^k`; ascending, each once.
fn full_scales(policies: &[ExposurePolicy], base_s: f64) -> Vec<f64> {
    let mut scales = vec![1.0];
    for p in policies {
        match p {
            ExposurePolicy::Brackets { exposures_s } => {
                if let (Some(first), Some(last)) = (exposures_s.first(), exposures_s.last()) {
                    scales.push(first / last);
                }
            }
            ExposurePolicy::Auto { .. } => {
                if let Some(a) = p.auto() {
                    scales
                        .extend((1..=a.max_extra).map(|k| base_s / a.extra_exposure_s(base_s, k)));
                }
            }
            ExposurePolicy::Single {} => {}
        }
    }
    scales.sort_by(f64::total_cmp);
    scales.dedup_by(|a, b| (*a / *b - 1.0).abs() < 1e-9);
    scales
}

/// The index into `scales` of the scale nearest `want`.
fn nearest(scales: &[f64], want: f64) -> usize {
    (0..scales.len())
        .min_by(|&a, &b| {
            (scales[a] / want)
                .ln()
                .abs()
                .total_cmp(&(scales[b] / want).ln().abs())
        })
        .unwrap_or(0)
}

/// Per image, the index of the full scale its merged texture is clipped
/// at under `policy`; per trigger, the further exposures `auto` takes (0
/// for the other policies).
fn levels_of(
    policy: &ExposurePolicy,
    s: &Schedule,
    exposed: &[Vec<ExposedTexture>],
    scales: &[f64],
    base_s: f64,
) -> (Vec<usize>, Vec<u32>) {
    let mut retakes = vec![0u32; s.triggers.len()];
    let fixed = match policy {
        ExposurePolicy::Single {} => Some(nearest(scales, 1.0)),
        ExposurePolicy::Brackets { exposures_s } => Some(nearest(
            scales,
            exposures_s.first().unwrap_or(&1.0) / exposures_s.last().unwrap_or(&1.0),
        )),
        ExposurePolicy::Auto { .. } => None,
    };
    if let Some(level) = fixed {
        return (vec![level; s.images.len()], retakes);
    }
    let Some(a) = policy.auto() else {
        return (vec![0; s.images.len()], retakes);
    };
    let level_k = |k: u32| {
        let t = if k == 0 {
            base_s
        } else {
            a.extra_exposure_s(base_s, k)
        };
        nearest(scales, base_s / t)
    };
    // A trigger is taken again while any of its images clips more than the
    // threshold, as the engine does.
    for trig in &s.triggers {
        if trig.sweep.is_some() {
            continue;
        }
        let clips = |k: u32| {
            trig.images
                .iter()
                .any(|&i| exposed[i][level_k(k)].clipped_share > a.threshold)
        };
        retakes[trig.index] = (0..a.max_extra).find(|&k| !clips(k)).unwrap_or(a.max_extra);
    }
    let levels = s
        .images
        .iter()
        .map(|img| level_k(retakes[img.trigger]))
        .collect();
    (levels, retakes)
}

/// `n` held-out (light, view) pairs near the mirror direction: lights
/// uniform in solid angle up to 60°, each view within [`NEAR_MIRROR_DEG`]
/// of the light's mirror direction (uniform in that cap), so every view
/// stays within 70°. A light at the pole (φ undefined) mirrors to the
/// pole, and the cap around it is built the same way.
pub fn near_mirror_pairs(n: usize) -> Vec<(Direction, Direction)> {
    let frac = |k: usize, a: f64| (k as f64 * a).fract();
    let cos_max = 60f64.to_radians().cos();
    let cos_cap = NEAR_MIRROR_DEG.to_radians().cos();
    (1..=n)
        .map(|k| {
            let theta = (1.0 - frac(k, 0.618_034) * (1.0 - cos_max))
                .acos()
                .to_degrees();
            let light = Direction::new(theta, 360.0 * frac(k, 0.414_214));
            let [x, y, z] = light.to_vector();
            let mirror = [-x, -y, z];
            // Two unit vectors across the mirror direction.
            let helper = if mirror[0].abs() < 0.9 {
                [1.0, 0.0, 0.0]
            } else {
                [0.0, 1.0, 0.0]
            };
            let across = normalize(cross(mirror, helper));
            let other = cross(mirror, across);
            let delta = (1.0 - frac(k, 0.732_051) * (1.0 - cos_cap)).acos();
            let psi = std::f64::consts::TAU * frac(k, 0.236_068);
            let offset = add(
                scale(across, delta.sin() * psi.cos()),
                scale(other, delta.sin() * psi.sin()),
            );
            let view = Direction::from_vector(add(scale(mirror, delta.cos()), offset));
            (light, view)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn near_mirror_views_lie_within_the_cap_and_the_hemisphere() {
        let pairs = near_mirror_pairs(200);
        assert_eq!(pairs.len(), 200);
        for (l, v) in &pairs {
            let mirror = Direction::new(l.theta_deg, l.phi_deg + 180.0);
            let off = v.angle_to_deg(mirror);
            assert!(off <= NEAR_MIRROR_DEG + 1e-9, "{l:?} {v:?}: {off}°");
            assert!(l.theta_deg <= 60.0 + 1e-9 && v.theta_deg <= 70.0 + 1e-9);
        }
        // Spread over the cap, not on its rim or its centre only.
        let offs: Vec<f64> = pairs
            .iter()
            .map(|(l, v)| v.angle_to_deg(Direction::new(l.theta_deg, l.phi_deg + 180.0)))
            .collect();
        assert!(offs.iter().any(|&o| o < 3.0) && offs.iter().any(|&o| o > 8.0));
        // θ = 0, where φ is undefined: its mirror is the pole itself.
        let pole = Direction::new(0.0, 0.0);
        assert!(pole.angle_to_deg(Direction::new(0.0, 180.0)) < 1e-9);
    }

    #[test]
    fn the_policies_need_the_full_scales_of_their_shortest_exposures() {
        let scales = full_scales(&ExposurePolicy::choices(0.25), 0.25);
        // single 1, brackets 4 and 16, auto 4, 16 and 64.
        assert_eq!(scales.len(), 4, "{scales:?}");
        for (got, want) in scales.iter().zip([1.0, 4.0, 16.0, 64.0]) {
            assert!((got - want).abs() < 1e-9, "{scales:?}");
        }
        assert_eq!(nearest(&scales, 16.0), 2);
    }

    /// The family's rows for `scene` on H2's three inner rings (361
    /// images), 4 × 4 texels.
    fn rows_on(scene: &str) -> Vec<Row> {
        let profile = Profile::load("bonn-gonioreflectometer").expect("profile");
        let scene = Scene::load_on(scene, &profile.holder).expect("scene");
        let solver = Solver::new(&profile).expect("solver");
        let dirs = crate::plan::rings(
            &crate::plan::H2_THETAS[..3],
            &crate::plan::HEMISPHERE_RING_COUNTS[..3],
        );
        let s = schedule::build(&profile, &solver, &super::super::pairs_plan("three", &dirs));
        let cfg = TradeoffConfig {
            texture: 4,
            held_out: 16,
            components: 8,
            ..TradeoffConfig::default()
        };
        let truths: Vec<(Direction, Direction, Vec<f32>)> = super::super::held_out_pairs(16)
            .into_iter()
            .map(|(l, v)| (l, v, true_texture(&scene, 4, l, v)))
            .collect();
        rows(&profile, &scene, &s, "three", &cfg, &truths).expect("rows")
    }

    #[test]
    fn shorter_exposures_keep_leather_s_highlight_and_cost_time_a_matte_sample_does_not_pay() {
        let rows = rows_on("leather");
        let settings: Vec<&str> = rows.iter().map(|r| r.setting.as_str()).collect();
        assert_eq!(
            settings,
            [
                "single",
                "auto",
                "brackets:0.25,0.0625",
                "brackets:0.25,0.0625,0.015625"
            ]
        );
        let [single, auto, two, three] = [&rows[0], &rows[1], &rows[2], &rows[3]];
        let clipped = |r: &Row| r.clipped_share.expect("clipped share");
        let time = |r: &Row| r.physical_s.expect("time");
        let near = |r: &Row| r.near_mirror.expect("near-mirror error");
        // The glossy grain clips at the profile's exposure; each shorter
        // series keeps more of it, and auto keeps all of it here.
        assert!(clipped(single) > 0.1, "{single:?}");
        assert!(clipped(three) <= clipped(two) && clipped(two) < clipped(single));
        assert!(clipped(auto) <= clipped(two), "{auto:?}");
        // Near the mirror the measured highlight is what the BTF lacked.
        let (a, b) = (near(single), near(auto));
        let bars = 2.0 * (a.spread.unwrap_or(f64::NAN) + b.spread.unwrap_or(f64::NAN));
        assert!(b.error + bars < a.error, "single {a:?}, auto {b:?}");
        // Each exposure costs its time and its bytes.
        assert!(time(single) < time(auto) && time(single) < time(two) && time(two) < time(three));
        let bytes = |r: &Row| r.bytes.expect("bytes");
        assert_eq!(bytes(two), 2 * bytes(single));
        assert_eq!(bytes(three), 3 * bytes(single));
        assert!(auto
            .detail
            .as_deref()
            .is_some_and(|d| d.contains(" of 361 steps")));

        // A matte sample clips nowhere: auto takes nothing more.
        let rows = rows_on("flat-calibration");
        let (single, auto) = (&rows[0], &rows[1]);
        assert_eq!(clipped(single), 0.0);
        assert_eq!(time(auto), time(single));
        assert_eq!(bytes(auto), bytes(single));
        assert_eq!(auto.error, single.error);
    }
}
