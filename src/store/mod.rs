//! The dataset on disk: one directory per run.
//!
//! ```text
//! RUN/run.json          what was asked: profile snapshot, plan, sample, operator, versions, start
//! RUN/journal.ndjson    one line per image written, appended and fsynced: the source of truth
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
//! does not match, after a power loss) is retaken on resume. A torn last
//! journal line is cut off.

pub mod processed;

use std::collections::BTreeMap;
use std::fs::{self, File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::kinematics::Setpoints;
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
    /// The state the run ended in: completed, failed (frames missing) or aborted.
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
    /// The state the run's new session starts from: paused, failed, or
    /// interrupted (also for a run found preparing or running, which
    /// nobody drives any more).
    pub state: RunState,
}

/// An open run directory.
#[derive(Debug)]
pub struct RunDir {
    root: PathBuf,
    journal: File,
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
        let json = serde_json::to_vec_pretty(meta).map_err(|e| StoreError::Corrupt {
            path: root.join(RUN_FILE),
            why: e.to_string(),
        })?;
        write_atomic(&root.join(RUN_FILE), &json)?;
        let journal = open_journal(root)?;
        make_reserve(root);
        Ok(RunDir {
            root: root.to_path_buf(),
            journal,
        })
    }

    /// Opens an existing run to resume it: reads its metadata, repairs a
    /// torn journal tail, and checks every journaled frame.
    pub fn open(root: &Path) -> Result<(RunDir, RunMeta, Recovery), StoreError> {
        let shown = root.display().to_string();
        let meta = read_meta(root)?;
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
            let (entries, torn) = read_journal(&journal_path)?;
            recovery.torn_bytes = torn;
            for e in entries {
                recovery.physical_s = recovery.physical_s.max(e.t_s);
                recovery.done.insert(e.index, e);
            }
        }
        // Verify every frame the journal vouches for.
        let mut bad = Vec::new();
        for (index, e) in &recovery.done {
            let ok = fs::read(root.join(&e.file))
                .map(|b| sha256_hex(&b) == e.sha256)
                .unwrap_or(false);
            if !ok {
                bad.push(*index);
            }
        }
        for i in &bad {
            recovery.done.remove(i);
        }
        recovery.retake = bad;
        remove_temporaries(&root.join(FRAMES_DIR))?;
        remove_temporaries(root)?;
        if let Some(s) = state {
            recovery.physical_s = recovery.physical_s.max(s.physical_s);
        }
        let journal = open_journal(root)?;
        make_reserve(root);
        Ok((
            RunDir {
                root: root.to_path_buf(),
                journal,
            },
            meta,
            recovery,
        ))
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
        let path = root.join(&rel);
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
        let tmp = root
            .join(FRAMES_DIR)
            .join(format!(".{:06}.{ext}.tmp", entry.index));
        {
            let mut f = File::create(&tmp).map_err(io(&tmp, "create"))?;
            f.write_all(bytes).map_err(io(&tmp, "write"))?;
        }
        fs::rename(&tmp, &path).map_err(io(&path, "rename"))?;
        entry.file = rel;
        entry.sha256 = sha256_hex(bytes);
        entry.width = frame.width;
        entry.height = frame.height;
        entry.bit_depth = frame.bit_depth;
        entry.device = frame.device.clone();
        Ok(entry)
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
        self.journal.write_all(&buf).map_err(io(&path, "append"))?;
        self.journal.sync_data().map_err(io(&path, "fsync"))
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

fn open_journal(root: &Path) -> Result<File, StoreError> {
    let path = root.join(JOURNAL_FILE);
    OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)
        .map_err(io(&path, "open"))
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

/// Reads the journal; a torn last line (a crash mid-append) is cut off the
/// file and its length returned. A damaged line elsewhere is an error.
pub fn read_journal(path: &Path) -> Result<(Vec<FrameEntry>, u64), StoreError> {
    let file = File::open(path).map_err(io(path, "open"))?;
    let len = file.metadata().map_err(io(path, "stat"))?.len();
    let mut reader = BufReader::new(file);
    let mut entries = Vec::new();
    let mut good_end: u64 = 0;
    let mut line = Vec::new();
    let mut lineno = 0;
    loop {
        line.clear();
        let n = reader
            .read_until(b'\n', &mut line)
            .map_err(io(path, "read"))?;
        if n == 0 {
            break;
        }
        lineno += 1;
        let complete = line.last() == Some(&b'\n');
        match serde_json::from_slice::<FrameEntry>(&line) {
            Ok(e) if complete => {
                entries.push(e);
                good_end += n as u64;
            }
            _ if good_end + n as u64 >= len => break, // torn tail
            Err(e) => {
                return Err(StoreError::Corrupt {
                    path: path.to_path_buf(),
                    why: format!("line {lineno}: {e}"),
                })
            }
            Ok(_) => break,
        }
    }
    let torn = len - good_end;
    if torn > 0 {
        let f = OpenOptions::new()
            .write(true)
            .open(path)
            .map_err(io(path, "open"))?;
        f.set_len(good_end).map_err(io(path, "truncate"))?;
        f.sync_all().map_err(io(path, "fsync"))?;
    }
    Ok((entries, torn))
}

/// Removes what a crash left half-written in `dir`: frames (`.NNNNNN.EXT.tmp`)
/// and records (`.state.json.tmp.PID.N`, from `rigd_core::atomic`).
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

    #[test]
    fn torn_journal_tail_is_cut_and_reported() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let path = dir.path().join(JOURNAL_FILE);
        let mut text = String::new();
        for i in 0..3 {
            text.push_str(&serde_json::to_string(&entry(i)).unwrap_or_default());
            text.push('\n');
        }
        let good = text.len() as u64;
        text.push_str("{\"index\":3,\"trig");
        fs::write(&path, &text).unwrap_or_else(|e| panic!("{e}"));
        let (entries, torn) = read_journal(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(entries.len(), 3);
        assert_eq!(torn, text.len() as u64 - good);
        assert_eq!(fs::metadata(&path).map(|m| m.len()).unwrap_or(0), good);
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
