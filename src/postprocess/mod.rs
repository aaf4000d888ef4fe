//! Post-processing of run directories: loads what `rigd_process` needs from
//! a run (frames, their directions) and, for simulated runs, measures the
//! result against the scene's ground truth.

pub mod mdf;
pub mod viewer;

use std::path::{Path, PathBuf};

use rigd_process::image_io::Image;
use rigd_process::npy::Dtype;
use rigd_process::photometric_stereo::{PsDataset, PsResult};
use rigd_sim::scene::{Scene, Shot};
use serde::Serialize;

use crate::rig::sim::camera_geometry;
use crate::store::{decode_png, read_journal, read_meta, FrameEntry, RunMeta, JOURNAL_FILE};
use rigd_core::geometry::Direction;

#[derive(Debug, thiserror::Error)]
pub enum ProcessError {
    #[error("{0}")]
    Store(#[from] crate::store::StoreError),
    #[error("{path}: {message}")]
    Frame { path: PathBuf, message: String },
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Scene(#[from] rigd_sim::scene::SceneError),
}

/// A run's metadata and every frame it wrote, in capture order.
pub struct RunFrames {
    pub root: PathBuf,
    pub meta: RunMeta,
    pub entries: Vec<FrameEntry>,
}

impl RunFrames {
    pub fn open(root: &Path) -> Result<RunFrames, ProcessError> {
        let meta = read_meta(root)?;
        let (mut entries, _) = read_journal(&root.join(JOURNAL_FILE))?;
        entries.sort_by_key(|e| e.index);
        Ok(RunFrames {
            root: root.to_path_buf(),
            meta,
            entries,
        })
    }

    /// One frame as linear values in [0, 1].
    pub fn image(&self, entry: &FrameEntry) -> Result<Image, ProcessError> {
        let path = self.root.join(&entry.file);
        let bytes = std::fs::read(&path).map_err(|e| ProcessError::Frame {
            path: path.clone(),
            message: e.to_string(),
        })?;
        let (w, h, pixels) = decode_png(&bytes).map_err(|message| ProcessError::Frame {
            path: path.clone(),
            message,
        })?;
        let full = ((1u32 << entry.bit_depth.clamp(1, 16)) - 1) as f32;
        let mut img = Image::new(w as usize, h as usize, 1);
        for (d, p) in img.data.iter_mut().zip(pixels) {
            *d = p as f32 / full;
        }
        Ok(img)
    }
}

/// A photometric-stereo dataset from a run whose camera looks down on the
/// sample (VirTex): every frame of one camera, with the light each was
/// taken under. The camera's image axes are the sample's x and y (the
/// simulated and real VirTex cameras sit at the pole), so lights in the
/// sample frame are lights in the image frame photometric stereo expects.
pub fn ps_dataset_from_run(run: &RunFrames) -> Result<PsDataset, ProcessError> {
    let first = run.entries.first().ok_or_else(|| {
        ProcessError::Invalid(format!("{}: the run has no frames", run.root.display()))
    })?;
    let camera = first.camera.clone();
    let entries: Vec<&FrameEntry> = run.entries.iter().filter(|e| e.camera == camera).collect();
    for e in &entries {
        if e.achieved_view.theta_deg > 1.0 {
            return Err(ProcessError::Invalid(format!(
                "{}: frame {} of camera {camera} looks from θ = {:.1}°: photometric stereo here needs a camera at the pole",
                run.root.display(),
                e.index,
                e.achieved_view.theta_deg
            )));
        }
    }
    let mut images = Vec::with_capacity(entries.len());
    for e in &entries {
        images.push(run.image(e)?);
    }
    Ok(PsDataset {
        image_names: entries.iter().map(|e| e.file.clone()).collect(),
        images,
        lights: entries
            .iter()
            .map(|e| e.achieved_light.to_vector())
            .collect(),
        intensities: None,
        mask: None,
        lights_origin: format!("{} (journal)", run.root.display()),
    })
}

/// How far recovered normals are from the scene's true ones.
#[derive(Debug, Clone, Serialize)]
pub struct NormalError {
    pub scene: String,
    /// Pixels on the sample that photometric stereo solved.
    pub pixels: usize,
    pub mean_deg: f64,
    pub median_deg: f64,
    pub p95_deg: f64,
}

/// Compares photometric-stereo normals of a simulated run with the true
/// normals of the surface point each pixel sees.
pub fn ps_error_against_truth(
    run: &RunFrames,
    result: &PsResult,
) -> Result<Option<NormalError>, ProcessError> {
    if !run.meta.simulated {
        return Ok(None);
    }
    let Some(first) = run.entries.first() else {
        return Ok(None);
    };
    let scene = Scene::load(run.meta.profile.sim.scene_name())?;
    let size = [result.width as u32, result.height as u32];
    let geometry = camera_geometry(&run.meta.profile, &first.camera, size).ok_or_else(|| {
        ProcessError::Invalid(format!(
            "the run's profile has no camera `{}`",
            first.camera
        ))
    })?;
    let shot = Shot {
        view: first.achieved_view.to_vector(),
        width: size[0],
        height: size[1],
        focal_px: Some(geometry.focal_px),
        camera_distance_m: geometry.distance_m,
        ..Shot::default()
    };
    Ok(normal_error(&scene, &shot, result))
}

/// Mean, median and 95th percentile angle between `result`'s valid normals
/// and the true normals, over pixels that see the sample.
pub fn normal_error(scene: &Scene, shot: &Shot, result: &PsResult) -> Option<NormalError> {
    let mut angles = Vec::new();
    for j in 0..result.height {
        for i in 0..result.width {
            let k = j * result.width + i;
            if !result.valid[k] {
                continue;
            }
            let Some(p) = scene.true_surface_point(shot, i, j) else {
                continue;
            };
            if !scene.on_sample(p[0], p[1]) {
                continue;
            }
            let t = scene.true_normal(p[0], p[1]);
            let n = result.normals[k];
            let c = (t[0] * n[0] as f64 + t[1] * n[1] as f64 + t[2] * n[2] as f64).clamp(-1.0, 1.0);
            angles.push(c.acos().to_degrees());
        }
    }
    if angles.is_empty() {
        return None;
    }
    angles.sort_by(f64::total_cmp);
    let n = angles.len();
    Some(NormalError {
        scene: scene.name.clone(),
        pixels: n,
        mean_deg: angles.iter().sum::<f64>() / n as f64,
        median_deg: angles[n / 2],
        p95_deg: angles[(n * 95 / 100).min(n - 1)],
    })
}

/// Where processed results of a run go.
pub const PROCESSED_DIR: &str = "processed";
/// The registered textures, one per frame, and their index.
pub const NORMTEXTURES_DIR: &str = "normtextures";
pub const NORMTEXTURE_INDEX: &str = "index.json";

/// How `rigd process rectify` resamples and stores the textures.
#[derive(Debug, Clone, Copy)]
pub struct RectifyConfig {
    /// Side of the frontal normtexture each frame is resampled to first.
    pub size: usize,
    /// Fraction of the normtexture's side kept around its centre.
    pub roi: f64,
    /// Side of the stored texture (the ROI scaled).
    pub final_size: usize,
    /// Width of the linear edge blend that makes textures tile (seed 000
    /// §3.2), in final texels; 0 = none.
    pub blend: usize,
    pub bits: TextureBits,
}

/// How rectified textures are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TextureBits {
    /// 8-bit PNG of the top 8 bits of the sensor value (no clipping).
    Top8,
    /// 8-bit PNG of `value >> shift`, clipped at 255 (2 = the central 8
    /// bits of 12, as seed 000 §3.2 chose for the linear part of its CCD).
    Shift(u8),
    /// Linear float32 `.npy`, 1 = full scale.
    Float,
    /// Linear float16 `.npy` (the seed's "16-bit floats"), half the bytes.
    Half,
}

impl Default for RectifyConfig {
    fn default() -> Self {
        RectifyConfig {
            size: rigd_process::rectify::NORMTEXTURE_SIZE,
            roi: 1.0,
            final_size: rigd_process::rectify::FINAL_TEXTURE_SIZE,
            blend: 0,
            bits: TextureBits::Top8,
        }
    }
}

/// One frame's registration, as `processed/normtextures/index.json` records it.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct FrameRegistration {
    pub index: usize,
    pub view_slot: usize,
    pub light_index: usize,
    /// The texture file, relative to the normtextures folder; None if the
    /// frame could not be registered.
    pub file: Option<String>,
    pub rms_px: Option<f64>,
    pub max_px: Option<f64>,
    pub markers_found: usize,
    pub markers_used: usize,
    pub markers_rejected: Vec<usize>,
    /// Fraction of the texture the frame covered.
    pub coverage: Option<f64>,
    pub error: Option<String>,
}

