//! `rigd run`: capture a plan into a run directory, or resume one, with a
//! progress display; Ctrl-C leaves the run resumable.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use rigd::engine::launch::{self, NewRun};
use rigd::engine::{Outcome, PausePolicy};
use rigd::model::exposure::ExposurePolicy;
use rigd::model::profile::DEFAULT_PROFILE;
use rigd::model::run_state::RunState;
use rigd::model::text::sanitize;
use rigd::plan::Order;
use rigd::postprocess::executor::ProcessingConfig;
use rigd::postprocess::job::{self, JobControl, JobEnd, JobState, OwnJob, ProcessJob};
use rigd::postprocess::pipeline::{
    background_pool, check_frame_size, CaptureProgress, ProcessOptions, ProcessStep, RunFacts,
};
use rigd::postprocess::ProcessError;
use rigd::rig::FaultRule;
use rigd::schedule::timing::parse_exposure_s;
use rigd_core::Clock;

use super::exit::{bad_input, EXIT_ENDED_BADLY, EXIT_INTERRUPTED, EXIT_PAUSED};
use super::progress::{hms, Progress};

#[derive(Args)]
pub struct RunArgs {
    /// Rig profile: a TOML file or an embedded profile name
    /// [default: the simulated bonn-gonioreflectometer]
    #[arg(long)]
    pub profile: Option<String>,
    /// Drive the simulated rig (virtual time) instead of hardware.
    #[arg(long)]
    pub sim: bool,
    /// h1, h2, grid12x8, lamps, or a plan file [default: the profile's default plan]
    #[arg(long)]
    pub plan: Option<String>,
    /// Sample name, recorded in the dataset: 1 to 128 characters, no
    /// control characters.
    #[arg(long, default_value = "sample")]
    pub sample: String,
    /// Run directory to create (must not exist or be empty)
    /// [default: runs/SAMPLE-PLAN-TIMESTAMP]
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Simulated frame size, WIDTHxHEIGHT [default: the profile's [sim] frame_size]
    #[arg(long, value_parser = rigd::model::text::parse_frame_size)]
    pub frame_size: Option<[u32; 2]>,
    /// Scene the simulated cameras render: a built-in name (`rigd sim
    /// scenes`) or a scene file [default: the profile's [sim] scene, else
    /// flat-calibration]
    #[cfg(feature = "sim")]
    #[arg(long)]
    pub scene: Option<String>,
    /// Operator name, recorded in the dataset.
    #[arg(long)]
    pub operator: Option<String>,
    /// Free-text notes, recorded in the dataset.
    #[arg(long)]
    pub notes: Option<String>,
    /// Exposure time for every camera, seconds, up to 3600 and within each
    /// camera's `timing.exposure_range_s` (default: the profile's).
    #[arg(long, allow_negative_numbers = true, value_parser = parse_exposure_s)]
    pub exposure: Option<f64>,
    /// Exposures per step: single (one), brackets:T1,T2,… (the same series
    /// at every step, seconds, longest first) or
    /// auto[:threshold=S,factor=F,max_extra=N] (again F times shorter, up
    /// to N times, where a frame clips more than S of the sample's pixels;
    /// defaults 0.00001, 4, 3) [default: the profile's [exposure_policy],
    /// else single]. Processing merges a step's exposures
    /// (`docs/processing.md`, "Exposure brackets").
    #[arg(long)]
    pub exposure_policy: Option<ExposurePolicy>,
    /// Trigger order: optimised (the shortest physical time under the
    /// motion model), slots (the shortest with each view's triggers
    /// together, so view slots complete early) or naive (the plan's nested
    /// loops) [default: optimised; laser plans keep theirs].
    #[arg(long, value_enum)]
    pub order: Option<Order>,
    /// Process the run: steps rectify, btf, fit, mdf, photometric-stereo
    /// (comma-separated), with the daemon's defaults (`docs/api.md`,
    /// "Processing"); `auto` picks them from the plan. Frames are
    /// registered as they are journaled, on background threads at nice 10;
    /// the rest runs once the capture completes. Refused before the
    /// capture when the frames are too small for the holder's markers.
    #[arg(long, value_delimiter = ',')]
    pub process: Vec<String>,
    /// Resume the run in this directory (all other run options come from it).
    #[cfg_attr(feature = "sim", arg(long, conflicts_with_all = ["profile", "plan", "out", "frame_size", "scene", "operator", "notes", "exposure", "order"]))]
    #[cfg_attr(not(feature = "sim"), arg(long, conflicts_with_all = ["profile", "plan", "out", "frame_size", "operator", "notes", "exposure", "order"]))]
    pub resume: Option<PathBuf>,
    /// With --resume on a rig with an axis without homing (`homing =
    /// false`): confirm that each such axis stands at its 0° mark with its
    /// controller zeroed there, since no homing can restore it.
    #[arg(long, requires = "resume")]
    pub reference_confirmed: bool,
    /// Inject a fault into the simulated firmware: DEVICE:OP:N:KIND[:sticky], fired on
    /// the Nth OP command the device receives. OP: GRBL axes home, move, info;
    /// ACL arm home, move, define, query; Modbus lamps set, ready; PTP cameras
    /// expose, transfer, set_exposure; or * for any. KIND: timeout (no answer),
    /// disconnect, bad-frame (garbled reply or frame), alarm=TEXT (the device's
    /// own fault: GRBL ALARM, Modbus exception, PTP GeneralError); on a camera's
    /// expose also dark (a valid frame the lamp missed) and mask-markers (a valid
    /// frame with the holder's markers covered). Repeatable.
    /// See firmware-protocols/README.md.
    #[cfg(feature = "sim")]
    #[arg(long = "sim-fault", value_name = "SPEC")]
    pub sim_faults: Vec<FaultRule>,
    /// Simulated physical seconds per wall second: virtual time paced to
    /// the wall, for a demo or to watch a capture as it goes [default: as
    /// fast as the host renders].
    #[arg(long, value_name = "SPEED", allow_negative_numbers = true)]
    pub sim_speed: Option<f64>,
    /// Progress display: a bar on a terminal, log lines otherwise.
    #[arg(long, value_enum, default_value = "auto")]
    pub progress: Progress,
}

impl RunArgs {
    /// The faults to inject (none in a build without the simulator).
    fn faults(&self) -> Vec<FaultRule> {
        #[cfg(feature = "sim")]
        return self.sim_faults.clone();
        #[cfg(not(feature = "sim"))]
        return Vec::new();
    }
}

/// Runs `rigd run`.
pub fn run(args: RunArgs) -> Result<ExitCode> {
    // The embedded default is the simulated rig; a profile file names real
    // hardware unless --sim says otherwise.
    let simulated = match &args.resume {
        Some(dir) => {
            let meta = rigd::store::read_meta(dir)
                .with_context(|| format!("cannot resume {}", dir.display()))?;
            let unhomed = meta.profile.axes_without_homing();
            if !unhomed.is_empty() && !args.reference_confirmed {
                return Err(bad_input(format!(
                    "{} without homing: set each at its 0° mark and zero its controller there, then resume with --reference-confirmed",
                    unhomed.join(", ")
                )));
            }
            meta.simulated
        }
        None => args.sim || args.profile.is_none(),
    };
    if !simulated && !args.faults().is_empty() {
        return Err(bad_input("--sim-fault needs the simulated rig (--sim)"));
    }
    if !simulated && args.sim_speed.is_some() {
        return Err(bad_input("--sim-speed needs the simulated rig (--sim)"));
    }
    // The simulated rig runs in virtual time: a paused runtime whose clock
    // jumps whenever every task waits, held back to the wall by a paced
    // one. Hardware runs on the wall clock.
    let paced = args
        .sim_speed
        .map(rigd_core::pace::PacedRuntime::start)
        .transpose()
        .map_err(|e| bad_input(format!("--sim-speed: {e}")))?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .start_paused(simulated && paced.is_none())
        .build()
        .context("cannot start the runtime")?;
    let capture = async move {
        let sim = rigd::rig::simulated_rig(args.faults());
        let clock = if simulated {
            Clock::virtual_time()
        } else {
            Clock::real()
        };
        let mut process = None;
        let prepared = match &args.resume {
            Some(dir) => {
                if !args.process.is_empty() {
                    let meta = rigd::store::read_meta(dir)
                        .with_context(|| format!("cannot resume {}", dir.display()))?;
                    let size = meta
                        .frame_size
                        .or(meta.simulated.then_some(meta.profile.sim.frame_size));
                    process = Some(processing_options(&args.process, &meta.plan, size)?);
                }
                launch::prepare_resume(dir, sim.as_deref(), clock, PausePolicy::Return)
                    .await
                    .with_context(|| format!("cannot resume {}", dir.display()))?
            }
            None => {
                let source = args
                    .profile
                    .clone()
                    .unwrap_or_else(|| DEFAULT_PROFILE.to_string());
                #[cfg_attr(not(feature = "sim"), allow(unused_mut))]
                let mut profile = rigd::rig::load_profile(&source)?;
                #[cfg(feature = "sim")]
                if let Some(scene) = &args.scene {
                    // The run records its profile, so a resume renders
                    // the same scene.
                    rigd::rig::sim::Scene::load_on(scene, &profile.holder)?;
                    rigd::rig::sim::set_scene(&mut profile, scene);
                }
                let plan = args
                    .plan
                    .clone()
                    .unwrap_or_else(|| profile.default_plan.clone());
                let out = args.out.clone().unwrap_or_else(|| {
                    let stamp = humantime::format_rfc3339_seconds(std::time::SystemTime::now())
                        .to_string()
                        .replace(':', "");
                    // Names only: a sample or plan name never becomes a
                    // path of its own (`..`, `/`).
                    PathBuf::from("runs").join(format!(
                        "{}-{}-{}",
                        sanitize(&args.sample, 40),
                        sanitize(&plan_stem(&plan), 24),
                        stamp
                    ))
                });
                let req = NewRun {
                    profile_source: rigd::model::profile::Profile::origin(&source),
                    profile,
                    plan,
                    sample: args.sample.clone(),
                    operator: args.operator.clone(),
                    notes: args.notes.clone(),
                    exposure_s: args.exposure,
                    exposure_policy: args.exposure_policy.clone(),
                    frame_size: args.frame_size,
                    out,
                    simulated,
                    order: args.order,
                };
                let mut solved = launch::solve_plan(&req.profile, &req.plan, req.order)?;
                if !args.process.is_empty() {
                    let size = args
                        .frame_size
                        .or(simulated.then_some(req.profile.sim.frame_size));
                    let options = processing_options(&args.process, &solved.1, size)?;
                    // Compressing view slots during the capture can favour
                    // an order left to the default.
                    if args.order.is_none() && options.steps.contains(&ProcessStep::Btf) {
                        let (chosen, choice) = launch::prefer_slots(&req.profile, solved);
                        solved = chosen;
                        if let Some(choice) = choice {
                            eprintln!("{choice}");
                        }
                    }
                    process = Some(options);
                }
                launch::prepare_new_solved(req, solved, sim.as_deref(), clock, PausePolicy::Return)
                    .await?
            }
        };
        let root = prepared.root.clone();
        let job = process_job(&root, process, args.resume.is_some())?
            .map(|job| std::sync::Arc::new(OwnJob::new(job, JobLines::drawer())));
        let capturing = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
        let stream = job
            .clone()
            .map(|job| spawn_capture_stream(&root, job, capturing.clone()));
        let code = drive(prepared, args.progress).await;
        capturing.store(false, std::sync::atomic::Ordering::SeqCst);
        if let Some(Some(thread)) = stream {
            match thread.join() {
                Ok(Ok(Some(p))) => eprintln!(
                    "during the capture: {} of {} frames registered, {} view slots compressed",
                    p.frames.done, p.frames.journaled, p.slots_ahead
                ),
                Ok(Ok(None)) => {}
                // The `rectify` step registers whatever the stream did not.
                Ok(Err(e)) => eprintln!("rectify during the capture stopped: {e}"),
                Err(_) => eprintln!("rectify during the capture stopped (a panic)"),
            }
        }
        match (job, code?) {
            (Some(job), ExitCode::SUCCESS) => process_run(&root, &*job),
            (_, code) => Ok(code),
        }
    };
    match &paced {
        // Everything the capture spawns lives on the paced runtime, where
        // its clock is.
        Some(paced) => runtime
            .block_on(paced.handle().spawn(capture))
            .context("the capture's task failed")?,
        None => runtime.block_on(capture),
    }
}

/// The run's process job, written to its `job.json`: the one `--process`
/// asks for (the kept one when it asked the same, its done steps kept),
/// or on a resume without `--process` the one asked for with the capture
/// and not yet run to its end.
fn process_job(
    root: &std::path::Path,
    asked: Option<ProcessOptions>,
    resuming: bool,
) -> Result<Option<ProcessJob>> {
    let kept = if resuming { job::read_job(root) } else { None };
    let job = match (asked, kept) {
        (Some(options), Some(kept)) if kept.options == options => Some(kept),
        (Some(options), _) => {
            let run = root
                .file_name()
                .map_or_else(|| "run".into(), |n| n.to_string_lossy().into_owned());
            let mut job = ProcessJob::new(&run, options);
            job.after_capture = true;
            Some(job)
        }
        (None, Some(kept))
            if kept.after_capture && matches!(kept.state, JobState::Queued | JobState::Running) =>
        {
            let steps: Vec<&str> = kept.steps.iter().map(|s| s.step.name()).collect();
            eprintln!(
                "its processing, asked with the capture, follows: {}",
                steps.join(", ")
            );
            Some(kept)
        }
        (None, _) => None,
    };
    let Some(mut job) = job else {
        return Ok(None);
    };
    if job.state == JobState::Running {
        job.resumed += 1;
    }
    job.requeue();
    job::write_job(root, &job).map_err(|e| anyhow::anyhow!("the run's process job: {e}"))?;
    Ok(Some(job))
}

/// A process job's steps on stderr, as `rigd process` shows its own: each
/// running step's progress line and each step's summary once done.
#[derive(Default)]
struct JobLines {
    lines: std::collections::BTreeMap<usize, StepLine>,
    reported: std::collections::BTreeSet<usize>,
}

/// One step's progress line.
type StepLine = Box<dyn Fn(usize, usize) + Send + Sync>;

impl JobLines {
    /// Draws a job's changes once its steps run (not while the capture
    /// streams): a closure for [`OwnJob`].
    fn drawer() -> impl Fn(&ProcessJob) + Send + Sync {
        let lines = std::sync::Mutex::new(JobLines::default());
        move |job: &ProcessJob| {
            if matches!(job.state, JobState::Running | JobState::Done) {
                rigd_core::sync::lock(&lines).show(job);
            }
        }
    }

