//! What the rig cannot do, or a file cannot mean, is refused at the edge
//! with the key and the range: plan directions, sample names, processing
//! options, exposures; files as editors save them (a byte order mark) are
//! read; an error names each of its causes once; the environment's
//! failures (a read-only disk) are failures, not bad input.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Output;

use common::{repo_file, rigd, run_ok, test_python, tiny_plan};

/// Runs rigd expecting exit `code`, with one line on stderr (clap's pointer
/// to `--help` aside) and no panic; returns that line.
fn fails_with(code: i32, args: &[&str]) -> String {
    let out = rigd().args(args).output().expect("spawn rigd");
    one_error_line(code, args, &out)
}

fn one_error_line(code: i32, args: &[&str], out: &Output) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    assert_eq!(out.status.code(), Some(code), "rigd {args:?}: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    let lines: Vec<&str> = stderr
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with("For more information"))
        .collect();
    assert_eq!(lines.len(), 1, "rigd {args:?}: not one line: {stderr}");
    assert!(stderr.starts_with("error: "), "{stderr}");
    stderr
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).expect("write");
    path
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf8 path")
}

/// φ = 1e300 was captured at φ = 0 but indexed as 228°; NaN came through
/// TOML; θ = 90 was captured at the arm's 89°. Each is refused, naming the
/// file, the key in it and the range, before anything is created.
#[test]
fn plan_directions_out_of_range_are_refused_naming_the_key() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let cases = [
        (
            "phi-huge.json",
            r#"{"directions": [{"theta_deg": 30, "phi_deg": 0}, {"theta_deg": 30, "phi_deg": 1e300}]}"#,
            "directions[1]",
            "φ = 1e300",
        ),
        (
            "phi-nan.toml",
            "[[directions]]\ntheta_deg = 30.0\nphi_deg = nan\n",
            "directions[0]",
            "φ = NaN",
        ),
        (
            "theta-90.json",
            r#"{"lights": [{"theta_deg": 90, "phi_deg": 0}], "views": [{"theta_deg": 0, "phi_deg": 0}]}"#,
            "lights[0]",
            "θ = 90: expected 0 ≤ θ < 90",
        ),
        (
            "theta-negative.json",
            r#"{"pairs": [{"light": {"theta_deg": 30, "phi_deg": 0}, "view": {"theta_deg": -1, "phi_deg": 0}}]}"#,
            "pairs[0].view",
            "θ = -1",
        ),
    ];
    for (name, text, key, what) in cases {
        let plan = write(tmp.path(), name, text);
        let out = tmp.path().join(format!("run-{name}"));
        for args in [
            vec!["plan", "show", s(&plan)],
            vec!["run", "--sim", "--plan", s(&plan), "--out", s(&out)],
        ] {
            let e = fails_with(2, &args);
            assert!(
                e.contains(name) && e.contains(key) && e.contains(what),
                "{key} {what}: {e}"
            );
        }
        assert!(!out.exists(), "{name}: a run folder was created");
    }
}

