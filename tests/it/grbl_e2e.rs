//! The GRBL driver against the simulated GRBL firmware over an in-memory
//! pipe, in virtual time: homing, move timing, soft limits, every fault
//! kind, and position re-sync after a reconnect.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use rigd::model::profile::{Limits, Motion};
use rigd::rig::drivers::grbl::{GrblAxis, GrblConfig};
use rigd::rig::hal::{Axis, ErrorKind};
use rigd_core::Clock;
use rigd_core::Trapezoid;
use rigd_proto::grbl::MachineState;
use rigd_sim::firmware::grbl::{serve_with_stats, Eeprom, GrblParams, GrblStats};
use rigd_sim::{FaultInjector, FaultRule};
use tokio::io::DuplexStream;

const TRAP: Trapezoid = Trapezoid {
    max_velocity: 30.0,
    acceleration: 60.0,
    settle_s: 0.2,
};

fn params() -> GrblParams {
    GrblParams {
        name: "turntable".into(),
        motion: TRAP,
        home_position: 0.0,
        physical_start: 25.0,
        start_homed: false,
        settings: Eeprom::configured(TRAP, true, 360.0),
        reset_on_open: true,
        world: None,
        answer_delay_s: 0.0,
    }
}

fn config() -> GrblConfig {
    GrblConfig::new(
        "turntable",
        Limits {
            min: -10.0,
            max: 350.0,
        },
        Motion {
            max_velocity: TRAP.max_velocity,
            acceleration: TRAP.acceleration,
            settle_s: TRAP.settle_s,
        },
    )
}

fn rules(r: &[&str]) -> Arc<FaultInjector> {
    Arc::new(FaultInjector::new(
        r.iter()
            .map(|s| s.parse::<FaultRule>().expect("rule"))
            .collect(),
    ))
}

/// Starts a simulator and returns the host end of the pipe.
fn start_sim(
    p: GrblParams,
    clock: &Clock,
    faults: Arc<FaultInjector>,
) -> (DuplexStream, Arc<GrblStats>) {
    let (host, dev) = tokio::io::duplex(4096);
    let stats = Arc::new(GrblStats::default());
    tokio::spawn(serve_with_stats(
        dev,
        p,
        clock.clone(),
        faults,
        stats.clone(),
    ));
    (host, stats)
}

async fn connected(faults: Arc<FaultInjector>) -> (GrblAxis<DuplexStream>, Arc<GrblStats>, Clock) {
    let clock = Clock::virtual_time();
    let (host, stats) = start_sim(params(), &clock, faults);
    let axis = GrblAxis::connect(host, config(), clock.clone())
        .await
        .expect("connect");
    (axis, stats, clock)
}

#[tokio::test(start_paused = true)]
async fn homes_and_moves_in_modelled_time() {
    let (mut axis, stats, clock) = connected(Arc::default()).await;
    assert_eq!(axis.version(), Some("1.1h.20190830:"));
    assert_eq!(
        axis.last_status().map(|s| s.state),
        Some(MachineState::Alarm)
    );

    let t0 = clock.now_s();
    let home = axis.home().await.expect("home");
    assert_eq!(home, 0.0);
    let homing = clock.now_s() - t0;
    assert!((homing - TRAP.move_time(25.0)).abs() < 1e-3, "{homing}");

    let poll = config().poll_interval.as_secs_f64();
    let t0 = clock.now_s();
    let reached = axis.move_to(90.0).await.expect("move");
    let took = clock.now_s() - t0;
    let model = TRAP.move_time(90.0);
    assert!((reached - 90.0).abs() < 1e-6, "{reached}");
    assert!(
        took >= model - 1e-6 && took <= model + poll + 1e-6,
        "move took {took} s, model {model} s, poll {poll} s"
    );
    assert_eq!(axis.position().await.expect("position"), 90.0);
    assert_eq!(stats.rx_overflow_bytes.load(Ordering::Relaxed), 0);
}

