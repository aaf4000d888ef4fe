//! The command line: plan listings, and one-line errors (never a panic) for
//! bad input.

use crate::common;

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use common::{repo_file, rigd, run_ok};

fn plan_json(plan: &str, profile: &str) -> serde_json::Value {
    let out = run_ok(&["plan", "show", plan, "--profile", profile, "--json"]);
    serde_json::from_slice(&out.stdout).expect("plan JSON")
}

/// (θ → number of distinct φ) of the light directions of a plan listing.
fn light_rings(v: &serde_json::Value) -> BTreeMap<i64, usize> {
    let mut lights = BTreeSet::new();
    for s in v["steps"].as_array().expect("steps") {
        let l = &s["light"];
        let theta = l["theta_deg"].as_f64().expect("theta");
        let phi = l["phi_deg"].as_f64().expect("phi");
        lights.insert((
            (theta * 1000.0).round() as i64,
            (phi * 1000.0).round() as i64,
        ));
    }
    let mut rings = BTreeMap::new();
    for (t, _) in lights {
        *rings.entry(t / 1000).or_insert(0) += 1;
    }
    rings
}

#[test]
fn h1_and_h2_have_6561_steps_and_81_lights_in_table_1_rings() {
    let bonn = repo_file("rig-profiles/bonn-gonioreflectometer.toml");
    for (plan, thetas) in [
        ("h1", [0, 17, 34, 51, 68, 85]),
        ("h2", [0, 15, 30, 45, 60, 75]),
    ] {
        let v = plan_json(plan, bonn.to_str().expect("utf8"));
        assert_eq!(v["steps_total"], 6561);
        assert_eq!(v["steps"].as_array().map(Vec::len), Some(6561));
        let rings = light_rings(&v);
        let expected: BTreeMap<i64, usize> =
            thetas.iter().copied().zip([1, 6, 12, 18, 20, 24]).collect();
        assert_eq!(rings, expected, "{plan}");
        assert!(v["estimated_physical_s"].as_f64().expect("estimate") > 3600.0);
        // The Bonn rig's 16-bit camera at its full resolution, 6561 times.
        let image = v["image_bytes"].as_u64().expect("image bytes");
        assert!(image > 10_000_000, "{}", v["image_bytes"]);
        assert_eq!(v["raw_bytes"].as_u64(), Some(6561 * image));
        let first = &v["steps"][0];
        for key in [
            "light",
            "view",
            "feasible",
            "trigger",
            "achieved_light",
            "achieved_view",
            "setpoints",
        ] {
            assert!(first.get(key).is_some(), "{key} missing");
        }
    }
}

#[test]
fn grid12x8_on_msra_has_9216_steps_sharing_triggers() {
    let v = plan_json(
        "grid12x8",
        repo_file("rig-profiles/msra-btf-mdf.toml")
            .to_str()
            .expect("utf8"),
    );
    assert_eq!(v["steps_total"], 9216);
    assert_eq!(v["triggers_total"], 1152);
    let mut per_trigger: BTreeMap<u64, usize> = BTreeMap::new();
    for s in v["steps"].as_array().expect("steps") {
        *per_trigger
            .entry(s["trigger"].as_u64().expect("trigger"))
            .or_insert(0) += 1;
    }
    assert!(per_trigger.values().all(|&n| n == 8));
    // 12 azimuths × 8 elevations of light, the same of view.
    let rings = light_rings(&v);
    assert_eq!(rings.len(), 8);
    assert!(rings.values().all(|&n| n == 12));
}

