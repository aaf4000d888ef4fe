//! The sample's surface: procedural heightfields and albedo patterns, baked
//! once per scene into grids that the renderer samples bilinearly.

use std::f64::consts::PI;

use super::spec::{AlbedoSpec, HeightSpec, MacroSpec};

/// A scalar field over the sample, `nx × ny` texels centred on the origin,
/// sampled bilinearly; outside the sample it reads as its edge value.
#[derive(Debug, Clone)]
pub struct Grid {
    /// Texels along x.
    pub nx: usize,
    /// Texels along y.
    pub ny: usize,
    /// Texel size, metres.
    pub texel: f64,
    /// The texel values, row-major (`data[j * nx + i]`), rows along +y.
    pub data: Vec<f32>,
}

impl Grid {
    /// Evaluates `f(x, y)` (metres) at every texel centre.
    pub fn bake(nx: usize, ny: usize, texel: f64, f: impl Fn(f64, f64) -> f64 + Sync) -> Grid {
        use rayon::prelude::*;
        let mut data = vec![0f32; nx * ny];
        data.par_chunks_mut(nx).enumerate().for_each(|(j, row)| {
            let y = (j as f64 + 0.5 - ny as f64 / 2.0) * texel;
            for (i, v) in row.iter_mut().enumerate() {
                let x = (i as f64 + 0.5 - nx as f64 / 2.0) * texel;
                *v = f(x, y) as f32;
            }
        });
        Grid {
            nx,
            ny,
            texel,
            data,
        }
    }

    fn at(&self, i: isize, j: isize) -> f64 {
        let i = i.clamp(0, self.nx as isize - 1) as usize;
        let j = j.clamp(0, self.ny as isize - 1) as usize;
        self.data[j * self.nx + i] as f64
    }

    /// Bilinear value at (x, y), metres.
    #[inline(always)]
    pub fn sample(&self, x: f64, y: f64) -> f64 {
        self.sampler().sample(x, y)
    }

    /// This grid ready for hot loops: see [`Sampler`].
    #[inline(always)]
    pub(crate) fn sampler(&self) -> Sampler<'_> {
        Sampler {
            data: &self.data,
            nx: self.nx,
            ny: self.ny,
            texel: self.texel,
            centre: [self.nx as f64 / 2.0, self.ny as f64 / 2.0],
        }
    }

    /// True when `other` has this grid's size and texel, so the same point
    /// falls on the same texels of both.
    pub(crate) fn same_layout(&self, other: &Grid) -> bool {
        self.nx == other.nx && self.ny == other.ny && self.texel == other.texel
    }

    /// Central-difference gradient of the baked field.
    pub fn gradient(&self) -> (Grid, Grid) {
        let d = 2.0 * self.texel;
        let gx = Grid::bake_index(self, |g, i, j| (g.at(i + 1, j) - g.at(i - 1, j)) / d);
        let gy = Grid::bake_index(self, |g, i, j| (g.at(i, j + 1) - g.at(i, j - 1)) / d);
        (gx, gy)
    }

    fn bake_index(src: &Grid, f: impl Fn(&Grid, isize, isize) -> f64) -> Grid {
        let mut data = Vec::with_capacity(src.data.len());
        for j in 0..src.ny as isize {
            for i in 0..src.nx as isize {
                data.push(f(src, i, j) as f32);
            }
        }
        Grid {
            nx: src.nx,
            ny: src.ny,
            texel: src.texel,
            data,
        }
    }

    /// The largest texel value, or 0 if none is positive.
    pub fn max(&self) -> f64 {
        self.data.iter().copied().fold(0f32, f32::max) as f64
    }
}

/// A [`Grid`] for hot loops, with the constants of its layout (which
/// [`Grid::sample`] would convert from integers on every call) worked out
/// once. Sampling is [`Grid::sample`]'s arithmetic in the same order, so
/// values are bit for bit the same.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Sampler<'a> {
    data: &'a [f32],
    nx: usize,
    ny: usize,
    texel: f64,
    /// Half the grid's texels along x and y.
    centre: [f64; 2],
}

