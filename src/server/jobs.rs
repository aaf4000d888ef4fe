//! Process jobs: `POST /api/v1/runs/{id}/process` hands a finished run's
//! processing (rectify, btf, fit, mdf, photometric stereo) to the daemon.
//!
//! - One job runs at a time, in the order they were asked for, on a worker
//!   thread of its own beside the capture. Its threads run at a lower
//!   priority (nice 10), so a capture's device calls are scheduled first.
//! - Each job is kept in `RUN/processed/job.json`, rewritten atomically at
//!   every step's start and end. A daemon that stops or dies mid-job finds
//!   the job at its next start and resumes it: the steps done are kept, the
//!   step that was running runs again (each step writes its index last, so
//!   a cut step leaves nothing a reader would take for a result; `rectify`
//!   keeps each frame's first pass and registers only the frames it had
//!   not done).
//! - Asking again for what is queued, running or done with the same
//!   options returns that job and does no work twice; a failed job asked
//!   again resumes from the step that failed.
//! - A job asked for with its run (`process` in `POST /runs`) waits for the
//!   capture, but between jobs the worker processes the capture as it goes
//!   ([`pipeline::CaptureStream`]): each newly journaled frame's
//!   registration, and each view slot's compression once its lights are
//!   all in. The steps after the capture take both as they are.
//! - Progress goes out as `process` events: the job's state, the step, done
//!   and total in the step's units, and the step's ETA in seconds.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use super::error::SupervisorError;
use super::events::EventHub;
use super::wire::{JobState, ProcessJob, RunView, StepStatus};
use crate::model::run_state::RunState;
use crate::postprocess::executor::ProcessingConfig;
use crate::postprocess::frames::RunFrames;
use crate::postprocess::pipeline::{self, ProcessOptions, ProcessStep, RunFacts};
use crate::postprocess::slurm::SlurmError;
use crate::store::StoreError;
use rigd_core::sync::lock;

/// The job's file in `RUN/processed/`.
pub const JOB_FILE: &str = "job.json";
/// Least wall time between two progress events of a step.
const EVENT_INTERVAL: Duration = Duration::from_millis(500);
/// How often an idle worker looks at the queue without being woken, and
/// at a capturing run's journal for frames to register.
const IDLE_RECHECK: Duration = pipeline::STREAM_POLL;
/// How long a stream that failed waits before it tries again.
const STREAM_RETRY: Duration = Duration::from_secs(30);

impl ProcessJob {
    fn new(run: &str, options: ProcessOptions) -> ProcessJob {
        let now = crate::store::now_rfc3339();
        ProcessJob {
            run: run.to_string(),
            steps: options
                .steps
                .iter()
                .map(|&step| StepStatus {
                    step,
                    state: JobState::Queued,
                    done: 0,
                    total: 0,
                    elapsed_s: 0.0,
                    eta_s: None,
                    summary: None,
                    detail: None,
                })
                .collect(),
            options,
            state: JobState::Queued,
            error: None,
            created_at: now.clone(),
            updated_at: now,
            resumed: 0,
            after_capture: false,
            streamed: 0,
            slots_ahead: 0,
            cancelling: false,
        }
    }

    /// Queued again: the steps not done start over, the done ones stay.
    fn requeue(&mut self) {
        self.state = JobState::Queued;
        self.error = None;
        self.cancelling = false;
        self.updated_at = crate::store::now_rfc3339();
        for s in &mut self.steps {
            if s.state != JobState::Done {
                s.state = JobState::Queued;
                s.done = 0;
                s.eta_s = None;
            }
        }
    }

