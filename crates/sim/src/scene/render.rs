//! The renderer: one camera ray per pixel onto the holder plane or into the
//! heightfield, direct light from the lamp with its shadow, Lambert plus an
//! anisotropic Ward lobe, then the sensor. Each optional step runs only when
//! the frame's [`EffectPlan`] has it live, so a flat matte scene costs a
//! plane intersection and a texture lookup per pixel.
//!
//! Units: radiance is a reflectance factor, 1 for a white Lambertian
//! surface lit frontally by the lamp at its nominal distance; the sensor
//! maps that to [`WHITE_LEVEL`] of full scale at nominal exposure and gain.

use rayon::prelude::*;
use rigd_core::camera::Camera;
use rigd_core::geometry::{add, cross, dot, norm, normalize, scale, sub};
use serde::Serialize;

use super::effects::{Effect, EffectPlan, EffectSet, EffectSwitches};
use super::{Relief, Scene};

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
    Camera::new(
        shot.view,
        [shot.width, shot.height],
        shot.focal_px,
        shot.camera_distance_m,
        1.1 * scene.holder.half,
    )
}

/// The lamp as seen from the sample.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Lamp {
    dir: [f64; 3],
    distance: Option<f64>,
}

impl Lamp {
    pub(crate) fn new(shot: &Shot) -> Option<Lamp> {
        shot.lamp_on().then(|| Lamp {
            dir: normalize(shot.light),
            distance: shot.lamp_distance_m.filter(|d| *d > 0.0),
        })
    }

    /// Direction to the lamp from `p`, the inverse-square fall-off relative
    /// to the sample centre, and how far the lamp is.
    fn towards(&self, p: [f64; 3]) -> ([f64; 3], f64, f64) {
        match self.distance {
            None => (self.dir, 1.0, f64::INFINITY),
            Some(d) => {
                let to = sub(scale(self.dir, d), p);
                let r = norm(to);
                (scale(to, 1.0 / r), (d / r).powi(2), r)
            }
        }
    }
}

/// Everything shading needs for one frame.
pub(crate) struct Frame<'a> {
    pub scene: &'a Scene,
    pub plan: EffectPlan,
    pub lamp: Option<Lamp>,
    pub laser: Option<LaserSheet>,
    plate: Option<f64>,
}

/// Reflectance of the laser calibration plate (matte white paint).
pub const PLATE_ALBEDO: f64 = 0.8;

/// Cosine-weighted directions of the local hemisphere for the one-bounce
/// gather (fixed, so frames stay deterministic without an RNG).
const GATHER: [[f64; 2]; 8] = [
    [0.125, 0.0],
    [0.375, 0.25],
    [0.625, 0.5],
    [0.875, 0.75],
    [0.25, 0.125],
    [0.5, 0.375],
    [0.75, 0.625],
    [0.9, 0.875],
];

impl<'a> Frame<'a> {
    pub(crate) fn new(scene: &'a Scene, shot: &Shot) -> Frame<'a> {
        Frame {
            scene,
            plan: scene.plan(shot),
            lamp: Lamp::new(shot),
            laser: shot.laser,
            plate: shot.plate_height_m.filter(|h| h.is_finite() && *h > 0.0),
        }
    }

    fn relief(&self) -> Option<&'a Relief> {
        if self.plan.has(Effect::Relief) && self.plate.is_none() {
            self.scene.relief.as_ref()
        } else {
            None
        }
    }

    fn height(&self, x: f64, y: f64) -> f64 {
        if self.relief().is_some() {
            self.scene.height(x, y)
        } else {
            0.0
        }
    }

    fn normal(&self, x: f64, y: f64) -> [f64; 3] {
        if self.relief().is_some() {
            self.scene.normal(x, y)
        } else {
            [0.0, 0.0, 1.0]
        }
    }

    /// Where the ray `o + t d` first meets the surface.
    pub(crate) fn intersect(&self, o: [f64; 3], d: [f64; 3]) -> Option<[f64; 3]> {
        if d[2] >= -1e-9 {
            return None;
        }
        let t_floor = (o[2] - self.plate.unwrap_or(0.0)) / -d[2];
        let floor = add(o, scale(d, t_floor));
        let Some(relief) = self.relief() else {
            return Some(floor);
        };
        let top = relief.top + 1e-7;
        let t_top = ((o[2] - top) / -d[2]).max(0.0);
        let Some((ta, tb)) = self.clip_to_sample(o, d, t_top, t_floor) else {
            return Some(floor);
        };
        match self.march(relief, o, d, ta, tb, -1.0) {
            Some(t) => Some(add(o, scale(d, t))),
            None => Some(floor),
        }
    }

