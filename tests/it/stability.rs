//! Numerical stability across the codebase: one named test per hard case,
//! each checking every numeric output for NaN and infinity, plus round-trip
//! properties.
//!
//! Hard cases:
//!  1. the pole θ = 0, where φ is undefined (geometry, pose solver, direction
//!     table interpolation);
//!  2. grazing θ = 85° and 89.9° (pose solver, interpolation, scene renderer);
//!  3. the φ wrap at 360° (interpolation continuity, pose solver);
//!  4. l = v, the Ward specular peak (`true_btf`, `render_linear`);
//!  5. the gonio arm's wrist singularity (pitch 0: roll and twist aligned);
//!  6. near-coplanar photometric-stereo lights, condition number 1e3 and 1e8;
//!  7. rank-deficient and constant PCA input (`compress_slot`);
//!  8. Levenberg–Marquardt fits of lobes with exponent 1e4, on and between
//!     lights;
//!  9. a laser plane nearly parallel to the view ray (`space_time`), and
//!     laser tilts near the horizon (`LaserGeometry`);
//! 10. 12-bit saturation (renderer) and 8-bit quantisation of values > 1;
//! 11. an empty plan;
//! 12. a single-step plan;
//! 13. a very long run: a 100 000-step plan, with time and memory reported.
//!
//! Properties: `Direction` vector round trip, laser tilt ↔ offset round
//! trip, `.npy` F32 (exact) and F16 (relative 2⁻¹¹) round trips.

use std::time::Instant;

use proptest::prelude::*;
use rigd::kinematics::{PoseSolution, Solver};
use rigd::model::profile::Profile;
use rigd::plan::laser::LaserGeometry;
use rigd::plan::Order;
use rigd::plan::{Pair, Plan};
use rigd::schedule::order::OrderReport;
use rigd::schedule::timing::Timing;
use rigd::schedule::{self, Schedule};
use rigd_core::geometry::{Direction, Vec3};
use rigd_process::btf::{compress_slot, SlotPca, TextureShape};
use rigd_process::directions::{self as pdir, DirectionTable, Interpolation};
use rigd_process::image_io::Image;
use rigd_process::mdf::{space_time, LaserPlane, PinholeCamera, SpaceTimeOptions, NO_DEPTH};
use rigd_process::npy::{self, Dtype};
use rigd_process::photometric_stereo::{solve_images, PsError, PsOptions, PsResult};
use rigd_process::rectify::{codes8, quantise, Quantisation};
use rigd_process::reflectance_fit::{
    fit_slot, fit_texel, FitOptions, Lobe, LobeModel, TexelFit, MAX_EXPONENT,
};
use rigd_sim::scene::{EffectSwitches, Scene, Shot};

// ------------------------------------------------------------------ helpers

/// True when every value is neither NaN nor infinite.
fn all_finite(xs: impl IntoIterator<Item = f64>) -> bool {
    xs.into_iter().all(f64::is_finite)
}

fn all_finite_f32(xs: &[f32]) -> bool {
    all_finite(xs.iter().map(|&x| f64::from(x)))
}

fn profile(name: &str) -> Profile {
    Profile::load(name).unwrap()
}

fn solver(name: &str) -> Solver {
    Solver::new(&profile(name)).unwrap()
}

fn bonn() -> Solver {
    solver("bonn-gonioreflectometer")
}

fn msra() -> Solver {
    solver("msra-btf-mdf")
}

fn d(theta: f64, phi: f64) -> Direction {
    Direction::new(theta, phi)
}

/// Every number a pose solution carries.
fn pose_numbers(sol: &PoseSolution) -> Vec<f64> {
    let mut out = vec![
        sol.achieved_light.theta_deg,
        sol.achieved_light.phi_deg,
        sol.achieved_view.theta_deg,
        sol.achieved_view.phi_deg,
    ];
    out.extend(sol.setpoints.axes.values().copied());
    out.extend(sol.setpoints.arm.iter().flatten().copied());
    out.extend(sol.setpoints.plate_mm);
    out
}

/// Finite set-points, and either feasible or with a reason; forward
/// kinematics agrees and is finite too.
fn assert_sane_pose(s: &Solver, sol: &PoseSolution, what: &str) {
    assert!(all_finite(pose_numbers(sol)), "{what}: {sol:?}");
    assert_eq!(sol.feasible, sol.reason.is_none(), "{what}: {sol:?}");
    let (l, v) = s.forward(&sol.setpoints, &sol.camera).unwrap();
    assert!(
        all_finite([l.theta_deg, l.phi_deg, v.theta_deg, v.phi_deg]),
        "{what}: forward {l:?} {v:?}"
    );
}

/// Distance between two angles modulo whole turns, degrees.
fn mod_dist(a: f64, b: f64) -> f64 {
    let r = (a - b).rem_euclid(360.0);
    r.min(360.0 - r)
}

/// The H1 directions of the plan module, as the processing crate's type.
fn h1_table() -> DirectionTable {
    let dirs = rigd::plan::h1()
        .into_iter()
        .map(|x| pdir::Direction::new(x.theta_deg, x.phi_deg))
        .collect();
    DirectionTable::new(dirs).unwrap()
}

/// Non-negative finite weights summing to 1.
fn assert_sane_weights(w: &Interpolation, what: &str) {
    assert!(!w.entries().is_empty(), "{what}");
    assert!(all_finite(w.entries().iter().map(|e| e.1)), "{what}: {w:?}");
    assert!(w.entries().iter().all(|e| e.1 >= 0.0), "{what}: {w:?}");
    let sum: f64 = w.entries().iter().map(|e| e.1).sum();
    assert!((sum - 1.0).abs() < 1e-12, "{what}: sum {sum}");
}

