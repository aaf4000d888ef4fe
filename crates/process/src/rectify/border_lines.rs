//! Border lines.

use super::*;

/// The white border lines around the sample: centrelines at `x = ±offset[0]`
/// and `y = ±offset[1]` (plate metres), each `2 × half_width_m` wide,
/// running to the square's corners.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BorderLines {
    /// Distance of the centrelines from the sample centre along x and y,
    /// plate metres.
    pub offset: [f64; 2],
    /// Half a line's width, metres.
    pub half_width_m: f64,
}

impl BorderLines {
    /// The simulator's default: 2 mm lines 5 mm outside a 100 × 100 mm
    /// sample.
    pub fn default_holder() -> BorderLines {
        BorderLines {
            offset: [0.055, 0.055],
            half_width_m: 0.001,
        }
    }

    /// Where the centrelines cross, in the simulator's order
    /// `(−,−), (+,−), (+,+), (−,+)`.
    pub fn corners(&self) -> [[f64; 2]; 4] {
        let [ox, oy] = self.offset;
        [[-ox, -oy], [ox, -oy], [ox, oy], [-ox, oy]]
    }
}

/// Profiles taken across each border line.
pub(super) const LINE_PROFILES: usize = 48;
/// Samples per profile.
pub(super) const PROFILE_SAMPLES: usize = 64;
/// Fewest accepted profiles for a line to be fitted.
pub(super) const MIN_LINE_PROFILES: usize = 10;

/// Locates the border lines' corners (see [`BorderLines::corners`]) given a
/// homography that is already good to about a pixel (e.g. from
/// [`register`] on the point markers). Each line is measured by
/// 48 cross profiles between its ends (4 mm clear of the
/// corners), each spanning `±(half_width + 1.5 mm)` on the plate so it
/// stays clear of the sample 5 mm inside: the line's centre on a profile is
/// the intensity-weighted centroid (above the profile's background, per
/// image length) of the contiguous bright run around its peak; profiles
/// whose run is flat, too wide, or touches the profile's ends (hidden,
/// out of the frame, a bright sample) are dropped. A straight line is
/// fitted through the centres by total least squares, dropping centres
/// farther than `max(0.5 px, 3 × 1.4826 × MAD)`; the corners are the
/// intersections of adjacent lines (`None` when a line has fewer than
/// 10 usable profiles). The detections can be appended to the
/// point markers with [`MarkerLayout::with_border_corners`].
pub fn detect_border_corners(
    image: &Image,
    homography: &Homography,
    border: &BorderLines,
    opts: &DetectOptions,
) -> Result<Vec<Option<Detection>>, RectifyError> {
    check_image(image)?;
    if homography.iter().flatten().any(|v| !v.is_finite())
        || !border.offset.iter().all(|v| v.is_finite() && *v > 0.0)
        || !(border.half_width_m.is_finite() && border.half_width_m > 0.0)
    {
        return Err(RectifyError::InvalidInput(format!(
            "border lines {border:?} or homography"
        )));
    }
    let [ox, oy] = border.offset;
    // Lines as (point on centreline at parameter t, along, across) with
    // t ∈ [−len, len]: bottom, right, top, left.
    // Bottom, right, top, left.
    let line = |centre, along, across, len| LineSpec {
        centre,
        along,
        across,
        len,
    };
    let lines = [
        line([0.0, -oy], [1.0, 0.0], [0.0, 1.0], ox),
        line([ox, 0.0], [0.0, 1.0], [1.0, 0.0], oy),
        line([0.0, oy], [1.0, 0.0], [0.0, 1.0], ox),
        line([-ox, 0.0], [0.0, 1.0], [1.0, 0.0], oy),
    ];
    let grey = Image {
        width: image.width,
        height: image.height,
        channels: 1,
        data: luminance(image),
    };
    let fitted: Vec<Option<FittedLine>> = lines
        .par_iter()
        .map(|spec| fit_border_line(&grey, homography, spec, border, opts))
        .collect();
    // Corner k is where line k meets line k−1 (bottom/left, bottom/right,
    // top/right, top/left).
    let pairs = [(0usize, 3usize), (0, 1), (2, 1), (2, 3)];
    Ok(pairs
        .iter()
        .map(|&(a, b)| {
            let FittedLine {
                a: a1,
                b: b1,
                c: c1,
                used: n1,
                contrast: k1,
            } = fitted[a]?;
            let FittedLine {
                a: a2,
                b: b2,
                c: c2,
                used: n2,
                contrast: k2,
            } = fitted[b]?;
            let det = a1 * b2 - a2 * b1;
            if !above(det.abs(), 1e-6) {
                return None;
            }
            let x = (b1 * c2 - b2 * c1) / det;
            let y = (a2 * c1 - a1 * c2) / det;
            (x.is_finite() && y.is_finite()).then_some(Detection {
                centre_px: [x, y],
                area_px: (n1 + n2) as f64,
                contrast: k1.min(k2),
                elongation: 1.0,
            })
        })
        .collect())
}

/// A border line's centreline on the plate: `centre + t along` for
/// `t ∈ [−len, len]`, with `across` its unit normal.
pub(super) struct LineSpec {
    pub(super) centre: [f64; 2],
    pub(super) along: [f64; 2],
    pub(super) across: [f64; 2],
    pub(super) len: f64,
}

/// A line `a x + b y + c = 0` in the image (unit normal), the profiles
/// used and their median contrast.
#[derive(Clone, Copy)]
pub(super) struct FittedLine {
    pub(super) a: f64,
    pub(super) b: f64,
    pub(super) c: f64,
    pub(super) used: usize,
    pub(super) contrast: f64,
}

