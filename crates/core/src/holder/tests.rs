use super::*;

fn patched() -> Holder {
    let spec = HolderSpec {
        colour_patches: true,
        ..HolderSpec::default()
    };
    spec.holder()
        .expect("the standard plate has room for its patches")
}

/// A plate with a ColorChecker below an 80 mm sample: 220 mm, markers
/// of the lab's own, dark ones among them on a light-grey plate.
fn chart_plate() -> HolderSpec {
    let text = r#"
        name = "lab-b"
        size_mm = 220
        sample_mm = [80, 80]
        colour = 0.5
        chart = { name = "colorchecker24", centre_mm = [0, -75], patch_mm = 8, pitch_mm = 10 }
        markers = [
            { at_mm = [-95, -95] }, { at_mm = [95, -95], polarity = "dark" },
            { at_mm = [95, 95] }, { at_mm = [-95, 95], polarity = "dark" },
            { at_mm = [0, 95], diameter_mm = 8 }, { at_mm = [-95, 0] }, { at_mm = [95, 0] },
        ]
        white = [{ centre_mm = [0, 65], size_mm = [40, 8] }]
    "#;
    toml::from_str(text).expect("a holder table")
}

fn refused(spec: &HolderSpec) -> HolderError {
    spec.check().expect_err("refused")
}

#[test]
fn the_standard_plate_carries_no_patches() {
    assert!(Holder::standard().patches.is_empty());
    assert_eq!(Holder::standard().reflectance(0.0, -0.0625), [0.06; 3]);
    HolderSpec::default()
        .check()
        .expect("the standard plate works");
}

#[test]
fn the_standard_markers_are_the_eight_around_the_plate() {
    let h = Holder::standard();
    assert_eq!(h.points.len(), 8);
    let [x, y] = h.points[0].position;
    assert!(
        (x + 0.071).abs() < 1e-12 && (y + 0.071).abs() < 1e-12,
        "{x} {y}"
    );
    assert_eq!(h.markers().len(), 12, "8 points and 4 border corners");
}

#[test]
fn patches_sit_between_the_border_line_and_the_point_markers_clear_of_both() {
    let h = patched();
    assert_eq!(h.patches.len(), COLOUR_PATCHES.len());
    h.check_patches(5.0).expect("the standard plate has room");
    for (p, want) in h.patches.iter().zip(&COLOUR_PATCHES) {
        let (x, y) = (p.centre[0], p.centre[1]);
        assert_eq!(p.name, want.name);
        assert!((2e3 * p.half - 7.0).abs() < 1e-9, "{p:?}");
        assert_eq!(h.reflectance(x, y), p.rgb);
        assert!((h.albedo(x, y) - luminance(p.rgb)).abs() < 1e-12);
        // Its edges touch neither a marker nor the border line.
        for (dx, dy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            let margin = p.half + 1e-3;
            let (ex, ey) = (x + dx * margin, y + dy * margin);
            assert_eq!(h.albedo(ex, ey), h.colour, "beside {}", p.name);
        }
    }
    // Neighbours do not touch.
    for w in h.patches.windows(2) {
        assert!(w[1].centre[0] - w[0].centre[0] > 2.0 * w[0].half + 5e-3);
    }
}

#[test]
fn a_plate_without_room_for_patches_says_so() {
    let spec = HolderSpec {
        colour_patches: true,
        size_mm: 130.0,
        ..HolderSpec::default()
    };
    let e = refused(&spec);
    assert_eq!(e.key, "holder.colour_patches", "{e}");
    assert!(e.message.contains("mm wide"), "{e}");
}

#[test]
fn a_chart_is_laid_out_as_its_maker_prints_it() {
    let spec = chart_plate();
    let h = spec.holder().expect("a plate that works");
    assert_eq!(h.patches.len(), 24);
    let at = |name: &str| {
        h.patches
            .iter()
            .find(|p| p.name == name)
            .unwrap_or_else(|| panic!("{name}"))
            .centre
    };
    // Dark skin top left, bluish green top right, black bottom right,
    // white bottom left, 10 mm apart, around (0, -75) mm.
    let close = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9;
    assert!(
        close(at("dark skin"), [-0.025, -0.060]),
        "{:?}",
        at("dark skin")
    );
    assert!(close(at("bluish green"), [0.025, -0.060]));
    assert!(close(at("black 2"), [0.025, -0.090]));
    assert!(close(at("white 9.5"), [-0.025, -0.090]));
    // The white patch reflects about 0.9 in every channel; a dark
    // marker is dark, the plate light grey, the white area white.
    let w = h.reflectance(-0.025, -0.090);
    assert!(w.iter().all(|v| (0.8..0.93).contains(v)), "{w:?}");
    assert_eq!(h.albedo(0.095, -0.095), spec.dark_marker_colour);
    assert_eq!(h.albedo(-0.095, -0.095), spec.marker_colour);
    assert_eq!(h.albedo(0.0, 0.065), 0.9);
    assert_eq!(h.albedo(0.08, 0.08), 0.5);
    assert_eq!(h.sample_half, [0.04, 0.04]);
}

