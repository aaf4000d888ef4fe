//! `rigd sim serve`: the simulated firmware of the MSRA rig on ptys and
//! loopback sockets, reached by a stock Modbus TCP client and by `rigd run`
//! with the profile it prints, in real time.

use crate::common;

use std::time::{Duration, Instant};

use common::{assert_complete_run, repo_file, rigd, serve_sim};
use tokio_modbus::client::Reader;

#[test]
fn served_msra_rig_answers_a_modbus_client_and_completes_a_run() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let served = tmp.path().join("served.toml");
    let (_server, lines) = serve_sim(&repo_file("rig-profiles/msra-btf-mdf.toml"), &served, 20.0);
    let modbus = lines
        .iter()
        .find(|l| l.contains("Modbus TCP"))
        .and_then(|l| l.split_whitespace().last())
        .expect("a Modbus TCP endpoint line");
    let addr: std::net::SocketAddr = modbus.parse().expect("host:port");
    assert!(addr.ip().is_loopback(), "{addr}");
    for dev in ["turntable", "light_arc", "laser_tilt"] {
        let line = lines
            .iter()
            .find(|l| l.split_whitespace().nth(1) == Some(dev))
            .unwrap_or_else(|| panic!("no endpoint for {dev}: {lines:?}"));
        assert!(line.contains("/dev/pts/"), "{line}");
    }
    for cam in 0..8 {
        let name = format!("cam{cam}");
        assert!(
            lines
                .iter()
                .any(|l| l.split_whitespace().nth(1) == Some(name.as_str())
                    && l.contains("PTP/IP")),
            "{name}"
        );
    }

    // A stock Modbus TCP client reads the eight lamp coils and the laser.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let coils = runtime.block_on(async {
        let mut ctx = tokio_modbus::client::tcp::connect(addr)
            .await
            .expect("connect");
        ctx.read_coils(0, 9)
            .await
            .expect("transport")
            .expect("reply")
    });
    assert_eq!(coils, vec![false; 9]);

    // `rigd run` with the printed profile drives the served rig.
    let plan = common::tiny_plan(tmp.path());
    let out = tmp.path().join("run");
    let start = Instant::now();
    let o = rigd()
        .args([
            "run",
            "--profile",
            served.to_str().expect("utf8"),
            "--plan",
            plan.to_str().expect("utf8"),
            "--sample",
            "served",
            "--progress",
            "none",
            "--out",
            out.to_str().expect("utf8"),
        ])
        .output()
        .expect("rigd run");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(start.elapsed() < Duration::from_secs(60));
    let m = assert_complete_run(&out, 4);
    assert_eq!(m.profile, "msra-btf-mdf-sim-served");
}
