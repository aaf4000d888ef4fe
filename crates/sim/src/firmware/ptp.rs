//! The firmware of a simulated PTP camera: it serves the device end of an
//! in-memory USB link exactly as `firmware-protocols/ptp-camera.md` says, so
//! `rigd`'s real PTP driver runs unchanged against it.
//!
//! Timing goes through the [`Clock`]: InitiateCapture answers at once and the
//! ObjectAdded/CaptureComplete events follow after exposure + readout;
//! GetObject costs the transfer time. Which light and view the frame shows
//! is the rig's business, so a callback supplies the [`Shot`].
//!
//! Faults come from the [`FaultInjector`](crate::FaultInjector), keyed by
//! the camera's name and these operation names: `get_device_info`,
//! `open_session`, `close_session`, `get_exposure`, `set_exposure`, `expose`
//! (InitiateCapture), `get_object_info`, `transfer` (GetObject),
//! `delete_object`. `timeout` leaves the command unanswered, `disconnect`
//! closes the link, `alarm=…` answers GeneralError, `bad-frame` cuts the
//! GetObject data phase short.
//!
//! Frames are DNG files ([`super::dng`]), object format DNG (0x3811), as a
//! camera that shoots DNG delivers them: the Bayer mosaic of a colour
//! sensor (or the samples of a monochrome one) above a black level, with
//! the tags a raw decoder needs.

use std::collections::BTreeMap;
use std::future::Future;
use std::pin::Pin;

use rigd_core::Cfa;
use rigd_proto::ptp::link::{DeviceEnd, LinkClosed};
use rigd_proto::ptp::property::{DevicePropDesc, PropForm, DATATYPE_UINT16, DATATYPE_UINT32};
use rigd_proto::ptp::{
    exposure_to_prop, prop_to_exposure, Container, ContainerKind, DeviceInfo, EventCode,
    ObjectInfo, OpCode, PropCode, ResponseCode, FORMAT_DNG, HEADER_LEN,
};

use super::dng::{self, DngCamera};

use crate::devices::{CameraTimes, SimContext};
use crate::faults::FaultKind;
use std::sync::Arc;

use crate::scene::{Scene, Shot, DEFAULT_SCENE};

/// The storage every simulated frame is stored on.
pub const STORAGE_ID: u32 = 0x0001_0001;
/// The ExposureIndex (ISO) the simulated camera starts at, at which frames
/// have the scene's nominal brightness.
pub const BASE_ISO: u16 = 100;
/// The handle of the first captured object; later ones count up.
pub const FIRST_HANDLE: u32 = 0x0001_0001;
/// The shutter speeds the camera lists, seconds: the third-stop series of
/// a camera body, from 1/2000 s (the shortest the 0.1 ms unit of
/// ExposureTime tells apart) to 30 s.
pub const SHUTTER_SPEEDS_S: [f64; 46] = [
    1.0 / 2000.0,
    1.0 / 1600.0,
    1.0 / 1250.0,
    1.0 / 1000.0,
    1.0 / 800.0,
    1.0 / 640.0,
    1.0 / 500.0,
    1.0 / 400.0,
    1.0 / 320.0,
    1.0 / 250.0,
    1.0 / 200.0,
    1.0 / 160.0,
    1.0 / 125.0,
    1.0 / 100.0,
    1.0 / 80.0,
    1.0 / 60.0,
    1.0 / 50.0,
    1.0 / 40.0,
    1.0 / 30.0,
    1.0 / 25.0,
    1.0 / 20.0,
    1.0 / 15.0,
    1.0 / 13.0,
    1.0 / 10.0,
    1.0 / 8.0,
    1.0 / 6.0,
    1.0 / 5.0,
    1.0 / 4.0,
    0.3,
    0.4,
    0.5,
    0.6,
    0.8,
    1.0,
    1.3,
    1.6,
    2.0,
    2.5,
    3.2,
    4.0,
    5.0,
    6.0,
    8.0,
    10.0,
    15.0,
    30.0,
];
/// The ISO speeds the camera lists.
pub const ISO_SPEEDS: [u32; 7] = [100, 200, 400, 800, 1600, 3200, 6400];

