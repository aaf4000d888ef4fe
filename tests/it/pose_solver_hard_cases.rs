//! The hard cases of pose solving, one named test each, on the embedded rig
//! profiles, plus round-trip and finiteness properties.

use proptest::prelude::*;
use rigd::kinematics::{PoseSolution, Setpoints, Solver};
use rigd::model::profile::{Profile, EMBEDDED};
use rigd_core::geometry::{angle_between, wrap_deg_180, Direction};
use std::sync::LazyLock;

fn solver(name: &str) -> Solver {
    Solver::new(&Profile::load(name).unwrap()).unwrap()
}

// Built once: the properties call them thousands of times.
static BONN: LazyLock<Solver> = LazyLock::new(|| solver("bonn-gonioreflectometer"));
static MSRA: LazyLock<Solver> = LazyLock::new(|| solver("msra-btf-mdf"));
static VIRTEX: LazyLock<Solver> = LazyLock::new(|| solver("virtex-photometric-stereo"));

fn bonn() -> &'static Solver {
    &BONN
}

fn msra() -> &'static Solver {
    &MSRA
}

fn virtex() -> &'static Solver {
    &VIRTEX
}

/// Angle between two directions in radians.
fn err(a: Direction, b: Direction) -> f64 {
    angle_between(a.to_vector(), b.to_vector())
}

/// Joint values in profile order [roll, pitch, twist].
fn arm(sol: &PoseSolution) -> [f64; 3] {
    let a = sol.setpoints.arm.as_ref().unwrap();
    [a[0], a[1], a[2]]
}

/// Distance between two angles modulo whole turns, in degrees.
fn mod_dist(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(360.0);
    d.min(360.0 - d)
}

fn all_finite(sol: &PoseSolution) -> bool {
    let dirs = [sol.achieved_light, sol.achieved_view];
    dirs.iter()
        .all(|d| d.theta_deg.is_finite() && d.phi_deg.is_finite())
        && sol.setpoints.axes.values().all(|x| x.is_finite())
        && sol
            .setpoints
            .arm
            .as_ref()
            .is_none_or(|a| a.iter().all(|x| x.is_finite()))
}

/// `achieved_*` must be exactly what forward kinematics says of the set-points.
fn assert_forward_consistent(s: &Solver, sol: &PoseSolution) {
    let (l, v) = s.forward(&sol.setpoints, &sol.camera).unwrap();
    assert_eq!((l, v), (sol.achieved_light, sol.achieved_view));
}

fn bits(sp: &Setpoints) -> Vec<(String, u64)> {
    sp.axes
        .iter()
        .map(|(k, v)| (k.clone(), v.to_bits()))
        .collect()
}

/// The H1 sampling of Sattler et al.: rings θ = 0, 17, ..., 85 with 1, 6, 12, 18, 20, 24
/// azimuths, Δφ = 360/n from φ = 0.
fn h1() -> Vec<Direction> {
    let rings = [
        (0.0, 1),
        (17.0, 6),
        (34.0, 12),
        (51.0, 18),
        (68.0, 20),
        (85.0, 24),
    ];
    let mut out = Vec::new();
    for (theta, n) in rings {
        for i in 0..n {
            out.push(Direction::new(theta, 360.0 / n as f64 * i as f64));
        }
    }
    out
}

/// The grid12x8 directions of the MSRA rig for the given elevations.
fn grid(elevations: &[f64]) -> Vec<Direction> {
    let mut out = Vec::new();
    for &theta in elevations {
        for i in 0..12 {
            out.push(Direction::new(theta, 30.0 * i as f64));
        }
    }
    out
}

