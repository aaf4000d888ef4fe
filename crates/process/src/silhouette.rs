//! Mesostructure silhouettes and shadows from the measured MDF (Wang, Tong,
//! Snyder, Chen, Guo & Shum, "Capturing and Rendering Geometry Details for
//! BTF-mapped Surfaces", §4): the reference the viewer's WebGL2 depth
//! peeling (`src/server/dashboard/viewer.js`) is tested against. It
//! extends [`crate::relight`]'s image; with both modes off the image is
//! exactly [`crate::relight::relight`]'s.
//!
//! # The MDF offset at a surface point
//!
//! [`MdfTexture::offset`]: for texture coordinate (s, r) (tiles, as the mesh
//! gives them) and a local direction `v` (the frame (t, b, n) of
//! [`crate::relight`], `v` pointing away from the surface):
//! 1. the entries of the MDF's view table for `v`
//!    ([`crate::directions::DirectionTable::interpolate`], the same nearest-direction rule as
//!    the BTF's view slots, grazing queries clamped to the outermost ring);
//! 2. in each entry's layer the texel `(⌊fract(s)·N⌋, ⌊fract(−r)·N⌋)` (nearest,
//!    never filtered, so a −1 texel is never blended with a depth): the same
//!    rows and columns the BTF's textures are sampled at;
//! 3. the weighted mean over the entries whose texel holds a measurement;
//!    when none does, 0: **a texel without a measurement counts as a hit**
//!    (the surface at the mesh), so gaps in the laser data never punch
//!    holes through an object;
//! 4. millimetres to world units: `/ (tile_mm · density)`, one material tile
//!    spanning `1 / density` world units.
//!
//! # Silhouettes (`Silhouettes::Mdf`)
//!
//! Per pixel, the fragments of every triangle covering the pixel centre
//! (the rasteriser of [`crate::relight`]), sorted by distance `t` from the
//! eye, at most [`MAX_PEEL_LAYERS`] of them (the viewer's peel passes; a
//! farther layer is not there). A fragment is *front* when its triangle's
//! winding faces the eye (`gl_FrontFacing`; the meshes are wound so that
//! the side their normals point to is the front), else *back*. Its offset
//! `d` is the MDF at it for the direction the ray arrives from: `−ray` at a
//! front fragment, `+ray` at a back one (both point away from the surface).
//! Walking the layers near to far, with a pending front fragment `f`:
//! - a front fragment: if one is pending already (an open mesh), the pending
//!   one is hit; else it becomes pending;
//! - a back fragment `b` with `f` pending: the interval [f, b] holds
//!   mesostructure only if `d_f + d_b ≤ t_b − t_f` (Wang et al.'s test); then
//!   `f` is hit, else the ray passes through and `f` is dropped;
//! - a back fragment with nothing pending (the inside of an open mesh seen
//!   through its opening): it is hit, as without the MDF;
//! - after the last layer a pending `f` is hit (an open mesh's sheet has no
//!   back: its interval runs to infinity).
//!
//! No hit: the background. The hit fragment is shaded as
//! [`crate::relight`] shades its first fragment. So the sphere (closed)
//! shows the mesostructure along its whole outline, the cylinder along its
//! sides (its open ends keep their edges) and the cloth wherever a ray
//! passes through a fold; the flat sample has one layer and is unchanged.
//!
//! # Shadows (`Shadows::Mdf`)
//!
//! An MDF-offset shadow map for the viewer's light (directional, as the
//! BTF's measured lights are, so the map is orthographic):
//! - light frame: `w = L`; `a = (0,0,1)` if `|w_z| < 0.9` else `(1,0,0)`;
//!   `right = unit(a × w)`, `up = w × right`; `R = 1.05 · max |p|` over the
//!   mesh's vertices; texel (i, j) of the [`SHADOW_MAP_SIZE`]² map has its
//!   centre at `((i + ½)/S·2 − 1)·R` along `right` and `((j + ½)/S·2 − 1)·R`
//!   along `up` (j counts up);
//! - along each texel's ray (direction −L) the same layer walk with
//!   `t = −p·L` (larger is farther from the light), front = facing the
//!   light; the texel keeps two values of the hit fragment: `t_hit` (the
//!   mesh) and `t_hit + d_hit` (the mesostructure surface: the offset for
//!   direction L; 0 for an unpaired back fragment), or +∞ twice without a
//!   hit;
//! - a shaded fragment at p with unit normal n: `t = −p·L` and
//!   `z = t + d_L` (`d_L` its offset towards L; 0 when L is below its local
//!   horizon), its texel `i = ⌊(p·right / R + 1)/2·S⌋`, `j` likewise along
//!   `up` (outside the map: lit), is in shadow when both
//!   `t > map.mesh + bias` and `z > map.meso + bias`, with
//!   `bias = texel · (2 + min(tan θ, 20))`, texel = 2R/S and
//!   `cos θ = max(n·L, 0.05)`. The first condition keeps a surface from
//!   shadowing itself where the MDF jumps between neighbouring texels
//!   (the BTF holds the mesostructure's own shadows already); the second
//!   lets light through where the occluder's mesostructure lies deeper
//!   than the receiver. A shadowed fragment gets no direct light (factor
//!   0, on top of eq. 6's smooth boundary).
//!
//! A light below the horizon keeps the same map (from below); eq. 6 has
//! already taken its light away from every surface facing up.

