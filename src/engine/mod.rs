//! The run engine: drives a [`Schedule`] on a [`Rig`] and writes the run.
//!
//! Per trigger: all axes, the arm and the lamp change move in parallel, and
//! together overlap the transfer and writing of the previous trigger's
//! frames; then every camera of the trigger exposes while nothing moves and
//! no lamp switches. Every device call has a deadline. A fault pauses the run
//! with its reason; idempotent calls (absolute moves, transfers of a frame
//! that can be retaken) are retried first. A frame counts as taken once its
//! journal line is fsynced, so a resumed run repeats and loses nothing.

pub mod bracket;
pub mod command;
pub mod estop;
pub mod launch;
pub mod manual;

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::future::join_all;
use rigd_core::Clock;
use serde::{Deserialize, Serialize};
use tokio::sync::{broadcast, mpsc};

use crate::model::run_state::{IllegalTransition, RunState};
use command::{check_command, Command};
pub use estop::{EStop, StopAck, StopReport};

use crate::kinematics::Setpoints;
use crate::model::exposure::ExposurePolicy;
use crate::model::profile::Profile;
use crate::rig::hal::{
    Arm, Axis, Camera, DeviceError, ErrorKind, Fixture, Frame, Lamp, LaserLine, Rig,
};
use crate::schedule::timing::Timing;
use crate::schedule::Schedule;
use crate::store::{
    now_rfc3339, storage_fault_reason, FrameEntry, InfeasibleEntry, Manifest, Recovery, RunDir,
    RunMeta, StateRecord, StoreError, RUN_FORMAT,
};

/// Slack added to every deadline on top of the physical time a call should
/// take: serial round trips, USB latency, a slow controller.
const DEADLINE_SLACK_S: f64 = 10.0;
/// Deadline of a homing cycle.
const HOMING_DEADLINE_S: f64 = 300.0;
/// Deadline for an operator (or the simulator) to place or remove the
/// laser calibration plate.
const PLATE_DEADLINE_S: f64 = 3600.0;

/// What the engine does when a run pauses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PausePolicy {
    /// Wait for Resume, Abort or Detach on the command channel (the daemon).
    Wait,
    /// Return at once, leaving the run resumable from its directory (the
    /// command line, which has no operator to wait for).
    Return,
}

/// Retries of calls that are safe to repeat.
#[derive(Debug, Clone, Copy)]
pub struct RetryPolicy {
    /// Attempts in all at one trigger, the first included, before a
    /// retryable fault (timeout, bad frame) pauses the run.
    pub max_attempts: u32,
    /// Physical back-off before attempt n is n × this.
    pub backoff_s: f64,
}

impl Default for RetryPolicy {
    fn default() -> Self {
        RetryPolicy {
            max_attempts: 3,
            backoff_s: 1.0,
        }
    }
}

/// Something the engine did, for progress bars, logs and the event stream.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunEvent {
    /// Number of the event within this engine session: 1, 2, 3, … with no
    /// gaps (a resumed run starts again at 1).
    pub seq: u64,
    /// Physical seconds since the run started.
    pub t_s: f64,
    /// What happened; flattened into the event, tagged by `type`.
    #[serde(flatten)]
    pub kind: EventKind,
}

/// What a [`RunEvent`] reports, tagged by `type`: `state`, `step`, `retry`
/// or `refused`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum EventKind {
    /// The run changed state.
    State {
        /// The state it left.
        from: RunState,
        /// The state it entered.
        to: RunState,
        /// Why, when there is a reason (a fault, the operator, missing frames);
        /// absent otherwise.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        reason: Option<String>,
    },
    /// A trigger's frames are written and journaled.
    Step {
        /// The trigger's index in the schedule.
        trigger: usize,
        /// Indices of the images it wrote.
        images: Vec<usize>,
        /// Images with a valid frame so far, earlier sessions included.
        frames_done: usize,
        /// Images in the plan.
        frames_total: usize,
    },
    /// A failed call is being retried.
    Retry {
        /// The device whose call failed, named as in the profile.
        device: String,
        /// The error that is being retried.
        reason: String,
        /// The attempt that failed: 1 for the first.
        attempt: u32,
    },
    /// A command was refused in the current state.
    Refused {
        /// The refused command.
        command: Command,
        /// The run's state when it arrived.
        state: RunState,
    },
}

/// How a call of [`Engine::run`] ended.
#[derive(Debug, Clone, PartialEq)]
pub struct Outcome {
    /// The state the call ended in: completed, aborted or failed, or paused
    /// (the run returned under [`PausePolicy::Return`] or was detached).
    pub state: RunState,
    /// Why it ended there (a fault, the operator, frames missing); None when
    /// it completed.
    pub reason: Option<String>,
    /// Physical seconds of the run over all its sessions; for a finished
    /// capture, up to its last frame.
    pub physical_s: f64,
    /// Images with a valid frame, earlier sessions included.
    pub frames_written: usize,
    /// Images in the plan.
    pub frames_total: usize,
}

/// Why a run paused after an emergency stop.
pub const ESTOP_REASON: &str = "emergency stop: every device stopped; resume re-homes the rig";

/// The caller's end of a running engine.
#[derive(Debug, Clone)]
pub struct EngineHandle {
    /// Sends operator commands; the engine acts on them between triggers (a
    /// paused engine at once).
    pub commands: mpsc::Sender<Command>,
    /// The engine's events; `subscribe` to watch them.
    pub events: broadcast::Sender<RunEvent>,
    /// The rig's stop button (works while a device call is in flight).
    pub estop: EStop,
    /// The runtime the engine runs on when it is not the caller's (a
    /// simulated rig in paced virtual time): the stop is timed there, on
    /// the run's own clock.
    pub runtime: Option<tokio::runtime::Handle>,
}

impl EngineHandle {
    /// Stops every device at once, then has the run pause until the
    /// operator resumes it (which re-homes the rig first).
    pub async fn emergency_stop(&self) -> StopReport {
        let report = match &self.runtime {
            Some(rt) => {
                let estop = self.estop.clone();
                match rt.spawn(async move { estop.trigger().await }).await {
                    Ok(report) => report,
                    // The run's runtime is gone: its engine has ended and
                    // its devices with it.
                    Err(_) => StopReport {
                        latency_s: 0.0,
                        devices: Vec::new(),
                    },
                }
            }
            None => self.estop.trigger().await,
        };
        // Calls in flight fail and pause the run; between steps nothing
        // fails, so the engine is told as well. A finished engine has
        // nothing left to pause.
        let _ = self.commands.try_send(Command::EmergencyStop);
        report
    }
}

/// The name a storage fault goes by where a device's name would be.
pub const STORAGE_DEVICE: &str = "run directory";

/// Errors that end the engine rather than pause it.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    /// The run directory could not record a state change the run cannot
    /// go on without.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The engine asked for a transition the state table refuses: a bug.
    #[error(transparent)]
    Transition(#[from] IllegalTransition),
}

