//! The run index (`DATA/runs-index.json`): a cache of every run's view, so
//! that start-up does not read every run's record (run.json, state.json,
//! the whole journal, the manifest), which at tens of thousands of runs
//! takes far too long.
//!
//! The run directories stay the only source of truth. Each entry carries a
//! stamp of the four files a view is made from (size, modification and
//! change times, inode: a rewrite through a temporary file always changes
//! the inode); at start-up an entry is used only when its stamp matches the
//! files on disk and its run was not active (an active run must be marked
//! interrupted). A missing, unreadable, corrupt or foreign index is ignored
//! and written anew. Only the daemon writes it, whole or not at all.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::data_dir::{is_valid_id, load_run};
use super::wire::RunView;
use crate::model::run_state::RunState;
use crate::store::{JOURNAL_FILE, MANIFEST_FILE, RUN_FILE, STATE_FILE};

/// The index's file in the data directory (beside `runs/`, not in it).
pub const INDEX_FILE: &str = "runs-index.json";
/// The index's format; a file of another format (or another rigd version,
/// whose views may differ) is ignored.
const INDEX_FORMAT: &str = "rigd-runs-index/1";
/// Largest index read back: about a thousand bytes a run, so room for a
/// million runs.
const INDEX_FILE_LIMIT: u64 = 1 << 30;

/// One file's identity and state as `stat` gives it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileStamp {
    /// Size in bytes.
    pub len: u64,
    /// Modification time, ns since the epoch.
    pub mtime_ns: i128,
    /// Status-change time, ns since the epoch (cannot be set back by hand).
    pub ctime_ns: i128,
    /// Inode number.
    pub ino: u64,
}

/// The stamps of the files a run's view is made from: run.json,
/// state.json, the journal and the manifest (None where absent).
pub type RunStamp = [Option<FileStamp>; 4];

/// Stamps the files of the run directory `root`.
pub fn stamp(root: &Path) -> RunStamp {
    [RUN_FILE, STATE_FILE, JOURNAL_FILE, MANIFEST_FILE].map(|f| file_stamp(&root.join(f)))
}

fn file_stamp(path: &Path) -> Option<FileStamp> {
    use std::os::unix::fs::MetadataExt;
    let m = std::fs::metadata(path).ok()?;
    Some(FileStamp {
        len: m.size(),
        mtime_ns: i128::from(m.mtime()) * 1_000_000_000 + i128::from(m.mtime_nsec()),
        ctime_ns: i128::from(m.ctime()) * 1_000_000_000 + i128::from(m.ctime_nsec()),
        ino: m.ino(),
    })
}

/// One run in the index: the view its files gave when they had `stamp`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IndexEntry {
    /// The run's files as they were read.
    pub stamp: RunStamp,
    /// What [`load_run`] made of them.
    pub view: RunView,
}

#[derive(Debug, Serialize, Deserialize)]
struct IndexFile {
    format: String,
    software_version: String,
    runs: HashMap<String, IndexEntry>,
}

/// The index in memory: what the next write of the file will hold.
#[derive(Debug, Default)]
pub struct RunIndex {
    entries: HashMap<String, IndexEntry>,
}

/// A state whose run was being driven: never taken from the index, since
/// start-up must mark such a run interrupted (and so must read it).
fn was_driven(state: RunState) -> bool {
    state.is_active() || state == RunState::Idle
}

/// Reads the index file; None (with a warning, unless it is just absent)
/// when it cannot be used.
fn read_index(data_dir: &Path) -> Option<HashMap<String, IndexEntry>> {
    let path = data_dir.join(INDEX_FILE);
    // Bounded, regular files only: a FIFO or a huge file put there must not
    // hold up the start.
    let bytes = match rigd_core::read::read_bounded(&path, INDEX_FILE_LIMIT) {
        Ok(b) => b,
        Err(e) if e.io_kind() == Some(std::io::ErrorKind::NotFound) => return None,
        Err(e) => {
            tracing::warn!("cannot read {}: {e}; reading every run", path.display());
            return None;
        }
    };
    match serde_json::from_slice::<IndexFile>(&bytes) {
        Ok(f) if f.format == INDEX_FORMAT && f.software_version == env!("CARGO_PKG_VERSION") => {
            Some(f.runs)
        }
        Ok(f) => {
            tracing::warn!(
                "{} is of another format or rigd ({} {}): reading every run, then writing it anew",
                path.display(),
                short(&f.format),
                short(&f.software_version)
            );
            None
        }
        Err(e) => {
            tracing::warn!(
                "{} is not a run index ({e}): reading every run, then writing it anew",
                path.display()
            );
            None
        }
    }
}