#[tokio::test(start_paused = true)]
async fn out_of_limits_is_refused_without_sending() {
    let (mut axis, stats, _) = connected(Arc::default()).await;
    axis.home().await.expect("home");
    let lines = stats.lines.load(Ordering::Relaxed);
    for target in [400.0, -10.5, f64::NAN, f64::INFINITY] {
        let e = axis.move_to(target).await.expect_err("refused");
        assert_eq!(e.kind, ErrorKind::OutOfLimits, "{target}: {e}");
    }
    assert_eq!(stats.lines.load(Ordering::Relaxed), lines);
    // The edge of the limits is allowed.
    assert_eq!(axis.move_to(350.0).await.expect("edge"), 350.0);
    assert_eq!(stats.lines.load(Ordering::Relaxed), lines + 1);
}

#[tokio::test(start_paused = true)]
async fn swallowed_command_times_out_then_the_link_recovers() {
    let (mut axis, _, clock) = connected(rules(&["turntable:move:1:timeout"])).await;
    axis.home().await.expect("home");
    let t0 = clock.now_s();
    let e = axis.move_to(45.0).await.expect_err("timeout");
    let waited = clock.now_s() - t0;
    assert_eq!(e.kind, ErrorKind::Timeout, "{e}");
    let deadline = config().command_timeout.as_secs_f64();
    assert!((waited - deadline).abs() < 1e-3, "waited {waited} s");
    // The next calls resynchronise and work (the lost move never ran).
    assert_eq!(axis.position().await.expect("position"), 0.0);
    assert_eq!(axis.move_to(45.0).await.expect("retry"), 45.0);
}

#[tokio::test(start_paused = true)]
async fn homing_that_never_answers_times_out_at_the_homing_deadline() {
    let (mut axis, _, clock) = connected(rules(&["turntable:home:1:timeout"])).await;
    let t0 = clock.now_s();
    let e = axis.home().await.expect_err("timeout");
    assert_eq!(e.kind, ErrorKind::Timeout, "{e}");
    let waited = clock.now_s() - t0;
    assert!((waited - config().home_timeout.as_secs_f64()).abs() < 1e-3);
}

#[tokio::test(start_paused = true)]
async fn disconnect_is_reported() {
    let (mut axis, _, _) = connected(rules(&["turntable:move:1:disconnect"])).await;
    axis.home().await.expect("home");
    let e = axis.move_to(10.0).await.expect_err("disconnect");
    assert_eq!(e.kind, ErrorKind::Disconnected, "{e}");
    let e = axis.position().await.expect_err("still gone");
    assert_eq!(e.kind, ErrorKind::Disconnected, "{e}");
}

#[tokio::test(start_paused = true)]
async fn alarm_is_a_device_fault_in_the_devices_words() {
    let (mut axis, _, _) =
        connected(rules(&["turntable:move:2:alarm=limit switch X tripped"])).await;
    axis.home().await.expect("home");
    axis.move_to(30.0).await.expect("first move");
    let e = axis.move_to(60.0).await.expect_err("alarm");
    assert_eq!(e.kind, ErrorKind::DeviceFault, "{e}");
    assert!(e.message.contains("ALARM:1"), "{}", e.message);
    assert!(
        e.message.contains("limit switch X tripped"),
        "{}",
        e.message
    );
    assert_eq!(
        axis.last_status().map(|s| s.state),
        Some(MachineState::Alarm)
    );
    // Locked until homed: GRBL refuses G-code with error:9.
    let e = axis.move_to(60.0).await.expect_err("locked");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("error:9"), "{}", e.message);
    assert_eq!(axis.home().await.expect("re-home"), 0.0);
    assert_eq!(axis.move_to(60.0).await.expect("after re-home"), 60.0);
}