/// φ = −30 and φ = 720 are normalised once, where the plan is read: the
/// listing and the captured journal both say 330 and 0, so the index and
/// the export (made from the journal) cannot say otherwise.
#[test]
fn plan_azimuths_are_normalised_once_for_every_later_step() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let plan = write(
        tmp.path(),
        "wrapped.json",
        r#"{"directions": [{"theta_deg": 30, "phi_deg": -30}, {"theta_deg": 45, "phi_deg": 720}]}"#,
    );
    let out = run_ok(&["plan", "show", s(&plan), "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("plan JSON");
    let mut phis: Vec<f64> = v["steps"]
        .as_array()
        .expect("steps")
        .iter()
        .flat_map(|s| [&s["light"]["phi_deg"], &s["view"]["phi_deg"]])
        .map(|p| p.as_f64().expect("phi"))
        .collect();
    phis.sort_by(f64::total_cmp);
    phis.dedup();
    assert_eq!(phis, vec![0.0, 330.0], "{}", v["steps"]);

    let run = tmp.path().join("run");
    run_ok(&[
        "run",
        "--sim",
        "--plan",
        s(&plan),
        "--frame-size",
        "32x24",
        "--progress",
        "none",
        "--out",
        s(&run),
    ]);
    let journal = std::fs::read_to_string(run.join(rigd::store::JOURNAL_FILE)).expect("journal");
    let entries: Vec<serde_json::Value> = journal
        .lines()
        .map(|l| serde_json::from_str(l).expect("journal line"))
        .collect();
    assert_eq!(entries.len(), 4);
    for e in &entries {
        for phi in [&e["light"]["phi_deg"], &e["view"]["phi_deg"]] {
            let phi = phi.as_f64().expect("φ");
            assert!(phi == 0.0 || phi == 330.0, "journal φ = {phi}");
        }
    }
}

/// A profile's own exposure range bounds its `exposure_s` and every run's
/// `--exposure`; the refusal names the camera and the range.
#[test]
fn exposures_beyond_the_camera_s_range_are_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let text = std::fs::read_to_string(repo_file("rig-profiles/bonn-gonioreflectometer.toml"))
        .expect("read");
    let from = "timing = { exposure_s = 0.25,";
    assert!(text.contains(from), "fixture drifted");
    let ranged = text.replace(
        from,
        "timing = { exposure_range_s = [0.001, 2.0], exposure_s = 0.25,",
    );
    let profile = write(tmp.path(), "ranged.toml", &ranged);
    let plan = tiny_plan(tmp.path());
    run_ok(&["profile", "check", s(&profile)]);
    run_ok(&[
        "plan",
        "show",
        s(&plan),
        "--profile",
        s(&profile),
        "--exposure",
        "2",
    ]);
    let out = tmp.path().join("run");
    for args in [
        vec![
            "plan",
            "show",
            s(&plan),
            "--profile",
            s(&profile),
            "--exposure",
            "5",
        ],
        vec![
            "run",
            "--sim",
            "--profile",
            s(&profile),
            "--plan",
            s(&plan),
            "--exposure",
            "5",
            "--out",
            s(&out),
        ],
    ] {
        let e = fails_with(2, &args);
        assert!(
            e.contains("exposure") && e.contains("camera `camera`") && e.contains("0.001 … 2 s"),
            "{e}"
        );
    }
    assert!(!out.exists());
    let beyond = write(
        tmp.path(),
        "beyond.toml",
        &ranged.replace("exposure_s = 0.25,", "exposure_s = 3.0,"),
    );
    let e = fails_with(2, &["profile", "check", s(&beyond)]);
    assert!(
        e.contains("devices.camera.timing.exposure_s") && e.contains("[0.001, 2]"),
        "{e}"
    );

    // Exposure policies: brackets that are not decreasing or leave the
    // camera's range, an `auto` threshold outside (0, 1), a factor of at
    // most 1, and retakes that reach below the range; each names its key.
    let run = |policy: &str| {
        vec![
            "run".to_string(),
            "--sim".into(),
            "--profile".into(),
            s(&profile).into(),
            "--plan".into(),
            s(&plan).into(),
            "--exposure-policy".into(),
            policy.into(),
            "--out".into(),
            s(&out).into(),
        ]
    };
    for (policy, wanted) in [
        ("brackets:0.1,0.2", "exposures_s: 0.1 s then 0.2 s"),
        (
            "brackets:5,1",
            "exposure_policy.exposures_s: 5 s: camera `camera` exposes 0.001 … 2 s",
        ),
        ("auto:threshold=0", "threshold: 0"),
        ("auto:threshold=1.5", "threshold: 1.5"),
        ("auto:factor=1", "factor: 1"),
        ("auto:factor=0.5", "factor: 0.5"),
        (
            "auto:factor=10,max_extra=3",
            "exposure_policy.max_extra: 3 further exposures 10 times shorter than 0.25 s",
        ),
        ("sometimes", "expected single, brackets"),
    ] {
        let args = run(policy);
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let e = fails_with(2, &args);
        assert!(e.contains(wanted), "{policy}: {e}");
    }
    assert!(!out.exists());
    let in_profile = write(
        tmp.path(),
        "policy.toml",
        &format!("{ranged}\n[exposure_policy]\npolicy = \"brackets\"\nexposures_s = [0.5, 0.5]\n"),
    );
    let e = fails_with(2, &["profile", "check", s(&in_profile)]);
    assert!(
        e.contains("exposure_policy.exposures_s") && e.contains("strictly decreasing"),
        "{e}"
    );
}

