//! Devices whose link can be lost and opened again: after a call fails
//! with `Disconnected`, the device's next call first opens its link again
//! and brings the driver back to where it was ([`Linked`], one wrapper for
//! every kind; [`Relinkable`] says how each kind re-opens). A Modbus
//! module's connection, shared by its lamps and laser, re-opens itself
//! (`Bus` in the parent module).

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;

use async_trait::async_trait;

use super::{open_pipe, open_stream, BoxPipe, ByteStream, Opener, PipeOpener};
use crate::rig::drivers::acl::AclArm;
use crate::rig::drivers::grbl::GrblAxis;
use crate::rig::drivers::ptp::{PtpCamera, PtpConfig};
use crate::rig::hal::{Arm, Axis, Camera, DeviceError, ErrorKind, Frame};
use rigd_core::Clock;

/// A device call's future, borrowing the device.
type Call<'a, T> = Pin<Box<dyn Future<Output = Result<T, DeviceError>> + Send + 'a>>;

/// How a device opens its lost link again and restores its state.
#[async_trait]
pub(super) trait Relinkable: Send {
    /// Opens the link again; the driver is ready for calls after it.
    async fn relink(&mut self) -> Result<(), DeviceError>;
}

/// A device behind a link that can be lost.
pub(super) struct Linked<D> {
    device: D,
    lost: bool,
}

impl<D: Relinkable> Linked<D> {
    /// A device whose link is open.
    pub(super) fn new(device: D) -> Linked<D> {
        Linked {
            device,
            lost: false,
        }
    }

    /// Runs `call`, opening the link first if an earlier call lost it.
    async fn call<T>(
        &mut self,
        call: impl for<'a> FnOnce(&'a mut D) -> Call<'a, T>,
    ) -> Result<T, DeviceError> {
        if self.lost {
            self.device.relink().await?;
            self.lost = false;
        }
        self.without_relink(call).await
    }

    /// Runs `call` on the link as it is (a call that cannot be helped by a
    /// fresh link), noting whether it lost it.
    async fn without_relink<T>(
        &mut self,
        call: impl for<'a> FnOnce(&'a mut D) -> Call<'a, T>,
    ) -> Result<T, DeviceError> {
        let r = call(&mut self.device).await;
        self.lost |= lost_link(&r);
        r
    }
}

/// True when a call failed because the link is gone (so the next call
/// must open it again).
pub(super) fn lost_link<T>(r: &Result<T, DeviceError>) -> bool {
    matches!(r, Err(e) if e.kind == ErrorKind::Disconnected)
}

/// A line-protocol driver (GRBL, ACL) and what opens its serial link.
pub(super) struct OnLine<D> {
    /// The driver.
    pub driver: D,
    /// Its link.
    pub line: Line,
}

/// What opens a line device's link again.
pub(super) struct Line {
    /// The device's name, for errors.
    pub name: String,
    /// Opens the link.
    pub opener: Arc<dyn Opener>,
    /// The rig's clock (the opening's deadline).
    pub clock: Clock,
}

impl Line {
    async fn open(&self) -> Result<ByteStream, DeviceError> {
        let stream = open_stream(&self.clock, &self.name, self.opener.as_ref()).await?;
        tracing::info!(device = %self.name, "link re-opened");
        Ok(stream)
    }
}

#[async_trait]
impl Relinkable for OnLine<GrblAxis<ByteStream>> {
    async fn relink(&mut self) -> Result<(), DeviceError> {
        let stream = self.line.open().await?;
        self.driver.reconnect(stream).await
    }
}

#[async_trait]
impl Relinkable for OnLine<AclArm<ByteStream>> {
    async fn relink(&mut self) -> Result<(), DeviceError> {
        let stream = self.line.open().await?;
        self.driver.reconnect(stream).await.map(|_| ())
    }
}

#[async_trait]
impl Axis for Linked<OnLine<GrblAxis<ByteStream>>> {
    async fn home(&mut self) -> Result<f64, DeviceError> {
        self.call(|d| Box::pin(d.driver.home())).await
    }

    async fn move_to(&mut self, target: f64) -> Result<f64, DeviceError> {
        self.call(move |d| Box::pin(d.driver.move_to(target))).await
    }

    async fn position(&mut self) -> Result<f64, DeviceError> {
        self.call(|d| Box::pin(d.driver.position())).await
    }

    async fn start_sweep(&mut self, target: f64, velocity: f64) -> Result<(), DeviceError> {
        self.call(move |d| Box::pin(d.driver.start_sweep(target, velocity)))
            .await
    }

    async fn wait_idle(&mut self) -> Result<f64, DeviceError> {
        self.call(|d| Box::pin(d.driver.wait_idle())).await
    }
}

#[async_trait]
impl Arm for Linked<OnLine<AclArm<ByteStream>>> {
    async fn home(&mut self) -> Result<Vec<f64>, DeviceError> {
        self.call(|d| Box::pin(d.driver.home())).await
    }

    async fn move_joints(&mut self, joints: &[f64]) -> Result<Vec<f64>, DeviceError> {
        let joints = joints.to_vec();
        self.call(move |d| Box::pin(async move { d.driver.move_joints(&joints).await }))
            .await
    }

    async fn joints(&mut self) -> Result<Vec<f64>, DeviceError> {
        self.call(|d| Box::pin(d.driver.joints())).await
    }
}

/// A PTP camera and what opens its USB pipe again.
pub(super) struct PtpOnUsb {
    /// The driver.
    pub cam: PtpCamera<BoxPipe>,
    /// The camera's name, for errors.
    pub name: String,
    /// The driver's settings, for a fresh session.
    pub config: PtpConfig,
    /// Opens the pipe.
    pub opener: Arc<dyn PipeOpener>,
    /// The rig's clock.
    pub clock: Clock,
    /// The exposure last set, set again on a fresh session.
    pub exposure_s: Option<f64>,
}

#[async_trait]
impl Relinkable for PtpOnUsb {
    async fn relink(&mut self) -> Result<(), DeviceError> {
        let pipe = open_pipe(&self.clock, &self.name, self.opener.as_ref()).await?;
        let mut cam = PtpCamera::new(&self.name, pipe, self.clock.clone(), self.config.clone());
        cam.connect()
            .await
            .map_err(|e| DeviceError::new(&self.name, e.kind(), e.to_string()))?;
        if let Some(e) = self.exposure_s {
            cam.set_exposure(e).await?;
        }
        self.cam = cam;
        tracing::info!(device = %self.name, "camera re-opened");
        Ok(())
    }
}

#[async_trait]
impl Camera for Linked<PtpOnUsb> {
    async fn set_exposure(&mut self, exposure_s: f64) -> Result<(), DeviceError> {
        self.call(move |d| {
            Box::pin(async move {
                d.cam.set_exposure(exposure_s).await?;
                d.exposure_s = Some(exposure_s);
                Ok(())
            })
        })
        .await
    }

    async fn expose(&mut self) -> Result<(), DeviceError> {
        self.call(|d| Box::pin(d.cam.expose())).await
    }

    async fn transfer(&mut self) -> Result<Frame, DeviceError> {
        // A lost link lost the frame with it: re-opening cannot bring it back.
        self.without_relink(|d| Box::pin(d.cam.transfer())).await
    }
}
