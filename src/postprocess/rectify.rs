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
    /// frame has no texture (its whole view slot was unusable).
    pub file: Option<String>,
    /// RMS reprojection residual of the markers used, pixels; None if the
    /// markers did not register the frame.
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
    /// Why the frame has no texture at all (its whole view slot was
    /// unusable); None when it has one.
    pub error: Option<String>,
    /// How the frame was registered; None for an index written before
    /// rigd recorded it (then `markers`).
    #[serde(default)]
    pub method: Option<RegistrationMethod>,
    /// Estimated registration error at the sample, pixels of the frame:
    /// the marker RMS residual for `markers`; for `pose` and
    /// `pose+texture` the 95th percentile of how far that method lands
    /// from the markers on the run's marker-registered frames (None if the
    /// run has none to measure it on).
    #[serde(default)]
    pub error_px: Option<f64>,
    /// Why the markers did not register the frame (`pose`,
    /// `pose+texture`), or why the frame is unusable (`interpolated`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub problem: Option<String>,
    /// The frames an `interpolated` texture was filled from, by image index.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub interpolated_from: Vec<usize>,
}

/// How a frame's texture came to be (`index.json` `method`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, serde::Deserialize)]
pub enum RegistrationMethod {
    /// The holder's point markers, found in the frame (Sattler et al., §3.2).
    #[serde(rename = "markers")]
    Markers,
    /// The camera model at the achieved pose, corrected by the holder's
    /// offset that the run's marker-registered frames measure.
    #[serde(rename = "pose")]
    Pose,
    /// `pose`, then shifted onto a marker-registered frame of the same
    /// view slot by the sample's own texture (phase correlation).
    #[serde(rename = "pose+texture")]
    PoseTexture,
    /// The frame is unusable (lost, black, saturated): its texture is the
    /// mean of its view slot's nearest lights, weighted by inverse angle.
    #[serde(rename = "interpolated")]
    Interpolated,
}

impl RegistrationMethod {
    /// The name `index.json` and the summary use.
    pub fn name(self) -> &'static str {
        match self {
            RegistrationMethod::Markers => "markers",
            RegistrationMethod::Pose => "pose",
            RegistrationMethod::PoseTexture => "pose+texture",
            RegistrationMethod::Interpolated => "interpolated",
        }
    }
}

