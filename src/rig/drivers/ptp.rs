//! The PTP camera driver (ISO 15740 over USB, `firmware-protocols/ptp-camera.md`):
//! a [`Camera`] over any [`PtpPipe`], so the same code drives a real camera
//! through `nusb` and the simulated firmware through the in-memory link.
//!
//! Every transaction is command → optional data phase → response, with a
//! deadline through the [`Clock`]. Exposure is SetDevicePropValue
//! ExposureTime; `expose` is InitiateCapture plus waiting for ObjectAdded
//! and CaptureComplete on the interrupt endpoint; `transfer` is
//! GetObjectInfo, GetObject, DeleteObject.
//!
//! A frame is the object exactly as the camera delivered it (DNG, vendor
//! raw, TIFF or JPEG), kept as [`Frame::original`]; the driver decodes it
//! ([`camera_file`]) to refuse a broken file and to check that its colour
//! filter array is the one the profile describes.

use std::time::Duration;

use async_trait::async_trait;
use rigd_core::Cfa;
use rigd_core::Clock;
use rigd_proto::ptp::{
    exposure_to_prop, may_be_image, CodecError, Container, ContainerKind, DeviceInfo, EventCode,
    Header, ObjectInfo, OpCode, PropCode, ResponseCode, HEADER_LEN,
};

use super::usb::{PtpPipe, UsbError};
use crate::rig::camera_file::{self, CameraImage, DecodeIn};
use crate::rig::hal::{Camera, DeviceError, ErrorKind, Frame, OriginalFile};

/// Bulk-in reads ask for this much: a multiple of every USB packet size, so
/// a shorter read always means the device ended its transfer.
pub const BULK_CHUNK: usize = 64 * 1024;

/// The operations the driver cannot work without.
const REQUIRED_OPS: [OpCode; 6] = [
    OpCode::OpenSession,
    OpCode::SetDevicePropValue,
    OpCode::InitiateCapture,
    OpCode::GetObjectInfo,
    OpCode::GetObject,
    OpCode::DeleteObject,
];

/// Deadlines and the session id. The defaults suit a USB 2 camera with
/// frames of tens of megabytes.
#[derive(Debug, Clone, PartialEq)]
pub struct PtpConfig {
    /// Deadline of an ordinary transaction (everything but GetObject).
    pub transaction_timeout: Duration,
    /// How long after the exposure time the capture events may take
    /// (readout and storing).
    pub capture_slack: Duration,
    /// Deadline of GetObject (the frame transfer).
    pub transfer_timeout: Duration,
    /// The session id sent with OpenSession (any non-zero value).
    pub session_id: u32,
    /// The sensor's colour filter array as the profile describes it
    /// (`intrinsics.cfa`); None for a monochrome sensor. A raw frame with
    /// another one is refused.
    pub cfa: Option<Cfa>,
    /// The profile key that sets [`PtpConfig::cfa`], for messages.
    pub cfa_key: String,
    /// ExposureIndex (ISO) set at every connect; None leaves the camera's.
    pub exposure_index: Option<u16>,
    /// Where the camera's files are decoded: in a child, unless the camera
    /// is this process's own simulated one.
    pub decode_in: DecodeIn,
}

impl Default for PtpConfig {
    fn default() -> PtpConfig {
        PtpConfig {
            transaction_timeout: Duration::from_secs(5),
            capture_slack: Duration::from_secs(30),
            transfer_timeout: Duration::from_secs(60),
            session_id: 1,
            cfa: None,
            cfa_key: "intrinsics.cfa".into(),
            exposure_index: None,
            decode_in: DecodeIn::Child,
        }
    }
}