/// Who the simulated camera says it is, and its physics.
#[derive(Debug, Clone, PartialEq)]
pub struct PtpCameraSpec {
    /// The device name faults are armed for.
    pub name: String,
    /// Manufacturer string of the DeviceInfo dataset.
    pub manufacturer: String,
    /// Model string of the DeviceInfo dataset.
    pub model: String,
    /// DeviceVersion (firmware version) string of the DeviceInfo dataset.
    pub version: String,
    /// SerialNumber string of the DeviceInfo dataset.
    pub serial: String,
    /// Exposure (also the nominal one frames are scaled against), readout
    /// and transfer times.
    pub times: CameraTimes,
    /// The sensor's colour filter array; None for a monochrome sensor.
    pub cfa: Option<Cfa>,
}

/// A captured frame waiting on the camera: its DNG file and what
/// ObjectInfo says of it.
struct StoredObject {
    file: Vec<u8>,
    width: u32,
    height: u32,
    bit_depth: u8,
}

/// Supplies the scene at the moment of an InitiateCapture.
pub type ShotSource = Box<dyn FnMut() -> Shot + Send>;

type Timer = Pin<Box<dyn Future<Output = ()> + Send>>;

/// A capture in progress: its transaction, the scene, and when it ends.
struct Capture {
    transaction_id: u32,
    shot: Shot,
    timer: Timer,
    /// A frame fault armed on this exposure (`dark`, `mask-markers`).
    frame_fault: Option<FaultKind>,
}

/// The camera's firmware state.
pub struct PtpFirmware {
    spec: PtpCameraSpec,
    ctx: SimContext,
    shot: ShotSource,
    /// What the camera looks at; `None` only if the built-in default scene
    /// failed to load, and then frames are black.
    scene: Option<Arc<Scene>>,
    session: Option<u32>,
    exposure_units: u32,
    /// ExposureIndex (ISO); frames are as bright as at [`BASE_ISO`] times
    /// this over it.
    exposure_index: u16,
    objects: BTreeMap<u32, StoredObject>,
    next_handle: u32,
    capture: Option<Capture>,
}

impl std::fmt::Debug for PtpFirmware {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PtpFirmware")
            .field("spec", &self.spec)
            .field("session", &self.session)
            .field("exposure_units", &self.exposure_units)
            .field("objects", &self.objects.keys().collect::<Vec<_>>())
            .finish()
    }
}

/// What the firmware does after a command.
enum Next {
    Continue,
    Disconnect,
}

impl PtpFirmware {
    /// A camera with no session open, its exposure set to the nominal one,
    /// rendering the built-in default scene; `shot` is asked for the light
    /// and view at each InitiateCapture.
    pub fn new(spec: PtpCameraSpec, ctx: SimContext, shot: ShotSource) -> PtpFirmware {
        let exposure_units = exposure_to_prop(spec.times.exposure_s).unwrap_or(1);
        PtpFirmware {
            spec,
            ctx,
            shot,
            scene: Scene::load(DEFAULT_SCENE).ok(),
            session: None,
            exposure_units,
            exposure_index: BASE_ISO,
            objects: BTreeMap::new(),
            next_handle: FIRST_HANDLE,
            capture: None,
        }
    }

    /// The scene this camera renders (the built-in default otherwise).
    pub fn with_scene(mut self, scene: Arc<Scene>) -> PtpFirmware {
        self.scene = Some(scene);
        self
    }