impl FrameRegistration {
    /// A frame at (view slot, light) with nothing registered yet.
    pub fn new(index: usize, view_slot: usize, light_index: usize) -> FrameRegistration {
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
            method: None,
            error_px: None,
            problem: None,
            interpolated_from: Vec::new(),
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
    /// Frames per method and the residuals; None for an index written
    /// before rigd recorded it, or imported.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub summary: Option<RegistrationSummary>,
}

/// What `rigd process rectify` prints and `index.json` keeps: how the
/// frames were registered and how well.
#[derive(Debug, Clone, Default, Serialize, serde::Deserialize)]
pub struct RegistrationSummary {
    /// Frames per method (`markers`, `pose`, `pose+texture`,
    /// `interpolated`).
    pub frames_by_method: std::collections::BTreeMap<String, usize>,
    /// Frames without a texture (their whole view slot was unusable).
    pub frames_without_texture: usize,
    /// Marker RMS residual over the marker-registered frames, pixels:
    /// median, 95th percentile, worst.
    pub marker_rms_px: Option<[f64; 3]>,
    /// Where the holder sits relative to the pose model's sample centre,
    /// millimetres (plate x, y), measured on the marker-registered frames.
    pub holder_offset_mm: Option<[f64; 2]>,
    /// How far the bare camera model (no offset) lands from the markers:
    /// 95th percentile, pixels.
    pub uncalibrated_pose_error_px: Option<f64>,
    /// `pose` against the markers on the same frames: 95th percentile, pixels.
    pub pose_error_px: Option<f64>,
    /// `pose+texture` against the markers on marker-registered frames:
    /// 95th percentile, pixels, and on how many frames it was measured.
    pub pose_texture_error_px: Option<f64>,
    /// Frames `pose_texture_error_px` was measured on.
    pub pose_texture_checked: usize,
}

impl RegistrationSummary {
    /// The summary as the table `rigd process rectify` prints.
    pub fn table(&self) -> String {
        use std::fmt::Write;
        let mut out = String::from("method         frames\n");
        for (m, n) in &self.frames_by_method {
            let _ = writeln!(out, "{m:<14} {n:>6}");
        }
        if self.frames_without_texture > 0 {
            let _ = writeln!(
                out,
                "{:<14} {:>6}",
                "no texture", self.frames_without_texture
            );
        }
        let px = |v: Option<f64>| v.map_or("not measured".to_string(), |v| format!("{v:.2} px"));
        if let Some([p50, p95, max]) = self.marker_rms_px {
            let _ = writeln!(
                out,
                "marker residual (RMS per frame): median {p50:.2} px, p95 {p95:.2} px, worst {max:.2} px"
            );
        }
        if let Some([x, y]) = self.holder_offset_mm {
            let _ = writeln!(
                out,
                "holder offset from the pose model: x {x:+.3} mm, y {y:+.3} mm"
            );
        }
        let _ = writeln!(
            out,
            "pose vs markers (p95): {} calibrated, {} uncalibrated; pose+texture vs markers (p95): {} on {} frames",
            px(self.pose_error_px),
            px(self.uncalibrated_pose_error_px),
            px(self.pose_texture_error_px),
            self.pose_texture_checked
        );
        out
    }
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

/// A frame is black (a lamp that did not fire, a closed shutter) when its
/// 99th-percentile value is below this fraction of full scale and below
/// [`BLACK_RATIO`] of the darker of its slot's two nearest lights: a flat
/// sample under an 85° light is legitimately that dark (0.4 % measured),
/// but so are its neighbours.
pub const BLACK_P99: f32 = 0.01;
/// See [`BLACK_P99`].
pub const BLACK_RATIO: f32 = 0.25;
/// Below this 99th percentile a frame is black whatever its neighbours
/// (a whole slot the lamp missed): a dark frame's noise measured 0.12 %,
/// a flat sample under an 85° light 0.42 %.
pub const BLACK_FLOOR: f32 = 0.0025;
/// A marker registration from at most 5 markers (too few to locate an
/// outlier) that lands farther than this from the calibrated pose, and
/// than [`MARKER_DOUBT_FACTOR`] × the median disagreement, is not trusted:
/// at 85° views five nearly collinear markers fit a homography that is
/// tens of pixels off at the sample (measured on the demo H1).
pub const MARKER_DOUBT_PX: f64 = 3.0;
/// See [`MARKER_DOUBT_PX`].
pub const MARKER_DOUBT_FACTOR: f64 = 3.0;
/// A frame whose sample texture is at full scale in more than this
/// fraction of its texels is saturated.
pub const SATURATED_FRACTION: f64 = 0.5;
/// Side of the textures the texture refinement correlates.
const CORRELATION_SIZE: usize = 512;
/// Largest shift the texture refinement accepts, as a fraction of the
/// texture's side: the calibrated pose is good to a few texels.
const MAX_TEXTURE_SHIFT: f64 = 0.03;
/// A frame's texture is aligned only to a frame of its slot whose light is
/// at most this far from its own: beyond it a relief's shading differs too
/// much for the correlation to mean the same texture.
const MAX_REFERENCE_LIGHT_DEG: f64 = 20.0;
/// Marker-registered frames the texture refinement's error is measured on.
const TEXTURE_CHECKS: usize = 16;
/// An unusable frame is filled from this many nearest lights of its slot.
const FILL_NEIGHBOURS: usize = 3;

/// One frame after the first pass: its registration record and the two
/// homographies (markers, pose) it has.
struct FirstPass {
    /// The frame's position in the run's entries.
    position: usize,
    rec: FrameRegistration,
    markers: Option<rigd_process::rectify::Homography>,
    pose: Option<rigd_process::rectify::Homography>,
    /// The frame cannot be used at all (lost, black, saturated).
    unusable: bool,
    /// The frame's 99th-percentile value (fraction of full scale).
    p99: f32,
}

/// Everything the per-frame steps share.
struct Rectifier<'a> {
    run: &'a RunFrames,
    cfg: &'a RectifyConfig,
    holder: Holder,
    layout: rigd_process::rectify::MarkerLayout,
    out_dir: std::path::PathBuf,
}

impl Rectifier<'_> {
    /// The frame's camera at its achieved pose.
    fn camera(&self, entry: &crate::store::FrameEntry) -> Result<Camera, String> {
        let geometry = camera_geometry(
            &self.run.meta.profile,
            &entry.camera,
            [entry.width, entry.height],
        )
        .ok_or_else(|| format!("no camera `{}` in the run's profile", entry.camera))?;
        Ok(Camera::new(
            entry.achieved_view.to_vector(),
            [entry.width, entry.height],
            Some(geometry.focal_px),
            geometry.distance_m,
            1.1 * self.holder.half,
        ))
    }