use rayon::prelude::*;

use crate::btf::CompressedBtf;
use crate::directions::DirectionError;
use crate::mdf::MdfTexture;
use crate::mesh::Mesh;
use crate::relight::{
    rasterise_layers, surface_of, RelightError, RelightSettings, RgbImage, Shader, Surface,
};
use rigd_core::geometry::{cross, dot, norm, scale, sub, unit};

/// Peel passes of the viewer, and the layers the reference walks per ray.
pub const MAX_PEEL_LAYERS: usize = 4;
/// Side of the shadow map, texels.
pub const SHADOW_MAP_SIZE: usize = 512;
/// Factor of the largest vertex distance from the origin that the shadow
/// map's square spans (a margin so no vertex sits on its edge).
const SHADOW_MAP_MARGIN: f64 = 1.05;
/// Cosine floor of the light's angle in the shadow bias.
const SHADOW_BIAS_MIN_COS: f64 = 0.05;
/// Largest slope term of the shadow bias.
const SHADOW_BIAS_MAX_SLOPE: f64 = 20.0;

/// What [`render`] adds to [`crate::relight::relight`]'s image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MesoSettings {
    /// Wang et al.'s silhouette test per interval.
    pub silhouettes: bool,
    /// The MDF-offset shadow map.
    pub shadows: bool,
    /// Material tiles per world unit of the mesh (converts the MDF's
    /// millimetres to world units).
    pub density: f64,
}

/// Why [`render`] refused.
#[derive(Debug, thiserror::Error)]
pub enum SilhouetteError {
    /// The relighting itself refused (size, view, exposure, BTF).
    #[error(transparent)]
    Relight(#[from] RelightError),
    /// The density is not a positive finite number.
    #[error("density {0}: expected a positive number of tiles per unit")]
    Density(f64),
}

impl From<DirectionError> for SilhouetteError {
    fn from(e: DirectionError) -> Self {
        SilhouetteError::Relight(e.into())
    }
}

/// What the render measured, for the tests and `rigd process render`.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct SilhouetteReport {
    /// Pixels some triangle of the mesh covers (its projected outline and
    /// everything inside it).
    pub outline_pixels: usize,
    /// Pixels inside the outline where every interval passed the test:
    /// the background shows through the mesostructure.
    pub background_inside_outline: usize,
    /// Pixels the shadow map puts in a cast shadow.
    pub shadowed_pixels: usize,
    /// Most layers a camera ray or light ray crossed (up to
    /// [`MAX_PEEL_LAYERS`]): the peel passes that mattered.
    pub layers_used: usize,
}

/// One layer of a ray's walk.
#[derive(Debug, Clone, Copy)]
struct Layer {
    /// Distance along the ray.
    t: f64,
    /// The MDF offset for the direction the ray arrives from, world units.
    offset: f64,
    /// The winding faces the ray's origin.
    front: bool,
}

/// The layer a ray hits (module doc: the walk), or None.
fn walk(layers: &[Layer]) -> Option<usize> {
    let mut pending: Option<usize> = None;
    for (i, layer) in layers.iter().enumerate() {
        match (layer.front, pending) {
            (true, Some(f)) => return Some(f),
            (true, None) => pending = Some(i),
            (false, Some(f)) => {
                if layers[f].offset + layer.offset <= layer.t - layers[f].t {
                    return Some(f);
                }
                pending = None;
            }
            (false, None) => return Some(i),
        }
    }
    pending
}

