//! `rigd tradeoff` on the Bonn rig and corduroy, at the smallest textures:
//! every family's rows, the three files, and the orderings a lab relies on
//! (fewer rings: less time, more error).

use std::process::Command;

#[test]
fn the_tradeoff_table_is_written_and_ordered() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_rigd"))
        .args([
            "tradeoff",
            "--profile",
            concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/rig-profiles/bonn-gonioreflectometer.toml"
            ),
            "--scene",
            "corduroy",
            "--texture",
            "4",
            "--held-out",
            "6",
            "--render-size",
            "64x48",
            "--out",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{stdout}");
    for f in ["tradeoff.csv", "tradeoff.json", "tradeoff.svg"] {
        assert!(dir.path().join(f).exists(), "{f}");
    }
    let svg = std::fs::read_to_string(dir.path().join("tradeoff.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("polyline"));
    // A panel per family, the profile's default plan (h1) ringed.
    for title in [
        "How many directions?",
        "How many PCA components?",
        "How many laser sources?",
        "How many lights?",
        "Which effects matter?",
    ] {
        assert!(svg.contains(title), "{title}");
    }
    assert!(svg.contains("h1 (default)"));
    // `--from` without a question draws the figure again from the JSON.
    std::fs::remove_file(dir.path().join("tradeoff.svg")).unwrap();
    let redraw = Command::new(env!("CARGO_BIN_EXE_rigd"))
        .args(["tradeoff", "--from"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(redraw.status.success(), "{redraw:?}");
    assert_eq!(
        std::fs::read_to_string(dir.path().join("tradeoff.svg")).unwrap(),
        svg
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("tradeoff.json")).unwrap()).unwrap();
    let rows = report["rows"].as_array().unwrap();
    let find = |family: &str, setting: &str| {
        rows.iter()
            .find(|r| r["family"] == family && r["setting"] == setting)
            .unwrap_or_else(|| panic!("no row {family} / {setting}"))
    };
    for r in rows {
        if let Some(e) = r["error"].as_f64() {
            assert!(e.is_finite() && e >= 0.0, "{r}");
        }
    }
    let (h2, three) = (find("plans", "h2"), find("plans", "h2, 3 rings"));
    assert_eq!(h2["images"], 6561);
    assert_eq!(three["images"], 19 * 19);
    assert!(three["physical_s"].as_f64() < h2["physical_s"].as_f64());
    assert!(
        three["error"].as_f64() > h2["error"].as_f64(),
        "{three} vs {h2}"
    );
    // The texture-space shortcut, checked through camera and registration.
    let chain = find("plans", "h2, 3 rings, camera chain");
    assert_eq!(chain["images"], 361);
    let e = chain["error"].as_f64().unwrap();
    assert!(e.is_finite() && e > 0.0 && e < 1.5, "{chain}");
    assert!(chain["physical_s"].as_f64() >= three["physical_s"].as_f64());
    for c in [2, 4, 8, 16, 32] {
        find("pca", &format!("C = {c}"));
    }
    let c2 = find("pca", "C = 2")["bytes"].as_u64().unwrap();
    let c32 = find("pca", "C = 32")["bytes"].as_u64().unwrap();
    assert!(c32 > c2);
    assert!(rows.iter().any(|r| r["family"] == "fidelity"
        && r["setting"].as_str().unwrap().starts_with("without relief")));
    // Laser: four subsets of one scan, more sources take longer.
    let laser: Vec<&serde_json::Value> = rows.iter().filter(|r| r["family"] == "laser").collect();
    assert_eq!(laser.len(), 4, "{laser:?}");
    for pair in laser.windows(2) {
        assert!(pair[1]["physical_s"].as_f64() > pair[0]["physical_s"].as_f64());
    }
    for r in &laser {
        assert_eq!(r["unit"], "mm");
        let e = r["error"].as_f64().unwrap();
        assert!(e > 0.0 && e < 5.0, "{r}");
        assert!(
            r["detail"]
                .as_str()
                .unwrap()
                .contains("sample pixels every setting measures"),
            "{r}"
        );
    }
    // On the same pixels, more sources never measure worse (beyond the
    // error bars), and each reaches at least as much of the sample.
    for pair in laser.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        let bound = a["error"].as_f64().unwrap()
            + 2.0 * (a["spread"].as_f64().unwrap() + b["spread"].as_f64().unwrap());
        assert!(b["error"].as_f64().unwrap() <= bound, "{a} then {b}");
        assert!(
            b["coverage"].as_f64() >= a["coverage"].as_f64(),
            "{a} then {b}"
        );
    }
    // Every measured row carries its standard error; fidelity (one frame)
    // has none.
    for r in rows {
        let spread = r["spread"].as_f64();
        if r["family"] == "fidelity" {
            assert!(spread.is_none(), "{r}");
        } else {
            assert!(spread.is_some_and(|s| s.is_finite() && s >= 0.0), "{r}");
        }
    }
    // A plan row carries its directions (all paired with all), for the
    // dashboard's start form.
    assert_eq!(h2["plan"], "h2");
    assert_eq!(h2["directions"].as_array().unwrap().len(), 81);
    assert_eq!(
        find("plans", "h2, 3 rings")["directions"]
            .as_array()
            .unwrap()
            .len(),
        19
    );
    // Exposure policies on the default plan: each with its time, data,
    // clipped share and error near the mirror, with its standard error.
    let exposure: Vec<&serde_json::Value> =
        rows.iter().filter(|r| r["family"] == "exposure").collect();
    assert_eq!(exposure.len(), 4, "{exposure:?}");
    assert_eq!(exposure[0]["setting"], "single");
    assert_eq!(exposure[0]["physical_s"], find("plans", "h1")["physical_s"]);
    for r in &exposure {
        let share = r["clipped_share"].as_f64().expect("clipped_share");
        assert!((0.0..=1.0).contains(&share), "{r}");
        let near = r["near_mirror"]["error"]
            .as_f64()
            .expect("near-mirror error");
        assert!(near.is_finite() && near > 0.0, "{r}");
        assert!(r["near_mirror"]["spread"].as_f64().is_some(), "{r}");
        assert!(r["physical_s"].as_f64() >= exposure[0]["physical_s"].as_f64());
    }
    assert!(svg.contains("Which exposures?"));
    let csv = std::fs::read_to_string(dir.path().join("tradeoff.csv")).unwrap();
    assert!(csv
        .lines()
        .next()
        .unwrap()
        .contains("near_mirror_error,near_mirror_spread,clipped_share"));

    // Photometric stereo: twelve lights, robust, beat three.
    let three = find("photometric stereo", "3 lights");
    let twelve = find("photometric stereo", "12 lights, robust");
    assert_eq!(three["unit"], "degrees");
    assert!(
        twelve["error"].as_f64() < three["error"].as_f64(),
        "{twelve} vs {three}"
    );
    assert!(twelve["physical_s"].as_f64() > three["physical_s"].as_f64());

    // The knee of each family, a computed sentence each.
    let summary: Vec<&str> = report["summary"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l.as_str().unwrap())
        .collect();
    for question in [
        "How many directions? ",
        "How many components? ",
        "How many lights? ",
        "How many laser sources? ",
        "Which exposures? ",
    ] {
        let line = summary
            .iter()
            .find(|l| l.starts_with(question))
            .unwrap_or_else(|| panic!("no {question} in {summary:?}"));
        assert!(
            (line.contains(" reaches ") && line.contains(" adds "))
                || line.contains(" is both the cheapest and the most accurate, "),
            "{line}"
        );
    }
    assert!(
        stdout.contains("summary: How many directions? "),
        "{stdout}"
    );

    // `--budget` and `--target`, answered from the report just written.
    let plans: Vec<(String, f64, f64)> = rows
        .iter()
        .filter(|r| {
            r["family"] == "plans" && !r["setting"].as_str().unwrap().ends_with("camera chain")
        })
        .map(|r| {
            (
                r["setting"].as_str().unwrap().to_string(),
                r["physical_s"].as_f64().unwrap(),
                r["error"].as_f64().unwrap(),
            )
        })
        .collect();
    let ask = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_rigd"))
            .arg("tradeoff")
            .args(args)
            .arg("--from")
            .arg(dir.path())
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stdout).to_string(),
        )
    };
    let chosen = |stdout: &str| {
        let line = stdout
            .lines()
            .find(|l| l.ends_with(" (chosen)") || l.contains(" (chosen)\t"))
            .unwrap_or_else(|| panic!("no chosen plan in {stdout}"));
        let name = line.trim().split(" (chosen)").next().unwrap().to_string();
        plans
            .iter()
            .find(|p| p.0 == name)
            .unwrap_or_else(|| panic!("{name} is not a plan row"))
            .clone()
    };
    let (code, stdout) = ask(&["--budget", "3h"]);
    assert_eq!(code, Some(0), "{stdout}");
    assert!(stdout.starts_with("within 3 h: "), "{stdout}");
    let (_, time, error) = chosen(&stdout);
    assert!(time <= 3.0 * 3600.0, "{stdout}");
    for p in plans.iter().filter(|p| p.1 <= 3.0 * 3600.0) {
        assert!(
            p.2 >= error,
            "{} beats the choice within 3 h: {stdout}",
            p.0
        );
    }
    // A target some plans reach: the median plan's error.
    let mut errors: Vec<f64> = plans.iter().map(|p| p.2).collect();
    errors.sort_by(f64::total_cmp);
    let target = errors[errors.len() / 2];
    let (code, stdout) = ask(&["--target", &format!("{target}")]);
    assert_eq!(code, Some(0), "{stdout}");
    let (_, time, error) = chosen(&stdout);
    assert!(error <= target, "{stdout}");
    for p in plans.iter().filter(|p| p.2 <= target) {
        assert!(p.1 >= time, "{} is faster at {target}: {stdout}", p.0);
    }
    let (code, stdout) = ask(&["--budget", "1m"]);
    assert_eq!(code, Some(1), "{stdout}");
    assert!(
        stdout.contains("no measured plan fits in 1 min"),
        "{stdout}"
    );
    assert_eq!(ask(&["--budget", "soon"]).0, Some(2));
}
