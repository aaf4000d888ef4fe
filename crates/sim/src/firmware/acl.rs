//! A simulated ACL-style arm controller (`firmware-protocols/robot-arm.md`)
//! speaking over any byte stream.
//!
//! Motion is not simulated step by step: a move is a start time, start and
//! target counts, and a duration; positions are evaluated at the clock's
//! current time. Joint interpolation: every joint follows the slowest
//! joint's trapezoid, scaled to its own distance, so all arrive together.
//! `HOME` and `MOVED` block the interpreter (as on the real controller), so
//! lines sent meanwhile are read only afterwards.

use std::collections::HashMap;
use std::sync::Arc;

use rigd_proto::acl::{parse_command, Command, LineSplitter, Reply, Status, CURRENT, MAX_LINE};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};

use crate::faults::{FaultInjector, FaultKind};
use crate::world::SharedWorld;
use rigd_core::clock::Clock;
use rigd_core::motion::Trapezoid;

/// One joint of the simulated arm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AclJoint {
    /// Encoder counts per degree.
    pub counts_per_deg: f64,
    /// Limits in degrees (the controller's own, checked on every move).
    pub min_deg: f64,
    /// Upper limit in degrees (the lower one is `min_deg`).
    pub max_deg: f64,
    /// Motion model in degrees and seconds.
    pub motion: Trapezoid,
}

/// How the simulated controller is set up.
#[derive(Debug, Clone)]
pub struct AclParams {
    /// Device name for the [`FaultInjector`].
    pub name: String,
    /// Joints 1..=N in order.
    pub joints: Vec<AclJoint>,
    /// Duration of the homing cycle in seconds.
    pub home_s: f64,
    /// Counts reported at power-up before homing (encoders are relative).
    pub power_up_counts: Vec<i64>,
    /// Start homed (a controller that kept its position across a reconnect).
    pub start_homed: bool,
    /// Where to publish the joint angles for the simulated cameras.
    pub world: Option<SharedWorld>,
}

impl Default for AclParams {
    /// The Bonn wrist (roll, pitch, twist) with the figures of the spec.
    fn default() -> AclParams {
        let j = |cpd, min, max, v, a| AclJoint {
            counts_per_deg: cpd,
            min_deg: min,
            max_deg: max,
            motion: Trapezoid {
                max_velocity: v,
                acceleration: a,
                settle_s: 0.3,
            },
        };
        AclParams {
            name: "arm".into(),
            joints: vec![
                j(100.0, -180.0, 180.0, 40.0, 80.0),
                j(100.0, -1.0, 89.0, 40.0, 80.0),
                j(50.0, -360.0, 360.0, 60.0, 120.0),
            ],
            home_s: 12.0,
            power_up_counts: vec![0, 0, 0],
            start_homed: false,
            world: None,
        }
    }
}

/// Joint-interpolated move duration in seconds for a move between two
/// count vectors: the slowest joint's trapezoid (including its settle
/// time) decides; `min_s` (the optional MOVE duration) can only stretch it.
pub fn move_duration(joints: &[AclJoint], from: &[i64], to: &[i64], min_s: f64) -> f64 {
    let t = joints
        .iter()
        .zip(from.iter().zip(to))
        .map(|(j, (f, t))| {
            let deg = (*t - *f) as f64 / j.counts_per_deg;
            j.motion.move_time(deg)
        })
        .fold(0.0, f64::max);
    t.max(min_s)
}

#[derive(Debug, Clone)]
struct Motion {
    from: Vec<i64>,
    to: Vec<i64>,
    start_s: f64,
    duration_s: f64,
}

