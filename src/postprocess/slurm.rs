//! Processing on a lab's Slurm cluster: each part of a step
//! ([`super::parts`]) is a task of a Slurm job array that runs `rigd process
//! part` on the filesystem the cluster's nodes share. The run directory is
//! the shared state: a task keeps its result where the step finds it and
//! leaves a marker in `processed/slurm/<step>/done/` when it is complete;
//! nothing else is stored anywhere.
//!
//! rigd shells out to Slurm's own client commands (`sbatch --parsable`,
//! `squeue`, `sacct`, `scancel`, `sinfo`) rather than using `slurmrestd`:
//! they are on every login node of every Slurm cluster, authenticate as
//! the user through munge with nothing to configure, and need no token or
//! REST daemon that many sites do not run (docs/scaling.md says more).
//!
//! Following a step: `squeue` names the tasks still pending or running; a
//! task that has left the queue without its marker failed (a node that
//! died, `scancel` of the task, a crash). `sacct` tells why where the
//! cluster keeps accounting, the task's log otherwise. A failed task is
//! submitted again, up to [`SlurmConfig::max_retries`] times. When every
//! part is done, the step runs once where rigd runs, joining the parts:
//! the same code as a local run, so the same files.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::parts::{self, Split};
use super::pipeline::{ProcessOptions, ProcessStep, StepProgress};
use super::ProcessError;

/// Where a step's Slurm jobs keep their files, inside the run.
pub const SLURM_DIR: &str = "slurm";
/// How long a Slurm client command may take.
const COMMAND_DEADLINE: Duration = Duration::from_secs(30);
/// How long the queue may go unanswered (a controller restarting) before
/// the step fails.
const QUEUE_SILENCE: Duration = Duration::from_secs(120);
/// How long a task must be out of the queue without its marker before it
/// counts as failed: a shared filesystem may show a file written on a
/// node a moment late.
const MISSING_GRACE: Duration = Duration::from_secs(3);

/// How rigd runs processing on Slurm: the options of `rigd process …
/// --executor slurm` and of the daemon's `[processing]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct SlurmConfig {
    /// The partition to submit to [default: the cluster's default].
    pub partition: Option<String>,
    /// The account to charge [default: the user's default].
    pub account: Option<String>,
    /// More `sbatch` options, split as a shell would, e.g.
    /// `"--time=00:30:00 --mem=4G --cpus-per-task=4"`.
    pub sbatch_options: String,
    /// Folders the cluster's nodes mount at the same path; the run
    /// directory must be inside one.
    #[schema(value_type = Vec<String>)]
    pub shared_paths: Vec<PathBuf>,
    /// Frames per task of `rectify`.
    pub frames_per_task: usize,
    /// View slots per task of `btf` and `fit`. A task costs its start (a
    /// second or more on a busy cluster), so a task should carry seconds of
    /// work: a few slots of small textures, one of large ones.
    pub slots_per_task: usize,
    /// Times a failed task is submitted again before the step fails.
    pub max_retries: u32,
    /// The `rigd` the tasks run, at a path every node sees [default: this
    /// executable].
    #[schema(value_type = Option<String>)]
    pub rigd: Option<PathBuf>,
    /// Seconds between two looks at the queue.
    pub poll_s: f64,
}

impl Default for SlurmConfig {
    fn default() -> Self {
        SlurmConfig {
            partition: None,
            account: None,
            sbatch_options: String::new(),
            shared_paths: Vec::new(),
            frames_per_task: 256,
            slots_per_task: 4,
            max_retries: 2,
            rigd: None,
            poll_s: 1.0,
        }
    }
}

