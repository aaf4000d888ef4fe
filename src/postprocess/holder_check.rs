//! `rigd holder check`: bringing up a new holder plate on one frame. The
//! holder's point markers are looked for where the profile's camera model
//! puts them at the frame's view, by the same search and registration as
//! `rigd process rectify` ([`super::rectify`]); then each colour patch and
//! white area is read through the registered homography, and a channel at
//! or near full scale is reported as clipped.

use std::path::Path;

use rigd_core::geometry::Direction;
use rigd_core::holder::{HolderError, Polarity};
use rigd_process::image_io::Image;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::frames::{cfa_of_pixel_format, decode_frame, decode_samples};
use super::rectify::{find_markers, marker_layout, pose_camera};
use crate::model::profile::Profile;
use crate::rig::hal::Frame;

/// A sample at or above this fraction of full scale is clipped.
pub const CLIP_LEVEL: f64 = 0.98;

/// Fraction of a patch's or white area's side that is read: its edges
/// blur into the plate through the lens and a demosaic.
pub const INNER_FRACTION: f64 = 0.6;

/// Sample points across the read part of a patch, per side.
const POINTS_PER_SIDE: usize = 15;

/// How a frame was taken: what the camera model needs to predict where
/// the markers lie.
#[derive(Debug, Clone, PartialEq)]
pub struct FramePose {
    /// Direction towards the camera, sample frame.
    pub view: Direction,
    /// The profile's camera that took it; None: the profile's first.
    pub camera: Option<String>,
    /// Focal length of this frame, pixels, where it is known to differ
    /// from the profile's (a test frame rendered with a zoom); None: the
    /// profile's.
    pub focal_px: Option<f64>,
}

impl Default for FramePose {
    fn default() -> Self {
        FramePose {
            view: Direction::new(0.0, 0.0),
            camera: None,
            focal_px: None,
        }
    }
}

/// Why a frame could not be checked at all (not: what the check found
/// wrong, which [`HolderCheck::problems`] says).
#[derive(Debug, thiserror::Error)]
pub enum HolderCheckError {
    /// The profile's holder cannot work.
    #[error("the profile's holder cannot work: {0}")]
    Holder(#[from] HolderError),
    /// The profile has no such camera, or none with intrinsics.
    #[error("{0}")]
    Camera(String),
    /// The frame file cannot be read or is no frame.
    #[error("{path}: {message}")]
    Frame {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        message: String,
    },
    /// The frame's metadata or the view is out of range.
    #[error("{0}")]
    Invalid(String),
}

/// One point marker in the frame.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct MarkerCheck {
    /// Its index among the holder's markers.
    pub index: usize,
    /// `light` or `dark`.
    #[schema(schema_with = polarity_schema)]
    pub polarity: Polarity,
    /// Where it is on the plate, mm from the sample centre.
    pub position_mm: [f64; 2],
    /// Where the camera model puts it, pixels (x right, y down); None
    /// when behind the camera.
    pub predicted_px: Option<[f64; 2]>,
    /// Where it was found, pixels; None: not found.
    pub found_px: Option<[f64; 2]>,
    /// Distance between where it was found and where the registered
    /// homography puts it, pixels; None: not found, or not registered.
    pub residual_px: Option<f64>,
    /// Found, but left out of the fit as an outlier (something else was
    /// found near where it should be).
    pub rejected: bool,
}

/// The mean of a patch or white area in the frame.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct AreaReading {
    /// The patch's name, or `white[i]` for a white area.
    pub name: String,
    /// Mean value per channel over the inner part, fraction of full
    /// scale: one value (grey) for a monochrome frame, three (red, green,
    /// blue) for a colour one.
    pub mean: Vec<f64>,
    /// The channels with a sample at or above [`CLIP_LEVEL`] (`grey`,
    /// `red`, `green`, `blue`); empty: none clipped.
    pub clipped: Vec<String>,
}

