//! The dashboard in a real browser: the built `rigd` binary serves a
//! simulated rig, Debian's chromedriver drives headless Chromium over
//! WebDriver (fantoccini), and the test works the dashboard like an operator:
//! token dialog, start a small run, watch progress and the hemisphere plot
//! fill, pause, resume, and see the run completed in the history. It saves a
//! screenshot to `target/browser-test/dashboard.png`. The peers test runs
//! two daemons, one listing the other (`--peers`), and works both rigs from
//! one dashboard (`target/browser-test/peers.png`).
//!
//! Needs `/usr/bin/chromium` and `/usr/bin/chromedriver`; `scripts/test.sh`
//! installs them (Debian packages `chromium` and `chromium-driver`). Without
//! them this test fails: it never skips.

mod common;
#[path = "browser/mdf_viewer.rs"]
mod mdf_viewer;

use std::fs::File;
use std::net::TcpListener;
use std::os::unix::process::CommandExt;
use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::actions::{InputSource, MouseActions, PointerAction, MOUSE_BUTTON_LEFT};
use fantoccini::{Client, ClientBuilder, Locator};
use futures::FutureExt;
use serde_json::{json, Value};

const CHROMIUM: &str = "/usr/bin/chromium";
const CHROMEDRIVER: &str = "/usr/bin/chromedriver";
/// Physical seconds per wall second: the run below (64 images, about 940 s
/// physical with homing) takes about 16 s.
const SIM_SPEED: &str = "60";
/// 8 directions, all paired with all: 64 images, 8 of them infeasible on
/// the Bonn rig (lamp and camera too close).
const DIRECTIONS: &str = "0 0\n30 0\n30 120\n30 240\n60 60\n60 180\n60 300\n80 0";
const IMAGES: u64 = 64;

/// One Chromium at a time: the two tests share two cores, and the
/// dashboard test's pause check needs the daemon to keep its pace.
static ONE_BROWSER: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// Kills what the test started, also when an assertion fails: each child
/// runs in its own process group and the whole group is killed (so
/// Chromium's processes go with chromedriver).
struct Procs {
    children: Vec<(&'static str, Child)>,
}

impl Procs {
    fn spawn(&mut self, name: &'static str, cmd: &mut Command, log: &Path) {
        let out = File::create(log).unwrap_or_else(|e| panic!("{}: {e}", log.display()));
        let err = out.try_clone().expect("clone log file");
        let child = cmd
            .stdin(Stdio::null())
            .stdout(out)
            .stderr(err)
            .process_group(0)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {name}: {e}"));
        self.children.push((name, child));
    }
}

impl Procs {
    /// The child known as `name`, no longer killed at the end.
    fn take(&mut self, name: &str) -> Child {
        let i = self
            .children
            .iter()
            .position(|(n, _)| *n == name)
            .unwrap_or_else(|| panic!("{name} is not running"));
        self.children.remove(i).1
    }