/// The MDF offset at a surface for the world direction `towards` (pointing
/// away from the surface at a front fragment); 0 without a frame.
fn offset_at(
    mdf: &MdfTexture,
    surface: &Surface,
    towards: [f64; 3],
    density: f64,
) -> Result<f64, DirectionError> {
    match &surface.frame {
        Some(frame) => mdf.offset(
            surface.tex[0],
            surface.tex[1],
            Surface::to_local(frame, towards),
            density,
        ),
        None => Ok(0.0),
    }
}

/// The orthographic light view of the module doc.
struct LightFrame {
    light: [f64; 3],
    right: [f64; 3],
    up: [f64; 3],
    radius: f64,
}

impl LightFrame {
    fn new(mesh: &Mesh, light: [f64; 3]) -> LightFrame {
        let a = if light[2].abs() < 0.9 {
            [0.0, 0.0, 1.0]
        } else {
            [1.0, 0.0, 0.0]
        };
        let right = unit(cross(a, light)).unwrap_or([1.0, 0.0, 0.0]);
        let up = cross(light, right);
        let reach = (0..mesh.vertex_count())
            .map(|v| norm(mesh.position(v)))
            .fold(0.0, f64::max);
        LightFrame {
            light,
            right,
            up,
            radius: (SHADOW_MAP_MARGIN * reach).max(1e-6),
        }
    }

    /// Clip coordinates: x along `right`, y along `up`, depth growing away
    /// from the light, all within ±1 for the mesh.
    fn clip(&self, p: [f64; 3]) -> [f64; 4] {
        [
            dot(p, self.right) / self.radius,
            dot(p, self.up) / self.radius,
            -0.5 * dot(p, self.light) / self.radius,
            1.0,
        ]
    }
}

/// The MDF-offset shadow map: per texel the distance from the light of the
/// first hit's mesh and of its mesostructure, +∞ without one.
struct ShadowMap {
    frame: LightFrame,
    depth: Vec<[f64; 2]>,
    layers_used: usize,
}

impl ShadowMap {
    fn build(
        mesh: &Mesh,
        mdf: &MdfTexture,
        light: [f64; 3],
        density: f64,
    ) -> Result<ShadowMap, DirectionError> {
        let frame = LightFrame::new(mesh, light);
        let frags = rasterise_layers(
            mesh,
            &|p| frame.clip(p),
            &|_| light,
            (SHADOW_MAP_SIZE, SHADOW_MAP_SIZE),
            MAX_PEEL_LAYERS,
        );
        let no_shadow_u: [f64; 0] = [];
        let depth: Vec<Result<[f64; 2], DirectionError>> = frags
            .par_iter()
            .map(|layers| {
                let walked = layers
                    .iter()
                    .map(|f| {
                        let s = surface_of(mesh, f, &no_shadow_u);
                        let towards = if f.front { light } else { scale(light, -1.0) };
                        Ok(Layer {
                            t: -dot(s.p, light),
                            offset: offset_at(mdf, &s, towards, density)?,
                            front: f.front,
                        })
                    })
                    .collect::<Result<Vec<Layer>, DirectionError>>()?;
                // An unpaired back fragment's mesostructure faces away: 0.
                Ok(walk(&walked).map_or([f64::INFINITY; 2], |i| {
                    let hit = walked[i];
                    [hit.t, hit.t + if hit.front { hit.offset } else { 0.0 }]
                }))
            })
            .collect();
        let layers_used = frags.iter().map(Vec::len).max().unwrap_or(0);
        Ok(ShadowMap {
            frame,
            depth: depth.into_iter().collect::<Result<_, _>>()?,
            layers_used,
        })
    }

    /// True when the fragment `surface` (its offset towards the light
    /// `d_light`) lies behind the map's first hit.
    fn shadows(&self, surface: &Surface, d_light: f64) -> bool {
        let s = SHADOW_MAP_SIZE as f64;
        let c = self.frame.clip(surface.p);
        let x = ((c[0] + 1.0) / 2.0 * s).floor();
        let y = ((1.0 - c[1]) / 2.0 * s).floor();
        if !(0.0..s).contains(&x) || !(0.0..s).contains(&y) {
            return false;
        }
        let map = self.depth[y as usize * SHADOW_MAP_SIZE + x as usize];
        let texel = 2.0 * self.frame.radius / s;
        let cos = surface
            .frame
            .map_or(1.0, |f| dot(f[2], self.frame.light))
            .max(SHADOW_BIAS_MIN_COS);
        let slope = ((1.0 - cos * cos).max(0.0).sqrt() / cos).min(SHADOW_BIAS_MAX_SLOPE);
        let bias = texel * (2.0 + slope);
        let t = -dot(surface.p, self.frame.light);
        t > map[0] + bias && t + d_light > map[1] + bias
    }
}

