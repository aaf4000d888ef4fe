//! The JSON shapes of the API (and of `queue.json`), with their OpenAPI schemas.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use rigd_core::geometry::Direction;

use crate::model::run_state::RunState;
pub use crate::postprocess::job::{JobState, ProcessJob, StepStatus};

/// A direction in the sample frame, degrees.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Dir {
    /// Polar angle from the sample normal, 0..=90.
    pub theta_deg: f64,
    /// Azimuth.
    pub phi_deg: f64,
}

impl From<Direction> for Dir {
    fn from(d: Direction) -> Self {
        Dir {
            theta_deg: d.theta_deg,
            phi_deg: d.phi_deg,
        }
    }
}

/// One light/view pair of an inline plan.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PairDto {
    /// Light direction.
    pub light: Dir,
    /// View direction.
    pub view: Dir,
}

/// A plan given inline: exactly one of `directions` (all paired with all),
/// `lights` with `views` (all paired with all), or `pairs`.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct InlinePlan {
    /// Name of the plan (1..=128 characters), used in the run id and the
    /// run's records; `custom` if absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// Directions, each paired with each (as light and as view).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub directions: Option<Vec<Dir>>,
    /// Light directions, each paired with every one of `views`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lights: Option<Vec<Dir>>,
    /// View directions, each paired with every one of `lights`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub views: Option<Vec<Dir>>,
    /// Explicit light/view pairs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pairs: Option<Vec<PairDto>>,
}

/// A built-in plan name (`h1`, `h2`, `grid12x8`, `lamps`; see
/// `GET /api/v1/plans`) or an inline plan. Plan files are not read over the API.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(untagged)]
pub enum PlanSpec {
    /// A built-in plan: `h1`, `h2`, `grid12x8`, `lamps`, `laser` or
    /// `laser:key=value,…`.
    Name(String),
    /// A plan given in the request.
    Inline(InlinePlan),
}

impl PlanSpec {
    /// The plan's name: the built-in name, or the inline plan's `name`
    /// (`custom` if it has none).
    pub fn label(&self) -> String {
        match self {
            PlanSpec::Name(n) => n.clone(),
            PlanSpec::Inline(p) => p.name.clone().unwrap_or_else(|| "custom".into()),
        }
    }
}

/// A run to start (`POST /api/v1/runs`) or to queue (`POST /api/v1/queue`).
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(example = json!({
    "sample": "felt",
    "plan": {"name": "mini", "directions": [
        {"theta_deg": 20.0, "phi_deg": 0.0}, {"theta_deg": 50.0, "phi_deg": 120.0}]},
    "frame_size": [16, 12],
    "operator": "ada"
}))]
pub struct RunRequest {
    /// Sample name, recorded in the dataset (1..=128 characters, no
    /// control characters).
    #[schema(min_length = 1, max_length = 128)]
    pub sample: String,
    /// The plan to capture: a built-in plan's name or an inline plan.
    pub plan: PlanSpec,
    /// Who runs the capture, recorded in the dataset (at most 128 characters,
    /// no control characters).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub operator: Option<String>,
    /// Free-text notes recorded in the dataset (at most 8192 characters).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notes: Option<String>,
    /// Exposure for every camera, seconds (default: the profile's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exposure_s: Option<f64>,
    /// The exposures each step takes (default: the profile's
    /// `[exposure_policy]`, else one): `{"policy": "single"}`,
    /// `{"policy": "brackets", "exposures_s": [T1, T2, …]}` (longest
    /// first, each within every camera's range), or `{"policy": "auto",
    /// "threshold": S, "factor": F, "max_extra": N}` (each optional),
    /// which exposes again `factor` times shorter, up to `max_extra` times,
    /// where a frame clips more than `threshold` of the sample's pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exposure_policy: Option<crate::model::exposure::ExposurePolicy>,
    /// Simulated frame size `[width, height]`, each 1..=4096 (default: the profile's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_size: Option<[u32; 2]>,
    /// `optimised` (default: the shortest physical time under the motion
    /// model) or `naive` (the plan's nested-loop order).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub order: Option<crate::plan::Order>,
    /// Process the run when its capture completes (or is aborted): the
    /// body of `POST /runs/{id}/process` (`{}` for the defaults). Checked
    /// now: steps the plan cannot take, or frames too small for the
    /// holder's markers, refuse the run (422).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub process: Option<crate::postprocess::pipeline::ProcessOptions>,
}

