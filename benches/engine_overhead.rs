//! The run engine's own cost per step: a whole H1 run (6561 steps) on the
//! simulated Bonn rig in virtual time, so device waits cost no wall time,
//! with 1 × 1 frames, so image encoding is negligible, into a temporary
//! directory on tmpfs when there is one (fsync is then cheap, so this is the
//! engine's overhead, not the disk's). Criterion reports steps per second;
//! the time per step is its inverse.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use rigd::engine::{PausePolicy, RunState};
use rigd::profile::Profile;
use rigd::runner::{prepare_new, NewRun};
use rigd::sim::Clock;

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
            frame_size: Some([1, 1]),
            out: tmp.path().join("run"),
        };
        let p =
            prepare_new(req, vec![], Clock::virtual_time(), PausePolicy::Return).expect("prepare");
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
    group.bench_function("h1_6561_steps_zero_time_devices", |b| {
        b.iter_custom(|iters| (0..iters).map(|_| one_run("h1")).sum())
    });
    group.finish();
}

criterion_group!(benches, engine_overhead);
criterion_main!(benches);
