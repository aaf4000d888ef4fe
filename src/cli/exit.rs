//! Exit codes, so scripts can tell what happened, and how an error is
//! classed: the caller's input was wrong (2: fix the input), or something
//! failed while doing what was asked (1: the disk, a device, the system).
//! [`EXIT_CODES`] is the one place the codes are described; `--help` prints
//! it, and a test holds the README's table to it.

use std::io::ErrorKind as IoKind;

use rigd::engine::launch::RunError;
use rigd::postprocess::slurm::SlurmError;
use rigd::postprocess::ProcessError;
use rigd::rig::hal::DeviceError;
use rigd::server::ServerError;
use rigd::store::StoreError;

/// Something failed while doing what was asked.
pub const EXIT_FAILURE: u8 = 1;

/// Prints a check's report (`rig check`, `holder check`): as JSON with
/// `json`, else its lines; the exit code is success when it `passed`,
/// else [`EXIT_FAILURE`].
pub fn print_check(
    report: &impl serde::Serialize,
    lines: Vec<String>,
    json: bool,
    passed: bool,
) -> anyhow::Result<std::process::ExitCode> {
    use anyhow::Context;
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(report).context("cannot write the report")?
        );
    } else {
        for line in lines {
            println!("{line}");
        }
    }
    Ok(if passed {
        std::process::ExitCode::SUCCESS
    } else {
        std::process::ExitCode::from(EXIT_FAILURE)
    })
}
/// The input was wrong; nothing was done that needs undoing.
pub const EXIT_BAD_INPUT: u8 = 2;
/// The run paused on a fault and can be resumed.
pub const EXIT_PAUSED: u8 = 3;
/// The run was aborted or failed.
pub const EXIT_ENDED_BADLY: u8 = 4;
/// A signal stopped the run; it can be resumed.
pub const EXIT_INTERRUPTED: u8 = 130;

/// Every exit code and what it means, for the help text and the README.
pub const EXIT_CODES: &[(u8, &str)] = &[
    (0, "done (a run: completed)"),
    (
        EXIT_FAILURE,
        "failure while doing what was asked: I/O, a device that cannot be reached, the disk, \
         an internal error",
    ),
    (
        EXIT_BAD_INPUT,
        "bad input: arguments, a profile, a plan, a run directory or data that cannot be used \
         (one line on stderr; nothing was done)",
    ),
    (
        EXIT_PAUSED,
        "`rigd run`: paused by a fault, a full disk included (the reason is printed; fix it \
         and `--resume`)",
    ),
    (EXIT_ENDED_BADLY, "`rigd run`: aborted, or failed"),
    (
        EXIT_INTERRUPTED,
        "`rigd run`: interrupted by SIGINT/SIGTERM (resumable)",
    ),
];

/// The codes as the help text lists them, one per line.
pub fn exit_codes_help() -> String {
    let mut out = String::from("Exit codes:");
    for (code, meaning) in EXIT_CODES {
        out.push_str(&format!("\n  {code:<4} {meaning}"));
    }
    out
}

/// An error in what the caller gave: arguments, files, data.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BadInput(pub String);

/// A bad-input error with this message.
pub fn bad_input(message: impl Into<String>) -> anyhow::Error {
    anyhow::Error::new(BadInput(message.into()))
}

/// An error as one line: each message of its chain of causes, joined by
/// `: `, leaving out a cause whose message its caller's already holds.
/// Many library errors say their cause in their own message and also keep
/// it as their source, so the exit code can be classed by it; printed
/// with both, the line would say the same thing twice.
pub fn describe(error: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in error.chain() {
        let message = cause.to_string();
        let message = message.trim();
        if message.is_empty() || line.contains(message) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(message);
    }
    line
}

/// The exit code an error ends the process with: the deepest cause in the
/// chain that rigd can class decides (the root cause is the most specific:
/// a processing error caused by a full disk is a failure); an error rigd
/// cannot class at all is a failure.
pub fn exit_code_of(error: &anyhow::Error) -> u8 {
    error
        .chain()
        .filter_map(class_of)
        .last()
        .unwrap_or(EXIT_FAILURE)
}

