//! Cameras through libgphoto2: still cameras of every make libgphoto2
//! drives (on USB, or over PTP/IP), with libgphoto2's own camera drivers
//! doing the protocol, on `transport = { type = "gphoto2" }`.
//!
//! The driver speaks to a [`Gphoto2Session`]: the few blocking calls it
//! needs of an open camera. `rig::drivers::libgphoto2` implements it with
//! the `gphoto2` crate (cargo feature `gphoto2`, chosen in
//! `rig::hardware`); the tests here implement it with a scripted camera.
//!
//! libgphoto2's calls block, so every session lives on a thread of its
//! own and the driver hands it one call at a time over a channel, each
//! under a deadline through the [`Clock`]. A call that misses its
//! deadline (or that says the link is gone) abandons that thread and its
//! session: the camera counts as lost, the run pauses with the reason
//! once its retries are spent, and the next call opens a fresh session on
//! a new thread, with every widget set again.
//!
//! What the driver adds to the session:
//! - the profile's widgets (`devices.NAME.gphoto2.settings`) are set at
//!   every connect, and a value the camera does not offer is refused,
//!   naming what it offers;
//! - the exposure time is the `shutterspeed` choice whose time is the
//!   requested one (within [`SHUTTER_TOLERANCE`]); none is a refusal that
//!   names the choices;
//! - a capture is libgphoto2's own (`gp_camera_capture`); the file is
//!   downloaded as the camera delivered it, made a frame the way the PTP
//!   driver makes its frames, then deleted from the camera.

use std::collections::BTreeMap;
use std::sync::{mpsc, Arc};
use std::time::Duration;

use async_trait::async_trait;
use rigd_core::{Cfa, Clock};
use tokio::sync::oneshot;

use super::ptp::frame_of_file;
use crate::model::profile::{Device, Transport, GPHOTO2_SHUTTER_WIDGET};
use crate::rig::camera_file::DecodeIn;
use crate::rig::hal::{Camera, DeviceError, ErrorKind, Frame};

/// How far a `shutterspeed` choice's time may lie from the requested
/// exposure and still be it, relative (1/3 s is "0.3333s" or "1/3", 1/13 s
/// is "0.0769s"). A label in decimals also stands for anything it rounds
/// from: libgphoto2's ptp2 driver writes 1/1600 s as "0.0006s".
pub const SHUTTER_TOLERANCE: f64 = 0.01;

/// What a camera through libgphoto2 is asked for at every connect, and
/// the deadlines of its calls.
#[derive(Debug, Clone, PartialEq)]
pub struct Gphoto2Config {
    /// The camera's name in the profile.
    pub name: String,
    /// libgphoto2's port (`usb:001,004`, `ptpip:HOST:PORT:PORT`); None:
    /// autodetect.
    pub port: Option<String>,
    /// libgphoto2's model name; None: the one autodetected.
    pub model: Option<String>,
    /// Widget name → value, set at every connect.
    pub settings: BTreeMap<String, String>,
    /// The exposure until the run sets its own, seconds.
    pub exposure_s: f64,
    /// The sensor's colour filter array as the profile describes it; a
    /// raw frame with another is refused.
    pub cfa: Option<Cfa>,
    /// Opening the camera and setting its widgets.
    pub open_timeout: Duration,
    /// A widget read or write, or deleting a file.
    pub call_timeout: Duration,
    /// How long a capture may take beyond the exposure time (readout,
    /// storing the file, the driver's own waits for its events).
    pub capture_slack: Duration,
    /// Downloading one file.
    pub transfer_timeout: Duration,
}

impl Gphoto2Config {
    /// The configuration of a camera device on a gphoto2 transport; None
    /// for other devices. Validation guarantees timing for cameras.
    pub fn of(name: &str, dev: &Device) -> Option<Gphoto2Config> {
        let camera = dev.as_camera()?;
        let Transport::Gphoto2 { port, model } = &camera.transport else {
            return None;
        };
        let timing = camera.timing;
        Some(Gphoto2Config {
            name: name.to_string(),
            port: port.clone(),
            model: model.clone(),
            settings: camera
                .gphoto2
                .as_ref()
                .map(|g| g.settings.clone())
                .unwrap_or_default(),
            exposure_s: timing.exposure_s,
            cfa: camera.intrinsics.cfa,
            open_timeout: Duration::from_secs(30),
            call_timeout: Duration::from_secs(10),
            capture_slack: Duration::from_secs(30),
            transfer_timeout: Duration::from_secs(60),
        })
    }

