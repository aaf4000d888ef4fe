//! An in-memory USB Still Image link: the bulk-out, bulk-in and interrupt-in
//! endpoints of one camera, as a host end (for the driver) and a device end
//! (for the simulated firmware) joined by channels.
//!
//! It lives here, beside the codec, because both `rigd` (whose `PtpPipe`
//! trait the host end implements) and `rigd-sim` (whose firmware serves the
//! device end) must reach it without depending on each other.
//!
//! USB semantics kept: every `write_*` by the device is one transfer; a
//! host read returns at most `max` bytes of the current transfer, and a read
//! shorter than `max` ends the transfer. A transfer whose length is an exact
//! multiple of `max` is followed by a zero-length read, like the zero-length
//! packet a real device sends, so the host can always tell where it ends.
//! Dropping either end closes the link; the other end then sees
//! [`LinkClosed`] once the transfers already queued are read.

use std::io;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::sync::mpsc;

/// The other end of the link is gone (unplugged, or the firmware stopped).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("USB link closed")]
pub struct LinkClosed;

/// The driver's end: writes bulk-out, reads bulk-in and interrupt-in.
#[derive(Debug)]
pub struct HostEnd {
    out_tx: mpsc::UnboundedSender<Vec<u8>>,
    in_rx: mpsc::UnboundedReceiver<Vec<u8>>,
    int_rx: mpsc::UnboundedReceiver<Vec<u8>>,
    /// The unread rest of the current bulk-in transfer.
    pending: Option<Vec<u8>>,
}

/// The firmware's end: reads bulk-out, writes bulk-in and interrupt-in.
#[derive(Debug)]
pub struct DeviceEnd {
    out_rx: mpsc::UnboundedReceiver<Vec<u8>>,
    in_tx: mpsc::UnboundedSender<Vec<u8>>,
    int_tx: mpsc::UnboundedSender<Vec<u8>>,
}

/// A connected pair of ends.
pub fn pair() -> (HostEnd, DeviceEnd) {
    let (out_tx, out_rx) = mpsc::unbounded_channel();
    let (in_tx, in_rx) = mpsc::unbounded_channel();
    let (int_tx, int_rx) = mpsc::unbounded_channel();
    (
        HostEnd {
            out_tx,
            in_rx,
            int_rx,
            pending: None,
        },
        DeviceEnd {
            out_rx,
            in_tx,
            int_tx,
        },
    )
}

impl HostEnd {
    /// Sends one bulk-out transfer.
    pub fn bulk_out(&mut self, bytes: Vec<u8>) -> Result<(), LinkClosed> {
        self.out_tx.send(bytes).map_err(|_| LinkClosed)
    }

    /// Reads up to `max` bytes of the current bulk-in transfer (waiting for
    /// the next one if none is in progress).
    pub async fn bulk_in(&mut self, max: usize) -> Result<Vec<u8>, LinkClosed> {
        let mut buf = match self.pending.take() {
            Some(b) => b,
            None => self.in_rx.recv().await.ok_or(LinkClosed)?,
        };
        if max == 0 {
            self.pending = Some(buf);
            return Ok(Vec::new());
        }
        if buf.len() > max {
            self.pending = Some(buf.split_off(max));
        } else if buf.len() == max {
            // The zero-length packet that ends a full-sized transfer.
            self.pending = Some(Vec::new());
        }
        Ok(buf)
    }

    /// Waits for the next interrupt transfer (an event container).
    pub async fn interrupt_in(&mut self) -> Result<Vec<u8>, LinkClosed> {
        self.int_rx.recv().await.ok_or(LinkClosed)
    }
}

/// A host end taken apart, for a bridge that forwards whole transfers in
/// both directions at once.
#[derive(Debug)]
pub struct HostParts {
    /// Sends bulk-out transfers.
    pub bulk_out: mpsc::UnboundedSender<Vec<u8>>,
    /// Receives whole bulk-in transfers.
    pub bulk_in: mpsc::UnboundedReceiver<Vec<u8>>,
    /// Receives interrupt transfers.
    pub interrupt_in: mpsc::UnboundedReceiver<Vec<u8>>,
}

impl HostEnd {
    /// The end's channels, each usable on its own. A transfer already
    /// partly read is lost, so take an end apart before reading from it.
    pub fn into_parts(self) -> HostParts {
        HostParts {
            bulk_out: self.out_tx,
            bulk_in: self.in_rx,
            interrupt_in: self.int_rx,
        }
    }
}

impl DeviceEnd {
    /// Waits for the next bulk-out transfer from the host.
    pub async fn read_out(&mut self) -> Result<Vec<u8>, LinkClosed> {
        self.out_rx.recv().await.ok_or(LinkClosed)
    }

    /// Sends one bulk-in transfer.
    pub fn write_in(&self, bytes: Vec<u8>) -> Result<(), LinkClosed> {
        self.in_tx.send(bytes).map_err(|_| LinkClosed)
    }

    /// Sends one interrupt transfer.
    pub fn write_interrupt(&self, bytes: Vec<u8>) -> Result<(), LinkClosed> {
        self.int_tx.send(bytes).map_err(|_| LinkClosed)
    }
}

/// Frame kinds of a link carried over a byte stream.
const WIRE_OUT: u8 = 1;
const WIRE_IN: u8 = 2;
const WIRE_INTERRUPT: u8 = 3;
/// Largest transfer a stream frame may carry (a 16-bit frame of a large
/// sensor is tens of megabytes).
pub const WIRE_MAX_TRANSFER: usize = 256 * 1024 * 1024;