    fn event(&self) -> serde_json::Value {
        let current = self
            .steps
            .iter()
            .find(|s| s.state == JobState::Running || s.state == JobState::Failed);
        serde_json::json!({
            "state": self.state,
            "step": current.map(|s| s.step.name()),
            "done": current.map(|s| s.done),
            "total": current.map(|s| s.total),
            "eta_s": current.and_then(|s| s.eta_s),
            "detail": current.and_then(|s| s.detail.clone()),
            "steps_done": self.steps.iter().filter(|s| s.state == JobState::Done).count(),
            "steps_total": self.steps.len(),
            "error": self.error,
            "cancelling": self.cancelling,
            "streamed": self.streamed,
            "slots_ahead": self.slots_ahead,
        })
    }
}

fn job_path(root: &Path) -> PathBuf {
    crate::store::processed::processed_dir(root).join(JOB_FILE)
}

/// Reads a run's job file; None when there is none or it cannot be read
/// (then it is logged, and the run can be processed afresh).
fn read_job(root: &Path) -> Option<ProcessJob> {
    let path = job_path(root);
    let bytes = std::fs::read(&path).ok()?;
    match serde_json::from_slice(&bytes) {
        Ok(job) => Some(job),
        Err(e) => {
            tracing::warn!("{}: {e}; ignored", path.display());
            None
        }
    }
}

fn write_job(root: &Path, job: &ProcessJob) -> Result<(), String> {
    let path = job_path(root);
    let dir = crate::store::processed::processed_dir(root);
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut json = serde_json::to_vec_pretty(job).map_err(|e| e.to_string())?;
    json.push(b'\n');
    crate::store::write_atomic(&path, &json).map_err(|e| format!("{}: {e}", path.display()))
}

/// The daemon's process jobs, by run id, and the worker that runs them.
#[derive(Default)]
pub struct Jobs {
    jobs: Mutex<BTreeMap<String, ProcessJob>>,
    wake: Condvar,
    stop: AtomicBool,
    /// The operator asked to cancel the running job
    /// (`POST /runs/{id}/process/cancel`).
    cancel: AtomicBool,
}

impl Jobs {
    /// The jobs found in the run directories: a job that was running when
    /// the daemon stopped is queued again (counted in `resumed`).
    pub fn load<'a>(runs_dir: &Path, ids: impl Iterator<Item = &'a String>) -> Jobs {
        let mut jobs = BTreeMap::new();
        for id in ids {
            let root = runs_dir.join(id);
            let Some(mut job) = read_job(&root) else {
                continue;
            };
            if job.state == JobState::Running {
                job.requeue();
                job.resumed += 1;
                if let Err(e) = write_job(&root, &job) {
                    tracing::warn!("process job of {id}: {e}");
                }
            }
            jobs.insert(id.clone(), job);
        }
        Jobs {
            jobs: Mutex::new(jobs),
            ..Default::default()
        }
    }

    /// Run `id`'s job, if it has one.
    pub fn get(&self, id: &str) -> Option<ProcessJob> {
        lock(&self.jobs).get(id).cloned()
    }

    /// Stops the worker after the step it runs (or at once when idle).
    pub fn stop(&self) {
        self.stop.store(true, Ordering::SeqCst);
        self.wake.notify_all();
    }

    /// Wakes the worker: a job was queued or a run ended.
    pub fn notify(&self) {
        self.wake.notify_all();
    }

    /// The oldest queued job whose run is `ready`, else the oldest queued
    /// job whose capture has frames to register (`streamable`); waits for
    /// one. A wake-up lost between the check and the wait costs at most
    /// [`IDLE_RECHECK`].
    fn next_work(
        &self,
        ready: &dyn Fn(&ProcessJob) -> bool,
        streamable: &dyn Fn(&ProcessJob) -> bool,
    ) -> Option<Work> {
        let mut jobs = lock(&self.jobs);
        loop {
            if self.stop.load(Ordering::SeqCst) {
                return None;
            }
            let oldest = |pick: &dyn Fn(&ProcessJob) -> bool| {
                jobs.values()
                    .filter(|j| j.state == JobState::Queued && pick(j))
                    .min_by(|a, b| a.created_at.cmp(&b.created_at).then(a.run.cmp(&b.run)))
                    .map(|j| j.run.clone())
            };
            if let Some(id) = oldest(ready) {
                return Some(Work::Job(id));
            }
            if let Some(id) = oldest(streamable) {
                return Some(Work::Stream(id));
            }
            jobs = match self.wake.wait_timeout(jobs, IDLE_RECHECK) {
                Ok((g, _)) => g,
                Err(p) => p.into_inner().0,
            };
        }
    }

    /// Runs `f` on run `id`'s job under the lock.
    fn with_job<T>(&self, id: &str, f: impl FnOnce(&mut ProcessJob) -> T) -> Option<T> {
        lock(&self.jobs).get_mut(id).map(f)
    }

    /// Changes run `id`'s job under the lock; returns the job after.
    fn update(&self, id: &str, f: impl FnOnce(&mut ProcessJob)) -> Option<ProcessJob> {
        self.with_job(id, |job| {
            f(job);
            job.clone()
        })
    }
}