/// What `rigd holder check` found in one frame.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct HolderCheck {
    /// The profile's name.
    pub profile: String,
    /// The holder's name.
    pub holder: String,
    /// The camera whose model predicted the markers.
    pub camera: String,
    /// The view the frame was taken from.
    #[schema(schema_with = direction_schema)]
    pub view: Direction,
    /// Frame width and height, pixels.
    pub size: [usize; 2],
    /// Channels read: 1 (grey) or 3 (red, green, blue).
    pub channels: usize,
    /// Every point marker, in the holder's order.
    pub markers: Vec<MarkerCheck>,
    /// Markers found.
    pub markers_found: usize,
    /// Whether the markers registered the frame (a homography from at
    /// least 4 consistent markers).
    pub registered: bool,
    /// RMS residual of the markers used in the fit, pixels.
    pub rms_px: Option<f64>,
    /// Largest residual of the markers used in the fit, pixels.
    pub max_px: Option<f64>,
    /// The colour patches, in the holder's order (the standard row, the
    /// chart's, the lab's own); empty when the frame did not register.
    pub patches: Vec<AreaReading>,
    /// The white areas, in the holder's order; empty when the frame did
    /// not register.
    pub whites: Vec<AreaReading>,
    /// Each thing wrong, one line each, naming the marker, patch or area.
    pub problems: Vec<String>,
    /// Every marker found and used, and nothing clipped.
    pub ok: bool,
}

