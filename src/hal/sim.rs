//! The simulated rig behind the capability traits: thin adapters over the
//! device physics of `rigd-sim`, sharing one simulated world so a camera
//! renders what the axes and lamps really did (forward kinematics of the
//! positions reached, not the set-points asked for).

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, MutexGuard};

use async_trait::async_trait;
use rigd_sim::devices::{CameraTimes, SimAxis, SimCamera, SimContext, SimError, SimLamp};
use rigd_sim::motion::Trapezoid;
use rigd_sim::scene::Shot;
use rigd_sim::{Clock, FaultInjector, FaultRule};

use super::{Arm, Axis, Camera, DeviceError, ErrorKind, Frame, Lamp, LaserLine, Rig};
use crate::kinematics::{Setpoints, Solver};
use crate::profile::{DeviceKind, Motion, Profile};

/// The state of the simulated world that cameras render.
#[derive(Debug, Clone, Default)]
pub struct World {
    pub axes: BTreeMap<String, f64>,
    pub arm: Option<Vec<f64>>,
    pub lamps_on: BTreeMap<String, bool>,
}

/// What a test or the command line may set on the simulated rig.
#[derive(Debug, Clone, Default)]
pub struct SimOptions {
    /// Frame size the cameras render; the profile's `[sim] frame_size` if None.
    pub frame_size: Option<[u32; 2]>,
    pub faults: Vec<FaultRule>,
}

/// Handles into a running simulated rig: its faults and its world.
#[derive(Debug, Clone)]
pub struct SimHandle {
    pub faults: Arc<FaultInjector>,
    pub world: Arc<Mutex<World>>,
}

fn lock(world: &Mutex<World>) -> MutexGuard<'_, World> {
    // The world holds plain numbers; a panic elsewhere cannot break them.
    world.lock().unwrap_or_else(|p| p.into_inner())
}

fn map_err(device: &str, e: SimError) -> DeviceError {
    let kind = match e {
        SimError::Disconnected => ErrorKind::Disconnected,
        SimError::Alarm(_) => ErrorKind::DeviceFault,
        SimError::NotHomed | SimError::NoFrame => ErrorKind::NotReady,
    };
    DeviceError::new(device, kind, e.to_string())
}

fn trapezoid(m: Motion) -> Trapezoid {
    Trapezoid {
        max_velocity: m.max_velocity,
        acceleration: m.acceleration,
        settle_s: m.settle_s,
    }
}

/// Builds the simulated rig of a profile.
pub fn build(
    profile: &Profile,
    solver: Arc<Solver>,
    opts: SimOptions,
    clock: Clock,
) -> (Rig, SimHandle) {
    let faults = Arc::new(FaultInjector::new(opts.faults));
    let world = Arc::new(Mutex::new(World::default()));
    let ctx = SimContext::new(clock, faults.clone());
    let frame_size = opts.frame_size.unwrap_or(profile.sim.frame_size);
    let mut rig = Rig::default();
    for (name, dev) in &profile.devices {
        match dev.kind {
            DeviceKind::Axis => {
                let home = dev.home_deg.unwrap_or(0.0);
                let sim = SimAxis::new(name, trapezoid(dev.motion_or_default()), home, ctx.clone());
                rig.axes.insert(
                    name.clone(),
                    Box::new(SimAxisDevice {
                        sim,
                        home,
                        world: world.clone(),
                    }),
                );
            }
            DeviceKind::Arm => {
                let joints = dev.joints.clone().unwrap_or_default();
                let sims = joints
                    .iter()
                    .map(|j| {
                        SimAxis::new(
                            &format!("{name}.{}", j.name),
                            trapezoid(j.motion),
                            j.home_deg,
                            ctx.clone(),
                        )
                    })
                    .collect();
                rig.arms.insert(
                    name.clone(),
                    Box::new(SimArmDevice {
                        name: name.clone(),
                        joints: sims,
                        homes: joints.iter().map(|j| j.home_deg).collect(),
                        world: world.clone(),
                    }),
                );
            }
            DeviceKind::Lamp => {
                let sim = SimLamp::new(
                    name,
                    dev.warm_up_s.unwrap_or(0.0),
                    dev.switch_s.unwrap_or(0.0),
                    ctx.clone(),
                );
                lock(&world).lamps_on.insert(name.clone(), false);
                rig.lamps.insert(
                    name.clone(),
                    Box::new(SimLampDevice {
                        name: name.clone(),
                        sim,
                        world: world.clone(),
                    }),
                );
            }
            DeviceKind::Laser => {
                rig.lasers
                    .insert(name.clone(), Box::new(SimLaserDevice { on: false }));
            }
            DeviceKind::Camera => {
                let (times, bit_depth) = match (dev.timing, dev.intrinsics) {
                    (Some(t), Some(i)) => (
                        CameraTimes {
                            exposure_s: t.exposure_s,
                            readout_s: t.readout_s,
                            transfer_s: t.transfer_s,
                        },
                        i.bit_depth,
                    ),
                    // Validation guarantees both for cameras.
                    _ => continue,
                };
                rig.cameras.insert(
                    name.clone(),
                    Box::new(SimCameraDevice {
                        name: name.clone(),
                        sim: SimCamera::new(name, times, ctx.clone()),
                        solver: solver.clone(),
                        world: world.clone(),
                        frame_size,
                        bit_depth,
                    }),
                );
            }
        }
    }
    (rig, SimHandle { faults, world })
}

struct SimAxisDevice {
    sim: SimAxis,
    home: f64,
    world: Arc<Mutex<World>>,
}

