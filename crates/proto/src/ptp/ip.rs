//! PTP/IP (CIPA DC-005): PTP's operations, data and events carried over two
//! TCP connections instead of USB endpoints. The *command connection* carries
//! operation requests, data phases and responses; the *event connection*
//! carries events. Both start with an init handshake that pairs them.
//!
//! Every packet is a little-endian `u32` length (the whole packet, these
//! 8 bytes included), a `u32` packet type, and the type's fields:
//!
//! | type | packet | fields |
//! |---|---|---|
//! | 1 | Init Command Request | GUID (16 bytes), friendly name (UTF-16LE, NUL-terminated), protocol version `u32` |
//! | 2 | Init Command Ack | connection number `u32`, GUID, friendly name, protocol version |
//! | 3 | Init Event Request | connection number |
//! | 4 | Init Event Ack | none |
//! | 5 | Init Fail | reason `u32` (1 rejected, 2 busy, 3 unspecified) |
//! | 6 | Operation Request | data phase `u32` (1 none or data-in, 2 data-out), operation code `u16`, transaction id `u32`, up to 5 `u32` parameters |
//! | 7 | Operation Response | response code `u16`, transaction id, up to 5 parameters |
//! | 8 | Event | event code `u16`, transaction id, up to 3 parameters |
//! | 9 | Start Data | transaction id, total data length `u64` |
//! | 10 | Data | transaction id, payload |
//! | 11 | Cancel | transaction id |
//! | 12 | End Data | transaction id, the payload's last part |
//! | 13 | Probe Request | none |
//! | 14 | Probe Response | none |
//!
//! This module is the codec and the two bridges between PTP/IP and the
//! USB-shaped link of [`super::link`]: [`initiator`] gives a driver written
//! for USB containers a camera on the network, [`serve_device`] gives a
//! firmware written for USB containers a network front. Decoders take any
//! bytes and return [`IpError`], never panic.

use std::fmt;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::sync::mpsc;

use super::link::{self, DeviceEnd, HostEnd, WIRE_MAX_TRANSFER};
use super::{Container, ContainerKind, Reader, HEADER_LEN, MAX_PARAMS};

/// The IANA port of PTP/IP (15740, the ISO standard's number).
pub const DEFAULT_PORT: u16 = 15740;
/// Protocol version 1.0, as the initiator and responder both send it
/// (major in the high 16 bits).
pub const PROTOCOL_VERSION: u32 = 0x0001_0000;
/// The packet header: length and type.
pub const PACKET_HEADER_LEN: usize = 8;
/// Longest packet that is not a data packet: an init packet with a
/// 255-unit name is 8 + 4 + 16 + 510 + 4 bytes.
pub const MAX_CONTROL_PACKET: usize = 1024;
/// Longest data payload one Data or End Data packet may carry.
pub const MAX_DATA_PACKET: usize = WIRE_MAX_TRANSFER;
/// Events carry at most three parameters.
pub const MAX_EVENT_PARAMS: usize = 3;
/// A friendly name holds at most this many UTF-16 units (NUL excluded).
pub const MAX_NAME_UNITS: usize = 254;
/// The data payload of each Data packet a bridge sends; the rest goes in
/// the End Data packet.
pub const DATA_CHUNK: usize = 1024 * 1024;

/// Why a packet could not be read, decoded or sent.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum IpError {
    /// The peer closed the connection (or it broke).
    #[error("PTP/IP connection closed")]
    Closed,
    /// A socket error other than a clean close.
    #[error("PTP/IP connection: {0}")]
    Io(String),
    /// A packet that does not decode: its type, length or fields are wrong.
    #[error("malformed PTP/IP packet: {0}")]
    Malformed(String),
    /// A packet type that is valid but not expected here.
    #[error("unexpected PTP/IP {got} packet: {wanted}")]
    Unexpected {
        /// The packet type received.
        got: PacketType,
        /// What the protocol expected instead.
        wanted: String,
    },
    /// The responder refused the connection (Init Fail).
    #[error("the camera refused the PTP/IP connection: {0}")]
    Refused(FailReason),
}

impl From<std::io::Error> for IpError {
    fn from(e: std::io::Error) -> IpError {
        match e.kind() {
            std::io::ErrorKind::UnexpectedEof
            | std::io::ErrorKind::ConnectionReset
            | std::io::ErrorKind::ConnectionAborted
            | std::io::ErrorKind::BrokenPipe => IpError::Closed,
            _ => IpError::Io(e.to_string()),
        }
    }
}

fn malformed(what: impl fmt::Display) -> IpError {
    IpError::Malformed(what.to_string())
}

/// The packet types of DC-005.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PacketType {
    /// 1: opens the command connection.
    InitCommandRequest = 1,
    /// 2: accepts it, with the connection number the event connection quotes.
    InitCommandAck = 2,
    /// 3: opens the event connection.
    InitEventRequest = 3,
    /// 4: accepts it.
    InitEventAck = 4,
    /// 5: refuses either.
    InitFail = 5,
    /// 6: an operation (a USB Command container).
    OperationRequest = 6,
    /// 7: its response (a USB Response container).
    OperationResponse = 7,
    /// 8: an event (a USB interrupt Event container).
    Event = 8,
    /// 9: a data phase begins.
    StartData = 9,
    /// 10: part of a data phase.
    Data = 10,
    /// 11: cancels a transaction.
    Cancel = 11,
    /// 12: the data phase's last part.
    EndData = 12,
    /// 13: are you there?
    ProbeRequest = 13,
    /// 14: yes.
    ProbeResponse = 14,
}

