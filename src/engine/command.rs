//! What an operator (or script) can ask of a running engine, and in which
//! run states each command makes sense.

use serde::{Deserialize, Serialize};

use crate::model::run_state::RunState;

/// What an operator (or script) can ask of a running engine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Command {
    /// Pause between triggers, after writing the frames already exposed.
    /// Accepted while preparing or running.
    Pause,
    /// Go on after a pause; accepted only while paused. After a fault or an
    /// emergency stop the rig is re-homed and the lamp warmed up first.
    Resume,
    /// End the run for good: lamps off, the manifest written, state aborted.
    /// Accepted while idle, preparing, running or paused.
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
    /// The command that was refused.
    pub command: Command,
    /// The run's state when the command arrived.
    pub state: RunState,
}

/// Whether `command` is accepted in `state`.
pub fn check_command(state: RunState, command: Command) -> Result<(), Refused> {
    use RunState::*;
    let ok = match command {
        Command::Pause => matches!(state, Preparing | Running),
        Command::Resume => state == Paused,
        Command::Abort => matches!(state, Idle | Preparing | Running | Paused),
        Command::Detach | Command::EmergencyStop => !state.ends_session(),
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
