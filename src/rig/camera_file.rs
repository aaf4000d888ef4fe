//! Camera files: the objects a real camera delivers (DNG, vendor raw,
//! TIFF, JPEG), read back as the samples they hold.
//!
//! A frame from such a camera is stored exactly as delivered; this module
//! is how the driver checks it, and how previews and processing read it.
//! DNG and vendor raw files (NEF, CR2, CR3, ARW, RAF, ORF, RW2, …) go
//! through `rawler`, JPEG through `zune-jpeg`, plain TIFF through `tiff`.
//! Which one is chosen by the file's own bytes, never by its name.

use std::io::Cursor;

use rigd_core::Cfa;

use super::tiff_walk;

/// What kind of file a camera delivered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FileFormat {
    /// Adobe DNG.
    Dng,
    /// A vendor raw file rawler reads (its extension, lowercase).
    VendorRaw(&'static str),
    /// A plain (rendered) TIFF.
    Tiff,
    /// A JPEG (EXIF or JFIF).
    Jpeg,
}

impl FileFormat {
    /// The extension the stored frame gets, lowercase, no dot.
    pub fn extension(self) -> &'static str {
        match self {
            FileFormat::Dng => "dng",
            FileFormat::VendorRaw(ext) => ext,
            FileFormat::Tiff => "tif",
            FileFormat::Jpeg => "jpg",
        }
    }

    /// The format's name in messages.
    pub fn name(self) -> &'static str {
        match self {
            FileFormat::Dng => "DNG",
            FileFormat::VendorRaw(_) => "raw",
            FileFormat::Tiff => "TIFF",
            FileFormat::Jpeg => "JPEG",
        }
    }

    /// The MIME type a stored frame of this format is served with.
    pub fn mime(self) -> &'static str {
        match self {
            FileFormat::Dng => "image/x-adobe-dng",
            FileFormat::VendorRaw(_) => "application/octet-stream",
            FileFormat::Tiff => "image/tiff",
            FileFormat::Jpeg => "image/jpeg",
        }
    }
}

/// Every extension a stored camera file can have, besides rigd's own
/// `png` frames.
pub const EXTENSIONS: [&str; 16] = [
    "dng", "nef", "nrw", "cr2", "cr3", "crw", "arw", "raf", "orf", "rw2", "pef", "srw", "iiq",
    "raw", "tif", "jpg",
];

/// How the samples relate to light.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    /// Proportional to light above the black level (raw files).
    Linear,
    /// sRGB-encoded, as cameras render JPEG and TIFF files.
    Srgb,
}

/// A camera file's image, as samples.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraImage {
    /// The file's format.
    pub format: FileFormat,
    /// Width in pixels (a raw file's active area).
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Samples per pixel: 1 (a mosaic or grey) or 3 (RGB, interleaved).
    pub channels: usize,
    /// The colour filter array of a one-sample colour mosaic, relative to
    /// the first pixel; None for grey or RGB samples.
    pub cfa: Option<Cfa>,
    /// `width × height × channels` samples, row by row.
    pub samples: Vec<u16>,
    /// The sample value of no light.
    pub black: f32,
    /// The sample value of saturation.
    pub white: f32,
    /// How samples relate to light.
    pub encoding: Encoding,
}

impl CameraImage {
    /// Significant bits of a sample: enough to hold the white level.
    pub fn bit_depth(&self) -> u8 {
        let white = self.white.clamp(1.0, 65535.0) as u32;
        (32 - white.leading_zeros()) as u8
    }

    /// Every sample as light in [0, 1]: black level off, scaled by the
    /// white level, sRGB decoded. Below black is 0, above white 1.
    pub fn linear(&self) -> Vec<f32> {
        let span = (self.white - self.black).max(1.0);
        self.samples
            .iter()
            .map(|&s| {
                let v = ((f32::from(s) - self.black) / span).clamp(0.0, 1.0);
                match self.encoding {
                    Encoding::Linear => v,
                    Encoding::Srgb => srgb_to_linear(v),
                }
            })
            .collect()
    }
}

