//! The holder's other parts where a frame shows them, so that a blob
//! found near a marker can be told from a piece of something else.
//!
//! At grazing views the plate is squeezed into a band a few pixels tall:
//! a border line sampled at a slant breaks into short dashes the size of a
//! foreshortened marker, a few pixels from it. The nearest blob to where
//! the pose puts a marker is then, as often as not, a dash of the line
//! (the marker itself fails the isolation test beside it), and a fit to
//! such blobs lands pixels off. A blob that lies nearer to another part of
//! the holder than to the marker's predicted centre is not the marker.

use rigd_core::camera::Camera;
use rigd_core::holder::Holder;

/// The holder's parts in one frame's pixels, as the camera model puts
/// them.
pub(crate) struct HolderImage {
    /// Every point marker's predicted centre; None behind the camera.
    markers: Vec<Option<[f64; 2]>>,
    /// The border lines' centre lines.
    lines: Vec<[[f64; 2]; 2]>,
    /// The sample window, the colour patches and the white areas: what
    /// lies inside one of them, or nearer its outline than to the marker,
    /// is part of it.
    areas: Vec<[[f64; 2]; 4]>,
}

impl HolderImage {
    /// The holder's parts through `camera`; a part any of whose corners is
    /// behind the camera is left out.
    pub(crate) fn new(holder: &Holder, camera: &Camera) -> HolderImage {
        let at = |x: f64, y: f64| camera.project([x, y, 0.0]);
        let rectangle = |c: [f64; 2], h: [f64; 2]| -> Option<[[f64; 2]; 4]> {
            Some([
                at(c[0] - h[0], c[1] - h[1])?,
                at(c[0] + h[0], c[1] - h[1])?,
                at(c[0] + h[0], c[1] + h[1])?,
                at(c[0] - h[0], c[1] + h[1])?,
            ])
        };
        let lines = if holder.has_border_lines() {
            rectangle([0.0, 0.0], holder.line_offset).map_or_else(Vec::new, |q| {
                (0..4).map(|k| [q[k], q[(k + 1) % 4]]).collect()
            })
        } else {
            Vec::new()
        };
        let areas = std::iter::once(rectangle([0.0, 0.0], holder.sample_half))
            .chain(
                holder
                    .patches
                    .iter()
                    .map(|p| rectangle(p.centre, [p.half, p.half])),
            )
            .chain(holder.whites.iter().map(|w| rectangle(w.centre, w.half)))
            .flatten()
            .collect();
        HolderImage {
            markers: holder
                .points
                .iter()
                .map(|p| at(p.position[0], p.position[1]))
                .collect(),
            lines,
            areas,
        }
    }

    /// Whether a blob centred at `c` can be marker `i`: it lies no nearer
    /// to another marker's predicted centre, a border line or an area's
    /// outline than to marker `i`'s, and inside no area.
    pub(crate) fn belongs_to_marker(&self, i: usize, c: [f64; 2]) -> bool {
        let Some(own) = self.markers.get(i).copied().flatten() else {
            return false;
        };
        let d_own = distance(c, own);
        let other_marker = self
            .markers
            .iter()
            .enumerate()
            .filter(|&(j, _)| j != i)
            .filter_map(|(_, m)| *m)
            .any(|m| distance(c, m) < d_own);
        let line = self
            .lines
            .iter()
            .any(|&[a, b]| segment_distance(c, a, b) < d_own);
        let area = self.areas.iter().any(|q| {
            contains(q, c) || (0..4).any(|k| segment_distance(c, q[k], q[(k + 1) % 4]) < d_own)
        });
        !(other_marker || line || area)
    }
}