/// Why processing on Slurm could not start or did not finish.
#[derive(Debug, thiserror::Error)]
pub enum SlurmError {
    /// A Slurm client command is missing.
    #[error("`{0}` is not on the PATH: processing on Slurm needs Slurm's client commands (sbatch, squeue, scancel, sinfo; Debian: slurm-client) on this machine")]
    NotInstalled(&'static str),
    /// No shared path is configured.
    #[error("no shared path is set: name the folders the cluster's nodes mount at the same path (--shared-path DIR, or shared_paths in [processing.slurm]), the run directory must be inside one")]
    NoSharedPath,
    /// The run is not where the nodes can read it.
    #[error("the run directory {run} is not under a shared path ({shared}): the cluster's nodes could not read it; move the run there or add its filesystem to the shared paths")]
    NotShared {
        /// The run directory.
        run: PathBuf,
        /// The shared paths configured.
        shared: String,
    },
    /// The partition is not one of the cluster's.
    #[error("unknown partition `{name}`: the cluster has {known}")]
    UnknownPartition {
        /// The partition asked for.
        name: String,
        /// The cluster's partitions.
        known: String,
    },
    /// A setting that cannot work.
    #[error("{0}")]
    Invalid(String),
    /// A Slurm command failed or did not answer.
    #[error("`{command}` failed: {message}")]
    Command {
        /// The command line.
        command: String,
        /// What it said.
        message: String,
    },
    /// A task failed more often than allowed.
    #[error("{step}: task {part} of {parts} failed {attempts} times (Slurm job {job}): {reason}; its log is {log}")]
    TaskFailed {
        /// The step.
        step: &'static str,
        /// The task (part) index.
        part: usize,
        /// Parts of the step.
        parts: usize,
        /// Submissions of the task.
        attempts: u32,
        /// Its last job id.
        job: String,
        /// Why it failed, as Slurm or its log says.
        reason: String,
        /// Its log file.
        log: String,
    },
    /// The user stopped the processing.
    #[error("cancelled: Slurm job(s) {jobs} cancelled with scancel")]
    Cancelled {
        /// The jobs cancelled.
        jobs: String,
    },
    /// The step itself failed (joining the parts, or bad data).
    #[error(transparent)]
    Process(#[from] ProcessError),
}

impl SlurmError {
    /// The configuration or the request is at fault (nothing was
    /// submitted), not the cluster.
    pub fn is_bad_config(&self) -> bool {
        matches!(
            self,
            SlurmError::NotInstalled(_)
                | SlurmError::NoSharedPath
                | SlurmError::NotShared { .. }
                | SlurmError::UnknownPartition { .. }
                | SlurmError::Invalid(_)
        )
    }
}

/// Whether the user asked to stop: checked between two looks at the queue.
pub type Cancel<'a> = &'a (dyn Fn() -> bool + Sync);

/// What a step on Slurm tells as it goes, besides its progress: each
/// submission and each task submitted again.
pub type Notes<'a> = &'a (dyn Fn(&str) + Sync);

/// The folder of `step`'s Slurm jobs in the run at `root`.
pub fn job_dir(root: &Path, step: ProcessStep) -> PathBuf {
    crate::store::processed::processed_dir(root)
        .join(SLURM_DIR)
        .join(step.name())
}

fn marker_path(root: &Path, step: ProcessStep, part: usize) -> PathBuf {
    job_dir(root, step).join("done").join(format!("{part:05}"))
}

/// Marks part `part` of `step` complete (the last thing a task does).
pub fn mark_done(
    root: &Path,
    step: ProcessStep,
    part: usize,
    summary: &str,
) -> Result<(), ProcessError> {
    let path = marker_path(root, step, part);
    if let Some(dir) = path.parent() {
        crate::postprocess::create_dir(dir)?;
    }
    crate::store::write_atomic(&path, summary.as_bytes())?;
    Ok(())
}

fn done_parts(root: &Path, step: ProcessStep) -> BTreeSet<usize> {
    std::fs::read_dir(job_dir(root, step).join("done"))
        .map(|entries| {
            entries
                .filter_map(|e| e.ok()?.file_name().to_str()?.parse().ok())
                .collect()
        })
        .unwrap_or_default()
}

/// `program` on the PATH, if it is there.
fn on_path(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(program))
        .find(|p| p.is_file())
}

/// Runs a Slurm command with [`COMMAND_DEADLINE`]; its standard output, or
/// why it failed.
fn slurm_command(program: &str, args: &[String]) -> Result<String, SlurmError> {
    let line = std::iter::once(program.to_string())
        .chain(args.iter().cloned())
        .collect::<Vec<_>>()
        .join(" ");
    let failed = |message: String| SlurmError::Command {
        command: line.clone(),
        message,
    };
    let mut child = Command::new(program)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| failed(e.to_string()))?;
    let started = Instant::now();
    loop {
        match child.try_wait() {
            Ok(Some(_)) => break,
            Ok(None) if started.elapsed() > COMMAND_DEADLINE => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(failed(format!(
                    "no answer within {} s",
                    COMMAND_DEADLINE.as_secs()
                )));
            }
            Ok(None) => std::thread::sleep(Duration::from_millis(10)),
            Err(e) => return Err(failed(e.to_string())),
        }
    }
    let out = child
        .wait_with_output()
        .map_err(|e| failed(e.to_string()))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr).trim().to_string();
        return Err(failed(if err.is_empty() {
            out.status.to_string()
        } else {
            err
        }));
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// Quotes `s` for a POSIX shell.
fn shell_quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

