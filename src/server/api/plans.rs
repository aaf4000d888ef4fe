//! `/plans`: the built-in plans on this rig. Their schedules are solved in
//! the background when the daemon starts ([`crate::server::plan_cache`]),
//! so listing them never waits: a plan still being solved is listed with
//! `ready: false`.

use axum::extract::State;
use axum::Json;

use super::AppState;
use crate::model::exposure::ExposurePolicy;
use crate::plan::BUILTIN_PLANS;
use crate::schedule::timing::Timing;
use crate::schedule::Schedule;
use crate::server::error::{ApiError, ApiPath, ErrorBody};
use crate::server::supervisor::Daemon;
use crate::server::wire::*;

/// What `schedule` costs under the profile's own exposure policy and each
/// of [`ExposurePolicy::choices`] that every camera can expose.
fn exposure_estimates(d: &Daemon, schedule: &Schedule) -> Vec<PolicyEstimate> {
    let own = &d.profile.exposure_policy;
    let base_s = d
        .profile
        .camera_names()
        .first()
        .map_or(0.0, |c| Timing::new(&d.profile, None).exposure_s(c));
    let mut policies = vec![own.clone()];
    for p in ExposurePolicy::choices(base_s) {
        if !policies.contains(&p) && d.profile.check_exposure_policy(&p, None).is_ok() {
            policies.push(p);
        }
    }
    policies
        .into_iter()
        .map(|policy| {
            let physical = Timing::new(&d.profile, None)
                .with_exposure_policy(&policy)
                .estimate_s(schedule, |_| false);
            PolicyEstimate {
                profile_default: &policy == own,
                estimated_physical_s: physical,
                estimated_wall_s: physical / d.speed(),
                raw_bytes: crate::schedule::volume::data_volume(&d.profile, schedule, &policy)
                    .raw_bytes,
                lower_bound: policy.auto().is_some(),
                policy,
            }
        })
        .collect()
}

fn summary(d: &Daemon, name: &str, schedule: &Schedule) -> PlanSummary {
    let policy = &d.profile.exposure_policy;
    let est = Timing::new(&d.profile, None)
        .with_exposure_policy(policy)
        .estimate_s(schedule, |_| false);
    let volume = crate::schedule::volume::data_volume(&d.profile, schedule, policy);
    PlanSummary {
        name: name.into(),
        ready: true,
        fits: true,
        error: None,
        steps_total: schedule.images.len(),
        triggers_total: schedule.triggers.len(),
        infeasible_total: schedule.infeasible().count(),
        estimated_physical_s: est,
        estimated_wall_s: est / d.speed(),
        raw_bytes: volume.raw_bytes,
        image_bytes: volume.largest_image_bytes,
        exposure_estimates: exposure_estimates(d, schedule),
    }
}

fn unsized_summary(name: &str, ready: bool, error: Option<String>) -> PlanSummary {
    PlanSummary {
        name: name.into(),
        ready,
        fits: false,
        error,
        steps_total: 0,
        triggers_total: 0,
        infeasible_total: 0,
        estimated_physical_s: 0.0,
        estimated_wall_s: 0.0,
        raw_bytes: 0,
        image_bytes: 0,
        exposure_estimates: Vec::new(),
    }
}

/// The built-in plans on this rig: size, feasibility and estimated physical
/// duration. Answers at once; a plan still being solved has `ready: false`
/// (ask again in a moment).
#[utoipa::path(get, path = "/api/v1/plans", tag = "rig",
    responses((status = 200, description = "Every built-in plan", body = PlanList)))]
pub async fn plans(State(d): State<AppState>) -> Json<PlanList> {
    let plans = BUILTIN_PLANS
        .iter()
        .map(|&name| match d.plans.ready(name) {
            Some(Ok(s)) => summary(&d, name, &s),
            Some(Err(why)) => unsized_summary(name, true, Some(why)),
            None => unsized_summary(name, false, None),
        })
        .collect();
    Json(PlanList {
        profile: d.profile.name.clone(),
        plans,
    })
}

/// One built-in plan with every step: directions, feasibility, set-points.
/// Waits for the plan if it is still being solved.
#[utoipa::path(get, path = "/api/v1/plans/{name}", tag = "rig",
    params(("name" = String, Path, description = "h1, h2, grid12x8, lamps or laser")),
    responses((status = 200, description = "The plan", body = PlanDetail),
              (status = 404, description = "No such plan", body = ErrorBody),
              (status = 422, description = "The plan does not fit this rig", body = ErrorBody)))]
pub async fn plan_detail(
    State(d): State<AppState>,
    ApiPath(name): ApiPath<String>,
) -> Result<Json<PlanDetail>, ApiError> {
    let solved = d.plans.get(&name).await.ok_or_else(|| {
        ApiError::not_found(format!(
            "no built-in plan of that name (expected one of {})",
            BUILTIN_PLANS.join(", ")
        ))
    })?;
    let s = solved.map_err(ApiError::invalid)?;
    let steps = s.steps().map(PlanStep::from).collect();
    Ok(Json(PlanDetail {
        summary: summary(&d, &name, &s),
        steps,
    }))
}
