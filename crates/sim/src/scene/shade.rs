//! Light transport for one frame: where a ray meets the surface (the holder
//! plane or the heightfield, marched), direct light from the lamp with its
//! shadow, Lambert plus an anisotropic Ward lobe, the subsurface blur, one
//! diffuse bounce and the laser line. Each optional step runs only when the
//! frame's [`EffectPlan`] has it live.
//!
//! Everything that is the same for every pixel of a frame (which effects
//! are live, the lamp, the blur taps and bounce directions, their trig) is
//! worked out once in [`Frame::new`]. A point can be shaded in one call
//! ([`Frame::shade`]) or in stages, so that the renderer can run the
//! marches of many pixels side by side: where its ray meets the surface
//! ([`Primary`]), what the surface is there ([`Surface`]), the lamp as seen
//! from there ([`Incidence`]) and whether the relief hides it
//! ([`Shadow`]), then the rest ([`Frame::shade_from`]). Either way the
//! arithmetic of each point is what it always was, operation for
//! operation, so frames stay bit for bit the same.

use rigd_core::geometry::{add, cross, dot, norm, normalize, scale, sub};

use super::colour::{filtered, NEUTRAL};
use super::effects::{Effect, EffectPlan};
use super::march::{March, Marcher};
use super::shot::{LaserSheet, Shot};
use super::surface::{Sampler, SurfaceTexels};
use super::visibility::VisibilityMaps;
use super::{Relief, Scene, Specular};

/// Reflectance of the laser calibration plate (matte white paint).
pub(crate) const PLATE_ALBEDO: f64 = 0.8;

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

/// Taps of the subsurface blur around the centre one.
const BLUR_TAPS: usize = 6;

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

    /// The lamp as seen from `p` on a surface of normal `n`: the direction
    /// to it, the inverse-square fall-off relative to the sample centre,
    /// how far it is and the cosine of its incidence.
    #[inline]
    pub(crate) fn incidence(&self, p: [f64; 3], n: [f64; 3]) -> Incidence {
        let (dir, falloff, distance) = match self.distance {
            None => (self.dir, 1.0, f64::INFINITY),
            Some(d) => {
                let to = sub(scale(self.dir, d), p);
                let r = norm(to);
                (scale(to, 1.0 / r), (d / r).powi(2), r)
            }
        };
        Incidence {
            dir,
            falloff,
            distance,
            cos: dot(n, dir),
        }
    }
}

/// The lamp as seen from one surface point: see [`Lamp::incidence`].
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Incidence {
    /// Unit direction to the lamp.
    dir: [f64; 3],
    /// Inverse-square fall-off relative to the sample centre.
    falloff: f64,
    /// How far the lamp is, metres.
    distance: f64,
    /// Cosine between the surface normal and `dir`.
    cos: f64,
}

/// What a surface point is: on the sample or not, its normal, albedo and
/// (in a colour frame) tint.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Surface {
    on_sample: bool,
    pub normal: [f64; 3],
    albedo: f64,
    /// The tint over the albedo (luminance 1); read only in colour frames.
    tint: [f64; 3],
}

/// What may hide the lamp from a lit point in this frame.
#[derive(Clone, Copy)]
enum Occlusion<'a> {
    /// Nothing: a flat or plate-covered sample, or shadows not live.
    None,
    /// The macro shape's visibility maps.
    Maps(&'a VisibilityMaps),
    /// Shadow rays marched through the relief.
    Shadows,
}

