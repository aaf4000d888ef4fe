//! Registration.

use super::*;

/// Options of [`register`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegisterOptions {
    /// A marker is an outlier candidate when its residual exceeds
    /// `max(outlier_px, outlier_median_factor × median residual)`.
    pub outlier_px: f64,
    /// Multiple of the median residual in that threshold (see `outlier_px`).
    pub outlier_median_factor: f64,
    /// After rejection, a worst residual above this fails the frame.
    pub max_residual_px: f64,
    /// Refine the DLT estimate by Levenberg–Marquardt on the reprojection
    /// error.
    pub refine: bool,
}

impl Default for RegisterOptions {
    fn default() -> Self {
        RegisterOptions {
            outlier_px: 2.0,
            outlier_median_factor: 3.0,
            max_residual_px: 3.0,
            refine: true,
        }
    }
}

/// A frame's plate→image mapping and how well the markers agree with it.
#[derive(Debug, Clone, PartialEq)]
pub struct Registration {
    /// Plate metres → pixels; see the module doc.
    pub homography: Homography,
    /// Per layout marker: reprojection residual in pixels under the final
    /// homography (rejected markers included), `None` if not found.
    pub residuals_px: Vec<Option<f64>>,
    /// RMS and maximum residual over the markers used.
    pub rms_px: f64,
    /// Largest residual over the markers used, pixels.
    pub max_px: f64,
    /// Markers found, and used in the final fit.
    pub found: usize,
    /// Markers used in the final fit (found minus rejected).
    pub used: usize,
    /// Layout indices of the markers rejected as outliers.
    pub rejected: Vec<usize>,
}

/// Fewest markers at which an outlier can be identified: with 5 points
/// every 4-subset fits exactly, so a bad one can be detected (large
/// residual) but not told apart; from 6 on, leave-one-out separates it.
pub const MIN_FOR_REJECTION: usize = 6;

