//! MDF measurement on an analytic laser-scan renderer: a 160×120 pinhole
//! camera at θ = 40°, the turntable z = 0 with a 20 × 20 × 2 mm box bump,
//! a laser emitter (the simulator's model: the plane through the emitter,
//! Gaussian profile across it, cosine falloff, shadowed by the box) that
//! rotates so its strip sweeps across the sample, ambient light and
//! Gaussian noise. The truth is computed analytically per pixel (first ray
//! hit, shadow test), so every figure here can fail.

use proptest::prelude::*;
use rigd_core::geometry::{self as vec3, add, cross, dot, scale, sub};
use rigd_process::image_io::Image;
use rigd_process::mdf::*;

const W: usize = 160;
const H: usize = 120;
const THETA_DEG: f64 = 40.0;
const CAM_DIST: f64 = 0.3;
const FOCAL: f64 = 800.0;
/// Box bump: |x|, |y| ≤ BOX_HALF, 0 ≤ z ≤ BOX_H.
const BOX_HALF: f64 = 0.010;
const BOX_H: f64 = 0.002;
/// MDF reference plane, above the bump.
const REF_H: f64 = 0.003;
const MAX_DEPTH: f64 = 0.02;
const LASER_FWHM: f64 = 0.001;
const LASER_POWER: f64 = 0.8;
const AMBIENT: f64 = 0.03;
const NOISE: f64 = 0.01;
const SOURCE_R: f64 = 0.5;
const SOURCE_ELEV_DEG: f64 = 45.0;

/// A unit vector (test inputs are never zero).
fn unit(a: [f64; 3]) -> [f64; 3] {
    vec3::unit(a).unwrap_or([0.0, 0.0, 1.0])
}

fn camera() -> PinholeCamera {
    let t = THETA_DEG.to_radians();
    PinholeCamera::looking_at_origin([t.sin(), 0.0, t.cos()], CAM_DIST, FOCAL, W, H).unwrap()
}

