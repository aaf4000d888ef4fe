//! Real cameras' files (`tests/data/camera-files`, whose README names each
//! file's camera, source and licence).
//! - Whole files, in `whole/`: each is decoded as `rigd frame decode`
//!   decodes it, in the decoder child, and every value of its active area
//!   must equal LibRaw's (`unprocessed_raw`, Debian's `libraw-bin`).
//! - Files cut short: LibRaw refuses each, and `rigd frame decode` must
//!   refuse each with exit 2, naming the format and what is wrong.
//! - A lab's own files, in the folder `RIGD_RAW_SAMPLES` names, are compared
//!   the same way; there a file LibRaw cannot open must be refused by rigd
//!   too.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use rigd::rig::camera_file::{CameraFileError, Decoder};

/// Whether LibRaw opens the file: `raw-identify` exits 0 without saying
/// "Cannot decode" (which it says on stderr, and exits 0 all the same).
fn libraw_opens(file: &Path) -> bool {
    std::process::Command::new("raw-identify")
        .arg(file)
        .output()
        .map(|o| {
            o.status.success()
                && ![&o.stdout, &o.stderr]
                    .iter()
                    .any(|s| String::from_utf8_lossy(s).contains("Cannot decode"))
        })
        .unwrap_or(false)
}

/// The camera files in `dir`, by name.
fn files_in(dir: &Path) -> Vec<PathBuf> {
    let entries = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("the camera files' folder {}: {e}", dir.display()));
    let mut files: Vec<PathBuf> = entries
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_file() && !p.extension().is_some_and(|e| e.eq_ignore_ascii_case("md")))
        .collect();
    files.sort();
    files
}

#[test]
fn real_cameras_files_cut_short_are_refused_naming_their_format() {
    let dir = crate::common::repo_file("tests/data/camera-files");
    let files = files_in(&dir);
    assert_eq!(files.len(), 3, "{files:?}");
    for file in &files {
        assert!(!libraw_opens(file), "{}: LibRaw opens it", file.display());
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigd"))
            .args(["frame", "decode"])
            .arg(file)
            .output()
            .expect("run rigd");
        let said = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{}: {said}", file.display());
        let format = file
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_uppercase)
            .expect("an extension");
        assert!(
            said.contains(&format!("{format} file cannot be decoded")),
            "{}: {said}",
            file.display()
        );
        assert!(!said.contains("panicked"), "{said}");
    }
    if let Some(lab) = std::env::var_os("RIGD_RAW_SAMPLES") {
        read_as_libraw_reads_them(Path::new(&lab), false);
    }
}

#[test]
fn real_cameras_whole_files_decode_to_libraws_values() {
    let makes = read_as_libraw_reads_them(
        &crate::common::repo_file("tests/data/camera-files/whole"),
        true,
    );
    assert_eq!(makes.len(), 2, "{makes:?}");
}

/// Every file in `dir` decodes to LibRaw's values, or (unless `must_decode`)
/// is refused as LibRaw refuses it. Returns the makes decoded.
fn read_as_libraw_reads_them(dir: &Path, must_decode: bool) -> std::collections::BTreeSet<String> {
    let files = files_in(dir);
    assert!(!files.is_empty(), "no files in {}", dir.display());
    let decoder = Decoder::command(
        env!("CARGO_BIN_EXE_rigd"),
        ["internal", "decode-frame"].map(OsString::from),
    );
    let mut makes = std::collections::BTreeSet::new();
    for file in &files {
        let bytes = std::fs::read(file).expect("read");
        let name = file.display();
        match decoder.decode(&bytes) {
            Ok(img) => {
                assert!(
                    libraw_opens(file),
                    "{name}: rigd decodes what LibRaw cannot"
                );
                let (lw, lh, libraw) = crate::camera_files::libraw_raw(file);
                let [x0, y0, w, h] = img.facts.active_area;
                assert_eq!(
                    (lw, lh),
                    (img.facts.full_size[0], img.facts.full_size[1]),
                    "{name}: the sensor's size"
                );
                assert_eq!((w, h), (img.width, img.height), "{name}");
                let mut cropped = Vec::with_capacity(img.samples.len());
                for row in libraw
                    .chunks_exact(lw as usize)
                    .skip(y0 as usize)
                    .take(h as usize)
                {
                    cropped.extend_from_slice(&row[x0 as usize..(x0 + w) as usize]);
                }
                let differ = cropped
                    .iter()
                    .zip(&img.samples)
                    .filter(|(a, b)| a != b)
                    .count();
                assert_eq!(differ, 0, "{name}: {differ} values differ from LibRaw's");
                eprintln!(
                    "{name}: {} {} {}x{}, {:?}, equal to LibRaw's",
                    img.facts.make, img.facts.model, img.width, img.height, img.facts.cfa_pattern
                );
                makes.insert(img.facts.make.clone());
            }
            Err(e @ (CameraFileError::Unsupported { .. } | CameraFileError::Unknown(_)))
                if !must_decode =>
            {
                assert!(
                    !libraw_opens(file),
                    "{name}: LibRaw opens what rigd refuses ({e})"
                );
                eprintln!("{name}: refused, as by LibRaw: {e}");
            }
            Err(e) => panic!("{name}: {e}"),
        }
    }
    eprintln!("real camera files: {} files, makes {makes:?}", files.len());
    makes
}