#[test]
fn pole_light_gives_same_pose_whatever_phi() {
    let s = bonn();
    let view = Direction::new(51.0, 140.0);
    let first = s.solve(Direction::new(0.0, 0.0), view);
    assert!(first.feasible, "{:?}", first.reason);
    for phi in [45.0, 359.9, -90.0, 720.0, 1e6] {
        let sol = s.solve(Direction::new(0.0, phi), view);
        assert_eq!(sol, first, "φ = {phi}");
    }
    assert_eq!(first.achieved_light.theta_deg, 0.0);
    assert!(err(first.achieved_view, view) < 1e-12);
    assert_forward_consistent(s, &first);
}

#[test]
fn pole_view_gives_same_pose_whatever_phi() {
    let s = bonn();
    let light = Direction::new(34.0, 210.0);
    let first = s.solve(light, Direction::new(0.0, 0.0));
    assert!(first.feasible, "{:?}", first.reason);
    for phi in [30.0, 180.0, -359.0, 3600.0] {
        assert_eq!(s.solve(light, Direction::new(0.0, phi)), first, "φ = {phi}");
    }
    assert!(err(first.achieved_light, light) < 1e-12);
    assert!(first.achieved_view.theta_deg < 1e-9);
    assert!((first.setpoints.axes["rail"] - 34.0).abs() < 1e-12);

    // The same holds on the turntable rig: φ at the pole is taken as 0.
    let m = msra();
    let a = m.solve(Direction::new(40.0, 90.0), Direction::new(0.0, 0.0));
    let b = m.solve(Direction::new(40.0, 90.0), Direction::new(0.0, 250.0));
    assert_eq!(a, b);
    assert!(!a.feasible, "no camera at the pole");
    assert_eq!(a.camera, "cam0");
}

#[test]
fn grazing_85_degrees_light_and_view() {
    let s = bonn();
    for (l, v) in [
        (Direction::new(85.0, 0.0), Direction::new(85.0, 150.0)),
        (Direction::new(85.0, 345.0), Direction::new(85.0, 165.0)),
        (Direction::new(85.0, 90.0), Direction::new(17.0, 300.0)),
        (Direction::new(0.0, 0.0), Direction::new(85.0, 15.0)),
    ] {
        let sol = s.solve(l, v);
        assert!(sol.feasible, "{l:?} {v:?}: {:?}", sol.reason);
        assert_eq!(arm(&sol)[1], l.theta_deg, "pitch = θ_l");
        assert!(err(sol.achieved_light, l) < 1e-12);
        assert!(err(sol.achieved_view, v) < 1e-12);
        assert_forward_consistent(s, &sol);
    }
    // 85° is 5° beyond the MSRA arcs' last lamp and camera: substituted, not silently met.
    let m = msra();
    let sol = m.solve(Direction::new(85.0, 90.0), Direction::new(85.0, 0.0));
    assert!(!sol.feasible);
    assert_eq!(
        (sol.camera.as_str(), sol.setpoints.lamp.as_str()),
        ("cam7", "lamp7")
    );
    let reason = sol.reason.unwrap();
    assert!(reason.contains("nearest camera cam7") && reason.contains("nearest lamp lamp7"));
    assert_eq!(sol.achieved_light, Direction::new(80.0, 90.0));
    assert_eq!(sol.achieved_view, Direction::new(80.0, 0.0));
}

