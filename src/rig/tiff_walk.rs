//! The structure of a camera file, walked before `rawler` reads it.
//!
//! rawler parses a TIFF directory entry by allocating the number of values
//! the entry claims before it checks them against the file (`Entry::parse`
//! in its `formats/tiff/entry.rs`): one damaged count asks for tens of GB,
//! and a failed allocation aborts the process, which no `catch_unwind`
//! stops. Its ISO-BMFF (CR3) boxes, Phase One maker notes, CRW heaps and CR3
//! metadata records do the same with their own sizes and counts, and an IFD
//! chain that loops back on itself makes it read directories until memory
//! runs out.
//!
//! [`walk`] reads the structures rawler reads, the way rawler reads them
//! (which format `get_decoder` picks from the first bytes, which IFDs each
//! decoder follows, their byte orders, bases and offset corrections), and
//! refuses a file before rawler allocates what the file could not hold:
//!
//! - any directory entry whose values (count × rawler's size of its type)
//!   are more bytes than the file (or the block the directory is read
//!   from) has, anywhere rawler parses directories;
//! - in the file's own TIFF structure (the IFD chain and its SubIFDs, EXIF
//!   and GPS IFDs), also any value, directory or entry table that lies
//!   past the end of the file: only damage puts them there. Maker notes and
//!   other vendor directories are held only to the first rule, because real
//!   cameras write them carelessly and rawler skips such entries. Bytes
//!   rawler reads as an IFD by mistake (an ICC profile, a sub-IFD pointer
//!   of the wrong type) hold garbage counts even in a perfect file; rawler
//!   frees what it allocated for them when their read fails, so there only
//!   claims past 256 MiB are refused;
//! - IFD chains that loop, and files whose directories, entries, values or
//!   boxes add up to more than a bound (a few hundred IFDs, 8 bytes of
//!   values per file byte, …), so that no combination of entries that each
//!   fit can add up to an allocation that does not.
//!
//! It also collects the image sizes the file claims (TIFF `ImageWidth` ×
//! `ImageLength`, and the vendor fields rawler sizes its image buffers
//! from), for the caller's check against the file's size.
//!
//! The `tiff` crate cannot do this walk: its decoder reads only magic 42 or
//! 43 (no RW2 or ORF), reads types by the TIFF specification (rawler reads
//! unknown types as bytes and counts type 13 as one byte a value), does not
//! know vendor offset corrections or maker note headers, and checks values
//! by its own limit, not by the bytes rawler will read. So this is a small
//! walker of its own, and every place it mirrors rawler names the function.
//!
//! Where rawler's arithmetic overflows (a panic in a debug build, a
//! wrap-around in a release build) the walker follows the release build,
//! which reads more; where a wrap-around would make rawler loop forever,
//! the file is refused.

use std::collections::BTreeSet;
use std::fmt;
use std::ops::Range;

/// Most directories (IFDs) rawler may be made to read from one file; real
/// files have a few dozen at most.
const MAX_DIRECTORIES: usize = 512;

/// Most directory entries rawler may be made to read from one file.
const MAX_ENTRIES: usize = 1 << 17;

/// Deepest nesting of directories (IFD chain → SubIFD → maker note → …).
const MAX_NESTING: usize = 8;

/// Most bytes of directory values rawler may be made to allocate, per byte
/// of the file: real files use about one (each value once), two or three
/// where a decoder parses a maker note out of a value it already read.
const VALUE_BYTES_PER_FILE_BYTE: u64 = 8;

/// Most ISO-BMFF boxes rawler may be made to read; a CR3 has about fifty.
const MAX_BOXES: usize = 100_000;

/// Most bytes rawler's CRW (CIFF) reader may be made to copy, per byte of
/// the file: it copies every entry's data, nested heaps again at each level.
const CIFF_COPY_PER_FILE_BYTE: u64 = 16;

/// The largest claim refused only past the bytes in a directory rawler
/// reads by mistake ([`Trust::Misread`]): rawler's allocation of it lasts
/// until its read fails, and so much is there to take on any machine rigd
/// runs on.
const MISREAD_ALLOWANCE: u64 = 256 << 20;

/// rawler reads at most this many entries of one IFD (`MAX_IFD_ENTRIES`).
const RAWLER_MAX_IFD_ENTRIES: u16 = 4096;

/// rawler gives up on an IFD after this many entries in a row fail.
const RAWLER_MAX_ENTRY_ERRORS: usize = 5;

// TIFF tags the walk reads.
const IMAGE_WIDTH: u16 = 0x0100;
const IMAGE_LENGTH: u16 = 0x0101;
const MAKE: u16 = 0x010F;
const MODEL: u16 = 0x0110;
const SAMPLES_PER_PIXEL: u16 = 0x0115;
const SOFTWARE: u16 = 0x0131;
const TILE_WIDTH: u16 = 0x0142;
const TILE_LENGTH: u16 = 0x0143;
const SUB_IFDS: u16 = 0x014A;
const KODAK_IFD: u16 = 0x8290;
const CR2_KODAK_SUB_IFD: u16 = 33424;
const EXIF_IFD: u16 = 0x8769;
const ICC_PROFILE: u16 = 0x8773;
const GPS_IFD: u16 = 0x8825;
const MAKER_NOTE: u16 = 0x927C;
const DNG_VERSION: u16 = 0xC612;
const DNG_PRIVATE_DATA: u16 = 0xC634;
const PANASONIC_WIDTH: u16 = 0x0002;
const PANASONIC_LENGTH: u16 = 0x0003;
const PANASONIC_CAMERA_IFD: u16 = 0x0120;
const OLYMPUS_EQUIPMENT_IFD: u16 = 0x2010;
const OLYMPUS_IMAGE_PROCESSING_IFD: u16 = 0x2040;
const OLYMPUS_RAW_INFO: u16 = 0x3000;
const SONY_OFFSET: u16 = 0x7200;
const SONY_LENGTH: u16 = 0x7201;
const SONY_KEY: u16 = 0x7221;
const FUJI_IFD: u16 = 0xF000;
const FUJI_WIDTH: u16 = 0xF001;
const FUJI_HEIGHT: u16 = 0xF002;

/// The sub-IFD tags rawler's `TiffReader::wellknown_sub_ifd_tags` follows
/// from every IFD of a chain.
const WELL_KNOWN_SUB_IFDS: [u16; 4] = [SUB_IFDS, EXIF_IFD, GPS_IFD, ICC_PROFILE];

/// The sub-IFDs that are the file's own TIFF structure (held to the file's
/// end when they are pointed to by LONG offsets); the ICC profile is not
/// an IFD at all, rawler only reads it as one.
const STRUCTURE_SUB_IFDS: [u16; 3] = [SUB_IFDS, EXIF_IFD, GPS_IFD];

/// TIFF type UNDEFINED.
const UNDEFINED: u16 = 7;
/// TIFF type ASCII.
const ASCII: u16 = 2;
/// TIFF type LONG.
const LONG: u16 = 4;

/// An image size a camera file claims: rawler allocates this many samples
/// before it reads one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct ClaimedImage {
    /// Claimed width, in pixels.
    pub(crate) width: u64,
    /// Claimed height, in pixels.
    pub(crate) height: u64,
    /// Claimed samples per pixel (at least 1).
    pub(crate) samples: u64,
}

/// Walks the structures rawler would read in `bytes` and returns the image
/// sizes they claim; or why rawler must not read them (its words for a
/// `Corrupt` error).
///
/// For the bytes `camera_file` hands to rawler: not a JPEG (rigd decodes
/// JPEG itself; rawler's EXIF-JPEG path is refused here, not walked).
pub(crate) fn walk(bytes: &[u8]) -> Result<Vec<ClaimedImage>, String> {
    if u32::try_from(bytes.len()).is_err() {
        return Err(format!(
            "it has {} bytes, and rawler's offsets end at 4 GiB",
            bytes.len()
        ));
    }
    let mut walker = Walker::new(bytes.len());
    match walker.file(bytes) {
        // Where rawler gives up, it reads nothing more: what was walked up
        // to there is all it allocates.
        Ok(()) | Err(Halt::GivesUp) => Ok(walker.claims),
        Err(Halt::Refused(why)) => Err(why),
    }
}

/// Why a walk stopped before its end.
#[derive(Debug)]
enum Halt {
    /// The file is refused: rawler would allocate more than it holds, or
    /// read forever.
    Refused(String),
    /// rawler's own parse fails here (an error, or a panic its caller
    /// catches) before it allocates anything more.
    GivesUp,
}

type Step<T> = Result<T, Halt>;

fn refused<T>(why: String) -> Step<T> {
    Err(Halt::Refused(why))
}

/// A step whose failure rawler ignores, or after which it reads nothing
/// more of that part: a refusal still counts, giving up does not.
fn tolerated<T>(step: Step<T>) -> Step<Option<T>> {
    match step {
        Ok(t) => Ok(Some(t)),
        Err(Halt::GivesUp) => Ok(None),
        Err(refusal) => Err(refusal),
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Endian {
    Little,
    Big,
}

fn bytes_at<const N: usize>(b: &[u8], at: usize) -> Option<[u8; N]> {
    b.get(at..at.checked_add(N)?)?.try_into().ok()
}

fn u16_at(b: &[u8], at: usize, e: Endian) -> Option<u16> {
    let a = bytes_at::<2>(b, at)?;
    Some(match e {
        Endian::Little => u16::from_le_bytes(a),
        Endian::Big => u16::from_be_bytes(a),
    })
}

fn u32_at(b: &[u8], at: usize, e: Endian) -> Option<u32> {
    let a = bytes_at::<4>(b, at)?;
    Some(match e {
        Endian::Little => u32::from_le_bytes(a),
        Endian::Big => u32::from_be_bytes(a),
    })
}

fn u64_at(b: &[u8], at: usize, e: Endian) -> Option<u64> {
    let a = bytes_at::<8>(b, at)?;
    Some(match e {
        Endian::Little => u64::from_le_bytes(a),
        Endian::Big => u64::from_be_bytes(a),
    })
}

fn le32(b: &[u8], at: usize) -> Option<u32> {
    u32_at(b, at, Endian::Little)
}

fn be32(b: &[u8], at: usize) -> Option<u32> {
    u32_at(b, at, Endian::Big)
}

fn be16(b: &[u8], at: usize) -> Option<u16> {
    u16_at(b, at, Endian::Big)
}

/// rawler's `apply_corr`: an offset moved by a correction, truncated to 32
/// bits.
fn apply_corr(offset: u32, corr: i32) -> u32 {
    (i64::from(offset) + i64::from(corr)) as u32
}

/// The bytes rawler allocates for one value of a TIFF type, as
/// `Entry::parse` sizes it: unknown types (0 and above 12) as one byte.
fn value_size(typ: u16) -> u64 {
    match typ {
        3 | 8 => 2,
        4 | 9 | 11 => 4,
        5 | 10 | 12 => 8,
        _ => 1,
    }
}

/// A tag, with its name where the walk's messages are likely to show it.
struct TagName(u16);

impl fmt::Display for TagName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let name = match self.0 {
            0x00FE => "NewSubfileType",
            IMAGE_WIDTH => "ImageWidth",
            IMAGE_LENGTH => "ImageLength",
            0x0102 => "BitsPerSample",
            0x0103 => "Compression",
            0x0106 => "PhotometricInterpretation",
            MAKE => "Make",
            MODEL => "Model",
            0x0111 => "StripOffsets",
            SAMPLES_PER_PIXEL => "SamplesPerPixel",
            0x0116 => "RowsPerStrip",
            0x0117 => "StripByteCounts",
            SOFTWARE => "Software",
            TILE_WIDTH => "TileWidth",
            TILE_LENGTH => "TileLength",
            0x0144 => "TileOffsets",
            0x0145 => "TileByteCounts",
            SUB_IFDS => "SubIFDs",
            0x02BC => "XMP",
            0x828D => "CFARepeatPatternDim",
            0x828E => "CFAPattern",
            EXIF_IFD => "ExifIFD",
            ICC_PROFILE => "ICCProfile",
            GPS_IFD => "GPSInfo",
            MAKER_NOTE => "MakerNote",
            DNG_VERSION => "DNGVersion",
            0xC614 => "UniqueCameraModel",
            0xC61A => "BlackLevel",
            0xC61D => "WhiteLevel",
            0xC621 => "ColorMatrix1",
            DNG_PRIVATE_DATA => "DNGPrivateData",
            0xC68D => "ActiveArea",
            0xC740 => "OpcodeList1",
            0xC741 => "OpcodeList2",
            0xC74E => "OpcodeList3",
            _ => return write!(f, "{:#06x}", self.0),
        };
        write!(f, "{:#06x} ({name})", self.0)
    }
}

/// The bytes a directory is read from, and how messages name them.
#[derive(Clone, Copy)]
struct View<'v> {
    bytes: &'v [u8],
    name: &'static str,
}

