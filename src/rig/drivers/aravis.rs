//! The GenICam session on Aravis (Debian's libaravis 0.8, through the
//! `aravis` bindings): GigE Vision and USB3 Vision cameras by IP address or
//! device id. Built with the cargo feature `genicam`.
//!
//! Features are set by their SFNC names. Aravis's camera calls map
//! `ExposureTime` to the older `ExposureTimeAbs` and `Gain` to `GainRaw`
//! where a camera only has those (Aravis's fake camera does).

use std::time::Duration;

use aravis::glib;
use aravis::prelude::*;
use aravis::{AcquisitionMode, Buffer, BufferPayloadType, BufferStatus, Camera, Stream};

use super::genicam::{
    GenicamConfig, GenicamIdentity, GenicamOpener, GenicamSession, SessionError, StreamBuffer,
};
use crate::rig::hal::ErrorKind;

/// Stream buffers queued for the camera: one frame in flight per trigger,
/// and spares for a late frame of an earlier trigger.
const STREAM_BUFFERS: usize = 4;

/// Opens a GenICam camera through Aravis.
pub struct AravisOpener {
    /// What `arv_camera_new` takes: an IP address or a device id.
    pub id: String,
}

/// The kind of failure an Aravis error is: lost links, timeouts and a
/// camera that is not found are `Disconnected` (the run pauses and a resume
/// opens the camera again); refusals are device faults.
fn kind_of(e: &glib::Error) -> ErrorKind {
    use aravis::DeviceError as D;
    match e.kind::<D>() {
        Some(
            D::NotConnected
            | D::ProtocolError
            | D::TransferError
            | D::Timeout
            | D::NotFound
            | D::NotController,
        ) => ErrorKind::Disconnected,
        _ => ErrorKind::DeviceFault,
    }
}

fn failed(what: &str, e: &glib::Error) -> SessionError {
    SessionError::new(kind_of(e), format!("{what}: {e}"))
}

/// A feature the camera refused: not ready to capture as profiled. The
/// message names the profile key that sets the feature (`setting`, under
/// `devices.NAME`), so `rig check` needs no fix of its own.
fn refused(
    feature: &str,
    value: &str,
    e: &glib::Error,
    offers: Option<String>,
    setting: Option<(&str, &str)>,
) -> SessionError {
    let kind = match kind_of(e) {
        ErrorKind::Disconnected => ErrorKind::Disconnected,
        _ => ErrorKind::NotReady,
    };
    let offers = offers.map_or(String::new(), |o| format!("; it offers {o}"));
    let fix = setting.map_or(String::new(), |(device, key)| {
        format!("; set `devices.{device}.{key}` to what the camera offers")
    });
    SessionError::new(
        kind,
        format!("the camera refuses {feature} = {value}: {e}{offers}{fix}"),
    )
}

/// The camera's `ExposureTime` range, for a refusal's message.
fn exposure_range(cam: &Camera) -> Option<String> {
    cam.exposure_time_bounds()
        .ok()
        .map(|(lo, hi)| format!("{lo} to {hi} µs"))
}

/// Refuses an exposure outside the camera's own `ExposureTime` range
/// before it is asked: a camera may take a value beyond it without a word
/// (Aravis's fake camera does) and expose for something else.
fn check_exposure(
    cam: &Camera,
    exposure_us: f64,
    setting: Option<&str>,
) -> Result<(), SessionError> {
    let Ok((lo, hi)) = cam.exposure_time_bounds() else {
        return Ok(());
    };
    if (lo..=hi).contains(&exposure_us) {
        return Ok(());
    }
    let fix = setting.map_or(String::new(), |device| {
        format!("; set `devices.{device}.timing.exposure_s` to what the camera offers")
    });
    Err(SessionError::new(
        ErrorKind::OutOfLimits,
        format!(
            "the camera refuses ExposureTime = {exposure_us} µs: it offers {lo} to {hi} µs{fix}"
        ),
    ))
}

impl GenicamOpener for AravisOpener {
    fn describe(&self) -> String {
        format!("GenICam camera `{}` (Aravis)", self.id)
    }

