//! Camera files: the objects a real camera delivers (DNG, vendor raw,
//! TIFF, JPEG), read back as the samples they hold.
//!
//! A frame from such a camera is stored exactly as delivered; this module
//! is how the driver checks it, and how previews and processing read it.
//! DNG and vendor raw files (NEF, CR2, CR3, ARW, RAF, ORF, RW2, …) go
//! through `rawler`, JPEG through `rigd_process::image_io::decode_jpeg`,
//! plain TIFF through `tiff`. Which one is chosen by the file's own bytes,
//! never by its name.
//!
//! [`decode`] runs them in a child process ([`Decoder`]): a file from
//! outside can make a decoder allocate until its process aborts, and that
//! process must not be rigd (`docs/processing.md`, "Camera files").
//! [`decode_here`] runs them in this process, for frames rigd wrote itself
//! and checked against their journal's SHA-256.

mod child;
mod decoders;
mod wire;

use std::sync::OnceLock;

use rigd_core::Cfa;
use serde::{Deserialize, Serialize};

pub use child::{
    serve, BatchDecoder, Decoder, DecoderPool, DECODER_ENV, DEFAULT_DEADLINE, DEFAULT_MEMORY,
};

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
            FileFormat::VendorRaw(ext) => VENDOR_NAMES
                .iter()
                .find(|(e, _)| *e == ext)
                .map_or("raw", |(_, name)| name),
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

/// The vendor raw formats by extension, as their makers name them.
const VENDOR_NAMES: [(&str, &str); 13] = [
    ("nef", "NEF"),
    ("nrw", "NRW"),
    ("cr2", "CR2"),
    ("cr3", "CR3"),
    ("crw", "CRW"),
    ("arw", "ARW"),
    ("raf", "RAF"),
    ("orf", "ORF"),
    ("rw2", "RW2"),
    ("pef", "PEF"),
    ("srw", "SRW"),
    ("iiq", "IIQ"),
    ("raw", "raw"),
];

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
    /// What the file says of the camera and the exposure.
    pub facts: Facts,
}

/// What a camera file says of its sensor, camera and exposure, as far as
/// it says it (rendered JPEG and TIFF files say only their size).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Facts {
    /// The camera's maker, as the decoder cleans it up (`Nikon`).
    pub make: String,
    /// The camera's model (`D5100`).
    pub model: String,
    /// The whole sensor readout in pixels, masked borders included.
    pub full_size: [u32; 2],
    /// The image part of it: left, top, width, height.
    pub active_area: [u32; 4],
    /// The colour filter tile at the active area's corner, by its colours
    /// (`RGGB`); None for grey or RGB samples.
    pub cfa_pattern: Option<String>,
    /// Bits a sample is stored with.
    pub bits_per_sample: u32,
    /// Black level of each of the tile's 4 sites (R, G, B, G2 order as the
    /// decoder gives them).
    pub black_levels: Vec<f32>,
    /// White level of each of the tile's 4 sites.
    pub white_levels: Vec<f32>,
    /// The camera's white balance as shot: multipliers for red, green,
    /// blue and the second green (None when the file has none).
    pub white_balance: Option<Vec<f32>>,
    /// The camera's XYZ to camera RGB matrix, row by row (9 values).
    pub xyz_to_camera: Option<Vec<f32>>,
    /// Exposure time in seconds.
    pub exposure_s: Option<f64>,
    /// ISO speed.
    pub iso: Option<u32>,
    /// Aperture, as an f-number.
    pub f_number: Option<f64>,
    /// Focal length in millimetres.
    pub focal_length_mm: Option<f64>,
}

impl Facts {
    /// The facts of a rendered image: its size, nothing of a sensor.
    pub fn rendered(width: u32, height: u32, bits: u32) -> Facts {
        Facts {
            full_size: [width, height],
            active_area: [0, 0, width, height],
            bits_per_sample: bits,
            ..Facts::default()
        }
    }
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
        format: String,
        /// The decoder's words.
        message: String,
    },
    /// The file is whole but holds what rigd does not decode or process.
    #[error("{format} with {what}")]
    Unsupported {
        /// What the file is.
        format: String,
        /// What it holds, and what is missing for it.
        what: String,
    },
    /// The decoder child died on the file, hung, or answered garbage.
    #[error("the camera-file decoder (a child process) {0}")]
    Crashed(String),
    /// No decoder child could be started: a fault of the installation,
    /// not of the file.
    #[error("no camera-file decoder: {0}")]
    NoDecoder(String),
}

impl CameraFileError {
    /// Whether the error is the file's (anything but [`Self::NoDecoder`]).
    pub fn is_the_file_s(&self) -> bool {
        !matches!(self, CameraFileError::NoDecoder(_))
    }
}

/// Decodes a camera file by its content, in a decoder child
/// ([`child`]): a file that crashes or hangs the decoder is an error
/// naming what happened, and this process goes on. The children are kept
/// for the next file (one per thread decoding at once) and end with this
/// process.
pub fn decode(bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
    static KEPT: OnceLock<Result<DecoderPool, CameraFileError>> = OnceLock::new();
    match KEPT.get_or_init(|| Decoder::rigd().map(DecoderPool::new)) {
        Ok(pool) => pool.decode(bytes),
        Err(e) => Err(e.clone()),
    }
}