/// Σ|a_i − b_i| over the union of the entries.
fn weight_distance(a: &Interpolation, b: &Interpolation) -> f64 {
    let mut idx: Vec<usize> = a.entries().iter().chain(b.entries()).map(|e| e.0).collect();
    idx.sort_unstable();
    idx.dedup();
    idx.iter()
        .map(|&i| (a.weight_of(i) - b.weight_of(i)).abs())
        .sum()
}

fn shot(light: Vec3, view: Vec3) -> Shot {
    Shot {
        light,
        view,
        width: 48,
        height: 32,
        ..Shot::default()
    }
}

fn schedule_numbers(s: &Schedule) -> Vec<f64> {
    let mut out = Vec::new();
    for img in &s.images {
        for dir in [img.light, img.view, img.achieved_light, img.achieved_view] {
            out.push(dir.theta_deg);
            out.push(dir.phi_deg);
        }
    }
    for t in &s.triggers {
        out.extend(t.setpoints.axes.values().copied());
        out.extend(t.setpoints.arm.iter().flatten().copied());
    }
    out
}

fn report_numbers(r: &OrderReport) -> [f64; 3] {
    [r.naive_s, r.optimised_s, r.lower_bound_s]
}

// --------------------------------------------------------- 1. the pole

#[test]
fn pole_theta_0_phi_undefined() {
    // Geometry: any φ at θ = 0 is the normal, and back it reads φ = 0.
    for phi in [0.0, 90.0, 271.0, 359.999, -45.0, 1e6] {
        let v = d(0.0, phi).to_vector();
        assert!(all_finite(v), "φ = {phi}: {v:?}");
        assert_eq!(v, [0.0, 0.0, 1.0], "φ = {phi}");
        let back = Direction::from_vector(v);
        assert_eq!((back.theta_deg, back.phi_deg), (0.0, 0.0), "φ = {phi}");
    }
    // Nearly the pole, the zero vector and the antipode stay finite.
    for v in [
        [1e-15, 0.0, 1.0],
        [-1e-300, 1e-300, 1.0],
        [0.0, 0.0, 0.0],
        [0.0, 0.0, -1.0],
        [0.0, 0.0, 1e-300],
        [f64::MIN_POSITIVE, 0.0, f64::MIN_POSITIVE],
    ] {
        let back = Direction::from_vector(v);
        assert!(
            all_finite([back.theta_deg, back.phi_deg]),
            "{v:?}: {back:?}"
        );
        assert!((0.0..360.0).contains(&back.phi_deg), "{v:?}: {back:?}");
    }
    assert_eq!(Direction::from_vector([1e-15, 0.0, 1.0]).phi_deg, 0.0);

    // Pose solver: the view at the pole gives the same finite pose for any φ.
    let s = bonn();
    let light = d(40.0, 30.0);
    let first = s.solve(light, d(0.0, 0.0));
    assert!(first.feasible, "{:?}", first.reason);
    for phi in [0.0, 90.0, 271.0, 359.999, -180.0] {
        let sol = s.solve(light, d(0.0, phi));
        assert_sane_pose(&s, &sol, &format!("view φ = {phi}"));
        assert_eq!(sol.setpoints, first.setpoints, "view φ = {phi}");
        assert_eq!(sol.achieved_view.theta_deg, first.achieved_view.theta_deg);
    }

    // Interpolation: a query at the pole is independent of φ.
    let table = h1_table();
    let w0 = table.interpolate(pdir::Direction::new(0.0, 0.0)).unwrap();
    assert_sane_weights(&w0, "θ = 0, φ = 0");
    for phi in [90.0, 271.0] {
        let w = table.interpolate(pdir::Direction::new(0.0, phi)).unwrap();
        assert_sane_weights(&w, &format!("θ = 0, φ = {phi}"));
        assert_eq!(w, w0, "φ = {phi}");
    }
    // H1 has a sample at the pole: it takes the whole weight.
    assert_eq!(w0.entries(), &[(0, 1.0)]);
}

// ------------------------------------------------------- 2. grazing θ

#[test]
fn grazing_85_and_89_9_pose_solver() {
    for (name, s) in [("bonn", bonn()), ("msra", msra())] {
        for theta in [85.0, 89.9] {
            for phi in [0.0, 45.0, 180.0, 359.9] {
                for (l, v) in [
                    (d(theta, phi), d(30.0, phi + 180.0)),
                    (d(30.0, phi + 180.0), d(theta, phi)),
                    (d(theta, phi), d(theta, phi + 150.0)),
                    (d(theta, phi), d(0.0, 0.0)),
                ] {
                    let sol = s.solve(l, v);
                    assert_sane_pose(&s, &sol, &format!("{name} {l:?} {v:?}"));
                }
            }
        }
    }
    // Bonn's pitch stops at 89°: 89.9 is refused with a reason, not NaN.
    let s = bonn();
    let sol = s.solve(d(89.9, 10.0), d(40.0, 190.0));
    assert!(!sol.feasible);
    assert!(sol.reason.as_deref().unwrap().contains("pitch"), "{sol:?}");
}

