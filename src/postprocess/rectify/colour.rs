//! `rigd process colour`: a colour camera's white balance and 3×3 colour
//! correction, measured on the holder's reference patches
//! ([`rigd_core::holder::COLOUR_PATCHES`]) in the run's most frontal
//! frames, and each patch's colour difference ΔE*ab after correction, in
//! the fit and held out of it. Kept in `RUN/processed/colour.json`.

use std::path::{Path, PathBuf};

use rigd_core::geometry::Direction;
use rigd_core::holder::PlacedPatch;
use rigd_process::colour::{self as cc, ColourCalibration, PatchReading};
use serde::{Deserialize, Serialize};

use crate::postprocess::chart::ColourCalibrationFile;
use crate::postprocess::frames::{ColourPlanes, RunFrames};
use crate::postprocess::ProcessError;

/// The calibration's file in `RUN/processed/`.
pub const COLOUR_FILE: &str = "colour.json";

/// A camera calibration given to the run, in `RUN/processed/`.
pub const CAMERA_COLOUR_FILE: &str = "camera-colour.json";

/// Frames tried, most frontal first, before the step gives up.
const MAX_CANDIDATES: usize = 24;

/// Usable frames whose readings are averaged: each sees the patches at
/// another phase of the filter array and with its own noise.
const FRAMES_AVERAGED: usize = 8;

/// Sample points across a patch, per side.
const POINTS_PER_SIDE: usize = 9;

/// Fraction of a patch's side that is read: its edges blur into the plate
/// through the demosaic and the lens.
const INNER_FRACTION: f64 = 0.6;

/// A patch whose brightest channel reads above this fraction of full scale
/// may be clipped.
const SATURATION: f64 = 0.95;

/// The neutral plate beside a patch, left and right of it, is read from
/// this far from the patch's centre to this far, in half sides: clear of
/// the patch's blurred edge and of its neighbours.
const PLATE_BESIDE: [f64; 2] = [1.6, 2.1];

/// What `rigd process colour` measured and keeps.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ColourReport {
    /// The frames the patches were read in (image indices), most frontal
    /// first; their readings are averaged.
    pub frames: Vec<usize>,
    /// The camera that took them.
    pub camera: String,
    /// The most frontal frame's achieved light direction.
    pub light: Direction,
    /// The most frontal frame's achieved view direction.
    pub view: Direction,
    /// White balance and colour correction: `corrected = matrix ·
    /// (white_balance ⊙ raw)`, raw the camera's linear values.
    pub calibration: ColourCalibration,
    /// The same white balance and correction scaled so that the white
    /// patch's green keeps its raw value: what `rigd process rectify`
    /// applies to every frame, so RGB textures keep the grey pipeline's
    /// scale (fraction of full scale) instead of this frame's exposure.
    pub texture_calibration: ColourCalibration,
    /// Every patch: what it is, what the camera read and how close the
    /// correction brings it.
    pub patches: Vec<PatchReport>,
    /// The 3×3 matrix and the root-polynomial correction fitted on the
    /// patches' L\*a\*b\* references and judged by CIEDE2000, in the fit
    /// and left out (`rigd_process::colour::chart_fit`); None with too few
    /// patches (a root-polynomial needs 7 to be judged). Where the
    /// root-polynomial is chosen, it is `texture_calibration`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chart_fit: Option<cc::chart_fit::ChartFit>,
}

/// One reference patch in the report.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PatchReport {
    /// `white`, `red`, …
    pub name: String,
    /// Its known reflectance, linear sRGB.
    pub reference: [f64; 3],
    /// The camera's mean linear values over it, evened out for the light
    /// the patch gets against the others (as the neutral plate beside each
    /// patch measures it), averaged over the frames with each frame scaled
    /// to the most frontal one's white: fraction of full scale in that
    /// frame.
    pub raw: [f64; 3],
    /// `raw` through the calibration, linear sRGB.
    pub corrected: [f64; 3],
    /// ΔE*ab of `corrected` against `reference`.
    pub delta_e: f64,
    /// ΔE*ab when the matrix is fitted without this patch; the white
    /// patch, which sets the balance, is never left out.
    pub delta_e_held_out: Option<f64>,
    /// ΔE*ab after white balance alone (scaled so white's green is right):
    /// what the matrix adds.
    pub delta_e_white_balance_only: f64,
}

