//! Photometric stereo on analytic scenes rendered here (Lambertian, plus cast
//! shadows and Blinn–Phong highlights for robust mode), written as PNGs and
//! read back through the same path `rigd process photometric-stereo` uses.

use std::f64::consts::PI;
use std::path::{Path, PathBuf};

use proptest::prelude::*;
use rigd_process::image_io::{self, Image, PngDepth};
use rigd_process::npy;
use rigd_process::photometric_stereo::{
    integrate_frankot_chellappa, load_inputs, solve, solve_images, write_outputs, PsError,
    PsInputs, PsOptions, PsResult,
};

/// A surface: per pixel unit normal (x right, y up, z to camera), albedo
/// per channel and, when known, height (pixel units).
struct Scene {
    width: usize,
    height: usize,
    normals: Vec<[f64; 3]>,
    albedo: Vec<[f64; 3]>,
    heights: Vec<f64>,
    /// Height at fractional (column, row); used to trace cast shadows.
    height_at: Box<dyn Fn(f64, f64) -> f64>,
}

fn albedo_at(x: usize, y: usize) -> [f64; 3] {
    let a = 0.55 + 0.25 * (x as f64 * 0.31).sin() * (y as f64 * 0.23).cos();
    [a, 0.8 * a + 0.1, 0.85 - 0.5 * a]
}

/// Shallow spherical cap: radius 1.5 × width, so slopes stay below ~30°
/// and every light of the tests sees every pixel.
fn sphere_cap(width: usize, height: usize) -> Scene {
    let radius = 1.5 * width as f64;
    let (cx, cy) = ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0);
    let mut scene = Scene {
        width,
        height,
        normals: Vec::new(),
        albedo: Vec::new(),
        heights: Vec::new(),
        height_at: Box::new(move |c, r| {
            let (x, y) = (c - cx, cy - r);
            (radius * radius - x * x - y * y).sqrt()
        }),
    };
    for r in 0..height {
        for c in 0..width {
            let (x, y) = (c as f64 - cx, cy - r as f64);
            let z = (radius * radius - x * x - y * y).sqrt();
            scene.normals.push([x / radius, y / radius, z / radius]);
            scene.albedo.push(albedo_at(c, r));
            scene.heights.push(z);
        }
    }
    scene
}

/// Periodic heightfield `z = A sin(2πc/P) sin(2πr/P)` plus a slant-free
/// second term to break symmetry; rows r increase downwards, y = -r.
fn sinusoid(size: usize, period: f64, amplitude: f64) -> Scene {
    let k = 2.0 * PI / period;
    let z = move |c: f64, r: f64| {
        amplitude * ((k * c).sin() * (k * r).sin() + 0.3 * (k * c + 2.0 * k * r).cos())
    };
    let mut scene = Scene {
        width: size,
        height: size,
        normals: Vec::new(),
        albedo: Vec::new(),
        heights: Vec::new(),
        height_at: Box::new(z),
    };
    for r in 0..size {
        for c in 0..size {
            let (cf, rf) = (c as f64, r as f64);
            let dz_dc = amplitude
                * (k * (k * cf).cos() * (k * rf).sin() - 0.3 * k * (k * cf + 2.0 * k * rf).sin());
            let dz_dr = amplitude
                * (k * (k * cf).sin() * (k * rf).cos() - 0.6 * k * (k * cf + 2.0 * k * rf).sin());
            let (p, q) = (dz_dc, -dz_dr);
            let norm = (p * p + q * q + 1.0).sqrt();
            scene.normals.push([-p / norm, -q / norm, 1.0 / norm]);
            scene.albedo.push(albedo_at(c, r));
            scene.heights.push(z(cf, rf));
        }
    }
    scene
}

fn direction(tilt_deg: f64, slant_deg: f64) -> [f64; 3] {
    let (t, s) = (tilt_deg.to_radians(), slant_deg.to_radians());
    [t.cos() * s.sin(), t.sin() * s.sin(), s.cos()]
}

fn three_lights() -> Vec<[f64; 3]> {
    (0..3)
        .map(|i| direction(90.0 + 120.0 * i as f64, 40.0))
        .collect()
}

