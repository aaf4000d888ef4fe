//! Which pixels of a frame can show anything: those whose rays meet the
//! holder plate or pass through the relief over the sample. Every other ray
//! misses the plane or lands on the bare floor beyond the plate, whose
//! albedo is 0, so its pixel is exactly 0 before noise and the renderer
//! need not trace it. A capture's camera sees the plate small in a wide
//! frame: most of its pixels are such floor.
//!
//! The plate and the relief's bounding box are convex and, when every
//! corner is in front of the camera, so is their image: the hull of the
//! projected corners. Each row renders the columns where that hull, widened
//! by a safety margin far beyond rounding error, crosses the row.

use rigd_core::camera::Camera;

/// Pixels of slack around the projected hull, in both directions.
const MARGIN_PX: f64 = 2.0;

/// The columns each row of a frame must render.
#[derive(Debug, Clone)]
pub(crate) struct Coverage {
    /// `[first, end)` per row.
    spans: Vec<(usize, usize)>,
}

impl Coverage {
    /// Every pixel of every row: what a frame renders when nothing is known
    /// to be black.
    pub(crate) fn full(width: usize, height: usize) -> Coverage {
        Coverage {
            spans: vec![(0, width); height],
        }
    }

    /// The pixels that can see the plate (`holder_half` either side of the
    /// centre, at z = 0) or the relief (`sample_half`, up to `relief_top`).
    /// All of them when a corner is behind the camera or projects to a
    /// non-finite point.
    pub(crate) fn new(
        camera: &Camera,
        [width, height]: [usize; 2],
        holder_half: f64,
        sample_half: [f64; 2],
        relief_top: Option<f64>,
    ) -> Coverage {
        let mut corners = Vec::with_capacity(8);
        for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            corners.push([sx * holder_half, sy * holder_half, 0.0]);
            if let Some(top) = relief_top {
                // A little above the top the marching starts from.
                let z = top + 1e-6;
                corners.push([sx * sample_half[0], sy * sample_half[1], z]);
            }
        }
        let mut projected = Vec::with_capacity(corners.len());
        for c in corners {
            match camera.project(c) {
                Some([x, y]) if x.is_finite() && y.is_finite() => projected.push([x, y]),
                _ => return Coverage::full(width, height),
            }
        }
        let hull = convex_hull(projected);
        let spans = (0..height)
            .map(|j| {
                let centre = j as f64 + 0.5;
                match x_extent(&hull, centre - MARGIN_PX, centre + MARGIN_PX) {
                    Some((lo, hi)) => {
                        // Column i's centre is i + 0.5.
                        let first = (lo - MARGIN_PX).floor().clamp(0.0, width as f64) as usize;
                        let end = (hi + MARGIN_PX).ceil().clamp(0.0, width as f64) as usize;
                        (first, end.max(first))
                    }
                    None => (0, 0),
                }
            })
            .collect();
        Coverage { spans }
    }

    /// Columns `[first, end)` of row `j` that may not be black.
    #[inline]
    pub(crate) fn span(&self, j: usize) -> (usize, usize) {
        self.spans.get(j).copied().unwrap_or((0, 0))
    }
}

/// The convex hull of `points`, counter-clockwise (Andrew's monotone
/// chain); fewer than three points, or collinear ones, give the extreme
/// points of the chain.
fn convex_hull(mut points: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    points.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    points.dedup();
    if points.len() < 3 {
        return points;
    }
    let mut hull: Vec<[f64; 2]> = Vec::with_capacity(2 * points.len());
    push_chain(&mut hull, points.iter());
    push_chain(&mut hull, points.iter().rev());
    hull
}