    /// The DeviceInfo dataset this camera sends.
    pub fn device_info(&self) -> DeviceInfo {
        DeviceInfo {
            standard_version: 100,
            vendor_extension_id: 0,
            vendor_extension_version: 0,
            vendor_extension_desc: String::new(),
            functional_mode: 0,
            operations_supported: OpCode::ALL.iter().map(|c| c.0).collect(),
            events_supported: vec![EventCode::ObjectAdded.0, EventCode::CaptureComplete.0],
            device_properties_supported: vec![PropCode::ExposureTime.0, PropCode::ExposureIndex.0],
            capture_formats: vec![FORMAT_DNG],
            image_formats: vec![FORMAT_DNG],
            manufacturer: self.spec.manufacturer.clone(),
            model: self.spec.model.clone(),
            device_version: self.spec.version.clone(),
            serial_number: self.spec.serial.clone(),
        }
    }

    /// Runs the firmware on a spawned task until the host goes away or a
    /// disconnect fault closes the link.
    pub fn spawn(self, dev: DeviceEnd) -> tokio::task::JoinHandle<()> {
        tokio::spawn(self.run(dev))
    }

    /// Serves the link until the host goes away or a disconnect fault closes
    /// it (the device end is dropped, which is what the host sees).
    pub async fn run(mut self, mut dev: DeviceEnd) {
        loop {
            let next = match self.capture.as_mut() {
                Some(cap) => tokio::select! {
                    r = dev.read_out() => Some(r),
                    _ = cap.timer.as_mut() => None,
                },
                None => Some(dev.read_out().await),
            };
            let bytes = match next {
                None => {
                    if self.finish_capture(&dev).is_err() {
                        return;
                    }
                    continue;
                }
                Some(Err(LinkClosed)) => return,
                Some(Ok(b)) => b,
            };
            // Garbage or a stray data phase is dropped, as a device would
            // stall the pipe; the host's deadline notices.
            let Ok(cmd) = Container::decode(&bytes) else {
                continue;
            };
            if cmd.kind != ContainerKind::Command {
                continue;
            }
            match self.handle(&mut dev, cmd).await {
                Ok(Next::Continue) => {}
                Ok(Next::Disconnect) | Err(LinkClosed) => return,
            }
        }
    }

