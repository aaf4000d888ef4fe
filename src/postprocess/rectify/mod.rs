//! Registration and rectification of a run's frames into normtextures
//! (Sattler et al., §3.2).

use std::path::Path;

use rigd_core::geometry::Direction;
use rigd_core::holder::Holder;
use rigd_process::image_io::Image;
use serde::Serialize;

use super::frames::RunFrames;
use super::ProcessError;
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

impl TextureBits {
    /// Parses `top`, a shift `0` … `8`, `float` or `half`.
    pub fn parse(s: &str) -> Result<TextureBits, String> {
        match s {
            "top" => Ok(TextureBits::Top8),
            "float" => Ok(TextureBits::Float),
            "half" => Ok(TextureBits::Half),
            s => match s.parse::<u8>() {
                Ok(shift) if shift <= 8 => Ok(TextureBits::Shift(shift)),
                _ => Err(format!(
                    "bits `{s}`: expected `top`, a shift 0 ..= 8, `float` or `half`"
                )),
            },
        }
    }
}

impl RectifyConfig {
    /// The settings a run's frames are rectified with. A run whose steps
    /// take several exposures has highlights above its first exposure's
    /// full scale, which an 8-bit texture of the top bits would clip:
    /// its textures are float instead (a shift asked for is kept).
    pub fn for_run(&self, meta: &crate::store::RunMeta) -> RectifyConfig {
        let mut cfg = *self;
        if cfg.bits == TextureBits::Top8 && !meta.exposure_policy.is_single() {
            cfg.bits = TextureBits::Float;
        }
        cfg
    }

    /// The one check of these sizes, for `rigd process rectify`, `rigd run
    /// --process` and the daemon's jobs alike, before any frame is read:
    /// the error names the option and its range.
    pub fn check(&self) -> Result<(), String> {
        for (name, v) in [("size", self.size), ("final", self.final_size)] {
            if !(MIN_TEXTURE_SIDE..=MAX_TEXTURE_SIDE).contains(&v) {
                return Err(format!(
                    "{name} {v}: expected {MIN_TEXTURE_SIDE} … {MAX_TEXTURE_SIDE} texels"
                ));
            }
        }
        if self.final_size > self.size {
            return Err(format!(
                "final {}: expected at most the size {} it is resampled from",
                self.final_size, self.size
            ));
        }
        if !(self.roi.is_finite() && self.roi > 0.0 && self.roi <= 1.0) {
            return Err(format!("roi {}: expected 0 < roi ≤ 1", self.roi));
        }
        if self.blend >= self.final_size {
            return Err(format!(
                "blend {}: an edge blend must be narrower than the {}-texel texture",
                self.blend, self.final_size
            ));
        }
        Ok(())
    }
}

/// The smallest side of a normtexture or stored texture, texels.
pub const MIN_TEXTURE_SIDE: usize = 4;
/// The largest side of a normtexture or stored texture, texels.
pub const MAX_TEXTURE_SIDE: usize = 8192;

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
    /// The frame failed its SHA-256 check: its file is not what was
    /// measured (damaged on disk, or another frame's file). It is never
    /// registered; its texture, if any, is filled from its slot's nearest
    /// lights (`interpolated`), and `problem` says what was found.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub damaged: bool,
    /// The lamp's output in this frame relative to the run's first frame
    /// whose white reference areas are seen, as the holder's white areas
    /// measure it; the texture is divided by it. None when the holder has
    /// no white areas or they are not seen in this frame (the texture is
    /// then as measured).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lamp_level: Option<f64>,
    /// Texels of the texture that read a pixel the sensor clipped
    /// ([`crate::postprocess::frames::Clipped`]): their values are lower
    /// bounds, not measurements. 0 when none did.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub clipped_texels: usize,
    /// `clipped_texels` as a fraction of the texture's texels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clipped_share: Option<f64>,
    /// Which texels: an 8-bit PNG the texture's size, 255 where clipped,
    /// relative to the normtextures folder; None when none is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clipped_mask: Option<String>,
    /// The frame's exposures, seconds, in the order taken, when its step
    /// took more than one (merged into its texture, scaled to the first);
    /// absent for one.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub exposures_s: Vec<f64>,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
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
    /// The frame is unusable (lost, damaged, black, saturated): its texture
    /// is the mean of its view slot's nearest lights, weighted by inverse
    /// angle.
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
            damaged: false,
            lamp_level: None,
            clipped_texels: 0,
            clipped_share: None,
            clipped_mask: None,
            exposures_s: Vec::new(),
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
    /// Fraction of the sample's side the textures cover (`rectify --roi`);
    /// None for an index written before rigd recorded it, or imported.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub roi: Option<f64>,
    /// Values per texel: 1 (grey) or 3 (RGB, linear sRGB, corrected by
    /// the run's `processed/colour.json`).
    #[serde(default = "one_channel")]
    pub channels: usize,
}

