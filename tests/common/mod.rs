//! Helpers shared by the integration tests.
#![allow(dead_code)]

pub mod history;
pub mod slurm;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use rigd::store::{read_journal, sha256_hex, Manifest, JOURNAL_FILE, MANIFEST_FILE};

/// The `rigd` binary cargo built for these tests.
pub fn rigd() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rigd"))
}

pub fn run_ok(args: &[&str]) -> Output {
    let out = rigd().args(args).output().expect("spawn rigd");
    assert!(
        out.status.success(),
        "rigd {:?} failed: {}\n{}",
        args,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

pub fn repo_file(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)
}

/// The embedded Bonn profile as a monochrome camera on the flat
/// calibration scene at 320×240, its plate without colour patches, written
/// into `dir`: for tests whose numbers are a grey camera's on that scene
/// (the embedded profile's camera is the DCS 760's Bayer sensor, on
/// corduroy at 640×480, with patches to measure its colour on).
pub fn bonn_monochrome(dir: &Path) -> PathBuf {
    let mut text = std::fs::read_to_string(repo_file("rig-profiles/bonn-gonioreflectometer.toml"))
        .expect("the Bonn profile");
    for (from, to) in [
        (", cfa = \"RGGB\"", ""),
        ("frame_size = [640, 480]", "frame_size = [320, 240]"),
        ("scene = \"corduroy\"\n", ""),
        ("[holder]\ncolour_patches = true\n", ""),
    ] {
        assert!(text.contains(from), "the Bonn profile has no `{from}`");
        text = text.replace(from, to);
    }
    let path = dir.join("bonn-monochrome.toml");
    std::fs::write(&path, text).expect("write the profile");
    path
}

/// Checks a finished run: a completed manifest with every image exactly
/// once, every checksum matching its file (a bracketed image's every
/// exposure), and a journal with no index twice.
pub fn assert_complete_run(dir: &Path, expected_frames: usize) -> Manifest {
    let bytes = std::fs::read(dir.join(MANIFEST_FILE)).expect("manifest.json");
    let m: Manifest = serde_json::from_slice(&bytes).expect("manifest parses");
    assert_eq!(m.state, rigd::model::run_state::RunState::Completed);
    assert_eq!(m.steps_total, expected_frames);
    assert_eq!(m.frames_written, expected_frames);
    assert_eq!(m.frames.len(), expected_frames);
    let indices: BTreeSet<usize> = m.frames.iter().map(|f| f.index).collect();
    assert_eq!(
        indices.len(),
        expected_frames,
        "an index repeats in the manifest"
    );
    assert_eq!(
        indices.iter().next_back().copied(),
        Some(expected_frames - 1)
    );
    for (file, sha256) in m.frames.iter().flat_map(|f| f.files()) {
        let data = std::fs::read(dir.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert_eq!(sha256_hex(&data), sha256, "checksum of {file}");
    }
    // The journal's own lines, not the reader's view of them (which takes
    // one entry per image): exactly one line per image, none torn.
    let raw = std::fs::read_to_string(dir.join(JOURNAL_FILE)).expect("journal");
    assert!(raw.is_empty() || raw.ends_with('\n'), "a torn journal tail");
    let mut seen = BTreeSet::new();
    for line in raw.lines() {
        let e: rigd::store::FrameEntry = serde_json::from_str(line).expect("a journal line");
        assert!(seen.insert(e.index), "image {} journaled twice", e.index);
    }
    assert_eq!(seen.len(), expected_frames);
    let (journal, torn) = read_journal(&dir.join(JOURNAL_FILE)).expect("journal");
    assert_eq!((journal.len(), torn), (expected_frames, 0));
    m
}

pub mod http;

/// A device error's kind as the protocol transcripts in
/// `firmware-protocols/` name it.
pub fn kind_name(k: rigd::rig::hal::ErrorKind) -> &'static str {
    use rigd::rig::hal::ErrorKind;
    match k {
        ErrorKind::Timeout => "timeout",
        ErrorKind::Disconnected => "disconnected",
        ErrorKind::DeviceFault => "device_fault",
        ErrorKind::OutOfLimits => "out_of_limits",
        ErrorKind::BadFrame => "bad_frame",
        ErrorKind::NotReady => "not_ready",
        ErrorKind::Storage => "storage",
    }
}

/// A child process that is killed when the test ends, even when it fails.
pub struct Child(pub std::process::Child);

impl Drop for Child {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `cmd` with stdout piped and reads its lines until `ready` says
/// so, in a thread so that a silent process fails the test within
/// `timeout` instead of hanging it. Returns the process and the lines read.
pub fn spawn_until(
    mut cmd: Command,
    what: &str,
    timeout: std::time::Duration,
    ready: fn(&str) -> bool,
) -> (Child, Vec<String>) {
    use std::io::{BufRead, BufReader};
    let mut child = cmd
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::inherit())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {what}: {e}"));
    let stdout = child.stdout.take().expect("stdout");
    let child = Child(child);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut lines = Vec::new();
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            let done = ready(&line);
            lines.push(line);
            if done {
                let _ = tx.send(lines);
                return;
            }
        }
    });
    let lines = rx
        .recv_timeout(timeout)
        .unwrap_or_else(|_| panic!("{what} never said it was ready"));
    (child, lines)
}

