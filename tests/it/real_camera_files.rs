//! Real cameras' files, when the machine has them: every file in the
//! samples folder (`RIGD_RAW_SAMPLES`, else `shared/raw-samples` beside
//! the repository) is decoded as `rigd frame decode` decodes it, in the
//! decoder child, and its values compared with LibRaw's (`unprocessed_raw`,
//! Debian's `libraw-bin`) over the active area; a file LibRaw cannot open
//! either must be refused by rigd naming its format and what is missing.
//! The folder's README names each file's camera, source and licence.
//! Without the folder the test says so and checks nothing.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use rigd::rig::camera_file::{CameraFileError, Decoder};

/// Where the real files are.
fn samples_dir() -> PathBuf {
    std::env::var_os("RIGD_RAW_SAMPLES")
        .map(PathBuf::from)
        .unwrap_or_else(|| crate::common::repo_file("../shared/raw-samples"))
}

/// Whether LibRaw opens the file (`raw-identify` exits 0).
fn libraw_opens(file: &Path) -> bool {
    std::process::Command::new("raw-identify")
        .arg(file)
        .output()
        .map(|o| {
            o.status.success() && !String::from_utf8_lossy(&o.stdout).contains("Cannot decode")
        })
        .unwrap_or(false)
}

#[test]
fn real_cameras_files_read_as_libraw_reads_them() {
    let dir = samples_dir();
    let Ok(entries) = std::fs::read_dir(&dir) else {
        eprintln!(
            "no real camera files at {} (set RIGD_RAW_SAMPLES): nothing checked",
            dir.display()
        );
        return;
    };
    let mut files: Vec<PathBuf> = entries
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.is_file()
                && !p
                    .extension()
                    .is_some_and(|e| e.eq_ignore_ascii_case("md") || e.eq_ignore_ascii_case("pgm"))
        })
        .collect();
    files.sort();
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
            Err(e @ (CameraFileError::Unsupported { .. } | CameraFileError::Unknown(_))) => {
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
}
