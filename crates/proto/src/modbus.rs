//! Server-side Modbus frame codec for the lamp/laser relay module
//! (protocol: `firmware-protocols/modbus-lamps.md`).
//!
//! Scope: what a small relay module needs to serve any byte stream. Requests
//! are decoded, responses and exceptions encoded, in both framings:
//!
//! - [`Framing::Tcp`]: MBAP header `transaction (2) | protocol 0 (2) |
//!   length (2, unit + PDU) | unit (1)`, then the PDU, no checksum.
//! - [`Framing::Rtu`]: `unit (1) | PDU | CRC-16 (2, low byte first)`. RTU has
//!   no length field: a request's length follows from its function code
//!   (8 bytes for FC01..06, 9 + byte count for FC0F/FC10), so only those
//!   function codes can be framed.
//!
//! Decoding is incremental and total: [`decode_request`] returns `Ok(None)`
//! while a frame is incomplete, consumes exactly one frame on success and
//! nothing on error. After an error the caller resyncs: on RTU by dropping
//! one byte and retrying (a serial line has no other frame boundary here);
//! on TCP by closing the connection, as real servers do.
//!
//! A frame that is well formed but carries a value the Modbus specification
//! forbids (a coil value other than `FF 00`/`00 00`, a quantity out of range,
//! a byte count that does not match the quantity) or an unknown function
//! code (TCP only) decodes to [`RequestPdu::Rejected`]: the server answers it
//! with the exception it names instead of dropping the link.

/// How frames are delimited on the byte stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Framing {
    /// Modbus TCP (MBAP header).
    Tcp,
    /// Modbus RTU (unit id first, CRC-16 last), e.g. over RS-485 or a
    /// transparent RS-485/Ethernet gateway.
    Rtu,
}

/// The addressing part of a frame. `transaction` is 0 on RTU, which has none.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    /// Transaction identifier of the MBAP header, echoed in the response
    /// (0 on RTU).
    pub transaction: u16,
    /// Unit identifier: the MBAP header's last byte, or the RTU frame's
    /// first (slave address).
    pub unit: u8,
}

/// FC01..04: at most this many coils/inputs per read.
pub const MAX_READ_BITS: u16 = 2000;
/// FC03/04: at most this many registers per read.
pub const MAX_READ_REGISTERS: u16 = 125;
/// FC0F: at most this many coils per write.
pub const MAX_WRITE_COILS: u16 = 1968;
/// FC10: at most this many registers per write.
pub const MAX_WRITE_REGISTERS: u16 = 123;

/// Largest MBAP length field (unit + a 253-byte PDU).
const MAX_MBAP_LEN: u16 = 254;

/// A decoded request PDU.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RequestPdu {
    /// FC01.
    ReadCoils {
        /// Address of the first coil (0-based).
        addr: u16,
        /// Number of coils to read, 1..=[`MAX_READ_BITS`].
        count: u16,
    },
    /// FC02.
    ReadDiscreteInputs {
        /// Address of the first discrete input (0-based).
        addr: u16,
        /// Number of inputs to read, 1..=[`MAX_READ_BITS`].
        count: u16,
    },
    /// FC03.
    ReadHoldingRegisters {
        /// Address of the first holding register (0-based).
        addr: u16,
        /// Number of registers to read, 1..=[`MAX_READ_REGISTERS`].
        count: u16,
    },
    /// FC04.
    ReadInputRegisters {
        /// Address of the first input register (0-based).
        addr: u16,
        /// Number of registers to read, 1..=[`MAX_READ_REGISTERS`].
        count: u16,
    },
    /// FC05 (`FF 00` on, `00 00` off).
    WriteSingleCoil {
        /// Address of the coil (0-based).
        addr: u16,
        /// The value to write: `FF 00` on the wire for on, `00 00` for off.
        on: bool,
    },
    /// FC06.
    WriteSingleRegister {
        /// Address of the register (0-based).
        addr: u16,
        /// The register value to write.
        value: u16,
    },
    /// FC0F.
    WriteMultipleCoils {
        /// Address of the first coil (0-based).
        addr: u16,
        /// The coil values in address order (the quantity is their number).
        values: Vec<bool>,
    },
    /// FC10.
    WriteMultipleRegisters {
        /// Address of the first register (0-based).
        addr: u16,
        /// The register values in address order (the quantity is their number).
        values: Vec<u16>,
    },
    /// A well-framed request to be answered with `exception`:
    /// [`Exception::IllegalFunction`] for an unknown function code (TCP
    /// only), [`Exception::IllegalDataValue`] for a forbidden value.
    /// `data` is the PDU after the function code, verbatim.
    Rejected {
        /// The request's function code.
        function: u8,
        /// The PDU bytes after the function code.
        data: Vec<u8>,
        /// The exception to answer with.
        exception: Exception,
    },
}

