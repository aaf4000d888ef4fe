//! Measured direction tables and the four-nearest-direction interpolation of
//! Sattler et al. (§4.2, eq. 3 for lights and eq. 5 for view slots).
//!
//! A [`DirectionTable`] keeps the measured directions in measurement order
//! (the index of a direction is its light index or view slot) and groups them
//! into rings of equal elevation θ (within [`RING_THETA_TOLERANCE_DEG`]),
//! each ring sorted by azimuth φ. The samplings H1 and H2 of Sattler et al.
//! (Table 1) are such rings: θ = 0, 17, 34, 51, 68, 85° (H1) or
//! 0, 15, 30, 45, 60, 75° (H2) with 1, 6, 12, 18, 20, 24 evenly spaced φ.
//! A table that is not ring-structured still works: every distinct θ becomes
//! a ring, possibly of one sample.
//!
//! # Interpolation
//!
//! [`DirectionTable::interpolate`] returns non-negative weights summing to 1:
//!
//! * θ: the two rings bracketing the query θ are blended linearly in θ.
//! * φ: on each ring, the two samples bracketing the query φ (cyclically, so
//!   φ = 359° between samples at 345° and 0° works) are blended linearly in φ.
//!   A ring with one sample gets the whole ring weight.
//! * Pole: a ring at θ = 0 is one physical direction whatever φ its samples
//!   carry, so its weight is shared equally by its samples and a query at
//!   θ = 0 gives the same weights for every φ. A table without a sample at
//!   the pole blends, for θ below its innermost ring, between that ring's
//!   φ interpolation (at the ring) and the average of the whole ring (at the
//!   pole); this keeps θ = 0 independent of φ at the cost of more than four
//!   entries in that polar cap.
//! * Grazing: beyond the outermost ring (e.g. θ = 85° or 89.9° for H2) the
//!   outermost ring is used alone: no extrapolation.
//! * Out of range: a non-finite query is an error
//!   ([`DirectionError::NonFiniteQuery`]); θ is clamped into [0°, 90°] (a
//!   light below the horizon gets the grazing value rather than a failure in
//!   a render loop) and φ is taken modulo 360°.
//!
//! Away from the pole cap the result has at most four entries, as in eq. 3.

use serde::Serialize;

/// Directions whose θ differ by at most this are on the same ring; two
/// directions this close in both θ and φ are the same direction.
pub const RING_THETA_TOLERANCE_DEG: f64 = 0.01;

/// A direction in the sample frame: θ from the normal, φ azimuth, degrees;
/// the one direction type of rigd, shared with the capture side.
pub use rigd_core::geometry::Direction;

/// Why a direction table or a query direction is rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DirectionError {
    /// The table has no directions.
    #[error("direction table is empty")]
    Empty,
    /// A table direction has a non-finite θ or φ.
    #[error("direction {index} is not finite (θ = {theta_deg}, φ = {phi_deg})")]
    NonFinite {
        /// Index of the direction in the table.
        index: usize,
        /// Its θ, degrees.
        theta_deg: f64,
        /// Its φ, degrees.
        phi_deg: f64,
    },
    /// A table direction's θ is outside [0°, 90°].
    #[error("direction {index} has θ = {theta_deg}°, outside the hemisphere 0..=90°")]
    OutsideHemisphere {
        /// Index of the direction in the table.
        index: usize,
        /// Its θ, degrees.
        theta_deg: f64,
    },
    /// Two table directions off the pole agree in both θ and φ within
    /// [`RING_THETA_TOLERANCE_DEG`]: the same direction measured twice.
    #[error(
        "directions {first} and {second} are the same direction (θ = {theta_deg}°, φ = {phi_deg}°)"
    )]
    Duplicate {
        /// The lower of the two table indices.
        first: usize,
        /// The higher of the two table indices.
        second: usize,
        /// θ of the repeated direction, degrees.
        theta_deg: f64,
        /// φ of the repeated direction, degrees.
        phi_deg: f64,
    },
    /// A direction to interpolate at has a non-finite θ or φ.
    #[error("query direction is not finite (θ = {theta_deg}, φ = {phi_deg})")]
    NonFiniteQuery {
        /// The query's θ, degrees.
        theta_deg: f64,
        /// The query's φ, degrees.
        phi_deg: f64,
    },
}

/// Directions of equal θ, sorted by φ.
#[derive(Debug, Clone, PartialEq)]
struct Ring {
    theta_deg: f64,
    /// (φ in [0, 360), index into the table), sorted by φ.
    members: Vec<(f64, usize)>,
    /// θ = 0: all members are the same physical direction.
    is_pole: bool,
}

