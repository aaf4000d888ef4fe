//! GenICam cameras (GigE Vision, USB3 Vision): machine-vision cameras set by
//! SFNC feature names and triggered in software, as the fixed camera arcs
//! of today's rigs use them (the MSRA rig of Wang et al. triggers its
//! cameras together).
//!
//! The driver speaks to a [`GenicamSession`]: the few blocking calls it
//! needs of an open camera. `rig::drivers::aravis` implements it with
//! Aravis (cargo feature `genicam`, chosen in `rig::hardware`); the tests
//! here implement it with a scripted camera. Every blocking call runs on
//! tokio's blocking pool, one at a time per camera, under the engine's
//! deadlines.
//!
//! What the driver adds to the session:
//! - a stream buffer with lost packets is a [`ErrorKind::BadFrame`], which
//!   the engine retakes; a partial frame is never delivered;
//! - a camera that stops answering (a control call fails, or no buffer
//!   comes) is dropped, and the next call opens it afresh with every
//!   feature set again, so a resume after the camera came back reconnects;
//! - the frame carries the camera's frame id, timestamp and pixel format.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use async_trait::async_trait;

use crate::model::profile::{Device, GenicamSettings, Transport};
use crate::rig::hal::{Camera, DeviceError, DeviceFrameInfo, ErrorKind, Frame};
use rigd_core::{Clock, PixelFormat};

/// What a GenICam camera is asked for at every connect.
#[derive(Debug, Clone, PartialEq)]
pub struct GenicamConfig {
    /// The camera's name in the profile.
    pub name: String,
    /// What the transport layer opens: an IP address or a device id.
    pub id: String,
    /// `PixelFormat`.
    pub pixel_format: PixelFormat,
    /// `Width` and `Height`, pixels.
    pub size: [u32; 2],
    /// `Gain` in dB; None leaves the camera's own.
    pub gain_db: Option<f64>,
    /// `TriggerSource` of the frame-start trigger (`Software` or a line).
    pub trigger_source: String,
    /// `ExposureTime` until the run sets its own, seconds.
    pub exposure_s: f64,
    /// Readout after the exposure: the sensor is busy, nothing may move.
    pub readout_s: f64,
    /// How long a frame takes to reach the host after the readout.
    pub transfer_s: f64,
}

impl GenicamConfig {
    /// The configuration of a camera device on a GenICam transport; None
    /// for other devices. Validation guarantees intrinsics, timing and a
    /// pixel format of the sensor's depth.
    pub fn of(name: &str, dev: &Device) -> Option<GenicamConfig> {
        let camera = dev.as_camera()?;
        let Transport::Genicam { id } = &camera.transport else {
            return None;
        };
        let (intr, timing) = (camera.intrinsics, camera.timing);
        let settings = camera.genicam.as_ref();
        Some(GenicamConfig {
            name: name.to_string(),
            id: id.clone(),
            pixel_format: GenicamSettings::pixel_format_for(settings, intr.bit_depth).ok()?,
            size: intr.resolution,
            gain_db: settings.and_then(|g| g.gain_db),
            trigger_source: GenicamSettings::trigger_source_of(settings),
            exposure_s: timing.exposure_s,
            readout_s: timing.readout_s,
            transfer_s: timing.transfer_s,
        })
    }

    /// Whether rigd fires the trigger (else an external line does).
    pub fn software_trigger(&self) -> bool {
        self.trigger_source == "Software"
    }

    /// The longest a frame may take from the trigger to the host before
    /// the camera counts as silent: its exposure, readout and transfer,
    /// twice, plus two seconds for the network and the host.
    pub fn buffer_timeout(&self, exposure_s: f64) -> Duration {
        let s = 2.0 * (exposure_s + self.readout_s + self.transfer_s) + 2.0;
        Duration::try_from_secs_f64(s).unwrap_or(Duration::from_secs(3600))
    }
}