/// Everything shading needs for one frame.
pub(crate) struct Frame<'a> {
    pub scene: &'a Scene,
    pub plan: EffectPlan,
    pub lamp: Option<Lamp>,
    plate: Option<f64>,
    /// The relief when rays march it this frame (live, no plate over it).
    relief: Option<&'a Relief>,
    /// Its albedo, gradient and height interleaved, when they share a
    /// layout.
    texels: Option<&'a SurfaceTexels>,
    marcher: Option<Marcher<'a>>,
    albedo: Sampler<'a>,
    occlusion: Occlusion<'a>,
    /// The laser's sheet when the laser line is live.
    laser: Option<LaserSheet>,
    specular: Option<&'a Specular>,
    subsurface: bool,
    interreflection: bool,
    /// Whether the camera records colour, so surfaces need their tint.
    pub(crate) colour: bool,
    /// Offsets of the subsurface blur's outer taps from the centre.
    blur_offsets: [[f64; 2]; BLUR_TAPS],
    /// The gather directions in the local frame: along the tangent, the
    /// bitangent and the normal.
    gather: [[f64; 3]; GATHER.len()],
}

impl<'a> Frame<'a> {
    pub(crate) fn new(scene: &'a Scene, shot: &Shot) -> Frame<'a> {
        let plan = scene.plan(shot);
        let plate = shot.plate_height_m.filter(|h| h.is_finite() && *h > 0.0);
        let relief = if plan.has(Effect::Relief) && plate.is_none() {
            scene.relief.as_ref()
        } else {
            None
        };
        let occlusion = if plate.is_some() {
            // The plate lies over the sample: nothing shadows it.
            Occlusion::None
        } else if plan.has(Effect::VisibilityMaps) {
            scene
                .visibility
                .as_ref()
                .map_or(Occlusion::None, Occlusion::Maps)
        } else if plan.has(Effect::Shadows) && relief.is_some() {
            Occlusion::Shadows
        } else {
            Occlusion::None
        };
        let r = 1.2 * scene.subsurface;
        let blur_offsets = std::array::from_fn(|k| {
            let a = k as f64 * std::f64::consts::FRAC_PI_3;
            [r * a.cos(), r * a.sin()]
        });
        let gather = GATHER.map(|[u, v]| {
            let (r, phi) = (u.sqrt(), std::f64::consts::TAU * v);
            [r * phi.cos(), r * phi.sin(), (1.0 - u).sqrt()]
        });
        Frame {
            scene,
            plan,
            lamp: Lamp::new(shot),
            plate,
            relief,
            texels: relief.and_then(|r| r.texels.as_ref()),
            marcher: relief.map(|r| Marcher::new(r, scene.sample_half)),
            albedo: scene.albedo.sampler(),
            occlusion,
            laser: shot.laser.filter(|_| plan.has(Effect::Laser)),
            specular: scene
                .specular
                .as_ref()
                .filter(|_| plan.has(Effect::Specular)),
            subsurface: plan.has(Effect::Subsurface),
            interreflection: plan.has(Effect::Interreflection),
            colour: shot.cfa.is_some(),
            blur_offsets,
            gather,
        }
    }

    /// True when a point off the holder plate shades to exactly 0 in this
    /// frame (albedo 0 there, every factor it multiplies finite), so the
    /// renderer may skip it: no calibration plate covers the sample, the
    /// lamp is at a finite distance or directional, and the laser sheet,
    /// if live, is finite.
    pub(crate) fn black_off_holder(&self) -> bool {
        let lamp_finite = self
            .lamp
            .is_none_or(|l| l.distance.is_none_or(f64::is_finite));
        let laser_finite = self.laser.is_none_or(|l| {
            l.emitter.iter().chain(&l.normal).all(|v| v.is_finite())
                && l.width_m.is_finite()
                && l.power.is_finite()
        });
        self.plate.is_none() && lamp_finite && laser_finite
    }

    /// Whether camera rays march the relief this frame.
    pub(crate) fn marches_relief(&self) -> bool {
        self.marcher.is_some()
    }

    /// Whether the lamp's visibility takes shadow rays this frame.
    pub(crate) fn marches_shadows(&self) -> bool {
        matches!(self.occlusion, Occlusion::Shadows)
    }

    /// The relief's top, when rays march the relief this frame.
    pub(crate) fn relief_top(&self) -> Option<f64> {
        self.relief.map(|r| r.top)
    }

    /// The shading normal at (x, y): the relief's when it is marched.
    #[inline]
    fn normal(&self, x: f64, y: f64) -> [f64; 3] {
        if self.relief.is_some() {
            self.scene.normal(x, y)
        } else {
            [0.0, 0.0, 1.0]
        }
    }

    /// The normal and albedo at (x, y) of the sample (`on_sample` must
    /// hold), from the interleaved texels when there are.
    #[inline]
    fn sample_surface(&self, x: f64, y: f64) -> ([f64; 3], f64) {
        match (self.relief, self.texels) {
            (Some(_), Some(t)) => {
                let s = t.sample(x, y);
                (gradient_normal(s.grad), s.albedo)
            }
            (Some(_), None) => (self.scene.normal(x, y), self.albedo.sample(x, y)),
            (None, _) => ([0.0, 0.0, 1.0], self.albedo.sample(x, y)),
        }
    }

    /// Where the ray `o + t d` first meets the surface.
    pub(crate) fn intersect(&self, o: [f64; 3], d: [f64; 3]) -> Option<[f64; 3]> {
        let mut primary = [self.primary(o, d)];
        self.march_primaries(&mut primary);
        primary[0].point()
    }

    /// Where the ray `o + t d` meets the floor (or the calibration plate),
    /// and whether it must march the relief first.
    #[inline]
    pub(crate) fn primary(&self, o: [f64; 3], d: [f64; 3]) -> Primary {
        if d[2] >= -1e-9 {
            return Primary::Miss;
        }
        let t_floor = (o[2] - self.plate.unwrap_or(0.0)) / -d[2];
        let floor = add(o, scale(d, t_floor));
        let Some(relief) = self.relief else {
            return Primary::Floor(floor);
        };
        let top = relief.top + 1e-7;
        let t_top = ((o[2] - top) / -d[2]).max(0.0);
        match self.clip_to_sample(o, d, t_top, t_floor) {
            Some((ta, tb)) => Primary::Relief {
                march: March::new(o, d, ta, tb, false),
                floor,
            },
            None => Primary::Floor(floor),
        }
    }

    /// Marches the primary rays of `primaries` that meet the relief's box,
    /// side by side.
    pub(crate) fn march_primaries(&self, primaries: &mut [Primary]) {
        if let Some(m) = &self.marcher {
            m.run_in(primaries, |p| match p {
                Primary::Relief { march, .. } => Some(march),
                _ => None,
            });
        }
    }

    /// The part of `[t0, t1]` where the ray is over the sample.
    #[inline]
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

    /// The march that decides whether the relief hides the lamp from `p`
    /// (normal `n`); `None` when it cannot (no relief, or the shadow ray
    /// never passes over the sample).
    #[inline]
    fn shadow_march(
        &self,
        p: [f64; 3],
        n: [f64; 3],
        to_lamp: [f64; 3],
        lamp_dist: f64,
    ) -> Option<March> {
        let relief = self.relief?;
        let start = add(p, scale(n, 0.5 * relief.height.texel));
        let t_max = if to_lamp[2] > 1e-9 {
            ((relief.top - start[2]) / to_lamp[2]).min(lamp_dist)
        } else {
            lamp_dist.min(1.0)
        };
        let (ta, tb) = self.clip_to_sample(start, to_lamp, 0.0, t_max.max(0.0))?;
        Some(March::new(start, to_lamp, ta, tb, true))
    }

    /// Whether the lamp is hidden from `p` (normal `n`) by the relief.
    fn shadowed(&self, p: [f64; 3], n: [f64; 3], to_lamp: [f64; 3], lamp_dist: f64) -> bool {
        match (self.marcher, self.shadow_march(p, n, to_lamp, lamp_dist)) {
            (Some(m), Some(march)) => m.one(march).is_some(),
            _ => false,
        }
    }

    /// Direct irradiance at each point `q` of normal `n` (cosine, fall-off,
    /// shadow) into `out`, their shadow rays marched side by side. At most
    /// [`GATHER`]`.len()` points.
    fn irradiance_batch(&self, points: &[([f64; 3], [f64; 3])], out: &mut [f64]) {
        debug_assert!(points.len() <= GATHER.len() && out.len() >= points.len());
        let Some(lamp) = self.lamp else {
            out.fill(0.0);
            return;
        };
        let mut incidence = [Incidence::default(); GATHER.len()];
        let mut shadows = [Shadow::Known(1.0); GATHER.len()];
        let n = points.len().min(GATHER.len());
        for (k, &(q, nq)) in points.iter().take(n).enumerate() {
            incidence[k] = lamp.incidence(q, nq);
            shadows[k] = self.shadow(q, nq, &incidence[k]);
        }
        self.resolve(&mut shadows[..n]);
        for k in 0..n {
            out[k] = direct(&incidence[k], shadows[k].visibility());
        }
    }

    /// What decides the lamp's visibility at `q` (normal `n`): known at
    /// once, or a shadow ray to march ([`Frame::resolve`]).
    #[inline]
    pub(crate) fn shadow(&self, q: [f64; 3], n: [f64; 3], inc: &Incidence) -> Shadow {
        if inc.cos <= 0.0 {
            // Unlit whatever hides the lamp: the visibility is never read.
            return Shadow::Known(1.0);
        }
        match self.occlusion {
            Occlusion::None => Shadow::Known(1.0),
            Occlusion::Maps(maps) => Shadow::Known(maps.visibility(q[0], q[1], inc.dir)),
            Occlusion::Shadows => match self.shadow_march(q, n, inc.dir, inc.distance) {
                Some(march) => Shadow::March(march),
                None => Shadow::Known(1.0),
            },
        }
    }

    /// Marches the shadow rays of `shadows`, side by side.
    pub(crate) fn resolve(&self, shadows: &mut [Shadow]) {
        if let Some(m) = &self.marcher {
            m.run_in(shadows, |s| match s {
                Shadow::March(march) => Some(march),
                Shadow::Known(_) => None,
            });
        }
    }

    /// Irradiance blurred over the subsurface kernel: seven taps on the
    /// surface around `p`.
    fn blurred_irradiance(&self, p: [f64; 3], n: [f64; 3], e0: f64) -> f64 {
        let mut taps = [([0.0; 3], [0.0; 3]); BLUR_TAPS];
        for (tap, [dx, dy]) in taps.iter_mut().zip(self.blur_offsets) {
            let (x, y) = (p[0] + dx, p[1] + dy);
            let (h, nq) = match self.relief {
                Some(_) if self.scene.on_sample(x, y) => match self.texels {
                    Some(t) => {
                        let s = t.sample(x, y);
                        (s.height, gradient_normal(s.grad))
                    }
                    None => (self.scene.height(x, y), self.scene.normal(x, y)),
                },
                Some(_) => (0.0, n),
                None if self.scene.on_sample(x, y) => (0.0, [0.0, 0.0, 1.0]),
                None => (0.0, n),
            };
            *tap = ([x, y, h], nq);
        }
        let mut e = [0.0; BLUR_TAPS];
        self.irradiance_batch(&taps, &mut e);
        let mut sum = 0.4 * e0;
        for e in e {
            sum += 0.1 * e;
        }
        sum
    }

    /// Light that arrives at `p` after one diffuse bounce inside the relief.
    fn bounce(&self, p: [f64; 3], n: [f64; 3]) -> f64 {
        let Some(relief) = self.relief else {
            return 0.0;
        };
        let t = normalize(if n[0].abs() < 0.9 {
            cross(n, [1.0, 0.0, 0.0])
        } else {
            cross(n, [0.0, 1.0, 0.0])
        });
        let b = cross(n, t);
        let start = add(p, scale(n, 0.5 * relief.height.texel));
        let mut rays = [March::finished(); GATHER.len()];
        let mut count = 0;
        for [along_t, along_b, along_n] in self.gather {
            let w = normalize(add(
                scale(t, along_t),
                add(scale(b, along_b), scale(n, along_n)),
            ));
            let t_max = if w[2] > 1e-9 {
                (relief.top - start[2]) / w[2]
            } else {
                0.02
            };
            if let Some((ta, tb)) = self.clip_to_sample(start, w, 0.0, t_max.max(0.0)) {
                rays[count] = March::new(start, w, ta, tb, true);
                count += 1;
            }
        }
        if let Some(m) = &self.marcher {
            m.run(&mut rays[..count]);
        }
        // The rays that hit, in gather order, with what they hit.
        let mut hits = [([0.0; 3], [0.0; 3]); GATHER.len()];
        let mut albedo = [0.0; GATHER.len()];
        let mut found = 0;
        for ray in &rays[..count] {
            if let Some(th) = ray.hit() {
                let (start, w) = ray.ray();
                let q = add(start, scale(w, th));
                let (nq, a) = if self.scene.on_sample(q[0], q[1]) {
                    self.sample_surface(q[0], q[1])
                } else {
                    (self.normal(q[0], q[1]), self.scene.albedo(q[0], q[1]))
                };
                hits[found] = (q, nq);
                albedo[found] = a;
                found += 1;
            }
        }
        let mut e = [0.0; GATHER.len()];
        self.irradiance_batch(&hits[..found], &mut e[..found]);
        let mut sum = 0.0;
        for k in 0..found {
            sum += albedo[k] * e[k];
        }
        sum / GATHER.len() as f64
    }

    /// Outgoing radiance at surface point `p` towards `to_eye`, grey or
    /// through `filter` (see [`Frame::shade_from`]).
    pub(crate) fn shade(&self, p: [f64; 3], to_eye: [f64; 3], filter: Option<&[f64; 3]>) -> f64 {
        let surface = self.surface(p);
        let lit = self.lamp.map(|lamp| {
            let inc = lamp.incidence(p, surface.normal);
            let mut shadow = [self.shadow(p, surface.normal, &inc)];
            self.resolve(&mut shadow);
            (inc, direct(&inc, shadow[0].visibility()))
        });
        self.shade_from(p, to_eye, &surface, lit.as_ref(), filter)
    }

    /// What the surface is at point `p`.
    #[inline]
    pub(crate) fn surface(&self, p: [f64; 3]) -> Surface {
        let (x, y) = (p[0], p[1]);
        if self.plate.is_none() && self.scene.on_sample(x, y) {
            let (normal, albedo) = self.sample_surface(x, y);
            Surface {
                on_sample: true,
                normal,
                albedo,
                tint: if self.colour {
                    self.scene.tint(x, y)
                } else {
                    NEUTRAL
                },
            }
        } else {
            let albedo = match self.plate {
                Some(_) => PLATE_ALBEDO,
                None => self.scene.holder.albedo(x, y),
            };
            // Only a colour patch tints the plate; `albedo` is its luminance.
            let patch = match self.plate {
                None if self.colour && albedo > 0.0 => self.scene.holder.patch_at(x, y),
                _ => None,
            };
            let tint = patch.map_or(NEUTRAL, |p| p.rgb.map(|v| v / albedo));
            Surface {
                on_sample: false,
                normal: [0.0, 0.0, 1.0],
                albedo,
                tint,
            }
        }
    }

    /// Outgoing radiance at `p` towards `to_eye`, given what the surface is
    /// there and, when a lamp is on, the lamp as seen from there and the
    /// direct irradiance it gives: grey, or through `filter`, what a
    /// channel records of unit linear-sRGB red, green and blue (a colour
    /// camera's photosite: a row of the scene's colour response; a
    /// channel of linear sRGB itself: a unit vector).
    #[inline]
    pub(crate) fn shade_from(
        &self,
        p: [f64; 3],
        to_eye: [f64; 3],
        surface: &Surface,
        lit: Option<&(Incidence, f64)>,
        filter: Option<&[f64; 3]>,
    ) -> f64 {
        let &Surface {
            on_sample,
            normal: n,
            albedo,
            tint,
        } = surface;
        // A photosite records the albedo through its filter, and white
        // light (the highlight) at its channel's efficiency.
        let (albedo, white) = match filter {
            None => (albedo, None),
            Some(f) => (albedo * filtered(f, tint), Some(filtered(f, NEUTRAL))),
        };
        let mut radiance = 0.0;
        if let Some(&(inc, e)) = lit {
            let diffuse_e = if on_sample && self.subsurface {
                self.blurred_irradiance(p, n, e)
            } else {
                e
            };
            radiance += albedo * diffuse_e;
            if on_sample && e > 0.0 {
                if let Some(spec) = self.specular {
                    let highlight = e * ward(spec, n, inc.dir, to_eye);
                    radiance += white.map_or(highlight, |w| w * highlight);
                }
            }
            if on_sample && self.interreflection {
                radiance += albedo * self.bounce(p, n);
            }
        }
        if let Some(laser) = &self.laser {
            radiance += self.laser_radiance(laser, p, n, albedo);
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

/// Where a camera ray meets the surface, before and after its march.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Primary {
    /// The ray never comes down to the floor.
    Miss,
    /// The floor (or the calibration plate), without passing the relief.
    Floor([f64; 3]),
    /// Through the relief's box: its march, and the floor point it reaches
    /// if the march finds no surface.
    Relief { march: March, floor: [f64; 3] },
}

impl Primary {
    /// Where the ray meets the surface (its march done, if it has one).
    #[inline]
    pub(crate) fn point(&self) -> Option<[f64; 3]> {
        match *self {
            Primary::Miss => None,
            Primary::Floor(p) => Some(p),
            Primary::Relief { march, floor } => Some(match march.hit() {
                Some(t) => {
                    let (o, d) = march.ray();
                    add(o, scale(d, t))
                }
                None => floor,
            }),
        }
    }
}

/// The lamp's visibility at a lit point: known, or a shadow ray whose
/// march decides it.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Shadow {
    Known(f64),
    March(March),
}

impl Shadow {
    /// The visibility, once any march is done: 0 when the ray met the
    /// relief.
    #[inline]
    pub(crate) fn visibility(&self) -> f64 {
        match self {
            Shadow::Known(v) => *v,
            Shadow::March(m) => {
                if m.hit().is_some() {
                    0.0
                } else {
                    1.0
                }
            }
        }
    }
}

/// Direct irradiance: cosine, fall-off and the lamp's visibility; 0 when
/// the lamp is behind the surface.
#[inline]
pub(crate) fn direct(inc: &Incidence, visibility: f64) -> f64 {
    if inc.cos <= 0.0 {
        0.0
    } else {
        inc.cos * inc.falloff * visibility
    }
}

/// The unit normal of a surface with height gradient `grad`, as
/// [`Scene::normal`] computes it on the sample.
#[inline]
fn gradient_normal([gx, gy]: [f64; 2]) -> [f64; 3] {
    let len = (gx * gx + gy * gy + 1.0).sqrt();
    [-gx / len, -gy / len, 1.0 / len]
}

/// Ward's anisotropic lobe times π, so that times the irradiance (which
/// carries cos θ_i) it adds to the reflectance factor; zero where the half
/// vector leaves the hemisphere.
fn ward(spec: &Specular, n: [f64; 3], l: [f64; 3], v: [f64; 3]) -> f64 {
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
