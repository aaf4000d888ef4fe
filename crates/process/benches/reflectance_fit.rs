//! One view slot of 81 lights (rings 0, 15, …, 75°) at 64 × 64 texels,
//! fitted with K = 2 lobes and with the PTM. A full 256² × 81-view BTF is
//! 16 × 81 = 1296 such slots: multiply the per-slot time by 1296 (same
//! thread count).

use criterion::{criterion_group, criterion_main, Criterion};
use rigd_process::reflectance_fit::{
    error_table, fit_ptm_slot, fit_slot, FitOptions, Lobe, LobeModel,
};

const RING_COUNTS: [usize; 6] = [1, 6, 12, 18, 20, 24];
const RING_THETAS: [f64; 6] = [0.0, 15.0, 30.0, 45.0, 60.0, 75.0];
const SIDE: usize = 64;

fn direction(theta: f64, phi: f64) -> [f64; 3] {
    let (t, p) = (theta.to_radians(), phi.to_radians());
    [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
}

fn lights() -> Vec<[f64; 3]> {
    let mut out = Vec::new();
    for (&theta, &count) in RING_THETAS.iter().zip(&RING_COUNTS) {
        for i in 0..count {
            out.push(direction(theta, 360.0 * i as f64 / count as f64));
        }
    }
    out
}

/// Deterministic texels: a broad lobe plus a specular lobe (n 10…1000)
/// and ±0.01 noise, varying over the slot.
fn slot(lights: &[[f64; 3]]) -> Vec<f32> {
    let mut state = 0x5eed_u64;
    let mut next = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut values = Vec::with_capacity(SIDE * SIDE * lights.len());
    for _ in 0..SIDE * SIDE {
        let lobes = [
            (
                15.0 * next(),
                360.0 * next(),
                0.2 + 0.4 * next(),
                1.0 + 2.0 * next(),
            ),
            (
                50.0 * next(),
                360.0 * next(),
                0.1 + 0.9 * next(),
                10f64.powf(1.0 + 2.0 * next()),
            ),
        ];
        let model = lobes
            .iter()
            .map(|&(t, p, a, n)| Lobe::new(direction(t, p), a, n))
            .collect::<Result<Vec<_>, _>>()
            .and_then(LobeModel::new);
        let Ok(model) = model else {
            continue;
        };
        for &l in lights {
            values.push((model.evaluate(l) + 0.01 * (2.0 * next() - 1.0)) as f32);
        }
    }
    values
}

fn bench(c: &mut Criterion) {
    let lights = lights();
    let values = slot(&lights);
    let opts = FitOptions::default();
    // One untimed pass for Meseth et al.'s Table 1 figures at bench scale.
    match error_table(&lights, &values, &[1, 2], &opts) {
        Ok(table) => eprintln!("{SIDE}x{SIDE} slot, 81 lights:\n{table}"),
        Err(error) => eprintln!("error table failed: {error}"),
    }
    let mut group = c.benchmark_group("reflectance_fit_slot_64x64x81");
    group.sample_size(10);
    group.bench_function("k2", |b| b.iter(|| fit_slot(&lights, &values, 2, &opts)));
    group.bench_function("ptm", |b| b.iter(|| fit_ptm_slot(&lights, &values)));
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
