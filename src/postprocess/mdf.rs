//! `rigd process mdf`: the mesostructure distance function of a laser run
//! (Wang et al., §3.2). Per source position and camera, the laser plane's angle
//! comes from the two calibration frames (strip on the turntable and on the
//! plate); per sweep frame, the strip is found in the reference region
//! outside the sample's bounding box and its plane fixed; the space-time
//! analysis triangulates each pixel against its brightest frame's plane;
//! the displacement images of all sources of one view are merged with
//! Wang et al.'s tetrahedron-volume weights. `rigd_process::mdf` has the numerics;
//! this module feeds it a run directory and, for simulated runs, measures
//! the result against the scene.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use rigd_process::image_io::Image;
use rigd_process::mdf::{
    calibrate_plane, detect_line_in_regions, merge, plane_from_line, quantise_depth, space_time,
    DisplacementImage, LaserPlane, LineFit, PinholeCamera, PlaneConstraint, SpaceTimeOptions,
};
use serde::{Deserialize, Serialize};

use crate::kinematics::camera::camera_geometry;
use crate::plan::laser::{LaserPlan, LaserRig};
use crate::postprocess::accuracy::DepthError;
use crate::postprocess::frames::RunFrames;
use crate::postprocess::ProcessError;
use crate::schedule::laser::{LaserRole, LaserStep};
use crate::store::FrameEntry;
use rigd_core::geometry::Direction;

/// How a scan frame's laser plane is fixed besides its strip.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum PlaneModel {
    /// Wang et al.'s: every plane of a sweep makes the calibrated angle with
    /// the turntable (the emitter taken as far away).
    Calibrated,
    /// Through the emitter, whose place the profile gives; the calibration
    /// then only checks it.
    Emitter,
}

/// Settings of [`mdf_run`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MdfConfig {
    /// Gaussian filter before the strip search, pixels.
    pub sigma_px: f64,
    /// Grey level (0–1) a pixel's brightest frame must exceed to be
    /// triangulated (else it is occluded, −1).
    pub threshold: f64,
    /// Grey level (0–1) of the strip in the reference region, after the
    /// Gaussian filter: the holder is dark, so the strip is dimmer there.
    pub line_threshold: f64,
    /// How each scan frame's laser plane is fixed besides its strip.
    pub planes: PlaneModel,
    /// Use this many of the run's source positions (evenly picked), or all.
    pub sources: Option<usize>,
}

impl MdfConfig {
    /// The one check of these settings, for `rigd process mdf` and the
    /// daemon's jobs alike: the error names the option and its range.
    pub fn check(&self) -> Result<(), String> {
        if !(self.sigma_px.is_finite() && (0.0..=20.0).contains(&self.sigma_px)) {
            return Err(format!("sigma {}: expected 0 … 20 pixels", self.sigma_px));
        }
        for (name, t) in [
            ("threshold", self.threshold),
            ("line-threshold", self.line_threshold),
        ] {
            if !(t.is_finite() && t > 0.0 && t < 1.0) {
                return Err(format!("{name} {t}: expected a grey level between 0 and 1"));
            }
        }
        if self.sources == Some(0) {
            return Err("sources 0: expected at least 1 source position".into());
        }
        Ok(())
    }
}

impl Default for MdfConfig {
    fn default() -> MdfConfig {
        MdfConfig {
            sigma_px: 1.0,
            threshold: 0.15,
            line_threshold: 0.02,
            planes: PlaneModel::Calibrated,
            sources: None,
        }
    }
}

/// One source's calibration, seen by one camera.
#[derive(Debug, Clone, Serialize)]
pub struct CalibrationSummary {
    /// The laser source position (index along the light arc).
    pub source: usize,
    /// The camera whose calibration frames were used.
    pub camera: String,
    /// The laser plane's angle with the turntable, as calibrated.
    pub angle_deg: f64,
    /// The same angle from the profile's emitter geometry.
    pub geometric_angle_deg: f64,
    /// RMS distance of the two strips' back-projected points from the
    /// calibrated plane, mm (coplanarity residual).
    pub residual_mm: f64,
}