    /// The part of `[t0, t1]` where the ray is over the sample.
    fn clip_to_sample(&self, o: [f64; 3], d: [f64; 3], t0: f64, t1: f64) -> Option<(f64, f64)> {
        let (mut lo, mut hi) = (t0, t1);
        for k in 0..2 {
            let h = self.scene.sample_half[k];
            if d[k].abs() < 1e-15 {
                if o[k].abs() > h {
                    return None;
                }
            } else {
                let (a, b) = ((-h - o[k]) / d[k], (h - o[k]) / d[k]);
                lo = lo.max(a.min(b));
                hi = hi.min(a.max(b));
            }
        }
        (lo <= hi).then_some((lo, hi))
    }

    /// The first t in [ta, tb] where the ray is below the surface (or, for a
    /// shadow ray with `sign = 1`, any such t): conservative steps bounded
    /// by the steepest slope, then bisection.
    fn march(
        &self,
        relief: &Relief,
        o: [f64; 3],
        d: [f64; 3],
        ta: f64,
        tb: f64,
        sign: f64,
    ) -> Option<f64> {
        let horizontal = d[0].hypot(d[1]);
        let rate = d[2].abs() + relief.max_slope * horizontal;
        let min_step = 0.35 * relief.height.texel / horizontal.max(d[2].abs()).max(1e-6);
        let gap = |t: f64| {
            let p = add(o, scale(d, t));
            p[2] - self.scene.height(p[0], p[1])
        };
        let mut t_prev = ta;
        let mut t = ta;
        loop {
            let g = gap(t);
            if g <= 0.0 {
                if t == ta {
                    return Some(t);
                }
                let (mut lo, mut hi) = (t_prev, t);
                for _ in 0..12 {
                    let mid = 0.5 * (lo + hi);
                    if gap(mid) > 0.0 {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                return Some(hi);
            }
            if t >= tb || (sign > 0.0 && o[2] + t * d[2] > relief.top) {
                return None;
            }
            t_prev = t;
            t = (t + (g / rate).max(min_step)).min(tb);
        }
    }

    /// Whether the lamp is hidden from `p` (normal `n`) by the relief.
    fn shadowed(&self, p: [f64; 3], n: [f64; 3], to_lamp: [f64; 3], lamp_dist: f64) -> bool {
        let Some(relief) = self.relief() else {
            return false;
        };
        let start = add(p, scale(n, 0.5 * relief.height.texel));
        let t_max = if to_lamp[2] > 1e-9 {
            ((relief.top - start[2]) / to_lamp[2]).min(lamp_dist)
        } else {
            lamp_dist.min(1.0)
        };
        let Some((ta, tb)) = self.clip_to_sample(start, to_lamp, 0.0, t_max.max(0.0)) else {
            return false;
        };
        self.march(relief, start, to_lamp, ta, tb, 1.0).is_some()
    }

    /// Direct irradiance at `p` (cosine, fall-off, shadow), with its
    /// lamp direction.
    fn irradiance(&self, p: [f64; 3], n: [f64; 3]) -> (f64, [f64; 3]) {
        let Some(lamp) = self.lamp else {
            return (0.0, [0.0, 0.0, 1.0]);
        };
        let (l, falloff, dist) = lamp.towards(p);
        let cos = dot(n, l);
        if cos <= 0.0 {
            return (0.0, l);
        }
        let mut vis = 1.0;
        if self.plate.is_some() {
            // The plate lies over the sample: nothing shadows it.
        } else if self.plan.has(Effect::VisibilityMaps) {
            if let Some(maps) = &self.scene.visibility {
                vis = maps.visibility(p[0], p[1], l);
            }
        } else if self.plan.has(Effect::Shadows) && self.shadowed(p, n, l, dist) {
            vis = 0.0;
        }
        (cos * falloff * vis, l)
    }

    /// Irradiance blurred over the subsurface kernel: seven taps on the
    /// surface around `p`.
    fn blurred_irradiance(&self, p: [f64; 3], n: [f64; 3], e0: f64) -> f64 {
        let r = 1.2 * self.scene.subsurface;
        let mut sum = 0.4 * e0;
        for k in 0..6 {
            let a = k as f64 * std::f64::consts::FRAC_PI_3;
            let (x, y) = (p[0] + r * a.cos(), p[1] + r * a.sin());
            let q = [x, y, self.height(x, y)];
            let nq = if self.scene.on_sample(x, y) {
                self.normal(x, y)
            } else {
                n
            };
            sum += 0.1 * self.irradiance(q, nq).0;
        }
        sum
    }

    /// Light that arrives at `p` after one diffuse bounce inside the relief.
    fn bounce(&self, p: [f64; 3], n: [f64; 3]) -> f64 {
        let Some(relief) = self.relief() else {
            return 0.0;
        };
        let t = normalize(if n[0].abs() < 0.9 {
            cross(n, [1.0, 0.0, 0.0])
        } else {
            cross(n, [0.0, 1.0, 0.0])
        });
        let b = cross(n, t);
        let start = add(p, scale(n, 0.5 * relief.height.texel));
        let mut sum = 0.0;
        for [u, v] in GATHER {
            let (r, phi) = (u.sqrt(), std::f64::consts::TAU * v);
            let z = (1.0 - u).sqrt();
            let w = normalize(add(
                scale(t, r * phi.cos()),
                add(scale(b, r * phi.sin()), scale(n, z)),
            ));
            let t_max = if w[2] > 1e-9 {
                (relief.top - start[2]) / w[2]
            } else {
                0.02
            };
            let Some((ta, tb)) = self.clip_to_sample(start, w, 0.0, t_max.max(0.0)) else {
                continue;
            };
            if let Some(th) = self.march(relief, start, w, ta, tb, 1.0) {
                let q = add(start, scale(w, th));
                let nq = self.normal(q[0], q[1]);
                sum += self.scene.albedo(q[0], q[1]) * self.irradiance(q, nq).0;
            }
        }
        sum / GATHER.len() as f64
    }

    /// Outgoing radiance at surface point `p` towards `to_eye`.
    pub(crate) fn shade(&self, p: [f64; 3], to_eye: [f64; 3]) -> f64 {
        let (x, y) = (p[0], p[1]);
        let on_sample = self.plate.is_none() && self.scene.on_sample(x, y);
        let n = if on_sample {
            self.normal(x, y)
        } else {
            [0.0, 0.0, 1.0]
        };
        let albedo = match self.plate {
            Some(_) => PLATE_ALBEDO,
            None => self.scene.albedo(x, y),
        };
        let mut radiance = 0.0;
        if self.lamp.is_some() {
            let (e, l) = self.irradiance(p, n);
            let diffuse_e = if on_sample && self.plan.has(Effect::Subsurface) {
                self.blurred_irradiance(p, n, e)
            } else {
                e
            };
            radiance += albedo * diffuse_e;
            if on_sample && e > 0.0 && self.plan.has(Effect::Specular) {
                if let Some(spec) = &self.scene.specular {
                    radiance += e * ward(spec, n, l, to_eye);
                }
            }
            if on_sample && self.plan.has(Effect::Interreflection) {
                radiance += albedo * self.bounce(p, n);
            }
        }
        if let Some(laser) = &self.laser {
            if self.plan.has(Effect::Laser) {
                radiance += self.laser_radiance(laser, p, n, albedo);
            }
        }
        radiance
    }

    fn laser_radiance(&self, laser: &LaserSheet, p: [f64; 3], n: [f64; 3], albedo: f64) -> f64 {
        let sigma = (laser.width_m / 2.355).max(1e-7);
        let dist = dot(sub(p, laser.emitter), normalize(laser.normal));
        if dist.abs() > 3.0 * sigma {
            return 0.0;
        }
        let to = sub(laser.emitter, p);
        let r = norm(to);
        let l = scale(to, 1.0 / r);
        let cos = dot(n, l);
        if cos <= 0.0 || self.shadowed(p, n, l, r) {
            return 0.0;
        }
        laser.power * albedo * cos * (-0.5 * (dist / sigma).powi(2)).exp()
    }
}

/// Ward's anisotropic lobe times π, so that times the irradiance (which
/// carries cos θ_i) it adds to the reflectance factor; zero where the half
/// vector leaves the hemisphere.
fn ward(spec: &super::Specular, n: [f64; 3], l: [f64; 3], v: [f64; 3]) -> f64 {
    let (cl, cv) = (dot(n, l), dot(n, v));
    if cl <= 0.0 || cv <= 0.0 {
        return 0.0;
    }
    let h = normalize(add(l, v));
    let hn = dot(h, n);
    if hn <= 1e-6 {
        return 0.0;
    }
    let t0 = [spec.tangent[0], spec.tangent[1], 0.0];
    let t = normalize(sub(t0, scale(n, dot(t0, n))));
    let b = cross(n, t);
    let [ax, ay] = spec.alpha;
    let e = ((dot(h, t) / ax).powi(2) + (dot(h, b) / ay).powi(2)) / (hn * hn);
    // Grazing: the √(cos·cos) denominator is held away from zero.
    spec.strength / (4.0 * ax * ay * (cl * cv).max(1e-6).sqrt()) * (-e).exp()
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
    /// threads ([`render_pool`]).
    pub fn render(&self, shot: &Shot) -> Rendered {
        match render_pool() {
            Some(pool) => pool.install(|| self.render_here(shot)),
            None => self.render_here(shot),
        }
    }

    fn render_here(&self, shot: &Shot) -> Rendered {
        let (linear, plan) = self.render_linear(shot);
        let max_value = ((1u32 << shot.bit_depth.clamp(1, 16)) - 1) as f64;
        let noise = plan.has(Effect::Noise);
        let seed = self.sensor.seed ^ shot.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let (read, e_per_dn) = (self.sensor.read_noise_dn, self.sensor.electrons_per_dn);
        let pixels = linear
            .par_iter()
            .enumerate()
            .map(|(k, &v)| {
                let mut v = v as f64;
                if noise {
                    let mut var = read * read;
                    if e_per_dn > 0.0 {
                        var += v.max(0.0) / e_per_dn;
                    }
                    v += var.sqrt() * gaussian(seed, k as u64);
                }
                v.round().clamp(0.0, max_value) as u16
            })
            .collect();
        Rendered {
            width: shot.width.max(1),
            height: shot.height.max(1),
            bit_depth: shot.bit_depth.clamp(1, 16),
            pixels,
            plan,
        }
    }

    /// The frame before noise and quantisation, in digital numbers.
    pub fn render_linear(&self, shot: &Shot) -> (Vec<f32>, EffectPlan) {
        let (w, h) = (shot.width.max(1) as usize, shot.height.max(1) as usize);
        let max_value = ((1u32 << shot.bit_depth.clamp(1, 16)) - 1) as f64;
        let gain = WHITE_LEVEL * max_value * shot.relative_exposure.max(0.0) * shot.gain.max(0.0);
        let camera = camera(self, shot);
        let frame = Frame::new(self, shot);
        let vignette = frame
            .plan
            .has(Effect::Vignetting)
            .then_some(self.sensor.vignetting);
        let mut out = vec![0f32; w * h];
        out.par_chunks_mut(w).enumerate().for_each(|(j, row)| {
            for (i, px) in row.iter_mut().enumerate() {
                let (o, d) = camera.ray(i, j);
                let Some(p) = frame.intersect(o, d) else {
                    continue;
                };
                let mut v = frame.shade(p, scale(d, -1.0)) * gain;
                if let Some(s) = vignette {
                    v *= camera.vignetting(i, j, s);
                }
                *px = v as f32;
            }
        });
        (out, frame.plan)
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

/// A standard normal deviate from a counter-based hash: the same for a
/// (seed, pixel) whatever thread renders it.
fn gaussian(seed: u64, k: u64) -> f64 {
    let a = splitmix(seed ^ splitmix(k.wrapping_mul(2)));
    let b = splitmix(seed ^ splitmix(k.wrapping_mul(2) + 1));
    let u1 = ((a >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
    let u2 = (b >> 11) as f64 / (1u64 << 53) as f64;
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}