/// Estimates the homography from the detections (indexed like
/// `layout.points`).
///
/// Outlier rejection (for ≤ 8 markers exhaustive leave-one-out is cheaper
/// and more reliable than RANSAC or dropping the worst residual of a fit
/// the outlier has already pulled): while at least 6 markers are used, fit
/// every subset that leaves one marker out, take the subset whose worst
/// residual is smallest, and reject the left-out marker if its residual
/// under that subset's fit exceeds `max(outlier_px, outlier_median_factor ×
/// median residual of the subset)`; otherwise stop. If the worst residual
/// of the final fit exceeds `max_residual_px` the frame fails with
/// [`RectifyError::Inconsistent`] (with 4 markers the fit is exact and
/// cannot reveal an outlier; with 5 it can reveal but not locate one).
pub fn register(
    layout: &MarkerLayout,
    detections: &[Option<Detection>],
    opts: &RegisterOptions,
) -> Result<Registration, RectifyError> {
    if detections.len() != layout.points.len() {
        return Err(RectifyError::InvalidInput(format!(
            "{} detections for {} markers",
            detections.len(),
            layout.points.len()
        )));
    }
    if layout
        .points
        .iter()
        .flatten()
        .chain(&layout.sample_half)
        .any(|v| !v.is_finite())
    {
        return Err(RectifyError::InvalidInput("non-finite layout".into()));
    }
    let found_idx: Vec<usize> = detections
        .iter()
        .enumerate()
        .filter_map(|(i, d)| d.map(|_| i))
        .collect();
    let found = found_idx.len();
    let total = layout.points.len();
    if found < 4 {
        return Err(RectifyError::TooFewMarkers {
            found,
            total,
            missing: (0..total).filter(|i| !found_idx.contains(i)).collect(),
        });
    }
    let plate =
        |set: &[usize]| -> Vec<[f64; 2]> { set.iter().map(|&i| layout.points[i]).collect() };
    let pix = |set: &[usize]| -> Vec<[f64; 2]> {
        set.iter()
            .filter_map(|&i| detections[i].map(|d| d.centre_px))
            .collect()
    };
    if !general_position(&plate(&found_idx)) {
        return Err(RectifyError::Degenerate {
            found,
            used: found_idx,
        });
    }
    let fit_set = |set: &[usize]| -> Result<(Homography, Vec<f64>), RectifyError> {
        let (p, q) = (plate(set), pix(set));
        let h = fit_homography(&p, &q, opts.refine)?;
        let r = residuals(&h, &p, &q);
        Ok((h, r))
    };
    let mut used = found_idx.clone();
    let mut rejected = Vec::new();
    let (mut h, mut res) = fit_set(&used)?;
    while used.len() >= MIN_FOR_REJECTION {
        // The most self-consistent leave-one-out subset …
        let mut best: Option<(f64, usize, Homography, Vec<f64>)> = None;
        for k in 0..used.len() {
            let subset: Vec<usize> = used
                .iter()
                .enumerate()
                .filter_map(|(j, &m)| (j != k).then_some(m))
                .collect();
            if !general_position(&plate(&subset)) {
                continue;
            }
            let Ok((hk, rk)) = fit_set(&subset) else {
                continue;
            };
            let score = rk.iter().copied().fold(0.0, f64::max);
            if best.as_ref().is_none_or(|b| score < b.0) {
                best = Some((score, k, hk, rk));
            }
        }
        let Some((_, k, hk, rk)) = best else { break };
        // … and whether the marker it leaves out disagrees with it.
        let m = used[k];
        let left_out = residuals(&hk, &[layout.points[m]], &pix(&[m]))
            .first()
            .copied()
            .unwrap_or(f64::INFINITY);
        let threshold = opts
            .outlier_px
            .max(opts.outlier_median_factor * median_f64(&rk));
        if left_out <= threshold {
            break;
        }
        rejected.push(used.remove(k));
        h = hk;
        res = rk;
    }
    let max_px = res.iter().copied().fold(0.0, f64::max);
    let rms_px = (res.iter().map(|r| r * r).sum::<f64>() / res.len() as f64).sqrt();
    rejected.sort_unstable();
    // Fold check: w must stay clearly positive over the plate's region of
    // interest (sample corners and markers); w is affine so the corners of
    // the bounding box suffice.
    let [hx, hy] = layout.sample_half;
    let (mut x0, mut x1, mut y0, mut y1) = (-hx, hx, -hy, hy);
    for p in &layout.points {
        x0 = x0.min(p[0]);
        x1 = x1.max(p[0]);
        y0 = y0.min(p[1]);
        y1 = y1.max(p[1]);
    }
    let ws: Vec<f64> = [[x0, y0], [x1, y0], [x0, y1], [x1, y1]]
        .iter()
        .map(|p| h[2][0] * p[0] + h[2][1] * p[1] + h[2][2])
        .collect();
    let (wmin, wmax) = ws
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &w| {
            (a.min(w), b.max(w))
        });
    if !above(wmin, 0.02 * wmax) {
        return Err(RectifyError::Folded { found });
    }
    if !above_or_eq(opts.max_residual_px, max_px) {
        return Err(RectifyError::Inconsistent {
            found,
            used: used.len(),
            rejected,
            max_px,
            limit_px: opts.max_residual_px,
        });
    }
    let residuals_px = (0..total)
        .map(|i| {
            let d = detections[i]?;
            let q = project(&h, layout.points[i])?;
            Some((q[0] - d.centre_px[0]).hypot(q[1] - d.centre_px[1]))
        })
        .collect();
    Ok(Registration {
        homography: h,
        residuals_px,
        rms_px,
        max_px,
        found,
        used: used.len(),
        rejected,
    })
}

