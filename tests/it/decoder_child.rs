//! The decoder child, as the parent sees it: a child that aborts, hangs,
//! exits with an error or answers garbage is an error naming what happened,
//! and the calling process goes on; the real rigd child under its
//! address-space limit; and `rigd frame decode`, what rigd makes of a
//! camera's file.

use std::ffi::OsString;
use std::time::{Duration, Instant};

use rigd::rig::camera_file::{CameraFileError, Decoder, FileFormat};
use rigd_core::Cfa;
use rigd_sim::firmware::dng::{encode, to_raw, DngCamera};

use crate::common::rigd;

/// A stand-in decoder: `sh -c SCRIPT` (the limits rigd appends become the
/// script's positional parameters).
fn sh(script: &str) -> Decoder {
    Decoder::command("/bin/sh", [OsString::from("-c"), OsString::from(script)])
}

fn rigd_decoder() -> Decoder {
    Decoder::command(
        env!("CARGO_BIN_EXE_rigd"),
        ["internal", "decode-frame"].map(OsString::from),
    )
}

/// A simulated camera's DNG, `width × height`, 16 bits a sample.
fn dng(width: u32, height: u32, cfa: Option<Cfa>, bit_depth: u8) -> Vec<u8> {
    let camera = DngCamera {
        make: "rigd",
        model: "child",
        cfa,
        bit_depth,
    };
    let full = (1u32 << bit_depth.min(16)) - 1;
    let n = (width * height) as usize;
    let values: Vec<u16> = (0..n).map(|i| ((i * 7919) as u32 % full) as u16).collect();
    encode(&camera, width, height, &to_raw(&values, bit_depth), 0.004).expect("dng")
}

/// Sets the value of IFD0's SHORT or LONG entry `tag` in a little-endian
/// TIFF.
fn set_entry(bytes: &mut [u8], tag: u16, value: u32) {
    let le16 = |b: &[u8], at: usize| u16::from_le_bytes([b[at], b[at + 1]]);
    let ifd = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]) as usize;
    let entry = (0..usize::from(le16(bytes, ifd)))
        .map(|i| ifd + 2 + 12 * i)
        .find(|&at| le16(bytes, at) == tag)
        .expect("the tag");
    match le16(bytes, entry + 2) {
        3 => bytes[entry + 8..entry + 10].copy_from_slice(&(value as u16).to_le_bytes()),
        _ => bytes[entry + 8..entry + 12].copy_from_slice(&value.to_le_bytes()),
    }
}

fn crashed(result: Result<rigd::rig::camera_file::CameraImage, CameraFileError>) -> String {
    match result {
        Err(CameraFileError::Crashed(what)) => what,
        other => panic!("not a crash: {other:?}"),
    }
}

#[test]
fn a_child_that_aborts_hangs_fails_or_babbles_is_an_error_and_the_parent_goes_on() {
    let file = dng(8, 6, Some(Cfa::Rggb), 12);
    let what = crashed(sh("cat >/dev/null; kill -ABRT $$").decode(&file));
    assert!(
        what.contains("killed by signal 6 (SIGABRT)") && what.contains("4096 MiB"),
        "{what}"
    );
    let what = crashed(sh("cat >/dev/null; kill -SEGV $$").decode(&file));
    assert!(what.contains("signal 11 (SIGSEGV)"), "{what}");

    // A hang is killed at the deadline, the child's own children too.
    let started = Instant::now();
    let hang =
        sh("sleep 30 & cat >/dev/null; exec sleep 30").with_deadline(Duration::from_millis(500));
    let what = crashed(hang.decode(&file));
    assert!(what.contains("did not answer within 0.5 s"), "{what}");
    assert!(
        started.elapsed() < Duration::from_secs(10),
        "{:?}",
        started.elapsed()
    );

    let what = crashed(sh("cat >/dev/null; echo 'out of film' >&2; exit 3").decode(&file));
    assert_eq!(what, "exited with status 3: out of film");
    for garbage in [
        "cat >/dev/null; echo garbage",
        "cat >/dev/null; printf 'RIGDFRM1\\377\\377\\377\\377'",
        "cat >/dev/null; printf 'RIGDFRM1\\002\\000\\000\\000{}'",
        // A header that claims samples it does not send.
        r#"cat >/dev/null; printf 'RIGDFRM1\110\000\000\000{"image":{"format":"dng","width":9,"height":9,"channels":1,"cfa":null,' ; exit 0"#,
        "exec head -c 100000000 /dev/zero",
    ] {
        let what = crashed(sh(garbage).decode(&file));
        assert!(
            what.contains("garbage") || what.contains("ended early"),
            "{garbage}: {what}"
        );
    }
    // A child that does not read its input at all.
    let what = crashed(sh("exit 0").decode(&vec![0u8; 8 << 20]));
    assert!(what.contains("ended early"), "{what}");

    match Decoder::command("/nonexistent/rigd", []).decode(&file) {
        Err(e @ CameraFileError::NoDecoder(_)) => assert!(!e.is_the_file_s()),
        other => panic!("{other:?}"),
    }
    // And the real one, after all that, in this same process.
    let img = rigd_decoder().decode(&file).expect("the DNG");
    assert_eq!((img.width, img.height, img.cfa), (8, 6, Some(Cfa::Rggb)));
}

