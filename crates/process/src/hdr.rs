//! Exposure brackets merged into one linear frame. Raw values are linear in
//! the light and the exposure time, so each of a step's exposures, divided
//! by its time, estimates the same radiance; the merge is their weighted
//! mean, with Debevec & Malik's hat weighting ("Recovering High Dynamic
//! Range Radiance Maps from Photographs", 1997) over the range where a
//! sample measures anything: zero at or above the clipping level, zero at
//! or below the noise floor, rising linearly from either end to the middle.

use rigd_core::pixel_format::CLIPPED_LEVEL;

/// A sample at or below this fraction of full scale is lost in noise: about
/// 8 digital numbers of a 12-bit sensor, the read noise and dark-current
/// scatter of the cameras of the profiles.
pub const NOISE_FLOOR: f32 = 0.002;

/// How much a sample of value `z` (linear, 1 = full scale) counts in the
/// merge: Debevec & Malik's hat between [`NOISE_FLOOR`] and
/// [`CLIPPED_LEVEL`], 0 outside.
pub fn hat_weight(z: f32) -> f32 {
    if !(z > NOISE_FLOOR && z < CLIPPED_LEVEL) {
        return 0.0;
    }
    let mid = 0.5 * (NOISE_FLOOR + CLIPPED_LEVEL);
    if z <= mid {
        z - NOISE_FLOOR
    } else {
        CLIPPED_LEVEL - z
    }
}

/// One exposure of a bracket: its samples (linear, 1 = full scale, all
/// exposures the same length) and its exposure time, seconds.
#[derive(Debug, Clone, Copy)]
pub struct Exposure<'a> {
    /// The samples, linear, 1 = full scale.
    pub samples: &'a [f32],
    /// Exposure time, seconds (positive).
    pub time_s: f64,
}

/// Why exposures cannot be merged.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MergeError {
    /// No exposure at all.
    #[error("no exposure to merge")]
    Empty,
    /// Exposures of different sizes.
    #[error("exposure {index} has {found} samples, the first {expected}")]
    Size {
        /// Which exposure (from 0).
        index: usize,
        /// Samples it has.
        found: usize,
        /// Samples the first has.
        expected: usize,
    },
    /// An exposure time that is not a positive number.
    #[error("exposure {index} has the time {time_s} s: expected a positive number")]
    Time {
        /// Which exposure (from 0).
        index: usize,
        /// The time given.
        time_s: f64,
    },
}

/// A merged frame: its samples in units of the reference exposure's full
/// scale (a highlight beyond what that exposure could hold is above 1),
/// and the level at or above which a merged sample is still clipped.
#[derive(Debug, Clone, PartialEq)]
pub struct Merged {
    /// The samples, linear: 1 = full scale of the reference exposure.
    pub samples: Vec<f32>,
    /// A sample at or above this is clipped in every exposure: what it
    /// shows is a lower bound. [`CLIPPED_LEVEL`] scaled by the reference
    /// exposure over the shortest.
    pub clipped_level: f32,
}

/// The level at or above which a merged sample is clipped when the
/// reference exposure is `reference_s` and the shortest `shortest_s`:
/// [`CLIPPED_LEVEL`] scaled by their ratio.
pub fn clipped_level(reference_s: f64, shortest_s: f64) -> f32 {
    if reference_s > 0.0 && shortest_s > 0.0 {
        CLIPPED_LEVEL * (reference_s / shortest_s) as f32
    } else {
        CLIPPED_LEVEL
    }
}