/// One view's merged displacement image.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ViewSummary {
    /// The turntable's position for this view, degrees.
    pub turntable_deg: f64,
    /// The camera that saw it.
    pub camera: String,
    /// The achieved view direction, sample frame.
    pub view: Direction,
    /// `processed/mdf/<name>.npy` (float32, mm, −1 = no measurement) and `.png`.
    pub name: String,
    /// Source positions whose sweeps were merged into this view.
    pub sources: usize,
    /// Sweep frames whose strip was not found in the reference region.
    pub frames_without_strip: usize,
    /// Share of the merged image's pixels with a measurement.
    pub valid_fraction: f64,
    /// Against the simulated scene: over the sample's measured pixels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub truth: Option<DepthError>,
    /// The error pixel by pixel, behind `truth` (not written to the
    /// report): `rigd tradeoff` compares source subsets on the pixels
    /// they all measure.
    #[serde(skip)]
    pub truth_pixels: Option<super::accuracy::PixelErrors>,
}

/// `processed/mdf/report.json`.
#[derive(Debug, Clone, Serialize)]
pub struct MdfReport {
    /// How the scan frames' planes were fixed.
    pub planes: PlaneModel,
    /// The source positions analysed (all, or those `--sources` picked).
    pub sources_used: Vec<usize>,
    /// Height of the reference plane over the turntable from which
    /// displacements are measured, mm.
    pub reference_mm: f64,
    /// The calibration of every source and camera that succeeded.
    pub calibrations: Vec<CalibrationSummary>,
    /// What could not be calibrated or analysed, and why: those sweeps are
    /// left out of their view's merge.
    pub skipped: Vec<String>,
    /// One merged displacement image per turntable position and camera.
    pub views: Vec<ViewSummary>,
    /// Mean over views of the views' mean error (simulated runs).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mean_error_mm: Option<f64>,
    /// Wall-clock time the processing took, seconds.
    pub elapsed_s: f64,
}

/// How far below the turntable a triangulated point may lie (measured
/// vertically) before it is rejected, metres.
const DEPTH_MARGIN_M: f64 = 0.005;
/// Views closer to the horizon than this are treated as this steep when
/// bounding depths.
const MIN_VIEW_COS: f64 = 0.05;

/// The deepest displacement a view can measure: from the reference plane
/// down to the margin below the turntable, along the view's rays.
fn max_depth_m(reference_m: f64, view: Direction) -> f64 {
    (reference_m + DEPTH_MARGIN_M) / view.theta_deg.to_radians().cos().max(MIN_VIEW_COS)
}

/// The pinhole model of `camera` looking at the sample from `view`
/// (sample frame) in frames of `size` pixels: what the space-time analysis
/// triangulates with, and what maps a view's displacement image back onto
/// the sample.
pub(crate) fn view_camera(
    profile: &crate::model::profile::Profile,
    camera: &str,
    size: [u32; 2],
    view: Direction,
) -> Result<PinholeCamera, ProcessError> {
    let g = camera_geometry(profile, camera, size)
        .ok_or_else(|| ProcessError::Invalid(format!("camera `{camera}` has no intrinsics")))?;
    let distance = g
        .distance_m
        .ok_or_else(|| ProcessError::Invalid(format!("camera `{camera}` has no distance_m")))?;
    PinholeCamera::looking_at_origin(
        view.to_vector(),
        distance,
        g.focal_px,
        size[0] as usize,
        size[1] as usize,
    )
    .map_err(|e| ProcessError::Invalid(format!("camera `{camera}`: {e}")))
}

/// Frames of one sweep seen by one camera, in frame order.
struct SweepView<'a> {
    source: usize,
    turntable_deg: f64,
    camera: String,
    step: LaserStep,
    frames: Vec<&'a FrameEntry>,
}

/// Where views merged ahead of `mdf` (tasks of a cluster's job array)
/// wait for it, inside `processed/`.
const AHEAD_DIR: &str = "mdf-ahead";

/// A view merged ahead: the key of the frames and settings it was made
/// from, its summary (None: none of its sweeps could be analysed) and the
/// sweeps of it that were left out, and why. Its `.npy` and `.png` are in
/// `processed/mdf/` already.
#[derive(Serialize, Deserialize)]
struct KeptView {
    key: String,
    summary: Option<ViewSummary>,
    skipped: Vec<String>,
}

fn kept_view_path(run: &Path, view: usize) -> PathBuf {
    crate::store::processed::processed_dir(run)
        .join(AHEAD_DIR)
        .join(format!("view_{view:03}.json"))
}