    /// SIGTERM (graceful shutdown), then SIGKILL after 15 s.
    fn stop(&mut self, name: &str) {
        let mut child = self.take(name);
        // SAFETY: signals a child this test started.
        unsafe {
            libc::kill(child.id() as libc::pid_t, libc::SIGTERM);
        }
        let deadline = Instant::now() + Duration::from_secs(15);
        while child.try_wait().ok().flatten().is_none() {
            if Instant::now() > deadline {
                let _ = child.kill();
                let _ = child.wait();
                panic!("{name} did not stop within 15 s of SIGTERM");
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// SIGKILL to the child's process group, as a crash or a pulled plug;
    /// returns when it is gone.
    fn kill(&mut self, name: &str) {
        let mut child = self.take(name);
        // SAFETY: signals the process group this test created.
        unsafe {
            libc::kill(-(child.id() as libc::pid_t), libc::SIGKILL);
        }
        let _ = child.kill();
        let _ = child.wait();
    }
}

impl Drop for Procs {
    fn drop(&mut self) {
        for (_, child) in self.children.iter_mut().rev() {
            let pid = child.id() as libc::pid_t;
            // SAFETY: signals the process group this test created.
            unsafe {
                libc::kill(-pid, libc::SIGKILL);
            }
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port()
}

fn out_dir() -> PathBuf {
    // CARGO_TARGET_TMPDIR is <target>/tmp.
    let tmp = Path::new(env!("CARGO_TARGET_TMPDIR"));
    let dir = tmp.parent().unwrap_or(tmp).join("browser-test");
    std::fs::create_dir_all(&dir).expect("create target/browser-test");
    dir
}

async fn wait_http(client: &reqwest::Client, url: &str, what: &str, secs: u64) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        if let Ok(r) = client.get(url).send().await {
            if r.status().is_success() {
                return;
            }
        }
        assert!(
            Instant::now() < deadline,
            "timed out after {secs} s waiting for {what} ({url})"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Evaluates `script` in the page.
async fn js(c: &Client, script: &str) -> Value {
    c.execute(script, vec![])
        .await
        .unwrap_or_else(|e| panic!("script failed: {e}\n{script}"))
}

/// Polls `script` until `ok` holds for its value.
async fn wait_js(
    c: &Client,
    what: &str,
    secs: u64,
    script: &str,
    ok: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let v = js(c, script).await;
        if ok(&v) {
            return v;
        }
        assert!(
            Instant::now() < deadline,
            "timed out after {secs} s waiting for {what}; last value: {v}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

const PROGRESS: &str = "return Number(document.getElementById('progress').value)";
const CONN: &str = "return document.getElementById('conn').dataset.state";
const RUN_STATE: &str = "return document.getElementById('run-state').textContent";
const FILLED: &str = "return document.querySelectorAll(\
    '#hemisphere [data-testid=hemi-marker][data-state=done], \
     #hemisphere [data-testid=hemi-marker][data-state=partial]').length";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_drives_a_run_in_chromium() {
    let _one_browser = ONE_BROWSER.lock().await;
    let started = Instant::now();
    let out = out_dir();
    let data = tempfile::tempdir().expect("tempdir");
    let profile_dir = tempfile::tempdir().expect("tempdir");
    let mut procs = Procs { children: vec![] };

    let port = free_port();
    let base = format!("http://127.0.0.1:{port}");
    spawn_daemon(
        &mut procs,
        data.path(),
        port,
        SIM_SPEED,
        None,
        &out.join("rigd.log"),
    );
    let http = reqwest::Client::new();
    wait_http(&http, &format!("{base}/api/v1/health"), "the daemon", 30).await;
    let token = std::fs::read_to_string(data.path().join("token")).expect("token file");
    let token = token.trim().to_string();
    let client = chromium(&mut procs, &out, profile_dir.path(), "1400,1500").await;

    let ctx = Ctx {
        base: &base,
        token: &token,
        http: &http,
        out: &out,
        data: data.path(),
        port,
    };
    let result = AssertUnwindSafe(operate(&client, &ctx, &mut procs))
        .catch_unwind()
        .await;
    end_session(client, procs, result, &out.join("dashboard-failure.png")).await;
    eprintln!("browser test: {:.1} s", started.elapsed().as_secs_f64());
}

/// Closes the browser and what the test started; after a failure first
/// saves a screenshot of whatever the page shows, then fails.
async fn end_session(
    client: Client,
    procs: Procs,
    result: std::thread::Result<()>,
    failure_png: &Path,
) {
    if result.is_err() {
        if let Ok(png) = client.screenshot().await {
            let _ = std::fs::write(failure_png, png);
        }
    }
    let _ = tokio::time::timeout(Duration::from_secs(10), client.close()).await;
    drop(procs);
    if let Err(panic) = result {
        std::panic::resume_unwind(panic);
    }
}

/// Starts chromedriver and a headless Chromium session on it.
async fn chromium(procs: &mut Procs, out: &Path, profile: &Path, window: &str) -> Client {
    for bin in [CHROMIUM, CHROMEDRIVER] {
        assert!(
            Path::new(bin).exists(),
            "{bin} is missing: run scripts/test.sh, which installs Debian's chromium and \
             chromium-driver (apt-get install chromium chromium-driver)"
        );
    }
    let driver_port = free_port();
    procs.spawn(
        "chromedriver",
        Command::new(CHROMEDRIVER).arg(format!("--port={driver_port}")),
        &out.join("chromedriver.log"),
    );
    wait_http(
        &reqwest::Client::new(),
        &format!("http://127.0.0.1:{driver_port}/status"),
        "chromedriver",
        30,
    )
    .await;
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".into(),
        json!({
            "binary": CHROMIUM,
            "args": [
                "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--disable-quic", "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--enable-unsafe-swiftshader",
                format!("--window-size={window}"),
                format!("--user-data-dir={}", profile.display()),
            ],
        }),
    );
    let connector = hyper_util::client::legacy::connect::HttpConnector::new();
    tokio::time::timeout(
        Duration::from_secs(60),
        ClientBuilder::new(connector)
            .capabilities(caps)
            .connect(&format!("http://127.0.0.1:{driver_port}")),
    )
    .await
    .expect("timed out after 60 s starting a Chromium session")
    .expect("WebDriver session with Chromium")
}

/// `rigd serve` on `data` at `speed`: the embedded simulated Bonn rig, or
/// the simulation of the profile file `profile`.
fn spawn_daemon(
    procs: &mut Procs,
    data: &Path,
    port: u16,
    speed: &str,
    profile: Option<&Path>,
    log: &Path,
) {
    let extra: Vec<&str> = match profile {
        Some(profile) => vec!["--sim", "--profile", profile.to_str().expect("utf-8 path")],
        None => Vec::new(),
    };
    spawn_rig(procs, "rigd", (data, port, speed), &extra, log);
}

/// `rigd serve` on `data` at `speed` (the embedded simulated Bonn rig
/// unless `extra` names a profile), known to `procs` as `name`.
fn spawn_rig(
    procs: &mut Procs,
    name: &'static str,
    (data, port, speed): (&Path, u16, &str),
    extra: &[&str],
    log: &Path,
) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_rigd"));
    cmd.args([
        "serve",
        "--data",
        data.to_str().expect("utf-8 path"),
        "--listen",
        &format!("127.0.0.1:{port}"),
        "--sim-speed",
        speed,
    ]);
    cmd.args(extra);
    procs.spawn(name, &mut cmd, log);
}

struct Ctx<'a> {
    base: &'a str,
    token: &'a str,
    http: &'a reqwest::Client,
    out: &'a Path,
    data: &'a Path,
    port: u16,
}

async fn operate(c: &Client, ctx: &Ctx<'_>, procs: &mut Procs) {
    let (base, token, http, out) = (ctx.base, ctx.token, ctx.http, ctx.out);
    c.goto(&format!("{base}/"))
        .await
        .expect("open the dashboard");
    assert_eq!(c.title().await.expect("title"), "rigd dashboard");

    // No token stored yet: the dashboard asks for it. A wrong one first.
    enter_token(c, "not-the-token").await;
    wait_js(
        c,
        "the live event stream",
        10,
        "return document.getElementById('conn').dataset.state",
        |v| v == "live",
    )
    .await;
    // The rig panel lists the simulated Bonn rig's devices.
    wait_js(
        c,
        "the rig's devices",
        10,
        "return document.querySelectorAll('#rig tbody tr').length",
        |v| v.as_u64() == Some(4),
    )
    .await;
    // "Check rig" connects every device (a fresh simulated rig: nothing is
    // running yet) and lists one verdict per device.
    c.find(Locator::Id("rig-check"))
        .await
        .expect("#rig-check")
        .click()
        .await
        .expect("click Check rig");
    wait_js(
        c,
        "the rig check's verdict",
        30,
        "return document.getElementById('rig-check-summary').textContent",
        |v| v.as_str() == Some("bonn-gonioreflectometer: all 4 devices usable"),
    )
    .await;
    let rail = js(
        c,
        "return document.querySelector('#rig-check-list li[data-device=rail]').textContent",
    )
    .await;
    assert!(
        rail.as_str().is_some_and(
            |t| t.starts_with("OK rail (axis): GRBL 1.1h") && t.contains("$110=720.000")
        ),
        "{rail}"
    );
    // The plan select holds the built-in plans (h1 fits the Bonn rig); the
    // daemon solves them in the background and the page asks again until
    // each shows its size.
    wait_js(
        c,
        "the plan list",
        10,
        "return [...document.querySelectorAll('#plan option')].map(o => o.value)",
        |v| {
            v.as_array()
                .is_some_and(|a| a.contains(&json!("h1")) && a.contains(&json!("__custom")))
        },
    )
    .await;
    wait_js(
        c,
        "h1 solved and sized in the plan list",
        60,
        "return document.querySelector('#plan option[value=h1]').textContent",
        |v| v.as_str().is_some_and(|t| t.contains("6561 images")),
    )
    .await;

    // The form offers the exposure policies with what each costs: brackets
    // take longer than the profile's single exposure.
    let estimate = "return document.getElementById('plan-info').textContent";
    let single = wait_js(c, "h1's estimate", 10, estimate, |v| {
        v.as_str().is_some_and(|t| t.contains("about"))
    })
    .await;
    let bracketed = wait_js(
        c,
        "h1's estimate under brackets",
        10,
        "const s = document.getElementById('exposure-policy');
         const o = [...s.options].find((o) => o.textContent.startsWith('brackets'));
         if (!o) return null;
         s.value = o.value;
         s.dispatchEvent(new Event('change'));
         return [document.getElementById('plan-info').textContent, s.options.length];",
        |v| v[1].as_u64() == Some(4),
    )
    .await;
    assert_ne!(bracketed[0], single, "{bracketed} {single}");
    js(
        c,
        "const s = document.getElementById('exposure-policy');
         s.selectedIndex = 0;
         s.dispatchEvent(new Event('change'));",
    )
    .await;

    // A small custom run.
    c.find(Locator::Id("sample"))
        .await
        .expect("#sample")
        .send_keys("felt-browser")
        .await
        .expect("sample");
    select_value(c, "plan", "__custom").await;
    let dirs = c
        .find(Locator::Id("custom-dirs"))
        .await
        .expect("#custom-dirs");
    assert!(
        dirs.is_displayed().await.expect("displayed"),
        "the directions field appears for a custom plan"
    );
    dirs.clear().await.expect("clear");
    dirs.send_keys(DIRECTIONS).await.expect("directions");
    c.find(Locator::Id("frame-w"))
        .await
        .expect("#frame-w")
        .send_keys("32")
        .await
        .expect("w");
    c.find(Locator::Id("frame-h"))
        .await
        .expect("#frame-h")
        .send_keys("24")
        .await
        .expect("h");
    c.find(Locator::Id("operator"))
        .await
        .expect("#operator")
        .send_keys("webdriver")
        .await
        .expect("op");
    c.find(Locator::Id("start"))
        .await
        .expect("#start")
        .click()
        .await
        .expect("click Start");
    // The daemon answers 401: the dialog asks again; with the right token
    // the start goes through.
    let why = wait_js(
        c,
        "the token dialog after a 401",
        10,
        "const d = document.getElementById('token-dialog'); \
         return d.open ? document.getElementById('token-why').textContent : null",
        |v| v.is_string(),
    )
    .await;
    assert!(
        why.as_str().is_some_and(|t| t.contains("401")),
        "dialog says: {why}"
    );
    enter_token(c, token).await;

    // The run's total (or the form's error, if the start failed).
    let total = wait_js(
        c,
        "the run's progress bar (frames total)",
        15,
        "const e = document.getElementById('form-error'); \
         return e.hidden ? Number(document.getElementById('progress').dataset.total || 0) : e.textContent",
        |v| v.as_u64() == Some(IMAGES) || v.is_string(),
    )
    .await;
    assert_eq!(
        total,
        json!(IMAGES),
        "the run did not start (form error shown)"
    );
    let run_id = js(
        c,
        "return document.querySelector('#history tbody tr').dataset.runId",
    )
    .await;
    let run_id = run_id.as_str().expect("run id in the history").to_string();
    assert!(run_id.contains("felt-browser"), "history row {run_id}");

    // Progress and the hemisphere plot advance.
    let p1 = wait_js(c, "the first frames", 30, PROGRESS, |v| {
        v.as_u64().is_some_and(|n| n >= 2)
    })
    .await;
    let f1 = js(c, FILLED).await.as_u64().expect("marker count");
    assert!(f1 >= 1, "a captured direction is filled after {p1} frames");
    let p1 = p1.as_u64().expect("progress");
    wait_js(c, "the progress bar to advance", 30, PROGRESS, |v| {
        v.as_u64().is_some_and(|n| n >= p1 + 10)
    })
    .await;
    let f2 = wait_js(c, "more hemisphere markers filled", 30, FILLED, |v| {
        v.as_u64().is_some_and(|n| n > f1)
    })
    .await;
    let current = js(
        c,
        "return document.querySelectorAll('#hemisphere [data-testid=hemi-current]').length",
    )
    .await;
    assert_eq!(
        current,
        json!(2),
        "the current light and view are highlighted"
    );
    let crosses = js(
        c,
        "return document.querySelectorAll('#hemisphere [data-testid=hemi-infeasible]').length",
    )
    .await;
    assert!(
        crosses.as_u64().is_some_and(|n| n > 0),
        "infeasible views are marked"
    );
    let eta = js(
        c,
        "return document.getElementById('progress-text').textContent",
    )
    .await;
    assert!(
        eta.as_str()
            .is_some_and(|t| t.contains("ETA") && t.contains("physical")),
        "progress text: {eta}"
    );
    eprintln!("hemisphere: {f1} then {f2} markers filled");
    let png = c.screenshot().await.expect("screenshot");
    std::fs::write(out.join("dashboard-running.png"), png).expect("write the screenshot");

    // Pause: the state shows paused and the frames stop.
    wait_js(
        c,
        "the Pause button to be enabled",
        10,
        "return !document.getElementById('pause').disabled",
        |v| v == &json!(true),
    )
    .await;
    c.find(Locator::Id("pause"))
        .await
        .expect("#pause")
        .click()
        .await
        .expect("click Pause");
    wait_js(c, "the run to show paused", 15, RUN_STATE, |v| {
        v == "paused"
    })
    .await;
    let held = js(c, PROGRESS).await.as_u64().expect("progress");
    assert!(
        held < IMAGES,
        "the run finished before it could be paused ({held} frames)"
    );
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(
        js(c, PROGRESS).await.as_u64(),
        Some(held),
        "frames kept coming while paused"
    );
    assert_eq!(js(c, RUN_STATE).await, json!("paused"));
    // The paused run holds the rig: manual control is refused (409).
    open_manual(c).await;
    click_id(c, "manual-plus").await;
    manual_says(c, "manual control refused during the run", |t| {
        t.starts_with("jog: conflict: run") && t.contains("manual control waits")
    })
    .await;
    let (_, api_run) = get_json(http, &format!("{base}/api/v1/runs/{run_id}")).await;
    assert_eq!(
        api_run["state"],
        json!("paused"),
        "the daemon agrees: {api_run}"
    );

    // Resume: frames come again, then the run completes.
    wait_js(
        c,
        "the Resume button to be enabled",
        10,
        "return !document.getElementById('resume').disabled",
        |v| v == &json!(true),
    )
    .await;
    c.find(Locator::Id("resume"))
        .await
        .expect("#resume")
        .click()
        .await
        .expect("click Resume");
    wait_js(c, "frames after resuming", 30, PROGRESS, |v| {
        v.as_u64().is_some_and(|n| n > held)
    })
    .await;
    let row = format!("#history tr[data-run-id='{run_id}']");
    wait_js(
        c,
        "the run completed in the history",
        60,
        &format!("const r = document.querySelector(\"{row}\"); return r ? r.dataset.state : null"),
        |v| v == "completed",
    )
    .await;
    wait_js(c, "the full progress bar", 10, PROGRESS, |v| {
        v.as_u64() == Some(IMAGES)
    })
    .await;
    wait_js(
        c,
        "every hemisphere marker filled",
        10,
        "return document.querySelectorAll('#hemisphere [data-testid=hemi-marker]:not([data-state=done])').length",
        |v| v.as_u64() == Some(0),
    )
    .await;
    let links = js(
        c,
        &format!(
            "return [...document.querySelectorAll(\"{row} a\")].map(a => a.getAttribute('href'))"
        ),
    )
    .await;
    let manifest = format!("/api/v1/runs/{run_id}/manifest");
    assert!(
        links
            .as_array()
            .is_some_and(|a| a.contains(&json!(manifest))),
        "a manifest link in the history row: {links}"
    );
    let (status, m) = get_json(http, &format!("{base}{manifest}")).await;
    assert_eq!(status, 200, "manifest: {m}");
    assert_eq!(m["state"], json!("completed"));
    assert_eq!(m["frames_written"], json!(IMAGES));
    // The latest frame's preview is shown.
    let last_preview = format!("/api/v1/runs/{run_id}/frames/{}/preview", IMAGES - 1);
    wait_js(
        c,
        "the last frame's preview",
        10,
        "const i = document.getElementById('preview'); return i.complete && i.naturalWidth > 0 && i.getAttribute('src')",
        |v| v.as_str() == Some(last_preview.as_str()),
    )
    .await;
    // The rig is idle again.
    wait_js(
        c,
        "the rig to show idle",
        10,
        "return document.getElementById('rig-state').textContent",
        |v| v == "rig idle",
    )
    .await;
    // Manual control with the rig free: home and jog the rail, switch the
    // lamp, take a test frame into the preview.
    select_value(c, "manual-axis", "rail").await;
    click_id(c, "manual-home").await;
    manual_says(c, "the rail homed", |t| t == "rail homed at 90.00°").await;
    click_id(c, "manual-plus").await;
    manual_says(c, "the rail jogged", |t| t == "rail at 95.00°").await;
    click_id(c, "manual-on").await;
    manual_says(c, "the lamp on", |t| t == "hmi ON").await;
    click_id(c, "manual-off").await;
    manual_says(c, "the lamp off", |t| t == "hmi off").await;
    click_id(c, "manual-frame").await;
    manual_says(c, "the test frame", |t| {
        t.starts_with("test frame from camera: ")
    })
    .await;
    wait_js(
        c,
        "the test frame in the preview",
        10,
        "const i = document.getElementById('preview'); return i.complete && i.naturalWidth > 0 && i.getAttribute('src')",
        |v| v.as_str().is_some_and(|s| s.contains("/api/v1/rig/manual/frame")),
    )
    .await;
    // The holder check: refused until the rig has taken a pose (the rail
    // was jogged since it connected), then, posed frontally with the lamp
    // on, every marker of the default profile's standard plate (eight
    // light discs, no colour patches) found and registered.
    click_id(c, "manual-holder").await;
    manual_says(c, "the holder check refused before a pose", |t| {
        t.starts_with("holder-check: conflict: move to a pose first")
    })
    .await;
    select_value(c, "manual-axis", "arm").await;
    click_id(c, "manual-home").await;
    manual_says(c, "the arm homed", |t| t.starts_with("arm homed at ")).await;
    for (id, dir) in [("manual-light", "30,0"), ("manual-view", "0,0")] {
        let input = c.find(Locator::Id(id)).await.expect(id);
        input.clear().await.expect("clear");
        input.send_keys(dir).await.expect("a direction");
    }
    click_id(c, "manual-pose").await;
    manual_says(c, "the frontal pose", |t| {
        t.starts_with("pose reached: ") && t.ends_with("lit by hmi, seen by camera")
    })
    .await;
    click_id(c, "manual-on").await;
    manual_says(c, "the lamp on for the holder check", |t| t == "hmi ON").await;
    click_id(c, "manual-holder").await;
    manual_says(c, "the holder check", |t| {
        t == "holder check from camera: OK"
    })
    .await;
    let result = wait_js(
        c,
        "the holder check's result",
        10,
        "const r = document.getElementById('manual-holder-result'); \
         return r.hidden ? null : [r.querySelector('[data-testid=holder-summary]').textContent, \
           [...r.querySelectorAll('[data-testid=holder-problems] li')].map(l => l.textContent), \
           r.querySelectorAll('[data-testid=holder-patches] tr[data-patch]').length, r.textContent]",
        |v| v.is_array(),
    )
    .await;
    let summary = result[0].as_str().unwrap_or_default();
    assert!(
        summary.starts_with("holder standard (bonn-gonioreflectometer), camera at view θ 0.0°")
            && summary.contains("8 of 8 markers found, registered, residual RMS"),
        "{result}"
    );
    assert_eq!(
        result[1],
        json!(["OK every marker found, nothing clipped"]),
        "{result}"
    );
    assert_eq!(
        result[2],
        json!(6),
        "the standard plate's six colour patches, a row each: {result}"
    );
    assert!(
        result[3]
            .as_str()
            .is_some_and(|t| ["white", "red", "green", "grey", "blue", "yellow"]
                .iter()
                .all(|p| t.contains(p))),
        "{result}"
    );
    let holder_png = c
        .find(Locator::Id("manual-holder-result"))
        .await
        .expect("#manual-holder-result")
        .screenshot()
        .await
        .expect("a screenshot of the holder check");
    std::fs::write(out.join("dashboard-holder.png"), holder_png).expect("write the screenshot");
    // The clicks above scrolled far down the rig card: back to the top,
    // so the run card's buttons are not under the sticky top bar when a
    // click scrolls them into view.
    js(c, "window.scrollTo(0, 0); return true").await;
    let log_lines = js(c, "return document.querySelectorAll('#log li').length").await;
    assert!(
        log_lines.as_u64().is_some_and(|n| n > 10),
        "event log lines: {log_lines}"
    );

    // The screenshot.
    let png = c.screenshot().await.expect("screenshot");
    let path = out.join("dashboard.png");
    std::fs::write(&path, &png).expect("write the screenshot");
    check_png(&png);
    eprintln!("screenshot: {}", path.display());

    // The daemon restarts: the indicator shows the lost stream, the page
    // reconnects by itself and refetches its state. Event ids start again
    // from 1, so a run started now over the API (not from the page) must
    // still reach the page live.
    procs.stop("rigd");
    wait_js(c, "the indicator to show the lost stream", 10, CONN, |v| {
        v == "reconnecting" || v == "offline"
    })
    .await;
    spawn_daemon(
        procs,
        ctx.data,
        ctx.port,
        SIM_SPEED,
        None,
        &out.join("rigd-restarted.log"),
    );
    wait_http(
        http,
        &format!("{base}/api/v1/health"),
        "the restarted daemon",
        30,
    )
    .await;
    wait_js(c, "the stream to be live again", 20, CONN, |v| v == "live").await;
    let body = json!({
        "sample": "felt-restart",
        "plan": {"directions": [
            {"theta_deg": 0, "phi_deg": 0}, {"theta_deg": 30, "phi_deg": 0},
            {"theta_deg": 30, "phi_deg": 120}, {"theta_deg": 30, "phi_deg": 240},
            {"theta_deg": 60, "phi_deg": 60}, {"theta_deg": 60, "phi_deg": 180},
            {"theta_deg": 60, "phi_deg": 300}, {"theta_deg": 80, "phi_deg": 0},
        ]},
        "frame_size": [32, 24],
    });
    let r = http
        .post(format!("{base}/api/v1/runs"))
        .bearer_auth(token)
        .json(&body)
        .send()
        .await
        .expect("POST /runs");
    assert_eq!(r.status().as_u16(), 201, "start a run over the API");
    let run2: Value = r.json().await.expect("run JSON");
    let id2 = run2["id"].as_str().expect("run id").to_string();
    wait_js(
        c,
        "the run started over the API to show running after the reconnect",
        20,
        "return [document.getElementById('run-id').textContent, document.getElementById('run-state').textContent, \
         Number(document.getElementById('progress').value)]",
        |v| {
            v[0].as_str().is_some_and(|t| t.contains(&id2)) && v[1] == "running" && v[2].as_u64().is_some_and(|n| n >= 1)
        },
    )
    .await;

    // EMERGENCY STOP: the run pauses (no confirmation asked).
    c.find(Locator::Id("estop"))
        .await
        .expect("#estop")
        .click()
        .await
        .expect("click EMERGENCY STOP");
    wait_js(
        c,
        "the run to show paused after the emergency stop",
        15,
        RUN_STATE,
        |v| v == "paused",
    )
    .await;
    let (_, api_run) = get_json(http, &format!("{base}/api/v1/runs/{id2}")).await;
    assert_eq!(
        api_run["state"],
        json!("paused"),
        "the daemon agrees: {api_run}"
    );

    // Abort asks for confirmation; accepted, the run ends aborted.
    wait_js(
        c,
        "the Abort button to be enabled",
        10,
        "return !document.getElementById('abort').disabled",
        |v| v == &json!(true),
    )
    .await;
    c.find(Locator::Id("abort"))
        .await
        .expect("#abort")
        .click()
        .await
        .expect("click Abort");
    let deadline = Instant::now() + Duration::from_secs(10);
    let question = loop {
        match c.get_alert_text().await {
            Ok(t) => break t,
            Err(_) if Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(100)).await
            }
            Err(e) => panic!("no confirmation asked before aborting: {e}"),
        }
    };
    assert!(question.contains("Abort run"), "confirmation: {question}");
    c.accept_alert().await.expect("confirm the abort");
    let row2 = format!("#history tr[data-run-id='{id2}']");
    wait_js(
        c,
        "the aborted run in the history",
        20,
        &format!("const r = document.querySelector(\"{row2}\"); return r ? r.dataset.state : null"),
        |v| v == "aborted",
    )
    .await;
    let rows = js(
        c,
        "return document.querySelectorAll('#history tbody tr').length",
    )
    .await;
    assert_eq!(rows, json!(2), "both runs in the history");
}

/// Clicks the element with id `id`.
async fn click_id(c: &Client, id: &str) {
    c.find(Locator::Id(id))
        .await
        .unwrap_or_else(|e| panic!("#{id}: {e}"))
        .click()
        .await
        .unwrap_or_else(|e| panic!("click #{id}: {e}"));
}

/// Clicks the element `css` finds. The dashboard re-renders its run
/// history and rig rows on every poll, so an element found a moment ago may
/// have been replaced before the click lands: then it is found again.
async fn click_css(c: &Client, css: &str, what: &str) {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let element = c
            .find(Locator::Css(css))
            .await
            .unwrap_or_else(|e| panic!("{what} ({css}): {e}"));
        match element.click().await {
            Ok(()) => return,
            Err(e) if e.is_stale_element_reference() && Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            Err(e) => panic!("click {what} ({css}): {e}"),
        }
    }
}

/// Chooses `value` in the select with id `id`. The dashboard rebuilds a
/// list's options when what they show changes (a plan solved and sized),
/// so an option found a moment ago may be gone before the click: then the
/// select is found again.
async fn select_value(c: &Client, id: &str, value: &str) {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let select = c
            .find(Locator::Id(id))
            .await
            .unwrap_or_else(|e| panic!("#{id}: {e}"));
        match select.select_by_value(value).await {
            Ok(()) => return,
            Err(e) if e.is_stale_element_reference() && Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            Err(e) => panic!("choose {value} in #{id}: {e}"),
        }
    }
}

/// Opens the rig card's "Manual control" section.
async fn open_manual(c: &Client) {
    js(
        c,
        "document.getElementById('manual').open = true; return true",
    )
    .await;
}

/// Waits for the manual-control status line to satisfy `pred`.
async fn manual_says(c: &Client, what: &str, pred: fn(&str) -> bool) {
    wait_js(
        c,
        what,
        30,
        "return document.getElementById('manual-status').textContent",
        |v| v.as_str().is_some_and(pred),
    )
    .await;
}

async fn enter_token(c: &Client, token: &str) {
    wait_js(
        c,
        "the token dialog",
        10,
        "return document.getElementById('token-dialog').open",
        |v| v == &json!(true),
    )
    .await;
    let input = c
        .find(Locator::Id("token-input"))
        .await
        .expect("#token-input");
    input.clear().await.expect("clear the token field");
    input.send_keys(token).await.expect("type the token");
    c.find(Locator::Id("token-save"))
        .await
        .expect("#token-save")
        .click()
        .await
        .expect("save the token");
    wait_js(
        c,
        "the token stored and the dialog closed",
        10,
        "return !document.getElementById('token-dialog').open && localStorage.getItem('rigd-token')",
        |v| v.as_str() == Some(token),
    )
    .await;
}

async fn get_json(http: &reqwest::Client, url: &str) -> (u16, Value) {
    let r = http
        .get(url)
        .send()
        .await
        .unwrap_or_else(|e| panic!("GET {url}: {e}"));
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

/// A real picture: a PNG of the window's size with many colours.
fn check_png(png: &[u8]) {
    assert!(png.len() > 20_000, "screenshot only {} bytes", png.len());
    let decoder = png::Decoder::new(png);
    let mut reader = decoder.read_info().expect("screenshot is a PNG");
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).expect("PNG frame");
    assert!(
        info.width >= 1000 && info.height >= 800,
        "screenshot {}x{}",
        info.width,
        info.height
    );
    let bpp = info.line_size / info.width as usize;
    let mut colours = std::collections::HashSet::new();
    for px in buf[..info.buffer_size()].chunks(bpp).step_by(7) {
        colours.insert(px.to_vec());
    }
    assert!(
        colours.len() > 100,
        "screenshot has only {} colours",
        colours.len()
    );
}

// ------------------------------------------------------------ the viewer

/// Largest RMS difference (8-bit levels) between the viewer's image and
/// `rigd process render`: half floats, GPU filtering and the odd pixel on
/// a triangle edge; a wrong interpolation or frame costs tens of levels.
const VIEWER_RMS_BOUND: f64 = 2.0;
const VIEWER_SIZE: usize = 192;

/// Lights × views of the viewer's run: a pole, two rings each.
fn viewer_plan() -> Value {
    let ring = |theta: f64, n: usize, offset: f64| -> Vec<Value> {
        (0..n)
            .map(|k| json!({"theta_deg": theta, "phi_deg": offset + 360.0 * k as f64 / n as f64}))
            .collect()
    };
    let mut lights = vec![json!({"theta_deg": 0, "phi_deg": 0})];
    lights.extend(ring(30.0, 6, 0.0));
    lights.extend(ring(60.0, 8, 0.0));
    let mut views = vec![json!({"theta_deg": 0, "phi_deg": 0})];
    views.extend(ring(30.0, 4, 45.0));
    views.extend(ring(60.0, 4, 0.0));
    json!({"name": "viewer", "lights": lights, "views": views})
}

/// Waits until the viewer has drawn its first frame, and fails on its error.
async fn wait_viewer(c: &Client) {
    wait_js(
        c,
        "the viewer to load",
        60,
        "return window.rigdViewer && (window.rigdViewer.ready || window.rigdViewer.error)",
        |v| v == &json!(true) || v.is_string(),
    )
    .await;
    let err = js(c, "return window.rigdViewer.error").await;
    assert_eq!(err, Value::Null, "the viewer failed");
}

/// The viewer's left half, as RGB rows from the top.
async fn viewer_pixels(c: &Client) -> Vec<u8> {
    let px = js(c, "return window.rigdViewer.pixels()").await;
    px.as_array()
        .expect("an array of pixel values")
        .iter()
        .map(|v| {
            v.as_u64()
                .and_then(|v| u8::try_from(v).ok())
                .expect("8-bit value")
        })
        .collect()
}

/// Asserts the viewer's pixels within [`VIEWER_RMS_BOUND`] of the
/// reference's, keeping both images as `{prefix}-got.png` and
/// `{prefix}-want.png` in `out` when not; prints and returns the RMS.
fn assert_near_reference(got: &[u8], want: &[u8], case: &str, out: &Path, prefix: &str) -> f64 {
    // Per channel: an RGB BTF must be right in each of red, green and blue.
    let channel = |px: &[u8], c: usize| px.iter().skip(c).step_by(3).copied().collect::<Vec<u8>>();
    let e = (0..3)
        .map(|c| rms(&channel(got, c), &channel(want, c)))
        .fold(0.0, f64::max);
    eprintln!("{case}: RMS {e:.2} levels (worst channel)");
    if e > VIEWER_RMS_BOUND {
        write_rgb(&out.join(format!("{prefix}-got.png")), VIEWER_SIZE, got);
        write_rgb(&out.join(format!("{prefix}-want.png")), VIEWER_SIZE, want);
    }
    assert!(
        e <= VIEWER_RMS_BOUND,
        "{case}: RMS {e:.2} > {VIEWER_RMS_BOUND}"
    );
    e
}

fn rms(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len());
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
        .sum();
    (sum / a.len() as f64).sqrt()
}

fn mean_of(px: &[u8]) -> f64 {
    px.iter().map(|&v| f64::from(v)).sum::<f64>() / px.len() as f64
}

/// The step across a tile edge of the flat sample seen from straight above,
/// and the texture's own steps between neighbouring pixels, in levels.
#[derive(Debug)]
struct TileSeam {
    /// Whether the steps are between columns (across the vertical tile
    /// edge) or rows.
    across_columns: bool,
    /// Mean step over the three pixel pairs that straddle the tile edge.
    edge: f64,
    /// Mean step over the sample's other neighbouring pixel pairs.
    texture: f64,
}

/// The seam measure of [`TileSeam`] on RGB pixels (`size` × `size`, rows
/// from the top) whose sample covers `covered`. The tiles meet at the
/// middle of the covered square. The measure is taken across the edge
/// along which the texture is smoother: a corduroy's wales are steps of
/// their own across the other edge, and a seam shows only where the
/// texture is smooth across it. The sample's outermost two pixels, where
/// it meets the background, are left out.
fn tile_seam(px: &[u8], covered: &[bool], size: usize) -> TileSeam {
    let at = |x: usize, y: usize| covered[y * size + x];
    let xs: Vec<usize> = (0..size).filter(|&x| (0..size).any(|y| at(x, y))).collect();
    let ys: Vec<usize> = (0..size).filter(|&y| (0..size).any(|x| at(x, y))).collect();
    let (x0, x1) = (xs[0] + 2, xs[xs.len() - 1] - 2);
    let (y0, y1) = (ys[0] + 2, ys[ys.len() - 1] - 2);
    let value = |x: usize, y: usize, c: usize| f64::from(px[3 * (y * size + x) + c]);
    let step = |(xa, ya): (usize, usize), (xb, yb): (usize, usize)| {
        (0..3)
            .map(|c| (value(xb, yb, c) - value(xa, ya, c)).abs())
            .sum::<f64>()
            / 3.0
    };
    let measure = |across_columns: bool| {
        // Step k is between line k and k + 1 (columns or rows).
        let (lo, hi, along) = if across_columns {
            (x0, x1, y0..=y1)
        } else {
            (y0, y1, x0..=x1)
        };
        let steps: Vec<(usize, f64)> = (lo..hi)
            .map(|k| {
                let total: f64 = along
                    .clone()
                    .map(|j| {
                        if across_columns {
                            step((k, j), (k + 1, j))
                        } else {
                            step((j, k), (j, k + 1))
                        }
                    })
                    .sum();
                (k, total / along.clone().count() as f64)
            })
            .collect();
        // The edge lies between lines middle − 1 and middle.
        let middle = (lo + hi).div_ceil(2);
        let near = |k: usize| k + 2 >= middle && k <= middle;
        let mean = |v: Vec<f64>| v.iter().sum::<f64>() / v.len() as f64;
        TileSeam {
            across_columns,
            edge: mean(
                steps
                    .iter()
                    .filter(|(k, _)| near(*k))
                    .map(|s| s.1)
                    .collect(),
            ),
            texture: mean(
                steps
                    .iter()
                    .filter(|(k, _)| !near(*k))
                    .map(|s| s.1)
                    .collect(),
            ),
        }
    };
    let (columns, rows) = (measure(true), measure(false));
    eprintln!("tile seam across columns {columns:?}, across rows {rows:?}");
    if columns.texture <= rows.texture {
        columns
    } else {
        rows
    }
}

/// Sets the viewer to a mesh, light and view and returns its pixels.
async fn show_case(c: &Client, mesh: &str, light: (f64, f64), view: (f64, f64)) -> Vec<u8> {
    js(
        c,
        &format!(
            "window.rigdViewer.ready = false; window.rigdViewer.setMesh('{mesh}').then(() => {{ \
             window.rigdViewer.setLight({}, {}); window.rigdViewer.setView({}, {}); \
             window.rigdViewer.ready = true; }}); return 0",
            light.0, light.1, view.0, view.1
        ),
    )
    .await;
    wait_js(
        c,
        "the viewer to take the case",
        30,
        "return window.rigdViewer.ready",
        |v| v == &json!(true),
    )
    .await;
    viewer_pixels(c).await
}

/// Sets the viewer to a mesh, light and view; returns its pixels and the
/// reference render of the same.
async fn viewer_case(
    c: &Client,
    run: &Path,
    mesh: &str,
    light: (f64, f64),
    view: (f64, f64),
) -> (Vec<u8>, rigd_process::relight::RgbImage) {
    use rigd_process::directions::Direction;
    let got = show_case(c, mesh, light, view).await;
    let settings = rigd_process::relight::RelightSettings {
        width: VIEWER_SIZE,
        height: VIEWER_SIZE,
        light: Direction::new(light.0, light.1),
        view: Direction::new(view.0, view.1),
        ..Default::default()
    };
    let kind = mesh.parse().expect("mesh kind");
    let want = rigd::postprocess::viewer::relight_run(
        run,
        kind,
        rigd::postprocess::viewer::DEFAULT_DENSITY,
        &settings,
    )
    .expect("reference render");
    (got, want)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewer_relights_a_processed_run_like_the_reference_renderer() {
    let _one_browser = ONE_BROWSER.lock().await;
    let started = Instant::now();
    let out = out_dir();
    let data = tempfile::tempdir().expect("tempdir");
    let profile_dir = tempfile::tempdir().expect("tempdir");
    let mut procs = Procs { children: vec![] };
    let port = free_port();
    let base = format!("http://127.0.0.1:{port}");
    // The Bonn rig, simulated as its embedded profile has it: the
    // rust-dyed corduroy photographed by the DCS 760, a Bayer camera, on a
    // holder with colour patches, so rectification measures the colour on
    // them, and the BTF is RGB.
    let profile = data.path().join("bonn-corduroy.toml");
    let toml = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/rig-profiles/bonn-gonioreflectometer.toml"
    ))
    .expect("Bonn profile");
    assert!(
        [
            "cfa = \"RGGB\"",
            "scene = \"corduroy\"",
            "colour_patches = true"
        ]
        .iter()
        .all(|line| toml.contains(line)),
        "the embedded Bonn profile is the colour camera on corduroy, with patches"
    );
    std::fs::write(&profile, toml).expect("write the profile");
    spawn_daemon(
        &mut procs,
        data.path(),
        port,
        "5000",
        Some(&profile),
        &out.join("rigd-viewer.log"),
    );
    let http = reqwest::Client::new();
    wait_http(&http, &format!("{base}/api/v1/health"), "the daemon", 30).await;
    let token = std::fs::read_to_string(data.path().join("token")).expect("token file");