fn one_channel() -> usize {
    1
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
    /// Frames that failed their SHA-256 check (`damaged` in `frames`),
    /// none of them registered; they are counted under their method too.
    #[serde(default)]
    pub frames_damaged: usize,
    /// Their image indices.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub damaged: Vec<usize>,
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
    /// Frames whose first pass came from an earlier run of the step that
    /// was cut short (not registered again).
    #[serde(default)]
    pub resumed_frames: usize,
    /// Frames with texels that read a pixel the sensor clipped.
    #[serde(default)]
    pub frames_clipped: usize,
    /// Those texels, over all frames.
    #[serde(default)]
    pub clipped_texels: usize,
    /// The frames with the largest shares clipped, largest first (at most
    /// [`CLIPPED_LISTED`]): where the highlights are.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub most_clipped: Vec<ClippedFrame>,
}

/// Frames [`RegistrationSummary::most_clipped`] lists.
pub const CLIPPED_LISTED: usize = 5;

/// A frame with clipped texels, and its directions.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct ClippedFrame {
    /// The frame's image index.
    pub index: usize,
    /// The share of its texture's texels clipped.
    pub share: f64,
    /// Its commanded light direction.
    pub light: Direction,
    /// Its commanded view direction.
    pub view: Direction,
}

impl RegistrationSummary {
    /// The summary as the table `rigd process rectify` prints.
    pub fn table(&self) -> String {
        use std::fmt::Write;
        let mut out = String::from("method         frames\n");
        for (m, n) in &self.frames_by_method {
            let _ = writeln!(out, "{m:<14} {n:>6}");
        }
        if self.resumed_frames > 0 {
            let _ = writeln!(
                out,
                "{} frames taken from an interrupted run of this step",
                self.resumed_frames
            );
        }
        if self.frames_without_texture > 0 {
            let _ = writeln!(
                out,
                "{:<14} {:>6}",
                "no texture", self.frames_without_texture
            );
        }
        if self.frames_damaged > 0 {
            let _ = writeln!(
                out,
                "{:<14} {:>6}  {} failed the SHA-256 check against the journal: not registered, filled from their slot's nearest lights",
                "damaged",
                self.frames_damaged,
                crate::store::image_list(&self.damaged)
            );
        }
        if self.frames_clipped > 0 {
            let _ = writeln!(
                out,
                "clipped: {} texels in {} frames read a pixel at the sensor's white level (flagged \
                 per frame in index.json, clipped_texels and clipped_mask); most in:",
                self.clipped_texels, self.frames_clipped
            );
            for f in &self.most_clipped {
                let _ = writeln!(
                    out,
                    "  image {:>6}  {:>6.2} %  light θ {:.1}° φ {:.1}°, view θ {:.1}° φ {:.1}°",
                    f.index,
                    100.0 * f.share,
                    f.light.theta_deg,
                    f.light.phi_deg,
                    f.view.theta_deg,
                    f.view.phi_deg
                );
            }
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
    /// Refuses view slots `slots` beyond the index's (a part of a cluster's
    /// job array given a range from another run).
    pub fn check_slot_range(&self, slots: &std::ops::Range<usize>) -> Result<(), ProcessError> {
        if slots.end > self.views.len() {
            return Err(ProcessError::Invalid(format!(
                "view slots {}..{}: the run has {}",
                slots.start,
                slots.end,
                self.views.len()
            )));
        }
        Ok(())
    }

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
            let channels = a.shape.get(2).copied().unwrap_or(1);
            if a.data.len() != w * h * channels {
                return Err(frame_err(format!(
                    "shape {:?} does not hold its values",
                    a.shape
                )));
            }
            let mut img = Image::new(w, h, channels);
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
/// (metres): the one its recorded profile describes, simulated or not.
pub(crate) fn holder_of(meta: &RunMeta) -> Result<(Holder, [f64; 2]), ProcessError> {
    let holder = meta.profile.holder.holder().map_err(|e| {
        ProcessError::Invalid(format!(
            "the run's profile describes a holder that cannot work: {e}"
        ))
    })?;
    let half = holder.sample_half;
    Ok((holder, half))
}

/// A frame's plate → image homography from its holder's point markers, as
/// `rigd process rectify` registers it, for steps that read the holder
/// itself (the colour patches). `image` is the frame as
/// [`RunFrames::image`] reads it.
pub(crate) fn register_by_markers(
    run: &RunFrames,
    entry: &crate::store::FrameEntry,
    image: &Image,
) -> Result<rigd_process::rectify::Homography, String> {
    let (holder, layout) = run::holder_layout(&run.meta).map_err(|e| e.to_string())?;
    let cfg = RectifyConfig::default();
    let rectifier = steps::Rectifier {
        run,
        cfg: &cfg,
        holder,
        layout,
        out_dir: std::path::PathBuf::new(),
        colour: None,
        lamp: None,
    };
    let camera = rectifier.camera(entry)?;
    Ok(rectifier.markers(image, &camera)?.homography)
}

/// Largest marker blob accepted, as a multiple of the largest disc area
/// the pose predicts (blur, the holder offset and the scale's error fit in
/// it many times over).
const MARKER_AREA_MARGIN: f64 = 6.0;
/// The bound never falls below this many pixels (tiny frames).
const MIN_MARKER_AREA_BOUND_PX: f64 = 64.0;

/// The holder's point markers as registration fits them: their centres
/// and, bounding the blobs accepted, the largest disc's radius.
pub(crate) fn marker_layout(holder: &Holder) -> rigd_process::rectify::MarkerLayout {
    rigd_process::rectify::MarkerLayout {
        points: holder.points.iter().map(|p| p.position).collect(),
        radius_m: holder.points.iter().map(|p| p.radius).fold(0.0, f64::max),
        sample_half: holder.sample_half,
    }
}

/// The camera model of `profile`'s camera `camera` looking from `view` at
/// a frame of `size` pixels, as the rig's pose predicts it (`focal_px`, if
/// given, instead of the profile's focal length); None if the profile has
/// no such camera or no intrinsics for it.
pub(crate) fn pose_camera(
    profile: &crate::model::profile::Profile,
    camera: &str,
    size: [u32; 2],
    view: Direction,
    holder: &Holder,
    focal_px: Option<f64>,
) -> Option<rigd_core::camera::Camera> {
    let geometry = crate::kinematics::camera::camera_geometry(profile, camera, size)?;
    Some(rigd_core::camera::Camera::new(
        view.to_vector(),
        size,
        Some(focal_px.unwrap_or(geometry.focal_px)),
        geometry.distance_m,
        1.1 * holder.half,
    ))
}

/// Where a frame's holder markers are predicted and found.
pub(crate) struct MarkerSearch {
    /// Per marker, where the camera model puts it, pixels; None behind
    /// the camera.
    pub(crate) predicted: Vec<Option<[f64; 2]>>,
    /// Per marker, the blob found around the prediction, if any.
    pub(crate) detections: Vec<Option<rigd_process::rectify::Detection>>,
}

/// Looks for each of `holder`'s point markers (light or dark) around where
/// `camera` puts it: the search every registration by markers makes, in
/// `rigd process rectify`, `rigd process colour` and `rigd holder check`.
pub(crate) fn find_markers(
    holder: &Holder,
    layout: &rigd_process::rectify::MarkerLayout,
    image: &Image,
    camera: &rigd_core::camera::Camera,
) -> Result<MarkerSearch, rigd_process::rectify::RectifyError> {
    use rigd_process::rectify as rect;
    // Where the rig's pose says the markers are; the search finds them
    // around that.
    let predicted: Vec<Option<[f64; 2]>> = layout
        .points
        .iter()
        .map(|p| camera.project([p[0], p[1], 0.0]))
        .collect();
    let radius = (0.03 * image.width.max(image.height) as f64).max(6.0);
    // Blobs are accepted up to a few times the largest disc the pose
    // predicts, not the default's fixed 5000 px: the search window's
    // margin grows with that bound, and on a small textured frame the
    // fixed bound made each window most of the frame.
    let r = layout.radius_m;
    let predicted_area = layout
        .points
        .iter()
        .filter_map(|p| {
            let c = camera.project([p[0], p[1], 0.0])?;
            let a = camera.project([p[0] + r, p[1], 0.0])?;
            let b = camera.project([p[0], p[1] + r, 0.0])?;
            let (da, db) = ([a[0] - c[0], a[1] - c[1]], [b[0] - c[0], b[1] - c[1]]);
            Some(std::f64::consts::PI * (da[0] * db[1] - da[1] * db[0]).abs())
        })
        .fold(0.0, f64::max);
    let defaults = rect::DetectOptions::default();
    let opts = rect::DetectOptions {
        max_area_px: (MARKER_AREA_MARGIN * predicted_area)
            .clamp(MIN_MARKER_AREA_BOUND_PX, defaults.max_area_px),
        ..defaults
    };
    let dark: Vec<bool> = holder
        .points
        .iter()
        .map(|p| p.polarity == rigd_core::holder::Polarity::Dark)
        .collect();
    let parts = holder_image::HolderImage::new(holder, camera);
    let detections =
        rect::detect_markers_where(image, &predicted, &dark, radius, &opts, |i, c| {
            parts.belongs_to_marker(i, c)
        })?;
    Ok(MarkerSearch {
        predicted,
        detections,
    })
}

pub mod colour;
mod holder_image;
mod lamp;
mod part;
mod resume;
mod run;
mod steps;
mod stream;
pub use part::first_pass_range;
pub use run::rectify_run;
pub use steps::{
    BLACK_FLOOR, BLACK_P99, BLACK_RATIO, FILL_NEIGHBOURS, MARKER_DOUBT_FACTOR, MARKER_DOUBT_PX,
    SATURATED_FRACTION,
};
pub use stream::{RectifyStream, StreamProgress};
