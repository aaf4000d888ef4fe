//! The reference relighting: a compressed BTF relit on a [`Mesh`] on the CPU,
//! exactly as the browser viewer (`/viewer/{run}`) does it on the GPU, so it
//! is the ground truth of the viewer's browser test.
//!
//! # The image, step by step (the viewer's shader does the same)
//!
//! 1. **Camera.** An orbit camera at [`CAMERA_DISTANCE`] from the origin in
//!    the direction (θ_v, φ_v) of the world's upper hemisphere, looking at
//!    the origin; screen right is the φ direction (−sin φ, cos φ, 0), screen
//!    up is −∂/∂θ, so the pole view θ = 0 is well defined for every φ.
//!    Perspective with a vertical field of view of [`FOV_DEG`], near 0.1,
//!    far 20, as `gl.perspective` builds it. Pixel centres at half-integers,
//!    row 0 at the top.
//! 2. **Raster.** Triangles with a depth test, no culling; attributes are
//!    interpolated perspective-correctly (as GL varyings are).
//! 3. **Local frame.** Per pixel: n = normalise(interpolated normal), t the
//!    interpolated tangent made orthogonal to n, b = n × t. The world light
//!    L and the direction to the eye V give the local l = (L·t, L·b, L·n)
//!    and v likewise; θ = acos(z), φ = atan2(y, x).
//! 4. **BTF.** The four nearest view slots of v (Sattler et al. eq. 5) and, in
//!    each, the light weights interpolated from the four nearest measured
//!    light directions of l (eq. 3): `value = Σ_s ω_s (M_s + Σ_k γ_sk B_sk)`
//!    with `γ_sk = Σ_i τ_i p_isk`, every texture sampled bilinearly with
//!    wrap-around at texture coordinates (s, −r): the material tiles the
//!    mesh, row 0 of a normtexture being the sample's +y edge.
//! 5. **Smooth shadow boundary** (Sattler et al., §4.3, eq. 6). Per vertex
//!    `u = (1 + cos(α + ∠(n_V, L))) / 2`, interpolated, then
//!    `smoothstep(0.5, 0.5 + SHADOW_SOFTNESS, u)`: 0 from where the light
//!    meets the smooth surface's horizon, so a light below the horizon adds
//!    no light (and never negative light).
//! 6. **Display.** `clamp(exposure · shadow · value, 0, 1)^(1/2.2)`, to
//!    8 bits by rounding; the background is [`BACKGROUND`].
//!
//! [`Shading::Plain`] is the comparison Sattler et al.'s figures 13–14 make: the
//! same mesh with one plain texture (the BTF at frontal light and view)
//! shaded by Lambert's cosine.

use rayon::prelude::*;

use crate::btf::{BtfError, CompressedBtf};
use crate::directions::{Direction, DirectionError, Interpolation};
use crate::mesh::Mesh;
use rigd_core::geometry::{cross, dot, scale, sub, unit};

/// Distance of the orbit camera from the origin, world units (the meshes
/// are about two units across).
pub const CAMERA_DISTANCE: f64 = 4.5;
/// Vertical field of view of the camera, degrees.
pub const FOV_DEG: f64 = 40.0;
const NEAR: f64 = 0.1;
const FAR: f64 = 20.0;
/// Display value of pixels the mesh does not cover.
pub const BACKGROUND: f64 = 0.12;
/// Width of the blurred edge of eq. 6's half-black, half-white texture.
pub const SHADOW_SOFTNESS: f64 = 0.05;
/// Display gamma: the output is `clamp(linear, 0, 1)^(1/DISPLAY_GAMMA)`.
pub const DISPLAY_GAMMA: f64 = 2.2;
/// Largest image side, pixels.
pub const MAX_SIDE: usize = 4096;

