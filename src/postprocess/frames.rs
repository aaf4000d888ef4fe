//! A run's metadata and every frame it wrote, as the processing steps read
//! them: the journal through the store's reader (which never writes),
//! checked against the manifest of an ended run, and each frame checked
//! against the SHA-256 its journal line recorded before it is decoded.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use rigd_process::demosaic;
use rigd_process::image_io::Image;

use super::ProcessError;
use crate::rig::camera_file::{self, CameraFileError, CameraImage, Decoder, DecoderPool};
use crate::rig::hal::{decode_png, is_png};
use crate::store::{
    check_manifest, read_journal, read_meta, sha256_hex, FrameEntry, RunMeta, JOURNAL_FILE,
};
use rigd_core::sync::lock;
use rigd_core::Cfa;

/// A run's metadata and every frame it wrote, in capture order.
pub struct RunFrames {
    /// The run directory.
    pub root: PathBuf,
    /// What the run was asked for (`run.json`).
    pub meta: RunMeta,
    /// Every journaled frame, one per image, sorted by image index.
    pub entries: Vec<FrameEntry>,
    /// Reads frames checked against their SHA-256.
    checked: CheckedReads,
    /// Decoder children kept for a hardware run's camera files, started
    /// at the first one.
    decoders: OnceLock<Result<DecoderPool, CameraFileError>>,
}

/// Reads frames checked against the SHA-256 their journal lines recorded,
/// and remembers which passed, by file: the checksum and the file as it
/// was then. A frame read again (the registration reads some twice) from
/// the very same file is not hashed again.
#[derive(Default)]
struct CheckedReads(Mutex<HashMap<PathBuf, (String, FileStamp)>>);

/// What identifies a file's content without reading it: a file replaced
/// (renamed over) has another inode, one written in place another change
/// time, which no one can set back.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct FileStamp {
    dev: u64,
    ino: u64,
    len: u64,
    ctime: (i64, i64),
    mtime: (i64, i64),
}

impl FileStamp {
    fn of(m: &std::fs::Metadata) -> FileStamp {
        use std::os::unix::fs::MetadataExt;
        FileStamp {
            dev: m.dev(),
            ino: m.ino(),
            len: m.len(),
            ctime: (m.ctime(), m.ctime_nsec()),
            mtime: (m.mtime(), m.mtime_nsec()),
        }
    }
}

impl RunFrames {
    /// Reads the run directory's metadata and journal (its complete lines,
    /// one entry per image; a run still being captured is read as far as it
    /// is). An ended run whose journal and manifest disagree, or whose
    /// manifest does not parse, is refused naming both.
    pub fn open(root: &Path) -> Result<RunFrames, ProcessError> {
        let meta = read_meta(root)?;
        let (entries, _) = read_journal(&root.join(JOURNAL_FILE))?;
        check_manifest(root, &entries)?;
        Ok(RunFrames {
            root: root.to_path_buf(),
            meta,
            entries,
            checked: CheckedReads::default(),
            decoders: OnceLock::new(),
        })
    }

    /// One frame as linear values in [0, 1].
    pub fn image(&self, entry: &FrameEntry) -> Result<Image, ProcessError> {
        let (linear, _) = self.linear(entry)?;
        linear.grey().map_err(|e| self.frame_error(entry, e))
    }

    /// One frame as [`Self::image`] reads it, with the pixels the sensor
    /// clipped ([`Clipped`]).
    pub fn image_and_clipped(
        &self,
        entry: &FrameEntry,
    ) -> Result<(Image, Option<Clipped>), ProcessError> {
        let (linear, level) = self.linear(entry)?;
        let clipped = linear.clipped(level);
        let image = linear.grey().map_err(|e| self.frame_error(entry, e))?;
        Ok((image, clipped))
    }

    /// One frame's red, green and blue planes, linear in [0, 1], with its
    /// width and height: a Bayer mosaic demosaiced by
    /// [`demosaic::DEFAULT_METHOD`], an RGB file as it is. `None` for a
    /// monochrome camera's frame.
    pub fn colour_planes(&self, entry: &FrameEntry) -> Result<Option<ColourPlanes>, ProcessError> {
        let (linear, _) = self.linear(entry)?;
        linear.planes().map_err(|e| self.frame_error(entry, e))
    }