/// How an IFD's entries are held to the bytes they are read from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Trust {
    /// The file's own TIFF structure: every entry, value and directory
    /// must lie within the bytes.
    Structure,
    /// A vendor's directory (maker notes, private IFDs, embedded TIFFs of
    /// other containers): only claims larger than the bytes are refused;
    /// rawler skips a value past the end, and so does the walk.
    Vendor,
    /// Bytes that are no IFD, which rawler reads as one (an ICC profile; a
    /// sub-IFD pointer of type UNDEFINED, read at the value itself, or of
    /// an unknown type, read as its first byte): their "counts" are
    /// whatever the bytes hold, even in a perfect file. rawler allocates
    /// them, fails to read them and frees them again, so only a claim
    /// past [`MISREAD_ALLOWANCE`] is refused.
    Misread,
}

/// Where rawler's `IFD::new` reads a directory: at `base + offset` of the
/// view, its entries' value offsets moved by `corr` and counted from `base`.
#[derive(Clone, Copy)]
struct At<'v> {
    view: View<'v>,
    offset: u32,
    base: u32,
    corr: i32,
    endian: Endian,
}

/// One directory entry rawler keeps.
#[derive(Debug, Clone, Copy)]
struct Entry {
    tag: u16,
    typ: u16,
    count: u32,
    /// The value's offset from the directory's base, as rawler keeps it
    /// (`Entry::offset`).
    offset: u32,
    /// Where the value's bytes start in the view.
    at: usize,
    /// How many bytes the value takes.
    len: usize,
}

/// One directory as rawler reads it.
struct Dir<'v> {
    view: View<'v>,
    endian: Endian,
    base: u32,
    corr: i32,
    /// How messages name it ("IFD0", "SubIFD 1 of IFD0", …).
    label: String,
    depth: usize,
    /// The entries rawler keeps, in file order (rawler keeps the last of
    /// two with one tag: [`Dir::get`] does the same).
    entries: Vec<Entry>,
    /// The next IFD's offset as rawler computes it (0: none).
    next: u32,
    /// The sub-IFDs rawler read from this one, with the tag pointing there.
    subs: Vec<(u16, Dir<'v>)>,
}

/// A number as rawler's `Value::get_*` sees it.
enum Number {
    Int(i64),
    Float(f64),
}

impl<'v> Dir<'v> {
    fn get(&self, tag: u16) -> Option<&Entry> {
        self.entries.iter().rev().find(|e| e.tag == tag)
    }

    fn data(&self, e: &Entry) -> Option<&'v [u8]> {
        self.view.bytes.get(e.at..e.at.checked_add(e.len)?)
    }

    /// rawler's `Value::get_data`: the bytes of a BYTE, ASCII, UNDEFINED
    /// or unknown-type value (rawler panics for the others).
    fn raw_data(&self, e: &Entry) -> Option<&'v [u8]> {
        match e.typ {
            1 | ASCII | UNDEFINED => self.data(e),
            t if t == 0 || t > 12 => self.data(e),
            _ => None,
        }
    }

    /// rawler's `Value::as_string`: an ASCII value up to its first NUL.
    fn string(&self, e: &Entry) -> Option<String> {
        if e.typ != ASCII {
            return None;
        }
        let raw = self.data(e)?;
        let end = raw.iter().position(|&c| c == 0).unwrap_or(raw.len());
        let text = raw.get(..end)?;
        Some(
            std::str::from_utf8(text)
                .unwrap_or("!!!INVALID UTF8!!!")
                .to_string(),
        )
    }

    /// Value `i` of a numeric entry (None where rawler's getter fails).
    fn number(&self, e: &Entry, i: usize) -> Option<Number> {
        if i >= e.count as usize {
            return None;
        }
        let b = self.view.bytes;
        let en = self.endian;
        let at = |size: usize| e.at.checked_add(i.checked_mul(size)?);
        let ratio = |n: f32, d: f32| Number::Float(f64::from(n / d));
        Some(match e.typ {
            1 => Number::Int(i64::from(*b.get(at(1)?)?)),
            3 => Number::Int(i64::from(u16_at(b, at(2)?, en)?)),
            4 => Number::Int(i64::from(u32_at(b, at(4)?, en)?)),
            6 => Number::Int(i64::from(*b.get(at(1)?)? as i8)),
            8 => Number::Int(i64::from(u16_at(b, at(2)?, en)? as i16)),
            9 => Number::Int(i64::from(u32_at(b, at(4)?, en)? as i32)),
            5 => {
                let p = at(8)?;
                ratio(
                    u32_at(b, p, en)? as f32,
                    u32_at(b, p.checked_add(4)?, en)? as f32,
                )
            }
            10 => {
                let p = at(8)?;
                ratio(
                    u32_at(b, p, en)? as i32 as f32,
                    u32_at(b, p.checked_add(4)?, en)? as i32 as f32,
                )
            }
            11 => Number::Float(f64::from(f32::from_bits(u32_at(b, at(4)?, en)?))),
            12 => Number::Float(f64::from_bits(u64_at(b, at(8)?, en)?)),
            _ => return None,
        })
    }

    /// rawler's `Value::force_usize`: 0 where the value is missing, of
    /// another kind, or negative.
    fn force_usize(&self, e: &Entry, i: usize) -> u64 {
        match self.number(e, i) {
            Some(Number::Int(v)) => u64::try_from(v).unwrap_or(0),
            Some(Number::Float(v)) => v as usize as u64,
            None => 0,
        }
    }

    /// rawler's `Value::force_u32`.
    fn force_u32(&self, e: &Entry, i: usize) -> u32 {
        match self.number(e, i) {
            Some(Number::Int(v)) => u32::try_from(v).unwrap_or(0),
            Some(Number::Float(v)) => v as u32,
            None => 0,
        }
    }

    /// This directory and every directory below it.
    fn all(&self) -> Vec<&Dir<'v>> {
        let mut out = vec![self];
        for (_, sub) in &self.subs {
            out.extend(sub.all());
        }
        out
    }
}

/// The directories rawler's `TiffReader::find_ifds_with_tag` searches: the
/// chain's IFDs and their direct sub-IFDs.
fn chain_and_subs<'a, 'v>(chain: &'a [Dir<'v>]) -> Vec<&'a Dir<'v>> {
    let mut out = Vec::new();
    for dir in chain {
        out.push(dir);
        out.extend(dir.subs.iter().map(|(_, sub)| sub));
    }
    out
}

/// rawler's `TiffReader::get_entry`: the entry of the first chain IFD that
/// has the tag.
fn first_entry<'a, 'v>(chain: &'a [Dir<'v>], tag: u16) -> Option<(&'a Dir<'v>, &'a Entry)> {
    chain.iter().find_map(|d| d.get(tag).map(|e| (d, e)))
}

/// How rawler's `IFD::parse_makernote` counts a maker note's offsets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum NoteOffsets {
    /// From the enclosing TIFF's base (`OffsetMode::Absolute`).
    Absolute,
    /// From the maker note IFD itself (`OffsetMode::RelativeToIFD`).
    RelativeToIfd,
}

/// The decoder rawler's `get_decoder` picks for a TIFF-based file, as far
/// as it reads more of the file than the TIFF structure.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pick {
    /// DNG, Hasselblad, Mamiya, Leaf MOS, Kodak DCS, or none: nothing more.
    Nothing,
    /// A decoder that reads the EXIF maker note with
    /// `IFD::parse_makernote` (NEF, NRW, PEF, ARW, ERF, KDC, SRW).
    MakerNote(NoteOffsets),
    /// Sony ARW: the maker note, and the encrypted SR2 directory.
    Sony,
    /// Canon CR2: the TIFF again with the Kodak sub-IFD, and the maker
    /// note as a plain IFD.
    Canon,
    /// Olympus ORF: its own maker note reader and its sub-IFDs.
    Olympus,
    /// Kodak DCR: the Kodak IFD.
    KodakDcr,
    /// Panasonic RW2: the CameraIFD, a TIFF of its own.
    Panasonic,
    /// Phase One IIQ: its own maker note format.
    PhaseOne,
}

impl Pick {
    /// rawler's choice in `RawLoader::get_decoder`, from the chain's tags.
    fn of(chain: &[Dir<'_>]) -> Pick {
        if chain.iter().any(|d| d.get(DNG_VERSION).is_some()) {
            return Pick::Nothing;
        }
        if let Some((d, e)) = first_entry(chain, MODEL) {
            if d.string(e).as_deref() == Some("DCS560C") {
                return Pick::Canon;
            }
        }
        let Some(make) = first_entry(chain, MAKE).and_then(|(d, e)| d.string(e)) else {
            // Leaf MOS (by its Software tag) reads nothing more.
            return Pick::Nothing;
        };
        match make.trim_end() {
            "Canon" => Pick::Canon,
            "PENTAX"
            | "PENTAX Corporation"
            | "RICOH IMAGING COMPANY, LTD."
            | "SEIKO EPSON CORP."
            | "EASTMAN KODAK COMPANY"
            | "Eastman Kodak Company"
            | "NIKON"
            | "Nikon"
            | "NIKON CORPORATION" => Pick::MakerNote(NoteOffsets::Absolute),
            "SAMSUNG" => Pick::MakerNote(NoteOffsets::RelativeToIfd),
            "SONY" => Pick::Sony,
            "OLYMPUS IMAGING CORP."
            | "OLYMPUS CORPORATION"
            | "OLYMPUS OPTICAL CO.,LTD"
            | "OM Digital Solutions" => Pick::Olympus,
            "Kodak" => Pick::KodakDcr,
            "Panasonic" | "LEICA" | "LEICA CAMERA AG" => Pick::Panasonic,
            "Phase One" | "Phase One A/S" | "Leaf" => Pick::PhaseOne,
            _ => Pick::Nothing,
        }
    }
}

/// How one entry came out of rawler's `Entry::parse`.
enum Parsed {
    /// Read and kept.
    Kept(Entry),
    /// Failed after its fields were read; rawler's reader is at `cursor`.
    Skipped { cursor: usize },
    /// The entry's own fields run past the end: rawler stops the IFD.
    Truncated,
}

/// The walk's bounds and findings.
struct Walker {
    file_len: usize,
    directories: usize,
    entries: usize,
    value_bytes: u64,
    boxes: usize,
    ciff_copied: u64,
    claims: Vec<ClaimedImage>,
}

impl Walker {
    fn new(file_len: usize) -> Walker {
        Walker {
            file_len,
            directories: 0,
            entries: 0,
            value_bytes: 0,
            boxes: 0,
            ciff_copied: 0,
            claims: Vec::new(),
        }
    }

    fn claim(&mut self, width: u64, height: u64, samples: u64) {
        self.claims.push(ClaimedImage {
            width,
            height,
            samples: samples.max(1),
        });
    }

    /// rawler's `RawLoader::get_decoder`: which reader the first bytes
    /// select, in its order.
    fn file(&mut self, b: &[u8]) -> Step<()> {
        let file = View {
            bytes: b,
            name: "the file",
        };
        if b.starts_with(b"\0MRM") {
            return self.mrw(file);
        }
        if b.get(0..8) == Some(b"FUJIFILM") {
            return self.raf(file);
        }
        if b.starts_with(b"ARRI") {
            // `AriDecoder::raw_image`: width and height in the header.
            if let (Some(w), Some(h)) = (le32(b, 0x14), le32(b, 0x18)) {
                self.claim(w.into(), h.into(), 1);
            }
            return Ok(());
        }
        if b.starts_with(b"qktk") || b.starts_with(b"qktn") {
            // `QtkDecoder::raw_image`: height and width at byte 544.
            if let (Some(h), Some(w)) = (be16(b, 544), be16(b, 546)) {
                self.claim(w.into(), h.into(), 1);
            }
            return Ok(());
        }
        if b.get(6..14) == Some(b"HEAPCCDR") {
            return self.ciff(b);
        }
        if b.starts_with(&[0xFF, 0xD8, 0xFF, 0xE1]) {
            return refused(
                "an EXIF JPEG is not for rawler (rigd decodes JPEG itself)".to_string(),
            );
        }
        if b.starts_with(b"FOVb") {
            return self.x3f(file);
        }
        // rawler tries every other file as ISO-BMFF first.
        if let Some(Some(cr3)) = tolerated(self.bmff(b))? {
            // rawler picks the CR3 decoder and reads no TIFF.
            return self.cr3(b, cr3);
        }
        self.main_tiff(file)
    }

    // ----- TIFF -----

