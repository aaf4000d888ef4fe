//! The daemon's state and run supervisor: the run history, the one active
//! run (its engine handle and simulated rig), and the queue.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::{broadcast, watch};
use tokio::task::JoinHandle;

use super::data_dir::{self, RUNS_DIR};
use super::error::SupervisorError;
use super::events::EventHub;
use super::history::RunHistory;
use super::plan_cache::PlanCache;
use super::wire::{PaceView, PlanSpec, QueueItem, RunRequest, RunView};
use super::ServerConfig;
use crate::engine::command::{check_command, Command};
use crate::engine::launch::{self, NewRun, Prepared, RunError};
use crate::engine::{EngineError, EngineHandle, EventKind, Outcome, PausePolicy, RunEvent};
use crate::model::profile::Profile;
use crate::model::run_state::RunState;
use crate::plan::{self, BUILTIN_PLANS};
use crate::rig::SimHandle;
use crate::schedule::Schedule;
use rigd_core::pace::{Pace, PacedRuntime};
use rigd_core::sync::lock;
use rigd_core::Clock;

/// The run an engine drives.
pub struct Active {
    /// The run's id.
    pub id: String,
    /// Commands, events and the emergency stop of the run's engine.
    pub handle: EngineHandle,
    /// The simulated rig's world and faults (None on hardware).
    pub sim: Option<SimHandle>,
    /// The engine's state, as of its latest state event.
    pub state: RunState,
    /// The last command sent to the engine since that event: the same
    /// command again is already on its way, and is not sent twice.
    pub pending: Option<Command>,
    /// Physical time at which the run should end (t_offset + estimate).
    pub end_estimate_s: f64,
    /// The asked and achieved speed of a simulated run's paced virtual
    /// time (None on hardware).
    pub pace: Option<Arc<Pace>>,
}

/// The daemon's mutable state, under one lock ([`Daemon::inner`]).
#[derive(Default)]
pub struct Inner {
    /// Every known run, the active one included: the run history, in the
    /// list's order.
    pub runs: RunHistory,
    /// The run an engine drives now; None when the rig is free.
    pub active: Option<Active>,
    /// Queued runs, in the order they will start (kept in `queue.json`).
    pub queue: Vec<QueueItem>,
    /// Set when shutdown begins: from then on no run starts.
    pub shutting_down: bool,
    /// The rig of the last run, for positions after it ended.
    pub last_sim: Option<SimHandle>,
    queue_seq: u64,
}

/// Everything the handlers share.
pub struct Daemon {
    /// How the daemon was started.
    pub config: ServerConfig,
    /// The rig profile every run of this daemon uses.
    pub profile: Profile,
    /// Where the profile came from (a path, or `<embedded NAME>`).
    pub profile_source: String,
    /// The event stream the handlers and the runs publish to.
    pub hub: EventHub,
    /// The data directory.
    pub data_dir: PathBuf,
    /// `DATA/runs/`: one run directory per run id.
    pub runs_dir: PathBuf,
    inner: Mutex<Inner>,
    /// Serialises starting runs (prepare happens outside `inner`'s lock).
    pub(crate) start_gate: tokio::sync::Mutex<()>,
    /// Woken when a run's engine has ended and the rig is free again.
    run_ended: tokio::sync::Notify,
    /// The manual-control rig, between manual actions.
    pub manual: super::manual_session::ManualSession,
    supervisor: Mutex<Option<JoinHandle<()>>>,
    /// Turns true at the end of shutdown (the engine stopped, or 60 s
    /// passed): the event streams end and the HTTP server stops.
    pub shutdown_tx: watch::Sender<bool>,
    schedules: Mutex<HashMap<String, Arc<Schedule>>>,
    /// The built-in plans solved for this rig, in the background.
    pub plans: Arc<PlanCache>,
    /// A trade-off report is being computed (`POST /api/v1/tradeoff`).
    pub tradeoff_busy: std::sync::atomic::AtomicBool,
    /// The process jobs (`POST /api/v1/runs/{id}/process`) and their worker.
    pub jobs: super::jobs::Jobs,
    /// The other rigs' daemons (`--peers FILE`) and what each last answered.
    pub peers: Arc<super::peers::Peers>,
    /// The data directory's history id, which run-list cursors carry
    /// (`DATA/history-id`).
    pub history_id: String,
    /// The run index (`DATA/runs-index.json`) as last written; its lock
    /// also serialises the writes.
    run_index: Mutex<super::run_index::RunIndex>,
}

/// Longest a start waits for a run that has reported its final state to
/// close (its files and its paced runtime): far longer than that takes.
const ENDING_GRACE: Duration = Duration::from_secs(10);

/// Most characters a sample, operator name or plan name may have.
const MAX_NAME: usize = crate::model::text::MAX_NAME_CHARS;
const MAX_NOTES: usize = 8192;

fn run_error(e: RunError) -> SupervisorError {
    match e {
        RunError::Store(s) => SupervisorError::internal(s.to_string()),
        other => SupervisorError::invalid(other.to_string()),
    }
}

