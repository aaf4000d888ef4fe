//! A run killed with SIGKILL at random instants, then resumed, ends with every
//! image exactly once and every checksum valid; damage left on disk by a
//! crash (a torn journal line, a half-written or corrupted frame, a stray
//! temporary) is found and repaired on resume.

use crate::common;

use std::io::Write;
use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant, SystemTime};

use common::{assert_complete_run, rigd};
use rigd::store::{read_journal, JOURNAL_FILE};

/// A small deterministic generator, seeded from the clock and printed, so a
/// failure can be replayed with RIGD_TEST_SEED.
struct Lcg(u64);

impl Lcg {
    fn next_f64(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn seed() -> u64 {
    std::env::var("RIGD_TEST_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| {
            SystemTime::now()
                .duration_since(SystemTime::UNIX_EPOCH)
                .map(|d| d.as_nanos() as u64)
                .unwrap_or(7)
        })
}

fn journal_len(dir: &Path) -> usize {
    std::fs::read_to_string(dir.join(JOURNAL_FILE))
        .map(|s| s.lines().count())
        .unwrap_or(0)
}

/// Starts `rigd` with the arguments and SIGKILLs it once the journal holds
/// at least `after_frames` lines (or it exits). Returns true if it was killed.
fn kill_after(args: &[&str], dir: &Path, after_frames: usize, extra_delay: Duration) -> bool {
    let mut child = rigd()
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn rigd");
    let start = Instant::now();
    loop {
        if child.try_wait().expect("wait").is_some() {
            return false;
        }
        if journal_len(dir) >= after_frames {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "run made no progress"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    std::thread::sleep(extra_delay);
    let killed = child.try_wait().expect("wait").is_none();
    let _ = child.kill(); // SIGKILL
    let _ = child.wait();
    killed
}

#[test]
fn kill_9_at_random_points_then_resume_loses_and_repeats_nothing() {
    let seed = seed();
    eprintln!("RIGD_TEST_SEED={seed}");
    let mut rng = Lcg(seed);
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("run");
    let d = dir.to_str().expect("utf8");
    let total = 6561;
    let mut kills = 0;
    // First session, then resumed sessions, each killed at a random point.
    for round in 0..4 {
        let at = ((round as f64 + rng.next_f64()) / 5.0 * total as f64) as usize;
        let delay = Duration::from_micros((rng.next_f64() * 3000.0) as u64);
        let args: Vec<&str> = if round == 0 {
            vec![
                "run",
                "--sim",
                "--plan",
                "h1",
                "--frame-size",
                "24x16",
                "--progress",
                "none",
                "--out",
                d,
            ]
        } else {
            vec!["run", "--resume", d, "--progress", "none"]
        };
        if kill_after(&args, &dir, at, delay) {
            kills += 1;
        }
    }
    assert!(kills >= 3, "only {kills} sessions were killed mid-run");
    let out = rigd()
        .args(["run", "--resume", d, "--progress", "none"])
        .output()
        .expect("resume");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_complete_run(&dir, total);
}

#[test]
fn damage_left_by_a_crash_is_repaired_on_resume() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("run");
    let d = dir.to_str().expect("utf8");
    let killed = kill_after(
        &[
            "run",
            "--sim",
            "--plan",
            "h1",
            "--frame-size",
            "24x16",
            "--progress",
            "none",
            "--out",
            d,
        ],
        &dir,
        500,
        Duration::ZERO,
    );
    assert!(killed);
    let (entries, _) = read_journal(&dir.join(JOURNAL_FILE)).expect("journal");
    assert!(entries.len() >= 500);
    // A frame cut short (as by a crash without the rename protocol) ...
    let victim = &entries[10];
    let path = dir.join(&victim.file);
    let bytes = std::fs::read(&path).expect("frame");
    std::fs::write(&path, &bytes[..bytes.len() / 2]).expect("truncate frame");
    // ... a frame that vanished ...
    std::fs::remove_file(dir.join(&entries[20].file)).expect("remove frame");
    // ... a stray temporary and a torn journal line.
    std::fs::write(dir.join("frames/.009999.png.tmp"), b"partial").expect("tmp");
    let mut j = std::fs::OpenOptions::new()
        .append(true)
        .open(dir.join(JOURNAL_FILE))
        .expect("journal");
    j.write_all(b"{\"index\":99999,\"trigger\":").expect("tear");
    drop(j);
    let out = rigd()
        .args(["run", "--resume", d, "--progress", "log"])
        .output()
        .expect("resume");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("retaking 2 frames"), "{stderr}");
    assert!(!dir.join("frames/.009999.png.tmp").exists());
    // The retaken frames replaced their lines: every image has one line,
    // and the two lines they replaced are kept apart as history.
    let m = assert_complete_run(&dir, 6561);
    let history =
        std::fs::read_to_string(dir.join("journal.retaken.ndjson")).expect("the journal's history");
    let replaced: Vec<usize> = history
        .lines()
        .map(|l| {
            serde_json::from_str::<rigd::store::FrameEntry>(l)
                .expect("a history line")
                .index
        })
        .collect();
    assert_eq!(replaced, [entries[10].index, entries[20].index]);
    for f in &m.frames {
        let data = std::fs::read(dir.join(&f.file)).expect("frame");
        assert_eq!(rigd::store::sha256_hex(&data), f.sha256);
    }
}

#[test]
fn a_completed_run_cannot_be_resumed_again() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("run");
    let d = dir.to_str().expect("utf8");
    common::run_ok(&[
        "run",
        "--sim",
        "--profile",
        "virtex-photometric-stereo",
        "--progress",
        "none",
        "--out",
        d,
    ]);
    let out = rigd()
        .args(["run", "--resume", d])
        .output()
        .expect("resume");
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("already completed"), "{stderr}");
}

