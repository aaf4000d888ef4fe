//! Helpers shared by the integration tests.
#![allow(dead_code)]

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

/// Checks a finished run: a completed manifest with every image exactly
/// once, every checksum matching its file, and a journal with no index twice.
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
    for f in &m.frames {
        let data = std::fs::read(dir.join(&f.file)).unwrap_or_else(|e| panic!("{}: {e}", f.file));
        assert_eq!(sha256_hex(&data), f.sha256, "checksum of {}", f.file);
    }
    let (journal, torn) = read_journal(&dir.join(JOURNAL_FILE)).expect("journal");
    assert_eq!(torn, 0);
    let mut seen = BTreeSet::new();
    for e in &journal {
        assert!(seen.insert(e.index), "image {} journaled twice", e.index);
    }
    assert_eq!(seen.len(), expected_frames);
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
