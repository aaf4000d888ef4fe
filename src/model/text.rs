//! The small text forms people type on the command line and in API
//! queries: a direction `θ,φ` in degrees and a frame size `WIDTHxHEIGHT`.

use rigd_core::geometry::Direction;

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

/// Parses `θ,φ` in degrees, 0 ≤ θ ≤ 90.
pub fn parse_direction(s: &str) -> Result<Direction, String> {
    parse_direction_within(s, 90.0)
}

/// Parses `θ,φ` in degrees with 0 ≤ θ ≤ `theta_max`.
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
    Ok(Direction::new(theta, phi))
}