#[test]
fn a_bracketed_run_faulted_between_exposures_and_killed_resumes_whole() {
    let seed = seed();
    eprintln!("RIGD_TEST_SEED={seed}");
    let mut rng = Lcg(seed);
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("run");
    let d = dir.to_str().expect("utf8");
    let total = 6561;
    // The fourth exposure is image 1's second: the camera faults between
    // the two exposures of one image.
    let out = rigd()
        .args([
            "run",
            "--sim",
            "--plan",
            "h1",
            "--frame-size",
            "24x16",
            "--exposure-policy",
            "brackets:0.25,0.0625",
            "--sim-fault",
            "camera:expose:4:alarm=shutter jammed",
            "--progress",
            "none",
            "--out",
            d,
        ])
        .output()
        .expect("rigd run");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(stderr.contains("paused"), "{stderr}");
    // Image 1's first exposure is on disk, but without its second the image
    // is not taken: no line names it.
    let (entries, _) = read_journal(&dir.join(JOURNAL_FILE)).expect("journal");
    assert_eq!(entries.iter().map(|e| e.index).collect::<Vec<_>>(), [0]);
    assert_eq!(entries[0].brackets.len(), 1);
    assert!(dir.join("frames/000001.dng").exists());
    assert!(!dir.join("frames/000001.e1.dng").exists());

    // Resumed, and killed at random points.
    let mut kills = 0;
    for round in 0..3 {
        let at = ((round as f64 + rng.next_f64()) / 4.0 * total as f64) as usize;
        let delay = Duration::from_micros((rng.next_f64() * 3000.0) as u64);
        if kill_after(
            &["run", "--resume", d, "--progress", "none"],
            &dir,
            at,
            delay,
        ) {
            kills += 1;
        }
    }
    assert!(kills >= 2, "only {kills} sessions were killed mid-run");
    // A second exposure damaged on disk is found and its image retaken.
    let (entries, _) = read_journal(&dir.join(JOURNAL_FILE)).expect("journal");
    let victim = &entries[7].brackets[0];
    std::fs::write(dir.join(&victim.file), b"not the frame").expect("damage");
    let out = rigd()
        .args(["run", "--resume", d, "--progress", "log"])
        .output()
        .expect("resume");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("retaking 1 frame"), "{stderr}");
    let m = assert_complete_run(&dir, total);
    for f in &m.frames {
        assert_eq!(f.exposures_s(), [0.25, 0.0625], "image {}", f.index);
    }
}

/// A run has one writer. While one rigd captures into a folder, a second
/// `rigd run --resume` of it is refused at once (exit 2) and changes
/// nothing; once the first is killed, a resume takes the run over and
/// completes it.
#[test]
fn a_second_writer_is_refused_while_the_first_captures() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = tmp.path().join("run");
    let plan = common::tiny_plan(tmp.path());
    // Paced at twice the wall: the capture lasts well beyond the check.
    let mut child = rigd()
        .args(["run", "--sim", "--sim-speed", "2", "--progress", "none"])
        .args(["--frame-size", "32x24", "--plan"])
        .arg(&plan)
        .arg("--out")
        .arg(&dir)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn rigd");
    let start = Instant::now();
    while !dir.join(rigd::store::RUN_FILE).exists() {
        assert!(
            child.try_wait().expect("wait").is_none(),
            "the capture ended early"
        );
        assert!(start.elapsed() < Duration::from_secs(60), "no run created");
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = rigd()
        .args(["run", "--resume"])
        .arg(&dir)
        .output()
        .expect("rigd run --resume");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("another rigd is writing this run"), "{err}");
    assert!(child.try_wait().expect("wait").is_none(), "{err}");
    // The refused resume did not recover the run under its writer: only a
    // resume marks a run `interrupted`.
    let state = std::fs::read_to_string(dir.join(rigd::store::STATE_FILE)).unwrap_or_default();
    assert!(!state.contains("interrupted"), "{state}");
    let _ = child.kill();
    let _ = child.wait();
    let out = rigd()
        .args(["run", "--progress", "none", "--resume"])
        .arg(&dir)
        .output()
        .expect("rigd run --resume");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_complete_run(&dir, 4);
}
