//! Modbus lamps and laser end to end: the driver against the simulated relay
//! module over TCP on 127.0.0.1, under paused (virtual) time.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use proptest::prelude::*;
use rigd::drivers::modbus::{
    all_off, connect_tcp, rtu_bus, ModbusConfig, ModbusLamp, ModbusLaser, SharedBus,
};
use rigd::hal::{ErrorKind, Lamp, LaserLine};
use rigd::sim::firmware::modbus::{LampSpec, ModbusModule, ModuleConfig};
use rigd::sim::{Clock, FaultInjector};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_modbus::client::Reader;

const WARM_UP: Duration = Duration::from_secs(180);
const SWITCH: Duration = Duration::from_millis(500);

fn module(clock: &Clock, faults: &[&str]) -> ModbusModule {
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
        },
        clock.clone(),
        Arc::new(FaultInjector::new(rules)),
    )
}

async fn rig(faults: &[&str]) -> (Clock, ModbusModule, SocketAddr, SharedBus) {
    let clock = Clock::virtual_time();
    let m = module(&clock, faults);
    let (addr, _task) = m.serve_tcp().await.expect("serve");
    let bus = connect_tcp(&clock, addr, 1, Duration::from_secs(1))
        .await
        .expect("connect");
    (clock, m, addr, bus)
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
    let (clock, m, _addr, bus) = rig(&[]).await;
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
    let (clock, m, _addr, bus) = rig(&[]).await;
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

#[tokio::test(start_paused = true)]
async fn alarm_on_set_is_a_device_fault_naming_the_exception() {
    let (clock, _m, _addr, bus) = rig(&["hmi:set:1:alarm=ballast"]).await;
    let e = lamp(&clock, &bus, "hmi", 0)
        .set(true)
        .await
        .expect_err("alarm");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("slave device failure"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn alarm_during_warm_up_is_a_device_fault_in_plain_words() {
    let (clock, _m, _addr, bus) = rig(&["hmi:ready:3:alarm=bulb"]).await;
    let mut hmi = lamp(&clock, &bus, "hmi", 0);
    hmi.set(true).await.expect("on");
    let e = hmi.wait_ready().await.expect_err("fault bit");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("fault"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn silent_module_is_a_timeout() {
    let (clock, _m, _addr, bus) = rig(&["hmi:set:1:timeout"]).await;
    let e = lamp(&clock, &bus, "hmi", 0)
        .set(true)
        .await
        .expect_err("timeout");
    assert_eq!(e.kind, ErrorKind::Timeout);
}

#[tokio::test(start_paused = true)]
async fn dropped_connection_is_disconnected() {
    let (clock, _m, _addr, bus) = rig(&["hmi:set:1:disconnect"]).await;
    let e = lamp(&clock, &bus, "hmi", 0)
        .set(true)
        .await
        .expect_err("disconnect");
    assert_eq!(e.kind, ErrorKind::Disconnected, "{e}");
}

#[tokio::test(start_paused = true)]
async fn unwired_coil_is_illegal_address() {
    let (clock, _m, _addr, bus) = rig(&[]).await;
    let e = lamp(&clock, &bus, "ghost", 7)
        .set(true)
        .await
        .expect_err("no coil 7");
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("illegal data address"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn plain_modbus_tcp_client_reads_the_coils() {
    let (clock, _m, addr, bus) = rig(&[]).await;
    lamp(&clock, &bus, "lamp1", 1).set(true).await.expect("on");
    let mut ctx = tokio_modbus::client::tcp::connect_slave(addr, tokio_modbus::Slave(1))
        .await
        .expect("connect");
    let coils = ctx
        .read_coils(0, 3)
        .await
        .expect("io")
        .expect("no exception");
    assert_eq!(coils, vec![false, true, false]);
}

#[tokio::test(start_paused = true)]
async fn rtu_framing_through_a_gateway_socket() {
    let clock = Clock::virtual_time();
    let m = module(&clock, &[]);
    let (addr, _task) = m.serve_rtu_over_tcp().await.expect("serve");
    let stream = tokio::net::TcpStream::connect(addr).await.expect("connect");
    let bus = rtu_bus(stream, 1);
    let mut hmi = lamp(&clock, &bus, "hmi", 0);
    hmi.set(true).await.expect("on");
    hmi.wait_ready().await.expect("ready");
    assert_eq!(m.coils(), vec![true, false, false]);
}

/// Transcript: RTU exception reply, byte for byte (CRC included).
#[tokio::test(start_paused = true)]
async fn rtu_exception_transcript() {
    let clock = Clock::virtual_time();
    let m = module(&clock, &[]);
    let (addr, _task) = m.serve_rtu_over_tcp().await.expect("serve");
    let mut s = tokio::net::TcpStream::connect(addr).await.expect("connect");
    // FC05 coil 9 ON, unit 1.
    s.write_all(&[0x01, 0x05, 0x00, 0x09, 0xFF, 0x00, 0x5C, 0x38])
        .await
        .expect("write");
    let mut buf = [0u8; 5];
    s.read_exact(&mut buf).await.expect("read");
    assert_eq!(buf, [0x01, 0x85, 0x02, 0xC3, 0x51]);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 32, ..ProptestConfig::default() })]

    /// Arbitrary bytes on the wire: the server neither panics nor stops
    /// serving other connections.
    #[test]
    fn server_survives_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .start_paused(true)
            .build()
            .expect("runtime");
        rt.block_on(async {
            let (_clock, _m, addr, _bus) = rig(&[]).await;
            let mut junk = tokio::net::TcpStream::connect(addr).await.expect("connect");
            let _ = junk.write_all(&bytes).await;
            drop(junk);
            let mut ctx = tokio_modbus::client::tcp::connect_slave(addr, tokio_modbus::Slave(1))
                .await
                .expect("connect");
            let coils = ctx.read_coils(0, 3).await.expect("io").expect("no exception");
            assert_eq!(coils, vec![false, false, false]);
        });
    }
}