/// `0-80` or `3,5,9`: Slurm's `--array` for these task indices.
fn array_spec(parts: &[usize]) -> String {
    let contiguous = parts.windows(2).all(|w| w[1] == w[0] + 1);
    match (parts.first(), parts.last()) {
        (Some(first), Some(last)) if contiguous && first != last => format!("{first}-{last}"),
        _ => parts
            .iter()
            .map(usize::to_string)
            .collect::<Vec<_>>()
            .join(","),
    }
}

impl SlurmConfig {
    /// The parts' sizes: one part per task.
    pub fn part_sizes(&self) -> parts::PartSizes {
        parts::PartSizes {
            frames: self.frames_per_task,
            slots: self.slots_per_task,
        }
    }

    /// The `rigd` the tasks run.
    fn rigd_path(&self) -> Result<PathBuf, SlurmError> {
        match &self.rigd {
            Some(p) => Ok(p.clone()),
            None => std::env::current_exe().map_err(|e| {
                SlurmError::Invalid(format!("cannot tell this executable's path: {e}"))
            }),
        }
    }

    fn extra_options(&self) -> Result<Vec<String>, SlurmError> {
        shlex::split(&self.sbatch_options).ok_or_else(|| {
            SlurmError::Invalid(format!(
                "sbatch options `{}`: a quote is not closed",
                self.sbatch_options
            ))
        })
    }