/// Checks `profile`'s holder in `image` (linear, 0 to 1 of full scale; one
/// channel, or three of linear red, green, blue) taken as `pose` says:
/// each marker looked for around where the camera model puts it, the
/// frame registered by those found, and each patch and white area read
/// through the registration. `Err` only when the check cannot be made;
/// what it finds wrong is in [`HolderCheck::problems`].
pub fn check_frame(
    profile: &Profile,
    image: &Image,
    pose: &FramePose,
) -> Result<HolderCheck, HolderCheckError> {
    let holder = profile.holder.holder()?;
    if !(pose.view.is_finite() && (0.0..90.0).contains(&pose.view.theta_deg)) {
        return Err(HolderCheckError::Invalid(format!(
            "view θ = {}, φ = {}: expected 0 ≤ θ < 90 degrees",
            pose.view.theta_deg, pose.view.phi_deg
        )));
    }
    if image.width == 0 || image.height == 0 || !matches!(image.channels, 1 | 3) {
        return Err(HolderCheckError::Invalid(format!(
            "a {}×{} frame of {} channels: expected a grey or an RGB frame",
            image.width, image.height, image.channels
        )));
    }
    let camera_name = match &pose.camera {
        Some(c) => c.clone(),
        None => profile.camera_names().into_iter().next().ok_or_else(|| {
            HolderCheckError::Camera(format!("profile `{}` has no camera", profile.name))
        })?,
    };
    let size = [
        u32::try_from(image.width).unwrap_or(u32::MAX),
        u32::try_from(image.height).unwrap_or(u32::MAX),
    ];
    let camera = pose_camera(
        profile,
        &camera_name,
        size,
        pose.view,
        &holder,
        pose.focal_px,
    )
    .ok_or_else(|| {
        HolderCheckError::Camera(format!(
            "profile `{}` has no camera `{camera_name}` with intrinsics (its cameras: {})",
            profile.name,
            profile.camera_names().join(", ")
        ))
    })?;
    let grey = grey_of(image);
    let layout = marker_layout(&holder);
    let search = find_markers(&holder, &layout, &grey, &camera)
        .map_err(|e| HolderCheckError::Invalid(e.to_string()))?;
    let registration =
        rigd_process::rectify::register(&layout, &search.detections, &Default::default());
    let mut problems = Vec::new();
    let markers: Vec<MarkerCheck> = holder
        .points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let found = search.detections[i].map(|d| d.centre_px);
            let (residual, rejected) = match &registration {
                Ok(r) => (
                    r.residuals_px.get(i).copied().flatten(),
                    r.rejected.contains(&i),
                ),
                Err(_) => (None, false),
            };
            MarkerCheck {
                index: i,
                polarity: p.polarity,
                position_mm: p.position.map(|v| v * 1e3),
                predicted_px: search.predicted[i],
                found_px: found,
                residual_px: residual,
                rejected,
            }
        })
        .collect();
    for m in &markers {
        let what = format!(
            "marker {} ({}, at {:.1}, {:.1} mm)",
            m.index,
            polarity_name(m.polarity),
            m.position_mm[0],
            m.position_mm[1]
        );
        match (m.found_px, m.predicted_px) {
            (None, Some(p)) => problems.push(format!(
                "{what}: not found near its predicted pixel ({:.1}, {:.1})",
                p[0], p[1]
            )),
            (None, None) => problems.push(format!("{what}: not found (behind the camera)")),
            (Some(_), _) if m.rejected => problems.push(format!(
                "{what}: rejected as an outlier (residual {:.2} px): what was found there is not the marker",
                m.residual_px.unwrap_or(f64::NAN)
            )),
            _ => {}
        }
    }
    let markers_found = markers.iter().filter(|m| m.found_px.is_some()).count();
    let mut patches = Vec::new();
    let mut whites = Vec::new();
    let (registered, rms_px, max_px) = match &registration {
        Ok(r) => {
            let h = &r.homography;
            for p in &holder.patches {
                let reading = read_area(image, h, &p.name, p.centre, [p.half; 2]);
                match reading {
                    Some(r) => patches.push(r),
                    None => problems.push(format!("patch `{}`: not inside the frame", p.name)),
                }
            }
            for (i, w) in holder.whites.iter().enumerate() {
                let name = format!("white[{i}]");
                match read_area(image, h, &name, w.centre, w.half) {
                    Some(r) => whites.push(r),
                    None => problems.push(format!("{name}: not inside the frame")),
                }
            }
            (true, Some(r.rms_px), Some(r.max_px))
        }
        Err(e) => {
            problems.push(format!(
                "not registered: {e}; the patches and white areas were not read"
            ));
            (false, None, None)
        }
    };
    for a in patches.iter().chain(&whites) {
        if !a.clipped.is_empty() {
            let what = if a.name.starts_with("white[") {
                a.name.clone()
            } else {
                format!("patch `{}`", a.name)
            };
            problems.push(format!(
                "{what}: clipped in {} (a sample at or above {:.0} % of full scale): lower the exposure",
                a.clipped.join(", "),
                CLIP_LEVEL * 100.0
            ));
        }
    }
    Ok(HolderCheck {
        profile: profile.name.clone(),
        holder: holder.name.clone(),
        camera: camera_name,
        view: pose.view,
        size: [image.width, image.height],
        channels: image.channels,
        markers,
        markers_found,
        registered,
        rms_px,
        max_px,
        patches,
        whites,
        ok: problems.is_empty(),
        problems,
    })
}

/// The OpenAPI schema of a [`Direction`] (rigd-core knows nothing of
/// OpenAPI).
fn direction_schema() -> utoipa::openapi::Object {
    use utoipa::openapi::{ObjectBuilder, Type};
    let degrees = |what: &str| {
        ObjectBuilder::new()
            .schema_type(Type::Number)
            .description(Some(what))
    };
    ObjectBuilder::new()
        .description(Some("A direction in the sample frame, degrees."))
        .property(
            "theta_deg",
            degrees("Polar angle from the sample normal, degrees."),
        )
        .required("theta_deg")
        .property(
            "phi_deg",
            degrees("Azimuth in the sample plane, counter-clockwise from +x, degrees."),
        )
        .required("phi_deg")
        .build()
}

/// The OpenAPI schema of a marker's [`Polarity`].
fn polarity_schema() -> utoipa::openapi::Object {
    use utoipa::openapi::{ObjectBuilder, Type};
    ObjectBuilder::new()
        .schema_type(Type::String)
        .description(Some("`light` or `dark`: lighter or darker than the plate."))
        .enum_values(Some(["light", "dark"]))
        .build()
}