#[test]
fn grazing_85_and_89_9_interpolation() {
    let h1 = h1_table();
    let h2 = DirectionTable::new(pdir::h2()).unwrap();
    for theta in [85.0, 89.9, 90.0] {
        for phi in [0.0, 7.5, 100.0, 359.9] {
            let q = pdir::Direction::new(theta, phi);
            let a = h1.interpolate(q).unwrap();
            assert_sane_weights(&a, &format!("H1 {q:?}"));
            // Beyond H1's 85° ring only that ring contributes.
            assert!(a.entries().len() <= 2, "{q:?}: {a:?}");
            let b = h2.interpolate(q).unwrap();
            assert_sane_weights(&b, &format!("H2 {q:?}"));
            // H2 ends at 75°: grazing queries use that ring alone.
            for &(i, _) in b.entries() {
                assert_eq!(h2.directions()[i].theta_deg, 75.0, "{q:?}");
            }
        }
    }
    // 89.9 and 85 on H1 give the same weights (no extrapolation).
    let a = h1.interpolate(pdir::Direction::new(85.0, 20.0)).unwrap();
    let b = h1.interpolate(pdir::Direction::new(89.9, 20.0)).unwrap();
    assert_eq!(a, b);
}

#[test]
fn grazing_89_9_scene_render() {
    let scene = Scene::load("corduroy").unwrap();
    for (l, v) in [
        (d(89.9, 0.0), d(89.9, 180.0)),
        (d(89.9, 0.0), d(89.9, 0.0)),
        (d(89.9, 90.0), d(89.9, 0.0)),
        (d(85.0, 30.0), d(89.9, 210.0)),
    ] {
        let s = shot(l.to_vector(), v.to_vector());
        let (linear, _) = scene.render_linear(&s);
        assert_eq!(linear.len(), 48 * 32);
        assert!(all_finite_f32(&linear), "{l:?} {v:?}");
        assert!(linear.iter().all(|&x| x >= 0.0), "{l:?} {v:?}");
        let frame = scene.render(&s);
        assert!(frame.pixels.iter().all(|&p| p <= 4095), "{l:?} {v:?}");
        // The ground truth at grazing angles is finite as well.
        for (x, y) in [(0.0, 0.0), (0.01, -0.01)] {
            let b = scene.true_btf(
                x,
                y,
                l.to_vector(),
                v.to_vector(),
                EffectSwitches::default(),
            );
            assert!(b.is_finite() && b >= 0.0, "{l:?} {v:?}: {b}");
        }
    }
}

// ------------------------------------------------------ 3. the φ wrap

#[test]
fn phi_wrap_at_360() {
    let table = h1_table();
    for theta in [17.0, 34.0, 40.0, 68.0, 85.0] {
        let a = table
            .interpolate(pdir::Direction::new(theta, 359.999))
            .unwrap();
        let b = table
            .interpolate(pdir::Direction::new(theta, 0.001))
            .unwrap();
        assert_sane_weights(&a, "φ = 359.999");
        assert_sane_weights(&b, "φ = 0.001");
        let gap = weight_distance(&a, &b);
        // Δφ = 0.002° against ring spacings of ≥ 15°.
        assert!(gap < 1e-3, "θ = {theta}: weights differ by {gap}");
        let at0 = table.interpolate(pdir::Direction::new(theta, 0.0)).unwrap();
        for phi in [360.0, 720.0, -360.0, -0.0] {
            let w = table.interpolate(pdir::Direction::new(theta, phi)).unwrap();
            assert!(weight_distance(&w, &at0) < 1e-12, "θ = {theta}, φ = {phi}");
        }
    }

    // Pose solver: φ = 360 is φ = 0 exactly; 359.999 and 0.001 are close.
    for (name, s) in [("bonn", bonn()), ("msra", msra())] {
        let fixed = d(40.0, 120.0);
        for theta in [30.0, 50.0] {
            let pairs = [
                ((d(theta, 0.0), fixed), (d(theta, 360.0), fixed)),
                ((fixed, d(theta, 0.0)), (fixed, d(theta, 360.0))),
            ];
            for ((l0, v0), (l1, v1)) in pairs {
                let a = s.solve(l0, v0);
                let b = s.solve(l1, v1);
                assert_sane_pose(&s, &a, name);
                assert_sane_pose(&s, &b, name);
                assert_eq!(a, b, "{name}: {l0:?} {v0:?}");
            }
            let a = s.solve(d(theta, 359.999), fixed);
            let b = s.solve(d(theta, 0.001), fixed);
            assert_sane_pose(&s, &a, name);
            assert_sane_pose(&s, &b, name);
            if a.feasible && b.feasible {
                for (k, x) in &a.setpoints.axes {
                    let y = b.setpoints.axes[k];
                    assert!(mod_dist(*x, y) < 0.5, "{name} axis {k}: {x} vs {y}");
                }
                for (x, y) in a
                    .setpoints
                    .arm
                    .iter()
                    .flatten()
                    .zip(b.setpoints.arm.iter().flatten())
                {
                    assert!(mod_dist(*x, *y) < 0.5, "{name} arm: {x} vs {y}");
                }
            }
        }
    }
}

// ----------------------------------------------------------- 4. l = v

#[test]
fn light_equals_view_ward_peak() {
    let scene = Scene::load("leather").unwrap();
    let [hx, hy] = scene.sample_half;
    let texels = [
        (0.0, 0.0),
        (0.3 * hx, -0.2 * hy),
        (-0.7 * hx, 0.6 * hy),
        (0.99 * hx, 0.99 * hy),
    ];
    for (theta, phi) in [
        (0.0, 0.0),
        (1e-9, 45.0),
        (20.0, 10.0),
        (45.0, 200.0),
        (85.0, 300.0),
        (89.9, 90.0),
    ] {
        let dir = d(theta, phi).to_vector();
        for &(x, y) in &texels {
            let b = scene.true_btf(x, y, dir, dir, EffectSwitches::default());
            assert!(b.is_finite() && b >= 0.0, "θ = {theta} at ({x}, {y}): {b}");
        }
        let (linear, _) = scene.render_linear(&shot(dir, dir));
        assert!(all_finite_f32(&linear), "θ = {theta}");
        assert!(linear.iter().all(|&x| x >= 0.0), "θ = {theta}");
    }
}