/// A run as the API shows it.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct RunView {
    /// Server-made id: `YYYYMMDDTHHMMSSZ-SAMPLE-PLAN[-N]`.
    pub id: String,
    /// Sample name, as requested.
    pub sample: String,
    /// Plan name: the built-in name (`h1`, `laser:…`) or the inline plan's
    /// `name` (`custom` if it had none).
    pub plan: String,
    /// Name of the rig profile it was captured on.
    pub profile: String,
    /// Who ran it; null if not given.
    pub operator: Option<String>,
    /// Free-text notes; null if none were given.
    pub notes: Option<String>,
    /// Where the run stands: `interrupted` means the daemon died while it
    /// was active.
    pub state: RunState,
    /// Why it is in its current state (pause reason, failure), if any.
    pub reason: Option<String>,
    /// The last device error or fault seen (kept after a resume clears
    /// `reason`): a fault pause, a retry, a failure.
    pub last_error: Option<String>,
    /// True while an engine drives it (at most one run).
    pub active: bool,
    /// `POST /runs/{id}/resume` would continue it.
    pub resumable: bool,
    /// Images with a journaled frame so far.
    pub steps_done: usize,
    /// Images in the plan.
    pub steps_total: usize,
    /// Physical seconds of capture so far.
    pub physical_s: f64,
    /// Estimated physical seconds left (active runs).
    pub eta_physical_s: Option<f64>,
    /// The same in wall seconds at the daemon's simulation speed.
    pub eta_wall_s: Option<f64>,
    /// Exposure of every camera, seconds, as requested; null: each camera's
    /// exposure from the profile (laser plans: the plan's).
    pub exposure_s: Option<f64>,
    /// Simulated frame size `[width, height]` in pixels; null on hardware.
    pub frame_size: Option<[u32; 2]>,
    /// When the run was created, RFC 3339 UTC.
    pub started_at: String,
    /// When the run last changed (its state record, or its latest engine
    /// event while active), RFC 3339 UTC; null if it has no state record.
    pub updated_at: Option<String>,
    /// When the run's manifest was written at its end (completed, failed or
    /// aborted by its engine), RFC 3339 UTC; null until then, and for a run
    /// aborted with no live engine.
    pub finished_at: Option<String>,
    /// What `rigd process` made of it that the viewer (`/viewer/{id}`)
    /// shows: `btf` or `photometric-stereo`; null before processing.
    #[serde(default)]
    pub processed: Option<String>,
    /// The run's process job (`POST /api/v1/runs/{id}/process`), if it
    /// has one: its state, steps and progress.
    #[serde(default)]
    pub processing: Option<ProcessJob>,
    /// How fast a simulated run's physical time goes against the wall
    /// clock, asked and achieved; null on hardware and for runs no engine
    /// drives.
    #[serde(default)]
    pub pace: Option<PaceView>,
}

/// The pace of a simulated run: its physical time runs at most
/// `asked_speed` times the wall clock, and slower when the host cannot keep
/// up. The physical time itself is the rig model's either way.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct PaceView {
    /// Physical seconds per wall second asked for (`--sim-speed`).
    pub asked_speed: f64,
    /// Physical seconds per wall second over the last two seconds.
    pub achieved_speed: f64,
    /// The host falls behind the asked speed (achieved below 95 % of it).
    pub behind: bool,
}

/// `GET /api/v1/runs`: one page of the run history.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct RunList {
    /// The page's runs, newest first (`started_at` descending, then id
    /// descending).
    pub runs: Vec<RunView>,
    /// The active run's id (whether or not it is on this page).
    pub active: Option<String>,
    /// The `cursor` of the next page; null on the last page.
    #[serde(default)]
    pub next: Option<String>,
    /// How many runs match the filters, on every page.
    #[serde(default)]
    pub total: usize,
}

/// Answer to pause/resume/abort.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct CommandAck {
    /// pause, resume or abort.
    pub command: String,
    /// True when handed to the live engine (its state changes arrive as
    /// events); false when done on disk (a run with no live engine).
    pub sent_to_engine: bool,
    /// The run right after the command; with a live engine, its state change
    /// follows as an event.
    pub run: RunView,
}

/// One queued run.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct QueueItem {
    /// Queue item id, `q<unix milliseconds>-<n>`; not the id of the run it
    /// becomes.
    pub id: String,
    /// The run to start, as posted.
    pub request: RunRequest,
    /// When it was queued, RFC 3339 UTC.
    pub created_at: String,
}

/// `GET /api/v1/queue`.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct QueueView {
    /// In the order they will run.
    pub items: Vec<QueueItem>,
}

/// Answer to `POST /api/v1/queue`.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Enqueued {
    /// The new queue item.
    pub item: QueueItem,
    /// Set when the rig was free and the item started at once (it is then
    /// no longer in the queue).
    pub started_run: Option<RunView>,
}

