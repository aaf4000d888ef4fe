//! From the trade-off report to a decision: the most accurate plan within
//! a time budget (`rigd tradeoff --budget 3h`), or the fastest plan that
//! reaches an error (`--target 15%`), among the measured rows of the
//! `plans` family, with the Pareto frontier it was chosen from.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// The rows a choice reads: those of a report's `plans` family.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct PlanPoint {
    /// The plan as the report names it (`h2`, `h2, 5 rings`, `grid 12x8`).
    pub setting: String,
    /// Images captured.
    pub images: Option<usize>,
    /// Physical capture time on the rig, seconds.
    pub physical_s: f64,
    /// Held-out RMS error relative to the truth's RMS.
    pub error: f64,
}

/// What the operator asks for.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Goal {
    /// The most accurate plan that takes at most this many physical seconds.
    BudgetS(f64),
    /// The fastest plan whose error is at most this (relative, 0.15 = 15 %).
    TargetError(f64),
}

impl Goal {
    /// A budget as `3h`, `90m`, `2h 30m` or seconds.
    pub fn budget(text: &str) -> Result<Goal, String> {
        let t = text.trim();
        let seconds = match t.parse::<f64>() {
            Ok(s) => s,
            Err(_) => humantime::parse_duration(t)
                .map_err(|e| format!("budget `{text}`: {e} (expected e.g. 3h, 90m or 2h30m)"))?
                .as_secs_f64(),
        };
        if !(seconds.is_finite() && seconds > 0.0) {
            return Err(format!("budget `{text}`: expected a positive duration"));
        }
        Ok(Goal::BudgetS(seconds))
    }

    /// A target error as `15%` or a fraction `0.15`.
    pub fn target(text: &str) -> Result<Goal, String> {
        let t = text.trim();
        let value = match t.strip_suffix('%') {
            Some(p) => p.trim().parse::<f64>().map(|v| v / 100.0),
            None => t.parse::<f64>(),
        }
        .map_err(|_| {
            format!("target `{text}`: expected a percentage (15%) or a fraction (0.15)")
        })?;
        if !(value.is_finite() && value > 0.0) {
            return Err(format!("target `{text}`: expected a positive error"));
        }
        Ok(Goal::TargetError(value))
    }
}

/// The answer: one plan, and the frontier it lies on.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct PlanChoice {
    /// What was asked.
    pub goal: Goal,
    /// The plan chosen.
    pub plan: PlanPoint,
    /// The measured plans no other plan beats in both time and error,
    /// fastest first; the chosen one is among them.
    pub frontier: Vec<PlanPoint>,
    /// The answer in one sentence.
    pub answer: String,
}

/// Why no plan answers.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ChoiceError {
    /// The report has no measured plan (time and error) to choose from.
    #[error("the report has no measured plan to choose from")]
    NoPlans,
    /// Nothing fits the goal; the message names the nearest plan.
    #[error("{0}")]
    NoneFits(String),
}

/// `h m s` for an answer.
fn duration(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    match (s / 3600, (s % 3600) / 60) {
        (0, m) => format!("{m} min"),
        (h, 0) => format!("{h} h"),
        (h, m) => format!("{h} h {m:02} min"),
    }
}

fn percent(error: f64) -> String {
    format!("{:.1} %", 100.0 * error)
}

/// The plans no other beats in both time and error (a tie in one and a
/// win in the other beats), fastest first.
pub fn frontier(points: &[PlanPoint]) -> Vec<PlanPoint> {
    frontier_by(points, |p| (p.physical_s, p.error))
}

/// The items no other beats in both `(cost, error)`, cheapest first.
pub(crate) fn frontier_by<T: Clone>(items: &[T], key: impl Fn(&T) -> (f64, f64)) -> Vec<T> {
    let mut sorted: Vec<&T> = items.iter().collect();
    sorted.sort_by(|a, b| {
        let (ka, kb) = (key(a), key(b));
        ka.0.total_cmp(&kb.0).then(ka.1.total_cmp(&kb.1))
    });
    let mut best = f64::INFINITY;
    let mut out = Vec::new();
    for item in sorted {
        let (_, error) = key(item);
        if error < best {
            best = error;
            out.push(item.clone());
        }
    }
    out
}

/// One setting of a family for [`knee`]: its name, what it costs (time,
/// bytes) and its error.
#[derive(Debug, Clone, PartialEq)]
pub struct CurvePoint {
    /// The setting (`h2, 5 rings`, `C = 8`).
    pub label: String,
    /// What it costs, in the family's unit.
    pub cost: f64,
    /// Its error, in the family's unit.
    pub error: f64,
}

