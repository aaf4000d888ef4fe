//! The flat-sample scene: a textured Lambertian sample on a dark holder plate
//! with white point and border markers (seed 000, figure 5), seen by an
//! orthographic camera. A later scene simulator adds relief, shadows and
//! noise; this one costs a plane intersection and a texture lookup per pixel.

/// Half the sample's side (the sample is 10 × 10 cm), metres.
const SAMPLE_HALF_M: f64 = 0.05;
/// Half the holder plate's side, metres.
const HOLDER_HALF_M: f64 = 0.08;
/// Half the width of the field the camera sees, metres.
const FIELD_HALF_M: f64 = 0.1;
/// Fraction of full scale a white, frontally lit texel reaches at nominal exposure.
const WHITE_LEVEL: f64 = 0.8;

/// What one frame needs: directions in the sample frame (unit vectors, z the
/// sample normal, both pointing away from the sample) and the sensor set-up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shot {
    pub light: [f64; 3],
    pub view: [f64; 3],
    pub width: u32,
    pub height: u32,
    pub bit_depth: u8,
    /// Exposure relative to the camera's nominal exposure.
    pub relative_exposure: f64,
}

/// Renders a frame, row-major, one `u16` per pixel at the shot's bit depth.
pub fn render_flat(shot: &Shot) -> Vec<u16> {
    let (w, h) = (shot.width.max(1) as usize, shot.height.max(1) as usize);
    let max_value = ((1u32 << shot.bit_depth.clamp(1, 16)) - 1) as f64;
    let v = unit(shot.view);
    let l = unit(shot.light);
    let irradiance = l[2].max(0.0);
    // Image axes: `up` is the sample normal projected into the image plane;
    // at the pole it is undefined and the sample's +y is used instead.
    let (right, up) = if v[0].hypot(v[1]) < 1e-9 {
        ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    } else {
        let up = unit([-v[2] * v[0], -v[2] * v[1], 1.0 - v[2] * v[2]]);
        (cross(up, v), up)
    };
    let scale = 2.0 * FIELD_HALF_M / w.max(h) as f64;
    let gain = WHITE_LEVEL * max_value * shot.relative_exposure.max(0.0);
    let mut out = vec![0u16; w * h];
    for (j, row) in out.chunks_mut(w).enumerate() {
        let t = (h as f64 / 2.0 - j as f64 - 0.5) * scale;
        for (i, px) in row.iter_mut().enumerate() {
            let s = (i as f64 + 0.5 - w as f64 / 2.0) * scale;
            let p = [
                s * right[0] + t * up[0],
                s * right[1] + t * up[1],
                s * right[2] + t * up[2],
            ];
            // Follow the viewing ray (along -v) to the plane z = 0.
            if v[2] <= 1e-6 {
                continue;
            }
            let k = p[2] / v[2];
            let (x, y) = (p[0] - k * v[0], p[1] - k * v[1]);
            let radiance = albedo(x, y) * irradiance;
            *px = (radiance * gain).round().clamp(0.0, max_value) as u16;
        }
    }
    out
}

/// Reflectance of the plane at (x, y), metres from the sample centre.
pub fn albedo(x: f64, y: f64) -> f64 {
    let (ax, ay) = (x.abs(), y.abs());
    if ax <= SAMPLE_HALF_M && ay <= SAMPLE_HALF_M {
        // A woven-looking print: 1 cm checks with a finer thread pattern.
        let check = ((x / 0.01).floor() + (y / 0.01).floor()).rem_euclid(2.0);
        let thread = 0.5 + 0.5 * (x * 2.0 * std::f64::consts::PI / 0.0025).sin();
        return 0.3 + 0.35 * check + 0.15 * thread;
    }
    if ax <= HOLDER_HALF_M && ay <= HOLDER_HALF_M {
        // Border markers: white lines 5 mm outside the sample.
        let line = |a: f64| (a - (SAMPLE_HALF_M + 0.005)).abs() < 0.001;
        if (line(ax) && ay <= SAMPLE_HALF_M + 0.006) || (line(ay) && ax <= SAMPLE_HALF_M + 0.006) {
            return 0.95;
        }
        // Point markers: 3 mm discs at the corners and edge midpoints.
        let c = HOLDER_HALF_M - 0.012;
        for (mx, my) in [(c, c), (c, 0.0), (0.0, c)] {
            if (ax - mx).hypot(ay - my) < 0.003 {
                return 0.95;
            }
        }
        return 0.06;
    }
    0.0
}

fn unit(a: [f64; 3]) -> [f64; 3] {
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    if n == 0.0 || !n.is_finite() {
        [0.0, 0.0, 1.0]
    } else {
        [a[0] / n, a[1] / n, a[2] / n]
    }
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shot(light: [f64; 3], view: [f64; 3]) -> Shot {
        Shot {
            light,
            view,
            width: 64,
            height: 48,
            bit_depth: 12,
            relative_exposure: 1.0,
        }
    }

    #[test]
    fn frontal_light_is_bright_and_within_12_bits() {
        let f = render_flat(&shot([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]));
        assert_eq!(f.len(), 64 * 48);
        let max = f.iter().copied().max().unwrap_or(0);
        assert!(max > 2000 && max <= 4095, "{max}");
    }

    #[test]
    fn grazing_light_is_darker_than_frontal() {
        let sum = |f: Vec<u16>| f.iter().map(|&x| x as u64).sum::<u64>();
        let front = sum(render_flat(&shot([0.0, 0.0, 1.0], [0.0, 0.0, 1.0])));
        let s85 = 85f64.to_radians();
        let graze = sum(render_flat(&shot(
            [s85.sin(), 0.0, s85.cos()],
            [0.0, 0.0, 1.0],
        )));
        assert!(graze * 5 < front, "{graze} vs {front}");
    }

    #[test]
    fn light_below_the_horizon_gives_black() {
        let f = render_flat(&shot([0.0, 0.0, -1.0], [0.0, 0.0, 1.0]));
        assert!(f.iter().all(|&x| x == 0));
    }

    #[test]
    fn markers_are_white_on_a_dark_plate() {
        assert!(albedo(0.068, 0.068) > 0.9);
        assert!(albedo(0.055, 0.0) > 0.9);
        assert!(albedo(0.075, 0.03) < 0.1);
        assert_eq!(albedo(0.2, 0.0), 0.0);
    }
}
