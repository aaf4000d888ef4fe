//! Small helpers.

use super::*;

/// `max(c, 0)^n` as `exp(n ln c)`: in `[0, 1]` for every `n ≥ 0`, so it
/// cannot overflow; tiny results underflow harmlessly to 0.
pub(super) fn power(c: f64, n: f64) -> f64 {
    if c > 0.0 {
        (n * c.min(1.0).ln()).exp()
    } else {
        0.0
    }
}

pub(super) fn clamp_exponent(n: f64, max_exponent: f64) -> f64 {
    if n.is_nan() {
        MIN_EXPONENT
    } else {
        n.clamp(MIN_EXPONENT, max_exponent)
    }
}

pub(super) fn padded(mut lobes: Vec<Lobe>, k: usize) -> Vec<Lobe> {
    lobes.truncate(k);
    while lobes.len() < k {
        lobes.push(Lobe::zero());
    }
    lobes
}

pub(super) fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, count) = values.fold((0.0, 0usize), |(s, c), v| (s + v, c + 1));
    if count == 0 {
        0.0
    } else {
        sum / count as f64
    }
}

pub(super) fn unit_lights(lights: &[[f64; 3]]) -> Result<Vec<[f64; 3]>, FitError> {
    if lights.is_empty() {
        return Err(FitError::NoLights);
    }
    lights
        .iter()
        .enumerate()
        .map(|(index, &direction)| {
            normalized(direction).ok_or(FitError::InvalidLight { index, direction })
        })
        .collect()
}

pub(super) fn check_values(values: &[f32], lights: usize) -> Result<(), FitError> {
    if values.len() != lights {
        return Err(FitError::LengthMismatch {
            expected: lights,
            got: values.len(),
        });
    }
    check_finite(values)
}

pub(super) fn check_slot_values(values: &[f32], lights: usize) -> Result<(), FitError> {
    // Not `is_multiple_of`: the workspace still builds on Rust 1.85.
    if (values.len() / lights) * lights != values.len() {
        return Err(FitError::LengthMismatch {
            expected: (values.len() / lights + 1) * lights,
            got: values.len(),
        });
    }
    check_finite(values)
}

pub(super) fn check_finite(values: &[f32]) -> Result<(), FitError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(FitError::NonFiniteValue {
            index,
            value: values[index],
        }),
        None => Ok(()),
    }
}

pub(super) fn check_k(k: usize) -> Result<(), FitError> {
    if (1..=MAX_LOBES).contains(&k) {
        Ok(())
    } else {
        Err(FitError::InvalidLobeCount(k))
    }
}

pub(super) fn add_scaled(a: [f64; 3], b: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}

/// The unit vector along `v`, or None if `v` is zero or not finite.
pub(super) fn normalized(v: [f64; 3]) -> Option<[f64; 3]> {
    if !v.iter().all(|x| x.is_finite()) {
        return None;
    }
    // Scale first so huge or tiny components neither overflow nor vanish.
    let largest = v.iter().fold(0.0f64, |acc, x| acc.max(x.abs()));
    if largest == 0.0 {
        return None;
    }
    let s = v.map(|x| x / largest);
    let length = dot(s, s).sqrt();
    Some(s.map(|x| x / length))
}