/// The knee of a family's curve, in one sentence: on the frontier
/// (cheapest first), the point farthest below the chord from the cheapest
/// to the most accurate, with costs and errors scaled to that span; then
/// what the most accurate point adds beyond it. `cost_text` and
/// `error_text` format a cost and an error, `points` a difference of
/// errors. A frontier of one point (the cheapest setting is also the most
/// accurate) says so; None with fewer than two settings.
pub fn knee(
    points: &[CurvePoint],
    cost_text: &dyn Fn(f64) -> String,
    error_text: &dyn Fn(f64) -> String,
    points_text: &dyn Fn(f64) -> String,
) -> Option<String> {
    let finite: Vec<CurvePoint> = points
        .iter()
        .filter(|p| p.cost.is_finite() && p.error.is_finite())
        .cloned()
        .collect();
    if finite.len() < 2 {
        return None;
    }
    let f = frontier_by(&finite, |p| (p.cost, p.error));
    let (first, last) = (f.first()?, f.last()?);
    if f.len() < 2 {
        return Some(format!(
            "{} is both the cheapest and the most accurate, {} for {}",
            first.label,
            error_text(first.error),
            cost_text(first.cost)
        ));
    }
    let (span_cost, span_error) = (last.cost - first.cost, first.error - last.error);
    let below = |p: &CurvePoint| {
        let x = if span_cost > 0.0 {
            (p.cost - first.cost) / span_cost
        } else {
            0.0
        };
        let y = if span_error > 0.0 {
            (p.error - last.error) / span_error
        } else {
            0.0
        };
        1.0 - x - y
    };
    // The first of equals: the cheaper point.
    let knee = f.iter().fold(first, |best, p| {
        if below(p) > below(best) + 1e-12 {
            p
        } else {
            best
        }
    });
    // The chord's ends are on it (0): the knee is never the last point.
    Some(format!(
        "{} reaches {} for {}; {} adds {} for {}",
        knee.label,
        error_text(knee.error),
        cost_text(knee.cost),
        last.label,
        cost_text(last.cost - knee.cost),
        points_text(knee.error - last.error)
    ))
}

