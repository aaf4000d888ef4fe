//! Processing on a real Slurm: a one-node cluster of Debian's `slurm-wlm`
//! and `munge` on this machine ([`crate::common::slurm::SlurmCluster`]),
//! started and stopped by the test. A simulated H2 is rectified and
//! compressed once here and once as Slurm job arrays, with one array task
//! cancelled mid-way (`scancel`) and redone; the BTFs must agree. Then the
//! daemon's process job runs on the cluster, a colour run calibrated on its
//! own patches inside the array's tasks, and the configuration errors are
//! checked before anything is submitted.

use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

use crate::common::slurm::SlurmCluster;
use crate::common::{rigd, run_ok};

/// The H2's frames: the smallest whose holder markers a monochrome camera
/// finds at the 75° ring (`MIN_REGISTRABLE_FRAME`), so that every frame is
/// registered by its markers, here and on Slurm alike. (A Bayer camera
/// needs about twice the pixels for its markers, and its demosaicing took
/// two thirds of this H2's processing: colour on Slurm is the daemon's
/// job's part below.)
const FRAME: &str = "288x216";
/// The rectification of the test: small textures keep it quick.
const RECTIFY: [&str; 4] = ["--size", "64", "--final", "16"];
const COMPONENTS: &str = "8";

fn capture_h2(out: &Path) {
    let started = Instant::now();
    let dir = out.parent().expect("the run's folder");
    let monochrome = crate::common::bonn_monochrome(dir);
    run_ok(&[
        "run",
        "--sim",
        "--profile",
        monochrome.to_str().expect("utf8"),
        "--plan",
        "h2",
        "--frame-size",
        FRAME,
        "--progress",
        "none",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    eprintln!(
        "H2 at {FRAME} captured in {:.1} s",
        started.elapsed().as_secs_f64()
    );
}

/// `rigd ARGS` with the cluster's environment; (success, stdout, stderr).
fn rigd_on(cluster: &SlurmCluster, args: &[&str]) -> (bool, String, String) {
    let out = rigd()
        .args(args)
        .envs(cluster.env())
        .output()
        .expect("spawn rigd");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn slurm_args<'a>(shared: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut v = vec!["--executor", "slurm", "--shared-path", shared];
    v.extend_from_slice(extra);
    v
}

/// Every (slot, light) texture of two compressed BTFs agrees within `tol`.
fn assert_same_btf(a: &Path, b: &Path, tol: f32) -> f32 {
    let a = rigd_process::btf::CompressedBtf::read(a).expect("local BTF");
    let b = rigd_process::btf::CompressedBtf::read(b).expect("Slurm BTF");
    assert_eq!(a.slots().len(), b.slots().len());
    assert_eq!(a.lights().directions(), b.lights().directions());
    let mut worst = 0.0f32;
    for slot in 0..a.slots().len() {
        for light in 0..a.lights().directions().len() {
            let x = a.reconstruct_measured(slot, light).expect("local texture");
            let y = b.reconstruct_measured(slot, light).expect("Slurm texture");
            for (p, q) in x.iter().zip(&y) {
                worst = worst.max((p - q).abs());
            }
        }
    }
    assert!(worst <= tol, "BTFs differ by {worst}");
    worst
}

#[test]
fn an_h2_processed_on_slurm_gives_the_local_btf_with_a_killed_task_redone() {
    let cluster = SlurmCluster::start();
    let work = tempfile::tempdir().expect("tempdir");
    let shared = work.path().to_str().expect("utf8").to_string();
    let run = work.path().join("h2");
    let run_s = run.to_str().expect("utf8");
    capture_h2(&run);

    // Here.
    let started = Instant::now();
    let mut args = vec!["process", "rectify", run_s];
    args.extend(RECTIFY);
    run_ok(&args);
    run_ok(&["process", "btf", run_s, "--components", COMPONENTS]);
    let local_s = started.elapsed().as_secs_f64();
    let processed = run.join("processed");
    let local = work.path().join("local-processed");
    std::fs::rename(&processed, &local).expect("keep the local result");

    // On Slurm, with one rectify task cancelled while it runs.
    let started = Instant::now();
    let mut args = vec!["process", "rectify", run_s];
    args.extend(RECTIFY);
    args.extend(slurm_args(&shared, &["--frames-per-task", "1000"]));
    let mut child = rigd()
        .args(&args)
        .envs(cluster.env())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn rigd");
    let killed = cancel_one_running_task(&cluster, "rigd-rectify", Duration::from_secs(120));
    let out = wait_output(&mut child, Duration::from_secs(600));
    let (stdout, stderr) = out;
    assert!(
        stdout.contains("1 redone") && stderr.contains("submitting it again"),
        "task {killed} was cancelled, so it must be redone:\n{stdout}\n{stderr}\n{}",
        cluster.logs()
    );
    let (ok, stdout, stderr) = rigd_on(
        &cluster,
        &[
            "process",
            "btf",
            run_s,
            "--components",
            COMPONENTS,
            "--executor",
            "slurm",
            "--shared-path",
            &shared,
        ],
    );
    assert!(ok, "{stdout}\n{stderr}\n{}", cluster.logs());
    // 81 view slots, 4 to a task by default.
    assert!(stdout.contains("on Slurm: 21 tasks"), "{stdout}");
    let slurm_s = started.elapsed().as_secs_f64();
    assert!(
        !processed.join("slurm").exists(),
        "the job folders are removed once the step is done"
    );

    // The same files, the same BTF.
    let index = |dir: &Path| -> serde_json::Value {
        let bytes = std::fs::read(dir.join("normtextures/index.json")).expect("index");
        serde_json::from_slice(&bytes).expect("index parses")
    };
    let (li, si) = (index(&local), index(&processed));
    assert_eq!(li["frames"].as_array().map(Vec::len), Some(6561));
    let by_markers = (li["frames"].as_array().into_iter().flatten())
        .filter(|f| f["method"] == "markers")
        .count();
    assert_eq!(by_markers, 6561, "every frame registered by its markers");
    assert_eq!(li["frames"], si["frames"], "registrations differ");
    let worst = assert_same_btf(&local.join("btf"), &processed.join("btf"), 1e-4);
    let names = |dir: &Path| -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .expect("read_dir")
            .filter_map(|e| Some(e.ok()?.file_name().to_str()?.to_string()))
            .collect();
        v.sort();
        v
    };
    assert_eq!(names(&local), names(&processed));
    assert_eq!(names(&local.join("btf")), names(&processed.join("btf")));
    eprintln!(
        "H2 ({FRAME}, rectify {RECTIFY:?}, C = {COMPONENTS}): local {local_s:.1} s, Slurm {slurm_s:.1} s (one node, {} cores, a task redone); largest texture difference {worst:e}",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );

    // A partition the cluster does not have: refused before submitting.
    let (ok, _, stderr) = rigd_on(
        &cluster,
        &[
            "process",
            "btf",
            run_s,
            "--executor",
            "slurm",
            "--shared-path",
            &shared,
            "--partition",
            "gpu-nowhere",
        ],
    );
    assert!(!ok);
    assert!(
        stderr.contains("unknown partition `gpu-nowhere`: the cluster has rigd"),
        "{stderr}"
    );
    assert_eq!(cluster.command("squeue", &["-h", "--me"]).trim(), "");

    // The MDF of a laser scan, one view per task.
    mdf_on_slurm_matches_local(&cluster, work.path());

    // Ctrl-C cancels the arrays: with the partition down the tasks wait in
    // the queue, SIGINT reaches rigd, and it scancels them and exits 130.
    interrupt_cancels_the_jobs(&cluster, run_s, &shared);

    // The daemon's process jobs, with [processing] executor = "slurm".
    let runtime = tokio::runtime::Runtime::new().expect("runtime");
    runtime.block_on(daemon_processes_on_slurm(&cluster, work.path()));
}

/// The MSRA profile with three cameras, frames large enough for the strip
/// and the ps-target's domes (as tests/it/laser_mdf.rs has it).
fn laser_profile(dir: &Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(crate::common::repo_file("rig-profiles/msra-btf-mdf.toml"))
        .expect("profile");
    let cameras = r#"cameras = ["cam0", "cam1", "cam2", "cam3", "cam4", "cam5", "cam6", "cam7"]"#;
    let sim = "[sim]\nframe_size = [64, 48]";
    assert!(text.contains(cameras) && text.contains(sim));
    let text = text
        .replace(cameras, r#"cameras = ["cam0", "cam3", "cam5"]"#)
        .replace(
            sim,
            "[sim]\nframe_size = [240, 180]\nzoom = 2.4\nscene = \"ps-target\"",
        );
    let path = dir.join("msra-laser.toml");
    std::fs::write(&path, text).expect("profile");
    path
}

fn mdf_on_slurm_matches_local(cluster: &SlurmCluster, work: &Path) {
    let run = work.join("laser");
    let run_s = run.to_str().expect("utf8");
    let profile = laser_profile(work);
    run_ok(&[
        "run",
        "--sim",
        "--progress",
        "none",
        "--plan",
        "laser:sources=2,turns=2,step=2",
        "--profile",
        profile.to_str().expect("utf8"),
        "--out",
        run_s,
    ]);
    run_ok(&["process", "mdf", run_s]);
    let local = work.join("laser-local");
    std::fs::rename(run.join("processed"), &local).expect("keep the local MDF");
    let shared = work.to_str().expect("utf8");
    let (ok, stdout, stderr) = rigd_on(
        cluster,
        &[
            "process",
            "mdf",
            run_s,
            "--executor",
            "slurm",
            "--shared-path",
            shared,
        ],
    );
    assert!(ok, "{stdout}\n{stderr}\n{}", cluster.logs());
    // Two turntable positions × three cameras.
    assert!(
        stdout.contains("6 views") && stdout.contains("on Slurm: 6 tasks"),
        "{stdout}"
    );
    let slurm = run.join("processed/mdf");
    let report = |dir: &Path| -> serde_json::Value {
        let mut v: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("report.json")).expect("report"))
                .expect("report parses");
        v["elapsed_s"] = serde_json::Value::Null;
        v
    };
    assert_eq!(report(&local.join("mdf")), report(&slurm));
    let mut compared = 0;
    for entry in std::fs::read_dir(local.join("mdf")).expect("local MDF") {
        let path = entry.expect("entry").path();
        if path.extension().is_some_and(|e| e == "npy") {
            let name = path.file_name().expect("name");
            assert_eq!(
                std::fs::read(&path).expect("local npy"),
                std::fs::read(slurm.join(name)).expect("Slurm npy"),
                "{name:?}"
            );
            compared += 1;
        }
    }
    assert_eq!(compared, 6);
    assert!(!run.join("processed/mdf-ahead").exists() && !run.join("processed/slurm").exists());
}

