//! PNG input/output as `f32` samples in `[0, 1]`, and atomic file writes.
//!
//! Conventions:
//! - [`Image::data`] is row-major and channel-interleaved: the sample of
//!   column `x`, row `y`, channel `c` is `data[(y * width + x) * channels + c]`.
//!   Row 0 is the top row of the file.
//! - Loading accepts 8- and 16-bit (and, expanded to 8-bit, 1/2/4-bit and
//!   palette) PNGs in grey, grey+alpha, RGB and RGBA. Alpha is dropped, so a
//!   loaded image has 1 (grey) or 3 (RGB) channels. 8-bit samples are divided
//!   by 255, 16-bit by 65535; no gamma is applied (rig frames are linear).
//! - Writing clamps to `[0, 1]`, maps non-finite samples to 0, rounds to the
//!   nearest code and writes grey (1 channel) or RGB (3 channels).
//! - Every write goes to a temporary file in the destination folder that is
//!   renamed over the destination only once complete, so a failure never
//!   leaves a half-written file behind.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

/// Largest decoded image accepted, in bytes: guards against a corrupt or
/// hostile header making us allocate the whole machine.
const MAX_DECODED_BYTES: usize = 1 << 30;

/// An image as `f32` samples in `[0, 1]`; see the module doc for the layout.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Width, pixels (columns).
    pub width: usize,
    /// Height, pixels (rows).
    pub height: usize,
    /// 1 (grey) or 3 (RGB).
    pub channels: usize,
    /// `width · height · channels` samples, row-major from the top row,
    /// channels interleaved.
    pub data: Vec<f32>,
}

impl Image {
    /// A black image.
    pub fn new(width: usize, height: usize, channels: usize) -> Self {
        Image {
            width,
            height,
            channels,
            data: vec![0.0; width * height * channels],
        }
    }

    /// Sample at column `x`, row `y`, channel `c`.
    pub fn get(&self, x: usize, y: usize, c: usize) -> f32 {
        self.data[(y * self.width + x) * self.channels + c]
    }

    /// Sets the sample at column `x`, row `y`, channel `c`.
    pub fn set(&mut self, x: usize, y: usize, c: usize, value: f32) {
        self.data[(y * self.width + x) * self.channels + c] = value;
    }
}

/// Bit depth of a written PNG.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PngDepth {
    /// 8 bits per sample (codes 0 … 255).
    Eight,
    /// 16 bits per sample (codes 0 … 65535).
    Sixteen,
}