impl PacketType {
    const ALL: [PacketType; 14] = [
        PacketType::InitCommandRequest,
        PacketType::InitCommandAck,
        PacketType::InitEventRequest,
        PacketType::InitEventAck,
        PacketType::InitFail,
        PacketType::OperationRequest,
        PacketType::OperationResponse,
        PacketType::Event,
        PacketType::StartData,
        PacketType::Data,
        PacketType::Cancel,
        PacketType::EndData,
        PacketType::ProbeRequest,
        PacketType::ProbeResponse,
    ];

    /// The type with this number.
    pub fn from_u32(v: u32) -> Option<PacketType> {
        PacketType::ALL.into_iter().find(|t| *t as u32 == v)
    }

    /// The name transcripts write (`OperationRequest`, …).
    pub fn name(self) -> &'static str {
        match self {
            PacketType::InitCommandRequest => "InitCommandRequest",
            PacketType::InitCommandAck => "InitCommandAck",
            PacketType::InitEventRequest => "InitEventRequest",
            PacketType::InitEventAck => "InitEventAck",
            PacketType::InitFail => "InitFail",
            PacketType::OperationRequest => "OperationRequest",
            PacketType::OperationResponse => "OperationResponse",
            PacketType::Event => "Event",
            PacketType::StartData => "StartData",
            PacketType::Data => "Data",
            PacketType::Cancel => "Cancel",
            PacketType::EndData => "EndData",
            PacketType::ProbeRequest => "ProbeRequest",
            PacketType::ProbeResponse => "ProbeResponse",
        }
    }

    /// The type with this [`name`](PacketType::name).
    pub fn from_name(s: &str) -> Option<PacketType> {
        PacketType::ALL.into_iter().find(|t| t.name() == s)
    }

    /// Longest packet of this type a reader accepts.
    fn max_len(self) -> usize {
        match self {
            PacketType::Data | PacketType::EndData => PACKET_HEADER_LEN + 4 + MAX_DATA_PACKET,
            _ => MAX_CONTROL_PACKET,
        }
    }
}

impl fmt::Display for PacketType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Why a responder refused a connection (the Init Fail reason).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FailReason {
    /// 1: this initiator is not allowed.
    Rejected,
    /// 2: another initiator holds the camera.
    Busy,
    /// 3 (and any other value): no reason given.
    Unspecified,
}

impl FailReason {
    fn code(self) -> u32 {
        match self {
            FailReason::Rejected => 1,
            FailReason::Busy => 2,
            FailReason::Unspecified => 3,
        }
    }

    fn from_code(v: u32) -> FailReason {
        match v {
            1 => FailReason::Rejected,
            2 => FailReason::Busy,
            _ => FailReason::Unspecified,
        }
    }
}

impl fmt::Display for FailReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            FailReason::Rejected => "rejected",
            FailReason::Busy => "busy with another initiator",
            FailReason::Unspecified => "no reason given",
        })
    }
}

/// Whether an operation has a data-out phase (Operation Request's first
/// field). A data-in phase is announced by the responder's Start Data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DataPhase {
    /// 1: no data phase, or data from the camera.
    NoneOrIn,
    /// 2: data to the camera follows.
    Out,
    /// 3 (DC-005's "unknown"), or any other value: treated as no data-out.
    Unknown(u32),
}

impl DataPhase {
    fn code(self) -> u32 {
        match self {
            DataPhase::NoneOrIn => 1,
            DataPhase::Out => 2,
            DataPhase::Unknown(v) => v,
        }
    }

    fn from_code(v: u32) -> DataPhase {
        match v {
            1 => DataPhase::NoneOrIn,
            2 => DataPhase::Out,
            v => DataPhase::Unknown(v),
        }
    }
}

/// Who an end of the connection says it is (the init packets' fields).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Identity {
    /// A 16-byte id that stays the same across connections: cameras pair
    /// with an initiator by it.
    pub guid: [u8; 16],
    /// A name for people (the host name, the camera's model).
    pub name: String,
    /// The protocol version, [`PROTOCOL_VERSION`].
    pub version: u32,
}

/// One PTP/IP packet.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Packet {
    /// Opens the command connection.
    InitCommandRequest(Identity),
    /// Accepts the command connection.
    InitCommandAck {
        /// The number the event connection quotes.
        connection: u32,
        /// The camera's identity.
        identity: Identity,
    },
    /// Opens the event connection of a command connection.
    InitEventRequest {
        /// The command connection's number.
        connection: u32,
    },
    /// Accepts the event connection.
    InitEventAck,
    /// Refuses a connection.
    InitFail(FailReason),
    /// An operation.
    OperationRequest {
        /// Whether data to the camera follows.
        data_phase: DataPhase,
        /// The operation code.
        code: u16,
        /// The transaction id.
        transaction_id: u32,
        /// Up to five parameters.
        params: Vec<u32>,
    },
    /// An operation's response.
    OperationResponse {
        /// The response code.
        code: u16,
        /// The transaction id.
        transaction_id: u32,
        /// Up to five parameters.
        params: Vec<u32>,
    },
    /// An event.
    Event {
        /// The event code.
        code: u16,
        /// The transaction id it belongs to (0 for none).
        transaction_id: u32,
        /// Up to three parameters.
        params: Vec<u32>,
    },
    /// A data phase begins.
    StartData {
        /// The transaction id.
        transaction_id: u32,
        /// Bytes the data phase carries in all.
        total: u64,
    },
    /// A part of a data phase.
    Data {
        /// The transaction id.
        transaction_id: u32,
        /// The part's bytes.
        payload: Vec<u8>,
    },
    /// Cancels a transaction.
    Cancel {
        /// The transaction id.
        transaction_id: u32,
    },
    /// The last part of a data phase.
    EndData {
        /// The transaction id.
        transaction_id: u32,
        /// The part's bytes (may be empty).
        payload: Vec<u8>,
    },
    /// Asks the peer whether it is there.
    ProbeRequest,
    /// Answers a probe.
    ProbeResponse,
}

fn put_u16(out: &mut Vec<u8>, v: u16) {
    out.extend_from_slice(&v.to_le_bytes());
}

