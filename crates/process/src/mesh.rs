//! The meshes the BTF viewer and the reference renderer draw the material
//! on: a flat sample, a cylinder, a procedurally draped cloth and a sphere.
//!
//! Every mesh is a grid of `nu × nv` vertices over a parameter square
//! (u, v) ∈ [0, 1]², two triangles per cell, so the viewer (WebGL) and the
//! CPU renderer draw exactly the same triangles from the same arrays: the
//! daemon serves this module's output and the browser never builds geometry
//! itself.
//!
//! World frame: z up, the sample centred on the origin, about two units
//! across. Per vertex: the position, the unit normal n, the unit tangent t
//! (along ∂p/∂u, made orthogonal to n) and the texture coordinate. The
//! material's local frame at a vertex is (t, b = n × t, n): the BTF's φ = 0
//! is t, φ = 90° is b, θ = 0 is n. Texture coordinates count tiles of the
//! material: `s` along t and `r` along b, one tile per world unit times the
//! density.
//!
//! [`Mesh::visibility`] gives, per vertex and per direction of a table given
//! in the vertex's local frame, whether the surface itself hides that
//! direction (Ganster et al.'s visibility maps, sampled at the measured light
//! directions as Sattler et al. eq. 10 uses them). Only the cloth can hide its own
//! sky: the flat sample and the convex cylinder never do above their local
//! horizon.

use serde::Serialize;

use crate::directions::Direction;
use rigd_core::geometry::{add, cross, dot, scale, sub, unit};

/// The shapes the viewer offers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum MeshKind {
    /// A flat square sample in the z = 0 plane.
    Flat,
    /// A cylinder of radius 0.6 world units with its axis along x, the
    /// material wrapped round it.
    Cylinder,
    /// A draped cloth with two diagonal folds and a ripple, steep enough to
    /// shade itself.
    Cloth,
    /// A sphere of radius 0.8 world units, closed: what Wang et al.'s
    /// silhouette test per interval needs all round its outline.
    Sphere,
}

/// Why a mesh name was not understood.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    /// The name is not `flat`, `cylinder`, `cloth` or `sphere` (holds at
    /// most its first 32 characters).
    #[error("unknown mesh `{0}`: expected flat, cylinder, cloth or sphere")]
    UnknownKind(String),
}

impl std::str::FromStr for MeshKind {
    type Err = MeshError;

    fn from_str(s: &str) -> Result<Self, MeshError> {
        match s {
            "flat" => Ok(MeshKind::Flat),
            "cylinder" => Ok(MeshKind::Cylinder),
            "cloth" => Ok(MeshKind::Cloth),
            "sphere" => Ok(MeshKind::Sphere),
            other => Err(MeshError::UnknownKind(other.chars().take(32).collect())),
        }
    }
}

/// Cylinder radius, world units (its axis runs along x, two units long).
const CYLINDER_RADIUS: f64 = 0.6;
/// Sphere radius, world units.
const SPHERE_RADIUS: f64 = 0.8;
/// Step of the central differences that give the surface's derivatives.
const DERIVATIVE_STEP: f64 = 1e-4;
/// Ray-march step and reach for the cloth's self-visibility, world units.
const MARCH_STEP: f64 = 0.01;
const MARCH_REACH: f64 = 3.0;

impl MeshKind {
    /// Every mesh kind.
    pub const ALL: [MeshKind; 4] = [
        MeshKind::Flat,
        MeshKind::Cylinder,
        MeshKind::Cloth,
        MeshKind::Sphere,
    ];

