//! Bringing up a rig as a lab would: `rigd rig check` against GRBL boards
//! as they ship (factory settings, no banner on open), served by `rigd sim
//! serve` and reached the way hardware is; and lamps on a coil-only relay
//! module served by pymodbus, an implementation that shares no code with
//! rigd, through a complete VirTex capture and an emergency stop.

use crate::common;

use std::path::Path;
use std::time::Duration;

use common::{assert_complete_run, relay_log, relay_module, repo_file, rigd, serve_sim};
use rigd::rig::drivers::modbus::{all_off, connect_tcp, ModbusConfig, ModbusLamp};
use rigd::rig::hal::Lamp;
use rigd_core::Clock;

/// `rigd rig check --profile FILE [--json]`: exit code and stdout.
pub(crate) fn rig_check(profile: &Path, json: bool) -> (i32, String) {
    let mut cmd = rigd();
    cmd.args(["rig", "check", "--profile"]).arg(profile);
    if json {
        cmd.arg("--json");
    }
    let o = cmd.output().expect("rigd rig check");
    let stdout = String::from_utf8_lossy(&o.stdout).to_string();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.trim().is_empty(), "{stderr}");
    (o.status.code().unwrap_or(-1), stdout)
}

pub(crate) fn line_of<'a>(out: &'a str, device: &str) -> &'a str {
    out.lines()
        .find(|l| l.split_whitespace().nth(1) == Some(device))
        .unwrap_or_else(|| panic!("no line for {device}:\n{out}"))
}

/// A profile as TOML, edited in place.
pub(crate) fn edit(path: &Path, out: &Path, f: impl FnOnce(&mut toml::Table)) {
    let text = std::fs::read_to_string(path).expect("read profile");
    let mut t: toml::Table = text.parse().expect("profile is TOML");
    f(&mut t);
    std::fs::write(out, toml::to_string(&t).expect("write TOML")).expect("write profile");
}

pub(crate) fn device<'a>(t: &'a mut toml::Table, name: &str) -> &'a mut toml::Table {
    t.get_mut("devices")
        .and_then(|d| d.get_mut(name))
        .and_then(|d| d.as_table_mut())
        .unwrap_or_else(|| panic!("no [devices.{name}]"))
}

/// The MSRA rig's three GRBL boards with factory settings (`$22=0`,
/// `$110=500`, `$120=10`): `rig check` names each setting that differs,
/// with the controller's and the profile's values and the line that fixes
/// it, and exits 1; with `configure = true` it writes them and passes; and
/// the boards keep them, so a check without `configure` passes after that.
#[test]
fn rig_check_names_a_settings_mismatch_then_passes_after_configure() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let stock = tmp.path().join("msra-stock.toml");
    edit(&repo_file("rig-profiles/msra-btf-mdf.toml"), &stock, |t| {
        // A continuous turntable without a home switch, zeroed by hand.
        device(t, "turntable").insert("homing".into(), false.into());
        let sim = t
            .get_mut("sim")
            .and_then(|s| s.as_table_mut())
            .expect("[sim]");
        sim.insert("grbl_settings".into(), "factory".into());
    });
    let served = tmp.path().join("served.toml");
    let (_server, _) = serve_sim(&stock, &served, 20.0);

    let (code, out) = rig_check(&served, false);
    assert_eq!(code, 1, "{out}");
    let turntable = line_of(&out, "turntable");
    assert!(turntable.starts_with("FAIL"), "{turntable}");
    for part in [
        "$110 (X max rate, deg/min) is 500.000 on the controller, the profile needs 1800.000 (motion.max_velocity = 30 deg/s)",
        "$120 (X acceleration, deg/s²) is 10.000 on the controller, the profile needs 60.000",
        "send `$110=1800.000`, `$120=60.000` on the controller, or put `configure = true`",
    ] {
        assert!(turntable.contains(part), "{part}\n{turntable}");
    }
    let arc = line_of(&out, "light_arc");
    assert!(
        arc.contains("$22 (homing cycle enable) is 0 on the controller, the profile needs 1"),
        "{arc}"
    );
    assert!(arc.contains("needs at least 360.000"), "{arc}");
    for ok in ["cam0", "cam7", "lamp0", "laser"] {
        assert!(line_of(&out, ok).starts_with("OK"), "{out}");
    }
    assert!(out.contains("3 of 20 devices not usable"), "{out}");

    let configured = tmp.path().join("served-configure.toml");
    edit(&served, &configured, |t| {
        for axis in ["turntable", "light_arc", "laser_tilt"] {
            device(t, axis).insert("configure".into(), true.into());
        }
    });
    let (code, out) = rig_check(&configured, false);
    assert_eq!(code, 0, "{out}");
    let turntable = line_of(&out, "turntable");
    assert!(turntable.starts_with("OK"), "{turntable}");
    for part in [
        "GRBL 1.1h",
        "$22=0 $20=0 $110=1800.000 $120=60.000",
        "no homing: zeroed by the operator at its 0° mark",
        "Idle at MPos 0.000°",
    ] {
        assert!(turntable.contains(part), "{part}\n{turntable}");
    }
    assert!(
        line_of(&out, "light_arc").contains("homes with `$H`"),
        "{out}"
    );
    assert!(out.contains("all 20 devices usable"), "{out}");

    // The boards keep what was written (their EEPROM): no `configure` now.
    let (code, json) = rig_check(&served, true);
    assert_eq!(code, 0, "{json}");
    let v: serde_json::Value = serde_json::from_str(&json).expect("JSON report");
    assert_eq!(v["usable"], true);
    assert_eq!(v["devices"].as_array().map(Vec::len), Some(20));
    // Every device's time to its verdict, and the whole check's.
    let slowest = v["devices"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|d| d["connect_s"].as_f64())
        .fold(0.0, f64::max);
    let took = v["took_s"].as_f64().expect("took_s");
    assert!(slowest > 0.0 && took >= slowest, "{took} vs {slowest}");
}