/// Why [`relight`] refused to render.
#[derive(Debug, thiserror::Error)]
pub enum RelightError {
    /// An error of the compressed BTF store.
    #[error(transparent)]
    Btf(#[from] BtfError),
    /// A light or view direction to interpolate at is not finite.
    #[error(transparent)]
    Direction(#[from] DirectionError),
    /// The image size is 0 or above [`MAX_SIDE`] on a side.
    #[error("image size {width}×{height}: each side must be 1 … {MAX_SIDE}")]
    Size {
        /// Requested width, pixels.
        width: usize,
        /// Requested height, pixels.
        height: usize,
    },
    /// The exposure is not a positive finite number.
    #[error("exposure {0} must be a positive finite number")]
    Exposure(f64),
    /// The view's θ (degrees, given) is outside 0 … 89°, or the view is not
    /// finite.
    #[error("view θ = {0}° is outside the orbit camera's 0 … 89°")]
    ViewElevation(f64),
}

/// What the mesh shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shading {
    /// The BTF: view and light dependent texture (Sattler et al., §4).
    Btf,
    /// One texture (frontal light and view) and Lambert's cosine.
    Plain,
}

/// What [`relight`] renders and how.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelightSettings {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Directional light, world frame (θ from +z, φ from +x).
    pub light: Direction,
    /// Orbit camera direction, world frame.
    pub view: Direction,
    /// Factor on the linear value before clamping and gamma; positive.
    pub exposure: f64,
    /// Eq. 6's offset α, degrees.
    pub shadow_alpha_deg: f64,
    /// The BTF, or the plain-texture comparison.
    pub shading: Shading,
}

impl Default for RelightSettings {
    fn default() -> Self {
        RelightSettings {
            width: 512,
            height: 512,
            light: Direction::new(30.0, 45.0),
            view: Direction::new(35.0, 270.0),
            exposure: 1.0,
            shadow_alpha_deg: 0.0,
            shading: Shading::Btf,
        }
    }
}

/// An 8-bit RGB image, rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// `width · height` RGB triples, row-major from the top row.
    pub pixels: Vec<u8>,
    /// Per pixel: true where the mesh covers it.
    pub covered: Vec<bool>,
}

/// Unit vector of a world direction.
fn world(d: Direction) -> [f64; 3] {
    d.to_vector()
}

/// The camera: eye position and the combined view-projection matrix
/// (row-major, acting on column vectors).
#[derive(Debug, Clone, Copy)]
pub struct Camera {
    /// Eye position, world frame.
    pub eye: [f64; 3],
    /// Projection × view: world point (x, y, z, 1) → clip coordinates.
    pub view_projection: [[f64; 4]; 4],
}

impl Camera {
    /// The orbit camera of the module doc (step 1) for view direction `view`
    /// and aspect ratio `aspect` = width / height.
    pub fn orbit(view: Direction, aspect: f64) -> Camera {
        let (st, ct) = view.theta_deg.to_radians().sin_cos();
        let (sp, cp) = view.phi_deg.to_radians().sin_cos();
        let back = [st * cp, st * sp, ct];
        let right = [-sp, cp, 0.0];
        let up = [-ct * cp, -ct * sp, st];
        let eye = scale(back, CAMERA_DISTANCE);
        let view_rows = [
            [right[0], right[1], right[2], -dot(right, eye)],
            [up[0], up[1], up[2], -dot(up, eye)],
            [back[0], back[1], back[2], -dot(back, eye)],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let f = 1.0 / (FOV_DEG.to_radians() / 2.0).tan();
        let projection = [
            [f / aspect, 0.0, 0.0, 0.0],
            [0.0, f, 0.0, 0.0],
            [
                0.0,
                0.0,
                (FAR + NEAR) / (NEAR - FAR),
                2.0 * FAR * NEAR / (NEAR - FAR),
            ],
            [0.0, 0.0, -1.0, 0.0],
        ];
        let mut vp = [[0.0; 4]; 4];
        for (r, row) in vp.iter_mut().enumerate() {
            for (c, cell) in row.iter_mut().enumerate() {
                *cell = (0..4).map(|k| projection[r][k] * view_rows[k][c]).sum();
            }
        }
        Camera {
            eye,
            view_projection: vp,
        }
    }

    fn clip(&self, p: [f64; 3]) -> [f64; 4] {
        let m = &self.view_projection;
        let row = |r: usize| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3];
        [row(0), row(1), row(2), row(3)]
    }
}

/// θ and φ (degrees) of a local direction; φ = 0 at the pole.
pub fn local_angles(local: [f64; 3]) -> Direction {
    let theta = local[2].clamp(-1.0, 1.0).acos().to_degrees();
    let phi = local[1].atan2(local[0]).to_degrees();
    Direction::new(theta, phi)
}

