//! Texture alignment: the translation between two rectified textures of the
//! same sample, by phase correlation. A frame registered from the rig's
//! pose is refined against a marker-registered frame of the same view slot:
//! the light differs, the sample's own texture is the same.
//!
//! Phase correlation whitens the cross-power spectrum, so a change of
//! shading between the two lights weighs little against the texture's
//! structure; the textures are mean-removed and Hann-windowed first so
//! their borders do not correlate. The peak is refined to sub-texel
//! precision by a parabola through it and its neighbours on each axis.

use rustfft::num_complex::Complex;
use rustfft::FftPlanner;

use super::RectifyError;
use crate::image_io::Image;

/// A translation found by [`texture_shift`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TextureShift {
    /// Texels to the right (+x, columns): `moving(x, y) ≈ reference(x − dx, y − dy)`.
    pub dx: f64,
    /// Texels down (+y, rows).
    pub dy: f64,
    /// Height of the correlation peak (1 = the same texture, shifted).
    pub peak: f64,
    /// The peak's height over the highest value outside its 5 × 5
    /// neighbourhood within the search window (the allowed shifts and 3
    /// texels more): how unambiguous the match is.
    pub distinctness: f64,
}

/// Spatial frequencies below this many cycles per texture are left out of
/// the correlation.
pub const LOW_CUTOFF_CYCLES: f64 = 3.0;
/// A peak lower than this is no match.
pub const MIN_PEAK: f64 = 0.1;
/// A peak less than this many times the next best in the window is
/// ambiguous.
pub const MIN_DISTINCTNESS: f64 = 2.0;

/// The translation of `moving` against `reference` (same size, one
/// channel), or `None` when the correlation finds no unambiguous match
/// within `max_shift` texels of zero (flat textures, unrelated content).
pub fn texture_shift(
    reference: &Image,
    moving: &Image,
    max_shift: f64,
) -> Result<Option<TextureShift>, RectifyError> {
    let (w, h) = (reference.width, reference.height);
    if moving.width != w || moving.height != h || w < 8 || h < 8 {
        return Err(RectifyError::InvalidInput(format!(
            "texture alignment needs two textures of one size, at least 8×8: {}×{} and {}×{}",
            w, h, moving.width, moving.height
        )));
    }
    if reference.channels != 1 || moving.channels != 1 {
        return Err(RectifyError::InvalidInput(
            "texture alignment works on one channel".into(),
        ));
    }
    let fr = spectrum(reference);
    let fm = spectrum(moving);
    // Frequencies below a few cycles per texture are shading and the
    // window's own leakage, fixed in the frame: they would pull the peak
    // towards zero shift.
    let low = |i: usize, n: usize| i.min(n - i) as f64;
    let mut cross: Vec<Complex<f64>> = fm
        .iter()
        .zip(&fr)
        .enumerate()
        .map(|(k, (m, r))| {
            let c = m * r.conj();
            let n = c.norm();
            if low(k % w, w).hypot(low(k / w, h)) < LOW_CUTOFF_CYCLES {
                Complex::new(0.0, 0.0)
            } else if n > 1e-12 {
                c / n
            } else {
                Complex::new(0.0, 0.0)
            }
        })
        .collect();
    fft2(&mut cross, w, h, true);
    let scale = (w * h) as f64;
    let surface: Vec<f64> = cross.iter().map(|c| c.re / scale).collect();
    let at = |x: isize, y: isize| {
        let xi = x.rem_euclid(w as isize) as usize;
        let yi = y.rem_euclid(h as isize) as usize;
        surface[yi * w + xi]
    };
    // A textile's texture repeats (corduroy's ridges every few texels), so
    // the correlation has a peak at every period: only shifts the pose
    // allows count, and the match must stand out among them.
    let radius = max_shift.max(0.0);
    let window = radius.ceil() as isize + 3;
    let mut peak = f64::NEG_INFINITY;
    let (mut px, mut py) = (0isize, 0isize);
    for y in -window..=window {
        for x in -window..=window {
            let v = at(x, y);
            if (x as f64).hypot(y as f64) <= radius && v > peak {
                (peak, px, py) = (v, x, y);
            }
        }
    }
    if !peak.is_finite() {
        return Ok(None);
    }
    let mut next = f64::NEG_INFINITY;
    for y in -window..=window {
        for x in -window..=window {
            if (x - px).abs() > 2 || (y - py).abs() > 2 {
                next = next.max(at(x, y));
            }
        }
    }
    let distinctness = if next > 1e-12 {
        peak / next
    } else {
        f64::INFINITY
    };
    // Sub-texel: the vertex of the parabola through the peak and its two
    // neighbours on each axis.
    let vertex = |minus: f64, plus: f64| {
        let curvature = minus - 2.0 * peak + plus;
        if curvature < -1e-12 {
            (0.5 * (minus - plus) / curvature).clamp(-0.5, 0.5)
        } else {
            0.0
        }
    };
    let dx = px as f64 + vertex(at(px - 1, py), at(px + 1, py));
    let dy = py as f64 + vertex(at(px, py - 1), at(px, py + 1));
    let found = TextureShift {
        dx,
        dy,
        peak,
        distinctness,
    };
    let ok = peak >= MIN_PEAK
        && distinctness >= MIN_DISTINCTNESS
        && dx.hypot(dy) <= max_shift + 0.5
        && dx.is_finite()
        && dy.is_finite();
    Ok(ok.then_some(found))
}