impl Motion {
    fn at(&self, now_s: f64) -> Vec<i64> {
        let frac = if self.duration_s <= 0.0 {
            1.0
        } else {
            // Smooth unit profile: a trapezoid normalised to unit distance.
            let unit = Trapezoid {
                max_velocity: 1.5 / self.duration_s,
                acceleration: 4.5 / (self.duration_s * self.duration_s),
                settle_s: 0.0,
            };
            unit.position_at(
                0.0,
                1.0,
                (now_s - self.start_s) * unit.travel_time(1.0) / self.duration_s,
            )
        };
        self.from
            .iter()
            .zip(&self.to)
            .map(|(f, t)| f + ((t - f) as f64 * frac).round() as i64)
            .collect()
    }
    fn done(&self, now_s: f64) -> bool {
        now_s + super::END_TOLERANCE_S >= self.start_s + self.duration_s
    }
}

struct Machine {
    params: AclParams,
    clock: Clock,
    faults: Arc<FaultInjector>,
    homed: bool,
    control: bool,
    pos: Vec<i64>,
    motion: Option<Motion>,
    points: HashMap<String, Vec<i64>>,
    out: Vec<u8>,
    closed: bool,
}

/// Runs the simulated controller until the host closes the stream (or a
/// `Disconnect` fault closes it). Faults are checked once per command line
/// (ops `home`, `move`, `define`, `query`, `control`), never for `A`: an
/// emergency stop must always work.
pub async fn serve<S>(
    mut stream: S,
    params: AclParams,
    clock: Clock,
    faults: Arc<FaultInjector>,
) -> std::io::Result<()>
where
    S: AsyncRead + AsyncWrite + Unpin,
{
    let n = params.joints.len();
    let mut pos = params.power_up_counts.clone();
    pos.resize(n, 0);
    let mut m = Machine {
        homed: params.start_homed,
        params,
        clock,
        faults,
        control: true,
        pos,
        motion: None,
        points: HashMap::new(),
        out: Vec::new(),
        closed: false,
    };
    let mut split = LineSplitter::new(MAX_LINE);
    let mut buf = [0u8; 256];
    loop {
        let k = stream.read(&mut buf).await?;
        if k == 0 {
            return Ok(());
        }
        for &b in &buf[..k] {
            if let Some(line) = split.push(b) {
                m.line(&line.text, line.too_long).await;
                m.publish();
                if !m.out.is_empty() {
                    stream.write_all(&m.out).await?;
                    stream.flush().await?;
                    m.out.clear();
                }
                if m.closed {
                    return stream.shutdown().await;
                }
            }
        }
    }
}

impl Machine {
    fn reply(&mut self, r: Reply) {
        self.out.extend_from_slice(&r.encode());
    }

    fn now_counts(&mut self) -> Vec<i64> {
        let now = self.clock.now_s();
        if let Some(mv) = &self.motion {
            if mv.done(now) {
                self.pos = mv.to.clone();
                self.motion = None;
            } else {
                return mv.at(now);
            }
        }
        self.pos.clone()
    }

    /// Tells the world the joint angles, after every command line.
    fn publish(&mut self) {
        if let Some(world) = self.params.world.clone() {
            let counts = self.now_counts();
            let deg = counts
                .iter()
                .zip(&self.params.joints)
                .map(|(&c, j)| c as f64 / j.counts_per_deg)
                .collect();
            world.set_arm(deg);
        }
    }

    /// Stops all motion where the joints are now.
    fn stop(&mut self) {
        self.pos = self.now_counts();
        self.motion = None;
    }

