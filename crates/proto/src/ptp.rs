//! PTP (ISO 15740, the USB Still Image class) as rigd uses it: the generic
//! container, the operation/response/event/property codes, the datasets
//! (strings, DeviceInfo, ObjectInfo) and rigd's raw frame payload.
//!
//! Everything here is a pure codec: encoders build the exact bytes of
//! `firmware-protocols/ptp-camera.md`, decoders take arbitrary bytes and
//! return an error instead of panicking, because they face whatever a real
//! camera (or a broken cable) delivers. The in-memory USB link shared by the
//! driver tests and the simulated firmware lives in [`link`].

pub mod ip;
pub mod link;
pub mod property;

use std::fmt;

/// Size of the generic container header: length u32, type u16, code u16,
/// transaction id u32, all little-endian.
pub const HEADER_LEN: usize = 12;
/// Commands, responses and events carry at most five u32 parameters.
pub const MAX_PARAMS: usize = 5;
/// ObjectFormat Undefined (ISO 15740 §6): many cameras label their vendor
/// raw files (NEF, ARW) so.
pub const FORMAT_UNDEFINED: u16 = 0x3000;
/// ObjectFormat Association: a folder, never a frame.
pub const FORMAT_ASSOCIATION: u16 = 0x3001;
/// ObjectFormat EXIF/JPEG.
pub const FORMAT_EXIF_JPEG: u16 = 0x3801;
/// ObjectFormat TIFF/EP (ISO 12234-2), the base of most raw files.
pub const FORMAT_TIFF_EP: u16 = 0x3802;
/// ObjectFormat JFIF.
pub const FORMAT_JFIF: u16 = 0x3808;
/// ObjectFormat TIFF.
pub const FORMAT_TIFF: u16 = 0x380D;
/// ObjectFormat DNG (added by PTP 1.1).
pub const FORMAT_DNG: u16 = 0x3811;

/// Whether an ObjectFormat code may hold a frame: the image formats
/// (0x38xx), Undefined (vendor raw files), and vendor-defined codes (bit 15
/// set, e.g. Canon's CR2 0xB103 and CR3 0xB108). The file's own bytes say
/// what it is.
pub fn may_be_image(object_format: u16) -> bool {
    object_format & 0xFF00 == 0x3800
        || object_format == FORMAT_UNDEFINED
        || object_format & 0x8000 != 0
}
/// PTP strings hold at most 255 UTF-16 units including the terminating NUL.
pub const MAX_STRING_UNITS: usize = 254;

/// Why bytes could not be decoded (or a value could not be encoded).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    /// The input ended in the middle of a field.
    #[error("truncated: needed {needed} bytes, had {had}")]
    Truncated {
        /// Input length in bytes the field needs (the offset of its end).
        needed: usize,
        /// Input length in bytes.
        had: usize,
    },
    /// A container's length field is below [`HEADER_LEN`], or a payload is
    /// too long for the length field to describe (then `u32::MAX`).
    #[error("container length field {0} is shorter than the 12-byte header")]
    BadLength(u32),
    /// The container's length field disagrees with the bytes received.
    #[error("container length field says {declared} bytes but {actual} arrived")]
    LengthMismatch {
        /// Length in bytes the header announces.
        declared: usize,
        /// Length in bytes actually received.
        actual: usize,
    },
    /// The container type field is not 1..=4 (carries the value read).
    #[error("unknown container type {0}")]
    UnknownType(u16),
    /// A command, response or event payload is not whole u32 parameters or
    /// holds more than [`MAX_PARAMS`] of them.
    #[error("a {kind} container carries {len} parameter bytes (a multiple of 4, at most 20)")]
    BadParams {
        /// The container's type.
        kind: ContainerKind,
        /// Length of its payload in bytes.
        len: usize,
    },
    /// More than [`MAX_PARAMS`] parameters were given to encode (carries
    /// their number).
    #[error("{0} parameters given, PTP allows at most 5")]
    TooManyParams(usize),
    /// Bytes were left after a dataset was decoded (carries their number).
    #[error("{0} trailing bytes after the dataset")]
    Trailing(usize),
    /// A property value does not fit the property's data type.
    #[error("value {0} does not fit a 16-bit property")]
    ValueTooWide(u32),
    /// A property's value list is longer than its u16 count can say.
    #[error("{0} values in one list, at most 65535")]
    TooManyValues(usize),
    /// A property description of a data type rigd does not read.
    #[error("property data type 0x{0:04X} (rigd reads UINT16 and UINT32)")]
    UnknownDataType(u16),
    /// A property description's FormFlag is not 0, 1 or 2.
    #[error("property form flag {0}")]
    UnknownForm(u8),
}

