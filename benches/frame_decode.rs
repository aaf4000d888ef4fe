//! What decoding a camera file in a child process costs against decoding
//! it in rigd's own process (`rigd::rig::camera_file`): a 3032 × 2008
//! 16-bit DNG of the simulated camera (12 MB, one uncompressed strip, as
//! `rigd run --sim` writes them), decoded
//!
//! - `in_process`: the decoders called here (`decode_here`);
//! - `child`: a new `rigd internal decode-frame` for the file, as the
//!   driver, the CLI and the API decode (`Decoder::decode`): process start,
//!   the file through a pipe in, the samples through a pipe out;
//! - `batch_child`: one kept child for every file (`BatchDecoder`);
//!
//! and `child_tiny`, a new child for an 8 × 6 DNG: what starting a child
//! costs by itself. `cargo bench --bench frame_decode`.

use std::ffi::OsString;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use rigd::rig::camera_file::{decode_here, Decoder};
use rigd_core::Cfa;
use rigd_sim::firmware::dng::{encode, to_raw, DngCamera};

fn dng(width: u32, height: u32) -> Vec<u8> {
    let camera = DngCamera {
        make: "rigd",
        model: "bench",
        cfa: Some(Cfa::Rggb),
        bit_depth: 16,
    };
    // Sensor-like content: a gradient with noise.
    let mut state = 0x2545_f491_4f6c_dd1d_u64;
    let values: Vec<u16> = (0..width * height)
        .map(|i| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((i % width) * 20 + (state % 512) as u32).min(65535) as u16
        })
        .collect();
    encode(&camera, width, height, &to_raw(&values, 16), 0.01).expect("dng")
}

fn bench(c: &mut Criterion) {
    let decoder = Decoder::command(
        env!("CARGO_BIN_EXE_rigd"),
        ["internal", "decode-frame"].map(OsString::from),
    );
    let big = dng(3032, 2008);
    let tiny = dng(8, 6);
    // The three ways give the same image.
    let here = decode_here(&big).expect("in process");
    assert_eq!(decoder.decode(&big).expect("child"), here);
    let mut batch = decoder.batch();
    assert_eq!(batch.decode(&big).expect("batch child"), here);

    let mut g = c.benchmark_group("frame_decode");
    g.sample_size(30);
    g.throughput(Throughput::Bytes(big.len() as u64));
    g.bench_function("in_process_3032x2008x16", |b| {
        b.iter(|| decode_here(&big).expect("decode"))
    });
    g.bench_function("child_3032x2008x16", |b| {
        b.iter(|| decoder.decode(&big).expect("decode"))
    });
    g.bench_function("batch_child_3032x2008x16", |b| {
        b.iter(|| batch.decode(&big).expect("decode"))
    });
    g.throughput(Throughput::Elements(1));
    g.bench_function("child_tiny_8x6", |b| {
        b.iter(|| decoder.decode(&tiny).expect("decode"))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