fn put_u32(out: &mut Vec<u8>, v: u32) {
    out.extend_from_slice(&v.to_le_bytes());
}

fn put_name(out: &mut Vec<u8>, name: &str) -> Result<(), IpError> {
    let units: Vec<u16> = name.encode_utf16().collect();
    if units.len() > MAX_NAME_UNITS || units.contains(&0) {
        return Err(malformed(format!(
            "a friendly name is at most {MAX_NAME_UNITS} UTF-16 units without NUL"
        )));
    }
    for u in units.iter().chain(std::iter::once(&0)) {
        put_u16(out, *u);
    }
    Ok(())
}

fn read_name(r: &mut Reader<'_>) -> Result<String, IpError> {
    let mut units = Vec::new();
    loop {
        let u = r.u16().map_err(malformed)?;
        if u == 0 {
            break;
        }
        if units.len() == MAX_NAME_UNITS {
            return Err(malformed("friendly name without its NUL"));
        }
        units.push(u);
    }
    String::from_utf16(&units).map_err(|_| malformed("friendly name is not UTF-16"))
}

fn read_identity(r: &mut Reader<'_>) -> Result<Identity, IpError> {
    let mut guid = [0u8; 16];
    guid.copy_from_slice(r.bytes(16).map_err(malformed)?);
    let name = read_name(r)?;
    let version = r.u32().map_err(malformed)?;
    Ok(Identity {
        guid,
        name,
        version,
    })
}

fn put_identity(out: &mut Vec<u8>, id: &Identity) -> Result<(), IpError> {
    out.extend_from_slice(&id.guid);
    put_name(out, &id.name)?;
    put_u32(out, id.version);
    Ok(())
}

fn read_params(r: &mut Reader<'_>, rest: usize, max: usize) -> Result<Vec<u32>, IpError> {
    if !rest.is_multiple_of(4) || rest / 4 > max {
        return Err(malformed(format!(
            "{rest} parameter bytes (whole u32s, at most {max})"
        )));
    }
    (0..rest / 4).map(|_| r.u32().map_err(malformed)).collect()
}

fn check_params(params: &[u32], max: usize) -> Result<(), IpError> {
    if params.len() > max {
        return Err(malformed(format!(
            "{} parameters, at most {max}",
            params.len()
        )));
    }
    Ok(())
}

impl Packet {
    /// The packet's type.
    pub fn packet_type(&self) -> PacketType {
        match self {
            Packet::InitCommandRequest(_) => PacketType::InitCommandRequest,
            Packet::InitCommandAck { .. } => PacketType::InitCommandAck,
            Packet::InitEventRequest { .. } => PacketType::InitEventRequest,
            Packet::InitEventAck => PacketType::InitEventAck,
            Packet::InitFail(_) => PacketType::InitFail,
            Packet::OperationRequest { .. } => PacketType::OperationRequest,
            Packet::OperationResponse { .. } => PacketType::OperationResponse,
            Packet::Event { .. } => PacketType::Event,
            Packet::StartData { .. } => PacketType::StartData,
            Packet::Data { .. } => PacketType::Data,
            Packet::Cancel { .. } => PacketType::Cancel,
            Packet::EndData { .. } => PacketType::EndData,
            Packet::ProbeRequest => PacketType::ProbeRequest,
            Packet::ProbeResponse => PacketType::ProbeResponse,
        }
    }

    /// The packet's bytes, header included. Refuses what the format cannot
    /// carry: too many parameters, a name too long, a payload over
    /// [`MAX_DATA_PACKET`].
    pub fn encode(&self) -> Result<Vec<u8>, IpError> {
        let mut body = Vec::new();
        match self {
            Packet::InitCommandRequest(id) => put_identity(&mut body, id)?,
            Packet::InitCommandAck {
                connection,
                identity,
            } => {
                put_u32(&mut body, *connection);
                put_identity(&mut body, identity)?;
            }
            Packet::InitEventRequest { connection } => put_u32(&mut body, *connection),
            Packet::InitEventAck | Packet::ProbeRequest | Packet::ProbeResponse => {}
            Packet::InitFail(reason) => put_u32(&mut body, reason.code()),
            Packet::OperationRequest {
                data_phase,
                code,
                transaction_id,
                params,
            } => {
                check_params(params, MAX_PARAMS)?;
                put_u32(&mut body, data_phase.code());
                put_u16(&mut body, *code);
                put_u32(&mut body, *transaction_id);
                params.iter().for_each(|p| put_u32(&mut body, *p));
            }
            Packet::OperationResponse {
                code,
                transaction_id,
                params,
            }
            | Packet::Event {
                code,
                transaction_id,
                params,
            } => {
                let max = if matches!(self, Packet::Event { .. }) {
                    MAX_EVENT_PARAMS
                } else {
                    MAX_PARAMS
                };
                check_params(params, max)?;
                put_u16(&mut body, *code);
                put_u32(&mut body, *transaction_id);
                params.iter().for_each(|p| put_u32(&mut body, *p));
            }
            Packet::StartData {
                transaction_id,
                total,
            } => {
                put_u32(&mut body, *transaction_id);
                body.extend_from_slice(&total.to_le_bytes());
            }
            Packet::Data {
                transaction_id,
                payload,
            }
            | Packet::EndData {
                transaction_id,
                payload,
            } => {
                if payload.len() > MAX_DATA_PACKET {
                    return Err(malformed(format!(
                        "a data packet of {} bytes (at most {MAX_DATA_PACKET})",
                        payload.len()
                    )));
                }
                put_u32(&mut body, *transaction_id);
                body.extend_from_slice(payload);
            }
            Packet::Cancel { transaction_id } => put_u32(&mut body, *transaction_id),
        }
        let len = u32::try_from(PACKET_HEADER_LEN + body.len())
            .map_err(|_| malformed("packet longer than 4 GiB"))?;
        let mut out = Vec::with_capacity(PACKET_HEADER_LEN + body.len());
        put_u32(&mut out, len);
        put_u32(&mut out, self.packet_type() as u32);
        out.extend_from_slice(&body);
        Ok(out)
    }