/// `rigd process …` refuses every numeric option the daemon's jobs refuse,
/// with the same check, naming the option and its range, before it reads
/// the run.
#[test]
fn processing_options_are_refused_as_the_daemon_refuses_them() {
    let cases: &[(&[&str], &str)] = &[
        (&["rectify", "--size", "1"], "--size 1: expected 4 … 8192"),
        (
            &["rectify", "--size", "256", "--final", "300"],
            "--final 300",
        ),
        (&["rectify", "--final", "0"], "--final 0: expected 4 … 8192"),
        (&["rectify", "--roi", "NaN"], "--roi NaN"),
        (&["rectify", "--roi", "1.5"], "--roi 1.5"),
        (&["rectify", "--bits", "9"], "--bits `9`"),
        (&["rectify", "--final", "64", "--blend", "64"], "--blend 64"),
        (
            &["btf", "--components", "0"],
            "--components 0: expected 1 … 256",
        ),
        (&["btf", "--components", "1000"], "--components 1000"),
        (&["fit", "--lobes", "9"], "--lobes 9: expected 1 … 8"),
        (&["mdf", "--sigma", "NaN"], "--sigma NaN"),
        (&["mdf", "--threshold", "2"], "--threshold 2"),
        (
            &["mdf", "--line-threshold", "-0.5"],
            "--line-threshold -0.5",
        ),
        (&["mdf", "--sources", "0"], "--sources 0"),
        (
            &["photometric-stereo", "--max-condition", "NaN"],
            "--max-condition NaN",
        ),
        (
            &["photometric-stereo", "--max-condition", "0.5"],
            "--max-condition 0.5",
        ),
    ];
    let tmp = tempfile::tempdir().expect("tempdir");
    let run = tmp.path().join("no-run-here");
    for (args, says) in cases {
        let mut all = vec!["process"];
        all.extend_from_slice(args);
        all.push(s(&run));
        let e = fails_with(2, &all);
        assert!(e.contains(says), "{args:?}: {e}");
    }
}

/// The default run folder is made of the sample's name as a name, never a
/// path: `../../../escaped` stays inside `runs/`, and names the daemon
/// refuses (control characters, 10,000 characters, blank) the command line
/// refuses too.
#[test]
fn sample_names_never_leave_the_runs_folder() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let plan = tiny_plan(tmp.path());
    let cwd = tmp.path().join("a/b/c");
    std::fs::create_dir_all(&cwd).expect("mkdir");
    for sample in ["../../../escaped", "felt/blue"] {
        let out = rigd()
            .current_dir(&cwd)
            .args([
                "run",
                "--sim",
                "--frame-size",
                "32x24",
                "--progress",
                "none",
            ])
            .args(["--plan", s(&plan), "--sample", sample])
            .output()
            .expect("spawn rigd");
        assert!(
            out.status.success(),
            "{sample}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let printed = String::from_utf8_lossy(&out.stdout).trim().to_string();
        let root = cwd.join(&printed);
        assert!(root.join("run.json").is_file(), "{printed}");
        let canonical = root.canonicalize().expect("canonical");
        assert_eq!(
            canonical.parent(),
            Some(cwd.join("runs").canonicalize().expect("runs").as_path()),
            "{sample} -> {printed}"
        );
        // The dataset keeps the name as given.
        let meta = rigd::store::read_meta(&root).expect("run.json");
        assert_eq!(meta.sample, sample);
    }
    let escaped: Vec<_> = std::fs::read_dir(tmp.path())
        .expect("ls")
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains("escaped"))
        .collect();
    assert!(escaped.is_empty(), "written outside runs/: {escaped:?}");
    let long = "x".repeat(10_000);
    for (sample, says) in [
        ("a\u{1}b", "control characters"),
        ("line\nbreak", "control characters"),
        (long.as_str(), "10000 characters"),
        ("", "empty"),
        ("   ", "empty"),
    ] {
        let e = fails_with(
            2,
            &[
                "run",
                "--sim",
                "--plan",
                s(&plan),
                "--sample",
                sample,
                "--out",
                s(&tmp.path().join("refused")),
            ],
        );
        assert!(e.contains("sample") && e.contains(says), "{e}");
        assert!(e.len() < 300, "the message repeats the name: {e}");
    }
    assert!(!tmp.path().join("refused").exists());
}