    // Capture a small corduroy BTF through the API and process it.
    let r = http
        .post(format!("{base}/api/v1/runs"))
        .bearer_auth(token.trim())
        .json(
            &json!({"sample": "corduroy", "plan": viewer_plan(), "frame_size": [512, 384],
                      "operator": "viewer-test"}),
        )
        .send()
        .await
        .expect("POST /runs");
    let status = r.status().as_u16();
    let created: Value = r.json().await.unwrap_or(Value::Null);
    assert_eq!(status, 201, "{created}");
    let run_id = created["id"].as_str().expect("run id").to_string();
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let (_, v) = get_json(&http, &format!("{base}/api/v1/runs/{run_id}")).await;
        if v["state"] == "completed" {
            assert_eq!(v["processed"], Value::Null, "nothing processed yet");
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the capture did not complete: {v}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let run = data.path().join("runs").join(&run_id);
    let (status, v) = get_json(&http, &format!("{base}/api/v1/runs/{run_id}/btf")).await;
    assert_eq!(status, 404, "an unprocessed run has no BTF: {v}");
    assert!(
        v["detail"]
            .as_str()
            .is_some_and(|d| d.contains("rigd process btf")),
        "{v}"
    );
    // A second run holding a photometric-stereo result: bumps on a
    // two-tone albedo, written where `rigd process photometric-stereo RUN`
    // writes.
    let r = http
        .post(format!("{base}/api/v1/runs"))
        .bearer_auth(token.trim())
        .json(&json!({"sample": "bumps", "plan": {"name": "one", "directions": [{"theta_deg": 0, "phi_deg": 0}]},
                      "frame_size": [64, 48], "operator": "viewer-test"}))
        .send()
        .await
        .expect("POST /runs");
    let created: Value = r.json().await.unwrap_or(Value::Null);
    let ps_id = created["id"].as_str().expect("run id").to_string();
    write_bump_maps(&data.path().join("runs").join(&ps_id));

    let client = chromium(&mut procs, &out, profile_dir.path(), "1200,900").await;
    let result = AssertUnwindSafe(view_and_compare(
        &client,
        &base,
        token.trim(),
        (&run_id, &run),
        &ps_id,
        (data.path(), &out),
    ))
    .catch_unwind()
    .await;
    end_session(client, procs, result, &out.join("viewer-failure.png")).await;
    eprintln!("viewer test: {:.1} s", started.elapsed().as_secs_f64());
}

async fn view_and_compare(
    c: &Client,
    base: &str,
    token: &str,
    (run_id, run): (&str, &Path),
    ps_id: &str,
    (data, out): (&Path, &Path),
) {
    // From the run history to the viewer.
    c.goto(&format!("{base}/"))
        .await
        .expect("open the dashboard");
    enter_token(c, token).await;
    // Processing through the dashboard: the run's Process button queues
    // the daemon's default steps (rectify, btf), a bar follows them, and
    // the viewer link appears when they are done.
    let row = format!("#history tr[data-run-id='{run_id}']");
    let button = format!("{row} [data-testid=process]");
    wait_js(
        c,
        "the Process button in the run history",
        20,
        &format!("return !!document.querySelector(\"{button}\")"),
        |v| v == &json!(true),
    )
    .await;
    click_css(c, &button, "the Process button").await;
    let bar_seen = wait_js(
        c,
        "the processing bar or the result",
        30,
        &format!(
            "const r = document.querySelector(\"{row} [data-testid=processing]\"); \
             return r ? (r.querySelector('progress') ? 'bar' : r.textContent) : ''"
        ),
        |v| v == &json!("bar") || v == &json!("processed"),
    )
    .await;
    eprintln!("after Process: {bar_seen}");
    let png = c.screenshot().await.expect("screenshot");
    std::fs::write(out.join("dashboard-processing.png"), png).expect("write the screenshot");
    let link = format!("{row} [data-testid=open-viewer]");
    wait_js(
        c,
        "the viewer link in the run history",
        240,
        &format!("return !!document.querySelector(\"{link}\")"),
        |v| v == &json!(true),
    )
    .await;
    click_css(c, &link, "the viewer link").await;
    wait_viewer(c).await;
    let path = js(c, "return location.pathname").await;
    assert_eq!(path, json!(format!("/viewer/{run_id}")));
    // Fixed size for the comparison.
    c.goto(&format!("{base}/viewer/{run_id}?size={VIEWER_SIZE}"))
        .await
        .expect("viewer at a fixed size");
    wait_viewer(c).await;

    // The viewer agrees with the reference renderer, on every mesh and at
    // the hard cases: the pole view, a grazing light, the φ wrap.
    let cases = [
        ("flat", (40.0, 30.0), (35.0, 270.0)),
        ("cylinder", (35.0, 100.0), (40.0, 250.0)),
        ("cloth", (50.0, 200.0), (30.0, 300.0)),
        ("flat", (30.0, 10.0), (0.0, 123.0)),
        ("flat", (85.0, 40.0), (30.0, 200.0)),
        ("flat", (45.0, 359.9), (40.0, 0.1)),
    ];
    let mut worst = 0.0f64;
    for (mesh, light, view) in cases {
        let (got, want) = viewer_case(c, run, mesh, light, view).await;
        let e = assert_near_reference(
            &got,
            &want.pixels,
            &format!("viewer vs reference, {mesh} light {light:?} view {view:?}"),
            out,
            "viewer",
        );
        worst = worst.max(e);
        if mesh == "flat" {
            // Lit everywhere on the sample: no black (or NaN) texel.
            let dark = want
                .covered
                .iter()
                .enumerate()
                .filter(|(i, &c)| c && got[3 * i] == 0)
                .count();
            assert_eq!(
                dark, 0,
                "{light:?} {view:?}: black pixels on the lit sample"
            );
        }
    }
    eprintln!("viewer vs reference: worst RMS {worst:.2} levels (bound {VIEWER_RMS_BOUND})");
    // The flat sample from straight above tiles the material 2 × 2: its
    // tiles meet in a cross through the centre. The daemon's processing
    // blends the textures' edges, so no seam shows there.
    let (got, want) = viewer_case(c, run, "flat", (0.0, 0.0), (0.0, 0.0)).await;
    assert_near_reference(
        &got,
        &want.pixels,
        "viewer vs reference, tiles from above",
        out,
        "viewer-tiles",
    );
    let seam = tile_seam(&got, &want.covered, VIEWER_SIZE);
    eprintln!("tile seam: {seam:?}");
    assert!(
        seam.edge <= seam.texture,
        "the tiles meet in a seam: a step of {:.2} levels across the {} tile edge against the texture's own {:.2}",
        seam.edge,
        if seam.across_columns { "vertical" } else { "horizontal" },
        seam.texture
    );
    let index: Value = serde_json::from_slice(
        &std::fs::read(run.join("processed/normtextures/index.json")).expect("index.json"),
    )
    .expect("index");
    assert_eq!(index["channels"], 3, "the Bayer camera's textures are RGB");
    // The viewer shows the corduroy's rust dye: red well above blue (by
    // 1.43 measured, on the display's levels, with the white sheen in).
    let (flat, _) = viewer_case(c, run, "flat", (30.0, 10.0), (0.0, 123.0)).await;
    let mean_channel =
        |c: usize| mean_of(&flat.iter().skip(c).step_by(3).copied().collect::<Vec<u8>>());
    let (red, blue) = (mean_channel(0), mean_channel(2));
    eprintln!("viewer colour: mean red {red:.1}, blue {blue:.1} levels");
    assert!(
        red > 1.25 * blue,
        "the viewer shows colour: red {red}, blue {blue}"
    );

    // Moving the light changes the image as the reference says: a lower
    // light darkens the flat sample by what the reference predicts.
    let (high, high_ref) = viewer_case(c, run, "flat", (20.0, 60.0), (35.0, 270.0)).await;
    let (low, low_ref) = viewer_case(c, run, "flat", (70.0, 60.0), (35.0, 270.0)).await;
    let change = mean_of(&high) - mean_of(&low);
    let change_ref = mean_of(&high_ref.pixels) - mean_of(&low_ref.pixels);
    eprintln!("light 20° → 70°: the viewer's mean falls {change:.1} levels, the reference's {change_ref:.1}");
    assert!(change_ref > 5.0, "the reference darkens: {change_ref}");
    assert!(
        (change - change_ref).abs() < 0.1 * change_ref + 1.0,
        "{change} vs {change_ref}"
    );

    // A light below the horizon: no light at all, not negative light.
    let (below, below_ref) = viewer_case(c, run, "flat", (100.0, 0.0), (35.0, 270.0)).await;
    let lit = below_ref
        .covered
        .iter()
        .enumerate()
        .filter(|(i, &c)| c && (below[3 * i] != 0 || below_ref.pixels[3 * i] != 0))
        .count();
    assert_eq!(lit, 0, "light from below the horizon lit {lit} pixels");

    // The mouse: dragging the image orbits the camera, the disk moves the light.
    let before = js(c, "return window.rigdViewer.state.view.slice()").await;
    let canvas = c.find(Locator::Id("canvas")).await.expect("#canvas");
    let drag = MouseActions::new("mouse".into())
        .then(PointerAction::MoveToElement {
            element: canvas.clone(),
            duration: None,
            x: -100,
            y: 0,
        })
        .then(PointerAction::Down {
            button: MOUSE_BUTTON_LEFT,
        })
        .then(PointerAction::MoveBy {
            duration: Some(Duration::from_millis(100)),
            x: 60,
            y: -30,
        })
        .then(PointerAction::Up {
            button: MOUSE_BUTTON_LEFT,
        });
    c.perform_actions(drag).await.expect("drag the image");
    let after = js(c, "return window.rigdViewer.state.view.slice()").await;
    assert_ne!(before, after, "dragging the image orbits the camera");
    let disk = c
        .find(Locator::Id("light-disk"))
        .await
        .expect("#light-disk");
    let click = MouseActions::new("mouse".into())
        .then(PointerAction::MoveToElement {
            element: disk,
            duration: None,
            x: 30,
            y: -20,
        })
        .then(PointerAction::Down {
            button: MOUSE_BUTTON_LEFT,
        })
        .then(PointerAction::Up {
            button: MOUSE_BUTTON_LEFT,
        });
    c.perform_actions(click)
        .await
        .expect("click the light disk");
    let light = js(c, "return window.rigdViewer.state.light.slice()").await;
    let (theta, phi) = (
        light[0].as_f64().unwrap_or(-1.0),
        light[1].as_f64().unwrap_or(-1.0),
    );
    // 30 px right and 20 px up of the centre of a 60 px horizon radius.
    assert!(
        (theta - 54.1).abs() < 3.0 && (phi - 33.7).abs() < 3.0,
        "light {light}"
    );

    // Environment light and the cloth: renders, no error.
    js(c, "window.rigdViewer.ready = false; window.rigdViewer.setMesh('cloth').then(() => window.rigdViewer.setMode('env')).then(() => { window.rigdViewer.ready = true; }); return 0").await;
    wait_js(
        c,
        "environment mode",
        30,
        "return window.rigdViewer.ready",
        |v| v == &json!(true),
    )
    .await;
    let env = viewer_pixels(c).await;
    assert!(
        mean_of(&env) > 40.0,
        "the sky lights the cloth: mean {}",
        mean_of(&env)
    );
    assert_eq!(js(c, "return window.rigdViewer.error").await, Value::Null);
    js(c, "window.rigdViewer.setMode('point'); return 0").await;
    let fps = js(c, "return window.rigdViewer.benchmark(10)").await;
    eprintln!(
        "viewer frame rate under software GL: {:.1} frames/s ({VIEWER_SIZE}² per half, cloth, point light)",
        fps.as_f64().unwrap_or(0.0)
    );
    let png = c.screenshot().await.expect("screenshot");
    std::fs::write(out.join("viewer.png"), png).expect("write the screenshot");

    // A photometric-stereo run: the bump-mapped view of Spence et al..
    c.goto(&format!(
        "{base}/viewer/{ps_id}?size={VIEWER_SIZE}&mesh=flat&view=0,0&light=40,0"
    ))
    .await
    .expect("viewer of the photometric-stereo run");
    wait_viewer(c).await;
    assert_eq!(
        js(c, "return window.rigdViewer.kind").await,
        json!("photometric-stereo")
    );
    let east = viewer_pixels(c).await;
    js(c, "window.rigdViewer.setLight(40, 180); return 0").await;
    let west = viewer_pixels(c).await;
    // The bumps' east faces are lit from the east, their west faces from
    // the west: the images differ although the flat sample's cosine is the
    // same.
    let e = rms(&east, &west);
    eprintln!("photometric-stereo bumps lit from east vs west: RMS {e:.1} levels");
    assert!(e > 5.0, "bump mapping shows: RMS {e}");
    assert!((mean_of(&east) - mean_of(&west)).abs() < 3.0);
    let png = c.screenshot().await.expect("screenshot");
    std::fs::write(out.join("viewer-ps.png"), png).expect("write the screenshot");

    // The dashboard shows the trade-off plot the daemon serves.
    c.goto(&format!("{base}/"))
        .await
        .expect("the dashboard again");
    wait_js(
        c,
        "the trade-off card's hint",
        20,
        "return document.getElementById('tradeoff-caption').textContent",
        |v| v.as_str().is_some_and(|t| t.contains("rigd tradeoff")),
    )
    .await;
    let report = write_tradeoff_report(data);
    c.refresh().await.expect("reload the dashboard");
    let shown = wait_js(
        c,
        "the trade-off figure",
        20,
        "const p = document.getElementById('tradeoff-plot'); \
         return !p.hidden && p.querySelectorAll('.tradeoff-hit').length > 0 ? \
           document.getElementById('tradeoff-caption').textContent : null",
        |v| v.is_string(),
    )
    .await;
    let rows = report["rows"].as_array().expect("rows").len();
    assert!(
        shown
            .as_str()
            .is_some_and(|t| t.contains(&format!("{rows} rows"))),
        "{shown}"
    );
    // The knee sentences the report computed, under the plot.
    let knee = report["summary"][0].as_str().expect("a summary line");
    assert!(knee.starts_with("How many directions?"), "{knee}");
    assert!(shown.as_str().is_some_and(|t| t.contains(knee)), "{shown}");
    // One panel per family, each with its own question and its own unit.
    let texts = js(
        c,
        "return [...document.querySelectorAll('#tradeoff-plot svg text')].map(t => t.textContent.trim())",
    )
    .await;
    let texts: Vec<&str> = texts
        .as_array()
        .expect("texts")
        .iter()
        .filter_map(Value::as_str)
        .collect();
    for (family, title, unit) in [
        ("plans", "How many directions?", "held-out error, %"),
        ("pca", "How many PCA components?", "held-out error, %"),
        (
            "laser",
            "How many laser sources?",
            "depth error on common pixels, mm",
        ),
        (
            "photometric stereo",
            "How many lights?",
            "mean normal error, °",
        ),
        (
            "fidelity",
            "Which effects matter?",
            "frame change without it, %",
        ),
        (
            "exposure",
            "Which exposures?",
            "held-out error within 10° of the mirror, %",
        ),
    ] {
        assert_eq!(
            texts.iter().filter(|t| t.starts_with(title)).count(),
            1,
            "{family}: one panel titled {title:?} in {texts:?}"
        );
        assert!(
            texts.contains(&unit),
            "{family}: axis {unit:?} in {texts:?}"
        );
    }
    // The laser subsets reach different shares of the sample: coverage has
    // its own axis.
    assert!(
        texts.contains(&"coverage of the sample, % (×)"),
        "{texts:?}"
    );
    // No two texts of the figure overlap on screen: point labels, ticks,
    // titles, axis names and legend alike, by the browser's own boxes.
    let overlaps = js(
        c,
        "const b = [...document.querySelectorAll('#tradeoff-plot svg text')] \
           .filter(t => t.textContent.trim()) \
           .map(t => [t.textContent.trim(), t.getBoundingClientRect()]); \
         const out = []; \
         for (let i = 0; i < b.length; i++) for (let j = i + 1; j < b.length; j++) { \
           const [p, r] = b[i], [q, s] = b[j]; \
           const w = Math.min(r.right, s.right) - Math.max(r.left, s.left); \
           const h = Math.min(r.bottom, s.bottom) - Math.max(r.top, s.top); \
           if (w > 0.5 && h > 0.5) out.push(`${p} / ${q}`); } \
         return [b.length, out];",
    )
    .await;
    eprintln!(
        "trade-off figure: {} texts, overlapping: {}",
        overlaps[0], overlaps[1]
    );
    assert!(overlaps[0].as_u64().unwrap_or(0) > 40, "{overlaps}");
    assert_eq!(overlaps[1], json!([]), "texts overlap: {overlaps}");
    // Hovering a point shows its values.
    js(
        c,
        "document.getElementById('tradeoff-plot').scrollIntoView(); return 0",
    )
    .await;
    let point = |setting: &str| {
        format!("#tradeoff-plot .tradeoff-hit.point[data-family='plans'][data-setting='{setting}']")
    };
    let hit = c
        .find(Locator::Css(&point("h2, 4 rings")))
        .await
        .expect("the 4-ring point's hit target");
    let moved = MouseActions::new("mouse".into()).then(PointerAction::MoveToElement {
        element: hit,
        duration: None,
        x: 0,
        y: 0,
    });
    c.perform_actions(moved)
        .await
        .expect("hover the 4-ring point");
    let tip = wait_js(
        c,
        "the point's tooltip",
        10,
        "const t = document.getElementById('tradeoff-tip'); return t.hidden ? null : t.textContent",
        |v| v.is_string(),
    )
    .await;
    let four = report["rows"]
        .as_array()
        .and_then(|r| r.iter().find(|r| r["setting"] == "h2, 4 rings"))
        .expect("the 4-ring row");
    let error = format!("{:.1}", 100.0 * four["error"].as_f64().expect("its error"));
    let tip = tip.as_str().unwrap_or_default();
    assert!(tip.contains("plans: h2, 4 rings"), "{tip}");
    assert!(tip.contains(&format!("error {error} ±")), "{tip} / {error}");
    assert!(tip.contains("images"), "{tip}");
    let png = c.screenshot().await.expect("screenshot");
    std::fs::write(out.join("dashboard-tradeoff.png"), png).expect("write the screenshot");
    // Clicking a plan puts it into the start form with its time and volume.
    click_css(c, &point("h2, 4 rings"), "the 4-ring point").await;
    let form = js(
        c,
        "return [document.getElementById('plan').value, \
                 document.getElementById('custom-dirs').value.trim().split('\\n').length, \
                 document.getElementById('plan-info').textContent]",
    )
    .await;
    assert_eq!(form[0], json!("__custom"), "{form}");
    assert_eq!(form[1], json!(37), "the 4 rings' 37 directions: {form}");
    let info = form[2].as_str().unwrap_or_default();
    assert!(
        info.starts_with("From the trade-off: h2, 4 rings, 1369 images")
            && info.contains("physical")
            && info.contains("raw")
            && info.contains(&error),
        "{info}"
    );
    // A named plan is chosen by its name.
    if js(
        c,
        "const o = [...document.getElementById('plan').options].find(o => o.value === 'h2'); \
         return !!o && !o.disabled",
    )
    .await
        == json!(true)
    {
        // H1 and H2 coincide on this rig: the label takes the click.
        c.find(Locator::Css(
            "#tradeoff-plot .tradeoff-hit.label[data-family='plans'][data-setting='h2']",
        ))
        .await
        .expect("the h2 label")
        .click()
        .await
        .expect("click h2");
        assert_eq!(
            js(c, "return document.getElementById('plan').value").await,
            json!("h2")
        );
    }
    // A built-in plan's note in the start form states its raw data volume.
    let info = wait_js(
        c,
        "h1's note in the start form",
        20,
        "const s = document.getElementById('plan'); \
         const o = [...s.options].find(o => o.value === 'h1' && !o.disabled); \
         if (!o) return null; \
         s.value = 'h1'; s.dispatchEvent(new Event('change')); \
         return document.getElementById('plan-info').textContent",
        |v| v.is_string(),
    )
    .await;
    let info = info.as_str().unwrap_or_default();
    assert!(
        info.contains("6561 images") && info.contains("GB raw") && info.contains("MB an image"),
        "{info}"
    );
    // The scenes a report can be computed for, corduroy chosen.
    wait_js(
        c,
        "the trade-off scene choice",
        20,
        "const s = document.getElementById('tradeoff-scene'); \
         return s.options.length > 3 ? s.value : null",
        |v| v == "corduroy",
    )
    .await;
}

/// The Bonn corduroy report kept in `docs/tradeoff/` (every family, as
/// `rigd tradeoff` measured it), where `rigd tradeoff --out DATA/tradeoff`
/// puts it; its JSON.
fn write_tradeoff_report(data: &Path) -> Value {
    let kept = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("docs/tradeoff/bonn-gonioreflectometer-corduroy/tradeoff.json");
    let bytes = std::fs::read(&kept).expect("the kept Bonn corduroy report");
    let dir = data.join("tradeoff");
    std::fs::create_dir_all(&dir).expect("tradeoff dir");
    std::fs::write(dir.join("tradeoff.json"), &bytes).expect("json");
    serde_json::from_slice(&bytes).expect("a report")
}

/// Albedo and normals of a field of bumps (32² texels), as
/// `rigd process photometric-stereo` writes them.
fn write_bump_maps(run: &Path) {
    let dir = rigd::store::processed::ps_dir(run);
    std::fs::create_dir_all(&dir).expect("processed/ps");
    let n = 32usize;
    let mut normals = Vec::with_capacity(n * n * 3);
    let mut albedo = Vec::with_capacity(n * n);
    for y in 0..n {
        for x in 0..n {
            let (u, v) = (x as f64 / n as f64, y as f64 / n as f64);
            let tau = std::f64::consts::TAU;
            // Height h = 0.15 sin(2πu·2) sin(2πv·2), gradients in texels' units.
            let p = 0.15 * 2.0 * tau * (2.0 * tau * u).cos() * (2.0 * tau * v).sin();
            let q = -0.15 * 2.0 * tau * (2.0 * tau * u).sin() * (2.0 * tau * v).cos();
            let len = (p * p + q * q + 1.0).sqrt();
            normals.extend([(-p / len) as f32, (-q / len) as f32, (1.0 / len) as f32]);
            albedo.push(if (x / 8 + y / 8) % 2 == 0 { 0.8 } else { 0.6 });
        }
    }
    rigd_process::npy::write_f32(&dir.join("normals.npy"), &[n, n, 3], &normals).expect("normals");
    rigd_process::npy::write_f32(&dir.join("albedo.npy"), &[n, n], &albedo).expect("albedo");
}

fn write_rgb(path: &Path, size: usize, rgb: &[u8]) {
    let file = File::create(path).expect("create png");
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), size as u32, size as u32);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().expect("png header");
    w.write_image_data(rgb).expect("png data");
}

