//! Directions on the hemisphere above the sample, and rotations between frames.
//!
//! Angles at the API boundary are degrees (`theta_deg` from the sample normal,
//! `phi_deg` in the sample plane, counter-clockwise from the sample's +x axis);
//! internally everything is unit vectors, so the pole (θ = 0, where φ carries
//! no information) and the φ wrap-around need no special cases beyond
//! [`Direction::from_vector`].

use serde::{Deserialize, Serialize};

/// A 3-vector; plain arrays keep the numerics dependency-free and `Copy`.
pub type Vec3 = [f64; 3];
/// A rotation matrix, row-major: `m[row][col]`.
pub type Mat3 = [[f64; 3]; 3];

/// Below this sin θ a direction is treated as the pole, where φ is undefined.
pub const POLE_EPS: f64 = 1e-12;

/// A direction given by polar angle θ (from the normal) and azimuth φ, in degrees.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Direction {
    /// Polar angle from the sample normal, degrees.
    pub theta_deg: f64,
    /// Azimuth in the sample plane, counter-clockwise from +x, degrees.
    pub phi_deg: f64,
}

impl Direction {
    /// The direction at polar angle `theta_deg` and azimuth `phi_deg`.
    pub fn new(theta_deg: f64, phi_deg: f64) -> Self {
        Direction { theta_deg, phi_deg }
    }

    /// Both angles are finite numbers.
    pub fn is_finite(&self) -> bool {
        self.theta_deg.is_finite() && self.phi_deg.is_finite()
    }