/// `rigd sim serve` of a profile at `speed`, writing the profile that
/// points at its endpoints to `served`: the simulated firmware reached the
/// way hardware is (ptys, loopback sockets).
pub fn serve_sim(profile: &Path, served: &Path, speed: f64) -> (Child, Vec<String>) {
    let mut cmd = rigd();
    cmd.args(["sim", "serve", "--profile"])
        .arg(profile)
        .args(["--speed", &speed.to_string(), "--write-profile"])
        .arg(served);
    spawn_until(
        cmd,
        "rigd sim serve",
        std::time::Duration::from_secs(30),
        |l| l.starts_with("# ready"),
    )
}

/// The port of the (first) PTP/IP camera among `rigd sim serve`'s endpoint
/// lines: command and event connections both go to it.
pub fn served_ptpip_port(lines: &[String]) -> u16 {
    lines
        .iter()
        .find(|l| l.contains("PTP/IP"))
        .and_then(|l| l.split_whitespace().last())
        .and_then(|a| a.rsplit(':').next())
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("no PTP/IP endpoint: {lines:?}"))
}

/// The Python of the test venv (tests/support/requirements.txt: pymodbus,
/// Schemathesis, httpx, pytest): `RIGD_TEST_PYTHON`, which
/// `scripts/test.sh` sets, or the venv it creates under `target/`.
pub fn test_python() -> PathBuf {
    let path = std::env::var_os("RIGD_TEST_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_file("target/test-venv/bin/python"));
    assert!(
        path.exists(),
        "no test Python at {}: run scripts/test.sh once, which creates its venv",
        path.display()
    );
    path
}

/// A coil-only relay module served by pymodbus (`tests/support/relay_module.py`)
/// on 127.0.0.1, logging every write to `log`; `extra` adds options
/// (`--refuse-fc0f`). Returns the process and its port.
pub fn relay_module(log: &Path, extra: &[&str]) -> (Child, u16) {
    let mut cmd = Command::new(test_python());
    cmd.arg(repo_file("tests/support/relay_module.py"))
        .args([
            "--port",
            "0",
            "--coils",
            "8",
            "--max-seconds",
            "600",
            "--log",
        ])
        .arg(log)
        .args(extra);
    let (child, lines) = spawn_until(
        cmd,
        "the pymodbus relay module",
        std::time::Duration::from_secs(30),
        |l| l.starts_with("listening "),
    );
    let port = lines
        .last()
        .and_then(|l| l.rsplit(':').next())
        .and_then(|p| p.parse().ok())
        .expect("listening 127.0.0.1:PORT");
    (child, port)
}

/// The write requests a relay module logged, one per line.
pub fn relay_log(log: &Path) -> Vec<String> {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .map(str::to_string)
        .collect()
}

/// A plan file of 2 lights × 2 views (4 images) in `dir`.
pub fn tiny_plan(dir: &Path) -> PathBuf {
    let plan = dir.join("tiny.json");
    std::fs::write(
        &plan,
        r#"{"lights": [{"theta_deg": 30, "phi_deg": 0}, {"theta_deg": 45, "phi_deg": 90}],
            "views": [{"theta_deg": 20, "phi_deg": 0}, {"theta_deg": 40, "phi_deg": 180}]}"#,
    )
    .expect("write the plan");
    plan
}

/// Runs `cmd` in a process group of its own with its output to a file in
/// `work` (a pipe nobody reads until the end would block it once full),
/// killing the whole group if it runs past `limit`, so that a hung
/// service it started fails the test instead of the suite. Returns whether
/// it succeeded and what it printed.
pub fn run_bounded(mut cmd: Command, work: &Path, limit: std::time::Duration) -> (bool, String) {
    use std::os::unix::process::CommandExt;
    let log_path = work.join("output.log");
    let log = std::fs::File::create(&log_path).expect("log file");
    let mut child = cmd
        .stdin(std::process::Stdio::null())
        .stdout(log.try_clone().expect("log file"))
        .stderr(log)
        .process_group(0)
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {cmd:?}: {e}"));
    let deadline = std::time::Instant::now() + limit;
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait") {
            break status;
        }
        if std::time::Instant::now() > deadline {
            let _ = Command::new("kill")
                .args(["-KILL", &format!("-{}", child.id())])
                .status();
            let _ = child.wait();
            panic!(
                "{cmd:?} still ran after {limit:?}:\n{}",
                std::fs::read_to_string(&log_path).unwrap_or_default()
            );
        }
        std::thread::sleep(std::time::Duration::from_millis(200));
    };
    (
        status.success(),
        std::fs::read_to_string(&log_path).unwrap_or_default(),
    )
}

/// Every file under `dir`, by its path relative to `dir`, with its bytes.
pub fn tree_bytes(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display())) {
            let p = entry.expect("a directory entry").path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p
                    .strip_prefix(dir)
                    .expect("under dir")
                    .display()
                    .to_string();
                let bytes = std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
                out.insert(rel, bytes);
            }
        }
    }
    out
}

/// Copies the directory tree `from` to `to`.
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap_or_else(|e| panic!("{}: {e}", to.display()));
    for entry in std::fs::read_dir(from).unwrap_or_else(|e| panic!("{}: {e}", from.display())) {
        let entry = entry.expect("a directory entry");
        let target = to.join(entry.file_name());
        if entry.file_type().expect("file type").is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), &target)
                .unwrap_or_else(|e| panic!("{}: {e}", target.display()));
        }
    }
}