/// The UBO2003 databases ship as deflated zips; `rigd import` reads them.
#[test]
fn a_deflated_ubo2003_zip_is_imported() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let jpegs = tmp.path().join("jpegs");
    std::fs::create_dir(&jpegs).expect("mkdir");
    let mut names = Vec::new();
    for (tl, pl) in [(0, 0), (30, 90)] {
        for (tv, pv) in [(0, 0), (45, 180)] {
            let name = format!("tl{tl:03} pl{pl:03} tv{tv:03} pv{pv:03}.jpg");
            let grey = image::GrayImage::from_fn(16, 16, |x, y| image::Luma([(x * 8 + y) as u8]));
            grey.save(jpegs.join(&name)).expect("jpeg");
            names.push(name);
        }
    }
    let zip = tmp.path().join("db.zip");
    let script = "import sys, zipfile, os\n\
        with zipfile.ZipFile(sys.argv[1], 'w', zipfile.ZIP_DEFLATED) as z:\n\
        \x20   for f in sys.argv[2:]:\n\
        \x20       z.write(f, arcname=os.path.basename(f))\n";
    let status = std::process::Command::new(test_python())
        .args(["-c", script, s(&zip)])
        .args(names.iter().map(|n| jpegs.join(n)))
        .status()
        .expect("python");
    assert!(status.success(), "python zipfile");
    let bytes = std::fs::read(&zip).expect("zip");
    // Local header's compression method 8: deflate.
    assert_eq!(&bytes[8..10], &[8, 0], "the test zip is deflated");
    let out = tmp.path().join("imported");
    let o = run_ok(&["import", s(&zip), "--format", "ubo2003", "--out", s(&out)]);
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(said.contains("4 textures (2 views × 2 lights"), "{said}");
}

/// A read-only mount, unmounted (lazily) when dropped.
struct ReadOnlyMount(PathBuf);

impl ReadOnlyMount {
    fn over(dir: &Path) -> ReadOnlyMount {
        let status = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", "ro,size=64k", "tmpfs"])
            .arg(dir)
            .status()
            .expect("spawn mount");
        assert!(
            status.success(),
            "mount -t tmpfs -o ro failed: this test needs root (CI and scripts/test.sh run as root)"
        );
        ReadOnlyMount(dir.to_path_buf())
    }
}

impl Drop for ReadOnlyMount {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg("-l")
            .arg(&self.0)
            .status();
    }
}

/// A disk that refuses writes fails the step (exit 1, as a full disk
/// does), naming the file and the system's reason; it is not bad input.
#[test]
fn processing_onto_a_read_only_disk_is_a_failure_not_bad_input() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let plan = tiny_plan(tmp.path());
    let run = tmp.path().join("run");
    run_ok(&[
        "run",
        "--sim",
        "--plan",
        s(&plan),
        "--frame-size",
        "64x48",
        "--progress",
        "none",
        "--out",
        s(&run),
    ]);
    let processed = run.join("processed");
    std::fs::create_dir_all(&processed).expect("mkdir");
    let _ro = ReadOnlyMount::over(&processed);
    let e = fails_with(
        1,
        &[
            "process",
            "rectify",
            "--size",
            "64",
            "--final",
            "16",
            s(&run),
        ],
    );
    assert!(e.contains("Read-only file system"), "{e}");
}

/// Splits an error line into its clauses (`a: b: c`).
fn clauses(line: &str) -> Vec<&str> {
    line.trim_start_matches("error: ")
        .split(": ")
        .map(str::trim)
        .filter(|c| c.len() > 3)
        .collect()
}

