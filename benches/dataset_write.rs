//! Dataset write throughput: 1024 × 768 12-bit frames written as the engine
//! writes them (PNG encode, SHA-256, temp file + rename, journal line
//! fsynced), into a directory on the working disk, not tmpfs. Criterion
//! reports raw frame bytes per second. Beside it, the disk's own sequential
//! figure as `dd if=/dev/zero bs=1M count=256 conv=fsync` measures it,
//! printed once, so the two can be compared.

use std::io::Write;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use rigd::rig::hal::Frame;
use rigd::store::{FrameEntry, RunDir};

const W: u32 = 1024;
const H: u32 = 768;

/// Sensor-like content: a gradient with noise, so PNG cannot cheat.
fn frame() -> Frame {
    let mut state = 0x2545_f491_4f6c_dd1d_u64;
    let pixels = (0..W * H)
        .map(|i| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let base = (i % W) * 3;
            (base + (state % 64) as u32).min(4095) as u16
        })
        .collect();
    Frame {
        width: W,
        height: H,
        bit_depth: 12,
        pixels,
        device: None,
        original: None,
    }
}

/// What `dd if=/dev/zero of=FILE bs=1M count=256 conv=fsync` measures.
fn dd_mb_s(dir: &std::path::Path) -> f64 {
    let block = vec![0u8; 1 << 20];
    let path = dir.join("dd.bin");
    let started = Instant::now();
    let mut f = std::fs::File::create(&path).expect("create");
    for _ in 0..256 {
        f.write_all(&block).expect("write");
    }
    f.sync_all().expect("fsync");
    let s = started.elapsed().as_secs_f64();
    std::fs::remove_file(&path).ok();
    256.0 * 1.048_576 / s
}

fn bench(c: &mut Criterion) {
    let dir = tempfile::tempdir_in(std::env::current_dir().expect("cwd")).expect("tempdir");
    eprintln!(
        "this disk, dd-style sequential write with fsync: {:.0} MB/s",
        dd_mb_s(dir.path())
    );
    let meta_dir = dir.path().join("run");
    std::fs::create_dir_all(meta_dir.join("frames")).expect("frames dir");
    let frame = frame();
    let template: FrameEntry = serde_json::from_value(serde_json::json!({
        "index": 0, "trigger": 0, "file": "", "sha256": "",
        "light": {"theta_deg": 0.0, "phi_deg": 0.0}, "view": {"theta_deg": 0.0, "phi_deg": 0.0},
        "achieved_light": {"theta_deg": 0.0, "phi_deg": 0.0},
        "achieved_view": {"theta_deg": 0.0, "phi_deg": 0.0},
        "camera": "cam", "exposure_s": 0.01, "t_s": 0.0,
        "positions": {"axes": {}, "lamp": "lamp"},
        "width": 0, "height": 0, "bit_depth": 0
    }))
    .expect("entry");
    let mut journal = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(meta_dir.join("journal.ndjson"))
        .expect("journal");
    let mut g = c.benchmark_group("dataset_write");
    g.throughput(Throughput::Bytes(u64::from(W * H) * 2));
    g.sample_size(20);
    let mut index = 0usize;
    g.bench_function("frame_1024x768x12bit", |b| {
        b.iter(|| {
            let mut e = template.clone();
            e.index = index;
            index += 1;
            let written = RunDir::write_frame(&meta_dir, e, &frame).expect("write");
            // The journal line, fsynced, as RunDir::append_journal does.
            let mut line = serde_json::to_vec(&written).expect("json");
            line.push(b'\n');
            journal.write_all(&line).expect("append");
            journal.sync_data().expect("fsync");
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