/// A daemon configured for Slurm processes a captured run there: the job's
/// `process` events carry the array's progress and the Slurm job.
async fn daemon_processes_on_slurm(cluster: &SlurmCluster, work: &Path) {
    use crate::common::http::{small_plan, SseReader};
    use serde_json::{json, Value};
    let data = work.join("daemon");
    let config = work.join("rigd.toml");
    std::fs::write(
        &config,
        format!(
            "[processing]\nexecutor = \"slurm\"\n[processing.slurm]\npartition = \"{}\"\nshared_paths = [\"{}\"]\npoll_s = 0.3\n",
            cluster.partition,
            work.display()
        ),
    )
    .expect("config");
    let token_file = work.join("token");
    std::fs::write(&token_file, "slurm-test-token-0123456789\n").expect("token");
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("port")
        .port();
    let base = format!("http://127.0.0.1:{port}");
    let log = std::fs::File::create(work.join("daemon.log")).expect("log");
    let _daemon = crate::common::Child(
        rigd()
            .args([
                "serve",
                "--listen",
                &format!("127.0.0.1:{port}"),
                "--sim-speed",
                "20000",
            ])
            .arg("--data")
            .arg(&data)
            .arg("--token-file")
            .arg(&token_file)
            .arg("--config")
            .arg(&config)
            .envs(cluster.env())
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("spawn rigd serve"),
    );
    let client = reqwest::Client::new();
    let started = Instant::now();
    while client
        .get(format!("{base}/api/v1/health"))
        .send()
        .await
        .is_err()
    {
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "the daemon did not start"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let post = |path: String, body: Value| {
        let client = client.clone();
        let url = format!("{base}{path}");
        async move {
            let r = client
                .post(url)
                .bearer_auth("slurm-test-token-0123456789")
                .json(&body)
                .send()
                .await
                .expect("POST");
            let status = r.status().as_u16();
            (status, r.json::<Value>().await.unwrap_or(Value::Null))
        }
    };
    let (status, v) = post(
        "/api/v1/runs".into(),
        json!({"sample": "felt", "plan": small_plan(4), "frame_size": [320, 240], "operator": "tester"}),
    )
    .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    loop {
        let v: Value = client
            .get(format!("{base}/api/v1/runs/{id}"))
            .send()
            .await
            .expect("GET run")
            .json()
            .await
            .expect("json");
        if v["state"] == "completed" {
            break;
        }
        assert!(started.elapsed() < Duration::from_secs(120), "{v}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let (_, sse) = SseReader::connect(&client, &format!("{base}/api/v1/events"), None).await;
    let mut sse = sse.expect("event stream");
    let (status, job) = post(
        format!("/api/v1/runs/{id}/process"),
        json!({"steps": ["rectify", "btf", "fit"], "rectify": {"size": 128, "final": 32}, "btf": {"components": 4}}),
    )
    .await;
    assert!(status == 202 || status == 200, "{status} {job}");
    let deadline = Instant::now() + Duration::from_secs(300);
    let mut btf_progress = Vec::new();
    let mut details = Vec::new();
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let Some((_, ev)) = sse.next(left).await else {
            panic!(
                "the job did not end; details {details:?}\n{}",
                cluster.logs()
            );
        };
        if ev["kind"] != "process" || ev["run"] != id.as_str() {
            continue;
        }
        let e = &ev["event"];
        assert_ne!(e["state"], "failed", "{ev}");
        if let Some(d) = e["detail"].as_str() {
            if !details.iter().any(|x| x == d) {
                details.push(d.to_string());
            }
        }
        if e["step"] == "btf" && e["total"].as_u64() > Some(0) {
            btf_progress.push((e["done"].as_u64(), e["total"].as_u64()));
        }
        if e["state"] == "done" {
            break;
        }
    }
    assert!(
        details.iter().any(|d| d.starts_with("rectify: Slurm job"))
            && details.iter().any(|d| d.starts_with("btf: Slurm job")),
        "{details:?}"
    );
    // Four view slots: the array's one task, then the join's four slots.
    assert!(
        btf_progress.contains(&(Some(1), Some(1))),
        "{btf_progress:?}"
    );
    assert!(
        btf_progress.contains(&(Some(4), Some(4))),
        "{btf_progress:?}"
    );
    let job: Value = client
        .get(format!("{base}/api/v1/runs/{id}/process"))
        .send()
        .await
        .expect("GET job")
        .json()
        .await
        .expect("json");
    for step in job["steps"].as_array().expect("steps") {
        assert!(
            step["summary"]
                .as_str()
                .is_some_and(|t| t.contains("on Slurm")),
            "{job}"
        );
    }
    let root = data.join("runs").join(&id);
    assert!(root.join("processed/btf/btf.json").is_file());
    // The embedded profile's Bayer camera, calibrated on the plate's
    // patches by the array's tasks: RGB textures.
    let index: Value = serde_json::from_slice(
        &std::fs::read(root.join("processed/normtextures/index.json")).expect("index.json"),
    )
    .expect("index.json is JSON");
    assert_eq!(index["channels"], 3, "RGB textures");
    assert!(
        root.join("processed/colour.json").is_file(),
        "the run's colour"
    );

    // Cancelled by the operator while its array waits (the partition is
    // down, so no task starts): the daemon cancels it with scancel.
    cluster.command(
        "scontrol",
        &[
            "update",
            &format!("PartitionName={}", cluster.partition),
            "State=DOWN",
        ],
    );
    let (status, job) = post(
        format!("/api/v1/runs/{id}/process"),
        json!({"steps": ["rectify", "btf"], "rectify": {"size": 96, "final": 32}}),
    )
    .await;
    assert_eq!(status, 202, "{job}");
    let mut cancelled = false;
    let deadline = Instant::now() + Duration::from_secs(120);
    let error = loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let Some((_, ev)) = sse.next(left).await else {
            panic!("the cancelled job did not end\n{}", cluster.logs());
        };
        if ev["kind"] != "process" || ev["run"] != id.as_str() {
            continue;
        }
        let e = &ev["event"];
        if !cancelled
            && e["detail"]
                .as_str()
                .is_some_and(|d| d.starts_with("rectify: Slurm job"))
        {
            let queued = cluster.command("squeue", &["-h", "--me", "-o", "%T"]);
            assert!(queued.contains("PENDING"), "{queued}");
            let (status, job) = post(format!("/api/v1/runs/{id}/process/cancel"), json!({})).await;
            assert_eq!(status, 200, "{job}");
            assert_eq!(job["cancelling"], true, "{job}");
            cancelled = true;
        }
        if e["state"] == "failed" {
            break e["error"].as_str().unwrap_or_default().to_string();
        }
        assert_ne!(e["state"], "done", "{ev}");
    };
    assert!(
        cancelled && error.contains("cancelled by the operator") && error.contains("scancel"),
        "{error}"
    );
    assert_eq!(
        cluster.command("squeue", &["-h", "--me"]).trim(),
        "",
        "the array is gone"
    );
    let (status, v) = post(format!("/api/v1/runs/{id}/process/cancel"), json!({})).await;
    assert_eq!(status, 409, "nothing left to cancel: {v}");
    cluster.command(
        "scontrol",
        &[
            "update",
            &format!("PartitionName={}", cluster.partition),
            "State=UP",
        ],
    );

    // The fit's files are those a local fit of the same textures writes.
    let fitted = work.join("fit-on-slurm");
    std::fs::rename(root.join("processed/fit"), &fitted).expect("keep the Slurm fit");
    run_ok(&["process", "fit", root.to_str().expect("utf8")]);
    for name in ["slot_000_ptm.npy", "slot_003_lobes.npy"] {
        assert_eq!(
            std::fs::read(fitted.join(name)).expect("Slurm fit"),
            std::fs::read(root.join("processed/fit").join(name)).expect("local fit"),
            "{name}"
        );
    }
}

/// Waits for a task of the job array named `name` to run, cancels it with
/// `scancel JOB_TASK`, and returns its id.
fn cancel_one_running_task(cluster: &SlurmCluster, name: &str, within: Duration) -> String {
    let started = Instant::now();
    loop {
        let running = cluster.command(
            "squeue",
            &[
                "-h",
                "-r",
                "--me",
                &format!("--name={name}"),
                "-t",
                "RUNNING",
                "-o",
                "%i",
            ],
        );
        if let Some(task) = running.lines().map(str::trim).find(|l| !l.is_empty()) {
            // Let it work a moment, so it dies with its part half done.
            std::thread::sleep(Duration::from_millis(500));
            cluster.command("scancel", &[task]);
            return task.to_string();
        }
        assert!(
            started.elapsed() < within,
            "no task of {name} ran within {within:?}\n{}",
            cluster.logs()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The child's stdout and stderr once it ended successfully, within `within`.
fn wait_output(child: &mut std::process::Child, within: Duration) -> (String, String) {
    use std::io::Read;
    let (mut out, mut err) = (String::new(), String::new());
    let mut stdout = child.stdout.take().expect("stdout");
    let mut stderr = child.stderr.take().expect("stderr");
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stderr.read_to_string(&mut s);
        s
    });
    let _ = stdout.read_to_string(&mut out);
    let started = Instant::now();
    let status = loop {
        if let Ok(Some(status)) = child.try_wait() {
            break status;
        }
        if started.elapsed() > within {
            let _ = child.kill();
            panic!("rigd did not end within {within:?}");
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    err.push_str(&reader.join().unwrap_or_default());
    assert!(status.success(), "rigd failed ({status}):\n{out}\n{err}");
    (out, err)
}

#[test]
fn slurm_configuration_errors_are_said_before_anything_is_submitted() {
    let work = tempfile::tempdir().expect("tempdir");
    let run = work.path().join("tiny");
    let plan = crate::common::tiny_plan(work.path());
    run_ok(&[
        "run",
        "--sim",
        "--plan",
        plan.to_str().expect("utf8"),
        "--frame-size",
        "16x16",
        "--progress",
        "none",
        "--out",
        run.to_str().expect("utf8"),
    ]);
    let run_s = run.to_str().expect("utf8");
    let shared = work.path().to_str().expect("utf8");
    let fails = |args: &[&str], path: Option<&str>| -> String {
        let mut cmd = rigd();
        cmd.args(args);
        if let Some(p) = path {
            cmd.env("PATH", p);
        }
        let out = cmd.output().expect("spawn rigd");
        assert_eq!(out.status.code(), Some(2), "{args:?}: bad input");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    // No Slurm commands on the PATH.
    let empty = tempfile::tempdir().expect("tempdir");
    let e = fails(
        &[
            "process",
            "btf",
            run_s,
            "--executor",
            "slurm",
            "--shared-path",
            shared,
        ],
        empty.path().to_str(),
    );
    assert!(e.contains("`sbatch` is not on the PATH"), "{e}");
    // The run outside every shared path.
    let elsewhere = tempfile::tempdir().expect("tempdir");
    let e = fails(
        &[
            "process",
            "btf",
            run_s,
            "--executor",
            "slurm",
            "--shared-path",
            elsewhere.path().to_str().expect("utf8"),
        ],
        None,
    );
    assert!(e.contains("is not under a shared path"), "{e}");
    // No shared path at all.
    let e = fails(&["process", "btf", run_s, "--executor", "slurm"], None);
    assert!(e.contains("no shared path is set"), "{e}");
    // Slurm's options without Slurm.
    let e = fails(&["process", "btf", run_s, "--partition", "rigd"], None);
    assert!(e.contains("need --executor slurm"), "{e}");
    // The daemon refuses to start on a configuration that cannot work.
    let config = work.path().join("rigd.toml");
    std::fs::write(
        &config,
        format!(
            "[processing]\nexecutor = \"slurm\"\n[processing.slurm]\nshared_paths = [\"{}\"]\n",
            elsewhere.path().display()
        ),
    )
    .expect("config");
    let data = work.path().join("data");
    let serve_refused = || -> String {
        let out = rigd()
            .args(["serve", "--listen", "127.0.0.1:0", "--data"])
            .arg(&data)
            .arg("--config")
            .arg(&config)
            .output()
            .expect("spawn rigd serve");
        assert_eq!(out.status.code(), Some(2), "bad configuration");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let e = serve_refused();
    assert!(e.contains("is not under a shared path"), "{e}");
    std::fs::write(&config, "[processing]\nexecuter = \"slurm\"\n").expect("config");
    let e = serve_refused();
    assert!(e.contains("unknown field `executer`"), "{e}");
}

fn interrupt_cancels_the_jobs(cluster: &SlurmCluster, run: &str, shared: &str) {
    let partition = format!("PartitionName={}", cluster.partition);
    cluster.command("scontrol", &["update", &partition, "State=DOWN"]);
    let mut child = crate::common::Child(
        rigd()
            .args([
                "process",
                "btf",
                run,
                "--executor",
                "slurm",
                "--shared-path",
                shared,
            ])
            .envs(cluster.env())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn rigd"),
    );
    let started = Instant::now();
    while !cluster
        .command("squeue", &["-h", "--me", "-t", "PENDING", "-o", "%i"])
        .contains('_')
    {
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "no task queued\n{}",
            cluster.logs()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    // SAFETY: kill(2) of the child this test started.
    unsafe {
        libc::kill(child.0.id() as libc::pid_t, libc::SIGINT);
    }
    let status = loop {
        if let Ok(Some(status)) = child.0.try_wait() {
            break status;
        }
        assert!(
            started.elapsed() < Duration::from_secs(90),
            "rigd did not stop after SIGINT"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut stderr = String::new();
    if let Some(mut e) = child.0.stderr.take() {
        use std::io::Read;
        let _ = e.read_to_string(&mut stderr);
    }
    assert_eq!(status.code(), Some(130), "interrupted: {stderr}");
    assert!(stderr.contains("cancelled with scancel"), "{stderr}");
    assert_eq!(
        cluster.command("squeue", &["-h", "--me"]).trim(),
        "",
        "the array is gone"
    );
    cluster.command("scontrol", &["update", &partition, "State=UP"]);
}