impl FrameRegistration {
    /// A frame at (view slot, light) with nothing registered yet.
    fn new(index: usize, view_slot: usize, light_index: usize) -> FrameRegistration {
        FrameRegistration {
            index,
            view_slot,
            light_index,
            file: None,
            rms_px: None,
            max_px: None,
            markers_found: 0,
            markers_used: 0,
            markers_rejected: Vec::new(),
            coverage: None,
            error: None,
        }
    }
}

/// The index of a run's normtextures: the measured directions and, per
/// (view slot, light), the texture.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct NormtextureIndex {
    pub size: usize,
    /// `png8` (8-bit codes / 255), `npy-f32` or `npy-f16` (linear, 1 =
    /// full scale).
    pub encoding: String,
    pub bit_depth: u8,
    /// Commanded directions (sample frame); BTF slots are views.
    pub lights: Vec<Direction>,
    pub views: Vec<Direction>,
    pub frames: Vec<FrameRegistration>,
}

impl NormtextureIndex {
    pub fn read(run: &Path) -> Result<NormtextureIndex, ProcessError> {
        let path = run
            .join(PROCESSED_DIR)
            .join(NORMTEXTURES_DIR)
            .join(NORMTEXTURE_INDEX);
        let bytes = std::fs::read(&path).map_err(|e| ProcessError::Frame {
            path: path.clone(),
            message: format!("{e} (run `rigd process rectify` first)"),
        })?;
        serde_json::from_slice(&bytes).map_err(|e| ProcessError::Frame {
            path,
            message: e.to_string(),
        })
    }

