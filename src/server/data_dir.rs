//! What the daemon keeps in its data directory besides the run directories:
//! the queue (`queue.json`, written atomically), and the run history, which
//! is read back from `runs/*/` at startup (through the run index,
//! `super::run_index`).

use std::collections::BTreeSet;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::wire::{QueueItem, RunView};
use crate::model::run_state::RunState;
use crate::model::text::sanitize;
use crate::store::{
    check_manifest, mark_interrupted, read_journal, read_state, write_atomic, FrameEntry, RunMeta,
    StateRecord, StoreError, JOURNAL_FILE, MANIFEST_FILE, RUN_FILE,
};

/// The queue's file in the data directory.
pub const QUEUE_FILE: &str = "queue.json";
/// The folder of the data directory that holds one run directory per run id.
pub const RUNS_DIR: &str = "runs";
const QUEUE_FORMAT: &str = "rigd-queue/1";

/// Why a run was marked interrupted at startup.
pub const INTERRUPTED_REASON: &str =
    "the daemon stopped while this run was active; POST /api/v1/runs/{id}/resume continues it";

#[derive(Debug, Serialize, Deserialize)]
struct QueueFile {
    format: String,
    items: Vec<QueueItem>,
}

/// Loads the queue; a missing file is an empty queue, an unreadable one is
/// moved aside (`queue.json.bad`) with a warning.
pub fn load_queue(data: &Path) -> Vec<QueueItem> {
    let path = data.join(QUEUE_FILE);
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Vec::new(),
        Err(e) => {
            tracing::warn!(
                "cannot read {}: {e}; starting with an empty queue",
                path.display()
            );
            return Vec::new();
        }
    };
    match serde_json::from_slice::<QueueFile>(&bytes) {
        Ok(q) => q.items,
        Err(e) => {
            let aside = data.join("queue.json.bad");
            tracing::warn!(
                "{} is not a queue ({e}); moved to {}, starting with an empty queue",
                path.display(),
                aside.display()
            );
            let _ = std::fs::rename(&path, aside);
            Vec::new()
        }
    }
}

/// Writes the queue atomically (temporary file, fsync, rename).
pub fn save_queue(data: &Path, items: &[QueueItem]) -> Result<(), StoreError> {
    let file = QueueFile {
        format: QUEUE_FORMAT.into(),
        items: items.to_vec(),
    };
    let json = serde_json::to_vec_pretty(&file).map_err(|e| StoreError::Corrupt {
        path: data.join(QUEUE_FILE),
        why: e.to_string(),
    })?;
    write_atomic(&data.join(QUEUE_FILE), &json)
}

/// A run id is only ever made here, and only these characters pass.
pub fn is_valid_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= 128
        && !id.starts_with('.')
        && id.chars().all(crate::model::text::is_file_name_char)
}

/// A new run id: `YYYYMMDDTHHMMSSZ-SAMPLE-PLAN`, with `-N` added when taken.
pub fn new_run_id(
    runs_dir: &Path,
    sample: &str,
    plan: &str,
    taken: &dyn Fn(&str) -> bool,
) -> String {
    let stamp = humantime::format_rfc3339_seconds(std::time::SystemTime::now())
        .to_string()
        .replace(['-', ':'], "");
    let base = format!("{stamp}-{}-{}", sanitize(sample, 40), sanitize(plan, 24));
    let mut id = base.clone();
    let mut n = 2;
    while taken(&id) || runs_dir.join(&id).exists() {
        id = format!("{base}-{n}");
        n += 1;
    }
    id
}

/// Frame indices journaled in a run directory, read through the store's
/// reader (which never writes; a torn last line is not there yet); empty
/// when the journal cannot be read.
pub fn journaled(root: &Path) -> BTreeSet<usize> {
    read_journal(&root.join(JOURNAL_FILE))
        .map(|(entries, _)| entries.iter().map(|e| e.index).collect())
        .unwrap_or_default()
}

/// What is wrong with an ended run's record of its frames, for its view:
/// a journal that cannot be read, or one that disagrees with the manifest
/// (or a manifest that does not parse or is missing). None for a sound run.
fn record_problem(root: &Path, journal: &Result<Vec<FrameEntry>, StoreError>) -> Option<String> {
    let check = match journal {
        Ok(entries) => check_manifest(root, entries),
        Err(e) => return Some(e.to_string()),
    };
    check.err().map(|e| e.to_string())
}

/// The parts of `manifest.json` the run list needs.
#[derive(Debug, Deserialize)]
struct ManifestHead {
    finished_at: String,
    #[serde(default)]
    physical_duration_s: f64,
}