/// What the worker does next.
enum Work {
    /// Run the job of this run.
    Job(String),
    /// Register the frames this capturing run journaled since the last look.
    Stream(String),
}

/// What the jobs need of the daemon around them: the run history, the
/// event hub and where steps run. The supervisor provides it.
pub trait JobHost: Send + Sync + 'static {
    /// The process jobs.
    fn jobs(&self) -> &Jobs;
    /// Where events go out.
    fn hub(&self) -> &EventHub;
    /// Where the steps run: here, or on Slurm.
    fn executor(&self) -> &ProcessingConfig;
    /// A known run's folder.
    fn run_root(&self, id: &str) -> Option<PathBuf>;
    /// A known run as the API shows it.
    fn view(&self, id: &str) -> Option<RunView>;
    /// Whether run `id` is being captured now.
    fn capturing(&self, id: &str) -> bool;
    /// Whether run `id` can be processed now: it has ended, and a job asked
    /// for with the capture (`after_capture`) only once it completed or was
    /// aborted.
    fn ready_to_process(&self, id: &str, after_capture: bool) -> bool;
}

/// Whether a submission made a new job or found one.
pub enum Submitted {
    /// A job was queued (new, or a failed one resumed).
    Queued(ProcessJob),
    /// The same job is already queued, running or done.
    Existing(ProcessJob),
}

/// Queues `options` for run `id`, or returns the same job if it is already
/// queued, running or done.
pub fn submit(
    host: &dyn JobHost,
    id: &str,
    options: ProcessOptions,
) -> Result<Submitted, SupervisorError> {
    let root = host
        .run_root(id)
        .ok_or_else(|| SupervisorError::not_found(format!("no run `{id}`")))?;
    let view = host
        .view(id)
        .ok_or_else(|| SupervisorError::not_found(format!("no run `{id}`")))?;
    if view.active
        || !matches!(
            view.state,
            RunState::Completed | RunState::Aborted | RunState::Failed
        )
    {
        return Err(SupervisorError::conflict(format!(
            "run `{id}` is {}: a run is processed once it has ended (completed, aborted or failed)",
            view.state
        )));
    }
    let frames = RunFrames::open(&root).map_err(|e| match e {
        // The run's record cannot be used as it is: the request is refused.
        crate::postprocess::ProcessError::Store(StoreError::Corrupt { .. }) => {
            SupervisorError::invalid(e.to_string())
        }
        e => SupervisorError::internal(e.to_string()),
    })?;
    let options = options
        .resolve(&RunFacts::of_run(&frames))
        .map_err(SupervisorError::invalid)?;
    // A cluster that cannot take the job is said now, not after it queued.
    host.executor()
        .check(&root)
        .map_err(|e| SupervisorError::invalid(format!("processing on Slurm: {e}")))?;
    if options.steps.contains(&ProcessStep::Rectify) {
        if let Some(size) = view.frame_size {
            pipeline::check_frame_size(size).map_err(SupervisorError::invalid)?;
        }
    }
    let mut jobs = lock(&host.jobs().jobs);
    let job = match jobs.get(id) {
        Some(j) if j.options == options && j.state != JobState::Failed => {
            return Ok(Submitted::Existing(j.clone()));
        }
        Some(j) if j.state == JobState::Running => {
            return Err(SupervisorError::conflict(format!(
                "run `{id}` is being processed with other options; ask again when it has ended"
            )));
        }
        Some(j) if j.options == options => {
            let mut j = j.clone();
            j.requeue();
            j
        }
        _ => ProcessJob::new(id, options),
    };
    write_job(&root, &job).map_err(SupervisorError::internal)?;
    jobs.insert(id.to_string(), job.clone());
    drop(jobs);
    host.hub().publish(Some(id), "process", job.event());
    host.jobs().wake.notify_all();
    Ok(Submitted::Queued(job))
}