impl Daemon {
    /// Opens the data directory: creates `runs/`, reads the run history
    /// (marking runs found active as interrupted) and the queue, and starts
    /// solving the built-in plans in the background.
    pub fn new(
        config: ServerConfig,
        profile: Profile,
        profile_source: String,
    ) -> Result<Arc<Daemon>, super::ServerError> {
        let data_dir = config.data_dir.clone();
        let runs_dir = data_dir.join(RUNS_DIR);
        std::fs::create_dir_all(&runs_dir).map_err(|e| super::ServerError::DataDir {
            path: runs_dir.clone(),
            why: e.to_string(),
        })?;
        let history_id =
            super::history::history_id(&data_dir).map_err(|e| super::ServerError::DataDir {
                path: data_dir.join(super::history::HISTORY_ID_FILE),
                why: e.to_string(),
            })?;
        let mut inner = Inner::default();
        let scan = super::run_index::scan(&data_dir, &runs_dir);
        for view in scan.views {
            inner.runs.insert(view);
        }
        if scan.stale {
            // Written now so that the next start finds it even if this
            // daemon is killed before any run ends.
            if let Err(e) = scan.index.write(&data_dir) {
                tracing::warn!("cannot write the run index: {e}");
            }
        }
        inner.queue = data_dir::load_queue(&data_dir);
        let jobs = super::jobs::Jobs::load(&runs_dir, inner.runs.keys());
        let (shutdown_tx, _) = watch::channel(false);
        let plans = PlanCache::new(
            profile.clone(),
            Some(data_dir.join(super::plan_cache::PLAN_CACHE_DIR)),
        );
        let peers = Arc::new(super::peers::Peers::new(&config.peers));
        plans.start();
        Ok(Arc::new(Daemon {
            config,
            profile,
            profile_source,
            hub: EventHub::new(),
            data_dir,
            runs_dir,
            inner: Mutex::new(inner),
            start_gate: tokio::sync::Mutex::new(()),
            run_ended: tokio::sync::Notify::new(),
            manual: Default::default(),
            supervisor: Mutex::new(None),
            shutdown_tx,
            tradeoff_busy: std::sync::atomic::AtomicBool::new(false),
            schedules: Mutex::new(HashMap::new()),
            plans,
            jobs,
            peers,
            history_id,
            run_index: Mutex::new(scan.index),
        }))
    }

    /// Brings the run index up to the run directories and writes it, if
    /// anything changed. It is written at start-up, when a run ends or is
    /// aborted without an engine, and at shutdown, not on every engine
    /// event: a run's record changes on every frame, and only the next
    /// start-up reads the index, which checks every entry against the
    /// files anyway (a run changed after the last write is just read).
    /// Blocking: it stats every run's files.
    pub fn save_run_index(&self) {
        let mut index = lock(&self.run_index);
        let ids: Vec<String> = {
            let inner = self.inner();
            let active = inner.active.as_ref().map(|a| a.id.as_str());
            inner
                .runs
                .keys()
                .filter(|id| Some(id.as_str()) != active)
                .cloned()
                .collect()
        };
        if index.refresh(&self.runs_dir, ids.iter().map(String::as_str)) {
            if let Err(e) = index.write(&self.data_dir) {
                tracing::warn!("cannot write the run index: {e}");
            }
        }
    }

    /// [`Daemon::save_run_index`] on a blocking thread.
    fn save_run_index_soon(self: &Arc<Self>) {
        let d = self.clone();
        tokio::task::spawn_blocking(move || d.save_run_index());
    }