    /// One frame's colour planes, as [`Self::colour_planes`] reads them,
    /// with the grey [`Self::image`] reads, which its markers are found in
    /// ([`CorrectedFrame::grey`] says why). `None` for a monochrome
    /// camera's frame.
    pub fn colour_planes_and_grey(
        &self,
        entry: &FrameEntry,
    ) -> Result<Option<(ColourPlanes, Image)>, ProcessError> {
        let (linear, _) = self.linear(entry)?;
        let error = |e| self.frame_error(entry, e);
        let Some(grey) = linear.colour_grey().map_err(error)? else {
            return Ok(None);
        };
        Ok(linear.planes().map_err(error)?.map(|planes| (planes, grey)))
    }

    /// One frame white-balanced and colour-corrected by `calibration`:
    /// three interleaved channels of linear sRGB. `None` for a monochrome
    /// camera's frame.
    pub fn corrected(
        &self,
        entry: &FrameEntry,
        calibration: &rigd_process::colour::ColourCalibration,
    ) -> Result<Option<Image>, ProcessError> {
        Ok(self
            .corrected_frame(entry, calibration)?
            .map(|frame| frame.rgb))
    }

    /// One frame as [`Self::corrected`] reads it, with its grey and the
    /// pixels the sensor clipped ([`CorrectedFrame`]).
    pub fn corrected_frame(
        &self,
        entry: &FrameEntry,
        calibration: &rigd_process::colour::ColourCalibration,
    ) -> Result<Option<CorrectedFrame>, ProcessError> {
        let (linear, level) = self.linear(entry)?;
        let clipped = linear.clipped(level);
        let error = |e| self.frame_error(entry, e);
        let Some(grey) = linear.colour_grey().map_err(error)? else {
            return Ok(None);
        };
        let Some(planes) = linear.planes().map_err(error)? else {
            return Ok(None);
        };
        let mut out = Image::new(planes.width, planes.height, 3);
        let [r, g, b] = &planes.rgb;
        for (((px, r), g), b) in out.data.chunks_exact_mut(3).zip(r).zip(g).zip(b) {
            let c = calibration.apply([f64::from(*r), f64::from(*g), f64::from(*b)]);
            for (d, v) in px.iter_mut().zip(c) {
                *d = v as f32;
            }
        }
        Ok(Some(CorrectedFrame {
            rgb: out,
            grey,
            clipped,
        }))
    }

    fn frame_error(&self, entry: &FrameEntry, e: impl std::fmt::Display) -> ProcessError {
        ProcessError::Frame {
            path: self.root.join(&entry.file),
            message: e.to_string(),
        }
    }

    /// The frame's samples, linear, 1 = full scale of its first exposure,
    /// and the level at or above which a sample is clipped: as the camera
    /// recorded them, or its exposures merged ([`rigd_process::hdr`]) when
    /// the step took several. A file whose bytes do not hash to the
    /// SHA-256 its journal line recorded is [`ProcessError::Damaged`],
    /// whatever it would decode to.
    fn linear(&self, entry: &FrameEntry) -> Result<(Linear, f32), ProcessError> {
        let first = self.linear_file(entry, &entry.file, &entry.sha256)?;
        if entry.brackets.is_empty() {
            return Ok((first, CLIPPED_LEVEL));
        }
        let mut exposures = vec![(first, entry.exposure_s)];
        for b in &entry.brackets {
            exposures.push((self.linear_file(entry, &b.file, &b.sha256)?, b.exposure_s));
        }
        merge_linear(exposures, entry.exposure_s).map_err(|message| ProcessError::Frame {
            path: self.root.join(&entry.file),
            message: format!(
                "merging its {} exposures: {message}",
                entry.brackets.len() + 1
            ),
        })
    }

    /// One file of a frame's, checked against `sha256` and decoded.
    fn linear_file(
        &self,
        entry: &FrameEntry,
        file: &str,
        sha256: &str,
    ) -> Result<Linear, ProcessError> {
        let path = self.root.join(file);
        let bytes = self.checked.read(entry.index, sha256, &path)?;
        let frame_err = |message: String| ProcessError::Frame {
            path: path.clone(),
            message,
        };
        // A simulated run's frames are DNGs rigd's own simulator wrote,
        // and these bytes hash to the journal's line: they are decoded in
        // this process. Anything a camera delivered goes to the decoder
        // child (`docs/processing.md`, "Camera files").
        let decode = |bytes: &[u8]| {
            if self.meta.simulated {
                return camera_file::decode_here(bytes);
            }
            match self
                .decoders
                .get_or_init(|| Decoder::rigd().map(DecoderPool::new))
            {
                Ok(pool) => pool.decode(bytes),
                Err(e) => Err(e.clone()),
            }
        };
        decode_linear(&bytes, entry.bit_depth, cfa_of(entry), decode).map_err(frame_err)
    }
}