/// The sRGB transfer function, inverted (IEC 61966-2-1).
fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// Why a camera file could not be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraFileError {
    /// The bytes are no format rigd reads.
    #[error(
        "not a camera file rigd reads (it starts {0}); rigd reads DNG, vendor raw \
         (NEF, CR2, CR3, ARW, RAF, ORF, RW2), TIFF and JPEG"
    )]
    Unknown(String),
    /// The decoder refused the file (truncated, corrupt).
    #[error("{format} file cannot be decoded: {message}")]
    Corrupt {
        /// What the file claimed to be.
        format: &'static str,
        /// The decoder's words.
        message: String,
    },
    /// The file is whole but holds what rigd does not process.
    #[error("{format} file: {what} is not supported")]
    Unsupported {
        /// What the file is.
        format: &'static str,
        /// What it holds.
        what: String,
    },
}

fn corrupt(format: &'static str, e: impl std::fmt::Display) -> CameraFileError {
    CameraFileError::Corrupt {
        format,
        message: e.to_string(),
    }
}

fn unsupported(format: &'static str, what: impl Into<String>) -> CameraFileError {
    CameraFileError::Unsupported {
        format,
        what: what.into(),
    }
}

/// Whether `bytes` open like a TIFF (the base of DNG and most raw files).
fn is_tiff(bytes: &[u8]) -> bool {
    bytes.starts_with(b"II*\0") || bytes.starts_with(b"MM\0*")
}

/// Whether `bytes` open like a JPEG.
fn is_jpeg(bytes: &[u8]) -> bool {
    bytes.starts_with(&[0xFF, 0xD8, 0xFF])
}

/// Decodes a camera file by its content.
pub fn decode(bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
    // The decoders parse files from cameras and disks; rawler asserts on
    // some malformed ones. A panic in any of them is a corrupt file, not a
    // crashed daemon.
    std::panic::catch_unwind(|| decode_by_content(bytes))
        .unwrap_or_else(|_| Err(corrupt("camera", "the decoder gave up on a malformed file")))
}

fn decode_by_content(bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
    if is_jpeg(bytes) {
        return decode_jpeg(bytes);
    }
    match decode_raw(bytes) {
        // A TIFF that no raw decoder claims (rawler knows DNG by its
        // DNGVersion tag, vendor raw by its maker) is a rendered image.
        Err(CameraFileError::Unknown(_)) if is_tiff(bytes) => decode_tiff(bytes),
        other => other,
    }
}

fn shown_start(bytes: &[u8]) -> String {
    let head: Vec<String> = bytes.iter().take(8).map(|b| format!("{b:02x}")).collect();
    if head.is_empty() {
        "empty".into()
    } else {
        format!("with bytes {}", head.join(" "))
    }
}

/// The format rawler's decoder stands for.
fn raw_format(hint: rawler::decoders::FormatHint) -> FileFormat {
    use rawler::decoders::FormatHint as H;
    let ext = match hint {
        H::DNG => return FileFormat::Dng,
        H::CR2 => "cr2",
        H::CR3 => "cr3",
        H::CRW => "crw",
        H::NEF => "nef",
        H::NRW => "nrw",
        H::ARW => "arw",
        H::RAF => "raf",
        H::RW2 => "rw2",
        H::ORF => "orf",
        H::PEF => "pef",
        H::SRW => "srw",
        H::IIQ => "iiq",
        _ => "raw",
    };
    FileFormat::VendorRaw(ext)
}

/// The most samples a raw file may claim per byte it holds: no raw codec
/// packs a sample into less than half a bit (lossless JPEG reaches about
/// 2:1 on 12- to 14-bit data).
const MAX_SAMPLES_PER_BYTE: u64 = 16;

