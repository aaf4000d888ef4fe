//! The viewer's MDF silhouettes and shadows (Wang et al., §4) against the
//! reference renderer, on corduroy measured twice as a lab would: a small
//! BTF on the simulated Bonn rig, a laser scan of the same sample on the
//! simulated MSRA rig, `rigd process mdf` and `rigd process mdf-texture`
//! tying the two together.

use std::path::Path;
use std::process::Command;
use std::time::Instant;

use serde_json::{json, Value};

use super::{
    assert_near_reference, chromium, end_session, free_port, js, out_dir, rms, show_case,
    spawn_daemon, viewer_plan, wait_http, wait_js, wait_viewer, Procs, ONE_BROWSER,
    VIEWER_RMS_BOUND, VIEWER_SIZE,
};
use fantoccini::Client;
use futures::FutureExt;
use rigd_process::directions::Direction;
use rigd_process::relight::{RelightSettings, RgbImage};
use rigd_process::silhouette::{MesoSettings, SilhouetteReport};

/// Material tiles per world unit: one tile spans four units, so the
/// corduroy's 3 mm ridges are a few pixels apart on the meshes.
const DENSITY: f64 = 0.25;

fn rigd(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_rigd"))
        .args(args)
        .output()
        .expect("run rigd");
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "rigd {args:?}: {stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// An embedded profile with `edits` applied.
fn profile(dir: &Path, name: &str, edits: &[(&str, &str)]) -> String {
    let mut text = std::fs::read_to_string(crate::common::repo_file(&format!(
        "rig-profiles/{name}.toml"
    )))
    .expect("profile");
    for (from, to) in edits {
        assert!(text.contains(from), "{name}: {from}");
        text = text.replace(from, to);
    }
    let path = dir.join(format!("{name}-corduroy.toml"));
    std::fs::write(&path, text).expect("write the profile");
    path.to_str().expect("utf-8").to_string()
}

/// Captures and processes the two runs: the BTF in `data/runs/cord-btf`
/// (where the daemon finds it at start-up) with its MDF texture, from a
/// laser run kept outside.
fn capture(data: &Path, work: &Path) -> std::path::PathBuf {
    let started = Instant::now();
    let btf = data.join("runs").join("cord-btf");
    let btf_s = btf.to_str().expect("utf-8");
    let plan = work.join("viewer-plan.json");
    std::fs::write(&plan, viewer_plan().to_string()).expect("plan");
    // A monochrome camera: what this test measures is the mesostructure's
    // silhouettes and shadows, as on a grey BTF.
    let bonn = profile(
        work,
        "bonn-gonioreflectometer",
        &[
            (", cfa = \"RGGB\"", ""),
            ("[holder]\ncolour_patches = true\n", ""),
        ],
    );
    rigd(&[
        "run",
        "--sim",
        "--progress",
        "none",
        "--profile",
        &bonn,
        "--plan",
        plan.to_str().expect("utf-8"),
        "--frame-size",
        "512x384",
        "--sample",
        "corduroy",
        "--out",
        btf_s,
    ]);
    rigd(&[
        "process", "rectify", btf_s, "--size", "256", "--final", "128",
    ]);
    rigd(&["process", "btf", btf_s, "--components", "8"]);
    // The MSRA rig with four of its eight cameras, frames large enough for
    // the strip on 3 mm ridges.
    let msra = profile(
        work,
        "msra-btf-mdf",
        &[
            (
                r#"cameras = ["cam0", "cam1", "cam2", "cam3", "cam4", "cam5", "cam6", "cam7"]"#,
                r#"cameras = ["cam0", "cam2", "cam4", "cam6"]"#,
            ),
            (
                "[sim]\nframe_size = [64, 48]",
                "[sim]\nframe_size = [320, 240]\nzoom = 2.4\nscene = \"corduroy\"",
            ),
        ],
    );
    let laser = work.join("laser");
    let laser_s = laser.to_str().expect("utf-8");
    rigd(&[
        "run",
        "--sim",
        "--progress",
        "none",
        "--profile",
        &msra,
        "--plan",
        "laser:sources=2,turns=4,step=1.5",
        "--out",
        laser_s,
    ]);
    rigd(&["process", "mdf", laser_s]);
    let said = rigd(&["process", "mdf-texture", btf_s, "--laser", laser_s]);
    eprintln!("{}", said.trim());
    assert!(said.contains("16 views"), "{said}");
    // A steep view across the ridges (the best covered of θ ≤ 30°) sees
    // their relief below the top plane: the corduroy's ridges are 1.2 mm
    // high.
    let texture =
        rigd_process::mdf::MdfTexture::read(&btf.join("processed/mdf-texture")).expect("read");
    let header = texture.header();
    let n = header.size * header.size;
    let view = (0..header.views.len())
        .filter(|&v| header.views[v].theta_deg <= 30.0)
        .max_by(|&a, &b| header.coverage[a].total_cmp(&header.coverage[b]))
        .expect("a steep view");
    let mut depths: Vec<f32> = texture.depth_mm()[view * n..(view + 1) * n]
        .iter()
        .copied()
        .filter(|&d| d >= 0.0)
        .collect();
    depths.sort_by(f32::total_cmp);
    let quantile = |q: f64| depths[((depths.len() - 1) as f64 * q) as usize];
    let relief = quantile(0.95) - quantile(0.05);
    eprintln!(
        "MDF texture, view {:?} ({:.0} % measured): relief (5th to 95th percentile) {relief:.2} mm",
        header.views[view],
        100.0 * header.coverage[view]
    );
    assert!((0.5..1.6).contains(&relief), "relief {relief} mm");
    eprintln!(
        "corduroy BTF and laser scan captured and processed in {:.0} s",
        started.elapsed().as_secs_f64()
    );
    btf
}

fn reference(
    run: &Path,
    mesh: &str,
    light: (f64, f64),
    view: (f64, f64),
    size: usize,
    meso: MesoSettings,
) -> (RgbImage, Option<SilhouetteReport>) {
    let settings = RelightSettings {
        width: size,
        height: size,
        light: Direction::new(light.0, light.1),
        view: Direction::new(view.0, view.1),
        ..Default::default()
    };
    rigd::postprocess::viewer::render_run(run, mesh.parse().expect("mesh kind"), &settings, &meso)
        .expect("reference render")
}

const BOTH: MesoSettings = MesoSettings {
    silhouettes: true,
    shadows: true,
    density: DENSITY,
};
const NEITHER: MesoSettings = MesoSettings {
    silhouettes: false,
    shadows: false,
    density: DENSITY,
};

/// The acceptance check in the reference: on the corduroy cylinder the
/// background shows through between the ridges along both long edges of
/// the outline with the MDF, and nowhere without it.
fn reference_opens_the_cylinders_outline(run: &Path) {
    let (light, view) = ((40.0, 60.0), (60.0, 90.0));
    let (plain, none) = reference(run, "cylinder", light, view, 512, NEITHER);
    assert!(none.is_none());
    let silhouettes = MesoSettings {
        shadows: false,
        ..BOTH
    };
    let (img, report) = reference(run, "cylinder", light, view, 512, silhouettes);
    let report = report.expect("a report");
    let outline = plain.covered.iter().filter(|&&c| c).count();
    assert_eq!(report.outline_pixels, outline);
    let holes: Vec<usize> = (0..plain.covered.len())
        .filter(|&i| plain.covered[i] && !img.covered[i])
        .collect();
    let (upper, lower) = holes.iter().partition::<Vec<usize>, _>(|&&i| i / 512 < 256);
    eprintln!(
        "corduroy cylinder: outline {outline} px; background inside it: {} px with the MDF \
         ({} along the upper edge, {} along the lower), 0 without",
        holes.len(),
        upper.len(),
        lower.len()
    );
    assert_eq!(report.background_inside_outline, holes.len());
    assert!(
        upper.len() > 20 && lower.len() > 20,
        "upper {} lower {}",
        upper.len(),
        lower.len()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewer_draws_mdf_silhouettes_and_shadows_like_the_reference() {
    let _one_browser = ONE_BROWSER.lock().await;
    let started = Instant::now();
    let out = out_dir();
    let data = tempfile::tempdir().expect("tempdir");
    let work = tempfile::tempdir().expect("tempdir");
    let browser_profile = tempfile::tempdir().expect("tempdir");
    let run = capture(data.path(), work.path());
    reference_opens_the_cylinders_outline(&run);

    let mut procs = Procs { children: vec![] };
    let port = free_port();
    let base = format!("http://127.0.0.1:{port}");
    spawn_daemon(
        &mut procs,
        data.path(),
        port,
        "5000",
        None,
        &out.join("rigd-mdf-viewer.log"),
    );
    let http = reqwest::Client::new();
    wait_http(&http, &format!("{base}/api/v1/health"), "the daemon", 30).await;
    let manifest: Value = http
        .get(format!("{base}/api/v1/runs/cord-btf/mdf"))
        .send()
        .await
        .expect("GET mdf")
        .json()
        .await
        .expect("json");
    assert_eq!(manifest["views"], json!(16), "{manifest}");
    assert_eq!(manifest["depth"]["encoding"], json!("f32le"));
    let client = chromium(&mut procs, &out, browser_profile.path(), "1000,700").await;
    let result = std::panic::AssertUnwindSafe(compare(&client, &base, &run, &out))
        .catch_unwind()
        .await;
    end_session(client, procs, result, &out.join("mdf-viewer-failure.png")).await;
    eprintln!("MDF viewer test: {:.1} s", started.elapsed().as_secs_f64());
}

/// Sets the viewer to a case with both MDF modes on; its pixels and the
/// reference's.
async fn case(
    c: &Client,
    run: &Path,
    mesh: &str,
    light: (f64, f64),
    view: (f64, f64),
) -> (Vec<u8>, RgbImage, SilhouetteReport) {
    let got = show_case(c, mesh, light, view).await;
    let (want, report) = reference(run, mesh, light, view, VIEWER_SIZE, BOTH);
    (got, want, report.expect("a report"))
}

async fn compare(c: &Client, base: &str, run: &Path, out: &Path) {
    // An operator turns the modes on with the two toggles.
    c.goto(&format!(
        "{base}/viewer/cord-btf?size={VIEWER_SIZE}&density={DENSITY}&mesh=sphere"
    ))
    .await
    .expect("open the viewer");
    wait_viewer(c).await;
    for toggle in ["mdf-silhouettes", "mdf-shadows"] {
        wait_js(
            c,
            "the MDF toggles to be offered",
            30,
            &format!("return !document.querySelector('[data-testid={toggle}]').disabled"),
            |v| v == &json!(true),
        )
        .await;
        c.find(fantoccini::Locator::Css(&format!("[data-testid={toggle}]")))
            .await
            .expect("toggle")
            .click()
            .await
            .expect("click the toggle");
    }
    let state = js(
        c,
        "return [window.rigdViewer.state.silhouettes, window.rigdViewer.state.shadows]",
    )
    .await;
    assert_eq!(state, json!(["mdf", "mdf"]));
    // The same from the page's address.
    c.goto(&format!(
        "{base}/viewer/cord-btf?size={VIEWER_SIZE}&density={DENSITY}&silhouettes=mdf&shadows=mdf"
    ))
    .await
    .expect("open the viewer");
    wait_viewer(c).await;
    let state = js(
        c,
        "const v = window.rigdViewer; return [v.mdf, v.state.silhouettes, v.state.shadows]",
    )
    .await;
    assert_eq!(state, json!([true, "mdf", "mdf"]));
    // Closed and open meshes, the light moved over the cloth (its folds'
    // shadow silhouettes move), and the hard cases: a grazing view at the
    // outline, a light below the horizon.
    let cases = [
        ("sphere", (50.0, 30.0), (40.0, 250.0)),
        ("cylinder", (40.0, 60.0), (60.0, 90.0)),
        ("cloth", (70.0, 20.0), (40.0, 90.0)),
        ("cloth", (70.0, 200.0), (40.0, 90.0)),
        ("sphere", (40.0, 10.0), (89.0, 45.0)),
        ("cylinder", (120.0, 30.0), (50.0, 200.0)),
    ];
    let mut worst = 0.0f64;
    let mut cloth_shadows = Vec::new();
    for (mesh, light, view) in cases {
        let (got, want, report) = case(c, run, mesh, light, view).await;
        eprintln!(
            "reference, {mesh} light {light:?} view {view:?}: {} px background inside the \
             outline, {} px in cast shadow, {} layers",
            report.background_inside_outline, report.shadowed_pixels, report.layers_used
        );
        let e = assert_near_reference(
            &got,
            &want.pixels,
            &format!("MDF viewer vs reference, {mesh} light {light:?} view {view:?}"),
            out,
            "mdf-viewer",
        );
        worst = worst.max(e);
        if mesh == "cloth" {
            cloth_shadows.push((got, want, report.shadowed_pixels));
        }
    }
    // Moving the light moves the cast shadow, in both renderers.
    let [(got_a, want_a, shadow_a), (got_b, want_b, shadow_b)] = &cloth_shadows[..] else {
        panic!("two cloth cases");
    };
    assert!(*shadow_a > 100 && *shadow_b > 100, "{shadow_a} {shadow_b}");
    assert!(rms(&want_a.pixels, &want_b.pixels) > 5.0 && rms(got_a, got_b) > 5.0);
    eprintln!("MDF viewer vs reference: worst RMS {worst:.2} levels (bound {VIEWER_RMS_BOUND})");
    // The frame rate under software GL with depth peeling: a floor. Per
    // mode: frames per second and the peel passes of a frame.
    let fps = js(
        c,
        "const v = window.rigdViewer; return v.setMesh('sphere').then(() => { \
           const out = {}; \
           for (const [name, sil, sha] of [['none', 'none', 'none'], ['silhouettes', 'mdf', 'none'], \
                                           ['shadows', 'none', 'mdf'], ['both', 'mdf', 'mdf']]) { \
             v.setSilhouettes(sil); v.setShadows(sha); \
             out[name] = [Number(v.benchmark(4).toFixed(2)), v.peelPasses]; \
           } \
           return out; })",
    )
    .await;
    eprintln!(
        "MDF viewer under SwiftShader, sphere, {VIEWER_SIZE}² per half, [frames/s, peel passes]: {fps}"
    );
    assert_eq!(fps["both"][1], json!(8), "{fps}");
    assert_eq!(fps["none"][1], json!(0), "{fps}");
    let png = c.screenshot().await.expect("screenshot");
    std::fs::write(out.join("mdf-viewer.png"), png).expect("write the screenshot");
}
