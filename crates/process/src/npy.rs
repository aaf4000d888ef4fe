//! Minimal NumPy `.npy` reader and writer for little-endian `float32` and
//! `float16` arrays of shape `(H, W)` or `(H, W, C)` in C (row-major)
//! order; both read back as `f32`.
//!
//! Writing produces format version 1.0 with the header padded so the data
//! starts on a 64-byte boundary, as NumPy itself does. Reading accepts
//! versions 1.0, 2.0 and 3.0 (they differ only in the header-length field),
//! but only `descr` `'<f4'` or `'<f2'`, `fortran_order: False` and rank 2
//! or 3.
//! `np.load` reads the written files directly.

use std::path::{Path, PathBuf};

const MAGIC: &[u8] = b"\x93NUMPY";

/// An `f32` array and its shape (row-major).
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    /// Dimensions, outermost first: `[H, W]` or `[H, W, C]`.
    pub shape: Vec<usize>,
    /// The values in C (row-major) order, as many as the product of `shape`.
    pub data: Vec<f32>,
}

/// Why bytes are not an array this module handles.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct NpyFormatError(pub String);

/// Why a `.npy` file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum NpyError {
    /// The file could not be read.
    #[error("cannot read {}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file could not be written.
    #[error("cannot write {}: {source}", path.display())]
    Write {
        /// The destination.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The array cannot be encoded (wrong rank, shape not matching the data),
    /// or the bytes read are not a `.npy` this module handles (dtype, order,
    /// rank, version, truncated data).
    #[error("{}: not a supported .npy file: {source}", path.display())]
    Format {
        /// The file read or written.
        path: PathBuf,
        /// What is wrong with the array or the bytes.
        source: NpyFormatError,
    },
}

fn format_err<T>(reason: impl Into<String>) -> Result<T, NpyFormatError> {
    Err(NpyFormatError(reason.into()))
}

/// How values are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dtype {
    /// `'<f4'`.
    F32,
    /// `'<f2'`: IEEE half precision, an 11-bit mantissa (a 12-bit sensor's
    /// codes near full scale within half a code), half the bytes.
    F16,
}

impl Dtype {
    fn descr(self) -> &'static str {
        match self {
            Dtype::F32 => "<f4",
            Dtype::F16 => "<f2",
        }
    }

    fn size(self) -> usize {
        match self {
            Dtype::F32 => 4,
            Dtype::F16 => 2,
        }
    }
}

/// Encodes `data` with `shape` as `.npy` v1.0 bytes of `float32`.
pub fn encode_f32(shape: &[usize], data: &[f32]) -> Result<Vec<u8>, NpyFormatError> {
    encode(shape, data, Dtype::F32)
}

/// Encodes `data` with `shape` as `.npy` v1.0 bytes of `dtype` (values
/// beyond half precision's range become ±infinity, as NumPy's cast does).
pub fn encode(shape: &[usize], data: &[f32], dtype: Dtype) -> Result<Vec<u8>, NpyFormatError> {
    if shape.len() != 2 && shape.len() != 3 {
        return format_err(format!("rank {} (expected 2 or 3)", shape.len()));
    }
    let count = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| NpyFormatError("shape overflows".into()))?;
    if count != data.len() {
        return format_err(format!(
            "shape {shape:?} needs {count} values, got {}",
            data.len()
        ));
    }
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let mut header = format!(
        "{{'descr': '{}', 'fortran_order': False, 'shape': ({}), }}",
        dtype.descr(),
        dims.join(", ")
    );
    // Preamble is magic (6) + version (2) + length (2); NumPy pads with
    // spaces and ends with '\n' so the data is 64-byte aligned.
    let unpadded = MAGIC.len() + 4 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let header_len = u16::try_from(header.len())
        .map_err(|_| NpyFormatError("header too long for v1.0".into()))?;
    let mut out = Vec::with_capacity(MAGIC.len() + 4 + header.len() + dtype.size() * data.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&header_len.to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for &v in data {
        match dtype {
            Dtype::F32 => out.extend_from_slice(&v.to_le_bytes()),
            Dtype::F16 => out.extend_from_slice(&half::f16::from_f32(v).to_le_bytes()),
        }
    }
    Ok(out)
}