    async fn line(&mut self, text: &str, too_long: bool) {
        // Echo first, as the controller's terminal does.
        if too_long {
            self.out.extend_from_slice(text.as_bytes());
            self.out.extend_from_slice(b"\r\n");
            self.reply(Reply::Error("line too long".into()));
            self.reply(Reply::Prompt);
            return;
        }
        let cmd = match parse_command(text) {
            Ok(c) => c,
            Err(e) => {
                self.out.extend_from_slice(text.as_bytes());
                self.out.extend_from_slice(b"\r\n");
                self.reply(Reply::Error(format!("syntax: {e}")));
                self.reply(Reply::Prompt);
                return;
            }
        };
        let op = match &cmd {
            Command::Home => Some("home"),
            Command::Move { .. } | Command::Moved { .. } => Some("move"),
            Command::Defp(_) | Command::Setpv { .. } | Command::Here(_) => Some("define"),
            Command::Listpv(_) | Command::Status => Some("query"),
            Command::Con | Command::Coff => Some("control"),
            Command::Abort => None,
        };
        if let Some(op) = op {
            match self.faults.check(&self.params.name, op) {
                // Frame faults are a camera's; a controller ignores them.
                None | Some(FaultKind::Dark | FaultKind::MaskMarkers) => {}
                Some(FaultKind::Timeout) => return,
                Some(FaultKind::Disconnect) => {
                    self.closed = true;
                    return;
                }
                Some(FaultKind::Alarm(t)) => {
                    self.out.extend_from_slice(text.as_bytes());
                    self.out.extend_from_slice(b"\r\n");
                    self.stop();
                    self.control = false;
                    self.reply(Reply::Error(t));
                    self.reply(Reply::Prompt);
                    return;
                }
                Some(FaultKind::BadFrame) => {
                    self.out.extend_from_slice(b"\x00#garbage\r\n");
                    self.reply(Reply::Prompt);
                    return;
                }
            }
        }
        self.out.extend_from_slice(text.as_bytes());
        self.out.extend_from_slice(b"\r\n");
        let r = self.execute(cmd).await;
        match r {
            Ok(replies) => {
                for r in replies {
                    self.reply(r);
                }
            }
            Err(e) => self.reply(Reply::Error(e.into())),
        }
        self.reply(Reply::Prompt);
    }

