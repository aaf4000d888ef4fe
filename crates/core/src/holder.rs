//! The sample holder plate with its registration markers (Sattler et al.,
//! fig. 5): white point markers at the corners and edge midpoints, and
//! white border lines a few millimetres outside the sample, on a dark plate.
//! The simulator draws it; the rectification registers frames by it. On
//! hardware the plate is the standard one ([`HolderSpec::default`]) around
//! a sample of [`STANDARD_SAMPLE_MM`]. A plate may also carry a row of
//! colour reference patches ([`COLOUR_PATCHES`]) below the sample, from
//! which processing measures white balance and colour correction.

use serde::{Deserialize, Serialize};

/// Side of the square sample a hardware run holds, mm (the Bonn rig's
/// 10 × 10 cm samples).
pub const STANDARD_SAMPLE_MM: f64 = 100.0;

/// The plate as a scene file or a rig describes it, millimetres; a key
/// left out keeps the standard plate's value.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
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
    /// Whether the plate carries the colour reference patches
    /// ([`COLOUR_PATCHES`]) in a row below the sample, between the border
    /// line and the point markers.
    pub colour_patches: bool,
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
            colour_patches: false,
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
    /// The colour reference patches, when the plate carries them.
    pub patches: Vec<PlacedPatch>,
}

/// A colour reference patch: a matte square of known reflectance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ColourPatch {
    /// What the patch is called in reports (`white`, `red`, …).
    pub name: &'static str,
    /// Its diffuse reflectance in linear sRGB primaries (D65 white).
    pub rgb: [f64; 3],
}

/// The reference patches a plate with `colour_patches` carries, left to
/// right: the ColorChecker Classic's white, neutral 5, red, green, blue
/// and yellow, as their published sRGB values decode to linear sRGB.
pub const COLOUR_PATCHES: [ColourPatch; 6] = [
    ColourPatch {
        name: "white",
        rgb: [0.896, 0.896, 0.888],
    },
    ColourPatch {
        name: "red",
        rgb: [0.429, 0.037, 0.045],
    },
    ColourPatch {
        name: "green",
        rgb: [0.061, 0.296, 0.067],
    },
    ColourPatch {
        name: "grey",
        rgb: [0.195, 0.195, 0.191],
    },
    ColourPatch {
        name: "blue",
        rgb: [0.040, 0.047, 0.305],
    },
    ColourPatch {
        name: "yellow",
        rgb: [0.799, 0.571, 0.014],
    },
];

/// A reference patch where it lies on the plate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PlacedPatch {
    /// The patch and its reflectance.
    pub patch: ColourPatch,
    /// Its centre, metres from the sample centre.
    pub centre: [f64; 2],
    /// Half its side, metres.
    pub half: f64,
}

impl PlacedPatch {
    /// Whether (x, y) lies on the patch.
    pub fn contains(&self, x: f64, y: f64) -> bool {
        (x - self.centre[0]).abs() <= self.half && (y - self.centre[1]).abs() <= self.half
    }
}

/// Luminance Y of linear sRGB (Rec. 709 weights): the reflectance a
/// monochrome sensor with a photopic response sees.
pub fn luminance(rgb: [f64; 3]) -> f64 {
    0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
}

/// Clearance of the patches from the border line and the point markers
/// each side, metres.
const PATCH_MARGIN_M: f64 = 2.5e-3;

