//! Line detection.

use super::*;

/// Along which image axis [`detect_line`] searched for the peaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScanAxis {
    /// One peak per row (a steep line).
    Rows,
    /// One peak per column (a flat line).
    Columns,
}

/// A straight laser line in an image.
///
/// Parametrisation: the line through `point` with unit `direction`
/// (total least squares, so any orientation is represented equally well);
/// [`LineFit::x_at_y`] / [`LineFit::y_at_x`] give the `x = a·y + b` form.
#[derive(Debug, Clone, PartialEq)]
pub struct LineFit {
    /// The inlier candidate points (continuous pixel coordinates).
    pub points: Vec<[f64; 2]>,
    /// Centroid of the inliers, on the line.
    pub point: [f64; 2],
    /// Unit direction, `direction[1] ≥ 0` (pointing down the image).
    pub direction: [f64; 2],
    /// RMS perpendicular distance of the inliers, pixels.
    pub rms_px: f64,
    /// Candidates rejected as outliers.
    pub rejected: usize,
    /// Whether the peaks were found one per row or one per column.
    pub scan: ScanAxis,
}

impl LineFit {
    /// Signed perpendicular distance of `p` from the line, pixels.
    pub fn distance(&self, p: [f64; 2]) -> f64 {
        let (dx, dy) = (p[0] - self.point[0], p[1] - self.point[1]);
        dx * self.direction[1] - dy * self.direction[0]
    }

    /// `x` on the line at row `y` (`None` for a horizontal line).
    pub fn x_at_y(&self, y: f64) -> Option<f64> {
        (self.direction[1].abs() > 1e-12)
            .then(|| self.point[0] + (y - self.point[1]) * self.direction[0] / self.direction[1])
    }

    /// `y` on the line at column `x` (`None` for a vertical line).
    pub fn y_at_x(&self, x: f64) -> Option<f64> {
        (self.direction[0].abs() > 1e-12)
            .then(|| self.point[1] + (x - self.point[0]) * self.direction[1] / self.direction[0])
    }

    /// The two extreme inliers' feet on the fitted line.
    pub fn endpoints(&self) -> ([f64; 2], [f64; 2]) {
        let along = |p: &[f64; 2]| {
            (p[0] - self.point[0]) * self.direction[0] + (p[1] - self.point[1]) * self.direction[1]
        };
        let (mut lo, mut hi) = (0.0f64, 0.0f64);
        for p in &self.points {
            let s = along(p);
            lo = lo.min(s);
            hi = hi.max(s);
        }
        let at = |s: f64| {
            [
                self.point[0] + s * self.direction[0],
                self.point[1] + s * self.direction[1],
            ]
        };
        (at(lo), at(hi))
    }
}

