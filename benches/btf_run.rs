//! `rigd process btf --components 16` on a full H2 at 256² (81 view slots ×
//! 81 lights), end to end, beside its reference in the same run.
//!
//! `cargo bench --bench btf_run`. The run directory is synthetic: 6561 8-bit
//! normtextures of a smooth BTF with texture and noise, written as
//! `rigd process rectify` writes them, on the working disk (made once,
//! outside the timing; the page cache is warm, as it is right after
//! rectification). Three whole compressions are timed; the figure is the
//! fastest, with the peak resident memory the compression added.
//!
//! The reference is the floor the command is measured against: one slot's PCA through the
//! Gram matrix in f32 with faer (Gram, eigen-decomposition, 16
//! eigen-textures) on textures already in memory, on one thread (faer's own
//! threads made it vary fourfold with the other core busy), times 81. The
//! ratio says how close the whole command (PNG decoding, f64 accumulation,
//! the error report, writing 360 MB, on every core) comes to it.

use std::path::Path;
use std::time::{Duration, Instant};

use rayon::prelude::*;
use rigd::postprocess::btf::btf_run;
use rigd::postprocess::rectify::{FrameRegistration, NormtextureIndex, RegistrationMethod};
use rigd::store::processed::{normtextures_dir, NORMTEXTURE_INDEX};
use rigd_core::geometry::Direction;
use rigd_process::directions::h2;
use rigd_process::image_io::{encode_png, Image, PngDepth};

const SIDE: usize = 256;
const COMPONENTS: usize = 16;
const REPEATS: usize = 3;

/// One normtexture: a texel pattern lit by a few lobes of the light and view,
/// plus noise, as 8-bit codes / 255 (what `png8` normtextures hold).
fn texture(light: [f64; 3], view: [f64; 3], seed: u64) -> Image {
    let mut state = seed | 1;
    let mut img = Image::new(SIDE, SIDE, 1);
    let half = [light[0] + view[0], light[1] + view[1], light[2] + view[2]];
    let norm = (half[0] * half[0] + half[1] * half[1] + half[2] * half[2]).sqrt();
    let specular = (half[2] / norm).max(0.0).powi(8);
    for (i, out) in img.data.iter_mut().enumerate() {
        let (x, y) = ((i % SIDE) as f64, (i / SIDE) as f64);
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let noise = (state >> 40) as f64 / (1u64 << 24) as f64 - 0.5;
        let albedo = 0.45 + 0.25 * (0.11 * x).sin() * (0.07 * y).cos();
        let ridge = 0.15 * (0.4 * x).sin();
        let value = albedo * light[2].max(0.0)
            + ridge * light[0] * view[2]
            + 0.3 * specular * (1.0 + 0.5 * (0.05 * y).cos())
            + 0.01 * noise;
        *out = ((value.clamp(0.0, 1.0) * 255.0).round() / 255.0) as f32;
    }
    img
}

/// Writes the synthetic rectified run; returns its textures in slot-major
/// order for the reference.
fn make_run(run: &Path) -> Vec<Vec<f32>> {
    let dirs: Vec<Direction> = h2()
        .iter()
        .map(|d| Direction::new(d.theta_deg, d.phi_deg))
        .collect();
    let out = normtextures_dir(run);
    std::fs::create_dir_all(&out).expect("normtextures directory");
    let n = dirs.len();
    let textures: Vec<Vec<f32>> = (0..n * n)
        .into_par_iter()
        .map(|i| {
            let (slot, light) = (i / n, i % n);
            let img = texture(
                dirs[light].to_vector(),
                dirs[slot].to_vector(),
                i as u64 + 7,
            );
            let file = out.join(format!("v{slot:03}_l{light:03}.png"));
            let bytes = encode_png(&img, PngDepth::Eight, &file).expect("encode");
            std::fs::write(&file, bytes).expect("write texture");
            img.data
        })
        .collect();
    let frames = (0..n * n)
        .map(|i| FrameRegistration {
            index: i,
            view_slot: i / n,
            light_index: i % n,
            file: Some(format!("v{:03}_l{:03}.png", i / n, i % n)),
            rms_px: Some(0.1),
            max_px: Some(0.2),
            markers_found: 4,
            markers_used: 4,
            markers_rejected: Vec::new(),
            coverage: Some(1.0),
            method: Some(RegistrationMethod::Markers),
            error_px: Some(0.1),
            ..FrameRegistration::new(i, i / n, i % n)
        })
        .collect();
    let index = NormtextureIndex {
        size: SIDE,
        encoding: "png8".into(),
        bit_depth: 8,
        lights: dirs.clone(),
        views: dirs,
        frames,
        summary: None,
        roi: None,
        channels: 1,
    };
    let json = serde_json::to_vec_pretty(&index).expect("index json");
    std::fs::write(out.join(NORMTEXTURE_INDEX), json).expect("write index");
    textures
}