    /// Locks the daemon's mutable state (taken over even if a holder panicked).
    pub fn inner(&self) -> MutexGuard<'_, Inner> {
        lock(&self.inner)
    }

    /// Physical seconds per wall second: the simulation's speed, or 1 on
    /// hardware.
    pub fn speed(&self) -> f64 {
        if self.config.sim {
            self.config.sim_speed
        } else {
            1.0
        }
    }

    pub(crate) fn clock(&self) -> Clock {
        if self.config.sim {
            Clock::scaled(self.config.sim_speed)
        } else {
            Clock::real()
        }
    }

    /// A run's view with live ETA.
    pub fn view(&self, id: &str) -> Option<RunView> {
        self.inner().runs.get(id).cloned()
    }

    /// The directory of run `id`; None unless `id` is a well-formed id of a
    /// known run, so no path is built from unchecked input.
    pub fn run_root(&self, id: &str) -> Option<PathBuf> {
        if !data_dir::is_valid_id(id) || !self.inner().runs.contains_key(id) {
            return None;
        }
        Some(self.runs_dir.join(id))
    }

    /// Checks a request and resolves its plan (built-in names or inline only).
    pub fn validate(&self, req: &RunRequest) -> Result<plan::Plan, SupervisorError> {
        crate::model::text::check_name(&req.sample)
            .map_err(|why| SupervisorError::invalid(format!("`sample` {why}")))?;
        if let Some(op) = &req.operator {
            if op.chars().count() > MAX_NAME || op.chars().any(char::is_control) {
                return Err(SupervisorError::invalid(format!(
                    "`operator`: at most {MAX_NAME} characters, no control characters"
                )));
            }
        }
        if let Some(n) = &req.notes {
            if n.chars().count() > MAX_NOTES {
                return Err(SupervisorError::invalid(format!(
                    "`notes`: at most {MAX_NOTES} characters"
                )));
            }
        }
        if let Some(e) = req.exposure_s {
            self.profile
                .check_exposure_override(e)
                .map_err(|why| SupervisorError::invalid(format!("`exposure_s` {why}")))?;
        }
        if let Some(policy) = &req.exposure_policy {
            self.profile
                .check_exposure_policy(policy, req.exposure_s)
                .map_err(|(key, why)| {
                    SupervisorError::invalid(format!("`exposure_policy.{key}`: {why}"))
                })?;
        }
        if let Some([w, h]) = req.frame_size {
            if !(1..=4096).contains(&w) || !(1..=4096).contains(&h) {
                return Err(SupervisorError::invalid(
                    "`frame_size`: [width, height], each between 1 and 4096",
                ));
            }
        }
        let plan = self.resolve_plan(req)?;
        if let Some(options) = &req.process {
            self.process_after_capture(req, &plan, options.clone())?;
        }
        Ok(plan)
    }

    /// The checked options of a run's `process` field.
    fn process_after_capture(
        &self,
        req: &RunRequest,
        plan: &plan::Plan,
        options: crate::postprocess::pipeline::ProcessOptions,
    ) -> Result<crate::postprocess::pipeline::ProcessOptions, SupervisorError> {
        use crate::postprocess::pipeline::{check_frame_size, ProcessStep, RunFacts};
        let options = options
            .resolve(&RunFacts::of_plan(plan))
            .map_err(|e| SupervisorError::invalid(format!("`process`: {e}")))?;
        let size = req
            .frame_size
            .or(self.config.sim.then_some(self.profile.sim.frame_size));
        if let (true, Some(size)) = (options.steps.contains(&ProcessStep::Rectify), size) {
            check_frame_size(size)
                .map_err(|e| SupervisorError::invalid(format!("`process`: {e}")))?;
        }
        Ok(options)
    }

    fn resolve_plan(&self, req: &RunRequest) -> Result<plan::Plan, SupervisorError> {
        match &req.plan {
            PlanSpec::Name(name) => {
                if !BUILTIN_PLANS.contains(&name.as_str()) && !name.starts_with("laser:") {
                    return Err(SupervisorError::invalid(format!(
                        "unknown plan `{}` (expected one of {}, or an inline plan object)",
                        name.chars().take(64).collect::<String>(),
                        BUILTIN_PLANS.join(", ")
                    )));
                }
                let (_, plan) =
                    launch::resolve_plan(&self.profile, name, req.order).map_err(run_error)?;
                Ok(plan)
            }
            PlanSpec::Inline(p) => {
                if let Some(n) = &p.name {
                    if n.is_empty() || n.chars().count() > MAX_NAME {
                        return Err(SupervisorError::invalid(format!(
                            "plan `name` must have 1 to {MAX_NAME} characters"
                        )));
                    }
                }
                let value = serde_json::to_value(p)
                    .map_err(|e| SupervisorError::internal(e.to_string()))?;
                let mut plan = plan::from_json_value(value, "inline plan", "custom")
                    .map_err(|e| SupervisorError::invalid(e.to_string()))?;
                if let Some(o) = req.order {
                    plan.order = o;
                }
                Ok(plan)
            }
        }
    }

    /// Waits, at most [`ENDING_GRACE`], while the active run's engine has
    /// reported its final state but not yet closed the run: a client that
    /// saw `completed` and starts the next run at once gets the rig rather
    /// than a 409. Called with the start gate held.
    async fn settle_ending_run(&self) {
        let deadline = tokio::time::Instant::now() + ENDING_GRACE;
        loop {
            let ended = self.run_ended.notified();
            tokio::pin!(ended);
            ended.as_mut().enable();
            let ending = self
                .inner()
                .active
                .as_ref()
                .is_some_and(|a| a.state.ends_session());
            if !ending || tokio::time::timeout_at(deadline, ended).await.is_err() {
                return;
            }
        }
    }

    fn conflict_active(inner: &Inner) -> Option<SupervisorError> {
        inner.active.as_ref().map(|a| {
            SupervisorError::conflict(format!(
                "run {} is active ({}); pause/abort it or queue this run with POST /api/v1/queue",
                a.id, a.state
            ))
        })
    }

    /// `rig check` on the daemon's rig (simulated or hardware): every
    /// device connected and reported, nothing moved. 409 while a run holds
    /// the rig; a run started meanwhile waits until the check is done.
    pub async fn check_rig(
        self: &Arc<Self>,
    ) -> Result<crate::rig::check::RigCheck, SupervisorError> {
        let _gate = self.start_gate.lock().await;
        self.settle_ending_run().await;
        if let Some(e) = Self::conflict_active(&self.inner()) {
            return Err(e);
        }
        // The check opens every port itself.
        self.manual.release().await;
        let clock = self.clock();
        if !self.config.sim {
            return Ok(crate::rig::hardware::check(&self.profile, &clock).await);
        }
        #[cfg(feature = "sim")]
        {
            let solver = crate::kinematics::Solver::new(&self.profile)
                .map_err(|e| SupervisorError::internal(e.to_string()))?;
            crate::rig::sim::check(&self.profile, Arc::new(solver), &clock)
                .await
                .map_err(|e| SupervisorError::internal(e.to_string()))
        }
        #[cfg(not(feature = "sim"))]
        Err(SupervisorError::unavailable(
            "this rigd was built without the simulator",
        ))
    }

    /// Starts a new run now; 409 if one is active.
    pub async fn start_run(self: &Arc<Self>, req: RunRequest) -> Result<RunView, SupervisorError> {
        let gate = self.start_gate.lock().await;
        self.start_run_gated(req, &gate).await
    }

    /// [`Self::start_run`] for a caller that holds the start gate, so that
    /// what it decided before (which queued item goes next) still holds.
    async fn start_run_gated(
        self: &Arc<Self>,
        req: RunRequest,
        _gate: &tokio::sync::MutexGuard<'_, ()>,
    ) -> Result<RunView, SupervisorError> {
        let plan = self.validate(&req)?;
        // Processing during the capture compresses view slots as they
        // complete, which an order left to the default can favour.
        let prefer_slots = req.order.is_none()
            && match &req.process {
                Some(o) => self
                    .process_after_capture(&req, &plan, o.clone())?
                    .steps
                    .contains(&crate::postprocess::pipeline::ProcessStep::Btf),
                None => false,
            };
        self.settle_ending_run().await;
        {
            let inner = self.inner();
            if inner.shutting_down {
                return Err(SupervisorError::unavailable("the daemon is shutting down"));
            }
            if let Some(e) = Self::conflict_active(&inner) {
                return Err(e);
            }
        }
        self.manual.release().await;
        let id = {
            let inner = self.inner();
            data_dir::new_run_id(&self.runs_dir, &req.sample, &plan.name, &|id| {
                inner.runs.contains_key(id)
            })
        };
        let root = self.runs_dir.join(&id);
        let new = NewRun {
            profile: self.profile.clone(),
            profile_source: self.profile_source.clone(),
            plan: plan.name.clone(),
            sample: req.sample.clone(),
            operator: req.operator.clone(),
            notes: req.notes.clone(),
            exposure_s: req.exposure_s,
            exposure_policy: req.exposure_policy.clone(),
            frame_size: req.frame_size,
            out: root.clone(),
            simulated: self.config.sim,
            order: Some(plan.order),
        };
        let profile = self.profile.clone();
        let faults = self.config.sim_faults.clone();
        // A built-in plan in its own order is solved once, at start-up or
        // on first use, and kept (the plan cache); any other is solved now.
        let cached = match (&req.plan, req.order, prefer_slots) {
            (PlanSpec::Name(name), None, false) => self.plans.get(name).await,
            _ => None,
        };
        let solved = tokio::task::spawn_blocking(move || {
            if let Some(schedule) = cached {
                let schedule = schedule.map_err(RunError::Invalid)?;
                let solver = crate::kinematics::Solver::new(&profile)?;
                return Ok((solver, plan, Schedule::clone(&schedule)));
            }
            let mut solved = launch::solve_given_plan(&profile, plan)?;
            if prefer_slots {
                let (chosen, choice) = launch::prefer_slots(&profile, solved);
                solved = chosen;
                if let Some(choice) = choice {
                    tracing::info!("{choice}");
                }
            }
            Ok::<_, RunError>(solved)
        })
        .await
        .map_err(|e| SupervisorError::internal(format!("solving the plan failed: {e}")))?
        .map_err(run_error)?;
        let home = self.engine_home()?;
        let prepared = home
            .run(move |clock| {
                let sim = crate::rig::simulated_rig(faults);
                async move {
                    launch::prepare_new_solved(
                        new,
                        solved,
                        sim.as_deref(),
                        clock,
                        PausePolicy::Wait,
                    )
                    .await
                }
            })
            .await
            .map_err(|e| SupervisorError::internal(format!("preparing the run failed: {e}")))?
            .map_err(run_error)?;
        // The run exists on disk from here on: whatever follows, the daemon
        // knows it (from what was prepared, not from a second read of its
        // files), never leaving a folder it answers 404 for.
        let view = data_dir::view_of(&id, &prepared.meta, None, prepared.frames_done, None, None);
        if let Some(options) = &req.process {
            // Checked in `validate`; queued before the engine starts, so
            // the job is on disk before the first frame.
            let queued = self
                .process_after_capture(&req, &prepared.meta.plan, options.clone())
                .and_then(|options| {
                    super::jobs::queue_after_capture(
                        &**self,
                        &self.runs_dir.join(&id),
                        &id,
                        options,
                    )
                });
            if let Err(e) = queued {
                self.abandon(view, prepared, &e);
                return Err(e);
            }
        }
        let view = self.install(view, prepared, home, "run_created");
        Ok(view)
    }

    /// A run prepared but never started (its processing could not be
    /// queued): its engine and rig go, and it is recorded aborted with the
    /// reason, so it is listed and says why.
    fn abandon(&self, mut view: RunView, prepared: Prepared, why: &SupervisorError) {
        let root = prepared.root.clone();
        drop(prepared);
        let reason = format!("never started: {why}");
        match crate::store::transition_state(
            &root,
            None,
            RunState::Aborted,
            Some(reason.clone()),
            0.0,
        ) {
            Ok(record) => view.updated_at = Some(record.updated_at),
            Err(e) => {
                tracing::error!(run = %view.id, "cannot record that the run never started: {e}")
            }
        }
        view.state = RunState::Aborted;
        view.reason = Some(reason);
        view.resumable = false;
        self.inner().runs.insert(view.clone());
        self.hub.publish(
            Some(&view.id),
            "run_ended",
            serde_json::to_value(&view).unwrap_or_default(),
        );
    }

    /// Where a new engine runs: a simulated rig in virtual time paced to the
    /// daemon's speed, on a runtime of its own, so that neither the host's
    /// load nor the simulator's own work counts as rig time; hardware on the
    /// wall clock, on the daemon's runtime.
    fn engine_home(&self) -> Result<EngineHome, SupervisorError> {
        if !self.config.sim {
            return Ok(EngineHome::Wall);
        }
        PacedRuntime::start(self.config.sim_speed)
            .map(EngineHome::Paced)
            .map_err(|e| SupervisorError::internal(e.to_string()))
    }

    /// Makes a prepared engine the active run and spawns its supervisor.
    fn install(
        self: &Arc<Self>,
        mut view: RunView,
        mut p: Prepared,
        home: EngineHome,
        kind: &str,
    ) -> RunView {
        let rx = p.handle.events.subscribe();
        let pace = match &home {
            EngineHome::Paced(rt) => {
                p.handle.runtime = Some(rt.handle().clone());
                Some(rt.pace())
            }
            EngineHome::Wall => None,
        };
        view.state = RunState::Preparing;
        view.reason = None;
        view.active = true;
        view.resumable = false;
        view.steps_done = p.frames_done;
        view.steps_total = p.frames_total;
        view.physical_s = p.t_offset_s;
        view.eta_physical_s = Some(p.estimate_s);
        view.eta_wall_s = Some(p.estimate_s / self.speed());
        let id = view.id.clone();
        {
            let mut inner = self.inner();
            inner.active = Some(Active {
                id: id.clone(),
                handle: p.handle,
                sim: p.sim.clone(),
                state: RunState::Preparing,
                pending: None,
                end_estimate_s: p.t_offset_s + p.estimate_s,
                pace,
            });
            inner.last_sim = p.sim;
            inner.runs.insert(view.clone());
        }
        self.hub.publish(
            Some(&id),
            kind,
            serde_json::to_value(&view).unwrap_or_default(),
        );
        let daemon = self.clone();
        let run = home.spawn(p.engine.run());
        let task = tokio::spawn(supervise(daemon, id, run, rx, home));
        *lock(&self.supervisor) = Some(task);
        // Prepared while the daemon began shutting down: leave it resumable.
        let inner = self.inner();
        if inner.shutting_down {
            if let Some(a) = &inner.active {
                let _ = a.handle.commands.try_send(Command::Detach);
            }
        }
        drop(inner);
        view
    }

    fn on_engine_event(&self, id: &str, ev: RunEvent) {
        {
            let mut inner = self.inner();
            let speed = self.speed();
            let end_estimate = inner
                .active
                .as_ref()
                .filter(|a| a.id == id)
                .map(|a| a.end_estimate_s);
            let pace = inner
                .active
                .as_ref()
                .filter(|a| a.id == id)
                .and_then(|a| a.pace.as_ref())
                .map(|p| PaceView {
                    asked_speed: p.asked(),
                    achieved_speed: p.achieved(),
                    behind: p.is_behind(),
                });
            if let EventKind::State { to, .. } = &ev.kind {
                if let Some(a) = inner.active.as_mut().filter(|a| a.id == id) {
                    a.state = *to;
                    a.pending = None;
                }
            }
            inner.runs.update(id, |v| {
                v.physical_s = ev.t_s;
                v.updated_at = Some(crate::store::now_rfc3339());
                match &ev.kind {
                    EventKind::State { to, reason, .. } => {
                        v.state = *to;
                        v.reason = reason.clone();
                        if let Some(r) = reason.as_ref().filter(|r| data_dir::is_error_reason(r)) {
                            v.last_error = Some(r.clone());
                        }
                    }
                    EventKind::Retry { reason, .. } => {
                        v.last_error = Some(reason.clone());
                    }
                    EventKind::Step {
                        frames_done,
                        frames_total,
                        ..
                    } => {
                        v.steps_done = *frames_done;
                        v.steps_total = *frames_total;
                    }
                    _ => {}
                }
                if let Some(end) = end_estimate {
                    let left = (end - ev.t_s).max(0.0);
                    v.eta_physical_s = Some(left);
                    // At the speed the host achieves, not the one asked.
                    let speed = pace.as_ref().map_or(speed, |p| p.achieved_speed.max(1e-9));
                    v.eta_wall_s = Some(left / speed);
                }
                v.pace = pace;
            });
        }
        self.hub.publish(
            Some(id),
            "engine",
            serde_json::to_value(&ev).unwrap_or_default(),
        );
    }

    fn on_run_ended(
        self: &Arc<Self>,
        id: &str,
        result: Result<Result<Outcome, EngineError>, String>,
    ) {
        let root = self.runs_dir.join(id);
        let reloaded = data_dir::load_run(&root, id, false).ok().map(|(v, _)| v);
        let (shutting_down, view) = {
            let mut inner = self.inner();
            if inner.active.as_ref().is_some_and(|a| a.id == id) {
                inner.active = None;
                self.run_ended.notify_waiters();
            }
            let before = inner.runs.get(id).cloned();
            let mut view = reloaded.or_else(|| before.clone());
            if let Some(v) = view.as_mut() {
                v.active = false;
                if v.last_error.is_none() {
                    v.last_error = before.and_then(|b| b.last_error);
                }
                let err = match &result {
                    Err(e) => Some(e.clone()),
                    Ok(Err(e)) => Some(e.to_string()),
                    Ok(Ok(_)) => None,
                };
                if let Some(e) = err {
                    v.reason = Some(format!("engine error: {e}"));
                    v.last_error = v.reason.clone();
                    if !v.state.is_terminal() {
                        // Recorded on disk too (best effort: the error may
                        // be the disk's), so a restart shows the same.
                        let root = self.runs_dir.join(id);
                        let current = crate::store::read_state(&root).ok().flatten();
                        if let Err(w) = crate::store::transition_state(
                            &root,
                            current.as_ref(),
                            RunState::Failed,
                            v.reason.clone(),
                            v.physical_s,
                        ) {
                            tracing::warn!(run = %id, "cannot record the failure: {w}");
                        }
                        v.state = RunState::Failed;
                        v.resumable = true;
                    }
                }
                inner.runs.insert(v.clone());
            }
            (inner.shutting_down, view)
        };
        if let Some(v) = &view {
            tracing::info!(run = %id, state = %v.state, "run ended");
        }
        self.hub.publish(
            Some(id),
            "run_ended",
            serde_json::to_value(&view).unwrap_or_default(),
        );
        self.jobs.notify();
        if !shutting_down {
            // At shutdown the index is written once, after the engine.
            self.save_run_index_soon();
            self.pump_queue();
        }
    }

    /// Starts the next queued run if the rig is free.
    pub fn pump_queue(self: &Arc<Self>) {
        let daemon = self.clone();
        tokio::spawn(async move {
            let gate = daemon.start_gate.lock().await;
            let _ = daemon.start_next_queued(&gate).await;
        });
    }

    /// Starts the queue's head if the rig is free: the item and the run it
    /// became. Under the start gate, so the head cannot change between
    /// being taken and being started, and only one caller starts it.
    async fn start_next_queued(
        self: &Arc<Self>,
        gate: &tokio::sync::MutexGuard<'_, ()>,
    ) -> Option<(QueueItem, RunView)> {
        // A run whose final state is in but whose engine still holds the
        // rig is as good as ended.
        self.settle_ending_run().await;
        loop {
            let item = {
                let mut inner = self.inner();
                if inner.shutting_down || inner.active.is_some() || inner.queue.is_empty() {
                    return None;
                }
                let item = inner.queue.remove(0);
                self.save_queue_locked(&inner);
                item
            };
            self.publish_queue();
            match self.start_run_gated(item.request.clone(), gate).await {
                Ok(v) => {
                    tracing::info!(item = %item.id, run = %v.id, "queued run started");
                    return Some((item, v));
                }
                Err(SupervisorError::Conflict(_) | SupervisorError::Unavailable(_)) => {
                    // The rig is held (by a run nobody queued), or the
                    // daemon is stopping: put it back.
                    let mut inner = self.inner();
                    inner.queue.insert(0, item);
                    self.save_queue_locked(&inner);
                    return None;
                }
                Err(e) => {
                    tracing::warn!(item = %item.id, "queued run could not start: {}", e);
                    self.hub.publish(
                        None,
                        "queue_item_failed",
                        serde_json::json!({"item": item, "error": e.to_string()}),
                    );
                }
            }
        }
    }

    fn save_queue_locked(&self, inner: &Inner) {
        if let Err(e) = data_dir::save_queue(&self.data_dir, &inner.queue) {
            tracing::error!("cannot save the queue: {e}");
        }
    }

    fn publish_queue(&self) {
        let items = self.inner().queue.clone();
        self.hub
            .publish(None, "queue_changed", serde_json::json!({ "items": items }));
    }

    /// Adds a run to the queue; starts it at once if the rig is free.
    pub async fn enqueue(
        self: &Arc<Self>,
        req: RunRequest,
    ) -> Result<(QueueItem, Option<RunView>), SupervisorError> {
        self.validate(&req)?;
        // Held from adding the item to starting it, so no other start (a
        // pump after a run ended) can take it in between and leave this
        // caller unable to say which run it became.
        let gate = self.start_gate.lock().await;
        let item = {
            let mut inner = self.inner();
            if inner.shutting_down {
                return Err(SupervisorError::unavailable("the daemon is shutting down"));
            }
            if inner.queue.len() >= 1000 {
                return Err(SupervisorError::conflict("the queue is full (1000 items)"));
            }
            inner.queue_seq += 1;
            let ms = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_millis())
                .unwrap_or(0);
            let item = QueueItem {
                id: format!("q{ms}-{}", inner.queue_seq),
                request: req,
                created_at: crate::store::now_rfc3339(),
            };
            inner.queue.push(item.clone());
            data_dir::save_queue(&self.data_dir, &inner.queue)
                .map_err(|e| SupervisorError::internal(format!("cannot save the queue: {e}")))?;
            item
        };
        self.publish_queue();
        let started = self
            .start_next_queued(&gate)
            .await
            .and_then(|(started, run)| (started.id == item.id).then_some(run));
        Ok((item, started))
    }

    /// Removes a queued run by its item id and saves the queue; not found when
    /// no item has that id.
    pub fn dequeue(&self, item: &str) -> Result<(), SupervisorError> {
        {
            let mut inner = self.inner();
            let Some(pos) = inner.queue.iter().position(|q| q.id == item) else {
                return Err(SupervisorError::not_found("no such queue item"));
            };
            inner.queue.remove(pos);
            data_dir::save_queue(&self.data_dir, &inner.queue)
                .map_err(|e| SupervisorError::internal(format!("cannot save the queue: {e}")))?;
        }
        self.publish_queue();
        Ok(())
    }

    /// Pause, resume or abort. Returns whether the live engine got it.
    pub async fn command(
        self: &Arc<Self>,
        id: &str,
        cmd: Command,
    ) -> Result<(bool, RunView), SupervisorError> {
        let view = self
            .view(id)
            .ok_or_else(|| SupervisorError::not_found(format!("no run `{}`", short(id))))?;
        let live = {
            let mut inner = self.inner();
            match inner.active.as_mut().filter(|a| a.id == id) {
                None => None,
                // Already on its way (a client repeating itself, a fuzzer):
                // the engine acts on it once, and its queue never fills.
                Some(a) if a.pending == Some(cmd) => Some(Ok(())),
                // Nothing after an abort can matter to the run; so at most a
                // pause and an abort wait for an engine that is busy (homing,
                // say) and its command queue never fills.
                Some(a) if a.pending == Some(Command::Abort) => Some(Err(
                    SupervisorError::conflict("an abort is on its way to the run's engine"),
                )),
                Some(a) => Some(
                    check_command(a.state, cmd)
                        .map_err(|r| SupervisorError::conflict(r.to_string()))
                        .and_then(|()| {
                            a.handle.commands.try_send(cmd).map_err(|e| {
                                SupervisorError::unavailable(format!("the engine is busy: {e}"))
                            })
                        })
                        .map(|()| a.pending = Some(cmd)),
                ),
            }
        };
        if let Some(sent) = live {
            sent?;
            return Ok((true, self.view(id).unwrap_or(view)));
        }
        // No live engine.
        match cmd {
            Command::Resume if view.resumable => {
                let v = self.resume_from_disk(id).await?;
                Ok((false, v))
            }
            Command::Abort if view.resumable => {
                let root = self.runs_dir.join(id);
                let current = crate::store::read_state(&root)
                    .map_err(|e| SupervisorError::internal(e.to_string()))?;
                let record = crate::store::transition_state(
                    &root,
                    current.as_ref(),
                    RunState::Aborted,
                    Some("aborted by operator (no live engine)".into()),
                    view.physical_s,
                )
                .map_err(|e| SupervisorError::internal(e.to_string()))?;
                let v = {
                    let mut inner = self.inner();
                    let v = inner.runs.update(id, |v| {
                        v.state = RunState::Aborted;
                        v.reason = record.reason.clone();
                        v.resumable = false;
                        v.updated_at = Some(record.updated_at.clone());
                        v.clone()
                    });
                    v.unwrap_or(view)
                };
                self.save_run_index_soon();
                self.hub.publish(
                    Some(id),
                    "run_ended",
                    serde_json::to_value(&v).unwrap_or_default(),
                );
                self.pump_queue();
                Ok((false, v))
            }
            _ => Err(SupervisorError::conflict(format!(
                "cannot {} run {} in state {}{}",
                format!("{cmd:?}").to_lowercase(),
                id,
                view.state,
                if matches!(view.state, RunState::Paused | RunState::Interrupted) {
                    ""
                } else {
                    " (no live engine)"
                }
            ))),
        }
    }

    async fn resume_from_disk(self: &Arc<Self>, id: &str) -> Result<RunView, SupervisorError> {
        let _gate = self.start_gate.lock().await;
        self.settle_ending_run().await;
        {
            let inner = self.inner();
            if inner.shutting_down {
                return Err(SupervisorError::unavailable("the daemon is shutting down"));
            }
            if let Some(e) = Self::conflict_active(&inner) {
                return Err(e);
            }
        }
        self.manual.release().await;
        let root = self.runs_dir.join(id);
        let home = self.engine_home()?;
        // Resuming re-checks every frame's checksum: blocking work, on the
        // engine's runtime.
        let prepared = home
            .run(move |clock| async move {
                let sim = crate::rig::simulated_rig(Vec::new());
                launch::prepare_resume(&root, sim.as_deref(), clock, PausePolicy::Wait).await
            })
            .await
            .map_err(|e| SupervisorError::internal(format!("resuming failed: {e}")))?
            .map_err(|e| match e {
                RunError::Store(
                    crate::store::StoreError::Finished(..) | crate::store::StoreError::Busy(_),
                ) => SupervisorError::conflict(e.to_string()),
                other => run_error(other),
            })?;
        let view = self
            .view(id)
            .ok_or_else(|| SupervisorError::not_found("no such run"))?;
        Ok(self.install(view, prepared, home, "run_resumed"))
    }

    /// Emergency stop of the active run's rig.
    pub async fn estop(&self) -> (Option<String>, Option<crate::engine::StopReport>) {
        let active = {
            let inner = self.inner();
            inner
                .active
                .as_ref()
                .map(|a| (a.id.clone(), a.handle.clone()))
        };
        let Some((id, handle)) = active else {
            // No run: manual control may be moving something.
            let report = self.manual.emergency_stop().await;
            let note = if report.is_some() {
                "no run active: the manual-control rig stopped"
            } else {
                "no run active: nothing moving"
            };
            self.hub.publish(
                None,
                "estop",
                serde_json::json!({"run": null, "note": note, "report": report}),
            );
            return (None, report);
        };
        let report = handle.emergency_stop().await;
        tracing::warn!(run = %id, latency_s = report.latency_s, "emergency stop");
        self.hub.publish(
            Some(&id),
            "estop",
            serde_json::to_value(&report).unwrap_or_default(),
        );
        (Some(id), Some(report))
    }

    /// The schedule of a run (solved from its run.json, cached).
    pub fn run_schedule(&self, id: &str) -> Result<Arc<Schedule>, SupervisorError> {
        if let Some(s) = lock(&self.schedules).get(id) {
            return Ok(s.clone());
        }
        let root = self
            .run_root(id)
            .ok_or_else(|| SupervisorError::not_found(format!("no run `{}`", short(id))))?;
        let bytes = std::fs::read(root.join(crate::store::RUN_FILE))
            .map_err(|e| SupervisorError::internal(e.to_string()))?;
        let meta: crate::store::RunMeta =
            serde_json::from_slice(&bytes).map_err(|e| SupervisorError::internal(e.to_string()))?;
        let (_, _, schedule) =
            launch::solve_given_plan(&meta.profile, meta.plan).map_err(run_error)?;
        let schedule = Arc::new(schedule);
        let mut cache = lock(&self.schedules);
        if cache.len() >= 16 {
            cache.clear();
        }
        cache.insert(id.to_string(), schedule.clone());
        Ok(schedule)
    }

    /// Stops taking work, detaches the active run (it is left paused and
    /// resumable), waits for its engine to end, then ends the event streams.
    pub async fn shutdown(&self) {
        self.jobs.stop();
        let commands = {
            let mut inner = self.inner();
            inner.shutting_down = true;
            inner
                .active
                .as_ref()
                .map(|a| (a.id.clone(), a.handle.commands.clone()))
        };
        if let Some((id, tx)) = commands {
            tracing::info!(run = %id, "shutting down: detaching the active run (resumable)");
            let _ = tx.send(Command::Detach).await;
        }
        // A run being prepared right now is installed (and detached, see
        // `install`) before this gate opens; then its engine is awaited.
        let _gate = self.start_gate.lock().await;
        let task = lock(&self.supervisor).take();
        if let Some(task) = task {
            if tokio::time::timeout(Duration::from_secs(60), task)
                .await
                .is_err()
            {
                tracing::error!("the engine did not stop within 60 s; exiting anyway (the journal is fsynced per frame)");
            }
        }
        // Blocks this thread a moment (it stats every run's files), once,
        // with nothing left to serve but the streams about to end.
        self.save_run_index();
        let _ = self.shutdown_tx.send(true);
    }
}