impl RequestPdu {
    /// The function code on the wire.
    pub fn function(&self) -> u8 {
        match self {
            RequestPdu::ReadCoils { .. } => 0x01,
            RequestPdu::ReadDiscreteInputs { .. } => 0x02,
            RequestPdu::ReadHoldingRegisters { .. } => 0x03,
            RequestPdu::ReadInputRegisters { .. } => 0x04,
            RequestPdu::WriteSingleCoil { .. } => 0x05,
            RequestPdu::WriteSingleRegister { .. } => 0x06,
            RequestPdu::WriteMultipleCoils { .. } => 0x0F,
            RequestPdu::WriteMultipleRegisters { .. } => 0x10,
            RequestPdu::Rejected { function, .. } => *function,
        }
    }
}

/// A normal (non-exception) response PDU.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ResponsePdu {
    /// FC01: coil bits, LSB first.
    ReadCoils(Vec<bool>),
    /// FC02.
    ReadDiscreteInputs(Vec<bool>),
    /// FC03: registers, big-endian.
    ReadHoldingRegisters(Vec<u16>),
    /// FC04.
    ReadInputRegisters(Vec<u16>),
    /// FC05: echo of the request.
    WriteSingleCoil {
        /// Address of the coil written.
        addr: u16,
        /// The value written (`FF 00` on, `00 00` off).
        on: bool,
    },
    /// FC06: echo of the request.
    WriteSingleRegister {
        /// Address of the register written.
        addr: u16,
        /// The value written.
        value: u16,
    },
    /// FC0F: address and quantity written.
    WriteMultipleCoils {
        /// Address of the first coil written.
        addr: u16,
        /// Number of coils written.
        count: u16,
    },
    /// FC10: address and quantity written.
    WriteMultipleRegisters {
        /// Address of the first register written.
        addr: u16,
        /// Number of registers written.
        count: u16,
    },
}

/// Modbus exception codes the module sends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Exception {
    /// 0x01: the function code is not supported.
    IllegalFunction = 0x01,
    /// 0x02: the coil or register address is not wired on this module.
    IllegalDataAddress = 0x02,
    /// 0x03: a value or quantity the Modbus specification forbids.
    IllegalDataValue = 0x03,
    /// 0x04 (slave device failure): the relay driver or a lamp ballast
    /// failed during a write.
    ServerDeviceFailure = 0x04,
}

/// Why bytes could not be framed. See the module docs for how to resync.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// TCP: the MBAP protocol identifier is not 0 (carries the value read).
    #[error("MBAP protocol id {0:#06x}, expected 0")]
    ProtocolId(u16),
    /// TCP: the MBAP length field is outside 2..=254 (carries the value read).
    #[error("MBAP length {0} out of range 2..=254")]
    Length(u16),
    /// RTU: the frame's CRC-16 does not match its bytes.
    #[error("RTU CRC {got:#06x}, computed {computed:#06x}")]
    Crc {
        /// The CRC the frame carries.
        got: u16,
        /// The CRC computed over the frame's bytes.
        computed: u16,
    },
    /// RTU: a function code whose frame length cannot be known, so the
    /// frame cannot be delimited (carries the code).
    #[error("RTU function code {0:#04x} cannot be framed (unknown length)")]
    UnknownFunction(u8),
    /// The PDU's length does not fit its function code (a fixed-size request
    /// of the wrong size, or a byte count that disagrees with the bytes).
    #[error("function {function:#04x}: PDU of {len} bytes does not match its fields")]
    Malformed {
        /// The PDU's function code (0 for an empty PDU).
        function: u8,
        /// Length of the PDU in bytes, function code included.
        len: usize,
    },
}

/// CRC-16/MODBUS: reflected polynomial 0xA001, initial value 0xFFFF. Sent
/// low byte first.
pub fn crc16(bytes: &[u8]) -> u16 {
    let mut crc = 0xFFFFu16;
    for &b in bytes {
        crc ^= u16::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xA001
            } else {
                crc >> 1
            };
        }
    }
    crc
}

