//! Lamp drift: the simulated HMI lamp's output wanders by ±5 % over the
//! capture; `rigd process rectify` measures it on the holder's white strip
//! in every frame and divides it out. The BTF's held-out error against the
//! scene's truth is then that of a capture without drift, and without the
//! strip (nothing to measure the lamp by) it is worse.

use std::path::{Path, PathBuf};

use rigd_core::geometry::Direction;

use crate::bring_up::edit;

/// The drift injected: ±5 %, over a period the short test capture spans.
const AMPLITUDE: f64 = 0.05;
const PERIOD_S: f64 = 240.0;

/// A Bonn capture of `corduroy` (16 lights, 2 views, 320×240), its lamp
/// drifting when `drift`, its standard plate carrying a white strip
/// between the upper border line and the upper markers when `strip`.
fn capture(dir: &Path, name: &str, drift: bool, strip: bool) -> PathBuf {
    let profile = dir.join(format!("{name}.toml"));
    edit(&crate::common::bonn_monochrome(dir), &profile, |t| {
        if strip {
            let holder: toml::Table =
                toml::from_str("white = [{ centre_mm = [0.0, 62.0], size_mm = [40.0, 5.0] }]")
                    .expect("a holder table");
            t.insert("holder".into(), holder.into());
        }
        if drift {
            let sim = t
                .get_mut("sim")
                .and_then(|s| s.as_table_mut())
                .expect("[sim]");
            let d: toml::Table =
                toml::from_str(&format!("amplitude = {AMPLITUDE}\nperiod_s = {PERIOD_S}"))
                    .expect("a drift table");
            sim.insert("lamp_drift".into(), d.into());
        }
    });
    let run = dir.join(name);
    crate::colour::capture_sixteen_lights_two_views(&profile, &run, "320x240");
    run
}

/// The frontal view's measured lights: where the drift shows, rather than
/// the interpolation between directions.
fn frontal_pairs() -> Vec<(Direction, Direction)> {
    [30.0, 45.0]
        .iter()
        .flat_map(|&t| (0..8).map(move |k| Direction::new(t, 45.0 * k as f64)))
        .map(|l| (l, Direction::new(0.0, 0.0)))
        .collect()
}

/// Mean RMS error against the scene's truth of the compressed BTF at
/// [`frontal_pairs`], after `btf_error`'s processing.
fn mean_rms(run: &Path) -> f64 {
    crate::colour::btf_error(run);
    let errors = rigd::truth::btf_truth_error(run, &frontal_pairs()).expect("truth error");
    errors.iter().map(|e| e.rms).sum::<f64>() / errors.len() as f64
}

/// How far `run`'s compressed BTF lies from `reference`'s at
/// [`frontal_pairs`]: the RMS difference over the reference's RMS, after
/// the one scale that fits `run` best to `reference`. A corrected run is
/// divided by its levels relative to its first frame, so it keeps that
/// frame's level as a scale of the whole BTF, which an exposure could give
/// as well; the drift is what no one scale takes out.
fn relative_difference(run: &Path, reference: &Path) -> f64 {
    let textures = |run: &Path| -> Vec<f32> {
        let store = rigd_process::btf::CompressedBtf::read(&rigd::store::processed::btf_dir(run))
            .expect("the BTF");
        frontal_pairs()
            .iter()
            .flat_map(|&(l, v)| store.reconstruct(l, v).expect("reconstruct"))
            .collect()
    };
    let (a, b) = (textures(run), textures(reference));
    assert_eq!(a.len(), b.len());
    let dot = |x: &[f32], y: &[f32]| {
        x.iter()
            .zip(y)
            .map(|(&p, &q)| f64::from(p) * f64::from(q))
            .sum::<f64>()
    };
    let scale = dot(&a, &b) / dot(&a, &a);
    let diff: f64 = a
        .iter()
        .zip(&b)
        .map(|(&p, &q)| (scale * f64::from(p) - f64::from(q)).powi(2))
        .sum();
    (diff / dot(&b, &b)).sqrt()
}