#[test]
fn light_equals_view_is_infeasible_with_substitute_at_rail_minimum() {
    let s = bonn();
    // (request, where the view must go: along l's meridian towards the pole by 12°)
    for (d, want_view) in [
        (Direction::new(40.0, 30.0), Direction::new(28.0, 30.0)),
        (Direction::new(85.0, 200.0), Direction::new(73.0, 200.0)),
        (Direction::new(0.0, 123.0), Direction::new(12.0, 0.0)),
        (Direction::new(5.0, 90.0), Direction::new(7.0, 270.0)),
    ] {
        let sol = s.solve(d, d);
        assert!(!sol.feasible);
        let reason = sol.reason.as_deref().unwrap();
        assert!(
            reason.starts_with("camera would stand between lamp and sample (lamp-camera angle 0.0° < rail minimum 12°); view moved to θ="),
            "{reason}"
        );
        assert!(all_finite(&sol));
        assert_eq!(sol.setpoints.axes["rail"], 12.0);
        assert!(err(sol.achieved_light, d) < 1e-12, "light is kept");
        let a = sol.achieved_light.angle_to_deg(sol.achieved_view);
        assert!((a - 12.0).abs() < 1e-9, "{a}");
        assert!(
            err(sol.achieved_view, want_view) < 1e-12,
            "{:?}",
            sol.achieved_view
        );
        assert_forward_consistent(s, &sol);
    }
    // Nearly equal: the plane is still defined, the view moves away from l within it.
    let l = Direction::new(40.0, 30.0);
    let v = Direction::new(45.0, 30.0);
    let sol = s.solve(l, v);
    assert!(!sol.feasible);
    assert!(err(sol.achieved_view, Direction::new(52.0, 30.0)) < 1e-12);
}

#[test]
fn phi_crossing_360() {
    let s = bonn();
    let v = Direction::new(51.0, 180.0);
    let a = s.solve(Direction::new(34.0, 359.9), v);
    let b = s.solve(Direction::new(34.0, 0.1), v);
    assert!(a.feasible && b.feasible);
    let (ja, jb) = (arm(&a), arm(&b));
    for i in 0..3 {
        assert!(
            mod_dist(ja[i], jb[i]) < 0.5,
            "joint {i}: {} vs {}",
            ja[i],
            jb[i]
        );
    }
    // The twist branch cut is at φ = 180°, so no full turn between 359.9 and 0.1.
    assert!((ja[2] - jb[2]).abs() < 0.5, "{} vs {}", ja[2], jb[2]);
    assert!((a.setpoints.axes["rail"] - b.setpoints.axes["rail"]).abs() < 0.2);
    // 360 ≡ 0 exactly, for light and view.
    let l0 = Direction::new(68.0, 0.0);
    let l360 = Direction::new(68.0, 360.0);
    assert_eq!(s.solve(l0, v), s.solve(l360, v));
    assert_eq!(
        s.solve(v, Direction::new(17.0, 0.0)),
        s.solve(v, Direction::new(17.0, 360.0))
    );

    let m = msra();
    let l = Direction::new(40.0, 90.0);
    let a = m.solve(l, Direction::new(30.0, 359.9));
    let b = m.solve(l, Direction::new(30.0, 0.1));
    assert!(a.feasible && b.feasible);
    let (ta, tb) = (a.setpoints.axes["turntable"], b.setpoints.axes["turntable"]);
    assert!(
        (ta - 0.1).abs() < 1e-9 && (tb - 359.9).abs() < 1e-9,
        "{ta} {tb}"
    );
    assert!(mod_dist(ta, tb) < 0.2 + 1e-9);
    let (la, lb) = (a.setpoints.axes["light_arc"], b.setpoints.axes["light_arc"]);
    assert!(mod_dist(la, lb) < 0.2 + 1e-9);
    assert_eq!(
        m.solve(l, Direction::new(30.0, 360.0)),
        m.solve(l, Direction::new(30.0, 0.0))
    );
    assert_eq!(
        m.solve(l, Direction::new(30.0, 0.0)).setpoints.axes["turntable"],
        0.0
    );
}

#[test]
fn wrist_singularity_exact_and_near() {
    let s = bonn();
    for theta_l in [0.0, 1e-9, 1e-7, 1e-3] {
        for phi_l in [0.0, 90.0, 180.0, 271.3] {
            for v in [
                Direction::new(85.0, 0.0),
                Direction::new(34.0, 200.0),
                Direction::new(12.5, 359.0),
            ] {
                let l = Direction::new(theta_l, phi_l);
                let sol = s.solve(l, v);
                assert!(sol.feasible, "{l:?} {v:?}: {:?}", sol.reason);
                assert!(all_finite(&sol));
                let [roll, pitch, twist] = arm(&sol);
                assert_eq!(pitch, theta_l);
                if theta_l == 0.0 {
                    assert_eq!(roll, 0.0, "whole rotation in twist at the singularity");
                } else {
                    assert_eq!(twist, -wrap_deg_180(phi_l) + 0.0);
                }
                assert!(err(sol.achieved_light, l) < 1e-12, "{l:?} {v:?}");
                assert!(err(sol.achieved_view, v) < 1e-12, "{l:?} {v:?}");
                assert_forward_consistent(s, &sol);
            }
        }
    }
}