#[test]
fn plan_show_table_ends_with_totals() {
    let out = run_ok(&[
        "plan",
        "show",
        "lamps",
        "--profile",
        "virtex-photometric-stereo",
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    let totals = text
        .lines()
        .find(|l| l.starts_with("plan lamps on "))
        .unwrap_or_default();
    assert!(
        totals.contains("3 images") && totals.contains("estimated physical capture time"),
        "{text}"
    );
    // The raw data volume closes the listing.
    let last = text.lines().last().unwrap_or_default();
    assert!(
        last.starts_with("raw data: ") && last.contains(" an image at the cameras' resolution"),
        "{last}"
    );
}

#[test]
fn plan_from_a_file() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let file = tmp.path().join("ring.json");
    std::fs::write(
        &file,
        r#"{"directions":[{"theta_deg":0,"phi_deg":0},{"theta_deg":40,"phi_deg":0},{"theta_deg":40,"phi_deg":180}]}"#,
    )
    .expect("write");
    let v = plan_json(file.to_str().expect("utf8"), "bonn-gonioreflectometer");
    assert_eq!(v["steps_total"], 9);
    assert_eq!(v["plan"], "ring");
}

/// Runs rigd expecting bad input: exit code 2, one line on stderr, no panic.
fn fails_cleanly(args: &[&str]) -> String {
    fails_with(2, args)
}

/// Runs rigd expecting exit `code`, one line on stderr, no panic.
fn fails_with(code: i32, args: &[&str]) -> String {
    let out = rigd().args(args).output().expect("spawn");
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    assert_eq!(out.status.code(), Some(code), "rigd {args:?}: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    // clap adds a pointer to --help after argument errors; the error itself is one line.
    let lines = stderr
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with("For more information"))
        .count();
    assert_eq!(lines, 1, "not one line: {stderr}");
    assert!(stderr.starts_with("error: "), "{stderr}");
    stderr
}

fn broken_profile(dir: &Path, name: &str, from: &str, to: &str) -> String {
    let text = std::fs::read_to_string(repo_file("rig-profiles/bonn-gonioreflectometer.toml"))
        .expect("read");
    assert!(text.contains(from), "fixture drifted: {from}");
    let path = dir.join(name);
    std::fs::write(&path, text.replacen(from, to, 1)).expect("write");
    path.to_str().expect("utf8").to_string()
}

#[test]
fn broken_profiles_name_file_key_and_expectation() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let cases = [
        (
            "unknown-key.toml",
            "rail_radius_m = 1.6",
            "rail_radius_m = 1.6\nrail_radius = 2",
            "rig",
            "unknown field `rail_radius`",
        ),
        (
            "missing-device.toml",
            "camera = \"camera\"",
            "camera = \"cam9\"",
            "rig.camera",
            "no [devices.cam9]",
        ),
        (
            "inverted.toml",
            "min = 12.0, max = 172.0",
            "min = 172.0, max = 12.0",
            "devices.rail.limits",
            "expected min < max",
        ),
        (
            "missing-key.toml",
            "default_plan = \"h1\"\n",
            "",
            "",
            "missing field `default_plan`",
        ),
        (
            "bad-plan.toml",
            "default_plan = \"h1\"",
            "default_plan = \"h9\"",
            "default_plan",
            "unknown plan `h9`",
        ),
        ("syntax.toml", "[rig]", "[rig", "", "line"),
        (
            "homing-lamp.toml",
            "[devices.hmi]\nkind = \"lamp\"",
            "[devices.hmi]\nkind = \"lamp\"\nhoming = false",
            "devices.hmi.homing",
            "`homing` is for axes",
        ),
        (
            "homing-off-with-home.toml",
            "home_deg = 90.0",
            "home_deg = 90.0\nhoming = false",
            "devices.rail.home_deg",
            "zeroed at its 0° mark",
        ),
        (
            "configure-lamp.toml",
            "[devices.hmi]\nkind = \"lamp\"",
            "[devices.hmi]\nkind = \"lamp\"\nconfigure = true",
            "devices.hmi.configure",
            "`configure` is for axes",
        ),
        (
            // 5000 steps/deg at the rail's 12 deg/s: 60 kHz, twice GRBL's.
            "configure-too-fast.toml",
            "home_deg = 90.0",
            "home_deg = 90.0\nconfigure = true\nsteps_per_deg = 5000.0",
            "devices.rail.steps_per_deg",
            "60000 steps/s; GRBL steps at most 30000/s",
        ),
        (
            "slow-grbl.toml",
            "[sim]",
            "[sim]\ngrbl_answer_delay_s = 5.0",
            "sim.grbl_answer_delay_s",
            "expected 0 ..= 1 second",
        ),
        (
            // The simulator's own checks of `[sim]`, made wherever a profile
            // is loaded.
            "no-scene.toml",
            "scene = \"corduroy\"",
            "scene = \"velvet-9\"",
            "sim.scene",
            "no built-in scene or scene file `velvet-9`",
        ),
        (
            "fault-of-nothing.toml",
            "[sim]",
            "[sim]\nfaults = [\"lens:expose:1:timeout\"]",
            "sim.faults[0]",
            "names device `lens`",
        ),
        (
            "holder-far-off.toml",
            "[sim]",
            "[sim]\nholder_offset_mm = [25.0, 0.0]",
            "sim.holder_offset_mm",
            "within ±10 mm",
        ),
        (
            "sim-typo.toml",
            "[sim]",
            "[sim]\nscnee = \"felt\"",
            "sim.scnee",
            "unknown field `scnee`, expected one of `frame_size`, `zoom`, `faults`, `scene`",
        ),
        (
            "sim-zoom-nan.toml",
            "[sim]",
            "[sim]\nzoom = nan",
            "sim.zoom",
            "expected 0.1 ..= 100",
        ),
        (
            "twin-joints.toml",
            "name = \"pitch\"",
            "name = \"roll\"",
            "devices.arm.joints[1].name",
            "`roll` is also joints[0]'s name",
        ),
        (
            "no-baud.toml",
            "baud = 115200",
            "baud = 0",
            "devices.rail.transport.baud",
            "0: expected a line speed",
        ),
        (
            "huge-sensor.toml",
            "resolution = [3032, 2008]",
            "resolution = [100000, 100000]",
            "devices.camera.intrinsics.resolution",
            "100000×100000",
        ),
        (
            "three-sided-sensor.toml",
            "resolution = [3032, 2008]",
            "resolution = [3032, 2008, 3]",
            "devices.camera.intrinsics.resolution",
            "invalid length 3",
        ),
        (
            "sim-frame-extra.toml",
            "frame_size = [640, 480]",
            "frame_size = [640, 480, 3]",
            "sim.frame_size",
            "invalid length 3",
        ),
        (
            "sim-offset-extra.toml",
            "[sim]",
            "[sim]\nholder_offset_mm = [0.5, 0.5, 0.5]",
            "sim.holder_offset_mm",
            "length 3",
        ),
        (
            "nul-name.toml",
            "name = \"bonn-gonioreflectometer\"",
            "name = \"bonn\\u0000rig\"",
            "name",
            "the rig's name holds control characters",
        ),
        (
            "long-exposure.toml",
            "exposure_s = 0.25",
            "exposure_s = 5e5",
            "devices.camera.timing.exposure_s",
            "up to 3600",
        ),
    ];
    for (file, from, to, key, what) in cases {
        let path = broken_profile(tmp.path(), file, from, to);
        for args in [
            vec!["profile", "check", path.as_str()],
            vec!["plan", "show", "h1", "--profile", path.as_str()],
            vec![
                "run",
                "--sim",
                "--profile",
                path.as_str(),
                "--out",
                "/nonexistent/never",
            ],
        ] {
            let e = fails_cleanly(&args);
            assert!(e.contains(file), "{e}");
            assert!(e.contains(key), "{e}");
            assert!(e.contains(what), "{e}");
            assert_eq!(e.matches(what).count(), 1, "said twice: {e}");
        }
    }
    let e = fails_cleanly(&["profile", "check", "no-such-profile"]);
    assert!(e.contains("bonn-gonioreflectometer"), "{e}");
}