/// Eq. 6's texture coordinate at a vertex with unit normal `n`.
pub fn shadow_coordinate(n: [f64; 3], light: [f64; 3], alpha_deg: f64) -> f64 {
    let angle = dot(n, light).clamp(-1.0, 1.0).acos();
    (1.0 + (alpha_deg.to_radians() + angle).cos()) / 2.0
}

/// The blurred half-black, half-white lookup of eq. 6.
pub fn shadow_factor(u: f64) -> f64 {
    let t = ((u - 0.5) / SHADOW_SOFTNESS).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Bilinear sample with wrap-around of one texture (texel-major, channels
/// interleaved) at texture coordinates (s, t) in tiles, as GL's `LINEAR`
/// filter with `REPEAT` does; adds `weight ×` the sample to `out`.
fn sample_add(
    texture: &[f32],
    width: usize,
    height: usize,
    channels: usize,
    st: [f64; 2],
    weight: f64,
    out: &mut [f64; 3],
) {
    let x = st[0] * width as f64 - 0.5;
    let y = st[1] * height as f64 - 0.5;
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let wrap = |i: f64, n: usize| (i.rem_euclid(n as f64) as usize).min(n - 1);
    let (xa, xb) = (wrap(x0, width), wrap(x0 + 1.0, width));
    let (ya, yb) = (wrap(y0, height), wrap(y0 + 1.0, height));
    for (xi, yi, w) in [
        (xa, ya, (1.0 - fx) * (1.0 - fy)),
        (xb, ya, fx * (1.0 - fy)),
        (xa, yb, (1.0 - fx) * fy),
        (xb, yb, fx * fy),
    ] {
        let base = (yi * width + xi) * channels;
        for (c, o) in out.iter_mut().enumerate() {
            let v = texture[base + c.min(channels - 1)];
            *o += weight * w * f64::from(v);
        }
    }
}

/// The BTF's value (RGB; grey repeated) at texture coordinate `st` for the
/// given view-slot and light weights.
fn btf_value(
    store: &CompressedBtf,
    views: &Interpolation,
    lights: &Interpolation,
    st: [f64; 2],
) -> [f64; 3] {
    let shape = store.shape();
    let (w, h, ch) = (shape.width(), shape.height(), shape.channels());
    let mut out = [0.0; 3];
    for &(slot, omega) in views.entries() {
        let Some(pca) = store.slots().get(slot) else {
            continue;
        };
        sample_add(pca.mean(), w, h, ch, st, omega, &mut out);
        for k in 0..pca.components() {
            let gamma: f64 = lights
                .entries()
                .iter()
                .filter_map(|&(i, tau)| pca.light_weights(i).map(|p| tau * f64::from(p[k])))
                .sum();
            if gamma == 0.0 {
                continue;
            }
            if let Some(texture) = pca.eigen_texture(k) {
                sample_add(texture, w, h, ch, st, omega * gamma, &mut out);
            }
        }
    }
    out
}

/// A triangle's fragment at a pixel: the triangle, its perspective-correct
/// barycentric weights, its depth (NDC z) and whether its winding faces
/// the viewer (`gl_FrontFacing`).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Fragment {
    pub(crate) triangle: usize,
    pub(crate) bary: [f64; 3],
    pub(crate) depth: f64,
    pub(crate) front: bool,
}

/// Per pixel, the fragments of the triangles covering its centre, nearest
/// first, at most `layers` of them (1: the depth test's winner alone).
/// `clip` takes a world point to clip coordinates; `to_viewer` gives the
/// direction from a point towards the viewer, for the facing.
pub(crate) fn rasterise_layers(
    mesh: &Mesh,
    clip: &dyn Fn([f64; 3]) -> [f64; 4],
    to_viewer: &dyn Fn([f64; 3]) -> [f64; 3],
    (width, height): (usize, usize),
    layers: usize,
) -> Vec<Vec<Fragment>> {
    let clips: Vec<[f64; 4]> = (0..mesh.vertex_count())
        .map(|v| clip(mesh.position(v)))
        .collect();
    let screen: Vec<[f64; 3]> = clips
        .iter()
        .map(|c| {
            let w = c[3];
            [
                (c[0] / w + 1.0) / 2.0 * width as f64,
                (1.0 - c[1] / w) / 2.0 * height as f64,
                c[2] / w,
            ]
        })
        .collect();
    let mut frags: Vec<Vec<Fragment>> = (0..width * height).map(|_| Vec::new()).collect();
    for (triangle, tri) in mesh.indices.chunks_exact(3).enumerate() {
        let ids = [tri[0] as usize, tri[1] as usize, tri[2] as usize];
        let [a, b, c] = ids.map(|i| screen[i]);
        let area = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
        if area.abs() < 1e-12 || ids.iter().any(|&i| clips[i][3] <= NEAR * 0.5) {
            continue;
        }
        let [pa, pb, pc] = ids.map(|i| mesh.position(i));
        let front = dot(cross(sub(pb, pa), sub(pc, pa)), to_viewer(pa)) > 0.0;
        let min_x = a[0].min(b[0]).min(c[0]).floor().max(0.0) as usize;
        let max_x = (a[0].max(b[0]).max(c[0]).ceil() as usize).min(width);
        let min_y = a[1].min(b[1]).min(c[1]).floor().max(0.0) as usize;
        let max_y = (a[1].max(b[1]).max(c[1]).ceil() as usize).min(height);
        for y in min_y..max_y {
            for x in min_x..max_x {
                let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
                let edge = |p: [f64; 3], q: [f64; 3]| {
                    (q[0] - p[0]) * (py - p[1]) - (px - p[0]) * (q[1] - p[1])
                };
                let l0 = edge(b, c) / area;
                let l1 = edge(c, a) / area;
                let l2 = edge(a, b) / area;
                if l0 < 0.0 || l1 < 0.0 || l2 < 0.0 {
                    continue;
                }
                let z = l0 * a[2] + l1 * b[2] + l2 * c[2];
                let here = &mut frags[y * width + x];
                if !(-1.0..=1.0).contains(&z)
                    || (layers == 1 && here.first().is_some_and(|f| z >= f.depth))
                {
                    continue;
                }
                let p = [
                    l0 / clips[ids[0]][3],
                    l1 / clips[ids[1]][3],
                    l2 / clips[ids[2]][3],
                ];
                let sum = p[0] + p[1] + p[2];
                let frag = Fragment {
                    triangle,
                    bary: [p[0] / sum, p[1] / sum, p[2] / sum],
                    depth: z,
                    front,
                };
                if layers == 1 {
                    here.clear();
                }
                here.push(frag);
            }
        }
    }
    if layers > 1 {
        for here in &mut frags {
            here.sort_by(|a, b| a.depth.total_cmp(&b.depth));
            // A pixel centre on an edge two triangles share: GL draws one.
            here.dedup_by(|b, a| a.front == b.front && (b.depth - a.depth).abs() < 1e-12);
            here.truncate(layers);
        }
    }
    frags
}

/// A fragment's interpolated surface: position, local frame (t, b, n)
/// when the normal is not degenerate, texture coordinate (s, r) in tiles
/// and eq. 6's coordinate.
pub(crate) struct Surface {
    pub(crate) p: [f64; 3],
    pub(crate) frame: Option<[[f64; 3]; 3]>,
    pub(crate) tex: [f64; 2],
    pub(crate) shadow_u: f64,
}

impl Surface {
    /// `w` (world) in the local frame (t, b, n).
    pub(crate) fn to_local(frame: &[[f64; 3]; 3], w: [f64; 3]) -> [f64; 3] {
        [dot(w, frame[0]), dot(w, frame[1]), dot(w, frame[2])]
    }
}

/// Everything the shading of a fragment needs, checked once per image.
pub(crate) struct Shader<'a> {
    store: &'a CompressedBtf,
    mesh: &'a Mesh,
    settings: RelightSettings,
    pub(crate) camera: Camera,
    pub(crate) light: [f64; 3],
    shadow_u: Vec<f64>,
    plain_weights: (Interpolation, Interpolation),
}