/// Turns per-frame registration results into one error naming every frame
/// that failed (with its reason), or `Ok` when all succeeded.
pub fn require_all<'a, I>(frames: I) -> Result<(), RectifyError>
where
    I: IntoIterator<Item = (&'a str, &'a Result<Registration, RectifyError>)>,
{
    let mut total = 0;
    let mut failures = Vec::new();
    for (name, r) in frames {
        total += 1;
        if let Err(e) = r {
            failures.push((name.to_string(), e.to_string()));
        }
    }
    if failures.is_empty() {
        Ok(())
    } else {
        Err(RectifyError::Frames { total, failures })
    }
}

/// `a > b`, false when either is NaN (spelt as a function so the negation
/// `!above(a, b)` reads as "not clearly above", NaN included).
pub(super) fn above(a: f64, b: f64) -> bool {
    a > b
}

/// `a >= b`, false when either is NaN.
pub(super) fn above_or_eq(a: f64, b: f64) -> bool {
    a >= b
}

pub(super) fn median_f64(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_unstable_by(f64::total_cmp);
    match s.len() {
        0 => 0.0,
        n if n % 2 == 1 => s[n / 2],
        n => 0.5 * (s[n / 2 - 1] + s[n / 2]),
    }
}

pub(super) fn residuals(h: &Homography, plate: &[[f64; 2]], pix: &[[f64; 2]]) -> Vec<f64> {
    plate
        .iter()
        .zip(pix)
        .map(|(&p, q)| match project(h, p) {
            Some(r) => (r[0] - q[0]).hypot(r[1] - q[1]),
            None => f64::INFINITY,
        })
        .collect()
}

/// Whether some 4 of the points have no 3 (nearly) collinear.
pub(super) fn general_position(points: &[[f64; 2]]) -> bool {
    let n = points.len();
    if n < 4 {
        return false;
    }
    let scale = points
        .iter()
        .flat_map(|p| points.iter().map(move |q| (p[0] - q[0]).hypot(p[1] - q[1])))
        .fold(0.0, f64::max);
    if !above(scale, 0.0) {
        return false;
    }
    // |cross| / scale² is twice a triangle's area in units of the spread.
    let non_collinear = |a: [f64; 2], b: [f64; 2], c: [f64; 2]| {
        let cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        cross.abs() / (scale * scale) > 1e-3
    };
    for a in 0..n {
        for b in a + 1..n {
            for c in b + 1..n {
                if !non_collinear(points[a], points[b], points[c]) {
                    continue;
                }
                for d in c + 1..n {
                    let (pa, pb, pc, pd) = (points[a], points[b], points[c], points[d]);
                    if non_collinear(pa, pb, pd)
                        && non_collinear(pa, pc, pd)
                        && non_collinear(pb, pc, pd)
                    {
                        return true;
                    }
                }
            }
        }
    }
    false
}