/// The lamps of the VirTex rig on a coil-only module served by pymodbus:
/// `rig check` sees a coil-only module, a complete capture switches each
/// lamp on (its warm-up timed by rigd) and off again in turn, and nothing
/// but FC01, FC05 and FC0F reaches the module.
/// The VirTex rig served by `rigd sim serve`, its lamps on a coil-only
/// pymodbus module: the processes, the profile, and the module's log.
fn virtex_on_pymodbus(tmp: &Path) -> (Vec<common::Child>, std::path::PathBuf, std::path::PathBuf) {
    let log = tmp.join("relay.log");
    let (module, port) = relay_module(&log, &[]);
    let served = tmp.join("served.toml");
    let (server, _) = serve_sim(
        &repo_file("rig-profiles/virtex-photometric-stereo.toml"),
        &served,
        20.0,
    );
    let profile = tmp.join("virtex-pymodbus.toml");
    edit(&served, &profile, |t| {
        for lamp in ["lamp0", "lamp1", "lamp2"] {
            let mut transport = toml::Table::new();
            transport.insert("type".into(), "modbus_tcp".into());
            transport.insert("host".into(), "127.0.0.1".into());
            transport.insert("port".into(), i64::from(port).into());
            transport.insert("unit".into(), 1.into());
            transport.insert("status_registers".into(), false.into());
            device(t, lamp).insert("transport".into(), transport.into());
        }
    });
    (vec![module, server], profile, log)
}

#[test]
fn a_coil_only_pymodbus_module_drives_the_lamps_of_a_virtex_capture() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (_procs, profile, log) = virtex_on_pymodbus(tmp.path());

    let (code, out) = rig_check(&profile, false);
    assert_eq!(code, 0, "{out}");
    assert!(
        line_of(&out, "lamp1").contains(
            "relay coil 1 off; coil-only module: rigd times the 2 s warm-up from the coil's read-back"
        ),
        "{out}"
    );

    let run = tmp.path().join("run");
    let o = rigd()
        .args(["run", "--profile"])
        .arg(&profile)
        .args(["--sample", "pymodbus", "--progress", "none", "--out"])
        .arg(&run)
        .output()
        .expect("rigd run");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_complete_run(&run, 3);

    let writes = relay_log(&log);
    assert!(
        !writes.iter().any(|l| l.contains("refused")),
        "only coil functions: {writes:?}"
    );
    // Each lamp on, then off, one at a time, in the plan's order.
    let mut on = [false; 3];
    let mut switched_on = Vec::new();
    for w in &writes {
        let Some(rest) = w.strip_prefix("FC05 coil=") else {
            continue;
        };
        let (coil, state) = rest.split_once(" on=").expect("FC05 line");
        let coil: usize = coil.parse().expect("coil");
        on[coil] = state == "1";
        if on[coil] {
            switched_on.push(coil);
        }
        assert!(on.iter().filter(|&&x| x).count() <= 1, "{writes:?}");
    }
    assert_eq!(switched_on, vec![0, 1, 2], "{writes:?}");
    assert_eq!(on, [false; 3], "{writes:?}");
}

