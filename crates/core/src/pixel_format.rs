//! The pixel formats of raw camera frames, named as the GenICam Pixel Format
//! Naming Convention (PFNC) names them: monochrome (`Mono8` … `Mono16`) and
//! Bayer colour filter arrays (`BayerRG8` … `BayerBG16`), unpacked, one
//! sample per pixel in 1 byte (8 bits) or 2 little-endian bytes (10 to 16).
//!
//! Packed formats (`Mono12Packed`, `Mono12p`) are refused by name: rigd asks
//! the camera for an unpacked format instead, which costs bandwidth but no
//! bit-fiddling on every frame.

use std::fmt;
use std::str::FromStr;

/// A sample at or above this fraction of full scale is clipped: the
/// sensor's white level, less what rounding and a decoder's black
/// subtraction move it by. What a clipped sample shows is a lower bound,
/// not a measurement.
pub const CLIPPED_LEVEL: f32 = 0.995;

/// The 2×2 tile of a Bayer colour filter array, read left to right, top to
/// bottom from the frame's first pixel (PFNC: `BayerRG` starts with red).
///
/// In a profile and in messages it is named by its tile, `"RGGB"`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum Cfa {
    /// Red, green / green, blue.
    Rggb,
    /// Green, red / blue, green.
    Grbg,
    /// Green, blue / red, green.
    Gbrg,
    /// Blue, green / green, red.
    Bggr,
}

impl Cfa {
    /// The tile's name: `RGGB`, `GRBG`, `GBRG` or `BGGR`.
    pub fn tile(self) -> &'static str {
        match self {
            Cfa::Rggb => "RGGB",
            Cfa::Grbg => "GRBG",
            Cfa::Gbrg => "GBRG",
            Cfa::Bggr => "BGGR",
        }
    }

    /// The colour channel (0 red, 1 green, 2 blue) of the photosite at
    /// (`x`, `y`), counted from the frame's first pixel.
    pub fn channel_at(self, x: usize, y: usize) -> usize {
        let tile = match self {
            Cfa::Rggb => [0, 1, 1, 2],
            Cfa::Grbg => [1, 0, 2, 1],
            Cfa::Gbrg => [1, 2, 0, 1],
            Cfa::Bggr => [2, 1, 1, 0],
        };
        tile[(y % 2) * 2 + x % 2]
    }

    /// The PFNC infix: `RG`, `GR`, `GB` or `BG`.
    pub fn pfnc(self) -> &'static str {
        match self {
            Cfa::Rggb => "RG",
            Cfa::Grbg => "GR",
            Cfa::Gbrg => "GB",
            Cfa::Bggr => "BG",
        }
    }
}

impl fmt::Display for Cfa {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.tile())
    }
}

/// A raw frame's pixel format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PixelFormat {
    /// One grey sample per pixel, of this many bits.
    Mono(u8),
    /// One sample per pixel behind a colour filter array, of this many bits.
    Bayer(Cfa, u8),
}

/// Bit depths with an unpacked PFNC format.
const DEPTHS: [u8; 5] = [8, 10, 12, 14, 16];

/// A pixel format name rigd does not take.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("pixel format `{name}` is not one rigd takes ({why}); use one of {}", PixelFormat::names().join(", "))]
pub struct UnknownPixelFormat {
    /// The name given.
    pub name: String,
    /// Why it was refused.
    pub why: &'static str,
}

/// Frame bytes that do not fit the format and size.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{got} bytes for a {width}x{height} {format} frame, which needs {need}")]
pub struct WrongFrameSize {
    /// The format's name.
    pub format: String,
    /// Frame width, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
    /// Bytes delivered.
    pub got: usize,
    /// Bytes the size and format need.
    pub need: usize,
}

impl PixelFormat {
    /// Significant bits per sample.
    pub fn bit_depth(self) -> u8 {
        match self {
            PixelFormat::Mono(b) | PixelFormat::Bayer(_, b) => b,
        }
    }

    /// Bytes per pixel in an unpacked frame: 1 for 8 bits, else 2.
    pub fn bytes_per_pixel(self) -> usize {
        if self.bit_depth() <= 8 {
            1
        } else {
            2
        }
    }

    /// The colour filter array, or None for a monochrome sensor.
    pub fn cfa(self) -> Option<Cfa> {
        match self {
            PixelFormat::Mono(_) => None,
            PixelFormat::Bayer(c, _) => Some(c),
        }
    }

    /// Every name [`PixelFormat::from_str`] takes.
    pub fn names() -> Vec<String> {
        let mut out: Vec<String> = DEPTHS.iter().map(|b| format!("Mono{b}")).collect();
        for cfa in [Cfa::Rggb, Cfa::Grbg, Cfa::Gbrg, Cfa::Bggr] {
            out.extend(
                DEPTHS
                    .iter()
                    .map(|&b| PixelFormat::Bayer(cfa, b).to_string()),
            );
        }
        out
    }