/// A frame file's bytes as linear values in [0, 1], read as a run's frames
/// are: a camera file (DNG, vendor raw, JPEG, TIFF) by its content, a PNG
/// as a rig writes it (values of `bit_depth` significant bits, a Bayer
/// mosaic behind `cfa` when one is given). The image has one channel for
/// a monochrome frame and three (red, green, blue, demosaiced bilinearly
/// as [`RunFrames::colour_planes`] reads them) for a colour one. `Err`
/// says why the bytes are no frame.
pub fn decode_frame(bytes: &[u8], bit_depth: u8, cfa: Option<Cfa>) -> Result<Image, String> {
    decode_linear(bytes, bit_depth, cfa, camera_file::decode)?.into_image()
}

/// A frame's bare samples (`width × height` values of `bit_depth`
/// significant bits, row by row, as a camera delivers them) as
/// [`decode_frame`] reads the PNG a rig stores them in: one channel for a
/// monochrome sensor, three (demosaiced alike) behind `cfa`.
pub fn decode_samples(
    width: u32,
    height: u32,
    bit_depth: u8,
    pixels: &[u16],
    cfa: Option<Cfa>,
) -> Result<Image, String> {
    if pixels.len() as u64 != u64::from(width) * u64::from(height) {
        return Err(format!(
            "{} samples for a {width}×{height} frame",
            pixels.len()
        ));
    }
    png_linear(bit_depth, cfa, width, height, pixels).into_image()
}

/// The filter array a camera's pixel format (PFNC name, `BayerRG12`) puts
/// its samples behind; None for a monochrome or an unknown one.
pub fn cfa_of_pixel_format(pixel_format: &str) -> Option<Cfa> {
    pixel_format
        .parse::<rigd_core::PixelFormat>()
        .ok()
        .and_then(|f| f.cfa())
}

/// The filter array a frame was taken behind, as its device's pixel
/// format names it; None for a monochrome one.
fn cfa_of(entry: &FrameEntry) -> Option<Cfa> {
    entry
        .device
        .as_ref()
        .and_then(|d| cfa_of_pixel_format(&d.pixel_format))
}

/// A frame file's samples, linear in [0, 1], before any demosaicing.
/// A camera file is decoded by `decode` (the decoder child, or this
/// process for frames rigd wrote and checked).
fn decode_linear(
    bytes: &[u8],
    bit_depth: u8,
    cfa: Option<Cfa>,
    decode: impl FnOnce(&[u8]) -> Result<CameraImage, CameraFileError>,
) -> Result<Linear, String> {
    if !is_png(bytes) {
        let img = decode(bytes).map_err(|e| e.to_string())?;
        return Ok(camera_file_linear(&img));
    }
    let (w, h, pixels) = decode_png(bytes)?;
    Ok(png_linear(bit_depth, cfa, w, h, &pixels))
}

impl CheckedReads {
    /// The frame's bytes, read once, after they hash to the SHA-256 its
    /// journal line recorded (the hash is of the bytes read for decoding:
    /// no second read). The stamp is taken from the handle the bytes are
    /// read through, so it describes the file they came from.
    fn read(&self, index: usize, sha256: &str, path: &Path) -> Result<Vec<u8>, ProcessError> {
        use std::io::Read;
        let io_err = |e: std::io::Error| ProcessError::Frame {
            path: path.to_path_buf(),
            message: e.to_string(),
        };
        let mut file = std::fs::File::open(path).map_err(io_err)?;
        let stamp = FileStamp::of(&file.metadata().map_err(io_err)?);
        let mut bytes = Vec::with_capacity(usize::try_from(stamp.len).unwrap_or(0));
        file.read_to_end(&mut bytes).map_err(io_err)?;
        // Written to while it was read: the stamp says nothing of these bytes.
        let settled = file.metadata().ok().map(|m| FileStamp::of(&m)) == Some(stamp);
        let known = |(sha, seen): &(String, FileStamp)| sha == sha256 && *seen == stamp;
        if settled && lock(&self.0).get(path).is_some_and(known) {
            return Ok(bytes);
        }
        let found = sha256_hex(&bytes);
        if found != sha256 {
            return Err(ProcessError::Damaged {
                path: path.to_path_buf(),
                index,
                expected: sha256.to_string(),
                found,
            });
        }
        if settled {
            lock(&self.0).insert(path.to_path_buf(), (found, stamp));
        }
        Ok(bytes)
    }
}