impl ColourReport {
    /// The report as `rigd process colour` prints it.
    pub fn table(&self) -> String {
        use std::fmt::Write;
        let [r, g, b] = self.calibration.white_balance;
        let mut out = format!(
            "{} frames of `{}` averaged, the most frontal {} (light θ {:.1}° φ {:.1}°, view θ \
             {:.1}° φ {:.1}°)\nwhite balance: R ×{r:.3}, G ×{g:.3}, B ×{b:.3}\n\
             colour correction:\n",
            self.frames.len(),
            self.camera,
            self.frames.first().copied().unwrap_or_default(),
            self.light.theta_deg,
            self.light.phi_deg,
            self.view.theta_deg,
            self.view.phi_deg,
        );
        for row in &self.calibration.matrix {
            let _ = writeln!(out, "  {:>8.4} {:>8.4} {:>8.4}", row[0], row[1], row[2]);
        }
        let _ = writeln!(
            out,
            "patch    reference (linear sRGB)  corrected                ΔE*ab  held out  WB only"
        );
        let rgb = |v: [f64; 3]| format!("{:.3} {:.3} {:.3}", v[0], v[1], v[2]);
        for p in &self.patches {
            let held = p
                .delta_e_held_out
                .map_or("-".to_string(), |e| format!("{e:.2}"));
            let _ = writeln!(
                out,
                "{:<8} {:<24} {:<24} {:>5.2} {:>9} {:>8.2}",
                p.name,
                rgb(p.reference),
                rgb(p.corrected),
                p.delta_e,
                held,
                p.delta_e_white_balance_only
            );
        }
        if let Some(fit) = &self.chart_fit {
            let _ = writeln!(out, "CIEDE2000 against the patches' L*a*b* (D50):");
            for (name, f) in [
                ("3x3 matrix", &fit.matrix),
                ("root-polynomial", &fit.root_polynomial),
            ] {
                let left = |v: Option<f64>| v.map_or("-".to_string(), |e| format!("{e:.2}"));
                let _ = writeln!(
                    out,
                    "  {name:<16} in the fit mean {:.2} max {:.2}; left out mean {} max {}",
                    f.mean_delta_e2000,
                    f.max_delta_e2000,
                    left(f.mean_delta_e2000_left_out),
                    left(f.max_delta_e2000_left_out)
                );
            }
            let _ = writeln!(out, "  better left out: {:?}", fit.chosen);
        }
        let textures = if self.texture_calibration.root_polynomial.is_some() {
            "the root-polynomial"
        } else {
            "the white balance and 3x3 colour correction"
        };
        let _ = writeln!(out, "textures are corrected by {textures}");
        out
    }

    /// Reads a run's `processed/colour.json`.
    pub fn read(run: &Path) -> Result<ColourReport, ProcessError> {
        let path = colour_file(run);
        let bytes = std::fs::read(&path).map_err(|e| ProcessError::Frame {
            path: path.clone(),
            message: format!("{e} (run `rigd process colour` first)"),
        })?;
        serde_json::from_slice(&bytes).map_err(|e| ProcessError::Frame {
            path,
            message: e.to_string(),
        })
    }
}

/// The colour calibration `rigd process rectify` applies to a run's frames,
/// for its camera: the run's `processed/colour.json`, or else the camera
/// calibration it was given (`processed/camera-colour.json`,
/// [`import_calibration`]). When there is neither,
/// the run's camera records colour and its holder carries the reference
/// patches, and `calibrate` is set, it is measured now
/// ([`calibrate_run`]) and written. `None` means grey textures: a
/// monochrome camera, or a colour camera with no calibration (no patches
/// to measure one on, or one that failed: logged). An error if the file
/// cannot be read, or the run has frames of another camera, which it does
/// not calibrate.
pub fn texture_colour(
    run: &RunFrames,
    calibrate: bool,
) -> Result<Option<ColourCalibration>, ProcessError> {
    let measure = if calibrate {
        Measure::Now
    } else {
        Measure::Never
    };
    // Measured now, nothing is waited for: every frame there will be is here.
    Ok(texture_colour_by(run, measure)?.flatten())
}

/// The colour calibration of a run still capturing, the same one
/// [`texture_colour`] finds when the capture has ended, so that the frames
/// registered during the capture are the ones `rigd process rectify` keeps.
/// A run calibrated on its own patches is measured on its most frontal
/// frames: until no frame still to come can be among them, there is none
/// yet, and the frames wait.
#[derive(Debug, Default)]
pub struct ColourWhileCapturing {
    /// The patches read so far, by image index.
    readings: PatchReadings,
    /// The calibration once it is known (`Some(None)`: grey textures).
    known: Option<Option<ColourCalibration>>,
}

