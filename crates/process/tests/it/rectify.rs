//! Marker detection, registration and rectification on synthetic frames
//! rendered here (not by rigd-sim): a pinhole camera looking at the sample
//! centre from (θ, φ) with the image's up the sample normal projected, a
//! dark plate with the 8 white disc markers and white border lines, a
//! bright textured sample, 3×3 supersampled pixels, Gaussian noise and
//! 12-bit quantisation.

use proptest::prelude::*;
use rayon::prelude::*;
use rigd_process::image_io::{load_png, write_png, Image, PngDepth};
use rigd_process::rectify::{
    codes8, detect_border_corners, detect_markers, fit_homography, project, quantise, rectify,
    register, require_all, roi_cut, BorderLines, DetectOptions, Detection, Filter, Homography,
    MarkerLayout, Quantisation, RectifyError, RectifyOptions, Region, RegisterOptions, Roi,
    SATTLER_ROI_FRACTION,
};

const W: usize = 640;
const H: usize = 480;
const FOCAL: f64 = 1600.0;
const DIST: f64 = 0.6;
/// Radiance of a white frontal texel (the simulator's WHITE_LEVEL).
const GAIN: f64 = 0.8;
const NOISE: f64 = 0.004;
const MM: f64 = 1e-3;

// ---------------------------------------------------------------- camera

/// Plate → pixel homography of a pinhole at distance `dist` in direction
/// (θ, φ), looking at the origin, image up = the normal projected (or +y at
/// the pole), rolled by `roll` about the optical axis, principal point at
/// the image centre plus `pp`.
fn camera(
    theta_deg: f64,
    phi_deg: f64,
    dist: f64,
    focal: f64,
    roll_deg: f64,
    pp: [f64; 2],
) -> Homography {
    let (t, p) = (theta_deg.to_radians(), phi_deg.to_radians());
    let v = [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()];
    let (right0, up0) = if v[0].hypot(v[1]) < 1e-9 {
        ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    } else {
        let up = unit([-v[2] * v[0], -v[2] * v[1], 1.0 - v[2] * v[2]]);
        (cross(up, v), up)
    };
    let r = roll_deg.to_radians();
    let right = add(scale(right0, r.cos()), scale(up0, r.sin()));
    let up = add(scale(up0, r.cos()), scale(right0, -r.sin()));
    let fwd = scale(v, -1.0);
    let c = scale(v, dist);
    let row = |a: [f64; 3]| [a[0], a[1], -dot(c, a)];
    let rz = row(fwd);
    let rr = row(right);
    let ru = row(up);
    let (cx, cy) = (W as f64 / 2.0 + pp[0], H as f64 / 2.0 + pp[1]);
    let mut h = [[0.0; 3]; 3];
    for k in 0..3 {
        h[0][k] = focal * rr[k] + cx * rz[k];
        h[1][k] = cy * rz[k] - focal * ru[k];
        h[2][k] = rz[k];
    }
    h
}

fn unit(a: [f64; 3]) -> [f64; 3] {
    scale(a, 1.0 / dot(a, a).sqrt())
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}
fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn inv3(m: &Homography) -> Homography {
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    let mut r = [[0.0; 3]; 3];
    for (i, row) in r.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            let (a, b) = ((j + 1) % 3, (j + 2) % 3);
            let (c, d) = ((i + 1) % 3, (i + 2) % 3);
            *v = (m[a][c] * m[b][d] - m[a][d] * m[b][c]) / det;
        }
    }
    r
}

/// Pixel → plate point, `None` for rays that miss the plate plane.
fn unproject(hinv: &Homography, h: &Homography, u: f64, v: f64) -> Option<[f64; 2]> {
    let x = hinv[0][0] * u + hinv[0][1] * v + hinv[0][2];
    let y = hinv[1][0] * u + hinv[1][1] * v + hinv[1][2];
    let w = hinv[2][0] * u + hinv[2][1] * v + hinv[2][2];
    let p = [x / w, y / w];
    project(h, p).map(|_| p)
}

// ----------------------------------------------------------------- scene

#[derive(Clone, Copy, PartialEq)]
enum Tex {
    /// Bright, smooth texture (periods 17–31 mm), values 0.05..0.95.
    Smooth,
    /// Stripes of period 1.5 mm across y: aliases when minified.
    Stripes,
}

const STRIPE_PERIOD: f64 = 1.5 * MM;

fn texture(tex: Tex, x: f64, y: f64) -> f64 {
    use std::f64::consts::TAU;
    match tex {
        Tex::Smooth => {
            0.5 + 0.2 * (TAU * x / (23.0 * MM) + 0.3).sin()
                + 0.15 * (TAU * y / (17.0 * MM)).cos()
                + 0.1 * (TAU * (x + y) / (31.0 * MM)).sin()
        }
        Tex::Stripes => 0.5 + 0.35 * (TAU * y / STRIPE_PERIOD).sin(),
    }
}