/// A colour frame as rectification reads it ([`RunFrames::corrected_frame`]).
pub struct CorrectedFrame {
    /// White-balanced and colour-corrected: three interleaved channels of
    /// linear sRGB.
    pub rgb: Image,
    /// The frame's grey as [`RunFrames::image`] reads it, in fractions of
    /// the sensor's full scale: its markers are found, its lamp measured
    /// and whether it is black judged in this, as in an uncalibrated
    /// frame, so that calibrating a run later moves none of its textures
    /// and the black thresholds keep their meaning (`docs/processing.md`,
    /// "Frames as processing reads them").
    pub grey: Image,
    /// The pixels the sensor clipped.
    pub clipped: Option<Clipped>,
}

/// A colour frame as red, green and blue planes, linear in [0, 1].
pub struct ColourPlanes {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Red, green and blue, row-major from the top row.
    pub rgb: [Vec<f32>; 3],
}

impl ColourPlanes {
    /// The colour at continuous pixel position (x, y) (pixel (i, j)'s
    /// centre is (i + ½, j + ½)), bilinear; `None` outside the frame.
    pub fn sample(&self, x: f64, y: f64) -> Option<[f64; 3]> {
        let (u, v) = (x - 0.5, y - 0.5);
        if !(u >= 0.0 && v >= 0.0) {
            return None;
        }
        let (i, j) = (u.floor() as usize, v.floor() as usize);
        if i + 1 >= self.width || j + 1 >= self.height {
            return None;
        }
        let (fu, fv) = ((u - i as f64) as f32, (v - j as f64) as f32);
        let at =
            |p: &[f32], i: usize, j: usize| p.get(j * self.width + i).copied().unwrap_or(f32::NAN);
        Some(self.rgb.each_ref().map(|p| {
            let top = at(p, i, j) * (1.0 - fu) + at(p, i + 1, j) * fu;
            let bottom = at(p, i, j + 1) * (1.0 - fu) + at(p, i + 1, j + 1) * fu;
            f64::from(top * (1.0 - fv) + bottom * fv)
        }))
    }
}

pub use rigd_core::pixel_format::CLIPPED_LEVEL;

/// The pixels of a frame the sensor clipped: where a sample reached
/// [`CLIPPED_LEVEL`] in any channel, and for a Bayer mosaic every pixel
/// whose demosaiced value reads a clipped photosite (within
/// [`demosaic::Method::reach`] of it). What a clipped pixel shows is a
/// lower bound, not a measurement.
#[derive(Debug, Clone)]
pub struct Clipped {
    /// 1 where clipped, 0 elsewhere, one channel at the frame's size.
    pub mask: Image,
    /// Pixels clipped.
    pub pixels: usize,
}

/// A frame's samples, linear in [0, 1], before any demosaicing.
enum Linear {
    /// A monochrome sensor's.
    Grey(Image),
    /// A Bayer sensor's mosaic (one channel) behind its filter array.
    Mosaic(Image, Cfa),
    /// Three interleaved channels (a rendered JPEG or TIFF).
    Rgb(Image),
}

/// The level at or above which a sample of `entry`'s frame, as
/// [`RunFrames`] reads it, is clipped: [`CLIPPED_LEVEL`], scaled by the
/// first exposure over the shortest when its step took several.
pub fn clipped_level(entry: &FrameEntry) -> f32 {
    let shortest = entry
        .exposures_s()
        .into_iter()
        .fold(entry.exposure_s, f64::min);
    rigd_process::hdr::clipped_level(entry.exposure_s, shortest)
}