/// Deterministic Gaussian noise (xorshift64* + Box–Muller).
struct Rng(u64);
impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        ((self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn gauss(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }
}

/// Entry/exit ray parameters of the box (slab test), if hit.
fn box_hit(o: [f64; 3], d: [f64; 3]) -> Option<(f64, f64, usize, f64)> {
    let lo = [-BOX_HALF, -BOX_HALF, 0.0];
    let hi = [BOX_HALF, BOX_HALF, BOX_H];
    let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
    let (mut axis, mut sign) = (2, 1.0);
    for k in 0..3 {
        if d[k].abs() < 1e-15 {
            if o[k] < lo[k] || o[k] > hi[k] {
                return None;
            }
            continue;
        }
        let (a, b) = ((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]);
        let (near, far) = if a < b { (a, b) } else { (b, a) };
        if near > t0 {
            t0 = near;
            axis = k;
            sign = if d[k] > 0.0 { -1.0 } else { 1.0 };
        }
        t1 = t1.min(far);
    }
    (t0 <= t1).then_some((t0, t1, axis, sign))
}

/// The surface point and normal seen along a ray (ground at `ground_z`,
/// with the box when `with_box`).
fn first_hit(o: [f64; 3], d: [f64; 3], ground_z: f64, with_box: bool) -> ([f64; 3], [f64; 3], f64) {
    if with_box {
        if let Some((t0, _, axis, sign)) = box_hit(o, d) {
            if t0 > 0.0 {
                let mut n = [0.0; 3];
                n[axis] = sign;
                return (add(o, scale(d, t0)), n, t0);
            }
        }
    }
    let t = (ground_z - o[2]) / d[2];
    (add(o, scale(d, t)), [0.0, 0.0, 1.0], t)
}

/// Does the segment from `p` (on the surface, normal `n`) to the emitter
/// pass through the box?
fn shadowed(p: [f64; 3], n: [f64; 3], e: [f64; 3]) -> bool {
    let start = add(p, scale(n, 1e-9));
    let d = sub(e, start);
    match box_hit(start, d) {
        Some((t0, t1, _, _)) => t1 > 1e-12 && t0 < 1.0 && t0.max(0.0) <= t1,
        None => false,
    }
}

#[derive(Clone, Copy)]
struct Source {
    emitter: [f64; 3],
    /// Horizontal unit toward the source (the scan direction).
    h: [f64; 3],
    /// Strip direction on the turntable.
    u: [f64; 3],
}

fn source(azimuth_deg: f64) -> Source {
    let (a, e) = (azimuth_deg.to_radians(), SOURCE_ELEV_DEG.to_radians());
    let emitter = [
        SOURCE_R * e.cos() * a.cos(),
        SOURCE_R * e.cos() * a.sin(),
        SOURCE_R * e.sin(),
    ];
    let h = [a.cos(), a.sin(), 0.0];
    Source {
        emitter,
        h,
        u: unit(cross([0.0, 0.0, 1.0], h)),
    }
}

/// The plane of the strip that crosses the turntable (z = 0) through
/// `c · h` (the emitter rotates about the strip direction).
fn plane_at(s: &Source, c: f64) -> LaserPlane {
    let g = scale(s.h, c);
    let n = unit(cross(s.u, sub(g, s.emitter)));
    LaserPlane {
        normal: n,
        offset: dot(n, s.emitter),
    }
}

/// Per pixel: surface point, normal, ray parameter.
struct Geometry {
    hits: Vec<([f64; 3], [f64; 3], f64)>,
}

fn geometry(cam: &PinholeCamera, ground_z: f64, with_box: bool) -> Geometry {
    let hits = (0..W * H)
        .map(|idx| {
            let (o, d) = cam.ray(idx % W, idx / W);
            first_hit(o, d, ground_z, with_box)
        })
        .collect();
    Geometry { hits }
}

/// Analytic MDF: distance along the ray from z = REF_H to the surface.
fn true_mdf(cam: &PinholeCamera, g: &Geometry) -> Vec<f64> {
    (0..W * H)
        .map(|idx| {
            let (o, d) = cam.ray(idx % W, idx / W);
            g.hits[idx].2 - (REF_H - o[2]) / d[2]
        })
        .collect()
}

/// Is the pixel's surface point lit by the source (ever, in a sweep)?
fn lit_mask(g: &Geometry, s: &Source) -> Vec<bool> {
    g.hits
        .iter()
        .map(|&(p, n, _)| dot(n, sub(s.emitter, p)) > 0.0 && !shadowed(p, n, s.emitter))
        .collect()
}

fn render(g: &Geometry, s: &Source, lit: &[bool], plane: &LaserPlane, rng: &mut Rng) -> Image {
    let sigma = LASER_FWHM / 2.355;
    let mut img = Image::new(W, H, 1);
    for (idx, v) in img.data.iter_mut().enumerate() {
        let (p, n, _) = g.hits[idx];
        let mut value = AMBIENT;
        if lit[idx] {
            let dist = dot(plane.normal, p) - plane.offset;
            let l = unit(sub(s.emitter, p));
            value += LASER_POWER * dot(n, l) * (-0.5 * (dist / sigma).powi(2)).exp();
        }
        value += NOISE * rng.gauss();
        *v = value as f32;
    }
    img
}

/// Sweep positions on the turntable (metres along `h`).
fn sweep() -> Vec<f64> {
    let n = 181;
    (0..n)
        .map(|k| -0.036 + 0.072 * k as f64 / (n - 1) as f64)
        .collect()
}

/// Image line of the plane ∩ {z = z0}: distance of pixel `q` from it.
fn true_line_distance(
    cam: &PinholeCamera,
    s: &Source,
    plane: &LaserPlane,
    z0: f64,
    q: [f64; 2],
) -> f64 {
    // A point on the 3-D line: on the plane, z = z0, along h.
    let nh = dot(plane.normal, s.h);
    let c = (plane.offset - plane.normal[2] * z0) / nh;
    let p0 = add(scale(s.h, c), [0.0, 0.0, z0]);
    let a = cam.project(add(p0, scale(s.u, -0.02))).unwrap();
    let b = cam.project(add(p0, scale(s.u, 0.02))).unwrap();
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let len = dx.hypot(dy);
    ((q[0] - a[0]) * dy - (q[1] - a[1]) * dx).abs() / len
}

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    dot(unit(a), unit(b)).abs().min(1.0).acos().to_degrees()
}

