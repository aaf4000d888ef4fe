//! The daemon's manual control: a rig connected on the first manual action
//! and held between actions (a serial port re-opened per action would reset
//! an Arduino-based GRBL board and lose its position), released when a run
//! needs the rig. Actions take the run start gate, so a run and a manual
//! action never drive the rig at once, and are refused with 409 while a
//! run is active; the daemon's emergency stop covers them.

use std::sync::{Arc, Mutex};

use super::supervisor::{lock, Daemon, SupervisorError};
use crate::engine::estop::{EStop, StopReport};
use crate::engine::manual::{ManualError, ManualRig};

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
}

impl From<ManualError> for SupervisorError {
    fn from(e: ManualError) -> SupervisorError {
        match e {
            ManualError::BadInput(m) => SupervisorError::invalid(m),
            ManualError::Device(d) => SupervisorError::Device(d.to_string()),
        }
    }
}

impl Daemon {
    /// Runs one manual action on the manual rig, connecting it first if
    /// needed. 409 while a run is active.
    pub async fn manual<T, F>(self: &Arc<Self>, action: F) -> Result<T, SupervisorError>
    where
        F: for<'a> FnOnce(
            &'a mut ManualRig,
        ) -> std::pin::Pin<
            Box<dyn std::future::Future<Output = Result<T, ManualError>> + Send + 'a>,
        >,
    {
        let _gate = self.start_gate.lock().await;
        {
            let inner = self.inner();
            if inner.shutting_down {
                return Err(SupervisorError::unavailable("the daemon is shutting down"));
            }
            if let Some(a) = &inner.active {
                return Err(SupervisorError::conflict(format!(
                    "run {} is active ({}): manual control waits until it has ended",
                    a.id, a.state
                )));
            }
        }
        let mut slot = self.manual.rig.lock().await;
        if slot.is_none() {
            let rig = self.connect_manual_rig().await?;
            *lock(&self.manual.estop) = Some(rig.estop());
            *slot = Some(rig);
        }
        let Some(rig) = slot.as_mut() else {
            return Err(SupervisorError::internal("manual rig missing"));
        };
        Ok(action(rig).await?)
    }

    async fn connect_manual_rig(&self) -> Result<ManualRig, SupervisorError> {
        let clock = self.clock();
        let solver = Arc::new(
            crate::kinematics::Solver::new(&self.profile)
                .map_err(|e| SupervisorError::internal(e.to_string()))?,
        );
        let device = |e: crate::rig::hal::DeviceError| SupervisorError::Device(e.to_string());
        let rig = if self.config.sim {
            #[cfg(feature = "sim")]
            {
                let opts = crate::rig::sim::SimOptions {
                    frame_size: None,
                    faults: self.config.sim_faults.clone(),
                };
                let (rig, sim) =
                    crate::rig::sim::connect(&self.profile, solver.clone(), opts, &clock)
                        .await
                        .map_err(device)?;
                // The rig card shows the manual rig's positions and lamps.
                self.inner().last_sim = Some(sim);
                rig
            }
            #[cfg(not(feature = "sim"))]
            return Err(SupervisorError::unavailable(
                "this rigd was built without the simulator",
            ));
        } else {
            crate::rig::hardware::connect(&self.profile, &clock)
                .await
                .map_err(device)?
        };
        tracing::info!("manual control connected the rig");
        Ok(ManualRig::new(rig, self.profile.clone(), solver, clock))
    }
}