/// `GET /api/v1/health`.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Health {
    /// Always true: the daemon is up and answering.
    pub ok: bool,
    /// Version of the rigd serving the API (semantic versioning).
    pub version: String,
    /// Name of the rig profile the daemon drives.
    pub profile: String,
    /// True when it drives the simulated rig, false on hardware.
    pub sim: bool,
    /// Physical seconds per wall second of the simulated rig.
    pub sim_speed: f64,
}

/// A device and its live state.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct DeviceView {
    /// The device's name in the profile.
    pub name: String,
    /// axis, arm, lamp, camera or laser.
    pub kind: String,
    /// The protocol its driver speaks, as in the profile.
    pub protocol: String,
    /// True on the simulated rig; false on hardware, whose drivers connect for
    /// each run and report nothing here.
    pub connected: bool,
    /// Null for devices that do not home (lamps, cameras).
    pub homed: Option<bool>,
    /// Axes: whether the controller homes it; false for an axis zeroed by
    /// the operator at its 0° mark (`homing = false`), whose reference a
    /// resume asks the operator to confirm. Null for other devices.
    #[serde(default)]
    pub homing: Option<bool>,
    /// True while a run is preparing or running (the same for every device).
    pub busy: bool,
    /// The fault that paused the run, if it names this device.
    pub fault: Option<String>,
    /// Axis position, degrees (null until known).
    pub position_deg: Option<f64>,
    /// Arm joints: name → degrees.
    #[schema(value_type = Option<Object>)]
    pub joints: Option<serde_json::Value>,
    /// Lamps: switched on.
    pub on: Option<bool>,
    /// Cameras: resolution, bit depth, exposure, readout, transfer, and the
    /// simulated frame size.
    #[schema(value_type = Option<Object>)]
    pub camera: Option<serde_json::Value>,
}

/// `GET /api/v1/rig`.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct RigView {
    /// Name of the rig profile.
    pub profile: String,
    /// The profile's description of the rig.
    pub description: String,
    /// True when the daemon drives the simulated rig, false on hardware.
    pub sim: bool,
    /// Physical seconds per wall second: the simulation speed, or 1 on hardware.
    pub sim_speed: f64,
    /// Id of the run an engine drives; null when the rig is free.
    pub active_run: Option<String>,
    /// The active run's state, or `idle` when the rig is free.
    pub state: RunState,
    /// Every device of the profile, in name order.
    pub devices: Vec<DeviceView>,
    /// Lamp name → on.
    #[schema(value_type = Object)]
    pub lamps: serde_json::Value,
}

/// A plan on this rig, in short.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct PlanSummary {
    /// The built-in plan's name (`h1`, `h2`, `grid12x8`, `lamps` or `laser`).
    pub name: String,
    /// Solved for this rig; while `false` (the daemon has just started) the
    /// other fields say nothing yet: ask again in a moment.
    pub ready: bool,
    /// The plan fits this rig.
    pub fits: bool,
    /// Why not, when it does not fit.
    pub error: Option<String>,
    /// Images in the plan.
    pub steps_total: usize,
    /// Triggers: rig poses at which one or more cameras expose together.
    pub triggers_total: usize,
    /// Images the rig cannot take as asked (the nearest reachable pair is taken).
    pub infeasible_total: usize,
    /// Estimated physical capture time, seconds.
    pub estimated_physical_s: f64,
    /// The same in wall seconds at the daemon's simulation speed.
    pub estimated_wall_s: f64,
    /// Raw sensor data of the whole plan, bytes (every image at its
    /// camera's resolution, two bytes a pixel above 8 bits).
    pub raw_bytes: u64,
    /// The largest single image, bytes.
    pub image_bytes: u64,
    /// What the plan costs under each exposure policy the start form
    /// offers: the profile's own first, then `single`, `auto` and brackets
    /// of 2 and 3 exposures two stops apart from the first camera's
    /// exposure, each that every camera can expose. Empty while the plan
    /// is not solved.
    pub exposure_estimates: Vec<PolicyEstimate>,
}

/// A plan's cost under one exposure policy.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct PolicyEstimate {
    /// The policy, as `exposure_policy` in a run request takes it.
    pub policy: crate::model::exposure::ExposurePolicy,
    /// Whether it is the profile's own `[exposure_policy]` (what a run
    /// without `exposure_policy` takes).
    pub profile_default: bool,
    /// Estimated physical capture time, seconds.
    pub estimated_physical_s: f64,
    /// The same in wall seconds at the daemon's simulation speed.
    pub estimated_wall_s: f64,
    /// Raw sensor data, bytes, every exposure counted.
    pub raw_bytes: u64,
    /// True for `auto`: the time and data are those of a run in which no
    /// step clipped, and every step that does costs a further exposure
    /// (and its transfer) up to `max_extra` times.
    pub lower_bound: bool,
}

