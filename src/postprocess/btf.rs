//! BTF compression of a rectified run: a PCA per view slot (Sattler et al.,
//! §4.1), and its error at given (light, view) pairs.

use std::path::Path;

use rigd_core::geometry::Direction;
use serde::Serialize;

use super::rectify::NormtextureIndex;
use super::slot_textures::{load_slot, ClipFill};
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
    /// Size of the BTF's files in `processed/btf/` (`btf.json` and the
    /// slots; not this report), bytes.
    pub bytes: u64,
    /// View slots taken as compressed ahead, during the capture or as the
    /// tasks of a cluster's job array ([`compress_slot_ahead`]), rather
    /// than compressed now.
    pub slots_ahead: usize,
    /// Texels that read a clipped pixel, filled from their slot's
    /// neighbouring lights before the compression, and those clipped under
    /// every light and kept as read ([`crate::postprocess::slot_textures`]).
    pub clipped: ClipFill,
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

/// What the compression may hold in memory for the slots it works on at
/// once: each slot in flight holds its images (f32), its factors (f64 and
/// their f32 copies) and one block of its centred matrix, 37 MB for 81
/// lights at 256² and C = 16; at most one slot per core is in flight, and
/// fewer if this budget says so.
pub const BTF_MEMORY_BUDGET_BYTES: usize = 384 << 20;