// ------------------------------------------------ 5. wrist singularity

#[test]
fn robot_wrist_singularity() {
    // Pitch = θ_l: at θ_l = 0 the roll and twist axes coincide.
    let s = bonn();
    for theta_l in [0.0, 1e-15, 1e-12, 1e-9, 1e-7, 1e-3] {
        for phi_l in [0.0, 90.0, 180.0, 271.3, 359.999] {
            for v in [d(85.0, 0.0), d(34.0, 200.0), d(12.5, 359.0), d(0.0, 0.0)] {
                let l = d(theta_l, phi_l);
                let sol = s.solve(l, v);
                assert_sane_pose(&s, &sol, &format!("{l:?} {v:?}"));
                let arm = sol.setpoints.arm.as_ref().unwrap();
                assert_eq!(arm.len(), 3);
                // |pitch| is θ_l.
                assert!((arm[1] - theta_l).abs() < 1e-9, "{arm:?}");
            }
        }
    }
}

// ------------------------------------ 6. near-coplanar PS light matrices

/// A shallow spherical cap (slopes below ~20°) with a varying albedo,
/// Lambertian under each light; returns the images and true normals.
fn ps_scene(lights: &[[f64; 3]], size: usize) -> (Vec<Image>, Vec<[f64; 3]>) {
    let radius = 1.5 * size as f64;
    let c = (size as f64 - 1.0) / 2.0;
    let mut normals = Vec::new();
    let mut albedo = Vec::new();
    for r in 0..size {
        for col in 0..size {
            let (x, y) = (col as f64 - c, c - r as f64);
            let z = (radius * radius - x * x - y * y).sqrt();
            normals.push([x / radius, y / radius, z / radius]);
            albedo.push(0.5 + 0.2 * (col as f64 * 0.3).sin());
        }
    }
    let images = lights
        .iter()
        .map(|l| {
            let len = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt();
            let mut img = Image::new(size, size, 1);
            for (k, n) in normals.iter().enumerate() {
                let s = (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]) / len;
                img.set(k % size, k / size, 0, (albedo[k] * s.max(0.0)) as f32);
            }
            img
        })
        .collect();
    (images, normals)
}

/// Two lights 30° off the normal at opposite azimuths and a third near the
/// normal tilted by `eps` out of their plane: condition number ≈ 1.58 / eps.
fn coplanar_lights(eps: f64) -> Vec<[f64; 3]> {
    let (s, c) = 30f64.to_radians().sin_cos();
    vec![[s, 0.0, c], [-s, 0.0, c], [0.0, eps, 1.0]]
}

fn ps_numbers(r: &PsResult) -> Vec<f64> {
    let mut out: Vec<f64> = r.normals.iter().flatten().map(|&x| f64::from(x)).collect();
    for values in [&r.albedo, &r.p, &r.q, &r.height_map] {
        out.extend(values.iter().map(|&x| f64::from(x)));
    }
    out.push(r.report.condition_number);
    out.push(r.report.mean_residual);
    out
}

fn mean_angle_deg(r: &PsResult, truth: &[[f64; 3]]) -> f64 {
    let mut sum = 0.0;
    for (n, t) in r.normals.iter().zip(truth) {
        let n = n.map(f64::from);
        let cos = (n[0] * t[0] + n[1] * t[1] + n[2] * t[2])
            / (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        sum += cos.clamp(-1.0, 1.0).acos().to_degrees();
    }
    sum / truth.len() as f64
}

#[test]
fn near_coplanar_photometric_stereo_lights() {
    let size = 24;
    // Condition number ~1e3: solves, with finite and accurate normals.
    let lights = coplanar_lights(1.6e-3);
    let (images, truth) = ps_scene(&lights, size);
    for robust in [false, true] {
        let opts = PsOptions {
            robust,
            ..PsOptions::default()
        };
        let r = solve_images(&images, &lights, None, &opts).unwrap();
        let cond = r.report.condition_number;
        eprintln!("cond ≈ 1e3 (robust {robust}): condition {cond:.3e}");
        assert!((5e2..5e3).contains(&cond), "{cond}");
        assert!(all_finite(ps_numbers(&r)), "robust {robust}");
        if !robust {
            let err = mean_angle_deg(&r, &truth);
            eprintln!("  mean normal error {err:.4}°");
            assert!(err < 1.0, "{err}");
        }
    }

    // Condition number ~1e8: refused, naming the condition number.
    let lights = coplanar_lights(1.6e-8);
    let (images, _) = ps_scene(&lights, size);
    for robust in [false, true] {
        let opts = PsOptions {
            robust,
            ..PsOptions::default()
        };
        let err = solve_images(&images, &lights, None, &opts).unwrap_err();
        let message = err.to_string();
        eprintln!("cond ≈ 1e8 (robust {robust}): {message}");
        assert!(message.contains("condition number"), "{message}");
        match err {
            PsError::IllConditioned { condition, .. } => {
                assert!(condition.is_finite(), "{condition}");
                assert!((1e7..1e9).contains(&condition), "{condition}");
            }
            other => panic!("expected IllConditioned, got {other:?}"),
        }
        // Forced through with a raised limit: still never NaN.
        let lenient = PsOptions {
            max_condition: 1e12,
            ..opts
        };
        if let Ok(r) = solve_images(&images, &lights, None, &lenient) {
            assert!(all_finite(ps_numbers(&r)), "lenient, robust {robust}");
        }
    }
}

// ----------------------------------------------- 7. rank-deficient PCA

fn assert_sane_pca(pca: &SlotPca, images: &[Vec<f32>], table: &DirectionTable, what: &str) {
    let ev = pca.eigenvalues();
    assert!(all_finite(ev.iter().copied()), "{what}: {ev:?}");
    assert!(ev.iter().all(|&e| e >= 0.0), "{what}: {ev:?}");
    assert!(all_finite(pca.singular_values().iter().copied()), "{what}");
    assert!(all_finite_f32(pca.mean()), "{what}");
    for k in 0..pca.components() {
        assert!(
            all_finite_f32(pca.eigen_texture(k).unwrap()),
            "{what}: B_{k}"
        );
    }
    assert!(all_finite(pca.rms_error_curve(images.len())), "{what}");
    let scale = images.iter().flatten().fold(1.0f32, |a, &x| a.max(x.abs()));
    for (i, original) in images.iter().enumerate() {
        assert!(all_finite_f32(pca.light_weights(i).unwrap()), "{what}");
        let back = pca.reconstruct_measured(i).unwrap();
        assert!(all_finite_f32(&back), "{what}: light {i}");
        let worst = back
            .iter()
            .zip(original)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst <= 1e-5 * scale, "{what}: light {i} off by {worst}");
    }
    // Blends between measured lights as well.
    for q in [(10.0, 33.0), (0.0, 0.0), (80.0, 359.0)] {
        let w = table.interpolate(pdir::Direction::new(q.0, q.1)).unwrap();
        let blend = pca.reconstruct_blend(&w).unwrap();
        assert!(all_finite_f32(&blend), "{what}: blend at {q:?}");
    }
}

