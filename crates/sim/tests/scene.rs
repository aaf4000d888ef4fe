//! The scene renderer: effect planning, determinism, energy, the ground
//! truth against independent computations, and what each scene must show.

use std::f64::consts::PI;

use rigd_sim::scene::{
    dome, dome_normal, Effect, EffectSwitches, LaserSheet, Scene, Shot, DOME_FIELD_MM, WHITE_LEVEL,
};

fn dir(theta_deg: f64, phi_deg: f64) -> [f64; 3] {
    let (t, p) = (theta_deg.to_radians(), phi_deg.to_radians());
    [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
}

fn shot(light: [f64; 3], view: [f64; 3], w: u32, h: u32) -> Shot {
    Shot {
        light,
        view,
        width: w,
        height: h,
        ..Shot::default()
    }
}

fn scene_from(text: &str) -> Scene {
    Scene::from_toml(text, "test scene", None).unwrap()
}

const WHITE_FLAT: &str = r#"
name = "white"
[sample]
size_mm = [100.0, 100.0]
resolution = 64
albedo = { pattern = "uniform", value = 1.0 }
[sensor]
read_noise_dn = 2.0
electrons_per_dn = 4.0
seed = 3
"#;

#[test]
fn every_builtin_scene_loads_and_says_what_it_can_show() {
    for name in Scene::builtin_names() {
        let s = Scene::load(name).unwrap();
        let caps = s.capabilities();
        eprintln!("{}", s.describe_effects());
        let flat = name == "flat-calibration";
        assert_eq!(!caps.contains(Effect::Relief), flat, "{name}");
        assert_eq!(
            caps.contains(Effect::VisibilityMaps),
            name == "folded-cloth",
            "{name}"
        );
    }
}

#[test]
fn asking_for_effects_a_scene_cannot_show_changes_no_pixel() {
    let cases = [
        // Flat: no relief, shadows, bounces or visibility maps to pay for.
        ("flat-calibration", "all", dir(60.0, 30.0), dir(45.0, 200.0)),
        // Shadows and bounces forbidden by the scene itself.
        ("ps-target", "all", dir(70.0, 0.0), dir(30.0, 90.0)),
        // No laser in the shot, no folds, no subsurface in leather.
        (
            "leather",
            "laser,visibility-maps,subsurface",
            dir(40.0, 10.0),
            dir(20.0, 45.0),
        ),
    ];
    for (name, ask, l, v) in cases {
        let scene = Scene::load(name).unwrap();
        let mut plain = shot(l, v, 96, 72);
        plain.effects = "-noise".parse().unwrap();
        let mut asked = plain;
        asked.effects = ask.parse().unwrap();
        asked.effects.forbid.insert(Effect::Noise);
        let (a, plan_a) = scene.render_linear(&plain);
        let (b, plan_b) = scene.render_linear(&asked);
        assert_eq!(plan_a.live, plan_b.live, "{name}");
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max);
        assert!(worst <= 1e-6, "{name}: a pixel changed by {worst}");
        assert!(a.iter().any(|&x| x > 100.0), "{name}: frame is dark");
    }
}

#[test]
fn flat_scene_pays_for_nothing_it_does_not_show() {
    let scene = Scene::load("flat-calibration").unwrap();
    let plan = scene.plan(&shot(dir(30.0, 0.0), dir(0.0, 0.0), 8, 8));
    assert!(plan.live.is_empty(), "{}", plan.live);
    let scene = Scene::load("knitted-wool").unwrap();
    let mut s = shot(dir(30.0, 0.0), dir(0.0, 0.0), 8, 8);
    s.laser = Some(laser_across_x(0.0));
    let plan = scene.plan(&s);
    for e in Effect::ALL {
        if e != Effect::VisibilityMaps {
            assert!(
                plan.has(e),
                "knitted-wool with a laser should pay for {e:?}: {}",
                plan.live
            );
        }
    }
}

#[test]
fn frames_are_deterministic_for_a_seed() {
    let scene = Scene::load("knitted-wool").unwrap();
    let mut s = shot(dir(45.0, 30.0), dir(30.0, 200.0), 80, 60);
    s.seed = 7;
    let a = scene.render(&s);
    let b = scene.render(&s);
    assert_eq!(a, b);
    s.seed = 8;
    let c = scene.render(&s);
    assert_ne!(a.pixels, c.pixels, "another seed draws other noise");
}