/// The emergency stop on a coil-only module served by pymodbus: every coil
/// off in one FC0F; a module that refuses FC0F gets FC05 per coil, within
/// the stop's deadline.
#[tokio::test]
async fn an_emergency_stop_switches_a_pymodbus_module_off_with_or_without_fc0f() {
    let tmp = tempfile::tempdir().expect("tempdir");
    for refuse in [false, true] {
        let log = tmp.path().join(format!("relay-{refuse}.log"));
        let extra: &[&str] = if refuse { &["--refuse-fc0f"] } else { &[] };
        let (_module, port) = relay_module(&log, extra);
        let clock = Clock::real();
        let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
        let bus = connect_tcp(&clock, addr, 1, Duration::from_secs(5))
            .await
            .expect("connect");
        for coil in 0..3 {
            let mut cfg = ModbusConfig::new(
                &format!("lamp{coil}"),
                coil,
                Duration::from_millis(50),
                Duration::ZERO,
            );
            cfg.status_registers = false;
            let mut lamp = ModbusLamp::new(cfg, clock.clone(), bus.clone());
            lamp.set(true).await.expect("on");
            lamp.wait_ready().await.expect("ready");
        }
        all_off(&clock, &bus, 3, Duration::from_secs(1))
            .await
            .expect("all off");
        let writes = relay_log(&log);
        let stop: Vec<&str> = writes.iter().skip(3).map(String::as_str).collect();
        let expected: &[&str] = if refuse {
            &[
                "FC0F refused",
                "FC05 coil=0 on=0",
                "FC05 coil=1 on=0",
                "FC05 coil=2 on=0",
            ]
        } else {
            &["FC0F addr=0 values=000"]
        };
        assert_eq!(stop, expected, "{writes:?}");
    }
}

/// `rigd run --resume` on a rig with an axis without homing asks for the
/// operator's word that the axis is at its mark (`--reference-confirmed`),
/// exiting 2 (bad input) without it and resuming with it.
#[test]
fn a_cli_resume_on_an_axis_without_homing_needs_the_reference_confirmed() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let profile = tmp.path().join("msra-no-homing.toml");
    edit(
        &repo_file("rig-profiles/msra-btf-mdf.toml"),
        &profile,
        |t| {
            device(t, "turntable").insert("homing".into(), false.into());
        },
    );
    let plan = common::tiny_plan(tmp.path());
    let out = tmp.path().join("run");
    let o = rigd()
        .args(["run", "--sim", "--profile"])
        .arg(&profile)
        .args(["--plan"])
        .arg(&plan)
        .args(["--progress", "none", "--frame-size", "8x6"])
        .args([
            "--sim-fault",
            "light_arc:move:2:alarm=limit switch",
            "--out",
        ])
        .arg(&out)
        .output()
        .expect("rigd run");
    assert_eq!(
        o.status.code(),
        Some(3),
        "paused: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let o = rigd()
        .args(["run", "--resume"])
        .arg(&out)
        .output()
        .expect("rigd run --resume");
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("turntable without homing") && err.contains("--reference-confirmed"),
        "{err}"
    );
    let o = rigd()
        .args([
            "run",
            "--progress",
            "none",
            "--reference-confirmed",
            "--resume",
        ])
        .arg(&out)
        .output()
        .expect("rigd run --resume --reference-confirmed");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_complete_run(&out, 4);
}

/// The daemon on that hardware: manual lamp switching reaches the pymodbus
/// module (FC05, read back), and the emergency stop switches every coil off
/// in one FC0F.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemon_switches_pymodbus_lamps_by_hand_and_stops_them() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (_procs, profile, log) = virtex_on_pymodbus(tmp.path());
    let data = tmp.path().join("data");
    let mut s = common::http::start_with(&data, 1.0, profile.to_str(), false).await;
    let (status, check) = s.get("/api/v1/rig/check").await;
    assert_eq!(status, 200, "{check}");
    assert_eq!(check["usable"], true, "{check}");
    for lamp in ["lamp0", "lamp2"] {
        let (status, v) = s
            .post(
                "/api/v1/rig/manual/lamp",
                Some(serde_json::json!({"device": lamp, "on": true})),
            )
            .await;
        assert_eq!(status, 200, "{v}");
    }
    let (status, v) = s.post("/api/v1/estop", None).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["all_stopped"], true, "{v}");
    assert_eq!(
        relay_log(&log),
        [
            "FC05 coil=0 on=1",
            "FC05 coil=2 on=1",
            "FC0F addr=0 values=000"
        ],
        "every coil off in one request"
    );
    s.shutdown().await;
}

/// On a machine without the rig's hardware, every device fails with what
/// went wrong and where to look (exit 1); a bad profile is bad input (2).
#[test]
fn rig_check_without_the_hardware_names_every_device_and_the_fix() {
    let (code, out) = rig_check(
        &repo_file("rig-profiles/virtex-photometric-stereo.toml"),
        false,
    );
    assert_eq!(code, 1, "{out}");
    let cam = line_of(&out, "camera");
    assert!(
        cam.starts_with("FAIL") && cam.contains("cannot open USB camera 04a9:3200"),
        "{cam}"
    );
    assert!(
        cam.contains("fix: check that the device is powered and cabled"),
        "{cam}"
    );
    let lamp = line_of(&out, "lamp0");
    assert!(lamp.contains("/dev/ttyUSB1"), "{lamp}");
    assert!(out.contains("4 of 4 devices not usable"), "{out}");

    let o = rigd()
        .args(["rig", "check", "--profile", "no-such-profile.toml"])
        .output()
        .expect("rigd rig check");
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(err.lines().count(), 1, "{err}");
}