impl ColourWhileCapturing {
    /// The textures' calibration for `run` (the journal so far): `None`
    /// while it cannot be known yet, `Some(None)` for grey textures.
    pub fn texture_colour(
        &mut self,
        run: &RunFrames,
    ) -> Result<Option<Option<ColourCalibration>>, ProcessError> {
        if self.known.is_none() {
            self.known = texture_colour_by(run, Measure::WhileCapturing(&mut self.readings))?;
        }
        Ok(self.known)
    }
}

/// Patches read in a run's frames, by image index: the readings, or why
/// the frame does not show them usably.
type PatchReadings = std::collections::BTreeMap<usize, Result<Vec<PatchReading>, String>>;

/// Whether [`texture_colour_by`] measures a calibration on the run's
/// patches where it has none.
enum Measure<'a> {
    /// No: grey textures until `rigd process colour` has run.
    Never,
    /// Yes, on the frames the journal has.
    Now,
    /// Yes, once the frames still to come cannot change it; the readings
    /// are kept between calls.
    WhileCapturing(&'a mut PatchReadings),
}

/// [`texture_colour`], and `None` while the run's calibration waits for
/// frames still to come ([`Measure::WhileCapturing`]).
fn texture_colour_by(
    run: &RunFrames,
    measure: Measure,
) -> Result<Option<Option<ColourCalibration>>, ProcessError> {
    let report = if colour_file(&run.root).exists() {
        ColourReport::read(&run.root)?
    } else if camera_colour_file(&run.root).exists() {
        let path = camera_colour_file(&run.root);
        let file = ColourCalibrationFile::read(&path).map_err(|e| ProcessError::Frame {
            path: path.clone(),
            message: e.to_string(),
        })?;
        one_camera(run, &path)?;
        return camera_texture_calibration(&file).map(|c| Some(Some(c)));
    } else {
        let Some(first) = run.entries.first() else {
            let waits = matches!(measure, Measure::WhileCapturing(_));
            return Ok(if waits { None } else { Some(None) });
        };
        let mut fresh = PatchReadings::new();
        let (first_pending, readings) = match measure {
            Measure::Never => return Ok(Some(None)),
            Measure::Now => (None, &mut fresh),
            Measure::WhileCapturing(kept) => (first_pending_tilt(run), kept),
        };
        if run.colour_planes(first)?.is_none() {
            return Ok(Some(None));
        }
        match calibrate_on(run, first_pending, readings) {
            Ok(Some(report)) => report,
            Ok(None) => return Ok(None),
            Err(e) => {
                tracing::warn!(
                    "{}: camera `{}` records colour, but no colour calibration: {e}; its \
                     textures are grey",
                    run.root.display(),
                    first.camera
                );
                return Ok(Some(None));
            }
        }
    };
    if let Some(other) = run.entries.iter().find(|e| e.camera != report.camera) {
        return Err(ProcessError::Invalid(format!(
            "{} calibrates camera `{}` only, and the run also has frames of `{}`: RGB \
             textures from several cameras are not supported yet (remove the file for grey \
             textures)",
            colour_file(&run.root).display(),
            report.camera,
            other.camera
        )));
    }
    Ok(Some(Some(report.texture_calibration)))
}

/// Where a run's colour calibration is kept.
pub fn colour_file(run: &Path) -> PathBuf {
    crate::store::processed::processed_dir(run).join(COLOUR_FILE)
}

/// Where a run keeps the camera calibration it was given
/// ([`import_calibration`]).
pub fn camera_colour_file(run: &Path) -> PathBuf {
    crate::store::processed::processed_dir(run).join(CAMERA_COLOUR_FILE)
}