/// What a GenICam camera says of itself (its Device Control features).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct GenicamIdentity {
    /// `DeviceVendorName`.
    pub vendor: String,
    /// `DeviceModelName`.
    pub model: String,
    /// `DeviceSerialNumber` (or `DeviceID` on older cameras).
    pub serial: String,
    /// `DeviceVersion`.
    pub version: String,
}

/// One stream buffer, as the transport layer delivered it.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamBuffer {
    /// Ok when every packet arrived; else what went wrong (lost packets,
    /// a size mismatch), in the transport layer's words.
    pub complete: Result<(), String>,
    /// The camera's frame (block) id.
    pub frame_id: u64,
    /// The camera's timestamp, nanoseconds.
    pub timestamp_ns: u64,
    /// Image width and height as the buffer states them.
    pub size: [u32; 2],
    /// The image bytes (empty for an incomplete buffer).
    pub data: Vec<u8>,
}

/// A failed session call: what kind of failure, in the camera's words.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionError {
    /// Decides retry, retake or pause; `Disconnected` and `Timeout` also
    /// drop the session.
    pub kind: ErrorKind,
    /// What the transport layer or the camera said.
    pub message: String,
}

impl SessionError {
    /// An error of this kind.
    pub fn new(kind: ErrorKind, message: impl Into<String>) -> SessionError {
        SessionError {
            kind,
            message: message.into(),
        }
    }
}

/// An open, configured GenICam camera, acquiring on its trigger: the
/// blocking calls the driver makes.
pub trait GenicamSession: Send {
    /// What the camera said of itself at connect.
    fn identity(&self) -> GenicamIdentity;
    /// Sets `ExposureTime`, microseconds.
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<(), SessionError>;
    /// Drops frames left over from earlier triggers, then fires the
    /// software trigger (`TriggerSoftware`).
    fn trigger(&mut self) -> Result<(), SessionError>;
    /// Waits up to `timeout` for the next buffer; None when none came.
    fn next_buffer(&mut self, timeout: Duration) -> Result<Option<StreamBuffer>, SessionError>;
}

/// Opens a camera and sets its features; called again after it was lost.
pub trait GenicamOpener: Send + Sync {
    /// Where the camera is, for messages.
    fn describe(&self) -> String;
    /// Opens the camera, sets every feature of `cfg` (refusals are
    /// errors naming the feature and what the camera offers) and starts
    /// the acquisition, waiting for triggers.
    fn open(&self, cfg: &GenicamConfig) -> Result<Box<dyn GenicamSession>, SessionError>;
}

/// The session and what must be set again after a reconnect.
struct State {
    session: Option<Box<dyn GenicamSession>>,
    /// The exposure the run set, microseconds.
    exposure_us: Option<f64>,
}

/// A GenICam camera behind the HAL's [`Camera`].
pub struct GenicamCamera {
    cfg: Arc<GenicamConfig>,
    opener: Arc<dyn GenicamOpener>,
    state: Arc<Mutex<State>>,
    clock: Clock,
    exposure_s: f64,
}

impl GenicamCamera {
    /// Opens the camera and sets its features; returns the driver and
    /// what the camera said of itself.
    pub async fn connect(
        cfg: GenicamConfig,
        opener: Arc<dyn GenicamOpener>,
        clock: Clock,
    ) -> Result<(GenicamCamera, GenicamIdentity), DeviceError> {
        let exposure_s = cfg.exposure_s;
        let cam = GenicamCamera {
            cfg: Arc::new(cfg),
            opener,
            state: Arc::new(Mutex::new(State {
                session: None,
                exposure_us: None,
            })),
            clock,
            exposure_s,
        };
        let identity = cam.call(|s, _| Ok(s.identity())).await?;
        Ok((cam, identity))
    }

    /// Where the camera is, for messages.
    pub fn describe(&self) -> String {
        self.opener.describe()
    }

