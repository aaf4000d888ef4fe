//! The Python client (`clients/python`): its own pytest suite, run against
//! this build's `rigd`, as `cd clients/python && python -m pytest` does.
//! It starts its daemons itself and covers every call and every example.

use std::time::Duration;

use crate::common;

#[test]
fn the_python_clients_tests_pass_against_this_rigd() {
    let work = tempfile::tempdir().expect("tempdir");
    let mut cmd = std::process::Command::new(common::test_python());
    cmd.args(["-m", "pytest", "-q", "-p", "no:cacheprovider"])
        .current_dir(common::repo_file("clients/python"))
        .env("RIGD", env!("CARGO_BIN_EXE_rigd"));
    let (ok, out) = common::run_bounded(cmd, work.path(), Duration::from_secs(600));
    println!("{out}");
    assert!(ok, "the Python client's tests failed:\n{out}");
    assert!(
        out.contains(" passed") && !out.contains("xfail") && !out.contains("skipped"),
        "every test must run and pass:\n{out}"
    );
}