#[test]
fn rank_deficient_and_constant_pca_input() {
    let shape = TextureShape::new(8, 6, 3).unwrap();
    let values = shape.values();
    let lights = 12;
    let table = DirectionTable::new(
        (0..lights)
            .map(|i| pdir::Direction::new(if i == 0 { 0.0 } else { 40.0 }, 30.0 * i as f64))
            .collect(),
    )
    .unwrap();
    let texture = |seed: f32| -> Vec<f32> {
        (0..values)
            .map(|k| 0.5 + 0.4 * (seed * k as f32).sin())
            .collect()
    };
    let a = texture(0.37);
    let b = texture(1.91);
    let cases: Vec<(&str, Vec<Vec<f32>>)> = vec![
        ("all identical", vec![a.clone(); lights]),
        ("all zero", vec![vec![0.0; values]; lights]),
        (
            "two distinct repeated",
            (0..lights)
                .map(|i| if i % 2 == 0 { a.clone() } else { b.clone() })
                .collect(),
        ),
        ("one huge constant", vec![vec![3.0e38; values]; lights]),
    ];
    for (what, images) in &cases {
        let refs: Vec<&[f32]> = images.iter().map(Vec::as_slice).collect();
        for components in [1, 4, 64] {
            let pca = compress_slot(&refs, shape, components).unwrap();
            assert_sane_pca(&pca, images, &table, &format!("{what}, C = {components}"));
        }
    }
    // The rank is what the data has: 0 for constant slots, 1 for two images.
    let refs: Vec<&[f32]> = cases[2].1.iter().map(Vec::as_slice).collect();
    let sv = compress_slot(&refs, shape, 4)
        .unwrap()
        .singular_values()
        .to_vec();
    assert!(sv[0] > 0.0 && sv[1] <= 1e-6 * sv[0], "{sv:?}");
}

// --------------------------------------------- 8. LM with exponent 1e4

fn unit_dir(theta: f64, phi: f64) -> [f64; 3] {
    d(theta, phi).to_vector()
}

fn assert_finite_fit(fit: &TexelFit, what: &str) {
    let mut nums = vec![fit.rms_error, fit.mean_abs_error, fit.initial_rms_error];
    for lobe in fit.model.lobes() {
        nums.extend(lobe.axis());
        nums.push(lobe.amplitude());
        nums.push(lobe.exponent());
        nums.extend(lobe.to_paper_coefficients());
    }
    assert!(all_finite(nums), "{what}: {fit:?}");
    for lobe in fit.model.lobes() {
        assert!(lobe.amplitude() >= 0.0, "{what}: {fit:?}");
        assert!(lobe.exponent() <= MAX_EXPONENT, "{what}: {fit:?}");
    }
}