// ------------------------------------------------------- several rigs

/// Slow enough that both runs are still capturing when B is paused and
/// killed: 64 images take about half a minute.
const PEERS_SPEED: &str = "30";

/// The 64-image run of [`DIRECTIONS`], as an API body.
fn directions_run(sample: &str) -> Value {
    let dirs: Vec<Value> = DIRECTIONS
        .lines()
        .map(|l| {
            let mut it = l
                .split_whitespace()
                .map(|x| x.parse::<f64>().expect("degrees"));
            json!({"theta_deg": it.next(), "phi_deg": it.next()})
        })
        .collect();
    json!({"sample": sample, "plan": {"name": "dirs", "directions": dirs},
           "frame_size": [32, 24], "operator": "peers-test"})
}

async fn start_run_on(http: &reqwest::Client, base: &str, token: &str, sample: &str) -> String {
    let r = http
        .post(format!("{base}/api/v1/runs"))
        .bearer_auth(token)
        .json(&directions_run(sample))
        .send()
        .await
        .expect("POST /runs");
    let status = r.status().as_u16();
    let v: Value = r.json().await.unwrap_or(Value::Null);
    assert_eq!(status, 201, "start a run on {base}: {v}");
    v["id"].as_str().expect("run id").to_string()
}

/// Frames done of a run, by its daemon's API.
async fn frames_done(http: &reqwest::Client, base: &str, id: &str) -> (u64, Value) {
    let (status, v) = get_json(http, &format!("{base}/api/v1/runs/{id}")).await;
    assert_eq!(status, 200, "{v}");
    (v["steps_done"].as_u64().expect("steps_done"), v)
}