/// What a container is (the `type` field of the header).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ContainerKind {
    /// Host to camera on bulk-out: starts a transaction.
    Command = 1,
    /// The data phase of a transaction, in either direction.
    Data = 2,
    /// Camera to host on bulk-in: ends a transaction.
    Response = 3,
    /// Camera to host on the interrupt endpoint.
    Event = 4,
}

impl ContainerKind {
    /// The kind with this `type` field value; [`CodecError::UnknownType`]
    /// for any other.
    pub fn from_u16(v: u16) -> Result<ContainerKind, CodecError> {
        Ok(match v {
            1 => ContainerKind::Command,
            2 => ContainerKind::Data,
            3 => ContainerKind::Response,
            4 => ContainerKind::Event,
            other => return Err(CodecError::UnknownType(other)),
        })
    }

    /// The kind's name as transcripts and messages write it (`Command`, …).
    pub fn name(self) -> &'static str {
        match self {
            ContainerKind::Command => "Command",
            ContainerKind::Data => "Data",
            ContainerKind::Response => "Response",
            ContainerKind::Event => "Event",
        }
    }

    /// The kind with this [`name`](ContainerKind::name), if any.
    pub fn from_name(s: &str) -> Option<ContainerKind> {
        [
            ContainerKind::Command,
            ContainerKind::Data,
            ContainerKind::Response,
            ContainerKind::Event,
        ]
        .into_iter()
        .find(|k| k.name() == s)
    }
}

