//! The sample holder plate with its registration markers (Sattler et al.,
//! fig. 5): white point markers at the corners and edge midpoints, and
//! white border lines a few millimetres outside the sample, on a dark plate.
//! The simulator draws it; the rectification registers frames by it. On
//! hardware the plate is the standard one ([`HolderSpec::default`]) around
//! a sample of [`STANDARD_SAMPLE_MM`].

use serde::{Deserialize, Serialize};

/// Side of the square sample a hardware run holds, mm (the Bonn rig's
/// 10 × 10 cm samples).
pub const STANDARD_SAMPLE_MM: f64 = 100.0;

/// The plate as a scene file or a rig describes it, millimetres.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HolderSpec {
    /// Side of the square holder plate, mm.
    pub size_mm: f64,
    /// Reflectance of the plate.
    pub colour: f64,
    /// Reflectance of the markers.
    pub marker_colour: f64,
    /// Diameter of the point markers, mm.
    pub point_marker_mm: f64,
    /// Width of the border lines, mm.
    pub border_line_mm: f64,
    /// How far outside the sample the border lines run, mm.
    pub border_gap_mm: f64,
}

impl Default for HolderSpec {
    fn default() -> Self {
        HolderSpec {
            size_mm: 160.0,
            colour: 0.06,
            marker_colour: 0.95,
            point_marker_mm: 6.0,
            border_line_mm: 2.0,
            border_gap_mm: 5.0,
        }
    }
}

/// The plate in metres.
#[derive(Debug, Clone)]
pub struct Holder {
    /// Half the plate's side.
    pub half: f64,
    /// Reflectance of the plate.
    pub colour: f64,
    /// Reflectance of the markers.
    pub marker_colour: f64,
    /// Radius of a point marker.
    pub point_radius: f64,
    /// Half the width of a border line.
    pub line_half_width: f64,
    /// Distance of the border lines' centre from the sample centre, per axis.
    pub line_offset: [f64; 2],
    points: Vec<[f64; 2]>,
}

/// A registration marker in the sample frame (z = 0), metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Marker {
    /// `point` markers are discs; `corner` marks where two border lines meet.
    pub kind: &'static str,
    /// Where, metres from the sample centre.
    pub position: [f64; 2],
}

impl Holder {
    /// The plate of `spec` around a sample of half-sides `sample_half`
    /// (metres).
    pub fn new(spec: &HolderSpec, sample_half: [f64; 2]) -> Holder {
        let mm = 1e-3;
        let half = spec.size_mm * mm / 2.0;
        let c = half - 1.5 * spec.point_marker_mm * mm;
        let mut points = Vec::new();
        for sx in [-1.0, 0.0, 1.0] {
            for sy in [-1.0, 0.0, 1.0] {
                if sx != 0.0 || sy != 0.0 {
                    points.push([sx * c, sy * c]);
                }
            }
        }
        let gap = spec.border_gap_mm * mm;
        Holder {
            half,
            colour: spec.colour,
            marker_colour: spec.marker_colour,
            point_radius: spec.point_marker_mm * mm / 2.0,
            line_half_width: spec.border_line_mm * mm / 2.0,
            line_offset: [sample_half[0] + gap, sample_half[1] + gap],
            points,
        }
    }

    /// Reflectance of the plate at (x, y); 0 off the plate.
    pub fn albedo(&self, x: f64, y: f64) -> f64 {
        let (ax, ay) = (x.abs(), y.abs());
        if ax > self.half || ay > self.half {
            return 0.0;
        }
        let [ox, oy] = self.line_offset;
        let w = self.line_half_width;
        let on_x_line = (ax - ox).abs() <= w && ay <= oy + w;
        let on_y_line = (ay - oy).abs() <= w && ax <= ox + w;
        if on_x_line || on_y_line {
            return self.marker_colour;
        }
        let r2 = self.point_radius * self.point_radius;
        if self
            .points
            .iter()
            .any(|p| (x - p[0]).powi(2) + (y - p[1]).powi(2) <= r2)
        {
            return self.marker_colour;
        }
        self.colour
    }

    /// The standard plate around the standard sample: what a hardware
    /// run's frames show.
    pub fn standard() -> Holder {
        let half = STANDARD_SAMPLE_MM * 1e-3 / 2.0;
        Holder::new(&HolderSpec::default(), [half, half])
    }

    /// Every marker: the point markers' centres and the border's corners.
    pub fn markers(&self) -> Vec<Marker> {
        let [ox, oy] = self.line_offset;
        let mut m: Vec<Marker> = self
            .points
            .iter()
            .map(|&p| Marker {
                kind: "point",
                position: p,
            })
            .collect();
        for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            m.push(Marker {
                kind: "corner",
                position: [sx * ox, sy * oy],
            });
        }
        m
    }
}