impl<'a> Shader<'a> {
    /// Checks `settings` and prepares the camera, the light and eq. 6's
    /// per-vertex coordinates.
    pub(crate) fn new(
        store: &'a CompressedBtf,
        mesh: &'a Mesh,
        settings: &RelightSettings,
    ) -> Result<Shader<'a>, RelightError> {
        let (width, height) = (settings.width, settings.height);
        if !(1..=MAX_SIDE).contains(&width) || !(1..=MAX_SIDE).contains(&height) {
            return Err(RelightError::Size { width, height });
        }
        if !(settings.exposure.is_finite() && settings.exposure > 0.0) {
            return Err(RelightError::Exposure(settings.exposure));
        }
        let view_theta = settings.view.theta_deg;
        if !(view_theta.is_finite()
            && (0.0..=89.0).contains(&view_theta)
            && settings.view.phi_deg.is_finite())
        {
            return Err(RelightError::ViewElevation(view_theta));
        }
        if !(settings.light.theta_deg.is_finite() && settings.light.phi_deg.is_finite()) {
            return Err(DirectionError::NonFiniteQuery {
                theta_deg: settings.light.theta_deg,
                phi_deg: settings.light.phi_deg,
            }
            .into());
        }
        let camera = Camera::orbit(settings.view, width as f64 / height as f64);
        let light = world(settings.light);
        let shadow_u = (0..mesh.vertex_count())
            .map(|v| shadow_coordinate(mesh.normal(v), light, settings.shadow_alpha_deg))
            .collect();
        let frontal = Direction::new(0.0, 0.0);
        let plain_weights = (
            store.views().interpolate(frontal)?,
            store.lights().interpolate(frontal)?,
        );
        Ok(Shader {
            store,
            mesh,
            settings: *settings,
            camera,
            light,
            shadow_u,
            plain_weights,
        })
    }

    /// The fragments the camera sees, at most `layers` per pixel.
    pub(crate) fn rasterise(&self, layers: usize) -> Vec<Vec<Fragment>> {
        let eye = self.camera.eye;
        rasterise_layers(
            self.mesh,
            &|p| self.camera.clip(p),
            &|p| sub(eye, p),
            (self.settings.width, self.settings.height),
            layers,
        )
    }

    /// The interpolated surface of a fragment.
    pub(crate) fn surface(&self, frag: &Fragment) -> Surface {
        surface_of(self.mesh, frag, &self.shadow_u)
    }

    /// The display colour of a fragment, its direct light multiplied by
    /// `light_factor` (0 in a cast shadow).
    pub(crate) fn shade(
        &self,
        frag: &Fragment,
        light_factor: f64,
    ) -> Result<[u8; 3], RelightError> {
        let surface = self.surface(frag);
        let Some(frame) = surface.frame else {
            return Ok([(BACKGROUND * 255.0).round() as u8; 3]);
        };
        let l = Surface::to_local(&frame, self.light);
        let v = Surface::to_local(
            &frame,
            unit(sub(self.camera.eye, surface.p)).unwrap_or(frame[2]),
        );
        let st = [surface.tex[0], -surface.tex[1]];
        let value = match self.settings.shading {
            Shading::Btf => {
                let views = self.store.views().interpolate(local_angles(v))?;
                let lights = self.store.lights().interpolate(local_angles(l))?;
                btf_value(self.store, &views, &lights, st)
            }
            Shading::Plain => {
                let base = btf_value(self.store, &self.plain_weights.0, &self.plain_weights.1, st);
                base.map(|c| c * l[2].max(0.0))
            }
        };
        let gain = self.settings.exposure * shadow_factor(surface.shadow_u) * light_factor;
        Ok(value.map(|c| {
            let linear = (gain * c).clamp(0.0, 1.0);
            (linear.powf(1.0 / DISPLAY_GAMMA) * 255.0).round() as u8
        }))
    }

    /// The image from one colour (or none: background) per pixel.
    pub(crate) fn image(
        &self,
        shaded: Vec<Result<Option<[u8; 3]>, RelightError>>,
    ) -> Result<RgbImage, RelightError> {
        let (width, height) = (self.settings.width, self.settings.height);
        let background = (BACKGROUND * 255.0).round() as u8;
        let mut pixels = Vec::with_capacity(3 * width * height);
        let mut covered = Vec::with_capacity(width * height);
        for px in shaded {
            match px? {
                Some(rgb) => {
                    pixels.extend(rgb);
                    covered.push(true);
                }
                None => {
                    pixels.extend([background; 3]);
                    covered.push(false);
                }
            }
        }
        Ok(RgbImage {
            width,
            height,
            pixels,
            covered,
        })
    }
}

