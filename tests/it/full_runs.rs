//! Whole captures on the simulated rig of each profile, through the command line.

use crate::common;

use common::{assert_complete_run, run_ok};

#[test]
fn bonn_h1_full_run_writes_6561_frames() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("h1");
    let o = run_ok(&[
        "run",
        "--sim",
        "--plan",
        "h1",
        "--sample",
        "corduroy",
        "--frame-size",
        "64x64",
        "--progress",
        "log",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("physical duration"), "{stderr}");
    assert!(stderr.contains("wall time"), "{stderr}");
    let m = assert_complete_run(&out, 6561);
    assert_eq!(m.plan, "h1");
    assert_eq!(m.profile, "bonn-gonioreflectometer");
    // The l = v pairs are the ones the rail cannot reach.
    assert_eq!(m.infeasible.len(), 81);
    assert!(m
        .infeasible
        .iter()
        .all(|i| i.light == i.view && !i.reason.is_empty()));
    // Physical time of the gonioreflectometer: hours, not the seconds it took here.
    assert!(
        m.physical_duration_s > 3.0 * 3600.0,
        "{}",
        m.physical_duration_s
    );
    let f = &m.frames[100];
    assert_eq!((f.width, f.height, f.bit_depth), (64, 64, 12));
    assert_eq!(f.camera, "camera");
}