impl Sampler<'_> {
    /// Bilinear value at (x, y), metres.
    #[inline(always)]
    pub(crate) fn sample(&self, x: f64, y: f64) -> f64 {
        self.sample_at(&self.footprint(x, y))
    }

    /// Where (x, y) falls on the grid, for [`Sampler::sample_at`].
    #[inline(always)]
    fn footprint(&self, x: f64, y: f64) -> Footprint {
        let u = x / self.texel + self.centre[0] - 0.5;
        let v = y / self.texel + self.centre[1] - 0.5;
        let ((i0, fi), (j0, fj)) = (floor_index(u), floor_index(v));
        Footprint {
            i0,
            j0,
            fu: u - fi,
            fv: v - fj,
        }
    }

    /// Bilinear value at a footprint taken on this grid.
    #[inline(always)]
    fn sample_at(&self, f: &Footprint) -> f64 {
        let [c00, c10, c01, c11] = self.corners(f.i0, f.j0);
        let (fu, fv) = (f.fu, f.fv);
        let a = c00 * (1.0 - fu) + c10 * fu;
        let b = c01 * (1.0 - fu) + c11 * fu;
        a * (1.0 - fv) + b * fv
    }

    /// The four texels around (i0, j0), (i0 + 1, j0 + 1): read straight
    /// from two rows inside the grid, clamped to the edge outside it.
    #[inline(always)]
    fn corners(&self, i0: isize, j0: isize) -> [f64; 4] {
        // 0 ≤ i0 < nx − 1 and 0 ≤ j0 < ny − 1, a negative index wrapping
        // to a huge unsigned one.
        if (i0 as usize) < self.nx.wrapping_sub(1) && (j0 as usize) < self.ny.wrapping_sub(1) {
            let base = j0 as usize * self.nx + i0 as usize;
            if let Some(s) = self.data.get(base..base + self.nx + 2) {
                if let (Some(lo), Some(hi)) = (s.first_chunk::<2>(), s.last_chunk::<2>()) {
                    return [lo[0] as f64, lo[1] as f64, hi[0] as f64, hi[1] as f64];
                }
            }
        }
        [
            self.at(i0, j0),
            self.at(i0 + 1, j0),
            self.at(i0, j0 + 1),
            self.at(i0 + 1, j0 + 1),
        ]
    }

    fn at(&self, i: isize, j: isize) -> f64 {
        let i = i.clamp(0, self.nx as isize - 1) as usize;
        let j = j.clamp(0, self.ny as isize - 1) as usize;
        self.data.get(j * self.nx + i).map_or(0.0, |v| *v as f64)
    }
}

/// The sample's albedo, height gradient and height interleaved texel by
/// texel, for shading: a hit point's normal and albedo (or a blur tap's
/// height and normal) then come from two cache lines instead of six, one
/// per row per grid. Built from grids of one layout; sampling reads the
/// same values with the same arithmetic as [`Grid::sample`] on each.
#[derive(Debug, Clone)]
pub(crate) struct SurfaceTexels {
    nx: usize,
    ny: usize,
    texel: f64,
    /// `[albedo, ∂h/∂x, ∂h/∂y, height]` per texel, row-major.
    data: Vec<[f32; 4]>,
}

/// One point of the surface, read from [`SurfaceTexels`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct SurfaceSample {
    pub albedo: f64,
    pub grad: [f64; 2],
    pub height: f64,
}

impl SurfaceTexels {
    /// The interleaved texels of four grids, or None unless they share one
    /// layout.
    pub(crate) fn new(
        albedo: &Grid,
        grad_x: &Grid,
        grad_y: &Grid,
        height: &Grid,
    ) -> Option<SurfaceTexels> {
        let same = [grad_x, grad_y, height]
            .iter()
            .all(|g| g.same_layout(albedo));
        same.then(|| SurfaceTexels {
            nx: albedo.nx,
            ny: albedo.ny,
            texel: albedo.texel,
            data: albedo
                .data
                .iter()
                .zip(&grad_x.data)
                .zip(&grad_y.data)
                .zip(&height.data)
                .map(|(((a, gx), gy), h)| [*a, *gx, *gy, *h])
                .collect(),
        })
    }

