//! PTP/IP cameras (CIPA DC-005): a camera on the network reached by its
//! command and event TCP connections. [`PtpIpPipe`] presents the session as
//! a [`PtpPipe`], so the one PTP driver ([`super::ptp::PtpCamera`]) runs
//! unchanged on USB and on PTP/IP; the packet codec and the bridge are
//! `rigd_proto::ptp::ip`.

use async_trait::async_trait;
use rigd_proto::ptp::ip::{self, Identity, IpError, IpHost};
use sha2::{Digest, Sha256};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::TcpStream;

use super::usb::{PtpPipe, UsbError};

/// The connected session of one PTP/IP camera.
#[derive(Debug)]
pub struct PtpIpPipe {
    ip: IpHost,
    camera: Identity,
}

impl PtpIpPipe {
    /// Connects to the camera at `host:port`: the command connection and
    /// its handshake, then the event connection and its handshake. The
    /// caller bounds it with its deadline (opening a link has one).
    pub async fn connect(host: &str, port: u16) -> Result<PtpIpPipe, IpError> {
        let open = || async {
            let s = TcpStream::connect((host, port)).await?;
            s.set_nodelay(true)?;
            Ok::<TcpStream, IpError>(s)
        };
        let command = open().await?;
        PtpIpPipe::handshake(command, open, &initiator_identity()).await
    }

    /// Opens the session over a command connection already made, as the
    /// initiator `me`; `open_event` makes the event connection when the
    /// camera has acknowledged the command connection.
    pub async fn handshake<C, E, F, Fut>(
        command: C,
        open_event: F,
        me: &Identity,
    ) -> Result<PtpIpPipe, IpError>
    where
        C: AsyncRead + AsyncWrite + Send + Unpin + 'static,
        E: AsyncRead + AsyncWrite + Send + Unpin + 'static,
        F: FnOnce() -> Fut,
        Fut: std::future::Future<Output = Result<E, IpError>>,
    {
        let (camera, ip) = ip::initiator(command, open_event, me).await?;
        Ok(PtpIpPipe { ip, camera })
    }

    /// Who the camera said it is in its Init Command Ack.
    pub fn camera(&self) -> &Identity {
        &self.camera
    }

    fn lost(&self) -> UsbError {
        match self.ip.end_reason() {
            IpError::Closed => UsbError::Disconnected,
            other => UsbError::Io(other.to_string()),
        }
    }
}

/// rigd's identity as an initiator: the host's name, and a GUID made from
/// it, so a camera that pairs by GUID sees the same initiator every time.
pub fn initiator_identity() -> Identity {
    let host = std::fs::read_to_string("/etc/hostname")
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "localhost".into());
    let name = format!("rigd@{host}");
    let digest = Sha256::digest(name.as_bytes());
    let mut guid = [0u8; 16];
    guid.copy_from_slice(&digest[..16]);
    Identity {
        guid,
        name: name.chars().take(ip::MAX_NAME_UNITS / 2).collect(),
        version: ip::PROTOCOL_VERSION,
    }
}

#[async_trait]
impl PtpPipe for PtpIpPipe {
    async fn bulk_out(&mut self, bytes: Vec<u8>) -> Result<(), UsbError> {
        self.send_operation(bytes, None).await
    }

    async fn send_operation(
        &mut self,
        command: Vec<u8>,
        data_out: Option<Vec<u8>>,
    ) -> Result<(), UsbError> {
        self.ip
            .send_operation(command, data_out)
            .map_err(|_| self.lost())
    }

    async fn bulk_in(&mut self, max: usize) -> Result<Vec<u8>, UsbError> {
        match self.ip.host.bulk_in(max).await {
            Ok(b) => Ok(b),
            Err(_) => Err(self.lost()),
        }
    }

    async fn interrupt_in(&mut self) -> Result<Vec<u8>, UsbError> {
        match self.ip.host.interrupt_in().await {
            Ok(b) => Ok(b),
            Err(_) => Err(self.lost()),
        }
    }
}
