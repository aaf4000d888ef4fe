//! Physics of the simulated devices: where an axis is and how long it takes
//! to get somewhere, when a lamp gives stable light, what an exposure costs.
//! Every wait goes through the [`Clock`]; every call first asks the
//! [`FaultInjector`] whether it must fail.

use std::sync::Arc;

use crate::clock::Clock;
use crate::faults::{FaultInjector, FaultKind};
use crate::motion::Trapezoid;
use crate::scene::{render_flat, Shot};

/// How a simulated device call fails.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimError {
    #[error("disconnected")]
    Disconnected,
    #[error("{0}")]
    Alarm(String),
    #[error("not homed")]
    NotHomed,
    #[error("no frame was exposed")]
    NoFrame,
}

/// Shared wiring of every simulated device.
#[derive(Debug, Clone)]
pub struct SimContext {
    pub clock: Clock,
    pub faults: Arc<FaultInjector>,
}

impl SimContext {
    pub fn new(clock: Clock, faults: Arc<FaultInjector>) -> SimContext {
        SimContext { clock, faults }
    }

    /// Applies an armed fault: a timeout never answers (the caller's deadline
    /// must catch it); a bad frame is the camera's business and passes here.
    async fn gate(&self, device: &str, op: &str) -> Result<Option<FaultKind>, SimError> {
        match self.faults.check(device, op) {
            None => Ok(None),
            Some(FaultKind::Timeout) => {
                std::future::pending::<()>().await;
                Ok(None)
            }
            Some(FaultKind::Disconnect) => Err(SimError::Disconnected),
            Some(FaultKind::Alarm(m)) => Err(SimError::Alarm(m)),
            Some(FaultKind::BadFrame) => Ok(Some(FaultKind::BadFrame)),
        }
    }
}

/// A stepper axis (or one joint): trapezoidal moves, then settling.
#[derive(Debug)]
pub struct SimAxis {
    name: String,
    motion: Trapezoid,
    position: f64,
    homed: bool,
    ctx: SimContext,
}

impl SimAxis {
    pub fn new(name: &str, motion: Trapezoid, power_on_position: f64, ctx: SimContext) -> SimAxis {
        SimAxis {
            name: name.to_string(),
            motion,
            position: power_on_position,
            homed: false,
            ctx,
        }
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// Drives to the home switch and takes `home` as the position there.
    pub async fn home(&mut self, home: f64) -> Result<f64, SimError> {
        self.ctx.gate(&self.name, "home").await?;
        self.ctx
            .clock
            .sleep_s(self.motion.move_time(self.position - home))
            .await;
        self.position = home;
        self.homed = true;
        Ok(self.position)
    }

    /// Moves to an absolute position and settles; returns where it stands.
    pub async fn move_to(&mut self, target: f64) -> Result<f64, SimError> {
        self.ctx.gate(&self.name, "move").await?;
        if !self.homed {
            return Err(SimError::NotHomed);
        }
        self.ctx
            .clock
            .sleep_s(self.motion.move_time(target - self.position))
            .await;
        self.position = target;
        Ok(self.position)
    }

    pub async fn position(&mut self) -> Result<f64, SimError> {
        self.ctx.gate(&self.name, "position").await?;
        Ok(self.position)
    }

    /// The position without a device call, for the simulated world.
    pub fn current(&self) -> f64 {
        self.position
    }
}

/// A lamp behind a relay: switching costs `switch_s`; after switch-on the
/// light is stable only after `warm_up_s`.
#[derive(Debug)]
pub struct SimLamp {
    name: String,
    warm_up_s: f64,
    switch_s: f64,
    on: bool,
    stable_at_s: f64,
    ctx: SimContext,
}

impl SimLamp {
    pub fn new(name: &str, warm_up_s: f64, switch_s: f64, ctx: SimContext) -> SimLamp {
        SimLamp {
            name: name.to_string(),
            warm_up_s,
            switch_s,
            on: false,
            stable_at_s: 0.0,
            ctx,
        }
    }

    pub async fn set(&mut self, on: bool) -> Result<(), SimError> {
        self.ctx.gate(&self.name, "set").await?;
        if on == self.on {
            return Ok(());
        }
        self.ctx.clock.sleep_s(self.switch_s).await;
        self.on = on;
        if on {
            self.stable_at_s = self.ctx.clock.now_s() + self.warm_up_s;
        }
        Ok(())
    }

    /// Waits until the light is stable (returns at once if it is off).
    pub async fn wait_ready(&mut self) -> Result<(), SimError> {
        self.ctx.gate(&self.name, "ready").await?;
        if self.on {
            let wait = self.stable_at_s - self.ctx.clock.now_s();
            self.ctx.clock.sleep_s(wait).await;
        }
        Ok(())
    }

    pub fn is_on(&self) -> bool {
        self.on
    }
}

/// Camera timing: exposure and readout keep the sensor busy; the transfer
/// delivers the frame afterwards.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraTimes {
    pub exposure_s: f64,
    pub readout_s: f64,
    pub transfer_s: f64,
}

/// A frame as it leaves the camera.
#[derive(Debug, Clone, PartialEq)]
pub struct RawFrame {
    pub width: u32,
    pub height: u32,
    pub bit_depth: u8,
    pub pixels: Vec<u16>,
}

