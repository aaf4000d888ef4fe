//! How many exposures each step of a capture takes: one (`single`), a
//! fixed series (`brackets`), or more only where the first one clipped
//! (`auto`). A BTF's brightest texels sit near the mirror direction, where a
//! single exposure clips; raw values are linear, so shorter exposures of the
//! same step extend its range (merged by processing).

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use super::text::short_number;

/// Share of the sample's pixels that may clip before `auto` shoots again
/// shorter, unless a run says otherwise: less than one pixel of a 320×240
/// frame's sample (about 40,000 pixels), so any clipped pixel there is
/// taken again, while a 6-megapixel frame's sample (about 3.6 million)
/// tolerates a few dozen stuck pixels, which no shorter exposure mends.
pub const DEFAULT_AUTO_THRESHOLD: f64 = 0.000_01;
/// How much shorter each further exposure of `auto` is, unless a run says
/// otherwise: two stops, so three retakes cover six stops of highlight.
pub const DEFAULT_AUTO_FACTOR: f64 = 4.0;
/// The most further exposures `auto` takes at one step, unless a run says
/// otherwise.
pub const DEFAULT_AUTO_MAX_EXTRA: u32 = 3;
/// The most exposures one step may take, in any policy.
pub const MAX_EXPOSURES_PER_STEP: usize = 8;

/// The longest exposure rigd accepts, seconds, on any camera.
pub const MAX_EXPOSURE_S: f64 = 3600.0;

/// The one rule for an exposure time someone asks for: a finite number of
/// seconds, more than 0 and at most [`MAX_EXPOSURE_S`]. The error says
/// what was expected; callers prefix the option's name.
pub fn check_exposure_s(exposure_s: f64) -> Result<f64, String> {
    if exposure_s.is_finite() && exposure_s > 0.0 && exposure_s <= MAX_EXPOSURE_S {
        Ok(exposure_s)
    } else {
        Err(format!(
            "{}: expected a positive number of seconds up to {MAX_EXPOSURE_S}",
            short_number(exposure_s)
        ))
    }
}

/// The exposures each step of a capture takes.
// `Single {}` rather than a unit variant: serde lets a unit variant of a
// tagged enum ignore unknown fields, and a mistyped key must be refused.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(tag = "policy", rename_all = "snake_case", deny_unknown_fields)]
pub enum ExposurePolicy {
    /// One exposure per step, at the run's (or each camera's) exposure.
    Single {},
    /// The same series at every step, longest first, seconds; the first
    /// is the exposure the frame's values are scaled to.
    Brackets {
        /// Exposure times in seconds, strictly decreasing, each within
        /// every camera's exposure range.
        exposures_s: Vec<f64>,
    },
    /// The run's exposure first; where that frame clips more than
    /// `threshold` of the sample's pixels, again `factor` times shorter,
    /// up to `max_extra` times, until the highlight fits.
    // Fields inline rather than a newtype of `AutoExposure`: a tagged
    // newtype is described as `allOf` with a closed object, which no
    // value with the tag can match.
    Auto {
        /// Share of the sample's pixels, in (0, 1), that may clip before a
        /// shorter exposure is taken.
        #[serde(default = "default_threshold")]
        threshold: f64,
        /// How many times shorter each further exposure is; more than 1.
        #[serde(default = "default_factor")]
        factor: f64,
        /// The most further exposures at one step, 1 to 7.
        #[serde(default = "default_max_extra")]
        max_extra: u32,
    },
}

impl From<AutoExposure> for ExposurePolicy {
    fn from(a: AutoExposure) -> Self {
        ExposurePolicy::Auto {
            threshold: a.threshold,
            factor: a.factor,
            max_extra: a.max_extra,
        }
    }
}

impl Default for ExposurePolicy {
    fn default() -> Self {
        ExposurePolicy::Single {}
    }
}

/// The settings of [`ExposurePolicy::Auto`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AutoExposure {
    /// Share of the sample's pixels, in (0, 1), that may clip before a
    /// shorter exposure is taken.
    pub threshold: f64,
    /// How many times shorter each further exposure is; more than 1.
    pub factor: f64,
    /// The most further exposures at one step, 1 to 7.
    pub max_extra: u32,
}

impl Default for AutoExposure {
    fn default() -> Self {
        AutoExposure {
            threshold: DEFAULT_AUTO_THRESHOLD,
            factor: DEFAULT_AUTO_FACTOR,
            max_extra: DEFAULT_AUTO_MAX_EXTRA,
        }
    }
}

fn default_threshold() -> f64 {
    DEFAULT_AUTO_THRESHOLD
}
fn default_factor() -> f64 {
    DEFAULT_AUTO_FACTOR
}
fn default_max_extra() -> u32 {
    DEFAULT_AUTO_MAX_EXTRA
}

/// A policy that cannot work: the key (below the policy's own, e.g.
/// `exposures_s`) and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PolicyError {
    /// The offending field, relative to the policy (`exposures_s`,
    /// `threshold`, `factor`, `max_extra`).
    pub key: &'static str,
    /// What was expected.
    pub message: String,
}