    /// The surface at (x, y), as [`Grid::sample`] reads each grid there.
    #[inline(always)]
    pub(crate) fn sample(&self, x: f64, y: f64) -> SurfaceSample {
        let centre = [self.nx as f64 / 2.0, self.ny as f64 / 2.0];
        let u = x / self.texel + centre[0] - 0.5;
        let v = y / self.texel + centre[1] - 0.5;
        let ((i0, fi), (j0, fj)) = (floor_index(u), floor_index(v));
        let (fu, fv) = (u - fi, v - fj);
        let [c00, c10, c01, c11] = self.corners(i0, j0);
        let channel = |c: usize| {
            let a = c00[c] as f64 * (1.0 - fu) + c10[c] as f64 * fu;
            let b = c01[c] as f64 * (1.0 - fu) + c11[c] as f64 * fu;
            a * (1.0 - fv) + b * fv
        };
        SurfaceSample {
            albedo: channel(0),
            grad: [channel(1), channel(2)],
            height: channel(3),
        }
    }

    /// The four texels around (i0, j0), (i0 + 1, j0 + 1), clamped to the
    /// edge outside the grid.
    #[inline(always)]
    fn corners(&self, i0: isize, j0: isize) -> [[f32; 4]; 4] {
        let (nx, ny) = (self.nx as isize, self.ny as isize);
        if (i0 as usize) < self.nx.wrapping_sub(1) && (j0 as usize) < self.ny.wrapping_sub(1) {
            let base = j0 as usize * self.nx + i0 as usize;
            if let Some(s) = self.data.get(base..base + self.nx + 2) {
                if let (Some(lo), Some(hi)) = (s.first_chunk::<2>(), s.last_chunk::<2>()) {
                    return [lo[0], lo[1], hi[0], hi[1]];
                }
            }
        }
        let at = |i: isize, j: isize| {
            let i = i.clamp(0, nx - 1) as usize;
            let j = j.clamp(0, ny - 1) as usize;
            self.data.get(j * self.nx + i).copied().unwrap_or_default()
        };
        [
            at(i0, j0),
            at(i0 + 1, j0),
            at(i0, j0 + 1),
            at(i0 + 1, j0 + 1),
        ]
    }
}

/// Where a point falls on a [`Grid`]: the texel below and left of it and
/// the bilinear weights towards the next ones.
#[derive(Debug, Clone, Copy)]
struct Footprint {
    i0: isize,
    j0: isize,
    fu: f64,
    fv: f64,
}

/// `u.floor()` (exactly, signed zero included) and the same value as an
/// index (saturating, as `as isize` converts it), from one float-to-integer
/// conversion, without the libm call baseline x86-64 (no SSE4.1 `roundsd`)
/// makes for `floor`: every grid lookup floors twice.
#[inline(always)]
fn floor_index(u: f64) -> (isize, f64) {
    if u.abs() < 4_503_599_627_370_496.0 {
        let whole = u as i64;
        let t = whole as f64;
        if t > u {
            ((whole - 1) as isize, t - 1.0)
        } else {
            (whole as isize, t.copysign(u))
        }
    } else {
        let f = u.floor();
        (f as isize, f)
    }
}

