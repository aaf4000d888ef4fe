//! Driver for the robot arm's ACL-style controller (protocol:
//! `firmware-protocols/robot-arm.md`).
//!
//! Joint mapping: the controller exposes joints 1..=N; joint n is the n-th
//! joint of the profile (`[[devices.arm.joints]]`, for the Bonn wrist
//! 1 = roll, 2 = pitch, 3 = twist). Degrees = `home_deg + counts /
//! counts_per_deg`.
//!
//! Why it is built this way:
//! - Moves go through one position variable (`RIGD`) set joint by joint
//!   with `SETPV`, then `MOVE` (not `MOVED`) and `STATUS` polling: `MOVED`
//!   blocks the controller's interpreter, so an abort sent during it would
//!   only be read after the move had finished.
//! - Every answer ends with the prompt `>`. The driver counts prompts it is
//!   still owed (after a deadline or a cancelled call) and drains them
//!   before the next command, and it skips everything before the echo of
//!   its own command, so a late answer is never taken for the next one.
//! - After a (re)connect the pose is re-read with `LISTPV POSITION`, never
//!   taken from the last set-point: the arm may have moved meanwhile.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use rigd_proto::acl::{parse_reply, Command, LineSplitter, Reply, Status, CURRENT};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, ReadHalf, WriteHalf};
use tokio::sync::Mutex;

use super::{stop_failed, write_locked};
use crate::model::profile::{Limits, Motion};
use crate::rig::hal::{Arm, DeviceError, EmergencyStop, ErrorKind};
use rigd_core::Clock;

/// The position variable the driver moves through.
pub const TARGET: &str = "RIGD";

/// One joint as the driver sees it.
#[derive(Debug, Clone)]
pub struct AclJointConfig {
    /// The joint's name in the profile, used in errors.
    pub name: String,
    /// Soft limits in degrees; set-points outside are refused before sending.
    pub limits: Limits,
    /// Motion model, used only to size motion deadlines.
    pub motion: Motion,
    /// Encoder counts per degree (the controller works in counts).
    pub counts_per_deg: f64,
    /// Joint angle in degrees at zero counts (after homing).
    pub home_deg: f64,
}

impl AclJointConfig {
    fn to_counts(&self, deg: f64) -> i64 {
        ((deg - self.home_deg) * self.counts_per_deg).round() as i64
    }
    fn to_deg(&self, counts: i64) -> f64 {
        self.home_deg + counts as f64 / self.counts_per_deg
    }
}

/// How an ACL arm is driven.
#[derive(Debug, Clone)]
pub struct AclConfig {
    /// Device name used in errors.
    pub name: String,
    /// Joints 1..=N in controller order (= profile order).
    pub joints: Vec<AclJointConfig>,
    /// Deadline for the answer (up to the prompt) to one command.
    pub command_timeout: Duration,
    /// Deadline for `HOME`, which is answered when homing is complete.
    pub home_timeout: Duration,
    /// `STATUS` poll interval while waiting for motion to complete.
    pub poll_interval: Duration,
}

impl AclConfig {
    /// Defaults: 2 s per command, 120 s for homing, 100 ms polls.
    pub fn new(name: &str, joints: Vec<AclJointConfig>) -> AclConfig {
        AclConfig {
            name: name.to_string(),
            joints,
            command_timeout: Duration::from_secs(2),
            home_timeout: Duration::from_secs(120),
            poll_interval: Duration::from_millis(100),
        }
    }

    /// The modelled time of a joint-interpolated move: the slowest joint's.
    fn modelled_move_time(&self, from: &[f64], to: &[f64]) -> Duration {
        let t = self
            .joints
            .iter()
            .zip(from.iter().zip(to))
            .map(|(j, (f, t))| rigd_core::Trapezoid::from(j.motion).move_time(t - f))
            .filter(|t| t.is_finite())
            .fold(0.0, f64::max);
        Duration::from_secs_f64(t)
    }

    /// Worst case for a joint-interpolated move to finish: twice the
    /// slowest joint's modelled time plus a command timeout and a poll.
    fn motion_deadline(&self, from: &[f64], to: &[f64]) -> Duration {
        let t = self.modelled_move_time(from, to).as_secs_f64();
        Duration::from_secs_f64(2.0 * t) + self.command_timeout + self.poll_interval
    }
}

