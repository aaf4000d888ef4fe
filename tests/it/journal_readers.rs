//! Readers of a run's journal beside its writer: captures processed while
//! they run (`rigd run --sim --process rectify`, whose stream reads the
//! journal after every batch), with eight threads of this test reading the
//! same journal as fast as they can through the public readers while the
//! capture writes it (more threads than cores, so a reader is preempted in
//! mid-read as on a busy machine). A reader only reads, so no line is ever
//! lost: every capture ends completed with one journal line per image of
//! its plan. (The reader that cut what it took for a torn tail lost a line
//! in 2 to 3 of these 20 captures.)

use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Instant;

use crate::common::{assert_complete_run, rigd};
use rigd::postprocess::frames::RunFrames;
use rigd::store::{read_journal, JOURNAL_FILE, MANIFEST_FILE};

/// Captures in all.
const CAPTURES: usize = 20;
/// Lights × views of each capture's plan.
const SIDE: usize = 4;

fn plan(dir: &Path) -> std::path::PathBuf {
    let dirs: Vec<serde_json::Value> = (0..SIDE)
        .map(|i| serde_json::json!({"theta_deg": 10.0 + 15.0 * i as f64, "phi_deg": 80.0 * i as f64}))
        .collect();
    let path = dir.join("plan.json");
    let plan = serde_json::json!({"name": "stress", "directions": dirs});
    std::fs::write(&path, plan.to_string()).expect("plan");
    path
}

#[test]
fn readers_hammering_a_live_journal_lose_no_line() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let plan = plan(scratch.path());
    let images = SIDE * SIDE;
    let started = Instant::now();
    let reads = Arc::new(AtomicUsize::new(0));
    for round in 0..CAPTURES {
        let run = scratch.path().join(format!("run-{round}"));
        let stop = Arc::new(AtomicBool::new(false));
        let readers: Vec<_> = (0..8)
            .map(|k| {
                let (run, stop, reads) = (run.clone(), stop.clone(), reads.clone());
                std::thread::spawn(move || {
                    // While the capture writes: its manifest ends it.
                    while !stop.load(Ordering::Relaxed) && !run.join(MANIFEST_FILE).exists() {
                        if !run.join(JOURNAL_FILE).exists() {
                            std::thread::yield_now();
                            continue;
                        }
                        // Either reader: the processing steps' and the store's.
                        let ok = if k % 2 == 0 {
                            RunFrames::open(&run).is_ok()
                        } else {
                            read_journal(&run.join(JOURNAL_FILE)).is_ok()
                        };
                        if ok {
                            reads.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                })
            })
            .collect();
        let out = rigd()
            .args([
                "run",
                "--sim",
                "--progress",
                "none",
                "--frame-size",
                "288x216",
            ])
            .args(["--process", "rectify", "--plan"])
            .arg(&plan)
            .arg("--out")
            .arg(&run)
            .output()
            .expect("spawn rigd");
        stop.store(true, Ordering::Relaxed);
        for r in readers {
            r.join().expect("reader");
        }
        let lines = std::fs::read_to_string(run.join(JOURNAL_FILE))
            .map(|s| s.lines().count())
            .unwrap_or(0);
        assert!(
            out.status.success(),
            "capture {round}: {lines} journal lines of {images}\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert_complete_run(&run, images);
        std::fs::remove_dir_all(&run).expect("remove the run");
    }
    eprintln!(
        "{CAPTURES} captures of {images} images, {} journal reads beside them, in {:.1} s",
        reads.load(Ordering::Relaxed),
        started.elapsed().as_secs_f64()
    );
}
