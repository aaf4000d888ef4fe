//! The reflectance-field fit of a rectified run (Meseth et al., §4), with
//! the error table of their Table 1.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::rectify::NormtextureIndex;
use super::ProcessError;

/// One row of the run's fit table (Meseth et al. Table 1).
#[derive(Debug, Clone, Serialize)]
pub struct FitRow {
    /// The model fitted: `PTM` or `non-linear K=<lobes>`.
    pub method: String,
    /// Mean over slots of the mean |model − value| over texels and lights,
    /// in texture units (1 = full scale).
    pub mean_abs_error: f64,
    /// Mean over slots of the RMS of model − value over texels and lights,
    /// in texture units.
    pub rms_error: f64,
    /// Wall-clock time the fits of all slots took, seconds.
    pub fit_s: f64,
    /// Texels whose fit converged, summed over slots (PTM, a linear fit,
    /// counts every texel).
    pub converged_texels: usize,
}

/// One method's errors on one view slot.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
struct SlotStats {
    mean_abs_error: f64,
    rms_error: f64,
    fit_s: f64,
    converged_texels: usize,
}

/// A slot fitted ahead of `fit` (a task of a cluster's job array): the
/// key of the textures and settings it was fitted from, and the PTM's and
/// the lobes' errors. Its parameter files are in `processed/fit/` already.
#[derive(Serialize, Deserialize)]
struct SlotFitKept {
    key: String,
    methods: [SlotStats; 2],
}

/// Where slots fitted ahead wait for `fit`.
const AHEAD_DIR: &str = "fit-ahead";

fn kept_path(run: &Path, slot: usize) -> std::path::PathBuf {
    crate::store::processed::processed_dir(run)
        .join(AHEAD_DIR)
        .join(format!("slot_{slot:03}.json"))
}

fn fit_key(run: &Path, index: &NormtextureIndex, slot: usize, lobes: usize) -> Option<String> {
    super::btf::slot_key(run, index, slot, &format!("fit K{lobes}"))
}

fn param_files(slot: usize) -> [String; 2] {
    [
        format!("slot_{slot:03}_ptm.npy"),
        format!("slot_{slot:03}_lobes.npy"),
    ]
}

/// The slot's errors if it was fitted ahead from the textures `index`
/// lists for it now, with `lobes`, and its parameter files are there.
fn take_kept(
    run: &Path,
    index: &NormtextureIndex,
    slot: usize,
    lobes: usize,
) -> Option<[SlotStats; 2]> {
    let kept: SlotFitKept =
        serde_json::from_slice(&std::fs::read(kept_path(run, slot)).ok()?).ok()?;
    let dir = crate::store::processed::fit_dir(run);
    let files_there = param_files(slot).iter().all(|f| dir.join(f).is_file());
    (files_there && Some(&kept.key) == fit_key(run, index, slot, lobes).as_ref())
        .then_some(kept.methods)
}

/// Fits view slot `slot` with PTM and the K-lobe model, writes its
/// parameter files and returns both methods' errors.
fn fit_one_slot(
    run: &Path,
    index: &NormtextureIndex,
    slot: usize,
    lobes: usize,
) -> Result<[SlotStats; 2], ProcessError> {
    use rigd_process::reflectance_fit::{fit_ptm_slot, fit_slot, FitOptions};
    let lights: Vec<[f64; 3]> = index.lights.iter().map(|d| d.to_vector()).collect();
    let dir = crate::store::processed::fit_dir(run);
    crate::postprocess::create_dir(&dir)?;
    let invalid =
        |e: &dyn std::fmt::Display| ProcessError::Invalid(format!("view slot {slot}: {e}"));
    let (images, _) = crate::postprocess::slot_textures::load_slot(run, index, slot)?;
    let texels = images.first().map_or(0, |i| i.data.len());
    if let Some(l) = images.iter().position(|i| i.data.len() != texels) {
        return Err(ProcessError::Invalid(format!(
            "view slot {slot}: the texture of light {l} has {} values, that of light 0 {texels}",
            images[l].data.len()
        )));
    }
    // Texel-major: each texel's values under every light. An RGB texture
    // (channels interleaved) is fitted per channel: each of a texel's
    // channels is a series of its own.
    let mut values = Vec::with_capacity(texels * lights.len());
    for t in 0..texels {
        values.extend(images.iter().map(|img| img.data[t]));
    }
    let started = std::time::Instant::now();
    let ptm = fit_ptm_slot(&lights, &values).map_err(|e| invalid(&e))?;
    let ptm_s = started.elapsed().as_secs_f64();
    let started = std::time::Instant::now();
    let fit = fit_slot(&lights, &values, lobes, &FitOptions::default()).map_err(|e| invalid(&e))?;
    let fit_s = started.elapsed().as_secs_f64();
    // The fitted parameters, per texel (and channel): Meseth et al.'s
    // (a, b, c, n) per lobe, and the six PTM coefficients.
    let side = index.size;
    // An RGB texel's channels' parameters side by side (npy is rank 3).
    let shape = |per_series: usize| [side, side, index.channels.max(1) * per_series];
    let mut lobe_params = Vec::with_capacity(texels * lobes * 4);
    for t in &fit.texels {
        let mut coefficients = t.model.to_paper_coefficients();
        coefficients.resize(lobes, [0.0, 0.0, 0.0, 1.0]);
        lobe_params.extend(coefficients.iter().flatten().map(|&v| v as f32));
    }
    let ptm_params: Vec<f32> = ptm
        .texels
        .iter()
        .flat_map(|t| t.coefficients.map(|v| v as f32))
        .collect();
    let [ptm_file, lobes_file] = param_files(slot);
    let write = |name: String, shape: &[usize], data: &[f32]| {
        let path = dir.join(name);
        rigd_process::npy::write_f32(&path, shape, data)
            .map_err(|e| ProcessError::Invalid(format!("{}: {e}", path.display())))
    };
    write(lobes_file, &shape(4 * lobes), &lobe_params)?;
    write(ptm_file, &shape(6), &ptm_params)?;
    Ok([
        SlotStats {
            mean_abs_error: ptm.mean_abs_error(),
            rms_error: ptm.rms_error(),
            fit_s: ptm_s,
            converged_texels: texels,
        },
        SlotStats {
            mean_abs_error: fit.mean_abs_error(),
            rms_error: fit.rms_error(),
            fit_s,
            converged_texels: fit.converged_texels(),
        },
    ])
}