impl Ring {
    /// Weights of this ring's members for azimuth `phi` (in [0, 360)),
    /// summing to 1, appended to `out` scaled by `scale`.
    fn push_weights(&self, phi: f64, scale: f64, out: &mut Vec<(usize, f64)>) {
        if self.is_pole {
            self.push_uniform(scale, out);
            return;
        }
        let n = self.members.len();
        if n == 1 {
            out.push((self.members[0].1, scale));
            return;
        }
        // Last member with φ_m ≤ φ; before the first member we wrap to the last.
        let after = self.members.partition_point(|&(p, _)| p <= phi);
        let lo = if after == 0 { n - 1 } else { after - 1 };
        let hi = (lo + 1) % n;
        let (phi_lo, index_lo) = self.members[lo];
        let (phi_hi, index_hi) = self.members[hi];
        let gap = (phi_hi - phi_lo).rem_euclid(360.0);
        if gap <= 0.0 {
            // Unreachable for validated tables (duplicates are rejected).
            out.push((index_lo, scale));
            return;
        }
        let s = ((phi - phi_lo).rem_euclid(360.0) / gap).clamp(0.0, 1.0);
        out.push((index_lo, scale * (1.0 - s)));
        out.push((index_hi, scale * s));
    }

    fn push_uniform(&self, scale: f64, out: &mut Vec<(usize, f64)>) {
        let share = scale / self.members.len() as f64;
        out.extend(self.members.iter().map(|&(_, index)| (index, share)));
    }
}

/// One ring of a [`DirectionTable`], for consumers outside Rust.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RingLayout {
    /// The ring's elevation θ (mean over its members), degrees.
    pub theta_deg: f64,
    /// True for the ring at θ = 0, whose members are one physical direction.
    pub pole: bool,
    /// (φ in [0°, 360°), table index) of each member, sorted by φ.
    pub members: Vec<(f64, usize)>,
}

/// Interpolation weights: (table index, weight), sorted by index, each
/// index once, every weight > 0, weights summing to 1.
#[derive(Debug, Clone, PartialEq)]
pub struct Interpolation {
    entries: Vec<(usize, f64)>,
}

impl Interpolation {
    /// The (table index, weight) pairs, sorted by index; the weights sum to 1.
    pub fn entries(&self) -> &[(usize, f64)] {
        &self.entries
    }

    /// The weight of table index `index` (0 if it does not take part).
    pub fn weight_of(&self, index: usize) -> f64 {
        self.entries
            .binary_search_by_key(&index, |&(i, _)| i)
            .map_or(0.0, |at| self.entries[at].1)
    }

    /// The index with the largest weight (Sattler et al.'s "nearest slot").
    pub fn dominant(&self) -> Option<usize> {
        self.entries
            .iter()
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map(|&(index, _)| index)
    }

    fn from_raw(mut raw: Vec<(usize, f64)>) -> Self {
        raw.sort_by_key(|&(index, _)| index);
        let mut entries: Vec<(usize, f64)> = Vec::with_capacity(raw.len());
        for (index, weight) in raw {
            match entries.last_mut() {
                Some(last) if last.0 == index => last.1 += weight,
                _ => entries.push((index, weight)),
            }
        }
        entries.retain(|&(_, weight)| weight > 0.0);
        // Ring weights and φ weights each sum to 1; renormalising only
        // removes rounding so callers can rely on the sum.
        let total: f64 = entries.iter().map(|&(_, w)| w).sum();
        if total > 0.0 {
            for entry in &mut entries {
                entry.1 /= total;
            }
        }
        Interpolation { entries }
    }
}

/// Measured directions, in measurement order, grouped into rings of equal θ.
#[derive(Debug, Clone, PartialEq)]
pub struct DirectionTable {
    directions: Vec<Direction>,
    /// Sorted by θ, at least one.
    rings: Vec<Ring>,
}

/// φ in [0, 360). `rem_euclid` can round a tiny negative value up to 360.
fn wrap_phi(phi_deg: f64) -> f64 {
    let wrapped = phi_deg.rem_euclid(360.0);
    if wrapped >= 360.0 {
        0.0
    } else {
        wrapped
    }
}