/// No error says the same clause twice ("X: X"), whichever layer it came
/// through: a bad profile, a bad plan, a missing run or file, a bad option.
#[test]
fn errors_say_each_cause_once() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let text = std::fs::read_to_string(repo_file("rig-profiles/bonn-gonioreflectometer.toml"))
        .expect("read");
    let twin_joints = write(
        tmp.path(),
        "twin-joints.toml",
        &text.replacen("name = \"pitch\"", "name = \"roll\"", 1),
    );
    let bad_plan = write(tmp.path(), "bad.json", "{\"directions\": [");
    let missing = tmp.path().join("missing");
    let missing_png = tmp.path().join("missing.png");
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).expect("mkdir");
    let out = tmp.path().join("out");
    let (missing_plan, missing_scene) = (missing.join("plan.json"), missing.join("scene.toml"));
    let cases: Vec<Vec<&str>> = vec![
        vec![
            "run",
            "--sim",
            "--profile",
            s(&twin_joints),
            "--out",
            s(&out),
        ],
        vec!["profile", "check", s(&twin_joints)],
        vec!["plan", "show", s(&bad_plan)],
        vec!["plan", "show", s(&missing_plan)],
        vec!["run", "--resume", s(&missing)],
        vec!["process", "rectify", s(&missing)],
        vec!["process", "btf", s(&empty)],
        vec!["export", s(&missing), "--format", "utia", "--out", s(&out)],
        vec![
            "import",
            s(&missing),
            "--format",
            "ubo2003",
            "--out",
            s(&out),
        ],
        vec!["import", s(&missing), "--format", "utia", "--out", s(&out)],
        vec![
            "process",
            "photometric-stereo",
            "--images",
            s(&empty),
            "--lights",
            s(&missing),
            "--out",
            s(&out),
        ],
        vec![
            "process",
            "photometric-stereo",
            "--images",
            s(&missing),
            "--lights",
            s(&bad_plan),
            "--mask",
            s(&missing_png),
            "--out",
            s(&out),
        ],
        vec![
            "sim",
            "render",
            "--scene",
            s(&missing_scene),
            "--out",
            s(&out),
        ],
        vec!["run", "--sim", "--exposure", "-1", "--out", s(&out)],
    ];
    for args in cases {
        let o = rigd().args(&args).output().expect("spawn rigd");
        assert!(!o.status.success(), "{args:?} succeeded");
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(!stderr.contains("panicked"), "{stderr}");
        for line in stderr.lines() {
            let c = clauses(line);
            for (i, a) in c.iter().enumerate() {
                assert!(
                    !c[i + 1..].contains(a),
                    "rigd {args:?} says `{a}` twice: {line}"
                );
            }
        }
        // And says it once: no line of the error repeats another.
        let lines: Vec<&str> = stderr.lines().filter(|l| !l.trim().is_empty()).collect();
        let mut unique = lines.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len(), lines.len(), "rigd {args:?}: {stderr}");
    }
}

/// Editors that start a file with a byte order mark (U+FEFF): plans in
/// JSON and TOML, profiles, scenes, the daemon's configuration and peers
/// file are read as without it.
#[test]
fn a_byte_order_mark_is_read_past() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let bom = '\u{feff}';
    let json = write(
        tmp.path(),
        "bom.json",
        &format!(r#"{bom}{{"directions": [{{"theta_deg": 30, "phi_deg": 0}}]}}"#),
    );
    let toml = write(
        tmp.path(),
        "bom.toml",
        &format!("{bom}[[directions]]\ntheta_deg = 30.0\nphi_deg = 0.0\n"),
    );
    let bonn = std::fs::read_to_string(repo_file("rig-profiles/bonn-gonioreflectometer.toml"))
        .expect("read");
    let profile = write(tmp.path(), "bom-profile.toml", &format!("{bom}{bonn}"));
    for plan in [&json, &toml] {
        run_ok(&["plan", "show", s(plan), "--profile", s(&profile)]);
    }
    run_ok(&["profile", "check", s(&profile)]);
    let flat = std::fs::read_to_string(repo_file("crates/sim/scenes/flat-calibration.toml"))
        .expect("read");
    let scene = write(tmp.path(), "bom-scene.toml", &format!("{bom}{flat}"));
    run_ok(&[
        "sim",
        "render",
        "--scene",
        s(&scene),
        "--size",
        "32x24",
        "--out",
        s(&tmp.path().join("frame.png")),
    ]);
    // The daemon reads its peers file and configuration first, then fails
    // on the missing profile: with each file read, the error is the profile's.
    let peers = write(
        tmp.path(),
        "bom-peers.toml",
        &format!(
            "{bom}[[peer]]\nname = \"other\"\nurl = \"http://127.0.0.1:9\"\ntoken = \"0123456789abcdef0123\"\n"
        ),
    );
    let config = write(
        tmp.path(),
        "bom-config.toml",
        &format!("{bom}[processing]\nexecutor = \"local\"\n"),
    );
    let no_profile = tmp.path().join("no-profile.toml");
    let e = fails_with(
        2,
        &[
            "serve",
            "--peers",
            s(&peers),
            "--config",
            s(&config),
            "--profile",
            s(&no_profile),
            "--listen",
            "127.0.0.1:0",
            "--data",
            s(&tmp.path().join("data")),
        ],
    );
    assert!(e.contains("no-profile.toml"), "{e}");
}