/// Rigs with several lamps: a lamp listed twice, two lamps on one relay
/// coil. Each command that loads the profile refuses it, once, naming the key.
#[test]
fn broken_lamp_wiring_is_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let msra = std::fs::read_to_string(repo_file("rig-profiles/msra-btf-mdf.toml")).expect("read");
    let cases = [
        (
            "twice-listed.toml",
            "lamps = [\"lamp0\", \"lamp1\",",
            "lamps = [\"lamp0\", \"lamp0\",",
            "rig.lamps[1]",
            "`lamp0` is listed twice (also rig.lamps[0])",
        ),
        (
            "one-coil.toml",
            "coil = 1\n",
            "coil = 0\n",
            "devices.lamp1.coil",
            "also `lamp0`'s",
        ),
    ];
    for (file, from, to, key, what) in cases {
        assert!(msra.contains(from), "fixture drifted: {from}");
        let path = tmp.path().join(file);
        std::fs::write(&path, msra.replacen(from, to, 1)).expect("write");
        let path = path.to_str().expect("utf8");
        for args in [
            vec!["profile", "check", path],
            vec!["plan", "show", "grid12x8", "--profile", path],
            vec![
                "run",
                "--sim",
                "--profile",
                path,
                "--out",
                "/nonexistent/never",
            ],
        ] {
            let e = fails_cleanly(&args);
            assert!(
                e.contains(file) && e.contains(key) && e.contains(what),
                "{e}"
            );
            assert_eq!(e.matches(what).count(), 1, "said twice: {e}");
        }
    }
}

