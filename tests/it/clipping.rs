//! Highlights the sensor clipped are never taken as measured: a simulated
//! `leather` sample seen in its mirror direction clips at the profile's
//! exposure, and `rigd process rectify` counts the texels that read a
//! clipped pixel, writes their mask and names the frame and its
//! directions; the BTF compression fills them from the slot's
//! neighbouring lights and says how many; a matte sample under the same
//! lights clips nothing. With `--exposure-policy auto` the frames that clip
//! are taken again shorter and merged, so the highlight is measured above
//! full scale instead of clipped, and a matte sample costs no extra time.

use std::path::Path;

use crate::common::{repo_file, run_ok};

fn arg(p: &Path) -> String {
    p.to_str().expect("utf8").to_string()
}

/// Captures `scene` under three lights, the first (θ 34° φ 240°) seen in
/// its mirror direction, and from θ 60° φ 150°, and rectifies it; what
/// the rectify printed.
fn capture_and_rectify(dir: &Path, scene: &str) -> (std::path::PathBuf, String) {
    capture_and_rectify_with(dir, scene, "single")
}

/// [`capture_and_rectify`] under an exposure policy, into `dir/scene.policy`.
fn capture_and_rectify_with(dir: &Path, scene: &str, policy: &str) -> (std::path::PathBuf, String) {
    let run = dir.join(format!("{scene}.{policy}"));
    let plan = dir.join("plan.json");
    std::fs::write(
        &plan,
        r#"{"lights": [{"theta_deg": 34, "phi_deg": 240}, {"theta_deg": 60, "phi_deg": 300},
                       {"theta_deg": 15, "phi_deg": 120}],
            "views": [{"theta_deg": 34, "phi_deg": 60}, {"theta_deg": 60, "phi_deg": 150}]}"#,
    )
    .expect("plan");
    let profile = crate::common::bonn_monochrome(dir);
    run_ok(&[
        "run",
        "--sim",
        "--profile",
        &arg(&profile),
        "--scene",
        scene,
        "--frame-size",
        "320x240",
        "--plan",
        &arg(&plan),
        "--progress",
        "none",
        "--exposure-policy",
        policy,
        "--out",
        &arg(&run),
    ]);
    let out = run_ok(&["process", "rectify", &arg(&run)]);
    (run, String::from_utf8_lossy(&out.stdout).into_owned())
}