/// A step's exposures (each with its time, seconds) merged into one frame
/// scaled to `reference_s`, with the level at or above which a merged
/// sample is clipped. Every exposure must be the same kind of frame, of
/// the same size.
fn merge_linear(exposures: Vec<(Linear, f64)>, reference_s: f64) -> Result<(Linear, f32), String> {
    let parts = |l: &Linear| match l {
        Linear::Grey(img) => (img.width, img.height, img.channels, None, false),
        Linear::Mosaic(img, cfa) => (img.width, img.height, img.channels, Some(*cfa), false),
        Linear::Rgb(img) => (img.width, img.height, img.channels, None, true),
    };
    fn image(l: &Linear) -> &[f32] {
        match l {
            Linear::Grey(img) | Linear::Mosaic(img, _) | Linear::Rgb(img) => &img.data,
        }
    }
    let Some((first, _)) = exposures.first() else {
        return Err("no exposure".into());
    };
    let shape = parts(first);
    if let Some(k) = exposures.iter().position(|(l, _)| parts(l) != shape) {
        let (w, h, c, _, _) = parts(&exposures[k].0);
        return Err(format!(
            "exposure {} is a {w}×{h} frame of {c} channel(s) or another filter array, unlike the first ({}×{}, {})",
            k + 1,
            shape.0,
            shape.1,
            shape.2
        ));
    }
    let list: Vec<rigd_process::hdr::Exposure<'_>> = exposures
        .iter()
        .map(|(l, t)| rigd_process::hdr::Exposure {
            samples: image(l),
            time_s: *t,
        })
        .collect();
    let merged = rigd_process::hdr::merge(&list, reference_s).map_err(|e| e.to_string())?;
    let (mut out, _) = exposures.into_iter().next().ok_or("no exposure")?;
    match &mut out {
        Linear::Grey(img) | Linear::Mosaic(img, _) | Linear::Rgb(img) => img.data = merged.samples,
    }
    Ok((out, merged.clipped_level))
}

impl Linear {
    /// The clipped pixels: those with a sample at or above `level` (with a
    /// mosaic's neighbours that read one); `None` when there are none.
    fn clipped(&self, level: f32) -> Option<Clipped> {
        let (img, channels, spread) = match self {
            Linear::Grey(img) => (img, 1, 0),
            Linear::Mosaic(img, _) => (img, 1, demosaic::DEFAULT_METHOD.reach()),
            Linear::Rgb(img) => (img, 3, 0),
        };
        // Most frames clip nothing: no mask is made for them.
        if !img.data.iter().any(|&v| v >= level) {
            return None;
        }
        let (w, h) = (img.width, img.height);
        let mut mask = Image::new(w, h, 1);
        for (i, px) in img.data.chunks_exact(channels).enumerate() {
            if px.iter().any(|&v| v >= level) {
                let (x, y) = (i % w, i / w);
                for yy in y.saturating_sub(spread)..(y + spread + 1).min(h) {
                    for xx in x.saturating_sub(spread)..(x + spread + 1).min(w) {
                        mask.data[yy * w + xx] = 1.0;
                    }
                }
            }
        }
        Some(Clipped {
            pixels: mask.data.iter().filter(|&&v| v > 0.0).count(),
            mask,
        })
    }

    /// One image: grey as it is, three channels (red, green, blue) for a
    /// colour frame, a mosaic demosaiced as [`Self::planes`] does.
    fn into_image(self) -> Result<Image, String> {
        match self {
            Linear::Grey(img) | Linear::Rgb(img) => Ok(img),
            linear @ Linear::Mosaic(..) => {
                let planes = linear
                    .planes()
                    .map_err(|e| e.to_string())?
                    .ok_or("a mosaic without colour planes")?;
                let mut out = Image::new(planes.width, planes.height, 3);
                for (c, plane) in planes.rgb.iter().enumerate() {
                    for (px, v) in out.data.chunks_exact_mut(3).zip(plane) {
                        px[c] = *v;
                    }
                }
                Ok(out)
            }
        }
    }

    /// Grey: a mosaic demosaiced and weighted (R + 2G + B) / 4 as
    /// [`demosaic::luminance`] does, RGB weighted alike.
    fn grey(self) -> Result<Image, demosaic::TooSmall> {
        match self {
            Linear::Grey(img) => Ok(img),
            Linear::Mosaic(img, cfa) => mosaic_grey(&img, cfa),
            Linear::Rgb(img) => Ok(rgb_grey(&img)),
        }
    }