    /// The profile key of the colour filter array, for messages.
    fn cfa_key(&self) -> String {
        format!("devices.{}.intrinsics.cfa", self.name)
    }
}

/// What libgphoto2 says of the camera it opened.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Gphoto2Identity {
    /// libgphoto2's model name, which chose its driver (`PTP/IP Camera`).
    pub driver_model: String,
    /// The port it opened.
    pub port: String,
    /// The camera's manufacturer, as it says (empty when it does not).
    pub manufacturer: String,
    /// The camera's own model name (empty when it does not say).
    pub model: String,
    /// The camera's firmware version (empty when it does not say).
    pub version: String,
    /// The camera's serial number (empty when it does not say).
    pub serial: String,
    /// The widgets rigd set at connect, name and value, the
    /// `shutterspeed` last; filled in by the driver.
    pub widgets: Vec<(String, String)>,
}

/// A configuration widget as the camera reports it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WidgetState {
    /// Its current value, as text.
    pub value: String,
    /// The values it takes, for a widget with a list (radio or menu);
    /// None for free text, numbers and toggles.
    pub choices: Option<Vec<String>>,
    /// Whether the camera lets it be set.
    pub readonly: bool,
}

/// Where a captured file lies on the camera.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraPath {
    /// Its folder (`/store_00010001`).
    pub folder: String,
    /// Its name in the folder.
    pub name: String,
}

impl std::fmt::Display for CameraPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.folder.trim_end_matches('/'), self.name)
    }
}

/// A failed session call: what kind of failure, in libgphoto2's or the
/// driver's words, and whether the session is lost with it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{message}")]
pub struct Gphoto2Error {
    /// Decides retry, retake or pause.
    pub kind: ErrorKind,
    /// What went wrong.
    pub message: String,
    /// Whether the session is dropped: the next call opens a fresh one.
    pub session_lost: bool,
}

impl Gphoto2Error {
    /// An error of this kind; a lost link or a silent camera
    /// (`Disconnected`, `Timeout`) loses the session with it.
    pub fn new(kind: ErrorKind, message: impl Into<String>) -> Gphoto2Error {
        Gphoto2Error {
            kind,
            message: message.into(),
            session_lost: matches!(kind, ErrorKind::Disconnected | ErrorKind::Timeout),
        }
    }

    /// An error of this kind that leaves the session open (a busy camera
    /// is asked again on the same session).
    pub fn keeping_session(kind: ErrorKind, message: impl Into<String>) -> Gphoto2Error {
        Gphoto2Error {
            kind,
            message: message.into(),
            session_lost: false,
        }
    }
}

/// An open camera: the blocking calls the driver makes. Each runs on the
/// session's own thread.
pub trait Gphoto2Session: Send {
    /// What the camera and libgphoto2 said of it at open.
    fn identity(&self) -> Gphoto2Identity;
    /// Reads a configuration widget by name.
    fn widget(&mut self, name: &str) -> Result<WidgetState, Gphoto2Error>;
    /// Sets a configuration widget by name (a list's choice as text).
    fn set_widget(&mut self, name: &str, value: &str) -> Result<(), Gphoto2Error>;
    /// Captures one image through the camera driver's capture path;
    /// returns once the camera stored it.
    fn capture(&mut self) -> Result<CameraPath, Gphoto2Error>;
    /// Downloads a file as the camera delivers it.
    fn download(&mut self, file: &CameraPath) -> Result<Vec<u8>, Gphoto2Error>;
    /// Deletes a file from the camera.
    fn delete(&mut self, file: &CameraPath) -> Result<(), Gphoto2Error>;
}

/// Opens a camera; called again after it was lost.
pub trait Gphoto2Opener: Send + Sync {
    /// Where the camera is, for messages.
    fn describe(&self) -> String;
    /// Opens the camera (on the calling thread, which then owns the
    /// session).
    fn open(&self) -> Result<Box<dyn Gphoto2Session>, Gphoto2Error>;
}

/// A choice's exposure time, seconds: `1/1000`, `0.1000s`, `2.5`, `30s`,
/// `1"` (Canon's seconds); None for `Bulb`, `Time`, `auto` and other words.
pub fn choice_seconds(choice: &str) -> Option<f64> {
    let t = choice.trim();
    let t = t
        .strip_suffix('s')
        .or_else(|| t.strip_suffix('"'))
        .unwrap_or(t)
        .trim();
    let s = match t.split_once('/') {
        Some((n, d)) => n.trim().parse::<f64>().ok()? / d.trim().parse::<f64>().ok()?,
        None => t.parse::<f64>().ok()?,
    };
    (s.is_finite() && s > 0.0).then_some(s)
}

