//! Integration.

use super::*;

/// Frankot–Chellappa integration of gradients `p = ∂z/∂x` (x = column) and
/// `q = ∂z/∂y` (y = up, i.e. row decreasing) on a `width × height` grid;
/// returns the zero-mean height, row-major. Non-finite gradients count as 0.
pub fn integrate_frankot_chellappa(
    p: &[f32],
    q: &[f32],
    width: usize,
    height: usize,
) -> Result<Vec<f32>, PsError> {
    let n = width * height;
    if p.len() != n || q.len() != n || n == 0 {
        return Err(PsError::InvalidInput {
            origin: "Frankot–Chellappa".into(),
            reason: format!(
                "{} p and {} q values for a {width}x{height} grid",
                p.len(),
                q.len()
            ),
        });
    }
    let finite = |v: f32| if v.is_finite() { f64::from(v) } else { 0.0 };
    // Work in (row, column): ∂z/∂column = p, ∂z/∂row = -q because y is up.
    let mut gc: Vec<Complex<f64>> = p.iter().map(|&v| Complex::new(finite(v), 0.0)).collect();
    let mut gr: Vec<Complex<f64>> = q.iter().map(|&v| Complex::new(-finite(v), 0.0)).collect();
    let mut planner = FftPlanner::new();
    fft2(&mut planner, &mut gc, width, height, false);
    fft2(&mut planner, &mut gr, width, height, false);
    let omega = |k: usize, len: usize| {
        let signed = if k <= len / 2 {
            k as f64
        } else {
            k as f64 - len as f64
        };
        2.0 * std::f64::consts::PI * signed / len as f64
    };
    let j = Complex::new(0.0, 1.0);
    let mut z = gc;
    for r in 0..height {
        let wr = omega(r, height);
        for c in 0..width {
            let wc = omega(c, width);
            let denom = wc * wc + wr * wr;
            let i = r * width + c;
            z[i] = if denom > 0.0 {
                -j * (z[i] * wc + gr[i] * wr) / denom
            } else {
                Complex::new(0.0, 0.0)
            };
        }
    }
    fft2(&mut planner, &mut z, width, height, true);
    let scale = 1.0 / n as f64;
    let mean = z.iter().map(|v| v.re).sum::<f64>() * scale * scale;
    Ok(z.iter().map(|v| (v.re * scale - mean) as f32).collect())
}

/// In-place unnormalised 2-D FFT of a row-major `width × height` grid.
pub(super) fn fft2(
    planner: &mut FftPlanner<f64>,
    data: &mut [Complex<f64>],
    width: usize,
    height: usize,
    inverse: bool,
) {
    let plan = |planner: &mut FftPlanner<f64>, len| {
        if inverse {
            planner.plan_fft_inverse(len)
        } else {
            planner.plan_fft_forward(len)
        }
    };
    let row_fft = plan(planner, width);
    data.par_chunks_mut(width).for_each_init(
        || vec![Complex::new(0.0, 0.0); row_fft.get_inplace_scratch_len()],
        |scratch, row| row_fft.process_with_scratch(row, scratch),
    );
    let mut columns = vec![Complex::new(0.0, 0.0); data.len()];
    for r in 0..height {
        for c in 0..width {
            columns[c * height + r] = data[r * width + c];
        }
    }
    let col_fft = plan(planner, height);
    columns.par_chunks_mut(height).for_each_init(
        || vec![Complex::new(0.0, 0.0); col_fft.get_inplace_scratch_len()],
        |scratch, col| col_fft.process_with_scratch(col, scratch),
    );
    for r in 0..height {
        for c in 0..width {
            data[r * width + c] = columns[c * height + r];
        }
    }
}