    /// A colour frame's grey as [`Self::grey`] makes it; `None` for a
    /// monochrome frame.
    fn colour_grey(&self) -> Result<Option<Image>, demosaic::TooSmall> {
        match self {
            Linear::Grey(_) => Ok(None),
            Linear::Mosaic(img, cfa) => mosaic_grey(img, *cfa).map(Some),
            Linear::Rgb(img) => Ok(Some(rgb_grey(img))),
        }
    }

    /// Red, green and blue planes with the width and height; `None` for
    /// a monochrome frame.
    fn planes(self) -> Result<Option<ColourPlanes>, demosaic::TooSmall> {
        Ok(match self {
            Linear::Grey(_) => None,
            Linear::Mosaic(img, cfa) => Some(ColourPlanes {
                width: img.width,
                height: img.height,
                rgb: demosaic::demosaic(
                    &img.data,
                    img.width,
                    img.height,
                    cfa,
                    demosaic::DEFAULT_METHOD,
                )?,
            }),
            Linear::Rgb(img) => {
                let plane = |c: usize| img.data.iter().skip(c).step_by(3).copied().collect();
                Some(ColourPlanes {
                    width: img.width,
                    height: img.height,
                    rgb: [plane(0), plane(1), plane(2)],
                })
            }
        })
    }
}

/// A mosaic's grey: demosaiced bilinearly and weighted (R + 2G + B) / 4.
fn mosaic_grey(img: &Image, cfa: Cfa) -> Result<Image, demosaic::TooSmall> {
    let mut out = Image::new(img.width, img.height, 1);
    out.data = demosaic::luminance(&demosaic::bilinear(&img.data, img.width, img.height, cfa)?);
    Ok(out)
}

/// Three interleaved channels' grey, weighted as [`mosaic_grey`] weighs them.
fn rgb_grey(img: &Image) -> Image {
    let mut out = Image::new(img.width, img.height, 1);
    out.data = img
        .data
        .chunks_exact(3)
        .map(|c| 0.25 * c[0] + 0.5 * c[1] + 0.25 * c[2])
        .collect();
    out
}

/// A camera file's samples, linear in [0, 1].
fn camera_file_linear(img: &CameraImage) -> Linear {
    let (w, h) = (img.width as usize, img.height as usize);
    let channels = if img.channels == 3 { 3 } else { 1 };
    let mut out = Image::new(w, h, channels);
    out.data = img.linear();
    match (channels, img.cfa) {
        (3, _) => Linear::Rgb(out),
        (_, Some(cfa)) => Linear::Mosaic(out, cfa),
        _ => Linear::Grey(out),
    }
}