/// Half a unit of a choice's last decimal digit: how far from its label
/// a time it rounds from may lie (0 for a fraction or a whole number).
fn label_rounding(choice: &str) -> f64 {
    let t = choice.trim().trim_end_matches(['s', '"']);
    if t.contains('/') {
        return 0.0;
    }
    match t.split_once('.') {
        Some((_, decimals)) => 0.5 * 10f64.powi(-(decimals.len().min(12) as i32)),
        None => 0.0,
    }
}

/// An exposure as a photographer writes it: `1/250` below a second when
/// that is exact to 0.1 %, else seconds.
fn exposure_text(s: f64) -> String {
    if s < 1.0 {
        let n = (1.0 / s).round();
        if n >= 1.0 && ((1.0 / n) - s).abs() <= 1e-3 * s {
            return format!("1/{n}");
        }
    }
    format!("{s} s")
}

/// The `shutterspeed` choice for `exposure_s`: the listed choice whose
/// time is nearest, within [`SHUTTER_TOLERANCE`] or its label's rounding;
/// else why not, naming the choices.
pub fn shutter_choice(exposure_s: f64, choices: &[String]) -> Result<String, String> {
    let best = choices
        .iter()
        .filter_map(|c| {
            let off = (choice_seconds(c)? - exposure_s).abs();
            // 1e-12 s: the float error of parsing and dividing.
            let allowed = (SHUTTER_TOLERANCE * exposure_s).max(label_rounding(c)) + 1e-12;
            (off <= allowed).then_some((c, off))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1));
    match best {
        Some((c, _)) => Ok(c.clone()),
        None if choices.is_empty() => Err(format!(
            "{GPHOTO2_SHUTTER_WIDGET} {} cannot be set: the camera lists no choices",
            exposure_text(exposure_s)
        )),
        None => Err(format!(
            "{GPHOTO2_SHUTTER_WIDGET} {} is not offered; the camera offers: {}",
            exposure_text(exposure_s),
            choices.join(", ")
        )),
    }
}

/// A widget the camera refuses or lacks: a set-up error (the profile
/// asks for what the camera cannot do), not a lost link.
fn set_up_error(e: Gphoto2Error, what: String) -> Gphoto2Error {
    if e.session_lost {
        e
    } else {
        Gphoto2Error::keeping_session(ErrorKind::NotReady, format!("{what}: {}", e.message))
    }
}

/// Sets the `shutterspeed` choice of `exposure_s`; returns it. `refused`
/// is the kind of a refusal (a set-up error at connect, out of limits for
/// a run's exposure); `fix` names the profile key that sets it.
fn set_shutter(
    session: &mut dyn Gphoto2Session,
    exposure_s: f64,
    refused: ErrorKind,
    fix: Option<&str>,
) -> Result<String, Gphoto2Error> {
    let w = session.widget(GPHOTO2_SHUTTER_WIDGET).map_err(|e| {
        set_up_error(
            e,
            format!("the camera has no `{GPHOTO2_SHUTTER_WIDGET}` widget to set the exposure by"),
        )
    })?;
    let choices = w.choices.unwrap_or_default();
    let choice = shutter_choice(exposure_s, &choices).map_err(|why| {
        let fix = fix.map_or(String::new(), |key| {
            format!("; set `{key}` to what the camera offers")
        });
        Gphoto2Error::keeping_session(refused, format!("{why}{fix}"))
    })?;
    if w.value != choice {
        session
            .set_widget(GPHOTO2_SHUTTER_WIDGET, &choice)
            .map_err(|e| {
                set_up_error(
                    e,
                    format!("the camera refuses {GPHOTO2_SHUTTER_WIDGET} = {choice}"),
                )
            })?;
    }
    Ok(choice)
}