#[test]
fn msra_occlusion_moves_light_arc_to_nearest_clear_angle() {
    let m = msra();
    // Light and view at the same azimuth: the light arc stands over the camera arc
    // and lamp3 (40°) is hidden behind cam3 (40°).
    let l = Direction::new(40.0, 30.0);
    let sol = m.solve(l, Direction::new(60.0, 30.0));
    assert!(!sol.feasible);
    let reason = sol.reason.as_deref().unwrap();
    assert!(
        reason.contains("camera would stand between lamp and sample"),
        "{reason}"
    );
    assert!(
        reason.contains("lamp lamp3 hidden behind camera cam3"),
        "{reason}"
    );
    let lambda = sol.setpoints.axes["light_arc"];
    assert!(lambda > 0.0, "λ = 0 resolves to the + side");
    // Nearest clear: lamp3 exactly `occlusion_deg` from cam3 (the turntable does not
    // change angles, so compare in the sample frame with cam3's view).
    let cam3_view = m.forward(&sol.setpoints, "cam3").unwrap().1;
    let gap = sol.achieved_light.angle_to_deg(cam3_view);
    assert!((gap - 4.0).abs() < 1e-9, "{gap}");
    assert_eq!(sol.achieved_light.theta_deg, 40.0);
    assert!((sol.achieved_light.phi_deg - (30.0 + lambda)).abs() < 1e-9);
    assert_forward_consistent(m, &sol);

    // Slightly on the − side: the substitute goes to the − side, same distance.
    let neg = m.solve(Direction::new(40.0, 29.0), Direction::new(60.0, 30.0));
    assert!(!neg.feasible);
    assert_eq!(neg.setpoints.axes["light_arc"], -lambda);

    // Every cam gets the same substitute (one trigger).
    for theta_v in [10.0, 20.0, 80.0] {
        let other = m.solve(l, Direction::new(theta_v, 30.0));
        assert_eq!(other.setpoints, sol.setpoints);
    }
    // Clear by a margin: not occluded.
    let ok = m.solve(Direction::new(40.0, 60.0), Direction::new(40.0, 30.0));
    assert!(ok.feasible, "{:?}", ok.reason);
}

#[test]
fn out_of_limit_setpoints_are_infeasible_naming_the_joint_or_axis() {
    // Bonn: θ_l = 89.5 needs pitch 89.5 > 89.
    let s = bonn();
    let sol = s.solve(Direction::new(89.5, 10.0), Direction::new(40.0, 190.0));
    assert!(!sol.feasible);
    let reason = sol.reason.as_deref().unwrap();
    assert!(reason.contains("arm joint pitch = 89.500°"), "{reason}");
    assert!(reason.contains("[-1, 89]"), "{reason}");
    assert_eq!(arm(&sol)[1], 89.0);
    assert!((sol.achieved_light.theta_deg - 89.0).abs() < 1e-9);
    assert!(all_finite(&sol));

    // MSRA with a light arc limited to [-90, 90]: λ = 150 cannot be reached.
    let text = EMBEDDED
        .iter()
        .find(|(n, _)| *n == "msra-btf-mdf")
        .unwrap()
        .1;
    let narrowed = text.replacen(
        "limits = { min = -180.0, max = 180.0 }",
        "limits = { min = -90.0, max = 90.0 }",
        1,
    );
    assert_ne!(narrowed, text, "the light arc's limits line was found");
    let m = Solver::new(&Profile::parse(&narrowed, "narrowed").unwrap()).unwrap();
    let sol = m.solve(Direction::new(40.0, 150.0), Direction::new(40.0, 0.0));
    assert!(!sol.feasible);
    let reason = sol.reason.as_deref().unwrap();
    assert!(reason.contains("axis light_arc = 150.000°"), "{reason}");
    assert_eq!(sol.setpoints.axes["light_arc"], 90.0);
    assert_eq!(sol.achieved_light, Direction::new(40.0, 90.0));
    // Within its limits the same rig is fine.
    assert!(
        m.solve(Direction::new(40.0, 60.0), Direction::new(40.0, 0.0))
            .feasible
    );
}

