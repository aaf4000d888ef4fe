//! Replays every ```transcript block of `firmware-protocols/modbus-lamps.md`
//! against the simulated module (the test is the driver, bytes go through
//! `serve_stream`) and against the driver (the test is the module), so spec,
//! simulator and driver cannot drift apart. Syntax and the replay's module
//! and driver settings are in the spec.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use rigd::rig::drivers::modbus::{all_off, rtu_bus, tcp_bus, ModbusConfig, ModbusLamp, SharedBus};
use rigd::rig::hal::{DeviceError, Lamp};
use rigd_core::Clock;
use rigd_proto::modbus::Framing;
use rigd_sim::firmware::modbus::{LampSpec, ModbusModule, ModuleConfig};
use rigd_sim::{FaultInjector, FaultRule};
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};

#[derive(Debug, Clone)]
enum Step {
    Send(Vec<u8>),
    Recv(Vec<u8>),
    After(f64),
    Fault(String),
    Call(String, Vec<String>),
    Expect(String),
}

struct Transcript {
    title: String,
    framing: Framing,
    steps: Vec<Step>,
}

fn hex(x: &str) -> Vec<u8> {
    x.split_whitespace()
        .map(|b| u8::from_str_radix(b, 16).unwrap_or_else(|_| panic!("bad hex byte `{b}`")))
        .collect()
}

fn parse_step(line: &str) -> Step {
    if let Some(x) = line.strip_prefix("> ") {
        Step::Send(hex(x))
    } else if let Some(x) = line.strip_prefix("< ") {
        Step::Recv(hex(x))
    } else if let Some(x) = line.strip_prefix("@ after ") {
        Step::After(x.trim().parse().expect("after seconds"))
    } else if let Some(x) = line.strip_prefix("@ fault ") {
        Step::Fault(x.trim().to_string())
    } else if let Some(x) = line.strip_prefix("@ call ") {
        let mut it = x.split_whitespace().map(str::to_string);
        let op = it.next().unwrap_or_default();
        Step::Call(op, it.collect())
    } else if let Some(x) = line.strip_prefix("@ expect ") {
        Step::Expect(x.trim().to_string())
    } else {
        panic!("bad transcript line `{line}`")
    }
}

fn transcripts() -> Vec<Transcript> {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/firmware-protocols/modbus-lamps.md"
    );
    let text = std::fs::read_to_string(path).expect("read modbus-lamps.md");
    let mut out = Vec::new();
    let mut current: Option<(String, Vec<Step>)> = None;
    for line in text.lines() {
        if let Some((title, steps)) = current.as_mut() {
            if line.trim() == "```" {
                let (title, steps) = current.take().expect("open block");
                let framing = if title.contains("[tcp]") {
                    Framing::Tcp
                } else if title.contains("[rtu]") {
                    Framing::Rtu
                } else {
                    panic!("`{title}`: first comment names no [tcp]/[rtu] framing")
                };
                out.push(Transcript {
                    title,
                    framing,
                    steps,
                });
            } else if let Some(c) = line.strip_prefix('#') {
                if title.is_empty() {
                    *title = c.trim().to_string();
                }
            } else if !line.trim().is_empty() {
                steps.push(parse_step(line));
            }
        } else if line.trim() == "```transcript" {
            current = Some((String::new(), Vec::new()));
        }
    }
    assert!(current.is_none(), "unterminated transcript block");
    out
}

fn module(clock: &Clock, t: &Transcript) -> ModbusModule {
    let rules: Vec<FaultRule> = t
        .steps
        .iter()
        .filter_map(|s| match s {
            Step::Fault(r) => Some(r.parse().expect("fault rule")),
            _ => None,
        })
        .collect();
    let lamps = (0..8)
        .map(|k| LampSpec {
            name: format!("lamp{k}"),
            warm_up_s: 0.5,
            switch_s: 0.2,
        })
        .collect();
    ModbusModule::new(
        ModuleConfig {
            unit: 1,
            lamps,
            laser: Some("laser".into()),
            laser_switch_s: 0.01,
            status_registers: true,
            write_multiple_coils: true,
        },
        clock.clone(),
        Arc::new(FaultInjector::new(rules)),
    )
}