/// Why a PNG could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The file could not be opened.
    #[error("cannot open {}: {source}", path.display())]
    Open {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The PNG decoder rejected the file: corrupt, truncated or over the
    /// decoder's memory limit.
    #[error("cannot decode PNG {}: {source}", path.display())]
    Decode {
        /// The file.
        path: PathBuf,
        /// The decoder's error.
        source: png::DecodingError,
    },
    /// The PNG decodes but is not one this module loads (an unexpanded
    /// palette, an odd bit depth, short data) or exceeds the 1 GiB
    /// decoded-size limit.
    #[error("unsupported PNG {}: {reason}", path.display())]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// What is unsupported.
        reason: String,
    },
    /// An image could not be encoded: a channel count other than 1 or 3,
    /// a sample count that does not match its size, an empty or oversized
    /// image, or an encoder failure.
    #[error("cannot write PNG {}: {reason}", path.display())]
    Encode {
        /// The destination the image was meant for.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// Writing the encoded file failed.
    #[error("cannot write {}: {source}", path.display())]
    Write {
        /// The destination.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// Loads a PNG as described in the module doc.
pub fn load_png(path: &Path) -> Result<Image, ImageError> {
    let file = File::open(path).map_err(|source| ImageError::Open {
        path: path.to_path_buf(),
        source,
    })?;
    let decode_err = |source| ImageError::Decode {
        path: path.to_path_buf(),
        source,
    };
    let mut decoder = png::Decoder::new_with_limits(
        BufReader::new(file),
        png::Limits {
            bytes: MAX_DECODED_BYTES,
        },
    );
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(decode_err)?;
    let size = reader.output_buffer_size();
    if size > MAX_DECODED_BYTES {
        return Err(ImageError::Unsupported {
            path: path.to_path_buf(),
            reason: format!("decoded size {size} bytes exceeds the {MAX_DECODED_BYTES}-byte limit"),
        });
    }
    let mut buf = vec![0u8; size];
    let info = reader.next_frame(&mut buf).map_err(decode_err)?;
    let (in_channels, keep) = match info.color_type {
        png::ColorType::Grayscale => (1, 1),
        png::ColorType::GrayscaleAlpha => (2, 1),
        png::ColorType::Rgb => (3, 3),
        png::ColorType::Rgba => (4, 3),
        png::ColorType::Indexed => {
            return Err(ImageError::Unsupported {
                path: path.to_path_buf(),
                reason: "palette image was not expanded".into(),
            })
        }
    };
    let bytes_per_sample = match info.bit_depth {
        png::BitDepth::Eight => 1,
        png::BitDepth::Sixteen => 2,
        other => {
            return Err(ImageError::Unsupported {
                path: path.to_path_buf(),
                reason: format!("bit depth {other:?} after expansion"),
            })
        }
    };
    let width = info.width as usize;
    let height = info.height as usize;
    let mut data = Vec::with_capacity(width * height * keep);
    let row_bytes = width * in_channels * bytes_per_sample;
    for row in buf.chunks(info.line_size.max(1)).take(height) {
        let Some(row) = row.get(..row_bytes) else {
            break; // reported below as short data
        };
        for pixel in row.chunks(in_channels * bytes_per_sample) {
            for c in 0..keep {
                let value = if bytes_per_sample == 1 {
                    f32::from(pixel[c]) / 255.0
                } else {
                    f32::from(u16::from_be_bytes([pixel[2 * c], pixel[2 * c + 1]])) / 65535.0
                };
                data.push(value);
            }
        }
    }
    if data.len() != width * height * keep {
        return Err(ImageError::Unsupported {
            path: path.to_path_buf(),
            reason: "decoded data shorter than the header's size".into(),
        });
    }
    Ok(Image {
        width,
        height,
        channels: keep,
        data,
    })
}

/// Encodes an image as PNG bytes (grey for 1 channel, RGB for 3).
/// `path` only names the destination in errors.
pub fn encode_png(image: &Image, depth: PngDepth, path: &Path) -> Result<Vec<u8>, ImageError> {
    let encode_err = |reason: String| ImageError::Encode {
        path: path.to_path_buf(),
        reason,
    };
    let color = match image.channels {
        1 => png::ColorType::Grayscale,
        3 => png::ColorType::Rgb,
        n => return Err(encode_err(format!("{n} channels (expected 1 or 3)"))),
    };
    if image.data.len() != image.width * image.height * image.channels {
        return Err(encode_err(format!(
            "{} samples for {}x{}x{}",
            image.data.len(),
            image.width,
            image.height,
            image.channels
        )));
    }
    let width = u32::try_from(image.width).map_err(|_| encode_err("width too large".into()))?;
    let height = u32::try_from(image.height).map_err(|_| encode_err("height too large".into()))?;
    if width == 0 || height == 0 {
        return Err(encode_err("empty image".into()));
    }
    let quantise = |v: f32, max: f32| -> f32 {
        let v = if v.is_finite() {
            v.clamp(0.0, 1.0)
        } else {
            0.0
        };
        (v * max).round()
    };
    let raw: Vec<u8> = match depth {
        PngDepth::Eight => image
            .data
            .iter()
            .map(|&v| quantise(v, 255.0) as u8)
            .collect(),
        PngDepth::Sixteen => image
            .data
            .iter()
            .flat_map(|&v| (quantise(v, 65535.0) as u16).to_be_bytes())
            .collect(),
    };
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(color);
        encoder.set_depth(match depth {
            PngDepth::Eight => png::BitDepth::Eight,
            PngDepth::Sixteen => png::BitDepth::Sixteen,
        });
        let mut writer = encoder
            .write_header()
            .map_err(|e| encode_err(e.to_string()))?;
        writer
            .write_image_data(&raw)
            .map_err(|e| encode_err(e.to_string()))?;
        writer.finish().map_err(|e| encode_err(e.to_string()))?;
    }
    Ok(out)
}

/// A decoded JPEG: 8-bit codes, sRGB-encoded, as the file holds them.
#[derive(Debug, Clone, PartialEq)]
pub struct Jpeg {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// 1 for a one-component (grey) JPEG, else 3 (RGB).
    pub channels: usize,
    /// `width · height · channels` codes, row-major, channels interleaved.
    pub samples: Vec<u8>,
}

/// Decodes a JPEG (zune-jpeg) as what it is: grey for a one-component
/// file, RGB for a colour one. The one JPEG reader of rigd: camera files,
/// and the texture databases an import reads. `Err` says why the bytes are
/// no JPEG.
pub fn decode_jpeg(bytes: &[u8]) -> Result<Jpeg, String> {
    use zune_core::bytestream::ZCursor;
    use zune_core::colorspace::ColorSpace;
    use zune_core::options::DecoderOptions;
    // The header says whether the JPEG is grey; decode it as what it is.
    let mut probe = zune_jpeg::JpegDecoder::new(ZCursor::new(bytes));
    probe.decode_headers().map_err(|e| e.to_string())?;
    let grey = probe
        .input_colorspace()
        .is_some_and(|c| c.num_components() == 1);
    let (space, channels) = if grey {
        (ColorSpace::Luma, 1)
    } else {
        (ColorSpace::RGB, 3)
    };
    let options = DecoderOptions::default().jpeg_set_out_colorspace(space);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(bytes), options);
    decoder.decode_headers().map_err(|e| e.to_string())?;
    let (width, height) = decoder.dimensions().ok_or("no image dimensions")?;
    let samples = decoder.decode().map_err(|e| e.to_string())?;
    if samples.len() != width * height * channels {
        return Err(format!(
            "decoded {} values for {width}x{height} pixels of {channels} channels",
            samples.len()
        ));
    }
    Ok(Jpeg {
        width,
        height,
        channels,
        samples,
    })
}

