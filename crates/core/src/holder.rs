//! The sample holder plate with its registration markers (Sattler et al.,
//! "Efficient and Realistic Visualization of Cloth", fig. 5): point markers
//! and border lines a few millimetres outside the sample window, on a plate
//! of one reflectance. Every lab builds its own, so the plate is part of
//! the rig's profile (`[holder]`, [`HolderSpec`]) and of each run's record:
//! the simulator draws it, and processing registers frames by it. A plate
//! may also carry colour references: a row of the standard reference
//! patches ([`COLOUR_PATCHES`]), a chart known by name
//! ([`crate::chart::CHARTS`]), patches of its own with their L\*a\*b\*, and
//! white areas that measure the lamp's level in every frame.

use serde::{Deserialize, Serialize};

use crate::chart;

/// Side of the square sample the standard plate holds, mm (the Bonn rig's
/// 10 × 10 cm samples).
pub const STANDARD_SAMPLE_MM: f64 = 100.0;

/// Fewest point markers a plate may have: registration fits a homography
/// to 4, and tells a misdetected one apart only from 6 on, which frames
/// at grazing angles (a marker hidden or lost) need.
pub const MIN_POINT_MARKERS: usize = 6;

/// Least clearance between a marker and anything else on the plate, mm:
/// a detector's search window must not take in a neighbour's edge.
const CLEARANCE_MM: f64 = 1.0;

/// Least difference in reflectance between a marker and the plate.
const MIN_CONTRAST: f64 = 0.2;

/// The narrowest colour patch or white area a plate may carry, mm: a few
/// pixels across at the rigs' resolutions, after demosaicing.
pub const MIN_PATCH_MM: f64 = 5.0;

/// Largest plate, mm.
const MAX_PLATE_MM: f64 = 1000.0;

/// The plate as a profile's `[holder]` table describes it, millimetres
/// from the sample centre (+x right, +y up in the frontal view); a key
/// left out keeps the standard plate's value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HolderSpec {
    /// The plate's name, printed on its template.
    pub name: String,
    /// Side of the square plate, mm.
    pub size_mm: f64,
    /// Width and height of the sample window, centred on the plate, mm.
    pub sample_mm: [f64; 2],
    /// Reflectance of the plate.
    pub colour: f64,
    /// Reflectance of light point markers and of the border lines.
    pub marker_colour: f64,
    /// Reflectance of dark point markers.
    pub dark_marker_colour: f64,
    /// Diameter of a point marker that gives none, mm.
    pub point_marker_mm: f64,
    /// Width of the border lines, mm; 0: the plate has none.
    pub border_line_mm: f64,
    /// How far outside the sample window the border lines run, mm.
    pub border_gap_mm: f64,
    /// The point markers, in the order registration reports them. Empty:
    /// the standard eight, at the corners and edge midpoints of the
    /// square at ±(size/2 − 1.5 diameters).
    pub markers: Vec<MarkerSpec>,
    /// Whether the plate carries the standard reference patches
    /// ([`COLOUR_PATCHES`]) in a row below the sample, between the border
    /// line and the point markers.
    pub colour_patches: bool,
    /// A colour chart known by name, placed on the plate.
    pub chart: Option<ChartSpec>,
    /// Colour patches of the lab's own, with their reference values.
    pub patches: Vec<PatchSpec>,
    /// White reference areas, which measure the lamp's level per frame.
    pub white: Vec<AreaSpec>,
}

impl Default for HolderSpec {
    fn default() -> Self {
        HolderSpec {
            name: "standard".into(),
            size_mm: 160.0,
            sample_mm: [STANDARD_SAMPLE_MM; 2],
            colour: 0.06,
            marker_colour: 0.95,
            dark_marker_colour: 0.02,
            point_marker_mm: 6.0,
            border_line_mm: 2.0,
            border_gap_mm: 5.0,
            markers: Vec::new(),
            colour_patches: false,
            chart: None,
            patches: Vec::new(),
            white: Vec::new(),
        }
    }
}

