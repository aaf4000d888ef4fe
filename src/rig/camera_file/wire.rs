//! What the decoder child writes back: one record a file, `RIGDFRM1`, the
//! length of a JSON header (u32, little-endian), the header (the image's
//! facts and its sample count, or the error), then the samples as u16
//! little-endian. The parent reads it as untrusted bytes: every length is
//! checked against what it asked for before anything is allocated.

use std::io::{self, Read, Write};

use serde::{Deserialize, Serialize};

use super::{CameraFileError, CameraImage, Encoding, Facts, FileFormat, EXTENSIONS};

/// The first bytes of every record.
const MAGIC: &[u8; 8] = b"RIGDFRM1";

/// The largest header the parent reads: the facts are a few hundred bytes.
const MAX_HEADER: u32 = 1 << 20;

/// The header of a record: the image or why there is none.
#[derive(Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Header {
    Image(Box<ImageHeader>),
    Error(ErrorHeader),
}

#[derive(Serialize, Deserialize)]
struct ImageHeader {
    /// The stored frame's extension (`FileFormat::extension`).
    format: String,
    width: u32,
    height: u32,
    channels: usize,
    cfa: Option<rigd_core::Cfa>,
    black: f32,
    white: f32,
    srgb: bool,
    facts: Facts,
    /// How many u16 samples follow.
    samples: u64,
}

#[derive(Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
enum ErrorHeader {
    Unknown { start: String },
    Corrupt { format: String, message: String },
    Unsupported { format: String, what: String },
}