    /// Runs `f` on the session on the blocking pool, opening the camera
    /// first if it is not open; a lost camera is dropped for the next call
    /// to open again. `f` also gets the exposure a reconnect sets again.
    async fn call<T: Send + 'static>(
        &self,
        f: impl FnOnce(&mut dyn GenicamSession, &mut Option<f64>) -> Result<T, SessionError>
            + Send
            + 'static,
    ) -> Result<T, DeviceError> {
        let state = self.state.clone();
        let opener = self.opener.clone();
        let cfg = self.cfg.clone();
        let name = self.cfg.name.clone();
        let joined = tokio::task::spawn_blocking(move || {
            // A poisoned lock only means an earlier call panicked; the
            // state is still a session or none.
            let mut guard = rigd_core::sync::lock(&state);
            let st = &mut *guard;
            if st.session.is_none() {
                let mut session = opener.open(&cfg)?;
                if let Some(us) = st.exposure_us {
                    session.set_exposure_us(us)?;
                }
                st.session = Some(session);
                tracing::info!(device = %cfg.name, camera = %opener.describe(), "GenICam camera opened");
            }
            let Some(session) = st.session.as_mut() else {
                return Err(SessionError::new(ErrorKind::NotReady, "no session"));
            };
            let r = f(session.as_mut(), &mut st.exposure_us);
            if let Err(e) = &r {
                if matches!(e.kind, ErrorKind::Disconnected | ErrorKind::Timeout) {
                    st.session = None;
                }
            }
            r
        })
        .await;
        match joined {
            Ok(r) => r.map_err(|e| DeviceError::new(&name, e.kind, e.message)),
            Err(e) => Err(DeviceError::new(
                &name,
                ErrorKind::DeviceFault,
                format!("the camera's worker failed: {e}"),
            )),
        }
    }
}

impl Drop for GenicamCamera {
    fn drop(&mut self) {
        // Closing a session stops the acquisition: a control call that can
        // take the transport's timeouts on a vanished camera, so it runs on
        // the blocking pool, not on the runtime's worker. A call still in
        // flight holds the state, and the session closes where that call
        // lets go of it.
        let session = match self.state.try_lock() {
            Ok(mut st) => st.session.take(),
            Err(_) => None,
        };
        if let (Some(session), Ok(rt)) = (session, tokio::runtime::Handle::try_current()) {
            rt.spawn_blocking(move || drop(session));
        }
    }
}

#[async_trait]
impl Camera for GenicamCamera {
    async fn set_exposure(&mut self, exposure_s: f64) -> Result<(), DeviceError> {
        if !(exposure_s.is_finite() && exposure_s > 0.0) {
            return Err(DeviceError::new(
                &self.cfg.name,
                ErrorKind::OutOfLimits,
                format!("exposure {exposure_s} s is not a positive time"),
            ));
        }
        let us = exposure_s * 1e6;
        self.call(move |s, remembered| {
            s.set_exposure_us(us)?;
            *remembered = Some(us);
            Ok(())
        })
        .await?;
        self.exposure_s = exposure_s;
        Ok(())
    }

    async fn expose(&mut self) -> Result<(), DeviceError> {
        if self.cfg.software_trigger() {
            self.call(|s, _| s.trigger()).await?;
        }
        // The sensor is busy for the exposure and the readout; the frame's
        // transfer overlaps the next moves.
        self.clock
            .sleep_s(self.exposure_s + self.cfg.readout_s)
            .await;
        Ok(())
    }

    async fn transfer(&mut self) -> Result<Frame, DeviceError> {
        let timeout = self.cfg.buffer_timeout(self.exposure_s);
        let cfg = self.cfg.clone();
        self.call(move |s, _| {
            let Some(buffer) = s.next_buffer(timeout)? else {
                return Err(SessionError::new(
                    ErrorKind::Timeout,
                    format!("no frame within {timeout:?} of the trigger"),
                ));
            };
            frame_of(&cfg, buffer)
        })
        .await
    }
}