#[test]
fn unusable_input_is_infeasible_with_finite_substitute() {
    for s in [bonn(), msra(), virtex()] {
        for (l, v) in [
            (Direction::new(f64::NAN, 0.0), Direction::new(40.0, 0.0)),
            (
                Direction::new(40.0, f64::INFINITY),
                Direction::new(40.0, 0.0),
            ),
            (Direction::new(45.0, 0.0), Direction::new(-5.0, 0.0)),
            (
                Direction::new(100.0, 0.0),
                Direction::new(f64::NEG_INFINITY, 1.0),
            ),
        ] {
            let sol = s.solve(l, v);
            assert!(!sol.feasible);
            assert!(sol.reason.is_some());
            assert!(all_finite(&sol), "{sol:?}");
        }
    }
}

#[test]
fn bonn_h1_infeasible_count() {
    let s = bonn();
    let dirs = h1();
    assert_eq!(dirs.len(), 81);
    let mut infeasible = 0;
    for &l in &dirs {
        for &v in &dirs {
            let sol = s.solve(l, v);
            assert!(all_finite(&sol));
            if sol.feasible {
                assert!(err(sol.achieved_light, l) < 1e-9 && err(sol.achieved_view, v) < 1e-9);
            } else {
                infeasible += 1;
                // The only H1 pairs closer than 12° are l = v (rings are 17° apart and
                // neighbours within a ring at least ~14.9° apart); none is above 172°.
                assert_eq!(l, v, "{:?}", sol.reason);
            }
        }
    }
    assert_eq!(infeasible, 81);
}

#[test]
fn msra_grid_counts_and_trigger_groups() {
    let m = msra();
    let (lamp_el, cam_el) = m.arc_elevations().unwrap();
    assert_eq!(lamp_el, [10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0]);
    assert_eq!(cam_el, lamp_el);
    let lights = grid(&lamp_el);
    let views = grid(&cam_el);
    assert_eq!((lights.len(), views.len()), (96, 96));
    let mut occluded = 0;
    let mut other_infeasible = 0;
    let mut triggers = std::collections::BTreeSet::new();
    for &l in &lights {
        for i in 0..12 {
            let phi_v = 30.0 * i as f64;
            let group: Vec<PoseSolution> = cam_el
                .iter()
                .map(|&t| m.solve(l, Direction::new(t, phi_v)))
                .collect();
            // One trigger: bitwise-equal set-points for all eight cameras.
            for sol in &group {
                assert_eq!(sol.setpoints, group[0].setpoints);
                assert_eq!(bits(&sol.setpoints), bits(&group[0].setpoints));
            }
            triggers.insert((bits(&group[0].setpoints), group[0].setpoints.lamp.clone()));
            for (sol, &t) in group.iter().zip(&cam_el) {
                match sol.reason.as_deref() {
                    None => {
                        assert_eq!(sol.achieved_light, l);
                        assert_eq!(sol.achieved_view, Direction::new(t, phi_v));
                    }
                    Some(r) if r.contains("camera would stand between lamp and sample") => {
                        occluded += 1;
                        assert_eq!(l.phi_deg, phi_v, "only λ = 0 is occluded on the grid");
                    }
                    Some(_) => other_infeasible += 1,
                }
            }
        }
    }
    assert_eq!(triggers.len(), 96 * 12);
    assert_eq!(other_infeasible, 0);
    // 12 azimuths × 8 lamps with λ = 0, each hiding the lamp for all 8 cameras.
    assert_eq!(occluded, 768);
}