/// Renders `store` on `mesh` as [`crate::relight::relight`] does, with the
/// MDF's silhouettes and shadows as `meso` asks (module doc).
pub fn render(
    store: &CompressedBtf,
    mesh: &Mesh,
    mdf: &MdfTexture,
    settings: &RelightSettings,
    meso: &MesoSettings,
) -> Result<(RgbImage, SilhouetteReport), SilhouetteError> {
    if !(meso.density.is_finite() && meso.density > 0.0) {
        return Err(SilhouetteError::Density(meso.density));
    }
    let shader = Shader::new(store, mesh, settings)?;
    let frags = shader.rasterise(if meso.silhouettes { MAX_PEEL_LAYERS } else { 1 });
    let light = shader.light;
    let shadow_map = if meso.shadows {
        Some(ShadowMap::build(mesh, mdf, light, meso.density)?)
    } else {
        None
    };
    let eye = shader.camera.eye;
    // Per pixel: the colour, whether a triangle covers it, whether shadowed.
    type Pixel = (Option<[u8; 3]>, bool, bool);
    let shaded: Vec<Result<Pixel, SilhouetteError>> = frags
        .par_iter()
        .map(|layers| {
            let hit = if meso.silhouettes {
                let walked = layers
                    .iter()
                    .map(|f| {
                        let s = shader.surface(f);
                        let ray = unit(sub(s.p, eye)).unwrap_or([0.0, 0.0, -1.0]);
                        let towards = if f.front { scale(ray, -1.0) } else { ray };
                        Ok(Layer {
                            t: norm(sub(s.p, eye)),
                            offset: offset_at(mdf, &s, towards, meso.density)?,
                            front: f.front,
                        })
                    })
                    .collect::<Result<Vec<Layer>, DirectionError>>()?;
                walk(&walked).map(|i| &layers[i])
            } else {
                layers.first()
            };
            let Some(hit) = hit else {
                return Ok((None, !layers.is_empty(), false));
            };
            let shadowed = match &shadow_map {
                Some(map) => {
                    let s = shader.surface(hit);
                    let d_light = match &s.frame {
                        Some(frame) if Surface::to_local(frame, light)[2] > 0.0 => {
                            offset_at(mdf, &s, light, meso.density)?
                        }
                        _ => 0.0,
                    };
                    map.shadows(&s, d_light)
                }
                None => false,
            };
            let rgb = shader.shade(hit, if shadowed { 0.0 } else { 1.0 })?;
            Ok((Some(rgb), true, shadowed))
        })
        .collect();
    let mut report = SilhouetteReport {
        layers_used: frags
            .iter()
            .map(Vec::len)
            .max()
            .unwrap_or(0)
            .max(shadow_map.as_ref().map_or(0, |m| m.layers_used)),
        ..SilhouetteReport::default()
    };
    let mut colours = Vec::with_capacity(shaded.len());
    for px in shaded {
        let (rgb, inside, shadowed) = px?;
        report.outline_pixels += usize::from(inside);
        report.background_inside_outline += usize::from(inside && rgb.is_none());
        report.shadowed_pixels += usize::from(shadowed);
        colours.push(Ok(rgb));
    }
    Ok((shader.image(colours)?, report))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::directions::Direction;
    use crate::mdf::{MdfTextureHeader, NO_DEPTH};
    use crate::mesh::MeshKind;
    use crate::relight::tests::lambert_store;

    fn layer(t: f64, offset: f64, front: bool) -> Layer {
        Layer { t, offset, front }
    }

    #[test]
    fn the_walk_tests_each_interval_and_closes_open_meshes_at_infinity() {
        // Enough room between the faces for both offsets: the front is hit.
        assert_eq!(
            walk(&[layer(1.0, 0.1, true), layer(1.5, 0.2, false)]),
            Some(0)
        );
        // Too little: the ray passes through, and nothing is behind.
        assert_eq!(walk(&[layer(1.0, 0.3, true), layer(1.5, 0.3, false)]), None);
        // …or it goes on to the next interval.
        assert_eq!(
            walk(&[
                layer(1.0, 0.3, true),
                layer(1.5, 0.3, false),
                layer(2.0, 0.0, true),
                layer(3.0, 0.0, false),
            ]),
            Some(2)
        );
        // An open sheet (a front face with no back) is always hit.
        assert_eq!(walk(&[layer(1.0, 5.0, true)]), Some(0));
        assert_eq!(
            walk(&[layer(1.0, 5.0, true), layer(2.0, 5.0, true)]),
            Some(0)
        );
        // The inside of an open mesh, seen through its opening.
        assert_eq!(walk(&[layer(1.0, 5.0, false)]), Some(0));
        assert_eq!(walk(&[]), None);
    }

    /// An MDF texture with one value everywhere, over an H1-like table.
    fn uniform_mdf(depth_mm: f32) -> MdfTexture {
        let views = vec![
            Direction::new(0.0, 0.0),
            Direction::new(45.0, 0.0),
            Direction::new(45.0, 90.0),
            Direction::new(45.0, 180.0),
            Direction::new(45.0, 270.0),
            Direction::new(80.0, 0.0),
            Direction::new(80.0, 120.0),
            Direction::new(80.0, 240.0),
        ];
        let n = 8;
        let coverage = vec![1.0; views.len()];
        let depth = vec![depth_mm; views.len() * n * n];
        MdfTexture::new(
            MdfTextureHeader {
                size: n,
                views,
                tile_mm: 100.0,
                top_mm: 2.0,
                coverage,
                source: "test".into(),
            },
            depth,
        )
        .unwrap()
    }

    /// A texture whose depth grows with the view's θ and alternates between
    /// ridge (0) and groove columns: a ridged relief seen from the side.
    fn ridged_mdf() -> MdfTexture {
        let base = uniform_mdf(0.0);
        let header = base.header().clone();
        let n = header.size;
        let depth = header
            .views
            .iter()
            .flat_map(|v| {
                let slope = v.theta_deg.to_radians().tan() as f32;
                (0..n * n).map(move |k| {
                    if (k % n).is_multiple_of(2) {
                        0.0
                    } else {
                        1.0 + 2.0 * slope
                    }
                })
            })
            .collect();
        MdfTexture::new(header, depth).unwrap()
    }

    fn settings(light: Direction, view: Direction) -> RelightSettings {
        RelightSettings {
            width: 128,
            height: 128,
            light,
            view,
            ..RelightSettings::default()
        }
    }

    const BOTH: MesoSettings = MesoSettings {
        silhouettes: true,
        shadows: true,
        density: 0.5,
    };

    #[test]
    fn without_the_modes_the_image_is_the_relit_one_and_zero_offsets_change_nothing() {
        let store = lambert_store(8);
        let s = settings(Direction::new(40.0, 30.0), Direction::new(50.0, 200.0));
        for kind in MeshKind::ALL {
            let mesh = Mesh::build(kind, 0.5);
            let plain = crate::relight::relight(&store, &mesh, &s).unwrap();
            let off = MesoSettings {
                silhouettes: false,
                shadows: false,
                density: 0.5,
            };
            let (img, report) = render(&store, &mesh, &ridged_mdf(), &s, &off).unwrap();
            assert_eq!(img, plain, "{kind:?}");
            assert_eq!(report.background_inside_outline, 0);
            // Offsets of 0 and texels without a measurement are hits: the
            // silhouettes keep every covered pixel.
            for mdf in [uniform_mdf(0.0), uniform_mdf(NO_DEPTH)] {
                let sil = MesoSettings {
                    shadows: false,
                    ..BOTH
                };
                let (img, report) = render(&store, &mesh, &mdf, &s, &sil).unwrap();
                assert_eq!(img.covered, plain.covered, "{kind:?}");
                assert_eq!(report.background_inside_outline, 0, "{kind:?}");
            }
        }
    }

    #[test]
    fn a_relief_opens_the_outline_of_closed_meshes_only_at_their_edges() {
        let store = lambert_store(8);
        let s = settings(Direction::new(40.0, 30.0), Direction::new(50.0, 200.0));
        let sil = MesoSettings {
            shadows: false,
            ..BOTH
        };
        let mesh = Mesh::build(MeshKind::Sphere, 0.5);
        let plain = crate::relight::relight(&store, &mesh, &s).unwrap();
        let (img, report) = render(&store, &mesh, &ridged_mdf(), &s, &sil).unwrap();
        assert!(report.background_inside_outline > 0);
        assert_eq!(
            report.outline_pixels,
            plain.covered.iter().filter(|&&c| c).count()
        );
        // Holes only next to the outline: the middle of the disc is intact,
        // and every quarter of the outline has some.
        let (w, h) = (img.width, img.height);
        let mut quarters = [0usize; 4];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if plain.covered[i] && !img.covered[i] {
                    let near_edge =
                        [(0i64, 1i64), (0, -1), (1, 0), (-1, 0)]
                            .iter()
                            .any(|&(dx, dy)| {
                                let (nx, ny) = (x as i64 + 4 * dx, y as i64 + 4 * dy);
                                nx < 0
                                    || ny < 0
                                    || nx >= w as i64
                                    || ny >= h as i64
                                    || !plain.covered[ny as usize * w + nx as usize]
                            });
                    assert!(near_edge, "a hole at ({x}, {y}) away from the outline");
                    quarters[usize::from(x >= w / 2) + 2 * usize::from(y >= h / 2)] += 1;
                }
            }
        }
        assert!(quarters.iter().all(|&q| q > 0), "{quarters:?}");
        // The flat sample has one layer: nothing to pass through.
        let flat = Mesh::build(MeshKind::Flat, 0.5);
        let (_, report) = render(&store, &flat, &ridged_mdf(), &s, &sil).unwrap();
        assert_eq!(report.background_inside_outline, 0);
        assert_eq!(report.layers_used, 1);
    }

    #[test]
    fn the_cloth_casts_shadows_that_follow_the_light() {
        let store = lambert_store(8);
        let mesh = Mesh::build(MeshKind::Cloth, 0.5);
        let shadows = MesoSettings {
            silhouettes: false,
            ..BOTH
        };
        let view = Direction::new(30.0, 270.0);
        let cast = |light| {
            let (img, report) = render(
                &store,
                &mesh,
                &uniform_mdf(0.0),
                &settings(light, view),
                &shadows,
            )
            .unwrap();
            (img, report.shadowed_pixels)
        };
        let (_, overhead) = cast(Direction::new(0.0, 0.0));
        let (east_img, east) = cast(Direction::new(75.0, 0.0));
        let (west_img, west) = cast(Direction::new(75.0, 180.0));
        assert_eq!(
            overhead, 0,
            "an overhead light casts no shadow on the folds"
        );
        assert!(east > 50 && west > 50, "east {east}, west {west}");
        assert_ne!(east_img.pixels, west_img.pixels);
    }

    #[test]
    fn hard_cases_render_without_holes_or_errors() {
        let store = lambert_store(8);
        for kind in MeshKind::ALL {
            let mesh = Mesh::build(kind, 0.5);
            for (light, view) in [
                // Grazing view at the outline, a light below the horizon,
                // the pole view, the φ wrap, a light straight up.
                (Direction::new(40.0, 10.0), Direction::new(89.0, 45.0)),
                (Direction::new(120.0, 30.0), Direction::new(40.0, 200.0)),
                (Direction::new(30.0, 10.0), Direction::new(0.0, 123.0)),
                (Direction::new(45.0, 359.9), Direction::new(40.0, 0.1)),
                (Direction::new(0.0, 0.0), Direction::new(60.0, 0.0)),
            ] {
                for mdf in [ridged_mdf(), uniform_mdf(NO_DEPTH)] {
                    let (img, report) =
                        render(&store, &mesh, &mdf, &settings(light, view), &BOTH).unwrap();
                    assert!(report.layers_used <= MAX_PEEL_LAYERS);
                    if mdf.depth_mm()[0] == NO_DEPTH {
                        assert_eq!(report.background_inside_outline, 0, "{kind:?}");
                    }
                    assert_eq!(img.pixels.len(), 3 * 128 * 128);
                }
            }
        }
        let mesh = Mesh::build(MeshKind::Sphere, 0.5);
        let s = settings(Direction::new(40.0, 10.0), Direction::new(30.0, 0.0));
        let bad = MesoSettings {
            density: 0.0,
            ..BOTH
        };
        assert!(matches!(
            render(&store, &mesh, &ridged_mdf(), &s, &bad),
            Err(SilhouetteError::Density(_))
        ));
    }
}