#[test]
fn lm_fit_lobe_exponent_1e4() {
    // H2's 81 lights, plus a fine patch around (30°, 60°) 1° apart in φ,
    // so a lobe of half width ~0.7° can fall between two lights.
    let mut lights: Vec<[f64; 3]> = pdir::h2()
        .iter()
        .map(|x| unit_dir(x.theta_deg, x.phi_deg))
        .collect();
    for phi in [61.0, 62.0, 63.0] {
        lights.push(unit_dir(30.0, phi));
    }
    lights.push(unit_dir(31.0, 60.0));
    lights.push(unit_dir(29.0, 60.0));
    let diffuse = Lobe::new([0.0, 0.0, 1.0], 0.2, 1.0).unwrap();
    let spikes = [
        ("on a light", unit_dir(30.0, 60.0)),
        ("between two patch lights", unit_dir(30.0, 61.5)),
        ("between two coarse lights", unit_dir(30.0, 45.0)),
        ("between rings", unit_dir(37.5, 0.0)),
    ];
    let mut slot = Vec::new();
    let mut peaks = Vec::new();
    for (what, axis) in spikes {
        let truth = LobeModel::new(vec![diffuse, Lobe::new(axis, 0.9, 1.0e4).unwrap()]).unwrap();
        let values: Vec<f32> = lights.iter().map(|&l| truth.evaluate(l) as f32).collect();
        assert!(all_finite_f32(&values), "{what}");
        peaks.push(values.iter().fold(0.0f32, |a, &v| a.max(v)));
        slot.extend_from_slice(&values);
        for k in [1, 2] {
            let fit = fit_texel(&lights, &values, k, &FitOptions::default()).unwrap();
            assert_finite_fit(&fit, &format!("{what}, k = {k}"));
            eprintln!(
                "exponent 1e4 {what}, k = {k}: rms {:.2e}, exponents {:?}",
                fit.rms_error,
                fit.model
                    .lobes()
                    .iter()
                    .map(|l| l.exponent())
                    .collect::<Vec<_>>()
            );
        }
    }
    let opts = FitOptions::default();
    let fit = fit_slot(&lights, &slot, 2, &opts).unwrap();
    assert_eq!(fit.texels.len(), spikes.len());
    assert!(fit.rms_error().is_finite() && fit.mean_abs_error().is_finite());
    // Every fitted model stays finite and bounded everywhere on the hemisphere.
    for (t, (texel, peak)) in fit.texels.iter().zip(&peaks).enumerate() {
        assert_finite_fit(texel, &format!("slot texel {t}"));
        let bound = 2.0 * opts.max_amplitude_ratio * f64::from(*peak);
        for theta in 0..=90 {
            for phi in (0..360).step_by(2) {
                let v = texel.model.evaluate(unit_dir(theta as f64, phi as f64));
                assert!(v.is_finite() && v <= bound, "texel {t}: {v} > {bound}");
            }
        }
    }
}

// --------------------------------- 9. laser plane parallel to the view ray

#[test]
fn laser_plane_nearly_parallel_to_view_ray() {
    let (w, h) = (160usize, 120usize);
    let t = 40f64.to_radians();
    let cam = PinholeCamera::looking_at_origin([t.sin(), 0.0, t.cos()], 0.3, 800.0, w, h).unwrap();
    // Planes holding the image's horizontal and making an angle with the
    // central ray that grows with the row: rays of the middle rows lie
    // within 3° of them, rays ±60 px away ~4.3° off. The first passes
    // through the pinhole (every ray meets it at the camera), the second
    // is shifted along `up` so rows ~55 px above the centre triangulate
    // near the reference plane.
    let (o, centre) = cam.ray_at(w as f64 / 2.0, h as f64 / 2.0);
    let n = rigd_core::geometry::normalize(rigd_core::geometry::cross(centre, cam.right));
    let mut frames: Vec<Image> = (0..5).map(|_| Image::new(w, h, 1)).collect();
    frames[2].data.iter_mut().for_each(|v| *v = 0.9);
    let (max_depth, reference) = (0.02, 0.003);
    let opts = SpaceTimeOptions::new(0.2, reference, max_depth);
    for shift in [0.0, 0.021] {
        let p: Vec3 = std::array::from_fn(|k| o[k] + 0.3 * centre[k] + shift * cam.up[k]);
        let plane = LaserPlane::through(p, n).unwrap();
        let (img, stats) = space_time(&frames, &[plane; 5], &cam, &opts).unwrap();
        eprintln!("near-parallel plane shifted {shift} m: {stats:?}");
        assert!(stats.grazing > 0, "{stats:?}");
        if shift > 0.0 {
            assert!(stats.measured > 0, "{stats:?}");
        }
        assert!(all_finite_f32(&img.depth) && all_finite_f32(&img.weight));
        let mut within_3deg = 0;
        for j in 0..h {
            for i in 0..w {
                let k = j * w + i;
                let (depth, weight) = (img.depth[k], img.weight[k]);
                assert!(weight >= 0.0, "({i}, {j})");
                assert!(
                    depth == NO_DEPTH || (0.0..=max_depth as f32).contains(&depth),
                    "({i}, {j}): depth {depth}"
                );
                assert_eq!(depth == NO_DEPTH, weight == 0.0, "({i}, {j})");
                let (_, ray) = cam.ray(i, j);
                let s = (ray[0] * n[0] + ray[1] * n[1] + ray[2] * n[2]).abs();
                if s < opts.min_sin_angle * (1.0 - 1e-9) {
                    within_3deg += 1;
                    assert_eq!((depth, weight), (NO_DEPTH, 0.0), "({i}, {j}): s = {s}");
                } else if depth != NO_DEPTH {
                    assert!(weight > 0.0 && weight <= 1.0, "({i}, {j}): {weight}");
                }
            }
        }
        assert!(within_3deg > w * 10, "{within_3deg}");
    }

    // Laser tilt near the horizon: None, or finite values, never infinite.
    for g in [
        LaserGeometry {
            theta_deg: 45.0,
            radius_m: 0.9,
        },
        LaserGeometry {
            theta_deg: 89.9,
            radius_m: 0.9,
        },
        LaserGeometry {
            theta_deg: 0.0,
            radius_m: 1.6,
        },
    ] {
        // Depression at tilt 0 is 90° − θ; the beam is horizontal at tilt θ − 90.
        let horizon = g.theta_deg - 90.0;
        assert_eq!(g.offset_for_tilt(horizon), None, "{g:?}");
        assert!(g.plane(0.0, horizon).is_none(), "{g:?}");
        for base in [horizon, horizon + 180.0] {
            for delta in [0.0, 1e-12, 1e-9, 1e-6, 1e-4, 1e-2, 1.0] {
                for tilt in [base + delta, base - delta] {
                    let off = g.offset_for_tilt(tilt);
                    assert!(off.is_none_or(f64::is_finite), "{g:?} tilt {tilt}: {off:?}");
                    if let Some((e, n)) = g.plane(37.0, tilt) {
                        assert!(all_finite(e) && all_finite(n), "{g:?} tilt {tilt}");
                        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                        assert!((len - 1.0).abs() < 1e-9, "{g:?} tilt {tilt}: |n| = {len}");
                    }
                }
            }
        }
        for offset in [-0.1, 0.0, 0.1] {
            assert!(g.tilt_for_offset(offset).is_finite(), "{g:?}");
        }
    }
}