/// Everything one run needs.
pub struct Engine {
    profile: Profile,
    schedule: Schedule,
    meta: RunMeta,
    rig: Rig,
    clock: Clock,
    estop: EStop,
    store: Arc<Mutex<RunDir>>,
    events: broadcast::Sender<RunEvent>,
    commands: mpsc::Receiver<Command>,
    done: BTreeMap<usize, FrameEntry>,
    t_offset: f64,
    state: RunState,
    seq: u64,
    policy: PausePolicy,
    retry: RetryPolicy,
    reason: Option<String>,
    /// Where the rig stands (or was last sent).
    pos: Setpoints,
    /// The set-points of the last step whose every move succeeded, while
    /// nothing else has moved the rig since (no pause, fault, sweep or
    /// homing): a device whose next set-point is the same is not commanded.
    settled: Option<Setpoints>,
    /// Physical time the last frame was taken, once the plan is through.
    finished_at_s: Option<f64>,
    /// Whether `pos.plate_mm` is known. A laser run starts not knowing (a
    /// resumed one cannot know what an operator left on the turntable), so
    /// its first move places or removes the plate; other plans never use it.
    plate_known: bool,
    /// A state change the run directory could not record (disk full): the
    /// run pauses with this reason before it goes on.
    storage_fault: Option<String>,
    /// The latest state record the run directory could not take: written
    /// again until it is, so `state.json` never goes on saying what the
    /// run no longer is.
    unrecorded: Option<StateRecord>,
    /// Triggers whose first exposure clipped too much under the `auto`
    /// exposure policy: their frames, written but not journaled, wait for
    /// the shorter exposures, taken when the rig is back at the trigger.
    held: BTreeMap<usize, Vec<FrameEntry>>,
    /// The exposure each camera is known to be set to: a bracketed run sets
    /// it before an exposure only where it differs. Forgotten on any fault.
    exposure_set: BTreeMap<String, f64>,
}

/// Physical seconds between two attempts at writing a state record the
/// run directory refused, while the run waits paused.
const STATE_RETRY_S: f64 = 5.0;

/// A trigger exposed but not yet transferred.
#[derive(Debug, Clone)]
struct Pending {
    trigger: usize,
    t_s: f64,
    reached: Setpoints,
}

enum Flow {
    Continue,
    Stop,
}

/// A failed step: the device error and whether it is safe to retry.
struct StepFault {
    error: DeviceError,
    retryable: bool,
}

impl From<DeviceError> for StepFault {
    fn from(error: DeviceError) -> Self {
        let retryable = matches!(error.kind, ErrorKind::Timeout | ErrorKind::BadFrame);
        StepFault { error, retryable }
    }
}

