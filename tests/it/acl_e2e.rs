//! The ACL arm driver against the simulated controller over an in-memory
//! pipe, in virtual time: homing, joint-interpolated move timing, soft
//! limits, every fault kind, abort mid-move, and re-sync after a reconnect.

use std::sync::Arc;
use std::time::Duration;

use proptest::prelude::*;
use rigd::model::profile::{Limits, Motion};
use rigd::rig::drivers::acl::{AclArm, AclConfig, AclJointConfig};
use rigd::rig::hal::{Arm, ErrorKind};
use rigd_core::Clock;
use rigd_sim::firmware::acl::{move_duration, serve, AclParams};
use rigd_sim::{FaultInjector, FaultRule};
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};

fn wrist() -> Vec<AclJointConfig> {
    let p = AclParams::default();
    ["roll", "pitch", "twist"]
        .iter()
        .zip(&p.joints)
        .map(|(n, j)| AclJointConfig {
            name: n.to_string(),
            limits: Limits {
                min: j.min_deg,
                max: j.max_deg,
            },
            motion: Motion {
                max_velocity: j.motion.max_velocity,
                acceleration: j.motion.acceleration,
                settle_s: j.motion.settle_s,
            },
            counts_per_deg: j.counts_per_deg,
            home_deg: 0.0,
        })
        .collect()
}

fn start(p: AclParams, clock: &Clock, faults: Arc<FaultInjector>) -> DuplexStream {
    let (host, dev) = tokio::io::duplex(4096);
    tokio::spawn(serve(dev, p, clock.clone(), faults));
    host
}

async fn homed(faults: Arc<FaultInjector>) -> (AclArm<DuplexStream>, Clock) {
    let clock = Clock::virtual_time();
    let host = start(AclParams::default(), &clock, faults);
    let cfg = AclConfig::new("arm", wrist());
    let mut arm = AclArm::connect(host, cfg, clock.clone())
        .await
        .expect("connect");
    let t0 = clock.now_s();
    let pose = arm.home().await.expect("home");
    assert_eq!(pose, vec![0.0, 0.0, 0.0]);
    let dt = clock.now_s() - t0;
    assert!((12.0..12.01).contains(&dt), "homing took {dt}");
    (arm, clock)
}

fn rule(s: &str) -> FaultRule {
    s.parse().expect("rule")
}

#[tokio::test(start_paused = true)]
async fn move_takes_the_slowest_joints_time() {
    let (mut arm, clock) = homed(Arc::new(FaultInjector::default())).await;
    let p = AclParams::default();
    let target = [30.0, 45.0, -90.0];
    let counts = [3000, 4500, -4500];
    let t = move_duration(&p.joints, &[0, 0, 0], &counts, 0.0);
    assert!((t - 2.3).abs() < 1e-9, "twist decides: {t}");
    let t0 = clock.now_s();
    let pose = arm.move_joints(&target).await.expect("move");
    let dt = clock.now_s() - t0;
    let poll = AclConfig::new("x", vec![]).poll_interval.as_secs_f64();
    assert!(dt >= t && dt <= t + poll + 1e-3, "took {dt}, model {t}");
    for (g, w) in pose.iter().zip(target) {
        assert!((g - w).abs() < 1e-9, "{pose:?}");
    }
    // A second move from there: the roll now decides.
    let t = move_duration(&p.joints, &counts, &[-9000, 4500, -4500], 0.0);
    let t0 = clock.now_s();
    arm.move_joints(&[-90.0, 45.0, -90.0]).await.expect("move");
    let dt = clock.now_s() - t0;
    assert!(dt >= t && dt <= t + poll + 1e-3, "took {dt}, model {t}");
}

#[tokio::test(start_paused = true)]
async fn out_of_limits_is_refused_without_sending() {
    let faults = Arc::new(FaultInjector::default());
    let (mut arm, clock) = homed(faults.clone()).await;
    // If the refused moves sent anything, DEFP would be the first `define`
    // and this rule would close the link then.
    faults.arm(rule("arm:define:1:disconnect"));
    let t0 = clock.now_s();
    let e = arm.move_joints(&[0.0, 95.0, 0.0]).await.expect_err("pitch");
    assert_eq!(e.kind, ErrorKind::OutOfLimits);
    assert!(e.message.contains("pitch"), "{e}");
    let e = arm
        .move_joints(&[0.0, f64::NAN, 0.0])
        .await
        .expect_err("nan");
    assert_eq!(e.kind, ErrorKind::OutOfLimits);
    let e = arm.move_joints(&[0.0, 1.0]).await.expect_err("count");
    assert_eq!(e.kind, ErrorKind::OutOfLimits);
    assert_eq!(clock.now_s(), t0, "nothing waited for the device");
    let e = arm
        .move_joints(&[0.0, 1.0, 0.0])
        .await
        .expect_err("now sent");
    assert_eq!(e.kind, ErrorKind::Disconnected);
}