    async fn handle(&mut self, dev: &mut DeviceEnd, cmd: Container) -> Result<Next, LinkClosed> {
        let op = OpCode(cmd.code);
        let tid = cmd.transaction_id;
        let params = cmd.params();
        let p0 = params.first().copied().unwrap_or(0);
        // The data-out phase belongs to the transaction whatever its outcome.
        let data_out = if op == OpCode::SetDevicePropValue {
            let b = dev.read_out().await?;
            match Container::decode(&b) {
                Ok(c) if c.kind == ContainerKind::Data && c.transaction_id == tid => {
                    Some(c.payload)
                }
                _ => None,
            }
        } else {
            None
        };
        let fault = self.ctx.faults.check(&self.spec.name, fault_op(op));
        match fault {
            Some(FaultKind::Timeout) => return Ok(Next::Continue),
            Some(FaultKind::Disconnect) => return Ok(Next::Disconnect),
            Some(FaultKind::Alarm(_)) => {
                respond(dev, ResponseCode::GeneralError, tid, &[])?;
                return Ok(Next::Continue);
            }
            Some(FaultKind::BadFrame | FaultKind::Dark | FaultKind::MaskMarkers) | None => {}
        }
        if op != OpCode::GetDeviceInfo && op != OpCode::OpenSession && self.session.is_none() {
            respond(dev, ResponseCode::SessionNotOpen, tid, &[])?;
            return Ok(Next::Continue);
        }
        let busy = self.capture.is_some();
        match op {
            OpCode::GetDeviceInfo => {
                send_data(dev, op, tid, self.device_info().encode())?;
                respond(dev, ResponseCode::OK, tid, &[])?;
            }
            OpCode::OpenSession => {
                if let Some(open) = self.session {
                    respond(dev, ResponseCode::SessionAlreadyOpen, tid, &[open])?;
                } else if p0 == 0 {
                    respond(dev, ResponseCode::InvalidParameter, tid, &[])?;
                } else {
                    self.session = Some(p0);
                    respond(dev, ResponseCode::OK, tid, &[])?;
                }
            }
            OpCode::CloseSession => {
                self.session = None;
                respond(dev, ResponseCode::OK, tid, &[])?;
            }
            OpCode::GetDevicePropValue => {
                let value = if p0 == u32::from(PropCode::ExposureTime.0) {
                    Some(self.exposure_units.to_le_bytes().to_vec())
                } else if p0 == u32::from(PropCode::ExposureIndex.0) {
                    Some(self.exposure_index.to_le_bytes().to_vec())
                } else {
                    None
                };
                match value {
                    Some(v) => {
                        send_data(dev, op, tid, v)?;
                        respond(dev, ResponseCode::OK, tid, &[])?;
                    }
                    None => respond(dev, ResponseCode::DevicePropNotSupported, tid, &[])?,
                }
            }
            OpCode::GetDevicePropDesc => match self.prop_desc(p0).map(|d| d.encode()) {
                Some(Ok(desc)) => {
                    send_data(dev, op, tid, desc)?;
                    respond(dev, ResponseCode::OK, tid, &[])?;
                }
                _ => respond(dev, ResponseCode::DevicePropNotSupported, tid, &[])?,
            },
            OpCode::SetDevicePropValue => {
                let value = data_out
                    .as_deref()
                    .and_then(|d| <[u8; 4]>::try_from(d).ok())
                    .map(u32::from_le_bytes);
                let iso = data_out
                    .as_deref()
                    .and_then(|d| <[u8; 2]>::try_from(d).ok())
                    .map(u16::from_le_bytes);
                let code = if p0 == u32::from(PropCode::ExposureIndex.0) {
                    match iso {
                        _ if busy => ResponseCode::DeviceBusy,
                        Some(v) if v > 0 => {
                            self.exposure_index = v;
                            ResponseCode::OK
                        }
                        _ => ResponseCode::InvalidDevicePropValue,
                    }
                } else if p0 != u32::from(PropCode::ExposureTime.0) {
                    ResponseCode::DevicePropNotSupported
                } else if busy {
                    ResponseCode::DeviceBusy
                } else {
                    match value {
                        Some(v) if v > 0 => {
                            self.exposure_units = v;
                            ResponseCode::OK
                        }
                        _ => ResponseCode::InvalidDevicePropValue,
                    }
                };
                respond(dev, code, tid, &[])?;
            }
            OpCode::InitiateCapture => {
                let format = params.get(1).copied().unwrap_or(0);
                if busy {
                    respond(dev, ResponseCode::DeviceBusy, tid, &[])?;
                } else if format != 0 && format != u32::from(FORMAT_DNG) {
                    respond(dev, ResponseCode::InvalidObjectFormatCode, tid, &[])?;
                } else {
                    respond(dev, ResponseCode::OK, tid, &[])?;
                    let frame_fault =
                        fault.filter(|f| matches!(f, FaultKind::Dark | FaultKind::MaskMarkers));
                    self.start_capture(tid, frame_fault);
                }
            }
            OpCode::GetObjectInfo => match self.objects.get(&p0) {
                Some(f) => {
                    let info = object_info(f, p0.wrapping_sub(FIRST_HANDLE).wrapping_add(1));
                    send_data(dev, op, tid, info.encode())?;
                    respond(dev, ResponseCode::OK, tid, &[])?;
                }
                None => respond(dev, ResponseCode::InvalidObjectHandle, tid, &[])?,
            },
            OpCode::GetObject => match self.objects.get(&p0) {
                Some(f) => {
                    let payload = f.file.clone();
                    self.ctx.clock.sleep_s(self.spec.times.transfer_s).await;
                    let mut bytes = Container::data(op.0, tid, payload)
                        .encode()
                        .map_err(|_| LinkClosed)?;
                    if fault == Some(FaultKind::BadFrame) {
                        // The header still announces the whole frame; the
                        // transfer ends halfway, as when a cable drops packets.
                        let keep = HEADER_LEN + (bytes.len() - HEADER_LEN) / 2;
                        bytes.truncate(keep);
                    }
                    dev.write_in(bytes)?;
                    respond(dev, ResponseCode::OK, tid, &[])?;
                }
                None => respond(dev, ResponseCode::InvalidObjectHandle, tid, &[])?,
            },
            OpCode::DeleteObject => {
                if p0 == 0xFFFF_FFFF {
                    self.objects.clear();
                    respond(dev, ResponseCode::OK, tid, &[])?;
                } else if self.objects.remove(&p0).is_some() {
                    respond(dev, ResponseCode::OK, tid, &[])?;
                } else {
                    respond(dev, ResponseCode::InvalidObjectHandle, tid, &[])?;
                }
            }
            _ => respond(dev, ResponseCode::OperationNotSupported, tid, &[])?,
        }
        Ok(Next::Continue)
    }