/// What went wrong, in the driver's words; [`PtpError::kind`] maps it to the
/// engine's [`ErrorKind`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PtpError {
    /// An operation (or the capture's events) got no answer before its
    /// deadline.
    #[error("{op} got no answer within {after:?}")]
    Timeout {
        /// The operation that timed out.
        op: OpCode,
        /// The deadline it had.
        after: Duration,
    },
    /// A USB transfer failed (the camera was unplugged, the pipe broke).
    #[error("{0}")]
    Usb(UsbError),
    /// The camera answered an operation with a response code other than OK.
    #[error("{op} answered {code} (0x{:04X})", .code.0)]
    Response {
        /// The operation answered.
        op: OpCode,
        /// The camera's response code.
        code: ResponseCode,
    },
    /// A data phase ended before the length its header declared.
    #[error("{op}: data phase truncated: {got} of {declared} bytes")]
    Truncated {
        /// The operation whose data phase it was.
        op: OpCode,
        /// Bytes received.
        got: usize,
        /// Bytes the container header declared.
        declared: usize,
    },
    /// The image arrived but is unusable: missing, undecodable, of another
    /// size or depth than announced, or with out-of-range values.
    #[error("bad frame: {0}")]
    BadFrame(String),
    /// A container that does not decode or does not fit the transaction
    /// (wrong code, missing data phase, unexpected events).
    #[error("{op}: protocol error: {message}")]
    Protocol {
        /// The operation in progress.
        op: OpCode,
        /// What was wrong.
        message: String,
    },
    /// The camera's DeviceInfo lacks an operation the driver needs.
    #[error("the camera does not support {0}")]
    Unsupported(OpCode),
    /// The profile sets a device property the camera does not list.
    #[error("the camera has no {0} property; remove it from the profile's `ptp` table")]
    NoProperty(PropCode),
    /// An exposure time (seconds) outside what the camera can set.
    #[error("exposure {0} s cannot be set (0.1 ms to 119 h)")]
    BadExposure(f64),
    /// The frame's sensor layout is not the one the profile describes: a
    /// set-up error that no retake mends.
    #[error("{0}")]
    WrongSensor(String),
    /// An operation was called before `connect` opened a session.
    #[error("no session: connect first")]
    NotConnected,
    /// A frame was fetched with no captured object pending.
    #[error("nothing was exposed")]
    NothingExposed,
}

impl PtpError {
    /// The kind the run engine acts on.
    pub fn kind(&self) -> ErrorKind {
        match self {
            PtpError::Timeout { .. } => ErrorKind::Timeout,
            PtpError::Usb(UsbError::Disconnected) => ErrorKind::Disconnected,
            PtpError::Usb(_) => ErrorKind::DeviceFault,
            PtpError::Response { .. }
            | PtpError::Protocol { .. }
            | PtpError::Unsupported(_)
            | PtpError::NoProperty(_)
            | PtpError::WrongSensor(_) => ErrorKind::DeviceFault,
            PtpError::Truncated { .. } | PtpError::BadFrame(_) => ErrorKind::BadFrame,
            PtpError::BadExposure(_) => ErrorKind::OutOfLimits,
            PtpError::NotConnected | PtpError::NothingExposed => ErrorKind::NotReady,
        }
    }
}

fn protocol(op: OpCode, e: impl std::fmt::Display) -> PtpError {
    PtpError::Protocol {
        op,
        message: e.to_string(),
    }
}

/// A PTP camera on a USB pipe.
#[derive(Debug)]
pub struct PtpCamera<P: PtpPipe> {
    name: String,
    pipe: P,
    clock: Clock,
    config: PtpConfig,
    next_tid: u32,
    session_open: bool,
    exposure_s: f64,
    info: Option<DeviceInfo>,
    /// The captured object not yet transferred.
    pending: Option<u32>,
}

impl<P: PtpPipe> PtpCamera<P> {
    /// A driver for the camera `name` (the device name in errors). Nothing is
    /// sent until [`PtpCamera::connect`].
    pub fn new(name: &str, pipe: P, clock: Clock, config: PtpConfig) -> PtpCamera<P> {
        PtpCamera {
            name: name.to_string(),
            pipe,
            clock,
            config,
            next_tid: 1,
            session_open: false,
            exposure_s: 0.0,
            info: None,
            pending: None,
        }
    }

    /// Identifies the camera (GetDeviceInfo), checks it supports what the
    /// driver needs, and opens a session.
    pub async fn connect(&mut self) -> Result<DeviceInfo, PtpError> {
        let op = OpCode::GetDeviceInfo;
        let (_, data) = self.transaction(op, &[], None).await?;
        let data = data.ok_or_else(|| protocol(op, "no DeviceInfo data phase"))?;
        let info = DeviceInfo::decode(&data).map_err(|e| protocol(op, e))?;
        if let Some(missing) = REQUIRED_OPS.iter().find(|&&o| !info.supports(o)) {
            return Err(PtpError::Unsupported(*missing));
        }
        let session = self.config.session_id.max(1);
        match self
            .transaction(OpCode::OpenSession, &[session], None)
            .await
        {
            // A camera that kept our session across a driver restart: adopt it.
            Ok(_)
            | Err(PtpError::Response {
                code: ResponseCode::SessionAlreadyOpen,
                ..
            }) => {}
            Err(e) => return Err(e),
        }
        self.session_open = true;
        self.next_tid = 1;
        self.info = Some(info.clone());
        if let Some(iso) = self.config.exposure_index {
            if !info
                .device_properties_supported
                .contains(&PropCode::ExposureIndex.0)
            {
                return Err(PtpError::NoProperty(PropCode::ExposureIndex));
            }
            let params = [u32::from(PropCode::ExposureIndex.0)];
            let data = iso.to_le_bytes().to_vec();
            self.transaction(OpCode::SetDevicePropValue, &params, Some(data))
                .await?;
        }
        Ok(info)
    }

