//! A capture that fills its disk: a fault like any other. The run pauses
//! with the reason and the space left, loses no frame, and completes once
//! space is freed; the daemon keeps serving meanwhile. The disk is a real
//! small filesystem (tmpfs, mounted by the test: CI runs as root), so the
//! error is the kernel's own ENOSPC.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

use crate::common::http::{run_body, small_plan, start_in};
use crate::common::{assert_complete_run, rigd};

/// A tmpfs of a given size, unmounted when dropped.
struct SmallDisk {
    dir: tempfile::TempDir,
}

impl SmallDisk {
    fn mount(kib: u64) -> SmallDisk {
        let dir = tempfile::tempdir().expect("tempdir");
        let status = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={kib}k"), "tmpfs"])
            .arg(dir.path())
            .status()
            .expect("spawn mount");
        assert!(
            status.success(),
            "mount -t tmpfs failed: these tests need root (CI and scripts/test.sh run as root)"
        );
        SmallDisk { dir }
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    /// More room on the same filesystem: the operator freed space.
    fn grow(&self, kib: u64) {
        let status = Command::new("mount")
            .args(["-o", &format!("remount,size={kib}k")])
            .arg(self.dir.path())
            .status()
            .expect("spawn mount");
        assert!(status.success(), "remount failed");
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        // Lazy, so an open file of a failed test cannot keep it mounted.
        let _ = Command::new("umount")
            .arg("-l")
            .arg(self.dir.path())
            .status();
    }
}

/// A write the full disk refused leaves no temporary file behind: not a
/// frame's (`frames/.NNNNNN.EXT.tmp.PID.N`), not a record's.
fn assert_no_temporaries(run: &Path) {
    for dir in [run.to_path_buf(), run.join("frames")] {
        let left: Vec<String> = std::fs::read_dir(&dir)
            .expect("read the run")
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.contains(".tmp"))
            .collect();
        assert!(left.is_empty(), "{}: {left:?}", dir.display());
    }
}

fn plan_file(dir: &Path, n: usize) -> PathBuf {
    let path = dir.join("plan.json");
    std::fs::write(&path, small_plan(n).to_string()).expect("write plan");
    path
}

/// `state.json` of a run that paused on the full disk says so.
fn assert_recorded_pause(run: &Path) {
    let record = rigd::store::read_state(run)
        .expect("state.json readable")
        .expect("state.json present");
    assert_eq!(
        record.state,
        rigd::model::run_state::RunState::Paused,
        "{record:?}"
    );
    assert!(
        record
            .reason
            .as_deref()
            .is_some_and(|r| r.contains("No space left on device")),
        "{record:?}"
    );
}

#[test]
fn the_command_line_pauses_when_the_disk_fills_and_resume_completes() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let plan = plan_file(scratch.path(), 9);
    // 81 frames of 64×48 16-bit noise (~6 KB each) cannot fit in 256 KiB.
    let disk = SmallDisk::mount(256);
    let run = disk.path().join("run");
    let out = rigd()
        .args(["run", "--sim", "--progress", "log", "--frame-size", "64x48"])
        .arg("--plan")
        .arg(&plan)
        .arg("--out")
        .arg(&run)
        .output()
        .expect("spawn rigd");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "a full disk pauses: {stderr}");
    assert!(
        stderr.contains("No space left on device") && stderr.contains("free on the filesystem"),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    // The record on disk says what the run is: paused, and why (the run's
    // reserve made room for it); nothing half-written is left.
    assert_recorded_pause(&run);
    assert_no_temporaries(&run);
    // Whatever is journaled is intact.
    let journal = run.join(rigd::store::JOURNAL_FILE);
    let (entries, _) = rigd::store::read_journal(&journal).expect("journal");
    assert!(
        !entries.is_empty() && entries.len() < 81,
        "{}",
        entries.len()
    );
    for e in &entries {
        let bytes = std::fs::read(run.join(&e.file)).expect("journaled frame");
        assert_eq!(rigd::store::sha256_hex(&bytes), e.sha256);
    }

    // Space freed: the resume completes with every frame.
    disk.grow(64 * 1024);
    let out = rigd()
        .args(["run", "--progress", "none", "--resume"])
        .arg(&run)
        .output()
        .expect("spawn rigd");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_complete_run(&run, 81);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemon_pauses_a_run_on_a_full_disk_and_keeps_serving() {
    let disk = SmallDisk::mount(256);
    let data = disk.path().join("data");
    let mut srv = start_in(&data, 1000.0).await;
    let mut body = run_body("full", small_plan(9));
    body["frame_size"] = serde_json::json!([64, 48]);
    let (status, run) = srv.post("/api/v1/runs", Some(body)).await;
    assert_eq!(status, 201, "{run}");
    let id = run["id"].as_str().expect("id").to_string();
    let paused = srv
        .wait_run(&id, "a storage pause", |v: &Value| {
            v["state"] == "paused"
                && v["reason"]
                    .as_str()
                    .is_some_and(|r| r.contains("No space left on device"))
        })
        .await;
    let reason = paused["reason"].as_str().unwrap_or_default();
    assert!(reason.contains("free on the filesystem"), "{reason}");
    assert_recorded_pause(&data.join("runs").join(&id));
    assert_no_temporaries(&data.join("runs").join(&id));
    // The daemon still answers, and says why the run waits.
    let (status, health) = srv.get("/api/v1/health").await;
    assert_eq!(status, 200, "{health}");
    let (status, listed) = srv.get("/api/v1/runs").await;
    assert_eq!(status, 200, "{listed}");

    disk.grow(64 * 1024);
    let (status, ack) = srv.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert!(status == 200 || status == 202, "{status}: {ack}");
    srv.wait_ended(&id, "completed").await;
    srv.shutdown().await;
    assert_complete_run(&data.join("runs").join(&id), 81);
}