#[test]
fn texels_that_read_a_clipped_pixel_are_counted_masked_and_reported() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (run, printed) = capture_and_rectify(dir.path(), "leather");

    let textures = run.join("processed/normtextures");
    let index: serde_json::Value =
        serde_json::from_slice(&std::fs::read(textures.join("index.json")).expect("index"))
            .expect("json");
    let frames = index["frames"].as_array().expect("frames");
    let views = index["views"].as_array().expect("views");
    let lights = index["lights"].as_array().expect("lights");
    // The first light's frame from the view at `theta`.
    let of_view = |theta: f64| {
        frames
            .iter()
            .find(|f| {
                let slot = f["view_slot"].as_u64().expect("slot") as usize;
                let light = f["light_index"].as_u64().expect("light") as usize;
                views[slot]["theta_deg"].as_f64().map(f64::round) == Some(theta)
                    && lights[light]["phi_deg"].as_f64().map(f64::round) == Some(240.0)
            })
            .expect("the view's frame")
    };
    let mirror = of_view(34.0);
    let aside = of_view(60.0);

    // The mirror frame: its clipped texels counted, and masked where they
    // are, each of them bright in the texture.
    let clipped = mirror["clipped_texels"].as_u64().unwrap_or(0) as usize;
    assert!(
        clipped > 0,
        "the mirror highlight clips: {mirror}\n{printed}"
    );
    let mask_file = mirror["clipped_mask"].as_str().expect("a clip mask");
    let mask = rigd_process::image_io::load_png(&textures.join(mask_file)).expect("mask png");
    let marked: Vec<usize> = (0..mask.data.len())
        .filter(|&i| mask.data[i] > 0.5)
        .collect();
    assert_eq!(marked.len(), clipped, "the mask marks every counted texel");
    let share = mirror["clipped_share"].as_f64().expect("share");
    assert!((share - clipped as f64 / mask.data.len() as f64).abs() < 1e-9);
    let texture =
        rigd_process::image_io::load_png(&textures.join(mirror["file"].as_str().expect("texture")))
            .expect("texture png");
    let mean = |clipped: bool| {
        let (sum, n) = (0..texture.data.len())
            .filter(|&i| (mask.data[i] > 0.5) == clipped)
            .fold((0.0, 0usize), |(s, n), i| (s + texture.data[i], n + 1));
        sum / n.max(1) as f32
    };
    assert!(
        mean(true) > 1.2 * mean(false),
        "clipped texels are the highlight: {} against {} elsewhere",
        mean(true),
        mean(false)
    );
    // Away from the mirror, far fewer.
    let aside_share = aside["clipped_share"].as_f64().unwrap_or(0.0);
    assert!(share > 4.0 * aside_share, "{share} against {aside_share}");

    // The summary counts them and names where they are, the mirror first.
    let summary = &index["summary"];
    let total = frames
        .iter()
        .map(|f| f["clipped_texels"].as_u64().unwrap_or(0))
        .sum::<u64>();
    assert_eq!(summary["clipped_texels"].as_u64(), Some(total));
    let worst = &summary["most_clipped"][0];
    assert_eq!(worst["index"], mirror["index"]);
    assert_eq!(
        worst["view"]["phi_deg"].as_f64().map(f64::round),
        Some(60.0)
    );
    assert_eq!(
        worst["light"]["phi_deg"].as_f64().map(f64::round),
        Some(240.0)
    );
    assert!(
        printed.contains("clipped:") && printed.contains("view θ 34.0° φ 60.0°"),
        "{printed}"
    );

    // The BTF compression takes none of them as measured: each is filled
    // from the lights of its slot that did not clip there, or counted as
    // clipped under every light. With as many components as lights it
    // gives back its input, so where the mirror frame clipped the BTF
    // holds the fill (lower than the clipped reading), and elsewhere what
    // was measured.
    let out = run_ok(&["process", "btf", "--components", "3", &arg(&run)]);
    let printed = String::from_utf8_lossy(&out.stdout);
    let report: serde_json::Value = serde_json::from_slice(
        &std::fs::read(run.join("processed/btf/report.json")).expect("btf report"),
    )
    .expect("json");
    // The report's size is the BTF's files, not the report an earlier
    // compression left beside them: compressing again says the same.
    run_ok(&["process", "btf", "--components", "3", &arg(&run)]);
    let again = json(&run.join("processed/btf/report.json"));
    let files: u64 = std::fs::read_dir(run.join("processed/btf"))
        .expect("btf folder")
        .map(|e| e.expect("entry"))
        .filter(|e| e.file_name() != "report.json")
        .map(|e| e.metadata().expect("metadata").len())
        .sum();
    assert_eq!(again["bytes"].as_u64(), Some(files), "{again}");
    assert_eq!(report["bytes"], again["bytes"]);
    let (filled, left) = (
        report["clipped"]["filled"].as_u64().expect("filled"),
        report["clipped"]["left"].as_u64().expect("left"),
    );
    assert_eq!(filled + left, total, "{printed}");
    assert!(
        filled > 0 && printed.contains("clipped texels:"),
        "{printed}"
    );
    let btf = rigd_process::btf::CompressedBtf::read(&run.join("processed/btf")).expect("the BTF");
    let slot = mirror["view_slot"].as_u64().expect("slot") as usize;
    let light = mirror["light_index"].as_u64().expect("light") as usize;
    let stored = btf
        .reconstruct_measured(slot, light)
        .expect("reconstructed");
    let (mut lowered, mut kept) = (0usize, 0usize);
    for (i, (&value, &read)) in stored.iter().zip(&texture.data).enumerate() {
        let difference = value - read;
        if mask.data[i] > 0.5 {
            lowered += usize::from(difference < -0.02);
        } else {
            assert!(difference.abs() < 1e-3, "texel {i}: {difference}");
            kept += 1;
        }
    }
    assert!(kept > 0);
    assert!(
        lowered > clipped / 2,
        "{lowered} of {clipped} clipped texels replaced by lower values"
    );

    // A matte sample under the same light clips nothing, and its index
    // says nothing of clipping.
    let (matte, printed) = capture_and_rectify(dir.path(), "flat-calibration");
    let index =
        std::fs::read_to_string(matte.join("processed/normtextures/index.json")).expect("index");
    assert!(!index.contains("clipped_mask"), "{index}");
    assert!(index.contains("\"frames_clipped\": 0"), "{index}");
    assert!(!printed.contains("clipped:"), "{printed}");
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).expect("readable")).expect("json")
}