fn polarity_name(p: Polarity) -> &'static str {
    match p {
        Polarity::Light => "light",
        Polarity::Dark => "dark",
    }
}

/// A frame's grey, as registration reads it: the image itself when it has
/// one channel, else its luminance.
fn grey_of(image: &Image) -> Image {
    if image.channels == 1 {
        return image.clone();
    }
    let mut grey = Image::new(image.width, image.height, 1);
    for (g, c) in grey.data.iter_mut().zip(image.data.chunks_exact(3)) {
        *g = rigd_core::holder::luminance([c[0], c[1], c[2]].map(f64::from)) as f32;
    }
    grey
}

/// The mean per channel of the inner part of the rectangle at `centre`
/// with half sides `half` (plate metres) through `h`, and which channels
/// clip; None if part of it falls outside the frame.
fn read_area(
    image: &Image,
    h: &rigd_process::rectify::Homography,
    name: &str,
    centre: [f64; 2],
    half: [f64; 2],
) -> Option<AreaReading> {
    let n = POINTS_PER_SIDE;
    let spread = |k: usize| 2.0 * (k as f64 + 0.5) / n as f64 - 1.0;
    let channels = image.channels;
    let mut sum = vec![0.0; channels];
    let mut clipped = vec![false; channels];
    for k in 0..n * n {
        let q = [
            centre[0] + INNER_FRACTION * half[0] * spread(k % n),
            centre[1] + INNER_FRACTION * half[1] * spread(k / n),
        ];
        let px = rigd_process::rectify::project(h, q)?;
        // The pixel the point falls in (pixel (i, j) spans [i, i + 1)).
        if !(px[0] >= 0.0 && px[1] >= 0.0) {
            return None;
        }
        let (x, y) = (px[0].floor() as usize, px[1].floor() as usize);
        if x >= image.width || y >= image.height {
            return None;
        }
        for c in 0..channels {
            let v = f64::from(image.get(x, y, c));
            sum[c] += v;
            clipped[c] |= v >= CLIP_LEVEL;
        }
    }
    let names: &[&str] = if channels == 1 {
        &["grey"]
    } else {
        &["red", "green", "blue"]
    };
    Some(AreaReading {
        name: name.to_string(),
        mean: sum.iter().map(|s| s / (n * n) as f64).collect(),
        clipped: names
            .iter()
            .zip(&clipped)
            .filter(|(_, &c)| c)
            .map(|(n, _)| n.to_string())
            .collect(),
    })
}

/// What `rigd sim render` writes beside a test frame (`NAME.json`), as far
/// as the check needs it.
#[derive(Debug, Clone, Deserialize)]
struct RenderedMeta {
    camera: Option<String>,
    view: Option<Direction>,
    bit_depth: Option<u8>,
    focal_px: Option<f64>,
}

/// A frame file ready to check, and how it was taken as far as the file
/// tells.
#[derive(Debug, Clone)]
pub struct FrameFile {
    /// The frame, linear in [0, 1]: one channel, or three (red, green,
    /// blue) for a colour camera's.
    pub image: Image,
    /// The pose its metadata gives (a test frame's `NAME.json`): the view,
    /// the camera and the focal length it was rendered with; defaults
    /// where it has none.
    pub pose: FramePose,
    /// Whether that metadata was found.
    pub has_metadata: bool,
}

