//! Registration from the rig's pose: the homography the camera model
//! predicts from the achieved kinematics, the holder's offset from it that
//! marker-registered frames reveal, and how far two registrations disagree.

use super::*;

/// The plate→image homography of a camera model: `project` maps a plate
/// point (metres, z = 0) to pixels; a 3 × 3 grid over `region` is projected
/// and fitted exactly (no refinement needed: a pinhole maps a plane by a
/// homography).
pub fn pose_homography(
    project: impl Fn([f64; 2]) -> Option<[f64; 2]>,
    region: Region,
) -> Result<Homography, RectifyError> {
    if !region.is_valid() {
        return Err(RectifyError::InvalidInput(format!("region {region:?}")));
    }
    let mut plate = Vec::with_capacity(9);
    let mut pixels = Vec::with_capacity(9);
    for j in 0..3 {
        for i in 0..3 {
            let q = [
                region.x_min + (region.x_max - region.x_min) * i as f64 / 2.0,
                region.y_min + (region.y_max - region.y_min) * j as f64 / 2.0,
            ];
            if let Some(p) = project(q) {
                plate.push(q);
                pixels.push(p);
            }
        }
    }
    if plate.len() < 9 {
        return Err(RectifyError::Folded { found: plate.len() });
    }
    fit_homography(&plate, &pixels, false)
}

/// `h` after a shift of the plate by `offset` metres: `h'(q) = h(q + offset)`.
pub fn shift_plate(h: &Homography, offset: [f64; 2]) -> Homography {
    mul3(
        h,
        &[
            [1.0, 0.0, offset[0]],
            [0.0, 1.0, offset[1]],
            [0.0, 0.0, 1.0],
        ],
    )
}

/// The plate offset `d` with `measured(q) ≈ pose(q + d)`, averaged over the
/// region's corners: where the holder really sits relative to where the
/// pose model puts it. `None` if either mapping folds there.
pub fn plate_offset(pose: &Homography, measured: &Homography, region: Region) -> Option<[f64; 2]> {
    let inverse = invert(pose)?;
    let mut sum = [0.0, 0.0];
    for q in corners(region) {
        let p = project(measured, q)?;
        let w = project(&inverse, p)?;
        sum[0] += w[0] - q[0];
        sum[1] += w[1] - q[1];
    }
    Some([sum[0] / 4.0, sum[1] / 4.0])
}

/// The one plate offset `d` that best explains every pair (pose, markers)
/// at once: least squares, in pixels, of `pose(q + d) − markers(q)` over
/// the region's corners of every pair (Gauss–Newton from the median of the
/// per-pair [`plate_offset`]s). In pixels because at grazing views a
/// millimetre along the foreshortened axis is a fraction of a pixel: a
/// per-frame offset there is noise in millimetres, and the least squares
/// weighs each view by how well it sees the offset.
pub fn fit_plate_offset(pairs: &[(Homography, Homography)], region: Region) -> Option<[f64; 2]> {
    let mut per_pair: Vec<[f64; 2]> = pairs
        .iter()
        .filter_map(|(p, m)| plate_offset(p, m, region))
        .collect();
    if per_pair.is_empty() {
        return None;
    }
    let median = |k: usize, v: &mut Vec<[f64; 2]>| {
        v.sort_by(|a, b| a[k].total_cmp(&b[k]));
        v[v.len() / 2][k]
    };
    let mut d = [median(0, &mut per_pair), median(1, &mut per_pair)];
    // A step of a micrometre for the numerical Jacobian.
    const STEP: f64 = 1e-6;
    for _ in 0..5 {
        let (mut a, mut b) = ([[0.0; 2]; 2], [0.0; 2]);
        for (pose, markers) in pairs {
            for q in corners(region) {
                let (Some(target), Some(at)) = (
                    project(markers, q),
                    project(pose, [q[0] + d[0], q[1] + d[1]]),
                ) else {
                    continue;
                };
                let (Some(ax), Some(ay)) = (
                    project(pose, [q[0] + d[0] + STEP, q[1] + d[1]]),
                    project(pose, [q[0] + d[0], q[1] + d[1] + STEP]),
                ) else {
                    continue;
                };
                let j = [
                    [(ax[0] - at[0]) / STEP, (ay[0] - at[0]) / STEP],
                    [(ax[1] - at[1]) / STEP, (ay[1] - at[1]) / STEP],
                ];
                let r = [target[0] - at[0], target[1] - at[1]];
                for row in 0..2 {
                    for c in 0..2 {
                        a[c][row] += j[0][c] * j[0][row] + j[1][c] * j[1][row];
                    }
                    b[row] += j[0][row] * r[0] + j[1][row] * r[1];
                }
            }
        }
        let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
        if det.abs() <= 1e-300 || !det.is_finite() {
            break;
        }
        let step = [
            (a[1][1] * b[0] - a[0][1] * b[1]) / det,
            (a[0][0] * b[1] - a[1][0] * b[0]) / det,
        ];
        d = [d[0] + step[0], d[1] + step[1]];
        if step[0].hypot(step[1]) < 1e-9 {
            break;
        }
    }
    d.iter().all(|v| v.is_finite()).then_some(d)
}

