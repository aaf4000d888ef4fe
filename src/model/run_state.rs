//! Where a run stands, and the one table of which transitions exist. The
//! engine, the run directory's `state.json` and the HTTP API all use this
//! type.

use std::fmt;

use serde::{Deserialize, Serialize};

/// Where a run stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RunState {
    Idle,
    /// Homing axes, warming up lamps.
    Preparing,
    Running,
    /// Waiting for the operator: paused on request or by a fault.
    Paused,
    Completed,
    Aborted,
    Failed,
}

impl RunState {
    pub fn as_str(self) -> &'static str {
        match self {
            RunState::Idle => "idle",
            RunState::Preparing => "preparing",
            RunState::Running => "running",
            RunState::Paused => "paused",
            RunState::Completed => "completed",
            RunState::Aborted => "aborted",
            RunState::Failed => "failed",
        }
    }

    /// A run in this state will not change again.
    pub fn is_final(self) -> bool {
        matches!(
            self,
            RunState::Completed | RunState::Aborted | RunState::Failed
        )
    }

    /// The transition table. Resuming from a fault goes through Preparing
    /// (re-home, re-check lamps); resuming from an operator's pause goes
    /// straight back to Running.
    pub fn can_go_to(self, to: RunState) -> bool {
        use RunState::*;
        matches!(
            (self, to),
            (Idle, Preparing)
                | (Preparing, Running)
                | (Preparing, Paused)
                | (Preparing, Aborted)
                | (Preparing, Failed)
                | (Running, Paused)
                | (Running, Completed)
                | (Running, Aborted)
                | (Running, Failed)
                | (Paused, Running)
                | (Paused, Preparing)
                | (Paused, Aborted)
        )
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

    const ALL: [RunState; 7] = [Idle, Preparing, Running, Paused, Completed, Aborted, Failed];

    #[test]
    fn final_states_have_no_way_out() {
        for from in [Completed, Aborted, Failed] {
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
}