    /// Marker registration, as Sattler et al. §3.2 does it.
    fn markers(
        &self,
        image: &Image,
        camera: &Camera,
        entry: &crate::store::FrameEntry,
    ) -> Result<rigd_process::rectify::Registration, String> {
        use rigd_process::rectify as rect;
        // Where the rig's pose says the markers are; the search finds them
        // around that.
        let predicted: Vec<Option<[f64; 2]>> = self
            .layout
            .points
            .iter()
            .map(|p| camera.project([p[0], p[1], 0.0]))
            .collect();
        let radius = (0.03 * f64::from(entry.width.max(entry.height))).max(6.0);
        let detections = rect::detect_markers(image, &predicted, radius, &Default::default())
            .map_err(|e| e.to_string())?;
        rect::register(&self.layout, &detections, &Default::default()).map_err(|e| e.to_string())
    }

    /// The sample square of `image` through `h` at `side` texels.
    fn sample_texture(
        &self,
        image: &Image,
        h: &rigd_process::rectify::Homography,
        side: usize,
    ) -> Result<rigd_process::rectify::Rectified, String> {
        rigd_process::rectify::rectify(
            image,
            h,
            self.layout.sample_region(),
            [side, side],
            &Default::default(),
        )
        .map_err(|e| e.to_string())
    }

    /// Rectifies, cuts, blends and stores a frame's texture through `h`;
    /// `Err` names why it cannot be used (saturated) or written.
    fn write_texture(
        &self,
        rec: &mut FrameRegistration,
        image: &Image,
        h: &rigd_process::rectify::Homography,
        bit_depth: u8,
    ) -> Result<(), String> {
        use rigd_process::rectify as rect;
        let cfg = self.cfg;
        let full = self.sample_texture(image, h, cfg.size)?;
        let saturated = full.texture.data.iter().filter(|&&v| v >= 0.995).count() as f64
            / full.texture.data.len().max(1) as f64;
        if saturated > SATURATED_FRACTION {
            return Err(format!(
                "saturated: {:.0} % of the sample at full scale",
                100.0 * saturated
            ));
        }
        rec.coverage = Some(full.coverage);
        let roi = rect::Roi::centred(cfg.size, cfg.size, cfg.roi);
        // With a blend the ROI is scaled to final + blend texels, whose
        // extra band is blended into the opposite edge.
        let side = cfg.final_size + cfg.blend;
        let texture = rect::roi_cut(&full.texture, roi, [side, side])
            .and_then(|t| rect::edge_blend(&t, cfg.blend))
            .map_err(|e| e.to_string())?;
        self.store(rec, &texture, bit_depth)
    }

    /// Writes a final texture in the configured encoding.
    fn store(
        &self,
        rec: &mut FrameRegistration,
        texture: &Image,
        bit_depth: u8,
    ) -> Result<(), String> {
        use rigd_process::image_io::{write_png, PngDepth};
        use rigd_process::rectify::{quantise, Quantisation};
        let name = format!("v{:03}_l{:03}", rec.view_slot, rec.light_index);
        let (shift, dtype) = match self.cfg.bits {
            TextureBits::Top8 => (Some(bit_depth.saturating_sub(8)), Dtype::F32),
            TextureBits::Shift(s) => (Some(s), Dtype::F32),
            TextureBits::Float => (None, Dtype::F32),
            TextureBits::Half => (None, Dtype::F16),
        };
        let file = match shift {
            Some(shift) => {
                let q = quantise(texture, bit_depth, Quantisation::Bits8 { shift })
                    .map_err(|e| e.to_string())?;
                let file = format!("{name}.png");
                write_png(&self.out_dir.join(&file), &q, PngDepth::Eight)
                    .map_err(|e| e.to_string())?;
                file
            }
            None => {
                let file = format!("{name}.npy");
                rigd_process::npy::write(
                    &self.out_dir.join(&file),
                    &[texture.height, texture.width],
                    &texture.data,
                    dtype,
                )
                .map_err(|e| e.to_string())?;
                file
            }
        };
        rec.file = Some(file);
        Ok(())
    }

