//! The per-frame steps of `rigd process rectify`: reading a frame,
//! registering it by its markers or from the pose (with the texture
//! refinement), storing its texture, and filling an unusable one from its
//! neighbours. [`super::rectify_run`] orders them over the run.

use rigd_core::camera::Camera;
use rigd_core::geometry::Direction;
use rigd_core::holder::Holder;
use rigd_process::image_io::Image;
use rigd_process::npy::Dtype;

use super::{FrameRegistration, NormtextureIndex, RectifyConfig, RegistrationMethod, TextureBits};
use crate::postprocess::frames::RunFrames;

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
/// tens of pixels off at the sample (measured on the demo H1), and four,
/// which fit exactly and show no residual at all, landed 2.8 px off (the
/// median) on a lab's plate whose pose was right to 0.2 px.
pub const MARKER_DOUBT_PX: f64 = 1.0;
/// See [`MARKER_DOUBT_PX`].
pub const MARKER_DOUBT_FACTOR: f64 = 3.0;
/// A frame whose sample texture is at full scale in more than this
/// fraction of its texels is saturated.
pub const SATURATED_FRACTION: f64 = 0.5;
/// Frames, from the run's first, in which the lamp's reference level is
/// looked for; a holder whose white areas none of them sees is not
/// corrected for the lamp.
pub(super) const LAMP_REFERENCE_CANDIDATES: usize = 16;
/// Side of the textures the texture refinement correlates.
pub(super) const CORRELATION_SIZE: usize = 512;
/// Largest shift the texture refinement accepts, as a fraction of the
/// texture's side: the calibrated pose is good to a few texels.
pub(super) const MAX_TEXTURE_SHIFT: f64 = 0.03;
/// A frame's texture is aligned only to a frame of its slot whose light is
/// at most this far from its own: beyond it a relief's shading differs too
/// much for the correlation to mean the same texture.
pub(super) const MAX_REFERENCE_LIGHT_DEG: f64 = 20.0;
/// Marker-registered frames the texture refinement's error is measured on.
pub(super) const TEXTURE_CHECKS: usize = 16;
/// An unusable frame, or a texel that clipped, is filled from this many
/// nearest lights of its slot.
pub const FILL_NEIGHBOURS: usize = 3;
/// A texel whose resampled clip mask exceeds this read a clipped pixel
/// (the mask is 0 or 1 before resampling; this is above float noise).
const CLIPPED_WEIGHT: f32 = 1e-4;

/// One frame after the first pass: its registration record and the two
/// homographies (markers, pose) it has.
pub(super) struct FirstPass {
    /// The frame's position in the run's entries.
    pub(super) position: usize,
    pub(super) rec: FrameRegistration,
    pub(super) markers: Option<rigd_process::rectify::Homography>,
    pub(super) pose: Option<rigd_process::rectify::Homography>,
    /// The frame cannot be used at all (lost, black, saturated).
    pub(super) unusable: bool,
    /// The frame's 99th-percentile value (fraction of full scale).
    pub(super) p99: f32,
}

/// Everything the per-frame steps share.
pub(super) struct Rectifier<'a> {
    pub(super) run: &'a RunFrames,
    pub(super) cfg: &'a RectifyConfig,
    pub(super) holder: Holder,
    pub(super) layout: rigd_process::rectify::MarkerLayout,
    pub(super) out_dir: std::path::PathBuf,
    /// The run's colour calibration (`rigd process colour`): textures are
    /// then RGB, corrected by it; `None`: grey.
    pub(super) colour: Option<rigd_process::colour::ColourCalibration>,
    /// The lamp meter of a holder with white areas and the lamp's output
    /// in the run's first frame that sees them: each frame is divided by
    /// its lamp's output relative to that ([`Rectifier::with_lamp`]).
    pub(super) lamp: Option<(super::lamp::LampMeter, f64)>,
}

/// A frame as rectification reads it: what its texture is made of, and
/// grey for registering it.
pub(super) struct FrameImages {
    /// Colour-corrected RGB with a colour calibration, else grey.
    pub(super) texture: Image,
    /// When `texture` is RGB, the greys it is registered by: the sensor's,
    /// as an uncalibrated frame's, for the markers
    /// ([`crate::postprocess::frames::CorrectedFrame::grey`]), and the
    /// texture's own luminance, for the texture alignment (the colour
    /// demosaic aliases a textile's weave less than the bilinear one).
    rgb_greys: Option<RgbGreys>,
    /// The lamp's output relative to the run's reference frame, which
    /// both images have been divided by; `None`: not measured.
    pub(super) lamp_level: Option<f64>,
    /// The pixels the sensor clipped; `None`: none.
    pub(super) clipped: Option<crate::postprocess::frames::Clipped>,
    /// A texel at or above this is at full scale: the clipping level,
    /// scaled as the merge of a step's exposures scales the frame.
    full_scale: f32,
}