/// The plan that answers `goal` among `points`.
pub fn choose(points: &[PlanPoint], goal: Goal) -> Result<PlanChoice, ChoiceError> {
    let points: Vec<PlanPoint> = points
        .iter()
        .filter(|p| p.physical_s.is_finite() && p.error.is_finite())
        .cloned()
        .collect();
    if points.is_empty() {
        return Err(ChoiceError::NoPlans);
    }
    let frontier = frontier(&points);
    // The frontier holds the answer to either question: any plan off it
    // is beaten by one on it that is no slower and no less accurate.
    let (plan, answer) = match goal {
        Goal::BudgetS(budget) => {
            let fits = frontier.iter().rfind(|p| p.physical_s <= budget);
            let Some(p) = fits else {
                let fastest = &frontier[0];
                return Err(ChoiceError::NoneFits(format!(
                    "no measured plan fits in {}: the fastest, {}, takes {}",
                    duration(budget),
                    fastest.setting,
                    duration(fastest.physical_s)
                )));
            };
            let answer = format!(
                "within {}: {}, {} at {} held-out error",
                duration(budget),
                p.setting,
                duration(p.physical_s),
                percent(p.error)
            );
            (p.clone(), answer)
        }
        Goal::TargetError(target) => {
            let reaches = frontier.iter().find(|p| p.error <= target);
            let Some(p) = reaches else {
                let best = &frontier[frontier.len() - 1];
                return Err(ChoiceError::NoneFits(format!(
                    "no measured plan reaches {}: the most accurate, {}, reaches {} in {}",
                    percent(target),
                    best.setting,
                    percent(best.error),
                    duration(best.physical_s)
                )));
            };
            let answer = format!(
                "to reach {}: {}, {} at {} held-out error",
                percent(target),
                p.setting,
                duration(p.physical_s),
                percent(p.error)
            );
            (p.clone(), answer)
        }
    };
    Ok(PlanChoice {
        goal,
        plan,
        frontier,
        answer,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(setting: &str, hours: f64, error: f64) -> PlanPoint {
        PlanPoint {
            setting: setting.into(),
            images: None,
            physical_s: hours * 3600.0,
            error,
        }
    }

    /// The Bonn rig's corduroy report, as `rigd tradeoff` measured it.
    fn bonn() -> Vec<PlanPoint> {
        vec![
            p("h2", 9.62, 0.1009),
            p("h1", 9.62, 0.0968),
            p("h2, 3 rings", 0.58, 0.5736),
            p("h2, 4 rings", 2.05, 0.3071),
            p("h2, 5 rings", 4.79, 0.1414),
            p("grid 12x8", 13.49, 0.1341),
            p("grid 12x5", 5.30, 0.1286),
            p("dense, 15° rings", 21.45, 0.0917),
        ]
    }

    #[test]
    fn the_frontier_drops_every_plan_another_beats() {
        let f: Vec<String> = frontier(&bonn()).into_iter().map(|p| p.setting).collect();
        assert_eq!(
            f,
            [
                "h2, 3 rings",
                "h2, 4 rings",
                "h2, 5 rings",
                "grid 12x5",
                "h1",
                "dense, 15° rings"
            ]
        );
    }

    #[test]
    fn a_budget_gets_the_most_accurate_plan_that_fits_and_nothing_within_it_beats_it() {
        let points = bonn();
        for hours in [0.6, 1.0, 3.0, 5.0, 6.0, 10.0, 30.0] {
            let c = choose(&points, Goal::BudgetS(hours * 3600.0)).expect("a plan fits");
            assert!(c.plan.physical_s <= hours * 3600.0);
            assert!(c.frontier.contains(&c.plan));
            for q in points.iter().filter(|q| q.physical_s <= hours * 3600.0) {
                assert!(
                    q.error >= c.plan.error,
                    "{} beats {} in {hours} h",
                    q.setting,
                    c.plan.setting
                );
            }
        }
        let c = choose(&points, Goal::budget("3h").expect("3h")).expect("a plan fits");
        assert_eq!(c.plan.setting, "h2, 4 rings");
        assert_eq!(
            c.answer,
            "within 3 h: h2, 4 rings, 2 h 03 min at 30.7 % held-out error"
        );
        // h1 and h2 tie in time: the more accurate one is the answer.
        let c = choose(&points, Goal::BudgetS(10.0 * 3600.0)).expect("a plan fits");
        assert_eq!(c.plan.setting, "h1");
    }

    #[test]
    fn a_target_gets_the_fastest_plan_that_reaches_it() {
        let points = bonn();
        let c = choose(&points, Goal::target("15%").expect("15%")).expect("a plan reaches it");
        assert_eq!(c.plan.setting, "h2, 5 rings");
        for q in points.iter().filter(|q| q.error <= 0.15) {
            assert!(q.physical_s >= c.plan.physical_s, "{} is faster", q.setting);
        }
        assert_eq!(
            choose(&points, Goal::target("0.13").expect("0.13")).map(|c| c.plan.setting),
            Ok("grid 12x5".to_string())
        );
    }

    #[test]
    fn the_knee_is_the_frontier_point_farthest_below_the_chord() {
        let curve: Vec<CurvePoint> = bonn()
            .into_iter()
            .map(|p| CurvePoint {
                label: p.setting,
                cost: p.physical_s,
                error: p.error,
            })
            .collect();
        let hours = |s: f64| format!("{:.1} h", s / 3600.0);
        let pct = |e: f64| format!("{:.1} %", 100.0 * e);
        let pts = |e: f64| format!("{:.1} points", 100.0 * e);
        assert_eq!(
            knee(&curve, &hours, &pct, &pts).as_deref(),
            Some("grid 12x5 reaches 12.9 % for 5.3 h; dense, 15° rings adds 16.1 h for 3.7 points")
        );
        // One point, or none: no curve.
        assert_eq!(knee(&curve[..1], &hours, &pct, &pts), None);
        assert_eq!(knee(&[], &hours, &pct, &pts), None);
        // A straight line: the cheapest end is the knee.
        let line: Vec<CurvePoint> = (0..4)
            .map(|i| CurvePoint {
                label: format!("p{i}"),
                cost: f64::from(i),
                error: 3.0 - f64::from(i),
            })
            .collect();
        assert!(knee(&line, &hours, &pct, &pts).is_some_and(|s| s.starts_with("p0 reaches")));
        // The most accurate point is also the cheapest: said so.
        let best = vec![
            CurvePoint {
                label: "a".into(),
                cost: 1.0,
                error: 0.1,
            },
            CurvePoint {
                label: "b".into(),
                cost: 2.0,
                error: 0.2,
            },
        ];
        assert_eq!(
            knee(&best, &hours, &pct, &pts).as_deref(),
            Some("a is both the cheapest and the most accurate, 10.0 % for 0.0 h")
        );
    }

    #[test]
    fn nothing_fits_is_said_with_the_nearest_plan_and_bad_goals_are_refused() {
        let points = bonn();
        let e = choose(&points, Goal::BudgetS(600.0)).expect_err("nothing in 10 min");
        assert!(e.to_string().contains("h2, 3 rings"), "{e}");
        let e = choose(&points, Goal::TargetError(0.01)).expect_err("nothing reaches 1 %");
        assert!(e.to_string().contains("dense, 15° rings"), "{e}");
        assert_eq!(choose(&[], Goal::BudgetS(1.0)), Err(ChoiceError::NoPlans));
        for bad in ["", "soon", "-3h", "0"] {
            assert!(Goal::budget(bad).is_err(), "{bad}");
        }
        for bad in ["", "x%", "-5%", "0"] {
            assert!(Goal::target(bad).is_err(), "{bad}");
        }
        assert_eq!(Goal::budget("90m"), Ok(Goal::BudgetS(5400.0)));
        assert_eq!(Goal::budget("2h30m"), Ok(Goal::BudgetS(9000.0)));
        assert_eq!(Goal::target("15%"), Ok(Goal::TargetError(0.15)));
    }
}
