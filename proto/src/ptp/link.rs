//! An in-memory USB Still Image link: the bulk-out, bulk-in and interrupt-in
//! endpoints of one camera, as a host end (for the driver) and a device end
//! (for the simulated firmware) joined by channels.
//!
//! It lives here, beside the codec, because both `rigd` (whose `UsbPipe`
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

#[cfg(test)]
mod tests {
    use super::*;

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