    /// Decodes one whole packet (header and body).
    pub fn decode(bytes: &[u8]) -> Result<Packet, IpError> {
        let (ty, len) = decode_header(bytes)?;
        if bytes.len() != len {
            return Err(malformed(format!(
                "the header says {len} bytes, {} arrived",
                bytes.len()
            )));
        }
        Packet::decode_body(ty, &bytes[PACKET_HEADER_LEN..])
    }

    /// Decodes a packet's body, the bytes after its header.
    pub fn decode_body(ty: PacketType, body: &[u8]) -> Result<Packet, IpError> {
        let mut r = Reader::new(body);
        let u32_of = |r: &mut Reader<'_>| r.u32().map_err(malformed);
        let packet = match ty {
            PacketType::InitCommandRequest => Packet::InitCommandRequest(read_identity(&mut r)?),
            PacketType::InitCommandAck => {
                let connection = u32_of(&mut r)?;
                Packet::InitCommandAck {
                    connection,
                    identity: read_identity(&mut r)?,
                }
            }
            PacketType::InitEventRequest => Packet::InitEventRequest {
                connection: u32_of(&mut r)?,
            },
            PacketType::InitEventAck => Packet::InitEventAck,
            PacketType::InitFail => Packet::InitFail(FailReason::from_code(u32_of(&mut r)?)),
            PacketType::OperationRequest => {
                let data_phase = DataPhase::from_code(u32_of(&mut r)?);
                let code = r.u16().map_err(malformed)?;
                let transaction_id = u32_of(&mut r)?;
                let params = read_params(&mut r, body.len() - 10, MAX_PARAMS)?;
                Packet::OperationRequest {
                    data_phase,
                    code,
                    transaction_id,
                    params,
                }
            }
            PacketType::OperationResponse | PacketType::Event => {
                let code = r.u16().map_err(malformed)?;
                let transaction_id = u32_of(&mut r)?;
                if ty == PacketType::Event {
                    let params = read_params(&mut r, body.len() - 6, MAX_EVENT_PARAMS)?;
                    Packet::Event {
                        code,
                        transaction_id,
                        params,
                    }
                } else {
                    let params = read_params(&mut r, body.len() - 6, MAX_PARAMS)?;
                    Packet::OperationResponse {
                        code,
                        transaction_id,
                        params,
                    }
                }
            }
            PacketType::StartData => {
                let transaction_id = u32_of(&mut r)?;
                let lo = u64::from(u32_of(&mut r)?);
                let hi = u64::from(u32_of(&mut r)?);
                Packet::StartData {
                    transaction_id,
                    total: hi << 32 | lo,
                }
            }
            PacketType::Data | PacketType::EndData => {
                let transaction_id = u32_of(&mut r)?;
                let payload = body[4..].to_vec();
                r.bytes(payload.len()).map_err(malformed)?;
                if ty == PacketType::Data {
                    Packet::Data {
                        transaction_id,
                        payload,
                    }
                } else {
                    Packet::EndData {
                        transaction_id,
                        payload,
                    }
                }
            }
            PacketType::Cancel => Packet::Cancel {
                transaction_id: u32_of(&mut r)?,
            },
            PacketType::ProbeRequest => Packet::ProbeRequest,
            PacketType::ProbeResponse => Packet::ProbeResponse,
        };
        r.finish().map_err(malformed)?;
        Ok(packet)
    }
}

/// A packet header's type and length, checked against the type's bounds.
fn decode_header(bytes: &[u8]) -> Result<(PacketType, usize), IpError> {
    let mut r = Reader::new(bytes);
    let len = r.u32().map_err(malformed)? as usize;
    let raw = r.u32().map_err(malformed)?;
    let ty = PacketType::from_u32(raw).ok_or_else(|| malformed(format!("packet type {raw}")))?;
    if len < PACKET_HEADER_LEN || len > ty.max_len() {
        return Err(malformed(format!(
            "a {ty} packet of {len} bytes (8 to {})",
            ty.max_len()
        )));
    }
    Ok((ty, len))
}

/// Reads one packet from a stream. The length is checked against the
/// packet type's bound before anything is allocated, so a hostile length
/// costs nothing.
pub async fn read_packet<R: AsyncRead + Unpin>(r: &mut R) -> Result<Packet, IpError> {
    let mut head = [0u8; PACKET_HEADER_LEN];
    r.read_exact(&mut head).await?;
    let (ty, len) = decode_header(&head)?;
    let mut body = vec![0u8; len - PACKET_HEADER_LEN];
    r.read_exact(&mut body).await?;
    Packet::decode_body(ty, &body)
}

/// Writes one packet to a stream.
pub async fn write_packet<W: AsyncWrite + Unpin>(w: &mut W, p: &Packet) -> Result<(), IpError> {
    let bytes = p.encode()?;
    w.write_all(&bytes).await?;
    w.flush().await?;
    Ok(())
}

/// A USB Command container as an Operation Request.
fn request_of(cmd: &Container, data_out: bool) -> Packet {
    Packet::OperationRequest {
        data_phase: if data_out {
            DataPhase::Out
        } else {
            DataPhase::NoneOrIn
        },
        code: cmd.code,
        transaction_id: cmd.transaction_id,
        params: cmd.params(),
    }
}

