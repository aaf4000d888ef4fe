//! The lamp's level in each frame, measured on the holder's white
//! reference areas: an HMI lamp drifts by a few per cent over a capture of
//! hours, and every texel of a frame drifts with it. A white area is
//! matte, so its level is the irradiance it gets (the lamp's distance and
//! angle, known from the frame's achieved light direction) times the
//! lamp's output; dividing the first by the second leaves the output.
//! Levels are relative to the run's first frame whose white areas are
//! seen, so a frame processed during the capture gets the same level as
//! afterwards.

use rigd_core::holder::{Holder, WhiteArea};
use rigd_process::image_io::Image;

use crate::kinematics::camera::lamp_distances;
use crate::postprocess::frames::RunFrames;
use crate::store::FrameEntry;

/// Sample points across a white area, per side.
const POINTS_PER_SIDE: usize = 7;

/// Fraction of a white area's sides that is read: clear of its edges,
/// which blur into the plate, and of the pose's error.
const INNER_FRACTION: f64 = 0.6;

/// Below this irradiance (relative to a lamp overhead at its distance) a
/// white area is too grazingly lit to measure the lamp by.
const MIN_IRRADIANCE: f64 = 0.15;

/// A white area reading at or above this fraction of full scale may be
/// clipped, and does not measure the lamp.
const CLIPPED: f32 = 0.98;

/// How a frame's lamp level is measured: the holder's white areas and
/// the lamps' distances.
#[derive(Debug, Clone)]
pub(super) struct LampMeter {
    whites: Vec<WhiteArea>,
    /// Distance of each lamp from the sample centre, metres; a lamp not
    /// listed is far (a directional light).
    distances: std::collections::BTreeMap<String, f64>,
}

impl LampMeter {
    /// The meter for `run`'s holder; `None` when it has no white areas.
    pub(super) fn of(run: &RunFrames, holder: &Holder) -> Option<LampMeter> {
        (!holder.whites.is_empty()).then(|| LampMeter {
            whites: holder.whites.clone(),
            distances: lamp_distances(&run.meta.profile),
        })
    }

    /// The frame's white level over the irradiance its white areas get:
    /// the lamp's output, in units of this run; `None` when no white area
    /// is seen, lit enough and unclipped. `project` maps a plate point
    /// (metres) to its pixel.
    pub(super) fn output(
        &self,
        entry: &FrameEntry,
        grey: &Image,
        project: impl Fn([f64; 2]) -> Option<[f64; 2]>,
    ) -> Option<f64> {
        let light = entry.achieved_light.to_vector();
        if light[2] <= 0.0 {
            return None;
        }
        let distance = self.distances.get(&entry.positions.lamp).copied();
        let (mut sum, mut weight) = (0.0, 0.0);
        for w in &self.whites {
            let irradiance = irradiance(light, distance, w.centre);
            if irradiance < MIN_IRRADIANCE {
                continue;
            }
            let Some(level) = mean_over(grey, w, &project) else {
                continue;
            };
            let area = w.half[0] * w.half[1];
            sum += area * level / (w.reflectance * irradiance);
            weight += area;
        }
        (weight > 0.0).then(|| sum / weight)
    }
}

/// Irradiance at plate point `p` from a lamp in direction `light` (unit,
/// from the sample centre) at `distance` metres, relative to that lamp
/// overhead the centre; a directional light when the distance is unknown.
fn irradiance(light: [f64; 3], distance: Option<f64>, p: [f64; 2]) -> f64 {
    let Some(d) = distance.filter(|d| d.is_finite() && *d > 0.0) else {
        return light[2];
    };
    let to_lamp = [light[0] * d - p[0], light[1] * d - p[1], light[2] * d];
    let r = (to_lamp[0].powi(2) + to_lamp[1].powi(2) + to_lamp[2].powi(2)).sqrt();
    // cos(incidence) / r², against 1 / d² overhead.
    (to_lamp[2] / r) * (d * d) / (r * r)
}