fn distance(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

/// The point of the segment from `a` to `b` nearest to `p`.
fn nearest_on_segment(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    let ab = [b[0] - a[0], b[1] - a[1]];
    let len2 = ab[0] * ab[0] + ab[1] * ab[1];
    let t = if len2 > 0.0 {
        (((p[0] - a[0]) * ab[0] + (p[1] - a[1]) * ab[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    [a[0] + t * ab[0], a[1] + t * ab[1]]
}

/// Distance from `p` to the segment from `a` to `b`.
fn segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    distance(p, nearest_on_segment(p, a, b))
}

/// Whether `p` lies inside the convex quadrilateral `q` (either winding).
fn contains(q: &[[f64; 2]; 4], p: [f64; 2]) -> bool {
    let side = |k: usize| {
        let (a, b) = (q[k], q[(k + 1) % 4]);
        (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
    };
    let s = [side(0), side(1), side(2), side(3)];
    s.iter().all(|&v| v >= 0.0) || s.iter().all(|&v| v <= 0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigd_core::geometry::Direction;

    fn camera(theta_deg: f64, phi_deg: f64) -> Camera {
        let view = Direction::new(theta_deg, phi_deg).to_vector();
        Camera::new(view, [640, 480], Some(2322.0), Some(1.6), 0.12)
    }

    /// Seen from the normal every marker stands clear: a blob a few
    /// pixels off its predicted centre is still its own.
    #[test]
    fn a_frontal_marker_owns_the_blobs_around_it() {
        let holder = Holder::standard();
        let image = HolderImage::new(&holder, &camera(0.0, 0.0));
        for (i, m) in image.markers.iter().enumerate() {
            let m = m.expect("in front");
            for off in [[0.0, 0.0], [3.0, 0.0], [0.0, -3.0], [2.0, 2.0]] {
                assert!(image.belongs_to_marker(i, [m[0] + off[0], m[1] + off[1]]));
            }
        }
    }

    /// At 85° the border line passes a few pixels from the markers: a blob
    /// on the line belongs to the line, one at the marker to the marker.
    #[test]
    fn at_a_grazing_view_a_dash_of_the_border_line_is_not_a_marker() {
        let holder = Holder::standard();
        let cam = camera(85.0, 240.0);
        let image = HolderImage::new(&holder, &cam);
        let mut refused = 0;
        for (i, p) in holder.points.iter().enumerate() {
            let m = image.markers[i].expect("in front");
            assert!(
                image.belongs_to_marker(i, m),
                "marker {i} at its own centre"
            );
            // The point of the nearest border line closest to the marker.
            let on_line = image
                .lines
                .iter()
                .map(|&[a, b]| nearest_on_segment(m, a, b))
                .min_by(|x, y| distance(*x, m).total_cmp(&distance(*y, m)))
                .expect("lines");
            if distance(on_line, m) < 19.0 {
                assert!(
                    !image.belongs_to_marker(i, on_line),
                    "marker {i} at {:?} mm: a blob on the line {:.1} px away was taken",
                    p.position,
                    distance(on_line, m)
                );
                refused += 1;
            }
        }
        assert!(
            refused > 0,
            "no marker has the line within the search radius"
        );
    }

    /// A blob inside the sample window is the sample's, however near the
    /// marker.
    #[test]
    fn a_blob_in_the_sample_window_is_not_a_marker() {
        let holder = Holder::standard();
        let image = HolderImage::new(&holder, &camera(0.0, 0.0));
        let centre = image.markers[0].expect("in front");
        let window = image.areas[0];
        assert!(contains(&window, [320.0, 240.0]));
        assert!(!image.belongs_to_marker(0, [320.0, 240.0]));
        assert!(!contains(&window, centre));
    }

    #[test]
    fn distances_to_a_segment_clamp_at_its_ends() {
        assert_eq!(segment_distance([0.0, 1.0], [-1.0, 0.0], [1.0, 0.0]), 1.0);
        assert_eq!(segment_distance([3.0, 0.0], [-1.0, 0.0], [1.0, 0.0]), 2.0);
        assert_eq!(segment_distance([0.0, 2.0], [0.0, 0.0], [0.0, 0.0]), 2.0);
    }
}
