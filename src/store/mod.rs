//! The dataset on disk: one directory per run.
//!
//! ```text
//! RUN/run.json          what was asked: profile snapshot, plan, sample, operator, versions, start
//! RUN/journal.ndjson    one line per image written, appended and fsynced: the source of truth
//! RUN/journal.retaken.ndjson  lines a resume took out of the journal (history, not entries)
//! RUN/state.json        the run's last known state (replaced atomically)
//! RUN/frames/NNNNNN.png the frames, 16-bit grey PNG (8-bit for 8-bit cameras), raw sensor values;
//!                       a camera that delivers files (PTP: DNG, raw, JPEG) has its file kept as
//!                       delivered instead, NNNNNN.dng and so on
//! RUN/manifest.json     written atomically when the run ends
//! ```
//!
//! Crash safety: a frame is written to a temporary name and renamed into
//! place; only then is its journal line appended and fsynced. A run killed at
//! any instant therefore has, for every journal line, a complete frame file
//! whose sha256 is in that line; a frame without a line (or whose checksum
//! does not match, after a power loss) is retaken on resume.
//!
//! One writer, readers that only read:
//! - The capture's [`RunDir`] is the journal's one writer. Only it repairs
//!   the journal, and only when it opens the run to write
//!   ([`RunDir::open`]): a torn last line is cut off, and the lines it
//!   cannot use (an image's older lines, lines of frames it will retake, a
//!   line that does not parse) move to [`JOURNAL_HISTORY_FILE`], so the
//!   journal keeps exactly one line per image.
//! - A reader ([`read_journal`]) takes the complete lines, one entry per
//!   image (the last), and never writes: a line still being appended is
//!   not yet there for it.
//! - A run completes only when the journal on disk holds every planned
//!   image ([`RunDir::check_complete`]).
//! - A reader of an ended run checks the journal against the manifest
//!   ([`check_manifest`]) and refuses a run where they disagree.

pub mod processed;
mod writer_lock;

pub use writer_lock::{ProcessingLock, WriterLock};

use std::collections::BTreeMap;
use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::kinematics::Setpoints;
use crate::model::exposure::ExposurePolicy;
use crate::model::profile::Profile;
use crate::model::run_state::{IllegalTransition, RunState};
use crate::plan::Plan;
use crate::rig::hal::{encode_png, Frame};
use rigd_core::geometry::Direction;

/// Format tag of `run.json` and `manifest.json`.
pub const RUN_FORMAT: &str = "rigd-run/1";
/// File name of the run's metadata ([`RunMeta`]), written once at the start.
pub const RUN_FILE: &str = "run.json";
/// File name of the journal: one [`FrameEntry`] per line, appended and
/// fsynced as frames are taken.
pub const JOURNAL_FILE: &str = "journal.ndjson";
/// File name of the journal's history: lines a resume took out of the
/// journal (images it retakes, lines it could not use).
pub const JOURNAL_HISTORY_FILE: &str = "journal.retaken.ndjson";
/// File name of the run's last known state ([`StateRecord`]).
pub const STATE_FILE: &str = "state.json";
/// File name of the [`Manifest`], written when the run ends.
pub const MANIFEST_FILE: &str = "manifest.json";
/// Folder of the frames, `NNNNNN.png` (or the camera file's own extension) by image index.
pub const FRAMES_DIR: &str = "frames";
/// A small file of nothing a run keeps so that its state can still be
/// recorded on a full disk: a state write that fails for want of space
/// frees it and tries again, and the next session makes it anew.
pub const RESERVE_FILE: &str = ".reserve";
/// Bytes the reserve holds: a state record many times over.
const RESERVE_BYTES: usize = 64 * 1024;

/// Why a run directory could not be created, opened, read or written.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The I/O error is part of the message, not a separate cause, so it
    /// reads once in a one-line report.
    #[error("{path}: {op}: {error}")]
    Io {
        /// The file or folder the operation was on.
        path: PathBuf,
        /// The operation that failed (`create`, `write`, `fsync`, `rename`, …).
        op: &'static str,
        /// The operating system's error.
        error: std::io::Error,
    },
    /// The folder given for a new run already holds one: the folder, and that
    /// run's sample name (`?` if its `run.json` is unreadable).
    #[error("{0} already holds run `{1}`; resume it with `rigd run --resume {0}` or choose another --out")]
    AlreadyRun(String, String),
    /// The folder given for a new run holds other files and no run.
    #[error("{0} is not empty and holds no run; choose an empty or new folder for --out")]
    NotEmpty(String),
    /// The folder to open holds no run: it has no `run.json`.
    #[error("{0} holds no run (no run.json)")]
    NoRun(String),
    /// A file cannot be read back or parsed (`run.json`, `state.json`, a
    /// damaged journal line), or cannot be serialized or encoded as PNG.
    #[error("{path}: {why}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        why: String,
    },
    /// The run to resume has already ended (completed or aborted): its folder
    /// and its state.
    #[error("{0}: the run is already {1}; nothing to resume")]
    Finished(String, RunState),
    /// Another writer holds the run (a capture or a resume, in this
    /// process or another): its folder.
    #[error("{0}: another rigd is writing this run (capturing or resuming it); wait for it to end or stop it, then resume")]
    Busy(String),
    /// Another processor holds the run's `processed/` folder (a `rigd
    /// process` command, a process job, the registration during a
    /// capture): the run's folder.
    #[error("{0}: another rigd is processing this run (a `rigd process` command, or a process job); wait for it to end or cancel it, then process again")]
    ProcessingBusy(String),
    /// The state table refuses the state change asked of the run.
    #[error("{path}: {error}")]
    Transition {
        /// The run's `state.json`.
        path: PathBuf,
        /// The refused transition, naming both states.
        error: IllegalTransition,
    },
}

fn io<'a>(path: &'a Path, op: &'static str) -> impl FnOnce(std::io::Error) -> StoreError + 'a {
    move |error| StoreError::Io {
        path: path.to_path_buf(),
        op,
        error,
    }
}