#[test]
fn line_detection_within_a_tenth_of_a_pixel() {
    let cam = camera();
    let g = geometry(&cam, 0.0, false);
    let mut rng = Rng(7);
    for (az, c, expected_axis) in [
        (90.0, 0.004, ScanAxis::Rows),
        (0.0, -0.003, ScanAxis::Columns),
    ] {
        let s = source(az);
        let lit = lit_mask(&g, &s);
        let plane = plane_at(&s, c);
        let img = render(&g, &s, &lit, &plane, &mut rng);
        let fit = detect_line(&img, [0, 0, W, H], 1.0, 0.2).unwrap();
        let (a, b) = fit.endpoints();
        let err = true_line_distance(&cam, &s, &plane, 0.0, a)
            .max(true_line_distance(&cam, &s, &plane, 0.0, b));
        eprintln!(
            "line detection, source azimuth {az}°: {} points ({} rejected), rms {:.4} px, max error vs truth {:.4} px, scan {:?}",
            fit.points.len(),
            fit.rejected,
            fit.rms_px,
            err,
            fit.scan
        );
        assert_eq!(fit.scan, expected_axis);
        assert!(fit.points.len() > 60);
        assert!(err < 0.1, "line error {err} px");
    }
    // A dark reference region has no line: a typed error, not a panic.
    let dark = Image::new(W, H, 1);
    assert!(matches!(
        detect_line(&dark, [0, 0, W, H], 1.0, 0.2),
        Err(MdfError::NoLine { .. })
    ));
    assert!(matches!(
        detect_line(&dark, [0, 0, W + 1, H], 1.0, 0.2),
        Err(MdfError::InvalidInput(_))
    ));
}

#[test]
fn two_height_calibration_recovers_the_plane() {
    let cam = camera();
    let h = 0.010;
    let mut rng = Rng(11);
    for az in [90.0, 30.0] {
        let s = source(az);
        let plane = plane_at(&s, 0.002);
        let mut fits = Vec::new();
        for z in [0.0, h] {
            let g = geometry(&cam, z, false);
            let lit = lit_mask(&g, &s);
            let img = render(&g, &s, &lit, &plane, &mut rng);
            fits.push(detect_line(&img, [0, 0, W, H], 1.0, 0.2).unwrap());
        }
        let cal = calibrate_plane(&cam, &fits[0], &fits[1], h).unwrap();
        let err = angle_deg(cal.plane.normal, plane.normal);
        let true_tilt = plane.normal[2].abs().acos().to_degrees();
        let origin_err = (cal.plane.distance([0.0, 0.0, 0.0]).abs()
            - plane.distance([0.0, 0.0, 0.0]).abs())
        .abs();
        eprintln!(
            "calibration az {az}°: normal error {err:.4}°, tilt {:.3}° (true {true_tilt:.3}°), offset error {:.2} µm, residual {:.2} µm, line angle {:.3}°",
            cal.tilt_deg,
            origin_err * 1e6,
            cal.residual_m * 1e6,
            cal.line_angle_deg
        );
        assert!(err < 0.1, "plane angle error {err}°");
        assert!((cal.tilt_deg - true_tilt).abs() < 0.1);
        assert!(origin_err < 20e-6);
        // The calibrated tilt turns another frame's reference line into its
        // plane (Wang et al.'s per-frame step); a nearby plane of the same
        // rotating emitter is within a small fraction of a degree.
        let plane2 = plane_at(&s, -0.004);
        let g = geometry(&cam, 0.0, false);
        let lit = lit_mask(&g, &s);
        let img = render(&g, &s, &lit, &plane2, &mut rng);
        let line = detect_line(&img, [0, 0, W, H], 1.0, 0.2).unwrap();
        let p2 =
            plane_from_line(&cam, &line, 0.0, PlaneConstraint::CalibratedTilt(cal.plane)).unwrap();
        let e2 = angle_deg(p2.normal, plane2.normal);
        let p3 =
            plane_from_line(&cam, &line, 0.0, PlaneConstraint::ThroughEmitter(s.emitter)).unwrap();
        let e3 = angle_deg(p3.normal, plane2.normal);
        eprintln!("  per-frame plane: calibrated tilt {e2:.4}°, through emitter {e3:.4}°");
        assert!(e2 < 1.0 && e3 < 0.1);
    }
    // Degenerate inputs are typed errors.
    let g = geometry(&cam, 0.0, false);
    let s = source(90.0);
    let lit = lit_mask(&g, &s);
    let img = render(&g, &s, &lit, &plane_at(&s, 0.0), &mut rng);
    let fit = detect_line(&img, [0, 0, W, H], 1.0, 0.2).unwrap();
    assert!(matches!(
        calibrate_plane(&cam, &fit, &fit, 0.0),
        Err(MdfError::DegenerateCalibration(_))
    ));
    let s2 = source(0.0);
    let lit2 = lit_mask(&g, &s2);
    let img2 = render(&g, &s2, &lit2, &plane_at(&s2, 0.0), &mut rng);
    let fit2 = detect_line(&img2, [0, 0, W, H], 1.0, 0.2).unwrap();
    assert!(matches!(
        calibrate_plane(&cam, &fit, &fit2, 0.01),
        Err(MdfError::DegenerateCalibration(_))
    ));
}