/// The reference: one slot's PCA through an f32 Gram matrix with
/// faer, on textures in memory.
fn reference_slot(images: &[&[f32]]) -> Duration {
    use faer::Mat;
    let (values, lights) = (images[0].len(), images.len());
    let start = Instant::now();
    let mean: Vec<f32> = (0..values)
        .map(|r| images.iter().map(|im| im[r]).sum::<f32>() / lights as f32)
        .collect();
    let x = Mat::<f32>::from_fn(values, lights, |r, c| images[c][r] - mean[r]);
    let mut gram = Mat::<f32>::zeros(lights, lights);
    faer::linalg::matmul::matmul(
        gram.as_mut(),
        faer::Accum::Replace,
        x.transpose(),
        x.as_ref(),
        1.0,
        faer::Par::Seq,
    );
    let eigen = gram
        .self_adjoint_eigen(faer::Side::Lower)
        .expect("eigen-decomposition");
    let top = eigen
        .U()
        .subcols(lights - COMPONENTS, COMPONENTS)
        .to_owned();
    let mut textures = Mat::<f32>::zeros(values, COMPONENTS);
    faer::linalg::matmul::matmul(
        textures.as_mut(),
        faer::Accum::Replace,
        x.as_ref(),
        top.as_ref(),
        1.0,
        faer::Par::Seq,
    );
    std::hint::black_box(textures);
    start.elapsed()
}

/// The command as it was before the Gram route: slot after slot,
/// each by a thin SVD, written as it finishes; same reading and writing.
fn before_gram_route(run: &Path) -> Duration {
    use rigd_process::btf::{compress_slot_by, BtfWriter, PcaRoute, TextureShape};
    use rigd_process::directions::DirectionTable;
    let index = NormtextureIndex::read(run).expect("index");
    let table = DirectionTable::new(h2()).expect("H2 table");
    let shape = TextureShape::new(SIDE, SIDE, 1).expect("shape");
    let dir = run.join("processed").join("btf-before");
    let start = Instant::now();
    let mut writer = BtfWriter::create(&dir, shape, &table, &table, COMPONENTS).expect("writer");
    for slot in 0..table.len() {
        let images: Vec<Vec<f32>> = (0..table.len())
            .map(|l| index.load(run, slot, l).expect("texture").data)
            .collect();
        let refs: Vec<&[f32]> = images.iter().map(Vec::as_slice).collect();
        let pca = compress_slot_by(PcaRoute::ThinSvd, &refs, shape, COMPONENTS).expect("PCA");
        writer.write_slot(slot, &pca).expect("write slot");
    }
    writer.finish().expect("finish");
    let took = start.elapsed();
    let _ = std::fs::remove_dir_all(&dir);
    took
}

/// A memory field of `/proc/self/status` (`VmHWM`, the peak since the last
/// reset; `VmRSS`, the current), bytes (Linux).
fn status_bytes(field: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(field))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Resets the peak to the current resident size (Linux ≥ 4.0).
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

fn main() {
    // `cargo bench` passes `--bench`; a filter argument that does not match
    // skips this whole-run figure, as criterion benches skip theirs.
    if let Some(filter) = std::env::args().skip(1).find(|a| !a.starts_with('-')) {
        if !"btf_run".contains(&filter) {
            return;
        }
    }
    let work = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).expect("scratch directory");
    let run = work.path().join("h2-256");
    let made = Instant::now();
    let textures = make_run(&run);
    eprintln!(
        "synthetic H2 run at {SIDE}² written in {:.1?} ({} textures)",
        made.elapsed(),
        textures.len()
    );

    let n = h2().len();
    let first: Vec<&[f32]> = textures[..n].iter().map(Vec::as_slice).collect();
    let one_slot = (0..5)
        .map(|_| reference_slot(&first))
        .min()
        .unwrap_or_default();
    drop(textures);
    let reference = one_slot * n as u32;

    let mut times = Vec::new();
    let mut peak_added = 0u64;
    for _ in 0..REPEATS {
        let _ = std::fs::remove_dir_all(rigd::store::processed::btf_dir(&run));
        reset_peak_rss();
        let before = status_bytes("VmRSS:").unwrap_or(0);
        let start = Instant::now();
        let report = btf_run(&run, COMPONENTS, &|_, _| {}).expect("btf_run");
        times.push(start.elapsed());
        peak_added = peak_added.max(status_bytes("VmHWM:").unwrap_or(0).saturating_sub(before));
        assert_eq!(report.slots, n);
    }
    times.sort();
    reset_peak_rss();
    let before_rss = status_bytes("VmRSS:").unwrap_or(0);
    let before = before_gram_route(&run);
    let before_peak = status_bytes("VmHWM:")
        .unwrap_or(0)
        .saturating_sub(before_rss);
    let best = times[0];
    println!(
        "btf_run/h2_256_c16: best {best:.2?} of {REPEATS} (all {times:.2?}); peak memory added {:.0} MiB",
        peak_added as f64 / (1 << 20) as f64
    );
    println!(
        "before (slot after slot, thin SVD): {before:.2?}, peak memory added {:.0} MiB; \
         speed-up {:.1}×",
        before_peak as f64 / (1 << 20) as f64,
        before.as_secs_f64() / best.as_secs_f64()
    );
    println!(
        "reference: one slot's f32 Gram PCA with faer on one thread {one_slot:.1?} × {n} = {reference:.2?}; \
         btf_run / reference = {:.2}",
        best.as_secs_f64() / reference.as_secs_f64()
    );
}