/// What was asked for, written once at the start.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunMeta {
    /// Format tag of the file: [`RUN_FORMAT`].
    pub format: String,
    /// Version of the rigd that started the run.
    pub software_version: String,
    /// A full copy of the rig profile the run was started with; a resume
    /// uses this, not the file it came from.
    pub profile: Profile,
    /// Where the profile came from (a path, or `<embedded NAME>`).
    pub profile_source: String,
    /// The plan as resolved for the rig (every light and view pair, or the
    /// laser scan, and the trigger order); a resume rebuilds the schedule from it.
    pub plan: Plan,
    /// Name of the measured sample.
    pub sample: String,
    /// Who ran the capture; null if not given.
    #[serde(default)]
    pub operator: Option<String>,
    /// Free-text notes on the run; null if none were given.
    #[serde(default)]
    pub notes: Option<String>,
    /// Exposure override for every camera; the profile's own if None.
    #[serde(default)]
    pub exposure_s: Option<f64>,
    /// The exposures each step takes: the request's, else the profile's.
    #[serde(default, skip_serializing_if = "ExposurePolicy::is_single")]
    pub exposure_policy: ExposurePolicy,
    /// Frame size of the simulated cameras (None on real hardware).
    #[serde(default)]
    pub frame_size: Option<[u32; 2]>,
    /// True when the run drives the simulated rig, false on hardware.
    pub simulated: bool,
    /// The scene the simulated cameras render and the effects a lit frame
    /// of it pays for (None on hardware).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim_scene: Option<SimScene>,
    /// RFC 3339, UTC.
    pub started_at: String,
}

/// What a simulated run's frames show.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimScene {
    /// The scene's name (`rigd sim scenes` lists them).
    pub name: String,
    /// Effects live in a frame lit by a lamp (no laser).
    pub effects: Vec<String>,
}

/// One written image: a journal line, and later a manifest entry. The keys
/// are a contract other tools read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameEntry {
    /// The image's index in the plan's capture order; also names the frame file.
    pub index: usize,
    /// Index of the trigger that took it; images taken together share it.
    pub trigger: usize,
    /// Path relative to the run directory: `frames/NNNNNN.png` for
    /// samples rigd encoded, or the camera's own file (`.dng`, `.jpg`, …).
    pub file: String,
    /// SHA-256 of the frame's file, lowercase hex.
    pub sha256: String,
    /// Commanded directions, sample frame.
    pub light: Direction,
    /// Commanded view direction, sample frame.
    pub view: Direction,
    /// Light direction the set-points really produce (sample frame);
    /// for an infeasible pair, the substitute's.
    pub achieved_light: Direction,
    /// View direction the set-points really produce (sample frame);
    /// for an infeasible pair, the substitute's.
    pub achieved_view: Direction,
    /// The camera that took the frame, named as in the profile.
    pub camera: String,
    /// Exposure time in seconds: the run's override, else the camera's own.
    pub exposure_s: f64,
    /// Physical time of the exposure's start since the run started, seconds.
    pub t_s: f64,
    /// Where the devices stood.
    pub positions: Setpoints,
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// Bits per sensor value of the camera; the PNG holds 8 bits for 8 or
    /// fewer, else 16.
    pub bit_depth: u8,
    /// Laser frames: source, and the tilt measured around the exposure.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub laser: Option<crate::schedule::laser::LaserStep>,
    /// The camera's own frame id, timestamp and pixel format, for cameras
    /// that report them (GenICam); absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device: Option<crate::rig::hal::DeviceFrameInfo>,
    /// The further exposures of the same image, in the order taken (each
    /// shorter than `exposure_s`), when the run's exposure policy took
    /// more than one; empty otherwise. The image's exposures are one
    /// journal line, so a step is never half-taken.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub brackets: Vec<BracketFrame>,
}

/// A further exposure of a journaled image ([`FrameEntry::brackets`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BracketFrame {
    /// Path relative to the run directory: `frames/NNNNNN.eK.EXT`, K
    /// counting the image's exposures from 1.
    pub file: String,
    /// SHA-256 of the file, lowercase hex.
    pub sha256: String,
    /// Exposure time in seconds.
    pub exposure_s: f64,
}

impl FrameEntry {
    /// Every file of the image with its SHA-256: the first exposure, then
    /// the brackets.
    pub fn files(&self) -> impl Iterator<Item = (&str, &str)> {
        std::iter::once((self.file.as_str(), self.sha256.as_str())).chain(
            self.brackets
                .iter()
                .map(|b| (b.file.as_str(), b.sha256.as_str())),
        )
    }

    /// Every exposure of the image, seconds, in the order taken.
    pub fn exposures_s(&self) -> Vec<f64> {
        std::iter::once(self.exposure_s)
            .chain(self.brackets.iter().map(|b| b.exposure_s))
            .collect()
    }
}

/// The run's last known state, replaced atomically on every change.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StateRecord {
    /// Where the run stands.
    pub state: RunState,
    /// Why the run is in this state (a fault, the operator, an interruption,
    /// frames missing); null when there is none.
    #[serde(default)]
    pub reason: Option<String>,
    /// Physical time spent so far, over all sessions.
    pub physical_s: f64,
    /// When the record was written: RFC 3339, UTC, whole seconds.
    pub updated_at: String,
}

/// An image that could not be taken as asked.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InfeasibleEntry {
    /// The image's index in the plan's capture order.
    pub index: usize,
    /// Commanded light direction, sample frame.
    pub light: Direction,
    /// Commanded view direction, sample frame.
    pub view: Direction,
    /// Light direction taken instead (the nearest the rig reaches), sample frame.
    pub achieved_light: Direction,
    /// View direction taken instead (the nearest the rig reaches), sample frame.
    pub achieved_view: Direction,
    /// Why the rig cannot reach the pair, and what was substituted.
    pub reason: String,
}

/// Written at the end of a run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    /// Format tag of the file: [`RUN_FORMAT`].
    pub format: String,
    /// Version of the rigd that wrote the manifest.
    pub software_version: String,
    /// Name of the rig profile.
    pub profile: String,
    /// Name of the plan (`h1`, `laser:turns=4`, a plan file's name).
    pub plan: String,
    /// Name of the measured sample.
    pub sample: String,
    /// The state the run ended in: completed or aborted (`failed` in runs
    /// an older rigd ended with frames missing).
    pub state: RunState,
    /// Why it ended so; null for a completed run.
    #[serde(default)]
    pub reason: Option<String>,
    /// Images in the plan.
    pub steps_total: usize,
    /// Triggers in the plan; one trigger exposes one or more cameras together.
    pub triggers_total: usize,
    /// Images with a valid frame (the entries of `frames`).
    pub frames_written: usize,
    /// Physical capture time in seconds over all sessions: up to the last
    /// frame, or to the abort.
    pub physical_duration_s: f64,
    /// When the run was started, RFC 3339 UTC (as in `run.json`).
    pub started_at: String,
    /// When the manifest was written, RFC 3339 UTC.
    pub finished_at: String,
    /// Images the rig could not take as asked, with what was taken instead.
    pub infeasible: Vec<InfeasibleEntry>,
    /// Every valid frame, by image index.
    pub frames: Vec<FrameEntry>,
}