/// Sets the profile's widgets and the exposure on a freshly opened
/// camera; returns what it set, in order.
fn configure(
    session: &mut dyn Gphoto2Session,
    cfg: &Gphoto2Config,
    exposure_s: f64,
) -> Result<Vec<(String, String)>, Gphoto2Error> {
    let mut set = Vec::new();
    for (name, value) in &cfg.settings {
        let key = format!("devices.{}.gphoto2.settings.{name}", cfg.name);
        let w = session.widget(name).map_err(|e| {
            set_up_error(
                e,
                format!("the camera has no widget `{name}` (`gphoto2 --list-config` lists them); fix `{key}`"),
            )
        })?;
        if w.readonly {
            return Err(Gphoto2Error::keeping_session(
                ErrorKind::NotReady,
                format!("the camera's widget `{name}` is read-only; remove `{key}`"),
            ));
        }
        if let Some(choices) = &w.choices {
            if !choices.contains(value) {
                return Err(Gphoto2Error::keeping_session(
                    ErrorKind::NotReady,
                    format!(
                        "{name} {value} is not offered; the camera offers: {}; set `{key}` to what the camera offers",
                        choices.join(", ")
                    ),
                ));
            }
        }
        session
            .set_widget(name, value)
            .map_err(|e| set_up_error(e, format!("the camera refuses {name} = {value}")))?;
        set.push((name.clone(), value.clone()));
    }
    let key = format!("devices.{}.timing.exposure_s", cfg.name);
    let shutter = set_shutter(session, exposure_s, ErrorKind::NotReady, Some(&key))?;
    set.push((GPHOTO2_SHUTTER_WIDGET.to_string(), shutter));
    Ok(set)
}

/// One call for the session's thread.
type Job = Box<dyn FnOnce(&mut Option<Box<dyn Gphoto2Session>>) + Send>;

/// The thread that owns one session. Dropping it ends the thread once its
/// call in flight (if any) returns, and the session closes there: closing
/// a camera that vanished can take libgphoto2's own timeouts, which then
/// hold no one up.
struct Worker {
    jobs: mpsc::Sender<Job>,
}

impl Worker {
    fn spawn() -> Result<Worker, Gphoto2Error> {
        let (jobs, rx) = mpsc::channel::<Job>();
        std::thread::Builder::new()
            .name("rigd-gphoto2".into())
            .spawn(move || {
                let mut session = None;
                while let Ok(job) = rx.recv() {
                    job(&mut session);
                }
            })
            .map_err(|e| {
                Gphoto2Error::new(
                    ErrorKind::DeviceFault,
                    format!("cannot start the camera's thread: {e}"),
                )
            })?;
        Ok(Worker { jobs })
    }
}

/// A camera through libgphoto2 behind the HAL's [`Camera`].
pub struct Gphoto2Camera {
    cfg: Arc<Gphoto2Config>,
    opener: Arc<dyn Gphoto2Opener>,
    clock: Clock,
    /// The open session's thread; None when the camera is not open.
    worker: Option<Worker>,
    /// The exposure set (the profile's until the run sets its own).
    exposure_s: f64,
    /// The captured file not yet downloaded.
    pending: Option<CameraPath>,
}

impl Gphoto2Camera {
    /// Opens the camera and sets its widgets and exposure; returns the
    /// driver and what the camera said of itself.
    pub async fn connect(
        cfg: Gphoto2Config,
        opener: Arc<dyn Gphoto2Opener>,
        clock: Clock,
    ) -> Result<(Gphoto2Camera, Gphoto2Identity), DeviceError> {
        let mut cam = Gphoto2Camera {
            exposure_s: cfg.exposure_s,
            cfg: Arc::new(cfg),
            opener,
            clock,
            worker: None,
            pending: None,
        };
        let identity = cam.open().await?;
        Ok((cam, identity))
    }

    /// Where the camera is, for messages.
    pub fn describe(&self) -> String {
        self.opener.describe()
    }

    /// Opens a session on a new thread and configures the camera.
    async fn open(&mut self) -> Result<Gphoto2Identity, DeviceError> {
        self.pending = None;
        self.worker = Some(Worker::spawn().map_err(|e| self.device_error(e))?);
        let (opener, cfg, exposure_s) = (self.opener.clone(), self.cfg.clone(), self.exposure_s);
        let opened = self
            .run("opening the camera", self.cfg.open_timeout, move |slot| {
                let mut session = opener.open()?;
                let widgets = configure(session.as_mut(), &cfg, exposure_s)?;
                let mut identity = session.identity();
                identity.widgets = widgets;
                *slot = Some(session);
                Ok(identity)
            })
            .await;
        match opened {
            Ok(identity) => {
                tracing::info!(
                    device = %self.cfg.name,
                    camera = %self.opener.describe(),
                    model = %identity.model,
                    "camera opened through libgphoto2"
                );
                Ok(identity)
            }
            Err(e) => {
                // Half-configured is not open: the next call starts afresh.
                self.worker = None;
                Err(e)
            }
        }
    }