/// 12 lights, tilts 30° apart, slants alternating between 30° and 50°.
fn twelve_lights() -> Vec<[f64; 3]> {
    (0..12)
        .map(|i| direction(15.0 + 30.0 * i as f64, if i % 2 == 0 { 30.0 } else { 50.0 }))
        .collect()
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[derive(Default, Clone, Copy)]
struct Effects {
    cast_shadows: bool,
    /// Blinn–Phong `(strength, exponent)` with the camera along +z.
    specular: Option<(f64, f64)>,
}

/// True if the heightfield blocks light `l` from pixel (c, r).
fn in_cast_shadow(scene: &Scene, c: usize, r: usize, l: [f64; 3]) -> bool {
    let horizontal = (l[0] * l[0] + l[1] * l[1]).sqrt();
    if horizontal < 1e-9 {
        return false;
    }
    let (dc, dr, rise) = (l[0] / horizontal, -l[1] / horizontal, l[2] / horizontal);
    let start = (scene.height_at)(c as f64, r as f64);
    let mut t = 0.25;
    while t < 60.0 {
        let ray = start + t * rise;
        if (scene.height_at)(c as f64 + t * dc, r as f64 + t * dr) > ray + 1e-9 {
            return true;
        }
        t += 0.25;
    }
    false
}

/// Renders one image per light, clamped to [0, 1]; `intensities` scale
/// each light per channel.
fn render(
    scene: &Scene,
    lights: &[[f64; 3]],
    channels: usize,
    intensities: Option<&[[f64; 3]]>,
    effects: Effects,
) -> Vec<Image> {
    lights
        .iter()
        .enumerate()
        .map(|(i, &l)| {
            let mut image = Image::new(scene.width, scene.height, channels);
            let half = {
                let h = [l[0], l[1], l[2] + 1.0];
                let n = dot(h, h).sqrt();
                [h[0] / n, h[1] / n, h[2] / n]
            };
            for r in 0..scene.height {
                for c in 0..scene.width {
                    let index = r * scene.width + c;
                    let n = scene.normals[index];
                    if effects.cast_shadows && in_cast_shadow(scene, c, r, l) {
                        continue;
                    }
                    let shading = dot(n, l).max(0.0);
                    let highlight = match effects.specular {
                        Some((strength, exponent)) if shading > 0.0 => {
                            strength * dot(n, half).max(0.0).powf(exponent)
                        }
                        _ => 0.0,
                    };
                    for ch in 0..channels {
                        let albedo = if channels == 1 {
                            scene.albedo[index][0]
                        } else {
                            scene.albedo[index][ch]
                        };
                        let intensity = intensities.map_or(1.0, |t| t[i][ch]);
                        let v = (albedo * shading + highlight) * intensity;
                        image.set(c, r, ch, v.clamp(0.0, 1.0) as f32);
                    }
                }
            }
            image
        })
        .collect()
}

/// Writes `img_NN.png` and `lights.txt` into `dir`.
fn write_dataset(dir: &Path, images: &[Image], lights: &[[f64; 3]], depth: PngDepth) -> PsInputs {
    for (i, image) in images.iter().enumerate() {
        image_io::write_png(&dir.join(format!("img_{i:02}.png")), image, depth).unwrap();
    }
    let mut table = String::from("# x y z (x right, y up, z to camera)\n");
    for l in lights {
        table.push_str(&format!("{} {} {}\n", l[0], l[1], l[2]));
    }
    let lights_file = dir.join("lights.txt");
    std::fs::write(&lights_file, table).unwrap();
    PsInputs {
        images_dir: dir.to_path_buf(),
        lights_file,
        ..PsInputs::default()
    }
}

fn angle_deg(a: [f32; 3], b: [f64; 3]) -> f64 {
    let a = [f64::from(a[0]), f64::from(a[1]), f64::from(a[2])];
    let cos = dot(a, b) / (dot(a, a).sqrt() * dot(b, b).sqrt());
    cos.clamp(-1.0, 1.0).acos().to_degrees()
}

/// Mean angular error over the pixels `keep` accepts.
fn mean_angle_where(result: &PsResult, scene: &Scene, keep: impl Fn(usize) -> bool) -> f64 {
    let (mut sum, mut count) = (0.0, 0usize);
    for (i, (&n, &truth)) in result.normals.iter().zip(&scene.normals).enumerate() {
        if keep(i) {
            sum += angle_deg(n, truth);
            count += 1;
        }
    }
    assert!(count > 0);
    sum / count as f64
}

fn mean_angle(result: &PsResult, scene: &Scene) -> f64 {
    mean_angle_where(result, scene, |_| true)
}

fn plain() -> PsOptions<'static> {
    PsOptions::default()
}

fn robust() -> PsOptions<'static> {
    PsOptions {
        robust: true,
        ..PsOptions::default()
    }
}