/// A point marker: a disc lighter or darker than the plate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MarkerSpec {
    /// Centre, mm from the sample centre.
    pub at_mm: [f64; 2],
    /// Diameter, mm; the plate's `point_marker_mm` if left out.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub diameter_mm: Option<f64>,
    /// `light` (a disc of `marker_colour`, the default) or `dark` (of
    /// `dark_marker_colour`).
    #[serde(default)]
    pub polarity: Polarity,
}

/// Whether a marker is lighter or darker than the plate around it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Polarity {
    /// Lighter than the plate.
    #[default]
    Light,
    /// Darker than the plate.
    Dark,
}

/// A chart known by name, where its patch grid lies.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChartSpec {
    /// The chart's name (`colorchecker24`).
    pub name: String,
    /// Centre of the patch grid, mm from the sample centre.
    pub centre_mm: [f64; 2],
    /// Side of one square patch, mm.
    pub patch_mm: f64,
    /// Distance between neighbouring patches' centres, mm.
    pub pitch_mm: f64,
}

/// A colour patch of the lab's own.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PatchSpec {
    /// What reports call it.
    pub name: String,
    /// Centre, mm from the sample centre.
    pub centre_mm: [f64; 2],
    /// Side of the square patch, mm.
    pub size_mm: f64,
    /// Its reference value, CIE L\*a\*b\* (D50), as measured by a
    /// spectrophotometer or published by its maker.
    pub lab: Option<[f64; 3]>,
}

/// A white reference area.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AreaSpec {
    /// Centre, mm from the sample centre.
    pub centre_mm: [f64; 2],
    /// Width and height, mm.
    pub size_mm: [f64; 2],
    /// Its diffuse reflectance.
    #[serde(default = "white_reflectance")]
    pub reflectance: f64,
}

fn white_reflectance() -> f64 {
    0.9
}

/// A holder description that cannot work: the key (`holder.markers[2]`)
/// and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{key}: {message}")]
pub struct HolderError {
    /// The offending key, from `holder`.
    pub key: String,
    /// What is wrong, and what would do.
    pub message: String,
}

fn bad(key: impl Into<String>, message: impl Into<String>) -> HolderError {
    HolderError {
        key: key.into(),
        message: message.into(),
    }
}

/// The plate in metres, ready to draw and to register by.
#[derive(Debug, Clone)]
pub struct Holder {
    /// The plate's name.
    pub name: String,
    /// Half the plate's side.
    pub half: f64,
    /// Half the sample window's sides.
    pub sample_half: [f64; 2],
    /// Reflectance of the plate.
    pub colour: f64,
    /// Reflectance of light markers and the border lines.
    pub marker_colour: f64,
    /// Reflectance of dark markers.
    pub dark_marker_colour: f64,
    /// Radius of a point marker that gives none.
    pub point_radius: f64,
    /// Half the width of a border line; 0 when the plate has none.
    pub line_half_width: f64,
    /// Distance of the border lines' centre from the sample centre, per axis.
    pub line_offset: [f64; 2],
    /// The point markers, in registration's order.
    pub points: Vec<PointMarker>,
    /// The colour reference patches: the standard row, the chart's, the
    /// lab's own, in that order.
    pub patches: Vec<PlacedPatch>,
    /// The white reference areas.
    pub whites: Vec<WhiteArea>,
}

/// A point marker where it lies, metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PointMarker {
    /// Centre, metres from the sample centre.
    pub position: [f64; 2],
    /// Radius, metres.
    pub radius: f64,
    /// Lighter or darker than the plate.
    pub polarity: Polarity,
}

/// A standard reference patch: a matte square of known reflectance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ColourPatch {
    /// What the patch is called in reports (`white`, `red`, …).
    pub name: &'static str,
    /// Its diffuse reflectance in linear sRGB primaries (D65 white).
    pub rgb: [f64; 3],
}