/// Where a camera's files are decoded.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum DecodeIn {
    /// In a decoder child ([`decode`]): the file comes from outside this
    /// process (a camera, a network peer, a disk).
    #[default]
    Child,
    /// In this process ([`decode_here`]): the file was made by this
    /// process's own simulated camera, which no device or disk can have
    /// made hostile, and a simulated run of thousands of frames must not
    /// pay a child's round trip for each.
    ThisProcess,
}

impl DecodeIn {
    /// Decodes `bytes` where this says.
    pub fn decode(self, bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
        match self {
            DecodeIn::Child => decode(bytes),
            DecodeIn::ThisProcess => decode_here(bytes),
        }
    }
}

/// Decodes a camera file in this process. Only for bytes rigd wrote itself
/// and has checked since (a simulated run's DNG whose SHA-256 matches its
/// journal line, `docs/processing.md`): a file from a camera or a disk may
/// make a decoder allocate until this process aborts.
pub fn decode_here(bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
    decoders::decode(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    #[test]
    fn unknown_bytes_are_named_not_guessed() {
        for bytes in [
            &b""[..],
            b"hello world",
            &[0x89, b'P', b'N', b'G', 0, 0, 0, 0][..],
        ] {
            let e = decode_here(bytes).expect_err("not a camera file");
            assert!(matches!(e, CameraFileError::Unknown(_)), "{e}");
        }
    }

    #[test]
    fn a_truncated_jpeg_or_tiff_is_corrupt_not_a_panic() {
        assert!(decode_here(&[0xFF, 0xD8, 0xFF, 0xE0, 0, 16]).is_err());
        assert!(decode_here(b"II*\0\x08\0\0\0\xff\xff").is_err());
        assert!(decode_here(b"MM\0*\0\0\0\x08").is_err());
    }

    #[test]
    fn a_plain_tiff_reads_as_srgb() {
        let mut out = Cursor::new(Vec::new());
        let mut enc = tiff::encoder::TiffEncoder::new(&mut out).expect("encoder");
        enc.write_image::<tiff::encoder::colortype::RGB8>(2, 1, &[255, 0, 0, 0, 128, 255])
            .expect("write");
        let img = decode_here(out.get_ref()).expect("a TIFF");
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

    /// Sets the value of IFD0's SHORT entry `tag` in a little-endian TIFF.
    #[cfg(feature = "sim")]
    fn set_short(bytes: &mut [u8], tag: u16, value: u16) {
        let le16 = |b: &[u8], at: usize| u16::from_le_bytes([b[at], b[at + 1]]);
        let ifd = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]) as usize;
        let entry = (0..usize::from(le16(bytes, ifd)))
            .map(|i| ifd + 2 + 12 * i)
            .find(|&at| le16(bytes, at) == tag)
            .expect("the tag");
        bytes[entry + 8..entry + 10].copy_from_slice(&value.to_le_bytes());
    }

    #[cfg(feature = "sim")]
    #[test]
    fn a_dng_says_its_facts_and_one_rawler_cannot_decode_names_its_compression() {
        let good = sim_dng();
        let img = decode_here(&good).expect("the simulated DNG");
        assert_eq!((img.format, img.width, img.height), (FileFormat::Dng, 8, 6));
        assert_eq!(img.facts.active_area, [0, 0, 8, 6]);
        assert_eq!(img.facts.cfa_pattern.as_deref(), Some("RGGB"));
        assert_eq!(img.facts.exposure_s, Some(0.1));
        let mut vc5 = good.clone();
        set_short(&mut vc5, 0x0103, 9);
        let e = decode_here(&vc5).expect_err("no VC-5 decoder");
        assert_eq!(e.to_string(), "DNG with compression 9 (VC-5): no decoder");
    }

    #[cfg(feature = "sim")]
    #[test]
    fn a_raw_file_whose_white_level_is_not_above_its_black_is_refused() {
        let mut flat = sim_dng();
        // WhiteLevel 0: no range above the black level is left.
        set_short(&mut flat, 0xC61D, 0);
        let e = decode_here(&flat).expect_err("no range");
        assert!(matches!(e, CameraFileError::Corrupt { .. }), "{e}");
        assert!(
            e.to_string().contains("is not below its white level"),
            "{e}"
        );
    }

    #[test]
    fn a_cut_cr3_or_raf_is_named_by_its_signature() {
        let mut cr3 = b"\0\0\0\x18ftypcrx \0\0\0\x01".to_vec();
        cr3.resize(64, 0);
        let e = decode_here(&cr3).expect_err("cut short");
        assert!(
            e.to_string().starts_with("CR3 file cannot be decoded"),
            "{e}"
        );
        let raf = b"FUJIFILMCCD-RAW 0201FF383501".to_vec();
        let e = decode_here(&raf).expect_err("cut short");
        assert!(
            e.to_string().starts_with("RAF file cannot be decoded"),
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
            facts: Facts::default(),
        };
        assert_eq!(img.bit_depth(), 12);
        img.white = 15_000.0;
        assert_eq!(img.bit_depth(), 14);
        img.white = 65535.0;
        assert_eq!(img.bit_depth(), 16);
    }
}