/// The largest distance in pixels between where `a` and `b` put the
/// region's corners; `None` if either folds there.
pub fn disagreement_px(a: &Homography, b: &Homography, region: Region) -> Option<f64> {
    corners(region)
        .into_iter()
        .map(|q| {
            let (pa, pb) = (project(a, q)?, project(b, q)?);
            Some((pa[0] - pb[0]).hypot(pa[1] - pb[1]))
        })
        .try_fold(0f64, |m, d| d.map(|d| m.max(d)))
}

fn corners(r: Region) -> [[f64; 2]; 4] {
    [
        [r.x_min, r.y_min],
        [r.x_max, r.y_min],
        [r.x_max, r.y_max],
        [r.x_min, r.y_max],
    ]
}

/// The inverse of a 3 × 3 matrix by its adjugate; `None` if singular.
fn invert(m: &Homography) -> Option<Homography> {
    let c =
        |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let adj = [
        [c(1, 2, 1, 2), -c(0, 2, 1, 2), c(0, 1, 1, 2)],
        [-c(1, 2, 0, 2), c(0, 2, 0, 2), -c(0, 1, 0, 2)],
        [c(1, 2, 0, 1), -c(0, 2, 0, 1), c(0, 1, 0, 1)],
    ];
    let det = m[0][0] * adj[0][0] + m[0][1] * adj[1][0] + m[0][2] * adj[2][0];
    if det.abs() <= 1e-300 || !det.is_finite() {
        return None;
    }
    Some(adj.map(|row| row.map(|v| v / det)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn perspective() -> Homography {
        [
            [900.0, 40.0, 320.0],
            [-30.0, 700.0, 240.0],
            [0.3, -0.2, 1.0],
        ]
    }

    #[test]
    fn the_offset_of_a_shifted_plate_is_recovered() {
        let region = Region::centred([0.04, 0.04]);
        let pose = perspective();
        let d = [0.0015, -0.0008];
        let measured = shift_plate(&pose, d);
        let got = plate_offset(&pose, &measured, region).unwrap();
        assert!(
            (got[0] - d[0]).abs() < 1e-12 && (got[1] - d[1]).abs() < 1e-12,
            "{got:?}"
        );
        assert!(disagreement_px(&pose, &measured, region).unwrap() > 0.5);
        let corrected = shift_plate(&pose, got);
        assert!(disagreement_px(&corrected, &measured, region).unwrap() < 1e-9);
        // Several views with noise on their markers: the joint fit.
        let other: Homography = [[600.0, -20.0, 300.0], [10.0, 200.0, 200.0], [0.1, 0.9, 1.0]];
        let noisy = |h: &Homography, e: f64| {
            let mut m = shift_plate(h, d);
            m[0][2] += e;
            m
        };
        let pairs = vec![
            (pose, noisy(&pose, 0.2)),
            (other, noisy(&other, -0.2)),
            (pose, noisy(&pose, -0.2)),
            (other, noisy(&other, 0.2)),
        ];
        let fit = fit_plate_offset(&pairs, region).unwrap();
        assert!(
            (fit[0] - d[0]).abs() < 2e-5 && (fit[1] - d[1]).abs() < 2e-5,
            "{fit:?}"
        );
        assert_eq!(fit_plate_offset(&[], region), None);
    }

    #[test]
    fn the_pose_homography_reproduces_the_projection() {
        let h = perspective();
        let region = Region::centred([0.05, 0.03]);
        let fitted = pose_homography(|q| project(&h, q), region).unwrap();
        assert!(disagreement_px(&h, &fitted, region).unwrap() < 1e-6);
        // A camera that sees only part of the plate gives no homography.
        assert!(
            pose_homography(|q| (q[0] < 0.0).then(|| project(&h, q)).flatten(), region).is_err()
        );
        assert!(invert(&[[0.0; 3]; 3]).is_none());
    }
}