    /// The unpacked monochrome format of a sensor of `bit_depth` bits,
    /// rounded up to the next depth PFNC names (9 bits: `Mono10`).
    pub fn mono_for_depth(bit_depth: u8) -> PixelFormat {
        let b = DEPTHS
            .iter()
            .copied()
            .find(|&d| d >= bit_depth)
            .unwrap_or(16);
        PixelFormat::Mono(b)
    }

    /// The samples of a frame delivered as `bytes`, row by row. Samples
    /// are not checked against the bit depth here (see the HAL's frame
    /// validation): a camera that sets high bits is reported, not masked.
    pub fn decode(self, width: u32, height: u32, bytes: &[u8]) -> Result<Vec<u16>, WrongFrameSize> {
        let pixels = width as usize * height as usize;
        let need = pixels * self.bytes_per_pixel();
        if bytes.len() != need {
            return Err(WrongFrameSize {
                format: self.to_string(),
                width,
                height,
                got: bytes.len(),
                need,
            });
        }
        Ok(if self.bytes_per_pixel() == 1 {
            bytes.iter().map(|&b| u16::from(b)).collect()
        } else {
            bytes
                .chunks_exact(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]))
                .collect()
        })
    }
}

impl fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PixelFormat::Mono(b) => write!(f, "Mono{b}"),
            PixelFormat::Bayer(c, b) => write!(f, "Bayer{}{b}", c.pfnc()),
        }
    }
}

impl FromStr for PixelFormat {
    type Err = UnknownPixelFormat;

    fn from_str(name: &str) -> Result<PixelFormat, UnknownPixelFormat> {
        let refuse = |why| UnknownPixelFormat {
            name: name.to_string(),
            why,
        };
        if name.ends_with("Packed") || name.ends_with('p') {
            return Err(refuse("packed formats are not taken"));
        }
        let (kind, rest) = if let Some(rest) = name.strip_prefix("Mono") {
            (None, rest)
        } else if let Some(rest) = name.strip_prefix("Bayer") {
            let cfa = match rest.get(..2) {
                Some("RG") => Cfa::Rggb,
                Some("GR") => Cfa::Grbg,
                Some("GB") => Cfa::Gbrg,
                Some("BG") => Cfa::Bggr,
                _ => return Err(refuse("a Bayer format names its tile: RG, GR, GB or BG")),
            };
            (Some(cfa), &rest[2..])
        } else {
            return Err(refuse("only monochrome and Bayer raw formats"));
        };
        let bits: u8 = rest.parse().map_err(|_| refuse("no bit depth"))?;
        if !DEPTHS.contains(&bits) {
            return Err(refuse("bit depths are 8, 10, 12, 14 or 16"));
        }
        Ok(match kind {
            None => PixelFormat::Mono(bits),
            Some(cfa) => PixelFormat::Bayer(cfa, bits),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_name_parses_back_to_itself() {
        let names = PixelFormat::names();
        assert_eq!(names.len(), 25);
        for n in names {
            let f: PixelFormat = n.parse().expect("a listed name parses");
            assert_eq!(f.to_string(), n);
        }
        assert_eq!("BayerRG12".parse(), Ok(PixelFormat::Bayer(Cfa::Rggb, 12)));
        assert_eq!(
            "BayerRG12".parse::<PixelFormat>().map(PixelFormat::cfa),
            Ok(Some(Cfa::Rggb))
        );
    }

    #[test]
    fn packed_colour_and_odd_names_are_refused_with_the_list() {
        for bad in [
            "Mono12Packed",
            "Mono12p",
            "RGB8",
            "Mono9",
            "BayerXY8",
            "Mono",
            "",
        ] {
            let e = bad.parse::<PixelFormat>().expect_err(bad);
            assert!(e.to_string().contains("Mono8, Mono10"), "{e}");
        }
    }

    #[test]
    fn depths_round_up_to_a_named_format() {
        assert_eq!(PixelFormat::mono_for_depth(8), PixelFormat::Mono(8));
        assert_eq!(PixelFormat::mono_for_depth(9), PixelFormat::Mono(10));
        assert_eq!(PixelFormat::mono_for_depth(12), PixelFormat::Mono(12));
        assert_eq!(PixelFormat::mono_for_depth(16), PixelFormat::Mono(16));
    }

    #[test]
    fn decoding_reads_little_endian_samples_and_checks_the_size() {
        let f = PixelFormat::Mono(12);
        assert_eq!(f.decode(2, 1, &[0xff, 0x0f, 0x01, 0x00]), Ok(vec![4095, 1]));
        assert_eq!(PixelFormat::Mono(8).decode(2, 1, &[7, 9]), Ok(vec![7, 9]));
        let e = f.decode(2, 2, &[0; 7]).expect_err("short");
        assert_eq!((e.got, e.need), (7, 8));
        assert!(e.to_string().contains("2x2 Mono12"), "{e}");
    }
}