/// Takes a camera calibration saved by `rigd camera colour --save` (`file`,
/// fitted on a chart photograph) as the run's colour: checked, copied to
/// `RUN/processed/camera-colour.json`, replacing a calibration measured on
/// the run's own patches, and returned as the textures' calibration. For a
/// run whose plate carries no patches: its textures come out in colour.
pub fn import_calibration(
    run: &RunFrames,
    file: &Path,
) -> Result<(ColourCalibrationFile, ColourCalibration), ProcessError> {
    let calibration =
        ColourCalibrationFile::read(file).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let Some(first) = run.entries.first() else {
        return Err(ProcessError::Invalid(format!(
            "{} has no frames to colour",
            run.root.display()
        )));
    };
    if run.colour_planes(first)?.is_none() {
        return Err(ProcessError::Invalid(format!(
            "camera `{}` is monochrome (its profile gives no `intrinsics.cfa` and its frames \
             carry no colour): a colour calibration does not apply",
            first.camera
        )));
    }
    one_camera(run, file)?;
    let texture = camera_texture_calibration(&calibration)
        .map_err(|e| ProcessError::Invalid(format!("{}: {e}", file.display())))?;
    let mut json = serde_json::to_vec_pretty(&calibration)
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    let path = camera_colour_file(&run.root);
    if let Some(dir) = path.parent() {
        crate::postprocess::create_dir(dir)?;
    }
    // The run's own calibration goes first: a crash between the two
    // leaves none (grey textures, or one measured again), never both.
    remove_if_present(&colour_file(&run.root))?;
    crate::store::write_atomic(&path, &json)?;
    Ok((calibration, texture))
}

/// A camera calibration as the textures' calibration: scaled so that a
/// neutral surface's green keeps its raw value, as one measured on the
/// run's patches is. The neutral is the one the chart's grey patches
/// imply (the file's white balance).
fn camera_texture_calibration(
    file: &ColourCalibrationFile,
) -> Result<ColourCalibration, ProcessError> {
    let Some(wb) = file.white_balance else {
        return Err(ProcessError::Invalid(
            "the calibration gives no white balance (its chart had no neutral patches), so \
             a neutral surface's level is not known"
                .to_string(),
        ));
    };
    texture_scaled(&file.correction, Some([1.0 / wb[0], 1.0, 1.0 / wb[2]]))
}

/// Refuses a run with frames of more than one camera: a calibration is one
/// camera's.
fn one_camera(run: &RunFrames, calibration: &Path) -> Result<(), ProcessError> {
    let Some(first) = run.entries.first() else {
        return Ok(());
    };
    match run.entries.iter().find(|e| e.camera != first.camera) {
        Some(other) => Err(ProcessError::Invalid(format!(
            "{} is one camera's calibration, and the run has frames of `{}` and `{}`: RGB \
             textures from several cameras are not supported yet",
            calibration.display(),
            first.camera,
            other.camera
        ))),
        None => Ok(()),
    }
}

/// Removes `path`; absent is fine.
fn remove_if_present(path: &Path) -> Result<(), ProcessError> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            Err(ProcessError::io(path, "remove", e))
        }
        _ => Ok(()),
    }
}

/// Measures the patches in the run's most frontal usable frames (up to
/// [`FRAMES_AVERAGED`]), calibrates on their mean and writes
/// `RUN/processed/colour.json`.
pub fn calibrate_run(run: &RunFrames) -> Result<ColourReport, ProcessError> {
    calibrate_on(run, None, &mut PatchReadings::new())?.ok_or_else(|| {
        ProcessError::Invalid("the run's most frontal frames are still to come".to_string())
    })
}

/// How frontal a frame is, for choosing the frames a calibration is
/// measured on: by the directions commanded, which the plan knows for the
/// frames still to come too.
fn tilt(light: &Direction, view: &Direction) -> f64 {
    light.theta_deg + view.theta_deg
}

/// The lowest [`tilt`] among the plan's images the journal does not have
/// yet; None when it has them all. A journaled image's commanded
/// directions are its plan pair's, value for value.
fn first_pending_tilt(run: &RunFrames) -> Option<f64> {
    let mut planned: Vec<f64> = (run.meta.plan.pairs.iter())
        .map(|p| tilt(&p.light, &p.view))
        .collect();
    let mut taken: Vec<f64> = (run.entries.iter())
        .map(|e| tilt(&e.light, &e.view))
        .collect();
    planned.sort_by(f64::total_cmp);
    taken.sort_by(f64::total_cmp);
    let mut taken = taken.into_iter().peekable();
    for t in planned {
        // Journaled images below `t` that match no planned one are skipped.
        while taken.next_if(|&x| x < t).is_some() {}
        if taken.next_if(|&x| x == t).is_none() {
            return Some(t);
        }
    }
    None
}

