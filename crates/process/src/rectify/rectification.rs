//! Rectification.

use super::*;

/// How an output texel is computed from the frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Filter {
    /// The input pixel containing the texel centre's projection (for
    /// comparison; aliases when minifying, blocky when magnifying).
    Nearest,
    /// One bilinear lookup at the texel centre's projection.
    Bilinear,
    /// Anisotropic area filter: the texel's footprint in the frame is the
    /// parallelogram spanned by the columns of the Jacobian of the
    /// texel→pixel map; the texel is the mean of `k_c × k_r` bilinear
    /// lookups spread evenly over the texel (mapped exactly through the
    /// homography), with `k = ceil(footprint length in pixels)` per texel
    /// axis, capped at [`RectifyOptions::max_taps`]. Minification averages
    /// over the footprint (no aliasing); magnification is one bilinear tap
    /// (smooth).
    Area,
}

/// Options of [`rectify`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RectifyOptions {
    /// How each texel is computed from the frame ([`Filter::Area`] by
    /// default).
    pub filter: Filter,
    /// Cap on taps per texel axis for [`Filter::Area`].
    pub max_taps: usize,
}

impl Default for RectifyOptions {
    fn default() -> Self {
        RectifyOptions {
            filter: Filter::Area,
            max_taps: 16,
        }
    }
}

/// A frontal texture and how much of it the frame covered.
#[derive(Debug, Clone, PartialEq)]
pub struct Rectified {
    /// The frontal texture: row 0 is the region's `+y` edge, column 0 its
    /// `−x` edge; channels as the input.
    pub texture: Image,
    /// Mean over texels of the fraction of their taps that fell inside the
    /// frame (1 = fully covered). Uncovered taps are left out of a texel's
    /// mean; a texel with none is 0.
    pub coverage: f64,
}

/// Resamples `region` of the plate, seen in `image` through `homography`
/// (plate metres → pixels, e.g. [`Registration::homography`]), to a
/// frontal texture of `size = [width, height]` texels; row 0 is the `+y`
/// edge of the region, column 0 the `−x` edge. Channels as the input.
pub fn rectify(
    image: &Image,
    homography: &Homography,
    region: Region,
    size: [usize; 2],
    opts: &RectifyOptions,
) -> Result<Rectified, RectifyError> {
    check_image(image)?;
    let [ow, oh] = size;
    if ow == 0 || oh == 0 || ow > MAX_OUTPUT_SIDE || oh > MAX_OUTPUT_SIDE {
        return Err(RectifyError::InvalidInput(format!(
            "output size {ow}x{oh} (1..={MAX_OUTPUT_SIDE} per side)"
        )));
    }
    if !region.is_valid() {
        return Err(RectifyError::InvalidInput(format!("region {region:?}")));
    }
    if homography.iter().flatten().any(|v| !v.is_finite()) {
        return Err(RectifyError::InvalidInput("non-finite homography".into()));
    }
    if opts.max_taps == 0 || opts.max_taps > 256 {
        return Err(RectifyError::InvalidInput(format!(
            "max_taps {} (1..=256)",
            opts.max_taps
        )));
    }
    let h = homography;
    let ch = image.channels;
    let dx = (region.x_max - region.x_min) / ow as f64;
    let dy = (region.y_max - region.y_min) / oh as f64;
    let mut texture = Image::new(ow, oh, ch);
    let covered: f64 = texture
        .data
        .par_chunks_mut(ow * ch)
        .enumerate()
        .map(|(r, row)| {
            let mut acc = vec![0.0f64; ch];
            let mut row_cover = 0.0;
            for c in 0..ow {
                // Texel centre and its plate-space axes.
                let x = region.x_min + (c as f64 + 0.5) * dx;
                let y = region.y_max - (r as f64 + 0.5) * dy;
                let (kc, kr) = match opts.filter {
                    Filter::Nearest | Filter::Bilinear => (1, 1),
                    Filter::Area => match jacobian(h, x, y) {
                        Some(j) => {
                            let col = |v: f64| {
                                if v.is_finite() {
                                    (v.ceil() as usize).clamp(1, opts.max_taps)
                                } else {
                                    opts.max_taps
                                }
                            };
                            // sqrt of the sum of squares, not hypot: this
                            // runs per texel, the values are pixel scales
                            // (no overflow), and libm's hypot was a tenth
                            // of a 3032×2008 frame's rectification.
                            let len = |a: f64, b: f64| (a * a + b * b).sqrt();
                            (
                                col(len(j[0][0] * dx, j[1][0] * dx)),
                                col(len(j[0][1] * dy, j[1][1] * dy)),
                            )
                        }
                        None => (1, 1),
                    },
                };
                acc.iter_mut().for_each(|a| *a = 0.0);
                let mut hits = 0usize;
                for b in 0..kr {
                    let ty = y - ((b as f64 + 0.5) / kr as f64 - 0.5) * dy;
                    for a in 0..kc {
                        let tx = x + ((a as f64 + 0.5) / kc as f64 - 0.5) * dx;
                        let Some([u, v]) = project(h, [tx, ty]) else {
                            continue;
                        };
                        let ok = match opts.filter {
                            Filter::Nearest => sample_nearest(image, u, v, &mut acc),
                            _ => sample_bilinear(image, u, v, &mut acc),
                        };
                        hits += usize::from(ok);
                    }
                }
                let taps = (kc * kr) as f64;
                if hits > 0 {
                    for (k, a) in acc.iter().enumerate() {
                        let val = (a / hits as f64) as f32;
                        row[c * ch + k] = if val.is_finite() { val } else { 0.0 };
                    }
                }
                row_cover += hits as f64 / taps;
            }
            row_cover
        })
        .sum();
    Ok(Rectified {
        texture,
        coverage: covered / (ow * oh) as f64,
    })
}