/// The interpolated surface of `frag` on `mesh`; `shadow_u` per vertex.
pub(crate) fn surface_of(mesh: &Mesh, frag: &Fragment, shadow_u: &[f64]) -> Surface {
    let tri = &mesh.indices[3 * frag.triangle..3 * frag.triangle + 3];
    let ids = [tri[0] as usize, tri[1] as usize, tri[2] as usize];
    let mix3 = |f: &dyn Fn(usize) -> [f64; 3]| {
        let mut out = [0.0; 3];
        for (k, &id) in ids.iter().enumerate() {
            let v = f(id);
            for c in 0..3 {
                out[c] += frag.bary[k] * v[c];
            }
        }
        out
    };
    let p = mix3(&|v| mesh.position(v));
    let n_raw = mix3(&|v| mesh.normal(v));
    let t_raw = mix3(&|v| mesh.tangent(v));
    let tex = mix3(&|v| {
        [
            f64::from(mesh.texcoords[2 * v]),
            f64::from(mesh.texcoords[2 * v + 1]),
            0.0,
        ]
    });
    let shadow_u = (0..3)
        .map(|k| frag.bary[k] * shadow_u.get(ids[k]).copied().unwrap_or(0.0))
        .sum();
    let frame = unit(n_raw).map(|n| {
        let t = unit(sub(t_raw, scale(n, dot(n, t_raw)))).unwrap_or([1.0, 0.0, 0.0]);
        [t, cross(n, t), n]
    });
    Surface {
        p,
        frame,
        tex: [tex[0], tex[1]],
        shadow_u,
    }
}