/// The greys of an RGB texture's frame ([`FrameImages::rgb_greys`]).
struct RgbGreys {
    sensor: Image,
    texture: Image,
}

impl FrameImages {
    /// The grey its markers are found in, its lamp measured in and its
    /// blackness judged by.
    pub(super) fn grey(&self) -> &Image {
        self.rgb_greys.as_ref().map_or(&self.texture, |g| &g.sensor)
    }

    /// The grey its texture is aligned by.
    pub(super) fn texture_grey(&self) -> &Image {
        self.rgb_greys
            .as_ref()
            .map_or(&self.texture, |g| &g.texture)
    }
}

impl Rectifier<'_> {
    /// Textures per texel: 3 with a colour calibration, else 1.
    pub(super) fn channels(&self) -> usize {
        if self.colour.is_some() {
            3
        } else {
            1
        }
    }

    /// This rectifier with the lamp measured on the holder's white areas,
    /// when it has any: the reference is the lamp's output in the first
    /// frame, in journal order, that sees them, among the first
    /// [`LAMP_REFERENCE_CANDIDATES`] (a stream asks again for every chunk,
    /// and must not read the whole run each time).
    pub(super) fn with_lamp(mut self) -> Self {
        let Some(meter) = super::lamp::LampMeter::of(self.run, &self.holder) else {
            return self;
        };
        let mut candidates = self.run.entries.iter().take(LAMP_REFERENCE_CANDIDATES);
        let reference = candidates.find_map(|entry| {
            let images = self.frame_images(entry).ok()?;
            self.lamp_output(&meter, entry, images.grey())
        });
        self.lamp = reference.map(|r| (meter, r));
        self
    }

    /// The lamp's output in a frame, measured through its pose.
    fn lamp_output(
        &self,
        meter: &super::lamp::LampMeter,
        entry: &crate::store::FrameEntry,
        grey: &Image,
    ) -> Option<f64> {
        let camera = self.camera(entry).ok()?;
        meter
            .output(entry, grey, |p| camera.project([p[0], p[1], 0.0]))
            .filter(|o| o.is_finite() && *o > 0.0)
    }

    /// A frame as its texture is made and as it is registered, divided by
    /// its lamp's level where the holder's white areas measure it.
    pub(super) fn frame_images(
        &self,
        entry: &crate::store::FrameEntry,
    ) -> Result<FrameImages, crate::postprocess::ProcessError> {
        let mut images = self.read_images(entry)?;
        if let Some((meter, reference)) = &self.lamp {
            if let Some(output) = self.lamp_output(meter, entry, images.grey()) {
                let level = output / reference;
                let scale = (1.0 / level) as f32;
                images.texture.data.iter_mut().for_each(|v| *v *= scale);
                if let Some(g) = images.rgb_greys.as_mut() {
                    for grey in [&mut g.sensor, &mut g.texture] {
                        grey.data.iter_mut().for_each(|v| *v *= scale);
                    }
                }
                images.lamp_level = Some(level);
            }
        }
        Ok(images)
    }

    /// A frame as its file holds it: colour-corrected RGB with a colour
    /// calibration, else grey.
    fn read_images(
        &self,
        entry: &crate::store::FrameEntry,
    ) -> Result<FrameImages, crate::postprocess::ProcessError> {
        let Some(colour) = &self.colour else {
            let (texture, clipped) = self.run.image_and_clipped(entry)?;
            return Ok(FrameImages {
                texture,
                rgb_greys: None,
                lamp_level: None,
                clipped,
                full_scale: crate::postprocess::frames::clipped_level(entry),
            });
        };
        let Some(frame) = self.run.corrected_frame(entry, colour)? else {
            return Err(crate::postprocess::ProcessError::Invalid(format!(
                "frame {} is monochrome, and the run has a colour calibration",
                entry.index
            )));
        };
        let mut texture_grey = Image::new(frame.rgb.width, frame.rgb.height, 1);
        for (g, c) in texture_grey
            .data
            .iter_mut()
            .zip(frame.rgb.data.chunks_exact(3))
        {
            *g = rigd_core::holder::luminance([c[0], c[1], c[2]].map(f64::from)) as f32;
        }
        Ok(FrameImages {
            texture: frame.rgb,
            rgb_greys: Some(RgbGreys {
                sensor: frame.grey,
                texture: texture_grey,
            }),
            lamp_level: None,
            clipped: frame.clipped,
            full_scale: crate::postprocess::frames::clipped_level(entry),
        })
    }

    /// The frame's camera at its achieved pose.
    pub(super) fn camera(&self, entry: &crate::store::FrameEntry) -> Result<Camera, String> {
        super::pose_camera(
            &self.run.meta.profile,
            &entry.camera,
            [entry.width, entry.height],
            entry.achieved_view,
            &self.holder,
            None,
        )
        .ok_or_else(|| format!("no camera `{}` in the run's profile", entry.camera))
    }

    /// Marker registration, as Sattler et al. §3.2 does it.
    pub(super) fn markers(
        &self,
        image: &Image,
        camera: &Camera,
    ) -> Result<rigd_process::rectify::Registration, String> {
        let search = super::find_markers(&self.holder, &self.layout, image, camera)
            .map_err(|e| e.to_string())?;
        rigd_process::rectify::register(&self.layout, &search.detections, &Default::default())
            .map_err(|e| e.to_string())
    }

    /// The sample square of `image` through `h` at `side` texels.
    pub(super) fn sample_texture(
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

    /// Rectifies, cuts, blends and stores a frame's texture through `h`,
    /// with the texels that read a clipped pixel counted and their mask
    /// stored beside it; `Err` names why it cannot be used (saturated) or
    /// written.
    pub(super) fn write_texture(
        &self,
        rec: &mut FrameRegistration,
        images: &FrameImages,
        h: &rigd_process::rectify::Homography,
        bit_depth: u8,
    ) -> Result<(), String> {
        use rigd_process::rectify as rect;
        let cfg = self.cfg;
        let full = self.sample_texture(&images.texture, h, cfg.size)?;
        let saturated = full
            .texture
            .data
            .iter()
            .filter(|&&v| v >= images.full_scale)
            .count() as f64
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
        let cut = |t: &Image| {
            rect::roi_cut(t, roi, [side, side])
                .and_then(|t| rect::edge_blend(&t, cfg.blend))
                .map_err(|e| e.to_string())
        };
        let texture = cut(&full.texture)?;
        self.store(rec, &texture, bit_depth)?;
        (rec.clipped_texels, rec.clipped_share, rec.clipped_mask) = (0, None, None);
        if let Some(clipped) = &images.clipped {
            // Resampled as the texture is: a texel with any weight on a
            // clipped pixel read a value that is only a lower bound.
            let mask = cut(&self.sample_texture(&clipped.mask, h, cfg.size)?.texture)?;
            self.store_clipped(rec, &mask)?;
        }
        Ok(())
    }

    /// Counts the texels a resampled clip mask marks and, when there are
    /// any, writes them as the texture's clip mask.
    fn store_clipped(&self, rec: &mut FrameRegistration, mask: &Image) -> Result<(), String> {
        use rigd_process::image_io::{write_png, PngDepth};
        let mut marks = Image::new(mask.width, mask.height, 1);
        for (m, &v) in marks.data.iter_mut().zip(&mask.data) {
            *m = if v > CLIPPED_WEIGHT { 1.0 } else { 0.0 };
        }
        let count = marks.data.iter().filter(|&&v| v > 0.0).count();
        if count == 0 {
            return Ok(());
        }
        rec.clipped_texels = count;
        rec.clipped_share = Some(count as f64 / marks.data.len().max(1) as f64);
        let file = format!("v{:03}_l{:03}.clipped.png", rec.view_slot, rec.light_index);
        write_png(&self.out_dir.join(&file), &marks, PngDepth::Eight).map_err(|e| e.to_string())?;
        rec.clipped_mask = Some(file);
        Ok(())
    }

    /// Writes a final texture in the configured encoding.
    pub(super) fn store(
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
                let shape = match texture.channels {
                    1 => vec![texture.height, texture.width],
                    c => vec![texture.height, texture.width, c],
                };
                rigd_process::npy::write(&self.out_dir.join(&file), &shape, &texture.data, dtype)
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
    pub(super) fn first_pass(
        &self,
        position: usize,
        view_slot: usize,
        light_index: usize,
    ) -> FirstPass {
        let entry = &self.run.entries[position];
        let mut out = FirstPass {
            position,
            rec: FrameRegistration::new(entry.index, view_slot, light_index),
            markers: None,
            pose: None,
            unusable: false,
            p99: 0.0,
        };
        let images = match self.frame_images(entry) {
            Ok(images) => images,
            Err(e) => {
                out.rec.damaged = matches!(e, crate::postprocess::ProcessError::Damaged { .. });
                out.rec.problem = Some(if out.rec.damaged {
                    e.to_string()
                } else {
                    format!("lost: {e}")
                });
                out.unusable = true;
                return out;
            }
        };
        out.rec.lamp_level = images.lamp_level;
        if !entry.brackets.is_empty() {
            out.rec.exposures_s = entry.exposures_s();
        }
        // Whether it is black is decided against its neighbours, later.
        let image = images.grey();
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
        match self.markers(image, &camera) {
            Ok(reg) => {
                out.rec.rms_px = Some(reg.rms_px);
                out.rec.max_px = Some(reg.max_px);
                out.rec.markers_found = reg.found;
                out.rec.markers_used = reg.used;
                out.rec.markers_rejected = reg.rejected.clone();
                match self.write_texture(&mut out.rec, &images, &reg.homography, entry.bit_depth) {
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
    pub(super) fn reference_texture(&self, first: &FirstPass) -> Option<Image> {
        let entry = self.run.entries.get(first.position)?;
        let images = self.frame_images(entry).ok()?;
        let side = CORRELATION_SIZE.min(self.cfg.size);
        Some(
            self.sample_texture(images.texture_grey(), first.markers.as_ref()?, side)
                .ok()?
                .texture,
        )
    }

    /// The pose homography with the holder offset, refined by the texture
    /// against `reference` when that finds a clear match.
    pub(super) fn pose_registration(
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

/// The `q`-quantile of the finite values, clamped to [0, 1], to 2⁻¹⁶ of
/// full scale (0 if there are none).
pub(super) fn percentile_f32(values: &[f32], q: f64) -> f32 {
    // A histogram of 2^16 bins over [0, 1], one pass and no copy of the
    // frame: exact for sensor values of up to 16 bits, which is what the
    // frames hold (a full sort of a 3032×2008 frame cost a tenth of its
    // rectification).
    const BINS: usize = 1 << 16;
    let mut hist = vec![0u32; BINS];
    let mut n = 0usize;
    for &v in values {
        if v.is_finite() {
            // Rounded by +0.5 and truncation: `round` is a libm call.
            let bin = (v.clamp(0.0, 1.0) * (BINS - 1) as f32 + 0.5) as usize;
            hist[bin] += 1;
            n += 1;
        }
    }
    if n == 0 {
        return 0.0;
    }
    let k = ((n - 1) as f64 * q).round() as usize;
    let mut seen = 0usize;
    for (bin, &count) in hist.iter().enumerate() {
        seen += count as usize;
        if seen > k {
            return bin as f32 / (BINS - 1) as f32;
        }
    }
    1.0
}

/// Median, 95th percentile and maximum of `values` (None if empty).
pub(super) fn spread(values: &[f64]) -> Option<[f64; 3]> {
    let mut v: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    Some([at(0.5), at(0.95), at(1.0)])
}

/// Fills an unusable frame's texture with the inverse-angle-weighted mean
/// of the [`FILL_NEIGHBOURS`] nearest usable lights of its view slot, in
/// the index's encoding; returns their image indices.
pub(super) fn fill_from_neighbours(
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
        colour: rectifier.colour,
        lamp: None,
    };
    local.store(rec, &mean, bits)?;
    Ok(neighbours.iter().map(|(_, f)| f.index).collect())
}

#[cfg(test)]
mod tests {
    use super::percentile_f32;

    #[test]
    fn the_frame_percentile_is_exact_on_sensor_values_and_skips_non_finite() {
        // 12-bit values 0 … 4095 as a frame holds them.
        let values: Vec<f32> = (0..4096).map(|p| p as f32 / 4095.0).collect();
        for (q, want) in [(0.0, 0), (0.5, 2048), (0.99, 4054), (1.0, 4095)] {
            let got = percentile_f32(&values, q);
            let exact = want as f32 / 4095.0;
            assert!(
                (got - exact).abs() <= 1.0 / 65535.0,
                "q {q}: {got} vs {exact}"
            );
        }
        assert_eq!(percentile_f32(&[], 0.99), 0.0);
        assert_eq!(percentile_f32(&[f32::NAN, f32::INFINITY], 0.5), 0.0);
        let with_nan = [0.25, f32::NAN, 0.75, 0.5];
        assert!((percentile_f32(&with_nan, 0.5) - 0.5).abs() < 1e-4);
        // Out-of-range values count at the ends.
        assert_eq!(percentile_f32(&[-1.0, 2.0, 3.0], 1.0), 1.0);
    }
}