    fn point(&self, name: &str) -> Result<Vec<i64>, &'static str> {
        self.points.get(name).cloned().ok_or("position not defined")
    }

    async fn execute(&mut self, cmd: Command) -> Result<Vec<Reply>, &'static str> {
        let n = self.params.joints.len();
        match cmd {
            Command::Abort => {
                self.stop();
                Ok(vec![Reply::Ok])
            }
            Command::Con => {
                self.control = true;
                Ok(vec![Reply::Ok])
            }
            Command::Coff => {
                self.stop();
                self.control = false;
                Ok(vec![Reply::Ok])
            }
            Command::Status => {
                let now = self.clock.now_s();
                let moving = self.motion.as_ref().is_some_and(|m| !m.done(now));
                Ok(vec![Reply::Status(Status {
                    homed: self.homed,
                    moving,
                    control: self.control,
                })])
            }
            Command::Home => {
                if !self.control {
                    return Err("control disabled");
                }
                self.stop();
                self.clock.sleep_s(self.params.home_s).await;
                self.pos = vec![0; n];
                self.homed = true;
                Ok(vec![Reply::Done])
            }
            Command::Defp(name) => {
                if name == CURRENT {
                    return Err("reserved name");
                }
                let here = self.now_counts();
                self.points.entry(name).or_insert(here);
                Ok(vec![Reply::Done])
            }
            Command::Here(name) => {
                if name == CURRENT {
                    return Err("reserved name");
                }
                if !self.homed {
                    return Err("not homed");
                }
                let here = self.now_counts();
                self.points.insert(name, here);
                Ok(vec![Reply::Done])
            }
            Command::Setpv {
                name,
                joint,
                counts,
            } => {
                let j = usize::from(joint);
                if j == 0 || j > n {
                    return Err("bad joint number");
                }
                let p = self.points.get_mut(&name).ok_or("position not defined")?;
                p[j - 1] = counts;
                Ok(vec![Reply::Done])
            }
            Command::Listpv(name) => {
                let c = if name == CURRENT {
                    self.now_counts()
                } else {
                    self.point(&name)?
                };
                Ok(vec![Reply::Joints(c)])
            }
            Command::Move { name, duration } => {
                self.start_move(&name, duration)?;
                Ok(vec![Reply::Done])
            }
            Command::Moved { name, duration } => {
                let end = self.start_move(&name, duration)?;
                self.clock.sleep_s(end - self.clock.now_s()).await;
                self.now_counts();
                Ok(vec![Reply::Done])
            }
        }
    }

    /// Checks and starts a move; returns the clock time it ends.
    fn start_move(&mut self, name: &str, duration: Option<u32>) -> Result<f64, &'static str> {
        if !self.homed {
            return Err("not homed");
        }
        if !self.control {
            return Err("control disabled");
        }
        let target = self.point(name)?;
        let in_range = self.params.joints.iter().zip(&target).all(|(j, c)| {
            let deg = *c as f64 / j.counts_per_deg;
            deg >= j.min_deg - 1e-9 && deg <= j.max_deg + 1e-9
        });
        if !in_range {
            return Err("position out of range");
        }
        // A new move starts from wherever the joints are now.
        let from = self.now_counts();
        let min_s = duration.map(|d| f64::from(d) / 100.0).unwrap_or(0.0);
        let duration_s = move_duration(&self.params.joints, &from, &target, min_s);
        let start_s = self.clock.now_s();
        self.motion = Some(Motion {
            from,
            to: target,
            start_s,
            duration_s,
        });
        Ok(start_s + duration_s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::DuplexStream;

    async fn talk(host: &mut DuplexStream, line: &str) -> String {
        host.write_all(format!("{line}\r").as_bytes())
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let mut seen = String::new();
        let mut buf = [0u8; 256];
        while !seen.ends_with(">\r\n") {
            let n = host.read(&mut buf).await.unwrap_or_else(|e| panic!("{e}"));
            assert!(n > 0, "EOF");
            seen.push_str(&String::from_utf8_lossy(&buf[..n]));
        }
        seen
    }

    fn start(clock: &Clock) -> DuplexStream {
        let (host, dev) = tokio::io::duplex(4096);
        tokio::spawn(serve(
            dev,
            AclParams::default(),
            clock.clone(),
            Arc::new(FaultInjector::default()),
        ));
        host
    }

    #[tokio::test(start_paused = true)]
    async fn moved_blocks_and_duration_only_stretches() {
        let clock = Clock::virtual_time();
        let mut h = start(&clock);
        talk(&mut h, "HOME").await;
        talk(&mut h, "DEFP P").await;
        talk(&mut h, "SETPV P 3 4500").await;
        let t0 = clock.now_s();
        let r = talk(&mut h, "MOVED P 500").await;
        assert_eq!(r, "MOVED P 500\r\nDone.\r\n>\r\n");
        let dt = clock.now_s() - t0;
        assert!((5.0..5.01).contains(&dt), "{dt}");
        let r = talk(&mut h, "LISTPV POSITION").await;
        assert!(r.contains("1:0 2:0 3:4500"), "{r}");
        // A shorter requested duration cannot make the arm faster.
        talk(&mut h, "SETPV P 3 0").await;
        let t0 = clock.now_s();
        talk(&mut h, "MOVED P 1").await;
        let dt = clock.now_s() - t0;
        assert!((2.3..2.31).contains(&dt), "{dt}");
    }

    #[tokio::test(start_paused = true)]
    async fn limits_and_abort_are_enforced_by_the_controller() {
        let clock = Clock::virtual_time();
        let mut h = start(&clock);
        talk(&mut h, "HOME").await;
        talk(&mut h, "DEFP P").await;
        talk(&mut h, "SETPV P 2 9000").await;
        let r = talk(&mut h, "MOVE P").await;
        assert!(r.contains("*** position out of range"), "{r}");
        talk(&mut h, "SETPV P 2 8000").await;
        talk(&mut h, "MOVE P").await;
        clock.sleep_s(0.5).await;
        assert!(talk(&mut h, "A").await.contains("OK"));
        let a = talk(&mut h, "LISTPV POSITION").await;
        clock.sleep_s(5.0).await;
        let b = talk(&mut h, "LISTPV POSITION").await;
        assert_eq!(
            a.replace("LISTPV POSITION", ""),
            b.replace("LISTPV POSITION", "")
        );
        assert!(!a.contains("2:0 ") && !a.contains("2:8000"), "{a}");
    }
}
