//! Every kind of device fault, injected into the simulated firmware in the
//! middle of an H1 run on the Bonn rig and met by the real drivers. The
//! outcome is always a complete dataset with every frame exactly once and
//! valid checksums: directly when the engine could retry, or after a pause
//! whose reason names the device, and a resume once the fault is cleared.

use crate::common;

use common::assert_complete_run;
use rigd::engine::command::Command;
use rigd::engine::launch::{prepare_new, NewRun};
use rigd::engine::{EventKind, PausePolicy};
use rigd::model::profile::Profile;
use rigd::model::run_state::RunState;
use rigd::rig::sim::SimulatedRig;
use rigd_core::Clock;
use rigd_sim::FaultRule;
use tokio::sync::broadcast::error::RecvError;

/// What the operator saw: the reasons of every pause, in order.
async fn run_with_fault(rule: &str) -> Vec<String> {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let req = NewRun {
        profile: Profile::load("bonn-gonioreflectometer").expect("profile"),
        profile_source: "<embedded bonn-gonioreflectometer>".into(),
        plan: "h1".into(),
        sample: "faults".into(),
        operator: None,
        notes: None,
        exposure_s: None,
        exposure_policy: None,
        frame_size: Some([8, 8]),
        out: out.clone(),
        simulated: true,
        order: None,
    };
    let rule: FaultRule = rule.parse().expect("fault rule");
    let device = rule.device.clone();
    let p = prepare_new(
        req,
        Some(&SimulatedRig::new(vec![rule])),
        Clock::virtual_time(),
        PausePolicy::Wait,
    )
    .await
    .expect("prepare");
    let faults = p.sim.as_ref().expect("simulated rig").faults.clone();
    let mut events = p.handle.events.subscribe();
    let commands = p.handle.commands.clone();
    let engine = tokio::spawn(p.engine.run());
    drop(p.handle);
    let mut pauses = Vec::new();
    loop {
        match events.recv().await {
            Ok(ev) => match ev.kind {
                EventKind::State {
                    to: RunState::Paused,
                    reason,
                    ..
                } => {
                    pauses.push(reason.unwrap_or_default());
                    assert!(pauses.len() <= 3, "paused again and again: {pauses:?}");
                    // The operator fixes the device and resumes.
                    faults.clear(&device);
                    commands.send(Command::Resume).await.expect("resume");
                }
                EventKind::State { to, .. } if to.ends_session() => break,
                _ => {}
            },
            Err(RecvError::Lagged(_)) => continue,
            Err(RecvError::Closed) => break,
        }
    }
    drop(commands);
    let outcome = engine.await.expect("join").expect("engine");
    assert_eq!(outcome.state, RunState::Completed, "{:?}", outcome.reason);
    assert_complete_run(&out, 6561);
    pauses
}

fn assert_one_pause_naming(pauses: &[String], device: &str, words: &[&str]) {
    assert_eq!(pauses.len(), 1, "{pauses:?}");
    let r = &pauses[0];
    assert!(r.starts_with(&format!("{device}:")), "{r}");
    for w in words {
        assert!(r.contains(w), "`{w}` missing from: {r}");
    }
}

#[tokio::test(start_paused = true)]
async fn grbl_disconnect_pauses_then_reconnects_and_rehomes() {
    let pauses = run_with_fault("rail:move:300:disconnect").await;
    assert_one_pause_naming(&pauses, "rail", &["disconnected"]);
}

#[tokio::test(start_paused = true)]
async fn grbl_homing_failure_pauses_then_homes_again() {
    let pauses = run_with_fault("rail:home:1:alarm=Homing fail pull-off").await;
    assert_one_pause_naming(&pauses, "rail", &["ALARM:1", "Homing fail"]);
}

#[tokio::test(start_paused = true)]
async fn arm_disconnect_pauses_then_reconnects_keeping_its_counts() {
    let pauses = run_with_fault("arm:move:500:disconnect").await;
    assert_one_pause_naming(&pauses, "arm", &["disconnected"]);
}

#[tokio::test(start_paused = true)]
async fn arm_garbled_reply_is_handled() {
    // A garbled line is a protocol error: retried if the driver can tell,
    // else a pause naming the arm. Either way nothing is lost.
    let pauses = run_with_fault("arm:move:200:bad-frame").await;
    assert!(pauses.len() <= 1, "{pauses:?}");
    assert!(pauses.iter().all(|r| r.starts_with("arm:")), "{pauses:?}");
}

#[tokio::test(start_paused = true)]
async fn modbus_exception_reply_pauses_with_the_module_s_words() {
    // The relay module refuses the coil write with exception 04 (server
    // device failure); set #2 is the lamp's switch-on during preparation.
    let pauses = run_with_fault("hmi:set:2:alarm=relay welded").await;
    assert_one_pause_naming(&pauses, "hmi", &["exception"]);
}

#[tokio::test(start_paused = true)]
async fn lamp_that_never_becomes_ready_pauses_and_is_struck_again() {
    let pauses = run_with_fault("hmi:ready:3:alarm=no ignition").await;
    assert_one_pause_naming(&pauses, "hmi", &["fault"]);
}

#[tokio::test(start_paused = true)]
async fn stalled_camera_transfer_is_retried_then_pauses() {
    let pauses = run_with_fault("camera:transfer:40:timeout:sticky").await;
    assert_one_pause_naming(&pauses, "camera", &["timeout"]);
}

#[tokio::test(start_paused = true)]
async fn camera_capture_failure_pauses() {
    let pauses = run_with_fault("camera:expose:25:alarm=shutter jammed").await;
    assert_one_pause_naming(&pauses, "camera", &["GeneralError"]);
}

#[tokio::test(start_paused = true)]
async fn camera_disconnect_pauses_then_opens_a_new_session() {
    let pauses = run_with_fault("camera:expose:60:disconnect").await;
    assert_one_pause_naming(&pauses, "camera", &["disconnected"]);
}