    /// Everything that can be checked before a job is submitted: the
    /// settings, Slurm's commands on the PATH, the run directory under a
    /// shared path, the `rigd` executable, and the partition.
    pub fn check(&self, root: &Path) -> Result<(), SlurmError> {
        if self.frames_per_task == 0 || self.slots_per_task == 0 {
            return Err(SlurmError::Invalid(format!(
                "{} frames and {} view slots per task: expected at least 1 of each",
                self.frames_per_task, self.slots_per_task
            )));
        }
        if self.max_retries > 10 {
            return Err(SlurmError::Invalid(format!(
                "max retries {}: expected 0 … 10",
                self.max_retries
            )));
        }
        if !(self.poll_s.is_finite() && (0.05..=60.0).contains(&self.poll_s)) {
            return Err(SlurmError::Invalid(format!(
                "poll interval {} s: expected 0.05 … 60",
                self.poll_s
            )));
        }
        let extra = self.extra_options()?;
        if let Some(bad) = extra.iter().find(|o| {
            ["--array", "-a", "--parsable", "--output", "-o", "--wrap"]
                .iter()
                .any(|own| o.as_str() == *own || o.starts_with(&format!("{own}=")))
        }) {
            return Err(SlurmError::Invalid(format!(
                "sbatch option `{bad}`: rigd sets it itself"
            )));
        }
        for program in ["sbatch", "squeue", "scancel", "sinfo"] {
            if on_path(program).is_none() {
                return Err(SlurmError::NotInstalled(program));
            }
        }
        if self.shared_paths.is_empty() {
            return Err(SlurmError::NoSharedPath);
        }
        let run = root
            .canonicalize()
            .map_err(|e| SlurmError::Invalid(format!("run directory {}: {e}", root.display())))?;
        let shared: Vec<PathBuf> = self
            .shared_paths
            .iter()
            .filter_map(|p| p.canonicalize().ok())
            .collect();
        if !shared.iter().any(|s| run.starts_with(s)) {
            return Err(SlurmError::NotShared {
                run,
                shared: self
                    .shared_paths
                    .iter()
                    .map(|p| p.display().to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        }
        let rigd = self.rigd_path()?;
        if !rigd.is_file() {
            return Err(SlurmError::Invalid(format!(
                "the rigd the tasks would run, {}, is not a file",
                rigd.display()
            )));
        }
        let listed = slurm_command("sinfo", &["-h".into(), "-o".into(), "%P".into()])?;
        let partitions: Vec<&str> = listed
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .collect();
        let known = || {
            if partitions.is_empty() {
                "no partition".to_string()
            } else {
                partitions.join(", ")
            }
        };
        match &self.partition {
            Some(p) if !partitions.iter().any(|q| q.trim_end_matches('*') == p) => {
                Err(SlurmError::UnknownPartition {
                    name: p.clone(),
                    known: known(),
                })
            }
            None if !partitions.iter().any(|q| q.ends_with('*')) => {
                Err(SlurmError::Invalid(format!(
                    "the cluster has no default partition: name one of {}",
                    known()
                )))
            }
            _ => Ok(()),
        }
    }

    /// Runs `step` on the run at `root` as a Slurm job array, then joins
    /// its parts here; returns the step's summary. `progress` follows the
    /// tasks done, then the join; `notes` tells of each submission;
    /// `cancel` turning true cancels the jobs with `scancel`.
    pub fn run_step(
        &self,
        root: &Path,
        step: ProcessStep,
        opts: &ProcessOptions,
        progress: StepProgress<'_>,
        notes: Notes<'_>,
        cancel: Cancel<'_>,
    ) -> Result<String, SlurmError> {
        self.check(root)?;
        let split = parts::split(root, step, opts, self.part_sizes())?;
        let parts = split.parts();
        let dir = job_dir(root, step);
        // A job dir from an earlier run of the step holds markers of other
        // settings; the parts' own results are checked by their keys.
        match std::fs::remove_dir_all(&dir) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => {
                return Err(SlurmError::Invalid(format!("{}: {e}", dir.display())));
            }
        }
        let io = |path: &Path, e: std::io::Error| {
            SlurmError::Process(ProcessError::io(path, "write", e))
        };
        std::fs::create_dir_all(dir.join("done")).map_err(|e| io(&dir, e))?;
        let options_path = dir.join("options.json");
        let json = serde_json::to_vec_pretty(opts)
            .map_err(|e| SlurmError::Invalid(format!("options: {e}")))?;
        crate::store::write_atomic(&options_path, &json).map_err(ProcessError::from)?;
        let script = dir.join("task.sh");
        let root_abs = root.canonicalize().map_err(|e| io(root, e))?;
        let text = format!(
            "#!/bin/sh\n# rigd: one part of `{step}` of {run}, a task of a Slurm job array\n# (written by rigd, submitted with sbatch; see docs/scaling.md).\nexport RAYON_NUM_THREADS=\"${{SLURM_CPUS_PER_TASK:-1}}\"\nexec {rigd} process part {run_q} --step {step} --parts {parts} --frames-per-part {fpp} --slots-per-part {spp} --part \"$SLURM_ARRAY_TASK_ID\" --options {opts}\n",
            step = step.name(),
            run = root_abs.display(),
            rigd = shell_quote(&self.rigd_path()?.to_string_lossy()),
            run_q = shell_quote(&root_abs.to_string_lossy()),
            fpp = self.frames_per_task,
            spp = self.slots_per_task,
            opts = shell_quote(&options_path.to_string_lossy()),
        );
        crate::store::write_atomic(&script, text.as_bytes()).map_err(ProcessError::from)?;
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&script, std::fs::Permissions::from_mode(0o755))
                .map_err(|e| io(&script, e))?;
        }
        let name = format!("rigd-{}", step.name());
        let mut jobs: Vec<String> = Vec::new();
        let mut attempts = vec![0u32; parts];
        let mut last_job: Vec<String> = vec![String::new(); parts];
        let mut to_submit: Vec<usize> = (0..parts).collect();
        let mut missing_since: BTreeMap<usize, Instant> = BTreeMap::new();
        let mut queue_ok = Instant::now();
        let cancel_all = |jobs: &[String]| -> SlurmError {
            if !jobs.is_empty() {
                if let Err(e) = slurm_command("scancel", jobs) {
                    tracing::warn!("{e}");
                }
            }
            SlurmError::Cancelled {
                jobs: jobs.join(", "),
            }
        };
        loop {
            if cancel() {
                return Err(cancel_all(&jobs));
            }
            if !to_submit.is_empty() {
                let array = array_spec(&to_submit);
                let mut args: Vec<String> = vec![
                    "--parsable".into(),
                    format!("--job-name={name}"),
                    format!("--array={array}"),
                    format!("--output={}/task-%a-%A.log", dir.display()),
                    "--no-requeue".into(),
                    format!("--chdir={}", root_abs.display()),
                ];
                if let Some(p) = &self.partition {
                    args.push(format!("--partition={p}"));
                }
                if let Some(a) = &self.account {
                    args.push(format!("--account={a}"));
                }
                args.extend(self.extra_options()?);
                args.push(script.to_string_lossy().into_owned());
                let out = slurm_command("sbatch", &args).inspect_err(|_| {
                    // Parts submitted before stay queued: take them down.
                    let _ = cancel_all(&jobs);
                })?;
                let job = out.trim().split(';').next().unwrap_or_default().to_string();
                if job.is_empty() || !job.chars().all(|c| c.is_ascii_digit()) {
                    let _ = cancel_all(&jobs);
                    return Err(SlurmError::Command {
                        command: "sbatch --parsable".into(),
                        message: format!("answered `{}`, not a job id", out.trim()),
                    });
                }
                notes(&format!(
                    "{}: Slurm job {job}, array {array} ({} of {parts} tasks)",
                    step.name(),
                    to_submit.len()
                ));
                for &p in &to_submit {
                    attempts[p] += 1;
                    last_job[p] = job.clone();
                    missing_since.remove(&p);
                }
                jobs.push(job);
                to_submit.clear();
            }
            // The queue first, then the markers: a task gone from the
            // queue wrote its marker (if it did) before it left.
            let live = match self.live_tasks(&name, &jobs) {
                Ok(live) => {
                    queue_ok = Instant::now();
                    live
                }
                Err(e) if queue_ok.elapsed() < QUEUE_SILENCE => {
                    tracing::warn!("{e}; asking again");
                    std::thread::sleep(Duration::from_secs_f64(self.poll_s));
                    continue;
                }
                Err(e) => {
                    let _ = cancel_all(&jobs);
                    return Err(e);
                }
            };
            let done = done_parts(root, step);
            progress(done.len().min(parts), parts);
            if (0..parts).all(|p| done.contains(&p)) {
                break;
            }
            for p in (0..parts).filter(|p| !done.contains(p) && !live.contains(p)) {
                let since = *missing_since.entry(p).or_insert_with(Instant::now);
                if since.elapsed() < MISSING_GRACE {
                    continue;
                }
                let job = &last_job[p];
                let log = dir.join(format!("task-{p}-{job}.log"));
                let reason = failure_reason(job, p, &log);
                if attempts[p] > self.max_retries {
                    let _ = cancel_all(&jobs);
                    return Err(SlurmError::TaskFailed {
                        step: step.name(),
                        part: p,
                        parts,
                        attempts: attempts[p],
                        job: job.clone(),
                        reason,
                        log: log.display().to_string(),
                    });
                }
                notes(&format!(
                    "{}: task {p} of Slurm job {job} ended without its result ({reason}); submitting it again",
                    step.name()
                ));
                to_submit.push(p);
            }
            let wait = Instant::now();
            while wait.elapsed() < Duration::from_secs_f64(self.poll_s) {
                if cancel() {
                    return Err(cancel_all(&jobs));
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        }
        let redone: u32 = attempts.iter().map(|a| a.saturating_sub(1)).sum();
        let summary = match split {
            Split::Units { .. } => super::pipeline::run_step(root, step, opts, progress)?,
            Split::Whole => std::fs::read_to_string(marker_path(root, step, 0))
                .map_err(|e| io(&marker_path(root, step, 0), e))?,
        };
        if let Err(e) = std::fs::remove_dir_all(&dir) {
            tracing::warn!("{}: {e}", dir.display());
        }
        if let Ok(mut rest) = std::fs::read_dir(dir.parent().unwrap_or(&dir)) {
            if rest.next().is_none() {
                let _ = std::fs::remove_dir(dir.parent().unwrap_or(&dir));
            }
        }
        Ok(format!(
            "{summary}; on Slurm: {parts} task{} in job {}{}",
            if parts == 1 { "" } else { "s" },
            jobs.join(", "),
            if redone > 0 {
                format!(", {redone} redone")
            } else {
                String::new()
            }
        ))
    }

    /// The task indices of `jobs` still in the queue (pending, running,
    /// completing, requeued, suspended).
    fn live_tasks(&self, name: &str, jobs: &[String]) -> Result<BTreeSet<usize>, SlurmError> {
        // The user's jobs of this name, not `squeue -j`: a job that has left
        // the controller's memory is an error there, and simply absent here.
        let out = slurm_command(
            "squeue",
            &[
                "-h".into(),
                "-r".into(),
                "--me".into(),
                format!("--name={name}"),
                "-o".into(),
                "%F|%K|%T".into(),
            ],
        )?;
        let mut live = BTreeSet::new();
        for line in out.lines() {
            let mut fields = line.trim().split('|');
            let (Some(job), Some(task), Some(state)) =
                (fields.next(), fields.next(), fields.next())
            else {
                continue;
            };
            if !jobs.iter().any(|j| j == job) {
                continue;
            }
            let still = matches!(
                state,
                "PENDING"
                    | "RUNNING"
                    | "CONFIGURING"
                    | "COMPLETING"
                    | "REQUEUED"
                    | "REQUEUE_HOLD"
                    | "REQUEUE_FED"
                    | "RESIZING"
                    | "SUSPENDED"
                    | "STAGE_OUT"
                    | "SIGNALING"
                    | "STOPPED"
            );
            if let (true, Ok(task)) = (still, task.parse()) {
                live.insert(task);
            }
        }
        Ok(live)
    }
}

/// Why task `part` of `job` ended without its result: `sacct`'s state and
/// exit code where the cluster keeps accounting, and the last line of the
/// task's log.
fn failure_reason(job: &str, part: usize, log: &Path) -> String {
    let mut why = Vec::new();
    if on_path("sacct").is_some() {
        let accounted = slurm_command(
            "sacct",
            &[
                "-n".into(),
                "-P".into(),
                "-X".into(),
                "-j".into(),
                format!("{job}_{part}"),
                "-o".into(),
                "State,ExitCode,NodeList".into(),
            ],
        );
        if let Ok(line) = accounted {
            if let Some(first) = line.lines().find(|l| !l.trim().is_empty()) {
                why.push(format!("sacct: {}", first.trim().replace('|', " ")));
            }
        }
    }
    match std::fs::read_to_string(log) {
        Ok(text) => {
            if let Some(last) = text.lines().rev().find(|l| !l.trim().is_empty()) {
                why.push(format!("its log ends `{}`", last.trim()));
            } else {
                why.push("its log is empty".into());
            }
        }
        Err(_) => why.push("it left no log (it never started, or its node is gone)".into()),
    }
    why.join("; ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn array_specs_are_ranges_or_lists() {
        assert_eq!(array_spec(&[0, 1, 2, 3]), "0-3");
        assert_eq!(array_spec(&[3, 5, 9]), "3,5,9");
        assert_eq!(array_spec(&[7]), "7");
    }

    #[test]
    fn shell_quoting_survives_quotes_and_spaces() {
        assert_eq!(shell_quote("/a b/it's"), r"'/a b/it'\''s'");
    }

    #[test]
    fn bad_settings_are_refused_before_anything_runs() {
        let dir = tempfile::tempdir().expect("tempdir");
        let bad = |cfg: SlurmConfig, what: &str| {
            let e = cfg.check(dir.path()).expect_err(what);
            assert!(e.is_bad_config(), "{what}: {e}");
            e.to_string()
        };
        let zero = SlurmConfig {
            frames_per_task: 0,
            ..Default::default()
        };
        assert!(bad(zero, "0 frames").contains("expected at least 1"));
        let quote = SlurmConfig {
            sbatch_options: "--comment='open".into(),
            ..Default::default()
        };
        assert!(bad(quote, "open quote").contains("quote"));
        let own = SlurmConfig {
            sbatch_options: "--array=0-3".into(),
            ..Default::default()
        };
        assert!(bad(own, "own option").contains("rigd sets it itself"));
    }
}