fn solve_dir(inputs: &PsInputs, opts: &PsOptions) -> PsResult {
    solve(&load_inputs(inputs).unwrap(), opts).unwrap()
}

fn assert_all_finite(result: &PsResult) {
    assert!(result.normals.iter().flatten().all(|v| v.is_finite()));
    for values in [&result.albedo, &result.p, &result.q, &result.height_map] {
        assert!(values.iter().all(|v| v.is_finite()));
    }
}

#[test]
fn three_lights_16bit_grey_sphere_under_one_degree() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(64, 48);
    let lights = three_lights();
    let images = render(&scene, &lights, 1, None, Effects::default());
    let inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Sixteen);
    let result = solve_dir(&inputs, &plain());
    let error = mean_angle(&result, &scene);
    eprintln!("mean angular error, 3 lights, 16-bit grey, plain: {error:.4}°");
    assert!(error < 1.0, "{error}");
    assert_eq!(result.report.pixels_valid, 64 * 48);
    assert!(result.report.mean_residual < 1e-9, "3 lights fit exactly");
    for (i, a) in result.albedo.iter().enumerate() {
        assert!(
            (f64::from(*a) - scene.albedo[i][0]).abs() < 2e-3,
            "albedo at {i}: {a}"
        );
    }
}

#[test]
fn twelve_lights_16bit_grey_sphere_plain_and_robust_under_one_degree() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(64, 48);
    let lights = twelve_lights();
    let images = render(&scene, &lights, 1, None, Effects::default());
    let inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Sixteen);
    let dataset = load_inputs(&inputs).unwrap();
    let plain_result = solve(&dataset, &plain()).unwrap();
    let robust_result = solve(&dataset, &robust()).unwrap();
    let (e_plain, e_robust) = (
        mean_angle(&plain_result, &scene),
        mean_angle(&robust_result, &scene),
    );
    eprintln!("mean angular error, 12 lights, 16-bit grey, clean: plain {e_plain:.4}°, robust {e_robust:.4}°");
    assert!(e_plain < 1.0, "{e_plain}");
    assert!(e_robust < 1.0, "{e_robust}");
    assert!(
        plain_result.report.condition_number > 1.0 && plain_result.report.condition_number < 10.0
    );
}

#[test]
fn eight_bit_input_is_accurate_to_quantisation() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(64, 48);
    let lights = twelve_lights();
    let images = render(&scene, &lights, 1, None, Effects::default());
    let inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Eight);
    let result = solve_dir(&inputs, &plain());
    let error = mean_angle(&result, &scene);
    eprintln!("mean angular error, 12 lights, 8-bit grey, plain: {error:.4}°");
    assert!(error < 1.0, "{error}");
    // 8-bit must be measurably worse than 16-bit, or the depth was not honoured.
    let dir16 = tempfile::tempdir().unwrap();
    let inputs16 = write_dataset(dir16.path(), &images, &lights, PngDepth::Sixteen);
    assert!(mean_angle(&solve_dir(&inputs16, &plain()), &scene) < error);
}

#[test]
fn rgb_input_gives_luminance_normals_and_per_channel_albedo() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(48, 40);
    let lights = twelve_lights();
    let images = render(&scene, &lights, 3, None, Effects::default());
    let inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Sixteen);
    let result = solve_dir(&inputs, &plain());
    let error = mean_angle(&result, &scene);
    eprintln!("mean angular error, 12 lights, 16-bit RGB, plain: {error:.4}°");
    assert!(error < 1.0, "{error}");
    assert_eq!(result.albedo_channels, 3);
    for (i, px) in result.albedo.chunks(3).enumerate() {
        for (c, (&got, &expected)) in px.iter().zip(&scene.albedo[i]).enumerate() {
            assert!(
                (f64::from(got) - expected).abs() < 2e-3,
                "pixel {i} channel {c}: {got} vs {expected}"
            );
        }
    }
    let out = dir.path().join("out");
    write_outputs(&result, &out).unwrap();
    assert_eq!(
        npy::read_f32(&out.join("albedo.npy")).unwrap().shape,
        vec![40, 48, 3]
    );
    assert_eq!(
        image_io::load_png(&out.join("albedo.png"))
            .unwrap()
            .channels,
        3
    );
}