#[tokio::test(start_paused = true)]
async fn reconnect_resyncs_position_from_the_device() {
    let (mut axis, _, clock) = connected(Arc::default()).await;
    axis.home().await.expect("home");
    assert_eq!(axis.move_to(90.0).await.expect("move"), 90.0);

    // A fresh controller that kept its position somewhere else.
    let kept = GrblParams {
        start_homed: true,
        physical_start: 42.0,
        ..params()
    };
    let (host, _) = start_sim(kept, &clock, Arc::default());
    axis.reconnect(host).await.expect("reconnect");
    assert_eq!(axis.position().await.expect("position"), 42.0);
    assert_eq!(axis.move_to(50.0).await.expect("move"), 50.0);

    // A fresh controller that lost its position: MPos 0, locked.
    let (host, _) = start_sim(params(), &clock, Arc::default());
    axis.reconnect(host).await.expect("reconnect");
    assert_eq!(
        axis.last_status().map(|s| (s.state, s.x())),
        Some((MachineState::Alarm, Some(0.0)))
    );
    assert_eq!(axis.position().await.expect("position"), 0.0);
    let e = axis.move_to(10.0).await.expect_err("locked");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
}

#[tokio::test(start_paused = true)]
async fn soft_reset_mid_move_leaves_the_axis_in_alarm() {
    // Someone slows the controller down behind rigd's back (`$110` written
    // from another terminal after connect): the motion deadline, sized from
    // the rates read at connect, expires while the axis still runs, and the
    // soft reset then stops it.
    let clock = Clock::virtual_time();
    let p = GrblParams {
        start_homed: true,
        physical_start: 0.0,
        ..params()
    };
    let eeprom = p.settings.clone();
    let (host, _) = start_sim(p, &clock, Arc::default());
    let mut cfg = config();
    cfg.command_timeout = Duration::from_millis(500);
    cfg.poll_interval = Duration::from_millis(100);
    let mut axis = GrblAxis::connect(host, cfg, clock.clone())
        .await
        .expect("connect");
    eeprom.set(110, 60.0); // 1 deg/s instead of 30
    let e = axis.move_to(300.0).await.expect_err("deadline");
    assert_eq!(e.kind, ErrorKind::Timeout);
    let s = axis.soft_reset().await.expect("reset");
    assert_eq!(s.state, MachineState::Alarm);
    let x = s.x().unwrap_or(f64::NAN);
    assert!(x > 0.0 && x < 300.0, "stopped at {x}");
    assert_eq!(axis.home().await.expect("home"), 0.0);
}

/// The controller's rates, not the profile's, size the motion deadline: a
/// board set up slower than the profile models is refused at connect
/// (naming each setting and the line that fixes it), and with `configure`
/// it is set up, read back, and a long move then finishes in its time.
#[tokio::test(start_paused = true)]
async fn settings_are_compared_with_the_profile_and_configured_on_request() {
    let clock = Clock::virtual_time();
    let stock = || GrblParams {
        settings: Eeprom::factory(),
        physical_start: 0.0,
        ..params()
    };
    let mut cfg = config();
    cfg.homing = false;
    let (host, stats) = start_sim(stock(), &clock, Arc::default());
    let e = GrblAxis::connect(host, cfg.clone(), clock.clone())
        .await
        .expect_err("factory rates differ from the profile");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    for part in [
        "$110 (X max rate, deg/min) is 500.000 on the controller, the profile needs 1800.000",
        "$120 (X acceleration, deg/s²) is 10.000 on the controller, the profile needs 60.000",
        "`$110=1800.000`",
        "`configure = true`",
    ] {
        assert!(e.message.contains(part), "{part}: {e}");
    }
    // `$22=0` is what the profile wants here: not named.
    assert!(!e.message.contains("$22"), "{e}");
    assert_eq!(
        stats.lines.load(Ordering::Relaxed),
        2,
        "`$I`, `$$`; nothing written"
    );

    let board = stock();
    let eeprom = board.settings.clone();
    let (host, _) = start_sim(board, &clock, Arc::default());
    cfg.configure = true;
    let mut axis = GrblAxis::connect(host, cfg.clone(), clock.clone())
        .await
        .expect("configured");
    assert_eq!(eeprom.get(110), Some(1800.0));
    assert_eq!(eeprom.get(120), Some(60.0));
    assert_eq!(axis.settings().get(&110), Some(&1800.0));
    assert_eq!(axis.rates().max_velocity, 30.0);
    assert_eq!(axis.home().await.expect("reference"), 0.0);
    let t0 = clock.now_s();
    assert_eq!(axis.move_to(300.0).await.expect("move"), 300.0);
    let took = clock.now_s() - t0;
    let modelled = TRAP.move_time(300.0);
    assert!(
        took >= modelled && took < modelled + 0.5,
        "{took} vs {modelled}"
    );

    // A homing axis also needs `$22=1`, written first, and the travel.
    let board = stock();
    let eeprom = board.settings.clone();
    let (host, _) = start_sim(board, &clock, Arc::default());
    cfg.homing = true;
    GrblAxis::connect(host, cfg.clone(), clock.clone())
        .await
        .expect("configured for homing");
    assert_eq!(eeprom.get(22), Some(1.0));
    assert_eq!(eeprom.get(130), Some(360.0));
    assert_eq!(eeprom.get(20), Some(0.0));

    // A value the controller refuses (faster than its step generator) is
    // an error naming the line, and the board keeps its settings.
    let board = stock();
    let eeprom = board.settings.clone();
    let (host, _) = start_sim(board, &clock, Arc::default());
    cfg.steps_per_deg = Some(2000.0); // 2000 × 30 deg/s = 60 kHz
    let e = GrblAxis::connect(host, cfg, clock.clone())
        .await
        .expect_err("error:12");
    assert!(e.message.contains("error:12"), "{e}");
    assert_eq!(eeprom.get(100), Some(250.0));
}