    fn show(&mut self, job: &ProcessJob) {
        for (k, s) in job.steps.iter().enumerate() {
            match s.state {
                JobState::Running if s.total > 0 => self
                    .lines
                    .entry(k)
                    .or_insert_with(|| Box::new(super::progress::progress_line(s.step.name())))(
                    s.done, s.total,
                ),
                JobState::Done if self.reported.insert(k) => eprintln!(
                    "{}: {} ({:.1} s)",
                    s.step.name(),
                    s.summary.as_deref().unwrap_or(""),
                    s.elapsed_s
                ),
                _ => {}
            }
        }
    }
}

/// The options of `--process` for a run of `plan` with frames of `size`
/// (None: the camera's own, on hardware), or why they cannot run.
fn processing_options(
    steps: &[String],
    plan: &rigd::plan::Plan,
    size: Option<[u32; 2]>,
) -> Result<ProcessOptions> {
    let mut options = ProcessOptions::default();
    for s in steps.iter().filter(|s| s.as_str() != "auto") {
        options
            .steps
            .push(ProcessStep::parse(s).map_err(|e| bad_input(format!("--process: {e}")))?);
    }
    let options = options
        .resolve(&RunFacts::of_plan(plan))
        .map_err(|e| bad_input(format!("--process: {e}")))?;
    if let (true, Some(size)) = (options.steps.contains(&ProcessStep::Rectify), size) {
        check_frame_size(size).map_err(|e| bad_input(format!("--process: {e}")))?;
    }
    Ok(options)
}

/// Registers the run's frames during its capture
/// ([`job::stream_during_capture`]) on a background pool until `capturing`
/// turns false; None when the pool cannot be made (then the steps do it
/// all after the capture).
fn spawn_capture_stream<C: JobControl + Send + 'static>(
    root: &std::path::Path,
    job: std::sync::Arc<C>,
    capturing: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> Option<std::thread::JoinHandle<Result<Option<CaptureProgress>, ProcessError>>> {
    let root = root.to_path_buf();
    let pool = match background_pool("rigd-stream") {
        Ok(pool) => pool,
        Err(e) => {
            eprintln!("rectify during the capture: {e}; it runs after the capture");
            return None;
        }
    };
    std::thread::Builder::new()
        .name("rigd-stream".into())
        .spawn(move || job::stream_during_capture(&*job, &root, &pool, &capturing))
        .ok()
}

/// Runs the process job's steps on the completed run at `root`.
fn process_run(root: &std::path::Path, job: &impl JobControl) -> Result<ExitCode> {
    match job::run_job(job, root, &ProcessingConfig::default()) {
        JobEnd::Done => Ok(ExitCode::SUCCESS),
        JobEnd::Failed(e) => Err(anyhow::anyhow!(
            "the capture completed in {}, but processing it failed at {e}",
            root.display()
        )),
        JobEnd::Stopped => Err(anyhow::anyhow!(
            "the capture completed in {}, but its processing stopped",
            root.display()
        )),
    }
}

fn plan_stem(plan: &str) -> String {
    std::path::Path::new(plan)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "plan".into())
}