#[test]
fn white_lambertian_flat_follows_cos_theta_within_noise() {
    let scene = scene_from(WHITE_FLAT);
    for theta in [0.0, 30.0, 60.0, 80.0] {
        let s = shot(dir(theta, 0.0), dir(0.0, 0.0), 64, 64);
        let f = scene.render(&s);
        // The central 16 × 16 pixels all see the sample.
        let mut sum = 0.0;
        for j in 24..40 {
            for i in 24..40 {
                sum += f.pixels[j * 64 + i] as f64;
            }
        }
        let mean = sum / 256.0;
        let expected = WHITE_LEVEL * 4095.0 * theta.to_radians().cos();
        // Shot noise σ = √(v / 4) + read 2 DN, averaged over 256 pixels.
        let sigma = ((expected / 4.0) + 4.0).sqrt() / 16.0;
        assert!(
            (mean - expected).abs() < 4.0 * sigma + 0.5,
            "θ = {theta}: mean {mean:.2}, cos θ predicts {expected:.2}"
        );
    }
}

#[test]
fn twelve_bit_frames_saturate_instead_of_wrapping() {
    let scene = scene_from(WHITE_FLAT);
    let mut s = shot(dir(0.0, 0.0), dir(0.0, 0.0), 32, 32);
    s.gain = 4.0;
    let f = scene.render(&s);
    let centre = f.pixels[16 * 32 + 16];
    assert_eq!(centre, 4095);
    assert!(f.pixels.iter().all(|&p| p <= 4095));
}

#[test]
fn true_btf_of_a_flat_sample_is_lambert_plus_ward() {
    let white = scene_from(WHITE_FLAT);
    for (tl, tv) in [(0.0, 0.0), (45.0, 10.0), (85.0, 60.0), (89.9, 0.0)] {
        let got = white.true_btf(
            0.01,
            -0.02,
            dir(tl, 30.0),
            dir(tv, 200.0),
            EffectSwitches::default(),
        );
        let cos: f64 = tl.to_radians().cos();
        assert!((got - cos).abs() < 1e-9, "θl {tl}: {got} vs {cos}");
    }
    // Glossy: an independent Ward evaluation on the flat normal.
    let glossy = scene_from(
        r#"
name = "glossy"
[sample]
size_mm = [80.0, 80.0]
resolution = 32
albedo = { pattern = "uniform", value = 0.5 }
specular = { strength = 0.2, roughness = [0.1, 0.3], tangent_deg = 30.0 }
"#,
    );
    let (l, v) = (dir(40.0, 10.0), dir(35.0, 185.0));
    let h = {
        let s = [l[0] + v[0], l[1] + v[1], l[2] + v[2]];
        let n = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
        [s[0] / n, s[1] / n, s[2] / n]
    };
    let (t, b) = (dir(90.0, 30.0), dir(90.0, 120.0));
    let dot = |a: [f64; 3], c: [f64; 3]| a[0] * c[0] + a[1] * c[1] + a[2] * c[2];
    let e = ((dot(h, t) / 0.1).powi(2) + (dot(h, b) / 0.3).powi(2)) / (h[2] * h[2]);
    let brdf = 0.5 / PI + 0.2 / (4.0 * PI * 0.1 * 0.3 * (l[2] * v[2]).sqrt()) * (-e).exp();
    let expected = PI * brdf * l[2];
    let got = glossy.true_btf(0.0, 0.0, l, v, EffectSwitches::default());
    assert!((got - expected).abs() < 1e-9, "{got} vs {expected}");
}

#[test]
fn true_height_and_normals_match_the_analytic_domes() {
    let scene = Scene::load("ps-target").unwrap();
    let (r, h) = (14.0, 7.0);
    let mut worst_deg: f64 = 0.0;
    let mut worst_h: f64 = 0.0;
    for k in 0..400 {
        let x = -48.0 + 96.0 * ((k * 37) % 400) as f64 / 400.0;
        let y = -48.0 + 96.0 * ((k * 91) % 400) as f64 / 400.0;
        let z = dome(x, y, r, h, 3, DOME_FIELD_MM);
        // Stay off the rims, where the grid cannot hold the kink.
        if z < 0.3 || z > h - 0.05 {
            continue;
        }
        worst_h = worst_h.max((scene.true_height(x * 1e-3, y * 1e-3) * 1e3 - z).abs());
        let n = scene.true_normal(x * 1e-3, y * 1e-3);
        let a = dome_normal(x, y, r, h, 3, DOME_FIELD_MM);
        let c = (n[0] * a[0] + n[1] * a[1] + n[2] * a[2]).clamp(-1.0, 1.0);
        worst_deg = worst_deg.max(c.acos().to_degrees());
    }
    assert!(worst_h < 0.01, "height off by {worst_h} mm");
    assert!(worst_deg < 1.0, "normal off by {worst_deg}°");
}

