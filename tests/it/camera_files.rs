//! Frames as camera files: a simulated PTP run keeps every frame as the DNG
//! its camera delivered, with the file's SHA-256 in the manifest. LibRaw
//! (Debian's `libraw-bin`, a raw decoder rigd does not use) opens each one
//! and reads the same samples rigd reads; processing runs on them.

use std::path::Path;
use std::process::Command;

use proptest::prelude::*;

use std::ffi::OsString;

use rigd::rig::camera_file::{self, CameraFileError, Decoder, FileFormat};
use rigd_core::Cfa;

use crate::bring_up::{device, edit};
use crate::common::{assert_complete_run, repo_file, run_ok};

/// Runs a LibRaw sample program, which must be installed (scripts/test.sh).
fn libraw(program: &str, args: &[&Path]) -> String {
    let out = Command::new(program)
        .args(args)
        .output()
        .unwrap_or_else(|e| {
            panic!("{program} (Debian libraw-bin, installed by scripts/test.sh): {e}")
        });
    assert!(out.status.success(), "{program}: {out:?}");
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The samples of a 16-bit binary PGM, as `unprocessed_raw` writes them.
fn pgm_samples(bytes: &[u8]) -> (u32, u32, Vec<u16>) {
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        while bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        let start = at;
        while !bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        fields.push(String::from_utf8_lossy(&bytes[start..at]).into_owned());
    }
    assert_eq!((fields[0].as_str(), fields[3].as_str()), ("P5", "65535"));
    let (w, h): (u32, u32) = (
        fields[1].parse().expect("width"),
        fields[2].parse().expect("height"),
    );
    let samples = bytes[at + 1..]
        .chunks_exact(2)
        .map(|c| u16::from_be_bytes([c[0], c[1]]))
        .collect();
    (w, h, samples)
}

/// LibRaw's raw values of `file` (`unprocessed_raw`, the whole sensor
/// readout): width, height, samples.
pub(crate) fn libraw_raw(file: &Path) -> (u32, u32, Vec<u16>) {
    let dir = tempfile::tempdir().expect("tempdir");
    let name = file.file_name().expect("a file name");
    let copy = dir.path().join(name);
    std::fs::copy(file, &copy).expect("copy");
    libraw("unprocessed_raw", &[Path::new("-q"), &copy]);
    let mut pgm = copy.into_os_string();
    pgm.push(".pgm");
    pgm_samples(&std::fs::read(pgm).expect("LibRaw's PGM"))
}

/// The VirTex rig (three lamps, one PTP camera) with its camera's sensor
/// behind `cfa`, or monochrome, of `bit_depth` bits.
fn virtex_with(dir: &Path, cfa: Option<&str>, bit_depth: u8) -> std::path::PathBuf {
    virtex_on(dir, None, cfa, bit_depth)
}

/// [`virtex_with`], rendering `scene` (the profile's own if `None`).
pub(crate) fn virtex_on(
    dir: &Path,
    scene: Option<&str>,
    cfa: Option<&str>,
    bit_depth: u8,
) -> std::path::PathBuf {
    let profile = dir.join(format!(
        "virtex-{}-{}-{bit_depth}.toml",
        scene.unwrap_or("default"),
        cfa.unwrap_or("mono")
    ));
    edit(
        &repo_file("rig-profiles/virtex-photometric-stereo.toml"),
        &profile,
        |t| {
            let camera = device(t, "camera");
            let intrinsics = camera
                .get_mut("intrinsics")
                .and_then(|i| i.as_table_mut())
                .expect("intrinsics");
            intrinsics.insert("bit_depth".into(), i64::from(bit_depth).into());
            if let Some(cfa) = cfa {
                intrinsics.insert("cfa".into(), cfa.into());
            }
            if let Some(scene) = scene {
                t.get_mut("sim")
                    .and_then(|s| s.as_table_mut())
                    .expect("[sim]")
                    .insert("scene".into(), scene.into());
            }
        },
    );
    profile
}

fn capture(profile: &Path, out: &Path) {
    capture_at(profile, out, "96x64");
}

/// A simulated run of `profile` at frame size `size` (`WxH`) into `out`.
pub(crate) fn capture_at(profile: &Path, out: &Path, size: &str) {
    run_ok(&[
        "run",
        "--sim",
        "--profile",
        profile.to_str().expect("utf8"),
        "--frame-size",
        size,
        "--progress",
        "none",
        "--out",
        out.to_str().expect("utf8"),
    ]);
}