    /// The lowercase name the command line and the API use (`flat`,
    /// `cylinder`, `cloth`, `sphere`); `parse` reads it back.
    pub fn name(self) -> &'static str {
        match self {
            MeshKind::Flat => "flat",
            MeshKind::Cylinder => "cylinder",
            MeshKind::Cloth => "cloth",
            MeshKind::Sphere => "sphere",
        }
    }

    /// Grid resolution: enough vertices that the folds and the cylinder's
    /// curvature are smooth, few enough for software GL.
    fn grid(self) -> (usize, usize) {
        match self {
            MeshKind::Flat => (9, 9),
            MeshKind::Cylinder => (9, 65),
            MeshKind::Cloth => (65, 65),
            MeshKind::Sphere => (65, 33),
        }
    }

    /// World lengths of the u and v parameter lines (texture tiling).
    fn lengths(self) -> (f64, f64) {
        match self {
            MeshKind::Flat | MeshKind::Cloth => (2.0, 2.0),
            MeshKind::Cylinder => (2.0, 2.0 * std::f64::consts::PI * CYLINDER_RADIUS),
            MeshKind::Sphere => (
                2.0 * std::f64::consts::PI * SPHERE_RADIUS,
                std::f64::consts::PI * SPHERE_RADIUS,
            ),
        }
    }

    /// The surface point at parameters (u, v).
    fn point(self, u: f64, v: f64) -> [f64; 3] {
        match self {
            MeshKind::Flat => [2.0 * u - 1.0, 2.0 * v - 1.0, 0.0],
            MeshKind::Cylinder => {
                let a = 2.0 * std::f64::consts::PI * v;
                [
                    2.0 * u - 1.0,
                    -CYLINDER_RADIUS * a.cos(),
                    CYLINDER_RADIUS * a.sin(),
                ]
            }
            MeshKind::Cloth => {
                let (x, y) = (2.0 * u - 1.0, 2.0 * v - 1.0);
                [x, y, cloth_height(x, y)]
            }
            MeshKind::Sphere => {
                // u the longitude, v from the south pole to the north, so
                // ∂p/∂u × ∂p/∂v points outwards.
                let (sp, cp) = (2.0 * std::f64::consts::PI * u).sin_cos();
                let (st, ct) = (std::f64::consts::PI * (1.0 - v)).sin_cos();
                [
                    SPHERE_RADIUS * st * cp,
                    SPHERE_RADIUS * st * sp,
                    SPHERE_RADIUS * ct,
                ]
            }
        }
    }

    /// True when the surface hides the ray from `origin` along `dir`.
    fn hides(self, origin: [f64; 3], dir: [f64; 3]) -> bool {
        match self {
            // Above the local horizon neither a plane nor a convex
            // cylinder or sphere can meet itself again.
            MeshKind::Flat | MeshKind::Cylinder | MeshKind::Sphere => false,
            MeshKind::Cloth => {
                let mut s = 2.0 * MARCH_STEP;
                while s < MARCH_REACH {
                    let p = add(origin, scale(dir, s));
                    if p[0].abs() > 1.0 || p[1].abs() > 1.0 {
                        return false;
                    }
                    if p[2] < cloth_height(p[0], p[1]) {
                        return true;
                    }
                    s += MARCH_STEP;
                }
                false
            }
        }
    }
}

/// The draped cloth: two diagonal folds whose depth varies along them, and
/// a ripple across; steep enough to shade itself, no overhangs.
fn cloth_height(x: f64, y: f64) -> f64 {
    use std::f64::consts::PI;
    let folds =
        0.22 * (PI * (1.4 * x + 0.35 * y) + 0.4).sin() * (0.65 + 0.35 * (PI * 0.5 * y).cos());
    let ripple = 0.05 * (PI * (2.6 * y - 0.4 * x)).sin();
    folds + ripple
}

/// A grid mesh with per-vertex frames, ready for `gl.bufferData`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Mesh {
    /// Which shape this is.
    pub kind: MeshKind,
    /// Vertices per row (along u) and rows (along v); vertex (i, j) is
    /// number `j · nu + i`.
    pub nu: usize,
    /// Rows of vertices (along v); see `nu`.
    pub nv: usize,
    /// x y z per vertex.
    pub positions: Vec<f32>,
    /// Unit normal per vertex.
    pub normals: Vec<f32>,
    /// Unit tangent (along u, orthogonal to the normal) per vertex.
    pub tangents: Vec<f32>,
    /// Texture coordinates (s, r) in material tiles per vertex.
    pub texcoords: Vec<f32>,
    /// Grid parameters (u, v) ∈ [0, 1]² per vertex.
    pub params: Vec<f32>,
    /// Three vertex numbers per triangle.
    pub indices: Vec<u32>,
}