/// Queues the processing of run `id` (in `root`) to start when its capture
/// ends (the options resolved and checked against its plan).
pub fn queue_after_capture(
    host: &dyn JobHost,
    root: &Path,
    id: &str,
    options: ProcessOptions,
) -> Result<(), SupervisorError> {
    let mut job = ProcessJob::new(id, options);
    job.after_capture = true;
    write_job(root, &job).map_err(SupervisorError::internal)?;
    lock(&host.jobs().jobs).insert(id.to_string(), job.clone());
    host.hub().publish(Some(id), "process", job.event());
    Ok(())
}

/// What a cancel request did.
pub enum Cancelled {
    /// The job was queued: it will not run (failed, "cancelled").
    Dropped(ProcessJob),
    /// The job runs: its Slurm jobs are cancelled now, a local step stops
    /// at its end.
    Stopping(ProcessJob),
}

/// The error of a job the operator cancelled.
pub const CANCELLED: &str = "cancelled by the operator";

/// Cancels run `id`'s process job: a queued one is dropped, a running one
/// stops (on Slurm its arrays are cancelled with `scancel`).
pub fn cancel(host: &dyn JobHost, id: &str) -> Result<Cancelled, SupervisorError> {
    let root = host
        .run_root(id)
        .ok_or_else(|| SupervisorError::not_found(format!("no run `{id}`")))?;
    let mut jobs = lock(&host.jobs().jobs);
    let job = jobs
        .get_mut(id)
        .ok_or_else(|| SupervisorError::not_found(format!("run `{id}` has no process job")))?;
    let outcome = match job.state {
        JobState::Queued => {
            job.state = JobState::Failed;
            job.error = Some(CANCELLED.into());
            job.updated_at = crate::store::now_rfc3339();
            write_job(&root, job).map_err(SupervisorError::internal)?;
            Cancelled::Dropped(job.clone())
        }
        JobState::Running => {
            job.cancelling = true;
            host.jobs().cancel.store(true, Ordering::SeqCst);
            Cancelled::Stopping(job.clone())
        }
        JobState::Done | JobState::Failed => {
            return Err(SupervisorError::conflict(format!(
                "run `{id}`'s process job has ended ({}): nothing to cancel",
                if job.state == JobState::Done {
                    "done"
                } else {
                    "failed"
                }
            )));
        }
    };
    let event = match &outcome {
        Cancelled::Dropped(j) | Cancelled::Stopping(j) => j.event(),
    };
    drop(jobs);
    host.hub().publish(Some(id), "process", event);
    Ok(outcome)
}

