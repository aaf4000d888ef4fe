//! The built-in plans solved for the daemon's rig. Solving a plan includes
//! its optimised trigger order: seconds of work per plan on a two-core
//! machine, more when the other core is busy. The daemon starts solving
//! them one after another in the background when it starts; a read route
//! asks [`PlanCache::ready`], which never waits, and only a route that needs
//! one plan's every step waits for that plan ([`PlanCache::get`]), sharing
//! the computation already under way instead of starting another.

use std::sync::Arc;

use tokio::sync::OnceCell;

use crate::model::profile::Profile;
use crate::plan::BUILTIN_PLANS;
use crate::schedule::Schedule;

/// A plan solved for the rig, or why it does not fit.
pub type Solved = Result<Arc<Schedule>, String>;

/// Every built-in plan's schedule, computed at most once.
pub struct PlanCache {
    profile: Profile,
    cells: Vec<(&'static str, OnceCell<Solved>)>,
}

impl PlanCache {
    /// A cache for `profile`'s rig; nothing is computed yet.
    pub fn new(profile: Profile) -> Arc<PlanCache> {
        Arc::new(PlanCache {
            profile,
            cells: BUILTIN_PLANS
                .iter()
                .map(|&name| (name, OnceCell::new()))
                .collect(),
        })
    }

    /// Solves every plan in the background, one at a time (the daemon's
    /// other work keeps a core).
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

    /// The plan, solved now if nobody has started it, or when the solve
    /// under way finishes. `None` for a name that is not a built-in plan.
    pub async fn get(&self, name: &str) -> Option<Solved> {
        let cell = self.cell(name)?;
        let solved = cell
            .get_or_init(|| async {
                let profile = self.profile.clone();
                let plan = name.to_string();
                tokio::task::spawn_blocking(move || {
                    crate::engine::launch::solve_plan(&profile, &plan, None)
                })
                .await
                .map_err(|e| format!("solving {name} failed: {e}"))
                .and_then(|r| r.map_err(|e| e.to_string()))
                .map(|(_, _, schedule)| Arc::new(schedule))
            })
            .await;
        Some(solved.clone())
    }

    fn cell(&self, name: &str) -> Option<&OnceCell<Solved>> {
        self.cells.iter().find(|(n, _)| *n == name).map(|(_, c)| c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn reads_never_wait_and_each_plan_is_solved_once() {
        let profile = crate::plan::load_profile("virtex-photometric-stereo")
            .unwrap_or_else(|e| panic!("{e}"));
        let cache = PlanCache::new(profile);
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
}