/// Reads one run directory into a view (not active). With `mark_stale`
/// (the scan at start-up), a run that was preparing or running, whose
/// driver therefore died (no writer holds it), is marked `interrupted` in
/// its `state.json`;
/// without it (a run the daemon itself is starting or has just ended) the
/// record is read as it is.
pub fn load_run(root: &Path, id: &str, mark_stale: bool) -> Result<(RunView, RunMeta), StoreError> {
    let run_path = root.join(RUN_FILE);
    let bytes = std::fs::read(&run_path).map_err(|e| StoreError::Corrupt {
        path: run_path.clone(),
        why: e.to_string(),
    })?;
    let meta: RunMeta = serde_json::from_slice(&bytes).map_err(|e| StoreError::Corrupt {
        path: run_path.clone(),
        why: e.to_string(),
    })?;
    let mut state = read_state(root)?;
    // A run directory being created has no journal yet: no frames.
    let journal_path = root.join(JOURNAL_FILE);
    let journal = match journal_path.exists() {
        true => read_journal(&journal_path).map(|(entries, _)| entries),
        false => Ok(Vec::new()),
    };
    let problem = record_problem(root, &journal);
    let done: BTreeSet<usize> = journal.iter().flatten().map(|e| e.index).collect();
    let stale = state
        .as_ref()
        .is_none_or(|s| s.state.is_active() || s.state == RunState::Idle);
    // A run another process is writing (a `rigd run` into this folder) is
    // not stale: its writer alone may change its record.
    if stale && mark_stale && !crate::store::WriterLock::is_held(root) {
        let reason = INTERRUPTED_REASON.replace("{id}", id);
        state = Some(mark_interrupted(root, state.as_ref(), &reason)?);
    }
    let manifest: Option<ManifestHead> = std::fs::read(root.join(MANIFEST_FILE))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok());
    let view = view_of(
        id,
        &meta,
        state.as_ref(),
        done.len(),
        manifest.map(|m| (m.physical_duration_s, m.finished_at)),
        problem,
    );
    Ok((view, meta))
}

/// The view of run `id` from its metadata, its state record, how many
/// images it has journaled, for an ended run the physical time and end
/// time its manifest gives, and what is wrong with its record of the
/// frames, if anything.
pub fn view_of(
    id: &str,
    meta: &RunMeta,
    state: Option<&StateRecord>,
    steps_done: usize,
    ended: Option<(f64, String)>,
    problem: Option<String>,
) -> RunView {
    let run_state = state.map_or(RunState::Idle, |s| s.state);
    let resumable = run_state.is_resumable();
    RunView {
        id: id.to_string(),
        sample: meta.sample.clone(),
        plan: meta.plan.name.clone(),
        profile: meta.profile.name.clone(),
        operator: meta.operator.clone(),
        notes: meta.notes.clone(),
        state: run_state,
        reason: state.and_then(|s| s.reason.clone()),
        // A damaged record of the frames outweighs the last fault.
        last_error: problem.or_else(|| {
            state
                .filter(|s| matches!(s.state, RunState::Failed | RunState::Paused))
                .and_then(|s| s.reason.clone())
                .filter(|r| is_error_reason(r))
        }),
        active: false,
        resumable,
        steps_done,
        steps_total: images_in_plan(meta),
        physical_s: ended
            .as_ref()
            .map(|(physical_s, _)| *physical_s)
            .or(state.map(|s| s.physical_s))
            .unwrap_or(0.0),
        eta_physical_s: None,
        eta_wall_s: None,
        exposure_s: meta.exposure_s,
        frame_size: meta.frame_size,
        started_at: meta.started_at.clone(),
        updated_at: state.map(|s| s.updated_at.clone()),
        finished_at: ended.map(|(_, finished_at)| finished_at),
        processed: None,
        processing: None,
        pace: None,
    }
}

/// Images in a run's plan: one per pair, or for a laser plan every frame of
/// its calibrations and sweeps (a laser plan has no pairs).
fn images_in_plan(meta: &RunMeta) -> usize {
    match &meta.plan.laser {
        Some(laser) => crate::plan::laser::LaserRig::of(&meta.profile).map_or(0, |rig| {
            crate::schedule::laser::schedule(&rig, &meta.plan.name, &meta.profile.name, laser)
                .images
                .len()
        }),
        None => meta.plan.pairs.len(),
    }
}

