//! Wiring one run together: profile, plan, schedule, rig, run directory and
//! engine, for a new run or a resumed one. The command line and the tests
//! both start runs through here.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rigd_core::Clock;

use crate::engine::{Engine, EngineHandle, PausePolicy};
use crate::kinematics::{KinematicsError, Solver};
use crate::model::exposure::ExposurePolicy;
use crate::model::profile::{Profile, ProfileError};
use crate::plan::Order;
use crate::plan::{self, Plan, PlanError};
use crate::rig::hal::{DeviceError, Rig};
use crate::rig::{self, SimHandle, Simulator};
use crate::schedule::timing::Timing;
use crate::schedule::{self, Schedule};
use crate::store::{now_rfc3339, Recovery, RunDir, RunMeta, SimScene, StoreError, RUN_FORMAT};

/// Why a run could not be started or resumed.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The profile could not be read, parsed or validated.
    #[error(transparent)]
    Profile(#[from] ProfileError),
    /// The plan is unknown, its file is unusable, or it does not fit the rig.
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// The pose solver cannot be built for the profile's rig.
    #[error("pose solver: {0}")]
    Kinematics(#[from] KinematicsError),
    /// The run directory could not be created or opened: it is not empty,
    /// already holds a run, is finished, damaged, or the disk failed.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The simulated rig could not be set up (its scene, a device).
    #[error("connecting the simulated rig: {0}")]
    Simulator(DeviceError),
    /// A device of the profile's hardware could not be connected.
    #[error("connecting the rig's hardware: {0} (add --sim to use the simulated rig)")]
    Hardware(DeviceError),
    /// The request cannot be used: a bad exposure, a blank sample name, a
    /// journal naming images the plan lacks, or a simulated run without a
    /// simulated rig (a build without the simulator).
    #[error("{0}")]
    Invalid(String),
}

/// A new run as asked for on the command line or over the API.
#[derive(Debug, Clone)]
pub struct NewRun {
    /// The rig profile to run on; a snapshot of it goes into `run.json`.
    pub profile: Profile,
    /// Where the profile came from (a path, or `<embedded NAME>`).
    pub profile_source: String,
    /// The plan as given (`h1`, `laser:…`, a plan file path); only a label
    /// when the plan comes already solved ([`prepare_new_solved`]).
    pub plan: String,
    /// Name of the measured sample; must not be blank.
    pub sample: String,
    /// Who runs the capture, if given.
    pub operator: Option<String>,
    /// Free-text notes on the run, if given.
    pub notes: Option<String>,
    /// Exposure of every camera in seconds (positive, checked); None: each
    /// camera's exposure from the profile (laser plans: the plan's).
    pub exposure_s: Option<f64>,
    /// The exposures each step takes; None: the profile's
    /// (`[exposure_policy]`, one exposure if it has none). A laser sweep
    /// takes one exposure per frame whatever the policy.
    pub exposure_policy: Option<ExposurePolicy>,
    /// Simulated frames' `[width, height]` in pixels; None: the profile's
    /// simulator size. Ignored on hardware.
    pub frame_size: Option<[u32; 2]>,
    /// The run directory to create; it must be new or empty.
    pub out: PathBuf,
    /// Drive the simulated rig instead of the profile's hardware.
    pub simulated: bool,
    /// The trigger order; None: the plan's default (optimised, laser
    /// plans as planned).
    pub order: Option<Order>,
}

/// An engine ready to run, and what a progress display needs to know.
pub struct Prepared {
    /// The engine; [`Engine::run`] drives the run.
    pub engine: Engine,
    /// Commands, events and the emergency stop of that engine.
    pub handle: EngineHandle,
    /// The simulated rig's faults and world (None on hardware).
    pub sim: Option<SimHandle>,
    /// The run directory.
    pub root: PathBuf,
    /// Images in the plan.
    pub frames_total: usize,
    /// Images that already have a valid frame (0 for a new run).
    pub frames_done: usize,
    /// Physical time already spent (resumed runs).
    pub t_offset_s: f64,
    /// Estimated physical time of what is left.
    pub estimate_s: f64,
    /// Frames found damaged or missing on resume, to be retaken.
    pub retake: Vec<usize>,
    /// What the run was asked for, as its `run.json` holds it.
    pub meta: RunMeta,
}

/// Resolves a plan for a profile and solves every pose.
pub fn solve_plan(
    profile: &Profile,
    plan_spec: &str,
    order: Option<Order>,
) -> Result<(Solver, Plan, Schedule), RunError> {
    let (solver, plan) = resolve_plan(profile, plan_spec, order)?;
    let schedule = schedule::build(profile, &solver, &plan);
    Ok((solver, plan, schedule))
}

/// The plan a spec names for the rig, not yet solved: everything that can
/// refuse it (an unknown name, a plan the rig cannot take), without the
/// seconds of work [`schedule::build`] takes for its trigger order.
pub fn resolve_plan(
    profile: &Profile,
    plan_spec: &str,
    order: Option<Order>,
) -> Result<(Solver, Plan), RunError> {
    let solver = Solver::new(profile)?;
    let offer = schedule::rig_offer(profile, &solver);
    let mut plan = plan::resolve(plan_spec, &offer)?;
    if let Some(o) = order {
        plan.order = o;
    }
    Ok((solver, plan))
}

fn check_request(req: &NewRun) -> Result<(), RunError> {
    if let Some(e) = req.exposure_s {
        req.profile
            .check_exposure_override(e)
            .map_err(|why| RunError::Invalid(format!("exposure {why}")))?;
    }
    if let Some(policy) = &req.exposure_policy {
        req.profile
            .check_exposure_policy(policy, req.exposure_s)
            .map_err(|(key, why)| RunError::Invalid(format!("exposure_policy.{key}: {why}")))?;
    }
    crate::model::text::check_name(&req.sample)
        .map_err(|why| RunError::Invalid(format!("the sample name {why}")))?;
    Ok(())
}

/// Connects the rig and creates the run directory and an engine. A
/// simulated run (`req.simulated`) runs on `sim`, the simulated rig the
/// caller wires in.
pub async fn prepare_new(
    req: NewRun,
    sim: Option<&dyn Simulator>,
    clock: Clock,
    policy: PausePolicy,
) -> Result<Prepared, RunError> {
    check_request(&req)?;
    let (solver, plan, schedule) = solve_plan(&req.profile, &req.plan, req.order)?;
    create(req, solver, plan, schedule, sim, clock, policy).await
}

/// Most the `slots` order may add to the optimised order's physical time
/// for a run processed during its capture to take it: each view slot's
/// lights are then all in early, and the slot is compressed while the
/// capture goes on.
pub const SLOTS_PREFERRED_WITHIN: f64 = 0.02;

/// The trigger order a run processed during its capture was given, and
/// what each candidate would take.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrderChoice {
    /// The order taken.
    pub order: Order,
    /// Estimated physical seconds in the optimised order.
    pub optimised_s: f64,
    /// Estimated physical seconds in the `slots` order.
    pub slots_s: f64,
}