    /// The texture of (view slot, light) as linear values.
    pub fn load(&self, run: &Path, view_slot: usize, light: usize) -> Result<Image, ProcessError> {
        let frame = self
            .frames
            .iter()
            .find(|f| f.view_slot == view_slot && f.light_index == light);
        let Some(file) = frame.and_then(|f| f.file.as_ref()) else {
            return Err(ProcessError::Invalid(format!(
                "no registered texture for view slot {view_slot}, light {light}{}",
                frame
                    .and_then(|f| f.error.as_ref())
                    .map(|e| format!(" (frame {}: {e})", frame.map_or(0, |f| f.index)))
                    .unwrap_or_default()
            )));
        };
        let path = run.join(PROCESSED_DIR).join(NORMTEXTURES_DIR).join(file);
        let frame_err = |message: String| ProcessError::Frame {
            path: path.clone(),
            message,
        };
        if self.encoding.starts_with("npy-") {
            let a = rigd_process::npy::read_f32(&path).map_err(|e| frame_err(e.to_string()))?;
            let (h, w) = (a.shape[0], a.shape.get(1).copied().unwrap_or(1));
            let mut img = Image::new(w, h, 1);
            img.data = a.data;
            Ok(img)
        } else {
            rigd_process::image_io::load_png(&path).map_err(|e| frame_err(e.to_string()))
        }
    }
}

/// Index of `d` in `list` (adding it if new), by direction within 1e-6°.
fn slot_of(list: &mut Vec<Direction>, d: Direction) -> usize {
    let same = |a: &Direction| {
        (a.theta_deg - d.theta_deg).abs() < 1e-6
            && ((a.phi_deg - d.phi_deg).abs() < 1e-6 || d.theta_deg.abs() < 1e-9)
    };
    match list.iter().position(same) {
        Some(i) => i,
        None => {
            list.push(d);
            list.len() - 1
        }
    }
}

