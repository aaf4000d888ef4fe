//! Calibration.

use super::*;

/// The result of [`calibrate_plane`].
#[derive(Debug, Clone, PartialEq)]
pub struct PlaneCalibration {
    /// The fitted laser plane, world frame (metres).
    pub plane: LaserPlane,
    /// Angle between the laser plane and the reference plane `z = 0`,
    /// degrees (Wang et al.'s calibrated quantity).
    pub tilt_deg: f64,
    /// RMS distance of the back-projected line points from the fitted
    /// plane, metres (coplanarity residual).
    pub residual_m: f64,
    /// Angle between the two 3-D lines, degrees (0 for a consistent pair).
    pub line_angle_deg: f64,
}

/// Smallest-eigenvalue eigenvector of a symmetric 3×3 matrix (cyclic
/// Jacobi) and the eigenvalues ascending.
pub(super) fn smallest_eigenvector(mut a: [[f64; 3]; 3]) -> ([f64; 3], [f64; 3]) {
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _ in 0..50 {
        let off = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
        if off < 1e-30 {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q].abs() < 1e-300 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for row in a.iter_mut() {
                let (akp, akq) = (row[p], row[q]);
                row[p] = c * akp - s * akq;
                row[q] = s * akp + c * akq;
            }
            let (rp, rq) = (a[p], a[q]);
            for k in 0..3 {
                a[p][k] = c * rp[k] - s * rq[k];
                a[q][k] = s * rp[k] + c * rq[k];
            }
            for row in v.iter_mut() {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&i, &j| a[i][i].total_cmp(&a[j][j]));
    let k = idx[0];
    (
        [v[0][k], v[1][k], v[2][k]],
        [a[idx[0]][idx[0]], a[idx[1]][idx[1]], a[idx[2]][idx[2]]],
    )
}

/// Back-projects the inliers' feet on the fitted line to `z = height`.
pub(super) fn line_points_3d(
    camera: &PinholeCamera,
    line: &LineFit,
    height: f64,
    which: &str,
) -> Result<Vec<[f64; 3]>, MdfError> {
    let (a, b) = line.endpoints();
    let len = (b[0] - a[0]).hypot(b[1] - a[1]);
    if !gt(len, 2.0) {
        return Err(MdfError::DegenerateCalibration(format!(
            "{which} line spans only {len:.2} px"
        )));
    }
    let n = 16;
    (0..=n)
        .map(|k| {
            let s = k as f64 / n as f64;
            let (x, y) = (a[0] + s * (b[0] - a[0]), a[1] + s * (b[1] - a[1]));
            camera.back_project_to_height(x, y, height).ok_or_else(|| {
                MdfError::DegenerateCalibration(format!(
                    "{which} line pixel ({x:.1}, {y:.1}) does not see the plane z = {height}"
                ))
            })
        })
        .collect()
}

/// The laser plane from its line seen on the reference plane `z = 0`
/// (`line_at_0`) and on a raised plane `z = height` (`line_at_h`), Wang
/// et al., §3.2 ("project the laser strip onto two planes with different
/// heights"): both image lines back-project to 3-D lines; the plane is
/// the least-squares plane through points sampled along both. Errors when
/// a line is too short, does not back-project, `height` is not positive,
/// or the two 3-D lines are not parallel within
/// [`MAX_CALIBRATION_LINE_ANGLE_DEG`] (they cannot lie in one plane cut by
/// two parallel planes).
pub fn calibrate_plane(
    camera: &PinholeCamera,
    line_at_0: &LineFit,
    line_at_h: &LineFit,
    height: f64,
) -> Result<PlaneCalibration, MdfError> {
    camera.validate()?;
    if !(height.is_finite() && height > 0.0) {
        return Err(MdfError::DegenerateCalibration(format!(
            "raised plane height {height} m (must be > 0)"
        )));
    }
    let p0 = line_points_3d(camera, line_at_0, 0.0, "reference")?;
    let p1 = line_points_3d(camera, line_at_h, height, "raised")?;
    let dir = |p: &[[f64; 3]]| unit(sub(p[p.len() - 1], p[0]));
    let (d0, d1) = match (dir(&p0), dir(&p1)) {
        (Some(a), Some(b)) => (a, b),
        _ => {
            return Err(MdfError::DegenerateCalibration(
                "a 3-D line has no direction".into(),
            ))
        }
    };
    let line_angle_deg = dot(d0, d1).abs().min(1.0).acos().to_degrees();
    if line_angle_deg > MAX_CALIBRATION_LINE_ANGLE_DEG {
        return Err(MdfError::DegenerateCalibration(format!(
            "the two 3-D lines differ in direction by {line_angle_deg:.2}° (> {MAX_CALIBRATION_LINE_ANGLE_DEG}°): not one laser plane"
        )));
    }
    let all: Vec<[f64; 3]> = p0.iter().chain(&p1).copied().collect();
    let n = all.len() as f64;
    let c = scale(all.iter().fold([0.0; 3], |s, p| add(s, *p)), 1.0 / n);
    let mut cov = [[0.0; 3]; 3];
    for p in &all {
        let d = sub(*p, c);
        for (i, row) in cov.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v += d[i] * d[j];
            }
        }
    }
    let (normal, eig) = smallest_eigenvector(cov);
    let normal =
        unit(normal).ok_or_else(|| MdfError::DegenerateCalibration("no plane normal".into()))?;
    if !gt(eig[1], 1e-6 * eig[2].max(1e-300)) {
        return Err(MdfError::DegenerateCalibration(
            "the two 3-D lines coincide".into(),
        ));
    }
    let plane = LaserPlane {
        normal,
        offset: dot(normal, c),
    };
    let residual_m = (all.iter().map(|p| plane.distance(*p).powi(2)).sum::<f64>() / n).sqrt();
    let tilt_deg = normal[2].abs().min(1.0).acos().to_degrees();
    Ok(PlaneCalibration {
        plane,
        tilt_deg,
        residual_m,
        line_angle_deg,
    })
}