#[test]
fn a_batch_child_that_dies_is_replaced_for_the_next_file() {
    let file = dng(8, 6, None, 12);
    // Aborts on its first file: each file then starts a child.
    let mut batch = sh("kill -ABRT $$").batch();
    for n in 1..=3 {
        let what = crashed(batch.decode(&file));
        assert!(what.contains("SIGABRT"), "{what}");
        assert_eq!(batch.children_started(), n);
    }
    let mut batch = rigd_decoder().batch();
    for _ in 0..3 {
        batch.decode(&file).expect("the DNG");
    }
    assert!(batch.decode(b"II*\0junk").is_err());
    batch.decode(&file).expect("the DNG after a refusal");
    assert_eq!(batch.children_started(), 1);
}

#[test]
fn rigd_s_child_dies_alone_on_an_allocation_over_its_limit() {
    // A DNG claiming a 100000 × 100000 image: 20 GB of samples, which
    // rawler allocates before it finds the file holds 96 bytes of them.
    let mut huge = dng(8, 6, None, 12);
    set_entry(&mut huge, 0x0100, 100_000);
    set_entry(&mut huge, 0x0101, 100_000);
    let what = crashed(rigd_decoder().decode(&huge));
    assert!(
        what.contains("SIGABRT") && what.contains("memory allocation of 20000000000 bytes failed"),
        "{what}"
    );
    // A real frame needs more than 40 MiB: the child aborts, this process
    // goes on and says so.
    let big = dng(3032, 2008, Some(Cfa::Rggb), 16);
    let what = crashed(rigd_decoder().with_memory(40 << 20).decode(&big));
    assert!(
        what.contains("SIGABRT") && what.contains("40 MiB"),
        "{what}"
    );
    let img = rigd_decoder()
        .decode(&big)
        .expect("within the default limit");
    assert_eq!((img.width, img.height, img.bit_depth()), (3032, 2008, 16));
    assert_eq!(
        img,
        rigd::rig::camera_file::decode_here(&big).expect("here")
    );
}

