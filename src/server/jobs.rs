//! Process jobs: `POST /api/v1/runs/{id}/process` hands a finished run's
//! processing (rectify, btf, fit, mdf, photometric stereo) to the daemon.
//!
//! - One job runs at a time, in the order they were asked for, on a worker
//!   thread of its own beside the capture. Its threads run at a lower
//!   priority (nice 10), so a capture's device calls are scheduled first.
//! - Each job is kept in `RUN/processed/job.json` and run by
//!   [`job::run_job`], as `rigd run --process` runs its own: a daemon that
//!   stops or dies mid-job finds the job at its next start and resumes it.
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
use super::wire::RunView;
use crate::model::run_state::RunState;
use crate::postprocess::executor::ProcessingConfig;
use crate::postprocess::frames::RunFrames;
use crate::postprocess::job::{
    self, read_job, write_job, JobControl, JobState, ProcessJob, CANCELLED,
};
use crate::postprocess::pipeline::{self, ProcessOptions, ProcessStep, RunFacts};
use crate::store::StoreError;
use rigd_core::sync::lock;

/// How often an idle worker looks at the queue without being woken, and
/// at a capturing run's journal for frames to register.
const IDLE_RECHECK: Duration = pipeline::STREAM_POLL;
/// How long a stream that failed waits before it tries again.
const STREAM_RETRY: Duration = Duration::from_secs(30);

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
                streams.forget_ended(d.jobs());
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
    /// Forgets the runs whose job no longer waits for its capture
    /// (cancelled, or gone), so a daemon that runs for months holds the
    /// streams of the captures it still registers and no others.
    fn forget_ended(&mut self, jobs: &Jobs) {
        let waits = |id: &String| {
            jobs.get(id)
                .is_some_and(|j| j.state == JobState::Queued && j.after_capture)
        };
        self.runs.retain(|id, _| waits(id));
        self.not_before.retain(|id, _| waits(id));
    }

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
        let ctl = DaemonJob { d, id };
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            pool.install(|| job::stream_batch(&ctl, stream))
        }));
        match result {
            Ok(Ok(p)) => {
                if p.frames.done == job.streamed {
                    self.not_before
                        .insert(id.to_string(), Instant::now() + pipeline::STREAM_POLL);
                } else {
                    self.not_before.remove(id);
                }
            }
            Ok(Err(e)) => retry_later(self, e.to_string()),
            Err(_) => retry_later(self, "internal error (a panic; see the log)".into()),
        }
    }
}

/// A daemon's job as [`job::run_job`] sees it: kept in the jobs' table,
/// its changes published as `process` events.
struct DaemonJob<'a> {
    d: &'a dyn JobHost,
    id: &'a str,
}

impl JobControl for DaemonJob<'_> {
    fn with_job<T>(&self, f: impl FnOnce(&mut ProcessJob) -> T) -> Option<T> {
        self.d.jobs().with_job(self.id, f)
    }

    fn publish(&self, job: &ProcessJob) {
        self.d.hub().publish(Some(self.id), "process", job.event());
    }

    fn stopping(&self) -> bool {
        self.d.jobs().stop.load(Ordering::SeqCst)
    }

    fn cancelled(&self) -> bool {
        self.d.jobs().cancel.load(Ordering::SeqCst)
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
    d.jobs().cancel.store(false, Ordering::SeqCst);
    let ctl = DaemonJob { d, id };
    pool.install(|| job::run_job(&ctl, &root, d.executor()));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_worker_forgets_the_streams_of_jobs_that_no_longer_wait_for_their_capture() {
        let jobs = Jobs::default();
        let job = |state: JobState, after_capture: bool| {
            let mut job = ProcessJob::new("run", ProcessOptions::default());
            job.state = state;
            job.after_capture = after_capture;
            job
        };
        for (id, j) in [
            ("waits", job(JobState::Queued, true)),
            ("cancelled", job(JobState::Failed, true)),
            ("running", job(JobState::Running, true)),
            ("asked-after", job(JobState::Queued, false)),
        ] {
            lock(&jobs.jobs).insert(id.to_string(), j);
        }
        let mut streams = Streams::default();
        let later = Instant::now() + STREAM_RETRY;
        for id in ["waits", "cancelled", "running", "asked-after", "gone"] {
            streams.not_before.insert(id.to_string(), later);
        }
        streams.forget_ended(&jobs);
        let kept: Vec<&String> = streams.not_before.keys().collect();
        assert_eq!(kept, ["waits"]);
        assert!(!streams.due("waits"));
    }
}