/// The reference patches a plate with `colour_patches` carries, left to
/// right: the ColorChecker Classic's white, red, green, neutral 5, blue
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
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlacedPatch {
    /// What reports call it: the chart maker's name for a chart's patch.
    pub name: String,
    /// Its diffuse reflectance in linear sRGB (D65 white), clamped to
    /// [0, 1] where the reference lies outside the sRGB gamut.
    pub rgb: [f64; 3],
    /// Its reference value, CIE L\*a\*b\* (D50).
    pub lab_d50: [f64; 3],
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

/// A white reference area where it lies on the plate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct WhiteArea {
    /// Its centre, metres from the sample centre.
    pub centre: [f64; 2],
    /// Half its sides, metres.
    pub half: [f64; 2],
    /// Its diffuse reflectance.
    pub reflectance: f64,
}

impl WhiteArea {
    /// Whether (x, y) lies on the area.
    pub fn contains(&self, x: f64, y: f64) -> bool {
        (x - self.centre[0]).abs() <= self.half[0] && (y - self.centre[1]).abs() <= self.half[1]
    }
}

/// Luminance Y of linear sRGB (Rec. 709 weights): the reflectance a
/// monochrome sensor with a photopic response sees.
pub fn luminance(rgb: [f64; 3]) -> f64 {
    0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
}

/// Clearance of the standard patches from the border line and the point
/// markers each side, metres.
const PATCH_MARGIN_M: f64 = 2.5e-3;

/// Distance between neighbouring standard patches' centres, as a multiple
/// of their side.
const PATCH_PITCH: f64 = 15.0 / 7.0;

/// A registration marker in the sample frame (z = 0), metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Marker {
    /// `point` markers are discs; `corner` marks where two border lines meet.
    pub kind: &'static str,
    /// Where, metres from the sample centre.
    pub position: [f64; 2],
}

/// An axis-aligned rectangle, metres: what is checked for overlaps.
#[derive(Debug, Clone, Copy)]
struct Rect {
    lo: [f64; 2],
    hi: [f64; 2],
}

impl Rect {
    fn around(centre: [f64; 2], half: [f64; 2]) -> Rect {
        Rect {
            lo: [centre[0] - half[0], centre[1] - half[1]],
            hi: [centre[0] + half[0], centre[1] + half[1]],
        }
    }

    fn overlaps(&self, o: &Rect, gap: f64) -> bool {
        self.lo[0] < o.hi[0] + gap
            && o.lo[0] < self.hi[0] + gap
            && self.lo[1] < o.hi[1] + gap
            && o.lo[1] < self.hi[1] + gap
    }

    /// Distance from (x, y) to the rectangle (0 inside).
    fn distance(&self, p: [f64; 2]) -> f64 {
        let dx = (self.lo[0] - p[0]).max(p[0] - self.hi[0]).max(0.0);
        let dy = (self.lo[1] - p[1]).max(p[1] - self.hi[1]).max(0.0);
        dx.hypot(dy)
    }

    fn within(&self, half: f64) -> bool {
        self.lo[0] >= -half && self.lo[1] >= -half && self.hi[0] <= half && self.hi[1] <= half
    }
}

impl HolderSpec {
    /// The plate this describes, checked ([`HolderSpec::check`]).
    pub fn holder(&self) -> Result<Holder, HolderError> {
        self.check()?;
        Ok(Holder::new(self))
    }