/// What went wrong talking to the arm, in the driver's own terms.
#[derive(Debug, thiserror::Error)]
pub enum AclError {
    /// No complete answer (up to the prompt) to a command, or a move or
    /// homing that did not finish, before its deadline.
    #[error("no answer to {what} within {timeout:?}")]
    Timeout {
        /// The command or wait that timed out.
        what: String,
        /// The deadline it had.
        timeout: Duration,
    },
    /// The link reached end of file: the controller closed it.
    #[error("link closed by the device")]
    Disconnected,
    /// Reading or writing the link failed.
    #[error("link I/O error: {0}")]
    Io(#[from] std::io::Error),
    /// The controller answered a command with a `*** text` error line
    /// (not homed, impact protection, position out of range, …).
    #[error("`{command}`: *** {message}")]
    Device {
        /// The command it refused.
        command: String,
        /// The controller's text after `***`.
        message: String,
    },
    /// A set-point outside a joint's soft limits; refused before sending.
    #[error("joint {joint} target {target} deg outside soft limits [{min}, {max}]")]
    OutOfLimits {
        /// The joint's name.
        joint: String,
        /// The requested angle, degrees.
        target: f64,
        /// The joint's lower soft limit, degrees.
        min: f64,
        /// The joint's upper soft limit, degrees.
        max: f64,
    },
    /// A move was given a different number of joint values than the arm has.
    #[error("{got} joint values given, the arm has {expected}")]
    JointCount {
        /// Joints the arm has.
        expected: usize,
        /// Values given.
        got: usize,
    },
    /// An answer the driver cannot parse or did not expect (no status or
    /// joint line, a wrong joint count, an unexpected reply).
    #[error("unexpected reply: {0}")]
    Protocol(String),
}

impl AclError {
    /// The kind the run engine acts on.
    pub fn kind(&self) -> ErrorKind {
        match self {
            AclError::Timeout { .. } => ErrorKind::Timeout,
            AclError::Disconnected | AclError::Io(_) => ErrorKind::Disconnected,
            AclError::Device { .. } => ErrorKind::DeviceFault,
            AclError::OutOfLimits { .. } | AclError::JointCount { .. } => ErrorKind::OutOfLimits,
            AclError::Protocol(_) => ErrorKind::BadFrame,
        }
    }
}

/// An ACL-controlled arm on a byte stream (a serial port in production, an
/// in-memory duplex pipe in tests).
pub struct AclArm<S> {
    cfg: AclConfig,
    clock: Clock,
    reader: ReadHalf<S>,
    /// Shared with [`AclStop`], which sends the abort mid-call.
    writer: Arc<Mutex<WriteHalf<S>>>,
    split: LineSplitter,
    lines: VecDeque<String>,
    /// Prompts owed by the controller for lines already sent.
    pending: usize,
    /// `DEFP RIGD` was done on this link.
    defined: bool,
    /// The counts each joint of `RIGD` holds, as far as this link has set
    /// them (`None`: unknown, e.g. a `SETPV` that got no answer).
    target_counts: Vec<Option<i64>>,
    last_status: Option<Status>,
    last_joints: Option<Vec<f64>>,
}

impl<S> std::fmt::Debug for AclArm<S> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AclArm")
            .field("name", &self.cfg.name)
            .field("last_status", &self.last_status)
            .field("last_joints", &self.last_joints)
            .finish()
    }
}

