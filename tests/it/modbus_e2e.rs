//! Modbus lamps and laser end to end: the driver against the simulated relay
//! module over an in-memory `tokio::io::duplex` link under paused (virtual)
//! time (real sockets are unsafe there: tokio advances the clock while bytes
//! sit in the kernel). One test uses a real 127.0.0.1 socket and a stock
//! tokio-modbus client, in real time.

use std::sync::Arc;
use std::time::Duration;

use proptest::prelude::*;
use rigd::rig::drivers::modbus::{
    all_off, rtu_bus, tcp_bus, ModbusConfig, ModbusLamp, ModbusLaser, SharedBus,
};
use rigd::rig::hal::{ErrorKind, Lamp, LaserLine};
use rigd_core::Clock;
use rigd_proto::modbus::Framing;
use rigd_sim::firmware::modbus::{LampSpec, ModbusModule, ModuleConfig};
use rigd_sim::FaultInjector;
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};
use tokio_modbus::client::{Reader, Writer};

const WARM_UP: Duration = Duration::from_secs(180);
const SWITCH: Duration = Duration::from_millis(500);

fn module(clock: &Clock, faults: &[&str]) -> ModbusModule {
    module_as_sold(clock, faults, true, true)
}

/// A module with or without the status registers and FC0F.
fn module_as_sold(
    clock: &Clock,
    faults: &[&str],
    status_registers: bool,
    write_multiple_coils: bool,
) -> ModbusModule {
    let rules = faults
        .iter()
        .map(|f| f.parse().expect("fault rule"))
        .collect();
    let lamp = |name: &str| LampSpec {
        name: name.into(),
        warm_up_s: WARM_UP.as_secs_f64(),
        switch_s: SWITCH.as_secs_f64(),
    };
    ModbusModule::new(
        ModuleConfig {
            unit: 1,
            lamps: vec![lamp("hmi"), lamp("lamp1")],
            laser: Some("laser".into()),
            laser_switch_s: 0.01,
            status_registers,
            write_multiple_coils,
        },
        clock.clone(),
        Arc::new(FaultInjector::new(rules)),
    )
}

/// Serves `m` on one end of an in-memory link; returns the other end.
fn link(m: &ModbusModule, framing: Framing) -> DuplexStream {
    let (drv, dev) = tokio::io::duplex(1024);
    let m = m.clone();
    tokio::spawn(async move { m.serve_stream(dev, framing).await });
    drv
}

fn rig(faults: &[&str]) -> (Clock, ModbusModule, SharedBus) {
    let clock = Clock::virtual_time();
    let m = module(&clock, faults);
    let bus = tcp_bus(link(&m, Framing::Tcp), 1);
    (clock, m, bus)
}

fn lamp(clock: &Clock, bus: &SharedBus, name: &str, coil: u16) -> ModbusLamp {
    ModbusLamp::new(
        ModbusConfig::new(name, coil, WARM_UP, SWITCH),
        clock.clone(),
        bus.clone(),
    )
}

#[tokio::test(start_paused = true)]
async fn switch_on_waits_warm_up_and_off_clears_ready() {
    let (clock, m, bus) = rig(&[]);
    let mut hmi = lamp(&clock, &bus, "hmi", 0);
    let t0 = clock.now_s();
    hmi.set(true).await.expect("on");
    assert!((clock.now_s() - t0 - 0.5).abs() < 0.01, "switch time");
    assert_eq!(m.coils(), vec![true, false, false]);
    hmi.wait_ready().await.expect("ready");
    let waited = clock.now_s() - t0;
    assert!((180.5..181.0).contains(&waited), "{waited}");
    assert_eq!(m.input_registers()[0] & 1, 1);
    hmi.set(false).await.expect("off");
    assert_eq!(m.input_registers()[0], 0);
    let e = hmi.wait_ready().await.expect_err("off lamp");
    assert_eq!(e.kind, ErrorKind::NotReady);
}

