//! The simulated PTP camera's file format: a DNG, as a camera that shoots
//! DNG delivers it (Adobe's DNG specification 1.4 over TIFF 6.0).
//!
//! One uncompressed strip (8-bit samples for sensors of 8 bits or fewer,
//! else 16-bit) holds the sensor's samples as read out: a
//! colour camera's Bayer mosaic (PhotometricInterpretation CFA, with its
//! CFAPattern) or a monochrome camera's grey samples (LinearRaw, one
//! sample per pixel). The tags a raw decoder needs to turn the samples into
//! colour are there: BlackLevel, WhiteLevel, ColorMatrix1 under D65 and
//! AsShotNeutral.

use std::io::Cursor;

use rigd_core::Cfa;
use tiff::encoder::{Rational, SRational, TiffEncoder};
use tiff::tags::Tag;

/// What the DNG says of the camera and the exposure.
#[derive(Debug, Clone, PartialEq)]
pub struct DngCamera<'a> {
    /// Make (the PTP Manufacturer string).
    pub make: &'a str,
    /// Model (the PTP Model string).
    pub model: &'a str,
    /// The colour filter array, or None for a monochrome sensor.
    pub cfa: Option<Cfa>,
    /// Significant bits of a sample: the white level is `2^bits − 1`.
    pub bit_depth: u8,
}

/// The black level of a sensor of `bit_depth` bits: 1/16 of full scale, as
/// real sensors keep an offset so that read noise below black survives.
pub fn black_level(bit_depth: u8) -> u16 {
    white_level(bit_depth) / 16
}

/// The white level (saturation) of a sensor of `bit_depth` bits.
pub fn white_level(bit_depth: u8) -> u16 {
    if bit_depth >= 16 {
        u16::MAX
    } else {
        (1u16 << bit_depth.max(1)) - 1
    }
}

/// Maps rendered values (0 to the white level) onto the sensor's range
/// above its black level, as the camera's ADC would read them out.
pub fn to_raw(values: &[u16], bit_depth: u8) -> Vec<u16> {
    let (black, white) = (
        f64::from(black_level(bit_depth)),
        f64::from(white_level(bit_depth)),
    );
    let scale = (white - black) / white;
    values
        .iter()
        .map(|&v| (black + f64::from(v).min(white) * scale).round() as u16)
        .collect()
}

/// The DNG could not be written (the frame does not fit a TIFF strip).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("cannot write the DNG: {0}")]
pub struct DngError(String);

/// XYZ (D65) to linear sRGB: the simulated sensor's channels are the sRGB
/// primaries, so this is its ColorMatrix1 (XYZ to camera).
const XYZ_TO_CAMERA: [f64; 9] = [
    3.2406, -1.5372, -0.4986, -0.9689, 1.8758, 0.0415, 0.0557, -0.2040, 1.0570,
];

/// TIFF/EP and DNG tag numbers used here beside the baseline TIFF ones.
mod tags {
    pub const CFA_REPEAT_PATTERN_DIM: u16 = 33421;
    pub const CFA_PATTERN: u16 = 33422;
    pub const EXPOSURE_TIME: u16 = 33434;
    pub const DNG_VERSION: u16 = 50706;
    pub const DNG_BACKWARD_VERSION: u16 = 50707;
    pub const UNIQUE_CAMERA_MODEL: u16 = 50708;
    pub const CFA_PLANE_COLOR: u16 = 50710;
    pub const CFA_LAYOUT: u16 = 50711;
    pub const BLACK_LEVEL_REPEAT_DIM: u16 = 50713;
    pub const BLACK_LEVEL: u16 = 50714;
    pub const WHITE_LEVEL: u16 = 50717;
    pub const COLOR_MATRIX_1: u16 = 50721;
    pub const AS_SHOT_NEUTRAL: u16 = 50728;
    pub const CALIBRATION_ILLUMINANT_1: u16 = 50778;
    /// PhotometricInterpretation values.
    pub const PHOTOMETRIC_CFA: u16 = 32803;
    pub const PHOTOMETRIC_LINEAR_RAW: u16 = 34892;
    /// CalibrationIlluminant: D65.
    pub const ILLUMINANT_D65: u16 = 21;
}

/// The CFAPattern of a 2×2 tile: 0 red, 1 green, 2 blue, row by row.
fn cfa_pattern(cfa: Cfa) -> [u8; 4] {
    match cfa {
        Cfa::Rggb => [0, 1, 1, 2],
        Cfa::Grbg => [1, 0, 2, 1],
        Cfa::Gbrg => [1, 2, 0, 1],
        Cfa::Bggr => [2, 1, 1, 0],
    }
}