/// Compresses a rectified run's BTF: a PCA per view slot with `components`
/// components (Sattler et al., §4.1), into `processed/btf/`, and its report.
/// Slots are read and compressed in parallel, as many at a time as there are
/// cores and [`BTF_MEMORY_BUDGET_BYTES`] allows, and written in slot order as
/// they finish; `progress(done, total)` follows the slots written.
pub fn btf_run(
    run: &Path,
    components: usize,
    progress: &dyn Fn(usize, usize),
) -> Result<BtfReport, ProcessError> {
    use rayon::prelude::*;
    use rigd_process::btf::{compress_slot, slot_memory_bytes, BtfWriter, TextureShape};
    use rigd_process::directions::{Direction as PDir, DirectionTable};
    crate::store::check_run(run)?;
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
    let shape = TextureShape::new(index.size, index.size, index.channels)
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let dir = crate::store::processed::btf_dir(run);
    let started = std::time::Instant::now();
    let mut writer = BtfWriter::create(&dir, shape, &lights, &views, components)
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let slots = index.views.len();
    let in_flight = (BTF_MEMORY_BUDGET_BYTES
        / slot_memory_bytes(shape.values(), index.lights.len(), components).max(1))
    .clamp(1, rayon::current_num_threads().max(1));
    let ahead = std::sync::atomic::AtomicUsize::new(0);
    let compress = |slot: usize| -> Result<_, ProcessError> {
        if let Some((pca, fill)) = take_slot_ahead(run, &index, slot, components) {
            ahead.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            return Ok((pca, fill));
        }
        let (images, fill) = load_slot(run, &index, slot)?;
        let refs: Vec<&[f32]> = images.iter().map(|i| i.data.as_slice()).collect();
        let pca = compress_slot(&refs, shape, components)
            .map_err(|e| ProcessError::Invalid(format!("view slot {slot}: {e}")))?;
        Ok((pca, fill))
    };
    let mut clipped = ClipFill::default();
    let mut per_slot = Vec::with_capacity(slots);
    for first in (0..slots).step_by(in_flight) {
        let batch = (first..(first + in_flight).min(slots))
            .into_par_iter()
            .map(compress)
            .collect::<Result<Vec<_>, _>>()?;
        for ((pca, fill), slot) in batch.into_iter().zip(first..) {
            clipped = clipped + fill;
            writer
                .write_slot(slot, &pca)
                .map_err(|e| ProcessError::Invalid(format!("view slot {slot}: {e}")))?;
            per_slot.push(SlotSummary {
                slot,
                view: index.views[slot],
                eigenvalues: pca.eigenvalues().into_iter().take(32).collect(),
                rms_by_components: pca.rms_error_curve(32),
            });
            progress(slot + 1, slots);
        }
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
    // The BTF's own files: not this report (an earlier one may be there)
    // and not the folder entries.
    let bytes = std::fs::read_dir(&dir)
        .map(|entries| {
            entries
                .filter_map(|e| {
                    let e = e.ok()?;
                    (e.file_name() != "report.json").then_some(e.metadata().ok()?)
                })
                .filter(|m| m.is_file())
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
        slots_ahead: ahead.into_inner(),
        clipped,
    };
    let mut json =
        serde_json::to_vec_pretty(&report).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    crate::store::write_atomic(&dir.join("report.json"), &json)?;
    remove_slots_ahead(run);
    Ok(report)
}

/// Where view slots compressed ahead (during the capture, or as cluster
/// tasks) wait for `btf`.
const AHEAD_DIR: &str = "btf-ahead";

/// What a slot compressed ahead is kept with: the key it was made for and
/// what its bytes need to be read back.
#[derive(serde::Serialize, serde::Deserialize)]
struct SlotAhead {
    key: String,
    shape: [usize; 3],
    singular_values: Vec<f64>,
    #[serde(default)]
    clipped: ClipFill,
}

fn ahead_paths(run: &Path, slot: usize) -> (std::path::PathBuf, std::path::PathBuf) {
    let dir = crate::store::processed::processed_dir(run).join(AHEAD_DIR);
    (
        dir.join(format!("slot_{slot:03}.json")),
        dir.join(rigd_process::btf::slot_file_name(slot)),
    )
}

/// What a result computed from one view slot's textures depends on: the
/// rigd version, the `setting` of the step (`C16`, a fit's lobes), the
/// texture size and encoding, the lights, and per light its texture
/// file's name, length and modification time. `rectify`'s later passes
/// rewrite every texture they change, which gives it a new time; a
/// texture they keep is the file the result was computed from. None when
/// a light of the slot has no texture.
pub(crate) fn slot_key(
    run: &Path,
    index: &NormtextureIndex,
    slot: usize,
    setting: &str,
) -> Option<String> {
    use std::fmt::Write;
    let dir = crate::store::processed::normtextures_dir(run);
    let mut key = format!(
        "{} {setting} {}² {} L{}",
        env!("CARGO_PKG_VERSION"),
        index.size,
        index.encoding,
        index.lights.len()
    );
    for light in 0..index.lights.len() {
        let file = index
            .frames
            .iter()
            .find(|f| f.view_slot == slot && f.light_index == light)?
            .file
            .as_ref()?;
        let meta = std::fs::metadata(dir.join(file)).ok()?;
        let modified = meta
            .modified()
            .ok()?
            .duration_since(std::time::UNIX_EPOCH)
            .ok()?;
        let _ = write!(key, " {file}:{}:{}", meta.len(), modified.as_nanos());
    }
    Some(key)
}

/// Compresses view slot `slot` of a run still capturing, from the textures
/// `index` (the frames registered so far) lists for it, and keeps it in
/// `processed/btf-ahead/` for `btf`, which takes it if none of its
/// textures changed since ([`btf_run`]). Every light of the slot must
/// have its texture.
pub fn compress_slot_ahead(
    run: &Path,
    index: &NormtextureIndex,
    slot: usize,
    components: usize,
) -> Result<(), ProcessError> {
    use rigd_process::btf::{compress_slot, TextureShape};
    let key = slot_key(run, index, slot, &format!("C{components}")).ok_or_else(|| {
        ProcessError::Invalid(format!("view slot {slot}: a light has no texture yet"))
    })?;
    let shape = TextureShape::new(index.size, index.size, index.channels)
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let (images, clipped) = load_slot(run, index, slot)?;
    let refs: Vec<&[f32]> = images.iter().map(|i| i.data.as_slice()).collect();
    let pca = compress_slot(&refs, shape, components)
        .map_err(|e| ProcessError::Invalid(format!("view slot {slot}: {e}")))?;
    let (meta_path, bin_path) = ahead_paths(run, slot);
    if let Some(dir) = bin_path.parent() {
        crate::postprocess::create_dir(dir)?;
    }
    crate::store::write_atomic(&bin_path, &pca.to_le_bytes())?;
    let kept = SlotAhead {
        key,
        shape: [pca.values(), pca.lights(), pca.components()],
        singular_values: pca.singular_values().to_vec(),
        clipped,
    };
    let json = serde_json::to_vec(&kept).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    // Written last: a slot without it is not taken.
    crate::store::write_atomic(&meta_path, &json)?;
    Ok(())
}

/// Compresses the view slots `slots` of a rectified run and keeps each in
/// `processed/btf-ahead/` for `btf` (one task of a cluster's job array,
/// [`crate::postprocess::parts`]); a slot kept already from the same
/// textures is left as it is. Returns how many it compressed.
pub fn compress_slots_part(
    run: &Path,
    slots: std::ops::Range<usize>,
    components: usize,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<usize, ProcessError> {
    let index = NormtextureIndex::read(run)?;
    index.check_slot_range(&slots)?;
    let total = slots.len();
    let mut compressed = 0;
    for (n, slot) in slots.enumerate() {
        if !slot_ahead_is_current(run, &index, slot, components) {
            compress_slot_ahead(run, &index, slot, components)?;
            compressed += 1;
        }
        progress(n + 1, total);
    }
    Ok(compressed)
}

/// Whether slot `slot` was compressed ahead from the textures `index`
/// lists for it now, with `components` (a stream cut by a restart).
pub fn slot_ahead_is_current(
    run: &Path,
    index: &NormtextureIndex,
    slot: usize,
    components: usize,
) -> bool {
    let (meta_path, _) = ahead_paths(run, slot);
    std::fs::read(meta_path)
        .ok()
        .and_then(|b| serde_json::from_slice::<SlotAhead>(&b).ok())
        .is_some_and(|kept| Some(kept.key) == slot_key(run, index, slot, &format!("C{components}")))
}

/// The slot compressed ahead, if it was made from the textures `index`
/// lists for it now, with `components`.
fn take_slot_ahead(
    run: &Path,
    index: &NormtextureIndex,
    slot: usize,
    components: usize,
) -> Option<(rigd_process::btf::SlotPca, ClipFill)> {
    let (meta_path, bin_path) = ahead_paths(run, slot);
    let kept: SlotAhead = serde_json::from_slice(&std::fs::read(meta_path).ok()?).ok()?;
    let key = slot_key(run, index, slot, &format!("C{components}"));
    if Some(&kept.key) != key.as_ref() {
        tracing::debug!(
            "view slot {slot} was compressed from other textures: {} then, {key:?} now",
            kept.key
        );
        return None;
    }
    let bytes = std::fs::read(bin_path).ok()?;
    let pca =
        rigd_process::btf::SlotPca::from_le_bytes(&bytes, kept.shape, kept.singular_values).ok()?;
    Some((pca, kept.clipped))
}

fn remove_slots_ahead(run: &Path) {
    let dir = crate::store::processed::processed_dir(run).join(AHEAD_DIR);
    if let Err(e) = std::fs::remove_dir_all(&dir) {
        if e.kind() != std::io::ErrorKind::NotFound {
            tracing::warn!("{}: {e}", dir.display());
        }
    }
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
    /// `rms` per channel (red, green, blue for an RGB BTF; one value for
    /// grey).
    pub rms_by_channel: Vec<f64>,
    /// `truth_rms` per channel.
    pub truth_rms_by_channel: Vec<f64>,
}

/// RMS differences between the run's compressed BTF at each pair and the
/// given textures.
pub fn btf_error(
    run: &Path,
    pairs: &[(Direction, Direction)],
    truths: &[Vec<f32>],
) -> Result<Vec<HeldOutError>, ProcessError> {
    let store = rigd_process::btf::CompressedBtf::read(&crate::store::processed::btf_dir(run))
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
            // Values are texel-major with the channels interleaved.
            let channels = store.shape().channels().max(1);
            let (mut err2, mut truth2) = (vec![0.0; channels], vec![0.0; channels]);
            for (k, (a, b)) in tex.iter().zip(truth).enumerate() {
                err2[k % channels] += f64::from(a - b).powi(2);
                truth2[k % channels] += f64::from(*b).powi(2);
            }
            let n = tex.len().max(1) as f64;
            let per_channel = (tex.len() / channels).max(1) as f64;
            let rms = |sums: &[f64], n: f64| sums.iter().map(|s| (s / n).sqrt()).collect();
            Ok(HeldOutError {
                light,
                view,
                rms: (err2.iter().sum::<f64>() / n).sqrt(),
                truth_rms: (truth2.iter().sum::<f64>() / n).sqrt(),
                rms_by_channel: rms(&err2, per_channel),
                truth_rms_by_channel: rms(&truth2, per_channel),
            })
        })
        .collect()
}
