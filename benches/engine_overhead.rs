//! The cost per step of the engine and the driver path: a whole H1 run
//! (6561 steps) on the simulated Bonn rig in virtual time, so device waits
//! cost no wall time. Every step goes through the real drivers (GRBL, ACL,
//! PTP, Modbus codecs, status polling) to the simulated firmware over
//! in-memory pipes. Frames are 1 × 1, so image encoding is negligible, and
//! the run directory is on tmpfs when there is one (fsync is then cheap, so
//! this is software overhead, not the disk's). Criterion reports steps per
//! second; the time per step is its inverse.
//!
//! The second group presses the emergency stop in the middle of a run and
//! measures the wall time until every device acknowledged; it prints the
//! latency in physical (virtual) time that the stop report gives.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use rigd::engine::launch::{prepare_new, NewRun};
use rigd::engine::PausePolicy;
use rigd::model::profile::Profile;
use rigd::model::run_state::RunState;
use rigd::rig::sim::SimulatedRig;
use rigd_core::Clock;

fn scratch_root() -> PathBuf {
    let shm = PathBuf::from("/dev/shm");
    if shm.is_dir() {
        shm
    } else {
        std::env::temp_dir()
    }
}

fn one_run(plan: &str) -> Duration {
    let tmp = tempfile::tempdir_in(scratch_root()).expect("tempdir");
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .start_paused(true)
        .build()
        .expect("runtime");
    runtime.block_on(async {
        let req = NewRun {
            profile: Profile::load("bonn-gonioreflectometer").expect("profile"),
            profile_source: "<embedded bonn-gonioreflectometer>".into(),
            plan: plan.into(),
            sample: "bench".into(),
            operator: None,
            notes: None,
            exposure_s: None,
            exposure_policy: None,
            frame_size: Some([1, 1]),
            out: tmp.path().join("run"),
            simulated: true,
            order: None,
        };
        let p = prepare_new(
            req,
            Some(&SimulatedRig::new(vec![])),
            Clock::virtual_time(),
            PausePolicy::Return,
        )
        .await
        .expect("prepare");
        let start = Instant::now();
        let outcome = p.engine.run().await.expect("run");
        let took = start.elapsed();
        assert_eq!(outcome.state, RunState::Completed);
        took
    })
}

fn engine_overhead(c: &mut Criterion) {
    let mut group = c.benchmark_group("engine");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(35));
    group.throughput(Throughput::Elements(6561));
    group.bench_function("h1_6561_steps_through_drivers", |b| {
        b.iter_custom(|iters| (0..iters).map(|_| one_run("h1")).sum())
    });
    group.finish();
}

/// One emergency stop after `frames` frames of an H1 run: the wall time of
/// the stop, and the physical latency its report gives.
fn one_stop(frames: usize) -> (Duration, f64, usize) {
    let tmp = tempfile::tempdir_in(scratch_root()).expect("tempdir");
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .start_paused(true)
        .build()
        .expect("runtime");
    runtime.block_on(async {
        let req = NewRun {
            profile: Profile::load("bonn-gonioreflectometer").expect("profile"),
            profile_source: "<embedded bonn-gonioreflectometer>".into(),
            plan: "h1".into(),
            sample: "bench".into(),
            operator: None,
            notes: None,
            exposure_s: None,
            exposure_policy: None,
            frame_size: Some([1, 1]),
            out: tmp.path().join("run"),
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
        let mut events = p.handle.events.subscribe();
        let handle = p.handle.clone();
        let engine = tokio::spawn(p.engine.run());
        loop {
            match events.recv().await {
                Ok(ev) => {
                    if let rigd::engine::EventKind::Step { frames_done, .. } = ev.kind {
                        if frames_done >= frames {
                            break;
                        }
                    }
                }
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => continue,
                Err(e) => panic!("events: {e}"),
            }
        }
        let start = Instant::now();
        let report = handle.emergency_stop().await;
        let took = start.elapsed();
        assert!(report.all_stopped(), "{report:?}");
        handle
            .commands
            .send(rigd::engine::command::Command::Abort)
            .await
            .expect("abort");
        engine.await.expect("join").expect("engine");
        (took, report.latency_s, report.devices.len())
    })
}

fn emergency_stop(c: &mut Criterion) {
    let (_, latency_s, devices) = one_stop(5);
    println!(
        "emergency stop: {devices} stops (axes, arm, lamp bus), physical latency to the last acknowledgement {:.3} ms",
        latency_s * 1e3
    );
    let mut group = c.benchmark_group("estop");
    group.sample_size(10);
    group.bench_function("bonn_h1_stop_mid_run_wall", |b| {
        b.iter_custom(|iters| (0..iters).map(|_| one_stop(5).0).sum())
    });
    group.finish();
}

criterion_group!(benches, engine_overhead, emergency_stop);
criterion_main!(benches);