/// What a resumed run finds on disk.
#[derive(Debug, Default)]
pub struct Recovery {
    /// Valid frames by image index.
    pub done: BTreeMap<usize, FrameEntry>,
    /// Physical time already spent.
    pub physical_s: f64,
    /// Images whose frame was missing or damaged, to be retaken.
    pub retake: Vec<usize>,
    /// Bytes of a torn last journal line that were cut off.
    pub torn_bytes: u64,
    /// Journal lines moved to [`JOURNAL_HISTORY_FILE`]: an image's older
    /// lines, the lines of frames to retake, lines that did not parse.
    pub set_aside: usize,
    /// The state the run's new session starts from: paused, failed, or
    /// interrupted (also for a run found preparing or running, which
    /// nobody drives any more).
    pub state: RunState,
}

/// An open run directory.
#[derive(Debug)]
pub struct RunDir {
    root: PathBuf,
    /// Held while the run is written: one writer per run.
    _lock: WriterLock,
    journal: File,
    /// Bytes of complete lines in the journal; an append that fails
    /// partway is cut back to it, so the next line starts on a line.
    journal_len: u64,
}

/// Current time as RFC 3339 (UTC, seconds).
pub fn now_rfc3339() -> String {
    humantime::format_rfc3339_seconds(std::time::SystemTime::now()).to_string()
}

/// Writes `bytes` to `path` atomically: a temporary file, fsync, rename, and
/// an fsync of the directory so the rename itself survives a crash.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    rigd_core::atomic::write(path, bytes)?;
    Ok(rigd_core::atomic::sync_parent(path)?)
}

impl From<rigd_core::atomic::WriteError> for StoreError {
    fn from(e: rigd_core::atomic::WriteError) -> StoreError {
        StoreError::Io {
            path: e.path,
            op: e.op,
            error: e.error,
        }
    }
}

/// Lowercase hex SHA-256 of `bytes`, as in [`FrameEntry::sha256`].
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// Relative path of image `index`'s frame as rigd encodes it (PNG).
pub fn frame_file(index: usize) -> String {
    frame_file_with(index, "png")
}

/// Relative path of image `index`'s frame stored with extension `ext`: a
/// camera file keeps its own (`dng`, `nef`, `jpg`, …).
pub fn frame_file_with(index: usize, ext: &str) -> String {
    format!("{FRAMES_DIR}/{index:06}.{ext}")
}

/// Relative path of image `index`'s further exposure `k` (from 1) stored
/// with extension `ext` ([`BracketFrame::file`]).
pub fn bracket_file_with(index: usize, k: usize, ext: &str) -> String {
    format!("{FRAMES_DIR}/{index:06}.e{k}.{ext}")
}

impl RunDir {
    /// Creates a new run directory. Refuses a folder that already holds a
    /// run or anything else.
    pub fn create(root: &Path, meta: &RunMeta) -> Result<RunDir, StoreError> {
        let shown = root.display().to_string();
        if root.join(RUN_FILE).exists() {
            let sample = fs::read(root.join(RUN_FILE))
                .ok()
                .and_then(|b| serde_json::from_slice::<RunMeta>(&b).ok())
                .map(|m| m.sample)
                .unwrap_or_else(|| "?".into());
            return Err(StoreError::AlreadyRun(shown, sample));
        }
        if root.exists() {
            let mut entries = fs::read_dir(root).map_err(io(root, "read directory"))?;
            if entries.next().is_some() {
                return Err(StoreError::NotEmpty(shown));
            }
        }
        fs::create_dir_all(root.join(FRAMES_DIR)).map_err(io(root, "create directory"))?;
        let lock = WriterLock::acquire(root)?;
        // Another writer may have made the run between the check and the lock.
        if root.join(RUN_FILE).exists() {
            return Err(StoreError::Busy(shown));
        }
        let json = serde_json::to_vec_pretty(meta).map_err(|e| StoreError::Corrupt {
            path: root.join(RUN_FILE),
            why: e.to_string(),
        })?;
        write_atomic(&root.join(RUN_FILE), &json)?;
        let (journal, journal_len) = open_journal(root)?;
        make_reserve(root);
        Ok(RunDir {
            root: root.to_path_buf(),
            _lock: lock,
            journal,
            journal_len,
        })
    }

    /// Opens an existing run to resume it: reads its metadata, checks every
    /// journaled frame against its checksum, and repairs the journal (the
    /// one place it is repaired): afterwards it holds exactly one line per
    /// image with a valid frame, and no torn tail. The lines taken out go
    /// to [`JOURNAL_HISTORY_FILE`].
    pub fn open(root: &Path) -> Result<(RunDir, RunMeta, Recovery), StoreError> {
        let shown = root.display().to_string();
        let meta = read_meta(root)?;
        // Before anything is repaired: recovery belongs to the one writer.
        let lock = WriterLock::acquire(root)?;
        let state = read_state(root)?;
        let start = match &state {
            Some(s) if s.state.is_terminal() => {
                return Err(StoreError::Finished(shown, s.state));
            }
            Some(s) if s.state.is_resumable() => s.state,
            _ => mark_interrupted(root, state.as_ref(), INTERRUPTED_REASON)?.state,
        };
        fs::create_dir_all(root.join(FRAMES_DIR)).map_err(io(root, "create directory"))?;
        let mut recovery = Recovery {
            state: start,
            ..Recovery::default()
        };
        let journal_path = root.join(JOURNAL_FILE);
        if journal_path.exists() {
            let scan = JournalScan::read(&journal_path)?;
            recovery.torn_bytes = scan.torn_bytes();
            for line in &scan.lines {
                recovery.physical_s = recovery.physical_s.max(line.entry.t_s);
            }
            let mut keep = scan.last_of_each();
            // Verify every frame the journal vouches for, every exposure of it.
            keep.retain(|&index, &mut k| {
                let e = &scan.lines[k].entry;
                let ok = e.files().all(|(file, sha)| {
                    fs::read(root.join(file))
                        .map(|b| sha256_hex(&b) == sha)
                        .unwrap_or(false)
                });
                if !ok {
                    recovery.retake.push(index);
                }
                ok
            });
            recovery.set_aside = scan.rewrite(&journal_path, &keep)?;
            for k in keep.into_values() {
                let e = scan.lines[k].entry.clone();
                recovery.done.insert(e.index, e);
            }
        }
        remove_temporaries(&root.join(FRAMES_DIR))?;
        remove_temporaries(root)?;
        if let Some(s) = state {
            recovery.physical_s = recovery.physical_s.max(s.physical_s);
        }
        let (journal, journal_len) = open_journal(root)?;
        make_reserve(root);
        Ok((
            RunDir {
                root: root.to_path_buf(),
                _lock: lock,
                journal,
                journal_len,
            },
            meta,
            recovery,
        ))
    }

