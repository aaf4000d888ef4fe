//! The hardware-abstraction layer: small capability traits, one per thing a
//! device can do, and the [`Rig`] that holds a profile's devices behind them.
//!
//! Drivers keep their own rich errors and map them to a common
//! [`ErrorKind`], so the run engine can decide between retry and pause
//! without knowing the driver (the embedded-hal pattern).
//!
//! A crate of its own, so that a driver, the engine and anything that
//! stands in for a device depend on these traits and not on each other:
//! the simulator's firmware is reached through the same [`Opener`] a
//! serial port is.
#![warn(missing_docs)]

use std::collections::BTreeMap;
use std::fmt;
use std::sync::Arc;

use async_trait::async_trait;
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncWrite};

/// A byte stream a line or Modbus driver can run on.
pub trait ByteLink: AsyncRead + AsyncWrite + Send + Unpin + fmt::Debug + 'static {}
impl<T: AsyncRead + AsyncWrite + Send + Unpin + fmt::Debug + 'static> ByteLink for T {}

/// A boxed byte stream: a serial port, a TCP socket, an in-memory pipe to
/// simulated firmware.
pub type ByteStream = Box<dyn ByteLink>;

/// Opens (and re-opens) the byte stream of one device or bus: what a
/// serial or Modbus driver runs on, whatever is at the other end.
#[async_trait]
pub trait Opener: Send + Sync {
    /// Where the link goes, for error messages.
    fn describe(&self) -> String;
    /// Opens a fresh stream; called again after the link is lost.
    async fn open(&self) -> std::io::Result<ByteStream>;
}

/// What went wrong, as far as the run engine cares.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorKind {
    /// A call did not finish before its deadline.
    Timeout,
    /// The link to the device is gone.
    Disconnected,
    /// The device reported a fault (alarm, exception, not ready).
    DeviceFault,
    /// A set-point outside the soft limits (refused before sending).
    OutOfLimits,
    /// A frame arrived truncated or with the wrong size.
    BadFrame,
    /// The device was used out of order (not homed, nothing exposed).
    NotReady,
    /// The run directory could not take a frame (disk full, permission).
    Storage,
}

impl fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = match self {
            ErrorKind::Timeout => "timeout",
            ErrorKind::Disconnected => "disconnected",
            ErrorKind::DeviceFault => "device fault",
            ErrorKind::OutOfLimits => "out of limits",
            ErrorKind::BadFrame => "bad frame",
            ErrorKind::NotReady => "not ready",
            ErrorKind::Storage => "storage",
        };
        f.write_str(s)
    }
}

/// A failed device call: which device, what kind of failure, in the device's words.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{device}: {kind}: {message}")]
pub struct DeviceError {
    /// The device's (or bus's) name in the profile.
    pub device: String,
    /// What kind of failure, which decides whether the engine retries.
    pub kind: ErrorKind,
    /// The driver's description of what happened.
    pub message: String,
}

impl DeviceError {
    /// An error of `device` of this kind.
    pub fn new(device: &str, kind: ErrorKind, message: impl Into<String>) -> DeviceError {
        DeviceError {
            device: device.to_string(),
            kind,
            message: message.into(),
        }
    }
}

/// A frame as delivered by a camera: row-major, one `u16` per pixel holding
/// `bit_depth` significant bits.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Significant bits per pixel value.
    pub bit_depth: u8,
    /// `width × height` values, row by row.
    pub pixels: Vec<u16>,
    /// What the camera said of the frame itself, where it says anything
    /// (GenICam stream buffers); None for cameras that do not.
    pub device: Option<DeviceFrameInfo>,
    /// The file the camera delivered (a PTP camera's DNG, raw or JPEG),
    /// which the store keeps as the frame; None for cameras that deliver
    /// bare samples, stored as PNG.
    pub original: Option<OriginalFile>,
}

/// A frame as a camera's own file, kept byte for byte: `pixels` are what
/// it decodes to, this is what it is.
#[derive(Debug, Clone, PartialEq)]
pub struct OriginalFile {
    /// The file's bytes, as delivered.
    pub bytes: Vec<u8>,
    /// The stored file's extension (lowercase, one of
    /// `rigd::rig::camera_file::EXTENSIONS`).
    pub extension: &'static str,
}