impl Engine {
    /// Builds an engine for a run directory. `recovery` holds what a
    /// resumed run already has (its frames, the physical time spent, the
    /// state its new session starts from); a new run passes the default.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        profile: Profile,
        schedule: Schedule,
        mut meta: RunMeta,
        mut rig: Rig,
        clock: Clock,
        store: RunDir,
        recovery: Recovery,
        policy: PausePolicy,
    ) -> (Engine, EngineHandle) {
        if meta.exposure_s.is_none() {
            // Laser sweeps use the plan's short exposure (Wang et al., §3.2).
            meta.exposure_s = schedule.laser.as_ref().map(|l| l.plan.exposure_s);
        }
        let laser_plan = schedule.laser.is_some();
        let (cmd_tx, cmd_rx) = mpsc::channel(16);
        let (ev_tx, _) = broadcast::channel(1024);
        let estop = EStop::new(std::mem::take(&mut rig.stops), clock.clone());
        let engine = Engine {
            profile,
            schedule,
            meta,
            rig,
            clock,
            estop: estop.clone(),
            store: Arc::new(Mutex::new(store)),
            events: ev_tx.clone(),
            commands: cmd_rx,
            done: recovery.done,
            t_offset: recovery.physical_s,
            state: recovery.state,
            seq: 0,
            policy,
            retry: RetryPolicy::default(),
            reason: None,
            pos: Setpoints {
                axes: BTreeMap::new(),
                arm: None,
                lamp: String::new(),
                plate_mm: None,
            },
            settled: None,
            finished_at_s: None,
            plate_known: !laser_plan,
            storage_fault: None,
            unrecorded: None,
            held: BTreeMap::new(),
            exposure_set: BTreeMap::new(),
        };
        (
            engine,
            EngineHandle {
                commands: cmd_tx,
                events: ev_tx,
                estop,
                runtime: None,
            },
        )
    }

    /// Physical seconds since the run started, over all sessions.
    fn t(&self) -> f64 {
        self.t_offset + self.clock.now_s()
    }

    fn emit(&mut self, kind: EventKind) {
        self.seq += 1;
        let ev = RunEvent {
            seq: self.seq,
            t_s: self.t(),
            kind,
        };
        // No subscriber is fine: events are for whoever watches.
        let _ = self.events.send(ev);
    }

    fn go(&mut self, to: RunState, reason: Option<String>) -> Result<(), EngineError> {
        let from = self.state;
        self.state = from.transition(to)?;
        self.reason = reason.clone();
        let record = StateRecord {
            state: to,
            reason: reason.clone(),
            physical_s: self.t(),
            updated_at: now_rfc3339(),
        };
        self.unrecorded = Some(record);
        if let Err(why) = self.record_state() {
            // The state lives on in memory and in the events; the file is
            // stale until the disk takes it (tried again while paused).
            // Going on would capture into a directory that cannot record
            // it, so anything but a pause pauses first.
            tracing::error!("cannot record state {to}: {why}");
            if to != RunState::Paused && !to.ends_session() {
                self.storage_fault.get_or_insert(why);
            }
        }
        match &reason {
            Some(r) => tracing::info!(from = %from, to = %to, reason = %r, "run state"),
            None => tracing::info!(from = %from, to = %to, "run state"),
        }
        self.emit(EventKind::State { from, to, reason });
        Ok(())
    }

    /// Writes the state record the run directory has not taken yet, if
    /// any; the reason it still refuses it.
    fn record_state(&mut self) -> Result<(), String> {
        let Some(record) = &self.unrecorded else {
            return Ok(());
        };
        let written = lock_store(&self.store).write_state(record);
        match written {
            Ok(()) => {
                self.unrecorded = None;
                Ok(())
            }
            Err(e) => Err(storage_fault_reason(&self.meta_root(), &e)),
        }
    }

    /// The run directory.
    fn meta_root(&self) -> std::path::PathBuf {
        lock_store(&self.store).root().to_path_buf()
    }

    fn outcome(&self) -> Outcome {
        Outcome {
            state: self.state,
            reason: self.reason.clone(),
            physical_s: self.finished_at_s.unwrap_or_else(|| self.t()),
            frames_written: self.done.len(),
            frames_total: self.schedule.images.len(),
        }
    }

    /// Triggers that still have an image without a valid frame, in order.
    fn todo(&self) -> VecDeque<usize> {
        self.schedule
            .triggers
            .iter()
            .filter(|t| t.images.iter().any(|i| !self.done.contains_key(i)))
            .map(|t| t.index)
            .collect()
    }

    /// Runs until the run completes, is aborted, or pauses under
    /// [`PausePolicy::Return`] (or is detached).
    pub async fn run(mut self) -> Result<Outcome, EngineError> {
        // Physical time counts from here: whatever the clock ran while the
        // rig was connected and the run handed to its driver (a daemon
        // answering the request that made it) is no capture time.
        self.t_offset -= self.clock.now_s();
        let mut queue = self.todo();
        self.go(RunState::Preparing, None)?;
        match self.prepare(queue.front().copied()).await {
            Ok(at) => {
                self.pos = at;
                self.estop.rearm();
            }
            Err(e) => {
                if let Flow::Stop = self.fault_pause(e.error.to_string()).await? {
                    return Ok(self.outcome());
                }
            }
        }
        let mut pending: Option<Pending> = None;
        let mut attempts: HashMap<usize, u32> = HashMap::new();
        loop {
            // Operator commands act between triggers.
            while let Ok(cmd) = self.commands.try_recv() {
                if let Some(Flow::Stop) = self.command(cmd, &mut pending, &mut queue).await? {
                    return Ok(self.outcome());
                }
            }
            if let Some(reason) = self.storage_fault.take() {
                if let Flow::Stop = self.fault_pause(reason).await? {
                    return Ok(self.outcome());
                }
                continue;
            }
            if self.state != RunState::Running {
                // A resume from a fault re-prepared the rig.
                self.go(RunState::Running, None)?;
            }
            let next = queue.front().copied();
            if next.is_none() && pending.is_none() {
                match self.complete().await? {
                    Flow::Stop => return Ok(self.outcome()),
                    Flow::Continue => {
                        // Resumed: whatever the journal lacked is taken now.
                        queue = self.todo();
                        continue;
                    }
                }
            }
            let sweep_next = next.filter(|&i| self.schedule.triggers[i].sweep.is_some());
            if let (Some(i), None) = (sweep_next, &pending) {
                match self.sweep(&mut queue).await {
                    Ok(()) => {
                        attempts.remove(&i);
                        continue;
                    }
                    Err(fault) => match self.handle_fault(fault, i, &mut attempts).await? {
                        Flow::Continue => continue,
                        Flow::Stop => return Ok(self.outcome()),
                    },
                }
            }
            // A sweep starts once the frames still in flight are written.
            let target = next
                .filter(|_| sweep_next.is_none())
                .map(|i| self.schedule.triggers[i].setpoints.clone());
            let finishing = pending.take();
            // Whatever this step brings, only its own success settles the rig.
            let settled = self.settled.take();
            let (moved, finished) = {
                let timing = Timing::new(&self.profile, self.meta.exposure_s);
                let Rig {
                    axes,
                    arms,
                    lamps,
                    lasers,
                    fixture,
                    cameras,
                    ..
                } = &mut self.rig;
                let go = async {
                    match &target {
                        Some(to) => {
                            let mut lights = Lights { lamps, lasers };
                            goto(
                                &self.clock,
                                &timing,
                                Movers {
                                    axes,
                                    arms,
                                    fixture,
                                    plate_known: self.plate_known,
                                },
                                &mut lights,
                                &self.pos,
                                settled.as_ref(),
                                to,
                            )
                            .await
                            .map(Some)
                        }
                        None => Ok(None),
                    }
                };
                let hold = self.meta.exposure_policy.auto().map(|a| HoldRule {
                    profile: &self.profile,
                    threshold: a.threshold,
                });
                let fin = async {
                    match &finishing {
                        Some(p) => finish(
                            &self.clock,
                            &timing,
                            &self.schedule,
                            &self.store,
                            cameras,
                            p,
                            self.meta.exposure_s,
                            hold,
                        )
                        .await
                        .map(Some),
                        None => Ok(None),
                    }
                };
                tokio::join!(go, fin)
            };
            match finished {
                Ok(Some(Finished::Held(entries))) => {
                    // The rig is at the next trigger (or on its way): that
                    // one is exposed first, then the rig comes back here.
                    let trig = finishing.as_ref().map_or(0, |p| p.trigger);
                    self.held.insert(trig, entries);
                    let at = usize::from(!queue.is_empty() && moved.is_ok());
                    if !queue.contains(&trig) {
                        queue.insert(at.min(queue.len()), trig);
                    }
                }
                Ok(Some(Finished::Journaled(entries))) => {
                    let trig = finishing.as_ref().map_or(0, |p| p.trigger);
                    self.step_done(trig, entries);
                }
                Ok(None) => {}
                Err(fault) => {
                    // Retake the whole trigger: back to its pose first.
                    let p = finishing.as_ref().map_or(0, |p| p.trigger);
                    if queue.front() != Some(&p) {
                        queue.push_front(p);
                    }
                    if let Ok(Some(r)) = &moved {
                        self.pos = r.clone();
                    }
                    match self.handle_fault(fault, p, &mut attempts).await? {
                        Flow::Continue => continue,
                        Flow::Stop => return Ok(self.outcome()),
                    }
                }
            }
            let reached = match moved {
                Ok(Some(r)) => r,
                Ok(None) => continue, // nothing left to move to: the last transfer is done
                Err(fault) => {
                    let i = next.unwrap_or(0);
                    match self.handle_fault(fault, i, &mut attempts).await? {
                        Flow::Continue => continue,
                        Flow::Stop => return Ok(self.outcome()),
                    }
                }
            };
            self.pos = reached.clone();
            self.plate_known = true;
            let Some(i) = next else { continue };
            if self.estop.is_tripped() {
                // The stop cut the move short (or lands now): the rig is
                // not where this trigger needs it, so nothing is exposed.
                match self.fault_pause(ESTOP_REASON.into()).await? {
                    Flow::Continue => continue,
                    Flow::Stop => return Ok(self.outcome()),
                }
            }
            self.settled = target;
            let t_s = self.t();
            let cams = self.cameras_of(i);
            if self.bracketed(i) {
                match self.bracket_step(i, t_s, reached).await {
                    Ok(()) => {
                        queue.pop_front();
                    }
                    Err(fault) => match self.handle_fault(fault, i, &mut attempts).await? {
                        Flow::Continue => continue,
                        Flow::Stop => return Ok(self.outcome()),
                    },
                }
                continue;
            }
            let exposed = {
                let timing = Timing::new(&self.profile, self.meta.exposure_s);
                let at_base = if self.meta.exposure_policy.is_single() {
                    Ok(())
                } else {
                    // A bracket may have left a camera at a shorter exposure.
                    let want: Vec<(String, f64)> = cams
                        .iter()
                        .map(|c| (c.clone(), timing.exposure_s(c)))
                        .collect();
                    set_exposures(
                        &self.clock,
                        &mut self.rig.cameras,
                        &mut self.exposure_set,
                        &want,
                    )
                    .await
                };
                match at_base {
                    Ok(()) => expose(&self.clock, &timing, &mut self.rig.cameras, &cams).await,
                    Err(fault) => Err(fault),
                }
            };
            match exposed {
                Ok(()) => {
                    queue.pop_front();
                    pending = Some(Pending {
                        trigger: i,
                        t_s,
                        reached,
                    });
                }
                Err(fault) => match self.handle_fault(fault, i, &mut attempts).await? {
                    Flow::Continue => continue,
                    Flow::Stop => return Ok(self.outcome()),
                },
            }
        }
    }

    /// Whether trigger `i` takes its exposures at its pose, one after the
    /// other: every step of a `brackets` run, and an `auto` step whose
    /// first exposure clipped. A laser sweep never does.
    fn bracketed(&self, i: usize) -> bool {
        self.schedule.triggers[i].sweep.is_none()
            && (self.held.contains_key(&i)
                || matches!(self.meta.exposure_policy, ExposurePolicy::Brackets { .. }))
    }

    /// Takes trigger `i`'s exposures at its pose, each transferred before
    /// the next: a `brackets` run's series, or an `auto` step's shorter
    /// exposures after its held first one, each `factor` times shorter
    /// until the sample clips no more than the threshold (or `max_extra`
    /// are taken). Then every exposure of every image is journaled at once:
    /// a step is never half-taken.
    async fn bracket_step(
        &mut self,
        i: usize,
        t_s: f64,
        reached: Setpoints,
    ) -> Result<(), StepFault> {
        let cams = self.cameras_of(i);
        let timing = Timing::new(&self.profile, self.meta.exposure_s);
        let held = self.held.get(&i).cloned();
        // Each exposure's time, per camera.
        let series: Vec<BTreeMap<String, f64>> = match (self.meta.exposure_policy.auto(), &held) {
            (Some(a), Some(_)) => (1..=a.max_extra)
                .map(|k| {
                    cams.iter()
                        .map(|c| (c.clone(), a.extra_exposure_s(timing.exposure_s(c), k)))
                        .collect()
                })
                .collect(),
            _ => self
                .meta
                .exposure_policy
                .first_exposures(0.0)
                .into_iter()
                .map(|t| cams.iter().map(|c| (c.clone(), t)).collect())
                .collect(),
        };
        let threshold = self.meta.exposure_policy.auto().map(|a| a.threshold);
        let pending = Pending {
            trigger: i,
            t_s,
            reached,
        };
        let mut entries = held;
        for times in series {
            let want: Vec<(String, f64)> = times.iter().map(|(c, t)| (c.clone(), *t)).collect();
            set_exposures(
                &self.clock,
                &mut self.rig.cameras,
                &mut self.exposure_set,
                &want,
            )
            .await?;
            expose(&self.clock, &timing, &mut self.rig.cameras, &cams).await?;
            let mut frames = transfer(
                &self.clock,
                &timing,
                &self.schedule,
                &mut self.rig.cameras,
                i,
            )
            .await?;
            let rule = threshold.map(|threshold| HoldRule {
                profile: &self.profile,
                threshold,
            });
            let clipped = rule.is_some_and(|rule| {
                self.schedule.triggers[i].images.iter().any(|&n| {
                    let img = &self.schedule.images[n];
                    frames
                        .get(&img.camera)
                        .is_some_and(|frame| rule.clips(&img.camera, img.achieved_view, frame))
                })
            });
            entries = Some(match entries.take() {
                None => {
                    let work = step_entries(&self.schedule, &pending, frames, &times)?;
                    in_store(&self.store, move |dir| {
                        let root = dir.root().to_path_buf();
                        work.into_iter()
                            .map(|(entry, frame)| RunDir::write_frame(&root, entry, &frame))
                            .collect()
                    })
                    .await?
                }
                Some(mut so_far) => {
                    for entry in &so_far {
                        if !frames.contains_key(&entry.camera) {
                            return Err(DeviceError::new(
                                &entry.camera,
                                ErrorKind::BadFrame,
                                "camera delivered no frame",
                            )
                            .into());
                        }
                    }
                    in_store(&self.store, move |dir| {
                        let root = dir.root().to_path_buf();
                        for entry in &mut so_far {
                            if let Some(frame) = frames.remove(&entry.camera) {
                                let t = times.get(&entry.camera).copied().unwrap_or(0.0);
                                let k = entry.brackets.len() + 1;
                                RunDir::write_bracket(&root, entry, k, t, &frame)?;
                            }
                        }
                        Ok(so_far)
                    })
                    .await?
                }
            });
            if rule.is_some() && !clipped {
                break;
            }
        }
        let entries = entries.unwrap_or_default();
        let journal = entries.clone();
        in_store(&self.store, move |dir| dir.append_journal(&journal)).await?;
        self.held.remove(&i);
        self.step_done(i, entries);
        Ok(())
    }

    /// Records a journaled step's images as taken and tells the listeners.
    fn step_done(&mut self, trigger: usize, entries: Vec<FrameEntry>) {
        let images = entries.iter().map(|e| e.index).collect();
        for e in entries {
            self.done.insert(e.index, e);
        }
        let (done, total) = (self.done.len(), self.schedule.images.len());
        self.emit(EventKind::Step {
            trigger,
            images,
            frames_done: done,
            frames_total: total,
        });
    }

    fn cameras_of(&self, trigger: usize) -> Vec<String> {
        self.schedule.triggers[trigger]
            .images
            .iter()
            .map(|&i| self.schedule.images[i].camera.clone())
            .collect()
    }

    /// Runs the laser sweep whose trigger heads the queue (Wang et al., §3.2):
    /// moves to its first pose with the laser on, starts the tilt axis at
    /// the sweep velocity, and while it runs exposes every camera at the
    /// video rate, recording the tilt measured just before and after each
    /// exposure (their mean). A fault retakes the whole sweep.
    async fn sweep(&mut self, queue: &mut VecDeque<usize>) -> Result<(), StepFault> {
        self.settled = None;
        let Some(&head) = queue.front() else {
            return Ok(());
        };
        let (Some(id), Some(run)) = (
            self.schedule.triggers[head].sweep,
            self.schedule.laser.clone(),
        ) else {
            return Ok(());
        };
        let members: Vec<usize> = self
            .schedule
            .triggers
            .iter()
            .filter(|t| t.sweep == Some(id))
            .map(|t| t.index)
            .collect();
        let (Some(&first), Some(&last)) = (members.first(), members.last()) else {
            return Ok(());
        };
        let start = self.schedule.triggers[first].setpoints.clone();
        let end_tilt = self.schedule.triggers[last]
            .setpoints
            .axes
            .get(&run.tilt_axis)
            .copied()
            .unwrap_or_default();
        let tilt_name = run.tilt_axis.clone();
        let period = 1.0 / run.plan.frame_hz;
        let timing = Timing::new(&self.profile, self.meta.exposure_s);
        let reached = {
            let Rig {
                axes,
                arms,
                lamps,
                lasers,
                fixture,
                ..
            } = &mut self.rig;
            goto(
                &self.clock,
                &timing,
                Movers {
                    axes,
                    arms,
                    fixture,
                    plate_known: self.plate_known,
                },
                &mut Lights { lamps, lasers },
                &self.pos,
                None,
                &start,
            )
            .await?
        };
        self.pos = reached;
        self.plate_known = true;
        let no_axis = || no_tilt_axis(&tilt_name);
        let budget = DEADLINE_SLACK_S;
        {
            let axis = self.rig.axes.get_mut(&tilt_name).ok_or_else(no_axis)?;
            deadline(
                &self.clock,
                &tilt_name,
                budget,
                axis.start_sweep(end_tilt, run.velocity_deg_s),
            )
            .await?;
        }
        let t0 = self.clock.now_s();
        let result = self.sweep_frames(&members, &run, t0, period).await;
        // Whatever happened, the axis ends its move before anything else
        // commands it.
        let remaining = (members.len() as f64 * period - (self.clock.now_s() - t0)).max(0.0);
        let idle = match self.rig.axes.get_mut(&tilt_name) {
            Some(axis) => {
                deadline(
                    &self.clock,
                    &tilt_name,
                    remaining * 2.0 + budget,
                    axis.wait_idle(),
                )
                .await
            }
            None => Err(no_axis().error),
        };
        result?;
        let at = idle?;
        self.pos.axes.insert(tilt_name, at);
        queue.retain(|t| !members.contains(t));
        Ok(())
    }

    /// The frames of a running sweep, one trigger per video frame.
    async fn sweep_frames(
        &mut self,
        members: &[usize],
        run: &crate::schedule::laser::LaserRun,
        t0: f64,
        period: f64,
    ) -> Result<(), StepFault> {
        for (j, &trigger) in members.iter().enumerate() {
            let due = t0 + j as f64 * period;
            let wait = due - self.clock.now_s();
            if wait > 0.0 {
                self.clock.sleep_s(wait).await;
            }
            if self.estop.is_tripped() {
                return Err(DeviceError::new(
                    &run.tilt_axis,
                    ErrorKind::NotReady,
                    "sweep cut short by the emergency stop",
                )
                .into());
            }
            let cams = self.cameras_of(trigger);
            let timing = Timing::new(&self.profile, self.meta.exposure_s);
            let t_s = self.t();
            let tilt = {
                let Rig { axes, cameras, .. } = &mut self.rig;
                let axis = axes
                    .get_mut(&run.tilt_axis)
                    .ok_or_else(|| no_tilt_axis(&run.tilt_axis))?;
                let before = deadline(
                    &self.clock,
                    &run.tilt_axis,
                    DEADLINE_SLACK_S,
                    axis.position(),
                )
                .await?;
                expose(&self.clock, &timing, cameras, &cams).await?;
                let after = deadline(
                    &self.clock,
                    &run.tilt_axis,
                    DEADLINE_SLACK_S,
                    axis.position(),
                )
                .await?;
                0.5 * (before + after)
            };
            let mut reached = self.schedule.triggers[trigger].setpoints.clone();
            for (name, v) in &self.pos.axes {
                if name != &run.tilt_axis {
                    reached.axes.insert(name.clone(), *v);
                }
            }
            reached.axes.insert(run.tilt_axis.clone(), tilt);
            let pending = Pending {
                trigger,
                t_s,
                reached,
            };
            let entries = finish(
                &self.clock,
                &timing,
                &self.schedule,
                &self.store,
                &mut self.rig.cameras,
                &pending,
                self.meta.exposure_s,
                None,
            )
            .await?;
            // A sweep's frames are never held: it takes one exposure each.
            let (Finished::Journaled(entries) | Finished::Held(entries)) = entries;
            self.step_done(trigger, entries);
        }
        Ok(())
    }

    /// Homes every axis and arm, sets exposures, and switches on and warms
    /// up the first trigger's lamp. Returns where the rig stands.
    async fn prepare(&mut self, first: Option<usize>) -> Result<Setpoints, StepFault> {
        self.settled = None;
        self.exposure_set.clear();
        let clock = &self.clock;
        let Rig {
            axes,
            arms,
            lamps,
            lasers,
            cameras,
            ..
        } = &mut self.rig;
        let homing = join_all(axes.iter_mut().map(|(name, a)| async move {
            deadline(clock, name, HOMING_DEADLINE_S, a.home())
                .await
                .map(|x| (name.clone(), x))
        }));
        let arm_homing = join_all(
            arms.iter_mut()
                .map(|(name, a)| deadline(clock, name, HOMING_DEADLINE_S, a.home())),
        );
        let (h, ah) = tokio::join!(homing, arm_homing);
        let mut homed = BTreeMap::new();
        for r in h {
            let (name, x) = r?;
            homed.insert(name, x);
        }
        for r in ah {
            r?;
        }
        if let Some(exposure) = self.meta.exposure_s {
            for (name, c) in cameras.iter_mut() {
                deadline(clock, name, DEADLINE_SLACK_S, c.set_exposure(exposure)).await?;
            }
        }
        let timing = Timing::new(&self.profile, self.meta.exposure_s);
        let mut at = timing.home_setpoints();
        // Where each axis reports it stands: an axis without homing is
        // wherever the operator zeroed it, not necessarily at its home.
        at.axes.extend(homed);
        // Homing moves no plate.
        at.plate_mm = self.pos.plate_mm;
        // Every lamp off, the needed one too: a known state after a crash,
        // and a lamp whose ballast tripped is struck again, not trusted.
        let lamp = first
            .map(|t| self.schedule.triggers[t].setpoints.lamp.clone())
            .unwrap_or_default();
        for (name, l) in lamps.iter_mut() {
            deadline(clock, name, DEADLINE_SLACK_S, l.set(false)).await?;
        }
        for (name, l) in lasers.iter_mut() {
            deadline(clock, name, DEADLINE_SLACK_S, l.set(false)).await?;
        }
        switch_lamp(clock, &timing, &mut Lights { lamps, lasers }, "", &lamp).await?;
        at.lamp = lamp;
        Ok(at)
    }

    /// Decides between retry and pause.
    async fn handle_fault(
        &mut self,
        fault: StepFault,
        trigger: usize,
        attempts: &mut HashMap<usize, u32>,
    ) -> Result<Flow, EngineError> {
        // Whatever failed, a camera's exposure is no longer known.
        self.exposure_set.clear();
        let n = attempts.entry(trigger).or_insert(0);
        *n += 1;
        let attempt = *n;
        if self.estop.is_tripped() {
            // A call cut short by the stop is no device fault: never retry.
            attempts.remove(&trigger);
            tracing::info!("call ended by the emergency stop: {}", fault.error);
            return self.fault_pause(ESTOP_REASON.into()).await;
        }
        if fault.retryable && attempt < self.retry.max_attempts {
            tracing::warn!(device = %fault.error.device, attempt, "retrying: {}", fault.error);
            self.emit(EventKind::Retry {
                device: fault.error.device.clone(),
                reason: fault.error.to_string(),
                attempt,
            });
            self.clock
                .sleep_s(self.retry.backoff_s * attempt as f64)
                .await;
            return Ok(Flow::Continue);
        }
        attempts.remove(&trigger);
        self.fault_pause(fault.error.to_string()).await
    }

    /// Pauses for a fault; after the operator resumes, the rig is prepared
    /// again (re-homed, lamp warmed) before the run goes on.
    async fn fault_pause(&mut self, reason: String) -> Result<Flow, EngineError> {
        self.settled = None;
        self.go(RunState::Paused, Some(reason))?;
        if !self.wait_in_pause().await? {
            return Ok(Flow::Stop);
        }
        self.prepare_after_pause().await
    }

    /// From Paused, after a resume: prepares the rig again; pauses anew
    /// (and waits) for as long as preparing fails.
    async fn prepare_after_pause(&mut self) -> Result<Flow, EngineError> {
        loop {
            self.go(RunState::Preparing, None)?;
            let first = self.todo().front().copied();
            match self.prepare(first).await {
                Ok(at) => {
                    self.pos = at;
                    self.estop.rearm();
                    return Ok(Flow::Continue);
                }
                Err(e) => {
                    self.go(RunState::Paused, Some(e.error.to_string()))?;
                    if !self.wait_in_pause().await? {
                        return Ok(Flow::Stop);
                    }
                }
            }
        }
    }

    /// In Paused: true when resumed, false when the run stops here
    /// (aborted, detached, or the caller does not wait).
    async fn wait_in_pause(&mut self) -> Result<bool, EngineError> {
        if self.policy == PausePolicy::Return {
            return Ok(false);
        }
        loop {
            let command = if self.unrecorded.is_some() {
                // The pause itself is not on disk yet: try again now and
                // then, so an operator who frees space sees the truth there
                // without resuming first.
                let retry = self.clock.sleep_s(STATE_RETRY_S);
                tokio::select! {
                    c = self.commands.recv() => c,
                    _ = retry => {
                        if self.record_state().is_ok() {
                            tracing::info!("recorded the run's state at last");
                        }
                        continue;
                    }
                }
            } else {
                self.commands.recv().await
            };
            match command {
                Some(Command::Resume) => return Ok(true),
                Some(Command::Abort) => {
                    self.abort().await?;
                    return Ok(false);
                }
                Some(Command::Detach) | None => return Ok(false),
                Some(Command::Pause) => self.emit(EventKind::Refused {
                    command: Command::Pause,
                    state: self.state,
                }),
                // Already paused; the tripped stop makes the resume re-home.
                Some(Command::EmergencyStop) => {}
            }
        }
    }

    /// Handles an operator command between triggers.
    async fn command(
        &mut self,
        cmd: Command,
        pending: &mut Option<Pending>,
        queue: &mut VecDeque<usize>,
    ) -> Result<Option<Flow>, EngineError> {
        // An operator may touch the rig while it waits.
        self.settled = None;
        if let Err(refused) = check_command(self.state, cmd) {
            self.emit(EventKind::Refused {
                command: refused.command,
                state: refused.state,
            });
            return Ok(None);
        }
        // Whatever happens next, frames already exposed are kept.
        if let Some(p) = pending.take() {
            let timing = Timing::new(&self.profile, self.meta.exposure_s);
            let hold = self.meta.exposure_policy.auto().map(|a| HoldRule {
                profile: &self.profile,
                threshold: a.threshold,
            });
            let r = finish(
                &self.clock,
                &timing,
                &self.schedule,
                &self.store,
                &mut self.rig.cameras,
                &p,
                self.meta.exposure_s,
                hold,
            )
            .await;
            match r {
                Ok(Finished::Journaled(entries)) => {
                    for e in entries {
                        self.done.insert(e.index, e);
                    }
                }
                Ok(Finished::Held(entries)) => {
                    self.held.insert(p.trigger, entries);
                    queue.push_front(p.trigger);
                }
                Err(_) => queue.push_front(p.trigger),
            }
        }
        match cmd {
            Command::Pause => {
                self.go(RunState::Paused, Some("paused by operator".into()))?;
                if !self.wait_in_pause().await? {
                    return Ok(Some(Flow::Stop));
                }
                if self.estop.is_tripped() {
                    // Stopped while paused: the rig must re-home first.
                    return self.prepare_after_pause().await.map(Some);
                }
                self.go(RunState::Running, None)?;
                Ok(Some(Flow::Continue))
            }
            Command::EmergencyStop => self.fault_pause(ESTOP_REASON.into()).await.map(Some),
            Command::Abort => {
                self.abort().await?;
                Ok(Some(Flow::Stop))
            }
            Command::Detach => {
                self.go(
                    RunState::Paused,
                    Some("detached; resume from the run directory".into()),
                )?;
                Ok(Some(Flow::Stop))
            }
            Command::Resume => Ok(None),
        }
    }

    async fn abort(&mut self) -> Result<(), EngineError> {
        self.lamps_off().await;
        let reason = Some("aborted by operator".to_string());
        if let Err(e) = self.write_manifest(RunState::Aborted, reason.clone()) {
            // The operator's abort stands; the journal still lists every frame.
            let why = storage_fault_reason(&self.meta_root(), &e);
            tracing::error!("aborted without a manifest: {why}");
        }
        self.go(RunState::Aborted, reason)?;
        Ok(())
    }

    /// Ends the run once its plan is through: the journal checked, the
    /// manifest, then the final state. The journal as read back from disk
    /// decides: an image it lacks (a line lost behind the writer's back) is
    /// not taken, and the run pauses naming it, so that a resume takes it
    /// ([`Flow::Continue`], after which the caller queues what is left). A
    /// manifest the disk cannot take pauses the run as well.
    async fn complete(&mut self) -> Result<Flow, EngineError> {
        let total = self.schedule.images.len();
        let checked = lock_store(&self.store).check_complete(total);
        let missing = match checked {
            Ok(missing) => missing,
            Err(e) => {
                let why = storage_fault_reason(&self.meta_root(), &e);
                return self.fault_pause(why).await;
            }
        };
        if !missing.is_empty() {
            for i in &missing {
                self.done.remove(i);
            }
            let reason = format!(
                "{} lacks {} of the plan's {total} images ({}): resume to take them",
                crate::store::JOURNAL_FILE,
                missing.len(),
                crate::store::image_list(&missing)
            );
            return self.fault_pause(reason).await;
        }
        // The capture ends with its last frame; switching off is not part of it.
        self.finished_at_s = Some(self.t());
        self.lamps_off().await;
        // The manifest first: whoever sees the run end can read it.
        if let Err(e) = self.write_manifest(RunState::Completed, None) {
            self.finished_at_s = None;
            let why = storage_fault_reason(&self.meta_root(), &e);
            return self.fault_pause(why).await;
        }
        self.go(RunState::Completed, None)?;
        Ok(Flow::Stop)
    }

    /// Leaves the lamps dark at the end; a failure here is logged, not fatal.
    async fn lamps_off(&mut self) {
        for (name, l) in self.rig.lamps.iter_mut() {
            if let Err(e) = deadline(&self.clock, name, DEADLINE_SLACK_S, l.set(false)).await {
                tracing::warn!("could not switch {name} off: {e}");
            }
        }
        for (name, l) in self.rig.lasers.iter_mut() {
            if let Err(e) = deadline(&self.clock, name, DEADLINE_SLACK_S, l.set(false)).await {
                tracing::warn!("could not switch {name} off: {e}");
            }
        }
    }

    /// Writes the manifest of a run ending in `state`.
    fn write_manifest(&self, state: RunState, reason: Option<String>) -> Result<(), StoreError> {
        let infeasible = self
            .schedule
            .infeasible()
            .map(|i| InfeasibleEntry {
                index: i.index,
                light: i.light,
                view: i.view,
                achieved_light: i.achieved_light,
                achieved_view: i.achieved_view,
                reason: i.reason.clone().unwrap_or_default(),
            })
            .collect();
        let manifest = Manifest {
            format: RUN_FORMAT.into(),
            software_version: env!("CARGO_PKG_VERSION").into(),
            profile: self.profile.name.clone(),
            plan: self.schedule.plan.clone(),
            sample: self.meta.sample.clone(),
            state,
            reason,
            steps_total: self.schedule.images.len(),
            triggers_total: self.schedule.triggers.len(),
            frames_written: self.done.len(),
            physical_duration_s: self.finished_at_s.unwrap_or_else(|| self.t()),
            started_at: self.meta.started_at.clone(),
            finished_at: now_rfc3339(),
            infeasible,
            frames: self.done.values().cloned().collect(),
        };
        lock_store(&self.store).write_manifest(&manifest)?;
        Ok(())
    }
}