impl<S> AclArm<S>
where
    S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    /// Takes over a freshly opened link: reads status and pose.
    pub async fn connect(stream: S, cfg: AclConfig, clock: Clock) -> Result<Self, DeviceError> {
        let (reader, writer) = tokio::io::split(stream);
        let mut arm = AclArm {
            cfg,
            clock,
            reader,
            writer: Arc::new(Mutex::new(writer)),
            split: LineSplitter::new(256),
            lines: VecDeque::new(),
            pending: 0,
            defined: false,
            target_counts: Vec::new(),
            last_status: None,
            last_joints: None,
        };
        let r = arm.sync().await;
        arm.map(r)?;
        Ok(arm)
    }

    /// Replaces a lost link and re-reads status and pose from the controller.
    pub async fn reconnect(&mut self, stream: S) -> Result<Vec<f64>, DeviceError> {
        let (reader, writer) = tokio::io::split(stream);
        self.reader = reader;
        *self.writer.lock().await = writer;
        self.split = LineSplitter::new(256);
        self.lines.clear();
        self.pending = 0;
        self.defined = false;
        self.target_counts.clear();
        self.last_status = None;
        self.last_joints = None;
        let r = self.sync().await;
        self.map(r)
    }

    /// Emergency stop: `A` stops all motion at once; returns where the
    /// joints stopped. Call it after cancelling a `move_joints` future.
    pub async fn abort(&mut self) -> Result<Vec<f64>, DeviceError> {
        let r = async {
            self.command(&Command::Abort, self.cfg.command_timeout)
                .await?;
            self.read_joints().await
        }
        .await;
        self.map(r)
    }

    /// The out-of-band emergency stop of this arm (it survives reconnects).
    pub fn stopper(&self) -> AclStop<S> {
        AclStop {
            name: self.cfg.name.clone(),
            writer: self.writer.clone(),
        }
    }

    /// The last status the controller reported.
    pub fn last_status(&self) -> Option<Status> {
        self.last_status
    }

    /// The last pose read from the controller (degrees).
    pub fn last_joints(&self) -> Option<&[f64]> {
        self.last_joints.as_deref()
    }

    fn map<T>(&self, r: Result<T, AclError>) -> Result<T, DeviceError> {
        r.map_err(|e| DeviceError::new(&self.cfg.name, e.kind(), e.to_string()))
    }

    async fn sync(&mut self) -> Result<Vec<f64>, AclError> {
        self.status().await?;
        self.read_joints().await
    }

    /// Next line from the device; EOF means the link is gone.
    async fn next_line(&mut self) -> Result<String, AclError> {
        loop {
            if let Some(l) = self.lines.pop_front() {
                return Ok(l);
            }
            let mut buf = [0u8; 256];
            // `read` is cancel-safe: a deadline firing here loses no bytes.
            let n = self.reader.read(&mut buf).await?;
            if n == 0 {
                return Err(AclError::Disconnected);
            }
            for &b in &buf[..n] {
                if let Some(l) = self.split.push(b) {
                    self.lines.push_back(l.text);
                }
            }
        }
    }

    /// Reads away the answers still owed for earlier lines. If they never
    /// come (the controller lost the line), gives up after one command
    /// timeout; the echo check in [`Self::exchange`] still protects the
    /// next answer.
    async fn drain(&mut self) -> Result<(), AclError> {
        if self.pending == 0 {
            return Ok(());
        }
        let clock = self.clock.clone();
        let r = clock
            .deadline(self.cfg.command_timeout, async {
                while self.pending > 0 {
                    if parse_reply(&self.next_line().await?) == Ok(Reply::Prompt) {
                        self.pending -= 1;
                    }
                }
                Ok::<(), AclError>(())
            })
            .await;
        match r {
            Ok(inner) => inner,
            Err(_) => {
                tracing::warn!(device = %self.cfg.name, "answers to {} lines never came", self.pending);
                self.pending = 0;
                Ok(())
            }
        }
    }

    /// Sends one command and collects its replies up to the prompt.
    async fn exchange(&mut self, cmd: &Command) -> Result<Vec<Reply>, AclError> {
        let line = cmd.line();
        self.pending += 1;
        write_locked(&self.writer, &cmd.encode()).await?;
        // Skip to the echo of our own line.
        loop {
            let l = self.next_line().await?;
            if l.trim() == line {
                break;
            }
            if parse_reply(&l) == Ok(Reply::Prompt) {
                // A late prompt owed for an earlier line; an answer without
                // our echo is caught by the deadline.
                self.pending = self.pending.saturating_sub(1);
            }
        }
        let mut replies = Vec::new();
        let mut bad = None;
        loop {
            let l = self.next_line().await?;
            match parse_reply(&l) {
                Ok(Reply::Prompt) => {
                    self.pending = self.pending.saturating_sub(1);
                    break;
                }
                Ok(r) => replies.push(r),
                Err(e) => bad = Some(e.to_string()),
            }
        }
        if let Some(Reply::Error(message)) = replies.iter().find(|r| matches!(r, Reply::Error(_))) {
            return Err(AclError::Device {
                command: line,
                message: message.clone(),
            });
        }
        if let Some(b) = bad {
            return Err(AclError::Protocol(b));
        }
        Ok(replies)
    }

    async fn command(&mut self, cmd: &Command, timeout: Duration) -> Result<Vec<Reply>, AclError> {
        // Draining has its own deadline, so it never eats this command's.
        self.drain().await?;
        let clock = self.clock.clone();
        match clock.deadline(timeout, self.exchange(cmd)).await {
            Ok(r) => r,
            Err(_) => Err(AclError::Timeout {
                what: format!("`{cmd}`"),
                timeout,
            }),
        }
    }

    /// A command whose answer must be `want` (`Done.` or `OK`).
    async fn expect(
        &mut self,
        cmd: &Command,
        want: Reply,
        timeout: Duration,
    ) -> Result<(), AclError> {
        let r = self.command(cmd, timeout).await?;
        if r.contains(&want) {
            Ok(())
        } else {
            Err(AclError::Protocol(format!("`{cmd}` answered {r:?}")))
        }
    }

    async fn status(&mut self) -> Result<Status, AclError> {
        let r = self
            .command(&Command::Status, self.cfg.command_timeout)
            .await?;
        for x in r {
            if let Reply::Status(s) = x {
                self.last_status = Some(s);
                return Ok(s);
            }
        }
        Err(AclError::Protocol("STATUS gave no status line".into()))
    }

    async fn read_joints(&mut self) -> Result<Vec<f64>, AclError> {
        let r = self
            .command(&Command::Listpv(CURRENT.into()), self.cfg.command_timeout)
            .await?;
        let counts = r
            .into_iter()
            .find_map(|x| match x {
                Reply::Joints(j) => Some(j),
                _ => None,
            })
            .ok_or_else(|| AclError::Protocol("LISTPV gave no joint line".into()))?;
        if counts.len() != self.cfg.joints.len() {
            return Err(AclError::Protocol(format!(
                "controller has {} joints, profile {}",
                counts.len(),
                self.cfg.joints.len()
            )));
        }
        let deg: Vec<f64> = self
            .cfg
            .joints
            .iter()
            .zip(&counts)
            .map(|(j, c)| j.to_deg(*c))
            .collect();
        self.last_joints = Some(deg.clone());
        Ok(deg)
    }

    async fn home_inner(&mut self) -> Result<Vec<f64>, AclError> {
        let t = self.cfg.command_timeout;
        self.expect(&Command::Con, Reply::Ok, t).await?;
        self.expect(&Command::Home, Reply::Done, self.cfg.home_timeout)
            .await?;
        self.read_joints().await
    }

    /// Refuses bad set-points before anything is sent.
    fn check(&self, joints: &[f64]) -> Result<Vec<i64>, AclError> {
        if joints.len() != self.cfg.joints.len() {
            return Err(AclError::JointCount {
                expected: self.cfg.joints.len(),
                got: joints.len(),
            });
        }
        self.cfg
            .joints
            .iter()
            .zip(joints)
            .map(|(j, &t)| {
                if t.is_finite() && j.limits.contains(t) {
                    Ok(j.to_counts(t))
                } else {
                    Err(AclError::OutOfLimits {
                        joint: j.name.clone(),
                        target: t,
                        min: j.limits.min,
                        max: j.limits.max,
                    })
                }
            })
            .collect()
    }

    async fn move_inner(&mut self, joints: &[f64]) -> Result<Vec<f64>, AclError> {
        let counts = self.check(joints)?;
        let t = self.cfg.command_timeout;
        if !self.defined {
            self.expect(&Command::Defp(TARGET.into()), Reply::Done, t)
                .await?;
            self.defined = true;
            self.target_counts.clear();
        }
        // A joint whose value `RIGD` already holds is not set again: each
        // `SETPV` is a round trip on the serial line.
        if self.target_counts.len() != counts.len() {
            self.target_counts = vec![None; counts.len()];
        }
        for (i, c) in counts.iter().enumerate() {
            if self.target_counts[i] == Some(*c) {
                continue;
            }
            self.target_counts[i] = None;
            let cmd = Command::Setpv {
                name: TARGET.into(),
                joint: u8::try_from(i + 1)
                    .map_err(|_| AclError::Protocol("more than 255 joints".into()))?,
                counts: *c,
            };
            self.expect(&cmd, Reply::Done, t).await?;
            self.target_counts[i] = Some(*c);
        }
        let from = match self.last_joints.clone() {
            Some(j) => j,
            None => self.read_joints().await?,
        };
        let mv = Command::Move {
            name: TARGET.into(),
            duration: None,
        };
        self.expect(&mv, Reply::Done, t).await?;
        let deadline = self.cfg.motion_deadline(&from, joints);
        let modelled = self.cfg.modelled_move_time(&from, joints);
        let clock = self.clock.clone();
        match clock.deadline(deadline, self.wait_still(modelled)).await {
            Ok(r) => r?,
            Err(_) => {
                return Err(AclError::Timeout {
                    what: "motion to complete".into(),
                    timeout: deadline,
                })
            }
        }
        self.read_joints().await
    }

    /// Polls `STATUS` until the controller reports no motion, when
    /// [`super::Polls`] says for a move modelled to take `modelled`.
    async fn wait_still(&mut self, modelled: Duration) -> Result<(), AclError> {
        let start = self.clock.now();
        let mut polls = super::Polls::new(self.cfg.poll_interval, modelled);
        loop {
            let elapsed = self.clock.now().saturating_sub(start);
            self.clock.sleep(polls.next_wait(elapsed)).await;
            let s = self.status().await?;
            if !s.moving {
                return Ok(());
            }
        }
    }
}

