//! The libgphoto2 session, through the `gphoto2` crate (Debian's
//! libgphoto2 2.5): USB and PTP/IP cameras by libgphoto2's port and model.
//! Built with the cargo feature `gphoto2`.
//!
//! The crate runs every libgphoto2 call on one thread of its own and hands
//! back a task; the session waits for each on the driver's thread for the
//! camera, which holds the deadline. A call that libgphoto2 never ends
//! therefore also holds up the other cameras' calls through the crate:
//! libgphoto2's own I/O timeouts bound that.

use ::gphoto2::list::CameraDescriptor;
use ::gphoto2::widget::Widget;
use ::gphoto2::{Camera, Context};

use super::gphoto2::{
    CameraPath, Gphoto2Error, Gphoto2Identity, Gphoto2Opener, Gphoto2Session, WidgetState,
};
use crate::rig::hal::ErrorKind;

/// libgphoto2's model for a PTP/IP camera it has no entry of its own for.
pub const GENERIC_PTPIP_MODEL: &str = "PTP/IP Camera";

/// Opens a camera through libgphoto2.
pub struct LibGphoto2Opener {
    /// libgphoto2's port; None: autodetect.
    pub port: Option<String>,
    /// libgphoto2's model; None: the one autodetected (the generic PTP/IP
    /// model on a `ptpip:` port, which libgphoto2 cannot autodetect).
    pub model: Option<String>,
}

/// The kind of failure a libgphoto2 error is. A port that fails (I/O,
/// USB, an unknown or vanished port) is `Disconnected`: the session is
/// dropped and the next call opens the camera afresh, so a resume after
/// the cable is back reconnects. libgphoto2's own timeout is `Timeout`
/// (retried, on a fresh session). A busy camera is `Timeout` too, so the
/// engine asks again, but on the same session: it is still storing the
/// last frame, not lost. Corrupted data is a `BadFrame` to retake. An
/// unknown model or bad parameters are set-up errors (`NotReady`: the
/// profile must change). Anything else is a `DeviceFault` that also drops
/// the session: libgphoto2's ptp2 driver reports a PTP/IP connection that
/// closed mid-call as a bare "Unspecified error", and a session kept after
/// it would fail every call until rigd restarts, while opening the camera
/// afresh costs a second.
fn error(what: &str, e: &::gphoto2::Error) -> Gphoto2Error {
    use ::gphoto2::error::ErrorKind as G;
    let message = format!("{what}: {e}");
    match e.kind() {
        G::Io
        | G::IoRead
        | G::IoWrite
        | G::IoUpdate
        | G::IoSerialSpeed
        | G::IoUsbClearHalt
        | G::IoUsbFind
        | G::IoUsbClaim
        | G::IoLock
        | G::OsFailure
        | G::UnknownPort => Gphoto2Error::new(ErrorKind::Disconnected, message),
        G::Timeout => Gphoto2Error::new(ErrorKind::Timeout, message),
        G::CameraBusy => Gphoto2Error::keeping_session(ErrorKind::Timeout, message),
        G::CorruptedData => Gphoto2Error::keeping_session(ErrorKind::BadFrame, message),
        G::ModelNotFound | G::BadParameters | G::PathNotAbsolute => {
            Gphoto2Error::keeping_session(ErrorKind::NotReady, message)
        }
        _ => Gphoto2Error::new(ErrorKind::DeviceFault, message),
    }
}

/// Waits for a task of the crate's libgphoto2 thread.
fn wait<T: Send + 'static>(
    what: &str,
    task: ::gphoto2::task::Task<::gphoto2::Result<T>>,
) -> Result<T, Gphoto2Error> {
    match task.try_wait() {
        Ok(r) => r.map_err(|e| error(what, &e)),
        Err(_) => Err(Gphoto2Error::new(
            ErrorKind::DeviceFault,
            format!("{what}: libgphoto2's thread has ended"),
        )),
    }
}