    /// Refuses a plate that cannot work, naming the key under `holder`:
    /// sizes and reflectances out of range, a marker off the plate or
    /// overlapping another, the sample window, its border or a patch;
    /// fewer than [`MIN_POINT_MARKERS`] markers; markers that do not stand
    /// out from the plate; a patch without reference values; a chart rigd
    /// does not know.
    pub fn check(&self) -> Result<(), HolderError> {
        let finite = |key: &str, v: f64, lo: f64, hi: f64| {
            if v.is_finite() && v > lo && v <= hi {
                Ok(())
            } else {
                Err(bad(
                    format!("holder.{key}"),
                    format!("expected a number above {lo} and at most {hi}, got {v}"),
                ))
            }
        };
        let unit = |key: &str, v: f64| {
            if (0.0..=1.0).contains(&v) {
                Ok(())
            } else {
                Err(bad(
                    format!("holder.{key}"),
                    format!("expected a reflectance from 0 to 1, got {v}"),
                ))
            }
        };
        finite("size_mm", self.size_mm, 0.0, MAX_PLATE_MM)?;
        finite("sample_mm[0]", self.sample_mm[0], 0.0, MAX_PLATE_MM)?;
        finite("sample_mm[1]", self.sample_mm[1], 0.0, MAX_PLATE_MM)?;
        finite("point_marker_mm", self.point_marker_mm, 0.0, 100.0)?;
        if !(self.border_line_mm.is_finite() && (0.0..=50.0).contains(&self.border_line_mm)) {
            return Err(bad(
                "holder.border_line_mm",
                format!(
                    "expected a width from 0 (no border lines) to 50 mm, got {}",
                    self.border_line_mm
                ),
            ));
        }
        if !(self.border_gap_mm.is_finite() && (0.0..=100.0).contains(&self.border_gap_mm)) {
            return Err(bad(
                "holder.border_gap_mm",
                format!("expected 0 to 100 mm, got {}", self.border_gap_mm),
            ));
        }
        unit("colour", self.colour)?;
        unit("marker_colour", self.marker_colour)?;
        unit("dark_marker_colour", self.dark_marker_colour)?;
        let h = Holder::new(self);
        let mm = 1e-3;
        let gap = CLEARANCE_MM * mm;
        // The window and its border lines, which nothing else may touch.
        let reach = if h.line_half_width > 0.0 {
            [
                h.line_offset[0] + h.line_half_width,
                h.line_offset[1] + h.line_half_width,
            ]
        } else {
            h.sample_half
        };
        let window = Rect::around([0.0, 0.0], reach);
        if !window.within(h.half) {
            return Err(bad(
                "holder.sample_mm",
                format!(
                    "the sample window and its border lines ({:.1} × {:.1} mm) do not fit on the \
                     {:.1} mm plate",
                    2e3 * reach[0],
                    2e3 * reach[1],
                    self.size_mm
                ),
            ));
        }
        let marker_key = |i: usize| {
            if self.markers.is_empty() {
                "holder.point_marker_mm".to_string()
            } else {
                format!("holder.markers[{i}]")
            }
        };
        if h.points.len() < MIN_POINT_MARKERS {
            return Err(bad(
                "holder.markers",
                format!(
                    "{} point markers; registration needs at least {MIN_POINT_MARKERS} (4 to fit \
                     the plate's homography, 6 to tell a misdetected one apart)",
                    h.points.len()
                ),
            ));
        }
        // Reference areas: the standard row, the chart, the lab's patches
        // and the white areas, each with the key it came from.
        let mut areas: Vec<(String, Rect)> = Vec::new();
        if let Some(c) = &self.chart {
            chart::chart(&c.name).ok_or_else(|| {
                bad(
                    "holder.chart.name",
                    format!(
                        "unknown chart '{}'; rigd knows {}",
                        c.name,
                        chart::CHARTS.map(|c| c.name).join(", ")
                    ),
                )
            })?;
            finite("chart.patch_mm", c.patch_mm, 0.0, 200.0)?;
            if c.patch_mm < MIN_PATCH_MM {
                return Err(bad(
                    "holder.chart.patch_mm",
                    format!(
                        "patches need at least {MIN_PATCH_MM} mm, got {}",
                        c.patch_mm
                    ),
                ));
            }
            if !(c.pitch_mm.is_finite() && c.pitch_mm >= c.patch_mm && c.pitch_mm <= 400.0) {
                return Err(bad(
                    "holder.chart.pitch_mm",
                    format!(
                        "expected at least the patch side ({} mm), got {}",
                        c.patch_mm, c.pitch_mm
                    ),
                ));
            }
        }
        for (i, p) in self.patches.iter().enumerate() {
            if p.name.trim().is_empty() {
                return Err(bad(
                    format!("holder.patches[{i}].name"),
                    "a patch needs a name",
                ));
            }
            if !(p.size_mm.is_finite() && p.size_mm >= MIN_PATCH_MM && p.size_mm <= 200.0) {
                return Err(bad(
                    format!("holder.patches[{i}].size_mm"),
                    format!("expected {MIN_PATCH_MM} to 200 mm, got {}", p.size_mm),
                ));
            }
            match p.lab {
                None => {
                    return Err(bad(
                        format!("holder.patches[{i}].lab"),
                        format!(
                            "patch '{}' has no reference value: give its CIE L*a*b* (D50), \
                             e.g. lab = [95.19, -1.03, 2.93]",
                            p.name
                        ),
                    ))
                }
                Some(lab) if !valid_lab(lab) => {
                    return Err(bad(
                        format!("holder.patches[{i}].lab"),
                        format!("expected L* from 0 to 100 and a*, b* within ±200, got {lab:?}"),
                    ))
                }
                Some(_) => {}
            }
        }
        for (i, w) in self.white.iter().enumerate() {
            for k in 0..2 {
                if !(w.size_mm[k].is_finite() && w.size_mm[k] >= MIN_PATCH_MM) {
                    return Err(bad(
                        format!("holder.white[{i}].size_mm"),
                        format!("expected at least {MIN_PATCH_MM} mm, got {:?}", w.size_mm),
                    ));
                }
            }
            unit(&format!("white[{i}].reflectance"), w.reflectance)?;
        }
        let mut patch_keys: Vec<String> = Vec::new();
        if self.colour_patches {
            h.check_patches(MIN_PATCH_MM)
                .map_err(|m| bad("holder.colour_patches", m))?;
            patch_keys.extend(
                COLOUR_PATCHES
                    .iter()
                    .map(|_| "holder.colour_patches".into()),
            );
        }
        if let Some(c) = &self.chart {
            let n = chart::chart(&c.name).map_or(0, |c| c.patches.len());
            patch_keys.extend((0..n).map(|_| "holder.chart".to_string()));
        }
        patch_keys.extend((0..self.patches.len()).map(|i| format!("holder.patches[{i}]")));
        for (p, key) in h.patches.iter().zip(&patch_keys) {
            areas.push((key.clone(), Rect::around(p.centre, [p.half; 2])));
        }
        for (i, w) in h.whites.iter().enumerate() {
            areas.push((format!("holder.white[{i}]"), Rect::around(w.centre, w.half)));
        }
        for (key, r) in &areas {
            if !r.within(h.half) {
                return Err(bad(key.clone(), "lies partly off the plate"));
            }
            if r.overlaps(&window, gap) {
                return Err(bad(
                    key.clone(),
                    "overlaps the sample window or its border lines",
                ));
            }
        }
        for (a, (key_a, ra)) in areas.iter().enumerate() {
            for (key_b, rb) in &areas[a + 1..] {
                // The chart's own patches sit side by side by design.
                if key_a == key_b && key_a == "holder.chart" {
                    continue;
                }
                if ra.overlaps(rb, 0.0) {
                    return Err(bad(key_b.clone(), format!("overlaps {key_a}")));
                }
            }
        }
        for (i, m) in h.points.iter().enumerate() {
            let key = marker_key(i);
            if !(m.radius.is_finite() && m.radius > 0.0) {
                return Err(bad(key, "a marker needs a diameter above 0"));
            }
            let [x, y] = m.position;
            if !(x.is_finite() && y.is_finite())
                || x.abs() + m.radius > h.half
                || y.abs() + m.radius > h.half
            {
                return Err(bad(
                    key,
                    format!(
                        "the marker at ({:.1}, {:.1}) mm, {:.1} mm across, lies off the \
                         {:.1} mm plate",
                        x * 1e3,
                        y * 1e3,
                        2e3 * m.radius,
                        self.size_mm
                    ),
                ));
            }
            if window.distance(m.position) < m.radius + gap {
                return Err(bad(
                    key,
                    format!(
                        "the marker at ({:.1}, {:.1}) mm overlaps the sample window or its \
                         border lines (keep {CLEARANCE_MM} mm clear)",
                        x * 1e3,
                        y * 1e3
                    ),
                ));
            }
            for (j, o) in h.points[..i].iter().enumerate() {
                let d = (x - o.position[0]).hypot(y - o.position[1]);
                if d < m.radius + o.radius + gap {
                    return Err(bad(
                        key,
                        format!(
                            "overlaps marker {j} at ({:.1}, {:.1}) mm (keep {CLEARANCE_MM} mm clear)",
                            o.position[0] * 1e3,
                            o.position[1] * 1e3
                        ),
                    ));
                }
            }
            for (area_key, r) in &areas {
                if r.distance(m.position) < m.radius + gap {
                    return Err(bad(key, format!("overlaps {area_key}")));
                }
            }
            let contrast = match m.polarity {
                Polarity::Light => self.marker_colour - self.colour,
                Polarity::Dark => self.colour - self.dark_marker_colour,
            };
            if contrast < MIN_CONTRAST {
                let (what, colour_key) = match m.polarity {
                    Polarity::Light => ("a light marker", "marker_colour"),
                    Polarity::Dark => ("a dark marker", "dark_marker_colour"),
                };
                return Err(bad(
                    key,
                    format!(
                        "{what} on a plate of reflectance {} stands out by {contrast:.2}; \
                         registration needs {MIN_CONTRAST} (see holder.colour and \
                         holder.{colour_key})",
                        self.colour
                    ),
                ));
            }
        }
        Ok(())
    }
}