#[tokio::test(start_paused = true)]
async fn all_off_drops_every_coil_in_one_request() {
    let (clock, m, bus) = rig(&[]);
    lamp(&clock, &bus, "hmi", 0).set(true).await.expect("on");
    lamp(&clock, &bus, "lamp1", 1).set(true).await.expect("on");
    let mut laser = ModbusLaser::new(
        ModbusConfig::new("laser", 2, Duration::ZERO, Duration::from_millis(10)),
        clock.clone(),
        bus.clone(),
    );
    laser.set(true).await.expect("laser on");
    assert_eq!(m.coils(), vec![true, true, true]);
    all_off(&clock, &bus, 3, Duration::from_secs(2))
        .await
        .expect("all off");
    assert_eq!(m.coils(), vec![false, false, false]);
}

/// A coil-only module (no status registers, no FC0F), on a TCP bus.
fn coil_only_rig() -> (Clock, ModbusModule, SharedBus) {
    let clock = Clock::virtual_time();
    let m = module_as_sold(&clock, &[], false, false);
    let bus = tcp_bus(link(&m, Framing::Tcp), 1);
    (clock, m, bus)
}

fn coil_only_lamp(clock: &Clock, bus: &SharedBus, name: &str, coil: u16) -> ModbusLamp {
    let mut cfg = ModbusConfig::new(name, coil, WARM_UP, SWITCH);
    cfg.status_registers = false;
    ModbusLamp::new(cfg, clock.clone(), bus.clone())
}

#[tokio::test(start_paused = true)]
async fn a_coil_only_module_times_the_warm_up_from_the_read_back() {
    let (clock, m, bus) = coil_only_rig();
    // The module really has no registers: asking for them is refused.
    let refused = bus
        .lock()
        .await
        .read_input_registers(0, 2)
        .await
        .expect("transport");
    assert!(refused.is_err(), "{refused:?}");
    let mut hmi = coil_only_lamp(&clock, &bus, "hmi", 0);
    let t0 = clock.now_s();
    hmi.set(true).await.expect("on");
    let switched = clock.now_s() - t0;
    assert!((switched - 0.5).abs() < 0.01, "switch time {switched}");
    hmi.wait_ready()
        .await
        .expect("ready after the timed warm-up");
    let waited = clock.now_s() - t0;
    assert!(
        (180.5..180.6).contains(&waited),
        "warm-up timed from the read-back: {waited}"
    );
    // Switching on again does not restart the warm-up.
    hmi.set(true).await.expect("on again");
    let t1 = clock.now_s();
    hmi.wait_ready().await.expect("still ready");
    assert!(clock.now_s() - t1 < 0.1);
    hmi.set(false).await.expect("off");
    assert_eq!(m.coils(), vec![false, false, false]);
    let e = hmi.wait_ready().await.expect_err("off lamp");
    assert_eq!(e.kind, ErrorKind::NotReady);
}