/// The first `Key: value` line of libgphoto2's summary with this key.
fn summary_field(summary: &str, key: &str) -> String {
    summary
        .lines()
        .find_map(|l| l.trim().strip_prefix(key)?.strip_prefix(':'))
        .map(|v| v.trim().to_string())
        .unwrap_or_default()
}

impl LibGphoto2Opener {
    /// The camera to open: the profile's port and model, whatever of them
    /// is missing autodetected; exactly one camera must match.
    fn descriptor(&self, context: &Context) -> Result<CameraDescriptor, Gphoto2Error> {
        let generic_ptpip = self
            .port
            .as_deref()
            .is_some_and(|p| p.starts_with("ptpip:"));
        match (&self.port, &self.model) {
            (Some(port), Some(model)) => {
                return Ok(CameraDescriptor {
                    model: model.clone(),
                    port: port.clone(),
                })
            }
            (Some(port), None) if generic_ptpip => {
                return Ok(CameraDescriptor {
                    model: GENERIC_PTPIP_MODEL.into(),
                    port: port.clone(),
                })
            }
            _ => {}
        }
        let found: Vec<CameraDescriptor> =
            wait("autodetecting cameras", context.list_cameras())?.collect();
        let matching: Vec<&CameraDescriptor> = found
            .iter()
            .filter(|d| self.port.as_ref().is_none_or(|p| *p == d.port))
            .filter(|d| self.model.as_ref().is_none_or(|m| *m == d.model))
            .collect();
        match matching.as_slice() {
            [one] => Ok((*one).clone()),
            _ => {
                let list = if found.is_empty() {
                    "none".to_string()
                } else {
                    found
                        .iter()
                        .map(|d| format!("`{}` on `{}`", d.model, d.port))
                        .collect::<Vec<_>>()
                        .join(", ")
                };
                let want = if matching.is_empty() {
                    "no"
                } else {
                    "more than one"
                };
                Err(Gphoto2Error::new(
                    ErrorKind::Disconnected,
                    format!(
                        "libgphoto2 autodetected {want} camera matching {}; found: {list}; name the camera's `port` and `model` in the transport",
                        self.describe()
                    ),
                ))
            }
        }
    }
}

impl Gphoto2Opener for LibGphoto2Opener {
    fn describe(&self) -> String {
        match (&self.model, &self.port) {
            (Some(m), Some(p)) => format!("libgphoto2 camera `{m}` on `{p}`"),
            (None, Some(p)) => format!("libgphoto2 camera on `{p}`"),
            (Some(m), None) => format!("libgphoto2 camera `{m}`"),
            (None, None) => "the one camera libgphoto2 autodetects".into(),
        }
    }

    fn open(&self) -> Result<Box<dyn Gphoto2Session>, Gphoto2Error> {
        let context = Context::new().map_err(|e| error("libgphoto2's context", &e))?;
        let descriptor = self.descriptor(&context)?;
        let opening = format!("opening `{}` on `{}`", descriptor.model, descriptor.port);
        let camera = wait(&opening, context.get_camera(&descriptor))?;
        // get_camera only chooses driver and port: the summary is the
        // first call that reaches the camera (gp_camera_init runs on it).
        let summary = camera.summary().map_err(|e| error(&opening, &e))?;
        let identity = Gphoto2Identity {
            driver_model: camera.abilities().model().into_owned(),
            port: descriptor.port.clone(),
            manufacturer: summary_field(&summary, "Manufacturer"),
            model: summary_field(&summary, "Model"),
            version: summary_field(&summary, "Version"),
            serial: summary_field(&summary, "Serial Number"),
            widgets: Vec::new(),
        };
        Ok(Box::new(LibGphoto2Session { camera, identity }))
    }
}

/// An open camera.
struct LibGphoto2Session {
    camera: Camera,
    identity: Gphoto2Identity,
}