/// For a run that compresses view slots during its capture and left its
/// order to the default (optimised): the `slots` order when it adds at
/// most [`SLOTS_PREFERRED_WITHIN`] physical time, else the plan as solved.
/// None when there was nothing to choose (another order asked for, a laser
/// plan, a plan whose order is kept).
pub fn prefer_slots(
    profile: &Profile,
    solved: (Solver, Plan, Schedule),
) -> ((Solver, Plan, Schedule), Option<OrderChoice>) {
    let (solver, plan, schedule) = solved;
    if plan.order != Order::Optimised || plan.laser.is_some() {
        return ((solver, plan, schedule), None);
    }
    let mut slots_plan = plan.clone();
    slots_plan.order = Order::Slots;
    let (slots_schedule, report) = schedule::build_with_report(profile, &solver, &slots_plan);
    let Some(slots_s) = report.slots_s.filter(|_| report.kept.is_none()) else {
        return ((solver, plan, schedule), None);
    };
    let mut choice = OrderChoice {
        order: Order::Optimised,
        optimised_s: report.optimised_s,
        slots_s,
    };
    if slots_s <= report.optimised_s * (1.0 + SLOTS_PREFERRED_WITHIN) {
        choice.order = Order::Slots;
        ((solver, slots_plan, slots_schedule), Some(choice))
    } else {
        ((solver, plan, schedule), Some(choice))
    }
}