#[test]
fn intensities_are_divided_out_per_channel() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(48, 40);
    let lights = twelve_lights();
    let intensities: Vec<[f64; 3]> = (0..12)
        .map(|i| {
            [
                0.6 + 0.03 * i as f64,
                0.9 - 0.04 * i as f64,
                0.7 + 0.02 * (i % 5) as f64,
            ]
        })
        .collect();
    let images = render(&scene, &lights, 3, Some(&intensities), Effects::default());
    let mut inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Sixteen);
    let without = solve_dir(&inputs, &plain());
    let table: String = intensities
        .iter()
        .map(|t| format!("{} {} {}\n", t[0], t[1], t[2]))
        .collect();
    let file = dir.path().join("intensities.txt");
    std::fs::write(&file, table).unwrap();
    inputs.intensities_file = Some(file);
    let with = solve_dir(&inputs, &plain());
    let (e_with, e_without) = (mean_angle(&with, &scene), mean_angle(&without, &scene));
    eprintln!("intensities: error with table {e_with:.4}°, without {e_without:.4}°");
    assert!(e_with < 1.0, "{e_with}");
    assert!(
        e_without > 2.0,
        "unequal intensities must matter: {e_without}"
    );
    for (i, px) in with.albedo.chunks(3).enumerate() {
        for (&got, &expected) in px.iter().zip(&scene.albedo[i]) {
            assert!((f64::from(got) - expected).abs() < 3e-3, "pixel {i}");
        }
    }
    assert_eq!(with.report.intensities.as_deref(), Some(&intensities[..]));
}

#[test]
fn mask_invalidates_pixels_and_is_not_an_input_image() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(40, 30);
    let lights = twelve_lights();
    let images = render(&scene, &lights, 1, None, Effects::default());
    let mut inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Sixteen);
    let mut mask = Image::new(40, 30, 1);
    for r in 0..30 {
        for c in 20..40 {
            mask.set(c, r, 0, 1.0);
        }
    }
    // Inside the images folder on purpose: it must not be taken for a 13th image.
    let mask_file = dir.path().join("zz_mask.png");
    image_io::write_png(&mask_file, &mask, PngDepth::Eight).unwrap();
    inputs.mask_file = Some(mask_file);
    let result = solve_dir(&inputs, &plain());
    assert_eq!(result.report.pixels_masked, 20 * 30);
    assert_eq!(result.report.pixels_valid, 20 * 30);
    for i in 0..40 * 30 {
        if i % 40 < 20 {
            assert!(!result.valid[i]);
            assert_eq!(result.normals[i], [0.0, 0.0, 1.0]);
            assert_eq!(
                (result.albedo[i], result.p[i], result.q[i]),
                (0.0, 0.0, 0.0)
            );
        } else {
            assert!(result.valid[i]);
        }
    }
    assert!(mean_angle_where(&result, &scene, |i| i % 40 >= 20) < 1.0);
}

#[test]
fn robust_mode_beats_plain_with_cast_shadows_and_highlights() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sinusoid(72, 24.0, 2.5);
    // Low lights cast shadows over the bumps; high ones put highlights on them.
    let lights: Vec<[f64; 3]> = (0..12)
        .map(|i| direction(30.0 * i as f64, if i % 2 == 0 { 60.0 } else { 35.0 }))
        .collect();
    let effects = Effects {
        cast_shadows: true,
        specular: Some((0.8, 200.0)),
    };
    let images = render(&scene, &lights, 1, None, effects);
    let total_samples = 12 * 72 * 72;
    let shadowed = images
        .iter()
        .flat_map(|im| &im.data)
        .filter(|&&v| v == 0.0)
        .count();
    let clean = render(&scene, &lights, 1, None, Effects::default());
    let spiked = images
        .iter()
        .zip(&clean)
        .flat_map(|(a, b)| a.data.iter().zip(&b.data))
        .filter(|(a, b)| **a > **b + 0.05)
        .count();
    eprintln!(
        "robust scene: {:.1}% samples shadowed, {:.1}% with a highlight above 0.05",
        100.0 * shadowed as f64 / total_samples as f64,
        100.0 * spiked as f64 / total_samples as f64
    );
    assert!(
        shadowed * 50 > total_samples && spiked * 100 > total_samples,
        "scene must have both effects"
    );

    let inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Sixteen);
    let dataset = load_inputs(&inputs).unwrap();
    let plain_result = solve(&dataset, &plain()).unwrap();
    let robust_result = solve(&dataset, &robust()).unwrap();
    let (e_plain, e_robust) = (
        mean_angle(&plain_result, &scene),
        mean_angle(&robust_result, &scene),
    );
    let r = &robust_result.report;
    eprintln!(
        "mean angular error, 12 lights, 16-bit, shadows + highlights: plain {e_plain:.4}°, robust {e_robust:.4}° \
         (rejected {} shadow, {} specular, {} saturated samples; {} fallback pixels)",
        r.samples_rejected_shadow, r.samples_rejected_specular, r.samples_rejected_saturated, r.pixels_fallback
    );
    assert!(
        e_robust < 0.25 * e_plain,
        "robust {e_robust} vs plain {e_plain}"
    );
    assert!(e_robust < 1.0, "{e_robust}");
    assert!(r.samples_rejected_shadow > 0 && r.samples_rejected_specular > 0);
    assert_all_finite(&robust_result);
}