impl LibGphoto2Session {
    fn get(&self, name: &str) -> Result<Widget, Gphoto2Error> {
        wait(
            &format!("reading widget `{name}`"),
            self.camera.config_key::<Widget>(name),
        )
    }
}

/// A toggle's value as text takes: 1, on, true, yes (and their opposites).
fn toggle_value(value: &str) -> Option<bool> {
    match value.trim().to_ascii_lowercase().as_str() {
        "1" | "on" | "true" | "yes" => Some(true),
        "0" | "off" | "false" | "no" => Some(false),
        _ => None,
    }
}

impl Gphoto2Session for LibGphoto2Session {
    fn identity(&self) -> Gphoto2Identity {
        self.identity.clone()
    }

    fn widget(&mut self, name: &str) -> Result<WidgetState, Gphoto2Error> {
        let w = self.get(name)?;
        let (value, choices, readonly) = match &w {
            Widget::Radio(r) => (r.choice(), Some(r.choices_iter().collect()), r.readonly()),
            Widget::Text(t) => (t.value(), None, t.readonly()),
            Widget::Range(r) => (r.value().to_string(), None, r.readonly()),
            Widget::Toggle(t) => (
                t.toggled()
                    .map_or(String::new(), |b| u8::from(b).to_string()),
                None,
                t.readonly(),
            ),
            Widget::Date(d) => (d.timestamp().to_string(), None, d.readonly()),
            Widget::Group(_) | Widget::Button(_) => {
                return Err(Gphoto2Error::keeping_session(
                    ErrorKind::NotReady,
                    format!("`{name}` is a section or a button, not a setting"),
                ))
            }
        };
        Ok(WidgetState {
            value,
            choices,
            readonly,
        })
    }

    fn set_widget(&mut self, name: &str, value: &str) -> Result<(), Gphoto2Error> {
        let w = self.get(name)?;
        let bad = |expected: &str| {
            Gphoto2Error::keeping_session(
                ErrorKind::NotReady,
                format!("`{name}` takes {expected}, not `{value}`"),
            )
        };
        let base = match &w {
            Widget::Radio(r) => {
                r.set_choice(value).map_err(|e| error(name, &e))?;
                &**r
            }
            Widget::Text(t) => {
                t.set_value(value).map_err(|e| error(name, &e))?;
                &**t
            }
            Widget::Range(r) => {
                let (range, _) = r.range_and_step();
                let v: f32 = value.trim().parse().map_err(|_| bad("a number"))?;
                if !range.contains(&v) {
                    return Err(bad(&format!(
                        "a number from {} to {}",
                        range.start(),
                        range.end()
                    )));
                }
                r.set_value(v);
                &**r
            }
            Widget::Toggle(t) => {
                t.set_toggled(toggle_value(value).ok_or_else(|| bad("1 or 0"))?);
                &**t
            }
            Widget::Date(d) => {
                d.set_timestamp(value.trim().parse().map_err(|_| bad("a UNIX time"))?);
                &**d
            }
            Widget::Group(_) | Widget::Button(_) => return Err(bad("no value")),
        };
        wait(
            &format!("setting `{name}` = {value}"),
            self.camera.set_config(base),
        )
    }

    fn capture(&mut self) -> Result<CameraPath, Gphoto2Error> {
        let path = wait("capturing", self.camera.capture_image())?;
        Ok(CameraPath {
            folder: path.folder().into_owned(),
            name: path.name().into_owned(),
        })
    }

    fn download(&mut self, file: &CameraPath) -> Result<Vec<u8>, Gphoto2Error> {
        let what = format!("downloading {file}");
        let fs = self.camera.fs();
        let data = wait(&what, fs.download(&file.folder, &file.name))?;
        let bytes = wait(&what, data.get_data(&self.camera))?;
        Ok(bytes.into_vec())
    }

    fn delete(&mut self, file: &CameraPath) -> Result<(), Gphoto2Error> {
        wait(
            &format!("deleting {file}"),
            self.camera.fs().delete_file(&file.folder, &file.name),
        )
    }
}