/// A data phase as Start Data, Data packets of [`DATA_CHUNK`] and End Data.
/// `declared` is the length announced, which a cut transfer exceeds.
fn data_packets(transaction_id: u32, payload: &[u8], declared: u64) -> Vec<Packet> {
    let mut out = vec![Packet::StartData {
        transaction_id,
        total: declared,
    }];
    let mut chunks = payload.chunks(DATA_CHUNK).peekable();
    if chunks.peek().is_none() {
        out.push(Packet::EndData {
            transaction_id,
            payload: Vec::new(),
        });
    }
    while let Some(c) = chunks.next() {
        let payload = c.to_vec();
        out.push(if chunks.peek().is_some() {
            Packet::Data {
                transaction_id,
                payload,
            }
        } else {
            Packet::EndData {
                transaction_id,
                payload,
            }
        });
    }
    out
}

/// Reads the Data and End Data packets of a data phase announced as `total`
/// bytes. Returns the bytes, shorter than `total` when End Data came early
/// (a cut transfer).
async fn read_data_phase<R: AsyncRead + Unpin>(
    r: &mut R,
    transaction_id: u32,
    total: u64,
) -> Result<Vec<u8>, IpError> {
    let total = usize::try_from(total)
        .ok()
        .filter(|&t| t <= MAX_DATA_PACKET)
        .ok_or_else(|| malformed(format!("a data phase of {total} bytes")))?;
    let mut data = Vec::new();
    loop {
        let (tid, payload, last) = match read_packet(r).await? {
            Packet::Data {
                transaction_id,
                payload,
            } => (transaction_id, payload, false),
            Packet::EndData {
                transaction_id,
                payload,
            } => (transaction_id, payload, true),
            other => {
                return Err(IpError::Unexpected {
                    got: other.packet_type(),
                    wanted: "Data or EndData".into(),
                })
            }
        };
        if tid != transaction_id {
            return Err(malformed(format!(
                "data of transaction {tid} inside transaction {transaction_id}"
            )));
        }
        if data.len() + payload.len() > total {
            return Err(malformed(format!(
                "more data than the {total} bytes Start Data announced"
            )));
        }
        data.extend_from_slice(&payload);
        if last {
            return Ok(data);
        }
    }
}

/// The container a Data phase becomes on the USB-shaped link: its header
/// announces `declared` bytes, so a cut phase reads as a truncated transfer.
fn data_container(code: u16, transaction_id: u32, payload: &[u8], declared: usize) -> Vec<u8> {
    let len = u32::try_from(HEADER_LEN + declared).unwrap_or(u32::MAX);
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len());
    put_u32(&mut out, len);
    put_u16(&mut out, ContainerKind::Data as u16);
    put_u16(&mut out, code);
    put_u32(&mut out, transaction_id);
    out.extend_from_slice(payload);
    out
}

/// The initiator's end of a PTP/IP camera: a [`HostEnd`] for data-in,
/// responses and events, plus a sender of operations, each with its
/// data-out phase, since an Operation Request must say whether data follows.
#[derive(Debug)]
pub struct IpHost {
    /// Reads the camera's containers (bulk-in) and events (interrupt-in).
    pub host: HostEnd,
    operations: mpsc::UnboundedSender<(Vec<u8>, Option<Vec<u8>>)>,
    /// Why the connection ended, once it has (set by the pump).
    ended: std::sync::Arc<std::sync::Mutex<Option<IpError>>>,
}

impl IpHost {
    /// Sends one operation: a USB Command container and, for an operation
    /// that sends data, its Data container.
    pub fn send_operation(
        &mut self,
        command: Vec<u8>,
        data_out: Option<Vec<u8>>,
    ) -> Result<(), IpError> {
        self.operations
            .send((command, data_out))
            .map_err(|_| self.end_reason())
    }

    /// Why the connection ended: a malformed packet names itself; anything
    /// else is a closed connection.
    pub fn end_reason(&self) -> IpError {
        self.ended
            .lock()
            .ok()
            .and_then(|e| e.clone())
            .unwrap_or(IpError::Closed)
    }
}

/// Opens a PTP/IP session as the initiator: the init handshake on the
/// command connection, then `open_event` for the event connection and its
/// handshake. Returns the camera's identity and the end the driver uses;
/// pump tasks on the current runtime carry the traffic until either
/// connection ends or sends a malformed packet, which closes both.
pub async fn initiator<C, E, F, Fut>(
    mut command: C,
    open_event: F,
    me: &Identity,
) -> Result<(Identity, IpHost), IpError>
where
    C: AsyncRead + AsyncWrite + Send + Unpin + 'static,
    E: AsyncRead + AsyncWrite + Send + Unpin + 'static,
    F: FnOnce() -> Fut,
    Fut: std::future::Future<Output = Result<E, IpError>>,
{
    write_packet(&mut command, &Packet::InitCommandRequest(me.clone())).await?;
    let (connection, camera) = match read_packet(&mut command).await? {
        Packet::InitCommandAck {
            connection,
            identity,
        } => (connection, identity),
        Packet::InitFail(reason) => return Err(IpError::Refused(reason)),
        other => {
            return Err(IpError::Unexpected {
                got: other.packet_type(),
                wanted: "InitCommandAck".into(),
            })
        }
    };
    let mut event = open_event().await?;
    write_packet(&mut event, &Packet::InitEventRequest { connection }).await?;
    match read_packet(&mut event).await? {
        Packet::InitEventAck => {}
        Packet::InitFail(reason) => return Err(IpError::Refused(reason)),
        other => {
            return Err(IpError::Unexpected {
                got: other.packet_type(),
                wanted: "InitEventAck".into(),
            })
        }
    }
    let (host, dev) = link::pair();
    let (operations, ops_rx) = mpsc::unbounded_channel();
    let ended = std::sync::Arc::new(std::sync::Mutex::new(None));
    tokio::spawn(pump_initiator(command, event, dev, ops_rx, ended.clone()));
    Ok((
        camera,
        IpHost {
            host,
            operations,
            ended,
        },
    ))
}