/// Appends one monotone chain of the hull through `points` (in x order,
/// or reversed for the upper chain), without its last point, which starts
/// the other chain.
fn push_chain<'a>(hull: &mut Vec<[f64; 2]>, points: impl Iterator<Item = &'a [f64; 2]>) {
    let turn = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    let start = hull.len();
    for &p in points {
        while hull.len() >= start + 2 && turn(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0
        {
            hull.pop();
        }
        hull.push(p);
    }
    hull.pop();
}

/// The smallest and largest x of the polygon `hull` (its vertices in
/// order) within the strip `y_lo ≤ y ≤ y_hi`, or None if it misses the
/// strip. The extremes lie on vertices inside the strip or where an edge
/// crosses the strip's border, so clipping every edge to the strip finds
/// them.
fn x_extent(hull: &[[f64; 2]], y_lo: f64, y_hi: f64) -> Option<(f64, f64)> {
    let mut extent: Option<(f64, f64)> = None;
    let mut include = |x: f64| {
        extent = Some(extent.map_or((x, x), |(lo, hi)| (lo.min(x), hi.max(x))));
    };
    let n = hull.len();
    for k in 0..n {
        let a = hull[k];
        let b = hull[(k + 1) % n];
        // The part of segment a → b with y in the strip, as parameters.
        let (mut s0, mut s1) = (0.0f64, 1.0f64);
        let dy = b[1] - a[1];
        if dy == 0.0 {
            if a[1] < y_lo || a[1] > y_hi {
                continue;
            }
        } else {
            let (ta, tb) = ((y_lo - a[1]) / dy, (y_hi - a[1]) / dy);
            s0 = s0.max(ta.min(tb));
            s1 = s1.min(ta.max(tb));
            if s0 > s1 {
                continue;
            }
        }
        include(a[0] + s0 * (b[0] - a[0]));
        include(a[0] + s1 * (b[0] - a[0]));
    }
    extent
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hull_of_a_square_with_an_inner_point() {
        let hull = convex_hull(vec![
            [0.0, 0.0],
            [2.0, 0.0],
            [1.0, 1.0],
            [2.0, 2.0],
            [0.0, 2.0],
        ]);
        assert_eq!(hull.len(), 4, "{hull:?}");
        assert_eq!(x_extent(&hull, 0.5, 0.5), Some((0.0, 2.0)));
        assert_eq!(x_extent(&hull, 3.0, 4.0), None);
    }

    #[test]
    fn strip_extent_of_a_diamond() {
        let hull = convex_hull(vec![[0.0, 1.0], [1.0, 0.0], [2.0, 1.0], [1.0, 2.0]]);
        let (lo, hi) = x_extent(&hull, 0.0, 0.5).unwrap_or_default();
        assert!(
            (lo - 0.5).abs() < 1e-12 && (hi - 1.5).abs() < 1e-12,
            "{lo} {hi}"
        );
        // A single point and a segment still give extents.
        assert_eq!(
            x_extent(&convex_hull(vec![[3.0, 3.0]]), 2.0, 4.0),
            Some((3.0, 3.0))
        );
        let segment = convex_hull(vec![[0.0, 0.0], [4.0, 4.0], [2.0, 2.0]]);
        assert_eq!(x_extent(&segment, 1.0, 3.0), Some((1.0, 3.0)));
    }

    #[test]
    fn a_frame_filled_by_the_plate_renders_every_pixel_and_a_wide_one_few() {
        let view = [0.3, -0.2, 0.93];
        let close = Camera::new(view, [64, 48], Some(400.0), Some(0.3), 0.088);
        let c = Coverage::new(&close, [64, 48], 0.08, [0.05, 0.05], Some(0.002));
        assert!((0..48).all(|j| c.span(j) == (0, 64)));
        let far = Camera::new(view, [384, 288], Some(1393.0), Some(1.6), 0.088);
        let c = Coverage::new(&far, [384, 288], 0.08, [0.05, 0.05], Some(0.002));
        let covered: usize = (0..288).map(|j| c.span(j).1 - c.span(j).0).sum();
        assert!(covered > 10_000 && covered < 30_000, "{covered}");
    }
}
