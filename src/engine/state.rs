//! The run state machine: an explicit table of which transitions exist,
//! and which operator commands make sense in which state.

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

/// What an operator (or script) can ask of a running engine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Command {
    Pause,
    Resume,
    Abort,
    /// Stop driving the run but leave it resumable (daemon shutdown, CLI interrupt).
    Detach,
    /// The devices were stopped out of band ([`super::EngineHandle::emergency_stop`]):
    /// pause, and re-home before going on.
    EmergencyStop,
}

/// A command that makes no sense in the current state.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("cannot {command:?} a run that is {state}")]
pub struct Refused {
    pub command: Command,
    pub state: RunState,
}

/// Whether `command` is accepted in `state`.
pub fn check_command(state: RunState, command: Command) -> Result<(), Refused> {
    use RunState::*;
    let ok = match command {
        Command::Pause => matches!(state, Preparing | Running),
        Command::Resume => state == Paused,
        Command::Abort => matches!(state, Idle | Preparing | Running | Paused),
        Command::Detach | Command::EmergencyStop => !state.is_final(),
    };
    if ok {
        Ok(())
    } else {
        Err(Refused { command, state })
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

    #[test]
    fn commands_are_refused_where_they_make_no_sense() {
        assert!(check_command(Running, Command::Pause).is_ok());
        assert!(check_command(Paused, Command::Pause).is_err());
        assert!(check_command(Running, Command::Resume).is_err());
        assert!(check_command(Paused, Command::Resume).is_ok());
        assert!(check_command(Completed, Command::Abort).is_err());
        let e = check_command(Completed, Command::Resume)
            .err()
            .map(|e| e.to_string());
        assert_eq!(e.as_deref(), Some("cannot Resume a run that is completed"));
    }
}