/// First hit of the ray from `o` along `d` with the dome grid: the spheres
/// of the nine cells and the base plane, in closed form (mm).
fn analytic_hit(o: [f64; 3], d: [f64; 3], r: f64, h: f64) -> f64 {
    let mut best = -o[2] / d[2];
    let cell = DOME_FIELD_MM / 3.0;
    for i in 0..3 {
        for j in 0..3 {
            let c = [
                -DOME_FIELD_MM / 2.0 + cell * (i as f64 + 0.5),
                -DOME_FIELD_MM / 2.0 + cell * (j as f64 + 0.5),
                -(r - h),
            ];
            let oc = [o[0] - c[0], o[1] - c[1], o[2] - c[2]];
            let b = oc[0] * d[0] + oc[1] * d[1] + oc[2] * d[2];
            let q = oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2] - r * r;
            let disc = b * b - q;
            if q <= 0.0 {
                // The reference plane (the grid's top) cuts the apex.
                best = 0.0;
            } else if disc >= 0.0 {
                let t = -b - disc.sqrt();
                if t >= -1e-9 && o[2] + t * d[2] >= 0.0 && t < best {
                    best = t.max(0.0);
                }
            }
        }
    }
    best
}

#[test]
fn true_mdf_matches_ray_sphere_intersection() {
    let scene = Scene::load("ps-target").unwrap();
    let top_mm = scene.reference_height() * 1e3;
    assert!((top_mm - 7.0).abs() < 0.01, "{top_mm}");
    let mut worst: f64 = 0.0;
    for (theta, phi) in [(0.0, 0.0), (30.0, 45.0), (60.0, 200.0), (75.0, 330.0)] {
        let v = dir(theta, phi);
        for k in 0..60 {
            let x = -40.0 + 80.0 * ((k * 7) % 60) as f64 / 60.0;
            let y = -40.0 + 80.0 * ((k * 13) % 60) as f64 / 60.0;
            let d = scene.true_mdf(x * 1e-3, y * 1e-3, v).unwrap() * 1e3;
            let expected = analytic_hit([x, y, top_mm], [-v[0], -v[1], -v[2]], 14.0, 7.0);
            worst = worst.max((d - expected).abs());
        }
    }
    // Grid of 0.1 mm texels; rays that graze a rim may differ by a bit more.
    assert!(worst < 0.25, "MDF off by {worst} mm");
    assert!(scene.true_mdf(0.0, 0.0, dir(90.0, 0.0)).is_none());
}

#[test]
fn true_marker_positions_are_where_the_frame_shows_them() {
    let scene = Scene::load("flat-calibration").unwrap();
    for (view, focal) in [
        (dir(0.0, 0.0), None),
        (dir(40.0, 60.0), Some(700.0)),
        (dir(65.0, 300.0), Some(900.0)),
    ] {
        let mut s = shot(dir(0.0, 0.0), view, 320, 240);
        s.focal_px = focal;
        s.camera_distance_m = focal.map(|_| 1.0);
        let f = scene.render(&s);
        let mut checked = 0;
        for (marker, px) in scene.true_markers(&s) {
            let Some([u, v]) = px else { continue };
            if marker.kind != "point" || u < 6.0 || v < 6.0 || u > 314.0 || v > 234.0 {
                continue;
            }
            // Centroid of the bright pixels around the predicted centre.
            let (mut sx, mut sy, mut sw) = (0.0, 0.0, 0.0);
            for j in (v as usize - 5)..(v as usize + 5) {
                for i in (u as usize - 5)..(u as usize + 5) {
                    let p = f.pixels[j * 320 + i] as f64;
                    if p > 1500.0 {
                        sx += (i as f64 + 0.5) * p;
                        sy += (j as f64 + 0.5) * p;
                        sw += p;
                    }
                }
            }
            assert!(sw > 0.0, "marker at {u:.1},{v:.1} not visible");
            let (cx, cy) = (sx / sw, sy / sw);
            assert!(
                (cx - u).hypot(cy - v) < 0.6,
                "marker predicted at {u:.2},{v:.2}, seen at {cx:.2},{cy:.2}"
            );
            checked += 1;
        }
        assert!(checked >= 4, "only {checked} markers in view");
    }
}