/// [`calibrate_run`] on the frames journaled so far: None while a frame
/// still to come (none below `first_pending` in [`tilt`]) may be among
/// those it is measured on, as frames tie or come before them. Patches
/// read before are taken from `readings`, and new readings kept there.
fn calibrate_on(
    run: &RunFrames,
    first_pending: Option<f64>,
    readings: &mut PatchReadings,
) -> Result<Option<ColourReport>, ProcessError> {
    let (holder, _) = super::holder_of(&run.meta)?;
    if holder.patches.is_empty() {
        return Err(ProcessError::Invalid(format!(
            "the run's holder `{}` carries no colour reference patches: describe them in the \
             profile's [holder] table (`colour_patches = true`, a `chart` or `patches`; see \
             docs/holder.md)",
            holder.name
        )));
    }
    let mut order: Vec<&crate::store::FrameEntry> = run.entries.iter().collect();
    order.sort_by(|a, b| {
        (tilt(&a.light, &a.view).total_cmp(&tilt(&b.light, &b.view))).then(a.index.cmp(&b.index))
    });
    let comes_first = |entry: &crate::store::FrameEntry| {
        first_pending.is_some_and(|t| t <= tilt(&entry.light, &entry.view))
    };
    let mut refused = Vec::new();
    let mut used: Vec<(&crate::store::FrameEntry, Vec<PatchReading>)> = Vec::new();
    let mut tried = 0;
    for entry in order.into_iter().take(MAX_CANDIDATES) {
        if used.len() == FRAMES_AVERAGED {
            break;
        }
        if comes_first(entry) {
            return Ok(None);
        }
        tried += 1;
        let read = match readings.get(&entry.index) {
            Some(read) => read.clone(),
            None => {
                let Some((planes, grey)) = run.colour_planes_and_grey(entry)? else {
                    return Err(ProcessError::Invalid(format!(
                        "camera `{}` is monochrome (its profile gives no `intrinsics.cfa` and \
                         its frames carry no colour): there is no colour to calibrate",
                        entry.camera
                    )));
                };
                let read = read_patches(run, entry, &planes, &grey, &holder.patches);
                readings.insert(entry.index, read.clone());
                read
            }
        };
        match read {
            Ok(r) => used.push((entry, r)),
            Err(why) => refused.push(format!("frame {}: {why}", entry.index)),
        }
    }
    if used.len() < FRAMES_AVERAGED && tried < MAX_CANDIDATES && first_pending.is_some() {
        return Ok(None);
    }
    let Some((first, _)) = used.first() else {
        return Err(ProcessError::Invalid(format!(
            "no frame shows the colour patches usably: {}",
            if refused.is_empty() {
                "the run has no frames".to_string()
            } else {
                refused.join("; ")
            }
        )));
    };
    let frames: Vec<usize> = used.iter().map(|(e, _)| e.index).collect();
    let readings = average(used.iter().map(|(_, r)| r.as_slice()).collect());
    let mut report = report(first, frames, &readings)?;
    // Both corrections on the patches' L*a*b* references, judged by
    // CIEDE2000 in the fit and left out, where there are patches enough.
    let chart: Vec<cc::chart_fit::ChartReading> = readings
        .iter()
        .zip(&holder.patches)
        .map(|(r, p)| cc::chart_fit::ChartReading {
            name: r.name.clone(),
            lab_d50: p.lab_d50,
            camera_rgb: r.raw,
        })
        .collect();
    report.chart_fit = match cc::chart_fit::fit_chart(&chart) {
        Ok(fit) => Some(fit),
        Err(e) => {
            tracing::info!("no chart fit on the run's {} patches: {e}", chart.len());
            None
        }
    };
    if let Some(fit) = &report.chart_fit {
        if fit.chosen == cc::chart_fit::CorrectionKind::RootPolynomial {
            let white = cc::white_patch(&readings).map(|k| readings[k].raw);
            let correction = &fit.root_polynomial.correction;
            report.texture_calibration = texture_scaled(correction, white)?;
        }
    }
    let mut json =
        serde_json::to_vec_pretty(&report).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    let path = colour_file(&run.root);
    if let Some(dir) = path.parent() {
        crate::postprocess::create_dir(dir)?;
    }
    remove_if_present(&camera_colour_file(&run.root))?;
    crate::store::write_atomic(&path, &json)?;
    Ok(Some(report))
}

