//! Frames: what a shot asks for ([`Shot`]), which effects it pays for
//! ([`Scene::plan`]), and the entry points that render it
//! ([`Scene::render`], [`Scene::render_linear`]) on the renderer's own
//! threads; the pixel loop itself is [`super::exposure`].
//!
//! Units: radiance is a reflectance factor, 1 for a white Lambertian
//! surface lit frontally by the lamp at its nominal distance; the sensor
//! maps that to [`WHITE_LEVEL`] of full scale at nominal exposure and gain.

use rigd_core::camera::Camera;
use serde::Serialize;

use super::effects::{Effect, EffectPlan, EffectSet, EffectSwitches};
use super::exposure::Exposure;
use super::sensor::Sensor;
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

/// A rendered frame and the effects it paid for.
#[derive(Debug, Clone, PartialEq)]
pub struct Rendered {
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// Bits per pixel; no value exceeds `2^bit_depth − 1`.
    pub bit_depth: u8,
    /// Row-major, top row first, one value per pixel at the bit depth.
    pub pixels: Vec<u16>,
    /// Which effects the frame rendered, and which it could have.
    pub plan: EffectPlan,
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

impl Scene {
    /// Which effects a frame pays for: what the scene can show for this
    /// frame, filtered by the scene's and the request's switches.
    pub fn plan(&self, shot: &Shot) -> EffectPlan {
        let mut possible = self.capabilities();
        if !shot.lamp_on() {
            for e in [
                Effect::Shadows,
                Effect::Specular,
                Effect::Subsurface,
                Effect::Interreflection,
                Effect::VisibilityMaps,
            ] {
                possible.remove(e);
            }
        }
        if shot.laser.is_none() {
            possible.remove(Effect::Laser);
        }
        let mut plan = EffectPlan::decide(possible, self.want, self.forbid, shot.effects);
        // Shadows, bounces and the laser's occlusion march the relief.
        if !plan.live.contains(Effect::Relief) {
            plan.live.remove(Effect::Shadows);
            plan.live.remove(Effect::Interreflection);
        }
        plan
    }

    /// Renders a frame at the shot's bit depth, on the renderer's own
    /// threads ([`render_pool`]); a frame of one band of rows renders on
    /// the caller's thread, since handing it over costs more than it saves.
    pub fn render(&self, shot: &Shot) -> Rendered {
        let one_band = shot.height as usize <= super::exposure::BAND_ROWS;
        match render_pool() {
            Some(pool) if !one_band => pool.install(|| self.render_here(shot)),
            _ => self.render_here(shot),
        }
    }

    fn render_here(&self, shot: &Shot) -> Rendered {
        let exposure = Exposure::new(self, shot);
        let sensor = Sensor::new(&self.sensor, shot, exposure.plan());
        let mut pixels = vec![0u16; exposure.pixels()];
        exposure.fill(&mut pixels, |linear, first, codes| {
            sensor.read_out(linear, first, codes)
        });
        Rendered {
            width: shot.width.max(1),
            height: shot.height.max(1),
            bit_depth: shot.bit_depth.clamp(1, 16),
            pixels,
            plan: *exposure.plan(),
        }
    }

    /// The frame before noise and quantisation, in digital numbers.
    pub fn render_linear(&self, shot: &Shot) -> (Vec<f32>, EffectPlan) {
        let exposure = Exposure::new(self, shot);
        let mut out = vec![0f32; exposure.pixels()];
        exposure.fill(&mut out, |linear, _, out| out.copy_from_slice(linear));
        (out, *exposure.plan())
    }

    /// Pixel positions of every registration marker in this frame.
    pub fn marker_pixels(&self, shot: &Shot) -> Vec<(super::Marker, Option<[f64; 2]>)> {
        let camera = camera(self, shot);
        self.holder
            .markers()
            .into_iter()
            .map(|m| (m, camera.project([m.position[0], m.position[1], 0.0])))
            .collect()
    }

    /// Pixel position of a point of the plate (metres, z = 0) in this frame.
    pub fn plate_pixel(&self, shot: &Shot, plate: [f64; 2]) -> Option<[f64; 2]> {
        camera(self, shot).project([plate[0], plate[1], 0.0])
    }

    /// All effects this scene's frames could ever pay for, for logs.
    pub fn describe_effects(&self) -> String {
        let caps = self.capabilities();
        let wanted: EffectSet = caps.iter().filter(|e| self.want.contains(*e)).collect();
        format!(
            "scene `{}`: can show {}; wants {}; forbids {}",
            self.name, caps, wanted, self.forbid
        )
    }
}

/// The threads simulated cameras render on, apart from rayon's global pool:
/// processing on the global pool (a trade-off report, a BTF compression,
/// processing beside a capture) would otherwise queue a camera's frame
/// behind its own work until the camera missed its deadline. `None` if the
/// system would not start the threads; frames then render on the global
/// pool.
pub fn render_pool() -> Option<&'static rayon::ThreadPool> {
    static POOL: std::sync::OnceLock<Option<rayon::ThreadPool>> = std::sync::OnceLock::new();
    POOL.get_or_init(|| {
        let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("rigd-render-{i}"))
            .build()
            .ok()
    })
    .as_ref()
}