fn be16(b: &[u8], at: usize) -> u16 {
    match (b.get(at), b.get(at + 1)) {
        (Some(&hi), Some(&lo)) => u16::from_be_bytes([hi, lo]),
        _ => 0,
    }
}

fn unpack_bits(bytes: &[u8], count: u16) -> Vec<bool> {
    (0..usize::from(count))
        .map(|i| bytes.get(i / 8).is_some_and(|b| b & (1 << (i % 8)) != 0))
        .collect()
}

fn pack_bits(bits: &[bool]) -> Vec<u8> {
    let mut out = vec![0u8; bits.len().div_ceil(8)];
    for (i, _) in bits.iter().enumerate().filter(|(_, &b)| b) {
        out[i / 8] |= 1 << (i % 8);
    }
    out
}

fn saturating_u8(n: usize) -> u8 {
    u8::try_from(n).unwrap_or(u8::MAX)
}

fn saturating_u16(n: usize) -> u16 {
    u16::try_from(n).unwrap_or(u16::MAX)
}

/// Parses one request PDU (function code first) whose extent is known.
fn parse_pdu(pdu: &[u8]) -> Result<RequestPdu, FrameError> {
    let Some((&function, data)) = pdu.split_first() else {
        return Err(FrameError::Malformed {
            function: 0,
            len: 0,
        });
    };
    let malformed = FrameError::Malformed {
        function,
        len: pdu.len(),
    };
    let rejected = |exception| RequestPdu::Rejected {
        function,
        data: data.to_vec(),
        exception,
    };
    let (addr, count) = (be16(data, 0), be16(data, 2));
    let req = match function {
        0x01..=0x06 if data.len() != 4 => return Err(malformed),
        0x01 | 0x02 if count == 0 || count > MAX_READ_BITS => rejected(Exception::IllegalDataValue),
        0x03 | 0x04 if count == 0 || count > MAX_READ_REGISTERS => {
            rejected(Exception::IllegalDataValue)
        }
        0x01 => RequestPdu::ReadCoils { addr, count },
        0x02 => RequestPdu::ReadDiscreteInputs { addr, count },
        0x03 => RequestPdu::ReadHoldingRegisters { addr, count },
        0x04 => RequestPdu::ReadInputRegisters { addr, count },
        0x05 => match count {
            0xFF00 => RequestPdu::WriteSingleCoil { addr, on: true },
            0x0000 => RequestPdu::WriteSingleCoil { addr, on: false },
            _ => rejected(Exception::IllegalDataValue),
        },
        0x06 => RequestPdu::WriteSingleRegister { addr, value: count },
        0x0F | 0x10 => {
            let byte_count = match data.get(4) {
                Some(&n) if data.len() == 5 + usize::from(n) => usize::from(n),
                _ => return Err(malformed),
            };
            let values = &data[5..];
            if function == 0x0F {
                if count == 0
                    || count > MAX_WRITE_COILS
                    || byte_count != usize::from(count).div_ceil(8)
                {
                    rejected(Exception::IllegalDataValue)
                } else {
                    RequestPdu::WriteMultipleCoils {
                        addr,
                        values: unpack_bits(values, count),
                    }
                }
            } else if count == 0
                || count > MAX_WRITE_REGISTERS
                || byte_count != 2 * usize::from(count)
            {
                rejected(Exception::IllegalDataValue)
            } else {
                RequestPdu::WriteMultipleRegisters {
                    addr,
                    values: values
                        .chunks_exact(2)
                        .map(|c| u16::from_be_bytes([c[0], c[1]]))
                        .collect(),
                }
            }
        }
        _ => rejected(Exception::IllegalFunction),
    };
    Ok(req)
}