struct Scan {
    frames: Vec<Image>,
    planes: Vec<LaserPlane>,
    lit: Vec<bool>,
}

fn scan(g: &Geometry, s: &Source, seed: u64) -> Scan {
    let lit = lit_mask(g, s);
    let mut rng = Rng(seed);
    let planes: Vec<LaserPlane> = sweep().iter().map(|&c| plane_at(s, c)).collect();
    let frames = planes
        .iter()
        .map(|p| render(g, s, &lit, p, &mut rng))
        .collect();
    Scan {
        frames,
        planes,
        lit,
    }
}

/// Mean and 95th percentile absolute error (mm) over measured pixels,
/// and the measured fraction.
fn score(d: &DisplacementImage, truth: &[f64]) -> (f64, f64, f64) {
    let mut errs: Vec<f64> = d
        .depth
        .iter()
        .zip(truth)
        .filter(|(v, _)| **v >= 0.0)
        .map(|(v, t)| (f64::from(*v) - t).abs() * 1e3)
        .collect();
    errs.sort_by(f64::total_cmp);
    let mean = errs.iter().sum::<f64>() / errs.len().max(1) as f64;
    let p95 = errs.get(errs.len() * 95 / 100).copied().unwrap_or(f64::NAN);
    (mean, p95, errs.len() as f64 / d.depth.len() as f64)
}