#[async_trait]
impl Axis for SimAxisDevice {
    async fn home(&mut self) -> Result<f64, DeviceError> {
        let p = self
            .sim
            .home(self.home)
            .await
            .map_err(|e| map_err(self.sim.name(), e))?;
        lock(&self.world)
            .axes
            .insert(self.sim.name().to_string(), p);
        Ok(p)
    }

    async fn move_to(&mut self, target: f64) -> Result<f64, DeviceError> {
        let p = self
            .sim
            .move_to(target)
            .await
            .map_err(|e| map_err(self.sim.name(), e))?;
        lock(&self.world)
            .axes
            .insert(self.sim.name().to_string(), p);
        Ok(p)
    }

    async fn position(&mut self) -> Result<f64, DeviceError> {
        self.sim
            .position()
            .await
            .map_err(|e| map_err(self.sim.name(), e))
    }
}

struct SimArmDevice {
    name: String,
    joints: Vec<SimAxis>,
    homes: Vec<f64>,
    world: Arc<Mutex<World>>,
}

impl SimArmDevice {
    fn publish(&self) -> Vec<f64> {
        let q: Vec<f64> = self.joints.iter().map(|j| j.current()).collect();
        lock(&self.world).arm = Some(q.clone());
        q
    }
}

#[async_trait]
impl Arm for SimArmDevice {
    async fn home(&mut self) -> Result<Vec<f64>, DeviceError> {
        let homes = self.homes.clone();
        let moves = self.joints.iter_mut().zip(homes).map(|(j, h)| j.home(h));
        for r in futures::future::join_all(moves).await {
            r.map_err(|e| map_err(&self.name, e))?;
        }
        Ok(self.publish())
    }

    async fn move_joints(&mut self, joints: &[f64]) -> Result<Vec<f64>, DeviceError> {
        if joints.len() != self.joints.len() {
            return Err(DeviceError::new(
                &self.name,
                ErrorKind::OutOfLimits,
                format!(
                    "expected {} joint values, got {}",
                    self.joints.len(),
                    joints.len()
                ),
            ));
        }
        // The arm's controller interpolates all joints together; each joint
        // follows its own trapezoid, so the slowest one decides the time.
        let moves = self
            .joints
            .iter_mut()
            .zip(joints)
            .map(|(j, &q)| j.move_to(q));
        let results = futures::future::join_all(moves).await;
        let published = self.publish();
        for r in results {
            r.map_err(|e| map_err(&self.name, e))?;
        }
        Ok(published)
    }

    async fn joints(&mut self) -> Result<Vec<f64>, DeviceError> {
        Ok(self.joints.iter().map(|j| j.current()).collect())
    }
}

struct SimLampDevice {
    name: String,
    sim: SimLamp,
    world: Arc<Mutex<World>>,
}

#[async_trait]
impl Lamp for SimLampDevice {
    async fn set(&mut self, on: bool) -> Result<(), DeviceError> {
        self.sim.set(on).await.map_err(|e| map_err(&self.name, e))?;
        lock(&self.world)
            .lamps_on
            .insert(self.name.clone(), self.sim.is_on());
        Ok(())
    }

    async fn wait_ready(&mut self) -> Result<(), DeviceError> {
        self.sim
            .wait_ready()
            .await
            .map_err(|e| map_err(&self.name, e))
    }
}

struct SimLaserDevice {
    on: bool,
}

#[async_trait]
impl LaserLine for SimLaserDevice {
    async fn set(&mut self, on: bool) -> Result<(), DeviceError> {
        self.on = on;
        Ok(())
    }
}

struct SimCameraDevice {
    name: String,
    sim: SimCamera,
    solver: Arc<Solver>,
    world: Arc<Mutex<World>>,
    frame_size: [u32; 2],
    bit_depth: u8,
}

impl SimCameraDevice {
    /// Light and view in the sample frame, from where the devices really are.
    fn shot(&self) -> Shot {
        let world = lock(&self.world).clone();
        let lamp = world
            .lamps_on
            .iter()
            .find(|(_, on)| **on)
            .map(|(n, _)| n.clone());
        let setpoints = Setpoints {
            axes: world.axes,
            arm: world.arm,
            lamp: lamp.clone().unwrap_or_default(),
        };
        let (light, view) = match self.solver.forward(&setpoints, &self.name) {
            Ok((l, v)) => (l.to_vector(), v.to_vector()),
            // Devices not yet where forward kinematics needs them: render the
            // holder unlit rather than invent a pose.
            Err(_) => ([0.0, 0.0, -1.0], [0.0, 0.0, 1.0]),
        };
        Shot {
            light: if lamp.is_some() {
                light
            } else {
                [0.0, 0.0, -1.0]
            },
            view,
            width: self.frame_size[0],
            height: self.frame_size[1],
            bit_depth: self.bit_depth,
            relative_exposure: 1.0,
        }
    }
}

#[async_trait]
impl Camera for SimCameraDevice {
    async fn set_exposure(&mut self, exposure_s: f64) -> Result<(), DeviceError> {
        if !(exposure_s > 0.0 && exposure_s.is_finite()) {
            return Err(DeviceError::new(
                &self.name,
                ErrorKind::OutOfLimits,
                format!("exposure {exposure_s} s is not a positive time"),
            ));
        }
        self.sim.set_exposure(exposure_s);
        Ok(())
    }

    async fn expose(&mut self) -> Result<(), DeviceError> {
        let shot = self.shot();
        self.sim
            .expose(shot)
            .await
            .map_err(|e| map_err(&self.name, e))
    }

    async fn transfer(&mut self) -> Result<Frame, DeviceError> {
        let raw = self
            .sim
            .transfer()
            .await
            .map_err(|e| map_err(&self.name, e))?;
        Ok(Frame {
            width: raw.width,
            height: raw.height,
            bit_depth: raw.bit_depth,
            pixels: raw.pixels,
        })
    }
}