    /// rawler's `IFD::new`: one directory at `at`, the sub-IFDs its
    /// `sub_tags` point to (read with no sub tags of their own), and the
    /// offset of the next.
    fn ifd<'v>(
        &mut self,
        at: At<'v>,
        sub_tags: &[u16],
        trust: Trust,
        label: String,
        depth: usize,
    ) -> Step<Dir<'v>> {
        let View { bytes, name } = at.view;
        let len = bytes.len();
        if depth > MAX_NESTING {
            return refused(format!(
                "{label} is nested more than {MAX_NESTING} directories deep"
            ));
        }
        self.directories += 1;
        if self.directories > MAX_DIRECTORIES {
            return refused(format!(
                "it has more than {MAX_DIRECTORIES} directories (IFDs) for rawler to read"
            ));
        }
        let Some(start) = at.base.checked_add(at.offset) else {
            return refused(format!(
                "{label} is at offset {} + {}, beyond 4 GiB",
                at.base, at.offset
            ));
        };
        let start = start as usize;
        let Some(count) = u16_at(bytes, start, at.endian) else {
            return match trust {
                Trust::Structure => refused(format!(
                    "{label} is at offset {start}, past the end of {name} ({len} bytes)"
                )),
                Trust::Vendor | Trust::Misread => Err(Halt::GivesUp),
            };
        };
        let mut entries = Vec::new();
        let mut errors = 0;
        // Where rawler's reader is when it reads the next IFD's offset.
        let mut cursor = start + 2;
        for i in 0..count.min(RAWLER_MAX_IFD_ENTRIES) {
            let entry_at = start + 2 + 12 * usize::from(i);
            match self.entry(at, entry_at, &label, trust)? {
                Parsed::Kept(e) => {
                    errors = 0;
                    cursor = entry_at + 12;
                    entries.push(e);
                }
                Parsed::Skipped { cursor: c } => {
                    errors += 1;
                    cursor = c;
                    if errors >= RAWLER_MAX_ENTRY_ERRORS {
                        break;
                    }
                }
                Parsed::Truncated => {
                    if trust == Trust::Structure {
                        return refused(format!(
                            "{label} lists {count} entries, but {name} ({len} bytes) ends within entry {i}"
                        ));
                    }
                    // A failed read leaves rawler's cursor at the end.
                    cursor = len;
                    break;
                }
            }
        }
        let next = match u32_at(bytes, cursor, at.endian) {
            None | Some(0) => 0,
            Some(n) => apply_corr(n, at.corr),
        };
        let mut dir = Dir {
            view: at.view,
            endian: at.endian,
            base: at.base,
            corr: at.corr,
            label,
            depth,
            entries,
            next,
            subs: Vec::new(),
        };
        let pointers: Vec<Entry> = dir
            .entries
            .iter()
            .filter(|e| sub_tags.contains(&e.tag))
            .copied()
            .collect();
        for e in pointers {
            self.sub_ifds(&mut dir, &e, trust)?;
        }
        Ok(dir)
    }

    /// rawler's `Entry::parse` of the entry at `entry_at`.
    fn entry(&mut self, at: At<'_>, entry_at: usize, label: &str, trust: Trust) -> Step<Parsed> {
        let View { bytes, name } = at.view;
        let len = bytes.len();
        let en = at.endian;
        let (Some(tag), Some(typ), Some(count)) = (
            u16_at(bytes, entry_at, en),
            u16_at(bytes, entry_at + 2, en),
            u32_at(bytes, entry_at + 4, en),
        ) else {
            return Ok(Parsed::Truncated);
        };
        let size = value_size(typ);
        let claimed = u64::from(count) * size;
        let value_field = entry_at + 8;
        let offset = if claimed <= 4 {
            // The value is in the entry: rawler's `position() - base`.
            (value_field as u32).wrapping_sub(at.base)
        } else {
            let Some(raw) = u32_at(bytes, value_field, en) else {
                return Ok(Parsed::Truncated);
            };
            apply_corr(raw, at.corr)
        };
        let t = TagName(tag);
        let Some(value_at) = at.base.checked_add(offset).filter(|_| offset != u32::MAX) else {
            // rawler skips the entry before it allocates.
            return match trust {
                Trust::Structure => refused(format!(
                    "tag {t} of {label} puts its value at offset {offset} from {}, beyond 4 GiB",
                    at.base
                )),
                Trust::Vendor | Trust::Misread => Ok(Parsed::Skipped {
                    cursor: entry_at + 12,
                }),
            };
        };
        // Here rawler allocates `count` values, before it reads one.
        let allowed = match trust {
            Trust::Structure | Trust::Vendor => len as u64,
            Trust::Misread => MISREAD_ALLOWANCE.max(len as u64),
        };
        if claimed > allowed {
            let unit = if size == 1 { "byte" } else { "bytes" };
            return refused(format!(
                "tag {t} of {label} claims {count} values of {size} {unit} each ({claimed} bytes), \
                 but {name} has only {len} bytes"
            ));
        }
        let value_at = value_at as usize;
        if value_at
            .checked_add(claimed as usize)
            .is_none_or(|end| end > len)
        {
            return match trust {
                Trust::Structure => refused(format!(
                    "tag {t} of {label} puts its {count} values ({claimed} bytes) at offset \
                     {value_at}, past the end of {name} ({len} bytes)"
                )),
                // The read fails, rawler frees the values, and its cursor
                // is left at the end.
                Trust::Vendor | Trust::Misread => Ok(Parsed::Skipped { cursor: len }),
            };
        }
        // rawler keeps the values it read.
        self.value_bytes += claimed;
        let budget = VALUE_BYTES_PER_FILE_BYTE * self.file_len as u64;
        if self.value_bytes > budget {
            return refused(format!(
                "its directories hold more than {budget} bytes of values for rawler to keep \
                 ({VALUE_BYTES_PER_FILE_BYTE} times its {} bytes)",
                self.file_len
            ));
        }
        let claimed = claimed as usize;
        self.entries += 1;
        if self.entries > MAX_ENTRIES {
            return refused(format!(
                "it has more than {MAX_ENTRIES} directory entries for rawler to read"
            ));
        }
        Ok(Parsed::Kept(Entry {
            tag,
            typ,
            count,
            offset,
            at: value_at,
            len: claimed,
        }))
    }

    /// The sub-IFDs rawler's `IFD::new` reads from a pointer entry: every
    /// offset of a LONG value, the value's own offset for UNDEFINED, the
    /// first byte for an unknown type; other types are ignored. A sub-IFD
    /// rawler cannot read it skips.
    fn sub_ifds<'v>(&mut self, dir: &mut Dir<'v>, e: &Entry, trust: Trust) -> Step<()> {
        let (view, endian, base, corr, depth) =
            (dir.view, dir.endian, dir.base, dir.corr, dir.depth);
        let sub_trust = match (trust, e.typ) {
            _ if e.tag == ICC_PROFILE || e.typ != LONG => Trust::Misread,
            (Trust::Structure, _) if STRUCTURE_SUB_IFDS.contains(&e.tag) => Trust::Structure,
            (Trust::Misread, _) => Trust::Misread,
            _ => Trust::Vendor,
        };
        let (value_at, count) = (e.at, e.count as usize);
        let offsets: Box<dyn Iterator<Item = Option<u32>>> = match e.typ {
            LONG => Box::new((0..count).map(move |i| {
                u32_at(view.bytes, value_at.checked_add(i.checked_mul(4)?)?, endian)
            })),
            UNDEFINED => Box::new(std::iter::once(Some(e.offset))),
            t if (t == 0 || t > 12) && count > 0 => Box::new(std::iter::once(
                view.bytes.get(value_at).map(|&first| u32::from(first)),
            )),
            _ => Box::new(std::iter::empty()),
        };
        for (k, offset) in offsets.enumerate() {
            let Some(offset) = offset else { break };
            let label = sub_label(e.tag, k, &dir.label);
            let at = At {
                view,
                offset: apply_corr(offset, corr),
                base,
                corr,
                endian,
            };
            if let Some(sub) = tolerated(self.ifd(at, &[], sub_trust, label, depth + 1))? {
                dir.subs.push((e.tag, sub));
            }
        }
        Ok(())
    }

    /// rawler's `TiffReader::parse_file` (what `GenericTiffReader::new`
    /// runs): the header at `base`, then the IFD chain, each IFD with the
    /// well-known sub-IFD tags and `extra_sub_tags`; at most
    /// `max_chained + 1` IFDs, or the whole chain.
    fn tiff_file<'v>(
        &mut self,
        view: View<'v>,
        max_chained: Option<usize>,
        extra_sub_tags: &[u16],
        trust: Trust,
        whose: &str,
    ) -> Step<Vec<Dir<'v>>> {
        let b = view.bytes;
        let endian = match u16_at(b, 0, Endian::Little) {
            Some(0x4949) => Endian::Little,
            Some(0x4d4d) => Endian::Big,
            _ => return Err(Halt::GivesUp),
        };
        // TIFF, Panasonic RW2 ("IIU\0"), Olympus ORF ("IIRS", "IIRO", "MMOR").
        match u16_at(b, 2, endian) {
            Some(42 | 85 | 21330 | 20306) => {}
            _ => return Err(Halt::GivesUp),
        }
        let first = u32_at(b, 4, endian).ok_or(Halt::GivesUp)?;
        if first == 0 {
            return Err(Halt::GivesUp);
        }
        let sub_tags: Vec<u16> = WELL_KNOWN_SUB_IFDS
            .iter()
            .chain(extra_sub_tags)
            .copied()
            .collect();
        let mut chain: Vec<Dir<'v>> = Vec::new();
        let mut seen = BTreeSet::new();
        let mut next = first;
        while next != 0 {
            if max_chained.is_none() && !seen.insert(next) {
                // rawler follows it for ever, keeping every IFD.
                return refused(format!("the IFD chain{whose} loops back to offset {next}"));
            }
            let at = At {
                view,
                offset: next,
                base: 0,
                corr: 0,
                endian,
            };
            let label = format!("IFD{}{whose}", chain.len());
            let dir = self.ifd(at, &sub_tags, trust, label, 0)?;
            if dir.entries.is_empty() {
                return Err(Halt::GivesUp);
            }
            next = dir.next;
            chain.push(dir);
            if max_chained.is_some_and(|max| chain.len() > max) {
                break;
            }
        }
        Ok(chain)
    }

    /// rawler's `IFD::new_root_with_correction` (at offset 0 from `base`,
    /// as every caller uses it): a TIFF header (magic 42 only) at `base`,
    /// its root IFD and up to `max_chain` more.
    fn tiff_root<'v>(
        &mut self,
        view: View<'v>,
        base: u32,
        max_chain: usize,
        sub_tags: &[u16],
        trust: Trust,
        whose: &str,
    ) -> Step<Vec<Dir<'v>>> {
        let b = view.bytes;
        let header = base as usize;
        let endian = match u16_at(b, header, Endian::Little) {
            Some(0x4949) => Endian::Little,
            Some(0x4d4d) => Endian::Big,
            _ => return Err(Halt::GivesUp),
        };
        if u16_at(b, header + 2, endian) != Some(42) {
            return Err(Halt::GivesUp);
        }
        let first = u32_at(b, header + 4, endian).ok_or(Halt::GivesUp)?;
        if first == 0 {
            return Err(Halt::GivesUp);
        }
        let mut chain: Vec<Dir<'v>> = Vec::new();
        let mut seen = BTreeSet::new();
        // rawler corrects the root's offset, and each next offset twice
        // (once in `IFD::new`, once in its loop); the correction is 0 for
        // every caller.
        let mut next = first;
        loop {
            if max_chain == 0 && !seen.insert(next) {
                return refused(format!("the IFD chain{whose} loops back to offset {next}"));
            }
            let at = At {
                view,
                offset: next,
                base,
                corr: 0,
                endian,
            };
            let label = format!("IFD{}{whose}", chain.len());
            let dir = self.ifd(at, sub_tags, trust, label, 0)?;
            if dir.entries.is_empty() {
                return Err(Halt::GivesUp);
            }
            next = dir.next;
            chain.push(dir);
            if next == 0 || (max_chain > 0 && chain.len() - 1 > max_chain) {
                break;
            }
        }
        Ok(chain)
    }

    /// The image sizes TIFF directories claim: `ImageWidth` ×
    /// `ImageLength` × `SamplesPerPixel`, and for a tiled image the whole
    /// tiles rawler's `decode_tiles` allocates.
    fn claim_tiff_sizes(&mut self, dirs: &[&Dir<'_>]) {
        for dir in dirs {
            if let Some(w) = dir.get(IMAGE_WIDTH) {
                let value = |tag| dir.get(tag).map_or(0, |e| dir.force_usize(e, 0));
                let (w, h) = (dir.force_usize(w, 0), value(IMAGE_LENGTH));
                let samples = value(SAMPLES_PER_PIXEL);
                self.claim(w, h, samples);
                let (tw, tl) = (value(TILE_WIDTH), value(TILE_LENGTH));
                if tw > 0 && tl > 0 {
                    // `((width - 1) / tile_width + 1) * tile_width`, wrapping
                    // as a release build does.
                    let whole = |side: u64, tile: u64| {
                        (side.wrapping_sub(1) / tile)
                            .wrapping_add(1)
                            .wrapping_mul(tile)
                    };
                    self.claim(whole(w, tw), whole(h, tl), samples);
                }
            }
        }
    }

    /// A TIFF-based file (DNG, NEF, CR2, ARW, ORF, RW2, PEF, …, or a
    /// rendered TIFF): what `GenericTiffReader::new` reads in
    /// `get_decoder`, then what the decoder it picks reads.
    fn main_tiff(&mut self, file: View<'_>) -> Step<()> {
        let chain = self.tiff_file(file, None, &[], Trust::Structure, "")?;
        self.claim_tiff_sizes(&chain_and_subs(&chain));
        match Pick::of(&chain) {
            Pick::Nothing => Ok(()),
            Pick::MakerNote(offsets) => self.maker_notes(&chain, offsets),
            Pick::Sony => {
                self.maker_notes(&chain, NoteOffsets::Absolute)?;
                tolerated(self.sony_sr2(&chain, file)).map(drop)
            }
            Pick::Canon => self.canon(file),
            Pick::Olympus => {
                for exif in chain_and_subs(&chain) {
                    tolerated(self.olympus_maker_note(exif))?;
                }
                Ok(())
            }
            Pick::KodakDcr => {
                // `DcrDecoder::new`: the IFD the Kodak tag points to.
                let Some((d, e)) = first_entry(&chain, KODAK_IFD) else {
                    return Ok(());
                };
                let at = At {
                    view: file,
                    offset: d.force_u32(e, 0),
                    base: 0,
                    corr: 0,
                    endian: chain.first().map_or(Endian::Little, |root| root.endian),
                };
                let label = "the Kodak IFD".to_string();
                tolerated(self.ifd(at, &[], Trust::Vendor, label, 1)).map(drop)
            }
            Pick::Panasonic => self.panasonic(&chain),
            Pick::PhaseOne => self.phase_one(file.bytes),
        }
    }

    /// The maker notes `IFD::parse_makernote` reads: rawler takes the first
    /// IFD with a MakerNote tag (from a hash map, so in no fixed order);
    /// the walk reads them all.
    fn maker_notes(&mut self, chain: &[Dir<'_>], offsets: NoteOffsets) -> Step<()> {
        for exif in chain_and_subs(chain) {
            tolerated(self.maker_note(exif, offsets))?;
        }
        Ok(())
    }

    /// rawler's `IFD::parse_makernote`: the maker note of `exif` as an IFD,
    /// after the vendor header it recognises.
    fn maker_note(&mut self, exif: &Dir<'_>, offsets: NoteOffsets) -> Step<()> {
        let Some(e) = exif.get(MAKER_NOTE) else {
            return Ok(());
        };
        if e.typ != UNDEFINED {
            return Ok(());
        }
        let Some(data) = exif.data(e) else {
            return Ok(());
        };
        let label = format!("the maker note IFD of {}", exif.label);
        // rawler compares fixed prefixes by slicing: a shorter note panics
        // (caught), and nothing more is read.
        let is = |range: Range<usize>, with: &[u8]| -> Step<bool> {
            data.get(range).map(|d| d == with).ok_or(Halt::GivesUp)
        };
        let overflow = || Halt::Refused(format!("{label} is beyond 4 GiB"));
        let mut off: usize = 0;
        let mut endian = exif.endian;
        if is(0..5, b"OLYMP")? {
            off += 8;
            if is(0..7, b"OLYMPUS")? {
                off += 4;
            }
        }
        if is(0..5, b"EPSON")? {
            off += 8;
        }
        if is(0..8, b"FUJIFILM")? {
            off += 12;
        }
        if is(0..9, b"SONY DSC ")? {
            off += 12;
        }
        if is(0..4, b"AOC\0")? {
            off += 4;
        }
        let order = |off: usize| -> Step<Endian> {
            Ok(if is(off..off + 2, b"II")? {
                Endian::Little
            } else {
                Endian::Big
            })
        };
        let at = if is(0..6, b"PENTAX")? {
            off += 8;
            // Offsets count from the maker note; the IFD starts 10 bytes in.
            At {
                view: exif.view,
                offset: e.offset.checked_add(10).ok_or_else(overflow)?,
                base: exif.base,
                corr: e.offset as i32,
                endian: order(off)?,
            }
        } else if is(0..7, b"Nikon\0\x02")? {
            off += 10;
            // A TIFF of its own 10 bytes in; its first IFD at 8.
            let base = exif
                .base
                .checked_add(e.offset)
                .and_then(|b| b.checked_add(10));
            At {
                view: exif.view,
                offset: 8,
                base: base.ok_or_else(overflow)?,
                corr: 0,
                endian: order(off)?,
            }
        } else {
            if is(off..off + 2, b"II")? {
                off += 2;
                endian = Endian::Little;
            }
            if is(off..off + 2, b"MM")? {
                off += 2;
                endian = Endian::Big;
            }
            let offset = u32::try_from(off)
                .ok()
                .and_then(|off| e.offset.checked_add(off))
                .ok_or_else(overflow)?;
            At {
                view: exif.view,
                offset,
                base: exif.base,
                corr: match offsets {
                    NoteOffsets::Absolute => exif.corr,
                    NoteOffsets::RelativeToIfd => offset as i32,
                },
                endian,
            }
        };
        self.ifd(at, &[], Trust::Vendor, label, exif.depth + 1)
            .map(drop)
    }

    /// Canon CR2 (`Cr2Decoder::new`): the TIFF read again with the Kodak
    /// sub-IFD tag, and the maker note of the root's EXIF IFD (or the
    /// root's own) read as a plain IFD at its offset.
    fn canon(&mut self, file: View<'_>) -> Step<()> {
        let chain = self.tiff_file(file, None, &[CR2_KODAK_SUB_IFD], Trust::Structure, "")?;
        let Some(root) = chain.first() else {
            return Ok(());
        };
        let exifs = root
            .subs
            .iter()
            .filter(|(tag, _)| *tag == EXIF_IFD)
            .map(|(_, d)| d)
            .chain(std::iter::once(root));
        for exif in exifs {
            if let Some(e) = exif.get(MAKER_NOTE) {
                let at = At {
                    view: file,
                    offset: e.offset,
                    base: 0,
                    corr: 0,
                    endian: exif.endian,
                };
                let label = format!("the maker note IFD of {}", exif.label);
                tolerated(self.ifd(at, &[], Trust::Vendor, label, exif.depth + 1))?;
            }
        }
        Ok(())
    }

    /// Olympus ORF (`orf::parse_makernote`): the maker note IFD after the
    /// OLYMPUS or OM SYSTEM header, and its equipment and image processing
    /// IFDs, counted from the maker note.
    fn olympus_maker_note(&mut self, exif: &Dir<'_>) -> Step<()> {
        let Some(e) = exif.get(MAKER_NOTE) else {
            return Ok(());
        };
        if e.typ != UNDEFINED {
            return Ok(());
        }
        let Some(data) = exif.data(e) else {
            return Ok(());
        };
        let is = |range: Range<usize>, with: &[u8]| -> Step<bool> {
            data.get(range).map(|d| d == with).ok_or(Halt::GivesUp)
        };
        let mut off: u32 = 0;
        if is(0..5, b"OLYMP")? {
            off += 8;
            if is(0..7, b"OLYMPUS")? {
                off += 4;
            }
        }
        if is(0..9, b"OM SYSTEM")? {
            off += 16;
            // rawler asserts the byte order mark.
            if !is(12..14, b"II")? {
                return Err(Halt::GivesUp);
            }
        }
        let label = format!("the maker note IFD of {}", exif.label);
        let Some(offset) = e.offset.checked_add(off) else {
            return refused(format!("{label} is beyond 4 GiB"));
        };
        let at = At {
            view: exif.view,
            offset,
            base: exif.base,
            corr: exif.corr,
            endian: exif.endian,
        };
        let note = self.ifd(
            at,
            &[OLYMPUS_RAW_INFO],
            Trust::Vendor,
            label,
            exif.depth + 1,
        )?;
        let mut inner = vec![OLYMPUS_EQUIPMENT_IFD];
        if off == 12 || off == 16 {
            inner.push(OLYMPUS_IMAGE_PROCESSING_IFD);
        }
        for tag in inner {
            let Some(p) = note.get(tag) else { continue };
            // `get_entry_raw_with_len(tag, 4)`: four bytes at the value.
            let Some(pos) = note.base.checked_add(p.offset) else {
                return refused(format!(
                    "tag {} of {} is beyond 4 GiB",
                    TagName(tag),
                    note.label
                ));
            };
            let ioff = u32_at(exif.view.bytes, pos as usize, note.endian).ok_or(Halt::GivesUp)?;
            if tag == OLYMPUS_IMAGE_PROCESSING_IFD && ioff == 0 {
                continue;
            }
            let at = At {
                view: exif.view,
                offset: ioff,
                base: e.offset,
                corr: 0,
                endian: exif.endian,
            };
            let label = format!("the IFD tag {} of {} points to", TagName(tag), note.label);
            self.ifd(at, &[], Trust::Vendor, label, note.depth + 1)?;
        }
        Ok(())
    }

    /// Sony ARW (`ArwDecoder::get_params`): the private IFD the
    /// DNGPrivateData tag points to, and the SR2 IFD in the block it
    /// encrypts.
    fn sony_sr2(&mut self, chain: &[Dir<'_>], file: View<'_>) -> Step<()> {
        let Some((d, e)) = first_entry(chain, DNG_PRIVATE_DATA) else {
            return Ok(());
        };
        let offset = d
            .raw_data(e)
            .and_then(|data| le32(data, 0))
            .ok_or(Halt::GivesUp)?;
        let at = At {
            view: file,
            offset,
            base: 0,
            corr: 0,
            endian: Endian::Little,
        };
        let label = "Sony's private IFD".to_string();
        let private = self.ifd(at, &[], Trust::Vendor, label, 1)?;
        let field = |tag| private.get(tag).ok_or(Halt::GivesUp);
        let sony_offset = private.force_u32(field(SONY_OFFSET)?, 0);
        let sony_length = private.force_usize(field(SONY_LENGTH)?, 0);
        let key = private
            .raw_data(field(SONY_KEY)?)
            .and_then(|data| le32(data, 0))
            .ok_or(Halt::GivesUp)?;
        let sony_length = usize::try_from(sony_length).map_err(|_| Halt::GivesUp)?;
        let decrypted = sony_decrypt(file.bytes, sony_offset as usize, sony_length, key)
            .ok_or(Halt::GivesUp)?;
        let at = At {
            view: View {
                bytes: &decrypted,
                name: "Sony's decrypted SR2 block",
            },
            offset: 0,
            base: 0,
            corr: (sony_offset as i32).wrapping_neg(),
            endian: Endian::Little,
        };
        self.ifd(at, &[], Trust::Vendor, "Sony's SR2 IFD".to_string(), 2)
            .map(drop)
    }

    /// Panasonic RW2 (`Rw2Decoder::new`): the sensor size it allocates
    /// from, and the CameraIFD, a TIFF inside a tag's value.
    fn panasonic(&mut self, chain: &[Dir<'_>]) -> Step<()> {
        for dir in chain_and_subs(chain) {
            if let (Some(w), Some(h)) = (dir.get(PANASONIC_WIDTH), dir.get(PANASONIC_LENGTH)) {
                let (w, h) = (dir.force_usize(w, 0), dir.force_usize(h, 0));
                self.claim(w, h, 1);
            }
        }
        let Some((d, e)) = first_entry(chain, PANASONIC_CAMERA_IFD) else {
            return Ok(());
        };
        let Some(data) = d.raw_data(e) else {
            return Ok(());
        };
        let view = View {
            bytes: data,
            name: "Panasonic's CameraIFD block",
        };
        let sub_tags = [SUB_IFDS, EXIF_IFD];
        let whose = " of Panasonic's CameraIFD block";
        tolerated(self.tiff_root(view, 0, 10, &sub_tags, Trust::Vendor, whose)).map(drop)
    }

    /// Phase One IIQ (`iiq::new_makernote`): its own directory of 16-byte
    /// entries, right after the TIFF header.
    fn phase_one(&mut self, b: &[u8]) -> Step<()> {
        const START: usize = 8;
        let dir = le32(b, START + 8).ok_or(Halt::GivesUp)? as usize;
        let table = START + dir;
        let count = le32(b, table).ok_or(Halt::GivesUp)? as u64;
        le32(b, table + 4).ok_or(Halt::GivesUp)?;
        let len = self.file_len as u64;
        if count * 16 > len {
            return refused(format!(
                "its Phase One maker notes claim {count} entries ({} bytes), but the file has only {len} bytes",
                count * 16
            ));
        }
        let rows = b.get(table + 8..).ok_or(Halt::GivesUp)?;
        for row in rows.chunks_exact(16).take(count as usize) {
            let (Some(tag), Some(size)) = (le32(row, 0), le32(row, 8)) else {
                return Err(Halt::GivesUp);
            };
            // rawler allocates the size of strings and of the black level
            // columns and rows it reads.
            if u64::from(size) > len {
                return refused(format!(
                    "Phase One maker note tag {tag:#x} claims {size} bytes, but the file has only {len} bytes"
                ));
            }
        }
        Ok(())
    }

    // ----- Fujifilm RAF -----

    /// Fujifilm RAF (`raf::parse_raf`, `RafDecoder`): the embedded TIFF,
    /// the Fuji TIFF, the RAF directory, the maker notes.
    fn raf(&mut self, file: View<'_>) -> Step<()> {
        let b = file.bytes;
        let main_at = be32(b, 84).ok_or(Halt::GivesUp)?;
        let main = self.tiff_root(
            file,
            main_at.wrapping_add(12),
            10,
            &[SUB_IFDS, EXIF_IFD],
            Trust::Vendor,
            " of the RAF's TIFF",
        )?;
        let fuji_at = be32(b, 100).ok_or(Halt::GivesUp)?;
        let fuji = tolerated(self.tiff_root(
            file,
            fuji_at,
            10,
            &[FUJI_IFD],
            Trust::Vendor,
            " of the RAF's Fuji TIFF",
        ))?
        .unwrap_or_default();
        let raf_at = be32(b, 92).ok_or(Halt::GivesUp)?;
        for dir in fuji.iter().flat_map(|d| d.all()) {
            if let (Some(w), Some(h)) = (dir.get(FUJI_WIDTH), dir.get(FUJI_HEIGHT)) {
                let (w, h) = (dir.force_usize(w, 0), dir.force_usize(h, 0));
                self.claim(w, h, 1);
            }
        }
        if let Some((w, h)) = raf_directory_size(b, raf_at as usize) {
            self.claim(w, h, 1);
        }
        let dirs: Vec<&Dir<'_>> = main.iter().chain(&fuji).flat_map(|d| d.all()).collect();
        for exif in dirs {
            tolerated(self.maker_note(exif, NoteOffsets::Absolute))?;
        }
        Ok(())
    }

    // ----- Minolta MRW -----

    /// Minolta MRW (`MrwDecoder::new_mrw`): its blocks, the sensor size,
    /// and the IFD of its TTW block.
    fn mrw(&mut self, file: View<'_>) -> Step<()> {
        let b = file.bytes;
        let data_offset = be32(b, 4).ok_or(Halt::GivesUp)?.wrapping_add(8) as usize;
        let mut at: usize = 8;
        let mut tiff_at = 0;
        let mut size = None;
        while at + 20 < data_offset {
            let tag = be32(b, at).ok_or(Halt::GivesUp)?;
            let len = be32(b, at + 4).ok_or(Halt::GivesUp)?;
            match tag {
                0x505244 => {
                    let h = be16(b, at + 16).ok_or(Halt::GivesUp)?;
                    let w = be16(b, at + 18).ok_or(Halt::GivesUp)?;
                    b.get(at + 24).ok_or(Halt::GivesUp)?;
                    size = Some((w, h));
                }
                0x574247 => {
                    be16(b, at + 12 + 6).ok_or(Halt::GivesUp)?;
                }
                0x545457 => tiff_at = at + 8,
                _ => {}
            }
            let step = len.wrapping_add(8);
            if step == 0 {
                return refused(format!(
                    "its MRW block at offset {at} has length {len}: rawler would read it for ever"
                ));
            }
            at += step as usize;
        }
        let view = View {
            bytes: b.get(tiff_at..).ok_or(Halt::GivesUp)?,
            name: "the MRW TTW block",
        };
        let at = At {
            view,
            offset: 8,
            base: 0,
            corr: 0,
            endian: Endian::Big,
        };
        self.ifd(at, &[], Trust::Vendor, "the MRW TTW IFD".to_string(), 0)?;
        if let Some((w, h)) = size {
            self.claim(w.into(), h.into(), 1);
        }
        Ok(())
    }

    // ----- Sigma X3F -----

    /// Sigma X3F (`X3fFile::new`, `X3fDecoder::raw_image`): its directory,
    /// the EXIF IFD of the camera info, the image sizes.
    fn x3f(&mut self, file: View<'_>) -> Step<()> {
        let b = file.bytes;
        let dir_at =
            le32(b, b.len().checked_sub(4).ok_or(Halt::GivesUp)?).ok_or(Halt::GivesUp)? as usize;
        let data = b.get(dir_at..).ok_or(Halt::GivesUp)?;
        if le32(data, 4).ok_or(Halt::GivesUp)? < 0x0002_0000 {
            return Err(Halt::GivesUp);
        }
        let count = le32(data, 8).ok_or(Halt::GivesUp)? as usize;
        // (type, format, width, height, data offset) of each IMA2 image.
        let mut images = Vec::new();
        for i in 0..count {
            let row = data.get(12 + i * 12..).ok_or(Halt::GivesUp)?;
            let at = le32(row, 0).ok_or(Halt::GivesUp)? as usize;
            le32(row, 4).ok_or(Halt::GivesUp)?;
            if row.get(8..12).ok_or(Halt::GivesUp)? == b"IMA2" {
                let image = b.get(at..).ok_or(Halt::GivesUp)?;
                le32(image, 24).ok_or(Halt::GivesUp)?;
                let field = |k| le32(image, k).unwrap_or(0);
                images.push((field(8), field(12), field(16), field(20), at + 28));
            }
        }
        let Some(&(_, _, _, _, info_at)) = images.iter().find(|i| i.0 == 2 && i.1 == 0x12) else {
            return Ok(());
        };
        if b.get(info_at + 6..).and_then(|d| d.get(0..4)) != Some(b"Exif") {
            return Ok(());
        }
        let at = At {
            view: file,
            offset: (info_at + 12) as u32,
            base: 0,
            corr: 0,
            endian: Endian::Little,
        };
        self.ifd(at, &[], Trust::Vendor, "the X3F EXIF IFD".to_string(), 0)?;
        if let Some(&(_, _, w, h, _)) = images.iter().find(|i| i.0 == 1 || i.0 == 3) {
            self.claim(w.into(), h.into(), 3);
        }
        Ok(())
    }

    // ----- Canon CRW (CIFF) -----

    /// Canon CRW (`CiffIFD::new_file`): its heaps, each entry's data
    /// copied, sub-heaps up to ten deep.
    fn ciff(&mut self, b: &[u8]) -> Step<()> {
        let start = le32(b, 2).ok_or(Halt::GivesUp)? as usize;
        match self.ciff_heap(b, start, b.len(), 1) {
            Ok(()) | Err(CiffStop::DirError) | Err(CiffStop::Halt(Halt::GivesUp)) => Ok(()),
            Err(CiffStop::Halt(refusal)) => Err(refusal),
        }
    }

    /// rawler's `CiffIFD::new`: the heap between `start` and `end`.
    fn ciff_heap(
        &mut self,
        b: &[u8],
        start: usize,
        end: usize,
        depth: u32,
    ) -> Result<(), CiffStop> {
        let gives_up = CiffStop::Halt(Halt::GivesUp);
        let values = le32(b, end.checked_sub(4).ok_or(gives_up)?)
            .ok_or(CiffStop::Halt(Halt::GivesUp))? as usize;
        let table = start + values;
        let count = u16_at(b, table, Endian::Little).ok_or(CiffStop::Halt(Halt::GivesUp))?;
        for i in 0..usize::from(count) {
            let at = table + 2 + i * 10;
            let p = u16_at(b, at, Endian::Little).ok_or(CiffStop::Halt(Halt::GivesUp))?;
            let (size, data_at) = match p & 0xc000 {
                0x0000 => {
                    let size = le32(b, at + 2).ok_or(CiffStop::Halt(Halt::GivesUp))?;
                    let offset = le32(b, at + 6).ok_or(CiffStop::Halt(Halt::GivesUp))?;
                    (size as usize, offset as usize + start)
                }
                0x4000 => (8, at + 2),
                _ => return Err(CiffStop::DirError),
            };
            if data_at.checked_add(size).is_none_or(|e| e > b.len()) {
                return Err(CiffStop::Halt(Halt::GivesUp));
            }
            self.entries += 1;
            self.ciff_copied += size as u64;
            let budget = CIFF_COPY_PER_FILE_BYTE * self.file_len as u64;
            if self.entries > MAX_ENTRIES || self.ciff_copied > budget {
                return Err(CiffStop::Halt(Halt::Refused(format!(
                    "its CRW heaps make rawler copy more than {budget} bytes \
                     ({CIFF_COPY_PER_FILE_BYTE} times the file) or read more than {MAX_ENTRIES} entries"
                ))));
            }
            let typ = p & 0x3800;
            if (typ == 0x2800 || typ == 0x3000) && depth < 10 {
                match self.ciff_heap(b, data_at, data_at + size, depth + 1) {
                    Ok(()) | Err(CiffStop::DirError) => {}
                    Err(stop) => return Err(stop),
                }
            }
        }
        Ok(())
    }

    // ----- ISO-BMFF (CR3) -----

    /// rawler's `BoxHeader::parse`: one box header at the reader.
    fn head(&mut self, r: &mut Reader<'_>) -> Step<BoxHead> {
        self.boxes += 1;
        if self.boxes > MAX_BOXES {
            return refused(format!(
                "it has more than {MAX_BOXES} ISO-BMFF boxes for rawler to read"
            ));
        }
        let offset = r.pos;
        let mut size = u64::from(r.u32()?);
        let typ: [u8; 4] = r.array()?;
        if size == 1 {
            size = r.u64()?;
        }
        let uuid = if &typ == b"uuid" {
            Some(r.array::<16>()?)
        } else {
            None
        };
        let Some(end) = offset.checked_add(size) else {
            return refused(format!(
                "its ISO-BMFF box at offset {offset} claims {size} bytes"
            ));
        };
        Ok(BoxHead {
            offset,
            size,
            typ,
            uuid,
            end,
        })
    }

    /// The loop of rawler's container boxes: each child box until the
    /// parent's end, then the parent's end.
    fn children<'b>(
        &mut self,
        r: &mut Reader<'b>,
        parent: &BoxHead,
        mut each: impl FnMut(&mut Walker, &mut Reader<'b>, BoxHead) -> Step<()>,
    ) -> Step<()> {
        let mut current = r.pos;
        while current < parent.end {
            let h = self.head(r)?;
            if h.end == h.offset {
                return refused(format!(
                    "its ISO-BMFF box at offset {} has size 0: rawler would read it for ever",
                    h.offset
                ));
            }
            each(self, r, h)?;
            current = r.pos;
        }
        r.seek(parent.end);
        Ok(())
    }

    /// Refuses a table of `count` entries of `entry` bytes that no file
    /// this size holds: rawler reserves room for them before reading one.
    fn reserve(&self, h: &BoxHead, count: u32, entry: u64) -> Step<u64> {
        let bytes = u64::from(count) * entry;
        let len = self.file_len as u64;
        if bytes > len {
            return refused(format!(
                "its {} box at offset {} claims {count} entries ({bytes} bytes), but the file has only {len} bytes",
                String::from_utf8_lossy(&h.typ),
                h.offset
            ));
        }
        Ok(bytes)
    }

    /// A table rawler reserves `count` entries for, then reads.
    fn table(&mut self, r: &mut Reader<'_>, h: &BoxHead, count: u32, entry: u64) -> Step<Table> {
        let bytes = self.reserve(h, count, entry)?;
        let at = r.pos;
        r.take(bytes)?;
        Ok(Table { at, count })
    }

    /// A box rawler copies whole (`CMT1`…`CMT4`, `CNOP`).
    fn box_data<'b>(&mut self, r: &mut Reader<'b>, h: &BoxHead) -> Step<&'b [u8]> {
        // A box ending before its data makes rawler's length wrap around
        // to more than any allocation: it panics.
        let n = h.end.checked_sub(r.pos).ok_or(Halt::GivesUp)?;
        let len = self.file_len as u64;
        if n > len {
            return refused(format!(
                "its {} box at offset {} claims {n} bytes, but the file has only {len} bytes",
                String::from_utf8_lossy(&h.typ),
                h.offset
            ));
        }
        let data = r.take(n)?;
        r.seek(h.end);
        Ok(data)
    }

    /// rawler's `FileBox::parse` (what `Bmff::new` runs on every file that
    /// is none of the formats before it): the CR3 it found, or None where
    /// the file is no CR3.
    fn bmff(&mut self, b: &[u8]) -> Step<Option<Cr3>> {
        let mut r = Reader { b, pos: 0 };
        let size = b.len() as u64;
        let mut current = 0;
        let (mut ftyp, mut crx, mut mdat) = (false, false, false);
        let mut moov = None;
        while current < size {
            let h = self.head(&mut r)?;
            match &h.typ {
                b"ftyp" => {
                    r.take(8)?;
                    if h.size % 4 != 0 {
                        return Err(Halt::GivesUp);
                    }
                    // A size under 16 wraps around: rawler then reads
                    // brands to the end of the file.
                    let brands = h.size.wrapping_sub(16) / 4;
                    for _ in 0..brands {
                        crx |= r.array::<4>()? == *b"crx ";
                    }
                    ftyp = true;
                }
                b"moov" => moov = Some(self.moov(&mut r, &h)?),
                b"mdat" => mdat = true,
                _ => {}
            }
            r.seek(h.end);
            if r.pos == current {
                return Err(Halt::GivesUp);
            }
            current = r.pos;
        }
        match moov {
            Some(moov) if ftyp && mdat && crx => Ok(Some(moov)),
            Some(_) if ftyp && mdat => Ok(None),
            _ => Err(Halt::GivesUp),
        }
    }

    fn moov(&mut self, r: &mut Reader<'_>, h: &BoxHead) -> Step<Cr3> {
        let mut cr3 = Cr3::default();
        let mut mvhd = false;
        self.children(r, h, |w, r, c| {
            match &c.typ {
                b"mvhd" => {
                    full_box_with_times(r)?;
                    r.seek(c.end);
                    mvhd = true;
                }
                b"trak" => {
                    let trak = w.trak(r, &c)?;
                    cr3.traks.push(trak);
                }
                _ => match c.uuid {
                    Some(uuid) if uuid == CR3_DESC_UUID => {
                        w.cr3_desc(r, &c)?;
                        cr3.desc = true;
                    }
                    // rawler reads on inside any other uuid box.
                    Some(_) => {}
                    None => r.seek(c.end),
                },
            }
            Ok(())
        })?;
        if !mvhd {
            return Err(Halt::GivesUp);
        }
        Ok(cr3)
    }

    fn trak(&mut self, r: &mut Reader<'_>, h: &BoxHead) -> Step<Trak> {
        let (mut tkhd, mut mdia) = (false, None);
        self.children(r, h, |w, r, c| {
            match &c.typ {
                b"tkhd" => {
                    r.take(4)?;
                    tkhd = true;
                }
                b"mdia" => mdia = Some(w.mdia(r, &c)?),
                _ => {}
            }
            r.seek(c.end);
            Ok(())
        })?;
        match mdia {
            Some(trak) if tkhd => Ok(trak),
            _ => Err(Halt::GivesUp),
        }
    }

    fn mdia(&mut self, r: &mut Reader<'_>, h: &BoxHead) -> Step<Trak> {
        let (mut mdhd, mut hdlr, mut minf) = (false, false, None);
        self.children(r, h, |w, r, c| {
            match &c.typ {
                b"mdhd" => {
                    full_box_with_times(r)?;
                    r.take(2)?;
                    mdhd = true;
                }
                b"hdlr" => {
                    r.take(4)?;
                    hdlr = true;
                }
                b"minf" => minf = Some(w.minf(r, &c)?),
                _ => {}
            }
            r.seek(c.end);
            Ok(())
        })?;
        match minf {
            Some(trak) if mdhd && hdlr => Ok(trak),
            _ => Err(Halt::GivesUp),
        }
    }

    fn minf(&mut self, r: &mut Reader<'_>, h: &BoxHead) -> Step<Trak> {
        let (mut dinf, mut stbl) = (false, None);
        self.children(r, h, |w, r, c| {
            match &c.typ {
                b"vmhd" => {
                    r.take(12)?;
                }
                b"dinf" => dinf = true,
                b"stbl" => stbl = Some(w.stbl(r, &c)?),
                _ => {}
            }
            r.seek(c.end);
            Ok(())
        })?;
        match stbl {
            Some(trak) if dinf => Ok(trak),
            _ => Err(Halt::GivesUp),
        }
    }

    fn stbl(&mut self, r: &mut Reader<'_>, h: &BoxHead) -> Step<Trak> {
        let mut trak = Trak::default();
        let (mut stsd, mut stts) = (false, false);
        self.children(r, h, |w, r, c| {
            match &c.typ {
                b"stsd" => {
                    let (ctmd, dims) = w.stsd(r, &c)?;
                    trak.ctmd = ctmd;
                    trak.dims = dims;
                    stsd = true;
                }
                b"stts" => {
                    r.take(4)?;
                    let count = r.u32()?;
                    w.table(r, &c, count, 8)?;
                    stts = true;
                }
                b"stsc" => {
                    r.take(4)?;
                    let count = r.u32()?;
                    trak.stsc = Some(w.table(r, &c, count, 12)?);
                }
                b"stsz" => {
                    r.take(4)?;
                    let sample_size = r.u32()?;
                    let count = r.u32()?;
                    // rawler reserves the count even when one size is all.
                    w.reserve(&c, count, 4)?;
                    let sizes = if sample_size == 0 {
                        w.table(r, &c, count, 4)?
                    } else {
                        Table {
                            at: r.pos,
                            count: 0,
                        }
                    };
                    trak.stsz = Some((sample_size, sizes));
                }
                b"co64" => {
                    r.take(4)?;
                    let count = r.u32()?;
                    trak.co64 = Some(w.table(r, &c, count, 8)?);
                }
                _ => {}
            }
            r.seek(c.end);
            Ok(())
        })?;
        if stsd && stts && trak.stsc.is_some() && trak.stsz.is_some() {
            Ok(trak)
        } else {
            Err(Halt::GivesUp)
        }
    }

    /// `StsdBox`: whether the track has a CTMD box, and the image sizes of
    /// its CRAW box.
    fn stsd(&mut self, r: &mut Reader<'_>, h: &BoxHead) -> Step<(bool, Vec<(u32, u32)>)> {
        r.take(8)?;
        let (mut craw, mut ctmd) = (false, false);
        let mut dims = Vec::new();
        self.children(r, h, |w, r, c| {
            match &c.typ {
                b"CRAW" => {
                    // rawler asserts there is only one.
                    if std::mem::replace(&mut craw, true) {
                        return Err(Halt::GivesUp);
                    }
                    dims = w.craw(r, &c)?;
                }
                b"CTMD" => {
                    if std::mem::replace(&mut ctmd, true) {
                        return Err(Halt::GivesUp);
                    }
                    r.take(8)?;
                    let count = r.u32()?;
                    w.table(r, &c, count, 8)?;
                    // rawler asserts the records end the box.
                    if r.pos != c.end {
                        return Err(Halt::GivesUp);
                    }
                }
                _ => {}
            }
            r.seek(c.end);
            Ok(())
        })?;
        Ok((ctmd, dims))
    }

    /// `CrawBox`: its fixed fields, then its boxes; the image sizes of its
    /// CMP1 boxes, which the CR3 decoder allocates.
    fn craw(&mut self, r: &mut Reader<'_>, h: &BoxHead) -> Step<Vec<(u32, u32)>> {
        r.take(82)?;
        let mut dims = Vec::new();
        self.children(r, h, |w, r, c| {
            match &c.typ {
                b"JPEG" => {
                    r.take(4)?;
                }
                b"HEVC" | b"free" => {}
                b"CMP1" => {
                    let fixed = r.take(36)?;
                    let field = |at| be32(fixed, at).unwrap_or(0);
                    let planes = fixed.get(25).map_or(0, |b| b >> 4);
                    let ext = field(32);
                    dims.push((field(8), field(12)));
                    if ext & 0x8000_0000 != 0 && planes == 4 && c.size >= 56 {
                        let more = r.take(24)?;
                        if be32(more, 20).is_some_and(|v| v & 0x4000_0000 != 0) && c.size > 84 {
                            r.take(25)?;
                        }
                    }
                }
                b"CDI1" => {
                    r.take(4)?;
                    let mut iad1 = false;
                    w.children(r, &c, |_, r, d| {
                        if &d.typ != b"IAD1" {
                            return Err(Halt::GivesUp);
                        }
                        r.take(4)?;
                        let fields = r.take(12)?;
                        match be16(fields, 6) {
                            Some(0) => r.take(16)?,
                            Some(2) => r.take(32)?,
                            // rawler panics on another type.
                            _ => return Err(Halt::GivesUp),
                        };
                        r.seek(d.end);
                        iad1 = true;
                        Ok(())
                    })?;
                    if !iad1 {
                        return Err(Halt::GivesUp);
                    }
                }
                _ => return Err(Halt::GivesUp),
            }
            r.seek(c.end);
            Ok(())
        })?;
        Ok(dims)
    }

    /// `Cr3DescBox`: the Canon boxes of `moov`, among them the four CMT
    /// boxes, each a TIFF rawler parses.
    fn cr3_desc(&mut self, r: &mut Reader<'_>, h: &BoxHead) -> Step<()> {
        let mut found: BTreeSet<[u8; 4]> = BTreeSet::new();
        self.children(r, h, |w, r, c| {
            match &c.typ {
                b"CNCV" => {
                    r.take(30)?;
                }
                b"CCTP" => {
                    r.take(12)?;
                    w.children(r, &c, |_, r, d| {
                        if &d.typ != b"CCDT" {
                            return Err(Halt::GivesUp);
                        }
                        r.take(16)?;
                        r.seek(d.end);
                        Ok(())
                    })?;
                }
                b"CTBO" | b"THMB" | b"skip" | b"free" => {}
                b"CNOP" => {
                    w.box_data(r, &c)?;
                }
                b"CMT1" | b"CMT2" | b"CMT3" | b"CMT4" => {
                    let (name, whose) = match &c.typ {
                        b"CMT1" => ("the CMT1 box", " of the CMT1 box"),
                        b"CMT2" => ("the CMT2 box", " of the CMT2 box"),
                        b"CMT3" => ("the CMT3 box", " of the CMT3 box"),
                        _ => ("the CMT4 box", " of the CMT4 box"),
                    };
                    let bytes = w.box_data(r, &c)?;
                    w.tiff_file(View { bytes, name }, None, &[], Trust::Vendor, whose)?;
                }
                _ => return Err(Halt::GivesUp),
            }
            found.insert(c.typ);
            r.seek(c.end);
            Ok(())
        })?;
        let needed = [
            b"CNCV", b"CCTP", b"CTBO", b"CMT1", b"CMT2", b"CMT3", b"CMT4", b"THMB",
        ];
        if needed.iter().all(|t| found.contains(*t)) {
            Ok(())
        } else {
            Err(Halt::GivesUp)
        }
    }

    /// What the CR3 decoder reads beyond the boxes: the image size it
    /// allocates (`CMP1`), and the CTMD records of the first sample
    /// (`Cr3Decoder::read_ctmd`), some of them TIFFs.
    fn cr3(&mut self, b: &[u8], cr3: Cr3) -> Step<()> {
        if !cr3.desc {
            return Ok(());
        }
        for trak in &cr3.traks {
            for &(w, h) in &trak.dims {
                self.claim(w.into(), h.into(), 1);
            }
        }
        let Some(trak) = cr3.traks.iter().find(|t| t.ctmd) else {
            return Ok(());
        };
        let Some((offset, size)) = first_sample(b, trak) else {
            return Ok(());
        };
        let Some(records) = offset.checked_add(size).and_then(|end| b.get(offset..end)) else {
            return Ok(());
        };
        self.ctmd(records)
    }

    /// rawler's `Ctmd::new` on one sample, then the TIFF blocks of records
    /// 7 to 9 it parses (`Ctmd::get_as_tiff`).
    fn ctmd(&mut self, mut rest: &[u8]) -> Step<()> {
        let mut blocks = Vec::new();
        while rest.len() >= 12 {
            let size = le32(rest, 0).ok_or(Halt::GivesUp)? as usize;
            let typ = u16_at(rest, 4, Endian::Little).ok_or(Halt::GivesUp)?;
            // A size under 12 wraps around to more than any allocation:
            // rawler panics.
            let n = size.checked_sub(12).ok_or(Halt::GivesUp)?;
            if n > self.file_len {
                return refused(format!(
                    "its CR3 CTMD record {typ} claims {n} bytes, but the file has only {} bytes",
                    self.file_len
                ));
            }
            let payload = rest.get(12..12 + n).ok_or(Halt::GivesUp)?;
            rest = rest.get(12 + n..).unwrap_or_default();
            if (7..=12).contains(&typ) {
                let mut p = payload;
                while p.len() >= 8 {
                    let sz = le32(p, 0).unwrap_or(0) as usize;
                    let tag = u16_at(p, 4, Endian::Little).unwrap_or(0);
                    p = p.get(8..).unwrap_or_default();
                    let Some(data) = sz.checked_sub(8).and_then(|n| p.get(..n)) else {
                        break;
                    };
                    p = p.get(data.len()..).unwrap_or_default();
                    if (7..=9).contains(&typ) && (tag == EXIF_IFD || tag == MAKER_NOTE) {
                        blocks.push(data);
                    }
                }
            }
        }
        for bytes in blocks {
            let view = View {
                bytes,
                name: "a CR3 CTMD block",
            };
            tolerated(self.tiff_file(view, Some(0), &[], Trust::Vendor, " of a CR3 CTMD block"))?;
        }
        Ok(())
    }
}

/// How one CRW heap walk stopped.
enum CiffStop {
    /// The walk stops altogether.
    Halt(Halt),
    /// rawler's heap reader returns an error: a parent heap keeps the
    /// entry and goes on.
    DirError,
}

/// The label of a sub-IFD.
fn sub_label(tag: u16, k: usize, parent: &str) -> String {
    match tag {
        SUB_IFDS => format!("SubIFD {k} of {parent}"),
        EXIF_IFD => format!("the EXIF IFD of {parent}"),
        GPS_IFD => format!("the GPS IFD of {parent}"),
        ICC_PROFILE => format!("the ICC profile of {parent} (which rawler reads as an IFD)"),
        t => format!("the IFD tag {} of {parent} points to", TagName(t)),
    }
}

/// rawler's `ArwDecoder::sony_decrypt`: `length / 4` words at `offset`,
/// decrypted with the key's pad.
fn sony_decrypt(buf: &[u8], offset: usize, length: usize, key: u32) -> Option<Vec<u8>> {
    let words = length / 4;
    if buf.len() < offset.checked_add(words.checked_mul(4)?)? {
        return None;
    }
    // The pad is indexed modulo its 128 words, as rawler indexes it.
    let mut pad = [0u32; 128];
    let mut mkey = key;
    for p in pad.iter_mut().take(4) {
        mkey = mkey.wrapping_mul(48_828_125).wrapping_add(1);
        *p = mkey;
    }
    pad[3] = (pad[3] << 1) | ((pad[0] ^ pad[2]) >> 31);
    for p in 4..127 {
        pad[p] = ((pad[p - 4] ^ pad[p - 2]) << 1) | ((pad[p - 3] ^ pad[p - 1]) >> 31);
    }
    for p in pad.iter_mut().take(127) {
        *p = u32::from_be(*p);
    }
    let mut out = Vec::with_capacity(words * 4);
    for i in 0..words {
        let p = i + 127;
        pad[p & 127] = pad[(p + 1) & 127] ^ pad[(p + 1 + 64) & 127];
        let word = le32(buf, offset + i * 4)? ^ pad[p & 127];
        out.extend_from_slice(&word.to_le_bytes());
    }
    Some(out)
}

/// The sensor size in a RAF's own directory (`raf::parse_raf_format`, tag
/// 0x100 as height and width), if rawler reads that directory whole.
fn raf_directory_size(b: &[u8], at: usize) -> Option<(u64, u64)> {
    let count = be32(b, at)?;
    if count > 4000 {
        return None;
    }
    let mut p = at + 4;
    let mut size = None;
    for _ in 0..count {
        let tag = be16(b, p)?;
        let len = usize::from(be16(b, p + 2)?);
        p += 4;
        let read = match tag {
            0x0100 | 0x0110 | 0x0111 | 0x0115 | 0x2ff0 => len / 2 * 2,
            0x0130 | 0x0131 => len,
            0xc000 => len / 4 * 4,
            _ => {
                p += len;
                continue;
            }
        };
        let value = b.get(p..p.checked_add(read)?)?;
        if tag == 0x0100 {
            let short = |i: usize| be16(value, i * 2).map_or(0, u64::from);
            size = Some((short(1), short(0)));
        }
        p += read;
    }
    size
}

/// The UUID of Canon's `moov` box (`Cr3DescBox::UUID`).
const CR3_DESC_UUID: [u8; 16] = [
    0x85, 0xc0, 0xb6, 0x87, 0x82, 0x0f, 0x11, 0xe0, 0x81, 0x11, 0xf4, 0xce, 0x46, 0x2b, 0x6a, 0x48,
];

/// An ISO-BMFF box header.
struct BoxHead {
    offset: u64,
    size: u64,
    typ: [u8; 4],
    uuid: Option<[u8; 16]>,
    end: u64,
}

/// Where a table of a box is, and how many entries it has.
#[derive(Debug, Clone, Copy, Default)]
struct Table {
    at: u64,
    count: u32,
}

/// What the CR3 decoder uses of one track.
#[derive(Default)]
struct Trak {
    ctmd: bool,
    dims: Vec<(u32, u32)>,
    stsc: Option<Table>,
    /// The one sample size (0: per sample), and the table of sizes.
    stsz: Option<(u32, Table)>,
    co64: Option<Table>,
}

/// What the walk keeps of a CR3's `moov`.
#[derive(Default)]
struct Cr3 {
    desc: bool,
    traks: Vec<Trak>,
}

/// A big-endian reader over the file, as rawler's cursor: reads past the
/// end fail (and leave it at the end), seeks do not.
struct Reader<'b> {
    b: &'b [u8],
    pos: u64,
}