impl DirectionTable {
    /// Builds the table. Errors on an empty list, non-finite values, θ
    /// outside [0°, 90°] and repeated directions (other than repeats of the
    /// pole, which only differ in a meaningless φ).
    pub fn new(directions: Vec<Direction>) -> Result<Self, DirectionError> {
        if directions.is_empty() {
            return Err(DirectionError::Empty);
        }
        for (index, d) in directions.iter().enumerate() {
            if !d.is_finite() {
                return Err(DirectionError::NonFinite {
                    index,
                    theta_deg: d.theta_deg,
                    phi_deg: d.phi_deg,
                });
            }
            if !(0.0..=90.0).contains(&d.theta_deg) {
                return Err(DirectionError::OutsideHemisphere {
                    index,
                    theta_deg: d.theta_deg,
                });
            }
        }
        let mut by_theta: Vec<usize> = (0..directions.len()).collect();
        by_theta.sort_by(|&a, &b| directions[a].theta_deg.total_cmp(&directions[b].theta_deg));

        let mut groups: Vec<Vec<usize>> = Vec::new();
        for index in by_theta {
            let theta = directions[index].theta_deg;
            match groups.last_mut() {
                Some(group)
                    if theta - directions[group[0]].theta_deg <= RING_THETA_TOLERANCE_DEG =>
                {
                    group.push(index)
                }
                _ => groups.push(vec![index]),
            }
        }

        let mut rings = Vec::with_capacity(groups.len());
        for group in groups {
            let theta_deg =
                group.iter().map(|&i| directions[i].theta_deg).sum::<f64>() / group.len() as f64;
            let is_pole = theta_deg <= RING_THETA_TOLERANCE_DEG;
            let mut members: Vec<(f64, usize)> = group
                .iter()
                .map(|&i| (wrap_phi(directions[i].phi_deg), i))
                .collect();
            members.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            if !is_pole {
                check_no_duplicates(&members, &directions)?;
            }
            rings.push(Ring {
                theta_deg,
                members,
                is_pole,
            });
        }
        Ok(DirectionTable { directions, rings })
    }

    /// The directions in measurement order.
    pub fn directions(&self) -> &[Direction] {
        &self.directions
    }

    /// Number of directions in the table.
    pub fn len(&self) -> usize {
        self.directions.len()
    }

    /// Always false: an empty table is rejected by [`DirectionTable::new`].
    pub fn is_empty(&self) -> bool {
        self.directions.is_empty()
    }

    /// θ of each ring, ascending, with the number of samples on it.
    pub fn rings(&self) -> Vec<(f64, usize)> {
        self.rings
            .iter()
            .map(|r| (r.theta_deg, r.members.len()))
            .collect()
    }

    /// The rings as the viewer's shader reads them: θ, whether it is the
    /// pole, and its members (φ in [0, 360), table index) sorted by φ.
    pub fn ring_layout(&self) -> Vec<RingLayout> {
        self.rings
            .iter()
            .map(|r| RingLayout {
                theta_deg: r.theta_deg,
                pole: r.is_pole,
                members: r.members.clone(),
            })
            .collect()
    }

    /// Solid angle (sr) each direction stands for: the hemisphere cut into
    /// bands at the midpoints between rings, each band shared equally by its
    /// ring's members. Sums to 2π.
    pub fn solid_angles(&self) -> Vec<f64> {
        let mut out = vec![0.0; self.directions.len()];
        for (k, ring) in self.rings.iter().enumerate() {
            let lo = if k == 0 {
                0.0
            } else {
                (self.rings[k - 1].theta_deg + ring.theta_deg) / 2.0
            };
            let hi = match self.rings.get(k + 1) {
                Some(next) => (ring.theta_deg + next.theta_deg) / 2.0,
                None => 90.0,
            };
            let band = 2.0 * std::f64::consts::PI * (lo.to_radians().cos() - hi.to_radians().cos());
            for &(_, index) in &ring.members {
                out[index] = band / ring.members.len() as f64;
            }
        }
        out
    }

    /// Bilinear weights of the measured directions around `query`; see the
    /// module documentation for the pole, wrap-around, grazing and
    /// out-of-range rules.
    pub fn interpolate(&self, query: Direction) -> Result<Interpolation, DirectionError> {
        if !query.is_finite() {
            return Err(DirectionError::NonFiniteQuery {
                theta_deg: query.theta_deg,
                phi_deg: query.phi_deg,
            });
        }
        let theta = query.theta_deg.clamp(0.0, 90.0);
        let phi = wrap_phi(query.phi_deg);
        let mut raw = Vec::with_capacity(4);

        let (first, last) = match (self.rings.first(), self.rings.last()) {
            (Some(first), Some(last)) => (first, last),
            // Unreachable: `new` rejects empty tables.
            _ => return Ok(Interpolation { entries: raw }),
        };
        if theta <= first.theta_deg {
            if first.is_pole || first.theta_deg <= 0.0 {
                first.push_weights(phi, 1.0, &mut raw);
            } else {
                // Polar cap without a pole sample: blend the ring's φ
                // interpolation towards its average, which is φ-free at θ = 0.
                let t = theta / first.theta_deg;
                first.push_weights(phi, t, &mut raw);
                first.push_uniform(1.0 - t, &mut raw);
            }
        } else if theta >= last.theta_deg {
            last.push_weights(phi, 1.0, &mut raw);
        } else {
            // first.θ < θ < last.θ, so a bracketing pair exists.
            let upper = self.rings.partition_point(|r| r.theta_deg <= theta);
            let (below, above) = (&self.rings[upper - 1], &self.rings[upper]);
            let t = (theta - below.theta_deg) / (above.theta_deg - below.theta_deg);
            below.push_weights(phi, 1.0 - t, &mut raw);
            above.push_weights(phi, t, &mut raw);
        }
        Ok(Interpolation::from_raw(raw))
    }