/// Decodes one request from the front of `buf`, removing its bytes.
///
/// `Ok(None)`: more bytes are needed (nothing consumed). `Err`: the front of
/// `buf` is not a frame (nothing consumed); resync as the module docs say.
/// Never panics, whatever `buf` holds.
pub fn decode_request(
    framing: Framing,
    buf: &mut Vec<u8>,
) -> Result<Option<(Header, RequestPdu)>, FrameError> {
    match framing {
        Framing::Tcp => {
            if buf.len() < 7 {
                return Ok(None);
            }
            let protocol = be16(buf, 2);
            if protocol != 0 {
                return Err(FrameError::ProtocolId(protocol));
            }
            let len = be16(buf, 4);
            if !(2..=MAX_MBAP_LEN).contains(&len) {
                return Err(FrameError::Length(len));
            }
            let total = 6 + usize::from(len);
            if buf.len() < total {
                return Ok(None);
            }
            let hdr = Header {
                transaction: be16(buf, 0),
                unit: buf[6],
            };
            let pdu = parse_pdu(&buf[7..total])?;
            buf.drain(..total);
            Ok(Some((hdr, pdu)))
        }
        Framing::Rtu => {
            let Some(&function) = buf.get(1) else {
                return Ok(None);
            };
            let total = match function {
                0x01..=0x06 => 8,
                0x0F | 0x10 => match buf.get(6) {
                    Some(&n) => 9 + usize::from(n),
                    None => return Ok(None),
                },
                f => return Err(FrameError::UnknownFunction(f)),
            };
            if buf.len() < total {
                return Ok(None);
            }
            let got = u16::from_le_bytes([buf[total - 2], buf[total - 1]]);
            let computed = crc16(&buf[..total - 2]);
            if got != computed {
                return Err(FrameError::Crc { got, computed });
            }
            let hdr = Header {
                transaction: 0,
                unit: buf[0],
            };
            let pdu = parse_pdu(&buf[1..total - 2])?;
            buf.drain(..total);
            Ok(Some((hdr, pdu)))
        }
    }
}

/// Wraps a PDU in the framing's header (and CRC).
fn frame(framing: Framing, hdr: &Header, pdu: &[u8]) -> Vec<u8> {
    match framing {
        Framing::Tcp => {
            let mut out = Vec::with_capacity(7 + pdu.len());
            out.extend_from_slice(&hdr.transaction.to_be_bytes());
            out.extend_from_slice(&[0, 0]);
            out.extend_from_slice(&saturating_u16(pdu.len() + 1).to_be_bytes());
            out.push(hdr.unit);
            out.extend_from_slice(pdu);
            out
        }
        Framing::Rtu => {
            let mut out = Vec::with_capacity(3 + pdu.len());
            out.push(hdr.unit);
            out.extend_from_slice(pdu);
            let crc = crc16(&out);
            out.extend_from_slice(&crc.to_le_bytes());
            out
        }
    }
}

fn addr_value(function: u8, addr: u16, value: u16) -> Vec<u8> {
    let [a0, a1] = addr.to_be_bytes();
    let [v0, v1] = value.to_be_bytes();
    vec![function, a0, a1, v0, v1]
}

fn coil_value(on: bool) -> u16 {
    if on {
        0xFF00
    } else {
        0x0000
    }
}

/// Encodes a request (the client side; used by tests and tools). Writes
/// longer than one frame allows produce a frame the decoder rejects.
pub fn encode_request(framing: Framing, hdr: &Header, req: &RequestPdu) -> Vec<u8> {
    let f = req.function();
    let pdu = match req {
        RequestPdu::ReadCoils { addr, count }
        | RequestPdu::ReadDiscreteInputs { addr, count }
        | RequestPdu::ReadHoldingRegisters { addr, count }
        | RequestPdu::ReadInputRegisters { addr, count } => addr_value(f, *addr, *count),
        RequestPdu::WriteSingleCoil { addr, on } => addr_value(f, *addr, coil_value(*on)),
        RequestPdu::WriteSingleRegister { addr, value } => addr_value(f, *addr, *value),
        RequestPdu::WriteMultipleCoils { addr, values } => {
            let mut pdu = addr_value(f, *addr, saturating_u16(values.len()));
            let bytes = pack_bits(values);
            pdu.push(saturating_u8(bytes.len()));
            pdu.extend(bytes);
            pdu
        }
        RequestPdu::WriteMultipleRegisters { addr, values } => {
            let mut pdu = addr_value(f, *addr, saturating_u16(values.len()));
            pdu.push(saturating_u8(2 * values.len()));
            pdu.extend(values.iter().flat_map(|v| v.to_be_bytes()));
            pdu
        }
        RequestPdu::Rejected { data, .. } => {
            let mut pdu = vec![f];
            pdu.extend_from_slice(data);
            pdu
        }
    };
    frame(framing, hdr, &pdu)
}

