//! One simulated frame on request: `rigd sim render` and
//! `GET /api/v1/sim/render`. The camera and lamp geometry come from a
//! profile exactly as the simulated cameras of a run use them; the scene
//! and directions from the caller.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use rigd_sim::scene::{EffectPlan, EffectSwitches, LaserSheet, Marker, Rendered, Scene, Shot};
use serde::Serialize;

use crate::kinematics::camera::{camera_geometry, CameraGeometry};
use crate::model::profile::Profile;
use crate::rig::hal::encode_png;
use crate::rig::hal::Frame;
use rigd_core::geometry::Direction;

/// Why a frame could not be rendered or written.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// A request value out of range (frame size, zoom, exposure, direction,
    /// laser) or a camera the profile does not have.
    #[error("{0}")]
    Invalid(String),
    /// The scene could not be loaded, or (asked by a client) is neither
    /// built in nor configured.
    #[error(transparent)]
    Scene(#[from] rigd_sim::scene::SceneError),
    /// The profile has no camera of that name.
    #[error("profile `{profile}` has no camera `{name}` (its cameras: {known})")]
    UnknownCamera {
        /// The profile's name.
        profile: String,
        /// The camera asked for, shortened to 64 characters.
        name: String,
        /// The profile's cameras, comma-separated.
        known: String,
    },
    /// Encoding or writing the PNG or its JSON failed.
    #[error("writing {path}: {message}")]
    Write {
        /// The file being written.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
}

/// What to render.
#[derive(Debug, Clone)]
pub struct RenderRequest {
    /// A built-in scene name or a scene file; the profile's `[sim] scene` if None.
    pub scene: Option<String>,
    /// Which camera of the profile; its first if None.
    pub camera: Option<String>,
    /// Direction towards the lamp, sample frame (θ 0 to 90°).
    pub light: Direction,
    /// Direction towards the camera, sample frame (θ 0 to 90°).
    pub view: Direction,
    /// Frame size; the profile's `[sim] frame_size` if None.
    pub size: Option<[u32; 2]>,
    /// Effects to force on or off beyond what the scene asks for.
    pub effects: EffectSwitches,
    /// Mixed into the scene's noise seed: another seed, other noise.
    pub seed: u64,
    /// Exposure relative to the camera's nominal one.
    pub exposure: f64,
    /// A laser plane crossing the sample plane at x = this many mm, tilted
    /// this many degrees from vertical, towards the emitter at +x.
    pub laser: Option<(f64, f64)>,
    /// Switch the lamp off (laser-only frames).
    pub lamp_off: bool,
    /// Focal length multiplier: a longer lens for a closer look.
    pub zoom: f64,
}

impl Default for RenderRequest {
    fn default() -> Self {
        RenderRequest {
            scene: None,
            camera: None,
            light: Direction::new(0.0, 0.0),
            view: Direction::new(0.0, 0.0),
            size: None,
            effects: EffectSwitches::default(),
            seed: 0,
            exposure: 1.0,
            laser: None,
            lamp_off: false,
            zoom: 1.0,
        }
    }
}

/// A rendered frame with everything needed to judge it.
#[derive(Debug, Clone)]
pub struct RenderOutput {
    /// The scene rendered.
    pub scene: Arc<Scene>,
    /// Exactly what was asked of the renderer.
    pub shot: Shot,
    /// The profile's camera whose geometry was used.
    pub camera: String,
    /// The pixels and the effects the frame used.
    pub rendered: Rendered,
    /// Wall-clock render time, milliseconds.
    pub render_ms: f64,
}

/// The frame's metadata, written next to the PNG.
#[derive(Debug, Serialize)]
pub struct RenderMeta<'a> {
    /// The scene's name.
    pub scene: &'a str,
    /// The profile's camera whose geometry was used.
    pub camera: &'a str,
    /// Direction towards the lamp, sample frame.
    pub light: Direction,
    /// Direction towards the camera, sample frame.
    pub view: Direction,
    /// Whether the lamp was on (off for laser-only frames).
    pub lamp_on: bool,
    /// Frame width, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
    /// Significant bits per pixel value.
    pub bit_depth: u8,
    /// Focal length in pixels of this frame (zoom included); None: an
    /// orthographic view.
    pub focal_px: Option<f64>,
    /// Distance from the sample centre to the camera, metres.
    pub camera_distance_m: Option<f64>,
    /// Distance of the point lamp, metres; None: a directional light.
    pub lamp_distance_m: Option<f64>,
    /// The laser's sheet of light, if it was on.
    pub laser: Option<LaserSheet>,
    /// The noise seed the frame was rendered with.
    pub seed: u64,
    /// The effects this frame paid for, and those it could have.
    pub effects: EffectPlan,
    /// Wall-clock render time, milliseconds.
    pub render_ms: f64,
    /// Where each registration marker lands, pixels (x right, y down).
    pub markers: Vec<MarkerPixel>,
}