async fn replay_against_sim(t: &Transcript) {
    let clock = Clock::virtual_time();
    let m = module(&clock, t);
    let (mut host, dev) = tokio::io::duplex(4096);
    let framing = t.framing;
    tokio::spawn(async move { m.serve_stream(dev, framing).await });
    for (i, step) in t.steps.iter().enumerate() {
        match step {
            Step::Send(x) => host.write_all(x).await.expect("send"),
            Step::Recv(want) => {
                let mut got = vec![0u8; want.len()];
                let r = clock
                    .deadline(Duration::from_secs(30), host.read_exact(&mut got))
                    .await;
                match r {
                    Ok(Ok(_)) => {}
                    Ok(Err(e)) => panic!("{}: step {i}: {e}, expected {want:02X?}", t.title),
                    Err(_) => panic!(
                        "{}: step {i}: nothing received, expected {want:02X?}",
                        t.title
                    ),
                }
                assert_eq!(&got, want, "{}: step {i}", t.title);
            }
            Step::After(s) => clock.sleep_s(*s).await,
            Step::Fault(_) | Step::Call(..) | Step::Expect(_) => {}
        }
    }
    // Nothing unexpected may follow.
    let mut b = [0u8; 64];
    let extra = clock
        .deadline(Duration::from_secs(5), host.read(&mut b))
        .await;
    assert!(
        matches!(extra, Err(_) | Ok(Ok(0))),
        "{}: unexpected extra bytes {extra:?} {:02X?}",
        t.title,
        &b[..]
    );
}

/// Plays the module: expects exactly the `>` bytes, answers the `<` bytes,
/// checks `@ after` waits, and finally that the driver sends nothing more.
async fn play_device(mut io: DuplexStream, steps: Vec<Step>, clock: Clock) -> Result<(), String> {
    let mut last_answer = clock.now();
    let mut not_before: Option<Duration> = None;
    for (i, step) in steps.iter().enumerate() {
        match step {
            Step::Recv(x) => {
                io.write_all(x)
                    .await
                    .map_err(|e| format!("step {i}: {e}"))?;
                last_answer = clock.now();
            }
            Step::After(s) => not_before = Some(last_answer + Duration::from_secs_f64(*s)),
            Step::Send(want) => {
                let mut got = vec![0u8; want.len()];
                io.read_exact(&mut got)
                    .await
                    .map_err(|e| format!("step {i}: {e}, expected {want:02X?}"))?;
                if &got != want {
                    return Err(format!(
                        "step {i}: expected {want:02X?}, driver sent {got:02X?}"
                    ));
                }
                if let Some(t) = not_before.take() {
                    let now = clock.now();
                    if now + Duration::from_millis(1) < t {
                        return Err(format!("step {i}: request at {now:?}, not before {t:?}"));
                    }
                }
            }
            Step::Fault(_) | Step::Call(..) | Step::Expect(_) => {}
        }
    }
    let mut rest = Vec::new();
    io.read_to_end(&mut rest).await.map_err(|e| e.to_string())?;
    if rest.is_empty() {
        Ok(())
    } else {
        Err(format!("driver sent extra bytes {rest:02X?}"))
    }
}

fn check(call: &str, expect: &str, got: &Result<(), DeviceError>) -> Result<(), String> {
    let (what, text) = match expect.split_once(' ') {
        Some((w, t)) => (w, Some(t)),
        None => (expect, None),
    };
    match (what, got) {
        ("ok", Ok(())) => Ok(()),
        (kind, Err(e)) if kind != "ok" => {
            if crate::common::kind_name(e.kind) != kind {
                return Err(format!("{call}: expected {expect}, got {e}"));
            }
            match text {
                Some(text) if !e.message.contains(text) => {
                    Err(format!("{call}: `{}` lacks `{text}`", e.message))
                }
                _ => Ok(()),
            }
        }
        _ => Err(format!("{call}: expected {expect}, got {got:?}")),
    }
}

