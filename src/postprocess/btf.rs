//! BTF compression of a rectified run: a PCA per view slot (Sattler et al.,
//! §4.1), and its error at given (light, view) pairs.

use std::path::Path;

use rigd_core::geometry::Direction;
use serde::Serialize;

use super::rectify::NormtextureIndex;
use super::ProcessError;

/// Per slot and for the whole run: how fast the spectrum decays and what
/// RMS error C components leave.
#[derive(Debug, Clone, Serialize)]
pub struct BtfReport {
    /// Components C kept per view slot in the stored BTF.
    pub components: usize,
    /// View slots (views) compressed.
    pub slots: usize,
    /// Light directions per view slot.
    pub lights: usize,
    /// Mean over slots of the RMS reconstruction error with C = 1 … 32
    /// components (in texture units, 1 = full scale).
    pub mean_rms_by_components: Vec<f64>,
    /// One summary per view slot, in slot order.
    pub per_slot: Vec<SlotSummary>,
    /// Wall-clock time the compression took, seconds.
    pub compress_s: f64,
    /// Size of `processed/btf/` on disk, bytes.
    pub bytes: u64,
}

/// The PCA of one view slot: its spectrum and error curve.
#[derive(Debug, Clone, Serialize)]
pub struct SlotSummary {
    /// The view slot's index.
    pub slot: usize,
    /// The slot's view direction in the sample frame.
    pub view: Direction,
    /// Eigenvalues (σ²), largest first, at most 32.
    pub eigenvalues: Vec<f64>,
    /// RMS reconstruction error of this slot with C = 1 … 32 components
    /// (texture units, 1 = full scale).
    pub rms_by_components: Vec<f64>,
}

/// Compresses a rectified run's BTF: a PCA per view slot with `components`
/// components (Sattler et al., §4.1), streamed slot by slot into
/// `processed/btf/`, and its report.
pub fn btf_run(
    run: &Path,
    components: usize,
    progress: &dyn Fn(usize, usize),
) -> Result<BtfReport, ProcessError> {
    use rigd_process::btf::{compress_slot, BtfWriter, TextureShape};
    use rigd_process::directions::{Direction as PDir, DirectionTable};
    let index = NormtextureIndex::read(run)?;
    let table = |dirs: &[Direction]| {
        DirectionTable::new(
            dirs.iter()
                .map(|d| PDir::new(d.theta_deg, d.phi_deg))
                .collect(),
        )
        .map_err(|e| ProcessError::Invalid(e.to_string()))
    };
    let (lights, views) = (table(&index.lights)?, table(&index.views)?);
    let shape = TextureShape::new(index.size, index.size, 1)
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let dir = crate::store::processed::btf_dir(run);
    let started = std::time::Instant::now();
    let mut writer = BtfWriter::create(&dir, shape, &lights, &views, components)
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let mut per_slot = Vec::with_capacity(index.views.len());
    for (slot, view) in index.views.iter().enumerate() {
        let images = (0..index.lights.len())
            .map(|l| index.load(run, slot, l).map(|img| img.data))
            .collect::<Result<Vec<_>, _>>()?;
        let refs: Vec<&[f32]> = images.iter().map(Vec::as_slice).collect();
        let pca = compress_slot(&refs, shape, components)
            .map_err(|e| ProcessError::Invalid(format!("view slot {slot}: {e}")))?;
        writer
            .write_slot(slot, &pca)
            .map_err(|e| ProcessError::Invalid(format!("view slot {slot}: {e}")))?;
        per_slot.push(SlotSummary {
            slot,
            view: *view,
            eigenvalues: pca.eigenvalues().into_iter().take(32).collect(),
            rms_by_components: pca.rms_error_curve(32),
        });
        progress(slot + 1, index.views.len());
    }
    writer
        .finish()
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let compress_s = started.elapsed().as_secs_f64();
    let longest = per_slot
        .iter()
        .map(|s| s.rms_by_components.len())
        .max()
        .unwrap_or(0);
    let mean_rms_by_components = (0..longest)
        .map(|c| {
            let vals: Vec<f64> = per_slot
                .iter()
                .map(|s| {
                    s.rms_by_components
                        .get(c)
                        .or(s.rms_by_components.last())
                        .copied()
                        .unwrap_or(0.0)
                })
                .collect();
            vals.iter().sum::<f64>() / vals.len().max(1) as f64
        })
        .collect();
    let bytes = std::fs::read_dir(&dir)
        .map(|entries| {
            entries
                .filter_map(|e| e.ok()?.metadata().ok())
                .map(|m| m.len())
                .sum()
        })
        .unwrap_or(0);
    let report = BtfReport {
        components,
        slots: index.views.len(),
        lights: index.lights.len(),
        mean_rms_by_components,
        per_slot,
        compress_s,
        bytes,
    };
    let mut json =
        serde_json::to_vec_pretty(&report).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    crate::store::write_atomic(&dir.join("report.json"), &json)?;
    Ok(report)
}

/// The error of a compressed BTF at one (light, view) against the scene's
/// true reflectance.
#[derive(Debug, Clone, Serialize)]
pub struct HeldOutError {
    /// The light direction reconstructed, sample frame.
    pub light: Direction,
    /// The view direction reconstructed, sample frame.
    pub view: Direction,
    /// RMS over texels of reconstruction − truth, texture units.
    pub rms: f64,
    /// RMS of the truth itself, for scale.
    pub truth_rms: f64,
}

/// RMS differences between the run's compressed BTF at each pair and the
/// given textures.
pub fn btf_error(
    run: &Path,
    pairs: &[(Direction, Direction)],
    truths: &[Vec<f32>],
) -> Result<Vec<HeldOutError>, ProcessError> {
    let store = rigd_process::btf::BtfStore::read(&crate::store::processed::btf_dir(run))
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    pairs
        .iter()
        .zip(truths)
        .map(|(&(light, view), truth)| {
            let tex = store
                .reconstruct(light, view)
                .map_err(|e| ProcessError::Invalid(e.to_string()))?;
            if tex.len() != truth.len() {
                return Err(ProcessError::Invalid(format!(
                    "{} texels reconstructed, {} in the truth",
                    tex.len(),
                    truth.len()
                )));
            }
            let n = tex.len().max(1) as f64;
            let err2: f64 = tex
                .iter()
                .zip(truth)
                .map(|(a, b)| f64::from(a - b).powi(2))
                .sum();
            let truth2: f64 = truth.iter().map(|b| f64::from(*b).powi(2)).sum();
            Ok(HeldOutError {
                light,
                view,
                rms: (err2 / n).sqrt(),
                truth_rms: (truth2 / n).sqrt(),
            })
        })
        .collect()
}