/// Whether a pause or end reason is an error (not the operator's doing).
pub fn is_error_reason(reason: &str) -> bool {
    !(reason.starts_with("paused by operator")
        || reason.starts_with("detached")
        || reason.starts_with("aborted by operator"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::server::wire::{PlanSpec, RunRequest};

    #[test]
    fn ids_are_filesystem_safe() {
        assert_eq!(sanitize("Felt #3 / blue", 40), "Felt__3___blue");
        assert_eq!(sanitize("../../etc", 40), "______etc");
        assert_eq!(sanitize("", 40), "x");
        assert_eq!(sanitize("ü", 40), "_");
        assert_eq!(sanitize(&"a".repeat(100), 40).len(), 40);
        for bad in [
            "", ".", "..", "../x", "a/b", "a\\b", ".hidden", "a b", "a\0",
        ] {
            assert!(!is_valid_id(bad), "{bad:?}");
        }
        assert!(is_valid_id("20260101T000000Z-felt-h1-2"));
        let dir = tempfile::tempdir().expect("tempdir");
        let a = new_run_id(dir.path(), "../x y", "h1", &|_| false);
        assert!(is_valid_id(&a), "{a}");
        assert!(a.ends_with("-___x_y-h1"), "{a}");
        let b = new_run_id(dir.path(), "../x y", "h1", &|id| id == a);
        assert_eq!(b, format!("{a}-2"));
    }

    #[test]
    fn the_queue_round_trips_and_a_bad_file_is_moved_aside() {
        let dir = tempfile::tempdir().expect("tempdir");
        assert!(load_queue(dir.path()).is_empty());
        let item = QueueItem {
            id: "q1".into(),
            request: RunRequest {
                sample: "s".into(),
                plan: PlanSpec::Name("h1".into()),
                operator: None,
                notes: Some("n".into()),
                exposure_s: Some(0.5),
                exposure_policy: Some(crate::model::exposure::ExposurePolicy::Brackets {
                    exposures_s: vec![0.5, 0.1],
                }),
                frame_size: Some([8, 8]),
                order: Some(crate::plan::Order::Naive),
                process: None,
            },
            created_at: "2026-01-01T00:00:00Z".into(),
        };
        save_queue(dir.path(), std::slice::from_ref(&item)).expect("save");
        let back = load_queue(dir.path());
        assert_eq!(back.len(), 1);
        assert_eq!(back[0].id, "q1");
        assert_eq!(back[0].request.exposure_s, Some(0.5));
        std::fs::write(dir.path().join(QUEUE_FILE), b"{torn").expect("write");
        assert!(load_queue(dir.path()).is_empty());
        assert!(dir.path().join("queue.json.bad").exists());
    }

    /// A laser plan has no (light, view) pairs: its image count comes from
    /// its sweeps, so frames of a laser run stay reachable after a restart.
    #[test]
    fn a_laser_run_read_back_counts_its_frames() {
        let profile = crate::plan::load_profile("msra-btf-mdf").unwrap_or_else(|e| panic!("{e}"));
        let spec = "laser:sources=2,turns=1";
        let (_, plan, schedule) = crate::engine::launch::solve_plan(&profile, spec, None)
            .unwrap_or_else(|e| panic!("{e}"));
        let meta = RunMeta {
            format: crate::store::RUN_FORMAT.into(),
            software_version: "test".into(),
            profile: profile.clone(),
            profile_source: "msra-btf-mdf".into(),
            plan,
            sample: "s".into(),
            operator: None,
            notes: None,
            exposure_s: None,
            exposure_policy: Default::default(),
            frame_size: None,
            simulated: true,
            sim_scene: None,
            started_at: crate::store::now_rfc3339(),
        };
        let dir = tempfile::tempdir().expect("tempdir");
        let root = dir.path().join("run");
        let writer = crate::store::RunDir::create(&root, &meta).expect("create");
        // While its writer (another process, as far as the scan can tell)
        // holds it, the run is not stale and its record is left alone.
        let (view, _) = load_run(&root, "run", true).expect("load");
        assert_ne!(view.state, RunState::Interrupted, "its writer holds it");
        assert!(!root.join(crate::store::STATE_FILE).exists());
        drop(writer);
        let (view, _) = load_run(&root, "run", true).expect("load");
        assert!(!schedule.images.is_empty());
        assert_eq!(view.steps_total, schedule.images.len());
        assert_eq!(view.state, RunState::Interrupted, "nobody drives it");
        let (view, _) = load_run(&root, "run", false).expect("load");
        assert_eq!(view.state, RunState::Interrupted, "the record as it is");
    }
}