#[test]
fn unknown_plan_is_refused() {
    let e = fails_cleanly(&[
        "run",
        "--sim",
        "--plan",
        "h3",
        "--out",
        "/nonexistent/never",
    ]);
    assert!(e.contains("unknown plan `h3`"), "{e}");
    let e = fails_cleanly(&["plan", "show", "grid12x8"]);
    assert!(e.contains("arcs"), "{e}");
    let e = fails_cleanly(&["plan", "show", "/nonexistent/plan.json"]);
    assert!(e.contains("/nonexistent/plan.json"), "{e}");
}

#[test]
fn an_output_folder_with_another_run_or_other_files_is_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let run = tmp.path().join("run");
    let d = run.to_str().expect("utf8");
    run_ok(&[
        "run",
        "--sim",
        "--profile",
        "virtex-photometric-stereo",
        "--sample",
        "wool",
        "--progress",
        "none",
        "--out",
        d,
    ]);
    let before = std::fs::read(run.join("manifest.json")).expect("manifest");
    let e = fails_cleanly(&["run", "--sim", "--out", d]);
    assert!(
        e.contains("already holds run `wool`") && e.contains("--resume"),
        "{e}"
    );
    // The earlier run is untouched.
    assert_eq!(
        std::fs::read(run.join("manifest.json")).expect("manifest"),
        before
    );
    let other = tmp.path().join("other");
    std::fs::create_dir(&other).expect("mkdir");
    std::fs::write(other.join("notes.txt"), "mine").expect("write");
    let e = fails_cleanly(&["run", "--sim", "--out", other.to_str().expect("utf8")]);
    assert!(e.contains("not empty"), "{e}");
}

#[test]
fn an_unwritable_output_folder_is_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    // A file where a folder must go: unwritable even for root, who ignores
    // permission bits.
    let file = tmp.path().join("a-file");
    std::fs::write(&file, "x").expect("write");
    let under_file = file.join("run");
    let e = fails_cleanly(&["run", "--sim", "--out", under_file.to_str().expect("utf8")]);
    assert!(
        e.contains("create directory") && e.contains("Not a directory"),
        "{e}"
    );
    // procfs refuses new folders to everyone.
    let e = fails_cleanly(&["run", "--sim", "--out", "/proc/rigd-test-run"]);
    assert!(e.contains("/proc/rigd-test-run"), "{e}");
    assert!(!under_file.exists());
}

