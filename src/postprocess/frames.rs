//! A run's metadata and every frame it wrote, as the processing steps read them.

use std::path::{Path, PathBuf};

use rigd_process::demosaic;
use rigd_process::image_io::Image;

use super::ProcessError;
use crate::rig::camera_file::{self, CameraImage};
use crate::rig::hal::decode_png;
use crate::store::{read_journal, read_meta, FrameEntry, RunMeta, JOURNAL_FILE};

/// A run's metadata and every frame it wrote, in capture order.
pub struct RunFrames {
    /// The run directory.
    pub root: PathBuf,
    /// What the run was asked for (`run.json`).
    pub meta: RunMeta,
    /// Every journaled frame, sorted by image index.
    pub entries: Vec<FrameEntry>,
}

impl RunFrames {
    /// Reads the run directory's metadata and journal.
    pub fn open(root: &Path) -> Result<RunFrames, ProcessError> {
        let meta = read_meta(root)?;
        let (mut entries, _) = read_journal(&root.join(JOURNAL_FILE))?;
        entries.sort_by_key(|e| e.index);
        Ok(RunFrames {
            root: root.to_path_buf(),
            meta,
            entries,
        })
    }

    /// One frame as linear values in [0, 1].
    pub fn image(&self, entry: &FrameEntry) -> Result<Image, ProcessError> {
        let path = self.root.join(&entry.file);
        let bytes = std::fs::read(&path).map_err(|e| ProcessError::Frame {
            path: path.clone(),
            message: e.to_string(),
        })?;
        let frame_err = |message: String| ProcessError::Frame {
            path: path.clone(),
            message,
        };
        if !bytes.starts_with(PNG_MAGIC) {
            let img = camera_file::decode(&bytes).map_err(|e| frame_err(e.to_string()))?;
            return camera_file_grey(&img).map_err(|e| frame_err(e.to_string()));
        }
        let (w, h, pixels) = decode_png(&bytes).map_err(frame_err)?;
        linear_grey(entry, w, h, &pixels).map_err(|e| frame_err(e.to_string()))
    }
}

/// The first bytes of every PNG file: how rigd's own frames are told from
/// camera files.
const PNG_MAGIC: &[u8] = b"\x89PNG\r\n\x1a\n";

/// A camera file's image as linear grey in [0, 1]: black level off, scaled
/// by the white level, sRGB decoded; a Bayer mosaic demosaiced and RGB
/// weighted as `rigd_process::demosaic::luminance` weights it.
pub fn camera_file_grey(img: &CameraImage) -> Result<Image, demosaic::TooSmall> {
    let (w, h) = (img.width as usize, img.height as usize);
    let linear = img.linear();
    let mut out = Image::new(w, h, 1);
    out.data = match (img.channels, img.cfa) {
        (3, _) => linear
            .chunks_exact(3)
            .map(|c| 0.25 * c[0] + 0.5 * c[1] + 0.25 * c[2])
            .collect(),
        (_, Some(cfa)) => demosaic::luminance(&demosaic::bilinear(&linear, w, h, cfa)?),
        _ => linear,
    };
    Ok(out)
}

/// A frame's samples as linear grey in [0, 1]. A Bayer frame is stored as
/// its mosaic; until the colour pipeline lands, processing reads it as
/// grey (see `rigd_process::demosaic`).
fn linear_grey(
    entry: &FrameEntry,
    w: u32,
    h: u32,
    pixels: &[u16],
) -> Result<Image, demosaic::TooSmall> {
    let full = ((1u32 << entry.bit_depth.clamp(1, 16)) - 1) as f32;
    let mut img = Image::new(w as usize, h as usize, 1);
    for (d, &p) in img.data.iter_mut().zip(pixels) {
        *d = p as f32 / full;
    }
    let cfa = entry
        .device
        .as_ref()
        .and_then(|d| d.pixel_format.parse::<rigd_core::PixelFormat>().ok())
        .and_then(|f| f.cfa());
    if let Some(cfa) = cfa {
        let rgb = demosaic::bilinear(&img.data, img.width, img.height, cfa)?;
        img.data = demosaic::luminance(&rgb);
    }
    Ok(img)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(pixel_format: Option<&str>) -> FrameEntry {
        let d = serde_json::json!({"theta_deg": 0.0, "phi_deg": 0.0});
        let mut e = serde_json::json!({
            "index": 0, "trigger": 0, "file": "frames/000000.png", "sha256": "",
            "light": d, "view": d, "achieved_light": d, "achieved_view": d,
            "camera": "camera", "exposure_s": 0.01, "t_s": 0.0,
            "positions": {"axes": {}, "arm": null, "lamp": "lamp0"},
            "width": 4, "height": 2, "bit_depth": 8
        });
        if let Some(f) = pixel_format {
            e["device"] = serde_json::json!({"frame_id": 1, "timestamp_ns": 2, "pixel_format": f});
        }
        serde_json::from_value(e).expect("a frame entry")
    }

    #[test]
    fn a_bayer_mosaic_reads_as_grey_and_a_mono_frame_as_it_is() {
        // Red 255, green 51, blue 0 behind an RGGB tile.
        let mosaic = [255, 51, 255, 51, 51, 0, 51, 0];
        let grey = linear_grey(&entry(Some("BayerRG8")), 4, 2, &mosaic).expect("grey");
        let want = (0.25 * 255.0 + 0.5 * 51.0) / 255.0;
        assert!(
            grey.data.iter().all(|v| (v - want).abs() < 1e-6),
            "{:?}",
            grey.data
        );
        for format in [None, Some("Mono8")] {
            let mono = linear_grey(&entry(format), 4, 2, &mosaic).expect("mono");
            assert_eq!(mono.data[1], 51.0 / 255.0, "{format:?}");
        }
        let e = linear_grey(&entry(Some("BayerRG8")), 4, 1, &mosaic[..4]).expect_err("1 row");
        assert_eq!(e.height, 1);
    }
}
