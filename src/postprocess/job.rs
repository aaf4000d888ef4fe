//! A run's process job: the processing asked for with a capture, done
//! during it ([`stream_during_capture`], [`stream_batch`]) and after it
//! ([`run_job`]), for `rigd run --process` and the daemon alike.
//!
//! - The job is kept in `RUN/processed/job.json`, rewritten atomically at
//!   every step's start and end. A job cut short (a kill, a stopping
//!   daemon) is found there and resumed: the steps done are kept, the step
//!   that was running runs again. Each step writes its index last, so a
//!   cut step leaves nothing a reader would take for a result, and
//!   `rectify` keeps each frame's first pass.
//! - Where the job lives while it runs, and where its changes go, is the
//!   caller's ([`JobControl`]): the daemon keeps its jobs in a table and
//!   publishes events; the command line keeps one and draws it.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::executor::ProcessingConfig;
use super::pipeline::{CaptureProgress, CaptureStream, ProcessOptions, ProcessStep, STREAM_POLL};
use super::slurm::SlurmError;
use super::ProcessError;
use rigd_core::sync::lock;

/// The job's file in `RUN/processed/`.
pub const JOB_FILE: &str = "job.json";
/// Least wall time between two progress reports of a step.
pub const EVENT_INTERVAL: Duration = Duration::from_millis(500);
/// The error of a job the operator cancelled.
pub const CANCELLED: &str = "cancelled by the operator";

/// Where a job or one of its steps is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    /// Waiting for its turn (a step: not started).
    Queued,
    /// Running now.
    Running,
    /// Finished.
    Done,
    /// Stopped by an error (`error` says which).
    Failed,
}

/// One step of a job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct StepStatus {
    /// The step.
    pub step: ProcessStep,
    /// Where it is.
    pub state: JobState,
    /// Units done: frames (rectify), view slots (btf, fit), sweeps (mdf),
    /// rows (photometric-stereo).
    pub done: usize,
    /// Units in all; 0 until the step reports.
    pub total: usize,
    /// Wall seconds the step has run (this attempt).
    pub elapsed_s: f64,
    /// Estimated wall seconds left in this step, while it runs.
    pub eta_s: Option<f64>,
    /// What the step wrote, when done.
    pub summary: Option<String>,
    /// The executor's latest word while the step runs on Slurm: the job
    /// and its array, a task submitted again. `done` and `total` count
    /// the array's tasks until they are all done, then the join's units.
    #[serde(default)]
    pub detail: Option<String>,
}

/// A run's process job, as `RUN/processed/job.json` keeps it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ProcessJob {
    /// The run.
    pub run: String,
    /// The steps and options, defaults filled in.
    pub options: ProcessOptions,
    /// Where the job is.
    pub state: JobState,
    /// Its steps, in running order.
    pub steps: Vec<StepStatus>,
    /// Why it failed.
    pub error: Option<String>,
    /// When it was asked for, RFC 3339 UTC.
    pub created_at: String,
    /// When it last changed state, RFC 3339 UTC.
    pub updated_at: String,
    /// How often it was taken up again after it was cut short.
    pub resumed: u32,
    /// Asked for with the run (`process` in `POST /runs`, `rigd run
    /// --process`): it waits for the capture to complete or be aborted.
    #[serde(default)]
    pub after_capture: bool,
    /// Frames from the start of the capture whose registration (the
    /// `rectify` step's first pass) was done while the capture ran; the
    /// step takes them as they are.
    #[serde(default)]
    pub streamed: usize,
    /// View slots compressed while the capture ran (the `btf` step's work
    /// for each slot whose lights were all in); the step takes them.
    #[serde(default)]
    pub slots_ahead: usize,
    /// The operator asked to cancel it while it ran: a step on Slurm stops
    /// at once (`scancel`), a local step at its end.
    #[serde(default)]
    pub cancelling: bool,
}