/// Fraction of the central quarter (all sample) that `with` darkens to
/// less than half of what `without` shows.
fn shadowed_fraction(scene: &Scene, s: &Shot, with: &str, without: &str) -> f64 {
    let mut a = *s;
    a.effects = with.parse().unwrap();
    let mut b = *s;
    b.effects = without.parse().unwrap();
    let (pa, _) = scene.render_linear(&a);
    let (pb, _) = scene.render_linear(&b);
    let (w, h) = (s.width as usize, s.height as usize);
    let (mut dark, mut n) = (0, 0);
    for j in h * 3 / 8..h * 5 / 8 {
        for i in w * 3 / 8..w * 5 / 8 {
            n += 1;
            if pa[j * w + i] < 0.5 * pb[j * w + i] {
                dark += 1;
            }
        }
    }
    dark as f64 / n as f64
}

#[test]
fn corduroy_ridges_shadow_each_other_at_grazing_light_across_them() {
    let scene = Scene::load("corduroy").unwrap();
    // The ridges run along y: light from +x at 80° rakes across them, while
    // the same grazing angle along them casts no shadows.
    let across = shot(dir(80.0, 0.0), dir(0.0, 0.0), 200, 200);
    let along = shot(dir(80.0, 90.0), dir(0.0, 0.0), 200, 200);
    let steep = shot(dir(30.0, 0.0), dir(0.0, 0.0), 200, 200);
    let f = |s: &Shot| shadowed_fraction(&scene, s, "-noise", "-noise,-shadows");
    let (across, along, steep) = (f(&across), f(&along), f(&steep));
    eprintln!("corduroy shadowed: {across:.2} at 80° across the ridges, {along:.2} along, {steep:.2} at 30°");
    assert!(across > 0.1, "{across}");
    assert!(along < 0.02 && steep < 0.02, "{along} {steep}");
}

fn laser_across_x(x0: f64) -> LaserSheet {
    // An emitter high over +x... whose plane x = x0 + z·tan(30°) sweeps the sample.
    let tilt = 30f64.to_radians();
    LaserSheet {
        emitter: [x0 + 0.3 * tilt.tan(), 0.0, 0.3],
        normal: [tilt.cos(), 0.0, -tilt.sin()],
        width_m: 0.4e-3,
        power: 1.0,
    }
}

/// The row of the brightest pixel per column (the line runs across the
/// image: the sample's y axis is the image's x axis for views from -x).
fn laser_columns(scene: &Scene, s: &Shot) -> Vec<Option<f64>> {
    let (px, _) = scene.render_linear(s);
    let (w, h) = (s.width as usize, s.height as usize);
    (0..w)
        .map(|i| {
            let (j, v) =
                (0..h)
                    .map(|j| (j, px[j * w + i]))
                    .fold((0, 0f32), |a, b| if b.1 > a.1 { b } else { a });
            (v > 100.0).then_some(j as f64)
        })
        .collect()
}

#[test]
fn the_laser_line_bends_over_the_relief() {
    // Lamp off: only the laser lights the ps-target; camera at 40° seeing
    // the line's displacement as the relief rises.
    let scene = Scene::load("ps-target").unwrap();
    let mut s = shot([0.0, 0.0, -1.0], dir(40.0, 180.0), 240, 240);
    s.laser = Some(laser_across_x(-100.0 / 3.0 * 1e-3));
    s.effects = "-noise".parse().unwrap();
    assert!(scene.plan(&s).has(Effect::Laser));
    let cols = laser_columns(&scene, &s);
    let xs: Vec<f64> = cols.iter().flatten().copied().collect();
    assert!(xs.len() > 100, "laser seen in only {} columns", xs.len());
    let spread =
        xs.iter().copied().fold(f64::MIN, f64::max) - xs.iter().copied().fold(f64::MAX, f64::min);
    eprintln!("laser line over the domes spans {spread:.1} rows");
    assert!(spread > 5.0, "the line stays straight: {spread} px");
    // On the flat calibration scene the same line is straight.
    let flat = Scene::load("flat-calibration").unwrap();
    let cols = laser_columns(&flat, &s);
    let xs: Vec<f64> = cols.iter().flatten().copied().collect();
    let spread_flat =
        xs.iter().copied().fold(f64::MIN, f64::max) - xs.iter().copied().fold(f64::MAX, f64::min);
    assert!(
        spread_flat <= 1.0,
        "flat laser line bends by {spread_flat} px"
    );
}