impl Mesh {
    /// Builds the mesh with `density` material tiles per world unit.
    pub fn build(kind: MeshKind, density: f64) -> Mesh {
        let (nu, nv) = kind.grid();
        let (len_u, len_v) = kind.lengths();
        let count = nu * nv;
        let mut mesh = Mesh {
            kind,
            nu,
            nv,
            positions: Vec::with_capacity(3 * count),
            normals: Vec::with_capacity(3 * count),
            tangents: Vec::with_capacity(3 * count),
            texcoords: Vec::with_capacity(2 * count),
            params: Vec::with_capacity(2 * count),
            indices: Vec::with_capacity(6 * (nu - 1) * (nv - 1)),
        };
        for j in 0..nv {
            for i in 0..nu {
                let u = i as f64 / (nu - 1) as f64;
                let v = j as f64 / (nv - 1) as f64;
                let p = kind.point(u, v);
                let (n, t) = frame(kind, u, v);
                mesh.positions.extend(p.map(|c| c as f32));
                mesh.normals.extend(n.map(|c| c as f32));
                mesh.tangents.extend(t.map(|c| c as f32));
                mesh.texcoords
                    .extend([(u * len_u * density) as f32, (v * len_v * density) as f32]);
                mesh.params.extend([u as f32, v as f32]);
            }
        }
        for j in 0..nv - 1 {
            for i in 0..nu - 1 {
                let a = (j * nu + i) as u32;
                let b = a + 1;
                let c = a + nu as u32;
                let d = c + 1;
                mesh.indices.extend([a, b, d, a, d, c]);
            }
        }
        mesh
    }

    /// Number of vertices, `nu · nv`.
    pub fn vertex_count(&self) -> usize {
        self.nu * self.nv
    }

    fn vec3_of(list: &[f32], vertex: usize) -> [f64; 3] {
        [
            f64::from(list[3 * vertex]),
            f64::from(list[3 * vertex + 1]),
            f64::from(list[3 * vertex + 2]),
        ]
    }

    /// World position of vertex number `vertex`.
    pub fn position(&self, vertex: usize) -> [f64; 3] {
        Mesh::vec3_of(&self.positions, vertex)
    }

    /// Unit normal of vertex number `vertex`, world frame.
    pub fn normal(&self, vertex: usize) -> [f64; 3] {
        Mesh::vec3_of(&self.normals, vertex)
    }

    /// Unit tangent (along u) of vertex number `vertex`, world frame.
    pub fn tangent(&self, vertex: usize) -> [f64; 3] {
        Mesh::vec3_of(&self.tangents, vertex)
    }

    /// Per vertex, then per direction (given in the vertex's local frame),
    /// 1 when the direction sees the sky and 0 when the surface hides it
    /// or it lies below the local horizon. Vertex-major: entry
    /// `vertex · directions.len() + k`.
    pub fn visibility(&self, directions: &[Direction]) -> Vec<u8> {
        let locals: Vec<[f64; 3]> = directions.iter().map(|d| d.to_vector()).collect();
        let mut out = Vec::with_capacity(self.vertex_count() * locals.len());
        for vertex in 0..self.vertex_count() {
            let p = self.position(vertex);
            let n = self.normal(vertex);
            let t = self.tangent(vertex);
            let b = cross(n, t);
            for d in &locals {
                let world = add(add(scale(t, d[0]), scale(b, d[1])), scale(n, d[2]));
                let visible = d[2] > 0.0 && !self.kind.hides(p, world);
                out.push(u8::from(visible));
            }
        }
        out
    }
}