/// A PNG frame's samples as linear values in [0, 1]. A Bayer frame (its
/// device's pixel format names a filter array, `cfa`) is kept as its mosaic.
fn png_linear(bit_depth: u8, cfa: Option<Cfa>, w: u32, h: u32, pixels: &[u16]) -> Linear {
    let full = ((1u32 << bit_depth.clamp(1, 16)) - 1) as f32;
    let mut img = Image::new(w as usize, h as usize, 1);
    for (d, &p) in img.data.iter_mut().zip(pixels) {
        *d = p as f32 / full;
    }
    match cfa {
        Some(cfa) => Linear::Mosaic(img, cfa),
        None => Linear::Grey(img),
    }
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

    /// [`png_linear`] as [`RunFrames`] calls it for `entry`.
    fn png_linear_of(entry: &FrameEntry, w: u32, h: u32, pixels: &[u16]) -> Linear {
        png_linear(entry.bit_depth, cfa_of(entry), w, h, pixels)
    }

    #[test]
    fn clipped_pixels_are_those_at_the_white_level_and_a_mosaic_s_neighbours() {
        let (w, h) = (10, 9);
        let grey = |data: Vec<f32>| Image {
            width: w,
            height: h,
            channels: 1,
            data,
        };
        let mut frame = vec![0.5f32; w * h];
        assert!(Linear::Grey(grey(frame.clone()))
            .clipped(CLIPPED_LEVEL)
            .is_none());
        // Just under the white level is measured; at it, clipped.
        let centre = 4 * w + 5;
        frame[centre] = CLIPPED_LEVEL - 1e-4;
        assert!(Linear::Grey(grey(frame.clone()))
            .clipped(CLIPPED_LEVEL)
            .is_none());
        frame[centre] = 1.0;
        let c = Linear::Grey(grey(frame.clone()))
            .clipped(CLIPPED_LEVEL)
            .expect("clipped");
        assert_eq!(c.pixels, 1);
        assert_eq!(c.mask.data[centre], 1.0);
        // Through a demosaic, every pixel within its reach of the
        // photosite, cut at the frame's edge.
        let reach = demosaic::DEFAULT_METHOD.reach();
        let c = Linear::Mosaic(grey(frame.clone()), Cfa::Rggb)
            .clipped(CLIPPED_LEVEL)
            .expect("clipped");
        assert_eq!(c.pixels, (2 * reach + 1).pow(2));
        frame[centre] = 0.5;
        frame[0] = 1.0;
        let c = Linear::Mosaic(grey(frame), Cfa::Rggb)
            .clipped(CLIPPED_LEVEL)
            .expect("clipped");
        assert_eq!(c.pixels, (reach + 1).pow(2));
        // RGB: any channel.
        let mut rgb = Image::new(2, 1, 3);
        rgb.data = vec![0.2, 0.3, 0.4, 0.2, 0.999, 0.4];
        let c = Linear::Rgb(rgb).clipped(CLIPPED_LEVEL).expect("clipped");
        assert_eq!(c.mask.data, vec![0.0, 1.0]);
    }

    #[test]
    fn a_frame_is_read_only_when_it_hashes_to_its_journal_line() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (a, b) = (dir.path().join("a.png"), dir.path().join("b.png"));
        std::fs::write(&a, b"frame a").expect("write");
        std::fs::write(&b, b"frame b").expect("write");
        let mut ea = entry(None);
        ea.sha256 = sha256_hex(b"frame a");
        let mut eb = entry(None);
        eb.index = 1;
        eb.sha256 = sha256_hex(b"frame b");
        let reads = CheckedReads::default();
        let damaged =
            |r: Result<Vec<u8>, ProcessError>| matches!(r, Err(ProcessError::Damaged { .. }));
        assert_eq!(
            reads.read(ea.index, &ea.sha256, &a).ok().as_deref(),
            Some(&b"frame a"[..])
        );
        assert_eq!(
            reads.read(eb.index, &eb.sha256, &b).ok().as_deref(),
            Some(&b"frame b"[..])
        );
        // Read again from the same files: not hashed again, the same bytes.
        assert_eq!(
            reads.read(ea.index, &ea.sha256, &a).ok().as_deref(),
            Some(&b"frame a"[..])
        );
        // Swapped (renamed over each other): both fail, though checked before.
        let t = dir.path().join("t");
        for (from, to) in [(&a, &t), (&b, &a), (&t, &b)] {
            std::fs::rename(from, to).expect("rename");
        }
        assert!(damaged(reads.read(ea.index, &ea.sha256, &a)));
        assert!(damaged(reads.read(eb.index, &eb.sha256, &b)));
        // Written in place after it was checked (file times tick in
        // jiffies, hence the pause): damaged.
        std::fs::write(&a, b"frame a").expect("write");
        assert!(reads.read(ea.index, &ea.sha256, &a).is_ok());
        std::thread::sleep(std::time::Duration::from_millis(20));
        std::fs::write(&a, b"frame A").expect("write");
        assert!(damaged(reads.read(ea.index, &ea.sha256, &a)));
    }

    #[test]
    fn a_bayer_mosaic_reads_as_grey_and_a_mono_frame_as_it_is() {
        // Red 255, green 51, blue 0 behind an RGGB tile.
        let mosaic = [255, 51, 255, 51, 51, 0, 51, 0];
        let grey = png_linear_of(&entry(Some("BayerRG8")), 4, 2, &mosaic)
            .grey()
            .expect("grey");
        let want = (0.25 * 255.0 + 0.5 * 51.0) / 255.0;
        assert!(
            grey.data.iter().all(|v| (v - want).abs() < 1e-6),
            "{:?}",
            grey.data
        );
        for format in [None, Some("Mono8")] {
            let mono = png_linear_of(&entry(format), 4, 2, &mosaic)
                .grey()
                .expect("mono");
            assert_eq!(mono.data[1], 51.0 / 255.0, "{format:?}");
        }
        let e = png_linear_of(&entry(Some("BayerRG8")), 4, 1, &mosaic[..4])
            .grey()
            .expect_err("1 row");
        assert_eq!(e.height, 1);
    }
}