/// A chart's fitted `correction` as the textures' calibration: scaled so
/// that the white patch's green (`white`, raw) keeps its raw value, as the
/// 3×3 texture calibration is.
fn texture_scaled(
    correction: &cc::chart_fit::Correction,
    white: Option<[f64; 3]>,
) -> Result<ColourCalibration, ProcessError> {
    let white = white.unwrap_or([1.0; 3]);
    let scale = white[1] / correction.apply(white)[1];
    if !scale.is_finite() || scale <= 0.0 {
        return Err(ProcessError::Invalid(format!(
            "the {} maps the white patch's green to {}",
            correction.kind,
            correction.apply(white)[1]
        )));
    }
    ColourCalibration::from_correction(correction, scale).ok_or_else(|| {
        ProcessError::Invalid(format!(
            "the {} has rows of the wrong length",
            correction.kind
        ))
    })
}

/// The frames' readings, patch by patch, each frame scaled so its white
/// patch's green is the first frame's (the frames' exposures differ), then
/// averaged.
fn average(frames: Vec<&[PatchReading]>) -> Vec<PatchReading> {
    let white_green = |r: &[PatchReading]| cc::white_patch(r).map_or(1.0, |k| r[k].raw[1]);
    let Some(first) = frames.first() else {
        return Vec::new();
    };
    let target = white_green(first);
    let mut out: Vec<PatchReading> = first
        .iter()
        .map(|p| PatchReading {
            raw: [0.0; 3],
            ..p.clone()
        })
        .collect();
    for readings in &frames {
        let scale = target / white_green(readings);
        for (o, p) in out.iter_mut().zip(readings.iter()) {
            for c in 0..3 {
                o.raw[c] += scale * p.raw[c] / frames.len() as f64;
            }
        }
    }
    out
}

/// The patches' mean raw colours in one frame, registered by its markers,
/// each evened out for the light it gets: a lamp to one side and the
/// lens's vignetting light the row of patches unevenly (by 10 % on the
/// VirTex rig's 45° lamps), and the neutral plate beside each patch
/// measures its share. `Err` says why the frame cannot be used.
fn read_patches(
    run: &RunFrames,
    entry: &crate::store::FrameEntry,
    planes: &ColourPlanes,
    grey: &rigd_process::image_io::Image,
    patches: &[PlacedPatch],
) -> Result<Vec<PatchReading>, String> {
    let h = super::register_by_markers(run, entry, grey)?;
    let n = POINTS_PER_SIDE;
    // Points evenly over [-1, 1] (`n` of them), scaled by the caller.
    let spread = |k: usize| 2.0 * (k as f64 + 0.5) / n as f64 - 1.0;
    let mean_at = |points: &mut dyn Iterator<Item = [f64; 2]>, name: &str, what: &str| {
        let (mut sum, mut count) = ([0.0; 3], 0usize);
        for q in points {
            let rgb = rigd_process::rectify::project(&h, q)
                .and_then(|px| planes.sample(px[0], px[1]))
                .filter(|v| v.iter().all(|c| c.is_finite()))
                .ok_or_else(|| format!("{what} of patch `{name}` is not inside the frame"))?;
            for c in 0..3 {
                sum[c] += rgb[c];
            }
            count += 1;
        }
        Ok::<_, String>(sum.map(|s| s / count.max(1) as f64))
    };
    let mut readings = Vec::with_capacity(patches.len());
    let mut light = Vec::with_capacity(patches.len());
    for p in patches {
        let name = p.name.as_str();
        let [cx, cy] = p.centre;
        let inner = p.half * INNER_FRACTION;
        let raw = mean_at(
            &mut (0..n * n).map(|k| [cx + inner * spread(k % n), cy + inner * spread(k / n)]),
            name,
            "the middle",
        )?;
        if raw.iter().any(|v| *v > SATURATION) {
            return Err(format!("patch `{name}` is saturated ({raw:.3?})"));
        }
        let [near, far] = PLATE_BESIDE.map(|f| f * p.half);
        let beside: Vec<[f64; 2]> = (0..2 * n * n)
            .map(|k| {
                let (side, k) = (if k < n * n { -1.0 } else { 1.0 }, k % (n * n));
                let along = near + (far - near) * (spread(k % n) + 1.0) / 2.0;
                [cx + side * along, cy + inner * spread(k / n)]
            })
            .collect();
        // A chart's patches touch their neighbours: there is no plate
        // beside them to even their light out by.
        let plate = if beside
            .iter()
            .any(|q| patches.iter().any(|o| o.contains(q[0], q[1])))
        {
            None
        } else {
            let beside = mean_at(&mut beside.into_iter(), name, "the plate beside")?;
            let plate: f64 = beside.iter().sum();
            if plate.is_nan() || plate <= 0.0 {
                return Err(format!("the plate beside patch `{name}` is black"));
            }
            Some(plate)
        };
        readings.push(PatchReading {
            name: name.to_string(),
            reference: p.rgb,
            raw,
        });
        light.push(plate);
    }
    // Evened out only when every patch has plate beside it (the standard
    // row); a chart is small enough to be evenly lit.
    let lights: Option<Vec<f64>> = light.into_iter().collect();
    if let Some(light) = lights {
        let mean_light = light.iter().sum::<f64>() / light.len().max(1) as f64;
        for (r, l) in readings.iter_mut().zip(&light) {
            r.raw = r.raw.map(|v| v * mean_light / l);
        }
    }
    Ok(readings)
}