async fn write_frame<W: AsyncWrite + Unpin>(w: &mut W, kind: u8, bytes: &[u8]) -> io::Result<()> {
    let len = u32::try_from(bytes.len())
        .map_err(|_| io::Error::new(io::ErrorKind::InvalidInput, "transfer too large"))?;
    let mut head = [0u8; 5];
    head[0] = kind;
    head[1..].copy_from_slice(&len.to_le_bytes());
    w.write_all(&head).await?;
    w.write_all(bytes).await?;
    w.flush().await
}

async fn read_frame<R: AsyncRead + Unpin>(r: &mut R) -> io::Result<(u8, Vec<u8>)> {
    let mut head = [0u8; 5];
    r.read_exact(&mut head).await?;
    let len = u32::from_le_bytes([head[1], head[2], head[3], head[4]]) as usize;
    if len > WIRE_MAX_TRANSFER || !(WIRE_OUT..=WIRE_INTERRUPT).contains(&head[0]) {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!("bad link frame: kind {}, {len} bytes", head[0]),
        ));
    }
    let mut bytes = vec![0u8; len];
    r.read_exact(&mut bytes).await?;
    Ok((head[0], bytes))
}

/// The host end of a link carried over a byte stream (a loopback socket to
/// `rigd sim serve`): each transfer travels as one frame, a kind byte
/// (1 bulk-out, 2 bulk-in, 3 interrupt), a little-endian `u32` length and
/// the bytes, so transfer boundaries survive the stream. Spawns the pump on
/// the current tokio runtime; the link closes when the stream does.
pub fn host_over<S>(stream: S) -> HostEnd
where
    S: AsyncRead + AsyncWrite + Send + 'static,
{
    let (host, dev) = pair();
    let DeviceEnd {
        mut out_rx,
        in_tx,
        int_tx,
    } = dev;
    let (mut rd, mut wr) = tokio::io::split(stream);
    tokio::spawn(async move {
        let to_device = async {
            while let Some(bytes) = out_rx.recv().await {
                if write_frame(&mut wr, WIRE_OUT, &bytes).await.is_err() {
                    break;
                }
            }
        };
        let from_device = async {
            while let Ok((kind, bytes)) = read_frame(&mut rd).await {
                let sent = match kind {
                    WIRE_IN => in_tx.send(bytes).is_ok(),
                    WIRE_INTERRUPT => int_tx.send(bytes).is_ok(),
                    _ => false,
                };
                if !sent {
                    break;
                }
            }
        };
        // Either direction ending ends the link (dropping the senders
        // closes it).
        tokio::select! {
            _ = to_device => {}
            _ = from_device => {}
        }
    });
    host
}

/// The device end of a link carried over a byte stream; see [`host_over`].
pub fn device_over<S>(stream: S) -> DeviceEnd
where
    S: AsyncRead + AsyncWrite + Send + 'static,
{
    let (host, dev) = pair();
    let HostEnd {
        out_tx,
        mut in_rx,
        mut int_rx,
        ..
    } = host;
    let (mut rd, mut wr) = tokio::io::split(stream);
    tokio::spawn(async move {
        let to_host = async {
            loop {
                let (kind, bytes) = tokio::select! {
                    Some(b) = in_rx.recv() => (WIRE_IN, b),
                    Some(b) = int_rx.recv() => (WIRE_INTERRUPT, b),
                    else => break,
                };
                if write_frame(&mut wr, kind, &bytes).await.is_err() {
                    break;
                }
            }
        };
        let from_host = async {
            while let Ok((kind, bytes)) = read_frame(&mut rd).await {
                if kind != WIRE_OUT || out_tx.send(bytes).is_err() {
                    break;
                }
            }
        };
        tokio::select! {
            _ = to_host => {}
            _ = from_host => {}
        }
    });
    dev
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_link_over_a_stream_keeps_transfer_boundaries() {
        let (a, b) = tokio::io::duplex(64);
        let mut h = host_over(a);
        let mut d = device_over(b);
        h.bulk_out(vec![1, 2, 3]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(d.read_out().await, Ok(vec![1, 2, 3]));
        d.write_in(vec![5; 300]).unwrap_or_else(|e| panic!("{e}"));
        d.write_in(vec![6]).unwrap_or_else(|e| panic!("{e}"));
        d.write_interrupt(vec![7, 7])
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(h.bulk_in(512).await, Ok(vec![5; 300]));
        assert_eq!(h.bulk_in(512).await, Ok(vec![6]));
        assert_eq!(h.interrupt_in().await, Ok(vec![7, 7]));
        drop(d);
        assert_eq!(h.bulk_in(8).await, Err(LinkClosed));
    }

    #[tokio::test]
    async fn garbage_on_the_stream_closes_the_link() {
        let (a, mut b) = tokio::io::duplex(64);
        let mut h = host_over(a);
        b.write_all(&[9, 0, 0, 0, 0])
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(h.bulk_in(8).await, Err(LinkClosed));
    }

    #[tokio::test]
    async fn reads_split_transfers_and_end_with_short_reads() {
        let (mut h, d) = pair();
        d.write_in(vec![1, 2, 3, 4, 5])
            .unwrap_or_else(|e| panic!("{e}"));
        d.write_in(vec![9]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(h.bulk_in(2).await, Ok(vec![1, 2]));
        assert_eq!(h.bulk_in(2).await, Ok(vec![3, 4]));
        assert_eq!(h.bulk_in(2).await, Ok(vec![5]));
        assert_eq!(h.bulk_in(2).await, Ok(vec![9]));
        d.write_in(vec![7, 8]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(h.bulk_in(2).await, Ok(vec![7, 8]));
        assert_eq!(h.bulk_in(2).await, Ok(vec![]));
        drop(d);
        assert_eq!(h.bulk_in(2).await, Err(LinkClosed));
        assert_eq!(h.interrupt_in().await, Err(LinkClosed));
        assert_eq!(h.bulk_out(vec![1]), Err(LinkClosed));
    }
}
