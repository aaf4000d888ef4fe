//! `rigd tradeoff`: what accuracy costs in time, for one rig and one
//! material. Every error figure is measured against the scene simulator's
//! ground truth; physical times come from the motion model (the same
//! `Timing` the engine follows, so a simulated capture reports exactly
//! them) and the table says so.
//!
//! Families measured by this version:
//! - **plans**: H2 and H1, H2's first 3, 4 and 5 rings, a 12 × 8 and a 12 × 5
//!   grid, and a dense reference of 15° rings. Each plan is solved on the
//!   profile and ordered; its "capture" is the scene's true BTF, area-averaged
//!   into normtextures, at the directions the rig really reaches (infeasible
//!   pairs show up as error). The BTF is compressed with C components and
//!   reconstructed at held-out (light, view) pairs (eq. 3 and 5 of Sattler et al.).
//!   The camera, registration and rectification are left out of this family:
//!   `tests/it/process_run.rs` and `tests/it/btf_accuracy.rs` measure them
//!   (registration residual 0.02–0.09 px).
//! - **pca**: C = 2, 4, 8, 16, 32 on H2: error, compressed size, compute time.
//! - **fidelity**: the renderer with every effect the scene can show, then
//!   with each effect off: render time, and how far the frame moves (the
//!   accuracy a shortcut costs).
//! - **laser**: a simulated laser scan on the MSRA rig (the rig with a
//!   laser unit; one camera at 40°, small frames) with 26 source positions,
//!   processed with 1, 5, 13 and 26 of them: MDF depth error against the
//!   scene, and the scan time of a plan with that many sources.
//! - **photometric stereo**: simulated VirTex captures with 3, 6 and 12
//!   lamps: mean normal error against the scene, and the capture time.
//! - **exposure**: `single`, `auto` and 2- and 3-exposure brackets on the
//!   default plan ([`exposure`]): time, data, clipped texels, and the
//!   held-out error overall and within 10° of the mirror direction.

use std::path::Path;
use std::time::Instant;

use rayon::prelude::*;
use rigd_process::btf::{compress_slot, BtfWriter, CompressedBtf, SlotPca, TextureShape};
use rigd_process::directions::{Direction as PDir, DirectionTable};
use rigd_sim::scene::{Effect, EffectSwitches, Scene, Shot};
use serde::{Deserialize, Serialize};

use crate::kinematics::Solver;
use crate::model::profile::Profile;
use crate::plan::{self, Plan, H2_THETAS, HEMISPHERE_RING_COUNTS};
use crate::postprocess::ProcessError;
use crate::schedule::{self, Schedule};
use crate::store::StoreError;
use crate::truth::{true_texture, true_texture_channels};
use rigd_core::geometry::Direction;

/// Settings of a trade-off run.
#[derive(Debug, Clone, Copy)]
pub struct TradeoffConfig {
    /// Side of the normtextures, texels.
    pub texture: usize,
    /// Held-out (light, view) pairs the error is measured at.
    pub held_out: usize,
    /// PCA components for the plan family.
    pub components: usize,
    /// Frame size of the fidelity renders.
    pub render_size: [u32; 2],
}

impl Default for TradeoffConfig {
    fn default() -> TradeoffConfig {
        TradeoffConfig {
            texture: 16,
            held_out: 24,
            components: 16,
            render_size: [256, 192],
        }
    }
}

pub mod choice;
pub mod exposure;
pub mod figure;

/// One row of the table.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Row {
    /// The family the row belongs to: `plans`, `pca`, `exposure`,
    /// `fidelity`, `laser` or `photometric stereo`.
    pub family: String,
    /// What varies within the family (a plan's name, `C = 8`, an effect
    /// left out, a source count).
    pub setting: String,
    /// Images captured; None for rows without a capture (fidelity).
    pub images: Option<usize>,
    /// Physical capture time, seconds (motion-model estimate).
    pub physical_s: Option<f64>,
    /// Raw sensor bytes of the capture, or the compressed BTF's bytes.
    pub bytes: Option<u64>,
    /// RMS error relative to the truth's RMS (plans, pca, exposure), or
    /// the RMS change of the frame relative to its RMS (fidelity).
    pub error: Option<f64>,
    /// Wall time of the computation (compression, render), seconds.
    pub compute_s: Option<f64>,
    /// What `error` is: `relative` (plans, pca, exposure, fidelity), `mm`
    /// (laser: mean depth error), `degrees` (photometric stereo: mean
    /// normal error).
    pub unit: String,
    /// One standard error of `error`, in its unit: the jackknife over the
    /// held-out pairs (plans, pca, exposure), or over 16 × 16-pixel tiles
    /// (laser, photometric stereo). None where there is nothing to
    /// resample (fidelity: one frame).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spread: Option<f64>,
    /// The share of the sample the setting itself measures, 0 … 1, where
    /// it varies within the family (laser). `error` may be over a smaller
    /// common set; `detail` says.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coverage: Option<f64>,
    /// The plan's directions, each paired with each (plans family): what
    /// the dashboard puts into the start form when the point is clicked.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub directions: Option<Vec<Direction>>,
    /// The held-out error within 10° of the mirror direction, with its
    /// standard error (exposure family).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub near_mirror: Option<exposure::NearMirror>,
    /// The share of the captured texels still clipped, 0 … 1 (exposure
    /// family).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clipped_share: Option<f64>,
    /// The plan's name where the daemon knows it by name (`h1`, `h2`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plan: Option<String>,
    /// More about the row (coverage, what was measured).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub detail: Option<String>,
}

/// The whole report.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Report {
    /// The profile's name (the rig of the plans and pca families).
    pub profile: String,
    /// The simulated scene (the material) measured.
    pub scene: String,
    /// Side of the normtextures, texels.
    pub texture: usize,
    /// Held-out (light, view) pairs the BTF error is measured at.
    pub held_out: usize,
    /// PCA components of the plans family.
    pub components: usize,
    /// How each figure was measured, one sentence per family or column.
    #[serde(default)]
    pub method: Vec<String>,
    /// The knee of each family's curve, one computed sentence each
    /// ([`summary`]).
    #[serde(default)]
    pub summary: Vec<String>,
    /// Every row of the table, family by family.
    pub rows: Vec<Row>,
}

