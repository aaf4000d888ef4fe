//! rigd's integration tests, in one binary: linking all of rigd once instead of
//! once per test file is most of what a build of the suite costs on two cores.
//! Each module is one area of behaviour; `common` holds their shared helpers.
//! The dashboard's browser test is its own binary (`tests/browser.rs`).

#[path = "../common/mod.rs"]
mod common;

mod acl_e2e;
mod acl_transcripts;
mod api;
mod api_abuse;
mod api_contract;
mod api_restart;
mod architecture;
mod bring_up;
mod btf_accuracy;
mod camera_colour;
mod camera_files;
mod cli;
mod clipping;
mod clock;
mod colour;
mod corruption;
mod crash_resume;
mod decoder_child;
mod disk_full;
mod estop;
mod fault_kinds;
mod faults;
mod full_runs;
#[cfg(feature = "genicam")]
mod genicam;
mod gphoto2_peer;
#[cfg(feature = "gphoto2")]
mod gphoto2_transport;
mod grbl_e2e;
mod grbl_transcripts;
mod holder;
mod journal_readers;
mod lab_holder;
mod lamp_drift;
mod laser_mdf;
mod manual_control;
mod modbus_e2e;
mod modbus_transcripts;
mod peers;
mod pose_solver_hard_cases;
mod process_jobs;
mod process_run;
mod ps_accuracy;
mod ptp_camera;
mod ptp_transcripts;
mod ptpip_transcripts;
mod python_client;
mod real_camera_files;
mod refusals;
mod runs_page;
mod sim_serve;
mod slurm;
mod stability;
mod tradeoff;

/// The GenICam tests (tests/it/genicam.rs) need a rigd built with Aravis:
/// without the feature they would vanish from the suite, so this fails
/// instead, saying how to run them.
#[cfg(not(feature = "genicam"))]
#[test]
fn genicam_tests_need_the_genicam_feature() {
    panic!(
        "the GenICam tests need `--features genicam` and Debian's libaravis-dev and aravis-tools: run scripts/test.sh, which installs them and passes the feature"
    );
}

/// The libgphoto2 transport's tests (tests/it/gphoto2_transport.rs) need a
/// rigd built with libgphoto2: without the feature they would vanish from
/// the suite, so this fails instead, saying how to run them.
#[cfg(not(feature = "gphoto2"))]
#[test]
fn gphoto2_transport_tests_need_the_gphoto2_feature() {
    panic!(
        "the libgphoto2 transport's tests need `--features gphoto2` and Debian's libgphoto2-dev and libclang-dev: run scripts/test.sh, which installs them and passes the feature"
    );
}