    /// First pass over one frame: read it, reject it if black, register
    /// it by its markers (and write its texture) or keep its pose for the
    /// second pass.
    fn first_pass(&self, position: usize, view_slot: usize, light_index: usize) -> FirstPass {
        let entry = &self.run.entries[position];
        let mut out = FirstPass {
            position,
            rec: FrameRegistration::new(entry.index, view_slot, light_index),
            markers: None,
            pose: None,
            unusable: false,
            p99: 0.0,
        };
        let image = match self.run.image(entry) {
            Ok(image) => image,
            Err(e) => {
                out.rec.problem = Some(format!("lost: {e}"));
                out.unusable = true;
                return out;
            }
        };
        // Whether it is black is decided against its neighbours, later.
        out.p99 = percentile_f32(&image.data, 0.99);
        let camera = match self.camera(entry) {
            Ok(c) => c,
            Err(e) => {
                out.rec.problem = Some(e);
                out.unusable = true;
                return out;
            }
        };
        out.pose = rigd_process::rectify::pose_homography(
            |q| camera.project([q[0], q[1], 0.0]),
            rigd_process::rectify::Region::centred([self.holder.half, self.holder.half]),
        )
        .ok();
        match self.markers(&image, &camera, entry) {
            Ok(reg) => {
                out.rec.rms_px = Some(reg.rms_px);
                out.rec.max_px = Some(reg.max_px);
                out.rec.markers_found = reg.found;
                out.rec.markers_used = reg.used;
                out.rec.markers_rejected = reg.rejected.clone();
                match self.write_texture(&mut out.rec, &image, &reg.homography, entry.bit_depth) {
                    Ok(()) => {
                        out.rec.method = Some(RegistrationMethod::Markers);
                        out.rec.error_px = Some(reg.rms_px);
                        out.markers = Some(reg.homography);
                    }
                    Err(e) => {
                        out.rec.problem = Some(e);
                        out.unusable = true;
                    }
                }
            }
            Err(e) => {
                if out.pose.is_none() {
                    out.unusable = true;
                    out.rec.problem =
                        Some(format!("{e}; the pose puts the plate outside the frame"));
                } else {
                    out.rec.problem = Some(e);
                }
            }
        }
        out
    }

    /// The texture of a marker-registered reference frame at the
    /// correlation size.
    fn reference_texture(&self, first: &FirstPass) -> Option<Image> {
        let entry = self.run.entries.get(first.position)?;
        let image = self.run.image(entry).ok()?;
        let side = CORRELATION_SIZE.min(self.cfg.size);
        Some(
            self.sample_texture(&image, first.markers.as_ref()?, side)
                .ok()?
                .texture,
        )
    }

    /// The pose homography with the holder offset, refined by the texture
    /// against `reference` when that finds a clear match.
    fn pose_registration(
        &self,
        image: &Image,
        pose: &rigd_process::rectify::Homography,
        offset: [f64; 2],
        reference: Option<&Image>,
    ) -> (rigd_process::rectify::Homography, RegistrationMethod) {
        use rigd_process::rectify as rect;
        let calibrated = rect::shift_plate(pose, offset);
        let Some(reference) = reference else {
            return (calibrated, RegistrationMethod::Pose);
        };
        let side = reference.width;
        let Ok(moving) = self.sample_texture(image, &calibrated, side) else {
            return (calibrated, RegistrationMethod::Pose);
        };
        match rect::texture_shift(reference, &moving.texture, MAX_TEXTURE_SHIFT * side as f64) {
            Ok(Some(shift)) => {
                let region = self.layout.sample_region();
                let tx = (region.x_max - region.x_min) / side as f64;
                let ty = (region.y_max - region.y_min) / side as f64;
                // Texture +x is plate +x, texture +y (rows) is plate −y.
                let e = [shift.dx * tx, -shift.dy * ty];
                (
                    rect::shift_plate(&calibrated, e),
                    RegistrationMethod::PoseTexture,
                )
            }
            _ => (calibrated, RegistrationMethod::Pose),
        }
    }
}

/// The `q`-quantile of finite values (0 if none).
fn percentile_f32(values: &[f32], q: f64) -> f32 {
    let mut v: Vec<f32> = values.iter().copied().filter(|v| v.is_finite()).collect();
    if v.is_empty() {
        return 0.0;
    }
    let k = ((v.len() - 1) as f64 * q).round() as usize;
    let (_, nth, _) = v.select_nth_unstable_by(k, f32::total_cmp);
    *nth
}