/// Decodes `.npy` bytes (see the module doc for what is accepted).
pub fn decode_f32(bytes: &[u8]) -> Result<NpyArray, NpyFormatError> {
    if bytes.len() < MAGIC.len() + 4 || &bytes[..MAGIC.len()] != MAGIC {
        return format_err("missing \\x93NUMPY magic");
    }
    let major = bytes[6];
    let (header_len, header_start): (usize, usize) = match major {
        1 => (usize::from(u16::from_le_bytes([bytes[8], bytes[9]])), 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return format_err("truncated preamble");
            }
            let len = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
            (
                usize::try_from(len).map_err(|_| NpyFormatError("header too long".into()))?,
                12,
            )
        }
        v => return format_err(format!("format version {v}.{}", bytes[7])),
    };
    let data_start = header_start
        .checked_add(header_len)
        .filter(|&end| end <= bytes.len())
        .ok_or_else(|| NpyFormatError("truncated header".into()))?;
    let header = std::str::from_utf8(&bytes[header_start..data_start])
        .map_err(|_| NpyFormatError("header is not UTF-8".into()))?;
    let header = parse_header(header)?;
    let dtype = match header.descr.as_str() {
        "<f4" => Dtype::F32,
        "<f2" => Dtype::F16,
        other => return format_err(format!("dtype '{other}' (expected '<f4' or '<f2')")),
    };
    if header.fortran_order {
        return format_err("Fortran order");
    }
    if header.shape.len() != 2 && header.shape.len() != 3 {
        return format_err(format!("rank {} (expected 2 or 3)", header.shape.len()));
    }
    let count = header
        .shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| NpyFormatError("shape overflows".into()))?;
    let payload = &bytes[data_start..];
    if count.checked_mul(dtype.size()) != Some(payload.len()) {
        return format_err(format!(
            "shape {:?} needs {} data bytes, file has {}",
            header.shape,
            count.saturating_mul(dtype.size()),
            payload.len()
        ));
    }
    let data = match dtype {
        Dtype::F32 => payload
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect(),
        Dtype::F16 => payload
            .chunks_exact(2)
            .map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32())
            .collect(),
    };
    Ok(NpyArray {
        shape: header.shape,
        data,
    })
}

/// Writes a `float32` array atomically (temporary file + rename).
pub fn write_f32(path: &Path, shape: &[usize], data: &[f32]) -> Result<(), NpyError> {
    write(path, shape, data, Dtype::F32)
}

/// Writes an array of `dtype` atomically (temporary file + rename).
pub fn write(path: &Path, shape: &[usize], data: &[f32], dtype: Dtype) -> Result<(), NpyError> {
    let bytes = encode(shape, data, dtype).map_err(|source| NpyError::Format {
        path: path.to_path_buf(),
        source,
    })?;
    rigd_core::atomic::write(path, &bytes).map_err(|e| NpyError::Write {
        path: path.to_path_buf(),
        source: e.error,
    })
}

/// Reads an array written by [`write_f32`] or by NumPy.
pub fn read_f32(path: &Path) -> Result<NpyArray, NpyError> {
    let bytes = std::fs::read(path).map_err(|source| NpyError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    decode_f32(&bytes).map_err(|source| NpyError::Format {
        path: path.to_path_buf(),
        source,
    })
}

struct Header {
    descr: String,
    fortran_order: bool,
    shape: Vec<usize>,
}

/// Parses the Python dict literal NumPy writes: string keys mapping to a
/// string, a bool or a tuple of integers.
fn parse_header(text: &str) -> Result<Header, NpyFormatError> {
    let mut p = Parser {
        s: text.as_bytes(),
        i: 0,
    };
    let (mut descr, mut fortran_order, mut shape) = (None, None, None);
    p.expect(b'{')?;
    loop {
        p.skip_ws();
        if p.eat(b'}') {
            break;
        }
        let key = p.string()?;
        p.expect(b':')?;
        p.skip_ws();
        match key.as_str() {
            "descr" => descr = Some(p.string()?),
            "fortran_order" => fortran_order = Some(p.boolean()?),
            "shape" => shape = Some(p.tuple()?),
            other => return format_err(format!("unexpected header key '{other}'")),
        }
        p.skip_ws();
        if !p.eat(b',') {
            p.expect(b'}')?;
            break;
        }
    }
    match (descr, fortran_order, shape) {
        (Some(descr), Some(fortran_order), Some(shape)) => Ok(Header {
            descr,
            fortran_order,
            shape,
        }),
        _ => format_err("header lacks descr, fortran_order or shape"),
    }
}

struct Parser<'a> {
    s: &'a [u8],
    i: usize,
}