#[test]
fn other_bad_arguments_are_refused() {
    let e = fails_cleanly(&[
        "run",
        "--sim",
        "--exposure",
        "-1",
        "--out",
        "/nonexistent/never",
    ]);
    assert!(e.contains("exposure"), "{e}");
    let e = fails_cleanly(&["run", "--resume", "/nonexistent/run"]);
    assert!(e.contains("no run"), "{e}");
    // Without --sim a profile file means hardware, which is not attached:
    // a device failure (exit 1), not bad input.
    let e = fails_with(
        1,
        &[
            "run",
            "--profile",
            "rig-profiles/msra-btf-mdf.toml",
            "--out",
            "/nonexistent/never",
        ],
    );
    assert!(
        e.contains("cannot open") && e.contains("--sim") && !e.contains("panick"),
        "{e}"
    );
    // Every device is tried at once, and the one line names all that failed.
    assert!(
        e.contains("also failed:") && e.contains("turntable") && e.contains("lamp0"),
        "{e}"
    );
    let e = fails_cleanly(&[
        "run",
        "--sim",
        "--sim-fault",
        "rail:melt",
        "--out",
        "/nonexistent/never",
    ]);
    assert!(e.contains("DEVICE:OP:N:KIND"), "{e}");
    for speed in ["0", "-3", "NaN"] {
        let e = fails_with(
            2,
            &[
                "run",
                "--sim",
                "--sim-speed",
                speed,
                "--out",
                "/nonexistent/never",
            ],
        );
        assert!(
            e.contains("--sim-speed") && e.contains("positive"),
            "{speed}: {e}"
        );
    }
    let e = fails_with(
        2,
        &[
            "run",
            "--profile",
            "rig-profiles/msra-btf-mdf.toml",
            "--sim-speed",
            "10",
            "--out",
            "/nonexistent/never",
        ],
    );
    assert!(e.contains("--sim-speed needs the simulated rig"), "{e}");
}

#[test]
fn help_documents_every_command() {
    for args in [
        vec!["--help"],
        vec!["run", "--help"],
        vec!["plan", "show", "--help"],
        vec!["profile", "check", "--help"],
    ] {
        let out = run_ok(&args);
        assert!(!out.stdout.is_empty());
    }
}

#[test]
fn sim_render_writes_a_frame_and_its_metadata() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("cord.png");
    let o = rigd()
        .args([
            "sim",
            "render",
            "--profile",
            "msra-btf-mdf",
            "--scene",
            "corduroy",
        ])
        .args([
            "--light", "80,0", "--view", "0,0", "--size", "96x72", "--zoom", "2", "--out",
        ])
        .arg(&out)
        .output()
        .expect("rigd");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (w, h, pixels) =
        rigd::rig::hal::decode_png(&std::fs::read(&out).expect("png")).expect("decodes");
    assert_eq!((w, h), (96, 72));
    assert!(
        pixels.iter().any(|&p| p > 0) && pixels.iter().all(|&p| p <= 255),
        "8-bit camera"
    );
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("cord.json")).expect("json"))
            .expect("parses");
    assert_eq!(meta["scene"], "corduroy");
    let live: Vec<&str> = meta["effects"]["live"]
        .as_array()
        .expect("live")
        .iter()
        .filter_map(|e| e.as_str())
        .collect();
    assert!(
        live.contains(&"relief") && live.contains(&"shadows"),
        "{meta}"
    );
    assert!(!live.contains(&"laser"), "no laser asked for: {meta}");
    assert_eq!(meta["markers"].as_array().expect("markers").len(), 12);
    // Bad input: one line naming the problem, exit 2, no file written.
    for (arg, value) in [
        ("--light", "95,0"),
        ("--effects", "sparkle"),
        ("--scene", "no-such-scene"),
    ] {
        let bad = dir.path().join("bad.png");
        let o = rigd()
            .args(["sim", "render", arg, value, "--out"])
            .arg(&bad)
            .output()
            .expect("rigd");
        assert_eq!(o.status.code(), Some(2), "{arg} {value}");
        assert!(!bad.exists(), "{arg} {value} wrote a file");
    }
}