/// Hartley normalisation: translate the centroid to 0, scale the mean
/// distance to √2. Returns the 3×3 transform.
pub(super) fn normaliser(points: &[[f64; 2]]) -> Option<[[f64; 3]; 3]> {
    let n = points.len() as f64;
    let cx = points.iter().map(|p| p[0]).sum::<f64>() / n;
    let cy = points.iter().map(|p| p[1]).sum::<f64>() / n;
    let mean = points
        .iter()
        .map(|p| (p[0] - cx).hypot(p[1] - cy))
        .sum::<f64>()
        / n;
    if !(mean > 0.0 && mean.is_finite()) {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean;
    Some([[s, 0.0, -s * cx], [0.0, s, -s * cy], [0.0, 0.0, 1.0]])
}

pub(super) fn apply(t: &[[f64; 3]; 3], p: [f64; 2]) -> [f64; 2] {
    // Normalisers are affine.
    [
        t[0][0] * p[0] + t[0][1] * p[1] + t[0][2],
        t[1][0] * p[0] + t[1][1] * p[1] + t[1][2],
    ]
}

pub(crate) fn mul3(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut m = [[0.0; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    m
}

/// Inverse of an affine normaliser `[[s,0,tx],[0,s,ty],[0,0,1]]`.
pub(super) fn inverse_normaliser(t: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let s = t[0][0];
    [
        [1.0 / s, 0.0, -t[0][2] / s],
        [0.0, 1.0 / s, -t[1][2] / s],
        [0.0, 0.0, 1.0],
    ]
}

/// Least-squares homography from ≥ 4 correspondences plate → pixels:
/// normalised DLT (SVD of the 2N×9 system with faer) and, with `refine`,
/// Levenberg–Marquardt on the reprojection error. Scaled to unit Frobenius
/// norm with `w > 0` at the points' centroid.
pub fn fit_homography(
    plate: &[[f64; 2]],
    pixels: &[[f64; 2]],
    refine: bool,
) -> Result<Homography, RectifyError> {
    let n = plate.len();
    if n != pixels.len() {
        return Err(RectifyError::InvalidInput(format!(
            "{n} plate points for {} pixel points",
            pixels.len()
        )));
    }
    if n < 4 {
        return Err(RectifyError::TooFewMarkers {
            found: n,
            total: n,
            missing: Vec::new(),
        });
    }
    if plate.iter().chain(pixels).flatten().any(|v| !v.is_finite()) {
        return Err(RectifyError::InvalidInput("non-finite point".into()));
    }
    if !general_position(plate) || !general_position(pixels) {
        return Err(RectifyError::Degenerate {
            found: n,
            used: (0..n).collect(),
        });
    }
    let degenerate = || RectifyError::Degenerate {
        found: n,
        used: (0..n).collect(),
    };
    let tp = normaliser(plate).ok_or_else(degenerate)?;
    let ti = normaliser(pixels).ok_or_else(degenerate)?;
    let p: Vec<[f64; 2]> = plate.iter().map(|&q| apply(&tp, q)).collect();
    let q: Vec<[f64; 2]> = pixels.iter().map(|&x| apply(&ti, x)).collect();
    // Rows padded with zeros to ≥ 9 so the thin SVD's V is 9×9.
    let rows = (2 * n).max(9);
    let a = faer::Mat::<f64>::from_fn(rows, 9, |r, c| {
        let k = r / 2;
        if k >= n {
            return 0.0;
        }
        let ([x, y], [u, v]) = (p[k], q[k]);
        let row = if r % 2 == 0 {
            [0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v]
        } else {
            [x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y, -u]
        };
        row[c]
    });
    let svd = a
        .thin_svd()
        .map_err(|e| RectifyError::Svd(format!("{e:?}")))?;
    let sigma = svd.S().column_vector();
    if !above(sigma[7], 1e-9 * sigma[0]) {
        return Err(degenerate());
    }
    let v = svd.V();
    let mut hn = [[0.0; 3]; 3];
    for (k, item) in hn.iter_mut().flatten().enumerate() {
        *item = v[(k, 8)];
    }
    if refine {
        if let Some(r) = refine_lm(&hn, &p, &q) {
            hn = r;
        }
    }
    let h = mul3(&mul3(&inverse_normaliser(&ti), &hn), &tp);
    normalise_h(h, plate).ok_or_else(degenerate)
}

/// Unit Frobenius norm, sign such that `w > 0` at the centroid of `points`.
pub(super) fn normalise_h(h: Homography, points: &[[f64; 2]]) -> Option<Homography> {
    let norm = h.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
    if !(norm > 0.0 && norm.is_finite()) {
        return None;
    }
    let n = points.len() as f64;
    let cx = points.iter().map(|p| p[0]).sum::<f64>() / n;
    let cy = points.iter().map(|p| p[1]).sum::<f64>() / n;
    let w = h[2][0] * cx + h[2][1] * cy + h[2][2];
    let s = if w < 0.0 { -1.0 / norm } else { 1.0 / norm };
    let mut out = h;
    out.iter_mut().flatten().for_each(|v| *v *= s);
    Some(out)
}

/// Levenberg–Marquardt on the (normalised) reprojection error with
/// `h22 = 1`; `None` when that parameterisation is unsuitable or nothing
/// improved.
pub(super) fn refine_lm(h0: &Homography, p: &[[f64; 2]], q: &[[f64; 2]]) -> Option<Homography> {
    let norm = h0.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
    if !above(h0[2][2].abs(), 1e-6 * norm) {
        return None;
    }
    let mut x = [0.0; 8];
    for (k, v) in x.iter_mut().enumerate() {
        *v = h0[k / 3][k % 3] / h0[2][2];
    }
    let cost = |x: &[f64; 8]| -> f64 {
        p.iter()
            .zip(q)
            .map(|(&[a, b], &[u, v])| {
                let w = x[6] * a + x[7] * b + 1.0;
                let eu = (x[0] * a + x[1] * b + x[2]) / w - u;
                let ev = (x[3] * a + x[4] * b + x[5]) / w - v;
                eu * eu + ev * ev
            })
            .sum()
    };
    let mut c = cost(&x);
    if !c.is_finite() {
        return None;
    }
    let mut lambda = 1e-3;
    for _ in 0..50 {
        let mut jtj = [[0.0; 8]; 8];
        let mut jtr = [0.0; 8];
        for (&[a, b], &[u, v]) in p.iter().zip(q) {
            let w = x[6] * a + x[7] * b + 1.0;
            let pu = (x[0] * a + x[1] * b + x[2]) / w;
            let pv = (x[3] * a + x[4] * b + x[5]) / w;
            let ju = [
                a / w,
                b / w,
                1.0 / w,
                0.0,
                0.0,
                0.0,
                -pu * a / w,
                -pu * b / w,
            ];
            let jv = [
                0.0,
                0.0,
                0.0,
                a / w,
                b / w,
                1.0 / w,
                -pv * a / w,
                -pv * b / w,
            ];
            for (jrow, r) in [(ju, pu - u), (jv, pv - v)] {
                for i in 0..8 {
                    jtr[i] += jrow[i] * r;
                    for k in 0..8 {
                        jtj[i][k] += jrow[i] * jrow[k];
                    }
                }
            }
        }
        let mut improved = false;
        for _ in 0..10 {
            let mut m = jtj;
            for (i, row) in m.iter_mut().enumerate() {
                row[i] += lambda * (jtj[i][i] + 1e-12);
            }
            let rhs = jtr.map(|v| -v);
            let Some(d) = solve8(m, rhs) else {
                lambda *= 10.0;
                continue;
            };
            let mut xn = x;
            for i in 0..8 {
                xn[i] += d[i];
            }
            let cn = cost(&xn);
            if cn.is_finite() && cn < c {
                let gain = c - cn;
                x = xn;
                c = cn;
                lambda = (lambda / 10.0).max(1e-12);
                improved = gain > 1e-15 * (1.0 + c);
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    let mut h = [[0.0; 3]; 3];
    for k in 0..8 {
        h[k / 3][k % 3] = x[k];
    }
    h[2][2] = 1.0;
    Some(h)
}

/// Gaussian elimination with partial pivoting.
pub(super) fn solve8(mut m: [[f64; 8]; 8], mut b: [f64; 8]) -> Option<[f64; 8]> {
    for col in 0..8 {
        let piv = (col..8).max_by(|&i, &j| m[i][col].abs().total_cmp(&m[j][col].abs()))?;
        if !above(m[piv][col].abs(), 1e-300) {
            return None;
        }
        m.swap(col, piv);
        b.swap(col, piv);
        for r in col + 1..8 {
            let f = m[r][col] / m[col][col];
            let pivot_row = m[col];
            for (x, p) in m[r].iter_mut().zip(pivot_row).skip(col) {
                *x -= f * p;
            }
            b[r] -= f * b[col];
        }
    }
    let mut x = [0.0; 8];
    for r in (0..8).rev() {
        let s: f64 = (r + 1..8).map(|k| m[r][k] * x[k]).sum();
        x[r] = (b[r] - s) / m[r][r];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}