/// Encodes a normal response. Reads are at most 250 data bytes when they
/// answer a request that decoded (the quantity limits guarantee it).
pub fn encode_response(framing: Framing, hdr: &Header, resp: &ResponsePdu) -> Vec<u8> {
    let bits = |f: u8, v: &[bool]| {
        let bytes = pack_bits(v);
        let mut pdu = vec![f, saturating_u8(bytes.len())];
        pdu.extend(bytes);
        pdu
    };
    let regs = |f: u8, v: &[u16]| {
        let mut pdu = vec![f, saturating_u8(2 * v.len())];
        pdu.extend(v.iter().flat_map(|r| r.to_be_bytes()));
        pdu
    };
    let pdu = match resp {
        ResponsePdu::ReadCoils(v) => bits(0x01, v),
        ResponsePdu::ReadDiscreteInputs(v) => bits(0x02, v),
        ResponsePdu::ReadHoldingRegisters(v) => regs(0x03, v),
        ResponsePdu::ReadInputRegisters(v) => regs(0x04, v),
        ResponsePdu::WriteSingleCoil { addr, on } => addr_value(0x05, *addr, coil_value(*on)),
        ResponsePdu::WriteSingleRegister { addr, value } => addr_value(0x06, *addr, *value),
        ResponsePdu::WriteMultipleCoils { addr, count } => addr_value(0x0F, *addr, *count),
        ResponsePdu::WriteMultipleRegisters { addr, count } => addr_value(0x10, *addr, *count),
    };
    frame(framing, hdr, &pdu)
}