#[test]
fn fixed_lamps_pick_nearest_lamp() {
    let s = virtex();
    assert!(s.arc_elevations().is_none());
    let sol = s.solve(Direction::new(45.2, 240.3), Direction::new(0.0, 99.0));
    assert!(sol.feasible, "{:?}", sol.reason);
    assert_eq!(sol.setpoints.lamp, "lamp2");
    assert_eq!(sol.achieved_light, Direction::new(45.0, 240.0));
    let far = s.solve(Direction::new(0.0, 0.0), Direction::new(0.0, 0.0));
    assert!(!far.feasible);
    assert!(far.reason.unwrap().contains("lamp0 substituted"));
    assert_forward_consistent(s, &sol);
}

fn theta_l_strategy() -> impl Strategy<Value = f64> {
    prop_oneof![
        4 => 0.0..85.0f64,
        1 => 0.0..1e-6f64,
        1 => Just(0.0),
        1 => Just(85.0),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn bonn_round_trip(
        theta_l in theta_l_strategy(),
        phi_l in 0.0..360.0f64,
        theta_v in 0.0..=85.0f64,
        phi_v in 0.0..360.0f64,
    ) {
        let s = bonn();
        let (l, v) = (Direction::new(theta_l, phi_l), Direction::new(theta_v, phi_v));
        let alpha = l.angle_to_deg(v);
        prop_assume!((12.0..=172.0).contains(&alpha));
        let sol = s.solve(l, v);
        prop_assert!(sol.feasible, "{:?}", sol.reason);
        prop_assert!(err(sol.achieved_light, l) < 1e-9);
        prop_assert!(err(sol.achieved_view, v) < 1e-9);
        let fwd = s.forward(&sol.setpoints, &sol.camera).unwrap();
        prop_assert_eq!(fwd, (sol.achieved_light, sol.achieved_view));
    }

    #[test]
    fn msra_round_trip_on_grid(
        lamp in 0usize..8, phi_l in 0usize..12, cam in 0usize..8, phi_v in 0usize..12,
    ) {
        let m = msra();
        let l = Direction::new(10.0 * (lamp + 1) as f64, 30.0 * phi_l as f64);
        let v = Direction::new(10.0 * (cam + 1) as f64, 30.0 * phi_v as f64);
        let sol = m.solve(l, v);
        prop_assert_eq!(sol.feasible, phi_l != phi_v);
        if sol.feasible {
            prop_assert!(err(sol.achieved_light, l) < 1e-9);
            prop_assert!(err(sol.achieved_view, v) < 1e-9);
        }
        let fwd = m.forward(&sol.setpoints, &sol.camera).unwrap();
        prop_assert_eq!(fwd, (sol.achieved_light, sol.achieved_view));
    }

    #[test]
    fn solve_is_always_finite(
        theta_l in -10.0..100.0f64, phi_l in -720.0..720.0f64,
        theta_v in -10.0..100.0f64, phi_v in -720.0..720.0f64,
    ) {
        let (l, v) = (Direction::new(theta_l, phi_l), Direction::new(theta_v, phi_v));
        for s in [bonn(), msra(), virtex()] {
            let sol = s.solve(l, v);
            prop_assert!(all_finite(&sol), "{:?}", sol);
            prop_assert_eq!(sol.feasible, sol.reason.is_none());
            let fwd = s.forward(&sol.setpoints, &sol.camera).unwrap();
            prop_assert_eq!(fwd, (sol.achieved_light, sol.achieved_view));
        }
    }
}
