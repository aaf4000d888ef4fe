//! Layout.

use super::*;

/// Where the markers are on the plate.
#[derive(Debug, Clone, PartialEq)]
pub struct MarkerLayout {
    /// Marker centres, plate metres. Detections and residuals are indexed
    /// like this list.
    pub points: Vec<[f64; 2]>,
    /// Radius of a point marker, metres.
    pub radius_m: f64,
    /// Half the sample's size, metres, per axis.
    pub sample_half: [f64; 2],
}

impl MarkerLayout {
    /// The simulator's default holder: a 160 mm plate with 6 mm discs at
    /// `±71 mm` (corners and edge midpoints, in the order
    /// `(sx, sy)` for `sx` in −1, 0, 1 and `sy` in −1, 0, 1 without the
    /// centre) and a 100 × 100 mm sample.
    pub fn default_holder() -> MarkerLayout {
        MarkerLayout::square(0.160, 0.006, [0.05, 0.05])
    }

    /// A plate of side `plate_m` with discs of diameter `marker_m` at the
    /// corners and edge midpoints of the square at `±(plate/2 − 1.5 marker)`
    /// (the simulator's layout).
    pub fn square(plate_m: f64, marker_m: f64, sample_half: [f64; 2]) -> MarkerLayout {
        let c = plate_m / 2.0 - 1.5 * marker_m;
        let mut points = Vec::with_capacity(8);
        for sx in [-1.0, 0.0, 1.0] {
            for sy in [-1.0, 0.0, 1.0] {
                if sx != 0.0 || sy != 0.0 {
                    points.push([sx * c, sy * c]);
                }
            }
        }
        MarkerLayout {
            points,
            radius_m: marker_m / 2.0,
            sample_half,
        }
    }

    /// This layout with the border lines' corners (see
    /// [`BorderLines::corners`]) appended as markers 8..12, to register
    /// with point and border markers together.
    pub fn with_border_corners(&self, border: &BorderLines) -> MarkerLayout {
        let mut out = self.clone();
        out.points.extend(border.corners());
        out
    }

    /// The sample square, `±sample_half`.
    pub fn sample_region(&self) -> Region {
        Region::centred(self.sample_half)
    }
}

/// An axis-aligned rectangle on the plate, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Region {
    /// Left edge (smallest x), metres.
    pub x_min: f64,
    /// Right edge (largest x), metres.
    pub x_max: f64,
    /// Bottom edge (smallest y; `+y` is up), metres.
    pub y_min: f64,
    /// Top edge (largest y), metres.
    pub y_max: f64,
}

impl Region {
    /// `[−half_x, half_x] × [−half_y, half_y]`.
    pub fn centred(half: [f64; 2]) -> Region {
        Region {
            x_min: -half[0],
            x_max: half[0],
            y_min: -half[1],
            y_max: half[1],
        }
    }

    pub(super) fn is_valid(&self) -> bool {
        [self.x_min, self.x_max, self.y_min, self.y_max]
            .iter()
            .all(|v| v.is_finite())
            && self.x_max > self.x_min
            && self.y_max > self.y_min
    }
}

/// Projects a plate point through `h`; `None` if it maps to or behind the
/// camera's horizon (`w ≤ 0`) or is not finite.
pub fn project(h: &Homography, p: [f64; 2]) -> Option<[f64; 2]> {
    let w = h[2][0] * p[0] + h[2][1] * p[1] + h[2][2];
    if !above(w, 0.0) {
        return None;
    }
    let u = (h[0][0] * p[0] + h[0][1] * p[1] + h[0][2]) / w;
    let v = (h[1][0] * p[0] + h[1][1] * p[1] + h[1][2]) / w;
    (u.is_finite() && v.is_finite()).then_some([u, v])
}

/// Predicted marker positions from a predicted homography (e.g. from the
/// commanded pose): `None` where a marker maps behind the camera.
pub fn predict_markers(h: &Homography, layout: &MarkerLayout) -> Vec<Option<[f64; 2]>> {
    layout.points.iter().map(|&p| project(h, p)).collect()
}