/// The holder the run's frames show, as the registration sees it: the
/// simulated scene's, or the default plate for hardware runs.
fn holder_scene(meta: &RunMeta) -> Result<std::sync::Arc<Scene>, ProcessError> {
    let name = if meta.simulated {
        meta.profile.sim.scene_name()
    } else {
        rigd_sim::scene::DEFAULT_SCENE
    };
    Ok(Scene::load(name)?)
}

/// Registers every frame of a run by its holder markers, resamples the
/// sample square to a frontal texture, and writes the textures and
/// `processed/normtextures/index.json`. Frames whose markers cannot be
/// found are listed in the index with the reason and make the whole call
/// fail with an error naming them (after every other frame is written).
pub fn rectify_run(
    run: &RunFrames,
    cfg: &RectifyConfig,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<NormtextureIndex, ProcessError> {
    use rayon::prelude::*;
    use rigd_process::image_io::{write_png, PngDepth};
    use rigd_process::rectify::{self as rect, MarkerLayout, Quantisation};
    if cfg.blend >= cfg.final_size {
        return Err(ProcessError::Invalid(format!(
            "edge blend of {} texels: must be narrower than the {}-texel texture",
            cfg.blend, cfg.final_size
        )));
    }
    if cfg.final_size == 0 || cfg.size == 0 || !(cfg.roi > 0.0 && cfg.roi <= 1.0) {
        return Err(ProcessError::Invalid(format!(
            "size {}, ROI {}, final size {}: expected positive sizes and 0 < ROI ≤ 1",
            cfg.size, cfg.roi, cfg.final_size
        )));
    }
    let scene = holder_scene(&run.meta)?;
    let points: Vec<[f64; 2]> = scene
        .holder
        .markers()
        .into_iter()
        .filter(|m| m.kind == "point")
        .map(|m| m.position)
        .collect();
    let layout = MarkerLayout {
        points,
        radius_m: scene.holder.point_radius,
        sample_half: scene.sample_half,
    };
    let out_dir = run.root.join(PROCESSED_DIR).join(NORMTEXTURES_DIR);
    std::fs::create_dir_all(&out_dir).map_err(|e| ProcessError::Frame {
        path: out_dir.clone(),
        message: e.to_string(),
    })?;
    let (mut lights, mut views) = (Vec::new(), Vec::new());
    let slots: Vec<(usize, usize)> = run
        .entries
        .iter()
        .map(|e| {
            (
                slot_of(&mut views, e.view.canonical()),
                slot_of(&mut lights, e.light.canonical()),
            )
        })
        .collect();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let total = run.entries.len();
    let bit_depth = run.entries.first().map_or(8, |e| e.bit_depth);
    let frames: Vec<FrameRegistration> = run
        .entries
        .par_iter()
        .zip(slots.par_iter())
        .map(|(entry, &(view_slot, light_index))| {
            let mut rec = FrameRegistration::new(entry.index, view_slot, light_index);
            let result = (|| -> Result<(), String> {
                let image = run.image(entry).map_err(|e| e.to_string())?;
                let geometry = camera_geometry(
                    &run.meta.profile,
                    &entry.camera,
                    [entry.width, entry.height],
                )
                .ok_or_else(|| format!("no camera `{}` in the run's profile", entry.camera))?;
                let shot = Shot {
                    view: entry.achieved_view.to_vector(),
                    width: entry.width,
                    height: entry.height,
                    focal_px: Some(geometry.focal_px),
                    camera_distance_m: geometry.distance_m,
                    ..Shot::default()
                };
                // Where the rig's pose says the markers are; the search
                // finds them around that.
                let predicted: Vec<Option<[f64; 2]>> = scene
                    .true_markers(&shot)
                    .into_iter()
                    .filter(|(m, _)| m.kind == "point")
                    .map(|(_, p)| p)
                    .collect();
                let radius = (0.03 * f64::from(entry.width.max(entry.height))).max(6.0);
                let detections =
                    rect::detect_markers(&image, &predicted, radius, &Default::default())
                        .map_err(|e| e.to_string())?;
                let reg = rect::register(&layout, &detections, &Default::default())
                    .map_err(|e| e.to_string())?;
                rec.rms_px = Some(reg.rms_px);
                rec.max_px = Some(reg.max_px);
                rec.markers_found = reg.found;
                rec.markers_used = reg.used;
                rec.markers_rejected = reg.rejected.clone();
                let full = rect::rectify(
                    &image,
                    &reg.homography,
                    layout.sample_region(),
                    [cfg.size, cfg.size],
                    &Default::default(),
                )
                .map_err(|e| e.to_string())?;
                rec.coverage = Some(full.coverage);
                let roi = rect::Roi::centred(cfg.size, cfg.size, cfg.roi);
                // With a blend the ROI is scaled to final + blend texels,
                // whose extra band is blended into the opposite edge.
                let side = cfg.final_size + cfg.blend;
                let texture = rect::roi_cut(&full.texture, roi, [side, side])
                    .and_then(|t| rect::edge_blend(&t, cfg.blend))
                    .map_err(|e| e.to_string())?;
                let name = format!("v{view_slot:03}_l{light_index:03}");
                let (shift, dtype) = match cfg.bits {
                    TextureBits::Top8 => (Some(entry.bit_depth.saturating_sub(8)), Dtype::F32),
                    TextureBits::Shift(s) => (Some(s), Dtype::F32),
                    TextureBits::Float => (None, Dtype::F32),
                    TextureBits::Half => (None, Dtype::F16),
                };
                match shift {
                    Some(shift) => {
                        let q = rect::quantise(
                            &texture,
                            entry.bit_depth,
                            Quantisation::Bits8 { shift },
                        )
                        .map_err(|e| e.to_string())?;
                        let file = format!("{name}.png");
                        write_png(&out_dir.join(&file), &q, PngDepth::Eight)
                            .map_err(|e| e.to_string())?;
                        rec.file = Some(file);
                    }
                    None => {
                        let file = format!("{name}.npy");
                        rigd_process::npy::write(
                            &out_dir.join(&file),
                            &[texture.height, texture.width],
                            &texture.data,
                            dtype,
                        )
                        .map_err(|e| e.to_string())?;
                        rec.file = Some(file);
                    }
                }
                Ok(())
            })();
            if let Err(e) = result {
                rec.error = Some(e);
            }
            let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress(n, total);
            rec
        })
        .collect();
    let index = NormtextureIndex {
        size: cfg.final_size,
        encoding: match cfg.bits {
            TextureBits::Float => "npy-f32",
            TextureBits::Half => "npy-f16",
            TextureBits::Top8 | TextureBits::Shift(_) => "png8",
        }
        .into(),
        bit_depth,
        lights: lights.clone(),
        views: views.clone(),
        frames,
    };
    let path = out_dir.join(NORMTEXTURE_INDEX);
    let mut json =
        serde_json::to_vec_pretty(&index).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    crate::store::write_atomic(&path, &json)?;
    let failed: Vec<String> = index
        .frames
        .iter()
        .filter_map(|f| f.error.as_ref().map(|e| format!("frame {}: {e}", f.index)))
        .collect();
    if !failed.is_empty() {
        let shown: Vec<&str> = failed.iter().take(10).map(String::as_str).collect();
        return Err(ProcessError::Invalid(format!(
            "{} of {} frames could not be registered (listed in {}): {}{}",
            failed.len(),
            index.frames.len(),
            path.display(),
            shown.join("; "),
            if failed.len() > 10 { "; …" } else { "" }
        )));
    }
    Ok(index)
}

/// Per slot and for the whole run: how fast the spectrum decays and what
/// RMS error C components leave.
#[derive(Debug, Clone, Serialize)]
pub struct BtfReport {
    pub components: usize,
    pub slots: usize,
    pub lights: usize,
    /// Mean over slots of the RMS reconstruction error with C = 1 … 32
    /// components (in texture units, 1 = full scale).
    pub mean_rms_by_components: Vec<f64>,
    pub per_slot: Vec<SlotSummary>,
    pub compress_s: f64,
    pub bytes: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct SlotSummary {
    pub slot: usize,
    pub view: Direction,
    /// Eigenvalues (σ²), largest first, at most 32.
    pub eigenvalues: Vec<f64>,
    pub rms_by_components: Vec<f64>,
}

/// Compresses a rectified run's BTF: a PCA per view slot with `components`
/// components (seed 000 §4.1), streamed slot by slot into
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
    let dir = run.join(PROCESSED_DIR).join("btf");
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

/// One row of the run's fit table (seed 001 Table 1).
#[derive(Debug, Clone, Serialize)]
pub struct FitRow {
    pub method: String,
    /// Mean over slots of the mean |model − value| over texels and lights,
    /// in texture units (1 = full scale).
    pub mean_abs_error: f64,
    pub rms_error: f64,
    pub fit_s: f64,
    pub converged_texels: usize,
}

/// Fits every view slot of a rectified run with PTM and the K-lobe model
/// (seed 001 §4) and tabulates the errors, written to
/// `processed/fit/report.json`. The fitted parameters are not stored.
pub fn fit_run(
    run: &Path,
    lobes: usize,
    progress: &dyn Fn(usize, usize),
) -> Result<Vec<FitRow>, ProcessError> {
    use rigd_process::reflectance_fit::{fit_ptm_slot, fit_slot, FitMethod, FitOptions};
    let index = NormtextureIndex::read(run)?;
    let lights: Vec<[f64; 3]> = index.lights.iter().map(|d| d.to_vector()).collect();
    let dir = run.join(PROCESSED_DIR).join("fit");
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
        // The fitted parameters, per texel: the seed's (a, b, c, n) per
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

fn to_pdir(d: Direction) -> rigd_process::directions::Direction {
    rigd_process::directions::Direction::new(d.theta_deg, d.phi_deg)
}

/// Writes a rectified run's textures in an existing BTF tool's layout
/// (`rigd export`); returns how many.
pub fn export_run(
    run: &Path,
    format: rigd_process::export::Format,
    out: &Path,
    jpeg_quality: u8,
) -> Result<usize, ProcessError> {
    use rigd_process::export::{write, Texture};
    let index = NormtextureIndex::read(run)?;
    let mut textures = Vec::with_capacity(index.frames.len());
    for f in &index.frames {
        let (Some(&light), Some(&view)) = (
            index.lights.get(f.light_index),
            index.views.get(f.view_slot),
        ) else {
            return Err(ProcessError::Invalid(format!(
                "{}: frame {} names light {} and view slot {}, which the index does not list",
                run.display(),
                f.index,
                f.light_index,
                f.view_slot
            )));
        };
        textures.push(Texture {
            light: to_pdir(light),
            view: to_pdir(view),
            image: index.load(run, f.view_slot, f.light_index)?,
        });
    }
    write(&textures, format, out, jpeg_quality).map_err(|e| ProcessError::Invalid(e.to_string()))
}

/// Reads textures in an export format into `out/processed/normtextures/`,
/// so `rigd process btf out` works on them (`rigd import`).
pub fn import_textures(
    format: rigd_process::export::Format,
    path: &Path,
    out: &Path,
) -> Result<NormtextureIndex, ProcessError> {
    use rigd_process::image_io::{write_png, PngDepth};
    let textures = rigd_process::export::read(format, path)
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let first = textures
        .first()
        .ok_or_else(|| ProcessError::Invalid(format!("{}: no textures found", path.display())))?;
    let size = first.image.width;
    let dir = out.join(PROCESSED_DIR).join(NORMTEXTURES_DIR);
    std::fs::create_dir_all(&dir).map_err(|e| ProcessError::Frame {
        path: dir.clone(),
        message: e.to_string(),
    })?;
    let (mut lights, mut views, mut frames) = (Vec::new(), Vec::new(), Vec::new());
    for (i, t) in textures.iter().enumerate() {
        if t.image.width != size || t.image.height != size {
            return Err(ProcessError::Invalid(format!(
                "{}: texture {i} is {}x{}, the first is {size}x{size}",
                path.display(),
                t.image.width,
                t.image.height
            )));
        }
        let view_slot = slot_of(&mut views, Direction::new(t.view.theta_deg, t.view.phi_deg));
        let light_index = slot_of(
            &mut lights,
            Direction::new(t.light.theta_deg, t.light.phi_deg),
        );
        let file = format!("v{view_slot:03}_l{light_index:03}.png");
        write_png(&dir.join(&file), &t.image, PngDepth::Eight).map_err(|e| {
            ProcessError::Frame {
                path: dir.join(&file),
                message: e.to_string(),
            }
        })?;
        frames.push(FrameRegistration {
            file: Some(file),
            ..FrameRegistration::new(i, view_slot, light_index)
        });
    }
    let index = NormtextureIndex {
        size,
        encoding: "png8".into(),
        bit_depth: 8,
        lights,
        views,
        frames,
    };
    let mut json =
        serde_json::to_vec_pretty(&index).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    crate::store::write_atomic(&dir.join(NORMTEXTURE_INDEX), &json)?;
    Ok(index)
}

/// The error of a compressed BTF at one (light, view) against the scene's
/// true reflectance.
#[derive(Debug, Clone, Serialize)]
pub struct HeldOutError {
    pub light: Direction,
    pub view: Direction,
    /// RMS over texels of reconstruction − truth, texture units.
    pub rms: f64,
    /// RMS of the truth itself, for scale.
    pub truth_rms: f64,
}

/// What a perfect rig's normtexture of `scene` at (light, view) holds:
/// `Scene::true_btf` over the sample square, `size`² texels (row 0 the +y
/// edge, column 0 the −x edge), each averaged over its area (4 × 4
/// samples, as the registration's area filter averages the frame's
/// pixels; point samples would alias the relief's highlights), scaled as
/// the sensor scales radiance ([`rigd_sim::scene::WHITE_LEVEL`] of full
/// scale for a white Lambertian sample lit frontally) with a directional
/// lamp (a rig's lamp fall-off therefore counts as error).
pub fn true_texture(scene: &Scene, size: usize, light: Direction, view: Direction) -> Vec<f32> {
    use rayon::prelude::*;
    const SUB: usize = 4;
    let [hx, hy] = scene.sample_half;
    let (l, v) = (light.to_vector(), view.to_vector());
    let mut out = vec![0f32; size * size];
    out.par_chunks_mut(size.max(1))
        .enumerate()
        .for_each(|(j, row)| {
            for (i, texel) in row.iter_mut().enumerate() {
                let mut sum = 0.0;
                for sj in 0..SUB {
                    let y =
                        hy - (j as f64 + (sj as f64 + 0.5) / SUB as f64) / size as f64 * 2.0 * hy;
                    for si in 0..SUB {
                        let x = -hx
                            + (i as f64 + (si as f64 + 0.5) / SUB as f64) / size as f64 * 2.0 * hx;
                        sum += scene.true_btf(x, y, l, v, Default::default());
                    }
                }
                *texel = (rigd_sim::scene::WHITE_LEVEL * sum / (SUB * SUB) as f64) as f32;
            }
        });
    out
}

/// Compares the run's compressed BTF (`processed/btf/`) at each (light,
/// view) with the simulated run's scene ([`true_texture`]).
pub fn btf_truth_error(
    run: &Path,
    pairs: &[(Direction, Direction)],
) -> Result<Vec<HeldOutError>, ProcessError> {
    let meta = read_meta(run)?;
    if !meta.simulated {
        return Err(ProcessError::Invalid(format!(
            "{}: ground truth exists only for simulated runs",
            run.display()
        )));
    }
    let scene = Scene::load(meta.profile.sim.scene_name())?;
    let size = NormtextureIndex::read(run)?.size;
    let truths: Vec<Vec<f32>> = pairs
        .iter()
        .map(|&(l, v)| true_texture(&scene, size, l, v))
        .collect();
    btf_error(run, pairs, &truths)
}

/// RMS differences between the run's compressed BTF at each pair and the
/// given textures.
pub fn btf_error(
    run: &Path,
    pairs: &[(Direction, Direction)],
    truths: &[Vec<f32>],
) -> Result<Vec<HeldOutError>, ProcessError> {
    let store = rigd_process::btf::BtfStore::read(&run.join(PROCESSED_DIR).join("btf"))
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    pairs
        .iter()
        .zip(truths)
        .map(|(&(light, view), truth)| {
            let tex = store
                .reconstruct(to_pdir(light), to_pdir(view))
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