/// Grey value of pixel `idx` (Rec. 709 luminance for RGB, the mean of the
/// channels otherwise; non-finite samples read as 0).
pub(super) fn grey(image: &Image, idx: usize) -> f32 {
    let c = image.channels;
    let px = image.data.get(idx * c..(idx + 1) * c).unwrap_or(&[]);
    let v = if let [r, g, b] = *px {
        0.2126 * r + 0.7152 * g + 0.0722 * b
    } else if c > 0 {
        px.iter().sum::<f32>() / c as f32
    } else {
        0.0
    };
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

pub(super) fn check_image(image: &Image, what: &str) -> Result<(), MdfError> {
    let len = image
        .width
        .checked_mul(image.height)
        .and_then(|n| n.checked_mul(image.channels));
    if image.width == 0 || image.height == 0 || image.channels == 0 || len != Some(image.data.len())
    {
        return Err(MdfError::InvalidInput(format!(
            "{what}: {}x{}x{} with {} samples",
            image.width,
            image.height,
            image.channels,
            image.data.len()
        )));
    }
    Ok(())
}

/// Separable Gaussian filter of the grey values of `[x0, x1) × [y0, y1)`,
/// reading up to `3σ` beyond the window where the image has pixels (edges
/// clamped). Returns the filtered window, row-major.
pub(super) fn gaussian_window(image: &Image, win: [usize; 4], sigma: f64) -> Vec<f64> {
    let [x0, y0, x1, y1] = win;
    let r = if sigma > 0.0 {
        (3.0 * sigma).ceil() as usize
    } else {
        0
    };
    let kernel: Vec<f64> = {
        let k: Vec<f64> = (0..=2 * r)
            .map(|i| {
                let d = i as f64 - r as f64;
                if r == 0 {
                    1.0
                } else {
                    (-0.5 * (d / sigma).powi(2)).exp()
                }
            })
            .collect();
        let s: f64 = k.iter().sum();
        k.into_iter().map(|v| v / s).collect()
    };
    let (w, h) = (image.width, image.height);
    // Rows ey0..ey1 of the horizontally filtered image, columns x0..x1.
    let ey0 = y0.saturating_sub(r);
    let ey1 = (y1 + r).min(h);
    let clamp_x = |x: isize| x.clamp(0, w as isize - 1) as usize;
    let clamp_y = |y: isize| y.clamp(ey0 as isize, ey1 as isize - 1) as usize;
    let ww = x1 - x0;
    let horiz: Vec<f64> = (ey0..ey1)
        .into_par_iter()
        .flat_map_iter(|y| {
            let kernel = &kernel;
            (x0..x1).map(move |x| {
                kernel
                    .iter()
                    .enumerate()
                    .map(|(k, kv)| {
                        let xx = clamp_x(x as isize + k as isize - r as isize);
                        kv * f64::from(grey(image, y * w + xx))
                    })
                    .sum::<f64>()
            })
        })
        .collect();
    (y0..y1)
        .into_par_iter()
        .flat_map_iter(|y| {
            let (kernel, horiz) = (&kernel, &horiz);
            (0..ww).map(move |xi| {
                kernel
                    .iter()
                    .enumerate()
                    .map(|(k, kv)| {
                        let yy = clamp_y(y as isize + k as isize - r as isize);
                        kv * horiz[(yy - ey0) * ww + xi]
                    })
                    .sum::<f64>()
            })
        })
        .collect()
}

/// Sub-sample offset in `[−0.5, 0.5]` of the peak of three samples
/// `a, b, c` around a maximum `b` (background already removed): the
/// 3-point Gaussian fit when all three are positive (exact for a sampled
/// Gaussian), else the parabola.
pub(super) fn peak_offset(a: f64, b: f64, c: f64) -> f64 {
    let d = if a > 0.0 && b > 0.0 && c > 0.0 {
        let (la, lb, lc) = (a.ln(), b.ln(), c.ln());
        let den = la - 2.0 * lb + lc;
        if den < -1e-12 {
            0.5 * (la - lc) / den
        } else {
            0.0
        }
    } else {
        let den = a - 2.0 * b + c;
        if den < -1e-12 {
            0.5 * (a - c) / den
        } else {
            0.0
        }
    };
    if d.is_finite() {
        d.clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

pub(super) fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let m = v.len() / 2;
    let (_, x, _) = v.select_nth_unstable_by(m, f64::total_cmp);
    *x
}

/// Candidate points scanning `lines` (each a sequence of filtered samples
/// along the scan direction).
pub(super) fn candidates(
    filt: &[f64],
    w: usize,
    h: usize,
    axis: ScanAxis,
    origin: [usize; 2],
    threshold: f64,
) -> Vec<[f64; 2]> {
    let (n_lines, len) = match axis {
        ScanAxis::Rows => (h, w),
        ScanAxis::Columns => (w, h),
    };
    let at = |line: usize, k: usize| match axis {
        ScanAxis::Rows => filt[line * w + k],
        ScanAxis::Columns => filt[k * w + line],
    };
    (0..n_lines)
        .filter_map(|line| {
            if len < 3 {
                return None;
            }
            let (mut best, mut kmax) = (f64::NEG_INFINITY, 0);
            for k in 0..len {
                let v = at(line, k);
                if v > best {
                    best = v;
                    kmax = k;
                }
            }
            if !gt(best, threshold) || kmax == 0 || kmax + 1 == len {
                return None;
            }
            let mut all: Vec<f64> = (0..len).map(|k| at(line, k)).collect();
            let bg = median(&mut all);
            let d = peak_offset(at(line, kmax - 1) - bg, best - bg, at(line, kmax + 1) - bg);
            let along = kmax as f64 + 0.5 + d;
            let across = line as f64 + 0.5;
            Some(match axis {
                ScanAxis::Rows => [origin[0] as f64 + along, origin[1] as f64 + across],
                ScanAxis::Columns => [origin[0] as f64 + across, origin[1] as f64 + along],
            })
        })
        .collect()
}

/// Total least-squares line through `pts`: centroid, unit direction
/// (`dir[1] ≥ 0`), `None` if the points do not define a direction.
pub(super) fn tls(pts: &[[f64; 2]]) -> Option<([f64; 2], [f64; 2])> {
    let n = pts.len() as f64;
    if pts.len() < 2 {
        return None;
    }
    let cx = pts.iter().map(|p| p[0]).sum::<f64>() / n;
    let cy = pts.iter().map(|p| p[1]).sum::<f64>() / n;
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in pts {
        let (dx, dy) = (p[0] - cx, p[1] - cy);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
    }
    // Principal axis of [[sxx, sxy], [sxy, syy]].
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let spread = sxx + syy;
    if !gt(spread, 1e-18) || !angle.is_finite() {
        return None;
    }
    let mut d = [angle.cos(), angle.sin()];
    if d[1] < 0.0 || (d[1] == 0.0 && d[0] < 0.0) {
        d = [-d[0], -d[1]];
    }
    Some(([cx, cy], d))
}

pub(super) fn fit_robust(cands: &[[f64; 2]], axis: ScanAxis) -> Option<LineFit> {
    let mut inliers: Vec<[f64; 2]> = cands.to_vec();
    let mut fit = None;
    for _ in 0..10 {
        let (c, d) = tls(&inliers)?;
        let dist = |p: &[f64; 2]| (p[0] - c[0]) * d[1] - (p[1] - c[1]) * d[0];
        let mut abs: Vec<f64> = cands.iter().map(|p| dist(p).abs()).collect();
        let mad = median(&mut abs);
        let limit = (3.0 * 1.4826 * mad).max(0.5);
        let next: Vec<[f64; 2]> = cands
            .iter()
            .copied()
            .filter(|p| dist(p).abs() <= limit)
            .collect();
        let done = next.len() == inliers.len();
        fit = Some((c, d));
        inliers = next;
        if done || inliers.len() < MIN_LINE_POINTS {
            break;
        }
    }
    let (c, d) = tls(&inliers).or(fit)?;
    if inliers.len() < MIN_LINE_POINTS {
        return None;
    }
    let rms = (inliers
        .iter()
        .map(|p| ((p[0] - c[0]) * d[1] - (p[1] - c[1]) * d[0]).powi(2))
        .sum::<f64>()
        / inliers.len() as f64)
        .sqrt();
    Some(LineFit {
        rejected: cands.len() - inliers.len(),
        points: inliers,
        point: c,
        direction: d,
        rms_px: rms,
        scan: axis,
    })
}

/// Detects the laser line in the reference region `[x0, y0, x1, y1)`
/// (pixels, end exclusive) of `image` (Wang et al., §3.2, Fig. 5a).
///
/// The grey image is Gaussian-filtered (`sigma_px`, 0 = none); then both
/// per row and per column the brightest filtered sample is taken as a
/// candidate if it exceeds `threshold` (in filtered grey units) and is not
/// on the region's border, refined to sub-pixel by a 3-point Gaussian fit
/// after subtracting that row's (column's) median as background. The scan
/// axis giving more candidates wins (a steep line gives one per row, a
/// flat one one per column). A total least-squares line is fitted with
/// iterative rejection of candidates farther than
/// `max(3 · 1.4826 · MAD, 0.5 px)` from it.
pub fn detect_line(
    image: &Image,
    region: [usize; 4],
    sigma_px: f64,
    threshold: f64,
) -> Result<LineFit, MdfError> {
    detect_line_in_regions(image, &[region], sigma_px, threshold)
}

/// [`detect_line`] over several reference regions at once (the reference
/// region of Wang et al. is the image minus the sample's bounding box, which
/// is rarely one rectangle): candidates of all regions are pooled per scan
/// axis before the fit, so a line crossing two bands is fitted over its
/// whole span.
pub fn detect_line_in_regions(
    image: &Image,
    regions: &[[usize; 4]],
    sigma_px: f64,
    threshold: f64,
) -> Result<LineFit, MdfError> {
    check_image(image, "line image")?;
    let first = *regions
        .first()
        .ok_or_else(|| MdfError::InvalidInput("no reference region".into()))?;
    for &region in regions {
        let [x0, y0, x1, y1] = region;
        if !(x0 < x1 && y0 < y1 && x1 <= image.width && y1 <= image.height) {
            return Err(MdfError::InvalidInput(format!(
                "region {region:?} is empty or outside the {}x{} image",
                image.width, image.height
            )));
        }
    }
    if !(sigma_px.is_finite() && (0.0..=100.0).contains(&sigma_px) && threshold.is_finite()) {
        return Err(MdfError::InvalidInput(format!(
            "sigma {sigma_px} px (0..=100), threshold {threshold}"
        )));
    }
    let filtered: Vec<Vec<f64>> = regions
        .iter()
        .map(|&r| gaussian_window(image, r, sigma_px))
        .collect();
    let mut best: Option<LineFit> = None;
    let mut counts = Vec::new();
    for axis in [ScanAxis::Rows, ScanAxis::Columns] {
        let mut c = Vec::new();
        for (&[x0, y0, x1, y1], filt) in regions.iter().zip(&filtered) {
            c.extend(candidates(
                filt,
                x1 - x0,
                y1 - y0,
                axis,
                [x0, y0],
                threshold,
            ));
        }
        counts.push(c.len());
        if let Some(fit) = fit_robust(&c, axis) {
            let better = match &best {
                None => true,
                Some(b) => fit.points.len() > b.points.len(),
            };
            if better {
                best = Some(fit);
            }
        }
    }
    best.ok_or_else(|| MdfError::NoLine {
        region: first,
        reason: format!(
            "{} row and {} column candidates above threshold {threshold} in {} region(s); at least {MIN_LINE_POINTS} collinear needed",
            counts.first().copied().unwrap_or(0),
            counts.get(1).copied().unwrap_or(0),
            regions.len()
        ),
    })
}