/// A controller as slow as one observed (each answer about 150 ms late):
/// connecting, homing and moving still work within the deadlines, and
/// connecting costs a handful of round trips, not a fixed wait.
#[tokio::test(start_paused = true)]
async fn a_slow_controller_answers_within_the_deadlines() {
    let clock = Clock::virtual_time();
    let slow = GrblParams {
        answer_delay_s: 0.15,
        ..params()
    };
    let (host, _) = start_sim(slow, &clock, Arc::default());
    let t0 = clock.now_s();
    let mut axis = GrblAxis::connect(host, config(), clock.clone())
        .await
        .expect("connect");
    let took = clock.now_s() - t0;
    // The banner, `$I`, `$$` and one status report: four late answers.
    assert!((0.6..1.0).contains(&took), "connecting took {took} s");
    assert_eq!(axis.home().await.expect("home"), 0.0);
    assert_eq!(axis.move_to(120.0).await.expect("move"), 120.0);
}

mod robustness {
    use super::*;
    use proptest::prelude::*;
    use rigd_proto::grbl::{parse_reply, LineSplitter, Reply};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    /// Feeds arbitrary bytes to the simulated firmware, then asks for a
    /// status report: the simulator must neither panic nor stop answering.
    fn garbage_then_status(bytes: Vec<u8>) -> Result<(), String> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .start_paused(true)
            .build()
            .map_err(|e| e.to_string())?;
        rt.block_on(async move {
            let clock = Clock::virtual_time();
            let (mut host, dev) = tokio::io::duplex(1 << 16);
            let sim = tokio::spawn(serve_with_stats(
                dev,
                params(),
                clock.clone(),
                Arc::default(),
                Arc::default(),
            ));
            host.write_all(&bytes).await.map_err(|e| e.to_string())?;
            host.write_all(b"\n").await.map_err(|e| e.to_string())?;
            // Homing started by the garbage may block lines, not `?`.
            clock.sleep_s(0.01).await;
            host.write_all(b"?").await.map_err(|e| e.to_string())?;
            let mut split = LineSplitter::new(256);
            let found = clock
                .deadline(Duration::from_secs(60), async {
                    let mut buf = [0u8; 512];
                    loop {
                        let n = host.read(&mut buf).await.map_err(|e| e.to_string())?;
                        if n == 0 {
                            return Err("simulator closed the link".to_string());
                        }
                        for &b in &buf[..n] {
                            if let Some(l) = split.push(b) {
                                if let Ok(Reply::Status(_)) = parse_reply(&l) {
                                    return Ok(());
                                }
                            }
                        }
                    }
                })
                .await;
            if sim.is_finished() {
                return Err("simulator task ended".into());
            }
            found.map_err(|e| e.to_string())?
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn simulator_survives_arbitrary_input(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
            prop_assert_eq!(garbage_then_status(bytes), Ok(()));
        }

        #[test]
        fn simulator_survives_command_like_input(s in "([$HXIJ=G0-9 .X?!~\n-]|\u{18}){0,200}") {
            prop_assert_eq!(garbage_then_status(s.into_bytes()), Ok(()));
        }
    }
}

/// An axis without homing on a controller as it ships (`$22=0`): `home`
/// takes the Idle controller's position and never sends `$H`; after a
/// reconnect the zero may be gone, so motion is refused until the operator
/// has zeroed the axis again and `home` is called (what a resume does).
#[tokio::test(start_paused = true)]
async fn an_axis_without_homing_takes_its_zero_from_the_operator() {
    let clock = Clock::virtual_time();
    // Homing off as shipped; the rates set up for the axis.
    let stock = GrblParams {
        settings: Eeprom::configured(TRAP, false, 360.0),
        physical_start: 0.0,
        ..params()
    };
    let faults: Arc<FaultInjector> = Arc::default();
    let (host, _) = start_sim(stock.clone(), &clock, faults.clone());
    let mut cfg = config();
    cfg.homing = false;
    let mut axis = GrblAxis::connect(host, cfg.clone(), clock.clone())
        .await
        .expect("connect");
    assert_eq!(axis.home().await.expect("reference"), 0.0);
    assert_eq!(axis.move_to(30.0).await.expect("move"), 30.0);

    // The link drops and the board resets somewhere else: MPos 0 there.
    let (host, _) = start_sim(
        GrblParams {
            physical_start: 30.0,
            ..stock.clone()
        },
        &clock,
        faults.clone(),
    );
    axis.reconnect(host).await.expect("reconnect");
    let e = axis.move_to(40.0).await.expect_err("zero may be gone");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("0° mark"), "{e}");
    // The operator zeroed it at the mark and resumed.
    assert_eq!(axis.home().await.expect("reference"), 0.0);
    assert_eq!(axis.move_to(40.0).await.expect("move"), 40.0);
    assert_eq!(faults.calls("turntable", "home"), 0, "`$H` was sent");