fn lock_store(store: &Mutex<RunDir>) -> std::sync::MutexGuard<'_, RunDir> {
    // A panic inside a write leaves at worst a torn journal tail, which the
    // reader repairs; the directory handle itself stays valid.
    rigd_core::sync::lock(store)
}

/// Runs a device call under a physical deadline.
async fn deadline<T>(
    clock: &Clock,
    device: &str,
    seconds: f64,
    fut: impl Future<Output = Result<T, DeviceError>>,
) -> Result<T, DeviceError> {
    match clock
        .deadline(Duration::from_secs_f64(seconds.max(0.001)), fut)
        .await
    {
        Ok(r) => r,
        Err(_) => Err(DeviceError::new(
            device,
            ErrorKind::Timeout,
            format!("no answer within {seconds:.1} s"),
        )),
    }
}

/// What lights a trigger: its lamps and lasers, by name.
struct Lights<'a> {
    lamps: &'a mut BTreeMap<String, Box<dyn Lamp>>,
    lasers: &'a mut BTreeMap<String, Box<dyn LaserLine>>,
}

/// What moves (or is placed) before a trigger.
struct Movers<'a> {
    axes: &'a mut BTreeMap<String, Box<dyn Axis>>,
    arms: &'a mut BTreeMap<String, Box<dyn Arm>>,
    fixture: &'a mut Option<Box<dyn Fixture>>,
    /// False: place (or remove) the plate whatever `from` says.
    plate_known: bool,
}