/// Mean of the texture over a texel `[x0,x1]×[y0,y1]`.
fn texture_mean(tex: Tex, x0: f64, x1: f64, y0: f64, y1: f64) -> f64 {
    match tex {
        Tex::Stripes => {
            let k = std::f64::consts::TAU / STRIPE_PERIOD;
            0.5 + 0.35 * ((k * y0).cos() - (k * y1).cos()) / (k * (y1 - y0))
        }
        Tex::Smooth => {
            let n = 4;
            let mut s = 0.0;
            for a in 0..n {
                for b in 0..n {
                    let x = x0 + (a as f64 + 0.5) / n as f64 * (x1 - x0);
                    let y = y0 + (b as f64 + 0.5) / n as f64 * (y1 - y0);
                    s += texture(tex, x, y);
                }
            }
            s / (n * n) as f64
        }
    }
}

struct Scene {
    layout: MarkerLayout,
    tex: Tex,
    /// Markers painted over in plate colour.
    hidden: Vec<usize>,
}

impl Scene {
    fn new(tex: Tex) -> Scene {
        Scene {
            layout: MarkerLayout::default_holder(),
            tex,
            hidden: Vec::new(),
        }
    }

    fn albedo(&self, x: f64, y: f64) -> f64 {
        let (ax, ay) = (x.abs(), y.abs());
        let half = 80.0 * MM;
        if ax > half || ay > half {
            return 0.0;
        }
        let [sx, sy] = self.layout.sample_half;
        if ax <= sx && ay <= sy {
            return texture(self.tex, x, y);
        }
        let (ox, oy, lw) = (sx + 5.0 * MM, sy + 5.0 * MM, 1.0 * MM);
        if ((ax - ox).abs() <= lw && ay <= oy + lw) || ((ay - oy).abs() <= lw && ax <= ox + lw) {
            return 0.95;
        }
        let r2 = self.layout.radius_m.powi(2);
        for (i, p) in self.layout.points.iter().enumerate() {
            if !self.hidden.contains(&i) && (x - p[0]).powi(2) + (y - p[1]).powi(2) <= r2 {
                return 0.95;
            }
        }
        0.06
    }