/// A named plan of the plan family.
struct PlanCase {
    name: String,
    plan: Plan,
    /// The spec `plan::resolve` knows it by, for the named plans.
    spec: Option<&'static str>,
    /// Its directions, each paired with each.
    directions: Vec<Direction>,
}

fn pairs_plan(name: &str, dirs: &[Direction]) -> Plan {
    Plan {
        name: name.into(),
        pairs: plan::btf(dirs, dirs),
        laser: None,
        order: crate::plan::Order::Optimised,
    }
}

fn plan_cases(profile: &Profile, solver: &Solver) -> Result<Vec<PlanCase>, ProcessError> {
    let offer = schedule::rig_offer(profile, solver);
    let resolve =
        |spec: &str| plan::resolve(spec, &offer).map_err(|e| ProcessError::Invalid(e.to_string()));
    let mut cases = vec![
        PlanCase {
            name: "h2".into(),
            plan: resolve("h2")?,
            spec: Some("h2"),
            directions: plan::h2(),
        },
        PlanCase {
            name: "h1".into(),
            plan: resolve("h1")?,
            spec: Some("h1"),
            directions: plan::h1(),
        },
    ];
    for k in [3, 4, 5] {
        let dirs = plan::rings(&H2_THETAS[..k], &HEMISPHERE_RING_COUNTS[..k]);
        cases.push(PlanCase {
            name: format!("h2, {k} rings"),
            plan: pairs_plan(&format!("h2-{k}rings"), &dirs),
            spec: None,
            directions: dirs,
        });
    }
    // The grids: the rig's own arcs where it has them, else evenly spaced
    // elevations up to 75°.
    let arcs = offer.arc_elevations.clone();
    for rows in [8usize, 5] {
        let elevations: Vec<f64> = match &arcs {
            Some((lamps, _)) if rows == 8 => lamps.clone(),
            Some((lamps, _)) => lamps.iter().copied().take(rows).collect(),
            None => (0..rows)
                .map(|i| 5.0 + 70.0 * i as f64 / (rows - 1) as f64)
                .collect(),
        };
        let dirs = plan::grid12(&elevations);
        cases.push(PlanCase {
            name: format!("grid 12x{rows}"),
            plan: pairs_plan(&format!("grid12x{rows}"), &dirs),
            spec: None,
            directions: dirs,
        });
    }
    let dense_thetas = [0.0, 15.0, 30.0, 45.0, 60.0, 75.0];
    let dense = plan::rings(&dense_thetas, &[1, 24, 24, 24, 24, 24]);
    cases.push(PlanCase {
        name: "dense, 15° rings".into(),
        plan: pairs_plan("dense15", &dense),
        spec: None,
        directions: dense,
    });
    Ok(cases)
}

/// Held-out (light, view) pairs: a fixed low-discrepancy set, θ ≤ 70°.
pub fn held_out_pairs(n: usize) -> Vec<(Direction, Direction)> {
    let at = |k: usize, a: f64, b: f64| {
        let u = (k as f64 * a).fract();
        let v = (k as f64 * b).fract();
        // Uniform in solid angle up to 70°.
        let cos_max = 70f64.to_radians().cos();
        let theta = (1.0 - u * (1.0 - cos_max)).acos().to_degrees();
        Direction::new(theta, 360.0 * v)
    };
    (1..=n)
        .map(|k| (at(k, 0.618_034, 0.414_214), at(k, 0.732_051, 0.236_068)))
        .collect()
}

fn pdir(d: Direction) -> PDir {
    PDir::new(d.theta_deg, d.phi_deg)
}

/// The schedule's images grouped as a BTF: commanded lights and views (as
/// tables) and, per view slot and light, the image's achieved directions.
struct Grid {
    lights: Vec<Direction>,
    views: Vec<Direction>,
    /// `achieved[slot][light]`.
    achieved: Vec<Vec<(Direction, Direction)>>,
}

fn grid(schedule: &Schedule) -> Result<Grid, ProcessError> {
    let mut lights: Vec<Direction> = Vec::new();
    let mut views: Vec<Direction> = Vec::new();
    let index = |list: &mut Vec<Direction>, d: Direction| match list.iter().position(|x| *x == d) {
        Some(i) => i,
        None => {
            list.push(d);
            list.len() - 1
        }
    };
    let mut cells = Vec::with_capacity(schedule.images.len());
    for img in &schedule.images {
        let l = index(&mut lights, img.light);
        let v = index(&mut views, img.view);
        cells.push((v, l, (img.achieved_light, img.achieved_view)));
    }
    let mut achieved = vec![vec![None; lights.len()]; views.len()];
    for (v, l, a) in cells {
        achieved[v][l] = Some(a);
    }
    let achieved = achieved
        .into_iter()
        .map(|row| row.into_iter().collect::<Option<Vec<_>>>())
        .collect::<Option<Vec<_>>>()
        .ok_or_else(|| {
            ProcessError::Invalid("the plan is not every light with every view".into())
        })?;
    Ok(Grid {
        lights,
        views,
        achieved,
    })
}

/// A grid's "capture": per view slot and light, the scene's true texture
/// at the achieved directions.
type Textures = Vec<Vec<Vec<f32>>>;

fn true_textures(scene: &Scene, g: &Grid, size: usize) -> Textures {
    g.achieved
        .par_iter()
        .map(|row| {
            row.iter()
                .map(|&(l, v)| true_texture(scene, size, l, v))
                .collect()
        })
        .collect()
}

/// The grid's light and view tables.
fn tables(g: &Grid) -> Result<(DirectionTable, DirectionTable), ProcessError> {
    let table = |d: &[Direction]| {
        DirectionTable::new(d.iter().map(|&x| pdir(x)).collect())
            .map_err(|e| ProcessError::Invalid(e.to_string()))
    };
    Ok((table(&g.lights)?, table(&g.views)?))
}