#[test]
fn every_frame_of_a_simulated_ptp_run_is_a_dng_libraw_reads_as_rigd_does() {
    let dir = tempfile::tempdir().expect("tempdir");
    for (cfa, want, depth) in [
        (Some("RGGB"), Some(Cfa::Rggb), 12u8),
        (None, None, 12),
        (Some("BGGR"), Some(Cfa::Bggr), 8),
    ] {
        let (black, white): (u16, u16) = if depth == 8 { (15, 255) } else { (255, 4095) };
        let out = dir
            .path()
            .join(format!("run-{}-{depth}", cfa.unwrap_or("mono")));
        capture(&virtex_with(dir.path(), cfa, depth), &out);
        // Every checksum matches its file (assert_complete_run reads them).
        let m = assert_complete_run(&out, 3);
        for f in &m.frames {
            assert!(f.file.ends_with(".dng"), "{}", f.file);
            let path = out.join(&f.file);
            let bytes = std::fs::read(&path).expect("frame");
            let img = camera_file::decode(&bytes).unwrap_or_else(|e| panic!("{}: {e}", f.file));
            assert_eq!(img.format, FileFormat::Dng);
            assert_eq!((img.width, img.height, img.cfa), (96, 64, want));
            assert_eq!((img.black, img.white), (f32::from(black), f32::from(white)));
            assert_eq!((f.width, f.height, f.bit_depth), (96, 64, depth));

            // raw-identify aligns its columns: compare with single spaces.
            let said = libraw("raw-identify", &[Path::new("-v"), &path])
                .lines()
                .map(|l| l.split_whitespace().collect::<Vec<_>>().join(" "))
                .collect::<Vec<_>>()
                .join("\n");
            let black_line = format!("black: {black}");
            for line in ["DNG Version: 1.4.0.0", "Full size: 96 x 64", &black_line] {
                assert!(said.contains(line), "{} lacks {line:?}:\n{said}", f.file);
            }
            if let Some(cfa) = cfa {
                // LibRaw prints the 2x2 tile four times over, and the
                // colour matrix the camera declares.
                assert!(said.contains("DNG Illuminant 1: D65"), "{said}");
                let pattern = format!("Filter pattern: {}", cfa.repeat(4));
                assert!(
                    said.contains(&pattern),
                    "{} lacks {pattern:?}:\n{said}",
                    f.file
                );
            }
            // LibRaw's unpacked samples, written next to the frame.
            libraw("unprocessed_raw", &[Path::new("-q"), &path]);
            let pgm = std::fs::read(path.with_extension("dng.pgm")).expect("LibRaw's PGM");
            assert_eq!(
                pgm_samples(&pgm),
                (96, 64, img.samples.clone()),
                "{}",
                f.file
            );
            // Lit frames: the lamp's light is well above black.
            assert!(
                img.samples.iter().any(|&s| s > 4 * black),
                "{} is dark",
                f.file
            );
        }
    }
}

#[test]
fn photometric_stereo_reads_a_bayer_camera_s_dngs() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run = dir.path().join("run");
    capture(&virtex_with(dir.path(), Some("GRBG"), 12), &run);
    let out = dir.path().join("ps");
    run_ok(&[
        "process",
        "photometric-stereo",
        run.to_str().expect("utf8"),
        "--out",
        out.to_str().expect("utf8"),
    ]);
    for file in ["normals.npy", "albedo.npy", "report.json"] {
        assert!(out.join(file).is_file(), "{file}");
    }
}

/// A small DNG of the simulated camera, for the decoder's hard cases.
fn sim_dng(cfa: Option<Cfa>, bit_depth: u8) -> Vec<u8> {
    use rigd_sim::firmware::dng::{encode, to_raw, DngCamera};
    let camera = DngCamera {
        make: "rigd",
        model: "fuzz",
        cfa,
        bit_depth,
    };
    let full = (1u32 << bit_depth) - 1;
    let values: Vec<u16> = (0..48u32).map(|i| (i * full / 47) as u16).collect();
    encode(&camera, 8, 6, &to_raw(&values, bit_depth), 0.1).expect("dng")
}

/// The rigd binary as the decoder child, as the library runs it.
fn rigd_decoder() -> Decoder {
    // `RIGD_DECODER` lets a long run use a binary that a rebuild cannot
    // replace under it.
    Decoder::command(
        std::env::var_os(rigd::rig::camera_file::DECODER_ENV)
            .unwrap_or_else(|| env!("CARGO_BIN_EXE_rigd").into()),
        ["internal", "decode-frame"].map(OsString::from),
    )
}