impl fmt::Display for ContainerKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Names the codes of one family, so transcripts and error messages say
/// `InvalidObjectHandle` rather than `0x2009`.
macro_rules! codes {
    ($(#[$m:meta])* $ty:ident { $($(#[$vm:meta])* $name:ident = $val:expr,)* }) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
        pub struct $ty(pub u16);

        #[allow(non_upper_case_globals)]
        impl $ty {
            $($(#[$vm])* pub const $name: $ty = $ty($val);)*

            /// Every named code, in numeric order of declaration.
            pub const ALL: &'static [$ty] = &[$($ty::$name,)*];

            /// The spec's name, if the code is one rigd knows.
            pub fn name(self) -> Option<&'static str> {
                match self.0 {
                    $($val => Some(stringify!($name)),)*
                    _ => None,
                }
            }

            /// A name or a `0x`-prefixed hex number.
            pub fn parse(s: &str) -> Option<$ty> {
                match s {
                    $(stringify!($name) => Some($ty::$name),)*
                    _ => s
                        .strip_prefix("0x")
                        .and_then(|h| u16::from_str_radix(h, 16).ok())
                        .map($ty),
                }
            }
        }

        impl fmt::Display for $ty {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                match self.name() {
                    Some(n) => f.write_str(n),
                    None => write!(f, "0x{:04X}", self.0),
                }
            }
        }
    };
}

codes! {
    /// Operation codes (the code of Command and Data containers).
    OpCode {
        /// Read the [`DeviceInfo`] dataset (allowed outside a session).
        GetDeviceInfo = 0x1001,
        /// Open a session; parameter: the session id (not 0).
        OpenSession = 0x1002,
        /// Close the open session.
        CloseSession = 0x1003,
        /// Read an object's [`ObjectInfo`]; parameter: the object handle.
        GetObjectInfo = 0x1008,
        /// Read an object's data (the raw frame); parameter: the object handle.
        GetObject = 0x1009,
        /// Delete an object; parameter: the handle (0xFFFFFFFF: all).
        DeleteObject = 0x100B,
        /// Start a capture; answered at once, the frame is announced by events.
        InitiateCapture = 0x100E,
        /// Read a device property's description (DevicePropDesc): its
        /// value and the values it takes; parameter: the property code.
        GetDevicePropDesc = 0x1014,
        /// Read a device property's value; parameter: the property code.
        GetDevicePropValue = 0x1015,
        /// Write a device property's value (data phase host to camera).
        SetDevicePropValue = 0x1016,
    }
}

codes! {
    /// Response codes (the code of Response containers).
    ResponseCode {
        /// The operation succeeded.
        OK = 0x2001,
        /// The operation failed for an unspecified reason.
        GeneralError = 0x2002,
        /// The operation needs an open session.
        SessionNotOpen = 0x2003,
        /// The transaction id is not valid in this session.
        InvalidTransactionID = 0x2004,
        /// The operation code is unknown to the camera.
        OperationNotSupported = 0x2005,
        /// A parameter was given that the operation does not use.
        ParameterNotSupported = 0x2006,
        /// The data phase did not complete.
        IncompleteTransfer = 0x2007,
        /// No storage has the given storage id.
        InvalidStorageID = 0x2008,
        /// No object has the given handle.
        InvalidObjectHandle = 0x2009,
        /// The camera does not have the device property.
        DevicePropNotSupported = 0x200A,
        /// The camera does not support the object format.
        InvalidObjectFormatCode = 0x200B,
        /// The camera's storage is full.
        StoreFull = 0x200C,
        /// Access to the object or storage is denied.
        AccessDenied = 0x200F,
        /// The camera is busy (e.g. a capture is running).
        DeviceBusy = 0x2019,
        /// The value is not allowed for the device property.
        InvalidDevicePropValue = 0x201C,
        /// A parameter value is invalid (e.g. session id 0).
        InvalidParameter = 0x201D,
        /// A session is already open; parameter: its id.
        SessionAlreadyOpen = 0x201E,
    }
}

codes! {
    /// Event codes (the code of Event containers on the interrupt endpoint).
    EventCode {
        /// The transaction in progress is cancelled.
        CancelTransaction = 0x4001,
        /// A new object is on the camera; parameter: its handle.
        ObjectAdded = 0x4002,
        /// An object was removed; parameter: its handle.
        ObjectRemoved = 0x4003,
        /// A device property changed; parameter: the property code.
        DevicePropChanged = 0x4006,
        /// The capture named by the transaction id has finished.
        CaptureComplete = 0x400D,
    }
}

codes! {
    /// Device property codes.
    PropCode {
        /// u32, in units of 0.1 ms (ISO 15740 §13.5.13).
        ExposureTime = 0x500D,
        /// u16, the ISO arithmetic speed (ISO 15740 §13.5.15).
        ExposureIndex = 0x500F,
    }
}

/// One generic container: the 12-byte header and its payload (parameters for
/// commands, responses and events; the dataset for data containers).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Container {
    /// Container type (header offset 4).
    pub kind: ContainerKind,
    /// Operation, response or event code (header offset 6).
    pub code: u16,
    /// Transaction id (header offset 8).
    pub transaction_id: u32,
    /// Everything after the header: up to five little-endian u32
    /// parameters, or the dataset of a data container.
    pub payload: Vec<u8>,
}

/// The header alone, read before the rest of a long data phase has arrived.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    /// Container length in bytes, header included (at least [`HEADER_LEN`]).
    pub length: u32,
    /// Container type (header offset 4).
    pub kind: ContainerKind,
    /// Operation, response or event code (header offset 6).
    pub code: u16,
    /// Transaction id (header offset 8).
    pub transaction_id: u32,
}

impl Header {
    /// Reads a header from the first 12 bytes of `buf`.
    pub fn decode(buf: &[u8]) -> Result<Header, CodecError> {
        let mut r = Reader::new(buf);
        let length = r.u32()?;
        let kind = ContainerKind::from_u16(r.u16()?)?;
        let code = r.u16()?;
        let transaction_id = r.u32()?;
        if (length as usize) < HEADER_LEN {
            return Err(CodecError::BadLength(length));
        }
        Ok(Header {
            length,
            kind,
            code,
            transaction_id,
        })
    }
}

impl Container {
    /// A command, response or event with up to five parameters.
    pub fn with_params(
        kind: ContainerKind,
        code: u16,
        transaction_id: u32,
        params: &[u32],
    ) -> Result<Container, CodecError> {
        if params.len() > MAX_PARAMS {
            return Err(CodecError::TooManyParams(params.len()));
        }
        let payload = params.iter().flat_map(|p| p.to_le_bytes()).collect();
        Ok(Container {
            kind,
            code,
            transaction_id,
            payload,
        })
    }