/// Unit normal and tangent at (u, v) from central differences of the
/// surface, the tangent along u made orthogonal to the normal.
fn frame(kind: MeshKind, u: f64, v: f64) -> ([f64; 3], [f64; 3]) {
    if kind == MeshKind::Sphere {
        // Exact, and defined at the poles where ∂p/∂u vanishes.
        let (sp, cp) = (2.0 * std::f64::consts::PI * u).sin_cos();
        let n = unit(kind.point(u, v)).unwrap_or([0.0, 0.0, 1.0]);
        let t =
            unit(sub([-sp, cp, 0.0], scale(n, dot([-sp, cp, 0.0], n)))).unwrap_or([-sp, cp, 0.0]);
        return (n, t);
    }
    let h = DERIVATIVE_STEP;
    let du = scale(sub(kind.point(u + h, v), kind.point(u - h, v)), 0.5 / h);
    let dv = scale(sub(kind.point(u, v + h), kind.point(u, v - h)), 0.5 / h);
    let n = unit(cross(du, dv)).unwrap_or([0.0, 0.0, 1.0]);
    let along = sub(du, scale(n, dot(du, n)));
    let t = unit(along).unwrap_or([1.0, 0.0, 0.0]);
    (n, t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigd_core::geometry::norm;

    #[test]
    fn frames_are_orthonormal_and_point_up_where_they_should() {
        for kind in MeshKind::ALL {
            let mesh = Mesh::build(kind, 1.0);
            assert_eq!(mesh.positions.len(), 3 * mesh.vertex_count());
            assert_eq!(mesh.indices.len(), 6 * (mesh.nu - 1) * (mesh.nv - 1));
            for vertex in 0..mesh.vertex_count() {
                let n = mesh.normal(vertex);
                let t = mesh.tangent(vertex);
                assert!((norm(n) - 1.0).abs() < 1e-5, "{kind:?} {vertex}");
                assert!((norm(t) - 1.0).abs() < 1e-5);
                assert!(dot(n, t).abs() < 1e-5);
            }
        }
        // The flat sample faces +z with φ = 0 along +x.
        let flat = Mesh::build(MeshKind::Flat, 1.0);
        assert_eq!(flat.normal(0), [0.0, 0.0, 1.0]);
        assert_eq!(flat.tangent(0), [1.0, 0.0, 0.0]);
        // The cylinder's normals point away from its axis.
        let cyl = Mesh::build(MeshKind::Cylinder, 1.0);
        for vertex in 0..cyl.vertex_count() {
            let p = cyl.position(vertex);
            let radial = [0.0, p[1], p[2]];
            assert!(dot(radial, cyl.normal(vertex)) > 0.5);
        }
    }

    #[test]
    fn only_the_cloth_hides_its_own_sky() {
        let dirs = [
            Direction::new(0.0, 0.0),
            Direction::new(80.0, 0.0),
            Direction::new(80.0, 180.0),
            Direction::new(60.0, 90.0),
        ];
        for kind in [MeshKind::Flat, MeshKind::Cylinder, MeshKind::Sphere] {
            let vis = Mesh::build(kind, 1.0).visibility(&dirs);
            assert!(vis.iter().all(|&v| v == 1), "{kind:?}");
        }
        let cloth = Mesh::build(MeshKind::Cloth, 1.0).visibility(&dirs);
        let hidden = cloth.iter().filter(|&&v| v == 0).count();
        // The folds shade a real part of the grazing sky, not the zenith.
        assert!(hidden > cloth.len() / 20, "{hidden} of {}", cloth.len());
        assert!(cloth
            .chunks(dirs.len())
            .all(|per_vertex| per_vertex[0] == 1));
    }

    #[test]
    fn mesh_names_parse_and_bad_ones_say_what_is_allowed() {
        for kind in MeshKind::ALL {
            assert_eq!(kind.name().parse::<MeshKind>(), Ok(kind));
        }
        let err = "torus".parse::<MeshKind>().unwrap_err().to_string();
        assert!(err.contains("flat, cylinder, cloth or sphere"), "{err}");
    }
}
