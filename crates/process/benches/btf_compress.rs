//! PCA compression at the size of Sattler et al.: one view slot of 81 lights (H1),
//! 256 × 256 RGB normtextures, C = 16; and a whole 81 × 81 BTF of 256²
//! grey normtextures (what `rigd process rectify` writes), slot by slot as
//! `rigd process btf` does, each slot's textures made outside the timing.

use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, Criterion};
use rigd_process::btf::{compress_slot, TextureShape};
use rigd_process::directions::h1;

const SIDE: usize = 256;
const COMPONENTS: usize = 16;

/// Smooth lighting response plus texel noise, so the spectrum decays but is
/// not trivially low-rank.
fn slot_images(shape: TextureShape) -> Vec<Vec<f32>> {
    slot_images_seeded(shape, 0x2545_F491_4F6C_DD1D)
}

fn slot_images_seeded(shape: TextureShape, seed: u64) -> Vec<Vec<f32>> {
    let channels = shape.values() / (SIDE * SIDE);
    let mut state = seed;
    h1().iter()
        .map(|light| {
            let l = light.to_vector();
            (0..shape.values())
                .map(|i| {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    let noise = (state >> 40) as f32 / (1u64 << 24) as f32;
                    let x = (i / channels.max(1)) as f64;
                    let shade = l[2] * (0.6 + 0.3 * (0.01 * x).sin())
                        + 0.2 * l[0] * (0.013 * x).cos()
                        + 0.1 * (l[1] * l[1]);
                    shade as f32 + 0.02 * noise
                })
                .collect()
        })
        .collect()
}

fn bench_compress_slot(c: &mut Criterion) {
    let Ok(shape) = TextureShape::new(SIDE, SIDE, 3) else {
        return;
    };
    let images = slot_images(shape);
    let refs: Vec<&[f32]> = images.iter().map(Vec::as_slice).collect();

    let start = Instant::now();
    if compress_slot(&refs, shape, COMPONENTS).is_ok() {
        let slot = start.elapsed();
        eprintln!(
            "one slot (81 lights, {SIDE}x{SIDE}x3, C = {COMPONENTS}): {slot:.2?}; \
             81-slot BTF estimate (81 x one slot, not measured): {:.1?}",
            slot * 81
        );
    }

    let mut group = c.benchmark_group("btf");
    // About a second per compression: ten samples need more than the default 5 s.
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(15));
    group.bench_function("compress_slot_81_lights_256x256x3_c16", |b| {
        b.iter(|| compress_slot(&refs, shape, COMPONENTS))
    });
    group.finish();
}

fn bench_full_btf(c: &mut Criterion) {
    let Ok(shape) = TextureShape::new(SIDE, SIDE, 1) else {
        return;
    };
    let mut group = c.benchmark_group("btf");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(60));
    group.bench_function("compress_81_slots_81_lights_256x256_c16", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                for slot in 0..81u64 {
                    let images = slot_images_seeded(shape, 0x9E37_79B9 + slot);
                    let refs: Vec<&[f32]> = images.iter().map(Vec::as_slice).collect();
                    let start = Instant::now();
                    let pca = compress_slot(&refs, shape, COMPONENTS);
                    total += start.elapsed();
                    criterion::black_box(pca.is_ok());
                }
            }
            total
        })
    });
    group.finish();
}

criterion_group!(benches, bench_compress_slot, bench_full_btf);
criterion_main!(benches);