/// A frame as the camera labelled it: recorded in the manifest beside
/// rigd's own index, so a frame can be matched to the camera's log.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DeviceFrameInfo {
    /// The camera's frame (block) id, counted by the camera.
    pub frame_id: u64,
    /// The camera's timestamp of the frame, nanoseconds of its own clock.
    pub timestamp_ns: u64,
    /// The pixel format the frame was delivered in (PFNC name).
    pub pixel_format: String,
}

impl Frame {
    /// The largest value a sample of this bit depth can hold.
    pub fn full_scale(&self) -> u16 {
        if self.bit_depth >= 16 {
            u16::MAX
        } else {
            (1u16 << self.bit_depth) - 1
        }
    }

    /// Checks that the pixel count matches the size and every value fits the depth.
    pub fn validate(&self, camera: &str) -> Result<(), DeviceError> {
        let expected = self.width as usize * self.height as usize;
        if self.pixels.len() != expected {
            return Err(DeviceError::new(
                camera,
                ErrorKind::BadFrame,
                format!(
                    "frame has {} pixels, expected {} ({}x{})",
                    self.pixels.len(),
                    expected,
                    self.width,
                    self.height
                ),
            ));
        }
        let max = self.full_scale();
        if let Some(v) = self.pixels.iter().find(|&&v| v > max) {
            return Err(DeviceError::new(
                camera,
                ErrorKind::BadFrame,
                format!("pixel value {v} exceeds {}-bit range", self.bit_depth),
            ));
        }
        Ok(())
    }
}

/// A motor that moves to absolute positions (degrees) and reports where it is.
#[async_trait]
pub trait Axis: Send {
    /// Runs the homing cycle; returns the position afterwards.
    async fn home(&mut self) -> Result<f64, DeviceError>;
    /// Moves to an absolute position and settles; returns the position reached.
    async fn move_to(&mut self, target: f64) -> Result<f64, DeviceError>;
    /// Asks the device where it stands; answers while the axis moves.
    async fn position(&mut self) -> Result<f64, DeviceError>;
    /// Starts a move at a constant velocity (degrees per second, within the
    /// axis's maximum) and returns once the controller accepted it: the
    /// laser sweep, during which cameras keep recording.
    async fn start_sweep(&mut self, target: f64, velocity: f64) -> Result<(), DeviceError>;
    /// Waits until a move started by [`Axis::start_sweep`] ends; returns the
    /// position reached.
    async fn wait_idle(&mut self) -> Result<f64, DeviceError>;
}

/// A multi-joint manipulator that moves all joints to a joint-space pose.
#[async_trait]
pub trait Arm: Send {
    /// Runs the homing cycle; returns the joint values afterwards (degrees,
    /// in profile order).
    async fn home(&mut self) -> Result<Vec<f64>, DeviceError>;
    /// Moves to joint values (degrees, in profile order); returns the pose reached.
    async fn move_joints(&mut self, joints: &[f64]) -> Result<Vec<f64>, DeviceError>;
    /// Asks the controller for the current joint values (degrees, in
    /// profile order).
    async fn joints(&mut self) -> Result<Vec<f64>, DeviceError>;
}

/// A lamp behind a relay.
#[async_trait]
pub trait Lamp: Send {
    /// Switches the lamp on or off; returns once the switch is confirmed.
    async fn set(&mut self, on: bool) -> Result<(), DeviceError>;
    /// Waits until the light output is stable (warm-up).
    async fn wait_ready(&mut self) -> Result<(), DeviceError>;
}

/// A laser line emitter (its tilt is an [`Axis`]).
#[async_trait]
pub trait LaserLine: Send {
    /// Switches the laser on or off; returns once the switch is confirmed.
    async fn set(&mut self, on: bool) -> Result<(), DeviceError>;
}

/// Something an operator places by hand, such as the laser calibration
/// plate of Wang et al., §3.2 (a flat plate at a known height over the
/// turntable).
#[async_trait]
pub trait Fixture: Send {
    /// Places the plate at `height_mm` above the turntable, or removes it
    /// (`None`); returns once it is in place.
    async fn place(&mut self, height_mm: Option<f64>) -> Result<(), DeviceError>;
}

/// A camera: expose (the sensor is busy and nothing may move), then transfer.
#[async_trait]
pub trait Camera: Send {
    /// Sets the exposure time, in seconds, of the following exposures.
    async fn set_exposure(&mut self, exposure_s: f64) -> Result<(), DeviceError>;
    /// Exposes and reads out the sensor; returns when the sensor is free.
    async fn expose(&mut self) -> Result<(), DeviceError>;
    /// Delivers the last exposed frame.
    async fn transfer(&mut self) -> Result<Frame, DeviceError>;
}