// ------------------------------------------------------- 10. saturation

#[test]
fn twelve_bit_saturation() {
    let scene = Scene::load("flat-calibration").unwrap();
    let s = Shot {
        relative_exposure: 50.0,
        ..shot(d(0.0, 0.0).to_vector(), d(0.0, 0.0).to_vector())
    };
    assert_eq!(s.bit_depth, 12);
    let (linear, _) = scene.render_linear(&s);
    assert!(all_finite_f32(&linear));
    let frame = scene.render(&s);
    assert_eq!(frame.bit_depth, 12);
    assert!(frame.pixels.iter().all(|&p| p <= 4095));
    assert_eq!(frame.pixels.iter().copied().max(), Some(4095));
    let mut clipped = 0;
    for (&p, &x) in frame.pixels.iter().zip(&linear) {
        if x > 4200.0 {
            assert_eq!(p, 4095, "linear {x}");
            clipped += 1;
        }
    }
    assert!(clipped > frame.pixels.len() / 2, "{clipped}");

    // 8-bit quantisation of values > 1 saturates, never wraps.
    let data = vec![
        1.0,
        1.0 + f32::EPSILON,
        1.5,
        2.0,
        1e30,
        f32::MAX,
        f32::INFINITY,
        f32::NAN,
        -1.0,
    ];
    let texture = Image {
        width: data.len(),
        height: 1,
        channels: 1,
        data,
    };
    for (bits, shift) in [(12u8, 2u8), (12, 4), (8, 0), (16, 8)] {
        let q = quantise(&texture, bits, Quantisation::Bits8 { shift }).unwrap();
        assert!(all_finite_f32(&q.data), "{bits}/{shift}");
        assert!(q.data.iter().all(|v| (0.0..=1.0).contains(v)));
        let codes = codes8(&q);
        assert_eq!(&codes[..6], &[255; 6], "{bits} bits, shift {shift}");
        // Infinity, NaN and negatives read as 0.
        assert_eq!(&codes[6..], &[0, 0, 0], "{bits} bits, shift {shift}");
    }
}

// ------------------------------------------------------ 11. empty plan

#[test]
fn empty_plan() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("empty.json");
    std::fs::write(&path, r#"{"directions": []}"#).unwrap();
    let err = rigd::plan::from_file(&path).unwrap_err().to_string();
    assert!(err.contains("no images"), "{err}");
    for text in [r#"{"lights": [], "views": []}"#, r#"{"pairs": []}"#] {
        std::fs::write(&path, text).unwrap();
        assert!(rigd::plan::from_file(&path).is_err(), "{text}");
    }

    let p = profile("bonn-gonioreflectometer");
    let s = Solver::new(&p).unwrap();
    let plan = Plan {
        name: "empty".into(),
        pairs: vec![],
        laser: None,
        order: Order::Optimised,
    };
    let sched = schedule::build(&p, &s, &plan);
    assert_eq!((sched.triggers.len(), sched.images.len()), (0, 0));
    let (sched, report) = schedule::build_with_report(&p, &s, &plan);
    assert_eq!(sched.triggers.len(), 0);
    assert_eq!(report.triggers, 0);
    assert!(all_finite(report_numbers(&report)), "{report:?}");
    let estimate = Timing::new(&p, None).estimate_s(&sched, |_| false);
    assert!(estimate.is_finite() && estimate >= 0.0, "{estimate}");
}

// ------------------------------------------------- 12. single-step plan

#[test]
fn single_step_plan() {
    for name in ["bonn-gonioreflectometer", "msra-btf-mdf"] {
        let p = profile(name);
        let s = Solver::new(&p).unwrap();
        let plan = Plan {
            name: "one".into(),
            pairs: vec![Pair {
                light: d(40.0, 90.0),
                view: d(30.0, 270.0),
            }],
            laser: None,
            order: Order::Optimised,
        };
        let (sched, report) = schedule::build_with_report(&p, &s, &plan);
        assert_eq!(sched.images.len(), 1, "{name}");
        assert_eq!(sched.triggers.len(), 1, "{name}");
        assert!(
            sched.images[0].feasible,
            "{name}: {:?}",
            sched.images[0].reason
        );
        assert!(all_finite(schedule_numbers(&sched)), "{name}");
        assert!(all_finite(report_numbers(&report)), "{name}: {report:?}");
        assert!(report.optimised_s <= report.naive_s, "{name}: {report:?}");
        let estimate = Timing::new(&p, None).estimate_s(&sched, |_| false);
        assert!(estimate.is_finite() && estimate > 0.0, "{name}: {estimate}");
        assert!(
            (estimate - report.naive_s).abs() <= 1e-9 * estimate,
            "{name}"
        );
    }
}

// ---------------------------------------------------- 13. very long run

/// Resident set size of this process, bytes.
fn rss_bytes() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
    let kb: u64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
    kb * 1024
}

/// Deterministic directions, θ in [0, 80], φ in [0, 360).
fn pseudo_random_directions(n: usize, seed: u64) -> Vec<serde_json::Value> {
    let mut x = seed;
    let mut next = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n)
        .map(|_| {
            let theta = 80.0 * next();
            let phi = 360.0 * next();
            serde_json::json!({ "theta_deg": theta, "phi_deg": phi })
        })
        .collect()
}