/// Refuses a file rawler must not read, before it reads a byte: whatever
/// rawler allocates from a file's own claims (an IFD entry's count, an
/// ISO-BMFF table, an image size) happens before it checks the claim
/// against the file, and a failed allocation aborts the process, which no
/// `catch_unwind` stops (one flipped bit asked for 26 GB in the property
/// test). [`tiff_walk::walk`] reads the structures rawler will read, the
/// way it reads them, and refuses any claim the file cannot back; this
/// then refuses an image bigger than the file's bytes could hold.
fn check_before_rawler(bytes: &[u8]) -> Result<(), CameraFileError> {
    let images = tiff_walk::walk(bytes).map_err(|why| corrupt("raw", why))?;
    let limit = (bytes.len() as u64).saturating_mul(MAX_SAMPLES_PER_BYTE);
    for image in images {
        let (w, h, samples) = (image.width, image.height, image.samples);
        // A zero side does not make the rest free: rawler sizes its white
        // levels by the samples a pixel alone.
        let claimed = w.max(1).saturating_mul(h.max(1)).saturating_mul(samples);
        if claimed > limit {
            let of = if samples > 1 {
                format!(" of {samples} samples a pixel")
            } else {
                String::new()
            };
            return Err(corrupt(
                "raw",
                format!(
                    "it claims a {w}x{h} image{of}, more than its {} bytes can hold",
                    bytes.len()
                ),
            ));
        }
    }
    Ok(())
}

fn decode_raw(bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
    use rawler::decoders::RawDecodeParams;
    use rawler::rawimage::{RawImageData, RawPhotometricInterpretation};
    check_before_rawler(bytes)?;
    let source = rawler::rawsource::RawSource::new_from_slice(bytes);
    // No raw decoder knows these bytes: they are no raw file.
    let decoder =
        rawler::get_decoder(&source).map_err(|_| CameraFileError::Unknown(shown_start(bytes)))?;
    let format = raw_format(decoder.format_hint());
    let name = format.name();
    let raw = decoder
        .raw_image(&source, &RawDecodeParams::default(), false)
        .map_err(|e| corrupt(name, e))?;
    let RawImageData::Integer(data) = &raw.data else {
        return Err(unsupported(name, "floating-point samples"));
    };
    if raw.cpp != 1 && raw.cpp != 3 {
        return Err(unsupported(name, format!("{} samples per pixel", raw.cpp)));
    }
    if raw.width == 0 || raw.height == 0 || data.len() != raw.width * raw.height * raw.cpp {
        return Err(corrupt(
            name,
            format!(
                "{} samples for {}x{}x{}",
                data.len(),
                raw.width,
                raw.height,
                raw.cpp
            ),
        ));
    }
    // Only the active area holds image; the CFA is relative to its corner.
    let (x0, y0, w, h) = match raw.active_area {
        Some(a) if a.p.x + a.d.w <= raw.width && a.p.y + a.d.h <= raw.height && a.d.w > 0 => {
            (a.p.x, a.p.y, a.d.w, a.d.h)
        }
        _ => (0, 0, raw.width, raw.height),
    };
    let cfa = match (&raw.photometric, raw.cpp) {
        (RawPhotometricInterpretation::Cfa(config), 1) => {
            let shifted = config.cfa.shift(x0, y0);
            Some(match shifted.name.as_str() {
                "RGGB" => Cfa::Rggb,
                "GRBG" => Cfa::Grbg,
                "GBRG" => Cfa::Gbrg,
                "BGGR" => Cfa::Bggr,
                other => {
                    return Err(unsupported(
                        name,
                        format!("the colour filter array {other} (rigd reads 2x2 Bayer tiles)"),
                    ))
                }
            })
        }
        _ => None,
    };
    let cpp = raw.cpp;
    let mut samples = Vec::with_capacity(w * h * cpp);
    for row in data.chunks_exact(raw.width * cpp).skip(y0).take(h) {
        samples.extend_from_slice(&row[x0 * cpp..(x0 + w) * cpp]);
    }
    let black = raw.blacklevel.as_bayer_array();
    let white = raw.whitelevel.as_bayer_array();
    let mean = |v: [f32; 4]| v.iter().sum::<f32>() / 4.0;
    let to_u32 = |n: usize| u32::try_from(n).map_err(|_| corrupt(name, "the image is too large"));
    Ok(CameraImage {
        format,
        width: to_u32(w)?,
        height: to_u32(h)?,
        channels: cpp,
        cfa,
        samples,
        black: mean(black),
        white: mean(white),
        encoding: Encoding::Linear,
    })
}