fn record(ended: &std::sync::Mutex<Option<IpError>>, e: IpError) {
    if let Ok(mut slot) = ended.lock() {
        slot.get_or_insert(e);
    }
}

/// Carries an initiator's traffic: operations out, data, responses and
/// events in, as USB containers on `dev`. Ends (dropping `dev`, which
/// closes the link) when a connection ends or misbehaves.
async fn pump_initiator<C, E>(
    command: C,
    mut event: E,
    dev: DeviceEnd,
    mut operations: mpsc::UnboundedReceiver<(Vec<u8>, Option<Vec<u8>>)>,
    ended: std::sync::Arc<std::sync::Mutex<Option<IpError>>>,
) where
    C: AsyncRead + AsyncWrite + Send + Unpin + 'static,
    E: AsyncRead + AsyncWrite + Send + Unpin + 'static,
{
    let (mut rd, mut wr) = tokio::io::split(command);
    // The operation whose data phase may arrive: Data containers carry its
    // code, which PTP/IP's data packets do not.
    let (current_tx, mut current_rx) = tokio::sync::watch::channel((0u16, 0u32));
    let (probe_tx, mut probe_rx) = mpsc::unbounded_channel::<()>();
    let send = async {
        loop {
            // A waiting probe is answered before the next operation goes out,
            // so the camera's liveness check never waits behind a transfer.
            let (cmd, data) = tokio::select! {
                biased;
                Some(()) = probe_rx.recv() => {
                    write_packet(&mut wr, &Packet::ProbeResponse).await?;
                    continue;
                }
                op = operations.recv() => match op {
                    Some(op) => op,
                    None => return Err(IpError::Closed),
                },
            };
            let container = Container::decode(&cmd).map_err(malformed)?;
            if container.kind != ContainerKind::Command {
                return Err(malformed("only Command containers start an operation"));
            }
            let _ = current_tx.send((container.code, container.transaction_id));
            write_packet(&mut wr, &request_of(&container, data.is_some())).await?;
            if let Some(d) = data {
                let data = Container::decode(&d).map_err(malformed)?;
                let total = data.payload.len() as u64;
                for p in data_packets(container.transaction_id, &data.payload, total) {
                    write_packet(&mut wr, &p).await?;
                }
            }
        }
    };
    let receive = async {
        loop {
            match read_packet(&mut rd).await? {
                Packet::StartData {
                    transaction_id,
                    total,
                } => {
                    let bytes = read_data_phase(&mut rd, transaction_id, total).await?;
                    let (code, tid) = *current_rx.borrow_and_update();
                    let code = if tid == transaction_id { code } else { 0 };
                    let declared = usize::try_from(total).unwrap_or(usize::MAX);
                    dev.write_in(data_container(code, transaction_id, &bytes, declared))
                        .map_err(|_| IpError::Closed)?;
                }
                Packet::OperationResponse {
                    code,
                    transaction_id,
                    params,
                } => {
                    let c = Container::with_params(
                        ContainerKind::Response,
                        code,
                        transaction_id,
                        &params,
                    )
                    .and_then(|c| c.encode())
                    .map_err(malformed)?;
                    dev.write_in(c).map_err(|_| IpError::Closed)?;
                }
                Packet::ProbeRequest => probe_tx.send(()).map_err(|_| IpError::Closed)?,
                Packet::ProbeResponse => {}
                other => {
                    return Err(IpError::Unexpected {
                        got: other.packet_type(),
                        wanted: "StartData or OperationResponse on the command connection".into(),
                    })
                }
            }
        }
    };
    let events = async {
        loop {
            match read_packet(&mut event).await? {
                Packet::Event {
                    code,
                    transaction_id,
                    params,
                } => {
                    let c =
                        Container::with_params(ContainerKind::Event, code, transaction_id, &params)
                            .and_then(|c| c.encode())
                            .map_err(malformed)?;
                    dev.write_interrupt(c).map_err(|_| IpError::Closed)?;
                }
                Packet::ProbeRequest => write_packet(&mut event, &Packet::ProbeResponse).await?,
                Packet::ProbeResponse => {}
                other => {
                    return Err(IpError::Unexpected {
                        got: other.packet_type(),
                        wanted: "Event on the event connection".into(),
                    })
                }
            }
        }
    };
    let why: Result<(), IpError> = tokio::select! {
        r = send => r,
        r = receive => r,
        r = events => r,
    };
    if let Err(e) = why {
        record(&ended, e);
    }
}