/// The controller's abort (`A`), written while any call may be in flight:
/// the controller stops all joints when it reads the line, and never
/// refuses it. The call in flight sees the arm stop short and fails.
pub struct AclStop<S> {
    name: String,
    writer: Arc<Mutex<WriteHalf<S>>>,
}

#[async_trait]
impl<S> EmergencyStop for AclStop<S>
where
    S: AsyncWrite + Send + 'static,
{
    async fn emergency_stop(&self) -> Result<(), DeviceError> {
        write_locked(&self.writer, &Command::Abort.encode())
            .await
            .map_err(|e| stop_failed(&self.name, e))
    }
}

#[async_trait]
impl<S> Arm for AclArm<S>
where
    S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    async fn home(&mut self) -> Result<Vec<f64>, DeviceError> {
        let r = self.home_inner().await;
        self.map(r)
    }

    async fn move_joints(&mut self, joints: &[f64]) -> Result<Vec<f64>, DeviceError> {
        let r = self.move_inner(joints).await;
        self.map(r)
    }

    async fn joints(&mut self) -> Result<Vec<f64>, DeviceError> {
        let r = self.read_joints().await;
        self.map(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_map_to_engine_kinds() {
        let d = AclError::Device {
            command: "MOVE RIGD".into(),
            message: "impact protection".into(),
        };
        assert_eq!(d.kind(), ErrorKind::DeviceFault);
        assert_eq!(d.to_string(), "`MOVE RIGD`: *** impact protection");
        assert_eq!(AclError::Disconnected.kind(), ErrorKind::Disconnected);
        assert_eq!(
            AclError::JointCount {
                expected: 3,
                got: 2
            }
            .kind(),
            ErrorKind::OutOfLimits
        );
    }

    #[test]
    fn degrees_and_counts_convert_per_joint() {
        let j = AclJointConfig {
            name: "twist".into(),
            limits: Limits {
                min: -360.0,
                max: 360.0,
            },
            motion: Motion {
                max_velocity: 1.0,
                acceleration: 1.0,
                settle_s: 0.0,
            },
            counts_per_deg: 50.0,
            home_deg: 10.0,
        };
        assert_eq!(j.to_counts(40.0), 1500);
        assert_eq!(j.to_deg(1500), 40.0);
        assert_eq!(j.to_counts(10.1), 5);
        assert_eq!(j.to_counts(-350.0), -18000);
    }
}