    /// The unit vector of this direction in its frame (z is the normal).
    pub fn to_vector(self) -> Vec3 {
        let (t, p) = (self.theta_deg.to_radians(), self.phi_deg.to_radians());
        [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
    }

    /// The direction of a (not necessarily unit) vector. φ is normalised into
    /// [0, 360); at the pole, where φ is undefined, it is reported as 0.
    pub fn from_vector(v: Vec3) -> Self {
        let u = normalize(v);
        let rho = u[0].hypot(u[1]);
        let theta = rho.atan2(u[2]).to_degrees();
        let phi = if rho < POLE_EPS {
            0.0
        } else {
            wrap_deg_360(u[1].atan2(u[0]).to_degrees())
        };
        Direction {
            theta_deg: theta,
            phi_deg: phi,
        }
    }

    /// Same direction with φ in [0, 360) and φ = 0 at the pole.
    pub fn canonical(self) -> Self {
        Direction::from_vector(self.to_vector())
    }

    /// Great-circle angle to another direction, in degrees.
    pub fn angle_to_deg(self, other: Direction) -> f64 {
        angle_between(self.to_vector(), other.to_vector()).to_degrees()
    }
}

/// Wraps an angle into [0, 360).
pub fn wrap_deg_360(a: f64) -> f64 {
    let r = a.rem_euclid(360.0);
    // rem_euclid can return exactly 360.0 for tiny negative inputs.
    if r >= 360.0 {
        0.0
    } else {
        r
    }
}

/// Wraps an angle into (-180, 180].
pub fn wrap_deg_180(a: f64) -> f64 {
    let r = wrap_deg_360(a);
    if r > 180.0 {
        r - 360.0
    } else {
        r
    }
}

/// Dot product.
pub fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Cross product.
pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Euclidean length.
pub fn norm(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// `a` times `s`.
pub fn scale(a: Vec3, s: f64) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// `a + b`.
pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `a − b`.
pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// Unit vector along `a`; the zero vector maps to +z so callers never see NaN.
pub fn normalize(a: Vec3) -> Vec3 {
    let n = norm(a);
    if n == 0.0 || !n.is_finite() {
        [0.0, 0.0, 1.0]
    } else {
        scale(a, 1.0 / n)
    }
}

/// `a / |a|`, `None` for a zero or non-finite vector (where
/// [`normalize`] would answer +z).
pub fn unit(a: Vec3) -> Option<Vec3> {
    let n = norm(a);
    (n.is_finite() && n > 1e-300).then(|| scale(a, 1.0 / n))
}

/// Angle between two vectors in radians, accurate near 0 and π (atan2 of
/// |a×b| and a·b instead of acos, which loses half its digits near 0).
pub fn angle_between(a: Vec3, b: Vec3) -> f64 {
    norm(cross(a, b)).atan2(dot(a, b))
}

/// `m · v`.
pub fn mat_vec(m: &Mat3, v: Vec3) -> Vec3 {
    [dot(m[0], v), dot(m[1], v), dot(m[2], v)]
}

/// `a · b`.
pub fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut r = [[0.0; 3]; 3];
    for (i, row) in r.iter_mut().enumerate() {
        for (j, cell) in row.iter_mut().enumerate() {
            *cell = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    r
}

/// The transpose (the inverse of a rotation).
pub fn transpose(m: &Mat3) -> Mat3 {
    let mut r = [[0.0; 3]; 3];
    for (i, row) in m.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            r[j][i] = *v;
        }
    }
    r
}

/// Rotation about the x axis by `a` radians.
pub fn rot_x(a: f64) -> Mat3 {
    let (s, c) = a.sin_cos();
    [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
}

/// Rotation about the y axis by `a` radians.
pub fn rot_y(a: f64) -> Mat3 {
    let (s, c) = a.sin_cos();
    [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
}

/// Rotation about the z axis by `a` radians.
pub fn rot_z(a: f64) -> Mat3 {
    let (s, c) = a.sin_cos();
    [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
}

/// Rotates `v` about the unit axis `k` by `a` radians (Rodrigues).
pub fn rotate_about(v: Vec3, k: Vec3, a: f64) -> Vec3 {
    let (s, c) = a.sin_cos();
    add(
        add(scale(v, c), scale(cross(k, v), s)),
        scale(k, dot(k, v) * (1.0 - c)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn pole_has_phi_zero_whatever_phi_was_given() {
        for phi in [0.0, 90.0, 359.9, -45.0] {
            let d = Direction::new(0.0, phi).canonical();
            assert_eq!(d.theta_deg, 0.0);
            assert_eq!(d.phi_deg, 0.0);
        }
    }

    #[test]
    fn phi_wraps_into_0_360() {
        let d = Direction::new(30.0, 360.0 + 15.0).canonical();
        assert!((d.phi_deg - 15.0).abs() < 1e-9);
        let d = Direction::new(30.0, -15.0).canonical();
        assert!((d.phi_deg - 345.0).abs() < 1e-9);
        assert_eq!(wrap_deg_360(-1e-18), 0.0);
        assert_eq!(wrap_deg_180(190.0), -170.0);
        assert_eq!(wrap_deg_180(180.0), 180.0);
    }

    #[test]
    fn grazing_85_degrees_round_trips() {
        let d = Direction::new(85.0, 345.0);
        let back = Direction::from_vector(d.to_vector());
        assert!((back.theta_deg - 85.0).abs() < 1e-12);
        assert!((back.phi_deg - 345.0).abs() < 1e-9);
    }

    #[test]
    fn angle_between_is_accurate_for_tiny_angles() {
        let a = Direction::new(40.0, 10.0).to_vector();
        let b = Direction::new(40.0 + 1e-7, 10.0).to_vector();
        let got = angle_between(a, b).to_degrees();
        assert!((got - 1e-7).abs() < 1e-12, "{got}");
    }

    #[test]
    fn zero_vector_normalizes_to_finite() {
        let n = normalize([0.0, 0.0, 0.0]);
        assert!(n.iter().all(|x| x.is_finite()));
    }

    proptest! {
        #[test]
        fn direction_vector_round_trip(theta in 1e-6f64..90.0, phi in 0.0f64..360.0) {
            let d = Direction::new(theta, phi);
            let back = Direction::from_vector(d.to_vector());
            prop_assert!(d.angle_to_deg(back) < 1e-9);
        }

        #[test]
        fn rotation_preserves_angles(ax in -3.2f64..3.2, ay in -3.2f64..3.2, az in -3.2f64..3.2) {
            let r = mat_mul(&rot_z(az), &mat_mul(&rot_y(ay), &rot_x(ax)));
            let a = Direction::new(20.0, 30.0).to_vector();
            let b = Direction::new(70.0, 200.0).to_vector();
            let before = angle_between(a, b);
            let after = angle_between(mat_vec(&r, a), mat_vec(&r, b));
            prop_assert!((before - after).abs() < 1e-12);
        }
    }
}