/// Switches from lamp (or laser) `from` to `to` and waits for it to be stable.
async fn switch_lamp(
    clock: &Clock,
    timing: &Timing<'_>,
    lights: &mut Lights<'_>,
    from: &str,
    to: &str,
) -> Result<(), DeviceError> {
    if from == to {
        return Ok(());
    }
    let budget = timing.lamp_change_s(from, to) + DEADLINE_SLACK_S;
    if let Some(l) = lights.lamps.get_mut(from) {
        deadline(clock, from, budget, l.set(false)).await?;
    }
    if let Some(l) = lights.lasers.get_mut(from) {
        deadline(clock, from, budget, l.set(false)).await?;
    }
    if let Some(l) = lights.lamps.get_mut(to) {
        deadline(clock, to, budget, l.set(true)).await?;
        deadline(clock, to, budget, l.wait_ready()).await?;
    }
    if let Some(l) = lights.lasers.get_mut(to) {
        deadline(clock, to, budget, l.set(true)).await?;
    }
    Ok(())
}

/// A laser plan on a rig whose tilt axis is missing.
fn no_tilt_axis(name: &str) -> StepFault {
    StepFault::from(DeviceError::new(
        name,
        ErrorKind::NotReady,
        "the laser tilt axis is not connected",
    ))
}