/// Renders `store` on `mesh`; see the module documentation for each step.
pub fn relight(
    store: &CompressedBtf,
    mesh: &Mesh,
    settings: &RelightSettings,
) -> Result<RgbImage, RelightError> {
    let shader = Shader::new(store, mesh, settings)?;
    let frags = shader.rasterise(1);
    let shaded = frags
        .par_iter()
        .map(|layers| layers.first().map(|f| shader.shade(f, 1.0)).transpose())
        .collect();
    shader.image(shaded)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::btf::{compress_slot, TextureShape};
    use crate::directions::{h1, DirectionTable};
    use crate::mesh::MeshKind;

    /// A BTF whose value is the light's cosine (a Lambertian material) with
    /// a checker so texture mapping shows.
    pub(crate) fn lambert_store(size: usize) -> CompressedBtf {
        let shape = TextureShape::new(size, size, 3).unwrap();
        let lights = DirectionTable::new(h1()).unwrap();
        let views = DirectionTable::new(h1()).unwrap();
        let slots = views
            .directions()
            .iter()
            .map(|_| {
                let images: Vec<Vec<f32>> = lights
                    .directions()
                    .iter()
                    .map(|l| {
                        let cos = l.theta_deg.to_radians().cos() as f32;
                        (0..size * size)
                            .flat_map(|i| {
                                let check = if (i % size + i / size).is_multiple_of(2) {
                                    0.8
                                } else {
                                    0.5
                                };
                                [check * cos; 3]
                            })
                            .collect()
                    })
                    .collect();
                let refs: Vec<&[f32]> = images.iter().map(Vec::as_slice).collect();
                compress_slot(&refs, shape, 4).unwrap()
            })
            .collect();
        CompressedBtf::new(shape, lights, views, slots).unwrap()
    }

    fn settings(light: Direction, view: Direction) -> RelightSettings {
        RelightSettings {
            width: 96,
            height: 96,
            light,
            view,
            ..RelightSettings::default()
        }
    }

    fn mesh_pixels(img: &RgbImage) -> Vec<u8> {
        img.covered
            .iter()
            .enumerate()
            .filter(|(_, &c)| c)
            .map(|(i, _)| img.pixels[3 * i])
            .collect()
    }

    #[test]
    fn the_flat_sample_fills_the_middle_and_follows_the_light() {
        let store = lambert_store(8);
        let mesh = Mesh::build(MeshKind::Flat, 1.0);
        let high = relight(
            &store,
            &mesh,
            &settings(Direction::new(0.0, 0.0), Direction::new(0.0, 0.0)),
        )
        .unwrap();
        let low = relight(
            &store,
            &mesh,
            &settings(Direction::new(70.0, 0.0), Direction::new(0.0, 0.0)),
        )
        .unwrap();
        assert!(high.covered[48 * 96 + 48] && !high.covered[0]);
        let mean = |v: Vec<u8>| v.iter().map(|&x| f64::from(x)).sum::<f64>() / v.len() as f64;
        let (h, l) = (mean(mesh_pixels(&high)), mean(mesh_pixels(&low)));
        assert!(h > l + 20.0, "overhead {h}, at 70° {l}");
    }

    #[test]
    fn hard_cases_give_finite_lit_pixels_and_no_light_from_below() {
        let store = lambert_store(8);
        for kind in MeshKind::ALL {
            let mesh = Mesh::build(kind, 1.0);
            // The pole view, a grazing light, φ across the wrap.
            for (light, view) in [
                (Direction::new(30.0, 10.0), Direction::new(0.0, 123.0)),
                (Direction::new(85.0, 0.0), Direction::new(30.0, 200.0)),
                (Direction::new(40.0, 359.9), Direction::new(40.0, 0.1)),
            ] {
                let img = relight(&store, &mesh, &settings(light, view)).unwrap();
                let lit = mesh_pixels(&img);
                assert!(!lit.is_empty());
                if kind == MeshKind::Flat {
                    assert!(lit.iter().all(|&p| p > 0), "{kind:?} {light:?} {view:?}");
                }
            }
            // Below the horizon: the flat sample gets nothing at all.
            let below = relight(
                &store,
                &mesh,
                &settings(Direction::new(100.0, 0.0), Direction::new(30.0, 0.0)),
            )
            .unwrap();
            if kind == MeshKind::Flat {
                assert!(mesh_pixels(&below).iter().all(|&p| p == 0));
            }
        }
    }

    #[test]
    fn pole_view_is_the_same_image_rotated_for_every_phi() {
        let store = lambert_store(8);
        let mesh = Mesh::build(MeshKind::Flat, 1.0);
        // φ only turns the camera about the axis; the overhead light keeps
        // every texel's value, so the count of lit pixels is unchanged.
        let a = relight(
            &store,
            &mesh,
            &settings(Direction::new(0.0, 0.0), Direction::new(0.0, 0.0)),
        )
        .unwrap();
        let b = relight(
            &store,
            &mesh,
            &settings(Direction::new(0.0, 0.0), Direction::new(0.0, 90.0)),
        )
        .unwrap();
        let count = |i: &RgbImage| i.covered.iter().filter(|&&c| c).count();
        assert!((count(&a) as i64 - count(&b) as i64).abs() < 40);
    }

    #[test]
    fn plain_texture_differs_from_the_btf_at_grazing_view_only_by_shading() {
        let store = lambert_store(8);
        let mesh = Mesh::build(MeshKind::Cylinder, 1.0);
        let mut s = settings(Direction::new(20.0, 0.0), Direction::new(30.0, 0.0));
        let btf = relight(&store, &mesh, &s).unwrap();
        s.shading = Shading::Plain;
        let plain = relight(&store, &mesh, &s).unwrap();
        assert_eq!(btf.covered, plain.covered);
        // Lambert's material is what a plain texture models: close images.
        let diff: f64 = btf
            .pixels
            .iter()
            .zip(&plain.pixels)
            .map(|(&a, &b)| (f64::from(a) - f64::from(b)).abs())
            .sum::<f64>()
            / btf.pixels.len() as f64;
        assert!(diff < 8.0, "{diff}");
    }

    #[test]
    fn bad_settings_are_refused() {
        let store = lambert_store(4);
        let mesh = Mesh::build(MeshKind::Flat, 1.0);
        let mut s = settings(Direction::new(0.0, 0.0), Direction::new(0.0, 0.0));
        s.width = 0;
        assert!(matches!(
            relight(&store, &mesh, &s),
            Err(RelightError::Size { .. })
        ));
        let mut s = settings(Direction::new(f64::NAN, 0.0), Direction::new(0.0, 0.0));
        assert!(relight(&store, &mesh, &s).is_err());
        s.light = Direction::new(0.0, 0.0);
        s.view = Direction::new(90.0, 0.0);
        assert!(matches!(
            relight(&store, &mesh, &s),
            Err(RelightError::ViewElevation(_))
        ));
        s.view = Direction::new(0.0, 0.0);
        s.exposure = 0.0;
        assert!(matches!(
            relight(&store, &mesh, &s),
            Err(RelightError::Exposure(_))
        ));
    }
}