fn write_lights(dir: &Path, lights: &[[f64; 3]]) -> PathBuf {
    let path = dir.join("lights.txt");
    let table: String = lights
        .iter()
        .map(|l| format!("{} {} {}\n", l[0], l[1], l[2]))
        .collect();
    std::fs::write(&path, table).unwrap();
    path
}

#[test]
fn near_coplanar_lights_fail_reporting_the_condition_number() {
    let dir = tempfile::tempdir().unwrap();
    let eps = 1e-8;
    let lights = [[1.0, 0.0, eps], [0.0, 1.0, eps], [-1.0, -1.0, 2.0 * eps]];
    let scene = sphere_cap(16, 16);
    let images = render(&scene, &three_lights(), 1, None, Effects::default());
    let inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Sixteen);
    let err = solve(&load_inputs(&inputs).unwrap(), &plain()).unwrap_err();
    let message = err.to_string();
    eprintln!("{message}");
    match err {
        PsError::IllConditioned { condition, max, .. } => {
            assert!(condition > 1e7 && condition < 1e10, "{condition}");
            assert_eq!(max, 1e6);
        }
        other => panic!("expected IllConditioned, got {other:?}"),
    }
    assert!(
        message.contains("condition number") && message.contains("lights.txt"),
        "{message}"
    );
    // The limit is an option: raising it lets the (useless) solve through.
    let lenient = PsOptions {
        max_condition: 1e12,
        ..PsOptions::default()
    };
    assert!(solve(&load_inputs(&inputs).unwrap(), &lenient).is_ok());
}

#[test]
fn repeated_lights_fail() {
    let scene = sphere_cap(16, 16);
    let l = three_lights();
    for lights in [vec![l[0], l[1], l[1]], vec![l[0], l[1], l[0], l[1]]] {
        let images = render(&scene, &lights, 1, None, Effects::default());
        for opts in [plain(), robust()] {
            match solve_images(&images, &lights, None, &opts) {
                Err(PsError::IllConditioned { condition, .. }) => assert!(condition > 1e6),
                other => panic!("expected IllConditioned, got {:?}", other.map(|r| r.report)),
            }
        }
    }
}

#[test]
fn frankot_chellappa_recovers_a_periodic_heightfield() {
    // Odd, non-power-of-two size; terms differ along x and y so a swapped
    // axis or flipped sign cannot pass.
    let (w, h) = (45usize, 32usize);
    let (kx, ky) = (2.0 * PI / w as f64, 2.0 * PI / h as f64);
    let z = |c: f64, r: f64| {
        2.0 * (kx * c).sin() + 1.5 * (2.0 * ky * r).cos() + 0.7 * (3.0 * kx * c + ky * r).sin()
    };
    let dz_dc =
        |c: f64, r: f64| 2.0 * kx * (kx * c).cos() + 0.7 * 3.0 * kx * (3.0 * kx * c + ky * r).cos();
    let dz_dr = |c: f64, r: f64| {
        -1.5 * 2.0 * ky * (2.0 * ky * r).sin() + 0.7 * ky * (3.0 * kx * c + ky * r).cos()
    };
    let (mut p, mut q, mut truth) = (Vec::new(), Vec::new(), Vec::new());
    for r in 0..h {
        for c in 0..w {
            let (cf, rf) = (c as f64, r as f64);
            p.push(dz_dc(cf, rf) as f32);
            q.push(-dz_dr(cf, rf) as f32); // y is up
            truth.push(z(cf, rf));
        }
    }
    let mean = truth.iter().sum::<f64>() / truth.len() as f64;
    let height = integrate_frankot_chellappa(&p, &q, w, h).unwrap();
    let max_error = height
        .iter()
        .zip(&truth)
        .map(|(&a, &b)| (f64::from(a) - (b - mean)).abs())
        .fold(0.0, f64::max);
    eprintln!("Frankot–Chellappa max error on a 45x32 periodic field: {max_error:.2e}");
    assert!(max_error < 1e-4, "{max_error}");
    assert!(
        height.iter().map(|&v| f64::from(v)).sum::<f64>().abs() < 1e-3,
        "zero mean"
    );
    let flipped: Vec<f32> = q.iter().map(|v| -v).collect();
    let wrong = integrate_frankot_chellappa(&p, &flipped, w, h).unwrap();
    assert!(wrong.iter().zip(&height).any(|(a, b)| (a - b).abs() > 0.5));
    assert!(integrate_frankot_chellappa(&p[1..], &q, w, h).is_err());
}