    /// Runs `f` on the open session (opening one first if there is none)
    /// under `limit`.
    async fn call<T: Send + 'static>(
        &mut self,
        what: &'static str,
        limit: Duration,
        f: impl FnOnce(&mut dyn Gphoto2Session) -> Result<T, Gphoto2Error> + Send + 'static,
    ) -> Result<T, DeviceError> {
        if self.worker.is_none() {
            self.open().await?;
        }
        self.run(what, limit, move |slot| match slot.as_deref_mut() {
            Some(session) => f(session),
            None => Err(Gphoto2Error::new(
                ErrorKind::Disconnected,
                "the camera is not open",
            )),
        })
        .await
    }

    /// Hands `job` to the session's thread and waits for it under
    /// `limit`. A job that misses its deadline, or whose error loses the
    /// session, abandons the thread.
    async fn run<T: Send + 'static>(
        &mut self,
        what: &'static str,
        limit: Duration,
        job: impl FnOnce(&mut Option<Box<dyn Gphoto2Session>>) -> Result<T, Gphoto2Error>
            + Send
            + 'static,
    ) -> Result<T, DeviceError> {
        let (tx, rx) = oneshot::channel();
        let sent = self.worker.as_ref().map(|w| {
            w.jobs.send(Box::new(move |slot| {
                // The driver may have given up waiting; nobody to tell.
                let _ = tx.send(job(slot));
            }))
        });
        let lost = |message: String| Gphoto2Error {
            kind: ErrorKind::DeviceFault,
            message,
            session_lost: true,
        };
        let outcome = match sent {
            None | Some(Err(_)) => Err(lost(format!("{what}: the camera's thread has ended"))),
            Some(Ok(())) => match self.clock.deadline(limit, rx).await {
                Ok(Ok(r)) => r,
                // The job was dropped unrun or panicked in libgphoto2's
                // binding: the session is in no known state.
                Ok(Err(_)) => Err(lost(format!("{what}: libgphoto2 failed on the camera's thread"))),
                Err(_) => Err(Gphoto2Error::new(
                    ErrorKind::Timeout,
                    format!(
                        "{what}: libgphoto2 gave no answer within {limit:?}; the camera is opened afresh at the next call"
                    ),
                )),
            },
        };
        if let Err(e) = &outcome {
            if e.session_lost {
                self.worker = None;
                self.pending = None;
            }
        }
        outcome.map_err(|e| self.device_error(e))
    }

    fn device_error(&self, e: Gphoto2Error) -> DeviceError {
        DeviceError::new(&self.cfg.name, e.kind, e.message)
    }
}

#[async_trait]
impl Camera for Gphoto2Camera {
    async fn set_exposure(&mut self, exposure_s: f64) -> Result<(), DeviceError> {
        if !(exposure_s.is_finite() && exposure_s > 0.0) {
            return Err(DeviceError::new(
                &self.cfg.name,
                ErrorKind::OutOfLimits,
                format!("exposure {exposure_s} s is not a positive time"),
            ));
        }
        let limit = self.cfg.call_timeout;
        self.call("setting the shutterspeed", limit, move |s| {
            set_shutter(s, exposure_s, ErrorKind::OutOfLimits, None)
        })
        .await?;
        self.exposure_s = exposure_s;
        Ok(())
    }

    async fn expose(&mut self) -> Result<(), DeviceError> {
        if let Some(stale) = self.pending.take() {
            // A file nobody downloaded would fill the card; it is not needed.
            let limit = self.cfg.call_timeout;
            let _ = self
                .call("deleting an earlier capture", limit, move |s| {
                    s.delete(&stale)
                })
                .await;
        }
        let limit = Duration::try_from_secs_f64(self.exposure_s)
            .unwrap_or(Duration::MAX)
            .saturating_add(self.cfg.capture_slack);
        let file = self.call("capturing", limit, |s| s.capture()).await?;
        self.pending = Some(file);
        Ok(())
    }

