//! `rigd holder template` and `rigd holder check`: a lab's own holder
//! plate drawn to scale (SVG read back by an independent XML parser, PDF
//! by a PDF parser), and found in a frame the simulated rig renders of it.

use std::path::{Path, PathBuf};

use rigd::model::profile::DEFAULT_PROFILE;
use rigd::postprocess::holder_template::MARGIN_MM;

use crate::bring_up::edit;
use crate::common::{repo_file, rigd, run_ok};

/// Largest distance between a marker's centre on the template and in the
/// profile, mm.
const MARKER_TOLERANCE_MM: f64 = 0.1;

/// Largest registration residual (RMS) on a clean frame, pixels.
const MAX_RMS_PX: f64 = 0.5;

/// A 280 mm plate of mid grey with markers of its own, six dark and two
/// light, a ColorChecker below the sample, a patch of the lab's own and a
/// white area above. (A light marker on a mid-grey plate is found only
/// where its search window holds nothing darker than the plate, such as
/// the background beyond the plate's edge, nor a bright chart patch: the
/// light ones sit away from both.)
const LAB_HOLDER: &str = r#"
name = "lab-plate-2"
size_mm = 280.0
sample_mm = [100.0, 100.0]
colour = 0.5
markers = [
    { at_mm = [-105.0, -105.0], polarity = "dark" },
    { at_mm = [0.0, -105.0], polarity = "dark" },
    { at_mm = [105.0, -105.0], polarity = "dark" },
    { at_mm = [-105.0, 0.0], diameter_mm = 8.0 },
    { at_mm = [105.0, 0.0], polarity = "dark", diameter_mm = 8.0 },
    { at_mm = [-105.0, 105.0], polarity = "dark" },
    { at_mm = [0.0, 105.0] },
    { at_mm = [105.0, 105.0], polarity = "dark" },
]
chart = { name = "colorchecker24", centre_mm = [0.0, -78.0], patch_mm = 8.0, pitch_mm = 9.0 }
patches = [{ name = "tan", centre_mm = [-80.0, 0.0], size_mm = 10.0, lab = [65.0, 12.0, 20.0] }]
white = [{ centre_mm = [0.0, 80.0], size_mm = [40.0, 15.0] }]
"#;

/// The Bonn profile with `holder` (TOML) as its `[holder]`, at `out`.
fn with_holder(out: &Path, holder: &str) -> PathBuf {
    let table: toml::Table = holder.parse().expect("holder TOML");
    edit(
        &repo_file("rig-profiles/bonn-gonioreflectometer.toml"),
        out,
        |t| {
            t.insert("holder".into(), table.into());
        },
    );
    out.to_path_buf()
}

/// `rigd holder …`: exit code, stdout, stderr.
fn holder(args: &[&str]) -> (i32, String, String) {
    let o = rigd()
        .arg("holder")
        .args(args)
        .output()
        .expect("rigd holder");
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).to_string(),
        String::from_utf8_lossy(&o.stderr).to_string(),
    )
}

fn number(node: &roxmltree::Node, attr: &str) -> f64 {
    node.attribute(attr)
        .unwrap_or_else(|| panic!("no {attr} on {node:?}"))
        .parse()
        .unwrap_or_else(|_| panic!("{attr} of {node:?} is no number"))
}

/// The template's markers and plate read back from the SVG by an XML
/// parser: every marker's centre within [`MARKER_TOLERANCE_MM`] of the
/// profile's, relative to the plate's outline; returns the worst error.
fn check_svg(svg: &Path, profile: &str) -> f64 {
    let text = std::fs::read_to_string(svg).expect("svg");
    let doc = roxmltree::Document::parse(&text).expect("the SVG is XML");
    let holder = rigd::plan::load_profile(profile)
        .expect("profile")
        .holder
        .holder()
        .expect("holder");
    let root = doc.root_element();
    assert_eq!(root.tag_name().name(), "svg");
    let plate_mm = 2e3 * holder.half;
    let page = plate_mm.max(100.0) + 2.0 * MARGIN_MM;
    assert_eq!(root.attribute("width"), Some(format!("{page}mm").as_str()));
    let by_class = |class: &str| {
        doc.descendants()
            .filter(|n| n.attribute("class") == Some(class))
            .collect::<Vec<_>>()
    };
    let plates = by_class("plate");
    assert_eq!(plates.len(), 1);
    let plate = plates[0];
    assert!((number(&plate, "width") - plate_mm).abs() < 1e-6);
    assert!((number(&plate, "height") - plate_mm).abs() < 1e-6);
    let centre = [
        number(&plate, "x") + plate_mm / 2.0,
        number(&plate, "y") + plate_mm / 2.0,
    ];
    let markers = by_class("marker");
    assert_eq!(markers.len(), holder.points.len());
    let mut worst: f64 = 0.0;
    for m in markers {
        assert_eq!(m.tag_name().name(), "circle");
        let i: usize = number(&m, "data-index") as usize;
        let p = holder.points[i];
        // The page's y runs down, the plate's up.
        let at = [number(&m, "cx") - centre[0], centre[1] - number(&m, "cy")];
        let err = (at[0] - 1e3 * p.position[0]).hypot(at[1] - 1e3 * p.position[1]);
        worst = worst.max(err);
        assert!(
            err < MARKER_TOLERANCE_MM,
            "marker {i}: {at:?} vs {:?}",
            p.position
        );
        assert!((number(&m, "r") - 1e3 * p.radius).abs() < MARKER_TOLERANCE_MM);
    }
    let texts: Vec<String> = doc
        .descendants()
        .filter(|n| n.has_tag_name("text"))
        .filter_map(|n| n.text().map(|t| t.trim().to_string()))
        .collect();
    for want in [
        "100 mm: measure this after printing",
        "print at 100 % (no scaling)",
    ] {
        assert!(texts.iter().any(|t| t == want), "{want} in {texts:?}");
    }
    assert!(
        texts.iter().any(|t| t.contains(&holder.name)),
        "the holder's name in {texts:?}"
    );
    for p in &holder.patches {
        assert!(texts.contains(&p.name), "patch {} named", p.name);
    }
    worst
}