#[test]
fn end_to_end_height_matches_the_rendered_sinusoid() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sinusoid(48, 24.0, 1.0);
    let lights = twelve_lights();
    let images = render(&scene, &lights, 1, None, Effects::default());
    let inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Sixteen);
    let result = solve_dir(&inputs, &plain());
    let out = dir.path().join("out");
    write_outputs(&result, &out).unwrap();
    let height = npy::read_f32(&out.join("height.npy")).unwrap();
    assert_eq!(height.shape, vec![48, 48]);
    let mean = scene.heights.iter().sum::<f64>() / scene.heights.len() as f64;
    let rms = (height
        .data
        .iter()
        .zip(&scene.heights)
        .map(|(&a, &b)| (f64::from(a) - (b - mean)).powi(2))
        .sum::<f64>()
        / scene.heights.len() as f64)
        .sqrt();
    eprintln!("end-to-end height RMS error (amplitude 1): {rms:.2e}");
    assert!(rms < 0.01, "{rms}");
    let q = npy::read_f32(&out.join("q.npy")).unwrap();
    let expected_q0 = -scene.normals[0][1] / scene.normals[0][2];
    assert!((f64::from(q.data[0]) - expected_q0).abs() < 1e-3);
}

#[test]
fn dark_and_saturated_pixels_give_finite_outputs() {
    let scene = sphere_cap(32, 24);
    let lights = twelve_lights();
    let mut images = render(&scene, &lights, 3, None, Effects::default());
    let dark = |i: usize| i % 32 < 4;
    let saturated = |i: usize| i % 32 >= 28;
    for image in &mut images {
        for (i, px) in image.data.chunks_mut(3).enumerate() {
            if dark(i) {
                px.fill(0.0);
            } else if saturated(i) {
                px.fill(1.0);
            }
        }
    }
    for opts in [plain(), robust()] {
        let result = solve_images(&images, &lights, None, &opts).unwrap();
        assert_all_finite(&result);
        assert_eq!(result.report.pixels_dark, 4 * 24);
        assert_eq!(result.report.pixels_saturated, 4 * 24);
        for i in 0..32 * 24 {
            if dark(i) || saturated(i) {
                assert_eq!(result.normals[i], [0.0, 0.0, 1.0]);
                assert!(result.albedo[3 * i..3 * i + 3].iter().all(|&a| a == 0.0));
            }
        }
        assert!(mean_angle_where(&result, &scene, |i| !dark(i) && !saturated(i)) < 1.0);
        let dir = tempfile::tempdir().unwrap();
        write_outputs(&result, dir.path()).unwrap();
        for name in ["normals.npy", "albedo.npy", "height.npy", "p.npy", "q.npy"] {
            let array = npy::read_f32(&dir.path().join(name)).unwrap();
            assert!(array.data.iter().all(|v| v.is_finite()), "{name}");
        }
    }
}

#[test]
fn robust_pixels_left_with_too_few_lights_fall_back_to_plain() {
    let scene = sphere_cap(16, 16);
    let lights: Vec<[f64; 3]> = (0..4).map(|i| direction(90.0 * i as f64, 40.0)).collect();
    let mut images = render(&scene, &lights, 1, None, Effects::default());
    // Two of four samples shadowed in the top rows: robust mode keeps only 2.
    for image in &mut images[..2] {
        image.data[..3 * 16].fill(0.0);
    }
    let result = solve_images(&images, &lights, None, &robust()).unwrap();
    assert_all_finite(&result);
    assert_eq!(result.report.pixels_fallback, 3 * 16);
    assert_eq!(result.report.pixels_valid, 16 * 16);
    let clean = mean_angle_where(&result, &scene, |i| i >= 3 * 16);
    assert!(clean < 1.0, "{clean}");
}

