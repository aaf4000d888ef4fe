//! Drivers for real device protocols. Each speaks its wire protocol (codecs
//! in `rigd-proto`) over a stream it is handed, never opening ports itself,
//! so tests can connect it to the simulated firmware in `rigd-sim`.

pub mod acl;
#[cfg(feature = "genicam")]
pub mod aravis;
pub mod genicam;
pub mod gphoto2;
pub mod grbl;
#[cfg(feature = "gphoto2")]
pub mod libgphoto2;
pub mod modbus;
pub mod ptp;
pub mod ptpip;
pub mod usb;

use std::time::Duration;

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

/// The shortest wait between two polls: a zero interval never spins.
const MIN_POLL_WAIT: Duration = Duration::from_millis(1);

/// When a driver asks a device whether an operation it models (a move, a
/// lamp's warm-up) has ended.
///
/// The first poll comes after one interval, or at the modelled end if that
/// is sooner, so a refused or faulted start shows at once; the next comes
/// at the modelled end, so an operation that takes
/// its modelled time is seen to end when it ends, and a run's physical
/// time is the timing model's, not the model's rounded up to a poll grid;
/// after that, every interval. A fault in mid-move is seen at the modelled
/// end at the latest (the emergency stop never waits for a poll). Two
/// polls per move keep a simulated capture's status traffic cheap and
/// spare a real serial line (GRBL's documentation asks for no more than
/// 5 polls a second).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Polls {
    interval: Duration,
    end: Duration,
    polled: bool,
}

impl Polls {
    /// Polls for an operation modelled to take `modelled`, at least every
    /// `interval` once it is overdue.
    pub(crate) fn new(interval: Duration, modelled: Duration) -> Polls {
        Polls {
            interval,
            end: modelled,
            polled: false,
        }
    }

    /// How long to wait before the next poll, `elapsed` after the
    /// operation started.
    pub(crate) fn next_wait(&mut self, elapsed: Duration) -> Duration {
        let to_end = self.end.saturating_sub(elapsed);
        let first = !std::mem::replace(&mut self.polled, true);
        if first {
            self.interval.min(to_end).max(MIN_POLL_WAIT)
        } else if to_end > Duration::ZERO {
            to_end
        } else {
            self.interval.max(MIN_POLL_WAIT)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{Polls, MIN_POLL_WAIT};
    use std::time::Duration;

    /// The instants a wait polls at while the device says "still busy".
    fn poll_times(interval_ms: u64, modelled_ms: u64, n: usize) -> Vec<Duration> {
        let mut p = Polls::new(
            Duration::from_millis(interval_ms),
            Duration::from_millis(modelled_ms),
        );
        let mut t = Duration::ZERO;
        (0..n)
            .map(|_| {
                t += p.next_wait(t);
                t
            })
            .collect()
    }

    #[test]
    fn a_wait_polls_once_early_then_at_the_modelled_end_then_every_interval() {
        let ms = Duration::from_millis;
        // 3 s move, 100 ms polls: a start fault shows at 0.1 s, the end is
        // seen at 3 s, then every 0.1 s.
        assert_eq!(
            poll_times(100, 3000, 4),
            vec![ms(100), ms(3000), ms(3100), ms(3200)]
        );
        // A move shorter than the interval is polled at its end at once.
        assert_eq!(poll_times(200, 50, 2), vec![ms(50), ms(250)]);
        // Nothing modelled (a sweep, an unknown move): every interval.
        assert_eq!(
            poll_times(200, 0, 3),
            vec![
                MIN_POLL_WAIT,
                MIN_POLL_WAIT + ms(200),
                MIN_POLL_WAIT + ms(400)
            ]
        );
        // A zero interval never spins with zero waits.
        assert!(poll_times(0, 0, 3).iter().all(|t| *t > Duration::ZERO));
        // A huge modelled time saturates instead of overflowing.
        let mut p = Polls::new(ms(100), Duration::MAX);
        assert_eq!(p.next_wait(Duration::ZERO), ms(100));
        assert_eq!(p.next_wait(ms(100)), Duration::MAX - ms(100));
    }
}