/// Starts the worker thread that runs the queued jobs one at a time, and
/// between them registers the frames of a capture whose job waits for it.
pub fn start_worker(host: Arc<dyn JobHost>) -> Result<(), String> {
    let pool = pipeline::background_pool("rigd-process")?;
    let d = host;
    std::thread::Builder::new()
        .name("rigd-process".into())
        .spawn(move || {
            pipeline::lower_priority();
            let mut streams = Streams::default();
            let ready = |job: &ProcessJob| d.ready_to_process(&job.run, job.after_capture);
            loop {
                let streamable = |job: &ProcessJob| {
                    job.after_capture
                        && job
                            .steps
                            .iter()
                            .any(|s| s.step == ProcessStep::Rectify && s.state != JobState::Done)
                        && streams.due(&job.run)
                        && d.capturing(&job.run)
                };
                match d.jobs().next_work(&ready, &streamable) {
                    Some(Work::Job(id)) => {
                        streams.runs.remove(&id);
                        run_job(&*d, &pool, &id);
                    }
                    Some(Work::Stream(id)) => streams.advance(&*d, &pool, &id),
                    None => break,
                }
            }
        })
        .map_err(|e| e.to_string())?;
    Ok(())
}

/// The rectification streams of capturing runs whose job waits for them.
#[derive(Default)]
struct Streams {
    runs: BTreeMap<String, pipeline::CaptureStream>,
    /// When a stream that found nothing new (or failed) looks again.
    not_before: BTreeMap<String, Instant>,
}

impl Streams {
    fn due(&self, id: &str) -> bool {
        self.not_before.get(id).is_none_or(|t| Instant::now() >= *t)
    }

    /// Registers the next batch of run `id`'s journaled frames.
    fn advance(&mut self, d: &dyn JobHost, pool: &rayon::ThreadPool, id: &str) {
        let retry_later = |streams: &mut Streams, e: String| {
            tracing::warn!(
                "registering {id}'s frames during the capture: {e}; again in {STREAM_RETRY:?}"
            );
            streams
                .not_before
                .insert(id.to_string(), Instant::now() + STREAM_RETRY);
        };
        let (Some(root), Some(job)) = (d.run_root(id), d.jobs().get(id)) else {
            return;
        };
        if !self.runs.contains_key(id) {
            match pipeline::CaptureStream::new(&root, &job.options) {
                Ok(Some(s)) => {
                    self.runs.insert(id.to_string(), s);
                }
                Ok(None) => return retry_later(self, "no rectify step".into()),
                Err(e) => return retry_later(self, e.to_string()),
            }
        }
        let Some(stream) = self.runs.get_mut(id) else {
            return;
        };
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            pool.install(|| stream.advance())
        }));
        match result {
            Ok(Ok(p)) => {
                if p.frames.done == job.streamed {
                    self.not_before
                        .insert(id.to_string(), Instant::now() + pipeline::STREAM_POLL);
                } else {
                    self.not_before.remove(id);
                    if let Some(event) = d.jobs().with_job(id, |j| {
                        j.streamed = p.frames.done;
                        j.slots_ahead = p.slots_ahead;
                        j.event()
                    }) {
                        d.hub().publish(Some(id), "process", event);
                    }
                }
            }
            Ok(Err(e)) => retry_later(self, e.to_string()),
            Err(_) => retry_later(self, "internal error (a panic; see the log)".into()),
        }
    }
}