/// Writes an image as PNG, atomically.
pub fn write_png(path: &Path, image: &Image, depth: PngDepth) -> Result<(), ImageError> {
    let bytes = encode_png(image, depth, path)?;
    rigd_core::atomic::write(path, &bytes).map_err(|e| ImageError::Write {
        path: path.to_path_buf(),
        source: e.error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(width: usize, height: usize, channels: usize) -> Image {
        let mut image = Image::new(width, height, channels);
        let n = image.data.len();
        for (i, v) in image.data.iter_mut().enumerate() {
            *v = i as f32 / (n - 1) as f32;
        }
        image
    }

    #[test]
    fn round_trips_grey_and_rgb_at_both_depths() {
        let dir = tempfile::tempdir().unwrap();
        for channels in [1, 3] {
            for (depth, step) in [(PngDepth::Eight, 255.0), (PngDepth::Sixteen, 65535.0)] {
                let image = ramp(7, 5, channels);
                let path = dir.path().join(format!("r{channels}{step}.png"));
                write_png(&path, &image, depth).unwrap();
                let back = load_png(&path).unwrap();
                assert_eq!((back.width, back.height, back.channels), (7, 5, channels));
                for (a, b) in image.data.iter().zip(&back.data) {
                    assert!((a - b).abs() <= 0.5 / step + 1e-7, "{a} vs {b}");
                }
            }
        }
    }

    #[test]
    fn alpha_is_dropped() {
        let dir = tempfile::tempdir().unwrap();
        for (color, channels, keep) in [
            (png::ColorType::GrayscaleAlpha, 2usize, 1usize),
            (png::ColorType::Rgba, 4, 3),
        ] {
            let path = dir.path().join(format!("a{channels}.png"));
            let mut bytes = Vec::new();
            {
                let mut enc = png::Encoder::new(&mut bytes, 2, 1);
                enc.set_color(color);
                enc.set_depth(png::BitDepth::Sixteen);
                let mut w = enc.write_header().unwrap();
                let data: Vec<u8> = (0..2 * channels)
                    .flat_map(|i| (i as u16 * 1000).to_be_bytes())
                    .collect();
                w.write_image_data(&data).unwrap();
            }
            std::fs::write(&path, bytes).unwrap();
            let image = load_png(&path).unwrap();
            assert_eq!(image.channels, keep);
            let expected: Vec<f32> = (0..2)
                .flat_map(|px| {
                    (0..keep).map(move |c| ((px * channels + c) * 1000) as f32 / 65535.0)
                })
                .collect();
            assert_eq!(image.data, expected);
        }
    }

    #[test]
    fn errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("missing.png");
        let err = load_png(&missing).unwrap_err().to_string();
        assert!(err.contains("missing.png"), "{err}");
        let garbage = dir.path().join("garbage.png");
        std::fs::write(&garbage, b"not a png").unwrap();
        let err = load_png(&garbage).unwrap_err().to_string();
        assert!(err.contains("garbage.png"), "{err}");
    }
}