/// Runs the engine with a progress display and signal handling; prints the summary.
async fn drive(p: launch::Prepared, progress: Progress) -> Result<ExitCode> {
    let wall = Instant::now();
    let root = p.root.clone();
    let events = p.handle.events.subscribe();
    let commands = p.handle.commands.clone();
    // The reporter ends when the engine drops the last event sender.
    drop(p.handle);
    eprintln!(
        "run {}: {} images, {} already taken; estimated physical time {}",
        root.display(),
        p.frames_total,
        p.frames_done,
        hms(p.estimate_s)
    );
    if !p.retake.is_empty() {
        eprintln!(
            "retaking {} frames found missing or damaged",
            p.retake.len()
        );
    }
    let reporter = super::progress::report_run(
        events,
        progress,
        p.frames_total,
        p.frames_done,
        p.t_offset_s + p.estimate_s,
    );
    let engine = tokio::spawn(p.engine.run());
    let interrupted = super::signal::detach_on_signal(commands);
    let outcome: Outcome = engine.await.context("engine task failed")??;
    interrupted.stop_listening();
    let _ = reporter.await;
    let wall_s = wall.elapsed().as_secs_f64();
    eprintln!(
        "{}: {} of {} frames; physical duration {} ({:.1} s); wall time {:.1} s",
        outcome.state,
        outcome.frames_written,
        outcome.frames_total,
        hms(outcome.physical_s),
        outcome.physical_s,
        wall_s
    );
    Ok(match outcome.state {
        RunState::Completed => {
            println!("{}", root.display());
            ExitCode::SUCCESS
        }
        RunState::Paused if interrupted.fired() => ExitCode::from(EXIT_INTERRUPTED),
        RunState::Paused => {
            eprintln!(
                "paused: {}; fix the cause, then `rigd run --resume {}`",
                outcome.reason.unwrap_or_default(),
                root.display()
            );
            ExitCode::from(EXIT_PAUSED)
        }
        _ => {
            eprintln!("{}", outcome.reason.unwrap_or_default());
            ExitCode::from(EXIT_ENDED_BADLY)
        }
    })
}