fn short(s: &str) -> String {
    s.chars().take(64).collect()
}

/// What start-up found: every run's view, and the index to keep.
pub struct Scan {
    /// Every readable run, not active.
    pub views: Vec<RunView>,
    /// The index for these runs.
    pub index: RunIndex,
    /// The file differs from `index` (or was unusable): write it.
    pub stale: bool,
}

/// Every run directory under `runs_dir`, with problems logged and skipped:
/// from the index where a run's files are as they were indexed, else read
/// (and marked interrupted if it was being driven).
pub fn scan(data_dir: &Path, runs_dir: &Path) -> Scan {
    let cached = read_index(data_dir);
    let mut stale = cached.is_none();
    let mut cached = cached.unwrap_or_default();
    let mut index = RunIndex::default();
    let mut views = Vec::new();
    let Ok(dir) = std::fs::read_dir(runs_dir) else {
        return Scan {
            views,
            index,
            stale,
        };
    };
    let (mut reused, mut read) = (0usize, 0usize);
    for entry in dir.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if !is_valid_id(&name) {
            continue;
        }
        let path = entry.path();
        let before = stamp(&path);
        if before[0].is_none() {
            // No run.json: not a run directory (or one being made).
            continue;
        }
        if let Some(hit) = cached
            .remove(&name)
            .filter(|e| e.stamp == before && e.view.id == name && !was_driven(e.view.state))
        {
            reused += 1;
            views.push(hit.view.clone());
            index.entries.insert(name, hit);
            continue;
        }
        read += 1;
        stale = true;
        match load_run(&path, &name, true) {
            Ok((view, _)) => {
                if view.state == RunState::Interrupted {
                    tracing::warn!(run = %name, "run was active when the daemon stopped: marked interrupted (resumable)");
                }
                // Indexed only if nothing changed the files while they were
                // read; marking a run interrupted did, so it is indexed at
                // the next write.
                if stamp(&path) == before {
                    index.entries.insert(
                        name,
                        IndexEntry {
                            stamp: before,
                            view: view.clone(),
                        },
                    );
                }
                views.push(view);
            }
            Err(e) => tracing::warn!("skipping {}: {e}", path.display()),
        }
    }
    // Entries of runs that are gone.
    stale |= !cached.is_empty();
    tracing::debug!(reused, read, "run history loaded");
    Scan {
        views,
        index,
        stale,
    }
}

impl RunIndex {
    /// Brings the index up to the run directories of `ids` (every run the
    /// daemon knows but the one an engine drives): a run whose files
    /// changed since it was indexed is read again; runs not in `ids` are
    /// dropped. Returns whether anything changed.
    pub fn refresh<'a>(&mut self, runs_dir: &Path, ids: impl Iterator<Item = &'a str>) -> bool {
        let mut changed = false;
        let mut keep: HashMap<String, IndexEntry> = HashMap::new();
        for id in ids {
            if !is_valid_id(id) {
                continue;
            }
            let root = runs_dir.join(id);
            let now = stamp(&root);
            if let Some(e) = self.entries.remove(id).filter(|e| e.stamp == now) {
                keep.insert(id.to_string(), e);
                continue;
            }
            changed = true;
            // Read as it is (an active record stays active; start-up reads
            // such a run again anyway); indexed only if unchanged meanwhile.
            if let Ok((view, _)) = load_run(&root, id, false) {
                if stamp(&root) == now {
                    keep.insert(id.to_string(), IndexEntry { stamp: now, view });
                }
            }
        }
        changed |= !self.entries.is_empty();
        self.entries = keep;
        changed
    }

    /// Writes the index to `DATA/runs-index.json`, whole or not at all.
    pub fn write(&self, data_dir: &Path) -> Result<(), std::io::Error> {
        #[derive(Serialize)]
        struct Out<'a> {
            format: &'a str,
            software_version: &'a str,
            runs: &'a HashMap<String, IndexEntry>,
        }
        let json = serde_json::to_vec(&Out {
            format: INDEX_FORMAT,
            software_version: env!("CARGO_PKG_VERSION"),
            runs: &self.entries,
        })
        .map_err(std::io::Error::other)?;
        rigd_core::atomic::write(&index_path(data_dir), &json)?;
        Ok(())
    }

    /// How many runs it holds.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether it holds none.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

/// `DATA/runs-index.json`.
pub fn index_path(data_dir: &Path) -> PathBuf {
    data_dir.join(INDEX_FILE)
}