/// One holder marker and where it lands in the frame.
#[derive(Debug, Serialize)]
pub struct MarkerPixel {
    /// The marker, flattened into the JSON object.
    #[serde(flatten)]
    pub marker: Marker,
    /// Its pixel position (x right, y down); None when behind the camera.
    pub pixel: Option<[f64; 2]>,
}

/// Renders one frame for the operator: `req.scene` is a built-in scene's
/// name or a scene file's path.
pub fn render(profile: &Profile, req: &RenderRequest) -> Result<RenderOutput, RenderError> {
    let configured = super::profile_scene(profile).map_err(scene_error)?;
    let scene = Scene::load_on(req.scene.as_deref().unwrap_or(&configured), &profile.holder)?;
    render_scene(profile, scene, req)
}

/// Renders one frame for a client (the API): `req.scene` must name a
/// built-in scene or the profile's configured one ([`offered_scene`]).
pub fn render_offered(profile: &Profile, req: &RenderRequest) -> Result<RenderOutput, RenderError> {
    let scene = offered_scene(profile, req.scene.as_deref())?;
    render_scene(profile, scene, req)
}

/// The scene a client asks for by name: a built-in one, or the one the
/// profile's `[sim] scene` configures (by the name written there); the
/// profile's when None. Any other name is refused, naming those there
/// are, and nothing is read.
pub fn offered_scene(
    profile: &Profile,
    name: Option<&str>,
) -> Result<Arc<Scene>, rigd_sim::scene::SceneError> {
    let configured = super::profile_scene(profile).map_err(scene_error)?;
    let configured = configured.as_str();
    let plate = profile
        .holder
        .holder()
        .map_err(|e| rigd_sim::scene::SceneError::Invalid {
            origin: "the profile".into(),
            message: e.to_string(),
        })?;
    Scene::offered(name.unwrap_or(configured), &[configured])?.on_holder(plate)
}

/// A profile's `[sim]` table that does not read, as a scene error.
fn scene_error(e: crate::rig::DeviceError) -> rigd_sim::scene::SceneError {
    rigd_sim::scene::SceneError::Invalid {
        origin: "the profile".into(),
        message: e.to_string(),
    }
}

/// The scene names [`offered_scene`] takes: the built-in ones, then the
/// profile's configured scene when it is not one of them.
pub fn offered_scene_names(profile: &Profile) -> Vec<String> {
    let mut names: Vec<String> = Scene::builtin_names()
        .into_iter()
        .map(String::from)
        .collect();
    // A profile whose `[sim]` table does not read offers the built-in ones.
    if let Ok(configured) = super::profile_scene(profile) {
        if !Scene::is_builtin(&configured) {
            names.push(configured);
        }
    }
    names
}