    /// Checks, before the run is marked completed, that the journal on
    /// disk (read back, not what the writer remembers) holds each of the
    /// plan's `images` exactly once; returns the images it lacks, in
    /// order. An image with more than one line, or a line that does not
    /// parse, has its extra lines moved to the history, as a resume would.
    pub fn check_complete(&mut self, images: usize) -> Result<Vec<usize>, StoreError> {
        let path = self.root.join(JOURNAL_FILE);
        let scan = JournalScan::read(&path)?;
        let keep = scan.last_of_each();
        if scan.rewrite(&path, &keep)? > 0 {
            (self.journal, self.journal_len) = open_journal(&self.root)?;
        }
        Ok((0..images).filter(|i| !keep.contains_key(i)).collect())
    }

    /// The run directory's path.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Writes a frame under its final name (via a temporary), returning
    /// the entry with its file and checksum filled in: the camera's own
    /// file byte for byte where it delivered one, else the samples encoded
    /// as PNG. Does not journal it: see [`RunDir::append_journal`].
    pub fn write_frame(
        root: &Path,
        mut entry: FrameEntry,
        frame: &Frame,
    ) -> Result<FrameEntry, StoreError> {
        let ext = frame.original.as_ref().map_or("png", |o| o.extension);
        let rel = frame_file_with(entry.index, ext);
        entry.sha256 = Self::write_frame_file(root, &rel, frame)?;
        entry.file = rel;
        entry.width = frame.width;
        entry.height = frame.height;
        entry.bit_depth = frame.bit_depth;
        entry.device = frame.device.clone();
        Ok(entry)
    }

    /// Writes a further exposure `k` (from 1) of the image `entry` holds,
    /// and adds it to the entry's brackets (its journal line, once
    /// appended, vouches for it).
    pub fn write_bracket(
        root: &Path,
        entry: &mut FrameEntry,
        k: usize,
        exposure_s: f64,
        frame: &Frame,
    ) -> Result<(), StoreError> {
        let ext = frame.original.as_ref().map_or("png", |o| o.extension);
        let file = bracket_file_with(entry.index, k, ext);
        let sha256 = Self::write_frame_file(root, &file, frame)?;
        entry.brackets.push(BracketFrame {
            file,
            sha256,
            exposure_s,
        });
        Ok(())
    }

    /// Writes a frame's file at `rel` (the camera's own bytes, else a PNG
    /// of its samples); returns the file's SHA-256.
    fn write_frame_file(root: &Path, rel: &str, frame: &Frame) -> Result<String, StoreError> {
        let path = root.join(rel);
        let encoded;
        let bytes = match &frame.original {
            Some(original) => &original.bytes,
            None => {
                encoded = encode_png(frame).map_err(|why| StoreError::Corrupt {
                    path: path.clone(),
                    why,
                })?;
                &encoded
            }
        };
        // Not synced here: the journal line, which is, carries the frame's
        // SHA-256, so a frame a crash lost or cut is known and taken again.
        rigd_core::atomic::write_unsynced(&path, bytes)?;
        Ok(sha256_hex(bytes))
    }

    /// Appends entries to the journal and fsyncs it: once this returns, the
    /// frames count as taken.
    pub fn append_journal(&mut self, entries: &[FrameEntry]) -> Result<(), StoreError> {
        let path = self.root.join(JOURNAL_FILE);
        let mut buf = Vec::new();
        for e in entries {
            serde_json::to_writer(&mut buf, e).map_err(|err| StoreError::Corrupt {
                path: path.clone(),
                why: err.to_string(),
            })?;
            buf.push(b'\n');
        }
        let appended = self
            .journal
            .write_all(&buf)
            .map_err(io(&path, "append"))
            .and_then(|()| self.journal.sync_data().map_err(io(&path, "fsync")));
        match appended {
            Ok(()) => {
                self.journal_len += buf.len() as u64;
                Ok(())
            }
            Err(e) => {
                // Part of the lines may be in the file: cut them off, so the
                // next append starts a line instead of finishing a torn one.
                // Should that fail too, the next open cuts the torn tail.
                let _ = self.journal.set_len(self.journal_len);
                Err(e)
            }
        }
    }

    /// Replaces `state.json` with `record`, atomically. On a full disk the
    /// run's reserve ([`RESERVE_FILE`]) is given up for it.
    pub fn write_state(&self, record: &StateRecord) -> Result<(), StoreError> {
        let path = self.root.join(STATE_FILE);
        let json = serde_json::to_vec_pretty(record).map_err(|e| StoreError::Corrupt {
            path: path.clone(),
            why: e.to_string(),
        })?;
        match write_atomic(&path, &json) {
            Err(e) if e.is_out_of_space() && release_reserve(&self.root) => {
                write_atomic(&path, &json)
            }
            r => r,
        }
    }

    /// Writes `manifest.json`, atomically.
    pub fn write_manifest(&self, manifest: &Manifest) -> Result<(), StoreError> {
        let json = serde_json::to_vec_pretty(manifest).map_err(|e| StoreError::Corrupt {
            path: self.root.join(MANIFEST_FILE),
            why: e.to_string(),
        })?;
        write_atomic(&self.root.join(MANIFEST_FILE), &json)
    }
}

impl StoreError {
    /// Whether the error is the filesystem having no room left (or the
    /// writer's quota spent).
    pub fn is_out_of_space(&self) -> bool {
        matches!(
            self,
            StoreError::Io { error, .. }
                if matches!(error.raw_os_error(), Some(libc::ENOSPC | libc::EDQUOT))
        )
    }
}

/// Makes the run's reserve if it is missing. Best effort: a disk too full
/// for it now is one the run is about to report anyway.
fn make_reserve(root: &Path) {
    let path = root.join(RESERVE_FILE);
    if path.exists() {
        return;
    }
    if let Err(e) = fs::write(&path, vec![0u8; RESERVE_BYTES]) {
        tracing::warn!(
            "cannot keep {} in reserve at {}: {e}",
            human_bytes(RESERVE_BYTES as u64),
            path.display()
        );
        let _ = fs::remove_file(&path);
    }
}