    /// A data phase container.
    pub fn data(code: u16, transaction_id: u32, payload: Vec<u8>) -> Container {
        Container {
            kind: ContainerKind::Data,
            code,
            transaction_id,
            payload,
        }
    }

    /// The bytes on the wire. A payload longer than `u32::MAX - 12` cannot be
    /// described by the header; it is refused.
    pub fn encode(&self) -> Result<Vec<u8>, CodecError> {
        let total = self.payload.len() + HEADER_LEN;
        let length = u32::try_from(total).map_err(|_| CodecError::BadLength(u32::MAX))?;
        let mut out = Vec::with_capacity(total);
        out.extend_from_slice(&length.to_le_bytes());
        out.extend_from_slice(&(self.kind as u16).to_le_bytes());
        out.extend_from_slice(&self.code.to_le_bytes());
        out.extend_from_slice(&self.transaction_id.to_le_bytes());
        out.extend_from_slice(&self.payload);
        Ok(out)
    }

    /// Decodes exactly one container: the length field must match `buf`.
    /// Parameter containers must carry whole u32s, at most five.
    pub fn decode(buf: &[u8]) -> Result<Container, CodecError> {
        let h = Header::decode(buf)?;
        let declared = h.length as usize;
        if declared != buf.len() {
            return Err(CodecError::LengthMismatch {
                declared,
                actual: buf.len(),
            });
        }
        let payload = buf[HEADER_LEN..].to_vec();
        if h.kind != ContainerKind::Data
            && (!payload.len().is_multiple_of(4) || payload.len() > 4 * MAX_PARAMS)
        {
            return Err(CodecError::BadParams {
                kind: h.kind,
                len: payload.len(),
            });
        }
        Ok(Container {
            kind: h.kind,
            code: h.code,
            transaction_id: h.transaction_id,
            payload,
        })
    }

    /// The payload read as u32 parameters (trailing odd bytes are ignored;
    /// [`Container::decode`] already refuses them for parameter containers).
    pub fn params(&self) -> Vec<u32> {
        self.payload
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    }
}