#[test]
fn write_outputs_writes_every_file_and_nothing_else() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(20, 12);
    let lights = twelve_lights();
    let images = render(&scene, &lights, 1, None, Effects::default());
    let result = solve_images(&images, &lights, None, &plain()).unwrap();
    let out = dir.path().join("nested").join("out");
    let written = write_outputs(&result, &out).unwrap();
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    let expected = [
        "albedo.npy",
        "albedo.png",
        "height.npy",
        "height.png",
        "normals.npy",
        "normals.png",
        "p.npy",
        "q.npy",
        "report.json",
    ];
    assert_eq!(names, expected);
    assert_eq!(written.len(), expected.len());
    let normals = npy::read_f32(&out.join("normals.npy")).unwrap();
    assert_eq!(normals.shape, vec![12, 20, 3]);
    for n in normals.data.chunks(3) {
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        assert!((len - 1.0).abs() < 1e-5);
    }
    assert_eq!(
        npy::read_f32(&out.join("albedo.npy")).unwrap().shape,
        vec![12, 20]
    );
    let png = image_io::load_png(&out.join("normals.png")).unwrap();
    assert_eq!((png.width, png.height, png.channels), (20, 12, 3));
    let n0 = result.normals[0];
    assert!((png.data[0] - 0.5 * (n0[0] + 1.0)).abs() <= 0.5 / 255.0 + 1e-6);
    let report = std::fs::read_to_string(out.join("report.json")).unwrap();
    for key in [
        "\"condition_number\"",
        "\"mean_residual\"",
        "\"lights_used\": 12",
        "\"pixels_masked\": 0",
        "\"mode\": \"plain\"",
    ] {
        assert!(report.contains(key), "{key} missing from {report}");
    }
}

#[test]
fn progress_reports_every_row() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let scene = sphere_cap(10, 17);
    let lights = three_lights();
    let images = render(&scene, &lights, 1, None, Effects::default());
    let (calls, last) = (AtomicUsize::new(0), AtomicUsize::new(0));
    let progress = |done: usize, total: usize| {
        assert_eq!(total, 17);
        calls.fetch_add(1, Ordering::Relaxed);
        last.fetch_max(done, Ordering::Relaxed);
    };
    let opts = PsOptions {
        progress: Some(&progress),
        ..PsOptions::default()
    };
    solve_images(&images, &lights, None, &opts).unwrap();
    assert_eq!(calls.load(Ordering::Relaxed), 17);
    assert_eq!(last.load(Ordering::Relaxed), 17);
}

#[test]
fn names_file_selects_and_orders_images() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(24, 16);
    let lights = twelve_lights();
    let images = render(&scene, &lights, 1, None, Effects::default());
    let mut inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Sixteen);
    // Reverse the order in both tables: the result must not change.
    let reversed: Vec<[f64; 3]> = lights.iter().rev().copied().collect();
    inputs.lights_file = write_lights(dir.path(), &reversed);
    let names: String = (0..12).rev().map(|i| format!("img_{i:02}.png\n")).collect();
    let names_file = dir.path().join("names.txt");
    std::fs::write(&names_file, format!("# reversed\n{names}")).unwrap();
    inputs.names_file = Some(names_file);
    let result = solve_dir(&inputs, &plain());
    assert!(mean_angle(&result, &scene) < 1.0);
    assert!(result.report.images[0].ends_with("img_11.png"));
}

#[test]
fn light_count_mismatch_names_the_lights_file() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(8, 8);
    let lights = twelve_lights();
    let images = render(&scene, &lights[..4], 1, None, Effects::default());
    let inputs = write_dataset(dir.path(), &images, &lights[..3], PngDepth::Eight);
    let err = load_inputs(&inputs).unwrap_err();
    let message = err.to_string();
    assert!(
        matches!(
            err,
            PsError::CountMismatch {
                found: 3,
                expected: 4,
                ..
            }
        ),
        "{message}"
    );
    assert!(message.contains("lights.txt"), "{message}");
}

#[test]
fn mismatched_image_size_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(12, 10);
    let lights = three_lights();
    let images = render(&scene, &lights, 1, None, Effects::default());
    let inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Eight);
    image_io::write_png(
        &dir.path().join("img_02.png"),
        &Image::new(10, 10, 1),
        PngDepth::Eight,
    )
    .unwrap();
    let message = load_inputs(&inputs).unwrap_err().to_string();
    assert!(
        message.contains("img_02.png") && message.contains("10x10"),
        "{message}"
    );
    // Channel count too.
    image_io::write_png(
        &dir.path().join("img_02.png"),
        &Image::new(12, 10, 3),
        PngDepth::Eight,
    )
    .unwrap();
    let message = load_inputs(&inputs).unwrap_err().to_string();
    assert!(
        message.contains("img_02.png") && message.contains("RGB"),
        "{message}"
    );
}