impl ProcessJob {
    /// A queued job of `options` for run `run`.
    pub fn new(run: &str, options: ProcessOptions) -> ProcessJob {
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
    pub fn requeue(&mut self) {
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

    /// The step running now, or the one that failed.
    pub fn current(&self) -> Option<&StepStatus> {
        self.steps
            .iter()
            .find(|s| s.state == JobState::Running || s.state == JobState::Failed)
    }

    /// The job as a `process` event's data.
    pub fn event(&self) -> serde_json::Value {
        let current = self.current();
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
/// (then it is logged, and the run can be processed afresh). A file that
/// is not a regular one (a FIFO) or is implausibly large is never waited
/// on or read whole.
pub fn read_job(root: &Path) -> Option<ProcessJob> {
    let path = job_path(root);
    let bytes = match rigd_core::read::read_bounded(&path, rigd_core::read::TEXT_LIMIT) {
        Ok(bytes) => bytes,
        Err(e) if e.io_kind() == Some(std::io::ErrorKind::NotFound) => return None,
        Err(e) => {
            tracing::warn!("{e}; ignored");
            return None;
        }
    };
    match serde_json::from_slice(&bytes) {
        Ok(job) => Some(job),
        Err(e) => {
            tracing::warn!("{}: {e}; ignored", path.display());
            None
        }
    }
}

/// Writes a run's job file atomically.
pub fn write_job(root: &Path, job: &ProcessJob) -> Result<(), String> {
    let path = job_path(root);
    let dir = crate::store::processed::processed_dir(root);
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut json = serde_json::to_vec_pretty(job).map_err(|e| e.to_string())?;
    json.push(b'\n');
    crate::store::write_atomic(&path, &json).map_err(|e| format!("{}: {e}", path.display()))
}

/// Where a job lives while it runs, and where its changes go.
pub trait JobControl: Sync {
    /// Applies `f` to the job where it is kept; None when it is gone.
    fn with_job<T>(&self, f: impl FnOnce(&mut ProcessJob) -> T) -> Option<T>;
    /// The job as it is now: after a change of state (already in
    /// `job.json`), after a batch registered during the capture, and while
    /// a step runs at most every [`EVENT_INTERVAL`] and at its last unit.
    fn publish(&self, job: &ProcessJob);
    /// The daemon is stopping: the job is left running on disk, for the
    /// next start to resume.
    fn stopping(&self) -> bool {
        false
    }
    /// The operator cancelled the job.
    fn cancelled(&self) -> bool {
        false
    }
}

/// How [`run_job`] ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum JobEnd {
    /// Every step is done.
    Done,
    /// A step failed or the job was cancelled: the error, as the job keeps it.
    Failed(String),
    /// Left for the next start ([`JobControl::stopping`]), or the job is gone.
    Stopped,
}

/// Runs the job's steps that are not done, in order, with `executor`,
/// keeping `RUN/processed/job.json` (at `root`) up to date. Call it once
/// the capture has ended; a step that panics fails the job.
pub fn run_job<C: JobControl>(ctl: &C, root: &Path, executor: &ProcessingConfig) -> JobEnd {
    let persist = |job: &ProcessJob| {
        if let Err(e) = write_job(root, job) {
            tracing::warn!("process job of {}: {e}", job.run);
        }
        ctl.publish(job);
    };
    let update = |f: &mut dyn FnMut(&mut ProcessJob)| -> Option<ProcessJob> {
        let job = ctl.with_job(|j| {
            f(j);
            j.updated_at = crate::store::now_rfc3339();
            j.clone()
        })?;
        persist(&job);
        Some(job)
    };
    // Held to the job's end: no other processor writes the run's files
    // meanwhile. Refused, the job fails in memory only: its file belongs
    // to whoever holds the run.
    let _processing = match crate::store::ProcessingLock::acquire(root) {
        Ok(lock) => lock,
        Err(e) => {
            let error = e.to_string();
            if let Some(job) = ctl.with_job(|j| {
                j.state = JobState::Failed;
                j.error = Some(error.clone());
                j.cancelling = false;
                j.clone()
            }) {
                ctl.publish(&job);
            }
            return JobEnd::Failed(error);
        }
    };
    let Some(job) = update(&mut |j| {
        j.state = JobState::Running;
        j.cancelling = false;
    }) else {
        return JobEnd::Stopped;
    };
    let id = job.run.clone();
    for (k, status) in job.steps.iter().enumerate() {
        if status.state == JobState::Done {
            continue;
        }
        if ctl.stopping() {
            return JobEnd::Stopped;
        }
        if ctl.cancelled() {
            update(&mut |j| {
                j.state = JobState::Failed;
                j.error = Some(CANCELLED.into());
                j.cancelling = false;
            });
            return JobEnd::Failed(CANCELLED.into());
        }
        let step = status.step;
        update(&mut |j| j.steps[k].state = JobState::Running);
        let started = Instant::now();
        let last_report = Mutex::new(Instant::now() - EVENT_INTERVAL);
        let progress = |done: usize, total: usize| {
            let elapsed = started.elapsed().as_secs_f64();
            let eta =
                (done > 0 && total >= done).then(|| elapsed / done as f64 * (total - done) as f64);
            let due = {
                let mut last = lock(&last_report);
                let due = done == total || last.elapsed() >= EVENT_INTERVAL;
                if due {
                    *last = Instant::now();
                }
                due
            };
            // Called per unit: the job is copied only when a report is due.
            let job = ctl.with_job(|j| {
                let s = &mut j.steps[k];
                s.done = done;
                s.total = total;
                s.elapsed_s = elapsed;
                s.eta_s = eta;
                due.then(|| j.clone())
            });
            if let Some(job) = job.flatten() {
                ctl.publish(&job);
            }
        };
        let notes = |note: &str| {
            tracing::info!("processing {id}: {note}");
            if let Some(job) = ctl.with_job(|j| {
                j.steps[k].detail = Some(note.to_string());
                j.clone()
            }) {
                ctl.publish(&job);
            }
        };
        let cancel = || ctl.stopping() || ctl.cancelled();
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            executor.run_step(root, step, &job.options, &progress, &notes, &cancel)
        }));
        let outcome = match result {
            Ok(Ok(summary)) => Ok(summary),
            // Stopping: the job stays running on disk, and the next start
            // submits what is not done again.
            Ok(Err(SlurmError::Cancelled { .. })) if ctl.stopping() => return JobEnd::Stopped,
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
        let failure = outcome.as_ref().err().cloned();
        if let Some(e) = &failure {
            tracing::warn!("processing {id}: {e}");
        }
        let mut outcome = Some(outcome);
        update(&mut |j| {
            let s = &mut j.steps[k];
            s.elapsed_s = elapsed;
            s.eta_s = None;
            match outcome.take() {
                Some(Ok(summary)) => {
                    s.state = JobState::Done;
                    s.done = s.total;
                    s.summary = Some(summary);
                }
                Some(Err(e)) => {
                    s.state = JobState::Failed;
                    j.state = JobState::Failed;
                    j.error = Some(e);
                    j.cancelling = false;
                }
                None => {}
            }
        });
        if let Some(error) = failure {
            return JobEnd::Failed(error);
        }
    }
    update(&mut |j| {
        j.state = JobState::Done;
        // A cancel that came during the last local step came too late.
        j.cancelling = false;
    });
    JobEnd::Done
}

/// Registers the next batch of the capture's journaled frames with
/// `stream` (and compresses the view slots they completed), on the current
/// rayon pool; records what is done in the job and publishes it when it
/// moved.
pub fn stream_batch<C: JobControl>(
    ctl: &C,
    stream: &mut CaptureStream,
) -> Result<CaptureProgress, ProcessError> {
    // Per batch, so that nothing stays locked between them.
    let _processing = crate::store::ProcessingLock::acquire(stream.root())?;
    let p = stream.advance()?;
    let moved = ctl.with_job(|j| {
        let moved = (j.streamed, j.slots_ahead) != (p.frames.done, p.slots_ahead);
        j.streamed = p.frames.done;
        j.slots_ahead = p.slots_ahead;
        moved.then(|| j.clone())
    });
    if let Some(job) = moved.flatten() {
        ctl.publish(&job);
    }
    Ok(p)
}

/// Registers the capture's frames as they are journaled
/// ([`stream_batch`]) on `pool` until `capturing` turns false; the daemon
/// interleaves the same batches with its queue. Returns the last progress;
/// None when there is nothing to stream (no `rectify` step).
pub fn stream_during_capture<C: JobControl>(
    ctl: &C,
    root: &Path,
    pool: &rayon::ThreadPool,
    capturing: &std::sync::atomic::AtomicBool,
) -> Result<Option<CaptureProgress>, ProcessError> {
    use std::sync::atomic::Ordering;
    let Some(options) = ctl.with_job(|j| j.options.clone()) else {
        return Ok(None);
    };
    let Some(mut stream) = CaptureStream::new(root, &options)? else {
        return Ok(None);
    };
    let mut last: Option<CaptureProgress> = None;
    while capturing.load(Ordering::SeqCst) {
        let before = last.map_or(0, |l| l.frames.done);
        match pool.install(|| stream_batch(ctl, &mut stream)) {
            Ok(p) => last = Some(p),
            // Another processor has the run for now: look again later.
            Err(ProcessError::Store(crate::store::StoreError::ProcessingBusy(_))) => {}
            Err(e) => return Err(e),
        }
        if last.map_or(0, |l| l.frames.done) == before {
            let idle = Instant::now();
            while capturing.load(Ordering::SeqCst) && idle.elapsed() < STREAM_POLL {
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    }
    Ok(last)
}

/// One job kept in memory, for a caller that runs a single job (`rigd run
/// --process`): its changes go to `on_change`.
pub struct OwnJob<F> {
    job: Mutex<ProcessJob>,
    on_change: F,
}

impl<F: Fn(&ProcessJob) + Sync> OwnJob<F> {
    /// Holds `job`; `on_change` sees each change [`JobControl::publish`]
    /// reports.
    pub fn new(job: ProcessJob, on_change: F) -> OwnJob<F> {
        OwnJob {
            job: Mutex::new(job),
            on_change,
        }
    }
}

impl<F: Fn(&ProcessJob) + Sync> JobControl for OwnJob<F> {
    fn with_job<T>(&self, f: impl FnOnce(&mut ProcessJob) -> T) -> Option<T> {
        Some(f(&mut lock(&self.job)))
    }

    fn publish(&self, job: &ProcessJob) {
        (self.on_change)(job);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job_of(steps: &[ProcessStep]) -> ProcessJob {
        let options = ProcessOptions {
            steps: steps.to_vec(),
            ..ProcessOptions::default()
        };
        ProcessJob::new("run", options)
    }

    /// A folder with a `run.json` that holds nothing usable: a run to
    /// lock, with no frames to process.
    fn empty_run() -> tempfile::TempDir {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(dir.path().join(crate::store::RUN_FILE), "{}").expect("run.json");
        dir
    }

    /// A job on a run that has no frames fails at its first step, says
    /// which in the job file, and publishes the failure; run again, it
    /// starts that step over and keeps the error's step.
    #[test]
    fn a_failing_step_fails_the_job_and_the_file_says_which() {
        let dir = empty_run();
        let seen = Mutex::new(Vec::new());
        let ctl = OwnJob::new(job_of(&[ProcessStep::Rectify, ProcessStep::Btf]), |j| {
            lock(&seen).push(j.state)
        });
        let end = run_job(&ctl, dir.path(), &ProcessingConfig::default());
        let JobEnd::Failed(error) = end else {
            panic!("{end:?}");
        };
        assert!(error.starts_with("rectify: "), "{error}");
        let kept = read_job(dir.path()).expect("job.json");
        assert_eq!(kept.state, JobState::Failed);
        assert_eq!(kept.steps[0].state, JobState::Failed);
        assert_eq!(kept.steps[1].state, JobState::Queued);
        assert_eq!(lock(&seen).last(), Some(&JobState::Failed));
    }

    /// Steps done before are not run again: a job whose only step is done
    /// ends done at once, without touching the (empty) run.
    #[test]
    fn steps_done_before_are_kept() {
        let dir = empty_run();
        let mut job = job_of(&[ProcessStep::Rectify]);
        job.steps[0].state = JobState::Done;
        job.steps[0].summary = Some("before".into());
        let ctl = OwnJob::new(job, |_| {});
        assert_eq!(
            run_job(&ctl, dir.path(), &ProcessingConfig::default()),
            JobEnd::Done
        );
        let kept = read_job(dir.path()).expect("job.json");
        assert_eq!(kept.state, JobState::Done);
        assert_eq!(kept.steps[0].summary.as_deref(), Some("before"));
    }

    /// A run another processor holds: the job fails naming it, in memory
    /// only, and writes nothing into the run.
    #[test]
    fn a_job_on_a_run_another_processor_holds_fails_and_writes_nothing() {
        let dir = empty_run();
        let held = crate::store::ProcessingLock::acquire(dir.path()).expect("the lock");
        let seen = Mutex::new(Vec::new());
        let ctl = OwnJob::new(job_of(&[ProcessStep::Rectify]), |j| {
            lock(&seen).push(j.state)
        });
        let end = run_job(&ctl, dir.path(), &ProcessingConfig::default());
        let JobEnd::Failed(error) = end else {
            panic!("{end:?}");
        };
        assert!(
            error.contains("another rigd is processing this run"),
            "{error}"
        );
        assert_eq!(lock(&seen).as_slice(), [JobState::Failed]);
        assert!(read_job(dir.path()).is_none(), "no job file written");
        // Let go, the job gets to its step (which fails on the empty run).
        drop(held);
        let end = run_job(&ctl, dir.path(), &ProcessingConfig::default());
        assert!(
            matches!(&end, JobEnd::Failed(e) if e.starts_with("rectify: ")),
            "{end:?}"
        );
    }

    /// A job file that is garbage or a FIFO with no writer is no job: the
    /// read neither fails loudly nor blocks.
    #[test]
    fn a_broken_job_file_reads_as_none_without_blocking() {
        let dir = tempfile::tempdir().expect("tempdir");
        assert!(read_job(dir.path()).is_none());
        let path = job_path(dir.path());
        std::fs::create_dir_all(path.parent().expect("processed/")).expect("processed/");
        std::fs::write(&path, b"{\"run\": 3").expect("write");
        assert!(read_job(dir.path()).is_none());
        std::fs::remove_file(&path).expect("remove");
        let made = std::process::Command::new("mkfifo")
            .arg(&path)
            .status()
            .expect("mkfifo");
        assert!(made.success());
        assert!(read_job(dir.path()).is_none());
    }

    /// A requeued job keeps its done steps and starts the others over.
    #[test]
    fn requeue_keeps_done_steps() {
        let mut job = job_of(&[ProcessStep::Rectify, ProcessStep::Btf]);
        job.state = JobState::Failed;
        job.error = Some("btf: broken".into());
        job.steps[0].state = JobState::Done;
        job.steps[1].state = JobState::Failed;
        job.steps[1].done = 3;
        job.requeue();
        assert_eq!(job.state, JobState::Queued);
        assert_eq!(job.error, None);
        assert_eq!(job.steps[0].state, JobState::Done);
        assert_eq!(job.steps[1].state, JobState::Queued);
        assert_eq!(job.steps[1].done, 0);
    }
}