#[test]
fn space_time_depth_matches_the_analytic_mdf() {
    let cam = camera();
    let g = geometry(&cam, 0.0, true);
    let truth = true_mdf(&cam, &g);
    let s = source(90.0);
    let sc = scan(&g, &s, 3);
    // Full pipeline: each frame's plane from its line in the reference
    // bands (top and bottom rows show only the turntable) and the emitter.
    let bands = [[0, 0, W, 18], [0, H - 18, W, H]];
    let mut frames = Vec::new();
    let mut planes = Vec::new();
    let mut plane_errs = Vec::new();
    for (f, truth_plane) in sc.frames.iter().zip(&sc.planes) {
        let Ok(line) = detect_line_in_regions(f, &bands, 1.0, 0.2) else {
            continue;
        };
        let p =
            plane_from_line(&cam, &line, 0.0, PlaneConstraint::ThroughEmitter(s.emitter)).unwrap();
        plane_errs.push(angle_deg(p.normal, truth_plane.normal));
        frames.push(f.clone());
        planes.push(p);
    }
    plane_errs.sort_by(f64::total_cmp);
    let plane_err = plane_errs.last().copied().unwrap_or(f64::NAN);
    let plane_med = plane_errs
        .get(plane_errs.len() / 2)
        .copied()
        .unwrap_or(f64::NAN);
    let opts = SpaceTimeOptions::new(0.2, REF_H, MAX_DEPTH);
    let (d, stats) = space_time(&frames, &planes, &cam, &opts).unwrap();
    let (mean, p95, valid) = score(&d, &truth);
    // With the true planes and without sub-frame interpolation, for scale.
    let (d_true, _) = space_time(&sc.frames, &sc.planes, &cam, &opts).unwrap();
    let (mean_t, _, _) = score(&d_true, &truth);
    let coarse = SpaceTimeOptions {
        subframe: false,
        ..opts
    };
    let (d_coarse, _) = space_time(&sc.frames, &sc.planes, &cam, &coarse).unwrap();
    let (mean_c, _, _) = score(&d_coarse, &truth);
    eprintln!(
        "space-time (az 90°, {} of {} frames with a detected line, plane error median {plane_med:.4}°, worst {plane_err:.4}°): mean |error| {mean:.4} mm, p95 {p95:.4} mm, valid {:.1} %; true planes {mean_t:.4} mm; without sub-frame {mean_c:.4} mm; stats {stats:?}",
        frames.len(),
        sc.frames.len(),
        valid * 100.0
    );
    assert!(mean < 0.1, "mean depth error {mean} mm");
    assert!(p95 < 0.2, "p95 depth error {p95} mm");
    assert!(mean_t < mean_c, "sub-frame interpolation should help");
    // Every pixel whose surface point the laser never reaches is −1, and
    // there are such pixels (the box's shadow).
    let shadowed = sc.lit.iter().filter(|l| !**l).count();
    assert!(shadowed > 100, "{shadowed} shadowed pixels");
    for (idx, l) in sc.lit.iter().enumerate() {
        if !l {
            assert_eq!(d.depth[idx], NO_DEPTH, "pixel {idx} is occluded");
            assert_eq!(d.weight[idx], 0.0);
        }
    }
    assert!(d.depth.iter().chain(&d.weight).all(|v| v.is_finite()));
    assert!(d
        .depth
        .iter()
        .all(|&v| v == NO_DEPTH || (0.0..=MAX_DEPTH as f32).contains(&v)));
    assert!(valid > 0.8);
}

#[test]
fn more_laser_positions_fill_occlusions_and_lower_the_error() {
    let cam = camera();
    let g = geometry(&cam, 0.0, true);
    let truth = true_mdf(&cam, &g);
    let azimuths = [90.0, -90.0, 180.0, 0.0, 45.0];
    let opts = SpaceTimeOptions::new(0.2, REF_H, MAX_DEPTH);
    let mut images = Vec::new();
    let mut sources = Vec::new();
    for (k, &az) in azimuths.iter().enumerate() {
        let s = source(az);
        let sc = scan(&g, &s, 100 + k as u64);
        let (d, _) = space_time(&sc.frames, &sc.planes, &cam, &opts).unwrap();
        let w = wang_source_weight(s.emitter, cam.centre, 0.05).unwrap();
        let (m, _, v) = score(&d, &truth);
        eprintln!("source az {az:>5}°: tetrahedron weight {:.3e} m³, alone: mean |error| {m:.4} mm, valid {:.1} %", w, v * 100.0);
        images.push(d);
        sources.push(s.emitter);
    }
    eprintln!("MDF depth error vs the number of laser positions (seed weights):");
    let mut table: Vec<(f64, f64)> = Vec::new();
    // Pixels measured with one position: the error there isolates the
    // effect of averaging from that of filling occlusions.
    let common: Vec<bool> = images[0].depth.iter().map(|&v| v >= 0.0).collect();
    for n in 1..=azimuths.len() {
        let merged = merge(&images[..n], &sources[..n], &cam, 0.05, false).unwrap();
        let (mean, p95, valid) = score(&merged, &truth);
        let on_common: Vec<f64> = merged
            .depth
            .iter()
            .zip(&truth)
            .zip(&common)
            .filter(|((v, _), c)| **c && **v >= 0.0)
            .map(|((v, t), _)| (f64::from(*v) - t).abs() * 1e3)
            .collect();
        let mean_common = on_common.iter().sum::<f64>() / on_common.len().max(1) as f64;
        let conf = merge(&images[..n], &sources[..n], &cam, 0.05, true).unwrap();
        let (mean_c, _, _) = score(&conf, &truth);
        eprintln!(
            "  {n} position(s): mean |error| {mean:.4} mm, p95 {p95:.4} mm, valid {:.2} %, on the 1-position pixels {mean_common:.4} mm (seed × pixel confidence: {mean_c:.4} mm)",
            valid * 100.0
        );
        if n > 1 {
            assert!(
                mean_common < table[0].0,
                "averaging must help on common pixels"
            );
        }
        assert!(merged
            .depth
            .iter()
            .chain(&merged.weight)
            .all(|v| v.is_finite()));
        table.push((mean, valid));
    }
    let (e1, v1) = table[0];
    let (e5, v5) = table[4];
    assert!(v5 > v1 + 0.02, "valid fraction {v1} → {v5}");
    assert!(e5 < e1, "error {e1} → {e5} mm");
    assert!(e5 < 0.1);
    // A pixel with no valid source stays −1.
    let all_missing: Vec<DisplacementImage> = images
        .iter()
        .map(|d| DisplacementImage {
            depth: vec![NO_DEPTH; d.depth.len()],
            weight: vec![0.0; d.depth.len()],
            ..d.clone()
        })
        .collect();
    let m = merge(&all_missing, &sources, &cam, 0.05, false).unwrap();
    assert!(m.depth.iter().all(|&v| v == NO_DEPTH));
}