fn run_job(d: &dyn JobHost, pool: &rayon::ThreadPool, id: &str) {
    let Some(root) = d.run_root(id) else {
        d.jobs().update(id, |j| {
            j.state = JobState::Failed;
            j.error = Some("the run is gone".into());
        });
        return;
    };
    let persist = |job: &ProcessJob| {
        if let Err(e) = write_job(&root, job) {
            tracing::warn!("process job of {id}: {e}");
        }
        d.hub().publish(Some(id), "process", job.event());
    };
    d.jobs().cancel.store(false, Ordering::SeqCst);
    let Some(job) = d.jobs().update(id, |j| {
        j.state = JobState::Running;
        j.cancelling = false;
        j.updated_at = crate::store::now_rfc3339();
    }) else {
        return;
    };
    persist(&job);
    for (k, status) in job.steps.iter().enumerate() {
        if status.state == JobState::Done {
            continue;
        }
        if d.jobs().stop.load(Ordering::SeqCst) {
            // Left running on disk: the next start resumes here.
            return;
        }
        if d.jobs().cancel.load(Ordering::SeqCst) {
            if let Some(j) = d.jobs().update(id, |j| {
                j.state = JobState::Failed;
                j.error = Some(CANCELLED.into());
                j.cancelling = false;
                j.updated_at = crate::store::now_rfc3339();
            }) {
                persist(&j);
            }
            return;
        }
        let step = status.step;
        if let Some(j) = d.jobs().update(id, |j| {
            j.steps[k].state = JobState::Running;
            j.updated_at = crate::store::now_rfc3339();
        }) {
            persist(&j);
        }
        let started = Instant::now();
        let last_event = Mutex::new(Instant::now() - EVENT_INTERVAL);
        let progress = |done: usize, total: usize| {
            let elapsed = started.elapsed().as_secs_f64();
            let eta =
                (done > 0 && total >= done).then(|| elapsed / done as f64 * (total - done) as f64);
            let due = {
                let mut last = lock(&last_event);
                let due = done == total || last.elapsed() >= EVENT_INTERVAL;
                if due {
                    *last = Instant::now();
                }
                due
            };
            // Called per frame: the job is only copied into an event when
            // one is due.
            let event = d.jobs().with_job(id, |j| {
                let s = &mut j.steps[k];
                s.done = done;
                s.total = total;
                s.elapsed_s = elapsed;
                s.eta_s = eta;
                due.then(|| j.event())
            });
            if let Some(event) = event.flatten() {
                d.hub().publish(Some(id), "process", event);
            }
        };
        let notes = |note: &str| {
            tracing::info!("processing {id}: {note}");
            if let Some(event) = d.jobs().with_job(id, |j| {
                j.steps[k].detail = Some(note.to_string());
                j.event()
            }) {
                d.hub().publish(Some(id), "process", event);
            }
        };
        let options = job.options.clone();
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            pool.install(|| {
                d.executor()
                    .run_step(&root, step, &options, &progress, &notes, &|| {
                        d.jobs().stop.load(Ordering::SeqCst)
                            || d.jobs().cancel.load(Ordering::SeqCst)
                    })
            })
        }));
        let outcome = match result {
            Ok(Ok(summary)) => Ok(summary),
            Ok(Err(SlurmError::Cancelled { .. })) if d.jobs().stop.load(Ordering::SeqCst) => {
                // The daemon is stopping: the job stays running on disk and
                // the next start submits what is not done again.
                return;
            }
            Ok(Err(e @ SlurmError::Cancelled { .. })) => {
                Err(format!("{}: {CANCELLED}: {e}", step.name()))
            }
            Ok(Err(e)) => Err(format!("{}: {e}", step.name())),
            Err(_) => Err(format!(
                "{}: internal error (a panic; see the log)",
                step.name()
            )),
        };
        let elapsed = started.elapsed().as_secs_f64();
        let failed = outcome.is_err();
        if let Some(j) = d.jobs().update(id, |j| {
            let s = &mut j.steps[k];
            s.elapsed_s = elapsed;
            s.eta_s = None;
            match outcome {
                Ok(summary) => {
                    s.state = JobState::Done;
                    s.done = s.total;
                    s.summary = Some(summary);
                }
                Err(e) => {
                    tracing::warn!("processing {id}: {e}");
                    s.state = JobState::Failed;
                    j.state = JobState::Failed;
                    j.error = Some(e);
                    j.cancelling = false;
                }
            }
            j.updated_at = crate::store::now_rfc3339();
        }) {
            persist(&j);
        }
        if failed {
            return;
        }
    }
    if let Some(j) = d.jobs().update(id, |j| {
        j.state = JobState::Done;
        // A cancel that came during the last local step came too late.
        j.cancelling = false;
        j.updated_at = crate::store::now_rfc3339();
    }) {
        persist(&j);
    }
}
