//! The built-in plans solved for the daemon's rig. Solving a plan includes
//! its optimised trigger order: seconds of work per plan on a two-core
//! machine, more when the other core is busy. So each solved plan is also
//! kept on disk (`DATA/plan-cache/`), keyed by a digest of this build, the
//! profile and the plan, and a daemon that starts again has them at once.
//! The daemon starts loading or solving them one after another in the
//! background when it starts; a read route asks [`PlanCache::ready`], which
//! never waits, and a route that needs one plan's every step waits for that
//! plan ([`PlanCache::get`]), sharing the computation already under way
//! instead of starting another.
//!
//! The daemon is the only writer of its cache. A file that cannot be read,
//! does not parse, or does not match its plan is ignored and solved again:
//! the cache is never the source of truth.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tokio::sync::OnceCell;

use crate::model::profile::Profile;
use crate::plan::BUILTIN_PLANS;
use crate::schedule::Schedule;

/// A plan solved for the rig, or why it does not fit.
pub type Solved = Result<Arc<Schedule>, String>;

/// Folder of the solved plans in the data directory.
pub const PLAN_CACHE_DIR: &str = "plan-cache";

/// Largest cache file read back: a 6,561-image plan's is about 5 MB.
const CACHE_FILE_LIMIT: u64 = 256 << 20;

/// Every built-in plan's schedule, computed at most once.
pub struct PlanCache {
    profile: Profile,
    /// Where solved plans are kept; None keeps them in memory only.
    dir: Option<PathBuf>,
    cells: Vec<(&'static str, OnceCell<Solved>)>,
}

/// One cache file: the digest it was made for, and the schedule.
#[derive(Serialize, Deserialize)]
struct CacheFile {
    key: String,
    schedule: Schedule,
}

impl PlanCache {
    /// A cache for `profile`'s rig, kept in `dir` when given; nothing is
    /// computed yet.
    pub fn new(profile: Profile, dir: Option<PathBuf>) -> Arc<PlanCache> {
        Arc::new(PlanCache {
            profile,
            dir,
            cells: BUILTIN_PLANS
                .iter()
                .map(|&name| (name, OnceCell::new()))
                .collect(),
        })
    }

    /// Loads or solves every plan in the background, one at a time (the
    /// daemon's other work keeps a core).
    pub fn start(self: &Arc<PlanCache>) {
        let cache = self.clone();
        tokio::spawn(async move {
            for &(name, _) in &cache.cells {
                let _ = cache.get(name).await;
            }
        });
    }

    /// The plan if it is solved; `None` while it is being computed (or for
    /// a name that is not a built-in plan).
    pub fn ready(&self, name: &str) -> Option<Solved> {
        self.cell(name).and_then(|c| c.get().cloned())
    }

    /// The plan in its own (default) order, from memory, from disk, or
    /// solved now if nobody has started it, or when the solve under way
    /// finishes. `None` for a name that is not a built-in plan.
    pub async fn get(&self, name: &str) -> Option<Solved> {
        let cell = self.cell(name)?;
        let solved = cell
            .get_or_init(|| async {
                let profile = self.profile.clone();
                let plan = name.to_string();
                let dir = self.dir.clone();
                tokio::task::spawn_blocking(move || load_or_solve(&profile, &plan, dir.as_deref()))
                    .await
                    .map_err(|e| format!("solving {name} failed: {e}"))
                    .and_then(|r| r)
                    .map(Arc::new)
            })
            .await;
        Some(solved.clone())
    }