/// Median, 95th percentile and maximum of `values` (None if empty).
fn spread(values: &[f64]) -> Option<[f64; 3]> {
    let mut v: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    Some([at(0.5), at(0.95), at(1.0)])
}

/// Registers every frame of a run and resamples the sample square to a
/// frontal texture, then writes the textures and
/// `processed/normtextures/index.json`. It never gives up on the dataset
/// for a few bad frames:
/// - a frame is registered by its holder markers where they are found
///   (`markers`);
/// - otherwise from the rig's achieved pose through the camera model,
///   corrected by the holder's offset that the marker-registered frames
///   measure (`pose`), and shifted onto a marker-registered frame of the
///   same view slot by the sample's texture where that finds a clear match
///   (`pose+texture`);
/// - a frame that is lost, black or saturated is filled from its view
///   slot's nearest lights (`interpolated`).
///
/// Each frame records its method and an error estimate. The call fails
/// only when a whole view slot has no usable frame, naming it and why
/// (after every other texture and the index are written).
pub fn rectify_run(
    run: &RunFrames,
    cfg: &RectifyConfig,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<NormtextureIndex, ProcessError> {
    use rayon::prelude::*;
    use rigd_process::rectify::{self as rect, MarkerLayout};
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
        points,
        radius_m: holder.point_radius,
        sample_half,
    };
    let out_dir = crate::store::processed::normtextures_dir(&run.root);
    std::fs::create_dir_all(&out_dir).map_err(|e| ProcessError::Frame {
        path: out_dir.clone(),
        message: e.to_string(),
    })?;
    let region = layout.sample_region();
    let rectifier = Rectifier {
        run,
        cfg,
        holder,
        layout,
        out_dir: out_dir.clone(),
    };
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
    let tick = || {
        let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        progress(n.min(total), total);
    };
    let bit_depth = run.entries.first().map_or(8, |e| e.bit_depth);

    // 1. Markers, where they are found.
    let mut first: Vec<FirstPass> = slots
        .par_iter()
        .enumerate()
        .map(|(position, &(view_slot, light_index))| {
            let f = rectifier.first_pass(position, view_slot, light_index);
            // Progress follows this pass, which reads every frame; the
            // fallbacks after it are a few frames in a healthy run.
            tick();
            f
        })
        .collect();

    // 2. Black frames, against their slot's nearest lights.
    let black: Vec<(usize, f32)> = (0..first.len())
        .filter(|&i| !first[i].unusable && first[i].p99 < BLACK_P99)
        .filter_map(|i| {
            let own = lights[first[i].rec.light_index].to_vector();
            let mut near: Vec<(f64, f32)> = first
                .iter()
                .enumerate()
                .filter(|(j, f)| {
                    *j != i && f.rec.view_slot == first[i].rec.view_slot && !f.unusable
                })
                .map(|(_, f)| {
                    let l = lights[f.rec.light_index].to_vector();
                    (-(own[0] * l[0] + own[1] * l[1] + own[2] * l[2]), f.p99)
                })
                .collect();
            near.sort_by(|a, b| a.0.total_cmp(&b.0));
            let reference = near
                .iter()
                .take(2)
                .map(|n| n.1)
                .fold(f32::INFINITY, f32::min);
            let p99 = first[i].p99;
            let black =
                p99 < BLACK_FLOOR || (reference.is_finite() && p99 < BLACK_RATIO * reference);
            black.then_some((i, reference))
        })
        .collect();
    for (i, reference) in black {
        let f = &mut first[i];
        f.unusable = true;
        f.markers = None;
        f.rec.file = None;
        f.rec.method = None;
        f.rec.error_px = None;
        f.rec.problem = Some(if reference.is_finite() {
            format!(
                "black: its 99th percentile is {:.2} % of full scale, its slot's nearest lights reach {:.2} %",
                100.0 * f.p99,
                100.0 * reference
            )
        } else {
            format!(
                "black: its 99th percentile is {:.2} % of full scale",
                100.0 * f.p99
            )
        });
    }

    // 3. The holder's offset from the pose model, measured where both
    // exist; marker fits too few to reveal an outlier that land far from
    // the calibrated pose are not trusted, and the offset is fitted again
    // without them.
    let pairs_of = |first: &[FirstPass]| -> Vec<(usize, rect::Homography, rect::Homography)> {
        first
            .iter()
            .enumerate()
            .filter_map(|(i, f)| Some((i, f.pose?, f.markers?)))
            .collect()
    };
    let fit = |pairs: &[(usize, rect::Homography, rect::Homography)]| {
        let hs: Vec<(rect::Homography, rect::Homography)> =
            pairs.iter().map(|(_, p, m)| (*p, *m)).collect();
        rect::fit_plate_offset(&hs, region).unwrap_or([0.0, 0.0])
    };
    // First from the fits that could reject an outlier, if there are any.
    let all_pairs = pairs_of(&first);
    let trusted: Vec<_> = all_pairs
        .iter()
        .filter(|(i, _, _)| first[*i].rec.markers_used >= rigd_process::rectify::MIN_FOR_REJECTION)
        .cloned()
        .collect();
    let first_offset = fit(if trusted.is_empty() {
        &all_pairs
    } else {
        &trusted
    });
    let disagreements: Vec<(usize, f64)> = all_pairs
        .iter()
        .filter_map(|(i, p, m)| {
            Some((
                *i,
                rect::disagreement_px(&rect::shift_plate(p, first_offset), m, region)?,
            ))
        })
        .collect();
    let median_disagreement = spread(
        &disagreements
            .iter()
            .filter(|(i, _)| trusted.is_empty() || trusted.iter().any(|t| t.0 == *i))
            .map(|d| d.1)
            .collect::<Vec<_>>(),
    )
    .map_or(0.0, |s| s[0]);
    let doubt = MARKER_DOUBT_PX.max(MARKER_DOUBT_FACTOR * median_disagreement);
    for &(i, d) in &disagreements {
        let f = &mut first[i];
        if d > doubt && f.rec.markers_used < rigd_process::rectify::MIN_FOR_REJECTION {
            f.markers = None;
            f.rec.method = None;
            f.rec.error_px = None;
            f.rec.problem = Some(format!(
                "the markers' fit lands {d:.1} px from the calibrated pose at the sample, and {} markers cannot reveal an outlier",
                f.rec.markers_used
            ));
        }
    }
    let pairs = pairs_of(&first);
    let offset = fit(&pairs);
    let both: Vec<(&rect::Homography, &rect::Homography)> =
        pairs.iter().map(|(_, p, m)| (p, m)).collect();
    let p95_against_markers = |shift: [f64; 2]| {
        let d: Vec<f64> = both
            .iter()
            .filter_map(|(p, m)| rect::disagreement_px(&rect::shift_plate(p, shift), m, region))
            .collect();
        spread(&d).map(|s| s[1])
    };
    let pose_error_px = p95_against_markers(offset);
    let uncalibrated_pose_error_px = p95_against_markers([0.0, 0.0]);

    // 4. The marker-registered frame each frame's texture is aligned to:
    // the one of its view slot with the nearest light, whose shading is
    // most alike (under lights far apart a relief's bright flanks swap
    // sides, and the correlation would lock on to that).
    let reference_of = |i: usize| -> Option<usize> {
        let own = lights[first[i].rec.light_index].to_vector();
        (0..first.len())
            .filter(|&j| j != i && first[j].markers.is_some())
            .filter(|&j| first[j].rec.view_slot == first[i].rec.view_slot)
            .map(|j| {
                let l = lights[first[j].rec.light_index].to_vector();
                (own[0] * l[0] + own[1] * l[1] + own[2] * l[2], j)
            })
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .filter(|(cos, _)| *cos >= MAX_REFERENCE_LIGHT_DEG.to_radians().cos())
            .map(|(_, j)| j)
    };
    let needs_pose: Vec<usize> = (0..first.len())
        .filter(|&i| first[i].markers.is_none() && !first[i].unusable)
        .collect();
    // The texture refinement's own error, measured on marker-registered
    // frames spread over the run.
    let checks: Vec<usize> = {
        let candidates: Vec<usize> = (0..first.len())
            .filter(|&i| first[i].markers.is_some() && first[i].pose.is_some())
            .collect();
        let step = (candidates.len() / TEXTURE_CHECKS).max(1);
        candidates
            .into_iter()
            .step_by(step)
            .take(TEXTURE_CHECKS)
            .collect()
    };
    let refine = |i: usize, image: &Image| {
        let reference = reference_of(i).and_then(|r| rectifier.reference_texture(&first[r]));
        let pose = first[i].pose.unwrap_or([[0.0; 3]; 3]);
        rectifier.pose_registration(image, &pose, offset, reference.as_ref())
    };
    let texture_errors: Vec<f64> = checks
        .par_iter()
        .filter_map(|&i| {
            let f = &first[i];
            let image = run.image(&run.entries[i]).ok()?;
            let (h, method) = refine(i, &image);
            (method == RegistrationMethod::PoseTexture)
                .then(|| rect::disagreement_px(&h, f.markers.as_ref()?, region))
                .flatten()
        })
        .collect();
    let pose_texture_error_px = spread(&texture_errors).map(|s| s[1]);
    // The run's own frames say whether the texture helps: only if it lands
    // nearer the markers than the calibrated pose does.
    let texture_helps = matches!(
        (pose_texture_error_px, pose_error_px),
        (Some(t), Some(p)) if t < p
    );
    let refine = |i: usize, image: &Image| {
        if texture_helps {
            refine(i, image)
        } else {
            let pose = first[i].pose.unwrap_or([[0.0; 3]; 3]);
            (rect::shift_plate(&pose, offset), RegistrationMethod::Pose)
        }
    };

    // 5. The rest from their pose.
    let pose_results: Vec<(usize, FrameRegistration, bool)> = needs_pose
        .par_iter()
        .map(|&i| {
            let f = &first[i];
            let mut rec = f.rec.clone();
            let mut usable = false;
            let entry = &run.entries[i];
            match run.image(entry) {
                Err(e) => rec.problem = Some(format!("lost: {e}")),
                Ok(image) => {
                    let (h, method) = refine(i, &image);
                    match rectifier.write_texture(&mut rec, &image, &h, entry.bit_depth) {
                        Ok(()) => {
                            rec.method = Some(method);
                            rec.error_px = match method {
                                RegistrationMethod::PoseTexture => pose_texture_error_px,
                                _ => pose_error_px,
                            };
                            usable = true;
                        }
                        Err(e) => rec.problem = Some(e),
                    }
                }
            }
            (i, rec, usable)
        })
        .collect();
    for (i, rec, usable) in pose_results {
        first[i].rec = rec;
        first[i].unusable = !usable;
    }

    // 6. Unusable frames from their slot's nearest usable lights.
    let mut frames: Vec<FrameRegistration> = first.into_iter().map(|f| f.rec).collect();
    let index_so_far = NormtextureIndex {
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
        frames: frames.clone(),
        summary: None,
    };
    type Filled = Result<(Option<String>, Vec<usize>), String>;
    let fills: Vec<(usize, Filled)> = (0..frames.len())
        .into_par_iter()
        .filter(|&i| frames[i].file.is_none())
        .map(|i| {
            let mut rec = frames[i].clone();
            let result = fill_from_neighbours(&rectifier, &index_so_far, &mut rec, &lights)
                .map(|from| (rec.file, from));
            (i, result)
        })
        .collect();
    let mut failed_slots: std::collections::BTreeMap<usize, Vec<String>> = Default::default();
    for (i, result) in fills {
        let rec = &mut frames[i];
        match result {
            Ok((file, from)) => {
                rec.file = file;
                rec.method = Some(RegistrationMethod::Interpolated);
                rec.interpolated_from = from;
                rec.coverage = None;
            }
            Err(e) => {
                rec.error = Some(format!(
                    "{}; {e}",
                    rec.problem.clone().unwrap_or_else(|| "unusable".into())
                ));
                failed_slots.entry(rec.view_slot).or_default().push(format!(
                    "frame {}: {}",
                    rec.index,
                    rec.problem.as_deref().unwrap_or("unusable")
                ));
            }
        }
    }

    let mut by_method: std::collections::BTreeMap<String, usize> = Default::default();
    for f in &frames {
        if let Some(m) = f.method {
            *by_method.entry(m.name().to_string()).or_default() += 1;
        }
    }
    let marker_rms: Vec<f64> = frames
        .iter()
        .filter(|f| f.method == Some(RegistrationMethod::Markers))
        .filter_map(|f| f.rms_px)
        .collect();
    let summary = RegistrationSummary {
        frames_by_method: by_method,
        frames_without_texture: frames.iter().filter(|f| f.file.is_none()).count(),
        marker_rms_px: spread(&marker_rms),
        holder_offset_mm: (!pairs.is_empty()).then(|| offset.map(|v| v * 1e3)),
        uncalibrated_pose_error_px,
        pose_error_px,
        pose_texture_error_px,
        pose_texture_checked: texture_errors.len(),
    };
    let index = NormtextureIndex {
        frames,
        summary: Some(summary),
        ..index_so_far
    };
    let path = out_dir.join(NORMTEXTURE_INDEX);
    let mut json =
        serde_json::to_vec_pretty(&index).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    crate::store::write_atomic(&path, &json)?;
    if !failed_slots.is_empty() {
        let described: Vec<String> = failed_slots
            .iter()
            .take(5)
            .map(|(slot, why)| {
                let v = index.views[*slot];
                format!(
                    "view slot {slot} (θ {:.1}°, φ {:.1}°): no usable frame ({}{})",
                    v.theta_deg,
                    v.phi_deg,
                    why.iter().take(2).cloned().collect::<Vec<_>>().join("; "),
                    if why.len() > 2 { "; …" } else { "" }
                )
            })
            .collect();
        return Err(ProcessError::Invalid(format!(
            "{} of {} view slots have no usable frame (listed in {}): {}{}",
            failed_slots.len(),
            index.views.len(),
            path.display(),
            described.join("; "),
            if failed_slots.len() > 5 { "; …" } else { "" }
        )));
    }
    Ok(index)
}