/// Frees the run's reserve; whether there was one to free.
fn release_reserve(root: &Path) -> bool {
    let freed = fs::remove_file(root.join(RESERVE_FILE)).is_ok();
    if freed {
        tracing::warn!("the disk is full: gave up the run's reserve to record its state");
    }
    freed
}

/// Opens the journal to append (the writer's handle), with its length.
fn open_journal(root: &Path) -> Result<(File, u64), StoreError> {
    let path = root.join(JOURNAL_FILE);
    let file = OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)
        .map_err(io(&path, "open"))?;
    let len = file.metadata().map_err(io(&path, "stat"))?.len();
    Ok((file, len))
}

/// Reads a run's metadata (`run.json`).
pub fn read_meta(root: &Path) -> Result<RunMeta, StoreError> {
    let run_path = root.join(RUN_FILE);
    if !run_path.exists() {
        return Err(StoreError::NoRun(root.display().to_string()));
    }
    let bytes = fs::read(&run_path).map_err(io(&run_path, "read"))?;
    serde_json::from_slice(&bytes).map_err(|e| StoreError::Corrupt {
        path: run_path,
        why: e.to_string(),
    })
}

/// Bytes an unprivileged writer may still use on the filesystem holding
/// `path`; `None` if the system cannot tell.
pub fn free_bytes(path: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(path.as_os_str().as_bytes()).ok()?;
    let mut st = std::mem::MaybeUninit::<libc::statvfs>::uninit();
    // SAFETY: `c` is a valid NUL-terminated path and `st` is written by
    // statvfs before it is read, only when the call succeeds.
    let rc = unsafe { libc::statvfs(c.as_ptr(), st.as_mut_ptr()) };
    if rc != 0 {
        return None;
    }
    // SAFETY: statvfs returned 0, so it filled `st`.
    let st = unsafe { st.assume_init() };
    Some(st.f_bavail.saturating_mul(st.f_frsize))
}

/// Why a write into the run at `root` failed, as a pause reason: the
/// error, and the space left on the run's filesystem, so an operator sees
/// at once whether freeing space is the fix.
pub fn storage_fault_reason(root: &Path, error: &StoreError) -> String {
    match free_bytes(root) {
        Some(b) => format!(
            "{error}; {} free on the filesystem of {}",
            human_bytes(b),
            root.display()
        ),
        None => error.to_string(),
    }
}

/// Bytes in binary units, for messages.
pub fn human_bytes(b: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = b as f64;
    let mut unit = 0;
    while v >= 1024.0 && unit + 1 < UNITS.len() {
        v /= 1024.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{b} B")
    } else {
        format!("{v:.1} {}", UNITS[unit])
    }
}

/// Why a run found preparing or running with nobody driving it is marked
/// interrupted.
pub const INTERRUPTED_REASON: &str =
    "interrupted: the process driving the run stopped while it was active; resume it to go on";

/// Moves the run at `root` from its recorded state (`current`, as read) to
/// `to`, if the state table allows it, and writes the record.
pub fn transition_state(
    root: &Path,
    current: Option<&StateRecord>,
    to: RunState,
    reason: Option<String>,
    physical_s: f64,
) -> Result<StateRecord, StoreError> {
    let path = root.join(STATE_FILE);
    let from = current.map_or(RunState::Idle, |s| s.state);
    from.transition(to)
        .map_err(|error| StoreError::Transition {
            path: path.clone(),
            error,
        })?;
    let record = StateRecord {
        state: to,
        reason,
        physical_s,
        updated_at: now_rfc3339(),
    };
    let json = serde_json::to_vec_pretty(&record).map_err(|e| StoreError::Corrupt {
        path: path.clone(),
        why: e.to_string(),
    })?;
    write_atomic(&path, &json)?;
    Ok(record)
}

/// Marks a run whose record says it is active (or that has no record) as
/// interrupted: nobody drives it any more.
pub fn mark_interrupted(
    root: &Path,
    current: Option<&StateRecord>,
    reason: &str,
) -> Result<StateRecord, StoreError> {
    transition_state(
        root,
        current,
        RunState::Interrupted,
        Some(reason.to_string()),
        current.map_or(0.0, |s| s.physical_s),
    )
}

/// Reads the state record, if any.
pub fn read_state(root: &Path) -> Result<Option<StateRecord>, StoreError> {
    let path = root.join(STATE_FILE);
    if !path.exists() {
        return Ok(None);
    }
    let bytes = fs::read(&path).map_err(io(&path, "read"))?;
    serde_json::from_slice(&bytes)
        .map(Some)
        .map_err(|e| StoreError::Corrupt {
            path,
            why: e.to_string(),
        })
}

/// Reads a journal as a reader may, while its writer appends: the complete
/// lines, one entry per image (its last line; an older rigd's resume left a
/// retaken image's lines twice), sorted by image index, and the length of
/// a torn last line (a line still being appended, or one a crash cut),
/// which is left where it is: a reader never writes. A line that does not
/// parse before the last is an error naming it.
pub fn read_journal(path: &Path) -> Result<(Vec<FrameEntry>, u64), StoreError> {
    let scan = JournalScan::read(path)?;
    if let Some(bad) = scan.damaged.first() {
        return Err(StoreError::Corrupt {
            path: path.to_path_buf(),
            why: format!("line {}: {}", bad.lineno, bad.why),
        });
    }
    let torn = scan.torn_bytes();
    let entries = scan
        .last_of_each()
        .into_values()
        .map(|k| scan.lines[k].entry.clone())
        .collect();
    Ok((entries, torn))
}

/// One complete journal line that parses.
struct JournalLine {
    entry: FrameEntry,
    /// Its bytes in the journal, newline included.
    span: std::ops::Range<usize>,
}

/// A complete journal line that does not parse.
struct DamagedLine {
    /// Line number, from 1.
    lineno: usize,
    /// Its bytes in the journal, newline included.
    span: std::ops::Range<usize>,
    /// The parser's words.
    why: String,
}

/// A journal as its bytes stand, split into lines: the one way rigd reads
/// a journal, for its readers and its writer alike.
struct JournalScan {
    bytes: Vec<u8>,
    lines: Vec<JournalLine>,
    damaged: Vec<DamagedLine>,
    /// Where the complete lines end; what follows is a torn line.
    complete_end: usize,
}