/// The emergency stop of one device (or one shared bus). It works from
/// outside any call in flight: GRBL's realtime bytes, the arm's abort, the
/// relay module's coils, so it never waits for a move to finish.
#[async_trait]
pub trait EmergencyStop: Send + Sync {
    /// Stops the device; returns once the device acknowledged.
    async fn emergency_stop(&self) -> Result<(), DeviceError>;
}

/// A profile's devices, by name, behind their capability traits.
#[derive(Default)]
pub struct Rig {
    /// Single axes (rail, turntable, light arc, laser tilt), by name.
    pub axes: BTreeMap<String, Box<dyn Axis>>,
    /// Robot arms, by name.
    pub arms: BTreeMap<String, Box<dyn Arm>>,
    /// Lamps, by name.
    pub lamps: BTreeMap<String, Box<dyn Lamp>>,
    /// Laser line emitters, by name.
    pub lasers: BTreeMap<String, Box<dyn LaserLine>>,
    /// The calibration plate, for rigs with a laser.
    pub fixture: Option<Box<dyn Fixture>>,
    /// Cameras, by name.
    pub cameras: BTreeMap<String, Box<dyn Camera>>,
    /// Out-of-band stops, by device (or bus) name.
    pub stops: BTreeMap<String, Arc<dyn EmergencyStop>>,
}

impl fmt::Debug for Rig {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Rig")
            .field("axes", &self.axes.keys().collect::<Vec<_>>())
            .field("arms", &self.arms.keys().collect::<Vec<_>>())
            .field("lamps", &self.lamps.keys().collect::<Vec<_>>())
            .field("lasers", &self.lasers.keys().collect::<Vec<_>>())
            .field("cameras", &self.cameras.keys().collect::<Vec<_>>())
            .field("stops", &self.stops.keys().collect::<Vec<_>>())
            .finish()
    }
}

/// Encodes a frame as a greyscale PNG: 8-bit for cameras of 8 bits or
/// fewer, else 16-bit holding the raw sensor values (not rescaled).
pub fn encode_png(frame: &Frame) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, frame.width, frame.height);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_compression(png::Compression::Fast);
        let data: Vec<u8> = if frame.bit_depth <= 8 {
            enc.set_depth(png::BitDepth::Eight);
            frame.pixels.iter().map(|&v| v.min(255) as u8).collect()
        } else {
            enc.set_depth(png::BitDepth::Sixteen);
            frame.pixels.iter().flat_map(|v| v.to_be_bytes()).collect()
        };
        let mut w = enc.write_header().map_err(|e| e.to_string())?;
        w.write_image_data(&data).map_err(|e| e.to_string())?;
    }
    Ok(out)
}

/// Whether `bytes` are a PNG file (its 8-byte signature): how rigd's own
/// frames are told from camera files.
pub fn is_png(bytes: &[u8]) -> bool {
    bytes.starts_with(b"\x89PNG\r\n\x1a\n")
}

/// Decodes a frame PNG written by [`encode_png`] back to pixel values.
pub fn decode_png(bytes: &[u8]) -> Result<(u32, u32, Vec<u16>), String> {
    let dec = png::Decoder::new(bytes);
    let mut reader = dec.read_info().map_err(|e| e.to_string())?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| e.to_string())?;
    let data = &buf[..info.buffer_size()];
    let pixels = match info.bit_depth {
        png::BitDepth::Sixteen => data
            .chunks_exact(2)
            .map(|c| u16::from_be_bytes([c[0], c[1]]))
            .collect(),
        png::BitDepth::Eight => data.iter().map(|&b| b as u16).collect(),
        d => return Err(format!("unsupported PNG depth {d:?}")),
    };
    Ok((info.width, info.height, pixels))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_validation_catches_truncation_and_overflow() {
        let mut f = Frame {
            width: 2,
            height: 2,
            bit_depth: 12,
            pixels: vec![0, 1, 4095, 7],
            device: None,
            original: None,
        };
        assert!(f.validate("cam").is_ok());
        f.pixels[1] = 4096;
        assert_eq!(
            f.validate("cam").map_err(|e| e.kind),
            Err(ErrorKind::BadFrame)
        );
        f.pixels.pop();
        assert_eq!(
            f.validate("cam").map_err(|e| e.kind),
            Err(ErrorKind::BadFrame)
        );
    }
}