#[test]
fn frame_decode_prints_the_facts_and_writes_raw_npy_frame_json_and_a_preview() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("frame.dng");
    std::fs::write(&file, dng(64, 48, Some(Cfa::Grbg), 12)).expect("write");
    let out_dir = dir.path().join("out");
    let out = rigd()
        .args(["frame", "decode"])
        .arg(&file)
        .arg("--out")
        .arg(&out_dir)
        .output()
        .expect("rigd");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for line in [
        "format        DNG",
        "camera        rigd child",
        "size          64 x 48 (1 channel)",
        "sensor        64 x 48, active area 64 x 48 at (0, 0)",
        "cfa           GRBG",
        "levels        black 255 255 255 255, white 4095 4095 4095 4095",
        "exposure      1/250 s",
    ] {
        assert!(text.contains(line), "{line:?} missing:\n{text}");
    }
    let facts: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out_dir.join("frame.json")).expect("frame.json"))
            .expect("json");
    assert_eq!(facts["cfa_pattern"], "GRBG");
    assert_eq!(facts["active_area"], serde_json::json!([0, 0, 64, 48]));
    assert_eq!(facts["exposure_s"], 0.004);
    // raw.npy: uint16, 48 × 64, the samples as LibRaw reads them.
    let npy = std::fs::read(out_dir.join("raw.npy")).expect("raw.npy");
    let header_len = u16::from_le_bytes([npy[8], npy[9]]) as usize;
    let header = String::from_utf8_lossy(&npy[10..10 + header_len]);
    assert!(
        header.contains("'descr': '<u2'") && header.contains("(48, 64,"),
        "{header}"
    );
    let values: Vec<u16> = npy[10 + header_len..]
        .chunks_exact(2)
        .map(|c| u16::from_le_bytes([c[0], c[1]]))
        .collect();
    let (w, h, libraw) = crate::camera_files::libraw_raw(&file);
    assert_eq!((w, h), (64, 48));
    assert_eq!(values, libraw);
    let png = std::fs::read(out_dir.join("preview.png")).expect("preview.png");
    let preview = rigd_process::image_io::load_png(&out_dir.join("preview.png")).expect("png");
    assert_eq!(
        (preview.width, preview.height, preview.channels),
        (64, 48, 3)
    );
    assert!(png.len() > 100);

    // --json says the same facts.
    let out = rigd()
        .args(["frame", "decode", "--json"])
        .arg(&file)
        .output()
        .expect("rigd");
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json");
    assert_eq!(json["make"], "rigd");
    assert_eq!(json["width"], 64);
}

#[test]
fn a_file_rigd_cannot_decode_exits_2_naming_the_format_and_what_is_missing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut vc5 = dng(16, 8, Some(Cfa::Rggb), 12);
    set_entry(&mut vc5, 0x0103, 9);
    let cases: [(&str, Vec<u8>, &str); 3] = [
        ("vc5.dng", vc5, "DNG with compression 9 (VC-5): no decoder"),
        (
            "text.nef",
            b"not a raw file".to_vec(),
            "not a camera file rigd reads",
        ),
        (
            "cut.dng",
            dng(16, 8, None, 12)[..200].to_vec(),
            "file cannot be decoded",
        ),
    ];
    for (name, bytes, says) in cases {
        let path = dir.path().join(name);
        std::fs::write(&path, bytes).expect("write");
        let out = rigd()
            .args(["frame", "decode"])
            .arg(&path)
            .output()
            .expect("rigd");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{name}: {err}");
        assert!(err.contains(says) && err.contains(name), "{name}: {err}");
    }
    let missing = rigd()
        .args(["frame", "decode", "/nonexistent/x.dng"])
        .output()
        .expect("rigd");
    assert_eq!(missing.status.code(), Some(2));
}

#[test]
fn the_decoder_is_hidden_from_help_and_frame_decode_is_not() {
    let help = rigd().arg("--help").output().expect("rigd");
    let text = String::from_utf8_lossy(&help.stdout);
    let commands: Vec<&str> = text
        .lines()
        .filter_map(|l| l.strip_prefix("  ")?.split_whitespace().next())
        .collect();
    assert!(commands.contains(&"frame"), "{text}");
    assert!(!commands.contains(&"internal"), "{text}");
    let help = rigd()
        .args(["frame", "decode", "--help"])
        .output()
        .expect("rigd");
    let text = String::from_utf8_lossy(&help.stdout);
    for word in ["raw.npy", "frame.json", "preview.png", "--out", "--json"] {
        assert!(text.contains(word), "{word}: {text}");
    }
}

/// The child's answer, through the record and its checks, is the image
/// the decoders give in this process.
#[test]
fn a_dng_through_the_child_is_the_dng_decoded_here() {
    for (cfa, depth) in [(Some(Cfa::Bggr), 8), (None, 14)] {
        let file = dng(30, 20, cfa, depth);
        let child = rigd_decoder().decode(&file).expect("child");
        assert_eq!(child.format, FileFormat::Dng);
        assert_eq!(
            child,
            rigd::rig::camera_file::decode_here(&file).expect("here")
        );
    }
}
