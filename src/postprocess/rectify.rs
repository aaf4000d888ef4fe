//! Registration and rectification of a run's frames into normtextures
//! (Sattler et al., §3.2).

use std::path::Path;

use rigd_core::camera::Camera;
use rigd_core::geometry::Direction;
use rigd_core::holder::{Holder, STANDARD_SAMPLE_MM};
use rigd_process::image_io::Image;
use rigd_process::npy::Dtype;
use serde::Serialize;

use super::frames::RunFrames;
use super::ProcessError;
use crate::kinematics::camera::camera_geometry;
use crate::store::processed::{normtextures_dir, NORMTEXTURE_INDEX};
use crate::store::RunMeta;

/// How `rigd process rectify` resamples and stores the textures.
#[derive(Debug, Clone, Copy)]
pub struct RectifyConfig {
    /// Side of the frontal normtexture each frame is resampled to first.
    pub size: usize,
    /// Fraction of the normtexture's side kept around its centre.
    pub roi: f64,
    /// Side of the stored texture (the ROI scaled).
    pub final_size: usize,
    /// Width of the linear edge blend that makes textures tile (Sattler et al.
    /// §3.2), in final texels; 0 = none.
    pub blend: usize,
    /// How the textures are stored: 8-bit PNG or linear `.npy`.
    pub bits: TextureBits,
}

/// How rectified textures are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TextureBits {
    /// 8-bit PNG of the top 8 bits of the sensor value (no clipping).
    Top8,
    /// 8-bit PNG of `value >> shift`, clipped at 255 (2 = the central 8
    /// bits of 12, as Sattler et al., §3.2 chose for the linear part of its CCD).
    Shift(u8),
    /// Linear float32 `.npy`, 1 = full scale.
    Float,
    /// Linear float16 `.npy` (Sattler et al.'s "16-bit floats"), half the bytes.
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
    /// The frame's image index in the run.
    pub index: usize,
    /// Index of its view in the index's `views` (the BTF slot).
    pub view_slot: usize,
    /// Index of its light in the index's `lights`.
    pub light_index: usize,
    /// The texture file, relative to the normtextures folder; None if the
    /// frame could not be registered.
    pub file: Option<String>,
    /// RMS reprojection residual of the markers used, pixels; None if the
    /// frame was not registered.
    pub rms_px: Option<f64>,
    /// Largest reprojection residual of the markers used, pixels.
    pub max_px: Option<f64>,
    /// Holder markers detected in the frame.
    pub markers_found: usize,
    /// Markers used in the final fit of the homography.
    pub markers_used: usize,
    /// Layout indices of the markers rejected as outliers.
    pub markers_rejected: Vec<usize>,
    /// Fraction of the texture the frame covered.
    pub coverage: Option<f64>,
    /// Why the frame could not be registered or written, if it could not.
    pub error: Option<String>,
}

impl FrameRegistration {
    /// A frame at (view slot, light) with nothing registered yet.
    pub(super) fn new(index: usize, view_slot: usize, light_index: usize) -> FrameRegistration {
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
    /// Side of every stored texture, texels.
    pub size: usize,
    /// `png8` (8-bit codes / 255), `npy-f32` or `npy-f16` (linear, 1 =
    /// full scale).
    pub encoding: String,
    /// Bit depth of the sensor values the frames were captured with.
    pub bit_depth: u8,
    /// Commanded directions (sample frame); BTF slots are views.
    pub lights: Vec<Direction>,
    /// Commanded view directions (sample frame), one per BTF slot.
    pub views: Vec<Direction>,
    /// Every frame's registration, in run order.
    pub frames: Vec<FrameRegistration>,
}

impl NormtextureIndex {
    /// Reads a run's `processed/normtextures/index.json`, written by
    /// `rigd process rectify`.
    pub fn read(run: &Path) -> Result<NormtextureIndex, ProcessError> {
        let path = normtextures_dir(run).join(NORMTEXTURE_INDEX);
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
        let path = normtextures_dir(run).join(file);
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
pub(super) fn slot_of(list: &mut Vec<Direction>, d: Direction) -> usize {
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

/// The holder plate the run's frames show and the sample's half-sides
/// (metres): a simulated run's scene's, the standard plate on hardware.
fn holder_of(meta: &RunMeta) -> Result<(Holder, [f64; 2]), ProcessError> {
    if meta.simulated {
        #[cfg(feature = "sim")]
        {
            let scene = rigd_sim::scene::Scene::load(meta.profile.sim.scene_name())?;
            return Ok((scene.holder.clone(), scene.sample_half));
        }
        #[cfg(not(feature = "sim"))]
        return Err(ProcessError::Invalid(
            "a simulated run shows its scene's holder, and this rigd was built without the \
             simulator (cargo feature `sim`)"
                .into(),
        ));
    }
    let half = STANDARD_SAMPLE_MM * 1e-3 / 2.0;
    Ok((Holder::standard(), [half, half]))
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
    let (holder, sample_half) = holder_of(&run.meta)?;
    let points: Vec<[f64; 2]> = holder
        .markers()
        .into_iter()
        .filter(|m| m.kind == "point")
        .map(|m| m.position)
        .collect();
    let layout = MarkerLayout {
        points: points.clone(),
        radius_m: holder.point_radius,
        sample_half,
    };
    let out_dir = crate::store::processed::normtextures_dir(&run.root);
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
                let camera = Camera::new(
                    entry.achieved_view.to_vector(),
                    [entry.width, entry.height],
                    Some(geometry.focal_px),
                    geometry.distance_m,
                    1.1 * holder.half,
                );
                // Where the rig's pose says the markers are; the search
                // finds them around that.
                let predicted: Vec<Option<[f64; 2]>> = points
                    .iter()
                    .map(|p| camera.project([p[0], p[1], 0.0]))
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