/// `GET /api/v1/plans`.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct PlanList {
    /// Name of the rig profile the plans are solved for.
    pub profile: String,
    /// Every built-in plan, in the order `h1`, `h2`, `grid12x8`, `lamps`, `laser`.
    pub plans: Vec<PlanSummary>,
}

/// One image of a plan.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct PlanStep {
    /// The image's index, in capture order.
    pub index: usize,
    /// Index of its trigger; images taken together share it.
    pub trigger: usize,
    /// The camera that takes it.
    pub camera: String,
    /// Commanded light direction.
    pub light: Dir,
    /// Commanded view direction.
    pub view: Dir,
    /// Light direction the set-points really produce; for an infeasible pair,
    /// the substitute's.
    pub achieved_light: Dir,
    /// View direction the set-points really produce; for an infeasible pair,
    /// the substitute's.
    pub achieved_view: Dir,
    /// Whether the rig can take the pair as asked.
    pub feasible: bool,
    /// When infeasible: why, and what is taken instead; absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Laser plans: the source and tilt of this frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Object>)]
    pub laser: Option<serde_json::Value>,
    /// Axes, arm joints and lamp for this image's trigger.
    #[schema(value_type = Object)]
    pub setpoints: serde_json::Value,
}

impl From<crate::schedule::PlanStep<'_>> for PlanStep {
    fn from(step: crate::schedule::PlanStep<'_>) -> PlanStep {
        let img = step.image;
        PlanStep {
            index: img.index,
            trigger: img.trigger,
            camera: img.camera.clone(),
            light: img.light.into(),
            view: img.view.into(),
            achieved_light: img.achieved_light.into(),
            achieved_view: img.achieved_view.into(),
            feasible: img.feasible,
            reason: img.reason.clone(),
            laser: img
                .laser
                .map(|l| serde_json::to_value(l).unwrap_or_default()),
            setpoints: serde_json::to_value(step.setpoints).unwrap_or_default(),
        }
    }
}

/// `GET /api/v1/plans/{name}`.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct PlanDetail {
    /// Size, feasibility and estimated duration (its fields are inlined here).
    #[serde(flatten)]
    pub summary: PlanSummary,
    /// Every image, in capture order.
    pub steps: Vec<PlanStep>,
}

/// One image of a run, planned and captured.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct RunStep {
    /// The image's index, in capture order.
    pub index: usize,
    /// Index of its trigger; images taken together share it.
    pub trigger: usize,
    /// The camera that takes it.
    pub camera: String,
    /// Commanded light direction.
    pub light: Dir,
    /// Commanded view direction.
    pub view: Dir,
    /// Light direction the set-points really produce; for an infeasible pair,
    /// the substitute's.
    pub achieved_light: Dir,
    /// View direction the set-points really produce; for an infeasible pair,
    /// the substitute's.
    pub achieved_view: Dir,
    /// Whether the rig can take the pair as asked.
    pub feasible: bool,
    /// When infeasible: why, and what is taken instead; null otherwise.
    pub reason: Option<String>,
    /// Its frame is written and journaled.
    pub done: bool,
}

/// `GET /api/v1/runs/{id}/steps`.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct RunSteps {
    /// The run's id.
    pub run: String,
    /// Images in the run's plan.
    pub steps_total: usize,
    /// Images with a journaled frame.
    pub steps_done: usize,
    /// Every image of the plan, in capture order.
    pub steps: Vec<RunStep>,
}

/// Answer to `POST /api/v1/estop`.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct EstopAnswer {
    /// The run that was active, if any (it is now paused; resume re-homes).
    pub run: Option<String>,
    /// Physical seconds to the last device's acknowledgement.
    pub latency_s: Option<f64>,
    /// Every device's acknowledgement: `{device, after_s, error?}`.
    #[schema(value_type = Vec<Object>)]
    pub devices: Vec<serde_json::Value>,
    /// True when every device acknowledged its stop (also when no run was
    /// active).
    pub all_stopped: bool,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The API lists a plan's steps in the shape `rigd plan show --json`
    /// prints them: the same JSON, step for step, laser steps included.
    #[test]
    fn api_plan_steps_match_the_command_line_shape() {
        for (profile, plan) in [("bonn-gonioreflectometer", "h1"), ("msra-btf-mdf", "laser")] {
            let (_, _, schedule) = crate::engine::launch::solve_plan(
                &crate::plan::load_profile(profile).unwrap_or_else(|e| panic!("{e}")),
                plan,
                None,
            )
            .unwrap_or_else(|e| panic!("{e}"));
            for step in schedule.steps().take(50) {
                let cli = serde_json::to_value(step).unwrap_or_default();
                let api = serde_json::to_value(PlanStep::from(step)).unwrap_or_default();
                assert_eq!(cli, api, "{profile} {plan}");
            }
        }
    }
}