#[tokio::test(start_paused = true)]
async fn a_coil_only_lamp_whose_relay_dropped_during_warm_up_is_not_ready() {
    let (clock, _m, bus) = coil_only_rig();
    let mut hmi = coil_only_lamp(&clock, &bus, "hmi", 0);
    hmi.set(true).await.expect("on");
    // Someone switches the relay off at the module's panel.
    bus.lock()
        .await
        .write_single_coil(0, false)
        .await
        .expect("transport")
        .expect("reply");
    let e = hmi.wait_ready().await.expect_err("relay dropped");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("coil 0 reads false"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn a_module_that_refuses_fc0f_gets_its_coils_off_one_by_one() {
    let (clock, m, bus) = coil_only_rig();
    coil_only_lamp(&clock, &bus, "hmi", 0)
        .set(true)
        .await
        .expect("on");
    coil_only_lamp(&clock, &bus, "lamp1", 1)
        .set(true)
        .await
        .expect("on");
    assert_eq!(m.coils(), vec![true, true, false]);
    let t0 = clock.now_s();
    all_off(&clock, &bus, 3, Duration::from_secs(2))
        .await
        .expect("all off, one coil at a time");
    assert_eq!(m.coils(), vec![false, false, false]);
    // Three FC05 writes, each answered after its relay switched.
    let took = clock.now_s() - t0;
    assert!((1.0..1.1).contains(&took), "{took}");
    // Too short a deadline for one by one is a timeout, not a hang.
    coil_only_lamp(&clock, &bus, "hmi", 0)
        .set(true)
        .await
        .expect("on");
    let e = all_off(&clock, &bus, 3, Duration::from_millis(700))
        .await
        .expect_err("deadline");
    assert!(e.to_string().contains("within"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn alarm_on_set_is_a_device_fault_naming_the_exception() {
    let (clock, _m, bus) = rig(&["hmi:set:1:alarm=ballast"]);
    let e = lamp(&clock, &bus, "hmi", 0)
        .set(true)
        .await
        .expect_err("alarm");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("slave device failure"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn alarm_during_warm_up_is_a_device_fault_in_plain_words() {
    let (clock, _m, bus) = rig(&["hmi:ready:3:alarm=bulb"]);
    let mut hmi = lamp(&clock, &bus, "hmi", 0);
    hmi.set(true).await.expect("on");
    let e = hmi.wait_ready().await.expect_err("fault bit");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("fault"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn silent_module_is_a_timeout() {
    let (clock, _m, bus) = rig(&["hmi:set:1:timeout"]);
    let e = lamp(&clock, &bus, "hmi", 0)
        .set(true)
        .await
        .expect_err("timeout");
    assert_eq!(e.kind, ErrorKind::Timeout);
}

#[tokio::test(start_paused = true)]
async fn dropped_connection_is_disconnected() {
    let (clock, _m, bus) = rig(&["hmi:set:1:disconnect"]);
    let e = lamp(&clock, &bus, "hmi", 0)
        .set(true)
        .await
        .expect_err("disconnect");
    assert_eq!(e.kind, ErrorKind::Disconnected, "{e}");
}

#[tokio::test(start_paused = true)]
async fn unwired_coil_is_illegal_address() {
    let (clock, _m, bus) = rig(&[]);
    let e = lamp(&clock, &bus, "ghost", 7)
        .set(true)
        .await
        .expect_err("no coil 7");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("illegal data address"), "{e}");
}

/// A stock Modbus TCP client over a real 127.0.0.1 socket, in real time
/// (no virtual-time deadlines): writes a coil, reads the coils back.
#[tokio::test]
async fn plain_modbus_tcp_client_reads_the_coils() {
    let clock = Clock::real();
    let m = module(&clock, &[]);
    let (addr, _task) = m.serve_tcp().await.expect("serve");
    let mut ctx = tokio_modbus::client::tcp::connect_slave(addr, tokio_modbus::Slave(1))
        .await
        .expect("connect");
    // The laser coil: 10 ms relay.
    ctx.write_single_coil(2, true)
        .await
        .expect("io")
        .expect("no exception");
    let coils = ctx
        .read_coils(0, 3)
        .await
        .expect("io")
        .expect("no exception");
    assert_eq!(coils, vec![false, false, true]);
    assert_eq!(m.coils(), vec![false, false, true]);
    let e = ctx.read_coils(0, 4).await.expect("io");
    assert_eq!(e, Err(tokio_modbus::ExceptionCode::IllegalDataAddress));
}

#[tokio::test(start_paused = true)]
async fn rtu_framing_over_an_in_memory_link() {
    let clock = Clock::virtual_time();
    let m = module(&clock, &[]);
    let bus = rtu_bus(link(&m, Framing::Rtu), 1);
    let mut hmi = lamp(&clock, &bus, "hmi", 0);
    hmi.set(true).await.expect("on");
    hmi.wait_ready().await.expect("ready");
    assert_eq!(m.coils(), vec![true, false, false]);
    let e = lamp(&clock, &bus, "ghost", 7)
        .set(true)
        .await
        .expect_err("no coil 7");
    assert!(e.message.contains("illegal data address"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn timeout_fault_loses_one_request_and_a_retry_succeeds() {
    let (clock, m, bus) = rig(&["hmi:set:1:timeout"]);
    let mut hmi = lamp(&clock, &bus, "hmi", 0);
    let t0 = clock.now_s();
    let e = hmi.set(true).await.expect_err("timeout");
    assert_eq!(e.kind, ErrorKind::Timeout);
    // The deadline is request timeout (1 s) + switch time (0.5 s).
    assert!((clock.now_s() - t0 - 1.5).abs() < 0.01, "{}", clock.now_s());
    hmi.set(true).await.expect("retry");
    assert_eq!(m.coils(), vec![true, false, false]);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 32, ..ProptestConfig::default() })]

    /// Arbitrary bytes on one link: the module neither panics nor stops
    /// serving other links.
    #[test]
    fn server_survives_arbitrary_bytes(
        rtu in any::<bool>(),
        bytes in proptest::collection::vec(any::<u8>(), 0..64),
    ) {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .start_paused(true)
            .build()
            .expect("runtime");
        rt.block_on(async {
            let framing = if rtu { Framing::Rtu } else { Framing::Tcp };
            let clock = Clock::virtual_time();
            let m = module(&clock, &[]);
            let mut junk = link(&m, framing);
            let _ = junk.write_all(&bytes).await;
            // Give the server a moment of virtual time on the junk.
            tokio::time::sleep(Duration::from_millis(10)).await;
            drop(junk);
            let bus = if rtu {
                rtu_bus(link(&m, framing), 1)
            } else {
                tcp_bus(link(&m, framing), 1)
            };
            let mut ctx = bus.lock().await;
            let coils = clock
                .deadline(Duration::from_secs(1), ctx.read_coils(0, 3))
                .await
                .expect("answer in time")
                .expect("io")
                .expect("no exception");
            assert_eq!(coils, vec![false, false, false]);
        });
    }

    /// Arbitrary bytes from the module: every driver call ends within its
    /// deadline (error or value), never panics.
    #[test]
    fn driver_survives_a_module_answering_garbage(
        rtu in any::<bool>(),
        garbage in proptest::collection::vec(any::<u8>(), 0..64),
        close_after in any::<bool>(),
        call in 0u8..3,
    ) {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .start_paused(true)
            .build()
            .expect("runtime");
        rt.block_on(async {
            let clock = Clock::virtual_time();
            let (drv, mut dev) = tokio::io::duplex(1024);
            // The fake module: answers the first request with the garbage,
            // then reads and ignores (or hangs up).
            tokio::spawn(async move {
                let mut b = [0u8; 256];
                if matches!(dev.read(&mut b).await, Ok(n) if n > 0) {
                    let _ = dev.write_all(&garbage).await;
                    if close_after {
                        return;
                    }
                    while matches!(dev.read(&mut b).await, Ok(n) if n > 0) {}
                }
            });
            let bus = if rtu { rtu_bus(drv, 1) } else { tcp_bus(drv, 1) };
            let cfg = ModbusConfig::new("hmi", 0, WARM_UP, SWITCH);
            let t0 = clock.now();
            // Each call's own deadlines bound it; the outer one only turns
            // a hang into a test failure instead of a stuck test.
            let (limit, done) = match call {
                0 => {
                    let limit = 2 * cfg.request_timeout + cfg.switch;
                    let mut l = ModbusLamp::new(cfg, clock.clone(), bus.clone());
                    (limit, clock.deadline(limit * 2, l.set(true)).await.is_ok())
                }
                1 => {
                    let limit = Duration::from_secs(2);
                    let r = clock
                        .deadline(limit * 2, all_off(&clock, &bus, 3, limit))
                        .await;
                    (limit, r.is_ok())
                }
                _ => {
                    let limit = 2 * cfg.request_timeout + cfg.switch;
                    let mut l = ModbusLaser::new(cfg, clock.clone(), bus.clone());
                    (limit, clock.deadline(limit * 2, l.set(true)).await.is_ok())
                }
            };
            assert!(done, "driver call did not return within {:?}", limit * 2);
            let took = clock.now() - t0;
            assert!(took <= limit, "took {took:?}, deadline {limit:?}");
        });
    }
}