    /// Closes the session (the camera may then power down its sensor).
    pub async fn close(&mut self) -> Result<(), PtpError> {
        self.require_session()?;
        self.transaction(OpCode::CloseSession, &[], None).await?;
        self.session_open = false;
        Ok(())
    }

    /// What the camera said it is, after [`PtpCamera::connect`].
    pub fn device_info(&self) -> Option<&DeviceInfo> {
        self.info.as_ref()
    }

    /// The exposure last set, seconds (0 before any).
    pub fn exposure_s(&self) -> f64 {
        self.exposure_s
    }

    fn require_session(&self) -> Result<(), PtpError> {
        if self.session_open {
            Ok(())
        } else {
            Err(PtpError::NotConnected)
        }
    }

    /// Sets ExposureTime (0.1 ms units).
    pub async fn set_exposure_s(&mut self, exposure_s: f64) -> Result<(), PtpError> {
        self.require_session()?;
        let units = exposure_to_prop(exposure_s).ok_or(PtpError::BadExposure(exposure_s))?;
        let params = [PropCode::ExposureTime.0 as u32];
        let data = units.to_le_bytes().to_vec();
        self.transaction(OpCode::SetDevicePropValue, &params, Some(data))
            .await?;
        self.exposure_s = exposure_s;
        Ok(())
    }

    /// InitiateCapture, then waits for ObjectAdded and CaptureComplete.
    pub async fn capture(&mut self) -> Result<u32, PtpError> {
        self.require_session()?;
        if let Some(stale) = self.pending.take() {
            // A frame nobody fetched would fill the card; it is not needed.
            let _ = self.transaction(OpCode::DeleteObject, &[stale], None).await;
        }
        let (tid, _) = self
            .transaction(OpCode::InitiateCapture, &[0, 0], None)
            .await?;
        let budget = Duration::from_secs_f64(self.exposure_s.max(0.0)) + self.config.capture_slack;
        let clock = self.clock.clone();
        let handle = clock
            .deadline(budget, self.wait_capture_events(tid))
            .await
            .map_err(|_| PtpError::Timeout {
                op: OpCode::InitiateCapture,
                after: budget,
            })??;
        self.pending = Some(handle);
        Ok(handle)
    }

    async fn wait_capture_events(&mut self, tid: u32) -> Result<u32, PtpError> {
        let op = OpCode::InitiateCapture;
        let mut handle = None;
        loop {
            let bytes = self.pipe.interrupt_in().await.map_err(PtpError::Usb)?;
            let ev = Container::decode(&bytes).map_err(|e| protocol(op, e))?;
            // Events of an abandoned capture (or unrelated ones) are skipped.
            if ev.kind != ContainerKind::Event || ev.transaction_id != tid {
                continue;
            }
            match EventCode(ev.code) {
                EventCode::ObjectAdded => {
                    let h = ev.params().first().copied();
                    handle = Some(h.ok_or_else(|| protocol(op, "ObjectAdded without a handle"))?);
                }
                EventCode::CaptureComplete => {
                    return handle
                        .ok_or_else(|| protocol(op, "CaptureComplete before any ObjectAdded"));
                }
                _ => {}
            }
        }
    }

