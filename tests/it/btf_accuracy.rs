//! The whole BTF chain against the scene simulator's ground truth: a
//! simulated capture, registration, compression with C components, and
//! reconstruction at held-out (light, view) pairs. The figures it prints
//! are the ones quoted in the notes:
//! `cargo test --release --test btf_accuracy -- --nocapture`.

use std::path::Path;
use std::process::Command;

use rigd_core::geometry::Direction;

fn rigd() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rigd"))
}

fn ring(theta: f64, n: usize, offset: f64) -> Vec<serde_json::Value> {
    (0..n)
        .map(|k| serde_json::json!({"theta_deg": theta, "phi_deg": offset + 360.0 * k as f64 / n as f64}))
        .collect()
}

fn plan(dir: &Path) -> std::path::PathBuf {
    let mut lights = vec![serde_json::json!({"theta_deg": 0, "phi_deg": 0})];
    lights.extend(ring(30.0, 6, 0.0));
    lights.extend(ring(60.0, 8, 0.0));
    let mut views = ring(20.0, 3, 0.0);
    views.extend(ring(50.0, 4, 45.0));
    let p = dir.join("plan.json");
    std::fs::write(
        &p,
        serde_json::json!({"lights": lights, "views": views}).to_string(),
    )
    .unwrap();
    p
}

#[test]
fn held_out_reconstruction_error_against_the_true_btf() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let profile = crate::common::bonn_monochrome(dir.path());
    let status = rigd()
        .args(["run", "--sim", "--profile"])
        .arg(&profile)
        .args([
            "--scene",
            "ps-target",
            "--frame-size",
            "768x512",
            "--sample",
            "l",
            "--progress",
            "none",
            "--plan",
        ])
        .arg(plan(dir.path()))
        .arg("--out")
        .arg(&run)
        .status()
        .unwrap();
    assert!(status.success());
    let out = rigd()
        .args([
            "process", "rectify", "--size", "192", "--final", "48", "--bits", "float",
        ])
        .arg(&run)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Held out: directions between the measured rings and azimuths; and
    // one measured pair, where only the capture and registration err.
    let measured = (Direction::new(30.0, 60.0), Direction::new(20.0, 120.0));
    let pairs = [
        measured,
        (Direction::new(45.0, 20.0), Direction::new(35.0, 70.0)),
        (Direction::new(15.0, 200.0), Direction::new(20.0, 300.0)),
        (Direction::new(50.0, 100.0), Direction::new(45.0, 200.0)),
    ];
    let scene = rigd_sim::scene::Scene::load("ps-target").unwrap();
    let truths: Vec<Vec<f32>> = pairs
        .iter()
        .map(|&(l, v)| rigd::truth::true_texture(&scene, 48, l, v))
        .collect();
    let mut by_c = Vec::new();
    for c in [1, 2, 4, 8, 15] {
        let status = rigd()
            .args(["process", "btf", "--components", &c.to_string()])
            .arg(&run)
            .output()
            .unwrap();
        assert!(
            status.status.success(),
            "{}",
            String::from_utf8_lossy(&status.stderr)
        );
        let errs = rigd::postprocess::btf::btf_error(&run, &pairs, &truths).unwrap();
        assert!(errs.iter().all(|e| e.rms.is_finite()));
        let held_out = &errs[1..];
        let mean = held_out.iter().map(|e| e.rms).sum::<f64>() / held_out.len() as f64;
        let scale = held_out.iter().map(|e| e.truth_rms).sum::<f64>() / held_out.len() as f64;
        eprintln!(
            "C = {c:2}: held-out RMS error {mean:.4} ({:.1} % of the truth's RMS {scale:.4}); at a measured pair {:.4} ({:.1} %)",
            100.0 * mean / scale,
            errs[0].rms,
            100.0 * errs[0].rms / errs[0].truth_rms
        );
        by_c.push((c, mean, scale, errs[0].rms / errs[0].truth_rms));
    }
    let (_, first, scale, _) = by_c[0];
    let (_, last, _, measured_rel) = by_c[by_c.len() - 1];
    assert!(last <= first, "more components do not help: {by_c:?}");
    // Capture and registration alone: a few per cent at a measured pair.
    assert!(measured_rel < 0.05, "{by_c:?}");
    // Interpolating 15 lights and 7 views of the domes' relief costs more,
    // but stays well inside the signal.
    assert!(last < 0.3 * scale, "{by_c:?}");
}