#[test]
fn unreadable_inputs_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let scene = sphere_cap(12, 10);
    let lights = three_lights();
    let images = render(&scene, &lights, 1, None, Effects::default());
    let mut inputs = write_dataset(dir.path(), &images, &lights, PngDepth::Eight);
    std::fs::write(dir.path().join("img_01.png"), b"\x89PNG truncated").unwrap();
    let message = load_inputs(&inputs).unwrap_err().to_string();
    assert!(message.contains("img_01.png"), "{message}");

    inputs.lights_file = dir.path().join("no-such-lights.txt");
    let message = load_inputs(&inputs).unwrap_err().to_string();
    assert!(message.contains("no-such-lights.txt"), "{message}");

    let bad = dir.path().join("bad-lights.txt");
    std::fs::write(&bad, "0 0 1\n# comment\n0.1 zero 1\n").unwrap();
    inputs.lights_file = bad;
    let message = load_inputs(&inputs).unwrap_err().to_string();
    assert!(message.contains("bad-lights.txt:3"), "{message}");

    inputs.lights_file = write_lights(dir.path(), &lights);
    image_io::write_png(&dir.path().join("img_01.png"), &images[1], PngDepth::Eight).unwrap();
    load_inputs(&inputs).unwrap();
    inputs.mask_file = Some(dir.path().join("missing-mask.png"));
    let message = load_inputs(&inputs).unwrap_err().to_string();
    assert!(message.contains("missing-mask.png"), "{message}");

    let empty = tempfile::tempdir().unwrap();
    inputs.images_dir = empty.path().to_path_buf();
    inputs.mask_file = None;
    assert!(matches!(
        load_inputs(&inputs),
        Err(PsError::NoImages { .. })
    ));
}

#[test]
fn in_memory_input_errors_are_typed() {
    let scene = sphere_cap(8, 8);
    let lights = three_lights();
    let mut images = render(&scene, &lights, 1, None, Effects::default());
    assert!(matches!(
        solve_images(&images, &lights[..2], None, &plain()),
        Err(PsError::InvalidInput { .. })
    ));
    assert!(matches!(
        solve_images(&images[..2], &lights[..2], None, &plain()),
        Err(PsError::TooFewLights { count: 2, .. })
    ));
    assert!(matches!(
        solve_images(&images, &lights, Some(&[true; 3]), &plain()),
        Err(PsError::MaskMismatch { .. })
    ));
    images[1] = Image::new(7, 8, 1);
    let message = solve_images(&images, &lights, None, &plain())
        .unwrap_err()
        .to_string();
    assert!(message.contains("image #1"), "{message}");
}

fn shape_and_bits() -> impl Strategy<Value = (Vec<usize>, Vec<u32>)> {
    (
        0usize..10,
        0usize..10,
        prop_oneof![Just(0usize), Just(3usize), 1usize..5],
    )
        .prop_flat_map(|(h, w, c)| {
            let shape = if c == 0 { vec![h, w] } else { vec![h, w, c] };
            let n: usize = shape.iter().product();
            (Just(shape), proptest::collection::vec(any::<u32>(), n))
        })
}

proptest! {
    // No regression files: integration tests have no lib.rs for proptest to sit beside.
    #![proptest_config(ProptestConfig { cases: 128, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn npy_round_trips_shape_and_exact_bits((shape, bits) in shape_and_bits()) {
        // Arbitrary bit patterns, NaNs included: the round trip must be bit-exact.
        let data: Vec<f32> = bits.iter().map(|&b| f32::from_bits(b)).collect();
        let back = npy::decode_f32(&npy::encode_f32(&shape, &data).unwrap()).unwrap();
        prop_assert_eq!(&back.shape, &shape);
        let back_bits: Vec<u32> = back.data.iter().map(|v| v.to_bits()).collect();
        prop_assert_eq!(back_bits, bits);
    }

    #[test]
    fn npy_file_round_trip(h in 1usize..6, w in 1usize..6, rgb in any::<bool>(), seed in any::<u32>()) {
        let shape = if rgb { vec![h, w, 3] } else { vec![h, w] };
        let n: usize = shape.iter().product();
        let data: Vec<f32> = (0..n).map(|i| (seed as f32) * 1e-3 - i as f32 * 0.5).collect();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.npy");
        npy::write_f32(&path, &shape, &data).unwrap();
        let back = npy::read_f32(&path).unwrap();
        prop_assert_eq!(back.shape, shape);
        prop_assert_eq!(back.data, data);
    }
}
