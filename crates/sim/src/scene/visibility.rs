//! Per-vertex binary visibility maps over the hemisphere (Ganster et al., the
//! hemisphere model): for a grid of vertices on a folded sample, which
//! directions of the sample frame's upper hemisphere the macro shape leaves
//! open. Computed once per scene; a frame only looks them up.

use rayon::prelude::*;

use super::spec::{MacroSpec, VisibilitySpec};
use super::surface::macro_height;

#[derive(Debug, Clone)]
pub struct VisibilityMaps {
    vertices: usize,
    theta_cells: usize,
    phi_cells: usize,
    half: [f64; 2],
    /// `vertices² × theta_cells × phi_cells`, 1 = open.
    bits: Vec<u8>,
}

impl VisibilityMaps {
    pub fn compute(m: &MacroSpec, spec: &VisibilitySpec, half: [f64; 2]) -> VisibilityMaps {
        let n = spec.vertices.max(2);
        let (nt, np) = (spec.theta_cells.max(1), spec.phi_cells.max(1));
        let top = m.fold_height_mm * 1e-3;
        let step = (m.wavelength_mm * 1e-3 / 64.0).max(1e-5);
        let mut bits = vec![0u8; n * n * nt * np];
        bits.par_chunks_mut(nt * np)
            .enumerate()
            .for_each(|(v, cells)| {
                let (vi, vj) = (v % n, v / n);
                let x = -half[0] + 2.0 * half[0] * vi as f64 / (n - 1) as f64;
                let y = -half[1] + 2.0 * half[1] * vj as f64 / (n - 1) as f64;
                let z = macro_height(Some(m), x, y);
                for (c, bit) in cells.iter_mut().enumerate() {
                    let d = cell_direction(c / np, c % np, nt, np);
                    *bit = u8::from(open(m, [x, y, z], d, top, half, step));
                }
            });
        VisibilityMaps {
            vertices: n,
            theta_cells: nt,
            phi_cells: np,
            half,
            bits,
        }
    }

    /// Visibility of direction `d` (unit, sample frame) at (x, y): the
    /// binary maps of the four nearest vertices, blended bilinearly over
    /// the vertices and linearly between the two nearest polar rings, so
    /// shadow boundaries are smooth rather than stepped by the cells.
    pub fn visibility(&self, x: f64, y: f64, d: [f64; 3]) -> f64 {
        if d[2] <= 0.0 {
            return 0.0;
        }
        let n = self.vertices;
        let (nt, np) = (self.theta_cells, self.phi_cells);
        let theta = d[2].clamp(-1.0, 1.0).acos();
        let phi = d[1].atan2(d[0]).rem_euclid(std::f64::consts::TAU);
        let pi = (((phi / std::f64::consts::TAU) * np as f64) as usize).min(np - 1);
        let tf =
            (theta / std::f64::consts::FRAC_PI_2 * nt as f64 - 0.5).clamp(0.0, (nt - 1) as f64);
        let t0 = (tf.floor() as usize).min(nt - 1);
        let t1 = (t0 + 1).min(nt - 1);
        let wt = tf - t0 as f64;
        let u =
            ((x + self.half[0]) / (2.0 * self.half[0]) * (n - 1) as f64).clamp(0.0, (n - 1) as f64);
        let v =
            ((y + self.half[1]) / (2.0 * self.half[1]) * (n - 1) as f64).clamp(0.0, (n - 1) as f64);
        let (i0, j0) = (
            (u.floor() as usize).min(n - 2),
            (v.floor() as usize).min(n - 2),
        );
        let (fu, fv) = (u - i0 as f64, v - j0 as f64);
        let cells = nt * np;
        let bit = |i: usize, j: usize| {
            let base = (j * n + i) * cells;
            let a = self.bits[base + t0 * np + pi] as f64;
            let b = self.bits[base + t1 * np + pi] as f64;
            a + (b - a) * wt
        };
        let a = bit(i0, j0) * (1.0 - fu) + bit(i0 + 1, j0) * fu;
        let b = bit(i0, j0 + 1) * (1.0 - fu) + bit(i0 + 1, j0 + 1) * fu;
        a * (1.0 - fv) + b * fv
    }
}

/// The centre direction of a hemisphere cell.
fn cell_direction(ti: usize, pi: usize, nt: usize, np: usize) -> [f64; 3] {
    let theta = (ti as f64 + 0.5) / nt as f64 * std::f64::consts::FRAC_PI_2;
    let phi = (pi as f64 + 0.5) / np as f64 * std::f64::consts::TAU;
    [
        theta.sin() * phi.cos(),
        theta.sin() * phi.sin(),
        theta.cos(),
    ]
}

/// Whether the ray from `p` along `d` leaves over the folds.
fn open(m: &MacroSpec, p: [f64; 3], d: [f64; 3], top: f64, half: [f64; 2], step: f64) -> bool {
    let mut t = step;
    loop {
        let q = [p[0] + t * d[0], p[1] + t * d[1], p[2] + t * d[2]];
        if q[2] >= top || q[0].abs() > half[0] || q[1].abs() > half[1] {
            return true;
        }
        if macro_height(Some(m), q[0], q[1]) > q[2] + 1e-6 {
            return false;
        }
        t += step;
    }
}
