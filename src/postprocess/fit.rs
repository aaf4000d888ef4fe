//! The reflectance-field fit of a rectified run (Meseth et al., §4), with
//! the error table of their Table 1.

use std::path::Path;

use serde::Serialize;

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

/// Fits every view slot of a rectified run with PTM and the K-lobe model
/// (Meseth et al., §4) and tabulates the errors, written to
/// `processed/fit/report.json`; the fitted parameters of every slot go to
/// `processed/fit/slot_NNN_lobes.npy` and `slot_NNN_ptm.npy`.
pub fn fit_run(
    run: &Path,
    lobes: usize,
    progress: &dyn Fn(usize, usize),
) -> Result<Vec<FitRow>, ProcessError> {
    use rigd_process::reflectance_fit::{fit_ptm_slot, fit_slot, FitMethod, FitOptions};
    let index = NormtextureIndex::read(run)?;
    let lights: Vec<[f64; 3]> = index.lights.iter().map(|d| d.to_vector()).collect();
    let dir = crate::store::processed::fit_dir(run);
    std::fs::create_dir_all(&dir).map_err(|e| ProcessError::Frame {
        path: dir.clone(),
        message: e.to_string(),
    })?;
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
    let invalid = |slot: usize, e: &dyn std::fmt::Display| {
        ProcessError::Invalid(format!("view slot {slot}: {e}"))
    };
    for slot in 0..slots {
        let images = (0..lights.len())
            .map(|l| index.load(run, slot, l))
            .collect::<Result<Vec<_>, _>>()?;
        let texels = images.first().map_or(0, |i| i.data.len());
        if let Some(l) = images.iter().position(|i| i.data.len() != texels) {
            return Err(ProcessError::Invalid(format!(
                "view slot {slot}: the texture of light {l} has {} values, that of light 0 {texels}",
                images[l].data.len()
            )));
        }
        // Texel-major: each texel's values under every light.
        let mut values = Vec::with_capacity(texels * lights.len());
        for t in 0..texels {
            values.extend(images.iter().map(|img| img.data[t]));
        }
        let started = std::time::Instant::now();
        let ptm = fit_ptm_slot(&lights, &values).map_err(|e| invalid(slot, &e))?;
        let ptm_s = started.elapsed().as_secs_f64();
        let started = std::time::Instant::now();
        let fit = fit_slot(&lights, &values, lobes, &FitOptions::default())
            .map_err(|e| invalid(slot, &e))?;
        let fit_s = started.elapsed().as_secs_f64();
        let per_method = [
            (ptm.mean_abs_error(), ptm.rms_error(), ptm_s, texels),
            (
                fit.mean_abs_error(),
                fit.rms_error(),
                fit_s,
                fit.converged_texels(),
            ),
        ];
        for (row, (mae, rms, secs, converged)) in rows.iter_mut().zip(per_method) {
            row.mean_abs_error += mae / slots as f64;
            row.rms_error += rms / slots as f64;
            row.fit_s += secs;
            row.converged_texels += converged;
        }
        // The fitted parameters, per texel: Meseth et al.'s (a, b, c, n) per
        // lobe, and the six PTM coefficients.
        let side = index.size;
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
        let write = |name: String, shape: &[usize], data: &[f32]| {
            let path = dir.join(name);
            rigd_process::npy::write_f32(&path, shape, data)
                .map_err(|e| ProcessError::Invalid(format!("{}: {e}", path.display())))
        };
        write(
            format!("slot_{slot:03}_lobes.npy"),
            &[side, side, 4 * lobes],
            &lobe_params,
        )?;
        write(
            format!("slot_{slot:03}_ptm.npy"),
            &[side, side, 6],
            &ptm_params,
        )?;
        progress(slot + 1, slots);
    }
    let mut json =
        serde_json::to_vec_pretty(&rows).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    crate::store::write_atomic(&dir.join("report.json"), &json)?;
    Ok(rows)
}