/// ∂(u, v)/∂(x, y) of the homography at a plate point.
pub(super) fn jacobian(h: &Homography, x: f64, y: f64) -> Option<[[f64; 2]; 2]> {
    let w = h[2][0] * x + h[2][1] * y + h[2][2];
    if !above(w, 0.0) {
        return None;
    }
    let u = (h[0][0] * x + h[0][1] * y + h[0][2]) / w;
    let v = (h[1][0] * x + h[1][1] * y + h[1][2]) / w;
    Some([
        [(h[0][0] - u * h[2][0]) / w, (h[0][1] - u * h[2][1]) / w],
        [(h[1][0] - v * h[2][0]) / w, (h[1][1] - v * h[2][1]) / w],
    ])
}

pub(super) fn sanitise(v: f32) -> f64 {
    if v.is_finite() {
        f64::from(v)
    } else {
        0.0
    }
}

/// Adds the pixel containing `(u, v)` to `acc`; false when outside.
pub(super) fn sample_nearest(image: &Image, u: f64, v: f64, acc: &mut [f64]) -> bool {
    if !(u >= 0.0 && v >= 0.0 && u < image.width as f64 && v < image.height as f64) {
        return false;
    }
    let (x, y) = (u as usize, v as usize);
    let base = (y * image.width + x) * image.channels;
    for (k, a) in acc.iter_mut().enumerate() {
        *a += sanitise(image.data[base + k]);
    }
    true
}

/// Adds the bilinear interpolation of the pixel centres around `(u, v)` to
/// `acc` (clamped to the edge within the image); false when outside.
pub(super) fn sample_bilinear(image: &Image, u: f64, v: f64, acc: &mut [f64]) -> bool {
    let (w, h) = (image.width, image.height);
    if !(u >= 0.0 && v >= 0.0 && u <= w as f64 && v <= h as f64) {
        return false;
    }
    let fx = (u - 0.5).clamp(0.0, (w - 1) as f64);
    let fy = (v - 0.5).clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (ax, ay) = (fx - x0 as f64, fy - y0 as f64);
    let ch = image.channels;
    let at = |x: usize, y: usize, k: usize| sanitise(image.data[(y * w + x) * ch + k]);
    for (k, a) in acc.iter_mut().enumerate() {
        let top = at(x0, y0, k) * (1.0 - ax) + at(x1, y0, k) * ax;
        let bottom = at(x0, y1, k) * (1.0 - ax) + at(x1, y1, k) * ax;
        *a += top * (1.0 - ay) + bottom * ay;
    }
    true
}

pub(super) fn check_image(image: &Image) -> Result<(), RectifyError> {
    if image.width == 0
        || image.height == 0
        || image.channels == 0
        || image
            .width
            .checked_mul(image.height)
            .and_then(|n| n.checked_mul(image.channels))
            != Some(image.data.len())
    {
        return Err(RectifyError::InvalidInput(format!(
            "image {}x{}x{} with {} samples",
            image.width,
            image.height,
            image.channels,
            image.data.len()
        )));
    }
    Ok(())
}