    /// Fetches the captured frame and deletes it from the camera. On failure
    /// the object stays pending, so a retried transfer reads it again.
    pub async fn fetch(&mut self) -> Result<Frame, PtpError> {
        self.require_session()?;
        let handle = self.pending.ok_or(PtpError::NothingExposed)?;
        let op = OpCode::GetObjectInfo;
        let (_, data) = self.transaction(op, &[handle], None).await?;
        let data = data.ok_or_else(|| protocol(op, "no ObjectInfo data phase"))?;
        let info = ObjectInfo::decode(&data).map_err(|e| protocol(op, e))?;
        if !may_be_image(info.object_format) {
            return Err(protocol(
                op,
                format!(
                    "object format 0x{:04X} is no image (a folder or a script?)",
                    info.object_format
                ),
            ));
        }
        let op = OpCode::GetObject;
        let (_, data) = self.transaction(op, &[handle], None).await?;
        let data = data.ok_or_else(|| PtpError::BadFrame("GetObject sent no data".into()))?;
        if info.compressed_size != u32::MAX && data.len() != info.compressed_size as usize {
            return Err(PtpError::BadFrame(format!(
                "{} bytes arrived of the {} ObjectInfo announced",
                data.len(),
                info.compressed_size
            )));
        }
        let frame = frame_of_file(
            &self.name,
            data,
            self.config.decode_in,
            self.config.cfa,
            &self.config.cfa_key,
        )
        .await?;
        self.transaction(OpCode::DeleteObject, &[handle], None)
            .await?;
        self.pending = None;
        Ok(frame)
    }

    /// One transaction under its deadline; returns its id and data-in phase.
    /// Session-less operations use transaction id 0 (ISO 15740 §9.3.1); in a
    /// session ids count up from 1.
    async fn transaction(
        &mut self,
        op: OpCode,
        params: &[u32],
        data_out: Option<Vec<u8>>,
    ) -> Result<(u32, Option<Vec<u8>>), PtpError> {
        let tid = if op == OpCode::OpenSession || !self.session_open {
            0
        } else {
            let t = self.next_tid;
            // 0 and 0xFFFFFFFF are reserved.
            self.next_tid = match self.next_tid.wrapping_add(1) {
                0 | 0xFFFF_FFFF => 1,
                n => n,
            };
            t
        };
        let after = if op == OpCode::GetObject {
            self.config.transfer_timeout
        } else {
            self.config.transaction_timeout
        };
        let clock = self.clock.clone();
        let data = clock
            .deadline(after, self.exchange(op, tid, params, data_out))
            .await
            .map_err(|_| PtpError::Timeout { op, after })??;
        Ok((tid, data))
    }

    async fn exchange(
        &mut self,
        op: OpCode,
        tid: u32,
        params: &[u32],
        data_out: Option<Vec<u8>>,
    ) -> Result<Option<Vec<u8>>, PtpError> {
        let codec = |e: CodecError| protocol(op, e);
        let cmd = Container::with_params(ContainerKind::Command, op.0, tid, params)
            .and_then(|c| c.encode())
            .map_err(codec)?;
        let data_out = match data_out {
            Some(d) => Some(Container::data(op.0, tid, d).encode().map_err(codec)?),
            None => None,
        };
        self.pipe
            .send_operation(cmd, data_out)
            .await
            .map_err(PtpError::Usb)?;
        let mut data: Option<Vec<u8>> = None;
        let mut truncated: Option<(usize, usize)> = None;
        loop {
            let (header, bytes) = self.read_container(op).await?;
            if header.transaction_id != tid {
                // Left over from a transaction that timed out.
                continue;
            }
            match header.kind {
                ContainerKind::Data => {
                    if header.code != op.0 {
                        return Err(protocol(op, format!("data phase of 0x{:04X}", header.code)));
                    }
                    if bytes.len() < header.length as usize {
                        truncated = Some((
                            bytes.len() - HEADER_LEN,
                            header.length as usize - HEADER_LEN,
                        ));
                    } else {
                        data = Some(bytes[HEADER_LEN..].to_vec());
                    }
                }
                ContainerKind::Response => {
                    let resp = Container::decode(&bytes).map_err(codec)?;
                    let code = ResponseCode(resp.code);
                    if code != ResponseCode::OK {
                        return Err(PtpError::Response { op, code });
                    }
                    if let Some((got, declared)) = truncated {
                        return Err(PtpError::Truncated { op, got, declared });
                    }
                    return Ok(data);
                }
                other => return Err(protocol(op, format!("unexpected {other} container"))),
            }
        }
    }

