//! Frames: which effects a shot ([`Shot`]) pays for ([`Scene::plan`]), and
//! the entry points that render it ([`Scene::render`],
//! [`Scene::render_linear`]) on the renderer's own threads; the pixel loop
//! itself is [`super::exposure`].

use super::effects::{Effect, EffectPlan, EffectSet};
use super::exposure::Exposure;
use super::sensor::Sensor;
use super::shot::{camera, Shot};
use super::Scene;

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