    fn open(&self, cfg: &GenicamConfig) -> Result<Box<dyn GenicamSession>, SessionError> {
        let cam = Camera::new(Some(&self.id)).map_err(|e| {
            SessionError::new(
                ErrorKind::Disconnected,
                format!("cannot open GenICam camera `{}`: {e}", self.id),
            )
        })?;
        let text = |r: Result<glib::GString, glib::Error>| r.map(|s| s.to_string()).ok();
        let identity = GenicamIdentity {
            vendor: text(cam.vendor_name()).unwrap_or_default(),
            model: text(cam.model_name()).unwrap_or_default(),
            serial: text(cam.device_serial_number())
                .or_else(|| text(cam.device_id()))
                .unwrap_or_default(),
            version: text(cam.string("DeviceVersion")).unwrap_or_default(),
        };
        // Continuous acquisition gated by the frame-start trigger.
        cam.set_acquisition_mode(AcquisitionMode::Continuous)
            .map_err(|e| refused("AcquisitionMode", "Continuous", &e, None, None))?;
        let format = cfg.pixel_format.to_string();
        cam.set_pixel_format_from_string(&format).map_err(|e| {
            let offers = cam.dup_available_pixel_formats_as_strings().ok().map(|v| {
                v.iter()
                    .map(|s| s.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            });
            refused(
                "PixelFormat",
                &format,
                &e,
                offers,
                Some((&cfg.name, "genicam.pixel_format")),
            )
        })?;
        for (feature, value) in [("Width", cfg.size[0]), ("Height", cfg.size[1])] {
            cam.set_integer(feature, i64::from(value)).map_err(|e| {
                let offers = cam
                    .integer_bounds(feature)
                    .ok()
                    .map(|(lo, hi)| format!("{lo} to {hi}"));
                refused(
                    feature,
                    &value.to_string(),
                    &e,
                    offers,
                    Some((&cfg.name, "intrinsics.resolution")),
                )
            })?;
        }
        if let Some(db) = cfg.gain_db {
            cam.set_gain(db).map_err(|e| {
                let offers = cam
                    .gain_bounds()
                    .ok()
                    .map(|(lo, hi)| format!("{lo} to {hi} dB"));
                refused(
                    "Gain",
                    &format!("{db} dB"),
                    &e,
                    offers,
                    Some((&cfg.name, "genicam.gain_db")),
                )
            })?;
        }
        check_exposure(&cam, cfg.exposure_s * 1e6, Some(&cfg.name))?;
        cam.set_exposure_time(cfg.exposure_s * 1e6).map_err(|e| {
            let offers = exposure_range(&cam);
            refused(
                "ExposureTime",
                &format!("{} µs", cfg.exposure_s * 1e6),
                &e,
                offers,
                Some((&cfg.name, "timing.exposure_s")),
            )
        })?;
        // The frame-start trigger, by name (SFNC), where the camera has a
        // selector; older cameras trigger frames only.
        if cam.is_feature_available("TriggerSelector").unwrap_or(false) {
            cam.set_string("TriggerSelector", "FrameStart")
                .map_err(|e| refused("TriggerSelector", "FrameStart", &e, None, None))?;
        }
        cam.set_string("TriggerMode", "On")
            .map_err(|e| refused("TriggerMode", "On", &e, None, None))?;
        cam.set_string("TriggerSource", &cfg.trigger_source)
            .map_err(|e| {
                refused(
                    "TriggerSource",
                    &cfg.trigger_source,
                    &e,
                    None,
                    Some((&cfg.name, "genicam.trigger_source")),
                )
            })?;
        let payload = cam.payload().map_err(|e| failed("PayloadSize", &e))?;
        let stream = cam
            .create_stream()
            .map_err(|e| failed("cannot open the stream channel", &e))?;
        for _ in 0..STREAM_BUFFERS {
            stream.push_buffer(Buffer::new_allocate(payload as usize));
        }
        cam.start_acquisition()
            .map_err(|e| failed("AcquisitionStart", &e))?;
        Ok(Box::new(AravisSession {
            cam,
            stream,
            identity,
        }))
    }
}

/// An open camera, acquiring on its trigger.
struct AravisSession {
    cam: Camera,
    stream: Stream,
    identity: GenicamIdentity,
}

impl Drop for AravisSession {
    fn drop(&mut self) {
        // A vanished camera cannot stop; that is no error worth reporting.
        let _ = self.cam.stop_acquisition();
    }
}

impl GenicamSession for AravisSession {
    fn identity(&self) -> GenicamIdentity {
        self.identity.clone()
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<(), SessionError> {
        check_exposure(&self.cam, exposure_us, None)?;
        self.cam.set_exposure_time(exposure_us).map_err(|e| {
            let offers = exposure_range(&self.cam);
            refused(
                "ExposureTime",
                &format!("{exposure_us} µs"),
                &e,
                offers,
                None,
            )
        })
    }

    fn trigger(&mut self) -> Result<(), SessionError> {
        // A frame of an earlier trigger that came after its deadline must
        // not pass for this trigger's.
        while let Some(stale) = self.stream.try_pop_buffer() {
            tracing::debug!(frame_id = stale.frame_id(), "stale GenICam frame dropped");
            self.stream.push_buffer(stale);
        }
        self.cam
            .software_trigger()
            .map_err(|e| failed("TriggerSoftware", &e))
    }

    fn next_buffer(&mut self, timeout: Duration) -> Result<Option<StreamBuffer>, SessionError> {
        let micros = u64::try_from(timeout.as_micros()).unwrap_or(u64::MAX);
        let Some(b) = self.stream.timeout_pop_buffer(micros) else {
            return Ok(None);
        };
        let status = b.status();
        let payload = b.payload_type();
        let image = matches!(
            payload,
            BufferPayloadType::Image | BufferPayloadType::ExtendedChunkData
        );
        let out = if status == BufferStatus::Success && image {
            let (w, h) = (b.image_width(), b.image_height());
            StreamBuffer {
                complete: Ok(()),
                frame_id: b.frame_id(),
                timestamp_ns: b.timestamp(),
                size: [u32::try_from(w).unwrap_or(0), u32::try_from(h).unwrap_or(0)],
                data: b.image_data(),
            }
        } else {
            // Only the status of a failed buffer (or the type of a payload
            // that is no raw image) is meaningful: no image fields are
            // filled in.
            let why = if status == BufferStatus::Success {
                format!("a {payload:?} payload, not a raw image")
            } else {
                format!("{status:?}")
            };
            StreamBuffer {
                complete: Err(why),
                frame_id: b.frame_id(),
                timestamp_ns: 0,
                size: [0, 0],
                data: Vec::new(),
            }
        };
        self.stream.push_buffer(b);
        Ok(Some(out))
    }
}