impl Parser<'_> {
    fn skip_ws(&mut self) {
        while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
            self.i += 1;
        }
    }

    fn eat(&mut self, c: u8) -> bool {
        if self.s.get(self.i) == Some(&c) {
            self.i += 1;
            true
        } else {
            false
        }
    }

    fn expect(&mut self, c: u8) -> Result<(), NpyFormatError> {
        self.skip_ws();
        if self.eat(c) {
            Ok(())
        } else {
            format_err(format!(
                "header: expected '{}' at byte {}",
                c as char, self.i
            ))
        }
    }

    fn string(&mut self) -> Result<String, NpyFormatError> {
        let quote = match self.s.get(self.i) {
            Some(&q @ (b'\'' | b'"')) => q,
            _ => return format_err(format!("header: expected a string at byte {}", self.i)),
        };
        let start = self.i + 1;
        let len = self.s[start..]
            .iter()
            .position(|&c| c == quote)
            .ok_or_else(|| NpyFormatError("header: unterminated string".into()))?;
        self.i = start + len + 1;
        Ok(String::from_utf8_lossy(&self.s[start..start + len]).into_owned())
    }

    fn boolean(&mut self) -> Result<bool, NpyFormatError> {
        for (word, value) in [(&b"True"[..], true), (&b"False"[..], false)] {
            if self.s[self.i..].starts_with(word) {
                self.i += word.len();
                return Ok(value);
            }
        }
        format_err(format!("header: expected True or False at byte {}", self.i))
    }

    fn tuple(&mut self) -> Result<Vec<usize>, NpyFormatError> {
        self.expect(b'(')?;
        let mut dims = Vec::new();
        loop {
            self.skip_ws();
            if self.eat(b')') {
                return Ok(dims);
            }
            let start = self.i;
            while self.i < self.s.len() && self.s[self.i].is_ascii_digit() {
                self.i += 1;
            }
            let digits = std::str::from_utf8(&self.s[start..self.i]).unwrap_or("");
            let dim = digits
                .parse::<usize>()
                .map_err(|_| NpyFormatError(format!("header: bad dimension at byte {start}")))?;
            dims.push(dim);
            self.skip_ws();
            if !self.eat(b',') {
                self.expect(b')')?;
                return Ok(dims);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_is_64_byte_aligned_and_numpy_shaped() {
        let bytes = encode_f32(&[2, 3], &[0.0; 6]).unwrap();
        let header_len = usize::from(u16::from_le_bytes([bytes[8], bytes[9]]));
        assert_eq!((10 + header_len) % 64, 0);
        let header = std::str::from_utf8(&bytes[10..10 + header_len]).unwrap();
        assert!(header.starts_with("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }"));
        assert!(header.ends_with('\n'));
        assert_eq!(bytes.len(), 10 + header_len + 24);
    }

    #[test]
    fn float16_round_trips_within_half_precision() {
        // 12-bit codes near full scale, small values, zero, and one beyond
        // half's range (infinity, as NumPy casts it).
        let values = [4095.0 / 4095.0, 4094.0 / 4095.0, 1e-3, 0.0, -0.5, 1e6];
        let bytes = encode(&[2, 3], &values, Dtype::F16).unwrap();
        let header_len = usize::from(u16::from_le_bytes([bytes[8], bytes[9]]));
        assert_eq!(bytes.len(), 10 + header_len + 12);
        let back = decode_f32(&bytes).unwrap();
        assert_eq!(back.shape, vec![2, 3]);
        for (a, b) in values.iter().zip(&back.data).take(5) {
            assert!((a - b).abs() <= a.abs() / 2048.0, "{a} -> {b}");
        }
        assert!(back.data[5].is_infinite());
    }

    #[test]
    fn rejects_wrong_dtype_order_rank_and_length() {
        let good = encode_f32(&[1, 2], &[1.0, 2.0]).unwrap();
        let swap = |from: &str, to: &str| {
            let text = String::from_utf8_lossy(&good).replace(from, to);
            let mut b = text.into_bytes();
            b.truncate(good.len());
            // Keep the byte-exact layout: replacements here are same-length.
            b
        };
        assert!(decode_f32(&swap("<f4", "<f8")).is_err());
        assert!(decode_f32(&swap("False", "True ")).is_err());
        assert!(decode_f32(&good[..good.len() - 1]).is_err());
        assert!(decode_f32(b"PK\x03\x04").is_err());
        assert!(encode_f32(&[4], &[0.0; 4]).is_err());
        assert!(encode_f32(&[2, 2], &[0.0; 3]).is_err());
    }

    #[test]
    fn file_round_trip_and_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.npy");
        write_f32(&path, &[2, 2, 3], &[1.5; 12]).unwrap();
        let back = read_f32(&path).unwrap();
        assert_eq!(back.shape, vec![2, 2, 3]);
        assert_eq!(back.data, vec![1.5; 12]);
        let missing = dir.path().join("missing.npy");
        assert!(read_f32(&missing)
            .unwrap_err()
            .to_string()
            .contains("missing.npy"));
        let bad = dir.path().join("bad.npy");
        std::fs::write(&bad, b"junk").unwrap();
        assert!(read_f32(&bad).unwrap_err().to_string().contains("bad.npy"));
    }
}