fn render_scene(
    profile: &Profile,
    scene: Arc<Scene>,
    req: &RenderRequest,
) -> Result<RenderOutput, RenderError> {
    let holder_offset_mm = super::settings(&profile.sim)
        .map_err(|(key, message)| RenderError::Invalid(format!("{key}: {message}")))?
        .holder_offset_mm;
    let cameras = profile.camera_names();
    let camera = match &req.camera {
        Some(c) if cameras.contains(c) => c.clone(),
        Some(c) => {
            return Err(RenderError::UnknownCamera {
                profile: profile.name.clone(),
                name: c.chars().take(64).collect(),
                known: cameras.join(", "),
            })
        }
        None => cameras.into_iter().next().ok_or_else(|| {
            RenderError::Invalid(format!("profile `{}` has no camera", profile.name))
        })?,
    };
    let size = req.size.unwrap_or(profile.sim.frame_size);
    if size[0] == 0 || size[1] == 0 || size[0] > 8192 || size[1] > 8192 {
        return Err(RenderError::Invalid(format!(
            "frame size {}x{}: expected 1 ..= 8192 pixels each way",
            size[0], size[1]
        )));
    }
    if !(req.zoom.is_finite() && (0.1..=100.0).contains(&req.zoom)) {
        return Err(RenderError::Invalid(format!(
            "zoom {}: expected 0.1 ..= 100",
            req.zoom
        )));
    }
    if !(req.exposure.is_finite() && req.exposure > 0.0) {
        return Err(RenderError::Invalid(format!(
            "exposure {}: expected a positive factor",
            req.exposure
        )));
    }
    for (what, d) in [("light", req.light), ("view", req.view)] {
        if !(d.theta_deg.is_finite()
            && d.phi_deg.is_finite()
            && (0.0..=90.0).contains(&d.theta_deg))
        {
            return Err(RenderError::Invalid(format!(
                "{what} θ = {}, φ = {}: expected 0 ≤ θ ≤ 90 degrees and a finite φ",
                d.theta_deg, d.phi_deg
            )));
        }
    }
    let CameraGeometry {
        focal_px,
        distance_m,
        bit_depth,
        lamp_distance_m,
    } = camera_geometry(profile, &camera, size).ok_or_else(|| {
        RenderError::Invalid(format!(
            "profile `{}` has no camera `{camera}`",
            profile.name
        ))
    })?;
    let laser = match req.laser {
        None => None,
        Some((offset_mm, tilt_deg)) => {
            if !(offset_mm.is_finite() && tilt_deg.is_finite() && tilt_deg.abs() < 80.0) {
                return Err(RenderError::Invalid(format!(
                    "laser {offset_mm},{tilt_deg}: expected an offset in mm and a tilt below 80°"
                )));
            }
            Some(laser_plane(offset_mm * 1e-3, tilt_deg))
        }
    };
    let shot = Shot {
        light: if req.lamp_off {
            [0.0, 0.0, -1.0]
        } else {
            req.light.to_vector()
        },
        view: req.view.to_vector(),
        width: size[0],
        height: size[1],
        bit_depth,
        relative_exposure: req.exposure,
        focal_px: Some(focal_px * req.zoom),
        camera_distance_m: distance_m,
        lamp_distance_m,
        laser,
        seed: req.seed,
        effects: req.effects,
        holder_offset_m: holder_offset_mm.map(|v| v * 1e-3),
        ..Shot::default()
    };
    let started = Instant::now();
    let rendered = scene.render(&shot);
    let render_ms = started.elapsed().as_secs_f64() * 1e3;
    tracing::debug!(scene = %scene.name, effects = %rendered.plan.live, render_ms, "rendered a frame");
    Ok(RenderOutput {
        scene,
        shot,
        camera,
        rendered,
        render_ms,
    })
}

/// A laser plane crossing z = 0 at x = `x0`, tilted about the y axis, its
/// emitter 30 cm above the sample.
pub fn laser_plane(x0: f64, tilt_deg: f64) -> LaserSheet {
    let t = tilt_deg.to_radians();
    let height = 0.3;
    LaserSheet {
        emitter: [x0 + height * t.tan(), 0.0, height],
        normal: [t.cos(), 0.0, -t.sin()],
        width_m: 0.8e-3,
        power: 1.0,
    }
}

impl RenderOutput {
    /// The rendered pixels as a camera would deliver them.
    pub fn frame(&self) -> Frame {
        Frame {
            width: self.rendered.width,
            height: self.rendered.height,
            bit_depth: self.rendered.bit_depth,
            pixels: self.rendered.pixels.clone(),
            device: None,
            original: None,
        }
    }