    // A controller that homes (`$22=1`) does not match `homing = false`:
    // refused at connect, with the line that fixes it.
    let (host, _) = start_sim(params(), &clock, Arc::default());
    let e = GrblAxis::connect(host, cfg, clock.clone())
        .await
        .expect_err("$22 differs");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("`$22=0`"), "{e}");
}

/// A board that does not reset when its port opens says nothing until
/// asked: the driver's first `?` gets its answer, so connecting takes one
/// round trip instead of a banner timeout, and the controller is not reset
/// (it keeps its position and its homing).
#[tokio::test(start_paused = true)]
async fn a_board_that_kept_running_connects_at_once_without_a_reset() {
    let clock = Clock::virtual_time();
    let running = GrblParams {
        reset_on_open: false,
        start_homed: true,
        physical_start: 42.0,
        ..params()
    };
    let (host, stats) = start_sim(running, &clock, Arc::default());
    let t0 = clock.now_s();
    let mut axis = GrblAxis::connect(host, config(), clock.clone())
        .await
        .expect("connect");
    let took = clock.now_s() - t0;
    assert!(took < 0.25, "connecting took {took} s");
    assert_eq!(
        axis.last_status().map(|s| (s.state, s.x())),
        Some((MachineState::Idle, Some(42.0)))
    );
    // `$I` and `$$` and nothing else were executed: no reset, no homing.
    assert_eq!(stats.lines.load(Ordering::Relaxed), 2);
    assert_eq!(axis.move_to(50.0).await.expect("move"), 50.0);

    // A board that resets on open still greets with its banner.
    let (host, _) = start_sim(params(), &clock, Arc::default());
    let t0 = clock.now_s();
    let axis = GrblAxis::connect(host, config(), clock.clone())
        .await
        .expect("connect");
    assert!(clock.now_s() - t0 < 0.25);
    assert_eq!(
        axis.last_status().map(|s| s.state),
        Some(MachineState::Alarm)
    );
}