    async fn transfer(&mut self) -> Result<Frame, DeviceError> {
        let Some(file) = self.pending.clone() else {
            return Err(DeviceError::new(
                &self.cfg.name,
                ErrorKind::NotReady,
                "nothing was exposed",
            ));
        };
        let limit = self.cfg.transfer_timeout;
        let from = file.clone();
        let bytes = self
            .call("downloading the capture", limit, move |s| s.download(&from))
            .await?;
        // A file that is no frame stays pending: the retake deletes it.
        let frame = frame_of_file(
            &self.cfg.name,
            bytes,
            DecodeIn::Child,
            self.cfg.cfa,
            &self.cfg.cfa_key(),
        )
        .await
        .map_err(|e| DeviceError::new(&self.cfg.name, e.kind(), format!("{file}: {e}")))?;
        let limit = self.cfg.call_timeout;
        self.call("deleting the capture", limit, move |s| s.delete(&file))
            .await?;
        self.pending = None;
        Ok(frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Mutex;

    /// The simulated camera's labels, as libgphoto2's ptp2 driver writes
    /// them, and other drivers' forms.
    fn labels(l: &[&str]) -> Vec<String> {
        l.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn choices_read_as_seconds_in_every_drivers_form() {
        for (text, s) in [
            ("1/1000", 0.001),
            ("0.1000s", 0.1),
            ("1", 1.0),
            ("30", 30.0),
            ("2.5s", 2.5),
            ("1\"", 1.0),
            ("1/3", 1.0 / 3.0),
        ] {
            let got = choice_seconds(text).expect(text);
            assert!((got - s).abs() < 1e-12, "{text}: {got}");
        }
        for text in ["Bulb", "Time", "auto", "0", "1/0", "", "-1"] {
            assert_eq!(choice_seconds(text), None, "{text}");
        }
    }

    #[test]
    fn an_exposure_takes_the_choice_of_its_time_or_is_refused_naming_them() {
        let ptp2 = labels(&[
            "0.0005s", "0.0006s", "0.0008s", "0.0769s", "0.1000s", "Bulb",
        ]);
        assert_eq!(shutter_choice(0.1, &ptp2).as_deref(), Ok("0.1000s"));
        // 1/1600 s is "0.0006s" (4 % off, within the label's rounding).
        assert_eq!(
            shutter_choice(1.0 / 1600.0, &ptp2).as_deref(),
            Ok("0.0006s")
        );
        assert_eq!(shutter_choice(1.0 / 13.0, &ptp2).as_deref(), Ok("0.0769s"));
        let nikon = labels(&["1/4000", "1/3200", "1/2000", "1/3", "30", "Bulb"]);
        assert_eq!(shutter_choice(0.333, &nikon).as_deref(), Ok("1/3"));
        assert_eq!(shutter_choice(30.0, &nikon).as_deref(), Ok("30"));
        let e = shutter_choice(1.0 / 3000.0, &nikon).expect_err("not listed");
        assert_eq!(
            e,
            "shutterspeed 1/3000 is not offered; the camera offers: 1/4000, 1/3200, 1/2000, 1/3, 30, Bulb"
        );
        let e = shutter_choice(0.0123, &ptp2).expect_err("between two");
        assert!(e.starts_with("shutterspeed 0.0123 s is not offered"), "{e}");
        assert!(shutter_choice(0.1, &[]).is_err());
    }

    /// What the scripted camera holds and does.
    #[derive(Default)]
    struct Script {
        widgets: BTreeMap<String, WidgetState>,
        /// Widget writes, in order, across sessions.
        set: Vec<(String, String)>,
        /// How long a capture takes.
        capture_delay: Duration,
        /// What a download delivers.
        file: Vec<u8>,
        captured: usize,
        deleted: Vec<String>,
        /// What the next captures fail with, in order.
        capture_errors: Vec<Gphoto2Error>,
    }

    struct Scripted(Arc<Mutex<Script>>);

    impl Gphoto2Session for Scripted {
        fn identity(&self) -> Gphoto2Identity {
            Gphoto2Identity {
                driver_model: "PTP/IP Camera".into(),
                model: "Scripted".into(),
                ..Gphoto2Identity::default()
            }
        }
        fn widget(&mut self, name: &str) -> Result<WidgetState, Gphoto2Error> {
            let s = self.0.lock().unwrap();
            s.widgets
                .get(name)
                .cloned()
                .ok_or_else(|| Gphoto2Error::keeping_session(ErrorKind::NotReady, "Bad parameters"))
        }
        fn set_widget(&mut self, name: &str, value: &str) -> Result<(), Gphoto2Error> {
            let mut s = self.0.lock().unwrap();
            s.set.push((name.into(), value.into()));
            if let Some(w) = s.widgets.get_mut(name) {
                w.value = value.into();
            }
            Ok(())
        }
        fn capture(&mut self) -> Result<CameraPath, Gphoto2Error> {
            let delay = self.0.lock().unwrap().capture_delay;
            std::thread::sleep(delay);
            let mut s = self.0.lock().unwrap();
            if !s.capture_errors.is_empty() {
                return Err(s.capture_errors.remove(0));
            }
            s.captured += 1;
            Ok(CameraPath {
                folder: "/store".into(),
                name: format!("IMG_{:04}.DNG", s.captured),
            })
        }
        fn download(&mut self, _file: &CameraPath) -> Result<Vec<u8>, Gphoto2Error> {
            Ok(self.0.lock().unwrap().file.clone())
        }
        fn delete(&mut self, file: &CameraPath) -> Result<(), Gphoto2Error> {
            self.0.lock().unwrap().deleted.push(file.to_string());
            Ok(())
        }
    }

    struct Opener {
        script: Arc<Mutex<Script>>,
        opens: AtomicUsize,
    }

    impl Gphoto2Opener for Opener {
        fn describe(&self) -> String {
            "scripted camera".into()
        }
        fn open(&self) -> Result<Box<dyn Gphoto2Session>, Gphoto2Error> {
            self.opens.fetch_add(1, Ordering::SeqCst);
            Ok(Box::new(Scripted(self.script.clone())))
        }
    }

    fn radio(value: &str, choices: &[&str]) -> WidgetState {
        WidgetState {
            value: value.into(),
            choices: Some(labels(choices)),
            readonly: false,
        }
    }

    fn script() -> Script {
        let mut s = Script::default();
        s.widgets.insert(
            "shutterspeed".into(),
            radio("0.1000s", &["0.0100s", "0.1000s", "1.0000s"]),
        );
        s.widgets
            .insert("iso".into(), radio("100", &["100", "200", "400"]));
        s
    }

    fn cfg(settings: &[(&str, &str)], exposure_s: f64) -> Gphoto2Config {
        Gphoto2Config {
            name: "camera".into(),
            port: None,
            model: None,
            settings: settings
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect(),
            exposure_s,
            cfa: None,
            open_timeout: Duration::from_secs(5),
            call_timeout: Duration::from_secs(5),
            capture_slack: Duration::from_millis(300),
            transfer_timeout: Duration::from_secs(5),
        }
    }

    fn opener(script: Script) -> (Arc<Opener>, Arc<Mutex<Script>>) {
        let script = Arc::new(Mutex::new(script));
        let o = Arc::new(Opener {
            script: script.clone(),
            opens: AtomicUsize::new(0),
        });
        (o, script)
    }

    #[tokio::test]
    async fn a_connect_sets_the_widgets_then_the_shutterspeed_of_the_exposure() {
        let (o, script) = opener(script());
        let (_cam, id) =
            Gphoto2Camera::connect(cfg(&[("iso", "400")], 0.01), o.clone(), Clock::real())
                .await
                .expect("connect");
        let set = vec![
            ("iso".to_string(), "400".to_string()),
            ("shutterspeed".to_string(), "0.0100s".to_string()),
        ];
        assert_eq!(id.widgets, set);
        assert_eq!(id.model, "Scripted");
        assert_eq!(script.lock().unwrap().set, set);
    }

    #[tokio::test]
    async fn a_value_the_camera_does_not_offer_fails_the_connect_naming_the_offer() {
        let (o, _) = opener(script());
        let e = Gphoto2Camera::connect(cfg(&[("iso", "123")], 0.1), o.clone(), Clock::real())
            .await
            .err()
            .expect("refused");
        assert_eq!(e.kind, ErrorKind::NotReady);
        assert!(e.message.contains("iso 123 is not offered; the camera offers: 100, 200, 400; set `devices.camera.gphoto2.settings.iso`"), "{e}");
        let e = Gphoto2Camera::connect(cfg(&[], 0.0123), o.clone(), Clock::real())
            .await
            .err()
            .expect("refused");
        assert_eq!(e.kind, ErrorKind::NotReady);
        assert!(
            e.message.contains(
                "shutterspeed 0.0123 s is not offered; the camera offers: 0.0100s, 0.1000s, 1.0000s; set `devices.camera.timing.exposure_s` to what the camera offers"
            ),
            "{e}"
        );
        let e = Gphoto2Camera::connect(cfg(&[("nosuch", "1")], 0.1), o, Clock::real())
            .await
            .err()
            .expect("refused");
        assert!(e.message.contains("no widget `nosuch`"), "{e}");
    }

    #[tokio::test]
    async fn a_run_exposure_the_camera_does_not_list_is_out_of_limits() {
        let (o, script) = opener(script());
        let (mut cam, _) = Gphoto2Camera::connect(cfg(&[], 0.1), o, Clock::real())
            .await
            .expect("connect");
        cam.set_exposure(1.0).await.expect("listed");
        let e = cam.set_exposure(0.5).await.expect_err("not listed");
        assert_eq!(e.kind, ErrorKind::OutOfLimits);
        assert!(e.message.contains("the camera offers"), "{e}");
        let last = script.lock().unwrap().set.last().cloned();
        assert_eq!(last, Some(("shutterspeed".into(), "1.0000s".into())));
    }

    #[tokio::test]
    async fn a_capture_past_its_deadline_drops_the_session_and_the_next_call_reopens() {
        let mut s = script();
        s.capture_delay = Duration::from_secs(2);
        let (o, script) = opener(s);
        let (mut cam, _) = Gphoto2Camera::connect(cfg(&[], 0.01), o.clone(), Clock::real())
            .await
            .expect("connect");
        let e = cam.expose().await.expect_err("too slow");
        assert_eq!(e.kind, ErrorKind::Timeout);
        assert!(e.message.contains("opened afresh"), "{e}");
        script.lock().unwrap().capture_delay = Duration::ZERO;
        cam.expose().await.expect("a fresh session");
        assert_eq!(o.opens.load(Ordering::SeqCst), 2);
    }

    #[tokio::test]
    async fn a_lost_link_reopens_with_every_widget_and_the_run_s_exposure_but_a_busy_camera_does_not(
    ) {
        let mut s = script();
        s.capture_errors = vec![
            Gphoto2Error::keeping_session(ErrorKind::Timeout, "Camera is busy"),
            Gphoto2Error::new(ErrorKind::Disconnected, "I/O problem"),
        ];
        let (o, script) = opener(s);
        let (mut cam, _) =
            Gphoto2Camera::connect(cfg(&[("iso", "200")], 0.1), o.clone(), Clock::real())
                .await
                .expect("connect");
        cam.set_exposure(1.0).await.expect("exposure");
        let e = cam.expose().await.expect_err("busy");
        assert_eq!(e.kind, ErrorKind::Timeout);
        assert_eq!(o.opens.load(Ordering::SeqCst), 1, "busy keeps the session");
        let e = cam.expose().await.expect_err("gone");
        assert_eq!(
            (e.kind, e.message.as_str()),
            (ErrorKind::Disconnected, "I/O problem")
        );
        {
            // The camera came back from a power cycle at its own settings.
            let mut s = script.lock().unwrap();
            s.set.clear();
            if let Some(w) = s.widgets.get_mut("shutterspeed") {
                w.value = "0.1000s".into();
            }
        }
        cam.expose().await.expect("reconnected");
        assert_eq!(o.opens.load(Ordering::SeqCst), 2);
        assert_eq!(
            script.lock().unwrap().set,
            vec![
                ("iso".to_string(), "200".to_string()),
                ("shutterspeed".to_string(), "1.0000s".to_string()),
            ]
        );
    }

    #[tokio::test]
    async fn a_file_that_is_no_frame_is_a_bad_frame_and_the_retake_deletes_it() {
        let mut s = script();
        s.file = b"not an image".to_vec();
        let (o, script) = opener(s);
        let (mut cam, _) = Gphoto2Camera::connect(cfg(&[], 0.1), o, Clock::real())
            .await
            .expect("connect");
        cam.expose().await.expect("expose");
        let e = cam.transfer().await.expect_err("no frame");
        assert_eq!(e.kind, ErrorKind::BadFrame);
        assert!(e.message.starts_with("/store/IMG_0001.DNG"), "{e}");
        assert!(script.lock().unwrap().deleted.is_empty());
        cam.expose().await.expect("retake");
        assert_eq!(script.lock().unwrap().deleted, vec!["/store/IMG_0001.DNG"]);
        let e = Gphoto2Camera::connect(
            cfg(&[], 0.1),
            Arc::new(crate::rig::hardware::NoGphoto2 { port: None }),
            Clock::real(),
        )
        .await
        .err()
        .expect("no libgphoto2");
        assert!(e.message.contains("--features gphoto2"), "{e}");
    }
}