/// Cases of the damaged-file property test: `RIGD_DAMAGED_CASES`, else
/// what CI runs. Each case decodes two files (the damaged one whole and
/// cut). `RIGD_DAMAGED_CASES=100000 cargo test --release -p rigd --test it
/// -- damaged` is the long run (`docs/processing.md`, "Camera files").
fn damaged_cases() -> u32 {
    std::env::var("RIGD_DAMAGED_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(DAMAGED_CASES_CI)
}

/// The cases CI runs (about half a minute in the test build).
const DAMAGED_CASES_CI: u32 = 2000;

/// Whatever a camera or a disk hands over, decoding answers: an image or
/// an error, never a crash of this process. Flipped and cut DNGs reach
/// deep into rawler's TIFF and DNG code; random bytes behind a JPEG or TIFF
/// header reach zune-jpeg's and tiff's. The files go to one decoder child
/// kept for all of them (`BatchDecoder`); one that dies (an allocation a
/// file asked for over its address-space limit aborts it) is an error and
/// a new child takes the next file. A fixed seed: the cases CI runs are
/// the ones a newcomer's run finds.
#[test]
fn decoding_a_damaged_camera_file_is_an_answer_not_a_crash() {
    use proptest::test_runner::{Config, RngSeed, TestRunner};
    let cases = damaged_cases();
    let mut runner = TestRunner::new(Config {
        cases,
        rng_seed: RngSeed::Fixed(16),
        failure_persistence: None,
        ..Config::default()
    });
    let decoder = std::sync::Mutex::new(
        rigd_decoder()
            .with_deadline(std::time::Duration::from_secs(20))
            .batch(),
    );
    // Images, refusals, crashes (signal, exit status, garbage, deadline).
    let counts = std::sync::Mutex::new([0usize; 3]);
    // How the decoder died, by the start of the message.
    let deaths = std::sync::Mutex::new(std::collections::BTreeMap::<String, usize>::new());
    let strategy = (
        proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
        any::<prop::sample::Index>(),
        proptest::collection::vec(any::<u8>(), 0..64),
        0usize..4,
    );
    let good = [sim_dng(Some(Cfa::Rggb), 12), sim_dng(None, 8)];
    let started = std::time::Instant::now();
    let outcome = runner.run(&strategy, |(flips, cut, tail, which)| {
        let mut file = match which {
            0 | 1 => good[which].clone(),
            2 => [&[0xFF, 0xD8, 0xFF, 0xE0][..], &tail].concat(),
            _ => [&b"II*\0\x08\0\0\0"[..], &tail].concat(),
        };
        for (at, byte) in &flips {
            let i = at.index(file.len());
            file[i] ^= byte;
        }
        let keep = cut.index(file.len() + 1);
        let mut decoder = decoder.lock().expect("decoder");
        for bytes in [&file[..keep], &file[..]] {
            let kind = match decoder.decode(bytes) {
                Ok(_) => 0,
                Err(CameraFileError::Crashed(what)) => {
                    let head: String = what
                        .chars()
                        .map(|c| if c.is_ascii_digit() { '#' } else { c })
                        .collect();
                    *deaths.lock().expect("deaths").entry(head).or_default() += 1;
                    2
                }
                Err(CameraFileError::NoDecoder(e)) => {
                    return Err(proptest::test_runner::TestCaseError::fail(e))
                }
                Err(_) => 1,
            };
            counts.lock().expect("counts")[kind] += 1;
        }
        Ok(())
    });
    let [images, refused, crashed] = *counts.lock().expect("counts");
    let children = decoder.lock().expect("decoder").children_started();
    eprintln!(
        "{cases} damaged-file cases, {} files: {images} images, {refused} refused, \
         {crashed} crashed the decoder ({children} children started) in {:.1} s",
        images + refused + crashed,
        started.elapsed().as_secs_f64()
    );
    for (how, n) in deaths.lock().expect("deaths").iter() {
        eprintln!("  {n:6}  {how}");
    }
    if let Err(e) = outcome {
        panic!("{e}");
    }
    assert_eq!(images + refused + crashed, 2 * cases as usize);
}

#[test]
fn an_undamaged_dng_decodes_at_every_depth_and_layout() {
    for (cfa, depth) in [
        (Some(Cfa::Gbrg), 16),
        (Some(Cfa::Grbg), 8),
        (None, 14),
        (None, 10),
    ] {
        let img = camera_file::decode(&sim_dng(cfa, depth)).expect("a DNG");
        assert_eq!(
            (img.width, img.height, img.cfa, img.bit_depth()),
            (8, 6, cfa, depth)
        );
        let linear = img.linear();
        // Black maps to 0 and white to 1, whatever the depth.
        assert_eq!((linear[0], linear[47]), (0.0, 1.0), "{cfa:?} {depth}");
    }
}
