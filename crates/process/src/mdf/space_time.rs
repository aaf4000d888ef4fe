//! Space-time.

use super::*;

/// A displacement image `D_{v,l}(x, y)` (or the merged `D_v`), indexed by
/// camera pixel, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct DisplacementImage {
    /// Width, camera pixels.
    pub width: usize,
    /// Height, camera pixels.
    pub height: usize,
    /// Distance along the view ray from the reference plane to the
    /// surface, metres; [`NO_DEPTH`] (−1) where there is no measurement.
    pub depth: Vec<f32>,
    /// Confidence, ≥ 0; 0 exactly where `depth` is −1.
    pub weight: Vec<f32>,
}

impl DisplacementImage {
    /// Fraction of pixels with a measurement.
    pub fn valid_fraction(&self) -> f64 {
        if self.depth.is_empty() {
            return 0.0;
        }
        self.depth.iter().filter(|&&d| d >= 0.0).count() as f64 / self.depth.len() as f64
    }

    pub(super) fn check(&self, index: usize, expected: (usize, usize)) -> Result<(), MdfError> {
        let n = self.width.checked_mul(self.height);
        if (self.width, self.height) != expected
            || n != Some(self.depth.len())
            || n != Some(self.weight.len())
        {
            return Err(MdfError::DisplacementSize {
                index,
                expected,
                got: (self.width, self.height),
            });
        }
        Ok(())
    }
}

/// Parameters of [`space_time`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpaceTimeOptions {
    /// A pixel's brightest frame must exceed this grey value (Wang et al.:
    /// "the prescribed threshold"); otherwise the pixel is occluded → −1.
    pub threshold: f64,
    /// Height of the MDF reference plane, metres (above the mesostructure).
    pub reference_height: f64,
    /// Sine of the smallest accepted angle between camera ray and laser
    /// plane; below it the pixel is "grazing" → −1, weight 0.
    pub min_sin_angle: f64,
    /// Largest accepted displacement, metres; a triangulation farther below
    /// the reference plane (or more than `depth_tolerance` above it) is
    /// rejected → −1.
    pub max_depth: f64,
    /// Triangulated points up to this far above the reference plane are
    /// kept (as depth 0); farther ones are rejected.
    pub depth_tolerance: f64,
    /// Refine the peak time between frames and interpolate the plane.
    pub subframe: bool,
}

impl SpaceTimeOptions {
    /// Defaults: `min_sin_angle = sin 3°`, `depth_tolerance = 2 % of
    /// max_depth`, sub-frame refinement on.
    pub fn new(threshold: f64, reference_height: f64, max_depth: f64) -> SpaceTimeOptions {
        SpaceTimeOptions {
            threshold,
            reference_height,
            min_sin_angle: 3f64.to_radians().sin(),
            max_depth,
            depth_tolerance: 0.02 * max_depth,
            subframe: true,
        }
    }
}

/// What happened to the pixels in [`space_time`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SpaceTimeStats {
    /// Pixels that got a depth.
    pub measured: usize,
    /// No frame above the threshold (occluded or outside the scan).
    pub dark: usize,
    /// Ray nearly parallel to the laser plane (`|n·d| < min_sin_angle`).
    pub grazing: usize,
    /// Triangulation behind the camera, not reaching the reference plane,
    /// or outside `[−depth_tolerance, max_depth]`.
    pub out_of_range: usize,
}

pub(super) enum PixelOutcome {
    Measured(f32, f32),
    Dark,
    Grazing,
    OutOfRange,
}

