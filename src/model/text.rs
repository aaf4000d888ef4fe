//! The small text forms people type on the command line, in API queries
//! and in plan files, and the one rule for each: a direction `θ,φ` in
//! degrees, an azimuth, a frame size `WIDTHxHEIGHT`, a name (a sample, an
//! operator) and the file-name form of a name.

use rigd_core::geometry::{wrap_deg_360, Direction};

/// Most characters a sample, operator or plan name may have.
pub const MAX_NAME_CHARS: usize = 128;

/// The largest |φ| accepted, degrees: ten turns. An azimuth beyond it is a
/// typo or garbage, not a direction anyone meant, and far beyond it whole
/// turns no longer round-trip through the trigonometry of the rig's
/// kinematics.
pub const MAX_ABS_PHI_DEG: f64 = 3600.0;

/// Parses `WIDTHxHEIGHT`, each 1 ..= 8192.
pub fn parse_frame_size(s: &str) -> Result<[u32; 2], String> {
    let bad = || format!("`{s}`: expected WIDTHxHEIGHT with each between 1 and 8192, e.g. 64x64");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let w: u32 = w.trim().parse().map_err(|_| bad())?;
    let h: u32 = h.trim().parse().map_err(|_| bad())?;
    if !(1..=8192).contains(&w) || !(1..=8192).contains(&h) {
        return Err(bad());
    }
    Ok([w, h])
}

/// A number for a message: plain where that is short, in exponent form
/// where plain would print hundreds of digits.
pub fn short_number(x: f64) -> String {
    if x.is_finite() && x.abs() >= 1e9 {
        format!("{x:e}")
    } else {
        x.to_string()
    }
}

/// The one rule for an azimuth someone gives: a finite number of degrees
/// within ±[`MAX_ABS_PHI_DEG`], returned in [0, 360), so the capture, the
/// index and the export all see the same value.
pub fn normalise_phi(phi_deg: f64) -> Result<f64, String> {
    if phi_deg.is_finite() && phi_deg.abs() <= MAX_ABS_PHI_DEG {
        // `+ 0.0` turns -0.0 into 0.0.
        Ok(wrap_deg_360(phi_deg) + 0.0)
    } else {
        Err(format!(
            "φ = {}: expected a finite azimuth within ±{MAX_ABS_PHI_DEG} degrees",
            short_number(phi_deg)
        ))
    }
}

/// A direction someone gave, checked: θ finite and within `theta` (a
/// range of degrees, which says whether its end is included), φ as
/// [`normalise_phi`] has it.
pub fn check_direction(
    d: Direction,
    theta: impl std::ops::RangeBounds<f64> + std::fmt::Debug,
) -> Result<Direction, String> {
    if !(d.theta_deg.is_finite() && theta.contains(&d.theta_deg)) {
        return Err(format!(
            "θ = {}: expected {} degrees",
            short_number(d.theta_deg),
            describe_range(&theta)
        ));
    }
    Ok(Direction::new(d.theta_deg + 0.0, normalise_phi(d.phi_deg)?))
}

/// `0 ≤ θ < 90`, `0 ≤ θ ≤ 180`: a range of θ for a message.
fn describe_range(r: &(impl std::ops::RangeBounds<f64> + std::fmt::Debug)) -> String {
    use std::ops::Bound::*;
    let low = match r.start_bound() {
        Included(x) => format!("{x} ≤ "),
        Excluded(x) => format!("{x} < "),
        Unbounded => String::new(),
    };
    let high = match r.end_bound() {
        Included(x) => format!(" ≤ {x}"),
        Excluded(x) => format!(" < {x}"),
        Unbounded => String::new(),
    };
    format!("{low}θ{high}")
}

/// Parses `θ,φ` in degrees, 0 ≤ θ ≤ 90, φ normalised into [0, 360).
pub fn parse_direction(s: &str) -> Result<Direction, String> {
    parse_direction_within(s, 90.0)
}

