//! Frames per second of the scene renderer, and what each effect costs.
//!
//! `cargo bench -p rigd-sim --bench render`. Each frame is one criterion
//! iteration, so frames/s = 1 / the reported time. The per-effect group
//! renders knitted-wool at 512×512 with every effect live, then with one
//! effect forbidden at a time: the difference is that effect's cost. The
//! capture group renders one frame as a simulated capture takes it: the
//! Bonn camera scaled to 384×288, 12 bits, the scene's default effects.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use rigd_sim::scene::{Effect, EffectSwitches, LaserSheet, Scene, Shot};

fn dir(theta_deg: f64, phi_deg: f64) -> [f64; 3] {
    let (t, p) = (theta_deg.to_radians(), phi_deg.to_radians());
    [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
}

/// The MSRA camera (1024 px, f = 2600 px, 0.9 m), scaled to the frame.
fn shot(w: u32, h: u32, effects: EffectSwitches, laser: bool) -> Shot {
    Shot {
        light: dir(45.0, 30.0),
        view: dir(30.0, 200.0),
        width: w,
        height: h,
        bit_depth: 8,
        focal_px: Some(2600.0 * f64::from(w) / 1024.0 * 2.0),
        camera_distance_m: Some(0.9),
        lamp_distance_m: Some(0.8),
        laser: laser.then_some(LaserSheet {
            emitter: [0.17, 0.0, 0.3],
            normal: [0.866, 0.0, -0.5],
            width_m: 0.4e-3,
            power: 1.0,
        }),
        effects,
        ..Shot::default()
    }
}

/// The Bonn rig's camera (3032 px, f = 11000 px, 12 bits, on a 1.6 m rail;
/// the lamp 2.5 m away) scaled to the frame, with the scene's default
/// effects: what each frame of a simulated capture costs.
fn capture_shot(w: u32, h: u32) -> Shot {
    Shot {
        light: dir(45.0, 30.0),
        view: dir(30.0, 200.0),
        width: w,
        height: h,
        bit_depth: 12,
        focal_px: Some(11000.0 * f64::from(w) / 3032.0),
        camera_distance_m: Some(1.6),
        lamp_distance_m: Some(2.5),
        seed: 7,
        ..Shot::default()
    }
}

fn capture_frame(c: &mut Criterion) {
    let mut g = c.benchmark_group("capture");
    g.sample_size(10);
    let corduroy = Scene::load("corduroy").expect("built-in scene");
    let s = capture_shot(384, 288);
    g.bench_with_input(BenchmarkId::new("corduroy", "384x288"), &s, |b, s| {
        b.iter(|| corduroy.render(s))
    });
    g.finish();
}

fn frames_per_second(c: &mut Criterion) {
    let mut g = c.benchmark_group("render");
    g.sample_size(10);
    let flat = Scene::load("flat-calibration").expect("built-in scene");
    let wool = Scene::load("knitted-wool").expect("built-in scene");
    let all: EffectSwitches = "all".parse().expect("switches");
    for (w, h) in [(512, 512), (1024, 768)] {
        let s = shot(w, h, EffectSwitches::default(), false);
        g.bench_with_input(
            BenchmarkId::new("flat-calibration", format!("{w}x{h}")),
            &s,
            |b, s| b.iter(|| flat.render(s)),
        );
        // Asking the flat scene for every effect but the laser costs
        // nothing: none of them can show.
        let s = shot(w, h, all, false);
        g.bench_with_input(
            BenchmarkId::new("flat-calibration-all-asked", format!("{w}x{h}")),
            &s,
            |b, s| b.iter(|| flat.render(s)),
        );
        let s = shot(w, h, all, true);
        g.bench_with_input(
            BenchmarkId::new("knitted-wool-all-effects", format!("{w}x{h}")),
            &s,
            |b, s| b.iter(|| wool.render(s)),
        );
    }
    g.finish();
}

fn per_effect_cost(c: &mut Criterion) {
    let mut g = c.benchmark_group("knitted-wool-512-without");
    g.sample_size(10);
    let wool = Scene::load("knitted-wool").expect("built-in scene");
    let all: EffectSwitches = "all".parse().expect("switches");
    g.bench_function("nothing", |b| {
        let s = shot(512, 512, all, true);
        b.iter(|| wool.render(&s))
    });
    for e in Effect::ALL {
        if e == Effect::VisibilityMaps {
            continue;
        }
        let mut sw = all;
        sw.forbid.insert(e);
        if e == Effect::Relief {
            // Without the relief nothing marches: shadows and bounces go too.
            sw.forbid.insert(Effect::Shadows);
            sw.forbid.insert(Effect::Interreflection);
        }
        let s = shot(512, 512, sw, true);
        g.bench_function(e.name(), |b| b.iter(|| wool.render(&s)));
    }
    g.finish();
    let mut g = c.benchmark_group("folded-cloth-512");
    g.sample_size(10);
    let cloth = Scene::load("folded-cloth").expect("built-in scene");
    for (name, sw) in [
        ("with-visibility-maps", "-noise"),
        ("without", "-noise,-visibility-maps"),
    ] {
        let s = shot(512, 512, sw.parse().expect("switches"), false);
        g.bench_function(name, |b| b.iter(|| cloth.render(&s)));
    }
    g.finish();
}

criterion_group!(benches, frames_per_second, capture_frame, per_effect_cost);
criterion_main!(benches);
