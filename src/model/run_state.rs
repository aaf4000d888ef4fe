//! Where a run stands, and the one table of which transitions exist. The
//! engine, the run directory's `state.json` and the HTTP API all use this
//! type.

use std::fmt;

use serde::{Deserialize, Serialize};

/// Where a run stands.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum RunState {
    /// Created, not yet driven.
    #[default]
    Idle,
    /// Homing axes, warming up lamps.
    Preparing,
    /// Capturing.
    Running,
    /// Waiting for the operator: paused on request or by a fault.
    Paused,
    /// Every frame of the plan is on disk; nothing follows.
    Completed,
    /// Stopped for good by the operator; nothing follows.
    Aborted,
    /// Ended with frames missing; a resume retakes them.
    Failed,
    /// The process driving it stopped while it was preparing or running
    /// (the daemon died, the command line was killed); a resume goes on.
    Interrupted,
}

/// Every state, in the order of the table.
pub const ALL_STATES: [RunState; 8] = [
    RunState::Idle,
    RunState::Preparing,
    RunState::Running,
    RunState::Paused,
    RunState::Completed,
    RunState::Aborted,
    RunState::Failed,
    RunState::Interrupted,
];

/// A change of state the table does not allow: a bug, reported as an
/// error rather than written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("illegal run-state transition {from} -> {to}")]
pub struct IllegalTransition {
    /// The state the run was in.
    pub from: RunState,
    /// The state asked for.
    pub to: RunState,
}

impl RunState {
    /// The name used on disk and in the API.
    pub fn as_str(self) -> &'static str {
        match self {
            RunState::Idle => "idle",
            RunState::Preparing => "preparing",
            RunState::Running => "running",
            RunState::Paused => "paused",
            RunState::Completed => "completed",
            RunState::Aborted => "aborted",
            RunState::Failed => "failed",
            RunState::Interrupted => "interrupted",
        }
    }

    /// Nothing follows: completed or aborted.
    pub fn is_terminal(self) -> bool {
        matches!(self, RunState::Completed | RunState::Aborted)
    }

    /// An engine session ends in this state: terminal, or failed.
    pub fn ends_session(self) -> bool {
        self.is_terminal() || self == RunState::Failed
    }

    /// An engine drives the run in this state.
    pub fn is_active(self) -> bool {
        matches!(self, RunState::Preparing | RunState::Running)
    }

    /// A new engine session can take the run up from its directory.
    pub fn is_resumable(self) -> bool {
        matches!(
            self,
            RunState::Paused | RunState::Interrupted | RunState::Failed
        )
    }

    /// The transition table. A session starts in `Preparing` (re-home,
    /// lamps warmed) from a new run or from any resumable state; resuming
    /// from an operator's pause within a session goes straight back to
    /// `Running`. A run found active with nobody driving it becomes
    /// `Interrupted`.
    pub fn can_go_to(self, to: RunState) -> bool {
        use RunState::*;
        matches!(
            (self, to),
            (Idle, Preparing)
                | (Idle, Aborted)
                | (Idle, Interrupted)
                | (Preparing, Running)
                | (Preparing, Paused)
                | (Preparing, Aborted)
                | (Preparing, Failed)
                | (Preparing, Interrupted)
                | (Running, Paused)
                | (Running, Completed)
                | (Running, Aborted)
                | (Running, Failed)
                | (Running, Interrupted)
                | (Paused, Running)
                | (Paused, Preparing)
                | (Paused, Aborted)
                | (Paused, Failed)
                | (Interrupted, Preparing)
                | (Interrupted, Aborted)
                | (Failed, Preparing)
                | (Failed, Aborted)
        )
    }

    /// `to` if the table allows it, the refused transition otherwise.
    pub fn transition(self, to: RunState) -> Result<RunState, IllegalTransition> {
        if self.can_go_to(to) {
            Ok(to)
        } else {
            Err(IllegalTransition { from: self, to })
        }
    }
}

impl fmt::Display for RunState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use RunState::*;

    const ALL: [RunState; 8] = ALL_STATES;

    #[test]
    fn final_states_have_no_way_out() {
        for from in [Completed, Aborted] {
            for to in ALL {
                assert!(!from.can_go_to(to), "{from} -> {to}");
            }
        }
    }

    #[test]
    fn every_state_is_reachable_from_idle() {
        let mut seen = vec![Idle];
        let mut i = 0;
        while i < seen.len() {
            for to in ALL {
                if seen[i].can_go_to(to) && !seen.contains(&to) {
                    seen.push(to);
                }
            }
            i += 1;
        }
        assert_eq!(seen.len(), ALL.len());
    }

    #[test]
    fn illegal_transitions_are_errors_and_name_both_states() {
        assert_eq!(Running.transition(Paused), Ok(Paused));
        let e = Completed.transition(Running);
        assert_eq!(
            e.map_err(|e| e.to_string()),
            Err("illegal run-state transition completed -> running".into())
        );
        assert!(Paused.transition(Completed).is_err());
        assert!(
            Interrupted.transition(Running).is_err(),
            "a resume re-prepares"
        );
    }

    #[test]
    fn a_run_found_active_can_be_marked_interrupted_and_resumed() {
        for from in [Idle, Preparing, Running] {
            assert!(from.can_go_to(Interrupted), "{from}");
        }
        for from in ALL.into_iter().filter(|s| s.is_resumable()) {
            assert!(from.can_go_to(Preparing), "{from}");
            assert!(from.can_go_to(Aborted), "{from}");
        }
        assert!(!Paused.can_go_to(Interrupted), "a paused run stays paused");
    }

    #[test]
    fn names_match_serde() {
        for s in ALL {
            let json = serde_json::to_string(&s).unwrap_or_default();
            assert_eq!(json, format!("\"{}\"", s.as_str()));
        }
    }
}