    fn cell(&self, name: &str) -> Option<&OnceCell<Solved>> {
        self.cells.iter().find(|(n, _)| *n == name).map(|(_, c)| c)
    }
}

/// What a cached schedule depends on: this build of rigd (a new build may
/// solve differently), the whole profile, and the plan's name.
fn cache_key(profile: &Profile, plan: &str) -> String {
    let build = std::env::current_exe()
        .and_then(std::fs::metadata)
        .map(|m| {
            let modified = m
                .modified()
                .ok()
                .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                .map_or(0, |d| d.as_nanos());
            format!("{}:{modified}", m.len())
        })
        .unwrap_or_default();
    let mut hash = Sha256::new();
    for part in [
        env!("CARGO_PKG_VERSION").to_string(),
        build,
        serde_json::to_string(profile).unwrap_or_default(),
        plan.to_string(),
    ] {
        hash.update(part.len().to_le_bytes());
        hash.update(part.as_bytes());
    }
    hex::encode(hash.finalize())
}

/// The cached schedule of `plan` if `dir` holds a sound one, else the plan
/// solved now and written there.
fn load_or_solve(profile: &Profile, plan: &str, dir: Option<&Path>) -> Result<Schedule, String> {
    let key = cache_key(profile, plan);
    let file = dir.map(|d| d.join(format!("{}-{}.json", plan, &key[..16])));
    if let Some(file) = &file {
        match read_cached(file, &key, profile, plan) {
            Ok(Some(schedule)) => return Ok(schedule),
            Ok(None) => {}
            Err(why) => tracing::warn!(
                "ignoring the cached plan {}: {why}; solving it again",
                file.display()
            ),
        }
    }
    let (_, _, schedule) =
        crate::engine::launch::solve_plan(profile, plan, None).map_err(|e| e.to_string())?;
    if let Some(file) = &file {
        if let Err(e) = write_cached(file, &key, &schedule) {
            tracing::warn!("cannot keep the solved plan in {}: {e}", file.display());
        }
    }
    Ok(schedule)
}

/// A cached schedule, checked against what it claims to be: None when
/// there is no file, an error when it is unusable.
fn read_cached(
    file: &Path,
    key: &str,
    profile: &Profile,
    plan: &str,
) -> Result<Option<Schedule>, String> {
    let bytes = match rigd_core::read::read_bounded(file, CACHE_FILE_LIMIT) {
        Ok(b) => b,
        Err(e) if e.io_kind() == Some(std::io::ErrorKind::NotFound) => return Ok(None),
        Err(e) => return Err(e.to_string()),
    };
    let cached: CacheFile = serde_json::from_slice(&bytes).map_err(|e| e.to_string())?;
    if cached.key != key {
        return Err("made for another build, profile or plan".into());
    }
    let schedule = cached.schedule;
    let (_, resolved) =
        crate::engine::launch::resolve_plan(profile, plan, None).map_err(|e| e.to_string())?;
    let indexed = schedule
        .images
        .iter()
        .enumerate()
        .all(|(i, im)| im.index == i);
    if schedule.plan != resolved.name
        || schedule.profile != profile.name
        || schedule.images.len() != resolved.pairs.len()
        || !indexed
    {
        return Err(format!(
            "it holds {} images of `{}` for `{}`, not the {} of `{}` for `{}`",
            schedule.images.len(),
            schedule.plan,
            schedule.profile,
            resolved.pairs.len(),
            resolved.name,
            profile.name
        ));
    }
    Ok(Some(schedule))
}

fn write_cached(file: &Path, key: &str, schedule: &Schedule) -> Result<(), String> {
    if let Some(dir) = file.parent() {
        std::fs::create_dir_all(dir).map_err(|e| e.to_string())?;
    }
    let bytes = serde_json::to_vec(&CacheFile {
        key: key.to_string(),
        schedule: schedule.clone(),
    })
    .map_err(|e| e.to_string())?;
    rigd_core::atomic::write(file, &bytes).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn virtex() -> Profile {
        crate::plan::load_profile("virtex-photometric-stereo").unwrap_or_else(|e| panic!("{e}"))
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn reads_never_wait_and_each_plan_is_solved_once() {
        let cache = PlanCache::new(virtex(), None);
        // Nothing started: a read answers at once, with nothing.
        assert!(cache.ready("lamps").is_none());
        assert!(cache.get("no-such-plan").await.is_none());
        let a = cache.get("lamps").await.and_then(Result::ok);
        let b = cache.ready("lamps").and_then(Result::ok);
        match (a, b) {
            (Some(a), Some(b)) => assert!(Arc::ptr_eq(&a, &b), "solved twice"),
            other => panic!("lamps did not solve: {other:?}"),
        }
        // A plan that does not fit this rig is an answer too.
        let h1 = cache.get("grid12x8").await;
        assert!(matches!(h1, Some(Err(_))), "{h1:?}");
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_solved_plan_is_read_back_from_disk_and_a_bad_file_is_solved_again() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let solved = PlanCache::new(virtex(), Some(dir.path().to_path_buf()))
            .get("lamps")
            .await
            .and_then(Result::ok)
            .unwrap_or_else(|| panic!("lamps did not solve"));
        let files: Vec<PathBuf> = std::fs::read_dir(dir.path())
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.path())
            .collect();
        assert_eq!(files.len(), 1, "{files:?}");
        // A second daemon reads it back: the same schedule.
        let again = PlanCache::new(virtex(), Some(dir.path().to_path_buf()))
            .get("lamps")
            .await
            .and_then(Result::ok);
        assert_eq!(again.as_deref(), Some(&*solved));

        // Damaged, truncated, or another plan's schedule under its name:
        // ignored, solved again, and the file made sound.
        let other_plan = {
            let mut s = (*solved).clone();
            s.images.pop();
            serde_json::to_vec(&CacheFile {
                key: cache_key(&virtex(), "lamps"),
                schedule: s,
            })
            .unwrap_or_default()
        };
        for bad in [b"{not json".to_vec(), Vec::new(), other_plan] {
            std::fs::write(&files[0], &bad).unwrap_or_else(|e| panic!("{e}"));
            let again = PlanCache::new(virtex(), Some(dir.path().to_path_buf()))
                .get("lamps")
                .await
                .and_then(Result::ok);
            assert_eq!(again.as_deref(), Some(&*solved));
            let rewritten = std::fs::read(&files[0]).unwrap_or_default();
            assert_ne!(rewritten, bad, "the bad file was left as it was");
        }
    }
}