#[test]
fn folds_shadow_each_other_through_visibility_maps() {
    let scene = Scene::load("folded-cloth").unwrap();
    // Folds run at 20°+90°: light at 80° along 20° rakes across them.
    let s = shot(dir(80.0, 20.0), dir(0.0, 0.0), 160, 160);
    assert!(scene.plan(&s).has(Effect::VisibilityMaps));
    let shadowed = shadowed_fraction(&scene, &s, "-noise", "-noise,-visibility-maps");
    let steep = shadowed_fraction(
        &scene,
        &shot(dir(20.0, 20.0), dir(0.0, 0.0), 160, 160),
        "-noise",
        "-noise,-visibility-maps",
    );
    eprintln!("folded cloth shadowed by its folds: {shadowed:.2} at 80°, {steep:.2} at 20°");
    assert!(shadowed > 0.1 && steep < 0.02, "{shadowed} {steep}");
}

#[test]
fn bad_scene_files_name_the_key() {
    let cases = [
        (
            WHITE_FLAT.replace("[100.0, 100.0]", "[150.0, 100.0]"),
            "sample.size_mm[0]",
        ),
        (
            WHITE_FLAT.replace("resolution = 64", "resolution = 64\nshine = 1"),
            "shine",
        ),
        (
            format!("{WHITE_FLAT}\n[effects]\nsparkle = true\n"),
            "effects.sparkle",
        ),
        (
            WHITE_FLAT.replace("read_noise_dn = 2.0", "read_noise_dn = -2.0"),
            "sensor.read_noise_dn",
        ),
    ];
    for (text, key) in cases {
        let err = Scene::from_toml(&text, "bad.toml", None)
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("bad.toml") && err.contains(key), "{err}");
    }
    let err = Scene::load("no-such-scene").unwrap_err().to_string();
    assert!(err.contains("flat-calibration"), "{err}");
}

#[test]
fn image_heightfields_and_albedos_load_relative_to_the_scene_file() {
    let dir = std::env::temp_dir().join(format!("rigd-scene-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // A left-to-right ramp: black (0) to white (the amplitude).
    let (w, h) = (64u32, 32u32);
    let data: Vec<u8> = (0..h)
        .flat_map(|_| (0..w).map(|i| (i * 255 / (w - 1)) as u8))
        .collect();
    let mut png_bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut png_bytes, w, h);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        enc.write_header().unwrap().write_image_data(&data).unwrap();
    }
    std::fs::write(dir.join("ramp.png"), &png_bytes).unwrap();
    let scene_path = dir.join("ramp.toml");
    std::fs::write(
        &scene_path,
        r#"
name = "ramp"
[sample]
size_mm = [80.0, 80.0]
resolution = 128
albedo = { pattern = "image", path = "ramp.png", min = 0.2, max = 0.6 }
heightfield = { kind = "image", path = "ramp.png", amplitude_mm = 2.0 }
"#,
    )
    .unwrap();
    let scene = Scene::load(scene_path.to_str().unwrap()).unwrap();
    let left = scene.true_height(-0.039, 0.0) * 1e3;
    let right = scene.true_height(0.039, 0.0) * 1e3;
    let mid = scene.true_height(0.0, 0.0) * 1e3;
    assert!(
        left < 0.1 && right > 1.9 && (mid - 1.0).abs() < 0.1,
        "{left} {mid} {right}"
    );
    assert!((scene.albedo(0.0, 0.01) - 0.4).abs() < 0.02);
    let n = scene.true_normal(0.0, 0.0);
    // Slope 2 mm over 80 mm: the normal leans towards −x.
    assert!((n[0] + 0.025).abs() < 0.003 && n[1].abs() < 1e-3, "{n:?}");
    std::fs::write(dir.join("broken.toml"), "name = \"b\"\n[sample]\nsize_mm = [50.0, 50.0]\nalbedo = { pattern = \"image\", path = \"missing.png\", min = 0.0, max = 1.0 }\n").unwrap();
    let err = Scene::load(dir.join("broken.toml").to_str().unwrap())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("sample.albedo.path") && err.contains("missing.png"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A hardware run is rectified against the standard holder plate
/// (`rigd_core::holder::Holder::standard`); the default scene shows that
/// same plate, so simulated and real runs register alike.
#[test]
fn the_default_scene_shows_the_standard_holder() {
    let scene = Scene::load(rigd_sim::scene::DEFAULT_SCENE).unwrap();
    let standard = rigd_core::holder::Holder::standard();
    assert_eq!(scene.holder.markers(), standard.markers());
    assert_eq!(scene.holder.point_radius, standard.point_radius);
    let half = rigd_core::holder::STANDARD_SAMPLE_MM * 1e-3 / 2.0;
    assert_eq!(scene.sample_half, [half, half]);
}