/// Places or removes the laser calibration plate; `from` None: unknown.
async fn place_plate(
    clock: &Clock,
    fixture: &mut Option<Box<dyn Fixture>>,
    from: Option<Option<f64>>,
    to: Option<f64>,
) -> Result<(), DeviceError> {
    if from == Some(to) {
        return Ok(());
    }
    let Some(f) = fixture.as_mut() else {
        if to.is_none() {
            // A rig without a plate has none to remove.
            return Ok(());
        }
        return Err(DeviceError::new(
            "plate",
            ErrorKind::NotReady,
            "this rig has no way to place the calibration plate",
        ));
    };
    deadline(clock, "plate", PLATE_DEADLINE_S, f.place(to)).await
}

/// Moves every axis and the arm to `to` and changes the lamp, all in
/// parallel; returns where the devices report they stand.
async fn goto(
    clock: &Clock,
    timing: &Timing<'_>,
    movers: Movers<'_>,
    lights: &mut Lights<'_>,
    from: &Setpoints,
    settled: Option<&Setpoints>,
    to: &Setpoints,
) -> Result<Setpoints, StepFault> {
    let Movers {
        axes,
        arms,
        fixture,
        plate_known,
    } = movers;
    // The plate goes in or out before anything moves over it.
    let from_plate = plate_known.then_some(from.plate_mm);
    place_plate(clock, fixture, from_plate, to.plate_mm).await?;
    let budget = timing.motion_s(from, to) * 2.0 + DEADLINE_SLACK_S;
    // A device already settled where this step wants it is left alone: on
    // a serial line each command is a round trip the step waits for.
    let stays = |name: &String, x: f64| {
        from.axes.contains_key(name) && settled.and_then(|s| s.axes.get(name)) == Some(&x)
    };
    let arm_stays = from.arm.is_some() && settled.and_then(|s| s.arm.as_ref()) == to.arm.as_ref();
    let axis_moves = join_all(
        axes.iter_mut()
            .filter_map(|(name, a)| to.axes.get(name).map(|&x| (name, a, x)))
            .filter(|(name, _, x)| !stays(name, *x))
            .map(|(name, a, x)| async move {
                deadline(clock, name, budget, a.move_to(x))
                    .await
                    .map(|p| (name.clone(), p))
            }),
    );
    let arm_move = async {
        match (&to.arm, arms.iter_mut().next()) {
            (Some(_), Some(_)) if arm_stays => Ok(from.arm.clone()),
            (Some(q), Some((name, arm))) => deadline(clock, name, budget, arm.move_joints(q))
                .await
                .map(Some),
            _ => Ok(None),
        }
    };
    let lamp = switch_lamp(clock, timing, lights, &from.lamp, &to.lamp);
    let (moved, arm, lamp) = tokio::join!(axis_moves, arm_move, lamp);
    let mut reached = Setpoints {
        axes: BTreeMap::new(),
        arm: None,
        lamp: to.lamp.clone(),
        plate_mm: to.plate_mm,
    };
    for r in moved {
        let (name, p) = r?;
        reached.axes.insert(name, p);
    }
    reached.arm = arm?;
    lamp?;
    // Axes the plan does not mention keep their place.
    for (name, p) in &from.axes {
        reached.axes.entry(name.clone()).or_insert(*p);
    }
    Ok(reached)
}

