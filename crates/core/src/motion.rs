//! The trapezoidal motion model of a stepper axis or robot joint.

/// Maximum velocity (units/s), acceleration (units/s²) and settle time (s).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Trapezoid {
    /// Top speed, units/s.
    pub max_velocity: f64,
    /// Acceleration and deceleration, units/s².
    pub acceleration: f64,
    /// Time to settle after the move ends, s.
    pub settle_s: f64,
}

impl Trapezoid {
    /// Time to travel `distance` units from rest to rest, without settling:
    /// a triangle profile for short moves, a trapezoid for long ones.
    pub fn travel_time(&self, distance: f64) -> f64 {
        let d = distance.abs();
        if d == 0.0 || !d.is_finite() {
            return 0.0;
        }
        let (v, a) = (self.max_velocity, self.acceleration);
        // Distance covered while accelerating to v and braking again.
        let ramp = v * v / a;
        if d <= ramp {
            2.0 * (d / a).sqrt()
        } else {
            d / v + v / a
        }
    }

    /// Travel time plus settle time; zero for no motion (nothing to settle).
    pub fn move_time(&self, distance: f64) -> f64 {
        if distance.abs() < 1e-12 {
            0.0
        } else {
            self.travel_time(distance) + self.settle_s
        }
    }

    /// Position `t` seconds into a move from `from` to `to`.
    pub fn position_at(&self, from: f64, to: f64, t: f64) -> f64 {
        let d = (to - from).abs();
        let total = self.travel_time(d);
        if t <= 0.0 {
            return from;
        }
        if t >= total || total == 0.0 {
            return to;
        }
        let (v, a) = (self.max_velocity, self.acceleration);
        let peak = (a * d).sqrt().min(v);
        let t_acc = peak / a;
        let covered = if t < t_acc {
            0.5 * a * t * t
        } else if t < total - t_acc {
            0.5 * a * t_acc * t_acc + peak * (t - t_acc)
        } else {
            let tr = total - t;
            d - 0.5 * a * tr * tr
        };
        from + (to - from).signum() * covered
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const AXIS: Trapezoid = Trapezoid {
        max_velocity: 10.0,
        acceleration: 20.0,
        settle_s: 0.5,
    };

    #[test]
    fn short_move_is_triangular() {
        // ramp distance v²/a = 5; a 2-unit move never reaches full speed.
        assert!((AXIS.travel_time(2.0) - 2.0 * (0.1f64).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn long_move_is_trapezoidal_and_continuous_at_the_switch() {
        assert!((AXIS.travel_time(100.0) - (10.0 + 0.5)).abs() < 1e-12);
        let below = AXIS.travel_time(5.0 - 1e-9);
        let above = AXIS.travel_time(5.0 + 1e-9);
        assert!((below - above).abs() < 1e-6);
    }

    #[test]
    fn no_motion_costs_no_settle() {
        assert_eq!(AXIS.move_time(0.0), 0.0);
        assert_eq!(AXIS.move_time(-3.0), AXIS.move_time(3.0));
        assert!(AXIS.move_time(1.0) > AXIS.settle_s);
    }

    #[test]
    fn position_profile_starts_and_ends_right() {
        let total = AXIS.travel_time(30.0);
        assert_eq!(AXIS.position_at(10.0, 40.0, 0.0), 10.0);
        assert_eq!(AXIS.position_at(10.0, 40.0, total), 40.0);
        let mid = AXIS.position_at(10.0, 40.0, total / 2.0);
        assert!((mid - 25.0).abs() < 1e-9, "{mid}");
        let back = AXIS.position_at(40.0, 10.0, total / 2.0);
        assert!((back - 25.0).abs() < 1e-9, "{back}");
    }
}