/// Why a record could not be read.
#[derive(Debug, thiserror::Error)]
pub(super) enum WireError {
    /// The stream ended, or could not be read.
    #[error("its answer ended early ({0})")]
    Io(#[from] io::Error),
    /// The bytes are not a record.
    #[error("it answered garbage ({0})")]
    Garbage(String),
}

fn garbage<T>(why: impl Into<String>) -> Result<T, WireError> {
    Err(WireError::Garbage(why.into()))
}

/// Writes one record: the image, or the error.
pub(super) fn write_record(
    out: &mut impl Write,
    result: &Result<CameraImage, CameraFileError>,
) -> io::Result<()> {
    let header = match result {
        Ok(img) => Header::Image(Box::new(ImageHeader {
            format: img.format.extension().to_string(),
            width: img.width,
            height: img.height,
            channels: img.channels,
            cfa: img.cfa,
            black: img.black,
            white: img.white,
            srgb: img.encoding == Encoding::Srgb,
            facts: img.facts.clone(),
            samples: img.samples.len() as u64,
        })),
        Err(e) => Header::Error(match e {
            CameraFileError::Unknown(start) => ErrorHeader::Unknown {
                start: start.clone(),
            },
            CameraFileError::Unsupported { format, what } => ErrorHeader::Unsupported {
                format: format.clone(),
                what: what.clone(),
            },
            CameraFileError::Corrupt { format, message } => ErrorHeader::Corrupt {
                format: format.clone(),
                message: message.clone(),
            },
            // The child's own errors are all about the file; the others
            // (no decoder, a crash) are the parent's to say.
            other => ErrorHeader::Corrupt {
                format: "camera".into(),
                message: other.to_string(),
            },
        }),
    };
    let json = serde_json::to_vec(&header).map_err(io::Error::other)?;
    let len = u32::try_from(json.len()).map_err(io::Error::other)?;
    out.write_all(MAGIC)?;
    out.write_all(&len.to_le_bytes())?;
    out.write_all(&json)?;
    if let Ok(img) = result {
        write_samples(out, &img.samples)?;
    }
    out.flush()
}

/// The format a header names, by its extension.
fn format_of(ext: &str) -> Option<FileFormat> {
    Some(match ext {
        "dng" => FileFormat::Dng,
        "tif" => FileFormat::Tiff,
        "jpg" => FileFormat::Jpeg,
        other => FileFormat::VendorRaw(EXTENSIONS.iter().copied().find(|e| *e == other)?),
    })
}

/// Reads one record; `max_samples` is the most samples the caller accepts
/// (what the child could have held in its memory).
pub(super) fn read_record(
    input: &mut impl Read,
    max_samples: u64,
) -> Result<Result<CameraImage, CameraFileError>, WireError> {
    let mut magic = [0u8; 8];
    input.read_exact(&mut magic)?;
    if &magic != MAGIC {
        return garbage(format!("it starts {magic:02x?}, not a record"));
    }
    let mut len = [0u8; 4];
    input.read_exact(&mut len)?;
    let len = u32::from_le_bytes(len);
    if len > MAX_HEADER {
        return garbage(format!("a header of {len} bytes"));
    }
    let mut json = vec![0u8; len as usize];
    input.read_exact(&mut json)?;
    let header: Header = serde_json::from_slice(&json)
        .or_else(|e| garbage(format!("its header does not parse: {e}")))?;
    let h = match header {
        Header::Error(e) => {
            return Ok(Err(match e {
                ErrorHeader::Unknown { start } => CameraFileError::Unknown(start),
                ErrorHeader::Corrupt { format, message } => {
                    CameraFileError::Corrupt { format, message }
                }
                ErrorHeader::Unsupported { format, what } => {
                    CameraFileError::Unsupported { format, what }
                }
            }))
        }
        Header::Image(h) => h,
    };
    let Some(format) = format_of(&h.format) else {
        return garbage(format!("an unknown format {:?}", h.format));
    };
    let expected = u64::from(h.width)
        .checked_mul(u64::from(h.height))
        .and_then(|n| n.checked_mul(h.channels as u64));
    if !matches!(h.channels, 1 | 3) || expected != Some(h.samples) {
        return garbage(format!(
            "{} samples for {}x{}x{}",
            h.samples, h.width, h.height, h.channels
        ));
    }
    if h.samples > max_samples {
        return garbage(format!(
            "{} samples, more than the {max_samples} it could hold",
            h.samples
        ));
    }
    let n = usize::try_from(h.samples).or_else(|_| garbage("too many samples"))?;
    let samples = read_samples(input, n)?;
    Ok(Ok(CameraImage {
        format,
        width: h.width,
        height: h.height,
        channels: h.channels,
        cfa: h.cfa,
        samples,
        black: h.black,
        white: h.white,
        encoding: if h.srgb {
            Encoding::Srgb
        } else {
            Encoding::Linear
        },
        facts: h.facts,
    }))
}

/// The samples as little-endian u16: on a little-endian machine the
/// memory as it is (no copy), else swapped block by block.
fn write_samples(out: &mut impl Write, samples: &[u16]) -> io::Result<()> {
    if cfg!(target_endian = "little") {
        return out.write_all(bytemuck::cast_slice(samples));
    }
    let mut block = Vec::with_capacity(64 * 1024);
    for chunk in samples.chunks(32 * 1024) {
        block.clear();
        for s in chunk {
            block.extend_from_slice(&s.to_le_bytes());
        }
        out.write_all(&block)?;
    }
    Ok(())
}

/// `n` little-endian u16 samples, read straight into their vector.
fn read_samples(input: &mut impl Read, n: usize) -> io::Result<Vec<u16>> {
    let mut samples = vec![0u16; n];
    input.read_exact(bytemuck::cast_slice_mut(&mut samples))?;
    if cfg!(target_endian = "big") {
        for s in &mut samples {
            *s = u16::from_le(*s);
        }
    }
    Ok(samples)
}

/// Writes one request of the batch mode: the file's length (u64,
/// little-endian), then its bytes.
pub(super) fn write_request(out: &mut impl Write, bytes: &[u8]) -> io::Result<()> {
    out.write_all(&(bytes.len() as u64).to_le_bytes())?;
    out.write_all(bytes)?;
    out.flush()
}

/// Reads one request of the batch mode; `None` at the end of the stream.
/// A file longer than `max` bytes is an error.
pub(super) fn read_request(input: &mut impl Read, max: u64) -> io::Result<Option<Vec<u8>>> {
    let mut len = [0u8; 8];
    match input.read_exact(&mut len) {
        Ok(()) => {}
        Err(e) if e.kind() == io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(e) => return Err(e),
    }
    let len = u64::from_le_bytes(len);
    if len > max {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!("a file of {len} bytes, more than {max}"),
        ));
    }
    let mut bytes = vec![0u8; len as usize];
    input.read_exact(&mut bytes)?;
    Ok(Some(bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image() -> CameraImage {
        CameraImage {
            format: FileFormat::VendorRaw("nef"),
            width: 3,
            height: 2,
            channels: 1,
            cfa: Some(rigd_core::Cfa::Gbrg),
            samples: vec![0, 1, 2, 65535, 4, 5],
            black: 10.5,
            white: 4095.0,
            encoding: Encoding::Linear,
            facts: Facts::rendered(3, 2, 12),
        }
    }

    #[test]
    fn a_record_reads_back_as_written() {
        for result in [
            Ok(image()),
            Err(CameraFileError::Unsupported {
                format: "DNG".into(),
                what: "compression 9 (VC-5): no decoder".into(),
            }),
            Err(CameraFileError::Unknown("empty".into())),
        ] {
            let mut out = Vec::new();
            write_record(&mut out, &result).expect("write");
            let back = read_record(&mut &out[..], 6).expect("a record");
            assert_eq!(back, result);
        }
    }

    #[test]
    fn every_cut_or_lie_of_a_record_is_an_error_not_an_allocation() {
        let mut good = Vec::new();
        write_record(&mut good, &Ok(image())).expect("write");
        for cut in 0..good.len() {
            assert!(read_record(&mut &good[..cut], 6).is_err(), "cut at {cut}");
        }
        // Fewer samples allowed than the record holds.
        assert!(matches!(
            read_record(&mut &good[..], 5),
            Err(WireError::Garbage(_))
        ));
        // A header length of 4 GB, and a sample count that lies.
        let mut bad = good.clone();
        bad[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            read_record(&mut &bad[..], 6),
            Err(WireError::Garbage(_))
        ));
        let text = String::from_utf8_lossy(&good).replace("\"samples\":6", "\"samples\":7");
        assert!(read_record(&mut text.as_bytes(), u64::MAX).is_err());
    }
}