#[test]
fn markers_that_overlap_each_other_are_refused() {
    let mut spec = chart_plate();
    spec.markers[6].at_mm = [95.0, 92.0];
    let e = refused(&spec);
    assert_eq!(e.key, "holder.markers[6]", "{e}");
    assert!(e.message.contains("overlaps marker"), "{e}");
}

#[test]
fn a_marker_on_the_sample_window_or_its_border_is_refused() {
    let mut spec = chart_plate();
    spec.markers[5].at_mm = [-47.0, 0.0];
    let e = refused(&spec);
    assert_eq!(e.key, "holder.markers[5]", "{e}");
    assert!(e.message.contains("sample window"), "{e}");
}

#[test]
fn a_marker_off_the_plate_is_refused() {
    let mut spec = chart_plate();
    spec.markers[0].at_mm = [-108.0, -95.0];
    let e = refused(&spec);
    assert_eq!(e.key, "holder.markers[0]", "{e}");
    assert!(e.message.contains("off the"), "{e}");
}

#[test]
fn fewer_markers_than_registration_needs_are_refused() {
    let mut spec = chart_plate();
    spec.markers.truncate(5);
    let e = refused(&spec);
    assert_eq!(e.key, "holder.markers", "{e}");
    assert!(e.message.contains("at least 6"), "{e}");
}

#[test]
fn a_patch_without_reference_values_is_refused() {
    let mut spec = chart_plate();
    spec.patches.push(PatchSpec {
        name: "lab grey".into(),
        centre_mm: [-80.0, 60.0],
        size_mm: 8.0,
        lab: None,
    });
    let e = refused(&spec);
    assert_eq!(e.key, "holder.patches[0].lab", "{e}");
    assert!(e.message.contains("lab grey"), "{e}");
    spec.patches[0].lab = Some([50.0, 0.0, 0.0]);
    spec.check().expect("with its L*a*b* it works");
}

#[test]
fn an_unknown_chart_is_refused_naming_the_known_ones() {
    let mut spec = chart_plate();
    if let Some(c) = spec.chart.as_mut() {
        c.name = "colorchecker140".into();
    }
    let e = refused(&spec);
    assert_eq!(e.key, "holder.chart.name", "{e}");
    assert!(e.message.contains("colorchecker24"), "{e}");
}

#[test]
fn a_chart_over_a_marker_or_the_window_is_refused() {
    let mut spec = chart_plate();
    if let Some(c) = spec.chart.as_mut() {
        c.centre_mm = [0.0, -60.0];
    }
    let e = refused(&spec);
    assert_eq!(e.key, "holder.chart", "{e}");
    let mut spec = chart_plate();
    spec.markers[0].at_mm = [-30.0, -75.0];
    let e = refused(&spec);
    assert_eq!(e.key, "holder.markers[0]", "{e}");
    assert!(e.message.contains("holder.chart"), "{e}");
}

#[test]
fn a_marker_that_does_not_stand_out_is_refused() {
    let mut spec = chart_plate();
    spec.colour = 0.1;
    let e = refused(&spec);
    assert_eq!(e.key, "holder.markers[1]", "{e}");
    assert!(e.message.contains("dark marker"), "{e}");
}

#[test]
fn white_has_unit_luminance_weights() {
    assert!((luminance([1.0; 3]) - 1.0).abs() < 1e-12);
}

#[test]
fn a_plate_without_border_lines_has_only_point_markers() {
    let spec = HolderSpec {
        border_line_mm: 0.0,
        ..HolderSpec::default()
    };
    let h = spec.holder().expect("works");
    assert!(!h.has_border_lines());
    assert_eq!(h.markers().len(), 8);
    assert_eq!(h.albedo(0.055, 0.0), h.colour);
}