    /// The measured direction with the largest interpolation weight.
    pub fn nearest(&self, query: Direction) -> Result<usize, DirectionError> {
        let weights = self.interpolate(query)?;
        // A valid table always yields at least one entry.
        Ok(weights.dominant().unwrap_or(0))
    }
}

/// `members` is one ring sorted by φ; neighbours (cyclically) closer than
/// the tolerance are the same direction measured twice.
fn check_no_duplicates(
    members: &[(f64, usize)],
    directions: &[Direction],
) -> Result<(), DirectionError> {
    if members.len() < 2 {
        return Ok(());
    }
    for k in 0..members.len() {
        let (phi_a, a) = members[k];
        let (phi_b, b) = members[(k + 1) % members.len()];
        let gap = (phi_b - phi_a).rem_euclid(360.0);
        let cyclic_gap = gap.min(360.0 - gap);
        if cyclic_gap <= RING_THETA_TOLERANCE_DEG {
            return Err(DirectionError::Duplicate {
                first: a.min(b),
                second: a.max(b),
                theta_deg: directions[a].theta_deg,
                phi_deg: directions[a].phi_deg,
            });
        }
    }
    Ok(())
}

/// Rings of directions: `counts[i]` directions at elevation `thetas[i]`,
/// evenly spaced in φ from 0 — the layout of rigd's built-in plans.
pub fn ring_directions(thetas: &[f64], counts: &[usize]) -> Vec<Direction> {
    let mut out = Vec::new();
    for (&theta, &n) in thetas.iter().zip(counts) {
        for k in 0..n {
            out.push(Direction::new(theta, 360.0 * k as f64 / n as f64));
        }
    }
    out
}

/// Ring sizes of H1 and H2 (Sattler et al., Table 1): 1 + 6 + 12 + 18 + 20 + 24 = 81.
pub const HEMISPHERE_RING_COUNTS: [usize; 6] = [1, 6, 12, 18, 20, 24];
/// Elevations of H1 (Sattler et al., Table 1, θ1), degrees.
pub const H1_THETAS: [f64; 6] = [0.0, 17.0, 34.0, 51.0, 68.0, 85.0];
/// Elevations of H2 (Sattler et al., Table 1, θ2), degrees.
pub const H2_THETAS: [f64; 6] = [0.0, 15.0, 30.0, 45.0, 60.0, 75.0];

/// The 81 directions of H1.
pub fn h1() -> Vec<Direction> {
    ring_directions(&H1_THETAS, &HEMISPHERE_RING_COUNTS)
}