/// Exposes the given cameras together; returns when every sensor is free.
async fn expose(
    clock: &Clock,
    timing: &Timing<'_>,
    cameras: &mut BTreeMap<String, Box<dyn Camera>>,
    which: &[String],
) -> Result<(), StepFault> {
    let names: Vec<&str> = which.iter().map(String::as_str).collect();
    let budget = timing.expose_s(&names) + DEADLINE_SLACK_S;
    let calls = cameras
        .iter_mut()
        .filter(|(n, _)| which.contains(n))
        .map(|(n, c)| deadline(clock, n, budget, c.expose()));
    for r in join_all(calls).await {
        r?;
    }
    Ok(())
}

/// What the `auto` exposure policy holds back: a step whose frame clips
/// more than `threshold` of the sample's pixels (where `profile`'s pose
/// puts the sample) waits, unjournaled, for shorter exposures.
#[derive(Clone, Copy)]
struct HoldRule<'a> {
    profile: &'a Profile,
    threshold: f64,
}

impl HoldRule<'_> {
    /// Whether `frame`, from `camera` at `view`, clips more of the sample
    /// than the rule allows.
    fn clips(&self, camera: &str, view: rigd_core::Direction, frame: &Frame) -> bool {
        let window =
            bracket::sample_window(self.profile, camera, [frame.width, frame.height], view);
        bracket::clipped_share(frame, window.as_ref()) > self.threshold
    }
}

