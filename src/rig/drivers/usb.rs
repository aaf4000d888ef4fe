//! USB pipes: the bulk-out, bulk-in and interrupt-in endpoints a USB Still
//! Image (PTP) camera talks over, behind one small trait so the PTP driver
//! runs unchanged on a real camera ([`NusbPipe`]) and on the simulated
//! firmware ([`MemoryPipe`], the host end of `rigd_proto::ptp::link`).

use async_trait::async_trait;

pub use rigd_proto::ptp::link::{
    pair as memory_pair, DeviceEnd as MemoryDevice, HostEnd as MemoryPipe,
};

/// USB interface class of Still Image devices (PTP cameras).
pub const STILL_IMAGE_CLASS: u8 = 0x06;

/// Why a USB pipe failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum UsbError {
    /// The device is gone (unplugged, powered off, or the simulated link
    /// closed).
    #[error("device disconnected")]
    Disconnected,
    /// Enumeration or a transfer failed for another reason.
    #[error("USB: {0}")]
    Io(String),
    /// No device with this vendor/product id is attached.
    #[error("no USB device {vendor_id:04x}:{product_id:04x}")]
    NotFound {
        /// The vendor id looked for.
        vendor_id: u16,
        /// The product id looked for.
        product_id: u16,
    },
    /// The device has no Still Image interface with the endpoints PTP needs.
    #[error("no Still Image interface with bulk-in, bulk-out and interrupt-in endpoints")]
    NoStillImageInterface,
    /// The camera is held by another session for now (a PTP/IP camera's
    /// Init Fail "busy"): opening again shortly may succeed.
    #[error("{0}")]
    Busy(String),
}

/// The channels a PTP camera talks over, in the shape of its USB
/// endpoints: bulk-out, bulk-in and interrupt-in. One transfer per call: a
/// `bulk_in` shorter than `max` ends the device's transfer. A PTP/IP camera
/// ([`super::ptpip::PtpIpPipe`]) presents its packets in this shape too.
#[async_trait]
pub trait PtpPipe: Send {
    /// Sends one bulk-out transfer.
    async fn bulk_out(&mut self, bytes: Vec<u8>) -> Result<(), UsbError>;
    /// Sends an operation: its Command container and, for an operation
    /// that sends data, its Data container. On USB each is its own
    /// bulk-out transfer; PTP/IP must know both at once, because its
    /// Operation Request says whether data follows.
    async fn send_operation(
        &mut self,
        command: Vec<u8>,
        data_out: Option<Vec<u8>>,
    ) -> Result<(), UsbError> {
        self.bulk_out(command).await?;
        match data_out {
            Some(d) => self.bulk_out(d).await,
            None => Ok(()),
        }
    }
    /// Reads up to `max` bytes of bulk-in data.
    async fn bulk_in(&mut self, max: usize) -> Result<Vec<u8>, UsbError>;
    /// Waits for the next interrupt-in transfer (a PTP event).
    async fn interrupt_in(&mut self) -> Result<Vec<u8>, UsbError>;
}

#[async_trait]
impl<P: PtpPipe + ?Sized> PtpPipe for Box<P> {
    async fn bulk_out(&mut self, bytes: Vec<u8>) -> Result<(), UsbError> {
        (**self).bulk_out(bytes).await
    }

    async fn send_operation(
        &mut self,
        command: Vec<u8>,
        data_out: Option<Vec<u8>>,
    ) -> Result<(), UsbError> {
        (**self).send_operation(command, data_out).await
    }

    async fn bulk_in(&mut self, max: usize) -> Result<Vec<u8>, UsbError> {
        (**self).bulk_in(max).await
    }

    async fn interrupt_in(&mut self) -> Result<Vec<u8>, UsbError> {
        (**self).interrupt_in().await
    }
}

#[async_trait]
impl PtpPipe for MemoryPipe {
    async fn bulk_out(&mut self, bytes: Vec<u8>) -> Result<(), UsbError> {
        MemoryPipe::bulk_out(self, bytes).map_err(|_| UsbError::Disconnected)
    }

    async fn bulk_in(&mut self, max: usize) -> Result<Vec<u8>, UsbError> {
        MemoryPipe::bulk_in(self, max)
            .await
            .map_err(|_| UsbError::Disconnected)
    }

    async fn interrupt_in(&mut self) -> Result<Vec<u8>, UsbError> {
        MemoryPipe::interrupt_in(self)
            .await
            .map_err(|_| UsbError::Disconnected)
    }
}

/// One attached USB device, as enumeration reports it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UsbDeviceSummary {
    /// USB vendor id.
    pub vendor_id: u16,
    /// USB product id.
    pub product_id: u16,
    /// The product string descriptor, if the device has one.
    pub product: Option<String>,
    /// The serial number string descriptor, if the device has one; what a
    /// profile's `transport.serial` matches.
    pub serial: Option<String>,
    /// True when one of its interfaces is of the Still Image class.
    pub still_image: bool,
}

/// Lists the attached USB devices. On a machine without a USB bus (a
/// container, CI) this is an error, never a panic.
pub fn enumerate() -> Result<Vec<UsbDeviceSummary>, UsbError> {
    let list = nusb::list_devices().map_err(|e| UsbError::Io(e.to_string()))?;
    Ok(list
        .map(|d| UsbDeviceSummary {
            vendor_id: d.vendor_id(),
            product_id: d.product_id(),
            product: d.product_string().map(str::to_string),
            serial: d.serial_number().map(str::to_string),
            still_image: d.interfaces().any(|i| i.class() == STILL_IMAGE_CLASS),
        })
        .collect())
}