/// The 81 directions of H2.
pub fn h2() -> Vec<Direction> {
    ring_directions(&H2_THETAS, &HEMISPHERE_RING_COUNTS)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn h2_table() -> DirectionTable {
        DirectionTable::new(h2()).unwrap()
    }

    fn assert_normalised(w: &Interpolation) {
        let sum: f64 = w.entries().iter().map(|e| e.1).sum();
        assert!((sum - 1.0).abs() < 1e-12, "sum {sum}");
        assert!(w.entries().iter().all(|e| e.1 > 0.0 && e.1.is_finite()));
    }

    #[test]
    fn solid_angles_cover_the_hemisphere_and_rings_list_every_direction() {
        for dirs in [h1(), h2(), ring_directions(&[20.0, 50.0], &[5, 7])] {
            let table = DirectionTable::new(dirs).unwrap();
            let omega = table.solid_angles();
            let total: f64 = omega.iter().sum();
            assert!((total - 2.0 * std::f64::consts::PI).abs() < 1e-9, "{total}");
            assert!(omega.iter().all(|&w| w > 0.0));
            let listed: usize = table.ring_layout().iter().map(|r| r.members.len()).sum();
            assert_eq!(listed, table.len());
        }
    }

    #[test]
    fn h1_and_h2_group_into_six_rings_of_table_1() {
        for dirs in [h1(), h2()] {
            let table = DirectionTable::new(dirs).unwrap();
            let counts: Vec<usize> = table.rings().iter().map(|r| r.1).collect();
            assert_eq!(counts, HEMISPHERE_RING_COUNTS.to_vec());
        }
    }

    #[test]
    fn empty_non_finite_outside_and_duplicate_tables_are_rejected() {
        assert_eq!(DirectionTable::new(vec![]), Err(DirectionError::Empty));
        assert!(matches!(
            DirectionTable::new(vec![Direction::new(10.0, f64::NAN)]),
            Err(DirectionError::NonFinite { index: 0, .. })
        ));
        assert!(matches!(
            DirectionTable::new(vec![Direction::new(0.0, 0.0), Direction::new(95.0, 0.0)]),
            Err(DirectionError::OutsideHemisphere { index: 1, .. })
        ));
        assert!(matches!(
            DirectionTable::new(vec![
                Direction::new(30.0, 359.999),
                Direction::new(45.0, 0.0),
                Direction::new(30.0, 0.0)
            ]),
            Err(DirectionError::Duplicate {
                first: 0,
                second: 2,
                ..
            })
        ));
        // Repeats at the pole are one direction with different φ labels.
        assert!(
            DirectionTable::new(vec![Direction::new(0.0, 0.0), Direction::new(0.0, 90.0)]).is_ok()
        );
    }

    #[test]
    fn between_two_rings_weights_are_bilinear() {
        let table = h2_table();
        // θ = 37.5 is halfway between rings 30 (Δφ 30) and 45 (Δφ 20);
        // φ = 10: ring 30 → 0°/30° at 2/3, 1/3; ring 45 → 0°/20° at 1/2, 1/2.
        let w = table.interpolate(Direction::new(37.5, 10.0)).unwrap();
        let index = |theta: f64, phi: f64| {
            table
                .directions()
                .iter()
                .position(|d| d.theta_deg == theta && (d.phi_deg - phi).abs() < 1e-9)
                .unwrap()
        };
        assert_eq!(w.entries().len(), 4);
        assert!((w.weight_of(index(30.0, 0.0)) - 0.5 * 2.0 / 3.0).abs() < 1e-12);
        assert!((w.weight_of(index(30.0, 30.0)) - 0.5 / 3.0).abs() < 1e-12);
        assert!((w.weight_of(index(45.0, 0.0)) - 0.25).abs() < 1e-12);
        assert!((w.weight_of(index(45.0, 20.0)) - 0.25).abs() < 1e-12);
    }

    #[test]
    fn phi_outside_0_360_wraps() {
        let table = h2_table();
        let a = table.interpolate(Direction::new(50.0, -20.0)).unwrap();
        let b = table.interpolate(Direction::new(50.0, 340.0)).unwrap();
        let c = table.interpolate(Direction::new(50.0, 700.0)).unwrap();
        for (x, y) in [(&a, &b), (&b, &c)] {
            for &(i, w) in x.entries() {
                assert!((y.weight_of(i) - w).abs() < 1e-9);
            }
        }
        assert_normalised(&a);
    }

    #[test]
    fn below_horizon_clamps_to_grazing_and_nan_query_is_an_error() {
        let table = h2_table();
        let below = table.interpolate(Direction::new(120.0, 30.0)).unwrap();
        let grazing = table.interpolate(Direction::new(90.0, 30.0)).unwrap();
        assert_eq!(below, grazing);
        assert!(matches!(
            table.interpolate(Direction::new(f64::INFINITY, 0.0)),
            Err(DirectionError::NonFiniteQuery { .. })
        ));
    }

    #[test]
    fn table_without_pole_is_phi_independent_at_theta_0() {
        let table = DirectionTable::new(ring_directions(&[20.0, 40.0], &[4, 8])).unwrap();
        let a = table.interpolate(Direction::new(0.0, 0.0)).unwrap();
        let b = table.interpolate(Direction::new(0.0, 123.0)).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.entries().len(), 4);
        assert!(a.entries().iter().all(|e| (e.1 - 0.25).abs() < 1e-12));
        // At the innermost ring itself it is plain φ interpolation.
        let at_ring = table.interpolate(Direction::new(20.0, 45.0)).unwrap();
        assert_eq!(at_ring.entries().len(), 2);
        assert_normalised(&at_ring);
    }

    #[test]
    fn nearest_picks_the_dominant_direction() {
        let table = h2_table();
        let index = table.nearest(Direction::new(61.0, 17.0)).unwrap();
        assert_eq!(table.directions()[index], Direction::new(60.0, 18.0));
    }
}