/// Reads a frame file: a camera file (DNG, vendor raw, JPEG, TIFF), or a
/// PNG as a rig writes it or `rigd sim render` does. A PNG's bit depth and
/// view come from the render's metadata beside it (`NAME.json`) where
/// there is one, else the bit depth and filter array of `profile`'s camera
/// `camera` (its first if None).
pub fn read_frame(
    path: &Path,
    profile: &Profile,
    camera: Option<&str>,
) -> Result<FrameFile, HolderCheckError> {
    let frame_err = |message: String| HolderCheckError::Frame {
        path: path.to_path_buf(),
        message,
    };
    let bytes = rigd_core::read::read_bounded(path, rigd_core::read::IMAGE_LIMIT)
        .map_err(|e| frame_err(e.to_string()))?;
    let mut pose = FramePose::default();
    let mut has_metadata = false;
    let is_png = crate::rig::hal::is_png(&bytes);
    let meta_path = path.with_extension("json");
    let mut bit_depth = None;
    if is_png && meta_path.is_file() {
        let text = rigd_core::read::read_bounded(&meta_path, rigd_core::read::TEXT_LIMIT).map_err(
            |e| HolderCheckError::Frame {
                path: meta_path.clone(),
                message: e.to_string(),
            },
        )?;
        let meta: RenderedMeta =
            serde_json::from_slice(&text).map_err(|e| HolderCheckError::Frame {
                path: meta_path.clone(),
                message: format!("not a rendered frame's metadata: {e}"),
            })?;
        has_metadata = true;
        if let Some(v) = meta.view {
            pose.view = v;
        }
        pose.camera = meta.camera;
        pose.focal_px = meta.focal_px;
        bit_depth = meta.bit_depth;
    }
    let name = camera
        .map(str::to_string)
        .or_else(|| pose.camera.clone())
        .or_else(|| profile.camera_names().into_iter().next());
    let intrinsics = name
        .as_deref()
        .and_then(|n| profile.devices.get(n))
        .and_then(|d| d.intrinsics());
    // The renderer writes grey frames; a rig's PNG of a colour camera
    // holds its mosaic.
    let cfa = if has_metadata {
        None
    } else {
        intrinsics.and_then(|i| i.cfa)
    };
    let bit_depth = bit_depth.or(intrinsics.map(|i| i.bit_depth)).unwrap_or(16);
    let image = super::frames::decode_frame(&bytes, bit_depth, cfa).map_err(frame_err)?;
    Ok(FrameFile {
        image,
        pose,
        has_metadata,
    })
}

/// A test frame as the camera delivered it, as the check reads it (linear,
/// 0 to 1 of full scale): the camera's own file (a PTP camera's DNG, raw
/// or JPEG) by its content, as a run's stored frame is read; else its
/// samples behind the filter array its pixel format names or, where the
/// camera names none, the one of `profile`'s camera `camera`
/// (`intrinsics.cfa`), as [`read_frame`] reads a rig's PNG. A Bayer mosaic
/// is demosaiced to red, green and blue, as there. `Err` says why the
/// frame cannot be read.
pub fn frame_image(frame: &Frame, profile: &Profile, camera: &str) -> Result<Image, String> {
    if let Some(original) = &frame.original {
        return decode_frame(&original.bytes, frame.bit_depth, None);
    }
    let cfa = match &frame.device {
        Some(d) => cfa_of_pixel_format(&d.pixel_format),
        None => profile
            .devices
            .get(camera)
            .and_then(|d| d.intrinsics())
            .and_then(|i| i.cfa),
    };
    decode_samples(
        frame.width,
        frame.height,
        frame.bit_depth,
        &frame.pixels,
        cfa,
    )
}