/// Merges a step's exposures, scaled to the exposure time `reference_s`.
/// Each sample is the hat-weighted mean of its exposures' values divided
/// by their times. Where no exposure measured it (every one clipped, or
/// lost in noise), it is the longest unclipped exposure's value, else the
/// shortest exposure's (clipped: at or above [`Merged::clipped_level`]).
pub fn merge(exposures: &[Exposure<'_>], reference_s: f64) -> Result<Merged, MergeError> {
    let first = exposures.first().ok_or(MergeError::Empty)?;
    let n = first.samples.len();
    for (index, e) in exposures.iter().enumerate() {
        if e.samples.len() != n {
            return Err(MergeError::Size {
                index,
                found: e.samples.len(),
                expected: n,
            });
        }
        if !(e.time_s.is_finite() && e.time_s > 0.0) {
            return Err(MergeError::Time {
                index,
                time_s: e.time_s,
            });
        }
    }
    // Shortest first: the fallbacks below take the first that qualifies.
    let mut order: Vec<&Exposure<'_>> = exposures.iter().collect();
    order.sort_by(|a, b| a.time_s.total_cmp(&b.time_s));
    let scale: Vec<f32> = order
        .iter()
        .map(|e| (reference_s / e.time_s) as f32)
        .collect();
    let shortest = scale[0];
    let mut samples = Vec::with_capacity(n);
    for j in 0..n {
        let (mut sum, mut weights) = (0.0f32, 0.0f32);
        let mut unclipped = None;
        for (e, &s) in order.iter().zip(&scale) {
            let z = e.samples[j];
            let w = hat_weight(z);
            sum += w * z * s;
            weights += w;
            if z < CLIPPED_LEVEL {
                // The longest unclipped one holds the most light.
                unclipped = Some(z * s);
            }
        }
        samples.push(if weights > 0.0 {
            sum / weights
        } else if let Some(v) = unclipped {
            v
        } else {
            order[0].samples[j] * shortest
        });
    }
    Ok(Merged {
        samples,
        clipped_level: clipped_level(reference_s, order[0].time_s),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// What a linear sensor records of `radiance` (full scale at 1 for the
    /// exposure 1 s) in `time_s`: clipped at 1.
    fn record(radiance: &[f32], time_s: f64) -> Vec<f32> {
        radiance
            .iter()
            .map(|r| (r * time_s as f32).min(1.0))
            .collect()
    }

    #[test]
    fn a_highlight_that_clips_the_long_exposure_is_measured_by_the_short_one() {
        let radiance = [0.3f32, 0.9, 3.0, 12.0];
        let long = record(&radiance, 1.0);
        let short = record(&radiance, 0.25);
        let m = merge(
            &[
                Exposure {
                    samples: &long,
                    time_s: 1.0,
                },
                Exposure {
                    samples: &short,
                    time_s: 0.25,
                },
            ],
            1.0,
        )
        .unwrap();
        assert!((m.samples[0] - 0.3).abs() < 1e-5);
        assert!((m.samples[1] - 0.9).abs() < 1e-5);
        assert!((m.samples[2] - 3.0).abs() < 1e-5, "{:?}", m.samples);
        // 12 × 0.25 = 3 clips the short one too: a lower bound, flagged.
        assert_eq!(m.clipped_level, CLIPPED_LEVEL * 4.0);
        assert!(m.samples[3] >= m.clipped_level);
        assert!(m.samples[2] < m.clipped_level);
    }

    #[test]
    fn one_exposure_is_itself() {
        let s = [0.0f32, 0.001, 0.5, 0.996, 1.0];
        let m = merge(
            &[Exposure {
                samples: &s,
                time_s: 0.1,
            }],
            0.1,
        )
        .unwrap();
        assert_eq!(m.samples, s.to_vec());
        assert_eq!(m.clipped_level, CLIPPED_LEVEL);
    }

    #[test]
    fn darkness_below_the_noise_floor_keeps_the_longest_exposure_s_value() {
        // Both under the floor: no weight; the long one holds more light.
        let long = [0.0015f32];
        let short = [0.0002f32];
        let m = merge(
            &[
                Exposure {
                    samples: &short,
                    time_s: 0.1,
                },
                Exposure {
                    samples: &long,
                    time_s: 1.0,
                },
            ],
            1.0,
        )
        .unwrap();
        assert_eq!(m.samples, vec![0.0015]);
    }

    #[test]
    fn bad_brackets_are_errors_not_numbers() {
        let a = [0.5f32; 4];
        let b = [0.5f32; 3];
        assert_eq!(merge(&[], 1.0), Err(MergeError::Empty));
        assert!(matches!(
            merge(
                &[
                    Exposure {
                        samples: &a,
                        time_s: 1.0
                    },
                    Exposure {
                        samples: &b,
                        time_s: 0.5
                    }
                ],
                1.0
            ),
            Err(MergeError::Size {
                index: 1,
                found: 3,
                expected: 4
            })
        ));
        for t in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(matches!(
                merge(
                    &[Exposure {
                        samples: &a,
                        time_s: t
                    }],
                    1.0
                ),
                Err(MergeError::Time { index: 0, .. })
            ));
        }
    }

    #[test]
    fn the_hat_is_zero_at_both_ends_and_peaks_in_the_middle() {
        assert_eq!(hat_weight(0.0), 0.0);
        assert_eq!(hat_weight(NOISE_FLOOR), 0.0);
        assert_eq!(hat_weight(CLIPPED_LEVEL), 0.0);
        assert_eq!(hat_weight(1.0), 0.0);
        assert_eq!(hat_weight(f32::NAN), 0.0);
        let mid = 0.5 * (NOISE_FLOOR + CLIPPED_LEVEL);
        assert!(hat_weight(mid) > hat_weight(0.25));
        assert!(hat_weight(mid) > hat_weight(0.9));
    }

    proptest! {
        /// A bracket of a linear, noiseless sensor merges back to the
        /// radiance wherever some exposure measured it; where none did the
        /// sample is flagged, never passed off as measured.
        #[test]
        fn a_noiseless_bracket_merges_back_to_the_radiance(
            radiance in proptest::collection::vec(0.0f32..64.0, 1..64),
            steps in 1usize..5,
            factor in 1.5f64..8.0,
        ) {
            let times: Vec<f64> = (0..steps).map(|k| factor.powi(-(k as i32))).collect();
            let recorded: Vec<Vec<f32>> = times.iter().map(|&t| record(&radiance, t)).collect();
            let exposures: Vec<Exposure<'_>> = recorded
                .iter()
                .zip(&times)
                .map(|(s, &t)| Exposure { samples: s, time_s: t })
                .collect();
            let m = merge(&exposures, 1.0).unwrap();
            let shortest = *times.last().unwrap() as f32;
            for (&r, &v) in radiance.iter().zip(&m.samples) {
                let measured = times.iter().any(|&t| {
                    let z = r * t as f32;
                    z > NOISE_FLOOR && z < CLIPPED_LEVEL
                });
                if measured {
                    prop_assert!((v - r).abs() <= 1e-4 * r.max(1.0), "{v} for {r}");
                    prop_assert!(v < m.clipped_level);
                } else if r * shortest >= CLIPPED_LEVEL {
                    prop_assert!(v >= m.clipped_level, "{v} for {r} not flagged");
                }
            }
        }
    }
}