    /// Reads one bulk-in transfer: the header says how long the container
    /// is; a short read before that length means the device cut the
    /// transfer (the returned bytes are then shorter than the header says).
    async fn read_container(&mut self, op: OpCode) -> Result<(Header, Vec<u8>), PtpError> {
        let mut buf = Vec::new();
        // Skip zero-length packets left from a previous transfer.
        while buf.is_empty() {
            buf = self.pipe.bulk_in(BULK_CHUNK).await.map_err(PtpError::Usb)?;
        }
        let mut ended = buf.len() < BULK_CHUNK;
        let header = Header::decode(&buf).map_err(|e| protocol(op, e))?;
        let declared = header.length as usize;
        while !ended && buf.len() < declared {
            let chunk = self.pipe.bulk_in(BULK_CHUNK).await.map_err(PtpError::Usb)?;
            ended = chunk.len() < BULK_CHUNK;
            buf.extend_from_slice(&chunk);
        }
        if !ended {
            // The transfer filled whole reads: its zero-length packet follows.
            let zlp = self.pipe.bulk_in(BULK_CHUNK).await.map_err(PtpError::Usb)?;
            buf.extend_from_slice(&zlp);
        }
        if buf.len() > declared {
            return Err(protocol(
                op,
                format!("{} bytes in a {declared}-byte container", buf.len()),
            ));
        }
        Ok((header, buf))
    }

    fn device_error(&self, e: PtpError) -> DeviceError {
        DeviceError::new(&self.name, e.kind(), e.to_string())
    }
}

/// The frame a camera file makes, the file kept byte for byte as
/// [`Frame::original`]: decoded ([`camera_file`], where `decode_in` says)
/// to refuse a broken file, and refused when its colour filter array is
/// not `cfa`, the one the profile describes at `cfa_key`. Every driver
/// that downloads camera files (PTP, libgphoto2) makes its frames here, so
/// they are stored and checked alike.
pub(crate) async fn frame_of_file(
    camera: &str,
    bytes: Vec<u8>,
    decode_in: DecodeIn,
    cfa: Option<Cfa>,
    cfa_key: &str,
) -> Result<Frame, PtpError> {
    let (decoded, bytes) = match decode_in {
        DecodeIn::ThisProcess => (camera_file::decode_here(&bytes), bytes),
        // A child's round trip blocks: it runs off the runtime's threads.
        DecodeIn::Child => {
            tokio::task::spawn_blocking(move || (camera_file::decode(&bytes), bytes))
                .await
                .map_err(|e| PtpError::BadFrame(format!("the decoding thread failed: {e}")))?
        }
    };
    let image = decoded.map_err(|e| PtpError::BadFrame(e.to_string()))?;
    check_sensor(&image, cfa, cfa_key)?;
    let frame = Frame {
        width: image.width,
        height: image.height,
        bit_depth: image.bit_depth(),
        pixels: grey_or_mosaic(&image),
        device: None,
        original: Some(OriginalFile {
            extension: image.format.extension(),
            bytes,
        }),
    };
    frame
        .validate(camera)
        .map_err(|e| PtpError::BadFrame(e.message))?;
    Ok(frame)
}

/// Refuses a raw frame whose colour filter array is not the profile's.
fn check_sensor(image: &CameraImage, cfa: Option<Cfa>, cfa_key: &str) -> Result<(), PtpError> {
    if image.channels != 1 || image.cfa == cfa {
        return Ok(());
    }
    let name = |c: Option<Cfa>| c.map_or("monochrome".to_string(), |c| format!("{c}"));
    let set = match image.cfa {
        Some(c) => format!("set `{cfa_key}` = \"{c}\""),
        None => format!("remove `{cfa_key}`"),
    };
    Err(PtpError::WrongSensor(format!(
        "the camera delivers a {} {} frame but the profile describes a {} sensor; \
         {set} if the camera is right",
        name(image.cfa),
        image.format.extension().to_uppercase(),
        name(cfa),
    )))
}

/// The samples a frame holds for in-flight checks and manual-shot
/// statistics: a mosaic or grey as it is, RGB as its green channel.
fn grey_or_mosaic(image: &CameraImage) -> Vec<u16> {
    if image.channels == 3 {
        image.samples.iter().skip(1).step_by(3).copied().collect()
    } else {
        image.samples.clone()
    }
}

#[async_trait]
impl<P: PtpPipe> Camera for PtpCamera<P> {
    async fn set_exposure(&mut self, exposure_s: f64) -> Result<(), DeviceError> {
        self.set_exposure_s(exposure_s)
            .await
            .map_err(|e| self.device_error(e))
    }

    async fn expose(&mut self) -> Result<(), DeviceError> {
        self.capture()
            .await
            .map(|_| ())
            .map_err(|e| self.device_error(e))
    }

    async fn transfer(&mut self) -> Result<Frame, DeviceError> {
        self.fetch().await.map_err(|e| self.device_error(e))
    }
}
