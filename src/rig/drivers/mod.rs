//! Drivers for real device protocols. Each speaks its wire protocol (codecs
//! in `rigd-proto`) over a stream it is handed, never opening ports itself,
//! so tests can connect it to the simulated firmware in `rigd-sim`.

pub mod acl;
pub mod grbl;
pub mod modbus;
pub mod ptp;
pub mod usb;

use tokio::io::{AsyncWrite, AsyncWriteExt};
use tokio::sync::Mutex;

use crate::rig::hal::{DeviceError, ErrorKind};

/// Writes and flushes under the link's writer lock, which line drivers
/// share with their out-of-band emergency stop.
pub(crate) async fn write_locked<W: AsyncWrite + Unpin>(
    writer: &Mutex<W>,
    bytes: &[u8],
) -> std::io::Result<()> {
    let mut w = writer.lock().await;
    w.write_all(bytes).await?;
    w.flush().await
}

/// An emergency stop that could not be written.
pub(crate) fn stop_failed(device: &str, e: std::io::Error) -> DeviceError {
    DeviceError::new(
        device,
        ErrorKind::Disconnected,
        format!("emergency stop not sent: {e}"),
    )
}
