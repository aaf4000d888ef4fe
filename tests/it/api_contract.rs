//! The API contract, checked by Schemathesis, an OpenAPI fuzzer that knows
//! nothing of rigd but its published description: every operation of a
//! live daemon, every status and body checked against the description, the
//! links followed, and every operation answered with a 2xx at least once
//! (`tests/support/api_contract.py` seeds what the routes need and runs it).

use std::time::Duration;

use crate::common;

#[test]
fn schemathesis_finds_no_failure_and_reaches_every_operation() {
    let work = tempfile::tempdir().expect("tempdir");
    let mut cmd = std::process::Command::new(common::test_python());
    cmd.arg(common::repo_file("tests/support/api_contract.py"))
        .arg("--rigd")
        .arg(env!("CARGO_BIN_EXE_rigd"))
        .arg("--work")
        .arg(work.path())
        .args(["--max-time", "90"]);
    let (ok, out) = common::run_bounded(cmd, work.path(), Duration::from_secs(900));
    println!("{out}");
    assert!(ok, "the API contract does not hold:\n{out}");
    assert!(
        out.contains("schemathesis pass all: exit 0"),
        "the broad pass did not run:\n{out}"
    );
}