    /// The frame as a greyscale PNG: 8-bit up to 8-bit sensors, else 16-bit
    /// holding the raw values.
    pub fn png(&self) -> Result<Vec<u8>, String> {
        encode_png(&self.frame())
    }

    /// The metadata written next to the PNG, markers included.
    pub fn meta(&self) -> RenderMeta<'_> {
        let s = &self.shot;
        RenderMeta {
            scene: &self.scene.name,
            camera: &self.camera,
            light: Direction::from_vector(s.light),
            view: Direction::from_vector(s.view),
            lamp_on: s.lamp_on(),
            width: s.width,
            height: s.height,
            bit_depth: s.bit_depth,
            focal_px: s.focal_px,
            camera_distance_m: s.camera_distance_m,
            lamp_distance_m: s.lamp_distance_m,
            laser: s.laser,
            seed: s.seed,
            effects: self.rendered.plan,
            render_ms: self.render_ms,
            markers: self
                .scene
                .true_markers(s)
                .into_iter()
                .map(|(marker, pixel)| MarkerPixel { marker, pixel })
                .collect(),
        }
    }

    /// Writes the PNG and, beside it, `NAME.json` with the metadata; each
    /// file appears whole or not at all.
    pub fn write(&self, out: &Path) -> Result<PathBuf, RenderError> {
        let werr = |path: &Path, message: String| RenderError::Write {
            path: path.to_path_buf(),
            message,
        };
        let png = self.png().map_err(|m| werr(out, m))?;
        let meta_path = out.with_extension("json");
        let mut json =
            serde_json::to_vec_pretty(&self.meta()).map_err(|e| werr(&meta_path, e.to_string()))?;
        json.push(b'\n');
        rigd_core::atomic::write(out, &png).map_err(|e| werr(out, e.to_string()))?;
        rigd_core::atomic::write(&meta_path, &json).map_err(|e| werr(&meta_path, e.to_string()))?;
        Ok(meta_path)
    }
}

/// Parses a laser spec `X` or `X,TILT` (mm, degrees; tilt 30 by default).
pub fn parse_laser(s: &str) -> Result<(f64, f64), String> {
    let bad = || format!("`{s}`: expected X or X,TILT in mm and degrees, like -20,30");
    let parts: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|_| bad()))
        .collect::<Result<_, _>>()?;
    match parts[..] {
        [x] => Ok((x, 30.0)),
        [x, tilt] => Ok((x, tilt)),
        _ => Err(bad()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A client names scenes; only the built-in ones and the profile's
    /// configured file are loaded, any other name (a path included) is
    /// refused without being read, naming those there are.
    #[test]
    fn clients_get_built_in_and_configured_scenes_only() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("mine.toml");
        let text = include_str!("../../../crates/sim/scenes/corduroy.toml").replacen(
            "name = \"corduroy\"",
            "name = \"mine\"",
            1,
        );
        std::fs::write(&file, text).unwrap();
        let mut profile = crate::plan::load_profile("bonn-gonioreflectometer").unwrap();
        let configured = file.display().to_string();
        crate::rig::sim::set_scene(&mut profile, &configured);
        assert_eq!(offered_scene(&profile, None).unwrap().name, "mine");
        assert_eq!(
            offered_scene(&profile, Some(&configured)).unwrap().name,
            "mine"
        );
        assert_eq!(
            offered_scene(&profile, Some("leather")).unwrap().name,
            "leather"
        );
        let names = offered_scene_names(&profile);
        assert_eq!(names.last(), Some(&configured));
        let other = dir.path().join("other.toml");
        std::fs::copy(&file, &other).unwrap();
        for asked in [
            other.display().to_string(),
            "/dev/zero".into(),
            "../mine.toml".into(),
        ] {
            let e = offered_scene(&profile, Some(&asked)).unwrap_err();
            assert!(
                matches!(e, rigd_sim::scene::SceneError::NotOffered { .. }),
                "{asked}: {e}"
            );
            let text = e.to_string();
            assert!(
                text.contains("corduroy") && text.contains(&configured),
                "{text}"
            );
        }
    }
}