    /// The description of a property the camera has. The lists are what a
    /// tool picks from: the standard third-stop shutter speeds and ISO
    /// speeds, plus the nominal and current values. Like a machine-vision
    /// body, the camera accepts any positive value set, listed or not.
    fn prop_desc(&self, code: u32) -> Option<DevicePropDesc> {
        let with = |mut list: Vec<u32>, extra: [u32; 2]| {
            list.extend(extra);
            list.sort_unstable();
            list.dedup();
            PropForm::Enumeration(list)
        };
        if code == u32::from(PropCode::ExposureTime.0) {
            let nominal = exposure_to_prop(self.spec.times.exposure_s).unwrap_or(1);
            let list = SHUTTER_SPEEDS_S
                .iter()
                .filter_map(|&s| exposure_to_prop(s))
                .collect();
            Some(DevicePropDesc {
                code: PropCode::ExposureTime,
                data_type: DATATYPE_UINT32,
                writable: true,
                factory_default: nominal,
                current: self.exposure_units,
                form: with(list, [nominal, self.exposure_units]),
            })
        } else if code == u32::from(PropCode::ExposureIndex.0) {
            let current = u32::from(self.exposure_index);
            let base = u32::from(BASE_ISO);
            Some(DevicePropDesc {
                code: PropCode::ExposureIndex,
                data_type: DATATYPE_UINT16,
                writable: true,
                factory_default: base,
                current,
                form: with(ISO_SPEEDS.to_vec(), [base, current]),
            })
        } else {
            None
        }
    }

    fn start_capture(&mut self, transaction_id: u32, frame_fault: Option<FaultKind>) {
        let shot = (self.shot)();
        let busy_s = prop_to_exposure(self.exposure_units) + self.spec.times.readout_s;
        let clock = self.ctx.clock.clone();
        self.capture = Some(Capture {
            transaction_id,
            shot,
            timer: Box::pin(async move { clock.sleep_s(busy_s).await }),
            frame_fault,
        });
    }

    /// Exposure and readout are over: store the frame and tell the host.
    fn finish_capture(&mut self, dev: &DeviceEnd) -> Result<(), LinkClosed> {
        let Some(cap) = self.capture.take() else {
            return Ok(());
        };
        let mut shot = cap.shot;
        let nominal = self.spec.times.exposure_s;
        shot.relative_exposure = if nominal > 0.0 {
            prop_to_exposure(self.exposure_units) / nominal
        } else {
            1.0
        };
        shot.gain *= f64::from(self.exposure_index) / f64::from(BASE_ISO);
        let handle = self.next_handle;
        shot.seed = u64::from(handle);
        if cap.frame_fault == Some(FaultKind::Dark) {
            shot.light = [0.0, 0.0, -1.0];
        }
        let pixels = match &self.scene {
            Some(scene) => {
                let mut pixels = scene.render(&shot).pixels;
                if cap.frame_fault == Some(FaultKind::MaskMarkers) {
                    mask_markers(scene, &shot, &mut pixels);
                }
                pixels
            }
            None => vec![0; shot.width as usize * shot.height as usize],
        };
        let camera = DngCamera {
            make: &self.spec.manufacturer,
            model: &self.spec.model,
            cfa: self.spec.cfa,
            bit_depth: shot.bit_depth,
        };
        let raw = dng::to_raw(&pixels, shot.bit_depth);
        let exposure_s = prop_to_exposure(self.exposure_units);
        // A frame the encoder cannot write (no pixels) is stored empty: the
        // host's decoder refuses it as a bad frame, as it would a broken file.
        let file =
            dng::encode(&camera, shot.width, shot.height, &raw, exposure_s).unwrap_or_default();
        let frame = StoredObject {
            file,
            width: shot.width,
            height: shot.height,
            bit_depth: shot.bit_depth,
        };
        self.next_handle = self.next_handle.wrapping_add(1);
        self.objects.insert(handle, frame);
        let tid = cap.transaction_id;
        event(dev, EventCode::ObjectAdded, tid, &[handle])?;
        event(dev, EventCode::CaptureComplete, tid, &[])
    }
}