/// A bounds-checked little-endian reader: every decoder goes through it, so
/// no slice index can panic on short input.
#[derive(Debug)]
pub struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    /// A reader at the start of `buf`.
    pub fn new(buf: &'a [u8]) -> Reader<'a> {
        Reader { buf, pos: 0 }
    }

    /// The next `n` bytes; [`CodecError::Truncated`] if fewer are left.
    pub fn bytes(&mut self, n: usize) -> Result<&'a [u8], CodecError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.buf.len());
        match end {
            Some(end) => {
                let s = &self.buf[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            None => Err(CodecError::Truncated {
                needed: self.pos.saturating_add(n),
                had: self.buf.len(),
            }),
        }
    }

    /// The next byte.
    pub fn u8(&mut self) -> Result<u8, CodecError> {
        Ok(self.bytes(1)?[0])
    }

    /// The next little-endian u16.
    pub fn u16(&mut self) -> Result<u16, CodecError> {
        let b = self.bytes(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }

    /// The next little-endian u32.
    pub fn u32(&mut self) -> Result<u32, CodecError> {
        let b = self.bytes(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// A PTP string: u8 count of UTF-16 units including the NUL, then the
    /// units. A missing NUL is tolerated and unpaired surrogates become
    /// U+FFFD, because real cameras are not always strict.
    pub fn string(&mut self) -> Result<String, CodecError> {
        let n = self.u8()? as usize;
        let raw = self.bytes(n * 2)?;
        let mut units: Vec<u16> = raw
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect();
        if units.last() == Some(&0) {
            units.pop();
        }
        Ok(char::decode_utf16(units)
            .map(|r| r.unwrap_or(char::REPLACEMENT_CHARACTER))
            .collect())
    }

    /// A PTP array of u16: u32 element count, then the elements.
    pub fn u16_array(&mut self) -> Result<Vec<u16>, CodecError> {
        let n = self.u32()? as usize;
        // Checked against the remaining input before allocating, so a huge
        // count in garbage input cannot exhaust memory.
        let raw = self.bytes(n.saturating_mul(2))?;
        Ok(raw
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect())
    }

    /// Fails if bytes are left, so a dataset of the wrong layout is noticed.
    pub fn finish(&self) -> Result<(), CodecError> {
        match self.buf.len() - self.pos {
            0 => Ok(()),
            n => Err(CodecError::Trailing(n)),
        }
    }
}

/// Appends a PTP string. Strings longer than 254 UTF-16 units are cut at a
/// character boundary: the count byte cannot describe more.
pub fn put_string(out: &mut Vec<u8>, s: &str) {
    let mut units: Vec<u16> = Vec::new();
    for c in s.chars() {
        let mut b = [0u16; 2];
        let enc = c.encode_utf16(&mut b);
        if units.len() + enc.len() > MAX_STRING_UNITS {
            break;
        }
        units.extend_from_slice(enc);
    }
    if units.is_empty() {
        out.push(0);
        return;
    }
    units.push(0);
    out.push(units.len() as u8);
    for u in units {
        out.extend_from_slice(&u.to_le_bytes());
    }
}

/// Encodes one PTP string on its own (for tests and transcripts).
pub fn encode_string(s: &str) -> Vec<u8> {
    let mut out = Vec::new();
    put_string(&mut out, s);
    out
}

/// Decodes one PTP string that fills `buf` exactly.
pub fn decode_string(buf: &[u8]) -> Result<String, CodecError> {
    let mut r = Reader::new(buf);
    let s = r.string()?;
    r.finish()?;
    Ok(s)
}

fn put_u16_array(out: &mut Vec<u8>, a: &[u16]) {
    out.extend_from_slice(&(a.len() as u32).to_le_bytes());
    for v in a {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

/// The DeviceInfo dataset (ISO 15740 §5.5.1): who the camera is and what it
/// supports, read before a session so the driver can refuse a camera that
/// lacks an operation it needs.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct DeviceInfo {
    /// StandardVersion: the PTP version times 100 (100 = 1.00).
    pub standard_version: u16,
    /// VendorExtensionID: whose vendor extension the camera speaks (0: none).
    pub vendor_extension_id: u32,
    /// VendorExtensionVersion: version of that extension, times 100.
    pub vendor_extension_version: u16,
    /// VendorExtensionDesc: the vendor extension's description string.
    pub vendor_extension_desc: String,
    /// FunctionalMode: 0 standard, 1 sleep; values with bit 15 set are
    /// vendor-defined.
    pub functional_mode: u16,
    /// OperationsSupported: the [`OpCode`]s the camera implements.
    pub operations_supported: Vec<u16>,
    /// EventsSupported: the [`EventCode`]s the camera may send.
    pub events_supported: Vec<u16>,
    /// DevicePropertiesSupported: the [`PropCode`]s the camera has.
    pub device_properties_supported: Vec<u16>,
    /// CaptureFormats: object format codes a capture can produce.
    pub capture_formats: Vec<u16>,
    /// ImageFormats: object format codes the camera supports for images.
    pub image_formats: Vec<u16>,
    /// Manufacturer string.
    pub manufacturer: String,
    /// Model string.
    pub model: String,
    /// DeviceVersion: the firmware version string.
    pub device_version: String,
    /// SerialNumber string.
    pub serial_number: String,
}

impl DeviceInfo {
    /// The dataset's bytes, fields in ISO 15740 order.
    pub fn encode(&self) -> Vec<u8> {
        let mut o = Vec::new();
        o.extend_from_slice(&self.standard_version.to_le_bytes());
        o.extend_from_slice(&self.vendor_extension_id.to_le_bytes());
        o.extend_from_slice(&self.vendor_extension_version.to_le_bytes());
        put_string(&mut o, &self.vendor_extension_desc);
        o.extend_from_slice(&self.functional_mode.to_le_bytes());
        put_u16_array(&mut o, &self.operations_supported);
        put_u16_array(&mut o, &self.events_supported);
        put_u16_array(&mut o, &self.device_properties_supported);
        put_u16_array(&mut o, &self.capture_formats);
        put_u16_array(&mut o, &self.image_formats);
        put_string(&mut o, &self.manufacturer);
        put_string(&mut o, &self.model);
        put_string(&mut o, &self.device_version);
        put_string(&mut o, &self.serial_number);
        o
    }

    /// Decodes a DeviceInfo dataset. Trailing bytes are refused: rigd's
    /// cameras send exactly this layout.
    pub fn decode(buf: &[u8]) -> Result<DeviceInfo, CodecError> {
        let mut r = Reader::new(buf);
        let d = DeviceInfo {
            standard_version: r.u16()?,
            vendor_extension_id: r.u32()?,
            vendor_extension_version: r.u16()?,
            vendor_extension_desc: r.string()?,
            functional_mode: r.u16()?,
            operations_supported: r.u16_array()?,
            events_supported: r.u16_array()?,
            device_properties_supported: r.u16_array()?,
            capture_formats: r.u16_array()?,
            image_formats: r.u16_array()?,
            manufacturer: r.string()?,
            model: r.string()?,
            device_version: r.string()?,
            serial_number: r.string()?,
        };
        r.finish()?;
        Ok(d)
    }

    /// True when the camera lists the operation.
    pub fn supports(&self, op: OpCode) -> bool {
        self.operations_supported.contains(&op.0)
    }
}

/// The ObjectInfo dataset (ISO 15740 §5.5.2): what a captured object is,
/// read before GetObject so the frame size is known before the pixels come.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ObjectInfo {
    /// StorageID: the storage holding the object.
    pub storage_id: u32,
    /// ObjectFormat: the object's format code (the simulated camera: [`FORMAT_DNG`]).
    pub object_format: u16,
    /// ProtectionStatus: 0 no protection, 1 read-only.
    pub protection_status: u16,
    /// ObjectCompressedSize: size of the object's data in bytes (what
    /// GetObject returns).
    pub compressed_size: u32,
    /// ThumbFormat: format code of the thumbnail (0: none).
    pub thumb_format: u16,
    /// ThumbCompressedSize: size of the thumbnail in bytes.
    pub thumb_compressed_size: u32,
    /// ThumbPixWidth: thumbnail width in pixels.
    pub thumb_width: u32,
    /// ThumbPixHeight: thumbnail height in pixels.
    pub thumb_height: u32,
    /// ImagePixWidth: image width in pixels.
    pub image_width: u32,
    /// ImagePixHeight: image height in pixels.
    pub image_height: u32,
    /// ImageBitDepth: significant bits per pixel.
    pub image_bit_depth: u32,
    /// ParentObject: handle of the folder object holding it (0: root).
    pub parent_object: u32,
    /// AssociationType: for folder-like objects, the kind of association.
    pub association_type: u16,
    /// AssociationDesc: association-type-specific description.
    pub association_desc: u32,
    /// SequenceNumber: the object's place in a capture sequence.
    pub sequence_number: u32,
    /// Filename on the camera's storage.
    pub filename: String,
    /// CaptureDate as a PTP date string (`YYYYMMDDThhmmss`), or empty.
    pub capture_date: String,
    /// ModificationDate, same format as `capture_date`, or empty.
    pub modification_date: String,
    /// Keywords string.
    pub keywords: String,
}

impl ObjectInfo {
    /// The dataset's bytes, fields in ISO 15740 order.
    pub fn encode(&self) -> Vec<u8> {
        let mut o = Vec::new();
        o.extend_from_slice(&self.storage_id.to_le_bytes());
        o.extend_from_slice(&self.object_format.to_le_bytes());
        o.extend_from_slice(&self.protection_status.to_le_bytes());
        o.extend_from_slice(&self.compressed_size.to_le_bytes());
        o.extend_from_slice(&self.thumb_format.to_le_bytes());
        o.extend_from_slice(&self.thumb_compressed_size.to_le_bytes());
        o.extend_from_slice(&self.thumb_width.to_le_bytes());
        o.extend_from_slice(&self.thumb_height.to_le_bytes());
        o.extend_from_slice(&self.image_width.to_le_bytes());
        o.extend_from_slice(&self.image_height.to_le_bytes());
        o.extend_from_slice(&self.image_bit_depth.to_le_bytes());
        o.extend_from_slice(&self.parent_object.to_le_bytes());
        o.extend_from_slice(&self.association_type.to_le_bytes());
        o.extend_from_slice(&self.association_desc.to_le_bytes());
        o.extend_from_slice(&self.sequence_number.to_le_bytes());
        put_string(&mut o, &self.filename);
        put_string(&mut o, &self.capture_date);
        put_string(&mut o, &self.modification_date);
        put_string(&mut o, &self.keywords);
        o
    }

    /// Decodes an ObjectInfo dataset; trailing bytes are refused.
    pub fn decode(buf: &[u8]) -> Result<ObjectInfo, CodecError> {
        let mut r = Reader::new(buf);
        let d = ObjectInfo {
            storage_id: r.u32()?,
            object_format: r.u16()?,
            protection_status: r.u16()?,
            compressed_size: r.u32()?,
            thumb_format: r.u16()?,
            thumb_compressed_size: r.u32()?,
            thumb_width: r.u32()?,
            thumb_height: r.u32()?,
            image_width: r.u32()?,
            image_height: r.u32()?,
            image_bit_depth: r.u32()?,
            parent_object: r.u32()?,
            association_type: r.u16()?,
            association_desc: r.u32()?,
            sequence_number: r.u32()?,
            filename: r.string()?,
            capture_date: r.string()?,
            modification_date: r.string()?,
            keywords: r.string()?,
        };
        r.finish()?;
        Ok(d)
    }
}

/// Converts an exposure in seconds to the ExposureTime property (0.1 ms
/// units); `None` if it is not positive, not finite or too long for a u32.
pub fn exposure_to_prop(exposure_s: f64) -> Option<u32> {
    if !exposure_s.is_finite() || exposure_s <= 0.0 {
        return None;
    }
    let units = (exposure_s * 10_000.0).round();
    if units < 1.0 || units > u32::MAX as f64 {
        return None;
    }
    Some(units as u32)
}

/// The ExposureTime property value in seconds.
pub fn prop_to_exposure(units: u32) -> f64 {
    units as f64 / 10_000.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn open_session_bytes_match_the_spec() {
        let c = Container::with_params(ContainerKind::Command, OpCode::OpenSession.0, 0, &[1])
            .unwrap_or_else(|e| panic!("{e}"));
        let b = c.encode().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(b, [0x10, 0, 0, 0, 1, 0, 0x02, 0x10, 0, 0, 0, 0, 1, 0, 0, 0]);
        assert_eq!(Container::decode(&b), Ok(c));
    }

    #[test]
    fn strings_follow_ptp_layout() {
        assert_eq!(encode_string(""), [0]);
        assert_eq!(encode_string("A"), [2, b'A', 0, 0, 0]);
        assert_eq!(decode_string(&[0]), Ok(String::new()));
        let long = "x".repeat(400);
        let enc = encode_string(&long);
        assert_eq!(enc[0], 255);
        assert_eq!(decode_string(&enc).map(|s| s.len()), Ok(254));
    }

    #[test]
    fn container_errors_are_reported() {
        assert!(matches!(
            Container::decode(&[1, 2, 3]),
            Err(CodecError::Truncated { .. })
        ));
        assert_eq!(
            Container::decode(&[4, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0]),
            Err(CodecError::BadLength(4))
        );
        assert_eq!(
            Container::decode(&[12, 0, 0, 0, 9, 0, 0, 0, 0, 0, 0, 0]),
            Err(CodecError::UnknownType(9))
        );
        assert!(Container::with_params(ContainerKind::Command, 1, 0, &[0; 6]).is_err());
    }

    #[test]
    fn image_formats_are_told_from_folders_and_scripts() {
        for f in [
            FORMAT_EXIF_JPEG,
            FORMAT_TIFF,
            FORMAT_DNG,
            FORMAT_UNDEFINED,
            0xB103,
        ] {
            assert!(may_be_image(f), "0x{f:04X}");
        }
        for f in [FORMAT_ASSOCIATION, 0x3002, 0x300A] {
            assert!(!may_be_image(f), "0x{f:04X}");
        }
    }

    #[test]
    fn exposure_units_are_tenths_of_ms() {
        assert_eq!(exposure_to_prop(0.25), Some(2500));
        assert_eq!(exposure_to_prop(0.0), None);
        assert_eq!(exposure_to_prop(f64::NAN), None);
        assert_eq!(exposure_to_prop(1e9), None);
        assert!((prop_to_exposure(2500) - 0.25).abs() < 1e-12);
    }

    #[test]
    fn code_names_round_trip() {
        for c in OpCode::ALL {
            assert_eq!(c.name().and_then(OpCode::parse), Some(*c));
        }
        assert_eq!(
            ResponseCode::parse("0x2009"),
            Some(ResponseCode::InvalidObjectHandle)
        );
        assert_eq!(ResponseCode(0x2FFF).to_string(), "0x2FFF");
    }

    fn arb_string() -> impl Strategy<Value = String> {
        proptest::collection::vec(any::<char>(), 0..40).prop_map(|v| v.into_iter().collect())
    }

    fn arb_u16s() -> impl Strategy<Value = Vec<u16>> {
        proptest::collection::vec(any::<u16>(), 0..20)
    }

    prop_compose! {
        fn arb_device_info()(
            a in any::<(u16, u32, u16, u16)>(),
            desc in arb_string(),
            ops in arb_u16s(), evs in arb_u16s(), props in arb_u16s(),
            cf in arb_u16s(), imf in arb_u16s(),
            s in (arb_string(), arb_string(), arb_string(), arb_string()),
        ) -> DeviceInfo {
            DeviceInfo {
                standard_version: a.0, vendor_extension_id: a.1,
                vendor_extension_version: a.2, vendor_extension_desc: desc,
                functional_mode: a.3, operations_supported: ops,
                events_supported: evs, device_properties_supported: props,
                capture_formats: cf, image_formats: imf,
                manufacturer: s.0, model: s.1, device_version: s.2, serial_number: s.3,
            }
        }
    }

    prop_compose! {
        fn arb_object_info()(
            a in any::<(u32, u16, u16, u32, u16, u32, u32, u32)>(),
            b in any::<(u32, u32, u32, u32, u16, u32, u32)>(),
            s in (arb_string(), arb_string(), arb_string(), arb_string()),
        ) -> ObjectInfo {
            ObjectInfo {
                storage_id: a.0, object_format: a.1, protection_status: a.2,
                compressed_size: a.3, thumb_format: a.4, thumb_compressed_size: a.5,
                thumb_width: a.6, thumb_height: a.7, image_width: b.0,
                image_height: b.1, image_bit_depth: b.2, parent_object: b.3,
                association_type: b.4, association_desc: b.5, sequence_number: b.6,
                filename: s.0, capture_date: s.1, modification_date: s.2, keywords: s.3,
            }
        }
    }

    proptest! {
        #[test]
        fn container_decode_never_panics(b in proptest::collection::vec(any::<u8>(), 0..64)) {
            let _ = Container::decode(&b);
            let _ = Header::decode(&b);
        }

        #[test]
        fn container_round_trips(
            kind in 1u16..=4, code in any::<u16>(), tid in any::<u32>(),
            params in proptest::collection::vec(any::<u32>(), 0..=5),
            data in proptest::collection::vec(any::<u8>(), 0..64),
        ) {
            let kind = ContainerKind::from_u16(kind).unwrap_or(ContainerKind::Data);
            let c = if kind == ContainerKind::Data {
                Container::data(code, tid, data)
            } else {
                Container::with_params(kind, code, tid, &params)
                    .unwrap_or_else(|e| panic!("{e}"))
            };
            let b = c.encode().unwrap_or_else(|e| panic!("{e}"));
            prop_assert_eq!(Container::decode(&b), Ok(c.clone()));
            if kind != ContainerKind::Data {
                prop_assert_eq!(c.params(), params);
            }
        }

        #[test]
        fn string_decode_never_panics(b in proptest::collection::vec(any::<u8>(), 0..80)) {
            let _ = decode_string(&b);
        }

        #[test]
        fn string_round_trips(s in arb_string()) {
            prop_assert_eq!(decode_string(&encode_string(&s)), Ok(s));
        }

        #[test]
        fn device_info_decode_never_panics(b in proptest::collection::vec(any::<u8>(), 0..200)) {
            let _ = DeviceInfo::decode(&b);
        }

        #[test]
        fn device_info_round_trips(d in arb_device_info()) {
            prop_assert_eq!(DeviceInfo::decode(&d.encode()), Ok(d));
        }

        #[test]
        fn object_info_decode_never_panics(b in proptest::collection::vec(any::<u8>(), 0..200)) {
            let _ = ObjectInfo::decode(&b);
        }

        #[test]
        fn object_info_round_trips(d in arb_object_info()) {
            prop_assert_eq!(ObjectInfo::decode(&d.encode()), Ok(d));
        }
    }
}