#[tokio::test(start_paused = true)]
async fn each_fault_maps_to_its_kind() {
    let (mut arm, _) = homed(Arc::new(FaultInjector::new(vec![rule(
        "arm:move:1:timeout",
    )])))
    .await;
    let e = arm.move_joints(&[10.0, 10.0, 10.0]).await.expect_err("t");
    assert_eq!(e.kind, ErrorKind::Timeout);
    // The swallowed line does not confuse the next exchange.
    let pose = arm.move_joints(&[10.0, 10.0, 10.0]).await.expect("retry");
    assert!((pose[2] - 10.0).abs() < 1e-9);

    let (mut arm, _) = homed(Arc::new(FaultInjector::new(vec![rule(
        "arm:move:1:alarm=impact protection",
    )])))
    .await;
    let e = arm.move_joints(&[10.0, 10.0, 10.0]).await.expect_err("a");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("*** impact protection"), "{e}");
    // Control went off: homing again turns it on.
    arm.home().await.expect("re-home");
    arm.move_joints(&[10.0, 10.0, 10.0])
        .await
        .expect("after re-home");

    let (mut arm, _) = homed(Arc::new(FaultInjector::new(vec![rule(
        "arm:query:4:disconnect",
    )])))
    .await;
    let e = arm.joints().await.expect_err("d");
    assert_eq!(e.kind, ErrorKind::Disconnected);
}

#[tokio::test(start_paused = true)]
async fn device_errors_arrive_in_the_devices_words() {
    let clock = Clock::virtual_time();
    let host = start(
        AclParams::default(),
        &clock,
        Arc::new(FaultInjector::default()),
    );
    let mut arm = AclArm::connect(host, AclConfig::new("arm", wrist()), clock)
        .await
        .expect("connect");
    let e = arm
        .move_joints(&[1.0, 1.0, 1.0])
        .await
        .expect_err("unhomed");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("*** not homed"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn abort_mid_move_stops_motion() {
    let (mut arm, clock) = homed(Arc::new(FaultInjector::default())).await;
    let r = clock
        .deadline(
            Duration::from_secs(1),
            arm.move_joints(&[100.0, 80.0, 300.0]),
        )
        .await;
    assert!(r.is_err(), "the move must still be running");
    let stopped = arm.abort().await.expect("abort");
    assert!(stopped[0] > 0.0 && stopped[0] < 100.0, "{stopped:?}");
    assert!(stopped[2] > 0.0 && stopped[2] < 300.0, "{stopped:?}");
    clock.sleep_s(20.0).await;
    let later = arm.joints().await.expect("joints");
    assert_eq!(later, stopped, "nothing moved after the abort");
}

#[tokio::test(start_paused = true)]
async fn reconnect_rereads_the_pose_from_the_controller() {
    let clock = Clock::virtual_time();
    let faults = Arc::new(FaultInjector::new(vec![rule("arm:move:1:disconnect")]));
    let host = start(AclParams::default(), &clock, faults.clone());
    let mut arm = AclArm::connect(host, AclConfig::new("arm", wrist()), clock.clone())
        .await
        .expect("connect");
    arm.home().await.expect("home");
    let e = arm.move_joints(&[5.0, 5.0, 5.0]).await.expect_err("drop");
    assert_eq!(e.kind, ErrorKind::Disconnected);
    // The controller kept its position (here: someone jogged it meanwhile).
    let p = AclParams {
        power_up_counts: vec![1000, 2000, 500],
        start_homed: true,
        ..AclParams::default()
    };
    let host = start(p, &clock, faults);
    let pose = arm.reconnect(host).await.expect("reconnect");
    assert_eq!(pose, vec![10.0, 20.0, 10.0]);
    assert_eq!(arm.last_status().map(|s| s.homed), Some(true));
    let pose = arm.move_joints(&[0.0, 0.0, 0.0]).await.expect("move");
    assert_eq!(pose, vec![0.0, 0.0, 0.0]);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn simulator_survives_arbitrary_input(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .start_paused(true)
            .build()
            .expect("runtime");
        let ok = rt.block_on(async move {
            let clock = Clock::virtual_time();
            let mut host = start(AclParams::default(), &clock, Arc::new(FaultInjector::default()));
            host.write_all(&bytes).await.expect("write");
            host.write_all(b"\rSTATUS\r").await.expect("write");
            let mut seen = Vec::new();
            let mut buf = [0u8; 1024];
            let found = clock.deadline(Duration::from_secs(3600), async {
                loop {
                    let n = host.read(&mut buf).await.expect("read");
                    if n == 0 { return false; }
                    seen.extend_from_slice(&buf[..n]);
                    if String::from_utf8_lossy(&seen).contains("HOMED=") { return true; }
                }
            }).await;
            found == Ok(true)
        });
        prop_assert!(ok, "simulator stopped answering");
    }
}