fn short(id: &str) -> String {
    id.chars().take(64).collect()
}

/// Where a run's engine runs ([`Daemon::engine_home`]).
enum EngineHome {
    /// On the daemon's runtime, on the wall clock (hardware).
    Wall,
    /// On a runtime of its own in virtual time paced to the wall clock
    /// (the simulated rig); it lives as long as the engine.
    Paced(PacedRuntime),
}

impl EngineHome {
    /// Runs `make(clock)` to its end where the engine will run, with a
    /// clock made there.
    async fn run<F, Fut, T>(&self, make: F) -> Result<T, tokio::task::JoinError>
    where
        F: FnOnce(Clock) -> Fut + Send + 'static,
        Fut: std::future::Future<Output = T> + Send + 'static,
        T: Send + 'static,
    {
        match self {
            EngineHome::Paced(rt) => {
                rt.handle()
                    .spawn(async move { make(Clock::virtual_time()).await })
                    .await
            }
            EngineHome::Wall => {
                // Connecting and checking a run's frames block; the rig's
                // tasks are spawned onto this runtime from there.
                let rt = tokio::runtime::Handle::current();
                tokio::task::spawn_blocking(move || rt.block_on(make(Clock::real()))).await
            }
        }
    }

    /// Spawns the engine's run where it lives.
    fn spawn<Fut>(&self, fut: Fut) -> JoinHandle<Fut::Output>
    where
        Fut: std::future::Future + Send + 'static,
        Fut::Output: Send + 'static,
    {
        match self {
            EngineHome::Paced(rt) => rt.handle().spawn(fut),
            EngineHome::Wall => tokio::spawn(fut),
        }
    }
}

