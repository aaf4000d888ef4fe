//! The one clock every wait goes through.
//!
//! It reads tokio's clock. On a runtime started with paused time (the
//! simulated rig) tokio advances time by itself whenever every task waits, so
//! physical durations are reproduced exactly in a fraction of the wall time.
//! A speed factor lets a real-time demo run faster than physics while still
//! reporting physical time.

use std::future::Future;
use std::time::Duration;

use tokio::time::Instant;

/// The shortest wall time a deadline of a sped-up clock allows.
/// Five seconds: a loaded CI machine stalled a healthy simulated camera
/// past 100 ms, and the render of a 640×480 Bayer frame past 2 s, and an
/// operator still sees a silent device within moments.
pub const MIN_WALL_DEADLINE: Duration = Duration::from_secs(5);

/// A deadline passed before the operation finished.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("deadline of {0:?} (physical) passed")]
pub struct DeadlineElapsed(pub Duration);

/// Physical time since the clock started, and waits measured in physical time.
#[derive(Debug, Clone)]
pub struct Clock {
    origin: Instant,
    speed: f64,
    virtual_time: bool,
}

impl Clock {
    /// Wall-clock time, for real hardware.
    pub fn real() -> Clock {
        Clock::build(1.0, false)
    }

    /// Virtual time. The caller promises the runtime was started with paused
    /// time (`Builder::start_paused(true)`), so sleeps cost no wall time.
    pub fn virtual_time() -> Clock {
        Clock::build(1.0, true)
    }

    /// Physical time running `speed` times faster than the wall clock, for
    /// demos of the simulated rig. Non-finite or non-positive speeds mean 1.
    pub fn scaled(speed: f64) -> Clock {
        Clock::build(speed, false)
    }

    fn build(speed: f64, virtual_time: bool) -> Clock {
        let speed = if speed.is_finite() && speed > 0.0 {
            speed
        } else {
            1.0
        };
        Clock {
            origin: Instant::now(),
            speed,
            virtual_time,
        }
    }

    /// Physical time elapsed since the clock was made.
    pub fn now(&self) -> Duration {
        self.origin.elapsed().mul_f64(self.speed)
    }

    /// Physical seconds since the clock was made.
    pub fn now_s(&self) -> f64 {
        self.now().as_secs_f64()
    }

    /// True when time is virtual (the runtime was started paused).
    pub fn is_virtual(&self) -> bool {
        self.virtual_time
    }

    /// Waits for a physical duration.
    pub async fn sleep(&self, physical: Duration) {
        tokio::time::sleep(physical.div_f64(self.speed)).await;
    }

    /// Waits for `physical` seconds; negative or NaN waits return at once.
    pub async fn sleep_s(&self, physical_s: f64) {
        if physical_s > 0.0 && physical_s.is_finite() {
            self.sleep(Duration::from_secs_f64(physical_s)).await;
        }
    }

    /// Whether `physical` has passed since `since` (a reading of
    /// [`Clock::now`]), by the same rule as [`Clock::deadline`]: on a
    /// sped-up clock, also at least [`MIN_WALL_DEADLINE`] of wall time. For
    /// polling loops that give up after a limit but must not cancel a
    /// request in flight to do so.
    pub fn has_passed(&self, since: Duration, physical: Duration) -> bool {
        let elapsed = self.now().saturating_sub(since);
        if elapsed < physical {
            return false;
        }
        if self.speed > 1.0 && !self.virtual_time {
            return elapsed.div_f64(self.speed) >= MIN_WALL_DEADLINE;
        }
        true
    }