/// Mean grey value over the inner part of a white area; `None` when part
/// of it falls outside the frame or reads clipped.
fn mean_over(
    grey: &Image,
    w: &WhiteArea,
    project: &impl Fn([f64; 2]) -> Option<[f64; 2]>,
) -> Option<f64> {
    let n = POINTS_PER_SIDE;
    let (mut sum, mut count) = (0.0, 0usize);
    for k in 0..n * n {
        let s = |i: usize| (2.0 * i as f64 / (n - 1) as f64 - 1.0) * INNER_FRACTION;
        let p = [
            w.centre[0] + w.half[0] * s(k % n),
            w.centre[1] + w.half[1] * s(k / n),
        ];
        let [u, v] = project(p)?;
        let (x, y) = (u.floor(), v.floor());
        if !(x >= 0.0 && y >= 0.0 && (x as usize) < grey.width && (y as usize) < grey.height) {
            return None;
        }
        let value = grey.data[(y as usize * grey.width + x as usize) * grey.channels];
        if !value.is_finite() || value >= CLIPPED {
            return None;
        }
        sum += f64::from(value);
        count += 1;
    }
    (count > 0).then(|| sum / count as f64)
}

/// The lamp-level figure's file in `RUN/processed/`.
pub const LAMP_FIGURE: &str = "lamp-level.svg";

/// Draws the lamp's level over the capture's physical time, one point a
/// frame, as an SVG: what an operator looks at to see how far the lamp
/// drifted. `points` are (physical seconds, level).
pub(super) fn figure(points: &[(f64, f64)]) -> Result<String, String> {
    use plotters::prelude::*;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (720, 360)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let hours: Vec<(f64, f64)> = points.iter().map(|&(t, l)| (t / 3600.0, l)).collect();
        let t_max = hours.iter().map(|p| p.0).fold(0.0, f64::max).max(1e-3);
        let (lo, hi) = hours
            .iter()
            .fold((1.0f64, 1.0f64), |(a, b), p| (a.min(p.1), b.max(p.1)));
        let pad = ((hi - lo) * 0.1).max(0.005);
        let mut chart = ChartBuilder::on(&root)
            .caption(
                "Lamp level over the capture (white reference areas)",
                ("sans-serif", 16),
            )
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(56)
            .build_cartesian_2d(0.0..t_max, (lo - pad)..(hi + pad))
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("physical time, h")
            .y_desc("lamp level (first frame = 1)")
            .draw()
            .map_err(|e| e.to_string())?;
        chart
            .draw_series(hours.iter().map(|&p| Circle::new(p, 2, BLUE.filled())))
            .map_err(|e| e.to_string())?;
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(svg)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn irradiance_falls_with_angle_and_distance() {
        let overhead = irradiance([0.0, 0.0, 1.0], Some(2.5), [0.0, 0.0]);
        assert!((overhead - 1.0).abs() < 1e-12);
        // 60° from the normal: half.
        let s = 60f64.to_radians();
        let tilted = irradiance([s.sin(), 0.0, s.cos()], None, [0.0, 0.0]);
        assert!((tilted - 0.5).abs() < 1e-12);
        // A point 65 mm towards a grazing lamp 2.5 m away gets more.
        let g = 75f64.to_radians();
        let near = irradiance([g.sin(), 0.0, g.cos()], Some(2.5), [0.065, 0.0]);
        let far = irradiance([g.sin(), 0.0, g.cos()], Some(2.5), [-0.065, 0.0]);
        assert!(near > far * 1.04, "{near} {far}");
    }

    #[test]
    fn the_figure_is_an_svg_with_a_point_per_frame() {
        let points: Vec<(f64, f64)> = (0..50)
            .map(|k| (k as f64 * 600.0, 1.0 + 0.001 * k as f64))
            .collect();
        let svg = figure(&points).expect("drawn");
        assert!(svg.starts_with("<svg"), "{}", &svg[..40.min(svg.len())]);
        assert_eq!(svg.matches("<circle").count(), 50);
        assert!(svg.contains("physical time, h"));
    }

    #[test]
    fn a_white_area_off_the_frame_or_clipped_measures_nothing() {
        let mut grey = Image::new(10, 10, 1);
        grey.data.iter_mut().for_each(|v| *v = 0.5);
        let w = WhiteArea {
            centre: [0.0, 0.0],
            half: [0.002, 0.001],
            reflectance: 0.9,
        };
        // 1 px per mm, centred.
        let inside = |p: [f64; 2]| Some([5.0 + 1e3 * p[0], 5.0 - 1e3 * p[1]]);
        assert_eq!(mean_over(&grey, &w, &inside), Some(0.5));
        let outside = |p: [f64; 2]| Some([9.5 + 1e3 * p[0], 5.0]);
        assert_eq!(mean_over(&grey, &w, &outside), None);
        grey.data.iter_mut().for_each(|v| *v = 0.99);
        assert_eq!(mean_over(&grey, &w, &inside), None);
    }
}
