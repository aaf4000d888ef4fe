//! The PTP/IP responder of `rigd sim serve`: a simulated camera offered as
//! a network camera on one TCP port, so that any PTP/IP initiator (rigd's
//! own driver, libgphoto2, the `gphoto2` tool) can drive it.
//!
//! A command connection opens with Init Command Request and is answered
//! with a connection number; the event connection quotes that number in
//! its Init Event Request. One initiator at a time holds the camera (a
//! second is refused as busy, as cameras do); each session starts the
//! camera's firmware afresh, as powering a camera on does.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use rigd_core::Clock;
use rigd_proto::ptp::ip::{
    read_packet, serve_device, write_packet, FailReason, Identity, Packet, PROTOCOL_VERSION,
};
use sha2::{Digest, Sha256};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::TcpListener;
use tokio::sync::oneshot;

use super::PtpOpener;
use crate::rig::drivers::usb::{memory_pair, MemoryDevice};

/// How long a connection may take to send its init packet, and a command
/// connection to be joined by its event connection.
const HANDSHAKE: Duration = Duration::from_secs(10);

/// Starts a camera's firmware on the device end of a fresh link, once per
/// session.
pub type StartFirmware = Arc<dyn Fn(MemoryDevice) + Send + Sync>;

/// The command connections waiting for their event connection, and whether
/// an initiator holds the camera.
struct Sessions<S> {
    next_connection: u32,
    waiting: BTreeMap<u32, oneshot::Sender<S>>,
    held: bool,
}

/// Frees the camera when a session ends, however it ends.
struct Hold<S>(Arc<Mutex<Sessions<S>>>, u32);

impl<S> Drop for Hold<S> {
    fn drop(&mut self) {
        let mut s = rigd_core::sync::lock(&self.0);
        s.held = false;
        s.waiting.remove(&self.1);
    }
}

/// The camera's identity: its model as the friendly name, and a GUID made
/// from the model and the device name.
fn camera_identity(model: &str, device: &str) -> Identity {
    let digest = Sha256::digest(format!("{model}/{device}").as_bytes());
    let mut guid = [0u8; 16];
    guid.copy_from_slice(&digest[..16]);
    Identity {
        guid,
        name: model.to_string(),
        version: PROTOCOL_VERSION,
    }
}

/// One simulated camera's PTP/IP responder, over any byte streams: TCP
/// connections in `rigd sim serve`, in-memory ones in the transcripts'
/// replay.
pub struct PtpIpResponder<S> {
    start: StartFirmware,
    sessions: Arc<Mutex<Sessions<S>>>,
    identity: Arc<Identity>,
    clock: Clock,
}

impl<S> PtpIpResponder<S>
where
    S: AsyncRead + AsyncWrite + Send + Unpin + 'static,
{
    /// The responder of the camera `device` whose DeviceInfo names `model`;
    /// `start` runs its firmware for each session.
    pub fn new(model: &str, device: &str, start: StartFirmware, clock: Clock) -> Self {
        PtpIpResponder {
            start,
            sessions: Arc::new(Mutex::new(Sessions {
                next_connection: 0,
                waiting: BTreeMap::new(),
                held: false,
            })),
            identity: Arc::new(camera_identity(model, device)),
            clock,
        }
    }

    /// Serves one new connection (a command or an event connection, as its
    /// first packet says) on a task of its own.
    pub fn accept(&self, stream: S) {
        tokio::spawn(connection(
            stream,
            self.start.clone(),
            self.sessions.clone(),
            self.identity.clone(),
            self.clock.clone(),
        ));
    }
}

/// Accepts initiators on `listener` until the runtime shuts down.
pub(crate) async fn serve_camera(
    listener: TcpListener,
    camera: Arc<PtpOpener>,
    device: String,
    clock: Clock,
) {
    let model = camera.model().to_string();
    let start: StartFirmware = Arc::new(move |dev| camera.start(dev));
    let responder = PtpIpResponder::new(&model, &device, start, clock);
    while let Ok((stream, peer)) = listener.accept().await {
        let _ = stream.set_nodelay(true);
        tracing::debug!(camera = %device, %peer, "PTP/IP connection");
        responder.accept(stream);
    }
}

/// Takes the camera for a new command connection: its number, and where
/// its event connection will arrive. None while another initiator holds it.
fn hold_camera<S>(sessions: &Mutex<Sessions<S>>) -> Option<(u32, oneshot::Receiver<S>)> {
    let mut s = rigd_core::sync::lock(sessions);
    if s.held {
        return None;
    }
    s.held = true;
    s.next_connection = s.next_connection.wrapping_add(1).max(1);
    let connection = s.next_connection;
    let (tx, rx) = oneshot::channel();
    s.waiting.insert(connection, tx);
    Some((connection, rx))
}

async fn connection<S>(
    mut stream: S,
    start: StartFirmware,
    sessions: Arc<Mutex<Sessions<S>>>,
    identity: Arc<Identity>,
    clock: Clock,
) where
    S: AsyncRead + AsyncWrite + Send + Unpin + 'static,
{
    let first = match clock.deadline(HANDSHAKE, read_packet(&mut stream)).await {
        Ok(Ok(p)) => p,
        Ok(Err(e)) => {
            tracing::info!("PTP/IP connection refused: {e}");
            return;
        }
        Err(_) => {
            tracing::info!("PTP/IP connection sent no init packet within {HANDSHAKE:?}");
            return;
        }
    };
    match first {
        Packet::InitCommandRequest(initiator) => {
            let Some((connection, joined)) = hold_camera(&sessions) else {
                let _ = write_packet(&mut stream, &Packet::InitFail(FailReason::Busy)).await;
                return;
            };
            let _hold = Hold(sessions.clone(), connection);
            let ack = Packet::InitCommandAck {
                connection,
                identity: (*identity).clone(),
            };
            if write_packet(&mut stream, &ack).await.is_err() {
                return;
            }
            let mut event = match clock.deadline(HANDSHAKE, joined).await {
                Ok(Ok(e)) => e,
                _ => {
                    tracing::info!(
                        initiator = %initiator.name,
                        "no PTP/IP event connection within {HANDSHAKE:?}"
                    );
                    return;
                }
            };
            if write_packet(&mut event, &Packet::InitEventAck)
                .await
                .is_err()
            {
                return;
            }
            tracing::info!(initiator = %initiator.name, "PTP/IP session open");
            let (host, dev) = memory_pair();
            start(dev);
            let why = serve_device(stream, event, host).await;
            tracing::info!(initiator = %initiator.name, "PTP/IP session ended: {why}");
        }
        Packet::InitEventRequest { connection } => {
            let waiting = rigd_core::sync::lock(&sessions).waiting.remove(&connection);
            match waiting {
                Some(tx) => {
                    let _ = tx.send(stream);
                }
                None => {
                    let _ =
                        write_packet(&mut stream, &Packet::InitFail(FailReason::Rejected)).await;
                }
            }
        }
        other => {
            tracing::info!(
                "PTP/IP connection began with {}, not an init request",
                other.packet_type()
            );
        }
    }
}