/// The calibration from one frame's readings, and every patch's ΔE.
fn report(
    entry: &crate::store::FrameEntry,
    frames: Vec<usize>,
    readings: &[PatchReading],
) -> Result<ColourReport, ProcessError> {
    let calibration = cc::calibrate(readings).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let held_out = cc::held_out_delta_e(readings);
    // White balance alone, scaled so the white patch's green is right.
    let white = cc::white_patch(readings).map(|k| &readings[k]);
    let scale = white.map_or(1.0, |w| w.reference[1] / w.raw[1]);
    let patches = readings
        .iter()
        .zip(held_out)
        .map(|(p, held)| {
            let corrected = calibration.apply(p.raw);
            let balanced = [0, 1, 2].map(|c| p.raw[c] * calibration.white_balance[c] * scale);
            PatchReport {
                name: p.name.clone(),
                reference: p.reference,
                raw: p.raw,
                corrected,
                delta_e: cc::delta_e(corrected, p.reference),
                delta_e_held_out: held,
                delta_e_white_balance_only: cc::delta_e(balanced, p.reference),
            }
        })
        .collect();
    let white_green = white.map_or(1.0, |w| calibration.apply(w.raw)[1] / w.raw[1]);
    if !white_green.is_finite() || white_green <= 0.0 {
        return Err(ProcessError::Invalid(format!(
            "the colour correction maps the white patch's green to {white_green}"
        )));
    }
    let texture_calibration = ColourCalibration {
        matrix: calibration.matrix.map(|row| row.map(|m| m / white_green)),
        ..calibration
    };
    Ok(ColourReport {
        frames,
        camera: entry.camera.clone(),
        light: entry.achieved_light,
        view: entry.achieved_view,
        calibration,
        texture_calibration,
        patches,
        chart_fit: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use cc::chart_fit::{Correction, CorrectionKind};

    #[test]
    fn a_chosen_root_polynomial_corrects_the_textures_at_the_white_patch_s_level() {
        let correction = Correction {
            kind: CorrectionKind::RootPolynomial,
            coefficients: [
                vec![1.6, -0.2, -0.1, 0.2, -0.05, 0.1],
                vec![-0.2, 1.1, -0.1, 0.15, 0.05, -0.05],
                vec![0.0, -0.3, 1.7, -0.05, 0.1, 0.0],
            ],
        };
        let white = [0.55, 0.8, 0.6];
        let cal = texture_scaled(&correction, Some(white)).expect("a calibration");
        assert!(cal.root_polynomial.is_some());
        // The white patch's green keeps its raw value, …
        assert!((cal.apply(white)[1] - white[1]).abs() < 1e-12);
        // … and every colour is the correction's, scaled alike.
        let scale = white[1] / correction.apply(white)[1];
        for raw in [[0.1, 0.2, 0.3], [0.7, 0.1, 0.05]] {
            let (got, want) = (cal.apply(raw), correction.apply(raw));
            for c in 0..3 {
                assert!((got[c] - scale * want[c]).abs() < 1e-12);
            }
        }
        // A correction that sends white's green to nothing is refused.
        let dark = Correction {
            kind: CorrectionKind::Matrix,
            coefficients: [vec![1.0, 0.0, 0.0], vec![0.0; 3], vec![0.0, 0.0, 1.0]],
        };
        assert!(texture_scaled(&dark, Some(white)).is_err());
    }
}