async fn supervise(
    daemon: Arc<Daemon>,
    id: String,
    mut run: JoinHandle<Result<Outcome, EngineError>>,
    mut rx: broadcast::Receiver<RunEvent>,
    home: EngineHome,
) {
    let result = loop {
        tokio::select! {
            ev = rx.recv() => match ev {
                Ok(ev) => daemon.on_engine_event(&id, ev),
                Err(broadcast::error::RecvError::Lagged(n)) => {
                    tracing::warn!(run = %id, missed = n, "event forwarder lagged");
                }
                Err(broadcast::error::RecvError::Closed) => break (&mut run).await,
            },
            res = &mut run => break res,
        }
    };
    while let Ok(ev) = rx.try_recv() {
        daemon.on_engine_event(&id, ev);
    }
    let result = result.map_err(|e| e.to_string());
    if let Ok(Err(e)) = &result {
        tracing::error!(run = %id, "engine error: {e}");
    }
    // The engine has ended: its paced runtime (and the simulated firmware
    // on it) goes now.
    drop(home);
    daemon.on_run_ended(&id, result);
}

impl Daemon {
    /// Runs one manual action on the manual rig, connecting it first if
    /// needed. 409 while a run is active.
    pub async fn manual<T, F>(self: &Arc<Self>, action: F) -> Result<T, SupervisorError>
    where
        F: for<'a> FnOnce(
            &'a mut crate::engine::manual::ManualRig,
        ) -> std::pin::Pin<
            Box<
                dyn std::future::Future<Output = Result<T, crate::engine::manual::ManualError>>
                    + Send
                    + 'a,
            >,
        >,
    {
        let _gate = self.start_gate.lock().await;
        self.settle_ending_run().await;
        {
            let inner = self.inner();
            if inner.shutting_down {
                return Err(SupervisorError::unavailable("the daemon is shutting down"));
            }
            if let Some(a) = &inner.active {
                return Err(SupervisorError::conflict(format!(
                    "run {} is active ({}): manual control waits until it has ended",
                    a.id, a.state
                )));
            }
        }
        let connect = || async {
            let sim = self.config.sim.then(|| self.config.sim_faults.clone());
            let (rig, handle) =
                super::manual_session::connect_rig(&self.profile, sim, self.clock()).await?;
            if handle.is_some() {
                self.inner().last_sim = handle;
            }
            Ok(rig)
        };
        self.manual.act(connect, action).await
    }
}

impl super::jobs::JobHost for Daemon {
    fn jobs(&self) -> &super::jobs::Jobs {
        &self.jobs
    }

    fn hub(&self) -> &EventHub {
        &self.hub
    }

    fn executor(&self) -> &crate::postprocess::executor::ProcessingConfig {
        &self.config.processing
    }

    fn run_root(&self, id: &str) -> Option<PathBuf> {
        Daemon::run_root(self, id)
    }

    fn view(&self, id: &str) -> Option<RunView> {
        Daemon::view(self, id)
    }

    fn capturing(&self, id: &str) -> bool {
        self.inner().runs.get(id).is_some_and(|v| v.active)
    }

    fn ready_to_process(&self, id: &str, after_capture: bool) -> bool {
        // A failed run may still be resumed: a job asked for with its
        // capture waits for it to complete or be aborted.
        self.inner().runs.get(id).is_some_and(|v| {
            !v.active
                && match v.state {
                    RunState::Completed | RunState::Aborted => true,
                    RunState::Failed => !after_capture,
                    _ => false,
                }
        })
    }
}