impl<'b> Reader<'b> {
    fn take(&mut self, n: u64) -> Step<&'b [u8]> {
        let bytes = usize::try_from(self.pos)
            .ok()
            .and_then(|start| Some((start, start.checked_add(usize::try_from(n).ok()?)?)))
            .and_then(|(start, end)| self.b.get(start..end));
        match bytes {
            Some(bytes) => {
                self.pos += n;
                Ok(bytes)
            }
            None => {
                self.pos = self.b.len() as u64;
                Err(Halt::GivesUp)
            }
        }
    }

    fn array<const N: usize>(&mut self) -> Step<[u8; N]> {
        self.take(N as u64)?.try_into().map_err(|_| Halt::GivesUp)
    }

    fn u32(&mut self) -> Step<u32> {
        Ok(u32::from_be_bytes(self.array()?))
    }

    fn u64(&mut self) -> Step<u64> {
        Ok(u64::from_be_bytes(self.array()?))
    }

    fn seek(&mut self, pos: u64) {
        self.pos = pos;
    }
}

/// The fields of `mvhd` and `mdhd` up to their duration: 64-bit times for
/// version 1, 32-bit for version 0, a panic in rawler for any other.
fn full_box_with_times(r: &mut Reader<'_>) -> Step<()> {
    let [version, ..] = r.array::<4>()?;
    match version {
        0 => r.take(16)?,
        1 => r.take(28)?,
        _ => return Err(Halt::GivesUp),
    };
    Ok(())
}