fn physical_s(run: &Path) -> f64 {
    json(&run.join("state.json"))["physical_s"]
        .as_f64()
        .expect("physical_s")
}

#[test]
fn auto_exposure_measures_the_highlight_where_a_single_exposure_clips() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (single, _) = capture_and_rectify(dir.path(), "leather");
    let (auto, printed) = capture_and_rectify_with(dir.path(), "leather", "auto");

    // Every frame of this plan clips at the profile's 0.25 s, so each took
    // a second exposure four times shorter, with its own file and hash.
    let journal = std::fs::read_to_string(auto.join("journal.ndjson")).expect("journal");
    let lines: Vec<serde_json::Value> = journal
        .lines()
        .map(|l| serde_json::from_str(l).expect("line"))
        .collect();
    assert_eq!(lines.len(), 6);
    for line in &lines {
        let brackets = line["brackets"].as_array().expect("brackets");
        assert_eq!(brackets.len(), 1, "{line}");
        assert_eq!(brackets[0]["exposure_s"].as_f64(), Some(0.0625), "{line}");
        let file = brackets[0]["file"].as_str().expect("file");
        let bytes = std::fs::read(auto.join(file)).expect("the bracket's file");
        assert_eq!(
            brackets[0]["sha256"].as_str(),
            Some(rigd::store::sha256_hex(&bytes).as_str())
        );
    }

    // The time model replays the engine's order (expose the next step, come
    // back, take the further exposures): with the retakes the journal
    // lists, it gives the run's physical time; without, a lower bound.
    let meta = rigd::store::read_meta(&auto).expect("meta");
    let solver = rigd::kinematics::Solver::new(&meta.profile).expect("solver");
    let schedule = rigd::schedule::build(&meta.profile, &solver, &meta.plan);
    let retakes: std::collections::HashMap<usize, u32> = lines
        .iter()
        .map(|l| {
            let trigger = l["trigger"].as_u64().expect("trigger") as usize;
            (trigger, l["brackets"].as_array().map_or(0, Vec::len) as u32)
        })
        .collect();
    let timing = rigd::schedule::timing::Timing::new(&meta.profile, meta.exposure_s)
        .with_exposure_policy(&meta.exposure_policy);
    let replayed = timing.estimate_with_retakes_s(&schedule, |_| false, |t| retakes[&t]);
    // The manifest's duration ends with the last frame, as the model does
    // (state.json's also counts switching the rig off).
    let ran = json(&auto.join("manifest.json"))["physical_duration_s"]
        .as_f64()
        .expect("physical_duration_s");
    let bound = timing.estimate_s(&schedule, |_| false);
    assert!(
        // Each of the 6 further exposures takes at least its exposure,
        // readout and transfer.
        (ran - replayed).abs() <= 1e-3 * ran && ran - bound >= 6.0 * (0.0625 + 1.0 + 4.0),
        "auto ran {ran} s; replayed {replayed} s; lower bound {bound} s"
    );

    // `plan show --scene` expects what the scene clips: every step of this
    // plan on leather, none on the matte sample (then the lower bound).
    let expected = |scene: &str| {
        let out = run_ok(&[
            "plan",
            "show",
            &arg(&dir.path().join("plan.json")),
            "--profile",
            &arg(&repo_file("rig-profiles/bonn-gonioreflectometer.toml")),
            "--exposure-policy",
            "auto",
            "--scene",
            scene,
            "--json",
        ]);
        let shown: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json");
        (
            shown["estimated_physical_s"].as_f64().expect("estimate"),
            shown["expected_retaken_triggers"].as_u64(),
        )
    };
    let (leather_s, leather_n) = expected("leather");
    assert_eq!(leather_n, Some(6));
    assert!(
        (leather_s - ran).abs() <= 1e-3 * ran,
        "plan show expects {leather_s} s, the run took {ran} s"
    );
    let (matte_s, matte_n) = expected("flat-calibration");
    assert_eq!(matte_n, Some(0));
    assert!((matte_s - bound).abs() < 1e-6, "{matte_s} against {bound}");
    // An unknown scene, or a scene for a policy it cannot change: bad input.
    for (policy, scene) in [("auto", "no-such-scene"), ("single", "leather")] {
        let o = crate::common::rigd()
            .args(["plan", "show"])
            .arg(dir.path().join("plan.json"))
            .arg("--profile")
            .arg(repo_file("rig-profiles/bonn-gonioreflectometer.toml"))
            .args(["--exposure-policy", policy, "--scene", scene])
            .output()
            .expect("rigd plan show");
        assert_eq!(o.status.code(), Some(2), "{policy} {scene}: {o:?}");
    }

    // Merged, no texel reads a clipped pixel, and the textures are floats
    // that say which exposures they came from.
    let single_index = json(&single.join("processed/normtextures/index.json"));
    let auto_index = json(&auto.join("processed/normtextures/index.json"));
    assert_eq!(auto_index["encoding"], "npy-f32", "{printed}");
    assert_eq!(auto_index["summary"]["clipped_texels"].as_u64(), Some(0));
    assert!(!printed.contains("clipped:"), "{printed}");
    let single_frames = single_index["frames"].as_array().expect("frames");
    let auto_frames = auto_index["frames"].as_array().expect("frames");
    assert_eq!(single_frames.len(), auto_frames.len());

    // Where the single exposure did not clip, the merged value is the
    // single one (up to the 8-bit rounding of its PNG); where it clipped,
    // the merge reads more than the clipped pixel let it, and the
    // highlight reaches past what a single exposure can hold (1).
    let (mut above, mut clipped_total, mut ratios) = (0usize, 0usize, Vec::new());
    let mut brightest = 0.0f32;
    for (one, merged) in single_frames.iter().zip(auto_frames) {
        assert_eq!(one["index"], merged["index"]);
        let exposures: Vec<f64> = merged["exposures_s"]
            .as_array()
            .expect("exposures_s")
            .iter()
            .filter_map(serde_json::Value::as_f64)
            .collect();
        assert_eq!(exposures, vec![0.25, 0.0625]);
        assert!(merged["clipped_mask"].is_null(), "{merged}");
        let textures = |run: &Path| run.join("processed/normtextures");
        let png = rigd_process::image_io::load_png(
            &textures(&single).join(one["file"].as_str().expect("file")),
        )
        .expect("single's texture");
        let npy = rigd_process::npy::read_f32(
            &textures(&auto).join(merged["file"].as_str().expect("file")),
        )
        .expect("auto's texture");
        assert_eq!(png.data.len(), npy.data.len());
        let mask = one["clipped_mask"]
            .as_str()
            .map(|m| rigd_process::image_io::load_png(&textures(&single).join(m)).expect("mask"));
        for (i, (&low, &high)) in png.data.iter().zip(&npy.data).enumerate() {
            let was_clipped = mask.as_ref().is_some_and(|m| m.data[i] > 0.5);
            if was_clipped {
                clipped_total += 1;
                above += usize::from(high > low * 1.05);
                brightest = brightest.max(high);
            } else if (0.1..0.9).contains(&low) {
                ratios.push(high / low);
            }
        }
    }
    assert!(clipped_total > 0 && ratios.len() > 1000);
    assert!(
        above * 2 > clipped_total && brightest > 1.5,
        "{above} of {clipped_total} once-clipped texels read 5 % more merged; brightest {brightest}"
    );
    ratios.sort_by(f32::total_cmp);
    let median = ratios[ratios.len() / 2];
    let (p05, p95) = (ratios[ratios.len() / 20], ratios[ratios.len() * 19 / 20]);
    assert!(
        (0.98..1.02).contains(&median) && p05 > 0.95 && p95 < 1.06,
        "merged over single where single did not clip: median {median}, p05 {p05}, p95 {p95}"
    );

    // A matte sample never clips: no second exposure, no extra time.
    let (matte_single, _) = capture_and_rectify(dir.path(), "flat-calibration");
    let (matte_auto, _) = capture_and_rectify_with(dir.path(), "flat-calibration", "auto");
    let journal = std::fs::read_to_string(matte_auto.join("journal.ndjson")).expect("journal");
    assert_eq!(journal.lines().count(), 6);
    assert!(!journal.contains("brackets"), "{journal}");
    let (once, auto_time) = (physical_s(&matte_single), physical_s(&matte_auto));
    assert!(
        auto_time <= once * 1.02,
        "auto {auto_time} s against single {once} s on a matte sample"
    );
}