impl JournalScan {
    /// Reads the journal at `path` (one read of what is there now).
    fn read(path: &Path) -> Result<JournalScan, StoreError> {
        let bytes = fs::read(path).map_err(io(path, "read"))?;
        let (mut lines, mut damaged) = (Vec::new(), Vec::new());
        let mut start = 0;
        let mut lineno = 0;
        while let Some(nl) = bytes[start..].iter().position(|&b| b == b'\n') {
            let span = start..start + nl + 1;
            let next = span.end;
            lineno += 1;
            match serde_json::from_slice::<FrameEntry>(&bytes[span.clone()]) {
                Ok(entry) => lines.push(JournalLine { entry, span }),
                Err(e) => damaged.push(DamagedLine {
                    lineno,
                    span: span.clone(),
                    why: e.to_string(),
                }),
            }
            start = next;
        }
        Ok(JournalScan {
            bytes,
            lines,
            damaged,
            complete_end: start,
        })
    }

    /// Bytes after the last complete line.
    fn torn_bytes(&self) -> u64 {
        (self.bytes.len() - self.complete_end) as u64
    }

    /// Each image's last line: image index → position in `lines`.
    fn last_of_each(&self) -> BTreeMap<usize, usize> {
        self.lines
            .iter()
            .enumerate()
            .map(|(k, l)| (l.entry.index, k))
            .collect()
    }

    /// The writer's repair: rewrites the journal at `path` with only the
    /// lines `keep` names (in the order they stand), after appending the
    /// complete lines it leaves out to the history file; a torn tail is
    /// dropped. Nothing is written when there is nothing to leave out.
    /// Returns how many lines went to the history.
    fn rewrite(&self, path: &Path, keep: &BTreeMap<usize, usize>) -> Result<usize, StoreError> {
        let kept: std::collections::BTreeSet<usize> = keep.values().copied().collect();
        let mut spans: Vec<(std::ops::Range<usize>, bool)> = self
            .lines
            .iter()
            .enumerate()
            .map(|(k, l)| (l.span.clone(), kept.contains(&k)))
            .chain(self.damaged.iter().map(|d| (d.span.clone(), false)))
            .collect();
        spans.sort_by_key(|(span, _)| span.start);
        let set_aside: Vec<u8> = spans
            .iter()
            .filter(|(_, keep)| !keep)
            .flat_map(|(span, _)| self.bytes[span.clone()].iter().copied())
            .collect();
        let moved = spans.iter().filter(|(_, keep)| !keep).count();
        if moved == 0 && self.torn_bytes() == 0 {
            return Ok(0);
        }
        if moved > 0 {
            // History first: a crash before the journal is replaced leaves
            // a line in both, never in neither.
            let history = path.with_file_name(JOURNAL_HISTORY_FILE);
            let mut f = OpenOptions::new()
                .create(true)
                .append(true)
                .open(&history)
                .map_err(io(&history, "open"))?;
            f.write_all(&set_aside).map_err(io(&history, "append"))?;
            f.sync_data().map_err(io(&history, "fsync"))?;
        }
        let journal: Vec<u8> = spans
            .iter()
            .filter(|(_, keep)| *keep)
            .flat_map(|(span, _)| self.bytes[span.clone()].iter().copied())
            .collect();
        write_atomic(path, &journal)?;
        Ok(moved)
    }
}

/// Reads the run's manifest, if it has one; one that does not parse is an
/// error naming it.
pub fn read_manifest(root: &Path) -> Result<Option<Manifest>, StoreError> {
    let path = root.join(MANIFEST_FILE);
    let bytes = match fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(io(&path, "read")(e)),
    };
    serde_json::from_slice(&bytes)
        .map(Some)
        .map_err(|e| StoreError::Corrupt {
            path,
            why: format!("not a manifest ({e})"),
        })
}

/// Checks that an ended run's journal, as read (`entries`, one per image),
/// and its manifest agree: the same images with the same checksums, and a
/// manifest that parses. A completed run must have one; a run aborted
/// while no engine drove it has none, and a run that has not ended
/// (`state.json` neither completed nor aborted) has none to agree with
/// yet: those pass. An error names both files and both counts.
pub fn check_manifest(root: &Path, entries: &[FrameEntry]) -> Result<(), StoreError> {
    let Some(ended) = read_state(root)?
        .map(|s| s.state)
        .filter(|s| s.is_terminal())
    else {
        return Ok(());
    };
    let manifest_path = root.join(MANIFEST_FILE);
    let journal_path = root.join(JOURNAL_FILE);
    let manifest = match read_manifest(root)? {
        Some(m) => m,
        None if ended != RunState::Completed => return Ok(()),
        None => return Err(StoreError::Corrupt {
            path: manifest_path,
            why: format!(
                "missing, though {STATE_FILE} says the run completed; the run's record of its frames is incomplete"
            ),
        }),
    };
    let listed: BTreeMap<usize, &str> = manifest
        .frames
        .iter()
        .map(|f| (f.index, f.sha256.as_str()))
        .collect();
    let journaled: BTreeMap<usize, &str> = entries
        .iter()
        .map(|e| (e.index, e.sha256.as_str()))
        .collect();
    if listed == journaled
        && manifest.frames.len() == listed.len()
        && manifest.frames_written == listed.len()
    {
        return Ok(());
    }
    let only = |a: &BTreeMap<usize, &str>, b: &BTreeMap<usize, &str>| -> Vec<usize> {
        a.keys().filter(|i| !b.contains_key(i)).copied().collect()
    };
    let differ: Vec<usize> = listed
        .iter()
        .filter(|(i, sha)| journaled.get(i).is_some_and(|j| j != *sha))
        .map(|(i, _)| *i)
        .collect();
    let mut details = Vec::new();
    for (what, list) in [
        ("only in the manifest", only(&listed, &journaled)),
        ("only in the journal", only(&journaled, &listed)),
        ("with other checksums in each", differ),
    ] {
        if !list.is_empty() {
            details.push(format!("{} {what}", image_list(&list)));
        }
    }
    if manifest.frames_written != manifest.frames.len() {
        details.push(format!(
            "the manifest says {} frames written but lists {}",
            manifest.frames_written,
            manifest.frames.len()
        ));
    }
    Err(StoreError::Corrupt {
        path: journal_path,
        why: format!(
            "holds {} images, and {} lists {}: the journal and the manifest disagree ({}); the run cannot be processed as it is",
            journaled.len(),
            manifest_path.display(),
            manifest.frames.len(),
            details.join("; ")
        ),
    })
}

/// [`check_manifest`] for the run at `root`, its journal read here: what a
/// step that reads the run's textures rather than its frames checks first.
/// A folder without `run.json` (textures imported from another format) is
/// no run, and passes.
pub fn check_run(root: &Path) -> Result<(), StoreError> {
    if !root.join(RUN_FILE).exists() {
        return Ok(());
    }
    let (entries, _) = read_journal(&root.join(JOURNAL_FILE))?;
    check_manifest(root, &entries)
}