#[test]
fn seed_weight_vanishes_when_the_camera_is_in_the_laser_plane() {
    let cam = camera();
    // Source on the far side of the camera along the same line from the
    // turntable centre: the camera lies in the plane of the source and the
    // strip through the centre.
    let w0 = wang_source_weight(scale(cam.centre, 2.0), cam.centre, 0.05).unwrap();
    let w1 = wang_source_weight(source(90.0).emitter, cam.centre, 0.05).unwrap();
    eprintln!("tetrahedron weight: camera in the plane {w0:.3e}, source at 90° {w1:.3e}");
    assert!(w0 < 1e-12 * w1.max(1e-30) + 1e-18);
    assert!(w1 > 0.0);
    assert!(wang_source_weight([0.0, 0.0, 1.0], cam.centre, 0.05).is_err());
}

#[test]
fn grazing_plane_is_detected_and_downweighted() {
    let cam = camera();
    let (i, j) = (80usize, 60usize);
    let (o, d) = cam.ray(i, j);
    // Planes containing a direction ⟂ to the ray, rotated about it so the
    // ray makes `angle` with the plane.
    let perp = unit(cross(d, [0.0, 1.0, 0.0]));
    let plane_with_angle = |angle_deg: f64| {
        let a = angle_deg.to_radians();
        // Normal ⟂ axis, making angle (90° − a) with d.
        let n = unit(add(scale(perp, a.cos()), scale(d, a.sin())));
        let p = add(o, scale(d, 0.3));
        LaserPlane::through(p, n).unwrap()
    };
    // Five frames, the pixel lit in the middle one only.
    let mut frames: Vec<Image> = (0..5).map(|_| Image::new(W, H, 1)).collect();
    frames[2].set(i, j, 0, 0.9);
    let opts = SpaceTimeOptions::new(0.2, REF_H, MAX_DEPTH);
    let mut results = Vec::new();
    for angle in [0.01, 2.0, 4.0, 10.0, 30.0] {
        let plane = plane_with_angle(angle);
        let (img, stats) = space_time(&frames, &[plane; 5], &cam, &opts).unwrap();
        let idx = j * W + i;
        // The unguarded triangulation would be this far from the
        // reference plane.
        let (t, _) = plane.intersect(o, d).unwrap();
        eprintln!(
            "ray–plane angle {angle:>5}°: depth {:.4} mm, weight {:.4}, stats {stats:?}",
            img.depth[idx] * 1e3,
            img.weight[idx]
        );
        let _ = t;
        assert!(img
            .depth
            .iter()
            .all(|v| v.is_finite() && *v <= MAX_DEPTH as f32));
        results.push((img.depth[idx], img.weight[idx], stats));
    }
    assert_eq!(results[0].0, NO_DEPTH);
    assert_eq!(results[0].1, 0.0);
    assert_eq!(results[0].2.grazing, 1);
    assert_eq!(results[1].2.grazing, 1);
    // Above the limit the weight rises continuously from ~0.
    assert!(results[2].1 > 0.0 && results[2].1 < results[3].1 && results[3].1 < results[4].1);
    assert!(results[2].1 < 0.05);
    // A plane through the reference point far below: out of range, not a
    // huge depth.
    let far = LaserPlane::through(add(o, scale(d, 5.0)), plane_with_angle(30.0).normal).unwrap();
    let (img, stats) = space_time(&frames, &[far; 5], &cam, &opts).unwrap();
    assert_eq!(img.depth[j * W + i], NO_DEPTH);
    assert_eq!(stats.out_of_range, 1);
}

