//! Demosaicing one Bayer frame of the Bonn rig's camera (3032 × 2008) by
//! every method rigd offers: the time per frame that the choice of
//! `demosaic::DEFAULT_METHOD` weighs against its accuracy.

use criterion::{criterion_group, criterion_main, Criterion};
use rigd_core::Cfa;
use rigd_process::demosaic::{demosaic, Method};

const WIDTH: usize = 3032;
const HEIGHT: usize = 2008;

/// A textured mosaic: wales and a colour gradient, recorded through RGGB.
fn mosaic() -> Vec<f32> {
    (0..WIDTH * HEIGHT)
        .map(|i| {
            let (x, y) = ((i % WIDTH) as f32, (i / WIDTH) as f32);
            let wale = 0.5 + 0.3 * (x * 1.3).sin() * (y * 0.05).cos();
            let colour = [0.9, 0.6, 0.3][Cfa::Rggb.channel_at(i % WIDTH, i / WIDTH)];
            wale * colour * (0.6 + 0.4 * x / WIDTH as f32)
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let m = mosaic();
    let mut group = c.benchmark_group("demosaic_3032x2008");
    group.sample_size(10);
    for method in Method::ALL {
        group.bench_function(method.name(), |b| {
            b.iter(|| demosaic(&m, WIDTH, HEIGHT, Cfa::Rggb, method).map(|p| p[1][0]))
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