/// Fits one border line in the image; see [`detect_border_corners`].
pub(super) fn fit_border_line(
    grey: &Image,
    h: &Homography,
    spec: &LineSpec,
    border: &BorderLines,
    opts: &DetectOptions,
) -> Option<FittedLine> {
    let LineSpec {
        centre,
        along,
        across,
        len,
    } = *spec;
    let clear = 0.004;
    let span = border.half_width_m + 0.0015;
    let mut points = Vec::new();
    let mut contrasts = Vec::new();
    let mut acc = [0.0f64];
    for k in 0..LINE_PROFILES {
        let t = -len + clear + (k as f64 + 0.5) / LINE_PROFILES as f64 * 2.0 * (len - clear);
        let base = [centre[0] + t * along[0], centre[1] + t * along[1]];
        let mut prof = Vec::with_capacity(PROFILE_SAMPLES);
        let mut outside = false;
        for i in 0..PROFILE_SAMPLES {
            let s = -span + (i as f64 + 0.5) / PROFILE_SAMPLES as f64 * 2.0 * span;
            let p = [base[0] + s * across[0], base[1] + s * across[1]];
            let Some(q) = project(h, p) else {
                outside = true;
                break;
            };
            acc[0] = 0.0;
            if !sample_bilinear(grey, q[0], q[1], &mut acc) {
                outside = true;
                break;
            }
            prof.push((q, acc[0]));
        }
        if outside {
            continue;
        }
        let Some(point) = profile_centre(&prof, opts) else {
            continue;
        };
        points.push(point.0);
        contrasts.push(point.1);
    }
    // Total least squares with MAD-based rejection.
    let mut keep: Vec<usize> = (0..points.len()).collect();
    let mut line = None;
    for _ in 0..4 {
        if keep.len() < MIN_LINE_PROFILES {
            return None;
        }
        let n = keep.len() as f64;
        let mx = keep.iter().map(|&i| points[i][0]).sum::<f64>() / n;
        let my = keep.iter().map(|&i| points[i][1]).sum::<f64>() / n;
        let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
        for &i in &keep {
            let (dx, dy) = (points[i][0] - mx, points[i][1] - my);
            sxx += dx * dx;
            syy += dy * dy;
            sxy += dx * dy;
        }
        // Normal = eigenvector of the smaller eigenvalue of the scatter.
        let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
        let (a, b) = (-angle.sin(), angle.cos());
        let c = -(a * mx + b * my);
        let dist: Vec<f64> = keep
            .iter()
            .map(|&i| (a * points[i][0] + b * points[i][1] + c).abs())
            .collect();
        let mad = median_f64(&dist);
        let limit = (3.0 * 1.4826 * mad).max(0.5);
        let next: Vec<usize> = keep
            .iter()
            .zip(&dist)
            .filter_map(|(&i, &d)| (d <= limit).then_some(i))
            .collect();
        line = Some((a, b, c));
        if next.len() == keep.len() {
            break;
        }
        keep = next;
    }
    let (a, b, c) = line?;
    if keep.len() < MIN_LINE_PROFILES || ![a, b, c].iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(FittedLine {
        a,
        b,
        c,
        used: keep.len(),
        contrast: median_f64(&contrasts),
    })
}

/// Centre (image point) and contrast of the bright run around a profile's
/// peak; `None` when implausible (see [`detect_border_corners`]).
pub(super) fn profile_centre(
    prof: &[([f64; 2], f64)],
    opts: &DetectOptions,
) -> Option<([f64; 2], f64)> {
    let n = prof.len();
    if n < 8 {
        return None;
    }
    let mut values: Vec<f64> = prof.iter().map(|p| p.1).collect();
    let peak_i = (0..n).max_by(|&i, &j| values[i].total_cmp(&values[j]))?;
    let peak = values[peak_i];
    // Background: median of the outer quarter on each side.
    let q = n / 4;
    let mut ends: Vec<f64> = values[..q]
        .iter()
        .chain(&values[n - q..])
        .copied()
        .collect();
    ends.sort_unstable_by(f64::total_cmp);
    let bg = ends[ends.len() / 2];
    let contrast = peak - bg;
    if !above_or_eq(contrast, opts.min_contrast) {
        return None;
    }
    let half = bg + 0.5 * contrast;
    let (mut lo, mut hi) = (peak_i, peak_i);
    while lo > 0 && values[lo - 1] > half {
        lo -= 1;
    }
    while hi + 1 < n && values[hi + 1] > half {
        hi += 1;
    }
    // The run must sit inside the profile with background on both sides.
    if lo < q / 2 || hi + q / 2 >= n || hi - lo + 1 > n / 2 {
        return None;
    }
    // Centroid over the run widened by its half-width on each side, per
    // image length.
    let pad = (hi - lo).div_ceil(2) + 1;
    let (a, b) = (lo.saturating_sub(pad), (hi + pad).min(n - 1));
    let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for i in a..=b {
        let prev = prof[i.saturating_sub(1)].0;
        let next = prof[(i + 1).min(n - 1)].0;
        let dl = 0.5 * (next[0] - prev[0]).hypot(next[1] - prev[1]);
        let w = (values[i] - bg).max(0.0) * dl;
        sw += w;
        sx += w * prof[i].0[0];
        sy += w * prof[i].0[1];
    }
    values.clear();
    (above(sw, 0.0)).then(|| ([sx / sw, sy / sw], contrast))
}
