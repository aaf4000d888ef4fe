//! Laser plane.

use super::*;

/// A laser plane `normal · x = offset` (`normal` unit; its sign is
/// arbitrary).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LaserPlane {
    /// Unit plane normal, world frame; its sign is arbitrary.
    pub normal: [f64; 3],
    /// `normal · x` for every point `x` of the plane, metres: the plane's
    /// signed distance from the origin along `normal`.
    pub offset: f64,
}

impl LaserPlane {
    /// The plane through `point` with normal `normal` (any length), e.g.
    /// the simulator's `LaserLine { emitter, normal }`.
    pub fn through(point: [f64; 3], normal: [f64; 3]) -> Result<LaserPlane, MdfError> {
        let n = unit(normal)
            .filter(|_| finite3(point))
            .ok_or_else(|| MdfError::InvalidPlane {
                index: 0,
                reason: format!("normal {normal:?} through {point:?}"),
            })?;
        Ok(LaserPlane {
            normal: n,
            offset: dot(n, point),
        })
    }

    /// Signed distance of `p` from the plane.
    pub fn distance(&self, p: [f64; 3]) -> f64 {
        dot(self.normal, p) - self.offset
    }

    /// Ray parameter `t` (so the point is `origin + t·dir`) where the ray
    /// meets the plane, with `|n·dir|/|dir|` (the sine of the angle between
    /// ray and plane). `None` when the ray is parallel to the plane or the
    /// values are not finite; `t` may be negative.
    pub fn intersect(&self, origin: [f64; 3], dir: [f64; 3]) -> Option<(f64, f64)> {
        let len = norm(dir);
        let nd = dot(self.normal, dir);
        if !gt(len, 0.0) || !gt(nd.abs(), 1e-15 * len) {
            return None;
        }
        let t = (self.offset - dot(self.normal, origin)) / nd;
        t.is_finite().then_some((t, (nd / len).abs()))
    }

    pub(super) fn normalised(self, index: usize) -> Result<LaserPlane, MdfError> {
        let n = norm(self.normal);
        if !(finite3(self.normal) && self.offset.is_finite() && n > 1e-12) {
            return Err(MdfError::InvalidPlane {
                index,
                reason: format!("normal {:?}, offset {}", self.normal, self.offset),
            });
        }
        Ok(LaserPlane {
            normal: scale(self.normal, 1.0 / n),
            offset: self.offset / n,
        })
    }
}
