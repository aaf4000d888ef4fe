//! Device faults in the middle of a run: retried where that is safe, a pause
//! with the device's reason where it is not, and a complete dataset after
//! the fault clears and the run resumes.

use crate::common;

use std::time::Duration;

use common::{assert_complete_run, rigd};
use rigd::engine::command::Command;
use rigd::engine::launch::{prepare_new, NewRun};
use rigd::engine::{EventKind, PausePolicy, RunEvent};
use rigd::model::profile::Profile;
use rigd::model::run_state::RunState;
use rigd::rig::sim::SimulatedRig;
use rigd_core::Clock;
use rigd_sim::FaultRule;
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::broadcast::Receiver;

fn new_run(out: &std::path::Path, plan: &str) -> NewRun {
    NewRun {
        profile: Profile::load("bonn-gonioreflectometer").expect("profile"),
        profile_source: "<embedded bonn-gonioreflectometer>".into(),
        plan: plan.into(),
        sample: "fault-test".into(),
        operator: None,
        notes: None,
        exposure_s: None,
        exposure_policy: None,
        frame_size: Some([16, 16]),
        out: out.to_path_buf(),
        simulated: true,
        order: None,
    }
}

/// The next event, skipping over any the test was too slow to see.
async fn next_event(events: &mut Receiver<RunEvent>) -> EventKind {
    loop {
        match events.recv().await {
            Ok(ev) => return ev.kind,
            Err(RecvError::Lagged(_)) => continue,
            Err(RecvError::Closed) => panic!("the engine stopped sending events"),
        }
    }
}

/// Waits until at least `n` frames are written.
async fn wait_frames(events: &mut Receiver<RunEvent>, n: usize) -> usize {
    loop {
        if let EventKind::Step { frames_done, .. } = next_event(events).await {
            if frames_done >= n {
                return frames_done;
            }
        }
    }
}

/// Waits for the run to pause; returns the reason.
async fn wait_paused(events: &mut Receiver<RunEvent>) -> String {
    loop {
        match next_event(events).await {
            EventKind::State {
                to: RunState::Paused,
                reason,
                ..
            } => return reason.unwrap_or_default(),
            EventKind::State {
                to: RunState::Completed,
                ..
            } => panic!("completed without pausing"),
            _ => {}
        }
    }
}

fn rule(s: &str) -> FaultRule {
    s.parse().expect("fault rule")
}

#[tokio::test(start_paused = true)]
async fn alarm_pauses_with_reason_and_resume_completes_after_clearing() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let p = prepare_new(
        new_run(&out, "h1"),
        Some(&SimulatedRig::new(vec![rule(
            "rail:move:300:alarm=ALARM 1 hard limit:sticky",
        )])),
        Clock::virtual_time(),
        PausePolicy::Wait,
    )
    .await
    .expect("prepare");
    let mut events = p.handle.events.subscribe();
    let commands = p.handle.commands.clone();
    let faults = p.sim.as_ref().expect("simulated rig").faults.clone();
    let engine = tokio::spawn(p.engine.run());
    // Wait for the pause, counting the frames written before it.
    let mut frames_at_pause = 0;
    let reason = loop {
        match next_event(&mut events).await {
            EventKind::Step { frames_done, .. } => frames_at_pause = frames_done,
            EventKind::State {
                to: RunState::Paused,
                reason,
                ..
            } => break reason.unwrap_or_default(),
            EventKind::State {
                to: RunState::Completed,
                ..
            } => panic!("the fault never fired"),
            _ => {}
        }
    };
    assert!(
        reason.contains("rail") && reason.contains("ALARM 1 hard limit"),
        "{reason}"
    );
    assert!(
        frames_at_pause > 200 && frames_at_pause < 400,
        "{frames_at_pause}"
    );
    let state = rigd::store::read_state(&out)
        .expect("state")
        .expect("state.json");
    assert_eq!(state.state, RunState::Paused);
    // Resuming before the fault is cleared pauses again with the same reason.
    commands.send(Command::Resume).await.expect("send");
    let again = wait_paused(&mut events).await;
    assert!(again.contains("ALARM 1"), "{again}");
    // The operator clears the alarm and resumes.
    faults.clear("rail");
    commands.send(Command::Resume).await.expect("send");
    let outcome = engine.await.expect("join").expect("engine");
    assert_eq!(outcome.state, RunState::Completed, "{:?}", outcome.reason);
    assert_eq!(outcome.frames_written, 6561);
    assert_complete_run(&out, 6561);
}

#[tokio::test(start_paused = true)]
async fn one_timeout_and_one_bad_frame_are_retried_without_a_pause() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let p = prepare_new(
        new_run(&out, "h1"),
        Some(&SimulatedRig::new(vec![
            rule("arm:move:40:timeout"),
            rule("camera:transfer:70:bad-frame"),
        ])),
        Clock::virtual_time(),
        PausePolicy::Wait,
    )
    .await
    .expect("prepare");
    let mut events = p.handle.events.subscribe();
    let collector = tokio::spawn(async move {
        let mut retries = Vec::new();
        loop {
            match events.recv().await {
                Ok(ev) => match ev.kind {
                    EventKind::Retry { device, .. } => retries.push(device),
                    EventKind::State {
                        to: RunState::Paused,
                        reason,
                        ..
                    } => panic!("paused: {reason:?}"),
                    _ => {}
                },
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => continue,
                Err(_) => return retries,
            }
        }
    });
    let engine = tokio::spawn(p.engine.run());
    drop(p.handle);
    let outcome = engine.await.expect("join").expect("engine");
    assert_eq!(outcome.state, RunState::Completed, "{:?}", outcome.reason);
    let mut retries = collector.await.expect("collector");
    retries.sort();
    assert_eq!(retries, ["arm", "camera"]);
    assert_complete_run(&out, 6561);
}