/// The 2-D spectrum of a texture, mean removed and Hann-windowed.
fn spectrum(image: &Image) -> Vec<Complex<f64>> {
    let (w, h) = (image.width, image.height);
    let n = (w * h) as f64;
    let mean = image.data.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
    let hann = |i: usize, n: usize| {
        0.5 - 0.5 * (2.0 * std::f64::consts::PI * (i as f64 + 0.5) / n as f64).cos()
    };
    let mut data: Vec<Complex<f64>> = (0..w * h)
        .map(|k| {
            let (x, y) = (k % w, k / w);
            let v = f64::from(image.data[k]);
            let v = if v.is_finite() { v - mean } else { 0.0 };
            Complex::new(v * hann(x, w) * hann(y, h), 0.0)
        })
        .collect();
    fft2(&mut data, w, h, false);
    data
}

/// In-place 2-D FFT of a row-major `w × h` array (unnormalised).
fn fft2(data: &mut [Complex<f64>], w: usize, h: usize, inverse: bool) {
    let mut planner = FftPlanner::<f64>::new();
    let (rows, cols) = if inverse {
        (planner.plan_fft_inverse(w), planner.plan_fft_inverse(h))
    } else {
        (planner.plan_fft_forward(w), planner.plan_fft_forward(h))
    };
    for row in data.chunks_exact_mut(w) {
        rows.process(row);
    }
    let mut column = vec![Complex::new(0.0, 0.0); h];
    for x in 0..w {
        for (y, c) in column.iter_mut().enumerate() {
            *c = data[y * w + x];
        }
        cols.process(&mut column);
        for (y, c) in column.iter().enumerate() {
            data[y * w + x] = *c;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bilinearly interpolated hash noise on a 2-texel lattice: broadband,
    /// like a fabric's texture.
    fn value_noise(u: f64, v: f64) -> f64 {
        let hash = |i: i64, j: i64| {
            let mut k = (i.wrapping_mul(73_856_093) ^ j.wrapping_mul(19_349_663)) as u64;
            k ^= k >> 13;
            k = k.wrapping_mul(0x5bd1_e995);
            k ^= k >> 15;
            (k % 1000) as f64 / 1000.0 - 0.5
        };
        let (u, v) = (u / 2.0, v / 2.0);
        let (i, j) = (u.floor() as i64, v.floor() as i64);
        let (fu, fv) = (u - u.floor(), v - v.floor());
        let a = hash(i, j) * (1.0 - fu) + hash(i + 1, j) * fu;
        let b = hash(i, j + 1) * (1.0 - fu) + hash(i + 1, j + 1) * fu;
        a * (1.0 - fv) + b * fv
    }

    /// A random-looking texture, sampled at (x − sx, y − sy), lit by
    /// `gain` with a shading ramp of `slope` across it.
    fn texture(n: usize, sx: f64, sy: f64, gain: f32, slope: f32) -> Image {
        let mut img = Image::new(n, n, 1);
        for y in 0..n {
            for x in 0..n {
                let t = value_noise(x as f64 - sx, y as f64 - sy);
                let shade = 1.0 + slope * (x as f32 / n as f32 - 0.5);
                img.set(x, y, 0, gain * shade * (0.5 + 0.2 * t as f32));
            }
        }
        img
    }

    #[test]
    fn finds_whole_and_sub_texel_shifts_under_other_light() {
        let reference = texture(96, 0.0, 0.0, 1.0, 0.0);
        for (sx, sy) in [(0.0, 0.0), (3.0, -2.0), (-1.4, 0.6), (5.25, 4.5)] {
            // Another light: dimmer and shaded across.
            let moving = texture(96, sx, sy, 0.6, 0.4);
            let s = texture_shift(&reference, &moving, 10.0).unwrap().unwrap();
            assert!(
                (s.dx - sx).abs() < 0.25 && (s.dy - sy).abs() < 0.25,
                "({sx}, {sy}): {s:?}"
            );
        }
    }

    #[test]
    fn a_repeating_texture_is_matched_within_the_window_the_pose_allows() {
        // Corduroy-like ridges every 7 texels, with a little fibre noise.
        let ridges = |sx: f64| {
            let mut img = Image::new(96, 96, 1);
            for y in 0..96 {
                for x in 0..96 {
                    let u = x as f64 - sx;
                    let v = 0.5
                        + 0.3 * (2.0 * std::f64::consts::PI * u / 7.0).sin()
                        + 0.1 * value_noise(u, y as f64);
                    img.set(x, y, 0, v as f32);
                }
            }
            img
        };
        let (reference, moving) = (ridges(0.0), ridges(1.5));
        let s = texture_shift(&reference, &moving, 3.0).unwrap().unwrap();
        assert!((s.dx - 1.5).abs() < 0.25 && s.dy.abs() < 0.25, "{s:?}");
        // A window wider than the period holds the next ridge's peak too:
        // the match is ambiguous or, if taken, still the nearest.
        if let Some(s) = texture_shift(&reference, &moving, 10.0).unwrap() {
            assert!((s.dx - 1.5).abs() < 0.25, "{s:?}");
        }
    }

    #[test]
    fn refuses_flat_unrelated_and_too_far() {
        let reference = texture(64, 0.0, 0.0, 1.0, 0.0);
        let mut flat = Image::new(64, 64, 1);
        flat.data.fill(0.4);
        assert_eq!(texture_shift(&reference, &flat, 10.0).unwrap(), None);
        let far = texture(64, 12.0, 0.0, 1.0, 0.0);
        assert_eq!(texture_shift(&reference, &far, 4.0).unwrap(), None);
        let small = Image::new(4, 4, 1);
        assert!(texture_shift(&small, &small, 1.0).is_err());
        assert!(texture_shift(&reference, &Image::new(32, 64, 1), 1.0).is_err());
    }
}