/// rawler's `StblBox::get_sample_offset(1)`: where the track's first
/// sample is, or None where rawler errs or panics.
fn first_sample(b: &[u8], t: &Trak) -> Option<(usize, usize)> {
    let co64 = t.co64?;
    let stsc = t.stsc?;
    let (sample_size, sizes) = t.stsz?;
    if stsc.count == 0 {
        // rawler asserts the table has an entry.
        return None;
    }
    let row = |i: u32, field: u64| {
        let at = stsc.at.checked_add(u64::from(i) * 12 + field)?;
        be32(b, usize::try_from(at).ok()?)
    };
    // The first sample of every entry, as `StscBox::read_box` computes it
    // (wrapping around, as a release build does).
    let mut firsts = Vec::with_capacity(stsc.count as usize);
    let mut held = (row(0, 0)?, row(0, 4)?, 1u32);
    firsts.push(1u32);
    for i in 1..stsc.count {
        let first_chunk = row(i, 0)?;
        let first = held
            .2
            .wrapping_add(first_chunk.wrapping_sub(held.2).wrapping_mul(held.1));
        held = (first_chunk, row(i, 4)?, first);
        firsts.push(first);
    }
    // `get_entry_for_sample`, by the same binary search.
    let i = match firsts.binary_search(&1) {
        Ok(i) => i,
        Err(i) => i.checked_sub(1)?,
    };
    let i = u32::try_from(i).ok()?;
    let (first_chunk, per_chunk, first) = (row(i, 0)?, row(i, 4)?, *firsts.get(i as usize)?);
    let chunk = first_chunk.wrapping_add(0u32.wrapping_sub(first.wrapping_sub(1)) / per_chunk);
    let in_chunk = 1u32.wrapping_sub(first) % per_chunk;
    let chunk_index = (chunk as usize).checked_sub(1)?;
    if chunk_index >= co64.count as usize {
        return None;
    }
    let chunk_at = co64.at.checked_add(chunk_index as u64 * 8)?;
    let chunk_offset = u64_at(b, usize::try_from(chunk_at).ok()?, Endian::Big)?;
    // The samples before ours in its chunk: one size for all, or rawler
    // reaches sample number 0 in its table and panics.
    let in_chunk_offset = match (in_chunk, sample_size) {
        (0, _) => 0,
        (_, 0) => return None,
        (n, size) => size.wrapping_mul(n),
    };
    let size = if sample_size > 0 {
        sample_size
    } else {
        if sizes.count == 0 {
            return None;
        }
        be32(b, usize::try_from(sizes.at).ok()?)?
    };
    let offset = (chunk_offset as usize).wrapping_add(in_chunk_offset as usize);
    Some((offset, size as usize))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A value of a hand-written test TIFF: bytes in the file's byte
    /// order, or a LONG pointer to another IFD of the file.
    enum Val {
        Bytes(Vec<u8>),
        Ifd(usize),
    }

    /// One entry of a hand-written test TIFF.
    struct E {
        tag: u16,
        typ: u16,
        count: u32,
        val: Val,
    }

    fn short(e: Endian, tag: u16, v: u16) -> E {
        let bytes = match e {
            Endian::Little => v.to_le_bytes(),
            Endian::Big => v.to_be_bytes(),
        };
        E {
            tag,
            typ: 3,
            count: 1,
            val: Val::Bytes(bytes.to_vec()),
        }
    }

    fn ascii(tag: u16, text: &str) -> E {
        let mut bytes = text.as_bytes().to_vec();
        bytes.push(0);
        E {
            tag,
            typ: ASCII,
            count: bytes.len() as u32,
            val: Val::Bytes(bytes),
        }
    }

    fn undefined(tag: u16, bytes: Vec<u8>) -> E {
        E {
            tag,
            typ: UNDEFINED,
            count: bytes.len() as u32,
            val: Val::Bytes(bytes),
        }
    }

    fn pointer(tag: u16, ifd: usize) -> E {
        E {
            tag,
            typ: LONG,
            count: 1,
            val: Val::Ifd(ifd),
        }
    }

    fn put16(out: &mut Vec<u8>, e: Endian, v: u16) {
        out.extend_from_slice(&match e {
            Endian::Little => v.to_le_bytes(),
            Endian::Big => v.to_be_bytes(),
        });
    }

    fn put32(out: &mut Vec<u8>, e: Endian, v: u32) {
        out.extend_from_slice(&match e {
            Endian::Little => v.to_le_bytes(),
            Endian::Big => v.to_be_bytes(),
        });
    }

    /// A TIFF of the given IFDs (the first is IFD0; each with the index of
    /// its next IFD), values that do not fit in an entry after them.
    fn tiff(e: Endian, ifds: &[(Vec<E>, Option<usize>)]) -> Vec<u8> {
        let mut offsets = Vec::new();
        let mut at = 8u32;
        for (entries, _) in ifds {
            offsets.push(at);
            at += 2 + 12 * entries.len() as u32 + 4;
        }
        let mut data_at = at;
        let mut out = Vec::new();
        out.extend_from_slice(match e {
            Endian::Little => b"II",
            Endian::Big => b"MM",
        });
        put16(&mut out, e, 42);
        put32(&mut out, e, offsets[0]);
        let mut data = Vec::new();
        for (entries, next) in ifds {
            put16(&mut out, e, entries.len() as u16);
            for entry in entries {
                put16(&mut out, e, entry.tag);
                put16(&mut out, e, entry.typ);
                put32(&mut out, e, entry.count);
                match &entry.val {
                    Val::Ifd(k) => put32(&mut out, e, offsets[*k]),
                    Val::Bytes(b) if b.len() <= 4 => {
                        let mut field = b.clone();
                        field.resize(4, 0);
                        out.extend_from_slice(&field);
                    }
                    Val::Bytes(b) => {
                        put32(&mut out, e, data_at);
                        data.extend_from_slice(b);
                        data_at += b.len() as u32;
                    }
                }
            }
            put32(&mut out, e, next.map_or(0, |k| offsets[k]));
        }
        out.extend_from_slice(&data);
        out
    }

    /// Sets the count of the first entry with `tag` in the IFD at `ifd`.
    fn set_count(bytes: &mut [u8], e: Endian, ifd: usize, tag: u16, count: u32) {
        let n = u16_at(bytes, ifd, e).expect("IFD") as usize;
        for i in 0..n {
            let at = ifd + 2 + 12 * i;
            if u16_at(bytes, at, e) == Some(tag) {
                let field = match e {
                    Endian::Little => count.to_le_bytes(),
                    Endian::Big => count.to_be_bytes(),
                };
                bytes[at + 4..at + 8].copy_from_slice(&field);
                return;
            }
        }
        panic!("no tag {tag:#x} in the IFD at {ifd}");
    }

    fn ifd0(bytes: &[u8], e: Endian) -> usize {
        u32_at(bytes, 4, e).expect("header") as usize
    }

    /// IFD0 with an image size, a SubIFD and an EXIF IFD (IFD 1 and 2).
    fn with_sub_ifd(e: Endian) -> Vec<u8> {
        tiff(
            e,
            &[
                (
                    vec![
                        short(e, IMAGE_WIDTH, 4),
                        short(e, IMAGE_LENGTH, 2),
                        ascii(MAKE, "rigd test"),
                        pointer(SUB_IFDS, 1),
                        pointer(EXIF_IFD, 2),
                    ],
                    None,
                ),
                (
                    vec![
                        short(e, IMAGE_WIDTH, 2),
                        short(e, IMAGE_LENGTH, 3),
                        undefined(0xC612, vec![1, 4, 0, 0]),
                        ascii(0xC614, "a camera model"),
                    ],
                    None,
                ),
                (vec![short(e, 0x8827, 100)], None),
            ],
        )
    }

    fn sub_ifd_offset(bytes: &[u8], e: Endian) -> usize {
        // IFD0 has 5 entries: SubIFD 0 follows it.
        ifd0(bytes, e) + 2 + 12 * 5 + 4
    }

    #[test]
    fn a_well_formed_tiff_passes_in_either_byte_order() {
        for e in [Endian::Little, Endian::Big] {
            let claims = walk(&with_sub_ifd(e)).expect("a good TIFF");
            assert_eq!(
                claims,
                vec![
                    ClaimedImage {
                        width: 4,
                        height: 2,
                        samples: 1
                    },
                    ClaimedImage {
                        width: 2,
                        height: 3,
                        samples: 1
                    },
                ],
                "{e:?}"
            );
        }
    }

    /// IFD0 with an ICC profile whose first bytes read as one IFD entry
    /// of `count` doubles (rawler reads the profile as an IFD).
    fn with_icc_profile(count: u32) -> Vec<u8> {
        let e = Endian::Little;
        let mut icc = Vec::new();
        put16(&mut icc, e, 1);
        put16(&mut icc, e, 0x6170);
        put16(&mut icc, e, 12);
        put32(&mut icc, e, count);
        put32(&mut icc, e, 0);
        put32(&mut icc, e, 0);
        icc.resize(64, 0);
        tiff(
            e,
            &[(
                vec![ascii(MAKE, "rigd test"), undefined(ICC_PROFILE, icc)],
                None,
            )],
        )
    }

    #[test]
    fn an_icc_profile_read_as_an_ifd_is_held_only_to_what_could_abort() {
        // 8 MB of doubles, more than the file: rawler allocates, fails to
        // read and frees them, as it does for a perfect file's profile.
        walk(&with_icc_profile(1 << 20)).expect("a profile's garbage");
        let why = walk(&with_icc_profile(u32::MAX)).expect_err("32 GB of doubles");
        assert!(
            why.contains("of the ICC profile of IFD0 (which rawler reads as an IFD) claims 4294967295 values of 8 bytes each"),
            "{why}"
        );
    }

    #[test]
    fn a_tiled_image_claims_its_whole_tiles() {
        let e = Endian::Big;
        let long = |tag: u16, v: u32| E {
            tag,
            typ: LONG,
            count: 1,
            val: Val::Bytes(v.to_be_bytes().to_vec()),
        };
        let bytes = tiff(
            e,
            &[(
                vec![
                    short(e, IMAGE_WIDTH, 8),
                    short(e, IMAGE_LENGTH, 6),
                    long(TILE_WIDTH, 1 << 28),
                    long(TILE_LENGTH, 16),
                ],
                None,
            )],
        );
        let claims = walk(&bytes).expect("a good TIFF");
        assert!(
            claims.contains(&ClaimedImage {
                width: 1 << 28,
                height: 16,
                samples: 1
            }),
            "{claims:?}"
        );
    }

    #[test]
    fn a_count_no_file_can_hold_is_refused_in_ifd0_and_in_a_sub_ifd() {
        for e in [Endian::Little, Endian::Big] {
            let mut bytes = with_sub_ifd(e);
            let at = ifd0(&bytes, e);
            set_count(&mut bytes, e, at, MAKE, u32::MAX);
            let why = walk(&bytes).expect_err("a huge count");
            assert!(
                why.contains("tag 0x010f (Make) of IFD0 claims 4294967295 values of 1 byte each")
                    && why.contains(&format!("the file has only {} bytes", bytes.len())),
                "{why}"
            );

            let mut bytes = with_sub_ifd(e);
            let at = sub_ifd_offset(&bytes, e);
            set_count(&mut bytes, e, at, IMAGE_LENGTH, u32::MAX);
            let why = walk(&bytes).expect_err("a huge count in the SubIFD");
            assert!(
                why.contains("tag 0x0101 (ImageLength) of SubIFD 0 of IFD0 claims 4294967295 values of 2 bytes each (8589934590 bytes)"),
                "{why}"
            );
        }
    }

    #[test]
    fn a_value_past_the_end_of_the_file_s_own_structure_is_refused() {
        let e = Endian::Little;
        let mut bytes = with_sub_ifd(e);
        let at = sub_ifd_offset(&bytes, e);
        // The model string is 15 bytes; 100 run past the end.
        set_count(&mut bytes, e, at, 0xC614, 100);
        let why = walk(&bytes).expect_err("past the end");
        assert!(
            why.contains("tag 0xc614 (UniqueCameraModel) of SubIFD 0 of IFD0 puts its 100 values")
                && why.contains("past the end of the file"),
            "{why}"
        );
        // A truncated file: the SubIFD's last entries are gone.
        let bytes = with_sub_ifd(e);
        let cut = sub_ifd_offset(&bytes, e) + 20;
        let why = walk(&bytes[..cut]).expect_err("truncated");
        assert!(why.contains("past the end of the file"), "{why}");
    }

    #[test]
    fn an_ifd_chain_that_loops_is_refused_and_the_walk_ends() {
        for e in [Endian::Little, Endian::Big] {
            // IFD0 → IFD1 → IFD0 …: rawler would read it for ever.
            let bytes = tiff(
                e,
                &[
                    (vec![short(e, IMAGE_WIDTH, 1)], Some(1)),
                    (vec![short(e, IMAGE_WIDTH, 1)], Some(0)),
                ],
            );
            let why = walk(&bytes).expect_err("a loop");
            assert!(why.contains("loops back to offset 8"), "{why}");
            // And to itself.
            let bytes = tiff(e, &[(vec![short(e, IMAGE_WIDTH, 1)], Some(0))]);
            assert!(walk(&bytes).is_err());
        }
    }

    #[test]
    fn many_small_claims_cannot_add_up_to_a_big_one() {
        let e = Endian::Little;
        // Each entry claims the whole file (which it fits), 2000 times over.
        let mut entries = vec![ascii(MAKE, "rigd test")];
        for tag in 0..2000u16 {
            entries.push(E {
                tag: 0x1000 + tag,
                typ: 1,
                count: 0,
                val: Val::Bytes(vec![]),
            });
        }
        let mut bytes = tiff(e, &[(entries, None)]);
        let len = bytes.len() as u32;
        let at = ifd0(&bytes, e);
        for i in 1..=2000usize {
            let entry = at + 2 + 12 * i;
            bytes[entry + 4..entry + 8].copy_from_slice(&(len / 2).to_le_bytes());
            bytes[entry + 8..entry + 12].copy_from_slice(&0u32.to_le_bytes());
        }
        let why = walk(&bytes).expect_err("too many value bytes");
        assert!(why.contains("bytes of values"), "{why}");
    }

    #[test]
    fn sub_ifds_without_end_are_refused() {
        let e = Endian::Little;
        // One SubIFDs entry listing the same IFD a thousand times.
        let mut bytes = tiff(
            e,
            &[
                (vec![ascii(MAKE, "rigd test"), pointer(SUB_IFDS, 1)], None),
                (vec![short(e, IMAGE_WIDTH, 1)], None),
            ],
        );
        let sub = u32_at(&bytes, ifd0(&bytes, e) + 2 + 12 + 8, e).expect("offset");
        let list_at = bytes.len() as u32;
        for _ in 0..1000 {
            bytes.extend_from_slice(&sub.to_le_bytes());
        }
        let entry = ifd0(&bytes, e) + 2 + 12;
        bytes[entry + 4..entry + 8].copy_from_slice(&1000u32.to_le_bytes());
        bytes[entry + 8..entry + 12].copy_from_slice(&list_at.to_le_bytes());
        let why = walk(&bytes).expect_err("too many directories");
        assert!(why.contains("more than 512 directories"), "{why}");
    }

    /// A Nikon-style TIFF: its EXIF IFD holds a maker note that is a TIFF
    /// of its own, with one entry.
    fn nikon(count: u32) -> Vec<u8> {
        let e = Endian::Little;
        let mut note = b"Nikon\0\x02\x10\0\0".to_vec();
        let mut inner = tiff(e, &[(vec![short(e, 0x0001, 7)], None)]);
        let at = ifd0(&inner, e);
        set_count(&mut inner, e, at, 0x0001, count);
        note.extend_from_slice(&inner);
        tiff(
            e,
            &[
                (
                    vec![ascii(MAKE, "NIKON CORPORATION"), pointer(EXIF_IFD, 1)],
                    None,
                ),
                (vec![undefined(MAKER_NOTE, note)], None),
            ],
        )
    }

    #[test]
    fn a_maker_note_is_walked_the_way_its_decoder_reads_it() {
        walk(&nikon(1)).expect("a good maker note");
        // A count past the end of a maker note: rawler skips the entry.
        walk(&nikon(40)).expect("a careless maker note");
        let why = walk(&nikon(u32::MAX)).expect_err("a huge count in the maker note");
        assert!(
            why.contains(
                "tag 0x0001 of the maker note IFD of the EXIF IFD of IFD0 claims 4294967295 values"
            ),
            "{why}"
        );
    }

    /// A box of `typ` around `body`.
    fn boxed(typ: &[u8; 4], body: &[u8]) -> Vec<u8> {
        let mut out = (8 + body.len() as u32).to_be_bytes().to_vec();
        out.extend_from_slice(typ);
        out.extend_from_slice(body);
        out
    }

    /// An ISO-BMFF file: `ftyp` with the CR3 brand, `moov` holding `mvhd`
    /// and `inside`, an empty `mdat`.
    fn bmff(inside: &[u8]) -> Vec<u8> {
        let mut moov = boxed(b"mvhd", &[0; 20]);
        moov.extend_from_slice(inside);
        let mut file = boxed(b"ftyp", b"crx \0\0\0\x01crx ");
        file.extend(boxed(b"moov", &moov));
        file.extend(boxed(b"mdat", &[]));
        file
    }

    #[test]
    fn an_iso_bmff_table_no_file_can_hold_is_refused() {
        // trak → mdia → minf → stbl → stts with 2^32-1 entries.
        let mut stts = vec![0; 4];
        stts.extend_from_slice(&u32::MAX.to_be_bytes());
        let stbl = boxed(b"stbl", &boxed(b"stts", &stts));
        let minf = boxed(b"minf", &stbl);
        let mdia = boxed(b"mdia", &minf);
        let trak = boxed(b"trak", &mdia);
        let why = walk(&bmff(&trak)).expect_err("a huge table");
        assert!(
            why.contains("stts box") && why.contains("claims 4294967295 entries"),
            "{why}"
        );
    }

    #[test]
    fn an_iso_bmff_box_of_size_zero_is_refused_where_rawler_would_loop() {
        let mut inside = 0u32.to_be_bytes().to_vec();
        inside.extend_from_slice(b"free");
        let why = walk(&bmff(&inside)).expect_err("a zero-size box");
        assert!(why.contains("has size 0"), "{why}");
    }

    #[test]
    fn a_cr3_metadata_tiff_is_walked() {
        let e = Endian::Little;
        let mut cmt = tiff(e, &[(vec![ascii(MAKE, "Canon")], None)]);
        let at = ifd0(&cmt, e);
        set_count(&mut cmt, e, at, MAKE, u32::MAX);
        let mut desc = CR3_DESC_UUID.to_vec();
        desc.extend(boxed(b"CMT1", &cmt));
        let mut uuid = (8 + desc.len() as u32).to_be_bytes().to_vec();
        uuid.extend_from_slice(b"uuid");
        uuid.extend_from_slice(&desc);
        let why = walk(&bmff(&uuid)).expect_err("a huge count in CMT1");
        assert!(
            why.contains("tag 0x010f (Make) of IFD0 of the CMT1 box claims 4294967295 values")
                && why.contains("but the CMT1 box has only"),
            "{why}"
        );
    }

    #[test]
    fn a_minolta_block_rawler_would_read_for_ever_is_refused() {
        let mut mrw = b"\0MRM".to_vec();
        mrw.extend_from_slice(&100u32.to_be_bytes());
        mrw.extend_from_slice(b"\0PRD");
        mrw.extend_from_slice(&0xFFFF_FFF8u32.to_be_bytes());
        mrw.resize(120, 0);
        let why = walk(&mrw).expect_err("a block of length -8");
        assert!(why.contains("for ever"), "{why}");
    }

    #[test]
    fn files_that_are_nothing_rawler_reads_pass_untouched() {
        for bytes in [
            &b""[..],
            b"hello world",
            &[0x89, b'P', b'N', b'G', 0, 0, 0, 0],
        ] {
            assert_eq!(walk(bytes), Ok(vec![]));
        }
    }

    #[test]
    fn sony_decryption_is_rawler_s() {
        // The key stream of key 0 starts as rawler's does; decrypting twice
        // gives the plain text back.
        let plain: Vec<u8> = (0..64u8).collect();
        let once = sony_decrypt(&plain, 0, 64, 0x1234_5678).expect("long enough");
        let twice = sony_decrypt(&once, 0, 64, 0x1234_5678).expect("long enough");
        assert_eq!(twice, plain);
        assert_ne!(once, plain);
        assert_eq!(sony_decrypt(&plain, 8, 64, 0), None);
    }

    #[cfg(feature = "sim")]
    fn sim_dng() -> Vec<u8> {
        use rigd_sim::firmware::dng::{encode, to_raw, DngCamera};
        let camera = DngCamera {
            make: "rigd",
            model: "walk",
            cfa: Some(rigd_core::Cfa::Rggb),
            bit_depth: 12,
        };
        let values: Vec<u16> = (0..48u16).map(|i| i * 87).collect();
        encode(&camera, 8, 6, &to_raw(&values, 12), 0.1).expect("dng")
    }

    #[cfg(feature = "sim")]
    #[test]
    fn the_simulated_camera_s_dng_passes_and_a_huge_count_in_it_does_not() {
        let dng = sim_dng();
        assert_eq!(
            walk(&dng),
            Ok(vec![ClaimedImage {
                width: 8,
                height: 6,
                samples: 1
            }])
        );
        let e = Endian::Little;
        let at = ifd0(&dng, e);
        for tag in [0x0102, 0x0111, 0xC612, 0xC614] {
            let mut bad = dng.clone();
            set_count(&mut bad, e, at, tag, 0xFFFF_FFFF);
            let why = walk(&bad).expect_err("a huge count");
            assert!(
                why.contains(&format!(
                    "tag {} of IFD0 claims 4294967295 values",
                    TagName(tag)
                )),
                "{why}"
            );
        }
    }
}