/// Space-time analysis of one scan sequence (Wang et al., §3.2, Fig. 5b; [4]):
/// per pixel, the frame `i0` with the brightest grey value; if it does not
/// exceed `opts.threshold` the pixel is occluded (−1). Otherwise, with
/// `opts.subframe`, the peak time is refined by a 3-point Gaussian fit of
/// frames `i0−1, i0, i0+1` (temporal median removed as background) and
/// the plane interpolated linearly (normal and offset, signs aligned)
/// between frame `i0` and its neighbour toward the peak; then the pixel
/// ray is intersected with that plane and the displacement measured from
/// the reference plane along the ray.
///
/// **Grazing rule.** With `s = |n·d|` the sine of the angle between the
/// (unit) ray `d` and the plane: `s < min_sin_angle` → −1 and weight 0
/// (counted as `grazing`); otherwise the geometric weight is
/// `g = s · clamp((s − s_min)/s_min, 0, 1)`, rising continuously from 0 at
/// `s_min` and ∝ `s` above `2·s_min` (depth errors scale as `1/s`). The
/// confidence weight is `g · c` with the peak contrast
/// `c = clamp((peak − median)/peak, 0, 1)` (temporal median of the
/// pixel; 0 with fewer than 3 frames). A triangulation is further
/// rejected (−1) when the point is behind the camera or outside
/// `[−depth_tolerance, max_depth]` from the reference plane, so no huge
/// depth is ever produced; depths in `[−depth_tolerance, 0)` read as 0.
///
/// Frames must be in scan order (for the sub-frame interpolation), all of
/// the camera's size; `planes[i]` is frame `i`'s laser plane.
pub fn space_time(
    frames: &[Image],
    planes: &[LaserPlane],
    camera: &PinholeCamera,
    opts: &SpaceTimeOptions,
) -> Result<(DisplacementImage, SpaceTimeStats), MdfError> {
    camera.validate()?;
    if frames.len() != planes.len() {
        return Err(MdfError::FrameCount {
            frames: frames.len(),
            planes: planes.len(),
        });
    }
    if frames.is_empty() {
        return Err(MdfError::InvalidInput("no frames".into()));
    }
    let ok = |v: f64| v.is_finite();
    if !(ok(opts.threshold)
        && ok(opts.reference_height)
        && ok(opts.min_sin_angle)
        && opts.min_sin_angle > 0.0
        && opts.min_sin_angle < 1.0
        && ok(opts.max_depth)
        && opts.max_depth > 0.0
        && ok(opts.depth_tolerance)
        && opts.depth_tolerance >= 0.0)
    {
        return Err(MdfError::InvalidInput(format!(
            "space-time options {opts:?}"
        )));
    }
    let (w, h) = (camera.width, camera.height);
    for (index, f) in frames.iter().enumerate() {
        check_image(f, "frame")?;
        if (f.width, f.height) != (w, h) {
            return Err(MdfError::FrameSize {
                index,
                expected: (w, h),
                got: (f.width, f.height, f.channels),
            });
        }
    }
    let planes: Vec<LaserPlane> = planes
        .iter()
        .enumerate()
        .map(|(i, p)| p.normalised(i))
        .collect::<Result<_, _>>()?;

    let outcomes: Vec<PixelOutcome> = (0..w * h)
        .into_par_iter()
        .map(|idx| {
            let values: Vec<f64> = frames.iter().map(|f| f64::from(grey(f, idx))).collect();
            pixel(idx % w, idx / w, &values, &planes, camera, opts)
        })
        .collect();
    let mut stats = SpaceTimeStats::default();
    let mut depth = Vec::with_capacity(w * h);
    let mut weight = Vec::with_capacity(w * h);
    for o in outcomes {
        let (d, wt) = match o {
            PixelOutcome::Measured(d, wt) => {
                stats.measured += 1;
                (d, wt)
            }
            PixelOutcome::Dark => {
                stats.dark += 1;
                (NO_DEPTH, 0.0)
            }
            PixelOutcome::Grazing => {
                stats.grazing += 1;
                (NO_DEPTH, 0.0)
            }
            PixelOutcome::OutOfRange => {
                stats.out_of_range += 1;
                (NO_DEPTH, 0.0)
            }
        };
        depth.push(d);
        weight.push(wt);
    }
    Ok((
        DisplacementImage {
            width: w,
            height: h,
            depth,
            weight,
        },
        stats,
    ))
}

pub(super) fn pixel(
    i: usize,
    j: usize,
    values: &[f64],
    planes: &[LaserPlane],
    camera: &PinholeCamera,
    opts: &SpaceTimeOptions,
) -> PixelOutcome {
    let mut i0 = 0;
    for (k, &v) in values.iter().enumerate() {
        if v > values[i0] {
            i0 = k;
        }
    }
    let peak = values[i0];
    if !gt(peak, opts.threshold) {
        return PixelOutcome::Dark;
    }
    // Background: the temporal median (0 with fewer than 3 frames, where a
    // median would be the peak itself).
    let bg = if values.len() >= 3 {
        let mut sorted = values.to_vec();
        median(&mut sorted)
    } else {
        0.0
    };
    let mut plane = planes[i0];
    if opts.subframe && i0 > 0 && i0 + 1 < values.len() {
        let d = peak_offset(values[i0 - 1] - bg, peak - bg, values[i0 + 1] - bg);
        let nb = if d < 0.0 { i0 - 1 } else { i0 + 1 };
        let other = planes[nb];
        let sign = if dot(plane.normal, other.normal) < 0.0 {
            -1.0
        } else {
            1.0
        };
        // Interpolate only between similar planes (same scan).
        if dot(plane.normal, other.normal).abs() > 0.9 && d != 0.0 {
            let f = d.abs();
            let n = add(scale(plane.normal, 1.0 - f), scale(other.normal, f * sign));
            let o = (1.0 - f) * plane.offset + f * sign * other.offset;
            let len = norm(n);
            if len > 1e-9 {
                plane = LaserPlane {
                    normal: scale(n, 1.0 / len),
                    offset: o / len,
                };
            }
        }
    }
    let (origin, dir) = camera.ray(i, j);
    let s = dot(plane.normal, dir).abs();
    if !gt(s, opts.min_sin_angle) {
        return PixelOutcome::Grazing;
    }
    let Some((t, _)) = plane.intersect(origin, dir) else {
        return PixelOutcome::Grazing;
    };
    // The reference plane along the same ray.
    if !gt(-dir[2], 1e-12) {
        return PixelOutcome::OutOfRange;
    }
    let t_ref = (opts.reference_height - origin[2]) / dir[2];
    let depth = t - t_ref;
    if !(t > 0.0 && t_ref > 0.0 && depth.is_finite())
        || depth > opts.max_depth
        || depth < -opts.depth_tolerance
    {
        return PixelOutcome::OutOfRange;
    }
    let s_min = opts.min_sin_angle;
    let g = s * ((s - s_min) / s_min).clamp(0.0, 1.0);
    let c = ((peak - bg) / peak).clamp(0.0, 1.0);
    let wt = (g * c) as f32;
    PixelOutcome::Measured(depth.max(0.0) as f32, if wt.is_finite() { wt } else { 0.0 })
}