/// Encodes an exception reply to a request with function code `function`:
/// the PDU is `function | 0x80, code`.
pub fn encode_exception(framing: Framing, hdr: &Header, function: u8, code: Exception) -> Vec<u8> {
    frame(framing, hdr, &[function | 0x80, code as u8])
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const H1: Header = Header {
        transaction: 0,
        unit: 1,
    };

    fn decode_all(
        framing: Framing,
        bytes: &[u8],
    ) -> Result<Option<(Header, RequestPdu)>, FrameError> {
        let mut buf = bytes.to_vec();
        let r = decode_request(framing, &mut buf);
        if let Ok(Some(_)) = r {
            assert!(buf.is_empty(), "left {buf:?}");
        } else {
            assert_eq!(buf, bytes, "consumed bytes without a frame");
        }
        r
    }

    #[test]
    fn crc_of_spec_frames() {
        // From firmware-protocols/modbus-lamps.md.
        assert_eq!(crc16(&[0x01, 0x05, 0x00, 0x09, 0xFF, 0x00]), 0x385C);
        assert_eq!(crc16(&[0x01, 0x85, 0x02]), 0x51C3);
        assert_eq!(
            crc16(&[0x01, 0x0F, 0x00, 0x00, 0x00, 0x09, 0x02, 0x00, 0x00]),
            0x7CE5
        );
        assert_eq!(crc16(&[0x01, 0x0F, 0x00, 0x00, 0x00, 0x09]), 0xCD95);
    }

    #[test]
    fn tcp_requests_decode_exactly() {
        let fc05 = [0, 7, 0, 0, 0, 6, 1, 0x05, 0, 2, 0xFF, 0];
        assert_eq!(
            decode_all(Framing::Tcp, &fc05),
            Ok(Some((
                Header {
                    transaction: 7,
                    unit: 1
                },
                RequestPdu::WriteSingleCoil { addr: 2, on: true }
            )))
        );
        let fc0f = [0, 1, 0, 0, 0, 9, 1, 0x0F, 0, 0, 0, 9, 2, 0b1000_0001, 1];
        let mut values = vec![false; 9];
        values[0] = true;
        values[7] = true;
        values[8] = true;
        assert_eq!(
            decode_all(Framing::Tcp, &fc0f),
            Ok(Some((
                Header {
                    transaction: 1,
                    unit: 1
                },
                RequestPdu::WriteMultipleCoils { addr: 0, values }
            )))
        );
    }

    #[test]
    fn incomplete_frames_need_more_bytes() {
        let fc04 = [0, 3, 0, 0, 0, 6, 1, 0x04, 0, 0, 0, 2];
        for n in 0..fc04.len() {
            assert_eq!(decode_all(Framing::Tcp, &fc04[..n]), Ok(None), "{n}");
        }
        let rtu = [
            0x01, 0x0F, 0x00, 0x00, 0x00, 0x09, 0x02, 0x00, 0x00, 0xE5, 0x7C,
        ];
        for n in 0..rtu.len() {
            assert_eq!(decode_all(Framing::Rtu, &rtu[..n]), Ok(None), "{n}");
        }
        assert!(matches!(
            decode_all(Framing::Rtu, &rtu),
            Ok(Some((_, RequestPdu::WriteMultipleCoils { addr: 0, .. })))
        ));
    }

    #[test]
    fn two_frames_in_one_buffer_decode_one_at_a_time() {
        let mut buf = encode_request(
            Framing::Rtu,
            &H1,
            &RequestPdu::ReadCoils { addr: 0, count: 3 },
        );
        buf.extend(encode_request(
            Framing::Rtu,
            &H1,
            &RequestPdu::ReadInputRegisters { addr: 0, count: 2 },
        ));
        assert_eq!(
            decode_request(Framing::Rtu, &mut buf),
            Ok(Some((H1, RequestPdu::ReadCoils { addr: 0, count: 3 })))
        );
        assert_eq!(buf.len(), 8);
        assert_eq!(
            decode_request(Framing::Rtu, &mut buf),
            Ok(Some((
                H1,
                RequestPdu::ReadInputRegisters { addr: 0, count: 2 }
            )))
        );
        assert!(buf.is_empty());
    }

    #[test]
    fn framing_errors() {
        assert_eq!(
            decode_all(Framing::Tcp, &[0, 1, 0, 1, 0, 6, 1, 1]),
            Err(FrameError::ProtocolId(1))
        );
        assert_eq!(
            decode_all(Framing::Tcp, &[0, 1, 0, 0, 0x10, 0, 1]),
            Err(FrameError::Length(0x1000))
        );
        assert_eq!(
            decode_all(Framing::Tcp, &[0, 1, 0, 0, 0, 1, 1]),
            Err(FrameError::Length(1))
        );
        // FC01 with a 3-byte body: the fields do not fit the MBAP length.
        assert_eq!(
            decode_all(Framing::Tcp, &[0, 1, 0, 0, 0, 5, 1, 1, 0, 0, 1]),
            Err(FrameError::Malformed {
                function: 1,
                len: 4
            })
        );
        assert_eq!(
            decode_all(
                Framing::Rtu,
                &[0x01, 0x05, 0x00, 0x09, 0xFF, 0x00, 0x5C, 0x39]
            ),
            Err(FrameError::Crc {
                got: 0x395C,
                computed: 0x385C
            })
        );
        assert_eq!(
            decode_all(Framing::Rtu, &[0x01, 0x2B, 0x0E]),
            Err(FrameError::UnknownFunction(0x2B))
        );
    }

    #[test]
    fn forbidden_values_are_rejected_not_dropped() {
        // FC05 with 0x1234 instead of FF00/0000 -> exception 03.
        let req = [0, 1, 0, 0, 0, 6, 1, 0x05, 0, 0, 0x12, 0x34];
        assert_eq!(
            decode_all(Framing::Tcp, &req),
            Ok(Some((
                Header {
                    transaction: 1,
                    unit: 1
                },
                RequestPdu::Rejected {
                    function: 5,
                    data: vec![0, 0, 0x12, 0x34],
                    exception: Exception::IllegalDataValue
                }
            )))
        );
        // FC0F for 9 coils with a 1-byte payload.
        let req = [0, 1, 0, 0, 0, 8, 1, 0x0F, 0, 0, 0, 9, 1, 0];
        assert!(matches!(
            decode_all(Framing::Tcp, &req),
            Ok(Some((
                _,
                RequestPdu::Rejected {
                    exception: Exception::IllegalDataValue,
                    ..
                }
            )))
        ));
        // FC01 for 0 coils.
        let req = encode_request(
            Framing::Rtu,
            &H1,
            &RequestPdu::Rejected {
                function: 1,
                data: vec![0, 0, 0, 0],
                exception: Exception::IllegalDataValue,
            },
        );
        assert!(matches!(
            decode_all(Framing::Rtu, &req),
            Ok(Some((
                _,
                RequestPdu::Rejected {
                    function: 1,
                    exception: Exception::IllegalDataValue,
                    ..
                }
            )))
        ));
        // TCP knows the length of an unknown function: exception 01.
        let req = [0, 1, 0, 0, 0, 3, 1, 0x2B, 0x0E];
        assert_eq!(
            decode_all(Framing::Tcp, &req),
            Ok(Some((
                Header {
                    transaction: 1,
                    unit: 1
                },
                RequestPdu::Rejected {
                    function: 0x2B,
                    data: vec![0x0E],
                    exception: Exception::IllegalFunction
                }
            )))
        );
    }

    #[test]
    fn responses_and_exceptions_encode_exactly() {
        let h = Header {
            transaction: 2,
            unit: 1,
        };
        assert_eq!(
            encode_response(Framing::Tcp, &h, &ResponsePdu::ReadCoils(vec![true])),
            vec![0, 2, 0, 0, 0, 4, 1, 1, 1, 1]
        );
        assert_eq!(
            encode_response(
                Framing::Tcp,
                &h,
                &ResponsePdu::ReadInputRegisters(vec![1, 0x0203])
            ),
            vec![0, 2, 0, 0, 0, 7, 1, 4, 4, 0, 1, 2, 3]
        );
        assert_eq!(
            encode_response(
                Framing::Rtu,
                &H1,
                &ResponsePdu::WriteMultipleCoils { addr: 0, count: 9 }
            ),
            vec![0x01, 0x0F, 0x00, 0x00, 0x00, 0x09, 0x95, 0xCD]
        );
        assert_eq!(
            encode_exception(Framing::Rtu, &H1, 0x05, Exception::IllegalDataAddress),
            vec![0x01, 0x85, 0x02, 0xC3, 0x51]
        );
        assert_eq!(
            encode_exception(Framing::Tcp, &h, 0x05, Exception::ServerDeviceFailure),
            vec![0, 2, 0, 0, 0, 3, 1, 0x85, 0x04]
        );
    }

    fn framing() -> impl Strategy<Value = Framing> {
        prop_oneof![Just(Framing::Tcp), Just(Framing::Rtu)]
    }

    fn request() -> impl Strategy<Value = RequestPdu> {
        let a = any::<u16>();
        prop_oneof![
            (a, 1..=MAX_READ_BITS).prop_map(|(addr, count)| RequestPdu::ReadCoils { addr, count }),
            (a, 1..=MAX_READ_BITS)
                .prop_map(|(addr, count)| RequestPdu::ReadDiscreteInputs { addr, count }),
            (a, 1..=MAX_READ_REGISTERS)
                .prop_map(|(addr, count)| RequestPdu::ReadHoldingRegisters { addr, count }),
            (a, 1..=MAX_READ_REGISTERS)
                .prop_map(|(addr, count)| RequestPdu::ReadInputRegisters { addr, count }),
            (a, any::<bool>()).prop_map(|(addr, on)| RequestPdu::WriteSingleCoil { addr, on }),
            (a, any::<u16>())
                .prop_map(|(addr, value)| RequestPdu::WriteSingleRegister { addr, value }),
            (
                a,
                proptest::collection::vec(any::<bool>(), 1..=usize::from(MAX_WRITE_COILS))
            )
                .prop_map(|(addr, values)| RequestPdu::WriteMultipleCoils { addr, values }),
            (
                a,
                proptest::collection::vec(any::<u16>(), 1..=usize::from(MAX_WRITE_REGISTERS))
            )
                .prop_map(|(addr, values)| RequestPdu::WriteMultipleRegisters { addr, values }),
        ]
    }

    proptest! {
        #[test]
        fn arbitrary_bytes_never_panic(
            framing in framing(),
            bytes in proptest::collection::vec(any::<u8>(), 0..300),
        ) {
            let mut buf = bytes.clone();
            // Decode as a server would: RTU drops a byte per error, TCP stops.
            loop {
                let before = buf.len();
                match decode_request(framing, &mut buf) {
                    Ok(Some(_)) => prop_assert!(buf.len() < before),
                    Ok(None) => break,
                    Err(_) if framing == Framing::Rtu && !buf.is_empty() => {
                        prop_assert_eq!(buf.len(), before);
                        buf.remove(0);
                    }
                    Err(_) => break,
                }
            }
        }

        #[test]
        fn requests_round_trip(
            framing in framing(),
            transaction in any::<u16>(),
            unit in any::<u8>(),
            req in request(),
        ) {
            let hdr = Header {
                transaction: if framing == Framing::Tcp { transaction } else { 0 },
                unit,
            };
            let bytes = encode_request(framing, &hdr, &req);
            let mut buf = bytes.clone();
            buf.extend_from_slice(&[0xAA, 0x55]);
            prop_assert_eq!(decode_request(framing, &mut buf), Ok(Some((hdr, req))));
            prop_assert_eq!(buf, vec![0xAA, 0x55]);
        }
    }
}