/// Computes the MDF of a laser run into `processed/mdf/`. Views merged
/// ahead from the same frames and settings ([`mdf_views_part`]) are taken
/// as they are.
pub fn mdf_run(
    run: &RunFrames,
    cfg: &MdfConfig,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<MdfReport, ProcessError> {
    mdf_views(run, cfg, None, progress)?.ok_or_else(|| ProcessError::Invalid("no report".into()))
}

/// The views (turntable position × camera) of a laser run's MDF, in the
/// order [`mdf_views_part`] numbers them.
pub fn mdf_view_count(run: &RunFrames, cfg: &MdfConfig) -> Result<usize, ProcessError> {
    let plan: &LaserPlan = run.meta.plan.laser.as_ref().ok_or_else(|| {
        ProcessError::Invalid(format!(
            "run {} is not a laser scan (plan `{}`)",
            run.root.display(),
            run.meta.plan.name
        ))
    })?;
    let rig = LaserRig::of(&run.meta.profile).ok_or_else(|| {
        ProcessError::Invalid(format!(
            "profile `{}` has no laser unit",
            run.meta.profile.name
        ))
    })?;
    let sources = pick_sources(plan.sources, cfg.sources)?;
    // A sweep's view is its first frame's, as `mdf_views` takes it.
    let mut sweeps: BTreeMap<(usize, &str), u64> = BTreeMap::new();
    for e in &run.entries {
        if let Some(LaserStep {
            role: LaserRole::Scan,
            sweep: Some(id),
            source,
            ..
        }) = e.laser
        {
            if sources.contains(&source) {
                let turn = e.positions.axes.get(&rig.turntable).copied().unwrap_or(0.0);
                sweeps
                    .entry((id, e.camera.as_str()))
                    .or_insert(turn.to_bits());
            }
        }
    }
    let views: std::collections::BTreeSet<(u64, &str)> = sweeps
        .iter()
        .map(|(&(_, camera), &turn)| (turn, camera))
        .collect();
    Ok(views.len())
}

/// Merges the views `views` (of [`mdf_view_count`]) of a laser run and
/// keeps each in `processed/mdf-ahead/` for `mdf` (one task of a cluster's
/// job array, [`crate::postprocess::parts`]); a view kept already from the
/// same frames is left as it is.
pub fn mdf_views_part(
    run: &RunFrames,
    cfg: &MdfConfig,
    views: std::ops::Range<usize>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<(), ProcessError> {
    mdf_views(run, cfg, Some(views), progress).map(|_| ())
}

/// What a view's merge depends on: the rigd version, the settings, the
/// view, and every frame of its sweeps and of its camera's calibration.
fn view_key(
    cfg: &MdfConfig,
    view: &(u64, String),
    frames: &mut dyn Iterator<Item = &FrameEntry>,
) -> String {
    use sha2::Digest;
    let mut hash = sha2::Sha256::new();
    for e in frames {
        hash.update(e.sha256.as_bytes());
    }
    format!(
        "{} {cfg:?} t{} {} {}",
        env!("CARGO_PKG_VERSION"),
        f64::from_bits(view.0),
        view.1,
        hex::encode(hash.finalize())
    )
}

/// [`mdf_run`] (`views` None: every view, then the report) or the part of
/// it a task does (`views` Some: those views, kept for `mdf`; no report).
fn mdf_views(
    run: &RunFrames,
    cfg: &MdfConfig,
    views: Option<std::ops::Range<usize>>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Option<MdfReport>, ProcessError> {
    let started = std::time::Instant::now();
    let plan: &LaserPlan = run.meta.plan.laser.as_ref().ok_or_else(|| {
        ProcessError::Invalid(format!(
            "run {} is not a laser scan (plan `{}`); capture one with `--plan laser`",
            run.root.display(),
            run.meta.plan.name
        ))
    })?;
    let profile = &run.meta.profile;
    let rig = LaserRig::of(profile).ok_or_else(|| {
        ProcessError::Invalid(format!("profile `{}` has no laser unit", profile.name))
    })?;
    cfg.check().map_err(ProcessError::Invalid)?;
    let sources = pick_sources(plan.sources, cfg.sources)?;
    let turntable = rig.turntable.clone();
    let turn_of = |e: &FrameEntry| e.positions.axes.get(&turntable).copied().unwrap_or(0.0);

    // Calibration frames by (source, camera, plane height); sweeps by id and camera.
    let mut calib: BTreeMap<(usize, String, u64), &FrameEntry> = BTreeMap::new();
    let mut sweeps: BTreeMap<(usize, String), SweepView> = BTreeMap::new();
    for e in &run.entries {
        let Some(step) = e.laser else { continue };
        match (step.role, step.sweep) {
            (LaserRole::Calibration, _) => {
                calib.insert((step.source, e.camera.clone(), step.plane_mm.to_bits()), e);
            }
            (LaserRole::Scan, Some(id)) if sources.contains(&step.source) => {
                sweeps
                    .entry((id, e.camera.clone()))
                    .or_insert_with(|| SweepView {
                        source: step.source,
                        turntable_deg: turn_of(e),
                        camera: e.camera.clone(),
                        step,
                        frames: Vec::new(),
                    })
                    .frames
                    .push(e);
            }
            _ => {}
        }
    }
    if sweeps.is_empty() {
        return Err(ProcessError::Invalid(format!(
            "run {} holds no sweep frames",
            run.root.display()
        )));
    }
    for s in sweeps.values_mut() {
        s.frames.sort_by_key(|e| e.laser.map_or(0, |l| l.frame));
    }
    // The views, numbered as `mdf_view_count` numbers them.
    let view_keys: Vec<(u64, String)> = sweeps
        .values()
        .map(|sv| (sv.turntable_deg.to_bits(), sv.camera.clone()))
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    let view_of = |sv: &SweepView| {
        view_keys
            .binary_search(&(sv.turntable_deg.to_bits(), sv.camera.clone()))
            .unwrap_or(usize::MAX)
    };
    let part = views.is_some();
    let selected = views.unwrap_or(0..view_keys.len());
    if selected.end > view_keys.len() {
        return Err(ProcessError::Invalid(format!(
            "views {}..{}: the run has {}",
            selected.start,
            selected.end,
            view_keys.len()
        )));
    }
    let keys: BTreeMap<usize, String> = selected
        .clone()
        .map(|v| {
            let mut frames = sweeps
                .values()
                .filter(|sv| view_of(sv) == v)
                .flat_map(|sv| sv.frames.iter().copied())
                .chain(
                    calib
                        .iter()
                        .filter(|((_, camera, _), _)| *camera == view_keys[v].1)
                        .map(|(_, e)| *e),
                );
            (v, view_key(cfg, &view_keys[v], &mut frames))
        })
        .collect();
    let out = crate::store::processed::mdf_dir(&run.root);
    let kept: BTreeMap<usize, KeptView> = keys
        .iter()
        .filter_map(|(&v, key)| {
            let bytes = std::fs::read(kept_view_path(&run.root, v)).ok()?;
            let k: KeptView = serde_json::from_slice(&bytes).ok()?;
            let files = k
                .summary
                .as_ref()
                .is_none_or(|s| out.join(format!("{}.npy", s.name)).is_file());
            (k.key == *key && files).then_some((v, k))
        })
        .collect();
    let size = {
        let first = run
            .entries
            .iter()
            .find(|e| e.laser.is_some())
            .ok_or_else(|| ProcessError::Invalid("no laser frames".into()))?;
        [first.width, first.height]
    };
    let camera_model = |camera: &str, view: Direction| view_camera(profile, camera, size, view);
    let box_half = plan.box_mm * 0.5e-3;

    // The calibration of every (source, camera), at turntable 0.
    let mut calibrations = Vec::new();
    let mut skipped = Vec::new();
    let mut calibrated: BTreeMap<(usize, String), LaserPlane> = BTreeMap::new();
    for &k in &sources {
        for (camera, _) in &rig.cameras {
            let key = |h: f64| (k, camera.clone(), h.to_bits());
            let (Some(low), Some(high)) = (calib.get(&key(0.0)), calib.get(&key(plan.plate_mm)))
            else {
                return Err(ProcessError::Invalid(format!(
                    "source {k}, camera {camera}: the calibration frames on the turntable and on the {} mm plate are missing",
                    plan.plate_mm
                )));
            };
            let cam = camera_model(camera, low.achieved_view)?;
            let regions = reference_regions(&cam, box_half);
            let line = |e: &FrameEntry, what: &str| -> Result<LineFit, ProcessError> {
                let img = run.image(e)?;
                detect_line_in_regions(&img, &regions, cfg.sigma_px, cfg.line_threshold).map_err(
                    |err| {
                        ProcessError::Invalid(format!(
                            "source {k}, camera {camera}: no strip on the {what} ({}): {err}",
                            e.file
                        ))
                    },
                )
            };
            let cal = line(low, "turntable").and_then(|l0| {
                let lh = line(high, "plate")?;
                calibrate_plane(&cam, &l0, &lh, plan.plate_mm * 1e-3).map_err(|err| {
                    ProcessError::Invalid(format!("source {k}, camera {camera}: {err}"))
                })
            });
            let cal = match cal {
                Ok(c) => c,
                Err(e) => {
                    skipped.push(e.to_string());
                    continue;
                }
            };
            let azimuth = low.laser.map_or(0.0, |l| l.source_direction.phi_deg);
            let geometric = rig
                .geometry
                .plane(azimuth, low.laser.map_or(0.0, |l| l.tilt_deg))
                .map_or(f64::NAN, |(_, n)| n[2].abs().min(1.0).acos().to_degrees());
            calibrations.push(CalibrationSummary {
                source: k,
                camera: camera.clone(),
                angle_deg: cal.tilt_deg,
                geometric_angle_deg: geometric,
                residual_mm: cal.residual_m * 1e3,
            });
            calibrated.insert((k, camera.clone()), cal.plane);
        }
    }

    // Space-time analysis per sweep and camera, in parallel.
    // Wang et al.'s planes need the calibration of their source and camera.
    let jobs: Vec<&SweepView> = sweeps
        .values()
        .filter(|sv| {
            let v = view_of(sv);
            selected.contains(&v)
                && !kept.contains_key(&v)
                && (cfg.planes == PlaneModel::Emitter
                    || calibrated.contains_key(&(sv.source, sv.camera.clone())))
        })
        .collect();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let analysed: Vec<Result<(DisplacementImage, usize), ProcessError>> = jobs
        .par_iter()
        .map(|sv| {
            let opts = SpaceTimeOptions::new(
                cfg.threshold,
                plan.reference_mm * 1e-3,
                max_depth_m(plan.reference_mm * 1e-3, sv.frames[0].achieved_view),
            );
            let r = sweep_displacement(
                run,
                sv,
                cfg,
                &opts,
                &rig,
                &calibrated,
                &camera_model,
                box_half,
            );
            let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress(n, jobs.len());
            r
        })
        .collect();
    // Unreadable frames are an error; a sweep the analysis rejects is
    // skipped, and said with its view.
    let mut results = Vec::with_capacity(analysed.len());
    let mut analysed_jobs = Vec::with_capacity(analysed.len());
    let mut view_skipped: BTreeMap<usize, Vec<String>> = BTreeMap::new();
    for (sv, r) in jobs.iter().zip(analysed) {
        match r {
            Ok(d) => {
                results.push(d);
                analysed_jobs.push(*sv);
            }
            Err(e @ ProcessError::Frame { .. }) => return Err(e),
            Err(e) => view_skipped
                .entry(view_of(sv))
                .or_default()
                .push(e.to_string()),
        }
    }
    let jobs = analysed_jobs;

    // Merge the sources of each view.
    let mut by_view: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (i, sv) in jobs.iter().enumerate() {
        by_view.entry(view_of(sv)).or_default().push(i);
    }
    std::fs::create_dir_all(&out).map_err(|e| io_error(&out, e))?;
    let truth_source = depth_truth(run)?;
    let mut views = Vec::new();
    for v in selected.clone() {
        if let Some(k) = kept.get(&v) {
            views.extend(k.summary.clone());
            skipped.extend(k.skipped.iter().cloned());
            continue;
        }
        let left_out = view_skipped.remove(&v).unwrap_or_default();
        let Some(members) = by_view.get(&v) else {
            if part {
                keep_view(&run.root, v, &keys[&v], None, &left_out)?;
            }
            skipped.extend(left_out);
            continue;
        };
        let camera = &view_keys[v].1;
        let first = jobs[members[0]];
        let view = first.frames[0].achieved_view;
        let cam = camera_model(camera, view)?;
        let displacements: Vec<DisplacementImage> =
            members.iter().map(|&i| results[i].0.clone()).collect();
        let positions: Vec<[f64; 3]> = members
            .iter()
            .map(|&i| rig.geometry.emitter(jobs[i].step.source_direction.phi_deg))
            .collect();
        let merged = merge(&displacements, &positions, &cam, box_half, true)
            .map_err(|e| ProcessError::Invalid(format!("view {camera}: {e}")))?;
        let name = format!("t{:03}_{camera}", first.turntable_deg.round() as i64);
        write_view(
            &out,
            &name,
            &merged,
            max_depth_m(plan.reference_mm * 1e-3, view),
        )?;
        let truth_pixels = truth_source
            .as_ref()
            .map(|t| t.depth_errors(&cam, &merged, plan.reference_mm * 1e-3, box_half));
        let truth = truth_pixels.as_ref().map(|p| p.summary());
        let summary = ViewSummary {
            turntable_deg: first.turntable_deg,
            camera: camera.clone(),
            view,
            name,
            sources: members.len(),
            frames_without_strip: members.iter().map(|&i| results[i].1).sum(),
            valid_fraction: merged.valid_fraction(),
            truth,
            truth_pixels,
        };
        if part {
            keep_view(&run.root, v, &keys[&v], Some(&summary), &left_out)?;
        }
        skipped.extend(left_out);
        views.push(summary);
    }
    if part {
        return Ok(None);
    }
    if views.is_empty() {
        return Err(ProcessError::Invalid(format!(
            "no sweep could be analysed: {}",
            skipped.join("; ")
        )));
    }
    let errors: Vec<f64> = views
        .iter()
        .filter_map(|v| v.truth.map(|t| t.mean_mm))
        .filter(|m| m.is_finite())
        .collect();
    let report = MdfReport {
        planes: cfg.planes,
        sources_used: sources,
        reference_mm: plan.reference_mm,
        calibrations,
        skipped,
        views,
        mean_error_mm: (!errors.is_empty())
            .then(|| errors.iter().sum::<f64>() / errors.len() as f64),
        elapsed_s: started.elapsed().as_secs_f64(),
    };
    let json = serde_json::to_vec_pretty(&report)
        .map_err(|e| ProcessError::Invalid(format!("report: {e}")))?;
    let path = out.join("report.json");
    rigd_core::atomic::write(&path, &json).map_err(|e| io_error(&path, e.error))?;
    let ahead = crate::store::processed::processed_dir(&run.root).join(AHEAD_DIR);
    if let Err(e) = std::fs::remove_dir_all(&ahead) {
        if e.kind() != std::io::ErrorKind::NotFound {
            tracing::warn!("{}: {e}", ahead.display());
        }
    }
    Ok(Some(report))
}

/// Keeps view `view`'s merge for `mdf` (written after its files).
fn keep_view(
    run: &Path,
    view: usize,
    key: &str,
    summary: Option<&ViewSummary>,
    skipped: &[String],
) -> Result<(), ProcessError> {
    let path = kept_view_path(run, view);
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| io_error(dir, e))?;
    }
    let kept = KeptView {
        key: key.to_string(),
        summary: summary.cloned(),
        skipped: skipped.to_vec(),
    };
    let json = serde_json::to_vec(&kept).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    crate::store::write_atomic(&path, &json)?;
    Ok(())
}

/// `n` of `total` source indices, evenly spread (all when `n` is None).
fn pick_sources(total: usize, n: Option<usize>) -> Result<Vec<usize>, ProcessError> {
    match n {
        None => Ok((0..total).collect()),
        Some(n) if n >= 1 && n <= total => Ok((0..n).map(|i| i * total / n).collect()),
        Some(n) => Err(ProcessError::Invalid(format!(
            "--sources {n}: the run has {total} source positions"
        ))),
    }
}

/// The image rectangles `[x0, y0, x1, y1)` outside the sample's bounding
/// box on the turntable: Wang et al.'s reference region.
fn reference_regions(cam: &PinholeCamera, box_half: f64) -> Vec<[usize; 4]> {
    let (w, h) = (cam.width, cam.height);
    let corners = [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]
        .map(|[a, b]| cam.project([a * box_half, b * box_half, 0.0]));
    let margin = 2.0;
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for c in corners.iter().flatten() {
        x0 = x0.min(c[0] - margin);
        y0 = y0.min(c[1] - margin);
        x1 = x1.max(c[0] + margin);
        y1 = y1.max(c[1] + margin);
    }
    let clamp = |v: f64, hi: usize| v.clamp(0.0, hi as f64) as usize;
    let (bx0, by0, bx1, by1) = (clamp(x0, w), clamp(y0, h), clamp(x1, w), clamp(y1, h));
    let min = 4;
    [
        [0, 0, bx0, h],
        [bx1, 0, w, h],
        [bx0, 0, bx1, by0],
        [bx0, by1, bx1, h],
    ]
    .into_iter()
    .filter(|r| r[2] >= r[0] + min && r[3] >= r[1] + min)
    .collect()
}

/// One sweep seen by one camera: its displacement image, and how many
/// frames showed no strip in the reference region (left out).
#[allow(clippy::too_many_arguments)]
fn sweep_displacement(
    run: &RunFrames,
    sv: &SweepView,
    cfg: &MdfConfig,
    opts: &SpaceTimeOptions,
    rig: &LaserRig,
    calibrated: &BTreeMap<(usize, String), LaserPlane>,
    camera_model: &(dyn Fn(&str, Direction) -> Result<PinholeCamera, ProcessError> + Sync),
    box_half: f64,
) -> Result<(DisplacementImage, usize), ProcessError> {
    let cam = camera_model(&sv.camera, sv.frames[0].achieved_view)?;
    let regions = reference_regions(&cam, box_half);
    let azimuth = sv.step.source_direction.phi_deg;
    let constraint = match cfg.planes {
        PlaneModel::Emitter => PlaneConstraint::ThroughEmitter(rig.geometry.emitter(azimuth)),
        PlaneModel::Calibrated => {
            let cal = calibrated
                .get(&(sv.source, sv.camera.clone()))
                .ok_or_else(|| {
                    ProcessError::Invalid(format!("source {} not calibrated", sv.source))
                })?;
            // Calibrated at turntable 0: turn the plane with the sample.
            let a = (-sv.turntable_deg).to_radians();
            let n = cal.normal;
            let normal = [
                a.cos() * n[0] - a.sin() * n[1],
                a.sin() * n[0] + a.cos() * n[1],
                n[2],
            ];
            PlaneConstraint::CalibratedTilt(LaserPlane {
                normal,
                offset: cal.offset,
            })
        }
    };
    let mut frames: Vec<Image> = Vec::with_capacity(sv.frames.len());
    let mut planes = Vec::with_capacity(sv.frames.len());
    let mut missing = 0;
    for e in &sv.frames {
        let img = run.image(e)?;
        let tilt = e.laser.map_or(0.0, |l| l.tilt_deg);
        let nominal = rig.geometry.plane(azimuth, tilt);
        let plane = detect_line_in_regions(&img, &regions, cfg.sigma_px, cfg.line_threshold)
            .ok()
            .and_then(|line| {
                let plane = plane_from_line(&cam, &line, 0.0, constraint).ok()?;
                let on_turntable = cam.back_project_to_height(line.point[0], line.point[1], 0.0)?;
                let (emitter, normal) = nominal?;
                // Wang et al.'s parallel planes differ from the true ones by
                // up to the sweep's tilt range: only their strip is checked.
                let check_angle = cfg.planes == PlaneModel::Emitter;
                plausible(&plane, on_turntable, emitter, normal, check_angle).then_some(plane)
            });
        match plane {
            Some(p) => {
                frames.push(img);
                planes.push(p);
            }
            None => missing += 1,
        }
    }
    let (d, _) = space_time(&frames, &planes, &cam, opts).map_err(|e| {
        ProcessError::Invalid(format!(
            "sweep of source {} seen by {}: {e}",
            sv.source, sv.camera
        ))
    })?;
    Ok((d, missing))
}

/// Largest angle between a frame's plane and the plane its measured tilt
/// predicts, and largest distance of its strip from the predicted one: a
/// strip found in the reference region that breaks these is something
/// else (a reflection, a fragment at a grazing view) and the frame is left
/// out rather than triangulated against a wrong plane.
const MAX_PLANE_ANGLE_DEG: f64 = 1.5;
const MAX_STRIP_OFFSET_M: f64 = 0.003;

fn plausible(
    plane: &LaserPlane,
    strip: [f64; 3],
    emitter: [f64; 3],
    normal: [f64; 3],
    check_angle: bool,
) -> bool {
    let cos = (0..3)
        .map(|k| plane.normal[k] * normal[k])
        .sum::<f64>()
        .abs();
    let off = (0..3)
        .map(|k| (strip[k] - emitter[k]) * normal[k])
        .sum::<f64>()
        .abs();
    (!check_angle || cos >= MAX_PLANE_ANGLE_DEG.to_radians().cos()) && off <= MAX_STRIP_OFFSET_M
}

/// Writes a view's displacement: float32 millimetres (−1 = none) and an
/// 8-bit PNG (255 = none).
fn write_view(
    dir: &Path,
    name: &str,
    d: &DisplacementImage,
    max_depth_m: f64,
) -> Result<(), ProcessError> {
    let mm: Vec<f32> = d
        .depth
        .iter()
        .map(|&v| if v >= 0.0 { v * 1e3 } else { v })
        .collect();
    let npy = dir.join(format!("{name}.npy"));
    rigd_process::npy::write_f32(&npy, &[d.height, d.width], &mm)
        .map_err(|e| ProcessError::Invalid(format!("{}: {e}", npy.display())))?;
    let codes = quantise_depth(d, max_depth_m)
        .map_err(|e| ProcessError::Invalid(format!("{name}: {e}")))?;
    let mut img = Image::new(d.width, d.height, 1);
    for (p, c) in img.data.iter_mut().zip(codes) {
        *p = f32::from(c) / 255.0;
    }
    let png = dir.join(format!("{name}.png"));
    rigd_process::image_io::write_png(&png, &img, rigd_process::image_io::PngDepth::Eight)
        .map_err(|e| ProcessError::Invalid(format!("{}: {e}", png.display())))
}

fn io_error(path: &Path, e: std::io::Error) -> ProcessError {
    ProcessError::io(path, "write", e)
}

/// The true surface under a run, against which the MDF's depths are
/// measured: the simulator's scene, for a simulated run. Processing never
/// links the simulator; the program that does installs a source of truth
/// with [`install_depth_truth`].
pub trait DepthTruth: Send + Sync {
    /// The measured displacement `d` against the true one, pixel by pixel,
    /// over pixels whose true surface point lies within `box_half` of the
    /// sample centre: the distance along the pixel's ray from the
    /// reference plane (`reference_m` above the holder) to the first
    /// surface hit.
    fn depth_errors(
        &self,
        cam: &PinholeCamera,
        d: &DisplacementImage,
        reference_m: f64,
        box_half: f64,
    ) -> super::accuracy::PixelErrors;
}

/// A run's depth truth, if it has one.
pub type DepthTruthSource = fn(&RunFrames) -> Result<Option<Box<dyn DepthTruth>>, ProcessError>;

static DEPTH_TRUTH: std::sync::OnceLock<DepthTruthSource> = std::sync::OnceLock::new();

/// Installs where MDF steps find a run's depth truth (once per process;
/// later calls change nothing). Without one, views carry no truth.
pub fn install_depth_truth(source: DepthTruthSource) {
    let _ = DEPTH_TRUTH.set(source);
}

fn depth_truth(run: &RunFrames) -> Result<Option<Box<dyn DepthTruth>>, ProcessError> {
    match DEPTH_TRUTH.get() {
        Some(source) => source(run),
        None => Ok(None),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sources_are_picked_evenly() {
        assert_eq!(pick_sources(26, Some(1)).ok(), Some(vec![0]));
        assert_eq!(pick_sources(26, Some(2)).ok(), Some(vec![0, 13]));
        assert_eq!(pick_sources(4, None).ok(), Some(vec![0, 1, 2, 3]));
        assert!(pick_sources(4, Some(5)).is_err());
        assert!(pick_sources(4, Some(0)).is_err());
    }

    #[test]
    fn the_reference_region_leaves_out_the_box() {
        let cam = PinholeCamera::looking_at_origin([0.0, 0.0, 1.0], 0.9, 1000.0, 320, 240)
            .unwrap_or_else(|e| panic!("{e}"));
        // A 100 mm box at 0.9 m and f = 1000 px spans about 111 px.
        let regions = reference_regions(&cam, 0.05);
        assert_eq!(regions.len(), 4, "{regions:?}");
        for r in &regions {
            for (x, y) in [(r[0], r[1]), (r[2] - 1, r[3] - 1)] {
                let p = cam
                    .back_project_to_height(x as f64 + 0.5, y as f64 + 0.5, 0.0)
                    .unwrap_or([0.0; 3]);
                assert!(p[0].abs() > 0.05 || p[1].abs() > 0.05, "{r:?} {p:?}");
            }
        }
    }
}