/// What fixes a scan frame's laser plane besides its line on the
/// reference plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PlaneConstraint {
    /// Wang et al.'s model (laser far away, planes of one scan parallel): the
    /// plane makes the calibrated plane's angle with `z = 0` (its normal's
    /// `z` component and side are taken from this calibrated plane).
    CalibratedTilt(LaserPlane),
    /// The plane passes through the emitter at this position (a near
    /// rotating emitter, e.g. the simulator's `LaserLine::emitter`).
    ThroughEmitter([f64; 3]),
}

/// A scan frame's laser plane from its line detected in the reference
/// region (on the plane `z = reference_z`, normally the turntable, 0), Wang
/// et al., §3.2: "projecting the laser line … to the 3D reference plane".
pub fn plane_from_line(
    camera: &PinholeCamera,
    line: &LineFit,
    reference_z: f64,
    constraint: PlaneConstraint,
) -> Result<LaserPlane, MdfError> {
    camera.validate()?;
    let pts = line_points_3d(camera, line, reference_z, "reference")?;
    let q = pts[pts.len() / 2];
    let u = unit(sub(pts[pts.len() - 1], pts[0]))
        .ok_or_else(|| MdfError::DegenerateCalibration("the 3-D line has no direction".into()))?;
    let normal = match constraint {
        PlaneConstraint::ThroughEmitter(e) => {
            if !finite3(e) {
                return Err(MdfError::InvalidInput(format!("emitter {e:?}")));
            }
            unit(cross(u, sub(e, q))).ok_or_else(|| {
                MdfError::DegenerateCalibration("the emitter lies on the laser line".into())
            })?
        }
        PlaneConstraint::CalibratedTilt(cal) => {
            let cal = cal.normalised(0)?;
            // Normals ⟂ u: n = nz·ẑ' + r·m with m horizontal ⟂ u; ẑ' = the
            // part of ẑ ⟂ u (u is horizontal on z = const, so ẑ itself).
            let m = unit(cross([0.0, 0.0, 1.0], u))
                .ok_or_else(|| MdfError::DegenerateCalibration("vertical 3-D line".into()))?;
            let nz = cal.normal[2];
            let r = (1.0 - nz * nz).max(0.0).sqrt();
            let side = if dot(m, cal.normal) < 0.0 { -1.0 } else { 1.0 };
            add([0.0, 0.0, nz], scale(m, side * r))
        }
    };
    Ok(LaserPlane {
        normal,
        offset: dot(normal, q),
    })
}