impl HolderCheck {
    /// The report as `rigd holder check` prints it, one line each.
    pub fn lines(&self) -> Vec<String> {
        let mut out = vec![format!(
            "holder `{}` of profile `{}`: camera {}, view θ {:.1}° φ {:.1}°, {}×{} px, {}",
            self.holder,
            self.profile,
            self.camera,
            self.view.theta_deg,
            self.view.phi_deg,
            self.size[0],
            self.size[1],
            if self.channels == 1 { "grey" } else { "RGB" }
        )];
        out.push("marker  polarity  predicted px        found px            residual".into());
        let px = |p: Option<[f64; 2]>| {
            p.map_or("not found".to_string(), |p| {
                format!("({:.1}, {:.1})", p[0], p[1])
            })
        };
        for m in &self.markers {
            out.push(format!(
                "{:<7} {:<9} {:<19} {:<19} {}{}",
                m.index,
                polarity_name(m.polarity),
                m.predicted_px
                    .map_or("behind the camera".to_string(), |p| px(Some(p))),
                px(m.found_px),
                m.residual_px
                    .map_or("-".to_string(), |r| format!("{r:.2} px")),
                if m.rejected { " (rejected)" } else { "" }
            ));
        }
        match (self.rms_px, self.max_px) {
            (Some(rms), Some(max)) => out.push(format!(
                "registration: {} of {} markers found, residual RMS {rms:.3} px, max {max:.3} px",
                self.markers_found,
                self.markers.len()
            )),
            _ => out.push(format!(
                "registration: {} of {} markers found, not registered",
                self.markers_found,
                self.markers.len()
            )),
        }
        for a in self.patches.iter().chain(&self.whites) {
            let means: Vec<String> = a.mean.iter().map(|v| format!("{v:.4}")).collect();
            out.push(format!(
                "{:<22} mean {}{}",
                a.name,
                means.join(" "),
                if a.clipped.is_empty() {
                    String::new()
                } else {
                    format!("  CLIPPED ({})", a.clipped.join(", "))
                }
            ));
        }
        if self.ok {
            out.push("OK: every marker found, nothing clipped".into());
        } else {
            for p in &self.problems {
                out.push(format!("FAIL {p}"));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::hal::DeviceFrameInfo;

    /// A 4×2 frame of 8-bit samples: red 255, green 51, blue 0 behind an
    /// RGGB tile.
    fn mosaic(device: Option<&str>) -> Frame {
        Frame {
            width: 4,
            height: 2,
            bit_depth: 8,
            pixels: vec![255, 51, 255, 51, 51, 0, 51, 0],
            device: device.map(|f| DeviceFrameInfo {
                frame_id: 1,
                timestamp_ns: 2,
                pixel_format: f.to_string(),
            }),
            original: None,
        }
    }

    fn profile(name: &str) -> Profile {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("rig-profiles")
            .join(format!("{name}.toml"));
        crate::plan::load_profile(&path.to_string_lossy()).expect("profile")
    }

    #[test]
    fn a_test_frame_is_demosaiced_where_its_camera_has_a_filter_array() {
        let bayer = profile("bonn-gonioreflectometer");
        let mono = Profile::parse(
            &std::fs::read_to_string(
                std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                    .join("rig-profiles/bonn-gonioreflectometer.toml"),
            )
            .expect("profile")
            .replace(", cfa = \"RGGB\"", ""),
            "monochrome Bonn",
        )
        .expect("monochrome profile");
        assert!(mono.devices["camera"]
            .intrinsics()
            .as_ref()
            .is_some_and(|i| i.cfa.is_none()));
        // The camera names no format: the profile's camera says.
        let grey = frame_image(&mosaic(None), &mono, "camera").expect("grey");
        assert_eq!(grey.channels, 1);
        assert_eq!(grey.get(1, 0, 0), 51.0 / 255.0);
        let rgb = frame_image(&mosaic(None), &bayer, "camera").expect("colour");
        assert_eq!((rgb.width, rgb.height, rgb.channels), (4, 2, 3));
        assert_eq!(rgb.get(1, 0, 0), 1.0, "red");
        assert_eq!(rgb.get(1, 0, 1), 0.2, "green");
        assert_eq!(rgb.get(1, 0, 2), 0.0, "blue");
        // The camera's own pixel format wins over the profile.
        let rgb = frame_image(&mosaic(Some("BayerRG8")), &mono, "camera").expect("colour");
        assert_eq!(rgb.channels, 3);
        let grey = frame_image(&mosaic(Some("Mono8")), &bayer, "camera").expect("grey");
        assert_eq!(grey.channels, 1);
        // Samples that do not fill the frame are refused, not read.
        let mut short = mosaic(None);
        short.pixels.pop();
        assert!(frame_image(&short, &mono, "camera").is_err());
    }
}