/// Mesostructure height at (x, y), metres, for a procedural heightfield.
pub fn height(spec: &HeightSpec, image: Option<&Grid>, x: f64, y: f64) -> f64 {
    let mm = 1e-3;
    match spec {
        HeightSpec::None => 0.0,
        HeightSpec::Ridges {
            amplitude_mm,
            period_mm,
            direction_deg,
        } => {
            let a = direction_deg.to_radians();
            let across = -x * a.sin() + y * a.cos();
            let f = (across / (period_mm * mm)).rem_euclid(1.0);
            // Rounded wales with narrow grooves between them.
            amplitude_mm * mm * (PI * f).sin().powf(0.6)
        }
        HeightSpec::Knit {
            amplitude_mm,
            stitch_width_mm,
            stitch_height_mm,
            yarn_radius_mm,
        } => {
            knit(
                x / mm,
                y / mm,
                *stitch_width_mm,
                *stitch_height_mm,
                *yarn_radius_mm,
            ) * amplitude_mm
                * mm
        }
        HeightSpec::Cells {
            amplitude_mm,
            cell_mm,
        } => {
            let (f1, f2) = worley(x / (cell_mm * mm), y / (cell_mm * mm));
            // Grains are plateaus, the creases between them are grooves.
            let edge = ((f2 - f1) / 0.3).clamp(0.0, 1.0);
            amplitude_mm * mm * edge * (2.0 - edge)
        }
        HeightSpec::Domes {
            radius_mm,
            height_mm,
            count,
        } => {
            dome(
                x / mm,
                y / mm,
                *radius_mm,
                *height_mm,
                *count,
                DOME_FIELD_MM,
            ) * mm
        }
        HeightSpec::Image { .. } => image.map_or(0.0, |g| g.sample(x, y)),
    }
}

/// The side of the square the dome grid fills, mm (the largest sample).
pub const DOME_FIELD_MM: f64 = 100.0;

/// Height of the spherical-cap grid at (x, y), mm: `count × count` caps of
/// sphere radius `r` rising `h` above the base, centred in equal cells of a
/// `field`-wide square.
pub fn dome(x: f64, y: f64, r: f64, h: f64, count: usize, field: f64) -> f64 {
    let (c, dx, dy) = dome_offset(x, y, count, field);
    let _ = c;
    let rho2 = dx * dx + dy * dy;
    let z = (r * r - rho2).max(0.0).sqrt() - (r - h);
    z.max(0.0)
}

/// The analytic unit normal of the dome grid at (x, y), mm.
pub fn dome_normal(x: f64, y: f64, r: f64, h: f64, count: usize, field: f64) -> [f64; 3] {
    if dome(x, y, r, h, count, field) <= 0.0 {
        return [0.0, 0.0, 1.0];
    }
    let (_, dx, dy) = dome_offset(x, y, count, field);
    let z = (r * r - dx * dx - dy * dy).max(0.0).sqrt();
    [dx / r, dy / r, z / r]
}

fn dome_offset(x: f64, y: f64, count: usize, field: f64) -> (usize, f64, f64) {
    let n = count.max(1) as f64;
    let cell = field / n;
    let centre = |a: f64| {
        ((a + field / 2.0) / cell).floor().clamp(0.0, n - 1.0) * cell + cell / 2.0 - field / 2.0
    };
    (count, x - centre(x), y - centre(y))
}

/// Stockinette: each stitch is a V of two yarn legs; the legs of one row
/// tuck under the row above, so loops interlock. Returns height in [0, 1].
fn knit(x: f64, y: f64, w: f64, h: f64, r: f64) -> f64 {
    let ci = (x / w).floor();
    let cj = (y / h).floor();
    let mut best: f64 = 0.0;
    for di in -1..=1 {
        for dj in -1..=1 {
            let (i, j) = (ci + di as f64, cj + dj as f64);
            let x0 = (i + 0.5) * w;
            let y0 = j * h;
            // The two legs run from the stitch's top corners down to its
            // centre, one row-height and a bit long, so they overlap the
            // next row's loops.
            for side in [-1.0, 1.0] {
                let a = [x0 + side * 0.42 * w, y0 + 1.25 * h];
                let b = [x0 + side * 0.04 * w, y0 - 0.05 * h];
                let (d, t) = segment_distance([x, y], a, b);
                if d < r {
                    // A round yarn that dips where it passes under the next loop.
                    let profile = (1.0 - (d / r).powi(2)).sqrt();
                    let dip = 0.55 + 0.45 * (PI * t).sin();
                    best = best.max(profile * dip);
                }
            }
        }
    }
    best
}