/// Paints a black disc of twice its radius over every point marker of the
/// holder the frame shows: a `mask-markers` fault.
fn mask_markers(scene: &Scene, shot: &Shot, pixels: &mut [u16]) {
    let (w, h) = (shot.width as usize, shot.height as usize);
    let r_m = scene.holder.point_radius;
    for (marker, centre) in scene.marker_pixels(shot) {
        let Some([cx, cy]) = centre.filter(|_| marker.kind == "point") else {
            continue;
        };
        // The disc's radius in pixels: how far its rim projects.
        let rim = scene
            .plate_pixel(shot, [marker.position[0] + r_m, marker.position[1]])
            .map_or(3.0, |[x, y]| (x - cx).hypot(y - cy));
        let r = (2.0 * rim).max(2.0);
        let (x0, x1) = (
            (cx - r).floor().max(0.0) as usize,
            (cx + r).ceil().max(0.0) as usize,
        );
        let (y0, y1) = (
            (cy - r).floor().max(0.0) as usize,
            (cy + r).ceil().max(0.0) as usize,
        );
        for y in y0..y1.min(h) {
            for x in x0..x1.min(w) {
                if (x as f64 + 0.5 - cx).hypot(y as f64 + 0.5 - cy) <= r {
                    pixels[y * w + x] = 0;
                }
            }
        }
    }
}

/// The fault-injection name of an operation.
pub fn fault_op(op: OpCode) -> &'static str {
    match op {
        OpCode::GetDeviceInfo => "get_device_info",
        OpCode::OpenSession => "open_session",
        OpCode::CloseSession => "close_session",
        OpCode::GetDevicePropValue | OpCode::GetDevicePropDesc => "get_exposure",
        OpCode::SetDevicePropValue => "set_exposure",
        OpCode::InitiateCapture => "expose",
        OpCode::GetObjectInfo => "get_object_info",
        OpCode::GetObject => "transfer",
        OpCode::DeleteObject => "delete_object",
        _ => "other",
    }
}

fn object_info(f: &StoredObject, sequence: u32) -> ObjectInfo {
    ObjectInfo {
        storage_id: STORAGE_ID,
        object_format: FORMAT_DNG,
        compressed_size: u32::try_from(f.file.len()).unwrap_or(u32::MAX),
        image_width: f.width,
        image_height: f.height,
        image_bit_depth: f.bit_depth as u32,
        sequence_number: sequence,
        filename: format!("IMG_{sequence:04}.DNG"),
        ..ObjectInfo::default()
    }
}

fn respond(
    dev: &DeviceEnd,
    code: ResponseCode,
    tid: u32,
    params: &[u32],
) -> Result<(), LinkClosed> {
    send(dev, ContainerKind::Response, code.0, tid, params, false)
}

fn event(dev: &DeviceEnd, code: EventCode, tid: u32, params: &[u32]) -> Result<(), LinkClosed> {
    send(dev, ContainerKind::Event, code.0, tid, params, true)
}