/// Fills an unusable frame's texture with the inverse-angle-weighted mean
/// of the [`FILL_NEIGHBOURS`] nearest usable lights of its view slot, in
/// the index's encoding; returns their image indices.
fn fill_from_neighbours(
    rectifier: &Rectifier<'_>,
    index: &NormtextureIndex,
    rec: &mut FrameRegistration,
    lights: &[Direction],
) -> Result<Vec<usize>, String> {
    let own = lights[rec.light_index].to_vector();
    let mut neighbours: Vec<(f64, &FrameRegistration)> = index
        .frames
        .iter()
        .filter(|f| {
            f.view_slot == rec.view_slot
                && f.file.is_some()
                && f.method != Some(RegistrationMethod::Interpolated)
        })
        .map(|f| {
            let l = lights[f.light_index].to_vector();
            let cos = (own[0] * l[0] + own[1] * l[1] + own[2] * l[2]).clamp(-1.0, 1.0);
            (cos.acos(), f)
        })
        .collect();
    if neighbours.is_empty() {
        return Err("no usable frame in its view slot to fill it from".into());
    }
    neighbours.sort_by(|a, b| a.0.total_cmp(&b.0));
    neighbours.truncate(FILL_NEIGHBOURS);
    let mut sum: Option<Image> = None;
    let mut weights = 0.0;
    for (angle, f) in &neighbours {
        let tex = index
            .load(&rectifier.run.root, f.view_slot, f.light_index)
            .map_err(|e| e.to_string())?;
        // Same light twice (a repeated direction) counts fully.
        let w = 1.0 / angle.max(1e-3);
        weights += w;
        let acc = sum.get_or_insert_with(|| Image::new(tex.width, tex.height, tex.channels));
        for (a, v) in acc.data.iter_mut().zip(&tex.data) {
            *a += (w as f32) * v;
        }
    }
    let mut mean = sum.ok_or("no neighbour texture")?;
    for v in &mut mean.data {
        *v /= weights as f32;
    }
    // Stored values are already quantised: store them as they are (an
    // 8-bit code / 255 is written back as that code).
    let bits = if index.encoding == "png8" {
        8
    } else {
        index.bit_depth
    };
    let saved = rectifier.cfg.bits;
    let store_as = match saved {
        TextureBits::Float | TextureBits::Half => saved,
        TextureBits::Top8 | TextureBits::Shift(_) => TextureBits::Shift(0),
    };
    let cfg = RectifyConfig {
        bits: store_as,
        ..*rectifier.cfg
    };
    let local = Rectifier {
        run: rectifier.run,
        cfg: &cfg,
        holder: rectifier.holder.clone(),
        layout: rectifier.layout.clone(),
        out_dir: rectifier.out_dir.clone(),
    };
    local.store(rec, &mean, bits)?;
    Ok(neighbours.iter().map(|(_, f)| f.index).collect())
}