#[test]
fn the_template_puts_every_marker_where_the_profile_says() {
    let dir = tempfile::tempdir().expect("tempdir");
    // The embedded default profile, without --profile.
    let svg = dir.path().join("standard.svg");
    run_ok(&["holder", "template", "--out", svg.to_str().expect("utf8")]);
    let worst = check_svg(&svg, DEFAULT_PROFILE);
    // A lab's plate: its own markers of both polarities, a chart, patches.
    let profile = with_holder(&dir.path().join("lab.toml"), LAB_HOLDER);
    let profile = profile.to_str().expect("utf8");
    let svg = dir.path().join("lab.svg");
    run_ok(&[
        "holder",
        "template",
        "--profile",
        profile,
        "--out",
        svg.to_str().expect("utf8"),
    ]);
    let worst = worst.max(check_svg(&svg, profile));
    eprintln!("largest marker error on the SVG templates: {worst:.6} mm");
    let text = std::fs::read_to_string(&svg).expect("svg");
    assert!(
        text.contains("sample 100 × 100 mm"),
        "the sample window's label"
    );

    // The PDF: a PDF whose one page is the plate and the margins.
    let pdf = dir.path().join("lab.pdf");
    run_ok(&[
        "holder",
        "template",
        "--profile",
        profile,
        "--out",
        pdf.to_str().expect("utf8"),
    ]);
    let bytes = std::fs::read(&pdf).expect("pdf");
    assert!(bytes.starts_with(b"%PDF-"));
    let doc = printpdf::lopdf::Document::load_mem(&bytes).expect("a PDF");
    let pages = doc.get_pages();
    assert_eq!(pages.len(), 1);
    let page_id = *pages.values().next().expect("a page");
    let page = doc.get_dictionary(page_id).expect("page dictionary");
    let media = page
        .get(b"MediaBox")
        .and_then(|m| m.as_array())
        .expect("a MediaBox");
    let side: Vec<f64> = media
        .iter()
        .map(|v| {
            v.as_float()
                .map(f64::from)
                .or_else(|_| v.as_i64().map(|i| i as f64))
        })
        .collect::<Result<_, _>>()
        .expect("numbers");
    let want_pt = (280.0 + 2.0 * MARGIN_MM) * 72.0 / 25.4;
    assert_eq!(side[0], 0.0);
    assert_eq!(side[1], 0.0);
    for v in &side[2..] {
        assert!(
            (v - want_pt).abs() < 0.1,
            "MediaBox {side:?}, want {want_pt} pt"
        );
    }
}

#[test]
fn a_bad_extension_or_a_broken_holder_is_refused_naming_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let png = dir.path().join("plate.png");
    let (code, _, err) = holder(&["template", "--out", png.to_str().expect("utf8")]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains(".svg or .pdf"), "{err}");
    assert!(!png.exists());
    // Three markers: registration needs six.
    let broken = with_holder(
        &dir.path().join("broken.toml"),
        "markers = [{ at_mm = [-70.0, -70.0] }, { at_mm = [70.0, -70.0] }, { at_mm = [70.0, 70.0] }]",
    );
    let svg = dir.path().join("plate.svg");
    let (code, _, err) = holder(&[
        "template",
        "--profile",
        broken.to_str().expect("utf8"),
        "--out",
        svg.to_str().expect("utf8"),
    ]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("holder.markers"), "{err}");
    assert!(!svg.exists());
}

/// `rigd sim render` of `profile`'s rig, frontal, at 960×720.
fn render(profile: &Path, out: &Path) {
    run_ok(&[
        "sim",
        "render",
        "--profile",
        profile.to_str().expect("utf8"),
        "--size",
        "960x720",
        "--out",
        out.to_str().expect("utf8"),
    ]);
}