/// A's row script: `[reachable, state, frames done, error]` of a rig's row
/// in the "Rigs" card, or null while it has none.
fn rig_row(name: &str) -> String {
    format!(
        "const r = document.querySelector(\"#rigs tr[data-peer='{name}']\"); \
         if (!r || document.getElementById('rigs-card').hidden) return null; \
         const q = (t) => r.querySelector(`[data-testid=${{t}}]`); \
         return [r.dataset.reachable, q('peer-state') ? q('peer-state').textContent : null, \
                 Number(q('peer-run').dataset.done || -1), q('peer-error') ? q('peer-error').textContent : null]"
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_dashboard_shows_every_rig_and_a_dead_one_blocks_nothing() {
    let _one_browser = ONE_BROWSER.lock().await;
    let started = Instant::now();
    let out = out_dir();
    let data_a = tempfile::tempdir().expect("tempdir");
    let data_b = tempfile::tempdir().expect("tempdir");
    let conf = tempfile::tempdir().expect("tempdir");
    let profile_dir = tempfile::tempdir().expect("tempdir");
    let mut procs = Procs { children: vec![] };
    let http = reqwest::Client::new();

    // B: a rig of its own; A lists B in its peers file, with B's token.
    let (port_a, port_b) = (free_port(), free_port());
    let (base_a, base_b) = (
        format!("http://127.0.0.1:{port_a}"),
        format!("http://127.0.0.1:{port_b}"),
    );
    spawn_rig(
        &mut procs,
        "rigd-b",
        (data_b.path(), port_b, PEERS_SPEED),
        &[],
        &out.join("rigd-peer-b.log"),
    );
    wait_http(&http, &format!("{base_b}/api/v1/health"), "daemon B", 30).await;
    let token_b = std::fs::read_to_string(data_b.path().join("token")).expect("B's token");
    std::fs::copy(data_b.path().join("token"), conf.path().join("b.token")).expect("copy");
    let peers = conf.path().join("peers.toml");
    std::fs::write(
        &peers,
        format!("[[peer]]\nname = \"rig-b\"\nurl = \"{base_b}\"\ntoken_file = \"b.token\"\n"),
    )
    .expect("peers file");
    spawn_rig(
        &mut procs,
        "rigd-a",
        (data_a.path(), port_a, PEERS_SPEED),
        &["--peers", peers.to_str().expect("utf-8 path")],
        &out.join("rigd-peer-a.log"),
    );
    wait_http(&http, &format!("{base_a}/api/v1/health"), "daemon A", 30).await;
    let token_a = std::fs::read_to_string(data_a.path().join("token")).expect("A's token");

    let client = chromium(&mut procs, &out, profile_dir.path(), "1400,1000").await;
    let ctx = PeersCtx {
        base_a: &base_a,
        base_b: &base_b,
        token_a: token_a.trim(),
        token_b: token_b.trim(),
        http: &http,
        out: &out,
    };
    let result = AssertUnwindSafe(operate_rigs(&client, &ctx, &mut procs))
        .catch_unwind()
        .await;
    end_session(client, procs, result, &out.join("peers-failure.png")).await;
    eprintln!("peers test: {:.1} s", started.elapsed().as_secs_f64());
}

struct PeersCtx<'a> {
    base_a: &'a str,
    base_b: &'a str,
    token_a: &'a str,
    token_b: &'a str,
    http: &'a reqwest::Client,
    out: &'a Path,
}

async fn operate_rigs(c: &Client, ctx: &PeersCtx<'_>, procs: &mut Procs) {
    let (base_a, base_b, http) = (ctx.base_a, ctx.base_b, ctx.http);
    c.goto(&format!("{base_a}/"))
        .await
        .expect("open A's dashboard");
    enter_token(c, ctx.token_a).await;
    // Both rigs in the "Rigs" card, B reachable and idle.
    let names = wait_js(
        c,
        "both rigs listed, B reachable",
        10,
        "const card = document.getElementById('rigs-card'); \
         const rows = [...document.querySelectorAll('#rigs tbody tr')]; \
         return card.hidden ? null : rows.map(r => [r.dataset.peer, r.dataset.reachable])",
        |v| v == &json!([["this rig", "true"], ["rig-b", "true"]]),
    )
    .await;
    eprintln!("rigs listed: {names}");
    let open = js(
        c,
        "return document.querySelector(\"#rigs tr[data-peer='rig-b'] [data-testid=peer-open]\").getAttribute('href')",
    )
    .await;
    assert_eq!(open, json!(format!("{base_b}/")), "B's own dashboard");
    assert_eq!(
        js(
            c,
            "return document.querySelectorAll(\"#rigs tr[data-peer='this rig'] button\").length"
        )
        .await,
        json!(0),
        "this rig's own run is driven from its own card"
    );

    // A run on each rig; A's dashboard shows both progressing.
    let id_b = start_run_on(http, base_b, ctx.token_b, "felt-on-b").await;
    let id_a = start_run_on(http, base_a, ctx.token_a, "felt-on-a").await;
    let row_b = wait_js(
        c,
        "B's run progressing in A's dashboard",
        30,
        &rig_row("rig-b"),
        |v| v[0] == "true" && v[1] == "running" && v[2].as_i64().is_some_and(|n| n >= 1),
    )
    .await;
    let row_a = wait_js(
        c,
        "A's own run in the Rigs card",
        30,
        &rig_row("this rig"),
        |v| v[1] == "running" && v[2].as_i64().is_some_and(|n| n >= 1),
    )
    .await;
    eprintln!("rows: A {row_a}, B {row_b}");
    let shown = js(
        c,
        "return document.querySelector(\"#rigs tr[data-peer='rig-b'] [data-testid=peer-run]\").textContent",
    )
    .await;
    assert!(
        shown
            .as_str()
            .is_some_and(|t| t.contains(&id_b) && t.contains("/ 64 frames")),
        "B's run in A's dashboard: {shown}"
    );

    // Pause B's run from A's dashboard: B's own API says paused.
    let pause = "#rigs tr[data-peer='rig-b'] [data-testid=peer-pause]";
    wait_js(
        c,
        "B's Pause button enabled",
        10,
        &format!("const b = document.querySelector(\"{pause}\"); return !!b && !b.disabled"),
        |v| v == &json!(true),
    )
    .await;
    click_css(c, pause, "Pause on B's row").await;
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        let (_, v) = frames_done(http, base_b, &id_b).await;
        if v["state"] == "paused" {
            break;
        }
        assert!(Instant::now() < deadline, "B's run never paused: {v}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    wait_js(c, "B paused in A's dashboard", 10, &rig_row("rig-b"), |v| {
        v[1] == "paused"
    })
    .await;
    let (_, a_run) = frames_done(http, base_a, &id_a).await;
    assert_eq!(a_run["state"], "running", "A's run is A's own: {a_run}");
    let png = c.screenshot().await.expect("screenshot");
    std::fs::write(ctx.out.join("peers-paused.png"), png).expect("write the screenshot");

    // B dies. A shows it unreachable within 5 s of the kill, and its own
    // run keeps capturing.
    let (before, _) = frames_done(http, base_a, &id_a).await;
    procs.kill("rigd-b");
    let killed = Instant::now();
    let row = wait_js(
        c,
        "B unreachable in A's dashboard",
        5,
        &rig_row("rig-b"),
        |v| v[0] == "false",
    )
    .await;
    let took = killed.elapsed();
    eprintln!(
        "B unreachable in A's dashboard {:.2} s after the kill: {}",
        took.as_secs_f64(),
        row[3]
    );
    assert!(took <= Duration::from_secs(5), "{took:?}");
    assert!(
        row[3]
            .as_str()
            .is_some_and(|t| t.contains("cannot connect") || t.contains("connection")),
        "{row}"
    );
    let badge = js(
        c,
        "return document.querySelector(\"#rigs tr[data-peer='rig-b'] [data-testid=peer-reachable]\").textContent",
    )
    .await;
    assert_eq!(badge, json!("unreachable"));
    let deadline = Instant::now() + Duration::from_secs(20);
    let after = loop {
        let (n, v) = frames_done(http, base_a, &id_a).await;
        assert!(
            ["running", "completed"].contains(&v["state"].as_str().unwrap_or("")),
            "A's run after B died: {v}"
        );
        if n > before {
            break n;
        }
        assert!(
            Instant::now() < deadline,
            "A's run stopped at {before} frames: {v}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    eprintln!("A's run: {before} frames at the kill, {after} after");
    wait_js(
        c,
        "A's progress shown after B died",
        10,
        &rig_row("this rig"),
        |v| {
            v[2].as_i64().is_some_and(|n| n > before as i64)
                || v[1] == "completed"
                || v[1] == "idle"
        },
    )
    .await;
    // A's dashboard itself is live and B's row stays unreachable.
    assert_eq!(js(c, CONN).await, json!("live"));
    let png = c.screenshot().await.expect("screenshot");
    let path = ctx.out.join("peers.png");
    std::fs::write(&path, &png).expect("write the screenshot");
    check_png(&png);
    eprintln!("screenshot: {}", path.display());
}

/// The script that reads the history rows: `[id, sample, state, plan]`.
const HISTORY_ROWS: &str = "return [...document.querySelectorAll('#history tbody tr')]\
    .map(tr => [tr.dataset.runId, tr.children[1].textContent, tr.dataset.state, tr.children[2].textContent])";
const HISTORY_POS: &str = "return document.getElementById('history-pos').textContent";

/// The history card over more runs than a page: one real run's record is
/// copied under 120 ids before the daemon starts; the dashboard shows 50
/// at a time, pages older and newer, and searches by sample, state and
/// plan (each a query of the daemon, never the whole history).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_pages_and_searches_a_long_history() {
    let _one_browser = ONE_BROWSER.lock().await;
    let out = out_dir();
    let data = tempfile::tempdir().expect("tempdir");
    let profile_dir = tempfile::tempdir().expect("tempdir");
    let mut procs = Procs { children: vec![] };
    let http = reqwest::Client::new();

    // One small real run, then its record copied.
    let port = free_port();
    let base = format!("http://127.0.0.1:{port}");
    let log = out.join("history-rigd.log");
    spawn_daemon(&mut procs, data.path(), port, "5000", None, &log);
    wait_http(&http, &format!("{base}/api/v1/health"), "the daemon", 30).await;
    let token = std::fs::read_to_string(data.path().join("token")).expect("token file");
    let token = token.trim().to_string();
    let r = http
        .post(format!("{base}/api/v1/runs"))
        .bearer_auth(&token)
        .json(&json!({"sample": "seed", "frame_size": [16, 12], "operator": "tester",
                      "plan": {"name": "mini", "directions": [{"theta_deg": 10.0, "phi_deg": 0.0}]}}))
        .send()
        .await
        .expect("POST /runs");
    let v: Value = r.json().await.unwrap_or(Value::Null);
    let seed = v["id"]
        .as_str()
        .unwrap_or_else(|| panic!("{v}"))
        .to_string();
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (_, v) = get_json(&http, &format!("{base}/api/v1/runs/{seed}")).await;
        if v["state"] == "completed" && v["active"] == false {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the seed run never completed: {v}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    procs.stop("rigd");
    let runs_dir = data.path().join("runs");
    let copies = common::history::clone_runs(&runs_dir.join(&seed), &runs_dir, 120);
    std::fs::remove_dir_all(runs_dir.join(&seed)).expect("remove the seed run");
    let all = common::history::newest_first(&copies);
    spawn_daemon(&mut procs, data.path(), port, "5000", None, &log);
    wait_http(&http, &format!("{base}/api/v1/health"), "the daemon", 30).await;

    let client = chromium(&mut procs, &out, profile_dir.path(), "1400,1500").await;
    let result = AssertUnwindSafe(async {
        history_card(&client, &base, &token, &all).await;
    })
    .catch_unwind()
    .await;
    end_session(client, procs, result, &out.join("history-failure.png")).await;
}

async fn history_card(c: &Client, base: &str, token: &str, all: &[common::history::Cloned]) {
    c.goto(&format!("{base}/"))
        .await
        .expect("open the dashboard");
    enter_token(c, token).await;
    let ids = |v: &Value| -> Vec<String> {
        v.as_array()
            .map(|rows| {
                rows.iter()
                    .map(|r| r[0].as_str().unwrap_or("").to_string())
                    .collect()
            })
            .unwrap_or_default()
    };
    let want = |from: usize, to: usize| -> Vec<String> {
        all[from..to].iter().map(|r| r.id.clone()).collect()
    };
    // The first page: the 50 newest.
    let rows = wait_js(c, "the first page", 30, HISTORY_ROWS, |v| {
        v.as_array().is_some_and(|a| a.len() == 50)
    })
    .await;
    assert_eq!(ids(&rows), want(0, 50));
    assert_eq!(js(c, HISTORY_POS).await, json!("1–50 of 120"));
    assert_eq!(
        js(c, "return document.getElementById('history-prev').disabled").await,
        json!(true)
    );
    // Older, older (the last 20), newer.
    click_id(c, "history-next").await;
    let rows = wait_js(c, "the second page", 10, HISTORY_ROWS, |v| {
        v[0][0].as_str() == Some(all[50].id.as_str())
    })
    .await;
    assert_eq!(ids(&rows), want(50, 100));
    assert_eq!(js(c, HISTORY_POS).await, json!("51–100 of 120"));
    click_id(c, "history-next").await;
    let rows = wait_js(c, "the last page", 10, HISTORY_ROWS, |v| {
        v.as_array().is_some_and(|a| a.len() == 20)
    })
    .await;
    assert_eq!(ids(&rows), want(100, 120));
    assert_eq!(
        js(c, "return document.getElementById('history-next').disabled").await,
        json!(true)
    );
    click_id(c, "history-prev").await;
    let rows = wait_js(c, "the second page again", 10, HISTORY_ROWS, |v| {
        v.as_array().is_some_and(|a| a.len() == 50)
    })
    .await;
    assert_eq!(ids(&rows), want(50, 100));

    // A search by sample, typed, from the first page on.
    let search = c
        .find(Locator::Id("history-sample"))
        .await
        .expect("#history-sample");
    search.send_keys("LEATH").await.expect("type a search");
    let leather: Vec<String> = all
        .iter()
        .filter(|r| r.sample == "Leather")
        .map(|r| r.id.clone())
        .collect();
    let rows = wait_js(c, "the search's runs", 10, HISTORY_ROWS, |v| {
        v.as_array().is_some_and(|a| a.len() == leather.len())
    })
    .await;
    assert_eq!(ids(&rows), leather);
    assert_eq!(js(c, HISTORY_POS).await, json!(format!("1–24 of 24")));
    // And by state and plan.
    js(
        c,
        "const s = document.getElementById('history-state'); s.value = 'aborted'; \
         s.dispatchEvent(new Event('change')); return true",
    )
    .await;
    let plan = c
        .find(Locator::Id("history-plan"))
        .await
        .expect("#history-plan");
    plan.send_keys("dome").await.expect("type a plan");
    let both: Vec<String> = all
        .iter()
        .filter(|r| r.sample == "Leather" && r.state == "aborted" && r.plan == "dome")
        .map(|r| r.id.clone())
        .collect();
    assert!(!both.is_empty());
    let rows = wait_js(c, "the filtered runs", 10, HISTORY_ROWS, |v| ids(v) == both).await;
    for r in rows.as_array().expect("rows") {
        assert_eq!(
            (&r[1], &r[2], &r[3]),
            (&json!("Leather"), &json!("aborted"), &json!("dome"))
        );
    }
    let png = c.screenshot().await.expect("screenshot");
    std::fs::write(out_dir().join("history.png"), &png).expect("save history.png");
}