/// Serves a firmware written for the USB-shaped link over an established
/// PTP/IP session (both connections past their handshake): operations
/// become Command and Data containers on `host`, the firmware's data,
/// responses and events become packets. Returns when either connection or
/// the firmware ends, or the initiator sends a malformed packet; the reason
/// is returned for the log.
pub async fn serve_device<C, E>(command: C, mut event: E, host: HostEnd) -> IpError
where
    C: AsyncRead + AsyncWrite + Send + Unpin,
    E: AsyncRead + AsyncWrite + Send + Unpin,
{
    let link::HostParts {
        bulk_out,
        mut bulk_in,
        mut interrupt_in,
    } = host.into_parts();
    let (mut rd, mut wr) = tokio::io::split(command);
    // The firmware's data and responses and the probe answers leave by one
    // queue, so their packets never interleave.
    let (cmd_tx, mut cmd_rx) = mpsc::unbounded_channel::<Packet>();
    let requests = async {
        loop {
            match read_packet(&mut rd).await? {
                Packet::OperationRequest {
                    data_phase,
                    code,
                    transaction_id,
                    params,
                } => {
                    let cmd = Container::with_params(
                        ContainerKind::Command,
                        code,
                        transaction_id,
                        &params,
                    )
                    .and_then(|c| c.encode())
                    .map_err(malformed)?;
                    bulk_out.send(cmd).map_err(closed)?;
                    if data_phase == DataPhase::Out {
                        let total = match read_packet(&mut rd).await? {
                            Packet::StartData {
                                transaction_id: t,
                                total,
                            } if t == transaction_id => total,
                            other => {
                                return Err(IpError::Unexpected {
                                    got: other.packet_type(),
                                    wanted: format!("StartData of transaction {transaction_id}"),
                                })
                            }
                        };
                        let bytes = read_data_phase(&mut rd, transaction_id, total).await?;
                        let declared = usize::try_from(total).unwrap_or(usize::MAX);
                        bulk_out
                            .send(data_container(code, transaction_id, &bytes, declared))
                            .map_err(closed)?;
                    }
                }
                Packet::ProbeRequest => cmd_tx.send(Packet::ProbeResponse).map_err(closed)?,
                Packet::Cancel { .. } | Packet::ProbeResponse => {}
                other => {
                    return Err(IpError::Unexpected {
                        got: other.packet_type(),
                        wanted: "OperationRequest".into(),
                    })
                }
            }
        }
    };
    let transfers = async {
        while let Some(bytes) = bulk_in.recv().await {
            for p in packets_of_transfer(&bytes)? {
                cmd_tx.send(p).map_err(closed)?;
            }
        }
        Err::<(), IpError>(IpError::Closed)
    };
    let events = async {
        loop {
            tokio::select! {
                ev = interrupt_in.recv() => {
                    let c = Container::decode(&ev.ok_or(IpError::Closed)?).map_err(malformed)?;
                    let p = Packet::Event {
                        code: c.code,
                        transaction_id: c.transaction_id,
                        params: c.params(),
                    };
                    write_packet(&mut event, &p).await?;
                }
                p = read_packet(&mut event) => match p? {
                    Packet::ProbeRequest => write_packet(&mut event, &Packet::ProbeResponse).await?,
                    Packet::ProbeResponse => {}
                    other => {
                        return Err::<(), IpError>(IpError::Unexpected {
                            got: other.packet_type(),
                            wanted: "nothing but probes on the event connection".into(),
                        })
                    }
                },
            }
        }
    };
    let send = async {
        while let Some(p) = cmd_rx.recv().await {
            write_packet(&mut wr, &p).await?;
        }
        Err::<(), IpError>(IpError::Closed)
    };
    let why: Result<(), IpError> = tokio::select! {
        r = requests => r,
        r = transfers => r,
        r = events => r,
        r = send => r,
    };
    why.err().unwrap_or(IpError::Closed)
}

/// A channel's send failed: the other side of the bridge is gone.
fn closed<T>(_: T) -> IpError {
    IpError::Closed
}