fn lamp(clock: &Clock, bus: &SharedBus, coil: u16) -> ModbusLamp {
    let mut cfg = ModbusConfig::new(
        &format!("lamp{coil}"),
        coil,
        Duration::from_millis(500),
        Duration::from_millis(200),
    );
    cfg.request_timeout = Duration::from_secs(1);
    cfg.poll_interval = Duration::from_secs(1);
    ModbusLamp::new(cfg, clock.clone(), bus.clone())
}

async fn replay_against_driver(t: &Transcript) {
    let clock = Clock::virtual_time();
    let (drv, dev) = tokio::io::duplex(4096);
    let device = play_device(dev, t.steps.clone(), clock.clone());
    let title = t.title.clone();
    let steps = t.steps.clone();
    let framing = t.framing;
    let driver = async move {
        let bus = match framing {
            Framing::Tcp => tcp_bus(drv, 1),
            Framing::Rtu => rtu_bus(drv, 1),
        };
        let mut lamps: BTreeMap<u16, ModbusLamp> = BTreeMap::new();
        let mut last: Option<(String, Result<(), DeviceError>)> = None;
        let mut checked = 0;
        let mut failures = Vec::new();
        for step in steps {
            match step {
                Step::Call(op, args) => {
                    let arg = |k: usize| -> u16 {
                        args.get(k)
                            .and_then(|a| a.parse().ok())
                            .unwrap_or_else(|| panic!("{title}: {op}: bad args {args:?}"))
                    };
                    let r = match op.as_str() {
                        "set" => {
                            let on = match args.get(1).map(String::as_str) {
                                Some("on") => true,
                                Some("off") => false,
                                _ => panic!("{title}: set: expected on|off in {args:?}"),
                            };
                            let c = arg(0);
                            let l = lamps.entry(c).or_insert_with(|| lamp(&clock, &bus, c));
                            l.set(on).await
                        }
                        "wait_ready" => {
                            let c = arg(0);
                            let l = lamps.entry(c).or_insert_with(|| lamp(&clock, &bus, c));
                            l.wait_ready().await
                        }
                        "all_off" => all_off(&clock, &bus, arg(0), Duration::from_secs(2))
                            .await
                            .map_err(|e| DeviceError::new("module", e.kind(), e.to_string())),
                        other => panic!("{title}: unknown call `{other}`"),
                    };
                    last = Some((op, r));
                }
                Step::Expect(e) => {
                    let (op, r) = last.as_ref().expect("expect without call");
                    if let Err(f) = check(op, &e, r) {
                        failures.push(f);
                    }
                    checked += 1;
                }
                _ => {}
            }
        }
        // Close the link so the device sees the end.
        drop(lamps);
        drop(bus);
        (checked, failures)
    };
    let (dev_result, (checked, failures)) = tokio::join!(device, driver);
    // The device's view first: it names the first byte that differed.
    if let Err(e) = dev_result {
        panic!("{}: device: {e}; driver: {failures:?}", t.title);
    }
    assert!(failures.is_empty(), "{}: {failures:?}", t.title);
    assert!(checked > 0, "{}: no expectations checked", t.title);
}

#[test]
fn every_block_parses_and_names_its_framing() {
    let ts = transcripts();
    assert!(ts.len() >= 6, "only {} transcripts found", ts.len());
    for t in &ts {
        assert!(
            t.steps.iter().any(|s| matches!(s, Step::Send(_))),
            "{}: no request",
            t.title
        );
    }
    assert!(ts.iter().any(|t| t.framing == Framing::Tcp));
    assert!(ts.iter().any(|t| t.framing == Framing::Rtu));
}

#[tokio::test(start_paused = true)]
async fn transcripts_replay_against_simulated_module() {
    for t in &transcripts() {
        replay_against_sim(t).await;
    }
}

#[tokio::test(start_paused = true)]
async fn transcripts_replay_against_driver() {
    for t in &transcripts() {
        replay_against_driver(t).await;
    }
}
