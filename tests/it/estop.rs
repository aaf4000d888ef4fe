//! The emergency stop in the middle of a run through the real drivers:
//! every device acknowledges, the lamps go dark, the run pauses with the
//! reason, and after the operator resumes it re-homes and completes with
//! every frame exactly once.

use crate::common;

use common::assert_complete_run;
use rigd::engine::command::Command;
use rigd::engine::launch::{prepare_new, NewRun};
use rigd::engine::{EventKind, PausePolicy, RunEvent, ESTOP_REASON};
use rigd::model::profile::Profile;
use rigd::model::run_state::RunState;
use rigd::rig::sim::SimulatedRig;
use rigd_core::Clock;
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::broadcast::Receiver;

async fn next_event(events: &mut Receiver<RunEvent>) -> EventKind {
    loop {
        match events.recv().await {
            Ok(ev) => return ev.kind,
            Err(RecvError::Lagged(_)) => continue,
            Err(RecvError::Closed) => panic!("the engine stopped sending events"),
        }
    }
}

#[tokio::test(start_paused = true)]
async fn emergency_stop_mid_run_pauses_and_resume_rehomes_and_completes() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let req = NewRun {
        profile: Profile::load("bonn-gonioreflectometer").expect("profile"),
        profile_source: "<embedded bonn-gonioreflectometer>".into(),
        plan: "h1".into(),
        sample: "estop".into(),
        operator: None,
        notes: None,
        exposure_s: None,
        exposure_policy: None,
        frame_size: Some([8, 8]),
        out: out.clone(),
        simulated: true,
        order: None,
    };
    let p = prepare_new(
        req,
        Some(&SimulatedRig::new(vec![])),
        Clock::virtual_time(),
        PausePolicy::Wait,
    )
    .await
    .expect("prepare");
    let sim = p.sim.clone().expect("simulated rig");
    let mut events = p.handle.events.subscribe();
    let handle = p.handle.clone();
    let engine = tokio::spawn(p.engine.run());
    loop {
        if let EventKind::Step { frames_done, .. } = next_event(&mut events).await {
            if frames_done >= 40 {
                break;
            }
        }
    }
    assert_eq!(sim.world().lamps_on.get("hmi"), Some(&true));

    let report = handle.emergency_stop().await;
    let mut names: Vec<&str> = report.devices.iter().map(|d| d.device.as_str()).collect();
    names.sort();
    assert_eq!(names.len(), 3, "{report:?}");
    assert!(
        names.contains(&"rail") && names.contains(&"arm"),
        "{names:?}"
    );
    assert!(
        names.iter().any(|n| n.starts_with("modbus-rtu:")),
        "{names:?}"
    );
    assert!(report.all_stopped(), "{report:?}");
    assert!(
        report.latency_s >= 0.0 && report.latency_s < 2.0,
        "{report:?}"
    );
    // The relay module dropped every coil.
    assert_eq!(sim.world().lamps_on.get("hmi"), Some(&false));

    let reason = loop {
        match next_event(&mut events).await {
            EventKind::State {
                to: RunState::Paused,
                reason,
                ..
            } => break reason.unwrap_or_default(),
            EventKind::State {
                to: RunState::Completed,
                ..
            } => panic!("completed through an emergency stop"),
            _ => {}
        }
    };
    assert_eq!(reason, ESTOP_REASON);

    handle.commands.send(Command::Resume).await.expect("resume");
    // Resuming re-homes (Preparing) before it captures again.
    loop {
        match next_event(&mut events).await {
            EventKind::State {
                to: RunState::Preparing,
                ..
            } => break,
            EventKind::Step { .. } => panic!("captured before re-homing"),
            _ => {}
        }
    }
    let outcome = engine.await.expect("join").expect("engine");
    assert_eq!(outcome.state, RunState::Completed, "{:?}", outcome.reason);
    assert_complete_run(&out, 6561);
}