#[test]
fn the_white_strip_measures_the_lamp_s_drift_and_rectify_divides_it_out() {
    let dir = tempfile::tempdir().expect("tempdir");
    let steady = capture(dir.path(), "steady", false, true);
    let corrected = capture(dir.path(), "corrected", true, true);
    let uncorrected = capture(dir.path(), "uncorrected", true, false);
    let (e_steady, e_corrected, e_uncorrected) = (
        mean_rms(&steady),
        mean_rms(&corrected),
        mean_rms(&uncorrected),
    );
    let (d_corrected, d_uncorrected) = (
        relative_difference(&corrected, &steady),
        relative_difference(&uncorrected, &steady),
    );
    eprintln!(
        "held-out RMS against the truth: no drift {e_steady:.5}, ±5 % drift corrected \
         {e_corrected:.5}, uncorrected {e_uncorrected:.5}; the BTF against the drift-free one's: \
         corrected {:.2} %, uncorrected {:.2} %",
        100.0 * d_corrected,
        100.0 * d_uncorrected
    );

    // Every frame's measured level follows the drift injected, relative
    // to the first frame's.
    let index: serde_json::Value = serde_json::from_slice(
        &std::fs::read(corrected.join("processed/normtextures/index.json")).expect("index"),
    )
    .expect("json");
    let (journal, _) =
        rigd::store::read_journal(&corrected.join(rigd::store::JOURNAL_FILE)).expect("journal");
    let t_of = |i: u64| {
        journal
            .iter()
            .find(|e| e.index as u64 == i)
            .map(|e| e.t_s)
            .expect("frame in the journal")
    };
    let drift = rigd_core::lamp_drift::LampDrift {
        amplitude: AMPLITUDE,
        period_s: PERIOD_S,
    };
    let frames = index["frames"].as_array().expect("frames");
    let first_t = t_of(frames[0]["index"].as_u64().expect("index"));
    let (mut worst, mut spread) = (0.0f64, (f64::MAX, f64::MIN));
    for f in frames {
        let level = f["lamp_level"]
            .as_f64()
            .expect("every frame sees the strip");
        let t = t_of(f["index"].as_u64().expect("index"));
        let want = drift.level(t) / drift.level(first_t);
        worst = worst.max((level / want - 1.0).abs());
        spread = (spread.0.min(want), spread.1.max(want));
    }
    assert!(
        spread.1 - spread.0 > 0.05,
        "the capture spans the drift: {spread:?}"
    );
    assert!(
        worst < 0.01,
        "a measured level is {:.2} % off the drift",
        100.0 * worst
    );
    assert!(corrected.join("processed/lamp-level.svg").is_file());
    let steady_index =
        std::fs::read_to_string(steady.join("processed/normtextures/index.json")).expect("index");
    assert!(steady_index.contains("lamp_level"));
    assert!(
        !std::fs::read_to_string(uncorrected.join("processed/normtextures/index.json"))
            .expect("index")
            .contains("lamp_level")
    );

    // Against the truth, the capture's other errors (vignetting, the
    // sensor, compression) outweigh a 5 % drift: the corrected run is held
    // to the steady one's error. Frame by frame against the steady run's
    // textures, the drift stands out uncorrected and is gone corrected.
    assert!(
        e_corrected <= 1.1 * e_steady,
        "corrected {e_corrected} against {e_steady} without drift"
    );
    let ratios = |run: &Path| -> Vec<f64> {
        let mean = |run: &Path, file: &str| {
            let img =
                rigd_process::image_io::load_png(&run.join("processed/normtextures").join(file))
                    .expect("texture");
            img.data.iter().map(|&v| f64::from(v)).sum::<f64>() / img.data.len() as f64
        };
        frames
            .iter()
            .filter_map(|f| f["file"].as_str())
            .map(|file| mean(run, file) / mean(&steady, file))
            .collect()
    };
    let extent = |r: &[f64]| {
        r.iter()
            .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)))
    };
    let (lo, hi) = extent(&ratios(&corrected));
    let (ulo, uhi) = extent(&ratios(&uncorrected));
    eprintln!(
        "texture means against the steady run's: corrected {lo:.4} … {hi:.4}, uncorrected \
         {ulo:.4} … {uhi:.4}"
    );
    assert!(
        uhi - ulo > 0.05,
        "the drift shows uncorrected: {ulo} … {uhi}"
    );
    assert!(hi - lo < 0.015, "corrected, it is gone: {lo} … {hi}");
    // The same in the compressed BTF: uncorrected, it carries the drift;
    // corrected, what is left is the measured levels' own error.
    assert!(
        d_uncorrected > 0.02 && d_uncorrected > 3.0 * d_corrected,
        "the BTF against the drift-free one's: corrected {d_corrected}, uncorrected {d_uncorrected}"
    );
}