fn send(
    dev: &DeviceEnd,
    kind: ContainerKind,
    code: u16,
    tid: u32,
    params: &[u32],
    interrupt: bool,
) -> Result<(), LinkClosed> {
    // At most one parameter is ever sent, so encoding cannot fail; if it
    // did, the host's deadline would report the silence.
    let Ok(bytes) = Container::with_params(kind, code, tid, params).and_then(|c| c.encode()) else {
        return Ok(());
    };
    if interrupt {
        dev.write_interrupt(bytes)
    } else {
        dev.write_in(bytes)
    }
}

fn send_data(dev: &DeviceEnd, op: OpCode, tid: u32, payload: Vec<u8>) -> Result<(), LinkClosed> {
    match Container::data(op.0, tid, payload).encode() {
        Ok(b) => dev.write_in(b),
        Err(_) => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::FaultInjector;
    use rigd_core::Clock;
    use rigd_proto::ptp::link::{pair, HostEnd};
    use std::sync::Arc;

    fn spec() -> PtpCameraSpec {
        PtpCameraSpec {
            name: "cam".into(),
            manufacturer: "rigd".into(),
            model: "SimCam".into(),
            version: "1.0".into(),
            serial: "SIM0001".into(),
            times: CameraTimes {
                exposure_s: 0.1,
                readout_s: 0.2,
                transfer_s: 0.3,
            },
            cfa: Some(Cfa::Rggb),
        }
    }

    fn shot() -> Shot {
        Shot {
            light: [0.0, 0.0, 1.0],
            view: [0.0, 0.0, 1.0],
            width: 8,
            height: 4,
            bit_depth: 12,
            ..Shot::default()
        }
    }

    async fn cmd(h: &mut HostEnd, op: OpCode, tid: u32, params: &[u32]) -> Container {
        let c = Container::with_params(ContainerKind::Command, op.0, tid, params)
            .and_then(|c| c.encode())
            .unwrap_or_else(|e| panic!("{e}"));
        h.bulk_out(c).unwrap_or_else(|e| panic!("{e}"));
        let b = h.bulk_in(1 << 20).await.unwrap_or_else(|e| panic!("{e}"));
        Container::decode(&b).unwrap_or_else(|e| panic!("{e}"))
    }

    #[tokio::test(start_paused = true)]
    async fn capture_events_follow_exposure_and_readout() {
        let clock = Clock::virtual_time();
        let ctx = SimContext::new(clock.clone(), Arc::new(FaultInjector::default()));
        let (mut h, d) = pair();
        PtpFirmware::new(spec(), ctx, Box::new(shot)).spawn(d);
        let r = cmd(&mut h, OpCode::InitiateCapture, 1, &[0, 0]).await;
        assert_eq!(r.code, ResponseCode::SessionNotOpen.0);
        let r = cmd(&mut h, OpCode::OpenSession, 0, &[1]).await;
        assert_eq!(r.code, ResponseCode::OK.0);
        let r = cmd(&mut h, OpCode::InitiateCapture, 1, &[0, 0]).await;
        assert_eq!(
            (r.kind, r.code),
            (ContainerKind::Response, ResponseCode::OK.0)
        );
        let r = cmd(&mut h, OpCode::InitiateCapture, 2, &[0, 0]).await;
        assert_eq!(r.code, ResponseCode::DeviceBusy.0);
        let e = h.interrupt_in().await.unwrap_or_else(|e| panic!("{e}"));
        let e = Container::decode(&e).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(e.code, EventCode::ObjectAdded.0);
        assert_eq!(e.params(), vec![FIRST_HANDLE]);
        assert!((clock.now_s() - 0.3).abs() < 1e-6, "{}", clock.now_s());
        let r = cmd(&mut h, OpCode::GetObjectInfo, 3, &[0x42]).await;
        assert_eq!(r.code, ResponseCode::InvalidObjectHandle.0);
    }
}