/// A real camera's Still Image interface, claimed through `nusb` (pure Rust,
/// no libusb).
pub struct NusbPipe {
    interface: nusb::Interface,
    bulk_in_ep: u8,
    bulk_out_ep: u8,
    interrupt_ep: u8,
}

impl std::fmt::Debug for NusbPipe {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NusbPipe")
            .field("bulk_in_ep", &self.bulk_in_ep)
            .field("bulk_out_ep", &self.bulk_out_ep)
            .field("interrupt_ep", &self.interrupt_ep)
            .finish()
    }
}

/// Events are small; 64 bytes hold a container with five parameters.
const INTERRUPT_MAX: usize = 64;

impl NusbPipe {
    /// Opens the first device with this vendor/product id and claims its
    /// Still Image interface's bulk-in, bulk-out and interrupt-in endpoints.
    pub fn open(vendor_id: u16, product_id: u16) -> Result<NusbPipe, UsbError> {
        NusbPipe::open_serial(vendor_id, product_id, None)
    }

    /// Like [`NusbPipe::open`], picking among identical cameras by serial
    /// number.
    pub fn open_serial(
        vendor_id: u16,
        product_id: u16,
        serial: Option<&str>,
    ) -> Result<NusbPipe, UsbError> {
        let io = |e: std::io::Error| UsbError::Io(e.to_string());
        let info = nusb::list_devices()
            .map_err(io)?
            .find(|d| {
                d.vendor_id() == vendor_id
                    && d.product_id() == product_id
                    && serial.is_none_or(|s| d.serial_number() == Some(s))
            })
            .ok_or(UsbError::NotFound {
                vendor_id,
                product_id,
            })?;
        let number = info
            .interfaces()
            .find(|i| i.class() == STILL_IMAGE_CLASS)
            .map(|i| i.interface_number())
            .ok_or(UsbError::NoStillImageInterface)?;
        let device = info.open().map_err(io)?;
        // A kernel driver (or gvfs) may hold the camera; take it over.
        let interface = device.detach_and_claim_interface(number).map_err(io)?;
        let (mut bulk_in_ep, mut bulk_out_ep, mut interrupt_ep) = (None, None, None);
        for alt in interface.descriptors() {
            for ep in alt.endpoints() {
                use nusb::transfer::{Direction, EndpointType};
                match (ep.transfer_type(), ep.direction()) {
                    (EndpointType::Bulk, Direction::In) => bulk_in_ep = Some(ep.address()),
                    (EndpointType::Bulk, Direction::Out) => bulk_out_ep = Some(ep.address()),
                    (EndpointType::Interrupt, Direction::In) => interrupt_ep = Some(ep.address()),
                    _ => {}
                }
            }
        }
        match (bulk_in_ep, bulk_out_ep, interrupt_ep) {
            (Some(bulk_in_ep), Some(bulk_out_ep), Some(interrupt_ep)) => Ok(NusbPipe {
                interface,
                bulk_in_ep,
                bulk_out_ep,
                interrupt_ep,
            }),
            _ => Err(UsbError::NoStillImageInterface),
        }
    }
}

fn transfer_error(e: nusb::transfer::TransferError) -> UsbError {
    match e {
        nusb::transfer::TransferError::Disconnected => UsbError::Disconnected,
        other => UsbError::Io(other.to_string()),
    }
}

#[async_trait]
impl PtpPipe for NusbPipe {
    async fn bulk_out(&mut self, bytes: Vec<u8>) -> Result<(), UsbError> {
        self.interface
            .bulk_out(self.bulk_out_ep, bytes)
            .await
            .into_result()
            .map(|_| ())
            .map_err(transfer_error)
    }

    async fn bulk_in(&mut self, max: usize) -> Result<Vec<u8>, UsbError> {
        self.interface
            .bulk_in(self.bulk_in_ep, nusb::transfer::RequestBuffer::new(max))
            .await
            .into_result()
            .map_err(transfer_error)
    }

    async fn interrupt_in(&mut self) -> Result<Vec<u8>, UsbError> {
        self.interface
            .interrupt_in(
                self.interrupt_ep,
                nusb::transfer::RequestBuffer::new(INTERRUPT_MAX),
            )
            .await
            .into_result()
            .map_err(transfer_error)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Without /dev/bus/usb (this container, CI) enumeration must fail
    /// cleanly; with a bus it lists devices. Either way: no panic, and
    /// opening an id that is surely absent is an error.
    #[test]
    fn enumeration_without_a_bus_is_an_error_not_a_panic() {
        match enumerate() {
            Ok(list) => assert!(list.iter().all(|d| d.vendor_id != 0 || d.product_id != 0)),
            Err(e) => assert!(matches!(e, UsbError::Io(_)), "{e}"),
        }
        assert!(NusbPipe::open(0xFFFF, 0xFFFE).is_err());
    }

    #[tokio::test]
    async fn memory_pipe_reports_a_closed_link_as_disconnected() {
        let (mut host, dev) = memory_pair();
        dev.write_in(vec![1, 2, 3])
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(PtpPipe::bulk_in(&mut host, 16).await, Ok(vec![1, 2, 3]));
        drop(dev);
        assert_eq!(
            PtpPipe::bulk_in(&mut host, 16).await,
            Err(UsbError::Disconnected)
        );
        assert_eq!(
            PtpPipe::bulk_out(&mut host, vec![0]).await,
            Err(UsbError::Disconnected)
        );
    }
}