/// Compresses a grid's textures with `components` and returns the store
/// and the compression's wall time.
fn compress(
    textures: &Textures,
    g: &Grid,
    size: usize,
    components: usize,
) -> Result<(CompressedBtf, Vec<SlotPca>, f64), ProcessError> {
    let invalid = |e: rigd_process::btf::BtfError| ProcessError::Invalid(e.to_string());
    let shape = TextureShape::new(size, size, 1).map_err(invalid)?;
    let started = Instant::now();
    let slots = textures
        .iter()
        .map(|row| {
            let refs: Vec<&[f32]> = row.iter().map(Vec::as_slice).collect();
            compress_slot(&refs, shape, components.min(row.len())).map_err(invalid)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let compress_s = started.elapsed().as_secs_f64();
    let (lights, views) = tables(g)?;
    let store = CompressedBtf::new(shape, lights, views, slots.clone()).map_err(invalid)?;
    Ok((store, slots, compress_s))
}

/// An error and its standard error.
#[derive(Debug, Clone, Copy)]
struct Measured {
    error: f64,
    spread: Option<f64>,
}

/// RMS error of the store at the held-out pairs, relative to the truth's
/// RMS, with its jackknife standard error over the pairs.
fn held_out_error(
    store: &CompressedBtf,
    truths: &[(Direction, Direction, Vec<f32>)],
) -> Result<Measured, ProcessError> {
    let mut per_pair = Vec::with_capacity(truths.len());
    for (l, v, truth) in truths {
        let tex = store
            .reconstruct(pdir(*l), pdir(*v))
            .map_err(|e| ProcessError::Invalid(e.to_string()))?;
        per_pair.push(squared_error(&tex, truth)?);
    }
    Ok(relative_rms_with_spread(&per_pair))
}

/// `(Σ (a − b)², Σ b²)` of a reconstructed texture against the true one,
/// value by value: grey against grey, interleaved RGB against RGB. Any
/// other pairing is an error, never a silent truncation.
fn squared_error(tex: &[f32], truth: &[f32]) -> Result<(f64, f64), ProcessError> {
    if tex.len() != truth.len() {
        return Err(ProcessError::Invalid(format!(
            "a reconstructed texture of {} values against a true one of {}",
            tex.len(),
            truth.len()
        )));
    }
    let (mut err, mut norm) = (0.0, 0.0);
    for (a, b) in tex.iter().zip(truth) {
        err += f64::from(a - b).powi(2);
        norm += f64::from(*b).powi(2);
    }
    Ok((err, norm))
}

/// `sqrt(Σ err / Σ norm)` over the pairs, and its jackknife standard
/// error: leave each pair out in turn, `sqrt((n − 1)/n · Σ (θ₋ᵢ − θ̄)²)`.
/// No spread with fewer than two pairs.
fn relative_rms_with_spread(per_pair: &[(f64, f64)]) -> Measured {
    let (err, norm) = per_pair
        .iter()
        .fold((0.0, 0.0), |(e, n), (a, b)| (e + a, n + b));
    let ratio = |e: f64, n: f64| (e.max(0.0) / n.max(1e-30)).sqrt();
    let error = ratio(err, norm);
    let n = per_pair.len();
    if n < 2 {
        return Measured {
            error,
            spread: None,
        };
    }
    let leave_out: Vec<f64> = per_pair
        .iter()
        .map(|(a, b)| ratio(err - a, norm - b))
        .collect();
    let mean = leave_out.iter().sum::<f64>() / n as f64;
    let var = leave_out.iter().map(|t| (t - mean).powi(2)).sum::<f64>();
    Measured {
        error,
        spread: Some(((n - 1) as f64 / n as f64 * var).sqrt()),
    }
}

/// A spread that is a number, else none.
fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// Runs every family and writes `tradeoff.csv`, `tradeoff.json` and
/// `tradeoff.svg` into `out`.
pub fn run(
    profile: &Profile,
    scene_name: &str,
    cfg: &TradeoffConfig,
    out: &Path,
    progress: &dyn Fn(&str),
) -> Result<Report, ProcessError> {
    if cfg.texture < 4 || cfg.texture > 256 || cfg.held_out == 0 || cfg.components == 0 {
        return Err(ProcessError::Invalid(format!(
            "texture {} (4..=256), held-out {} and components {} (≥ 1)",
            cfg.texture, cfg.held_out, cfg.components
        )));
    }
    // The laser family's MDF is measured against the scene.
    crate::truth::install();
    let scene = Scene::load_on(scene_name, &profile.holder)
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let solver = Solver::new(profile).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let held = held_out_pairs(cfg.held_out);
    let truths: Vec<(Direction, Direction, Vec<f32>)> = held
        .par_iter()
        .map(|&(l, v)| (l, v, true_texture(&scene, cfg.texture, l, v)))
        .collect();
    let mut rows = Vec::new();

    // Plans.
    let mut h2_grid = None;
    // The named plans' schedules, for the exposure family.
    let mut named: Vec<(&'static str, Schedule)> = Vec::new();
    for case in plan_cases(profile, &solver)? {
        progress(&format!("plan {}", case.name));
        let s = schedule::build(profile, &solver, &case.plan);
        // The ordered schedule's estimate: what the order report calls
        // `optimised_s`, without its bound and the `slots` comparison.
        let physical_s =
            crate::schedule::timing::Timing::new(profile, None).estimate_s(&s, |_| false);
        let g = grid(&s)?;
        let textures = true_textures(&scene, &g, cfg.texture);
        let (store, _, compress_s) = compress(&textures, &g, cfg.texture, cfg.components)?;
        let measured = held_out_error(&store, &truths)?;
        rows.push(Row {
            family: "plans".into(),
            setting: case.name.clone(),
            images: Some(s.images.len()),
            physical_s: Some(physical_s),
            bytes: Some(
                crate::schedule::volume::data_volume(profile, &s, &Default::default()).raw_bytes,
            ),
            error: Some(measured.error),
            spread: measured.spread,
            compute_s: Some(compress_s),
            unit: "relative".into(),
            directions: Some(case.directions.clone()),
            plan: case.spec.map(str::to_string),
            ..Row::default()
        });
        if let Some(spec) = case.spec {
            named.push((spec, s.clone()));
        }
        if case.name == "h2" {
            // The PCA family reuses H2's textures.
            h2_grid = Some((g, textures, physical_s, s.images.len()));
        }
    }

    // The shortcut above, measured: one plan through the whole chain.
    progress("plan h2, 3 rings through camera and registration");
    let mut chain = camera_chain(profile, &scene, scene_name, cfg, &truths, out)?;
    // The same plan at the rig's real camera resolution.
    chain.bytes = rows
        .iter()
        .find(|r| r.family == "plans" && r.setting == "h2, 3 rings")
        .and_then(|r| r.bytes);
    rows.push(chain);

    // PCA components, on H2.
    if let Some((g, textures, physical, images)) = &h2_grid {
        for c in [2usize, 4, 8, 16, 32] {
            progress(&format!("pca C = {c}"));
            let (store, slots, compress_s) = compress(textures, g, cfg.texture, c)?;
            let dir = out.join(format!(".pca-{c}"));
            let bytes = stored_bytes(&dir, &slots, g, cfg.texture, c);
            // Only the size was wanted: the files go either way.
            let _ = std::fs::remove_dir_all(&dir);
            let bytes = bytes?;
            let measured = held_out_error(&store, &truths)?;
            rows.push(Row {
                family: "pca".into(),
                setting: format!("C = {c}"),
                images: Some(*images),
                physical_s: Some(*physical),
                bytes: Some(bytes),
                error: Some(measured.error),
                spread: measured.spread,
                compute_s: Some(compress_s),
                unit: "relative".into(),
                ..Row::default()
            });
        }
    }

    let built: Vec<(&str, &Schedule)> = named.iter().map(|(n, s)| (*n, s)).collect();
    rows.extend(exposure::family(
        profile, &scene, &solver, cfg, &truths, &built, progress,
    )?);

    // Simulator fidelity.
    progress("fidelity");
    rows.extend(fidelity(&scene, cfg.render_size));

    progress("laser scan (MSRA rig, 26 sources)");
    rows.extend(laser_family(scene_name, out)?);
    progress("photometric stereo (VirTex rig)");
    rows.extend(ps_family(scene_name, out)?);

    let report = Report {
        profile: profile.name.clone(),
        scene: scene_name.to_string(),
        texture: cfg.texture,
        held_out: cfg.held_out,
        components: cfg.components,
        method: vec![
            "physical_s: motion-model estimate of the optimised order (the engine follows the same model)".into(),
            "plans: texture-space capture (the scene's true BTF at the achieved directions); camera and registration left out".into(),
            format!("plans, camera chain: the 3-ring plan captured by the simulated camera ({}×{} frames, every effect of the scene), registered by its markers (rectify to {}² float textures) and compressed; the gap to the texture-space row of the same plan is what that shortcut changes; time: the simulated run's physical duration", CHAIN_FRAME[0], CHAIN_FRAME[1], cfg.texture),
            "error: RMS over held-out (light, view) pairs relative to the truth's RMS".into(),
            "spread: one standard error of `error`: the jackknife over the held-out pairs (plans, pca), the standard error over 16 × 16-pixel tiles (laser, photometric stereo); fidelity has one frame and no spread".into(),
            format!("exposure: the policies an operator chooses among, on the profile's default plan (H1 where that is not every light with every view), in texture space: each sample of the true texture held at the sensor's full scale (white at {} of it at the profile's exposure), a series merged to the true value clipped at its shortest exposure's full scale (noise, vignetting and the lamp's fall-off left out); auto takes a step again, {}× shorter, while more than its threshold of the samples clip, and its time follows the engine's order (expose the next step, come back); near_mirror: the held-out error over {} pairs whose view lies within {}° of the light's mirror direction; clipped_share: the captured texels with a sample still at full scale", rigd_sim::scene::WHITE_LEVEL, crate::model::exposure::DEFAULT_AUTO_FACTOR, cfg.held_out, exposure::NEAR_MIRROR_DEG),
            "fidelity: error is the frame's RMS change with the effect off, relative to the frame's RMS".into(),
            "laser: one 26-source scan on the MSRA rig (cam3 at 40°, 160×120 frames, 1.5 mm steps) processed with subsets of its sources; time: motion-model estimate of a plan with that many sources; error: mean depth error in mm over the sample pixels every subset measures, so the subsets are compared on the same pixels (none when they share fewer than 50 pixels or 1 % of the sample); coverage: the share of the sample's pixels the subset itself measures, with its error over them in detail".into(),
            "photometric stereo: simulated VirTex captures (128×96 frames); time: the simulated run's physical duration; error: mean normal error in degrees over the sample pixels every layout solves; coverage: the share the layout itself solves".into(),
            "summary: per family, the knee of its frontier (the point farthest below the chord from the cheapest to the most accurate setting, both scaled to that span), and what the most accurate setting adds".into(),
        ],
        summary: summary(&rows),
        rows,
    };
    write_outputs(out, &report, Some(&profile.default_plan))?;
    Ok(report)
}

/// Frame size of the camera-chain capture. Smaller frames register too, but
/// the marker search then wades through the sample's texture (384×256 takes
/// three times as long).
const CHAIN_FRAME: [u32; 2] = [512, 384];

/// H2's three inner rings captured through the simulated camera, rectified
/// and compressed: the plan family's texture-space shortcut, checked. A
/// colour camera's textures are measured against the scene's RGB truth at
/// the held-out pairs of the grey `truths`.
fn camera_chain(
    profile: &Profile,
    scene: &Scene,
    scene_name: &str,
    cfg: &TradeoffConfig,
    truths: &[(Direction, Direction, Vec<f32>)],
    out: &Path,
) -> Result<Row, ProcessError> {
    use crate::postprocess::frames::RunFrames;
    use crate::postprocess::rectify::RectifyConfig;
    use crate::postprocess::rectify::TextureBits;
    let rings = 3;
    let dirs = plan::rings(&H2_THETAS[..rings], &HEMISPHERE_RING_COUNTS[..rings]);
    std::fs::create_dir_all(out)
        .map_err(|e| ProcessError::Invalid(format!("{}: {e}", out.display())))?;
    let plan_file = out.join(".tradeoff-chain-plan.json");
    let body = serde_json::json!({ "name": "h2-3rings", "directions": dirs });
    std::fs::write(&plan_file, body.to_string())
        .map_err(|e| ProcessError::Invalid(format!("{}: {e}", plan_file.display())))?;
    let mut p = profile.clone();
    crate::rig::sim::set_scene(&mut p, scene_name);
    p.sim.frame_size = CHAIN_FRAME;
    let dir = out.join(".tradeoff-chain");
    let plan_spec = plan_file.to_string_lossy().into_owned();
    let physical = capture(p, &plan_spec, &dir);
    let _ = std::fs::remove_file(&plan_file);
    let physical = physical?;
    let started = Instant::now();
    let frames = RunFrames::open(&dir)?;
    let images = frames.entries.len();
    let rectify = RectifyConfig {
        size: (4 * cfg.texture).max(64),
        roi: 1.0,
        final_size: cfg.texture,
        blend: 0,
        bits: TextureBits::Float,
    };
    crate::postprocess::rectify::rectify_run(&frames, &rectify, &|_, _| {})?;
    crate::postprocess::btf::btf_run(&dir, cfg.components, &|_, _| {})?;
    let compute_s = started.elapsed().as_secs_f64();
    let store = CompressedBtf::read(&crate::store::processed::btf_dir(&dir))
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let measured = if store.shape().channels() == 3 {
        let rgb: Vec<_> = truths
            .iter()
            .map(|&(l, v, _)| (l, v, true_texture_channels(scene, cfg.texture, l, v, 3)))
            .collect();
        held_out_error(&store, &rgb)?
    } else {
        held_out_error(&store, truths)?
    };
    let _ = std::fs::remove_dir_all(&dir);
    Ok(Row {
        family: "plans".into(),
        setting: format!("h2, {rings} rings{CAMERA_CHAIN_SUFFIX}"),
        images: Some(images),
        physical_s: Some(physical),
        bytes: None,
        error: Some(measured.error),
        spread: measured.spread,
        compute_s: Some(compute_s),
        unit: "relative".into(),
        detail: Some(format!(
            "{}×{} simulated frames, registered and compressed",
            CHAIN_FRAME[0], CHAIN_FRAME[1]
        )),
        ..Row::default()
    })
}

/// One simulated capture in virtual time into `out`; its physical duration.
fn capture(profile: Profile, plan: &str, out: &Path) -> Result<f64, ProcessError> {
    use crate::engine::PausePolicy;
    use crate::model::run_state::RunState;
    let invalid = |e: String| ProcessError::Invalid(format!("capture of `{plan}`: {e}"));
    let _ = std::fs::remove_dir_all(out);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .start_paused(true)
        .build()
        .map_err(|e| invalid(e.to_string()))?;
    runtime.block_on(async {
        let req = crate::engine::launch::NewRun {
            profile_source: format!("<tradeoff {}>", profile.name),
            profile,
            plan: plan.to_string(),
            sample: "tradeoff".into(),
            operator: None,
            notes: None,
            exposure_s: None,
            exposure_policy: None,
            frame_size: None,
            out: out.to_path_buf(),
            simulated: true,
            order: None,
        };
        let sim = crate::rig::sim::SimulatedRig::default();
        let p = crate::engine::launch::prepare_new(
            req,
            Some(&sim),
            rigd_core::Clock::virtual_time(),
            PausePolicy::Return,
        )
        .await
        .map_err(|e| invalid(e.to_string()))?;
        let outcome = p.engine.run().await.map_err(|e| invalid(e.to_string()))?;
        if outcome.state != RunState::Completed {
            return Err(invalid(format!(
                "ended {} ({})",
                outcome.state,
                outcome.reason.unwrap_or_default()
            )));
        }
        Ok(outcome.physical_s)
    })
}

/// MDF depth error against the number of laser source positions.
fn laser_family(scene_name: &str, out: &Path) -> Result<Vec<Row>, ProcessError> {
    let mut profile =
        Profile::load("msra-btf-mdf").map_err(|e| ProcessError::Invalid(e.to_string()))?;
    if let crate::model::profile::RigGeometry::TurntableArcs { cameras, .. } = &mut profile.rig {
        *cameras = vec!["cam3".into()];
    }
    profile.sim.frame_size = [160, 120];
    profile.sim.zoom = 2.4;
    crate::rig::sim::set_scene(&mut profile, scene_name);
    let plan = |n: usize| format!("laser:sources={n},turns=1,step=1.5");
    let dir = out.join(".tradeoff-laser");
    capture(profile.clone(), &plan(26), &dir)?;
    let run = crate::postprocess::frames::RunFrames::open(&dir)?;
    let solver = Solver::new(&profile).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let offer = schedule::rig_offer(&profile, &solver);
    // Each subset: its row without the error, and its error pixel by pixel.
    let mut subsets = Vec::new();
    for n in LASER_SOURCES {
        let cfg = crate::postprocess::mdf::MdfConfig {
            sources: Some(n),
            ..Default::default()
        };
        let started = Instant::now();
        let report = crate::postprocess::mdf::mdf_run(&run, &cfg, &|_, _| {})?;
        let compute_s = started.elapsed().as_secs_f64();
        let pixels = report
            .views
            .first()
            .and_then(|v| v.truth_pixels.clone())
            .ok_or_else(|| {
                ProcessError::Invalid("the laser scan's view has no ground truth".into())
            })?;
        let plan_n =
            plan::resolve(&plan(n), &offer).map_err(|e| ProcessError::Invalid(e.to_string()))?;
        let s = schedule::build(&profile, &solver, &plan_n);
        let physical = schedule::timing::Timing::new(&profile, None).estimate_s(&s, |_| false);
        let row = Row {
            family: "laser".into(),
            setting: format!("{n} source{}", if n == 1 { "" } else { "s" }),
            images: Some(s.images.len()),
            physical_s: Some(physical),
            compute_s: Some(compute_s),
            unit: "mm".into(),
            ..Row::default()
        };
        subsets.push((row, pixels));
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(rows_on_common_pixels(subsets, &|e| format!("{e:.3} mm")))
}

/// Source counts of the laser family's subsets.
const LASER_SOURCES: [usize; 4] = [1, 5, 13, 26];

/// The fewest pixels, and the smallest share of the sample's, that every
/// setting of a family must measure for their errors to be compared.
const COMMON_MIN: (usize, f64) = (50, 0.01);

/// A family's rows (laser subsets, photometric-stereo layouts) compared on
/// the same pixels: each setting's error is over the sample pixels that
/// every setting measures, so a setting that reaches more pixels is not
/// charged for the harder ones the others never saw (and one that reaches
/// fewer is not flattered by the easy ones). Its own coverage, and its
/// error over its own pixels, stay in `coverage` and `detail`. When the
/// settings share too few pixels ([`COMMON_MIN`]: they hardly see the
/// sample) the rows have no error, and `detail` says so. `text` writes an
/// error in the family's unit.
fn rows_on_common_pixels(
    subsets: Vec<(Row, crate::postprocess::accuracy::PixelErrors)>,
    text: &dyn Fn(f64) -> String,
) -> Vec<Row> {
    let len = subsets
        .iter()
        .map(|(_, p)| p.pixels.len())
        .min()
        .unwrap_or(0);
    let common: Vec<bool> = (0..len)
        .map(|k| subsets.iter().all(|(_, p)| p.measured(k)))
        .collect();
    let common_count = common.iter().filter(|c| **c).count();
    let sample = subsets.first().map_or(0, |(_, p)| p.sample_pixels());
    let comparable =
        common_count >= COMMON_MIN.0 && common_count as f64 >= COMMON_MIN.1 * sample as f64;
    subsets
        .into_iter()
        .map(|(mut row, pixels)| {
            let own = pixels.stats(|_| true);
            let shared = pixels.stats(|k| common.get(k).copied().unwrap_or(false));
            row.coverage = Some(own.coverage);
            let own_text = format!(
                "over its own {:.1} % of the sample: {}",
                100.0 * own.coverage,
                text(own.mean)
            );
            if comparable {
                row.error = finite(shared.mean);
                row.spread = finite(shared.spread);
                row.detail = Some(format!(
                    "error over the {common_count} sample pixels every setting measures (median {}, 95th percentile {}); {own_text}",
                    text(shared.median),
                    text(shared.p95)
                ));
            } else {
                row.detail = Some(format!(
                    "no error: the settings share only {common_count} measured pixels of the sample's {sample}, too few to compare (they hardly see this sample); {own_text}"
                ));
            }
            row
        })
        .collect()
}

/// Photometric-stereo normal error against the number of lamps.
fn ps_family(scene_name: &str, out: &Path) -> Result<Vec<Row>, ProcessError> {
    use rigd_process::photometric_stereo as ps;
    let base = Profile::load("virtex-photometric-stereo")
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let mut settings = Vec::new();
    let layouts: [(&str, Vec<Direction>); 3] = [
        ("3 lights", vec![]),
        (
            "6 lights",
            (0..6)
                .map(|k| Direction::new(45.0, 60.0 * k as f64))
                .collect(),
        ),
        (
            "12 lights",
            (0..12)
                .map(|k| {
                    Direction::new(
                        if k < 6 { 30.0 } else { 60.0 },
                        60.0 * (k % 6) as f64 + if k < 6 { 0.0 } else { 30.0 },
                    )
                })
                .collect(),
        ),
    ];
    for (name, lamps) in layouts {
        let mut profile = base.clone();
        if !lamps.is_empty() {
            with_lamps(&mut profile, &lamps)?;
        }
        crate::rig::sim::set_scene(&mut profile, scene_name);
        let dir = out.join(".tradeoff-ps");
        let physical = capture(profile, "lamps", &dir)?;
        let run = crate::postprocess::frames::RunFrames::open(&dir)?;
        let dataset = crate::postprocess::ps::ps_dataset_from_run(&run)?;
        let modes: &[bool] = if name == "3 lights" {
            &[false]
        } else {
            &[false, true]
        };
        for &robust in modes {
            let started = Instant::now();
            let result = ps::solve(
                &dataset,
                &ps::PsOptions {
                    robust,
                    ..Default::default()
                },
            )
            .map_err(|e| ProcessError::Invalid(format!("{name}: {e}")))?;
            let compute_s = started.elapsed().as_secs_f64();
            let (_, pixels) = crate::truth::ps_pixel_errors_against_truth(&run, &result)?
                .ok_or_else(|| {
                    ProcessError::Invalid(format!("{name}: the capture has no ground truth"))
                })?;
            let row = Row {
                family: "photometric stereo".into(),
                setting: if robust {
                    format!("{name}, robust")
                } else {
                    name.to_string()
                },
                images: Some(run.entries.len()),
                physical_s: Some(physical),
                compute_s: Some(compute_s),
                unit: "degrees".into(),
                ..Row::default()
            };
            settings.push((row, pixels));
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
    Ok(rows_on_common_pixels(settings, &|e| format!("{e:.2}°")))
}

/// Replaces a fixed-lamp rig's lamps with ones in `directions`, each a copy
/// of its first lamp on the next relay coil.
fn with_lamps(profile: &mut Profile, directions: &[Direction]) -> Result<(), ProcessError> {
    let crate::model::profile::RigGeometry::FixedLamps { lamps, .. } = &mut profile.rig else {
        return Err(ProcessError::Invalid("not a fixed-lamp rig".into()));
    };
    let template = lamps
        .first()
        .and_then(|l| profile.devices.get(l))
        .and_then(crate::model::profile::Device::as_lamp)
        .cloned()
        .ok_or_else(|| ProcessError::Invalid("the rig has no lamp".into()))?;
    for old in lamps.drain(..) {
        profile.devices.remove(&old);
    }
    for (k, d) in directions.iter().enumerate() {
        let name = format!("lamp{k}");
        let mut lamp = template.clone();
        lamp.direction = Some(*d);
        lamp.coil = k as u16;
        profile
            .devices
            .insert(name.clone(), crate::model::profile::Device::Lamp(lamp));
        lamps.push(name);
    }
    Ok(())
}

/// Writes the compressed BTF and returns its size on disk.
fn stored_bytes(
    dir: &Path,
    slots: &[SlotPca],
    g: &Grid,
    size: usize,
    components: usize,
) -> Result<u64, ProcessError> {
    let invalid = |e: rigd_process::btf::BtfError| ProcessError::Invalid(e.to_string());
    let shape = TextureShape::new(size, size, 1).map_err(invalid)?;
    let (lights, views) = tables(g)?;
    let mut w = BtfWriter::create(dir, shape, &lights, &views, components).map_err(invalid)?;
    for (k, pca) in slots.iter().enumerate() {
        w.write_slot(k, pca).map_err(invalid)?;
    }
    w.finish().map_err(invalid)?;
    let mut total = 0;
    for e in std::fs::read_dir(dir).map_err(|e| ProcessError::Invalid(e.to_string()))? {
        let e = e.map_err(|e| ProcessError::Invalid(e.to_string()))?;
        total += e.metadata().map(|m| m.len()).unwrap_or(0);
    }
    Ok(total)
}

/// Render time with every effect, then each effect off: time and change.
fn fidelity(scene: &Scene, size: [u32; 2]) -> Vec<Row> {
    let shot = |effects: EffectSwitches| Shot {
        light: Direction::new(60.0, 30.0).to_vector(),
        view: Direction::new(45.0, 180.0).to_vector(),
        width: size[0],
        height: size[1],
        seed: 1,
        effects,
        ..Shot::default()
    };
    let all: EffectSwitches = "all".parse().unwrap_or_default();
    let timed = |s: &Shot| {
        let started = Instant::now();
        let (pixels, plan) = scene.render_linear(s);
        (pixels, plan, started.elapsed().as_secs_f64())
    };
    let (reference, plan, t_all) = timed(&shot(all));
    let rms = |v: &[f32]| {
        (v.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>() / v.len().max(1) as f64).sqrt()
    };
    let ref_rms = rms(&reference).max(1e-30);
    let mut rows = vec![Row {
        family: "fidelity".into(),
        setting: format!("all effects ({})", plan.live),
        error: Some(0.0),
        compute_s: Some(t_all),
        unit: "relative".into(),
        ..Row::default()
    }];
    for effect in plan.live.iter().collect::<Vec<Effect>>() {
        let switches: EffectSwitches = format!("all,-{}", effect.name())
            .parse()
            .unwrap_or_default();
        let (pixels, _, t) = timed(&shot(switches));
        let diff: Vec<f32> = pixels.iter().zip(&reference).map(|(a, b)| a - b).collect();
        rows.push(Row {
            family: "fidelity".into(),
            setting: format!("without {}", effect.name()),
            error: Some(rms(&diff) / ref_rms),
            compute_s: Some(t),
            unit: "relative".into(),
            ..Row::default()
        });
    }
    rows
}

fn write_outputs(out: &Path, report: &Report, marked: Option<&str>) -> Result<(), ProcessError> {
    std::fs::create_dir_all(out).map_err(|error| StoreError::Io {
        path: out.to_path_buf(),
        op: "create directory",
        error,
    })?;
    let json =
        serde_json::to_vec_pretty(report).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    rigd_core::atomic::write(&out.join("tradeoff.json"), &json).map_err(StoreError::from)?;
    let opt = |v: Option<f64>| v.map(|x| format!("{x}")).unwrap_or_default();
    let mut csv = String::from(
        "family,setting,images,physical_s,bytes,error,spread,unit,coverage,compute_s,near_mirror_error,near_mirror_spread,clipped_share,detail\n",
    );
    for r in &report.rows {
        csv.push_str(&format!(
            "{},\"{}\",{},{},{},{},{},{},{},{},{},{},{},\"{}\"\n",
            r.family,
            r.setting.replace('"', "'"),
            r.images.map(|x| x.to_string()).unwrap_or_default(),
            opt(r.physical_s),
            r.bytes.map(|x| x.to_string()).unwrap_or_default(),
            opt(r.error),
            opt(r.spread),
            r.unit,
            opt(r.coverage),
            opt(r.compute_s),
            opt(r.near_mirror.map(|m| m.error)),
            opt(r.near_mirror.and_then(|m| m.spread)),
            opt(r.clipped_share),
            r.detail.clone().unwrap_or_default().replace('"', "'")
        ));
    }
    rigd_core::atomic::write(&out.join("tradeoff.csv"), csv.as_bytes())
        .map_err(StoreError::from)?;
    rigd_core::atomic::write(&out.join("tradeoff.svg"), svg(report, marked).as_bytes())
        .map_err(StoreError::from)?;
    Ok(())
}

/// The report's figure (see [`figure`]), with `marked` (a plan name,
/// the profile's default) ringed.
pub fn svg(report: &Report, marked: Option<&str>) -> String {
    figure::figure(report, marked).svg
}

/// The knee of each family's curve, in a sentence ([`choice::knee`]):
/// plans against physical time, PCA components against bytes,
/// photometric stereo and the laser scan against physical time (the laser
/// errors are over the pixels every subset measures, so they compare), and
/// the exposure policies' error near the mirror direction against physical
/// time.
pub fn summary(rows: &[Row]) -> Vec<String> {
    let curve_of = |family: &str,
                    cost: &dyn Fn(&Row) -> Option<f64>,
                    error: &dyn Fn(&Row) -> Option<f64>|
     -> Vec<choice::CurvePoint> {
        rows.iter()
            .filter(|r| r.family == family && !r.setting.ends_with(CAMERA_CHAIN_SUFFIX))
            .filter_map(|r| {
                Some(choice::CurvePoint {
                    label: r.setting.clone(),
                    cost: cost(r)?,
                    error: error(r)?,
                })
            })
            .collect()
    };
    let curve =
        |family: &str, cost: &dyn Fn(&Row) -> Option<f64>| curve_of(family, cost, &|r| r.error);
    let hours = |s: f64| {
        if s >= 3600.0 {
            format!("{:.1} h", s / 3600.0)
        } else if s >= 60.0 {
            format!("{:.0} min", s / 60.0)
        } else {
            format!("{s:.0} s")
        }
    };
    let percent = |e: f64| format!("{:.1} %", 100.0 * e);
    let points = |e: f64| format!("{:.1} points", 100.0 * e);
    let megabytes = |b: f64| format!("{:.1} MB", b / 1e6);
    let degrees = |e: f64| format!("{e:.1}°");
    let millimetres = |e: f64| format!("{e:.3} mm");
    let physical = |r: &Row| r.physical_s;
    let bytes = |r: &Row| r.bytes.map(|b| b as f64);
    let knees = [
        (
            "How many directions?",
            choice::knee(&curve("plans", &physical), &hours, &percent, &points),
        ),
        (
            "How many components?",
            choice::knee(&curve("pca", &bytes), &megabytes, &percent, &points),
        ),
        (
            "How many lights?",
            choice::knee(
                &curve("photometric stereo", &physical),
                &hours,
                &degrees,
                &degrees,
            ),
        ),
        (
            "Which exposures? Near the mirror direction,",
            choice::knee(
                &curve_of(exposure::FAMILY, &physical, &|r| {
                    r.near_mirror.map(|m| m.error)
                }),
                &hours,
                &percent,
                &points,
            ),
        ),
        (
            "How many laser sources?",
            choice::knee(
                &curve("laser", &physical),
                &hours,
                &millimetres,
                &millimetres,
            ),
        ),
    ];
    knees
        .into_iter()
        .filter_map(|(question, sentence)| Some(format!("{question} {}.", sentence?)))
        .collect()
}

/// Ends the setting of the `plans` row measured through the camera chain.
pub(crate) const CAMERA_CHAIN_SUFFIX: &str = ", camera chain";

/// The measured rows of the `plans` family, for [`choice::choose`]. The
/// camera-chain row is left out: it is a check of its plan's
/// texture-space row, the same plan measured another way, not a plan of
/// its own.
pub fn plan_points(rows: &[Row]) -> Vec<choice::PlanPoint> {
    rows.iter()
        .filter(|r| r.family == "plans" && !r.setting.ends_with(CAMERA_CHAIN_SUFFIX))
        .filter_map(|r| {
            Some(choice::PlanPoint {
                setting: r.setting.clone(),
                images: r.images,
                physical_s: r.physical_s?,
                error: r.error?,
            })
        })
        .collect()
}

/// Largest `tradeoff.json` read back (a report is a few hundred KiB).
pub const REPORT_LIMIT: u64 = 64 << 20;

/// The rows of a written report (`tradeoff.json`).
pub fn read_rows(json: &[u8]) -> Result<Vec<Row>, String> {
    read_report(json).map(|r| r.rows)
}

/// A written report (`tradeoff.json`).
pub fn read_report(json: &[u8]) -> Result<Report, String> {
    serde_json::from_slice::<Report>(json).map_err(|e| format!("not a trade-off report: {e}"))
}

/// Writes `tradeoff.svg` into `out` again from the report, with the
/// current figure and `marked` ringed.
pub fn redraw(out: &Path, report: &Report, marked: Option<&str>) -> Result<(), ProcessError> {
    rigd_core::atomic::write(&out.join("tradeoff.svg"), svg(report, marked).as_bytes())
        .map_err(StoreError::from)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A texture is compared value by value with a truth of its own size;
    /// an RGB texture against a grey truth (three times the values) is an
    /// error, not its first third compared with the whole truth.
    #[test]
    fn a_texture_is_compared_only_with_a_truth_of_its_own_channels() {
        let truth = [1.0_f32, 2.0, 3.0];
        assert_eq!(squared_error(&truth, &truth).ok(), Some((0.0, 14.0)));
        let rgb = [1.0_f32, 1.0, 1.0, 2.0, 2.0, 2.0, 3.0, 3.0, 4.0];
        let rgb_truth = [1.0_f32, 1.0, 1.0, 2.0, 2.0, 2.0, 3.0, 3.0, 3.0];
        assert_eq!(squared_error(&rgb, &rgb_truth).ok(), Some((1.0, 42.0)));
        assert!(squared_error(&rgb, &truth).is_err());
        assert!(squared_error(&[1.0; 4], &truth).is_err());
    }

    #[test]
    fn held_out_pairs_are_on_the_hemisphere_and_distinct() {
        let p = held_out_pairs(24);
        assert_eq!(p.len(), 24);
        for (l, v) in &p {
            for d in [l, v] {
                assert!((0.0..=70.0 + 1e-9).contains(&d.theta_deg), "{d:?}");
                assert!((0.0..360.0).contains(&d.phi_deg), "{d:?}");
            }
        }
        assert_ne!(p[0], p[1]);
    }

    #[test]
    fn the_jackknife_spread_is_zero_for_equal_pairs_and_grows_with_an_outlier() {
        let equal = relative_rms_with_spread(&[(1.0, 100.0); 6]);
        assert!((equal.error - 0.1).abs() < 1e-12);
        assert!(equal.spread.unwrap() < 1e-12);
        let mut pairs = vec![(1.0, 100.0); 6];
        pairs[0] = (16.0, 100.0);
        let outlier = relative_rms_with_spread(&pairs);
        assert!(outlier.error > 0.1 && outlier.spread.unwrap() > 0.01);
        // One pair: nothing to leave out.
        assert!(relative_rms_with_spread(&[(1.0, 4.0)]).spread.is_none());
        // No truth at all: no NaN.
        assert!(relative_rms_with_spread(&[(0.0, 0.0), (0.0, 0.0)]).error == 0.0);
    }

    #[test]
    fn settings_are_compared_on_the_pixels_all_of_them_measure() {
        use crate::postprocess::accuracy::{PixelError, PixelErrors};
        // 200 sample pixels in four blocks of 50, and an off-sample one.
        let img = |blocks: [Option<f64>; 4]| PixelErrors {
            width: 20,
            pixels: blocks
                .iter()
                .flat_map(|e| {
                    std::iter::repeat_n(e.map_or(PixelError::Unmeasured, PixelError::Measured), 50)
                })
                .chain([PixelError::OffSample])
                .collect(),
        };
        let row = |n: usize| Row {
            family: "laser".into(),
            setting: format!("{n} sources"),
            ..Row::default()
        };
        // The small subset measures the two easy blocks; the large one
        // also the two hard ones, and does better on the easy ones.
        let rows = rows_on_common_pixels(
            vec![
                (row(1), img([Some(0.2), Some(0.2), None, None])),
                (row(26), img([Some(0.1), Some(0.1), Some(0.9), Some(0.9)])),
            ],
            &|e| format!("{e:.3} mm"),
        );
        assert!((rows[0].error.unwrap() - 0.2).abs() < 1e-12);
        assert!((rows[1].error.unwrap() - 0.1).abs() < 1e-12);
        assert!((rows[0].coverage.unwrap() - 0.5).abs() < 1e-12);
        assert!((rows[1].coverage.unwrap() - 1.0).abs() < 1e-12);
        // Its own pixels' error (0.5 mm) stays in the detail.
        assert!(
            rows[1].detail.as_deref().unwrap().contains("0.500 mm"),
            "{:?}",
            rows[1].detail
        );
    }

    #[test]
    fn settings_that_share_too_few_pixels_have_no_error_and_say_why() {
        use crate::postprocess::accuracy::{PixelError, PixelErrors};
        // 400 sample pixels; the subsets share 3 of them.
        let img = |measured: usize| PixelErrors {
            width: 20,
            pixels: (0..400)
                .map(|k| {
                    if k < measured {
                        PixelError::Measured(0.1)
                    } else {
                        PixelError::Unmeasured
                    }
                })
                .collect(),
        };
        let row = || Row {
            family: "laser".into(),
            ..Row::default()
        };
        let rows = rows_on_common_pixels(vec![(row(), img(3)), (row(), img(300))], &|e| {
            format!("{e:.3} mm")
        });
        for r in &rows {
            assert!(r.error.is_none() && r.spread.is_none(), "{r:?}");
            assert!(r.detail.as_deref().unwrap().contains("too few to compare"));
        }
        assert!((rows[1].coverage.unwrap() - 0.75).abs() < 1e-12);
    }
}