#[derive(Debug)]
pub struct SimCamera {
    name: String,
    times: CameraTimes,
    nominal_exposure_s: f64,
    pending: Option<RawFrame>,
    ctx: SimContext,
}

impl SimCamera {
    pub fn new(name: &str, times: CameraTimes, ctx: SimContext) -> SimCamera {
        SimCamera {
            name: name.to_string(),
            times,
            nominal_exposure_s: times.exposure_s,
            pending: None,
            ctx,
        }
    }

    pub fn set_exposure(&mut self, exposure_s: f64) {
        if exposure_s > 0.0 && exposure_s.is_finite() {
            self.times.exposure_s = exposure_s;
        }
    }

    pub fn exposure_s(&self) -> f64 {
        self.times.exposure_s
    }

    /// Exposes and reads out the sensor under the given light and view.
    pub async fn expose(&mut self, mut shot: Shot) -> Result<(), SimError> {
        self.ctx.gate(&self.name, "expose").await?;
        self.ctx
            .clock
            .sleep_s(self.times.exposure_s + self.times.readout_s)
            .await;
        shot.relative_exposure = self.times.exposure_s / self.nominal_exposure_s;
        self.pending = Some(RawFrame {
            width: shot.width,
            height: shot.height,
            bit_depth: shot.bit_depth,
            pixels: render_flat(&shot),
        });
        Ok(())
    }

    /// Transfers the last exposed frame to the host.
    pub async fn transfer(&mut self) -> Result<RawFrame, SimError> {
        let fault = self.ctx.gate(&self.name, "transfer").await?;
        let mut frame = self.pending.take().ok_or(SimError::NoFrame)?;
        self.ctx.clock.sleep_s(self.times.transfer_s).await;
        if fault == Some(FaultKind::BadFrame) {
            // A truncated transfer: the host must notice the short frame.
            let keep = frame.pixels.len() / 2;
            frame.pixels.truncate(keep);
        }
        Ok(frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ctx(rules: &str) -> SimContext {
        let rules = rules
            .split(',')
            .filter(|s| !s.is_empty())
            .map(|s| s.parse().unwrap_or_else(|e| panic!("{e}")))
            .collect();
        SimContext::new(Clock::virtual_time(), Arc::new(FaultInjector::new(rules)))
    }

    const M: Trapezoid = Trapezoid {
        max_velocity: 10.0,
        acceleration: 20.0,
        settle_s: 0.5,
    };

    #[tokio::test(start_paused = true)]
    async fn axis_move_takes_its_physical_time() {
        let c = ctx("");
        let mut a = SimAxis::new("rail", M, 0.0, c.clone());
        assert_eq!(a.move_to(5.0).await, Err(SimError::NotHomed));
        a.home(0.0).await.unwrap_or_else(|e| panic!("{e}"));
        let t0 = c.clock.now_s();
        a.move_to(100.0).await.unwrap_or_else(|e| panic!("{e}"));
        let dt = c.clock.now_s() - t0;
        assert!((dt - (10.5 + 0.5)).abs() < 1e-3, "{dt}");
    }

    #[tokio::test(start_paused = true)]
    async fn lamp_warm_up_is_waited_for() {
        let c = ctx("");
        let mut l = SimLamp::new("hmi", 180.0, 0.5, c.clone());
        l.set(true).await.unwrap_or_else(|e| panic!("{e}"));
        l.wait_ready().await.unwrap_or_else(|e| panic!("{e}"));
        assert!((c.clock.now_s() - 180.5).abs() < 1e-3);
        // Already warm: no second wait.
        l.wait_ready().await.unwrap_or_else(|e| panic!("{e}"));
        assert!((c.clock.now_s() - 180.5).abs() < 1e-3);
    }

    #[tokio::test(start_paused = true)]
    async fn timeout_fault_never_answers() {
        let c = ctx("rail:home:1:timeout");
        let mut a = SimAxis::new("rail", M, 0.0, c.clone());
        let r = c
            .clock
            .deadline(std::time::Duration::from_secs(3), a.home(0.0))
            .await;
        assert!(r.is_err());
    }

    #[tokio::test(start_paused = true)]
    async fn bad_frame_is_truncated() {
        let c = ctx("cam:transfer:2:bad-frame");
        let t = CameraTimes {
            exposure_s: 0.1,
            readout_s: 0.2,
            transfer_s: 0.3,
        };
        let mut cam = SimCamera::new("cam", t, c.clone());
        let shot = Shot {
            light: [0.0, 0.0, 1.0],
            view: [0.0, 0.0, 1.0],
            width: 8,
            height: 8,
            bit_depth: 12,
            relative_exposure: 1.0,
        };
        assert_eq!(cam.transfer().await, Err(SimError::NoFrame));
        cam.expose(shot).await.unwrap_or_else(|e| panic!("{e}"));
        let f = cam.transfer().await.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(f.pixels.len(), 32);
        cam.expose(shot).await.unwrap_or_else(|e| panic!("{e}"));
        let f = cam.transfer().await.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(f.pixels.len(), 64);
        assert!((c.clock.now_s() - 1.2).abs() < 1e-6);
    }
}