#[tokio::test(start_paused = true)]
async fn operator_pause_and_resume_lose_nothing() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let p = prepare_new(
        new_run(&out, "h2"),
        Some(&SimulatedRig::new(vec![])),
        Clock::virtual_time(),
        PausePolicy::Wait,
    )
    .await
    .expect("prepare");
    let mut events = p.handle.events.subscribe();
    let commands = p.handle.commands.clone();
    let engine = tokio::spawn(p.engine.run());
    wait_frames(&mut events, 1000).await;
    commands.send(Command::Pause).await.expect("send");
    wait_paused(&mut events).await;
    // While paused, virtual hours pass and nothing is captured.
    let before = rigd::store::read_journal(&out.join("journal.ndjson"))
        .expect("journal")
        .0
        .len();
    tokio::time::sleep(Duration::from_secs(7200)).await;
    let after = rigd::store::read_journal(&out.join("journal.ndjson"))
        .expect("journal")
        .0
        .len();
    assert_eq!(before, after);
    // A second pause is refused, not fatal.
    commands.send(Command::Pause).await.expect("send");
    commands.send(Command::Resume).await.expect("send");
    let outcome = engine.await.expect("join").expect("engine");
    assert_eq!(outcome.state, RunState::Completed);
    assert_complete_run(&out, 6561);
}

#[tokio::test(start_paused = true)]
async fn abort_ends_the_run_with_a_manifest_of_what_was_taken() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let p = prepare_new(
        new_run(&out, "h1"),
        Some(&SimulatedRig::new(vec![])),
        Clock::virtual_time(),
        PausePolicy::Wait,
    )
    .await
    .expect("prepare");
    let mut events = p.handle.events.subscribe();
    let commands = p.handle.commands.clone();
    let engine = tokio::spawn(p.engine.run());
    wait_frames(&mut events, 100).await;
    commands.send(Command::Abort).await.expect("send");
    let outcome = engine.await.expect("join").expect("engine");
    assert_eq!(outcome.state, RunState::Aborted);
    let m: rigd::store::Manifest =
        serde_json::from_slice(&std::fs::read(out.join("manifest.json")).expect("manifest"))
            .expect("parse");
    assert_eq!(m.state, rigd::model::run_state::RunState::Aborted);
    assert_eq!(m.frames.len(), outcome.frames_written);
    assert!(m.frames_written >= 100 && m.frames_written < 6561);
}

#[test]
fn command_line_pauses_on_a_fault_and_resume_completes() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("run");
    let d = dir.to_str().expect("utf8");
    let out = rigd()
        .args([
            "run",
            "--sim",
            "--plan",
            "h1",
            "--frame-size",
            "16x16",
            "--progress",
            "log",
            "--out",
            d,
            "--sim-fault",
            "rail:move:200:disconnect",
        ])
        .output()
        .expect("run");
    let stderr = String::from_utf8_lossy(&out.stderr);
    // A disconnect is not retried blindly: the run pauses, resumably.
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(
        stderr.contains("rail") && stderr.contains("disconnected"),
        "{stderr}"
    );
    assert!(stderr.contains("--resume"), "{stderr}");
    let out = rigd()
        .args(["run", "--resume", d, "--progress", "none"])
        .output()
        .expect("resume");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_complete_run(&dir, 6561);
}

#[test]
fn faults_configured_in_the_profile_fire_once_and_resume_completes() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let bonn = std::fs::read_to_string(common::repo_file(
        "rig-profiles/bonn-gonioreflectometer.toml",
    ))
    .expect("profile");
    assert!(bonn.contains("[sim]\n"));
    let with_fault = bonn.replace(
        "[sim]\n",
        "[sim]\nfaults = [\"camera:expose:150:alarm=shutter jammed\"]\n",
    );
    let profile = tmp.path().join("faulty.toml");
    std::fs::write(&profile, with_fault).expect("write");
    let dir = tmp.path().join("run");
    let d = dir.to_str().expect("utf8");
    let p = profile.to_str().expect("utf8");
    let out = rigd()
        .args([
            "run",
            "--sim",
            "--profile",
            p,
            "--plan",
            "h1",
            "--frame-size",
            "8x8",
            "--progress",
            "none",
            "--out",
            d,
        ])
        .output()
        .expect("run");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(
        stderr.contains("camera") && stderr.contains("GeneralError"),
        "{stderr}"
    );
    let out = rigd()
        .args(["run", "--resume", d, "--progress", "none"])
        .output()
        .expect("resume");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_complete_run(&dir, 6561);

    // A fault naming no device of the profile is refused up front.
    let bad = tmp.path().join("bad.toml");
    std::fs::write(
        &bad,
        bonn.replace("[sim]\n", "[sim]\nfaults = [\"lens:expose:1:timeout\"]\n"),
    )
    .expect("write");
    let out = rigd()
        .args(["profile", "check", bad.to_str().expect("utf8")])
        .output()
        .expect("check");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("sim.faults[0]") && stderr.contains("lens"),
        "{stderr}"
    );
}