    /// The frame: 3×3 supersampled pixels, noise, 12-bit codes.
    fn render(&self, h: &Homography, seed: u64) -> Image {
        let hinv = inv3(h);
        let ss = 3;
        let data: Vec<f32> = (0..H)
            .into_par_iter()
            .flat_map_iter(|j| {
                let mut rng = Lcg(seed ^ (j as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
                let hinv = &hinv;
                (0..W).map(move |i| {
                    let mut s = 0.0;
                    for a in 0..ss {
                        for b in 0..ss {
                            let u = i as f64 + (a as f64 + 0.5) / ss as f64;
                            let v = j as f64 + (b as f64 + 0.5) / ss as f64;
                            if let Some(p) = unproject(hinv, h, u, v) {
                                s += self.albedo(p[0], p[1]);
                            }
                        }
                    }
                    let value = GAIN * s / (ss * ss) as f64 + NOISE * rng.gauss();
                    ((value.clamp(0.0, 1.0) * 4095.0).round() / 4095.0) as f32
                })
            })
            .collect();
        Image {
            width: W,
            height: H,
            channels: 1,
            data,
        }
    }

    /// The true frontal texture of `region` at `n²` texels (times the gain).
    fn truth(&self, region: Region, n: usize) -> Vec<f32> {
        let dx = (region.x_max - region.x_min) / n as f64;
        let dy = (region.y_max - region.y_min) / n as f64;
        (0..n * n)
            .into_par_iter()
            .map(|k| {
                let (c, r) = ((k % n) as f64, (k / n) as f64);
                let x0 = region.x_min + c * dx;
                let y1 = region.y_max - r * dy;
                (GAIN * texture_mean(self.tex, x0, x0 + dx, y1 - dy, y1)) as f32
            })
            .collect()
    }
}

/// Deterministic pseudo-random numbers (no rand dependency).
struct Lcg(u64);

impl Lcg {
    fn uniform(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn gauss(&mut self) -> f64 {
        let (a, b) = (self.uniform(), self.uniform());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    }
}

/// True marker projections and predictions off by up to `off` px.
fn predictions(
    h: &Homography,
    layout: &MarkerLayout,
    off: f64,
    seed: u64,
) -> (Vec<[f64; 2]>, Vec<Option<[f64; 2]>>) {
    let mut rng = Lcg(seed);
    let truth: Vec<[f64; 2]> = layout
        .points
        .iter()
        .map(|&p| project(h, p).expect("markers in front of the camera"))
        .collect();
    let pred = truth
        .iter()
        .map(|t| {
            let a = rng.uniform() * std::f64::consts::TAU;
            let r = off * rng.uniform();
            Some([t[0] + r * a.cos(), t[1] + r * a.sin()])
        })
        .collect();
    (truth, pred)
}

fn rms(a: &[f32], b: &[f32]) -> f64 {
    let s: f64 = a.iter().zip(b).map(|(x, y)| f64::from(x - y).powi(2)).sum();
    (s / a.len() as f64).sqrt()
}

/// RMS over the texels at least `margin` texels from the edge of an `n²`
/// texture (the sample's edge texels blend in the dark plate).
fn interior_rms(a: &[f32], b: &[f32], n: usize, margin: usize) -> f64 {
    let (mut s, mut k) = (0.0, 0usize);
    for r in margin..n - margin {
        for c in margin..n - margin {
            s += f64::from(a[r * n + c] - b[r * n + c]).powi(2);
            k += 1;
        }
    }
    (s / k as f64).sqrt()
}

fn detection_errors(found: &[Option<Detection>], truth: &[[f64; 2]]) -> Vec<f64> {
    found
        .iter()
        .zip(truth)
        .filter_map(|(d, t)| d.map(|d| (d.centre_px[0] - t[0]).hypot(d.centre_px[1] - t[1])))
        .collect()
}

const SEARCH: f64 = 35.0;

// ------------------------------------------------------------------ tests

/// Poses (θ, φ) in degrees, including Sattler et al.'s (60°, 342°) and the
/// φ = 360° wrap.
const POSES: [(f64, f64); 8] = [
    (0.0, 0.0),
    (45.0, 30.0),
    (45.0, 200.0),
    (60.0, 342.0),
    (75.0, 0.0),
    (75.0, 120.0),
    (75.0, 250.0),
    (75.0, 360.0),
];

#[test]
fn detects_registers_and_rectifies_across_poses() {
    let scene = Scene::new(Tex::Smooth);
    let region = scene.layout.sample_region();
    let n = 256;
    let truth = scene.truth(region, n);
    for (k, &(theta, phi)) in POSES.iter().enumerate() {
        let h = camera(theta, phi, DIST, FOCAL, 0.0, [0.0, 0.0]);
        let frame = scene.render(&h, 100 + k as u64);
        let (true_px, pred) = predictions(&h, &scene.layout, 20.0, 7 + k as u64);
        let found = detect_markers(&frame, &pred, SEARCH, &DetectOptions::default()).unwrap();
        assert!(
            found.iter().all(Option::is_some),
            "θ={theta} φ={phi}: {found:?}"
        );
        let errs = detection_errors(&found, &true_px);
        let max_err = errs.iter().copied().fold(0.0, f64::max);
        let reg = register(&scene.layout, &found, &RegisterOptions::default()).unwrap();
        // Border corners from the point-marker homography, then both kinds
        // of markers together.
        let border = BorderLines::default_holder();
        let corners =
            detect_border_corners(&frame, &reg.homography, &border, &DetectOptions::default())
                .unwrap();
        let corner_errs: Vec<f64> = corners
            .iter()
            .zip(border.corners())
            .map(|(d, p)| {
                let d = d.expect("border corner found");
                let t = project(&h, p).unwrap();
                (d.centre_px[0] - t[0]).hypot(d.centre_px[1] - t[1])
            })
            .collect();
        let max_corner = corner_errs.iter().copied().fold(0.0, f64::max);
        let all_layout = scene.layout.with_border_corners(&border);
        let all: Vec<Option<Detection>> = found.iter().chain(&corners).copied().collect();
        let reg12 = register(&all_layout, &all, &RegisterOptions::default()).unwrap();
        eprintln!(
            "pose θ={theta:>4} φ={phi:>5}: border-corner error max {max_corner:.3} px; points+corners residual RMS {:.3} px (used {}/12)",
            reg12.rms_px, reg12.used
        );
        assert!(
            max_corner < 0.3,
            "θ={theta} φ={phi}: border corners {corner_errs:?}"
        );
        assert!(reg12.rms_px < 0.3 && reg12.rejected.is_empty(), "{reg12:?}");
        let out = rectify(
            &frame,
            &reg12.homography,
            region,
            [n, n],
            &RectifyOptions::default(),
        )
        .unwrap();
        let tex_rms = rms(&out.texture.data, &truth);
        let inner_rms = interior_rms(&out.texture.data, &truth, n, 4);
        // How far the estimated homography puts the sample's corners.
        let corner_err = [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]
            .iter()
            .map(|s| {
                let p = [s[0] * region.x_max, s[1] * region.y_max];
                let (a, b) = (
                    project(&h, p).unwrap(),
                    project(&reg.homography, p).unwrap(),
                );
                (a[0] - b[0]).hypot(a[1] - b[1])
            })
            .fold(0.0, f64::max);
        eprintln!(
            "pose θ={theta:>4} φ={phi:>5}: detection error max {max_err:.3} px mean {:.3} px; \
             residual RMS {:.3} px max {:.3} px (used {}/{}); sample-corner error {corner_err:.3} px; \
             texture RMS error {tex_rms:.4} (of {GAIN} white; {inner_rms:.4} without the 4 edge texels), coverage {:.3}",
            errs.iter().sum::<f64>() / errs.len() as f64,
            reg.rms_px,
            reg.max_px,
            reg.used,
            reg.found,
            out.coverage
        );
        // Tolerance: noise and pixel sampling dominate; the perspective bias
        // of a 6 mm disc's centroid at 0.6 m is ~0.01 px.
        assert!(
            max_err < 0.3,
            "θ={theta} φ={phi}: detection error {max_err} px"
        );
        assert!(
            reg.rms_px < 0.3,
            "θ={theta} φ={phi}: residual RMS {}",
            reg.rms_px
        );
        assert!(reg.rejected.is_empty(), "{:?}", reg.rejected);
        assert!(
            corner_err < 1.0,
            "θ={theta} φ={phi}: corner error {corner_err}"
        );
        assert!((out.coverage - 1.0).abs() < 1e-12);
        assert!(out.texture.data.iter().all(|v| v.is_finite()));
        assert!(tex_rms < 0.03, "θ={theta} φ={phi}: texture RMS {tex_rms}");
        assert!(
            inner_rms < 0.01,
            "θ={theta} φ={phi}: interior texture RMS {inner_rms}"
        );
    }
}

#[test]
fn phi_360_wraps_to_phi_0() {
    let a = camera(75.0, 0.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let b = camera(75.0, 360.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let scene = Scene::new(Tex::Smooth);
    let (fa, fb) = (scene.render(&a, 1), scene.render(&b, 1));
    let layout = &scene.layout;
    let (_, pa) = predictions(&a, layout, 0.0, 1);
    let (_, pb) = predictions(&b, layout, 0.0, 1);
    let opts = DetectOptions::default();
    let ra = register(
        layout,
        &detect_markers(&fa, &pa, SEARCH, &opts).unwrap(),
        &RegisterOptions::default(),
    )
    .unwrap();
    let rb = register(
        layout,
        &detect_markers(&fb, &pb, SEARCH, &opts).unwrap(),
        &RegisterOptions::default(),
    )
    .unwrap();
    for p in &layout.points {
        let (x, y) = (
            project(&ra.homography, *p).unwrap(),
            project(&rb.homography, *p).unwrap(),
        );
        assert!((x[0] - y[0]).hypot(x[1] - y[1]) < 0.05);
    }
}

#[test]
fn normtexture_roi_cut_pipeline_matches_truth() {
    let scene = Scene::new(Tex::Smooth);
    let h = camera(45.0, 30.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let frame = scene.render(&h, 5);
    let (_, pred) = predictions(&h, &scene.layout, 15.0, 3);
    let found = detect_markers(&frame, &pred, SEARCH, &DetectOptions::default()).unwrap();
    let reg = register(&scene.layout, &found, &RegisterOptions::default()).unwrap();
    let region = scene.layout.sample_region();
    let norm = rectify(
        &frame,
        &reg.homography,
        region,
        [1024, 1024],
        &RectifyOptions::default(),
    )
    .unwrap();
    assert_eq!((norm.texture.width, norm.texture.height), (1024, 1024));
    let roi = Roi::centred(1024, 1024, SATTLER_ROI_FRACTION);
    assert_eq!((roi.width, roi.height, roi.x, roi.y), (550, 550, 237, 237));
    let small = roi_cut(&norm.texture, roi, [256, 256]).unwrap();
    // Truth over the same plate square.
    let texel = (region.x_max - region.x_min) / 1024.0;
    let roi_region = Region {
        x_min: region.x_min + roi.x as f64 * texel,
        x_max: region.x_min + (roi.x + roi.width) as f64 * texel,
        y_max: region.y_max - roi.y as f64 * texel,
        y_min: region.y_max - (roi.y + roi.height) as f64 * texel,
    };
    let truth = scene.truth(roi_region, 256);
    let e = rms(&small.data, &truth);
    eprintln!("normtexture 1024² → ROI 550² → 256²: texture RMS error {e:.4}");
    assert!(e < 0.03, "{e}");
}

#[test]
fn area_filter_beats_point_sampling_at_grazing_view() {
    // Stripes across y are resolved by the camera at θ = 75°, φ = 0 (the
    // foreshortening is along x) but have about one period per output
    // texel at 64²: point sampling aliases them into a moiré, the area
    // filter averages them out as the texel-mean truth does.
    let scene = Scene::new(Tex::Stripes);
    let region = scene.layout.sample_region();
    let n = 64;
    let truth = scene.truth(region, n);
    let h = camera(75.0, 0.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let frame = scene.render(&h, 9);
    let (_, pred) = predictions(&h, &scene.layout, 10.0, 4);
    let found = detect_markers(&frame, &pred, SEARCH, &DetectOptions::default()).unwrap();
    let reg = register(&scene.layout, &found, &RegisterOptions::default()).unwrap();
    let mut errors = Vec::new();
    for filter in [Filter::Nearest, Filter::Bilinear, Filter::Area] {
        let opts = RectifyOptions {
            filter,
            ..RectifyOptions::default()
        };
        let out = rectify(&frame, &reg.homography, region, [n, n], &opts).unwrap();
        errors.push(rms(&out.texture.data, &truth));
    }
    eprintln!(
        "θ=75° stripes at {n}²: texture RMS error nearest {:.4}, bilinear {:.4}, area {:.4}",
        errors[0], errors[1], errors[2]
    );
    assert!(errors[2] < 0.5 * errors[0], "{errors:?}");
    assert!(errors[2] < 0.5 * errors[1], "{errors:?}");
}

#[test]
fn hidden_marker_is_reported_missing_and_registration_holds() {
    let mut scene = Scene::new(Tex::Smooth);
    scene.hidden = vec![3];
    let h = camera(45.0, 200.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let frame = scene.render(&h, 11);
    let (true_px, pred) = predictions(&h, &scene.layout, 20.0, 5);
    let found = detect_markers(&frame, &pred, SEARCH, &DetectOptions::default()).unwrap();
    assert!(found[3].is_none(), "{:?}", found[3]);
    let reg = register(&scene.layout, &found, &RegisterOptions::default()).unwrap();
    assert_eq!((reg.found, reg.used), (7, 7));
    assert!(reg.residuals_px[3].is_none());
    let err = (0..8)
        .map(|i| {
            let p = project(&reg.homography, scene.layout.points[i]).unwrap();
            (p[0] - true_px[i][0]).hypot(p[1] - true_px[i][1])
        })
        .fold(0.0, f64::max);
    eprintln!(
        "hidden marker 3: residual RMS {:.3} px, hidden marker predicted within {err:.3} px",
        reg.rms_px
    );
    assert!(reg.rms_px < 0.3 && err < 0.5, "{} {err}", reg.rms_px);
}

#[test]
fn bright_speck_near_a_prediction_is_rejected_as_outlier() {
    let scene = Scene::new(Tex::Smooth);
    let h = camera(45.0, 30.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let mut frame = scene.render(&h, 13);
    let (true_px, mut pred) = predictions(&h, &scene.layout, 0.0, 6);
    // Marker 5's prediction is 20 px off, right on a bright speck.
    let speck = [true_px[5][0] + 14.0, true_px[5][1] - 14.0];
    pred[5] = Some(speck);
    for j in 0..H {
        for i in 0..W {
            let (dx, dy) = (i as f64 + 0.5 - speck[0], j as f64 + 0.5 - speck[1]);
            if dx.hypot(dy) <= 2.5 {
                frame.data[j * W + i] = 0.7;
            }
        }
    }
    let found = detect_markers(&frame, &pred, SEARCH, &DetectOptions::default()).unwrap();
    let d5 = found[5].expect("the speck is found");
    assert!((d5.centre_px[0] - speck[0]).hypot(d5.centre_px[1] - speck[1]) < 0.5);
    let reg = register(&scene.layout, &found, &RegisterOptions::default()).unwrap();
    eprintln!(
        "speck at marker 5: rejected {:?}, residual RMS {:.3} px, speck residual {:.1} px",
        reg.rejected,
        reg.rms_px,
        reg.residuals_px[5].unwrap_or(f64::NAN)
    );
    assert_eq!(reg.rejected, vec![5]);
    assert_eq!(reg.used, 7);
    assert!(reg.rms_px < 0.3);
    assert!(reg.residuals_px[5].is_some_and(|r| r > 15.0));
    // Without rejection the speck would have pulled the fit.
    let strict = RegisterOptions {
        outlier_px: 1e9,
        max_residual_px: 1e9,
        ..RegisterOptions::default()
    };
    let pulled = register(&scene.layout, &found, &strict).unwrap();
    assert!(pulled.rms_px > 1.0, "{}", pulled.rms_px);
}

#[test]
fn three_markers_is_a_typed_error_naming_the_count() {
    let mut scene = Scene::new(Tex::Smooth);
    scene.hidden = vec![0, 2, 4, 6, 7];
    let h = camera(45.0, 30.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let frame = scene.render(&h, 17);
    let (_, pred) = predictions(&h, &scene.layout, 10.0, 8);
    let found = detect_markers(&frame, &pred, SEARCH, &DetectOptions::default()).unwrap();
    assert_eq!(found.iter().filter(|d| d.is_some()).count(), 3);
    let result = register(&scene.layout, &found, &RegisterOptions::default());
    match &result {
        Err(RectifyError::TooFewMarkers {
            found,
            total,
            missing,
        }) => {
            assert_eq!((*found, *total), (3, 8));
            assert_eq!(missing, &vec![0, 2, 4, 6, 7]);
        }
        other => panic!("expected TooFewMarkers, got {other:?}"),
    }
    let msg = result.as_ref().unwrap_err().to_string();
    assert!(msg.contains("only 3 of 8 markers"), "{msg}");
    // A batch of frames names the failing one.
    let good_h = camera(0.0, 0.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let good_frame = Scene::new(Tex::Smooth).render(&good_h, 3);
    let (_, gp) = predictions(&good_h, &scene.layout, 5.0, 9);
    let good = register(
        &scene.layout,
        &detect_markers(&good_frame, &gp, SEARCH, &DetectOptions::default()).unwrap(),
        &RegisterOptions::default(),
    );
    assert!(good.is_ok());
    let err = require_all([("t000_p000", &good), ("t045_p030", &result)])
        .unwrap_err()
        .to_string();
    eprintln!("batch error: {err}");
    assert!(
        err.contains("1 of 2 frames") && err.contains("t045_p030") && !err.contains("t000_p000"),
        "{err}"
    );
}

#[test]
fn markers_cut_by_the_frame_edge_are_not_found() {
    // The principal point shifted so the left column of markers sits on the
    // image's left edge: partial discs would bias the centroid.
    let scene = Scene::new(Tex::Smooth);
    let h = camera(0.0, 0.0, DIST, FOCAL, 0.0, [-128.0, 0.0]);
    let frame = scene.render(&h, 23);
    let (true_px, pred) = predictions(&h, &scene.layout, 10.0, 2);
    assert!(
        true_px[..3].iter().all(|p| p[0] > 0.0 && p[0] < 6.0),
        "{true_px:?}"
    );
    let found = detect_markers(&frame, &pred, SEARCH, &DetectOptions::default()).unwrap();
    assert!(found[..3].iter().all(Option::is_none), "{:?}", &found[..3]);
    assert!(found[3..].iter().all(Option::is_some));
    let reg = register(&scene.layout, &found, &RegisterOptions::default()).unwrap();
    assert_eq!((reg.found, reg.used), (5, 5));
    eprintln!(
        "left column cut by the frame: 5 markers, residual RMS {:.3} px",
        reg.rms_px
    );
    assert!(reg.rms_px < 0.3);
}

#[test]
fn far_off_predictions_find_nothing() {
    let scene = Scene::new(Tex::Smooth);
    let h = camera(0.0, 0.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let frame = scene.render(&h, 19);
    let (true_px, _) = predictions(&h, &scene.layout, 0.0, 1);
    // Half-way between markers: on the dark plate for the edge markers, on
    // the bright textured sample for the corners.
    let pred: Vec<Option<[f64; 2]>> = true_px
        .iter()
        .map(|t| {
            let dx = if t[0] < W as f64 / 2.0 { 95.0 } else { -95.0 };
            let dy = if t[1] < H as f64 / 2.0 { 95.0 } else { -95.0 };
            Some([t[0] + dx, t[1] + dy])
        })
        .chain([Some([-500.0, -500.0]), None, Some([f64::NAN, 3.0])])
        .collect();
    let found = detect_markers(&frame, &pred, 20.0, &DetectOptions::default()).unwrap();
    assert!(found.iter().all(Option::is_none), "{found:?}");
}

#[test]
fn degenerate_inconsistent_and_folded_sets_are_typed_errors() {
    let layout = MarkerLayout::default_holder();
    let h = camera(30.0, 10.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let det = |p: [f64; 2]| {
        Some(Detection {
            centre_px: project(&h, p).unwrap(),
            area_px: 100.0,
            contrast: 0.5,
            elongation: 1.0,
        })
    };
    // Points 0, 1, 2 are the x = −c column; with 3 (x = 0, y = −c) no 4 are
    // in general position.
    let mut found: Vec<Option<Detection>> = vec![None; 8];
    for i in [0, 1, 2, 3] {
        found[i] = det(layout.points[i]);
    }
    let err = register(&layout, &found, &RegisterOptions::default()).unwrap_err();
    assert!(
        matches!(err, RectifyError::Degenerate { found: 4, .. }),
        "{err}"
    );
    // The four corners with two image positions swapped: a twisted quad that
    // an exact homography can only reach by folding over the plate.
    let corners = [0usize, 2, 7, 5]; // (−,−), (−,+), (+,+), (+,−)
    let mut found: Vec<Option<Detection>> = vec![None; 8];
    let pix: Vec<[f64; 2]> = corners
        .iter()
        .map(|&i| project(&h, layout.points[i]).unwrap())
        .collect();
    for (k, &i) in corners.iter().enumerate() {
        let swapped = match k {
            0 => pix[1],
            1 => pix[0],
            _ => pix[k],
        };
        found[i] = det(layout.points[i]).map(|d| Detection {
            centre_px: swapped,
            ..d
        });
    }
    // Five markers, one 20 px off: detectable but not locatable.
    let mut five: Vec<Option<Detection>> = vec![None; 8];
    for i in [0, 2, 3, 5, 7] {
        five[i] = det(layout.points[i]);
    }
    if let Some(d) = five[3].as_mut() {
        d.centre_px[0] += 20.0;
    }
    let err5 = register(&layout, &five, &RegisterOptions::default()).unwrap_err();
    eprintln!("five markers, one off: {err5}");
    assert!(
        matches!(
            err5,
            RectifyError::Inconsistent {
                found: 5,
                used: 5,
                ..
            }
        ),
        "{err5}"
    );
    let err = register(&layout, &found, &RegisterOptions::default()).unwrap_err();
    eprintln!("twisted quad: {err}");
    assert!(matches!(err, RectifyError::Folded { found: 4 }), "{err}");
}

#[test]
fn quantisation_takes_the_chosen_8_bits() {
    let codes: Vec<u32> = vec![0, 3, 4, 5, 7, 8, 1019, 1020, 1023, 1024, 2048, 4094, 4095];
    let image = Image {
        width: codes.len(),
        height: 1,
        channels: 1,
        data: codes.iter().map(|&c| c as f32 / 4095.0).collect(),
    };
    let float = quantise(&image, 12, Quantisation::Float).unwrap();
    assert_eq!(float, image);
    for shift in [2u8, 4] {
        let q = quantise(&image, 12, Quantisation::Bits8 { shift }).unwrap();
        let got = codes8(&q);
        let want: Vec<u8> = codes.iter().map(|&c| (c >> shift).min(255) as u8).collect();
        assert_eq!(got, want, "shift {shift}");
        // Written as 8-bit PNG the codes survive exactly.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("q.png");
        write_png(&path, &q, PngDepth::Eight).unwrap();
        assert_eq!(codes8(&load_png(&path).unwrap()), want);
    }
    let q = codes8(&quantise(&image, 12, Quantisation::Bits8 { shift: 2 }).unwrap());
    // Central 8 bits: 1020 and above saturate to 255, never wrap.
    assert_eq!(&q[q.len() - 6..], &[255, 255, 255, 255, 255, 255]);
    assert_eq!(&q[..6], &[0, 0, 1, 1, 1, 2]);
    // Out-of-range and non-finite values clamp.
    let odd = Image {
        width: 3,
        height: 1,
        channels: 1,
        data: vec![-1.0, 2.0, f32::NAN],
    };
    assert_eq!(
        codes8(&quantise(&odd, 12, Quantisation::Bits8 { shift: 2 }).unwrap()),
        vec![0, 255, 0]
    );
    assert!(quantise(&image, 12, Quantisation::Bits8 { shift: 12 }).is_err());
    assert!(quantise(&image, 17, Quantisation::Float).is_err());
}

#[test]
fn roi_cut_averages_when_shrinking() {
    // A 1-texel checkerboard shrunk 4× by area averaging is flat grey;
    // point sampling would return all black or all white.
    let n = 64;
    let mut img = Image::new(n, n, 1);
    for y in 0..n {
        for x in 0..n {
            img.set(x, y, 0, ((x + y) % 2) as f32);
        }
    }
    let out = roi_cut(
        &img,
        Roi {
            x: 0,
            y: 0,
            width: n,
            height: n,
        },
        [16, 16],
    )
    .unwrap();
    assert!(
        out.data.iter().all(|v| (v - 0.5).abs() < 1e-6),
        "{:?}",
        &out.data[..4]
    );
    // Non-integer ratio: a ramp stays a ramp (means of spans).
    let mut ramp = Image::new(10, 1, 1);
    for x in 0..10 {
        ramp.set(x, 0, 0, x as f32);
    }
    let out = roi_cut(
        &ramp,
        Roi {
            x: 0,
            y: 0,
            width: 10,
            height: 1,
        },
        [4, 1],
    )
    .unwrap();
    // Spans [0, 2.5], [2.5, 5], … of the piecewise-constant input.
    let want = [0.8, 3.2, 5.8, 8.2];
    for (v, w) in out.data.iter().zip(want) {
        assert!((v - w).abs() < 1e-5, "{:?}", out.data);
    }
    // Enlarging interpolates; sub-rectangles are honoured; bad ROIs fail.
    let out = roi_cut(
        &ramp,
        Roi {
            x: 2,
            y: 0,
            width: 2,
            height: 1,
        },
        [4, 1],
    )
    .unwrap();
    assert_eq!(out.data, vec![2.0, 2.25, 2.75, 3.0]);
    assert!(roi_cut(
        &ramp,
        Roi {
            x: 8,
            y: 0,
            width: 3,
            height: 1
        },
        [4, 1]
    )
    .is_err());
    assert!(roi_cut(
        &ramp,
        Roi {
            x: 0,
            y: 0,
            width: 10,
            height: 1
        },
        [0, 1]
    )
    .is_err());
}

#[test]
fn invalid_inputs_are_errors_not_panics() {
    let bad = Image {
        width: 4,
        height: 4,
        channels: 1,
        data: vec![0.0; 3],
    };
    assert!(detect_markers(&bad, &[None], 10.0, &DetectOptions::default()).is_err());
    let good = Image::new(4, 4, 1);
    assert!(detect_markers(&good, &[None], f64::NAN, &DetectOptions::default()).is_err());
    let h = camera(0.0, 0.0, DIST, FOCAL, 0.0, [0.0, 0.0]);
    let region = Region::centred([0.05, 0.05]);
    assert!(rectify(&bad, &h, region, [8, 8], &RectifyOptions::default()).is_err());
    assert!(rectify(
        &good,
        &h,
        Region::centred([0.0, 0.05]),
        [8, 8],
        &RectifyOptions::default()
    )
    .is_err());
    let mut nan_h = h;
    nan_h[0][0] = f64::NAN;
    assert!(rectify(&good, &nan_h, region, [8, 8], &RectifyOptions::default()).is_err());
    // Outside the frame: zeros and zero coverage.
    let out = rectify(&good, &h, region, [8, 8], &RectifyOptions::default()).unwrap();
    assert!(out.coverage == 0.0 && out.texture.data.iter().all(|&v| v == 0.0));
    let layout = MarkerLayout::default_holder();
    assert!(register(&layout, &[None; 3], &RegisterOptions::default()).is_err());
}

// -------------------------------------------------------------- proptest

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn dlt_reproduces_exact_homographies(
        theta in 0.0f64..80.0,
        phi in 0.0f64..360.0,
        dist in 0.4f64..1.5,
        focal in 800.0f64..3000.0,
        roll in -180.0f64..180.0,
        ppx in -50.0f64..50.0,
        ppy in -50.0f64..50.0,
        refine in any::<bool>(),
    ) {
        let layout = MarkerLayout::default_holder();
        let h = camera(theta, phi, dist, focal, roll, [ppx, ppy]);
        let pix: Vec<[f64; 2]> = layout.points.iter().map(|&p| project(&h, p).unwrap()).collect();
        let est = fit_homography(&layout.points, &pix, refine).unwrap();
        let probes = layout.points.iter().copied().chain([[-0.05, -0.05], [0.05, 0.05], [0.05, -0.05], [0.0, 0.0]]);
        for p in probes {
            let (a, b) = (project(&h, p).unwrap(), project(&est, p).unwrap());
            let e = (a[0] - b[0]).hypot(a[1] - b[1]);
            prop_assert!(e < 1e-6, "reprojection error {} px at {:?}", e, p);
        }
        // Equal up to scale: compare unit-norm matrices with w > 0.
        let norm = h.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
        for i in 0..3 {
            for j in 0..3 {
                prop_assert!((h[i][j] / norm - est[i][j]).abs() < 1e-8, "{:?} vs {:?}", h, est);
            }
        }
    }
}

/// A smooth texture that does not tile: a ramp plus a slow wave.
fn ramp(side: usize) -> Image {
    let mut img = Image::new(side, side, 1);
    for y in 0..side {
        for x in 0..side {
            let v = 0.2 + 0.5 * x as f32 / side as f32 + 0.1 * (y as f32 * 0.05).sin();
            img.set(x, y, 0, v);
        }
    }
    img
}

/// Largest step between neighbouring texels inside the texture, and across
/// the seam where it meets a copy of itself (right edge to left, bottom to top).
fn steps(img: &Image) -> (f32, f32) {
    let n = img.width;
    let (mut inside, mut seam) = (0f32, 0f32);
    for y in 0..n {
        for x in 0..n {
            let v = img.get(x, y, 0);
            let right = img.get((x + 1) % n, y, 0);
            let down = img.get(x, (y + 1) % n, 0);
            let (a, b) = ((v - right).abs(), (v - down).abs());
            if x + 1 == n {
                seam = seam.max(a);
            } else {
                inside = inside.max(a);
            }
            if y + 1 == n {
                seam = seam.max(b);
            } else {
                inside = inside.max(b);
            }
        }
    }
    (inside, seam)
}

#[test]
fn edge_blending_removes_the_tiling_seam() {
    let (n, band) = (64, 8);
    let input = ramp(n + band);
    let plain = rigd_process::rectify::roi_cut(
        &input,
        rigd_process::rectify::Roi {
            x: 0,
            y: 0,
            width: n,
            height: n,
        },
        [n, n],
    )
    .unwrap();
    let (_, raw_seam) = steps(&plain);
    let blended = rigd_process::rectify::edge_blend(&input, band).unwrap();
    assert_eq!((blended.width, blended.height), (n, n));
    let (inside, seam) = steps(&blended);
    assert!(raw_seam > 0.4, "the ramp jumps at the seam: {raw_seam}");
    // Across the seam now no larger a step than the blend band makes inside.
    assert!(seam <= 1.5 * inside, "seam {seam}, inside {inside}");
    assert!(blended.data.iter().all(|v| v.is_finite()));
    // Outside the band the texture is untouched; a constant stays constant.
    assert_eq!(
        blended.get(band + 3, band + 5, 0),
        input.get(band + 3, band + 5, 0)
    );
    let mut flat = Image::new(n + band, n + band, 1);
    flat.data.iter_mut().for_each(|v| *v = 0.37);
    let b = rigd_process::rectify::edge_blend(&flat, band).unwrap();
    assert!(b.data.iter().all(|v| (v - 0.37).abs() < 1e-6));
    // No band: unchanged; a band too wide for the texture: an error.
    assert_eq!(rigd_process::rectify::edge_blend(&input, 0).unwrap(), input);
    assert!(rigd_process::rectify::edge_blend(&ramp(10), 5).is_err());
}