fn valid_lab(lab: [f64; 3]) -> bool {
    lab.iter().all(|v| v.is_finite())
        && (0.0..=100.0).contains(&lab[0])
        && lab[1].abs() <= 200.0
        && lab[2].abs() <= 200.0
}

impl Holder {
    /// The plate of `spec`, unchecked: see [`HolderSpec::holder`].
    pub fn new(spec: &HolderSpec) -> Holder {
        let mm = 1e-3;
        let half = spec.size_mm * mm / 2.0;
        let sample_half = [spec.sample_mm[0] * mm / 2.0, spec.sample_mm[1] * mm / 2.0];
        let point_radius = spec.point_marker_mm * mm / 2.0;
        let c = half - 1.5 * spec.point_marker_mm * mm;
        let points: Vec<PointMarker> = if spec.markers.is_empty() {
            let mut points = Vec::new();
            for sx in [-1.0, 0.0, 1.0] {
                for sy in [-1.0, 0.0, 1.0] {
                    if sx != 0.0 || sy != 0.0 {
                        points.push(PointMarker {
                            position: [sx * c, sy * c],
                            radius: point_radius,
                            polarity: Polarity::Light,
                        });
                    }
                }
            }
            points
        } else {
            spec.markers
                .iter()
                .map(|m| PointMarker {
                    position: [m.at_mm[0] * mm, m.at_mm[1] * mm],
                    radius: m.diameter_mm.unwrap_or(spec.point_marker_mm) * mm / 2.0,
                    polarity: m.polarity,
                })
                .collect()
        };
        let gap = spec.border_gap_mm * mm;
        let line_offset = [sample_half[0] + gap, sample_half[1] + gap];
        let line_half_width = spec.border_line_mm * mm / 2.0;
        let mut patches = Vec::new();
        if spec.colour_patches {
            // A row below the sample, centred between the border line's
            // outer edge and the point markers' inner edge.
            let (inner, outer) = (line_offset[1] + line_half_width, c - point_radius);
            let side = (outer - inner - 2.0 * PATCH_MARGIN_M).max(0.0);
            let pitch = PATCH_PITCH * side;
            let first = -pitch * (COLOUR_PATCHES.len() as f64 - 1.0) / 2.0;
            patches.extend(COLOUR_PATCHES.iter().enumerate().map(|(k, p)| PlacedPatch {
                name: p.name.to_string(),
                rgb: p.rgb,
                lab_d50: chart::linear_srgb_to_lab_d50(p.rgb),
                centre: [first + k as f64 * pitch, -(inner + outer) / 2.0],
                half: side / 2.0,
            }));
        }
        if let Some(c) = &spec.chart {
            if let Some(known) = chart::chart(&c.name) {
                let pitch = c.pitch_mm * mm;
                let (cols, rows) = (known.columns as f64, known.rows as f64);
                for (k, p) in known.patches.iter().enumerate() {
                    let (row, col) = ((k / known.columns) as f64, (k % known.columns) as f64);
                    patches.push(PlacedPatch {
                        name: p.name.to_string(),
                        rgb: reflectance_of(p.lab_d50),
                        lab_d50: p.lab_d50,
                        centre: [
                            c.centre_mm[0] * mm + (col - (cols - 1.0) / 2.0) * pitch,
                            c.centre_mm[1] * mm - (row - (rows - 1.0) / 2.0) * pitch,
                        ],
                        half: c.patch_mm * mm / 2.0,
                    });
                }
            }
        }
        patches.extend(spec.patches.iter().map(|p| {
            let lab = p.lab.unwrap_or([0.0; 3]);
            PlacedPatch {
                name: p.name.clone(),
                rgb: reflectance_of(lab),
                lab_d50: lab,
                centre: [p.centre_mm[0] * mm, p.centre_mm[1] * mm],
                half: p.size_mm * mm / 2.0,
            }
        }));
        let whites = spec
            .white
            .iter()
            .map(|w| WhiteArea {
                centre: [w.centre_mm[0] * mm, w.centre_mm[1] * mm],
                half: [w.size_mm[0] * mm / 2.0, w.size_mm[1] * mm / 2.0],
                reflectance: w.reflectance,
            })
            .collect();
        Holder {
            name: spec.name.clone(),
            half,
            sample_half,
            colour: spec.colour,
            marker_colour: spec.marker_colour,
            dark_marker_colour: spec.dark_marker_colour,
            point_radius,
            line_half_width,
            line_offset,
            points,
            patches,
            whites,
        }
    }