#[test]
fn dark_frames_give_all_minus_one() {
    let cam = camera();
    let s = source(90.0);
    let frames: Vec<Image> = (0..5).map(|_| Image::new(W, H, 1)).collect();
    let planes: Vec<LaserPlane> = (0..5).map(|k| plane_at(&s, 0.001 * k as f64)).collect();
    let (d, stats) = space_time(
        &frames,
        &planes,
        &cam,
        &SpaceTimeOptions::new(0.2, REF_H, MAX_DEPTH),
    )
    .unwrap();
    assert!(d.depth.iter().all(|&v| v == NO_DEPTH));
    assert!(d.weight.iter().all(|&v| v == 0.0));
    assert_eq!(stats.dark, W * H);
    let codes = quantise_depth(&d, MAX_DEPTH).unwrap();
    assert!(codes.iter().all(|&c| c == NO_DEPTH_CODE));
    // NaN frames read as dark too.
    let nan: Vec<Image> = (0..5)
        .map(|_| Image {
            width: W,
            height: H,
            channels: 1,
            data: vec![f32::NAN; W * H],
        })
        .collect();
    let (d, _) = space_time(
        &nan,
        &planes,
        &cam,
        &SpaceTimeOptions::new(0.2, REF_H, MAX_DEPTH),
    )
    .unwrap();
    assert!(d.depth.iter().all(|&v| v == NO_DEPTH));
}

#[test]
fn mismatched_inputs_are_typed_errors() {
    let cam = camera();
    let s = source(90.0);
    let opts = SpaceTimeOptions::new(0.2, REF_H, MAX_DEPTH);
    let frames: Vec<Image> = (0..3).map(|_| Image::new(W, H, 1)).collect();
    let planes: Vec<LaserPlane> = (0..2).map(|k| plane_at(&s, 0.001 * k as f64)).collect();
    assert!(matches!(
        space_time(&frames, &planes, &cam, &opts),
        Err(MdfError::FrameCount {
            frames: 3,
            planes: 2
        })
    ));
    let mut bad = frames.clone();
    bad[1] = Image::new(W - 1, H, 1);
    let planes3: Vec<LaserPlane> = (0..3).map(|k| plane_at(&s, 0.001 * k as f64)).collect();
    assert!(matches!(
        space_time(&bad, &planes3, &cam, &opts),
        Err(MdfError::FrameSize { index: 1, .. })
    ));
    let mut short = frames.clone();
    short[2].data.pop();
    assert!(matches!(
        space_time(&short, &planes3, &cam, &opts),
        Err(MdfError::InvalidInput(_))
    ));
    let mut nan_plane = planes3.clone();
    nan_plane[0].normal = [f64::NAN, 0.0, 1.0];
    assert!(matches!(
        space_time(&frames, &nan_plane, &cam, &opts),
        Err(MdfError::InvalidPlane { index: 0, .. })
    ));
    assert!(matches!(
        space_time(&[], &[], &cam, &opts),
        Err(MdfError::InvalidInput(_))
    ));
    let bad_opts = SpaceTimeOptions {
        max_depth: -1.0,
        ..opts
    };
    assert!(space_time(&frames, &planes3, &cam, &bad_opts).is_err());
    let mut bad_cam = cam;
    bad_cam.focal_px = 0.0;
    assert!(matches!(
        space_time(&frames, &planes3, &bad_cam, &opts),
        Err(MdfError::InvalidCamera(_))
    ));

    let d = DisplacementImage {
        width: W,
        height: H,
        depth: vec![0.001; W * H],
        weight: vec![1.0; W * H],
    };
    let small = DisplacementImage {
        width: 2,
        height: 2,
        depth: vec![0.0; 4],
        weight: vec![1.0; 4],
    };
    assert!(matches!(
        merge(
            &[d.clone(), small],
            &[s.emitter, s.emitter],
            &cam,
            0.05,
            false
        ),
        Err(MdfError::DisplacementSize { index: 1, .. })
    ));
    assert!(matches!(
        merge(
            std::slice::from_ref(&d),
            &[s.emitter, s.emitter],
            &cam,
            0.05,
            false
        ),
        Err(MdfError::SourceCount {
            count: 1,
            sources: 2
        })
    ));
    assert!(matches!(
        merge_weighted(std::slice::from_ref(&d), &[f64::NAN], false),
        Err(MdfError::InvalidInput(_))
    ));
    assert!(merge_weighted(&[], &[], false).is_err());
    assert!(quantise_depth(&d, 0.0).is_err());
    assert!(PinholeCamera::looking_at_origin([0.0; 3], 0.3, 800.0, W, H).is_err());
}