fn decode_jpeg(bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
    use zune_jpeg::zune_core::bytestream::ZCursor;
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    let options = DecoderOptions::default().jpeg_set_out_colorspace(ColorSpace::RGB);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(bytes), options);
    let pixels = decoder.decode().map_err(|e| corrupt("JPEG", e))?;
    let info = decoder
        .info()
        .ok_or_else(|| corrupt("JPEG", "no image header"))?;
    let (w, h) = (u32::from(info.width), u32::from(info.height));
    if pixels.len() != w as usize * h as usize * 3 {
        return Err(corrupt(
            "JPEG",
            format!("{} samples for {w}x{h} RGB", pixels.len()),
        ));
    }
    Ok(CameraImage {
        format: FileFormat::Jpeg,
        width: w,
        height: h,
        channels: 3,
        cfa: None,
        samples: pixels.into_iter().map(u16::from).collect(),
        black: 0.0,
        white: 255.0,
        encoding: Encoding::Srgb,
    })
}

fn decode_tiff(bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
    use tiff::decoder::DecodingResult;
    use tiff::ColorType;
    let mut dec =
        tiff::decoder::Decoder::new(Cursor::new(bytes)).map_err(|e| corrupt("TIFF", e))?;
    let (w, h) = dec.dimensions().map_err(|e| corrupt("TIFF", e))?;
    let (channels, bits) = match dec.colortype().map_err(|e| corrupt("TIFF", e))? {
        ColorType::Gray(b) => (1, b),
        ColorType::RGB(b) => (3, b),
        other => return Err(unsupported("TIFF", format!("colour type {other:?}"))),
    };
    let samples: Vec<u16> = match dec.read_image().map_err(|e| corrupt("TIFF", e))? {
        DecodingResult::U8(v) if bits == 8 => v.into_iter().map(u16::from).collect(),
        DecodingResult::U16(v) if bits == 16 => v,
        _ => return Err(unsupported("TIFF", format!("{bits}-bit samples"))),
    };
    if samples.len() != w as usize * h as usize * channels {
        return Err(corrupt("TIFF", "sample count does not match the size"));
    }
    Ok(CameraImage {
        format: FileFormat::Tiff,
        width: w,
        height: h,
        channels,
        cfa: None,
        samples,
        black: 0.0,
        white: if bits == 8 { 255.0 } else { 65535.0 },
        encoding: Encoding::Srgb,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_bytes_are_named_not_guessed() {
        for bytes in [
            &b""[..],
            b"hello world",
            &[0x89, b'P', b'N', b'G', 0, 0, 0, 0][..],
        ] {
            let e = decode(bytes).expect_err("not a camera file");
            assert!(matches!(e, CameraFileError::Unknown(_)), "{e}");
        }
    }

    #[test]
    fn a_truncated_jpeg_or_tiff_is_corrupt_not_a_panic() {
        assert!(decode(&[0xFF, 0xD8, 0xFF, 0xE0, 0, 16]).is_err());
        assert!(decode(b"II*\0\x08\0\0\0\xff\xff").is_err());
        assert!(decode(b"MM\0*\0\0\0\x08").is_err());
    }

    #[test]
    fn a_plain_tiff_reads_as_srgb() {
        let mut out = Cursor::new(Vec::new());
        let mut enc = tiff::encoder::TiffEncoder::new(&mut out).expect("encoder");
        enc.write_image::<tiff::encoder::colortype::RGB8>(2, 1, &[255, 0, 0, 0, 128, 255])
            .expect("write");
        let img = decode(out.get_ref()).expect("a TIFF");
        assert_eq!(img.format, FileFormat::Tiff);
        assert_eq!((img.width, img.height, img.channels), (2, 1, 3));
        let lin = img.linear();
        assert_eq!(lin[0], 1.0);
        assert!((lin[4] - 0.2158).abs() < 1e-3, "{}", lin[4]);
    }

    /// The simulated camera's DNG (IFD0 only, little-endian).
    #[cfg(feature = "sim")]
    fn sim_dng() -> Vec<u8> {
        use rigd_sim::firmware::dng::{encode, to_raw, DngCamera};
        let camera = DngCamera {
            make: "rigd",
            model: "unit",
            cfa: Some(Cfa::Rggb),
            bit_depth: 12,
        };
        let values: Vec<u16> = (0..48u16).map(|i| i * 87).collect();
        encode(&camera, 8, 6, &to_raw(&values, 12), 0.1).expect("dng")
    }

    /// Sets the count of IFD0's entry `tag` in a little-endian TIFF.
    #[cfg(feature = "sim")]
    fn set_count(bytes: &mut [u8], tag: u16, count: u32) {
        let le16 = |b: &[u8], at: usize| u16::from_le_bytes([b[at], b[at + 1]]);
        let ifd = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]) as usize;
        let entry = (0..usize::from(le16(bytes, ifd)))
            .map(|i| ifd + 2 + 12 * i)
            .find(|&at| le16(bytes, at) == tag)
            .expect("the tag");
        bytes[entry + 4..entry + 8].copy_from_slice(&count.to_le_bytes());
    }

    #[cfg(feature = "sim")]
    #[test]
    fn a_dng_whose_entry_claims_four_billion_values_is_refused_before_rawler() {
        let good = sim_dng();
        let img = decode(&good).expect("the simulated DNG");
        assert_eq!((img.format, img.width, img.height), (FileFormat::Dng, 8, 6));
        // StripOffsets, ColorMatrix1 (rationals: 34 GB), UniqueCameraModel.
        for tag in [0x0111, 0xC621, 0xC614] {
            let mut bad = good.clone();
            set_count(&mut bad, tag, 0xFFFF_FFFF);
            match decode(&bad) {
                Err(CameraFileError::Corrupt { format, message }) => {
                    assert_eq!(format, "raw");
                    assert!(
                        message.contains("claims 4294967295 values")
                            && message.contains(&format!("the file has only {} bytes", bad.len())),
                        "{message}"
                    );
                }
                other => panic!("{tag:#x}: {other:?}"),
            }
        }
    }

    #[cfg(feature = "sim")]
    #[test]
    fn a_dng_claiming_a_bigger_image_than_its_bytes_is_refused() {
        let mut bad = sim_dng();
        // ImageWidth is a LONG with its value in the entry.
        let ifd = u32::from_le_bytes([bad[4], bad[5], bad[6], bad[7]]) as usize;
        let entry = (0..40)
            .map(|i| ifd + 2 + 12 * i)
            .find(|&at| bad[at..at + 2] == [0x00, 0x01])
            .expect("ImageWidth");
        bad[entry + 8..entry + 12].copy_from_slice(&1_000_000u32.to_le_bytes());
        let e = decode(&bad).expect_err("a huge image");
        assert!(e.to_string().contains("claims a 1000000x6 image"), "{e}");
        // No width does not make 65535 samples a pixel free.
        bad[entry + 8..entry + 12].copy_from_slice(&0u32.to_le_bytes());
        let spp = (0..40)
            .map(|i| ifd + 2 + 12 * i)
            .find(|&at| bad[at..at + 2] == [0x15, 0x01])
            .expect("SamplesPerPixel");
        bad[spp + 8..spp + 10].copy_from_slice(&u16::MAX.to_le_bytes());
        let e = decode(&bad).expect_err("a huge pixel");
        assert!(
            e.to_string()
                .contains("claims a 0x6 image of 65535 samples a pixel"),
            "{e}"
        );
    }

    #[test]
    fn bit_depth_follows_the_white_level() {
        let mut img = CameraImage {
            format: FileFormat::Dng,
            width: 1,
            height: 1,
            channels: 1,
            cfa: None,
            samples: vec![0],
            black: 0.0,
            white: 4095.0,
            encoding: Encoding::Linear,
        };
        assert_eq!(img.bit_depth(), 12);
        img.white = 15_000.0;
        assert_eq!(img.bit_depth(), 14);
        img.white = 65535.0;
        assert_eq!(img.bit_depth(), 16);
    }
}