    /// Runs `fut` with a physical deadline. On a sped-up clock the
    /// deadline never ends sooner than [`MIN_WALL_DEADLINE`] of wall time:
    /// the software's own latency (scheduling on a loaded machine, a pipe's
    /// round trip) does not speed up with the simulation, and must not be
    /// mistaken for a device that stopped answering.
    pub async fn deadline<F: Future>(
        &self,
        physical: Duration,
        fut: F,
    ) -> Result<F::Output, DeadlineElapsed> {
        let mut wall = physical.div_f64(self.speed);
        if self.speed > 1.0 && !self.virtual_time {
            wall = wall.max(MIN_WALL_DEADLINE);
        }
        tokio::time::timeout(wall, fut)
            .await
            .map_err(|_| DeadlineElapsed(physical))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn virtual_hour_passes_instantly() {
        let clock = Clock::virtual_time();
        assert!(clock.is_virtual());
        let wall = std::time::Instant::now();
        clock.sleep(Duration::from_secs(3600)).await;
        assert!(clock.now() >= Duration::from_secs(3600));
        assert!(wall.elapsed() < Duration::from_secs(5));
    }

    #[tokio::test(start_paused = true)]
    async fn a_limit_passes_in_physical_time_with_the_wall_floor_when_sped_up() {
        let limit = Duration::from_secs(182);
        // Virtual time: exactly the physical limit.
        let clock = Clock::virtual_time();
        let t0 = clock.now();
        clock.sleep(Duration::from_secs(181)).await;
        assert!(!clock.has_passed(t0, limit));
        clock.sleep(Duration::from_secs(1)).await;
        assert!(clock.has_passed(t0, limit));
        // 1000x: 182 s physical is 0.182 s of wall time, under the floor,
        // so a loaded machine's millisecond stalls are not a dead lamp.
        let fast = Clock::scaled(1000.0);
        let t0 = fast.now();
        tokio::time::sleep(Duration::from_millis(200)).await;
        assert!(fast.now() - t0 >= limit);
        assert!(!fast.has_passed(t0, limit), "before the wall floor");
        tokio::time::sleep(MIN_WALL_DEADLINE).await;
        assert!(fast.has_passed(t0, limit));
    }

    #[tokio::test(start_paused = true)]
    async fn deadline_fires_in_physical_time() {
        // 60 s physical at 10× is 6 s of wall time, above the floor.
        let clock = Clock::scaled(10.0);
        let r = clock
            .deadline(
                Duration::from_secs(60),
                clock.sleep(Duration::from_secs(100)),
            )
            .await;
        assert_eq!(r, Err(DeadlineElapsed(Duration::from_secs(60))));
        let s = clock.now_s();
        assert!((60.0..60.1).contains(&s), "{s}");
    }

    #[tokio::test(start_paused = true)]
    async fn a_sped_up_deadline_leaves_the_software_its_wall_time() {
        // 5 s physical at 1000× would be 5 ms: the floor keeps 5 s of wall
        // time, so a loaded machine's scheduling is not a silent device.
        let clock = Clock::scaled(1000.0);
        let r = clock
            .deadline(
                Duration::from_secs(5),
                clock.sleep(Duration::from_secs(10_000)),
            )
            .await;
        assert_eq!(r, Err(DeadlineElapsed(Duration::from_secs(5))));
        let wall = clock.now().div_f64(1000.0);
        assert!(
            wall >= MIN_WALL_DEADLINE && wall < MIN_WALL_DEADLINE + Duration::from_millis(50),
            "{wall:?}"
        );
        // Virtual time has no floor: its software costs no physical time.
        let virt = Clock::virtual_time();
        let before = virt.now();
        let r = virt
            .deadline(Duration::from_millis(5), virt.sleep(Duration::from_secs(1)))
            .await;
        assert!(r.is_err());
        assert!(virt.now() - before < Duration::from_millis(10));
    }

    #[test]
    fn bad_speed_falls_back_to_one() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .map_err(|e| e.to_string());
        let Ok(rt) = rt else { panic!("runtime") };
        rt.block_on(async {
            assert_eq!(Clock::scaled(f64::NAN).speed, 1.0);
            assert_eq!(Clock::scaled(-3.0).speed, 1.0);
            assert!(!Clock::real().is_virtual());
        });
    }
}