impl ExposurePolicy {
    /// Checks what the policy says of itself: brackets non-empty, strictly
    /// decreasing and each a valid exposure; `auto`'s threshold in (0, 1),
    /// factor above 1 and a bounded number of retakes. The cameras' own
    /// ranges are checked by the profile (`Profile::check_exposure_policy`).
    pub fn check(&self) -> Result<(), PolicyError> {
        match self {
            ExposurePolicy::Single {} => Ok(()),
            ExposurePolicy::Brackets { exposures_s } => {
                let bad = |message: String| PolicyError {
                    key: "exposures_s",
                    message,
                };
                if exposures_s.is_empty() || exposures_s.len() > MAX_EXPOSURES_PER_STEP {
                    return Err(bad(format!(
                        "expected 1 to {MAX_EXPOSURES_PER_STEP} exposure times, got {}",
                        exposures_s.len()
                    )));
                }
                for &t in exposures_s {
                    check_exposure_s(t).map_err(bad)?;
                }
                if let Some(w) = exposures_s.windows(2).find(|w| w[1] >= w[0]) {
                    return Err(bad(format!(
                        "{} s then {} s: expected strictly decreasing exposure times, longest first",
                        short_number(w[0]),
                        short_number(w[1])
                    )));
                }
                Ok(())
            }
            ExposurePolicy::Auto { .. } => self.auto().map_or(Ok(()), |a| a.check()),
        }
    }

    /// The exposures a step takes before anything is seen of it: the
    /// series of `brackets`, else only `base_s`.
    pub fn first_exposures(&self, base_s: f64) -> Vec<f64> {
        match self {
            ExposurePolicy::Brackets { exposures_s } => exposures_s.clone(),
            _ => vec![base_s],
        }
    }

    /// The settings of `auto`; None for the other policies.
    pub fn auto(&self) -> Option<AutoExposure> {
        match *self {
            ExposurePolicy::Auto {
                threshold,
                factor,
                max_extra,
            } => Some(AutoExposure {
                threshold,
                factor,
                max_extra,
            }),
            _ => None,
        }
    }

    /// Whether every step takes exactly one exposure at the run's exposure.
    pub fn is_single(&self) -> bool {
        matches!(self, ExposurePolicy::Single {})
    }

    /// The policies an operator chooses among for a base exposure of
    /// `base_s`: `single`, `auto` with its defaults, and brackets of 2 and
    /// 3 exposures, each [`DEFAULT_AUTO_FACTOR`] times shorter than the
    /// one before (two stops apart, as `auto` steps).
    pub fn choices(base_s: f64) -> Vec<ExposurePolicy> {
        let series = |n: i32| {
            (0..n)
                .map(|k| base_s / DEFAULT_AUTO_FACTOR.powi(k))
                .collect::<Vec<f64>>()
        };
        vec![
            ExposurePolicy::Single {},
            AutoExposure::default().into(),
            ExposurePolicy::Brackets {
                exposures_s: series(2),
            },
            ExposurePolicy::Brackets {
                exposures_s: series(3),
            },
        ]
    }
}

impl AutoExposure {
    /// Checks the threshold, factor and number of retakes.
    pub fn check(&self) -> Result<(), PolicyError> {
        if !(self.threshold > 0.0 && self.threshold < 1.0) {
            return Err(PolicyError {
                key: "threshold",
                message: format!(
                    "{}: expected a share of the sample's pixels between 0 and 1, both excluded",
                    short_number(self.threshold)
                ),
            });
        }
        if !(self.factor.is_finite() && self.factor > 1.0 && self.factor <= 1024.0) {
            return Err(PolicyError {
                key: "factor",
                message: format!(
                    "{}: expected how many times shorter each further exposure is, more than 1 and at most 1024",
                    short_number(self.factor)
                ),
            });
        }
        let most = MAX_EXPOSURES_PER_STEP as u32 - 1;
        if !(1..=most).contains(&self.max_extra) {
            return Err(PolicyError {
                key: "max_extra",
                message: format!("{}: expected 1 to {most} further exposures", self.max_extra),
            });
        }
        Ok(())
    }

    /// The `k`-th further exposure after `base_s` (k from 1).
    pub fn extra_exposure_s(&self, base_s: f64, k: u32) -> f64 {
        base_s / self.factor.powi(k as i32)
    }

    /// The shortest exposure it may take after `base_s`.
    pub fn shortest_s(&self, base_s: f64) -> f64 {
        self.extra_exposure_s(base_s, self.max_extra)
    }
}

impl fmt::Display for ExposurePolicy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ExposurePolicy::Single {} => write!(f, "single"),
            ExposurePolicy::Brackets { exposures_s } => {
                let list: Vec<String> = exposures_s.iter().map(|t| short_number(*t)).collect();
                write!(f, "brackets:{}", list.join(","))
            }
            ExposurePolicy::Auto {
                threshold,
                factor,
                max_extra,
            } => write!(
                f,
                "auto:threshold={},factor={},max_extra={max_extra}",
                short_number(*threshold),
                short_number(*factor),
            ),
        }
    }
}

