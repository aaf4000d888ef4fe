//! Drivers for real device protocols. Each speaks its wire protocol (codecs
//! in `rigd-proto`) over a stream it is handed, never opening ports itself,
//! so tests can connect it to the simulated firmware in `rigd-sim`.

pub mod acl;
#[cfg(feature = "genicam")]
pub mod aravis;
pub mod genicam;
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

/// How many status polls a motion wait skips after its first one.
///
/// The drivers poll on a grid, every `interval` from the motion command,
/// and a move is done at the first grid point the controller says so. The
/// first poll always happens (a refused or faulted start shows at once);
/// the polls after it up to the last grid point before 90 % of the
/// `modelled` move time are skipped, since the axis cannot have stopped by
/// then unless it faulted. The move is seen to end at the same grid point
/// as with every poll made, whenever it takes at least 90 % of its modelled
/// time; a fault in mid-move is seen at that grid point at the latest (the
/// emergency stop never waits for a poll). This is what makes a simulated
/// capture's status traffic cheap, and it spares a real serial line
/// (GRBL's documentation asks for no more than 5 polls a second).
pub(crate) fn quiet_polls(modelled: std::time::Duration, interval: std::time::Duration) -> u32 {
    if interval.is_zero() {
        return 0;
    }
    let sure_moving = 0.9 * modelled.as_secs_f64() / interval.as_secs_f64();
    if !sure_moving.is_finite() {
        return 0;
    }
    // The next poll after skipping k is grid point k + 2; it should be the
    // last one at or before 90 % of the modelled time.
    let last_quiet_point = sure_moving.floor().min(f64::from(u32::MAX));
    (last_quiet_point as u32).saturating_sub(2)
}

#[cfg(test)]
mod tests {
    use super::quiet_polls;
    use std::time::Duration;

    #[test]
    fn quiet_polls_keep_the_grid_and_stop_short_of_the_modelled_end() {
        let p = Duration::from_millis(100);
        // Short moves, no modelled time, a zero interval: every poll made.
        assert_eq!(quiet_polls(Duration::ZERO, p), 0);
        assert_eq!(quiet_polls(Duration::from_millis(250), p), 0);
        assert_eq!(quiet_polls(Duration::from_secs(5), Duration::ZERO), 0);
        // 3 s: 90 % is 2.7 s, the last grid point before it is 27, so the
        // polls at 2 … 26 are skipped and the next is at 2.7 s.
        assert_eq!(quiet_polls(Duration::from_secs(3), p), 25);
        // A huge modelled time saturates instead of overflowing.
        assert_eq!(
            quiet_polls(Duration::from_secs(u64::MAX / 4), p),
            u32::MAX - 2
        );
    }
}