/// The frame a buffer holds, or why it cannot be one.
fn frame_of(cfg: &GenicamConfig, b: StreamBuffer) -> Result<Frame, SessionError> {
    if let Err(why) = b.complete {
        return Err(SessionError::new(
            ErrorKind::BadFrame,
            format!("frame {} incomplete: {why}", b.frame_id),
        ));
    }
    if b.size != cfg.size {
        return Err(SessionError::new(
            ErrorKind::BadFrame,
            format!(
                "frame {} is {}x{}, the camera was set to {}x{}",
                b.frame_id, b.size[0], b.size[1], cfg.size[0], cfg.size[1]
            ),
        ));
    }
    let pixels = cfg
        .pixel_format
        .decode(b.size[0], b.size[1], &b.data)
        .map_err(|e| SessionError::new(ErrorKind::BadFrame, e.to_string()))?;
    Ok(Frame {
        width: b.size[0],
        height: b.size[1],
        bit_depth: cfg.pixel_format.bit_depth(),
        pixels,
        device: Some(DeviceFrameInfo {
            frame_id: b.frame_id,
            timestamp_ns: b.timestamp_ns,
            pixel_format: cfg.pixel_format.to_string(),
        }),
        original: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::VecDeque;
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// What the scripted camera does on each call.
    #[derive(Default)]
    struct Script {
        /// Buffers the stream delivers, in order; None: nothing comes.
        buffers: VecDeque<Option<StreamBuffer>>,
        /// Trigger results, in order; Ok when the list runs out.
        triggers: VecDeque<Result<(), SessionError>>,
        /// Exposures set, microseconds, across sessions.
        exposures: Vec<f64>,
    }

    struct Scripted(Arc<Mutex<Script>>);

    impl GenicamSession for Scripted {
        fn identity(&self) -> GenicamIdentity {
            GenicamIdentity {
                vendor: "Test".into(),
                model: "Scripted".into(),
                serial: "S1".into(),
                version: "1".into(),
            }
        }
        fn set_exposure_us(&mut self, us: f64) -> Result<(), SessionError> {
            self.0.lock().unwrap().exposures.push(us);
            Ok(())
        }
        fn trigger(&mut self) -> Result<(), SessionError> {
            self.0
                .lock()
                .unwrap()
                .triggers
                .pop_front()
                .unwrap_or(Ok(()))
        }
        fn next_buffer(&mut self, _t: Duration) -> Result<Option<StreamBuffer>, SessionError> {
            Ok(self.0.lock().unwrap().buffers.pop_front().flatten())
        }
    }

    struct ScriptedOpener {
        script: Arc<Mutex<Script>>,
        opens: AtomicUsize,
        refuse: Option<SessionError>,
    }

    impl GenicamOpener for ScriptedOpener {
        fn describe(&self) -> String {
            "scripted camera".into()
        }
        fn open(&self, _cfg: &GenicamConfig) -> Result<Box<dyn GenicamSession>, SessionError> {
            if let Some(e) = &self.refuse {
                return Err(e.clone());
            }
            self.opens.fetch_add(1, Ordering::SeqCst);
            Ok(Box::new(Scripted(self.script.clone())))
        }
    }

    fn cfg(format: PixelFormat) -> GenicamConfig {
        GenicamConfig {
            name: "cam".into(),
            id: "test".into(),
            pixel_format: format,
            size: [2, 2],
            gain_db: None,
            trigger_source: "Software".into(),
            exposure_s: 0.01,
            readout_s: 0.0,
            transfer_s: 0.0,
        }
    }

    fn buffer(id: u64, data: Vec<u8>) -> Option<StreamBuffer> {
        Some(StreamBuffer {
            complete: Ok(()),
            frame_id: id,
            timestamp_ns: 1000 * id,
            size: [2, 2],
            data,
        })
    }

    async fn camera(
        format: PixelFormat,
        script: Script,
    ) -> (GenicamCamera, Arc<ScriptedOpener>, Arc<Mutex<Script>>) {
        let script = Arc::new(Mutex::new(script));
        let opener = Arc::new(ScriptedOpener {
            script: script.clone(),
            opens: AtomicUsize::new(0),
            refuse: None,
        });
        let (cam, id) = GenicamCamera::connect(cfg(format), opener.clone(), Clock::real())
            .await
            .expect("connect");
        assert_eq!((id.vendor.as_str(), id.serial.as_str()), ("Test", "S1"));
        (cam, opener, script)
    }

    #[tokio::test]
    async fn a_complete_buffer_is_a_frame_with_the_cameras_labels() {
        let mut script = Script::default();
        script
            .buffers
            .push_back(buffer(7, vec![1, 0, 2, 0, 0xff, 0x0f, 0, 0]));
        let (mut cam, _, _) = camera(PixelFormat::Mono(12), script).await;
        cam.expose().await.expect("expose");
        let f = cam.transfer().await.expect("frame");
        assert_eq!(f.pixels, vec![1, 2, 4095, 0]);
        assert_eq!(f.bit_depth, 12);
        let d = f.device.expect("device info");
        assert_eq!((d.frame_id, d.timestamp_ns), (7, 7000));
        assert_eq!(d.pixel_format, "Mono12");
    }

    #[tokio::test]
    async fn lost_packets_are_a_bad_frame_to_retake_and_keep_the_session() {
        let mut script = Script::default();
        script.buffers.push_back(Some(StreamBuffer {
            complete: Err("MissingPackets".into()),
            frame_id: 3,
            timestamp_ns: 0,
            size: [2, 2],
            data: vec![],
        }));
        script.buffers.push_back(buffer(4, vec![0; 4]));
        // A buffer of the wrong size is no frame either.
        script.buffers.push_back(buffer(5, vec![0; 3]));
        let (mut cam, opener, _) = camera(PixelFormat::Mono(8), script).await;
        let e = cam.transfer().await.expect_err("incomplete");
        assert_eq!(e.kind, ErrorKind::BadFrame);
        assert!(
            e.message.contains("frame 3 incomplete: MissingPackets"),
            "{e}"
        );
        assert!(cam.transfer().await.is_ok());
        let e = cam.transfer().await.expect_err("short");
        assert_eq!(e.kind, ErrorKind::BadFrame);
        assert_eq!(opener.opens.load(Ordering::SeqCst), 1, "no reconnect");
    }

    #[tokio::test]
    async fn a_silent_or_vanished_camera_is_opened_again_with_its_exposure() {
        let mut script = Script::default();
        script.buffers.push_back(None);
        script
            .triggers
            .push_back(Err(SessionError::new(ErrorKind::Disconnected, "gone")));
        script.buffers.push_back(buffer(1, vec![0; 4]));
        let (mut cam, opener, script) = camera(PixelFormat::Mono(8), script).await;
        cam.set_exposure(0.02).await.expect("exposure");
        let e = cam.transfer().await.expect_err("no buffer");
        assert_eq!(e.kind, ErrorKind::Timeout);
        // The next call opened it again, and the trigger then failed.
        let e = cam.expose().await.expect_err("vanished");
        assert_eq!(e.kind, ErrorKind::Disconnected);
        assert_eq!(opener.opens.load(Ordering::SeqCst), 2);
        cam.expose().await.expect("back");
        assert!(cam.transfer().await.is_ok());
        assert_eq!(opener.opens.load(Ordering::SeqCst), 3);
        // Every reconnect set the run's exposure again.
        assert_eq!(script.lock().unwrap().exposures, vec![20_000.0; 3]);
    }

    #[tokio::test]
    async fn a_refused_feature_fails_the_connect_with_the_cameras_words() {
        let opener = Arc::new(ScriptedOpener {
            script: Arc::default(),
            opens: AtomicUsize::new(0),
            refuse: Some(SessionError::new(
                ErrorKind::NotReady,
                "refuses PixelFormat Mono12",
            )),
        });
        let e = GenicamCamera::connect(cfg(PixelFormat::Mono(12)), opener, Clock::real())
            .await
            .err()
            .expect("refused");
        assert_eq!((e.device.as_str(), e.kind), ("cam", ErrorKind::NotReady));
        assert!(e.message.contains("PixelFormat Mono12"), "{e}");
    }

    #[tokio::test]
    async fn a_build_without_aravis_says_how_to_get_one() {
        let e = GenicamCamera::connect(
            cfg(PixelFormat::Mono(8)),
            Arc::new(crate::rig::hardware::NoGenicam { id: "x".into() }),
            Clock::real(),
        )
        .await
        .err()
        .expect("no aravis");
        assert!(e.message.contains("--features genicam"), "{e}");
    }

    /// A camera whose trigger returns only once `expected` triggers are
    /// in flight at the same moment (or fails after 10 s).
    struct Rendezvous {
        arrived: Mutex<usize>,
        all_in: std::sync::Condvar,
        expected: usize,
    }

    struct TogetherSession(Arc<Rendezvous>);

    impl GenicamSession for TogetherSession {
        fn identity(&self) -> GenicamIdentity {
            GenicamIdentity::default()
        }
        fn set_exposure_us(&mut self, _us: f64) -> Result<(), SessionError> {
            Ok(())
        }
        fn trigger(&mut self) -> Result<(), SessionError> {
            let r = &self.0;
            let mut n = r.arrived.lock().unwrap();
            *n += 1;
            r.all_in.notify_all();
            let (n, wait) = r
                .all_in
                .wait_timeout_while(n, Duration::from_secs(10), |n| *n < r.expected)
                .unwrap();
            if wait.timed_out() {
                return Err(SessionError::new(
                    ErrorKind::Timeout,
                    format!("only {} of {} triggers together", *n, r.expected),
                ));
            }
            Ok(())
        }
        fn next_buffer(&mut self, _t: Duration) -> Result<Option<StreamBuffer>, SessionError> {
            Ok(None)
        }
    }

    struct TogetherOpener(Arc<Rendezvous>);

    impl GenicamOpener for TogetherOpener {
        fn describe(&self) -> String {
            "camera on the arc".into()
        }
        fn open(&self, _cfg: &GenicamConfig) -> Result<Box<dyn GenicamSession>, SessionError> {
            Ok(Box::new(TogetherSession(self.0.clone())))
        }
    }

    /// The cameras of one trigger, exposed together as the engine does
    /// (`join_all`), have their software triggers in flight at once: no
    /// camera waits for another's trigger (the MSRA arc of Wang et al.
    /// fires its cameras together).
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_cameras_of_one_trigger_fire_together() {
        let arc = 4;
        let meet = Arc::new(Rendezvous {
            arrived: Mutex::new(0),
            all_in: std::sync::Condvar::new(),
            expected: arc,
        });
        let mut cams = Vec::new();
        for _ in 0..arc {
            let opener = Arc::new(TogetherOpener(meet.clone()));
            let (cam, _) = GenicamCamera::connect(cfg(PixelFormat::Mono(8)), opener, Clock::real())
                .await
                .expect("connect");
            cams.push(cam);
        }
        let fired = futures::future::join_all(cams.iter_mut().map(|c| c.expose())).await;
        for r in fired {
            r.expect("every trigger met the others");
        }
    }

    #[test]
    fn the_buffer_timeout_grows_with_the_exposure_and_survives_nonsense() {
        let c = cfg(PixelFormat::Mono(8));
        assert_eq!(c.buffer_timeout(0.5), Duration::from_secs(3));
        assert_eq!(c.buffer_timeout(f64::INFINITY), Duration::from_secs(3600));
    }
}
