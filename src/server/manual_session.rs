//! The daemon's manual control: a rig connected on the first manual action
//! and held between actions (a serial port re-opened per action would reset
//! an Arduino-based GRBL board and lose its position), released when a run
//! needs the rig. Actions take the run start gate, so a run and a manual
//! action never drive the rig at once, and are refused with 409 while a
//! run is active; the daemon's emergency stop covers them.

use std::future::Future;
use std::sync::{Arc, Mutex};

use super::error::SupervisorError;
use crate::engine::estop::{EStop, StopReport};
use crate::engine::manual::{ManualError, ManualRig};
use crate::model::profile::Profile;
use crate::rig::{FaultRule, SimHandle};
use rigd_core::sync::lock;
use rigd_core::Clock;

/// The manual-control rig and what it last saw.
#[derive(Default)]
pub struct ManualSession {
    rig: tokio::sync::Mutex<Option<ManualRig>>,
    /// The rig's emergency stop, reachable while an action holds `rig`.
    estop: Mutex<Option<EStop>>,
    /// The last test frame as a PNG (raw sensor values).
    frame: Mutex<Option<Vec<u8>>>,
}

impl ManualSession {
    /// Drops the manual rig (closing its links) so a run can connect.
    pub async fn release(&self) {
        let released = self.rig.lock().await.take().is_some();
        *lock(&self.estop) = None;
        if released {
            tracing::info!("manual control released the rig");
        }
    }

    /// Stops every device of the manual rig, if there is one.
    pub async fn emergency_stop(&self) -> Option<StopReport> {
        let estop = lock(&self.estop).clone()?;
        Some(estop.trigger().await)
    }

    /// The last test frame's PNG.
    pub fn last_frame(&self) -> Option<Vec<u8>> {
        lock(&self.frame).clone()
    }

    /// Keeps a test frame's PNG for the preview.
    pub fn keep_frame(&self, png: Vec<u8>) {
        *lock(&self.frame) = Some(png);
    }

    /// Runs one manual action on the manual rig, connecting it first
    /// (`connect`) if there is none. The caller has checked that no run
    /// is active and holds the run start gate.
    pub async fn act<T, F, C, Connecting>(
        &self,
        connect: C,
        action: F,
    ) -> Result<T, SupervisorError>
    where
        C: FnOnce() -> Connecting,
        Connecting: Future<Output = Result<ManualRig, SupervisorError>>,
        F: for<'a> FnOnce(
            &'a mut ManualRig,
        ) -> std::pin::Pin<
            Box<dyn Future<Output = Result<T, ManualError>> + Send + 'a>,
        >,
    {
        let mut slot = self.rig.lock().await;
        if slot.is_none() {
            let rig = connect().await?;
            *lock(&self.estop) = Some(rig.estop());
            *slot = Some(rig);
        }
        let Some(rig) = slot.as_mut() else {
            return Err(SupervisorError::internal("manual rig missing"));
        };
        Ok(action(rig).await?)
    }
}

/// Connects the rig for manual control: the simulated one when `sim` holds
/// its fault rules (with its handle, so the rig card shows the manual
/// rig's positions and lamps), else the hardware.
pub async fn connect_rig(
    profile: &Profile,
    sim: Option<Vec<FaultRule>>,
    clock: Clock,
) -> Result<(ManualRig, Option<SimHandle>), SupervisorError> {
    let solver = Arc::new(
        crate::kinematics::Solver::new(profile)
            .map_err(|e| SupervisorError::internal(e.to_string()))?,
    );
    let device = |e: crate::rig::hal::DeviceError| SupervisorError::Device(e.to_string());
    let (rig, handle) = match sim {
        Some(faults) => {
            #[cfg(feature = "sim")]
            {
                let opts = crate::rig::sim::SimOptions {
                    frame_size: None,
                    faults,
                };
                let (rig, handle) = crate::rig::sim::connect(profile, solver.clone(), opts, &clock)
                    .await
                    .map_err(device)?;
                (rig, Some(handle))
            }
            #[cfg(not(feature = "sim"))]
            {
                let _ = faults;
                return Err(SupervisorError::unavailable(
                    "this rigd was built without the simulator",
                ));
            }
        }
        None => (
            crate::rig::hardware::connect(profile, &clock)
                .await
                .map_err(device)?,
            None,
        ),
    };
    tracing::info!("manual control connected the rig");
    Ok((ManualRig::new(rig, profile.clone(), solver, clock), handle))
}

impl From<ManualError> for SupervisorError {
    fn from(e: ManualError) -> SupervisorError {
        match e {
            ManualError::BadInput(m) => SupervisorError::invalid(m),
            ManualError::Device(d) => SupervisorError::Device(d.to_string()),
        }
    }
}
