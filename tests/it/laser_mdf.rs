//! A laser scan on the simulated MSRA rig (Wang et al., §3.2), end to end:
//! `rigd run --plan laser:…` captures the calibration frames and the sweeps,
//! `rigd process mdf` turns them into displacement images, measured against
//! the ps-target's true geometry.

use std::path::{Path, PathBuf};
use std::process::Command;

fn rigd() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rigd"))
}

/// The MSRA profile with three of its cameras (10°, 40°, 60°), a longer
/// simulated lens and the ps-target, so small frames resolve the domes.
fn profile(dir: &Path) -> PathBuf {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-profiles/msra-btf-mdf.toml");
    let text = std::fs::read_to_string(src).unwrap();
    let cameras = r#"cameras = ["cam0", "cam1", "cam2", "cam3", "cam4", "cam5", "cam6", "cam7"]"#;
    assert!(text.contains(cameras));
    let text = text
        .replace(cameras, r#"cameras = ["cam0", "cam3", "cam5"]"#)
        .replace(
            "[sim]\nframe_size = [64, 48]",
            "[sim]\nframe_size = [240, 180]\nzoom = 2.4\nscene = \"ps-target\"",
        );
    assert!(text.contains("zoom = 2.4"));
    let p = dir.join("msra-laser.toml");
    std::fs::write(&p, text).unwrap();
    p
}

fn run_ok(cmd: &mut Command) -> String {
    let out = cmd.output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

fn mdf(run: &Path, extra: &[&str]) -> serde_json::Value {
    let stdout = run_ok(rigd().args(["process", "mdf"]).arg(run).args(extra));
    eprintln!("rigd process mdf {}\n{stdout}", extra.join(" "));
    json(&run.join("processed/mdf/report.json"))
}

/// (mean error mm, coverage) per view, in camera order.
fn errors(report: &serde_json::Value) -> Vec<(String, f64, f64)> {
    report["views"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| {
            let t = &v["truth"];
            (
                v["camera"].as_str().unwrap().to_string(),
                t["mean_mm"].as_f64().unwrap_or(f64::NAN),
                t["coverage"].as_f64().unwrap_or(0.0),
            )
        })
        .collect()
}

#[test]
fn a_laser_scan_measures_the_domes() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let plan = "laser:sources=4,turns=1,step=0.75";
    run_ok(
        rigd()
            .args([
                "run",
                "--sim",
                "--progress",
                "none",
                "--plan",
                plan,
                "--profile",
            ])
            .arg(profile(dir.path()))
            .arg("--out")
            .arg(&run),
    );

    // The dataset: calibration frames on the plate and on the turntable,
    // then sweeps at video rate with the tilt as measured.
    let manifest = json(&run.join("manifest.json"));
    assert_eq!(manifest["state"], "completed");
    let frames = manifest["frames"].as_array().unwrap();
    let per_sweep = (2.0f64 * 65.0 / 0.75).ceil() as usize + 1;
    assert_eq!(frames.len(), (2 + per_sweep) * 4 * 3);
    let plate = frames
        .iter()
        .filter(|f| f["laser"]["role"] == "calibration" && f["laser"]["plane_mm"] == 10.0)
        .count();
    assert_eq!(plate, 4 * 3);
    let mut sweep0: Vec<&serde_json::Value> = frames
        .iter()
        .filter(|f| f["laser"]["sweep"] == 0 && f["camera"] == "cam0")
        .collect();
    sweep0.sort_by_key(|f| f["laser"]["frame"].as_u64().unwrap());
    assert_eq!(sweep0.len(), per_sweep);
    for pair in sweep0.windows(2) {
        let dt = pair[1]["t_s"].as_f64().unwrap() - pair[0]["t_s"].as_f64().unwrap();
        assert!(
            (dt - 1.0 / 7.5).abs() < 1e-3,
            "frames {dt} s apart, not at 7.5 Hz"
        );
        let (a, b) = (
            pair[0]["laser"]["tilt_deg"].as_f64().unwrap(),
            pair[1]["laser"]["tilt_deg"].as_f64().unwrap(),
        );
        assert!(b < a, "the tilt sweeps down: {a} then {b}");
        assert!(frames[0]["exposure_s"].as_f64().unwrap() <= 0.002);
    }

    // Planes through the profile's emitter: a few hundredths of a mm near
    // the pole (pixels are 0.6 mm), more at 60° where the domes occlude.
    let emitter = mdf(&run, &["--planes", "emitter"]);
    for (camera, mean, coverage) in errors(&emitter) {
        let bound = if camera == "cam0" { 0.05 } else { 0.25 };
        assert!(mean < bound, "{camera}: mean depth error {mean} mm");
        assert!(coverage > 0.95, "{camera}: coverage {coverage}");
    }
    let depth = rigd_process::npy::read_f32(&run.join("processed/mdf/t000_cam3.npy")).unwrap();
    assert_eq!(depth.shape, vec![180, 240]);
    assert!(depth
        .data
        .iter()
        .all(|v| v.is_finite() && (*v == -1.0 || *v >= 0.0)));
    assert!(run.join("processed/mdf/t000_cam3.png").exists());

    // Wang et al.'s model (planes of a sweep parallel at the calibrated angle)
    // pays for the emitter being near.
    let calibrated = mdf(&run, &[]);
    let cal = calibrated["calibrations"].as_array().unwrap();
    assert_eq!(cal.len(), 4 * 3);
    for c in cal {
        let (a, g) = (
            c["angle_deg"].as_f64().unwrap(),
            c["geometric_angle_deg"].as_f64().unwrap(),
        );
        assert!((a - g).abs() < 1.0, "calibrated {a}° vs geometric {g}°");
    }
    for (camera, mean, _) in errors(&calibrated) {
        assert!(mean < 0.3, "{camera}: mean depth error {mean} mm");
    }

    // More source positions fill the occlusions of fewer.
    let mut table = Vec::new();
    for n in ["1", "2", "4"] {
        let r = mdf(&run, &["--planes", "emitter", "--sources", n]);
        let e = errors(&r);
        let mean = e.iter().map(|x| x.1).sum::<f64>() / e.len() as f64;
        let cov = e.iter().map(|x| x.2).sum::<f64>() / e.len() as f64;
        table.push((n, mean, cov));
    }
    eprintln!("sources\tmean error\tcoverage");
    for (n, m, c) in &table {
        eprintln!("{n}\t{m:.4} mm\t{:.1}%", 100.0 * c);
    }
    assert!(table[2].2 > table[0].2, "coverage {table:?}");
}

#[test]
fn a_fault_mid_sweep_retakes_the_sweep_and_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    // cam3's 12th exposure: in the sweep, after 2 calibration frames.
    run_ok(
        rigd()
            .args([
                "run",
                "--sim",
                "--progress",
                "none",
                "--profile",
                "msra-btf-mdf",
                "--plan",
                "laser:sources=1,turns=1,step=5",
                "--sim-fault",
                "cam3:expose:12:timeout",
                "--out",
            ])
            .arg(&run),
    );
    let manifest = json(&run.join("manifest.json"));
    assert_eq!(manifest["state"], "completed");
    let per_sweep = (2.0f64 * 65.0 / 5.0).ceil() as usize + 1;
    let frames = manifest["frames"].as_array().unwrap();
    assert_eq!(frames.len(), (2 + per_sweep) * 8);
    // The sweep was retaken: the frames taken before the fault were written
    // twice, and their first lines went to the journal's history when the
    // run completed, leaving one line per image.
    let journal = std::fs::read_to_string(run.join("journal.ndjson")).unwrap();
    assert_eq!(journal.lines().count(), frames.len());
    let history = std::fs::read_to_string(run.join("journal.retaken.ndjson")).unwrap();
    assert!(history.lines().count() > 0, "the sweep was not retaken");
}