/// Image indices for a message: `image 3`, `images 3, 5, 8`, the first 10
/// and a count of the rest.
pub fn image_list(indices: &[usize]) -> String {
    const SHOWN: usize = 10;
    let shown: Vec<String> = indices.iter().take(SHOWN).map(usize::to_string).collect();
    let more = indices.len().saturating_sub(SHOWN);
    match indices.len() {
        1 => format!("image {}", shown[0]),
        _ if more > 0 => format!("images {} and {more} more", shown.join(", ")),
        _ => format!("images {}", shown.join(", ")),
    }
}

/// Removes what a crash left half-written in `dir`: the temporaries of
/// `rigd_core::atomic` (`.NAME.tmp.PID.N`), frames and records alike, and
/// frames' temporaries of older versions (`.NNNNNN.EXT.tmp`).
fn remove_temporaries(dir: &Path) -> Result<(), StoreError> {
    for entry in fs::read_dir(dir).map_err(io(dir, "read directory"))? {
        let entry = entry.map_err(io(dir, "read directory"))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') && (name.ends_with(".tmp") || name.contains(".tmp.")) {
            fs::remove_file(entry.path()).map_err(io(&entry.path(), "remove"))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(index: usize) -> FrameEntry {
        let d = Direction::new(0.0, 0.0);
        FrameEntry {
            index,
            trigger: index,
            file: String::new(),
            sha256: String::new(),
            light: d,
            view: d,
            achieved_light: d,
            achieved_view: d,
            camera: "camera".into(),
            exposure_s: 0.1,
            t_s: index as f64,
            positions: Setpoints {
                axes: Default::default(),
                arm: None,
                lamp: "hmi".into(),
                plate_mm: None,
            },
            width: 0,
            height: 0,
            bit_depth: 0,
            laser: None,
            device: None,
            brackets: Vec::new(),
        }
    }

    #[test]
    fn png_round_trips_12_and_8_bit() {
        for depth in [12u8, 8] {
            let max = (1u16 << depth) - 1;
            let f = Frame {
                width: 3,
                height: 2,
                bit_depth: depth,
                pixels: vec![0, 1, max, 7, 100, max / 2],
                device: None,
                original: None,
            };
            let bytes = encode_png(&f).unwrap_or_default();
            let (w, h, px) = crate::rig::hal::decode_png(&bytes).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!((w, h, px), (3, 2, f.pixels.clone()));
        }
    }

    /// A run directory with `n` images journaled, each with a frame file
    /// whose checksum its line holds; returns the lines.
    fn run_with(root: &Path, n: usize) -> Vec<String> {
        let profile = Profile::load("bonn-gonioreflectometer").unwrap_or_else(|e| panic!("{e}"));
        let d = [Direction::new(30.0, 0.0), Direction::new(45.0, 90.0)];
        let meta = RunMeta {
            format: RUN_FORMAT.into(),
            software_version: "test".into(),
            profile,
            profile_source: "test".into(),
            plan: Plan {
                name: "t".into(),
                pairs: crate::plan::btf(&d, &d),
                laser: None,
                order: Default::default(),
            },
            sample: "s".into(),
            operator: None,
            notes: None,
            exposure_s: None,
            exposure_policy: Default::default(),
            frame_size: None,
            simulated: true,
            sim_scene: None,
            started_at: now_rfc3339(),
        };
        drop(RunDir::create(root, &meta).unwrap_or_else(|e| panic!("{e}")));
        let mut lines = Vec::new();
        for i in 0..n {
            let bytes = format!("frame {i}");
            let mut e = entry(i);
            e.file = frame_file(i);
            e.sha256 = sha256_hex(bytes.as_bytes());
            fs::write(root.join(&e.file), bytes).unwrap_or_else(|e| panic!("{e}"));
            lines.push(serde_json::to_string(&e).unwrap_or_default() + "\n");
        }
        fs::write(root.join(JOURNAL_FILE), lines.concat()).unwrap_or_else(|e| panic!("{e}"));
        let paused = StateRecord {
            state: RunState::Paused,
            reason: None,
            physical_s: 0.0,
            updated_at: now_rfc3339(),
        };
        fs::write(
            root.join(STATE_FILE),
            serde_json::to_vec(&paused).unwrap_or_default(),
        )
        .unwrap_or_else(|e| panic!("{e}"));
        lines
    }

    fn journal_text(root: &Path) -> String {
        fs::read_to_string(root.join(JOURNAL_FILE)).unwrap_or_default()
    }

    #[test]
    fn a_reader_never_changes_the_journal() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let root = dir.path().join("run");
        let mut text = run_with(&root, 3).concat();
        // A line mid-append, as a reader beside the writer may see it.
        text.push_str("{\"index\":3,\"trig");
        let path = root.join(JOURNAL_FILE);
        fs::write(&path, &text).unwrap_or_else(|e| panic!("{e}"));
        let before = fs::metadata(&path).unwrap_or_else(|e| panic!("{e}"));
        std::thread::sleep(std::time::Duration::from_millis(20));
        let (entries, torn) = read_journal(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(entries.len(), 3);
        assert_eq!(torn, "{\"index\":3,\"trig".len() as u64);
        let after = fs::metadata(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(after.len(), before.len());
        assert_eq!(after.modified().ok(), before.modified().ok());
        assert_eq!(fs::read_to_string(&path).unwrap_or_default(), text);
    }

    #[test]
    fn a_reader_takes_one_entry_per_image_the_last() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let root = dir.path().join("run");
        let mut lines = run_with(&root, 3);
        // An older rigd's resume left the retaken image's line twice.
        let mut retaken = entry(1);
        retaken.file = frame_file(1);
        retaken.sha256 = "retaken".into();
        lines.push(serde_json::to_string(&retaken).unwrap_or_default() + "\n");
        fs::write(root.join(JOURNAL_FILE), lines.concat()).unwrap_or_else(|e| panic!("{e}"));
        let (entries, _) = read_journal(&root.join(JOURNAL_FILE)).unwrap_or_else(|e| panic!("{e}"));
        let got: Vec<(usize, &str)> = entries
            .iter()
            .map(|e| (e.index, e.sha256.as_str()))
            .collect();
        assert_eq!(got.len(), 3, "{got:?}");
        assert_eq!(got[1], (1, "retaken"));
    }

    #[test]
    fn opening_to_write_repairs_a_torn_tail() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let root = dir.path().join("run");
        let lines = run_with(&root, 3);
        let torn = "{\"index\":3,\"trig";
        fs::write(root.join(JOURNAL_FILE), lines.concat() + torn).unwrap_or_else(|e| panic!("{e}"));
        let (mut run, _, recovery) = RunDir::open(&root).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(recovery.torn_bytes, torn.len() as u64);
        assert_eq!(recovery.done.len(), 3);
        assert_eq!(journal_text(&root), lines.concat());
        // The next line follows the repaired tail.
        let mut next = entry(3);
        next.file = frame_file(3);
        run.append_journal(&[next])
            .unwrap_or_else(|e| panic!("{e}"));
        let (entries, torn) =
            read_journal(&root.join(JOURNAL_FILE)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((entries.len(), torn), (4, 0));
    }

    #[test]
    fn resume_leaves_one_line_per_image_and_keeps_the_rest_as_history() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let root = dir.path().join("run");
        let mut lines = run_with(&root, 4);
        // Image 1's line twice (an older rigd's resume), image 2's frame
        // deleted, a line in the middle that does not parse.
        lines.push(lines[1].clone());
        fs::remove_file(root.join(frame_file(2))).unwrap_or_else(|e| panic!("{e}"));
        lines.insert(3, "{\"index\": 9, \"cut\n".into());
        fs::write(root.join(JOURNAL_FILE), lines.concat()).unwrap_or_else(|e| panic!("{e}"));
        let (_, _, recovery) = RunDir::open(&root).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(recovery.retake, [2]);
        assert_eq!(recovery.done.keys().copied().collect::<Vec<_>>(), [0, 1, 3]);
        // The journal holds one line per valid image, each image's last
        // where it stood ...
        let text = journal_text(&root);
        let kept: Vec<usize> = text
            .lines()
            .map(|l| {
                serde_json::from_str::<FrameEntry>(l)
                    .map(|e| e.index)
                    .unwrap_or(99)
            })
            .collect();
        assert_eq!(kept, [0, 3, 1]);
        // ... and the lines set aside are history, not entries.
        let history = fs::read_to_string(root.join(JOURNAL_HISTORY_FILE)).unwrap_or_default();
        assert_eq!(history.lines().count(), 3, "{history}");
        assert!(history.contains("\"cut"), "{history}");
        // Opened again, there is nothing left to repair.
        let (_, _, again) = RunDir::open(&root).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((again.set_aside, again.torn_bytes), (0, 0));
        assert_eq!(journal_text(&root), text);
    }

    #[test]
    fn completion_is_checked_against_the_journal_on_disk() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let root = dir.path().join("run");
        let lines = run_with(&root, 4);
        let (mut run, _, _) = RunDir::open(&root).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            run.check_complete(4).unwrap_or_default(),
            Vec::<usize>::new()
        );
        assert_eq!(run.check_complete(6).unwrap_or_default(), [4, 5]);
        // A line gone behind the writer's back (as a reader that cut what
        // it took for a torn tail once did), and another image twice.
        let changed = [&lines[0], &lines[2], &lines[3], &lines[2]].map(|l| l.as_str());
        fs::write(root.join(JOURNAL_FILE), changed.concat()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(run.check_complete(4).unwrap_or_default(), [1]);
        assert_eq!(
            journal_text(&root),
            [&lines[0], &lines[3], &lines[2]]
                .map(|l| l.as_str())
                .concat(),
            "one line per image"
        );
        // The writer's handle follows the rewritten journal.
        let mut again = entry(1);
        again.file = frame_file(1);
        run.append_journal(&[again])
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            run.check_complete(4).unwrap_or_default(),
            Vec::<usize>::new()
        );
    }

    #[test]
    fn an_ended_run_whose_journal_and_manifest_disagree_is_refused() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let root = dir.path().join("run");
        run_with(&root, 4);
        let (entries, _) = read_journal(&root.join(JOURNAL_FILE)).unwrap_or_else(|e| panic!("{e}"));
        // A run that has not ended has no manifest to agree with.
        assert!(check_manifest(&root, &entries[..2]).is_ok());
        let completed = StateRecord {
            state: RunState::Completed,
            reason: None,
            physical_s: 0.0,
            updated_at: now_rfc3339(),
        };
        let state = serde_json::to_vec(&completed).unwrap_or_default();
        fs::write(root.join(STATE_FILE), state).unwrap_or_else(|e| panic!("{e}"));
        let err = |entries: &[FrameEntry]| {
            check_manifest(&root, entries)
                .err()
                .map(|e| e.to_string())
                .unwrap_or_default()
        };
        assert!(
            err(&entries).contains("manifest.json: missing"),
            "{}",
            err(&entries)
        );
        fs::write(root.join(MANIFEST_FILE), "").unwrap_or_else(|e| panic!("{e}"));
        assert!(
            err(&entries).contains("manifest.json: not a manifest"),
            "{}",
            err(&entries)
        );
        let manifest = Manifest {
            format: RUN_FORMAT.into(),
            software_version: "test".into(),
            profile: "p".into(),
            plan: "t".into(),
            sample: "s".into(),
            state: RunState::Completed,
            reason: None,
            steps_total: 4,
            triggers_total: 4,
            frames_written: 4,
            physical_duration_s: 1.0,
            started_at: now_rfc3339(),
            finished_at: now_rfc3339(),
            infeasible: Vec::new(),
            frames: entries.clone(),
        };
        fs::write(
            root.join(MANIFEST_FILE),
            serde_json::to_vec(&manifest).unwrap_or_default(),
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert!(check_manifest(&root, &entries).is_ok());
        let cut = err(&entries[..3]);
        assert!(
            cut.contains("journal.ndjson: holds 3 images") && cut.contains("manifest.json lists 4"),
            "{cut}"
        );
        assert!(cut.contains("image 3 only in the manifest"), "{cut}");
        let mut other = entries.clone();
        other[1].sha256 = "other".into();
        assert!(
            err(&other).contains("image 1 with other checksums"),
            "{}",
            err(&other)
        );
    }

    #[test]
    fn damaged_journal_line_in_the_middle_is_an_error() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let path = dir.path().join(JOURNAL_FILE);
        let line = serde_json::to_string(&entry(0)).unwrap_or_default();
        fs::write(&path, format!("{line}\ngarbage\n{line}\n")).unwrap_or_else(|e| panic!("{e}"));
        let err = read_journal(&path)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(err.contains("line 2"), "{err}");
    }
}