fn class_of(cause: &(dyn std::error::Error + 'static)) -> Option<u8> {
    if cause.is::<BadInput>() {
        return Some(EXIT_BAD_INPUT);
    }
    if let Some(e) = cause.downcast_ref::<std::io::Error>() {
        return Some(io_class(e));
    }
    if let Some(e) = cause.downcast_ref::<StoreError>() {
        return Some(store_class(e));
    }
    if let Some(e) = cause.downcast_ref::<RunError>() {
        return Some(match e {
            RunError::Store(s) => store_class(s),
            RunError::Simulator(_) | RunError::Hardware(_) => EXIT_FAILURE,
            RunError::Profile(_)
            | RunError::Plan(_)
            | RunError::Kinematics(_)
            | RunError::Invalid(_) => EXIT_BAD_INPUT,
        });
    }
    if let Some(e) = cause.downcast_ref::<ProcessError>() {
        return Some(process_class(e));
    }
    if let Some(e) = cause.downcast_ref::<SlurmError>() {
        return Some(match e {
            SlurmError::Process(p) => process_class(p),
            SlurmError::Cancelled { .. } => EXIT_INTERRUPTED,
            e if e.is_bad_config() => EXIT_BAD_INPUT,
            // The cluster failed: a command, or a task more often than allowed.
            _ => EXIT_FAILURE,
        });
    }
    // A peers file that cannot be read is the caller's input as much as
    // one that does not parse (`rigd serve --peers`).
    if cause.is::<rigd::server::peers::PeersError>() {
        return Some(EXIT_BAD_INPUT);
    }
    if cause.is::<DeviceError>() {
        return Some(EXIT_FAILURE);
    }
    // A camera file the decoder refuses, or that crashes it, is the
    // caller's input; a decoder that cannot be started is the system's.
    if let Some(e) = cause.downcast_ref::<rigd::rig::camera_file::CameraFileError>() {
        return Some(if e.is_the_file_s() {
            EXIT_BAD_INPUT
        } else {
            EXIT_FAILURE
        });
    }
    if let Some(e) = cause.downcast_ref::<ServerError>() {
        return Some(match e {
            ServerError::Profile(_)
            | ServerError::Speed(_)
            | ServerError::Peers(_)
            | ServerError::Processing(_)
            | ServerError::Http(_) => EXIT_BAD_INPUT,
            ServerError::DataDir { .. }
            | ServerError::Token { .. }
            | ServerError::Listen { .. } => EXIT_FAILURE,
        });
    }
    // Validation errors of rigd's libraries: their I/O variants carry the
    // I/O error as a deeper cause, which then decides.
    use rigd_process::*;
    let bad_input = cause.is::<rigd::model::profile::ProfileError>()
        || cause.is::<rigd::plan::PlanError>()
        || cause.is::<rigd::kinematics::KinematicsError>()
        || cause.is::<rigd::postprocess::viewer::ViewerError>()
        || cause.is::<rigd::postprocess::holder_check::HolderCheckError>()
        || cause.is::<rigd::postprocess::chart::ChartReadError>()
        || cause.is::<btf::BtfError>()
        || cause.is::<colour::chart_fit::ChartFitError>()
        || cause.is::<directions::DirectionError>()
        || cause.is::<export::ExportError>()
        || cause.is::<image_io::ImageError>()
        || cause.is::<mdf::MdfError>()
        || cause.is::<mesh::MeshError>()
        || cause.is::<npy::NpyError>()
        || cause.is::<photometric_stereo::PsError>()
        || cause.is::<rectify::RectifyError>()
        || cause.is::<reflectance_fit::FitError>()
        || cause.is::<relight::RelightError>()
        || cause.is::<rigd_process::silhouette::SilhouetteError>()
        || cause.is::<webgl::PackError>();
    #[cfg(feature = "sim")]
    let bad_input = bad_input
        || cause.is::<rigd::rig::sim::shot::RenderError>()
        || cause.is::<rigd::rig::sim::SceneError>();
    bad_input.then_some(EXIT_BAD_INPUT)
}

fn process_class(e: &ProcessError) -> u8 {
    match e {
        ProcessError::Store(s) => store_class(s),
        // A frame that cannot be read or registered, an option that does
        // not fit the run: the data or the request is at fault.
        _ => EXIT_BAD_INPUT,
    }
}

fn store_class(e: &StoreError) -> u8 {
    match e {
        StoreError::Io { error, .. } => io_class(error),
        // A state change the table refuses is a bug, not the caller's.
        StoreError::Transition { .. } => EXIT_FAILURE,
        StoreError::AlreadyRun(..)
        | StoreError::NotEmpty(_)
        | StoreError::NoRun(_)
        | StoreError::Corrupt { .. }
        | StoreError::Finished(..)
        | StoreError::Busy(_)
        | StoreError::ProcessingBusy(_) => EXIT_BAD_INPUT,
    }
}

/// A path that cannot be what the caller said it is (missing, a file where
/// a folder must go) or data that does not parse was the caller's input;
/// anything else (a full disk, permissions, a broken pipe) failed.
fn io_class(e: &std::io::Error) -> u8 {
    match e.kind() {
        IoKind::NotFound
        | IoKind::NotADirectory
        | IoKind::IsADirectory
        | IoKind::AlreadyExists
        | IoKind::InvalidFilename
        | IoKind::InvalidInput
        | IoKind::InvalidData => EXIT_BAD_INPUT,
        _ => EXIT_FAILURE,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The codes as the README's Markdown table.
    fn exit_codes_table() -> String {
        let mut out = String::from("| code | meaning |\n|---|---|\n");
        for (code, meaning) in EXIT_CODES {
            out.push_str(&format!("| {code} | {meaning} |\n"));
        }
        out
    }

    #[test]
    fn the_readme_lists_the_exit_codes_as_the_code_does() {
        let readme = include_str!("../../README.md");
        let table = exit_codes_table();
        assert!(
            readme.contains(&table),
            "README.md's exit code table differs from cli::exit::EXIT_CODES; it should read:\n{table}"
        );
        let help = exit_codes_help();
        for (code, _) in EXIT_CODES {
            assert!(help.contains(&format!("\n  {code} ")));
        }
    }

    #[test]
    fn a_full_disk_is_a_failure_and_a_bad_path_is_bad_input() {
        let full = StoreError::Io {
            path: "/x/.state.json.tmp".into(),
            op: "write",
            error: std::io::Error::from_raw_os_error(libc::ENOSPC),
        };
        assert_eq!(exit_code_of(&anyhow::Error::new(full)), EXIT_FAILURE);
        let missing = std::io::Error::from(IoKind::NotFound);
        assert_eq!(exit_code_of(&anyhow::Error::new(missing)), EXIT_BAD_INPUT);
        let no_run = StoreError::NoRun("/tmp/nothing".into());
        let wrapped = anyhow::Error::new(no_run).context("cannot resume /tmp/nothing");
        assert_eq!(exit_code_of(&wrapped), EXIT_BAD_INPUT);
    }

    #[test]
    fn a_cause_already_in_its_callers_message_is_said_once() {
        let io = std::io::Error::from(IoKind::NotFound);
        let said = io.to_string();
        #[derive(Debug, thiserror::Error)]
        #[error("cannot read x.toml: {source}")]
        struct Read {
            source: std::io::Error,
        }
        let e = anyhow::Error::new(Read { source: io }).context("loading the profile");
        assert_eq!(
            describe(&e),
            format!("loading the profile: cannot read x.toml: {said}")
        );
        let e = anyhow::anyhow!("inner").context("outer");
        assert_eq!(describe(&e), "outer: inner");
    }

    #[test]
    fn explicit_bad_input_and_unknown_errors() {
        assert_eq!(exit_code_of(&bad_input("--x 3: no")), EXIT_BAD_INPUT);
        assert_eq!(exit_code_of(&anyhow::anyhow!("who knows")), EXIT_FAILURE);
        let device = DeviceError::new("turntable", rigd::rig::hal::ErrorKind::Disconnected, "gone");
        let run = RunError::Hardware(device);
        assert_eq!(exit_code_of(&anyhow::Error::new(run)), EXIT_FAILURE);
    }
}