/// What became of a trigger's frames once transferred and written.
enum Finished {
    /// Journaled: the images are taken.
    Journaled(Vec<FrameEntry>),
    /// Written but not journaled: the sample clipped, so the rig comes
    /// back for shorter exposures ([`HoldRule`]).
    Held(Vec<FrameEntry>),
}

/// Transfers a trigger's frames, checks them, writes them and journals
/// them; under a [`HoldRule`] a step that clipped is written and held.
#[allow(clippy::too_many_arguments)]
async fn finish(
    clock: &Clock,
    timing: &Timing<'_>,
    schedule: &Schedule,
    store: &Arc<Mutex<RunDir>>,
    cameras: &mut BTreeMap<String, Box<dyn Camera>>,
    p: &Pending,
    exposure_override: Option<f64>,
    hold: Option<HoldRule<'_>>,
) -> Result<Finished, StepFault> {
    let frames = transfer(clock, timing, schedule, cameras, p.trigger).await?;
    let exposures: BTreeMap<String, f64> = frames
        .keys()
        .map(|c| {
            (
                c.clone(),
                exposure_override.unwrap_or_else(|| timing.exposure_s(c)),
            )
        })
        .collect();
    let work = step_entries(schedule, p, frames, &exposures)?;
    let held = hold.is_some_and(|rule| {
        work.iter()
            .any(|(entry, frame)| rule.clips(&entry.camera, entry.achieved_view, frame))
    });
    in_store(store, move |dir| {
        let root = dir.root().to_path_buf();
        let mut entries = Vec::with_capacity(work.len());
        for (entry, frame) in work {
            entries.push(RunDir::write_frame(&root, entry, &frame)?);
        }
        if held {
            return Ok(Finished::Held(entries));
        }
        dir.append_journal(&entries)?;
        Ok(Finished::Journaled(entries))
    })
    .await
}

/// Transfers the frames of trigger `trigger` from its cameras, each
/// checked, by camera.
async fn transfer(
    clock: &Clock,
    timing: &Timing<'_>,
    schedule: &Schedule,
    cameras: &mut BTreeMap<String, Box<dyn Camera>>,
    trigger: usize,
) -> Result<HashMap<String, Frame>, StepFault> {
    let trig = &schedule.triggers[trigger];
    let which: Vec<&str> = trig
        .images
        .iter()
        .map(|&i| schedule.images[i].camera.as_str())
        .collect();
    let budget = timing.transfer_s(&which) * 2.0 + DEADLINE_SLACK_S;
    let calls = cameras
        .iter_mut()
        .filter(|(n, _)| which.contains(&n.as_str()))
        .map(|(n, c)| async move {
            deadline(clock, n, budget, c.transfer())
                .await
                .map(|f| (n.clone(), f))
        });
    let mut frames: HashMap<String, Frame> = HashMap::new();
    for r in join_all(calls).await {
        let (name, frame) = r?;
        frame.validate(&name)?;
        frames.insert(name, frame);
    }
    Ok(frames)
}

/// The journal entries of a trigger's images, each with its frame, not yet
/// written: `exposures` gives each camera's exposure time.
fn step_entries(
    schedule: &Schedule,
    p: &Pending,
    mut frames: HashMap<String, Frame>,
    exposures: &BTreeMap<String, f64>,
) -> Result<Vec<(FrameEntry, Frame)>, StepFault> {
    let trig = &schedule.triggers[p.trigger];
    let mut work = Vec::new();
    for &i in &trig.images {
        let img = &schedule.images[i];
        let Some(frame) = frames.remove(&img.camera) else {
            return Err(DeviceError::new(
                &img.camera,
                ErrorKind::BadFrame,
                "camera delivered no frame",
            )
            .into());
        };
        let entry = FrameEntry {
            index: img.index,
            trigger: img.trigger,
            file: String::new(),
            sha256: String::new(),
            light: img.light,
            view: img.view,
            achieved_light: img.achieved_light,
            achieved_view: img.achieved_view,
            camera: img.camera.clone(),
            exposure_s: exposures.get(&img.camera).copied().unwrap_or(0.0),
            t_s: p.t_s,
            positions: p.reached.clone(),
            width: 0,
            height: 0,
            bit_depth: 0,
            laser: img.laser.map(|mut l| {
                // The tilt as measured, not as planned.
                let measured = schedule
                    .laser
                    .as_ref()
                    .and_then(|run| p.reached.axes.get(&run.tilt_axis));
                if let Some(&t) = measured {
                    l.tilt_deg = t;
                }
                l
            }),
            device: None,
            brackets: Vec::new(),
        };
        work.push((entry, frame));
    }
    Ok(work)
}

/// Runs `work` on the run directory off the async runtime: encoding and
/// fsync are blocking work, and on a paused runtime tokio does not advance
/// virtual time while it runs. A failure is a storage fault, never retried.
async fn in_store<T: Send + 'static>(
    store: &Arc<Mutex<RunDir>>,
    work: impl FnOnce(&mut RunDir) -> Result<T, StoreError> + Send + 'static,
) -> Result<T, StepFault> {
    let store = store.clone();
    let root = lock_store(&store).root().to_path_buf();
    let done = tokio::task::spawn_blocking(move || work(&mut lock_store(&store))).await;
    let why = match done {
        Ok(Ok(value)) => return Ok(value),
        Ok(Err(e)) => storage_fault_reason(&root, &e),
        Err(e) => format!("writer task failed: {e}"),
    };
    Err(StepFault {
        error: DeviceError::new(STORAGE_DEVICE, ErrorKind::Storage, why),
        retryable: false,
    })
}

/// Sets each camera of `want` to its exposure time where `known` does not
/// already say it is; a camera whose call fails is no longer known.
async fn set_exposures(
    clock: &Clock,
    cameras: &mut BTreeMap<String, Box<dyn Camera>>,
    known: &mut BTreeMap<String, f64>,
    want: &[(String, f64)],
) -> Result<(), StepFault> {
    for (name, t) in want {
        if known.get(name) == Some(t) {
            continue;
        }
        known.remove(name);
        if let Some(c) = cameras.get_mut(name) {
            deadline(clock, name, DEADLINE_SLACK_S, c.set_exposure(*t)).await?;
            known.insert(name.clone(), *t);
        }
    }
    Ok(())
}