#[test]
fn very_long_run_100k_steps() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("long.json");
    let plan_json = serde_json::json!({
        "name": "long",
        "lights": pseudo_random_directions(400, 0x9E37_79B9_7F4A_7C15),
        "views": pseudo_random_directions(250, 0xD1B5_4A32_D192_ED03),
    });
    std::fs::write(&path, serde_json::to_vec(&plan_json).unwrap()).unwrap();
    let p = profile("bonn-gonioreflectometer");

    let rss_before = rss_bytes();
    let start = Instant::now();
    // Read, solve pose by pose and order, once: what `rigd run` does.
    let plan = rigd::plan::from_file(&path).unwrap();
    assert_eq!(plan.pairs.len(), 100_000);
    assert_eq!(plan.order, Order::Optimised);
    let solver = rigd::kinematics::Solver::new(&p).unwrap();
    let (sched, report) = schedule::build_with_report(&p, &solver, &plan);
    let solved_s = start.elapsed().as_secs_f64();
    assert_eq!(sched.images.len(), 100_000);
    assert!(all_finite(schedule_numbers(&sched)));
    for (k, img) in sched.images.iter().enumerate() {
        assert_eq!(img.index, k);
    }
    let estimate = Timing::new(&p, None).estimate_s(&sched, |_| false);
    assert!(estimate.is_finite() && estimate > 0.0, "{estimate}");
    assert!((estimate - report.optimised_s).abs() <= 1e-6 * estimate);
    assert!(all_finite(report_numbers(&report)), "{report:?}");
    assert!(report.optimised_s <= report.naive_s, "{report:?}");
    assert!(report.lower_bound_s <= report.optimised_s, "{report:?}");
    let rss_after = rss_bytes();
    let growth = rss_after.saturating_sub(rss_before);
    eprintln!(
        "100 000 steps: read, solved and ordered in {solved_s:.2} s; \
         {} triggers, naive {:.0} s, optimised {:.0} s, bound {:.0} s ({}); \
         estimate {estimate:.0} s; RSS {} → {} MiB (growth {} MiB)",
        report.triggers,
        report.naive_s,
        report.optimised_s,
        report.lower_bound_s,
        report.bound,
        rss_before >> 20,
        rss_after >> 20,
        growth >> 20,
    );
    assert!(growth < 1 << 30, "RSS grew by {} MiB", growth >> 20);
}

// ------------------------------------------------------------ properties

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn direction_vector_round_trip(theta in 1e-3f64..=90.0, phi in -720.0f64..720.0) {
        let v = d(theta, phi).to_vector();
        prop_assert!(all_finite(v));
        let back = Direction::from_vector(v);
        prop_assert!(all_finite([back.theta_deg, back.phi_deg]));
        prop_assert!((0.0..360.0).contains(&back.phi_deg));
        let w = back.to_vector();
        for k in 0..3 {
            prop_assert!((v[k] - w[k]).abs() < 1e-12, "{:?} vs {:?}", v, w);
        }
    }

    #[test]
    fn laser_tilt_offset_round_trip(
        theta_deg in 10.0f64..80.0,
        radius_m in 0.3f64..2.0,
        offset in -0.0999f64..0.0999,
    ) {
        let g = LaserGeometry { theta_deg, radius_m };
        let tilt = g.tilt_for_offset(offset);
        prop_assert!(tilt.is_finite());
        let back = g.offset_for_tilt(tilt);
        prop_assert!(back.is_some(), "tilt {}", tilt);
        let back = back.unwrap();
        prop_assert!((back - offset).abs() < 1e-12, "{} → {} → {}", offset, tilt, back);
    }

    #[test]
    fn npy_f32_round_trip_is_exact(
        h in 1usize..6,
        w in 1usize..6,
        rgb in any::<bool>(),
        bits in proptest::collection::vec(any::<u32>(), 75),
    ) {
        let shape = if rgb { vec![h, w, 3] } else { vec![h, w] };
        let n: usize = shape.iter().product();
        let data: Vec<f32> = bits[..n].iter().map(|&b| f32::from_bits(b)).collect();
        let back = npy::decode_f32(&npy::encode(&shape, &data, Dtype::F32).unwrap()).unwrap();
        prop_assert_eq!(&back.shape, &shape);
        let got: Vec<u32> = back.data.iter().map(|x| x.to_bits()).collect();
        prop_assert_eq!(got, bits[..n].to_vec());
    }

    #[test]
    fn npy_f16_round_trip_within_half_ulp(
        h in 1usize..6,
        w in 1usize..6,
        rgb in any::<bool>(),
        mags in proptest::collection::vec((-14.0f32..15.9, any::<bool>()), 75),
    ) {
        let shape = if rgb { vec![h, w, 3] } else { vec![h, w] };
        let n: usize = shape.iter().product();
        // Normal half-precision magnitudes: 2^-14 ≤ |x| < 2^15.9 < 65504.
        let data: Vec<f32> = mags[..n]
            .iter()
            .map(|&(e, neg)| if neg { -e.exp2() } else { e.exp2() })
            .collect();
        let back = npy::decode_f32(&npy::encode(&shape, &data, Dtype::F16).unwrap()).unwrap();
        prop_assert_eq!(&back.shape, &shape);
        for (x, y) in data.iter().zip(&back.data) {
            prop_assert!(y.is_finite());
            let rel = (f64::from(*y) - f64::from(*x)).abs() / f64::from(x.abs());
            prop_assert!(rel <= 2f64.powi(-11), "{} → {} (relative {})", x, y, rel);
        }
    }
}