#[test]
fn bonn_h2_full_run() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("h2");
    run_ok(&[
        "run",
        "--sim",
        "--plan",
        "h2",
        "--frame-size",
        "16x16",
        "--progress",
        "none",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    let m = assert_complete_run(&out, 6561);
    assert_eq!(m.plan, "h2");
    assert_estimate_matches("h2", "bonn-gonioreflectometer", m.physical_duration_s);
}

/// The estimate of `plan show` follows the same timing model as the
/// simulated firmware, and the drivers poll at each wait's modelled end:
/// the run through the real drivers takes the estimate, homing and lamp
/// warm-up included, to tokio's millisecond per step (10 ppm here).
fn assert_estimate_matches(plan: &str, profile: &str, physical_s: f64) {
    let o = run_ok(&["plan", "show", plan, "--profile", profile, "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("json");
    let estimate = v["estimated_physical_s"].as_f64().expect("estimate");
    assert!(
        (physical_s - estimate).abs() <= 1e-5 * estimate,
        "estimate {estimate} s, simulated {physical_s} s"
    );
}

#[test]
fn msra_grid12x8_full_run_triggers_eight_cameras_together() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("grid");
    run_ok(&[
        "run",
        "--sim",
        "--profile",
        common::repo_file("rig-profiles/msra-btf-mdf.toml")
            .to_str()
            .expect("utf8"),
        "--plan",
        "grid12x8",
        "--frame-size",
        "16x12",
        "--progress",
        "none",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    let m = assert_complete_run(&out, 9216);
    assert_eq!(m.triggers_total, 1152);
    // Images of one trigger share their exposure time and set-points.
    let mut by_trigger = std::collections::BTreeMap::<usize, Vec<&rigd::store::FrameEntry>>::new();
    for f in &m.frames {
        by_trigger.entry(f.trigger).or_default().push(f);
    }
    assert_eq!(by_trigger.len(), 1152);
    for frames in by_trigger.values() {
        assert_eq!(frames.len(), 8);
        assert!(frames
            .iter()
            .all(|f| f.t_s == frames[0].t_s && f.positions == frames[0].positions));
    }
    // The MSRA cameras deliver 8 bits.
    assert_eq!(m.frames[0].bit_depth, 8);
    assert_eq!(m.infeasible.len(), 768);
    assert_estimate_matches("grid12x8", "msra-btf-mdf", m.physical_duration_s);
}

#[test]
fn virtex_default_plan_is_one_frame_per_lamp() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("ps");
    run_ok(&[
        "run",
        "--sim",
        "--profile",
        "virtex-photometric-stereo",
        "--progress",
        "none",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    let m = assert_complete_run(&out, 3);
    assert_eq!(m.plan, "lamps");
    assert!(m.infeasible.is_empty());
    let lamps: Vec<&str> = m.frames.iter().map(|f| f.positions.lamp.as_str()).collect();
    assert_eq!(lamps, ["lamp0", "lamp1", "lamp2"]);
    // Each frame is lit: brighter than the unlit holder.
    for f in &m.frames {
        let bytes = std::fs::read(out.join(&f.file)).expect("frame");
        let img = rigd::rig::camera_file::decode(&bytes).expect("the camera's DNG");
        assert!(
            img.samples.iter().copied().max().unwrap_or(0) > 1000,
            "{} is dark",
            f.file
        );
    }
}

/// Captures the MSRA rig's grid12x8 in 1×1 frames with `profile` on the
/// simulated rig, to completion; returns the manifest and the firmware's
/// fault injector, whose counters say what each device was sent.
async fn msra_grid_capture(
    profile: rigd::model::profile::Profile,
    source: &str,
) -> (
    rigd::store::Manifest,
    std::sync::Arc<rigd_sim::FaultInjector>,
) {
    use rigd::engine::launch::{prepare_new, NewRun};
    use rigd::engine::PausePolicy;
    use rigd::model::run_state::RunState;
    use rigd::rig::sim::SimulatedRig;

    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("grid");
    let p = prepare_new(
        NewRun {
            profile,
            profile_source: source.into(),
            plan: "grid12x8".into(),
            sample: "grid".into(),
            operator: None,
            notes: None,
            exposure_s: None,
            exposure_policy: None,
            frame_size: Some([1, 1]),
            out: out.clone(),
            simulated: true,
            order: None,
        },
        Some(&SimulatedRig::new(vec![])),
        rigd_core::Clock::virtual_time(),
        PausePolicy::Return,
    )
    .await
    .expect("prepare");
    let faults = p.sim.as_ref().expect("simulated rig").faults.clone();
    let outcome = p.engine.run().await.expect("run");
    assert_eq!(outcome.state, RunState::Completed);
    (assert_complete_run(&out, 9216), faults)
}

/// A step commands only the devices whose set-point changed: on the MSRA
/// rig the grid's lights change more often than its views, and every move
/// not made is a round trip the serial line is spared. Counted at the
/// simulated GRBL firmware, against the set-points the frames record.
#[tokio::test(start_paused = true)]
async fn devices_already_in_place_are_not_commanded() {
    let profile = rigd::model::profile::Profile::load("msra-btf-mdf").expect("profile");
    let (m, faults) = msra_grid_capture(profile, "<embedded msra-btf-mdf>").await;
    // One pose per trigger, in the order they were taken.
    let mut poses = std::collections::BTreeMap::new();
    for f in &m.frames {
        poses.insert((f.t_s.to_bits(), f.trigger), f.positions.clone());
    }
    assert_eq!(poses.len(), 1152);
    for axis in ["turntable", "light_arc"] {
        let mut last = None;
        let mut changes = 0u64;
        for pose in poses.values() {
            let at = pose.axes.get(axis).copied();
            if at != last {
                changes += 1;
                last = at;
            }
        }
        let moves = faults.calls(axis, "move");
        assert_eq!(
            moves, changes,
            "{axis}: moves sent against poses that changed"
        );
        assert!(moves < 1152, "{axis} was commanded on every trigger");
    }
}

/// Three GRBL boards as they ship (factory settings: `$22=0`, `$110=500`,
/// `$120=10`), a turntable without a home switch (`homing = false`), and
/// `configure = true` on every axis: rigd writes each board's settings at
/// connect, never sends the turntable `$H`, takes its zero from the
/// operator, and the run completes through the real driver.
#[tokio::test(start_paused = true)]
async fn a_turntable_without_homing_completes_a_run() {
    let text = std::fs::read_to_string(common::repo_file("rig-profiles/msra-btf-mdf.toml"))
        .expect("read profile");
    let mut text = text;
    for axis in ["turntable", "light_arc", "laser_tilt"] {
        let from = format!("[devices.{axis}]\nkind = \"axis\"\n");
        assert!(text.contains(&from), "fixture drifted");
        let homing = if axis == "turntable" {
            "homing = false\n"
        } else {
            ""
        };
        text = text.replacen(&from, &format!("{from}{homing}configure = true\n"), 1);
    }
    // The turntable's `home_deg = 0.0` is allowed: 0 is its mark.
    let text = text.replacen("[sim]\n", "[sim]\ngrbl_settings = \"factory\"\n", 1);
    let source = "msra-stock-grbl.toml";
    let profile = rigd::model::profile::Profile::parse(&text, source).expect("profile");
    let (_, faults) = msra_grid_capture(profile, source).await;
    assert_eq!(faults.calls("turntable", "home"), 0, "`$H` sent");
    assert!(faults.calls("light_arc", "home") >= 1);
    assert!(faults.calls("turntable", "move") > 0);
    // `$110` and `$120` for all; `$22` for the two that home, and `$130`
    // where the factory's 200 does not cover the limits (the light arc's
    // 360°, not the laser tilt's 60°).
    for (axis, writes) in [("turntable", 2), ("light_arc", 4), ("laser_tilt", 3)] {
        assert_eq!(faults.calls(axis, "configure"), writes, "{axis}");
    }
}