#[test]
fn the_holder_check_finds_every_marker_and_names_one_that_is_not_there() {
    let dir = tempfile::tempdir().expect("tempdir");
    let profile = with_holder(&dir.path().join("lab.toml"), LAB_HOLDER);
    let frame = dir.path().join("frame.png");
    render(&profile, &frame);
    let (code, out, err) = holder(&[
        "check",
        frame.to_str().expect("utf8"),
        "--profile",
        profile.to_str().expect("utf8"),
        "--json",
    ]);
    assert_eq!(code, 0, "{out}\n{err}");
    let report: serde_json::Value = serde_json::from_str(&out).expect("JSON");
    let markers = report["markers"].as_array().expect("markers");
    assert_eq!(markers.len(), 8);
    for m in markers {
        assert!(m["found_px"].is_array(), "{m}");
        assert_eq!(m["rejected"], false, "{m}");
    }
    let rms = report["rms_px"].as_f64().expect("rms");
    let max = report["max_px"].as_f64().expect("max");
    eprintln!("holder check on a clean frame: RMS {rms:.3} px, max {max:.3} px");
    assert!(rms < MAX_RMS_PX, "{out}");
    // The chart's 24 patches and the lab's own; the white area.
    let patches = report["patches"].as_array().expect("patches");
    assert_eq!(patches.len(), 25, "{out}");
    assert_eq!(patches[0]["name"], "dark skin");
    assert_eq!(patches[24]["name"], "tan");
    let mean = |p: &serde_json::Value| p["mean"][0].as_f64().expect("mean");
    let white = &report["whites"][0];
    // The chart's white patch (19th) reads brighter than its black (24th),
    // the white area brightest of all: the patches are read where they are.
    assert!(mean(&patches[18]) > 4.0 * mean(&patches[23]), "{out}");
    assert!(mean(white) > mean(&patches[23]), "{out}");
    assert_eq!(report["ok"], true);

    // The text report says the same.
    let (code, text, _) = holder(&[
        "check",
        frame.to_str().expect("utf8"),
        "--profile",
        profile.to_str().expect("utf8"),
    ]);
    assert_eq!(code, 0, "{text}");
    assert!(text.contains("residual RMS"), "{text}");
    assert!(text.contains("dark skin"), "{text}");

    // Checked against a holder that has a ninth marker the plate lacks.
    let extra = LAB_HOLDER.replace(
        "    { at_mm = [105.0, 105.0], polarity = \"dark\" },\n]",
        "    { at_mm = [105.0, 105.0], polarity = \"dark\" },\n    { at_mm = [105.0, 60.0], polarity = \"dark\" },\n]",
    );
    assert_ne!(extra, LAB_HOLDER);
    let other = with_holder(&dir.path().join("other.toml"), &extra);
    let (code, text, err) = holder(&[
        "check",
        frame.to_str().expect("utf8"),
        "--profile",
        other.to_str().expect("utf8"),
    ]);
    assert_eq!(code, 1, "{text}\n{err}");
    assert!(
        text.lines()
            .any(|l| l.starts_with("FAIL marker 8") && l.contains("not found")),
        "{text}"
    );

    // Not a frame at all, or no file: bad input.
    let garbage = dir.path().join("garbage.png");
    std::fs::write(&garbage, b"this is not an image").expect("write");
    for path in [garbage, dir.path().join("missing.dng")] {
        let (code, _, err) = holder(&["check", path.to_str().expect("utf8")]);
        assert_eq!(code, 2, "{}: {err}", path.display());
        assert!(err.contains(&path.display().to_string()), "{err}");
    }
    // A view beyond the horizon.
    let (code, _, err) = holder(&["check", frame.to_str().expect("utf8"), "--view", "95,0"]);
    assert_eq!(code, 2, "{err}");
}

/// At 85° and 640×480 the standard plate is a band a few pixels tall, and
/// its border lines break into dashes the size of a foreshortened marker a
/// few pixels from the markers. What the check reports as a marker is the
/// marker, never a dash: each one found lies within a pixel and a half of
/// where the pose puts it (a dash lies 3–18 px off), and a marker that
/// cannot be told apart is reported missing.
#[test]
fn at_a_grazing_view_a_dash_of_the_border_line_is_not_taken_for_a_marker() {
    let dir = tempfile::tempdir().expect("tempdir");
    let frame = dir.path().join("grazing.png");
    run_ok(&[
        "sim",
        "render",
        "--view",
        "85,240",
        "--size",
        "640x480",
        "--out",
        frame.to_str().expect("utf8"),
    ]);
    let (code, out, err) = holder(&["check", frame.to_str().expect("utf8"), "--json"]);
    assert!(code == 0 || code == 1, "{out}\n{err}");
    let report: serde_json::Value = serde_json::from_str(&out).expect("JSON");
    let markers = report["markers"].as_array().expect("markers");
    let mut found = 0;
    for m in markers {
        let (Some(p), Some(f)) = (m["predicted_px"].as_array(), m["found_px"].as_array()) else {
            continue;
        };
        let at = |v: &[serde_json::Value], k: usize| v[k].as_f64().expect("px");
        let off = (at(f, 0) - at(p, 0)).hypot(at(f, 1) - at(p, 1));
        assert!(
            off < 1.5,
            "marker found {off:.1} px from its prediction: {m}"
        );
        found += 1;
    }
    assert!(found > 0, "{out}");
    if found < markers.len() {
        assert_eq!(code, 1, "{out}");
    }
}