impl std::fmt::Display for OrderChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let extra = 100.0 * (self.slots_s / self.optimised_s.max(1e-9) - 1.0);
        match self.order {
            Order::Slots => write!(
                f,
                "trigger order `slots` (each view's triggers together, so view slots are compressed during the capture): {extra:+.1} % physical time against `optimised`"
            ),
            _ => write!(
                f,
                "trigger order `optimised`: `slots`, which completes view slots early, would take {extra:+.1} % physical time (more than {:.0} %)",
                100.0 * SLOTS_PREFERRED_WITHIN
            ),
        }
    }
}

/// Solves an already resolved plan (e.g. one given inline over the API).
pub fn solve_given_plan(
    profile: &Profile,
    plan: Plan,
) -> Result<(Solver, Plan, Schedule), RunError> {
    let solver = Solver::new(profile)?;
    let schedule = schedule::build(profile, &solver, &plan);
    Ok((solver, plan, schedule))
}

/// Like [`prepare_new`], with the plan already solved (`req.plan` is then
/// only a label).
pub async fn prepare_new_solved(
    req: NewRun,
    solved: (Solver, Plan, Schedule),
    sim: Option<&dyn Simulator>,
    clock: Clock,
    policy: PausePolicy,
) -> Result<Prepared, RunError> {
    check_request(&req)?;
    let (solver, plan, schedule) = solved;
    create(req, solver, plan, schedule, sim, clock, policy).await
}

async fn create(
    req: NewRun,
    solver: Solver,
    plan: Plan,
    schedule: Schedule,
    sim: Option<&dyn Simulator>,
    clock: Clock,
    policy: PausePolicy,
) -> Result<Prepared, RunError> {
    let sim_scene = match (req.simulated, sim) {
        (true, Some(sim)) => {
            let (name, effects) = sim.scene(&req.profile).map_err(RunError::Simulator)?;
            Some(SimScene { name, effects })
        }
        (true, None) => return Err(no_simulator()),
        (false, _) => None,
    };
    let meta = RunMeta {
        format: RUN_FORMAT.into(),
        software_version: env!("CARGO_PKG_VERSION").into(),
        profile: req.profile.clone(),
        profile_source: req.profile_source,
        plan,
        sample: req.sample,
        operator: req.operator,
        notes: req.notes,
        exposure_s: req.exposure_s,
        exposure_policy: req
            .exposure_policy
            .unwrap_or_else(|| req.profile.exposure_policy.clone()),
        frame_size: req
            .simulated
            .then(|| req.frame_size.unwrap_or(req.profile.sim.frame_size)),
        simulated: req.simulated,
        sim_scene,
        started_at: now_rfc3339(),
    };
    // The rig first: a rig that does not answer leaves no run directory.
    let (rig, sim) = connect_rig(&meta, &solver, sim, true, &clock).await?;
    let dir = RunDir::create(&req.out, &meta)?;
    Ok(assemble(
        meta,
        schedule,
        dir,
        Recovery::default(),
        (rig, sim),
        clock,
        policy,
    ))
}

/// Why a simulated run cannot start: no simulated rig was wired in.
fn no_simulator() -> RunError {
    RunError::Invalid(
        "no simulated rig to run on: this rigd drives hardware only (built without the cargo feature `sim`)"
            .into(),
    )
}

/// Connects the simulated rig or the profile's hardware, as the run says;
/// a run that `starts` arms the simulated rig's profile faults too.
async fn connect_rig(
    meta: &RunMeta,
    solver: &Solver,
    sim: Option<&dyn Simulator>,
    starts: bool,
    clock: &Clock,
) -> Result<(Rig, Option<SimHandle>), RunError> {
    if meta.simulated {
        let sim = sim.ok_or_else(no_simulator)?;
        let (rig, handle) = sim
            .connect(
                &meta.profile,
                Arc::new(solver.clone()),
                meta.frame_size,
                starts,
                clock,
            )
            .await
            .map_err(RunError::Simulator)?;
        Ok((rig, Some(handle)))
    } else {
        let rig = rig::hardware::connect(&meta.profile, clock)
            .await
            .map_err(RunError::Hardware)?;
        Ok((rig, None))
    }
}