/// The command line's form: `single`, `brackets:T1,T2,…` (seconds) or
/// `auto[:threshold=S,factor=F,max_extra=N]` (any of the three, in any
/// order). The policy is checked ([`ExposurePolicy::check`]).
impl FromStr for ExposurePolicy {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (kind, rest) = match s.split_once(':') {
            Some((k, r)) => (k.trim(), Some(r)),
            None => (s.trim(), None),
        };
        let policy = match (kind, rest) {
            ("single", None) => ExposurePolicy::Single {},
            ("brackets", Some(list)) => {
                let exposures_s = list
                    .split(',')
                    .map(|t| {
                        t.trim()
                            .parse::<f64>()
                            .map_err(|_| format!("`{t}`: expected an exposure time in seconds"))
                    })
                    .collect::<Result<Vec<f64>, String>>()?;
                ExposurePolicy::Brackets { exposures_s }
            }
            ("auto", settings) => {
                let mut a = AutoExposure::default();
                for pair in settings.into_iter().flat_map(|r| r.split(',')) {
                    let (key, value) = pair.split_once('=').ok_or_else(|| {
                        format!("`{pair}`: expected KEY=VALUE with threshold, factor or max_extra")
                    })?;
                    let number = || {
                        value
                            .trim()
                            .parse::<f64>()
                            .map_err(|_| format!("{key} `{value}`: expected a number"))
                    };
                    match key.trim() {
                        "threshold" => a.threshold = number()?,
                        "factor" => a.factor = number()?,
                        "max_extra" => {
                            a.max_extra = value
                                .trim()
                                .parse()
                                .map_err(|_| format!("max_extra `{value}`: expected a count"))?
                        }
                        other => {
                            return Err(format!(
                                "`{other}`: expected threshold, factor or max_extra"
                            ))
                        }
                    }
                }
                a.into()
            }
            _ => {
                return Err(format!(
                    "`{s}`: expected single, brackets:T1,T2,… (seconds, longest first) or auto[:threshold=S,factor=F,max_extra=N]"
                ))
            }
        };
        policy
            .check()
            .map_err(|e| format!("{}: {}", e.key, e.message))?;
        Ok(policy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_line_forms_parse_and_print_back() {
        for text in [
            "single",
            "brackets:0.25,0.0625,0.015625",
            "auto:threshold=0.001,factor=4,max_extra=3",
        ] {
            let p: ExposurePolicy = text.parse().unwrap();
            assert_eq!(p.to_string(), text);
            assert_eq!(p.to_string().parse::<ExposurePolicy>().unwrap(), p);
        }
        let a: ExposurePolicy = "auto".parse().unwrap();
        assert_eq!(a, ExposurePolicy::from(AutoExposure::default()));
        let a: ExposurePolicy = "auto:factor=2".parse().unwrap();
        assert_eq!(a.auto().unwrap().factor, 2.0);
        assert_eq!(a.auto().unwrap().max_extra, DEFAULT_AUTO_MAX_EXTRA);
    }

    #[test]
    fn a_policy_that_cannot_work_is_refused_naming_its_key() {
        let key = |text: &str| text.parse::<ExposurePolicy>().unwrap_err();
        assert!(key("brackets:0.1,0.2").starts_with("exposures_s: 0.1 s then 0.2 s"));
        assert!(key("brackets:0.1,0.1").contains("strictly decreasing"));
        assert!(key("brackets:0.1,-1").starts_with("exposures_s: -1"));
        assert!(key("brackets:").contains("expected an exposure time"));
        assert!(key("auto:threshold=0").starts_with("threshold: 0"));
        assert!(key("auto:threshold=1").starts_with("threshold: 1"));
        assert!(key("auto:threshold=NaN").starts_with("threshold: NaN"));
        assert!(key("auto:factor=1").starts_with("factor: 1"));
        assert!(key("auto:factor=0.5").starts_with("factor: 0.5"));
        assert!(key("auto:max_extra=0").starts_with("max_extra: 0"));
        assert!(key("auto:max_extra=99").starts_with("max_extra: 99"));
        assert!(key("auto:speed=3").contains("`speed`"));
        assert!(key("often").contains("expected single, brackets"));
        assert!(key("single:3").contains("expected single, brackets"));
    }

    #[test]
    fn the_json_form_is_tagged_by_policy() {
        let p: ExposurePolicy =
            serde_json::from_str(r#"{"policy":"brackets","exposures_s":[0.5,0.1]}"#).unwrap();
        assert_eq!(p.first_exposures(1.0), vec![0.5, 0.1]);
        let a: ExposurePolicy = serde_json::from_str(r#"{"policy":"auto"}"#).unwrap();
        assert_eq!(a.first_exposures(0.25), vec![0.25]);
        assert_eq!(a.auto().unwrap().extra_exposure_s(0.25, 2), 0.25 / 16.0);
        assert!(serde_json::from_str::<ExposurePolicy>(r#"{"policy":"often"}"#).is_err());
        assert!(serde_json::from_str::<ExposurePolicy>(r#"{"policy":"single","x":1}"#).is_err());
    }
}