/// Parses `θ,φ` in degrees with 0 ≤ θ ≤ `theta_max`, φ normalised into
/// [0, 360) ([`normalise_phi`]).
pub fn parse_direction_within(s: &str, theta_max: f64) -> Result<Direction, String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [theta, phi] = parts[..] else {
        return Err(format!("`{s}`: expected θ,φ in degrees, like 45,90"));
    };
    let num = |v: &str| {
        v.parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| format!("`{v}` in `{s}` is not a number"))
    };
    let (theta, phi) = (num(theta)?, num(phi)?);
    if !(0.0..=theta_max).contains(&theta) {
        return Err(format!("θ = {theta}: expected 0 ..= {theta_max} degrees"));
    }
    let phi = normalise_phi(phi).map_err(|e| format!("`{s}`: {e}"))?;
    Ok(Direction::new(theta + 0.0, phi))
}

/// The one rule for a name someone gives (a sample, an operator): 1 to
/// [`MAX_NAME_CHARS`] characters, not blank, no control characters. The
/// error says what was expected; callers prefix the option's name.
pub fn check_name(name: &str) -> Result<(), String> {
    if name.trim().is_empty() {
        return Err("is empty".into());
    }
    let chars = name.chars().count();
    if chars > MAX_NAME_CHARS {
        return Err(format!(
            "has {chars} characters: expected 1 to {MAX_NAME_CHARS}"
        ));
    }
    if name.chars().any(char::is_control) {
        return Err("holds control characters".into());
    }
    Ok(())
}

/// Whether `c` may stand in a name that becomes part of a file name (a run
/// id, a device's name): an ASCII letter or digit, `-` or `_`.
pub fn is_file_name_char(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '-' || c == '_'
}

/// A name as one path component: letters, digits, `-` and `_` are kept,
/// everything else becomes `_`; at most `max` characters; never empty. So
/// no name can climb out of the folder it is put in (`..`, `/`) or hide
/// (a leading `.`). The daemon's run ids and the command line's default
/// run folders are both made with it.
pub fn sanitize(s: &str, max: usize) -> String {
    let out: String = s
        .chars()
        .map(|c| if is_file_name_char(c) { c } else { '_' })
        .take(max)
        .collect();
    if out.is_empty() {
        "x".into()
    } else {
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_become_one_safe_path_component() {
        assert_eq!(sanitize("Felt #3 / blue", 40), "Felt__3___blue");
        assert_eq!(sanitize("../../etc", 40), "______etc");
        assert_eq!(sanitize("", 40), "x");
        assert_eq!(sanitize("ü", 40), "_");
        assert_eq!(sanitize("a\0b", 40), "a_b");
        assert_eq!(sanitize(&"a".repeat(100), 40).len(), 40);
    }

    #[test]
    fn names_are_short_printable_and_not_blank() {
        assert!(check_name("felt #3").is_ok());
        assert!(check_name(&"a".repeat(MAX_NAME_CHARS)).is_ok());
        for bad in ["", "  ", "a\0b", "a\nb", &"a".repeat(MAX_NAME_CHARS + 1)] {
            assert!(check_name(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn azimuths_are_normalised_once_and_garbage_refused() {
        assert_eq!(normalise_phi(-30.0), Ok(330.0));
        assert_eq!(normalise_phi(720.0), Ok(0.0));
        assert_eq!(normalise_phi(-0.0), Ok(0.0));
        assert_eq!(normalise_phi(359.5), Ok(359.5));
        for bad in [1e300, f64::NAN, f64::INFINITY, -MAX_ABS_PHI_DEG - 1.0] {
            let e = normalise_phi(bad).expect_err("refused");
            assert!(e.contains("φ = ") && e.contains("3600"), "{e}");
        }
        // The message stays short for a huge value.
        assert!(normalise_phi(1e300).expect_err("huge").len() < 80);
        assert_eq!(
            parse_direction("45,-90").map(|d| d.phi_deg),
            Ok(270.0),
            "text"
        );
        assert!(parse_direction("45,1e300").is_err());
        let d = check_direction(Direction::new(30.0, 400.0), 0.0..90.0).expect("usable");
        assert_eq!((d.theta_deg, d.phi_deg), (30.0, 40.0));
        let e = check_direction(Direction::new(90.0, 0.0), 0.0..90.0).expect_err("θ = 90");
        assert!(e.contains("0 ≤ θ < 90"), "{e}");
    }
}