    /// Whether the standard patches fit between the border line and point
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
    /// the neutral plate's, marker's or white area's; 0 off the plate.
    pub fn reflectance(&self, x: f64, y: f64) -> [f64; 3] {
        match self.patch_at(x, y) {
            Some(p) => p.rgb,
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
            return luminance(p.rgb);
        }
        if let Some(w) = self.whites.iter().find(|w| w.contains(x, y)) {
            return w.reflectance;
        }
        if self.line_half_width > 0.0 {
            let [ox, oy] = self.line_offset;
            let w = self.line_half_width;
            let on_x_line = (ax - ox).abs() <= w && ay <= oy + w;
            let on_y_line = (ay - oy).abs() <= w && ax <= ox + w;
            if on_x_line || on_y_line {
                return self.marker_colour;
            }
        }
        if let Some(m) = self.points.iter().find(|p| {
            (x - p.position[0]).powi(2) + (y - p.position[1]).powi(2) <= p.radius * p.radius
        }) {
            return match m.polarity {
                Polarity::Light => self.marker_colour,
                Polarity::Dark => self.dark_marker_colour,
            };
        }
        self.colour
    }

    /// The standard plate around the standard sample: what a run whose
    /// profile describes no holder shows.
    pub fn standard() -> Holder {
        Holder::new(&HolderSpec::default())
    }

    /// Whether the plate has border lines.
    pub fn has_border_lines(&self) -> bool {
        self.line_half_width > 0.0
    }

    /// Every marker: the point markers' centres and, where the plate has
    /// border lines, their corners.
    pub fn markers(&self) -> Vec<Marker> {
        let [ox, oy] = self.line_offset;
        let mut m: Vec<Marker> = self
            .points
            .iter()
            .map(|p| Marker {
                kind: "point",
                position: p.position,
            })
            .collect();
        if self.has_border_lines() {
            for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                m.push(Marker {
                    kind: "corner",
                    position: [sx * ox, sy * oy],
                });
            }
        }
        m
    }
}

/// A reference L\*a\*b\* (D50) as a diffuse reflectance in linear sRGB,
/// clamped to [0, 1] (a few chart colours lie just outside sRGB).
fn reflectance_of(lab: [f64; 3]) -> [f64; 3] {
    chart::lab_d50_to_linear_srgb(lab).map(|v| v.clamp(0.0, 1.0))
}

#[cfg(test)]
mod tests;