/// Fits the view slots `slots` of a rectified run and keeps their errors
/// in `processed/fit-ahead/` for `fit` (one task of a cluster's job array,
/// [`crate::postprocess::parts`]); a slot fitted already from the same
/// textures is left as it is. Returns how many it fitted.
pub fn fit_slots_part(
    run: &Path,
    slots: std::ops::Range<usize>,
    lobes: usize,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<usize, ProcessError> {
    let index = NormtextureIndex::read(run)?;
    index.check_slot_range(&slots)?;
    let total = slots.len();
    let mut fitted = 0;
    for (n, slot) in slots.enumerate() {
        if take_kept(run, &index, slot, lobes).is_none() {
            let key = fit_key(run, &index, slot, lobes).ok_or_else(|| {
                ProcessError::Invalid(format!("view slot {slot}: a light has no texture"))
            })?;
            let methods = fit_one_slot(run, &index, slot, lobes)?;
            let path = kept_path(run, slot);
            if let Some(dir) = path.parent() {
                crate::postprocess::create_dir(dir)?;
            }
            let json = serde_json::to_vec(&SlotFitKept { key, methods })
                .map_err(|e| ProcessError::Invalid(e.to_string()))?;
            crate::store::write_atomic(&path, &json)?;
            fitted += 1;
        }
        progress(n + 1, total);
    }
    Ok(fitted)
}

/// Fits every view slot of a rectified run with PTM and the K-lobe model
/// (Meseth et al., §4) and tabulates the errors, written to
/// `processed/fit/report.json`; the fitted parameters of every slot go to
/// `processed/fit/slot_NNN_lobes.npy` and `slot_NNN_ptm.npy`. Slots
/// fitted ahead from the same textures ([`fit_slots_part`]) are taken as
/// they are.
pub fn fit_run(
    run: &Path,
    lobes: usize,
    progress: &dyn Fn(usize, usize),
) -> Result<Vec<FitRow>, ProcessError> {
    use rigd_process::reflectance_fit::FitMethod;
    crate::store::check_run(run)?;
    let index = NormtextureIndex::read(run)?;
    let dir = crate::store::processed::fit_dir(run);
    crate::postprocess::create_dir(&dir)?;
    let methods = [FitMethod::Ptm, FitMethod::Lobes(lobes)];
    let mut rows: Vec<FitRow> = methods
        .iter()
        .map(|m| FitRow {
            method: m.to_string(),
            mean_abs_error: 0.0,
            rms_error: 0.0,
            fit_s: 0.0,
            converged_texels: 0,
        })
        .collect();
    let slots = index.views.len();
    for slot in 0..slots {
        let per_method = match take_kept(run, &index, slot, lobes) {
            Some(kept) => kept,
            None => fit_one_slot(run, &index, slot, lobes)?,
        };
        for (row, stats) in rows.iter_mut().zip(per_method) {
            row.mean_abs_error += stats.mean_abs_error / slots as f64;
            row.rms_error += stats.rms_error / slots as f64;
            row.fit_s += stats.fit_s;
            row.converged_texels += stats.converged_texels;
        }
        progress(slot + 1, slots);
    }
    let mut json =
        serde_json::to_vec_pretty(&rows).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    crate::store::write_atomic(&dir.join("report.json"), &json)?;
    let ahead = crate::store::processed::processed_dir(run).join(AHEAD_DIR);
    if let Err(e) = std::fs::remove_dir_all(&ahead) {
        if e.kind() != std::io::ErrorKind::NotFound {
            tracing::warn!("{}: {e}", ahead.display());
        }
    }
    Ok(rows)
}