#[test]
fn quantised_and_float_outputs_round_trip() {
    let mut d = DisplacementImage {
        width: 4,
        height: 3,
        depth: (0..12).map(|k| k as f32 * 0.0015).collect(),
        weight: vec![1.0; 12],
    };
    d.depth[5] = NO_DEPTH;
    d.weight[5] = 0.0;
    let max = 0.012;
    let codes = quantise_depth(&d, max).unwrap();
    let back = dequantise_depth(&codes, max);
    for (k, (a, b)) in d.depth.iter().zip(&back).enumerate() {
        if k == 5 {
            assert_eq!(codes[k], NO_DEPTH_CODE);
            assert_eq!(*b, NO_DEPTH);
        } else if f64::from(*a) <= max {
            assert!(
                ((a - b).abs() as f64) <= max / 254.0 / 2.0 + 1e-9,
                "{a} vs {b}"
            );
        } else {
            assert_eq!(codes[k], MAX_DEPTH_CODE);
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let (npy, png) = (dir.path().join("d.npy"), dir.path().join("d.png"));
    write_displacement(&d, &npy, &png, max).unwrap();
    let arr = rigd_process::npy::read_f32(&npy).unwrap();
    assert_eq!(arr.shape, vec![3, 4]);
    assert_eq!(arr.data, d.depth);
    let img = rigd_process::image_io::load_png(&png).unwrap();
    assert_eq!(rigd_process::rectify::codes8(&img), codes);
}

proptest! {
    // No regression files: integration tests have no lib.rs for proptest to sit beside.
    #![proptest_config(ProptestConfig { cases: 256, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn ray_plane_triangulation_round_trips(
        x in 0.0f64..160.0, y in 0.0f64..120.0, t in 0.1f64..1.0,
        nx in -1.0f64..1.0, ny in -1.0f64..1.0, nz in -1.0f64..1.0,
    ) {
        let cam = camera();
        let (o, d) = cam.ray_at(x, y);
        let p = add(o, scale(d, t));
        let n = [nx, ny, nz];
        prop_assume!(dot(n, n) > 0.01);
        let n = unit(n);
        prop_assume!(dot(n, d).abs() > 0.05);
        let plane = LaserPlane::through(p, n).unwrap();
        let q = cam.project(p).unwrap();
        prop_assert!((q[0] - x).abs() < 1e-9 && (q[1] - y).abs() < 1e-9);
        let (o2, d2) = cam.ray_at(q[0], q[1]);
        let (t2, _) = plane.intersect(o2, d2).unwrap();
        let p2 = add(o2, scale(d2, t2));
        let err = sub(p2, p);
        prop_assert!(dot(err, err).sqrt() < 1e-9, "{:?} vs {:?}", p2, p);
    }
}
