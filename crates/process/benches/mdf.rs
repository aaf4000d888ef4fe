//! MDF processing of one laser scan: 181 frames of 320 × 240 (a pinhole
//! camera at θ = 40°, a flat turntable swept by a rotating laser plane):
//! line detection in two reference bands per frame, and the space-time
//! analysis of the whole sequence. A view with L laser source positions
//! costs L times the sum, plus a negligible merge.

use criterion::{criterion_group, criterion_main, Criterion};
use rigd_process::image_io::Image;
use rigd_process::mdf::{
    detect_line_in_regions, space_time, LaserPlane, PinholeCamera, SpaceTimeOptions,
};

const W: usize = 320;
const H: usize = 240;
const FRAMES: usize = 181;

fn setup() -> (PinholeCamera, Vec<Image>, Vec<LaserPlane>) {
    let t = 40f64.to_radians();
    let cam = PinholeCamera::looking_at_origin([t.sin(), 0.0, t.cos()], 0.3, 1600.0, W, H)
        .expect("valid camera");
    let emitter = [0.0, 0.3536, 0.3536];
    let sigma = 0.001 / 2.355;
    let mut frames = Vec::new();
    let mut planes = Vec::new();
    for k in 0..FRAMES {
        let c = -0.036 + 0.072 * k as f64 / (FRAMES - 1) as f64;
        // Plane through the emitter and the line y = c on z = 0.
        let (a, b) = ([0.0, c, 0.0], [1.0, 0.0, 0.0]);
        let e = [emitter[0] - a[0], emitter[1] - a[1], emitter[2] - a[2]];
        let n = [
            b[1] * e[2] - b[2] * e[1],
            b[2] * e[0] - b[0] * e[2],
            b[0] * e[1] - b[1] * e[0],
        ];
        let plane = LaserPlane::through(a, n).expect("valid plane");
        let mut img = Image::new(W, H, 1);
        for j in 0..H {
            for i in 0..W {
                let p = cam.back_project_to_height(i as f64 + 0.5, j as f64 + 0.5, 0.0);
                if let Some(p) = p {
                    let d = plane.distance(p);
                    img.set(
                        i,
                        j,
                        0,
                        (0.03 + 0.7 * (-0.5 * (d / sigma).powi(2)).exp()) as f32,
                    );
                }
            }
        }
        frames.push(img);
        planes.push(plane);
    }
    (cam, frames, planes)
}

fn bench(c: &mut Criterion) {
    let (cam, frames, planes) = setup();
    let bands = [[0, 0, W, 30], [0, H - 30, W, H]];
    c.bench_function("mdf detect_line x181 (2 bands, 320x240)", |b| {
        b.iter(|| {
            frames
                .iter()
                .filter(|f| detect_line_in_regions(f, &bands, 1.0, 0.2).is_ok())
                .count()
        })
    });
    let opts = SpaceTimeOptions::new(0.2, 0.003, 0.02);
    c.bench_function("mdf space_time 181 frames 320x240", |b| {
        b.iter(|| space_time(&frames, &planes, &cam, &opts).map(|(d, _)| d.valid_fraction()))
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = bench
}
criterion_main!(benches);