/// Encodes `raw` (`width × height` samples, row by row, already offset by
/// the black level: see [`to_raw`]) as a DNG file.
pub fn encode(
    camera: &DngCamera,
    width: u32,
    height: u32,
    raw: &[u16],
    exposure_s: f64,
) -> Result<Vec<u8>, DngError> {
    let err = |e: tiff::TiffError| DngError(e.to_string());
    if raw.len() != width as usize * height as usize || width == 0 || height == 0 {
        return Err(DngError(format!(
            "{} samples for a {width}x{height} frame",
            raw.len()
        )));
    }
    let mut out = Cursor::new(Vec::new());
    let mut enc = TiffEncoder::new(&mut out).map_err(err)?;
    let mut dir = enc.image_directory().map_err(err)?;
    // A sensor of 8 bits or fewer gets one byte a sample, as cameras write
    // it; deeper ones two.
    let bytes_per_sample = if camera.bit_depth <= 8 { 1 } else { 2 };
    let strip_bytes = u32::try_from(raw.len() * bytes_per_sample)
        .map_err(|_| DngError(format!("a {width}x{height} frame is too big for one strip")))?;
    let strip = if bytes_per_sample == 1 {
        let bytes: Vec<u8> = raw.iter().map(|&v| v.min(255) as u8).collect();
        dir.write_data(&bytes[..]).map_err(err)?
    } else {
        dir.write_data(raw).map_err(err)?
    };
    let strip = u32::try_from(strip).map_err(|e| DngError(e.to_string()))?;
    let t = |n: u16| Tag::Unknown(n);
    dir.write_tag(Tag::NewSubfileType, 0u32).map_err(err)?;
    dir.write_tag(Tag::ImageWidth, width).map_err(err)?;
    dir.write_tag(Tag::ImageLength, height).map_err(err)?;
    dir.write_tag(Tag::BitsPerSample, 8 * bytes_per_sample as u16)
        .map_err(err)?;
    dir.write_tag(Tag::Compression, 1u16).map_err(err)?;
    dir.write_tag(Tag::Make, camera.make).map_err(err)?;
    dir.write_tag(Tag::Model, camera.model).map_err(err)?;
    dir.write_tag(Tag::StripOffsets, strip).map_err(err)?;
    dir.write_tag(Tag::Orientation, 1u16).map_err(err)?;
    dir.write_tag(Tag::SamplesPerPixel, 1u16).map_err(err)?;
    dir.write_tag(Tag::RowsPerStrip, height).map_err(err)?;
    dir.write_tag(Tag::StripByteCounts, strip_bytes)
        .map_err(err)?;
    dir.write_tag(Tag::PlanarConfiguration, 1u16).map_err(err)?;
    match camera.cfa {
        Some(cfa) => {
            dir.write_tag(Tag::PhotometricInterpretation, tags::PHOTOMETRIC_CFA)
                .map_err(err)?;
            dir.write_tag(t(tags::CFA_REPEAT_PATTERN_DIM), [2u16, 2])
                .map_err(err)?;
            dir.write_tag(t(tags::CFA_PATTERN), &cfa_pattern(cfa)[..])
                .map_err(err)?;
            dir.write_tag(t(tags::CFA_PLANE_COLOR), &[0u8, 1, 2][..])
                .map_err(err)?;
            dir.write_tag(t(tags::CFA_LAYOUT), 1u16).map_err(err)?;
        }
        None => {
            dir.write_tag(Tag::PhotometricInterpretation, tags::PHOTOMETRIC_LINEAR_RAW)
                .map_err(err)?;
        }
    }
    // Exposure in microseconds: exact for every 0.1 ms PTP step.
    let exposure_us = (exposure_s.max(0.0) * 1e6).round().min(f64::from(u32::MAX)) as u32;
    dir.write_tag(
        t(tags::EXPOSURE_TIME),
        Rational {
            n: exposure_us,
            d: 1_000_000,
        },
    )
    .map_err(err)?;
    dir.write_tag(t(tags::DNG_VERSION), &[1u8, 4, 0, 0][..])
        .map_err(err)?;
    dir.write_tag(t(tags::DNG_BACKWARD_VERSION), &[1u8, 1, 0, 0][..])
        .map_err(err)?;
    let unique = format!("{} {}", camera.make, camera.model);
    dir.write_tag(t(tags::UNIQUE_CAMERA_MODEL), unique.as_str())
        .map_err(err)?;
    dir.write_tag(t(tags::BLACK_LEVEL_REPEAT_DIM), [1u16, 1])
        .map_err(err)?;
    dir.write_tag(t(tags::BLACK_LEVEL), black_level(camera.bit_depth))
        .map_err(err)?;
    dir.write_tag(t(tags::WHITE_LEVEL), white_level(camera.bit_depth))
        .map_err(err)?;
    if camera.cfa.is_some() {
        let matrix = XYZ_TO_CAMERA.map(|v| SRational {
            n: (v * 10_000.0).round() as i32,
            d: 10_000,
        });
        dir.write_tag(t(tags::COLOR_MATRIX_1), &matrix[..])
            .map_err(err)?;
        dir.write_tag(t(tags::CALIBRATION_ILLUMINANT_1), tags::ILLUMINANT_D65)
            .map_err(err)?;
        let neutral: [Rational; 3] = std::array::from_fn(|_| Rational { n: 1, d: 1 });
        dir.write_tag(t(tags::AS_SHOT_NEUTRAL), &neutral[..])
            .map_err(err)?;
    }
    dir.finish().map_err(err)?;
    Ok(out.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raw_values_span_black_to_white() {
        assert_eq!((black_level(12), white_level(12)), (255, 4095));
        assert_eq!(black_level(16), 4095);
        let raw = to_raw(&[0, 4095, 5000, 2048], 12);
        assert_eq!(raw, vec![255, 4095, 4095, 2175]);
    }

    /// The first IFD's entries: (tag, type, count, value or offset).
    fn ifd0(file: &[u8]) -> Vec<(u16, u16, u32, u32)> {
        let u16_at = |i: usize| u16::from_le_bytes([file[i], file[i + 1]]);
        let u32_at =
            |i: usize| u32::from_le_bytes([file[i], file[i + 1], file[i + 2], file[i + 3]]);
        let at = u32_at(4) as usize;
        (0..u16_at(at) as usize)
            .map(|k| at + 2 + 12 * k)
            .map(|e| (u16_at(e), u16_at(e + 2), u32_at(e + 4), u32_at(e + 8)))
            .collect()
    }

    #[test]
    fn a_dng_is_a_little_endian_tiff_with_the_dng_tags() {
        let cam = DngCamera {
            make: "rigd",
            model: "SimCam",
            cfa: Some(Cfa::Bggr),
            bit_depth: 12,
        };
        let raw = to_raw(&[0, 1000, 2000, 4095, 10, 20, 30, 40], 12);
        let dng = encode(&cam, 4, 2, &raw, 0.25).expect("dng");
        assert_eq!(&dng[..4], b"II*\0");
        let entries = ifd0(&dng);
        let tag = |t: u16| entries.iter().find(|e| e.0 == t).copied();
        // DNGVersion 1.4.0.0 and the CFA tile, both four bytes held inline.
        assert_eq!(
            tag(tags::DNG_VERSION),
            Some((tags::DNG_VERSION, 1, 4, 0x0000_0401))
        );
        assert_eq!(
            tag(tags::CFA_PATTERN),
            Some((tags::CFA_PATTERN, 1, 4, 0x0001_0102))
        );
        assert_eq!(
            tag(262).map(|e| e.3),
            Some(u32::from(tags::PHOTOMETRIC_CFA))
        );
        assert_eq!(tag(tags::BLACK_LEVEL).map(|e| e.3), Some(255));
        assert_eq!(tag(tags::WHITE_LEVEL).map(|e| e.3), Some(4095));
        // The samples, as given, in the one strip.
        let strip = tag(273).map(|e| e.3 as usize).expect("StripOffsets");
        let stored: Vec<u16> = dng[strip..strip + 16]
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect();
        assert_eq!(stored, raw);
        let mono = DngCamera { cfa: None, ..cam };
        let dng = encode(&mono, 4, 2, &raw, 0.25).expect("dng");
        let entries = ifd0(&dng);
        let photometric = entries.iter().find(|e| e.0 == 262).map(|e| e.3);
        assert_eq!(photometric, Some(u32::from(tags::PHOTOMETRIC_LINEAR_RAW)));
        assert!(entries.iter().all(|e| e.0 != tags::CFA_PATTERN));
        assert!(encode(&cam, 4, 2, &raw[..7], 0.25).is_err());
        // An 8-bit sensor: one byte a sample.
        let eight = DngCamera {
            bit_depth: 8,
            ..cam
        };
        let raw8 = to_raw(&[0, 255, 128, 64, 1, 2, 3, 4], 8);
        let dng = encode(&eight, 4, 2, &raw8, 0.25).expect("dng");
        let entries = ifd0(&dng);
        let tag = |t: u16| entries.iter().find(|e| e.0 == t).map(|e| e.3);
        assert_eq!((tag(258), tag(279)), (Some(8), Some(8)));
        let strip = tag(273).expect("StripOffsets") as usize;
        let stored: Vec<u16> = dng[strip..strip + 8]
            .iter()
            .map(|&b| u16::from(b))
            .collect();
        assert_eq!(stored, raw8);
    }
}
