//! What one frame asks of the renderer ([`Shot`]) and the camera it is
//! seen through ([`camera`]), shared by the renderer's stages (exposure,
//! shading, the sensor) and the ground truth.
//!
//! Units: radiance is a reflectance factor, 1 for a white Lambertian
//! surface lit frontally by the lamp at its nominal distance; the sensor
//! maps that to [`WHITE_LEVEL`] of full scale at nominal exposure and gain.

use rigd_core::camera::Camera;
use serde::Serialize;

use super::effects::EffectSwitches;
use super::Scene;

/// Fraction of full scale a white, frontally lit texel reaches at nominal
/// exposure and gain.
pub const WHITE_LEVEL: f64 = 0.8;

/// The sheet of light a laser line emitter fans out: the plane through
/// `emitter` with unit normal `normal`; where it meets a surface it draws
/// the laser line.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LaserSheet {
    /// Where the emitter is, metres, sample frame.
    pub emitter: [f64; 3],
    /// Unit normal of the light sheet, sample frame.
    pub normal: [f64; 3],
    /// Full width of the line at half its peak, metres.
    pub width_m: f64,
    /// Peak radiance on a white surface facing the emitter, in reflectance
    /// factor units.
    pub power: f64,
}

/// What one frame needs: directions in the sample frame (unit vectors, z the
/// sample normal, both pointing away from the sample) and the sensor set-up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shot {
    /// Towards the lamp; a direction below the horizon means no lamp is on.
    pub light: [f64; 3],
    /// Towards the camera.
    pub view: [f64; 3],
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// Bits per pixel of the sensor; pixels clip at `2^bit_depth − 1`.
    pub bit_depth: u8,
    /// Exposure relative to the camera's nominal exposure.
    pub relative_exposure: f64,
    /// Analogue gain relative to nominal.
    pub gain: f64,
    /// The lamp's output relative to its nominal level: an HMI lamp
    /// drifts by a few per cent over hours ([`crate::scene::LampDrift`]).
    pub lamp_level: f64,
    /// Focal length in pixels of this frame, with `camera_distance_m` a
    /// pinhole camera; `None` an orthographic view of the whole plate.
    pub focal_px: Option<f64>,
    /// Distance from the sample centre to the camera, metres (used with
    /// `focal_px`).
    pub camera_distance_m: Option<f64>,
    /// A point lamp at this distance (irradiance falls off with the square
    /// of the distance); `None` a directional light.
    pub lamp_distance_m: Option<f64>,
    /// The laser line emitter's sheet of light, if the laser is on.
    pub laser: Option<LaserSheet>,
    /// A flat matte plate at this height over the holder hides the sample:
    /// the laser calibration plate of Wang et al., §3.2.
    pub plate_height_m: Option<f64>,
    /// Mixed into the scene's noise seed: one stream per frame.
    pub seed: u64,
    /// Effects this frame's request wants or forbids beyond the scene's.
    pub effects: EffectSwitches,
    /// Where the holder really sits in the plate plane, metres from the
    /// sample centre the rig's kinematics assume: the placement error a
    /// real rig has and its pose model does not know (markers see it, the
    /// pose does not).
    pub holder_offset_m: [f64; 2],
    /// A colour camera's filter array: each pixel records its own channel
    /// through the scene's colour response. `None`: a monochrome sensor.
    pub cfa: Option<rigd_core::Cfa>,
}

impl Default for Shot {
    fn default() -> Shot {
        Shot {
            light: [0.0, 0.0, 1.0],
            view: [0.0, 0.0, 1.0],
            width: 64,
            height: 48,
            bit_depth: 12,
            relative_exposure: 1.0,
            gain: 1.0,
            lamp_level: 1.0,
            focal_px: None,
            camera_distance_m: None,
            lamp_distance_m: None,
            laser: None,
            plate_height_m: None,
            seed: 0,
            effects: EffectSwitches::default(),
            holder_offset_m: [0.0, 0.0],
            cfa: None,
        }
    }
}

impl Shot {
    /// True when a lamp lights the frame: `light` points above the horizon.
    pub fn lamp_on(&self) -> bool {
        self.light[2] > 0.0
    }
}

/// The camera of a shot: the sample seen along `shot.view`, with the
/// field of an orthographic view just wider than the holder.
pub(crate) fn camera(scene: &Scene, shot: &Shot) -> Camera {
    let [dx, dy] = shot.holder_offset_m;
    // The camera aims at the rig's sample centre; in plate coordinates
    // that is `-offset` when the holder sits at `+offset`.
    Camera::new(
        shot.view,
        [shot.width, shot.height],
        shot.focal_px,
        shot.camera_distance_m,
        field_half(scene),
    )
    .translated([-dx, -dy, 0.0])
}

/// Half the field of an orthographic view: just wider than the holder.
fn field_half(scene: &Scene) -> f64 {
    1.1 * scene.holder.half
}
