//! The decoders themselves, run in whatever process calls them: rawler for
//! DNG and vendor raw, zune-jpeg for JPEG, tiff for plain TIFF. A file from
//! outside reaches them only inside the decoder child ([`super::child`]),
//! where an allocation a file tricks them into cannot take rigd down.

use std::io::Cursor;

use rigd_core::Cfa;

use super::{CameraFileError, CameraImage, Encoding, Facts, FileFormat};

fn corrupt(format: &str, e: impl std::fmt::Display) -> CameraFileError {
    CameraFileError::Corrupt {
        format: format.to_string(),
        message: e.to_string(),
    }
}

fn unsupported(format: &str, what: impl Into<String>) -> CameraFileError {
    CameraFileError::Unsupported {
        format: format.to_string(),
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

/// Decodes a camera file by its content, in this process. A decoder's
/// panic is a corrupt file; an allocation failure still aborts.
pub(super) fn decode(bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
    // rawler asserts on some malformed files (and `todo!()`s on others): a
    // panic in any decoder is a corrupt file, not a crashed process.
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

/// The raw format whose own signature `bytes` start with, for the raw
/// formats that are not TIFF underneath (a TIFF-based one that rawler does
/// not claim is read as a rendered TIFF).
fn signature_format(bytes: &[u8]) -> Option<&'static str> {
    // ISO base media (ISO/IEC 14496-12): a `ftyp` box whose brand is Canon's `crx `.
    if bytes.get(4..12) == Some(b"ftypcrx ") {
        return Some("CR3");
    }
    if bytes.starts_with(b"FUJIFILMCCD-RAW") {
        return Some("RAF");
    }
    if bytes.get(6..14) == Some(b"HEAPCCDR") {
        return Some("CRW");
    }
    None
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

/// What a TIFF compression code is, for the message refusing it.
fn compression_name(code: u32) -> &'static str {
    match code {
        1 => "uncompressed",
        7 => "lossless JPEG",
        8 => "Deflate",
        9 => "VC-5",
        34892 => "lossy JPEG",
        34713 => "Nikon NEF",
        52546 => "JPEG XL",
        65000 => "Kodak DCR",
        _ => "unknown",
    }
}

/// The compression codes of a DNG's full-size images (NewSubFileType 0)
/// that rawler has no decoder for, read with rawler's own TIFF reader.
fn dng_compressions_refused(bytes: &[u8]) -> Vec<u32> {
    use rawler::formats::tiff::reader::TiffReader;
    use rawler::formats::tiff::GenericTiffReader;
    use rawler::tags::TiffCommonTag;
    let Ok(tiff) = GenericTiffReader::new_with_buffer(bytes, 0, 0, None) else {
        return Vec::new();
    };
    let mut codes: Vec<u32> = tiff
        .root_ifd()
        .find_ifds_with_tag(TiffCommonTag::Compression)
        .into_iter()
        .filter(|ifd| {
            ifd.get_entry(TiffCommonTag::NewSubFileType)
                .is_none_or(|e| e.force_u32(0) & 1 == 0)
        })
        .filter_map(|ifd| ifd.get_entry(TiffCommonTag::Compression))
        .map(|e| e.force_u32(0))
        .filter(|c| ![1, 7, 8, 34892, 52546].contains(c))
        .collect();
    codes.dedup();
    codes
}

/// A 2×2 Bayer tile by its rawler name (colours row by row).
fn bayer(name: &str) -> Option<Cfa> {
    match name {
        "RGGB" => Some(Cfa::Rggb),
        "GRBG" => Some(Cfa::Grbg),
        "GBRG" => Some(Cfa::Gbrg),
        "BGGR" => Some(Cfa::Bggr),
        _ => None,
    }
}

/// A rational EXIF value as a number, when it is one.
fn ratio(r: Option<rawler::formats::tiff::Rational>) -> Option<f64> {
    r.filter(|r| r.d != 0)
        .map(|r| f64::from(r.n) / f64::from(r.d))
}

fn decode_raw(bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
    use rawler::decoders::RawDecodeParams;
    use rawler::rawimage::{RawImageData, RawPhotometricInterpretation};
    let source = rawler::rawsource::RawSource::new_from_slice(bytes);
    // No raw decoder knows these bytes: a raw file whose container is cut
    // short or broken says what it is by its signature; else it is no raw file.
    let decoder = rawler::get_decoder(&source).map_err(|_| match signature_format(bytes) {
        Some(format) => corrupt(
            format,
            "its container cannot be read (cut short, or not as the format defines it)",
        ),
        None => CameraFileError::Unknown(shown_start(bytes)),
    })?;
    let format = raw_format(decoder.format_hint());
    let name = format.name();
    let params = RawDecodeParams::default();
    let mut raw = match decoder.raw_image(&source, &params, false) {
        Ok(raw) => raw,
        Err(e) => {
            if format == FileFormat::Dng {
                if let Some(&code) = dng_compressions_refused(bytes).first() {
                    return Err(unsupported(
                        name,
                        format!(
                            "compression {code} ({}): no decoder",
                            compression_name(code)
                        ),
                    ));
                }
            }
            return Err(match e {
                rawler::RawlerError::Unsupported {
                    what, make, model, ..
                } => unsupported(name, format!("{what} ({make} {model}): no decoder")),
                other => corrupt(name, other),
            });
        }
    };
    let data = match std::mem::replace(&mut raw.data, RawImageData::Integer(Vec::new())) {
        RawImageData::Integer(data) => data,
        RawImageData::Float(_) => return Err(unsupported(name, "floating-point samples")),
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
    let mut pattern = None;
    let cfa = match (&raw.photometric, raw.cpp) {
        (RawPhotometricInterpretation::Cfa(config), 1) => {
            let shifted = config.cfa.shift(x0, y0);
            pattern = Some(shifted.name.clone());
            Some(bayer(&shifted.name).ok_or_else(|| {
                unsupported(
                    name,
                    format!(
                        "the {}x{} colour filter array {} (rigd reads 2x2 Bayer tiles)",
                        shifted.width, shifted.height, shifted.name
                    ),
                )
            })?)
        }
        _ => None,
    };
    let cpp = raw.cpp;
    let samples = if (x0, y0, w, h) == (0, 0, raw.width, raw.height) {
        data
    } else {
        let mut samples = Vec::with_capacity(w * h * cpp);
        for row in data.chunks_exact(raw.width * cpp).skip(y0).take(h) {
            samples.extend_from_slice(&row[x0 * cpp..(x0 + w) * cpp]);
        }
        samples
    };
    let black = raw.blacklevel.as_bayer_array();
    let white = raw.whitelevel.as_bayer_array();
    // Levels that leave no range between black and white make every sample
    // meaningless: a file whose metadata lies (or was stripped) is refused,
    // not decoded into numbers nobody can use.
    if let Some((b, w)) = black
        .iter()
        .zip(&white)
        .find(|(b, w)| !(b.is_finite() && w.is_finite() && **b >= 0.0 && b < w))
    {
        return Err(corrupt(
            name,
            format!("its black level {b} is not below its white level {w}"),
        ));
    }
    let mean = |v: [f32; 4]| v.iter().sum::<f32>() / 4.0;
    let to_u32 = |n: usize| u32::try_from(n).map_err(|_| corrupt(name, "the image is too large"));
    // The metadata is a description: a file whose EXIF cannot be read still
    // has its samples.
    let exif = decoder.raw_metadata(&source, &params).ok().map(|m| m.exif);
    let wb = raw.wb_coeffs;
    let facts = Facts {
        make: raw.clean_make.clone(),
        model: raw.clean_model.clone(),
        full_size: [to_u32(raw.width)?, to_u32(raw.height)?],
        active_area: [to_u32(x0)?, to_u32(y0)?, to_u32(w)?, to_u32(h)?],
        cfa_pattern: pattern,
        bits_per_sample: u32::try_from(raw.bps).unwrap_or(0),
        black_levels: black.to_vec(),
        white_levels: white.to_vec(),
        white_balance: wb.iter().all(|c| c.is_finite()).then(|| wb.to_vec()),
        xyz_to_camera: raw
            .xyz_to_cam
            .iter()
            .take(3)
            .flatten()
            .all(|v| v.is_finite())
            .then(|| raw.xyz_to_cam[..3].iter().flatten().copied().collect()),
        exposure_s: exif.as_ref().and_then(|e| ratio(e.exposure_time)),
        iso: exif.as_ref().and_then(|e| {
            e.iso_speed_ratings
                .map(u32::from)
                .or(e.iso_speed)
                .or(e.recommended_exposure_index)
        }),
        f_number: exif.as_ref().and_then(|e| ratio(e.fnumber)),
        focal_length_mm: exif.as_ref().and_then(|e| ratio(e.focal_length)),
    };
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
        facts,
    })
}

fn decode_jpeg(bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
    let jpeg = rigd_process::image_io::decode_jpeg(bytes).map_err(|e| corrupt("JPEG", e))?;
    let too_large = |_| corrupt("JPEG", "the image is too large");
    let (w, h) = (
        u32::try_from(jpeg.width).map_err(too_large)?,
        u32::try_from(jpeg.height).map_err(too_large)?,
    );
    Ok(CameraImage {
        format: FileFormat::Jpeg,
        width: w,
        height: h,
        channels: jpeg.channels,
        cfa: None,
        samples: jpeg.samples.into_iter().map(u16::from).collect(),
        black: 0.0,
        white: 255.0,
        encoding: Encoding::Srgb,
        facts: Facts::rendered(w, h, 8),
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
    let white = if bits == 8 { 255.0 } else { 65535.0 };
    Ok(CameraImage {
        format: FileFormat::Tiff,
        width: w,
        height: h,
        channels,
        cfa: None,
        samples,
        black: 0.0,
        white,
        encoding: Encoding::Srgb,
        facts: Facts::rendered(w, h, u32::from(bits)),
    })
}