/// Distance between neighbouring patches' centres, as a multiple of their
/// side.
const PATCH_PITCH: f64 = 15.0 / 7.0;

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
        let line_offset = [sample_half[0] + gap, sample_half[1] + gap];
        let line_half_width = spec.border_line_mm * mm / 2.0;
        let point_radius = spec.point_marker_mm * mm / 2.0;
        let patches = if spec.colour_patches {
            // A row below the sample, centred between the border line's
            // outer edge and the point markers' inner edge.
            let (inner, outer) = (line_offset[1] + line_half_width, c - point_radius);
            let side = (outer - inner - 2.0 * PATCH_MARGIN_M).max(0.0);
            let pitch = PATCH_PITCH * side;
            let first = -pitch * (COLOUR_PATCHES.len() as f64 - 1.0) / 2.0;
            COLOUR_PATCHES
                .iter()
                .enumerate()
                .map(|(k, &patch)| PlacedPatch {
                    patch,
                    centre: [first + k as f64 * pitch, -(inner + outer) / 2.0],
                    half: side / 2.0,
                })
                .collect()
        } else {
            Vec::new()
        };
        Holder {
            half,
            colour: spec.colour,
            marker_colour: spec.marker_colour,
            point_radius,
            line_half_width,
            line_offset,
            points,
            patches,
        }
    }

    /// Whether the patches of `spec` fit between its border line and point
    /// markers, at least `min_side_mm` wide and within the border's length;
    /// the message says what is too small.
    pub fn check_patches(&self, min_side_mm: f64) -> Result<(), String> {
        let Some(last) = self.patches.last() else {
            return Ok(());
        };
        if 2.0 * last.half < min_side_mm * 1e-3 {
            return Err(format!(
                "the colour patches would be {:.1} mm wide between the border line and the \
                 point markers; at least {min_side_mm} mm is needed",
                2e3 * last.half
            ));
        }
        if last.centre[0] + last.half > self.line_offset[0] - self.line_half_width {
            return Err("the row of colour patches is longer than the border line".into());
        }
        Ok(())
    }

    /// Reflectance of the plate at (x, y) in linear sRGB: a patch's, else
    /// the neutral plate's or marker's; 0 off the plate.
    pub fn reflectance(&self, x: f64, y: f64) -> [f64; 3] {
        match self.patch_at(x, y) {
            Some(p) => p.patch.rgb,
            None => [self.albedo(x, y); 3],
        }
    }

    /// The colour patch at (x, y), if one is there.
    pub fn patch_at(&self, x: f64, y: f64) -> Option<&PlacedPatch> {
        self.patches.iter().find(|p| p.contains(x, y))
    }

    /// Reflectance of the plate at (x, y) as a monochrome sensor sees it
    /// (a patch's luminance); 0 off the plate.
    pub fn albedo(&self, x: f64, y: f64) -> f64 {
        let (ax, ay) = (x.abs(), y.abs());
        if ax > self.half || ay > self.half {
            return 0.0;
        }
        if let Some(p) = self.patch_at(x, y) {
            return luminance(p.patch.rgb);
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

#[cfg(test)]
mod tests {
    use super::*;

    fn patched() -> Holder {
        let spec = HolderSpec {
            colour_patches: true,
            ..HolderSpec::default()
        };
        Holder::new(&spec, [0.05, 0.05])
    }

    #[test]
    fn the_standard_plate_carries_no_patches() {
        assert!(Holder::standard().patches.is_empty());
        assert_eq!(Holder::standard().reflectance(0.0, -0.0625), [0.06; 3]);
    }

    #[test]
    fn patches_sit_between_the_border_line_and_the_point_markers_clear_of_both() {
        let h = patched();
        assert_eq!(h.patches.len(), COLOUR_PATCHES.len());
        h.check_patches(5.0).expect("the standard plate has room");
        for p in &h.patches {
            let (x, y) = (p.centre[0], p.centre[1]);
            assert!((2e3 * p.half - 7.0).abs() < 1e-9, "{p:?}");
            assert_eq!(h.reflectance(x, y), p.patch.rgb);
            assert!((h.albedo(x, y) - luminance(p.patch.rgb)).abs() < 1e-12);
            // Its edges touch neither a marker nor the border line.
            for (dx, dy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                let margin = p.half + 1e-3;
                let (ex, ey) = (x + dx * margin, y + dy * margin);
                assert_eq!(h.albedo(ex, ey), h.colour, "beside {}", p.patch.name);
            }
        }
        // Neighbours do not touch.
        for w in h.patches.windows(2) {
            assert!(w[1].centre[0] - w[0].centre[0] > 2.0 * w[0].half + 5e-3);
        }
    }

    #[test]
    fn a_plate_without_room_for_patches_says_so() {
        let spec = HolderSpec {
            colour_patches: true,
            size_mm: 130.0,
            ..HolderSpec::default()
        };
        let e = Holder::new(&spec, [0.05, 0.05]).check_patches(5.0);
        assert!(e.is_err_and(|m| m.contains("mm wide")));
    }

    #[test]
    fn white_has_unit_luminance_weights() {
        assert!((luminance([1.0; 3]) - 1.0).abs() < 1e-12);
    }
}