/// Opens a run directory, connects the rig, and prepares an engine for
/// what is left.
pub async fn prepare_resume(
    root: &Path,
    sim: Option<&dyn Simulator>,
    clock: Clock,
    policy: PausePolicy,
) -> Result<Prepared, RunError> {
    let (dir, meta, recovery) = RunDir::open(root)?;
    let solver = Solver::new(&meta.profile)?;
    let schedule = schedule::build(&meta.profile, &solver, &meta.plan);
    if let Some(bad) = recovery.done.keys().find(|&&i| i >= schedule.images.len()) {
        return Err(RunError::Invalid(format!(
            "{}: the journal names image {bad}, but the plan has only {} images",
            root.display(),
            schedule.images.len()
        )));
    }
    if recovery.torn_bytes > 0 {
        tracing::warn!(
            bytes = recovery.torn_bytes,
            "cut a torn line off the end of the journal (the previous session died mid-write)"
        );
    }
    if recovery.set_aside > 0 {
        tracing::warn!(
            lines = recovery.set_aside,
            "moved journal lines it cannot use (an image's older lines, damaged frames' lines, lines that do not parse) to {}; their images are retaken",
            crate::store::JOURNAL_HISTORY_FILE
        );
    }
    if !recovery.retake.is_empty() {
        tracing::warn!(frames = ?recovery.retake, "frames missing or damaged on disk; they will be retaken");
    }
    let (rig, sim) = connect_rig(&meta, &solver, sim, false, &clock).await?;
    Ok(assemble(
        meta,
        schedule,
        dir,
        recovery,
        (rig, sim),
        clock,
        policy,
    ))
}

fn assemble(
    meta: RunMeta,
    schedule: Schedule,
    dir: RunDir,
    recovery: Recovery,
    (rig, sim): (Rig, Option<SimHandle>),
    clock: Clock,
    policy: PausePolicy,
) -> Prepared {
    let profile = meta.profile.clone();
    let done = &recovery.done;
    let estimate_s = {
        let timing =
            Timing::new(&profile, meta.exposure_s).with_exposure_policy(&meta.exposure_policy);
        let trigger_done = |t: usize| {
            schedule.triggers[t]
                .images
                .iter()
                .all(|i| done.contains_key(i))
        };
        timing.estimate_s(&schedule, trigger_done)
    };
    let frames_total = schedule.images.len();
    let frames_done = done.len();
    let root = dir.root().to_path_buf();
    let t_offset_s = recovery.physical_s;
    let retake = recovery.retake.clone();
    let run_meta = meta.clone();
    let (engine, handle) = Engine::new(profile, schedule, meta, rig, clock, dir, recovery, policy);
    Prepared {
        engine,
        handle,
        sim,
        root,
        frames_total,
        frames_done,
        t_offset_s,
        estimate_s,
        retake,
        meta: run_meta,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn choice(profile: &str, plan: &str) -> (Order, Option<OrderChoice>) {
        let profile = Profile::load(profile).unwrap_or_else(|e| panic!("{e}"));
        let solved = solve_plan(&profile, plan, None).unwrap_or_else(|e| panic!("{e}"));
        let ((_, plan, schedule), choice) = prefer_slots(&profile, solved);
        assert_eq!(schedule.images.len(), plan.pairs.len());
        (plan.order, choice)
    }

    #[test]
    fn a_run_processed_during_its_capture_takes_the_slots_order_only_when_it_costs_little() {
        // The Bonn rig: +0.9 % physical time.
        let (order, c) = choice("bonn-gonioreflectometer", "h1");
        let c = c.expect("a choice");
        assert_eq!((order, c.order), (Order::Slots, Order::Slots), "{c}");
        assert!(c.slots_s <= (1.0 + SLOTS_PREFERRED_WITHIN) * c.optimised_s);
        // The MSRA rig's grid: +3.7 %, so it stays optimised.
        let (order, c) = choice("msra-btf-mdf", "grid12x8");
        let c = c.expect("a choice");
        assert_eq!(
            (order, c.order),
            (Order::Optimised, Order::Optimised),
            "{c}"
        );
        assert!(c.slots_s > (1.0 + SLOTS_PREFERRED_WITHIN) * c.optimised_s);
    }
}
