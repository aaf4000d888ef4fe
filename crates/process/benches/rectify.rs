//! One 640 × 480 frame of the default holder seen from θ = 60° (affine
//! approximation of a pinhole at 0.6 m, f = 1600 px, plus a perspective
//! term): marker detection, registration, and rectification to a 1024²
//! normtexture followed by the ROI cut to 256². A measurement of N frames
//! costs N times the sum (same thread count).

use criterion::{criterion_group, criterion_main, Criterion};
use rigd_process::image_io::Image;
use rigd_process::rectify::{
    detect_markers, predict_markers, project, rectify, register, roi_cut, DetectOptions,
    Homography, MarkerLayout, RectifyOptions, RegisterOptions, Roi, NORMTEXTURE_SIZE,
    SATTLER_ROI_FRACTION,
};

const W: usize = 640;
const H: usize = 480;

fn homography() -> Homography {
    // x → right, y → up (foreshortened by cos 60°), slight perspective.
    let s = 1600.0 / 0.6;
    [[s, 0.0, 320.0], [0.0, -s * 0.5, 240.0], [0.0, 0.8, 1.0]]
}

fn frame(h: &Homography, layout: &MarkerLayout) -> Image {
    // Invert by solving for the plate point of each pixel centre (the map
    // above is invertible in closed form).
    let mut img = Image::new(W, H, 1);
    let s = 1600.0 / 0.6;
    for j in 0..H {
        for i in 0..W {
            let (u, v) = (i as f64 + 0.5, j as f64 + 0.5);
            // u = (s x + 320 w) / w', v = (-s/2 y + 240) / w', w' = 0.8 y + 1.
            let y = (240.0 - v) / (s * 0.5 + 0.8 * v);
            let w = 0.8 * y + 1.0;
            let x = (u * w - 320.0) / s;
            let on_disc = layout
                .points
                .iter()
                .any(|p| (x - p[0]).hypot(y - p[1]) <= layout.radius_m);
            let value = if x.abs() <= 0.05 && y.abs() <= 0.05 {
                0.5 + 0.3 * (x * 400.0).sin() * (y * 300.0).cos()
            } else if on_disc {
                0.76
            } else if x.abs() <= 0.08 && y.abs() <= 0.08 {
                0.05
            } else {
                0.0
            };
            img.set(i, j, 0, value as f32);
        }
    }
    debug_assert!(project(h, [0.0, 0.0]).is_some());
    img
}

fn bench(c: &mut Criterion) {
    let layout = MarkerLayout::default_holder();
    let h = homography();
    let img = frame(&h, &layout);
    let pred: Vec<_> = predict_markers(&h, &layout)
        .into_iter()
        .map(|p| p.map(|[u, v]| [u + 12.0, v - 9.0]))
        .collect();
    let opts = DetectOptions::default();
    let found = detect_markers(&img, &pred, 35.0, &opts).expect("valid frame");
    let reg = register(&layout, &found, &RegisterOptions::default()).expect("markers found");
    c.bench_function("detect_and_register_640x480", |b| {
        b.iter(|| {
            let found = detect_markers(&img, &pred, 35.0, &opts).expect("valid frame");
            register(&layout, &found, &RegisterOptions::default()).expect("markers found")
        })
    });
    let size = [NORMTEXTURE_SIZE, NORMTEXTURE_SIZE];
    c.bench_function("rectify_1024_and_roi_256", |b| {
        b.iter(|| {
            let norm = rectify(
                &img,
                &reg.homography,
                layout.sample_region(),
                size,
                &RectifyOptions::default(),
            )
            .expect("valid input");
            let roi = Roi::centred(size[0], size[1], SATTLER_ROI_FRACTION);
            roi_cut(&norm.texture, roi, [256, 256]).expect("valid ROI")
        })
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = bench
}
criterion_main!(benches);