fn segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> (f64, f64) {
    let ab = [b[0] - a[0], b[1] - a[1]];
    let ap = [p[0] - a[0], p[1] - a[1]];
    let len2 = ab[0] * ab[0] + ab[1] * ab[1];
    let t = if len2 > 0.0 {
        ((ap[0] * ab[0] + ap[1] * ab[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let q = [a[0] + t * ab[0] - p[0], a[1] + t * ab[1] - p[1]];
    (q[0].hypot(q[1]), t)
}

/// A deterministic hash of a lattice point to [0, 1).
fn hash2(i: i64, j: i64, salt: u64) -> f64 {
    let mut z = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ salt.wrapping_mul(0x1656_67B1_9E37_79F9);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}

/// Distances to the nearest and second-nearest jittered cell points.
fn worley(x: f64, y: f64) -> (f64, f64) {
    let (ci, cj) = (x.floor() as i64, y.floor() as i64);
    let (mut f1, mut f2) = (f64::MAX, f64::MAX);
    for di in -1..=1 {
        for dj in -1..=1 {
            let (i, j) = (ci + di, cj + dj);
            let px = i as f64 + hash2(i, j, 1);
            let py = j as f64 + hash2(i, j, 2);
            let d = (px - x).hypot(py - y);
            if d < f1 {
                f2 = f1;
                f1 = d;
            } else if d < f2 {
                f2 = d;
            }
        }
    }
    (f1, f2)
}

/// Smooth value noise in [0, 1], unit feature size.
fn value_noise(x: f64, y: f64, salt: u64) -> f64 {
    let (i, j) = (x.floor(), y.floor());
    let (fx, fy) = (x - i, y - j);
    let s = |t: f64| t * t * (3.0 - 2.0 * t);
    let (i, j) = (i as i64, j as i64);
    let a = hash2(i, j, salt) + (hash2(i + 1, j, salt) - hash2(i, j, salt)) * s(fx);
    let b = hash2(i, j + 1, salt) + (hash2(i + 1, j + 1, salt) - hash2(i, j + 1, salt)) * s(fx);
    a + (b - a) * s(fy)
}

/// Albedo at (x, y) given the (mesostructure) height there.
pub fn albedo(spec: &AlbedoSpec, image: Option<&Grid>, x: f64, y: f64, rel_height: f64) -> f64 {
    let mm = 1e-3;
    let v = match spec {
        AlbedoSpec::Uniform { value } => *value,
        AlbedoSpec::Checks {
            dark,
            light,
            check_mm,
            thread_mm,
        } => {
            let c = check_mm * mm;
            let check = ((x / c).floor() + (y / c).floor()).rem_euclid(2.0);
            let thread = 0.5 + 0.5 * (x * 2.0 * PI / (thread_mm * mm)).sin();
            dark + (light - dark) * (0.7 * check + 0.3 * thread)
        }
        AlbedoSpec::Yarn {
            base,
            variation,
            valley_darkening,
        } => {
            let n = value_noise(x / (2.0 * mm), y / (7.0 * mm), 3);
            base * (1.0 + variation * (2.0 * n - 1.0))
                * (1.0 - valley_darkening * (1.0 - rel_height.clamp(0.0, 1.0)))
        }
        AlbedoSpec::Mottled {
            base,
            variation,
            feature_mm,
        } => {
            let f = feature_mm * mm;
            let n =
                0.6 * value_noise(x / f, y / f, 5) + 0.4 * value_noise(2.7 * x / f, 2.7 * y / f, 6);
            base + variation * (2.0 * n - 1.0)
        }
        AlbedoSpec::Image { min, max, .. } => {
            let t = image.map_or(0.0, |g| g.sample(x, y));
            min + (max - min) * t
        }
    };
    v.clamp(0.0, 1.0)
}

/// Macro fold height at (x, y), metres (0 without a macro shape).
pub fn macro_height(m: Option<&MacroSpec>, x: f64, y: f64) -> f64 {
    let Some(m) = m else { return 0.0 };
    let a = m.direction_deg.to_radians();
    let u = x * a.cos() + y * a.sin();
    0.5 * m.fold_height_mm * 1e-3 * (1.0 + (2.0 * PI * u / (m.wavelength_mm * 1e-3)).sin())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_bilinear_reproduces_a_plane() {
        let g = Grid::bake(64, 32, 0.001, |x, y| 2.0 * x - 3.0 * y);
        for (x, y) in [(0.0, 0.0), (0.0101, -0.0053), (-0.02, 0.01)] {
            assert!((g.sample(x, y) - (2.0 * x - 3.0 * y)).abs() < 1e-6);
        }
        let (gx, gy) = g.gradient();
        assert!((gx.sample(0.003, 0.002) - 2.0).abs() < 1e-4);
        assert!((gy.sample(0.003, 0.002) + 3.0).abs() < 1e-4);
    }

    #[test]
    fn fast_floor_is_floor() {
        let cases = [
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            1.5,
            -1.5,
            2.999_999_999_999_999_6,
            -2.999_999_999_999_999_6,
            1e-300,
            -1e-300,
            4_503_599_627_370_495.5,
            -4_503_599_627_370_495.5,
            4_503_599_627_370_496.0,
            1e300,
            -1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
        ];
        for u in cases {
            let (i, f) = floor_index(u);
            assert_eq!(
                (i, f.to_bits()),
                (u.floor() as isize, u.floor().to_bits()),
                "{u}"
            );
        }
        let (i, f) = floor_index(f64::NAN);
        assert!(i == 0 && f.is_nan());
        let mut x = 0.123_456_789_f64;
        for _ in 0..10_000 {
            x = (x * 7919.0 + 0.3137).rem_euclid(2048.0) - 1024.0;
            let (i, f) = floor_index(x);
            assert_eq!(
                (i, f.to_bits()),
                (x.floor() as isize, x.floor().to_bits()),
                "{x}"
            );
        }
    }

    #[test]
    fn sampling_at_a_footprint_is_sampling() {
        let g = Grid::bake(37, 23, 0.002, |x, y| (x * 311.0).sin() + y * y * 1e3);
        for k in 0..2000 {
            let x = -0.05 + 1e-4 * (k as f64 * 0.7);
            let y = 0.03 - 1e-4 * (k as f64 * 0.31);
            let reference = {
                let u = x / g.texel + g.nx as f64 / 2.0 - 0.5;
                let v = y / g.texel + g.ny as f64 / 2.0 - 0.5;
                let (i0, j0) = (u.floor(), v.floor());
                let (fu, fv) = (u - i0, v - j0);
                let (i0, j0) = (i0 as isize, j0 as isize);
                let a = g.at(i0, j0) * (1.0 - fu) + g.at(i0 + 1, j0) * fu;
                let b = g.at(i0, j0 + 1) * (1.0 - fu) + g.at(i0 + 1, j0 + 1) * fu;
                a * (1.0 - fv) + b * fv
            };
            assert_eq!(g.sample(x, y).to_bits(), reference.to_bits(), "({x}, {y})");
        }
    }

    #[test]
    fn knit_loops_have_relief_and_gaps() {
        let mut lo = 0;
        let mut hi = 0;
        for i in 0..200 {
            for j in 0..200 {
                let h = knit(i as f64 * 0.05, j as f64 * 0.05, 4.0, 4.5, 0.85);
                assert!((0.0..=1.0).contains(&h));
                if h < 0.05 {
                    lo += 1;
                } else if h > 0.7 {
                    hi += 1;
                }
            }
        }
        assert!(lo > 1000 && hi > 1000, "{lo} {hi}");
    }

    #[test]
    fn dome_normal_is_the_gradient_normal() {
        let (r, h) = (12.0, 6.0);
        let (x, y) = (-31.0, 14.0);
        let e = 1e-5;
        let dx = (dome(x + e, y, r, h, 3, 100.0) - dome(x - e, y, r, h, 3, 100.0)) / (2.0 * e);
        let dy = (dome(x, y + e, r, h, 3, 100.0) - dome(x, y - e, r, h, 3, 100.0)) / (2.0 * e);
        let len = (dx * dx + dy * dy + 1.0).sqrt();
        let n = dome_normal(x, y, r, h, 3, 100.0);
        for (a, b) in n.iter().zip([-dx / len, -dy / len, 1.0 / len]) {
            assert!((a - b).abs() < 1e-6, "{n:?}");
        }
    }
}