/// The packets one bulk-in transfer of the firmware becomes.
fn packets_of_transfer(bytes: &[u8]) -> Result<Vec<Packet>, IpError> {
    let header = super::Header::decode(bytes).map_err(malformed)?;
    match header.kind {
        ContainerKind::Data => {
            let declared = u64::from(header.length).saturating_sub(HEADER_LEN as u64);
            Ok(data_packets(
                header.transaction_id,
                &bytes[HEADER_LEN..],
                declared,
            ))
        }
        ContainerKind::Response => {
            let c = Container::decode(bytes).map_err(malformed)?;
            Ok(vec![Packet::OperationResponse {
                code: c.code,
                transaction_id: c.transaction_id,
                params: c.params(),
            }])
        }
        other => Err(malformed(format!("the firmware sent a {other} on bulk-in"))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn id(name: &str) -> Identity {
        Identity {
            guid: [7; 16],
            name: name.into(),
            version: PROTOCOL_VERSION,
        }
    }

    #[test]
    fn init_command_request_has_dc005_layout() {
        let bytes = Packet::InitCommandRequest(id("ab"))
            .encode()
            .unwrap_or_else(|e| panic!("{e}"));
        // 8 header + 16 GUID + "ab\0" in UTF-16 + version.
        assert_eq!(bytes.len(), 8 + 16 + 6 + 4);
        assert_eq!(&bytes[..8], &[34, 0, 0, 0, 1, 0, 0, 0]);
        assert_eq!(&bytes[24..30], &[b'a', 0, b'b', 0, 0, 0]);
        assert_eq!(&bytes[30..], &[0, 0, 1, 0]);
    }

    #[test]
    fn hostile_lengths_and_types_are_refused_before_allocating() {
        // A control packet claiming 4 GiB, a data packet over the bound, a
        // length under the header, an unknown type.
        for head in [
            [0xFF, 0xFF, 0xFF, 0xFF, 6, 0, 0, 0],
            [0xFF, 0xFF, 0xFF, 0xFF, 10, 0, 0, 0],
            [4, 0, 0, 0, 6, 0, 0, 0],
            [8, 0, 0, 0, 99, 0, 0, 0],
        ] {
            assert!(matches!(decode_header(&head), Err(IpError::Malformed(_))));
        }
    }

    #[test]
    fn short_and_overlong_bodies_are_malformed() {
        // An operation request with 6 parameters, an event with 4, a name
        // without its NUL.
        let mut req = vec![0u8; 8 + 10 + 24];
        let n = req.len() as u32;
        req[..4].copy_from_slice(&n.to_le_bytes());
        req[4] = 6;
        assert!(Packet::decode(&req).is_err());
        let mut ev = vec![0u8; 8 + 6 + 16];
        let n = ev.len() as u32;
        ev[..4].copy_from_slice(&n.to_le_bytes());
        ev[4] = 8;
        assert!(Packet::decode(&ev).is_err());
        let mut init = vec![0u8; 8 + 16 + 4];
        let n = init.len() as u32;
        init[..4].copy_from_slice(&n.to_le_bytes());
        init[4] = 1;
        init[24..28].copy_from_slice(&[b'x', 0, b'y', 0]);
        assert!(Packet::decode(&init).is_err());
    }

    #[test]
    fn a_data_phase_splits_and_reassembles() {
        let payload: Vec<u8> = (0..DATA_CHUNK * 2 + 5).map(|i| i as u8).collect();
        let packets = data_packets(9, &payload, payload.len() as u64);
        assert_eq!(packets.len(), 4);
        assert!(matches!(packets[3], Packet::EndData { .. }));
        let empty = data_packets(9, &[], 0);
        assert_eq!(empty.len(), 2);
    }

    /// A responder that completes the handshake, then answers the first
    /// operation with a packet of an unknown type: the initiator's link
    /// closes, and the reason names the malformed packet.
    #[tokio::test]
    async fn a_malformed_packet_closes_the_session_with_its_reason() {
        let (cmd_host, mut cmd_cam) = tokio::io::duplex(4096);
        let (evt_host, mut evt_cam) = tokio::io::duplex(4096);
        let camera = tokio::spawn(async move {
            let first = read_packet(&mut cmd_cam).await;
            assert!(matches!(first, Ok(Packet::InitCommandRequest(_))));
            let ack = Packet::InitCommandAck {
                connection: 1,
                identity: id("cam"),
            };
            write_packet(&mut cmd_cam, &ack)
                .await
                .unwrap_or_else(|e| panic!("{e}"));
            let ev = read_packet(&mut evt_cam).await;
            assert_eq!(ev, Ok(Packet::InitEventRequest { connection: 1 }));
            write_packet(&mut evt_cam, &Packet::InitEventAck)
                .await
                .unwrap_or_else(|e| panic!("{e}"));
            let op = read_packet(&mut cmd_cam).await;
            assert!(matches!(op, Ok(Packet::OperationRequest { .. })));
            cmd_cam
                .write_all(&[8, 0, 0, 0, 99, 0, 0, 0])
                .await
                .unwrap_or_else(|e| panic!("{e}"));
            (cmd_cam, evt_cam)
        });
        let (cam, mut ip) = initiator(cmd_host, || async { Ok(evt_host) }, &id("host"))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(cam.name, "cam");
        let cmd = Container::with_params(ContainerKind::Command, 0x1001, 0, &[])
            .and_then(|c| c.encode())
            .unwrap_or_else(|e| panic!("{e}"));
        ip.send_operation(cmd, None)
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(ip.host.bulk_in(1024).await.is_err());
        assert!(
            matches!(ip.end_reason(), IpError::Malformed(ref m) if m.contains("packet type 99")),
            "{:?}",
            ip.end_reason()
        );
        let _streams = camera.await;
    }

    #[tokio::test]
    async fn a_refused_connection_says_why() {
        let (cmd_host, mut cmd_cam) = tokio::io::duplex(4096);
        tokio::spawn(async move {
            let _ = read_packet(&mut cmd_cam).await;
            let _ = write_packet(&mut cmd_cam, &Packet::InitFail(FailReason::Busy)).await;
            cmd_cam
        });
        let r = initiator(
            cmd_host,
            || async { Err::<tokio::io::DuplexStream, _>(IpError::Closed) },
            &id("host"),
        )
        .await;
        assert!(matches!(r, Err(IpError::Refused(FailReason::Busy))));
    }

    fn arb_packet() -> impl Strategy<Value = Packet> {
        let params = |n| proptest::collection::vec(any::<u32>(), 0..=n);
        let ident = ("[a-zA-Z0-9 ._-]{0,40}", any::<[u8; 16]>(), any::<u32>()).prop_map(
            |(name, guid, version)| Identity {
                guid,
                name,
                version,
            },
        );
        prop_oneof![
            ident.clone().prop_map(Packet::InitCommandRequest),
            (any::<u32>(), ident).prop_map(|(connection, identity)| Packet::InitCommandAck {
                connection,
                identity
            }),
            any::<u32>().prop_map(|connection| Packet::InitEventRequest { connection }),
            Just(Packet::InitEventAck),
            prop_oneof![
                Just(FailReason::Rejected),
                Just(FailReason::Busy),
                Just(FailReason::Unspecified)
            ]
            .prop_map(Packet::InitFail),
            (1u32..3, any::<u16>(), any::<u32>(), params(5)).prop_map(|(d, code, t, params)| {
                Packet::OperationRequest {
                    data_phase: DataPhase::from_code(d),
                    code,
                    transaction_id: t,
                    params,
                }
            }),
            (any::<u16>(), any::<u32>(), params(5)).prop_map(|(code, t, params)| {
                Packet::OperationResponse {
                    code,
                    transaction_id: t,
                    params,
                }
            }),
            (any::<u16>(), any::<u32>(), params(3)).prop_map(|(code, t, params)| Packet::Event {
                code,
                transaction_id: t,
                params
            }),
            (any::<u32>(), any::<u64>()).prop_map(|(t, total)| Packet::StartData {
                transaction_id: t,
                total
            }),
            (any::<u32>(), proptest::collection::vec(any::<u8>(), 0..64)).prop_map(
                |(t, payload)| Packet::Data {
                    transaction_id: t,
                    payload
                }
            ),
            (any::<u32>(), proptest::collection::vec(any::<u8>(), 0..64)).prop_map(
                |(t, payload)| Packet::EndData {
                    transaction_id: t,
                    payload
                }
            ),
            any::<u32>().prop_map(|t| Packet::Cancel { transaction_id: t }),
            Just(Packet::ProbeRequest),
            Just(Packet::ProbeResponse),
        ]
    }

    proptest! {
        #[test]
        fn packets_round_trip(p in arb_packet()) {
            let bytes = p.encode().unwrap_or_else(|e| panic!("{e}"));
            prop_assert_eq!(Packet::decode(&bytes), Ok(p));
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..128)) {
            let _ = Packet::decode(&bytes);
        }
    }
}
