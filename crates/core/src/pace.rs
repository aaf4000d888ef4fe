//! Virtual time paced to the wall clock, for sped-up demos of the simulated rig.
//!
//! A [`PacedRuntime`] is a current-thread tokio runtime started with paused
//! time, on a thread of its own: physical time there advances only by what
//! the rig model waits, exactly as in a `rigd run --sim` capture, and a
//! pacer task holds it back to `speed` times the wall clock. The pacer only
//! ever waits. When the host cannot keep up (a loaded machine, a slow
//! render), virtual time advances more slowly in wall time and the physical
//! time a run reports stays the rig's; a host that falls behind is not made
//! up for in a burst afterwards, and [`Pace::achieved`] says how fast it
//! really went.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::oneshot;

/// Wall time between two checks of the pace: virtual time never runs
/// further ahead of the wall than one tick's worth.
const TICK: Duration = Duration::from_millis(10);
/// How far the host may fall behind before the pace is re-anchored at the
/// present instead of being caught up.
const MAX_CATCH_UP: Duration = Duration::from_millis(50);
/// The wall time over which the achieved speed is measured.
const WINDOW: Duration = Duration::from_secs(2);
/// Achieved below this share of the asked speed counts as behind.
const BEHIND_SHARE: f64 = 0.95;

/// The asked speed and the speed the host achieves, shared between the
/// pacer and whoever reports on the run.
#[derive(Debug)]
pub struct Pace {
    asked: f64,
    achieved_bits: AtomicU64,
}

impl Pace {
    fn new(asked: f64) -> Pace {
        Pace {
            asked,
            achieved_bits: AtomicU64::new(asked.to_bits()),
        }
    }

    /// Physical seconds per wall second asked for.
    pub fn asked(&self) -> f64 {
        self.asked
    }

    /// Physical seconds per wall second over the last two seconds of wall
    /// time: at most [`Pace::asked`], less when the host falls behind.
    pub fn achieved(&self) -> f64 {
        f64::from_bits(self.achieved_bits.load(Ordering::Relaxed))
    }

    /// Whether the host falls behind the asked speed (below 95 % of it).
    pub fn is_behind(&self) -> bool {
        self.achieved() < BEHIND_SHARE * self.asked
    }

    fn record(&self, achieved: f64) {
        let achieved = achieved.clamp(0.0, self.asked);
        self.achieved_bits
            .store(achieved.to_bits(), Ordering::Relaxed);
    }
}

/// A runtime in virtual time paced to `speed` times the wall clock. Tasks
/// spawned on [`PacedRuntime::handle`] (a simulated rig's firmware, its
/// engine) wait in virtual time; their [`crate::Clock`] must be made with
/// [`crate::Clock::virtual_time`] on this runtime. Dropping it stops the
/// runtime and every task still on it.
#[derive(Debug)]
pub struct PacedRuntime {
    handle: tokio::runtime::Handle,
    pace: Arc<Pace>,
    stop: Option<oneshot::Sender<()>>,
}

/// Why a paced runtime could not start.
#[derive(Debug, thiserror::Error)]
pub enum PaceError {
    /// The speed is not a positive finite number.
    #[error("speed {0}: expected a positive number")]
    Speed(f64),
    /// The runtime or its thread could not be made.
    #[error("cannot start the paced runtime: {0}")]
    Start(#[from] std::io::Error),
}

impl PacedRuntime {
    /// Starts the runtime on a thread of its own, paced to `speed`.
    pub fn start(speed: f64) -> Result<PacedRuntime, PaceError> {
        if !(speed.is_finite() && speed > 0.0) {
            return Err(PaceError::Speed(speed));
        }
        let pace = Arc::new(Pace::new(speed));
        let (stop_tx, stop_rx) = oneshot::channel::<()>();
        let (handle_tx, handle_rx) = std::sync::mpsc::channel();
        let pacer = pace.clone();
        std::thread::Builder::new()
            .name("rigd-paced".into())
            .spawn(move || {
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .start_paused(true)
                    .build();
                let runtime = match runtime {
                    Ok(r) => r,
                    Err(e) => {
                        let _ = handle_tx.send(Err(e));
                        return;
                    }
                };
                if handle_tx.send(Ok(runtime.handle().clone())).is_err() {
                    return;
                }
                runtime.block_on(async move {
                    tokio::select! {
                        _ = stop_rx => {}
                        _ = pace_loop(pacer) => {}
                    }
                });
                // Whatever is still spawned (firmware loops) goes with it;
                // nothing waits for a task that no longer matters.
                runtime.shutdown_background();
            })?;
        let handle = handle_rx
            .recv()
            .map_err(|_| std::io::Error::other("the paced runtime's thread ended at start"))??;
        Ok(PacedRuntime {
            handle,
            pace,
            stop: Some(stop_tx),
        })
    }

    /// Spawns tasks onto the runtime (from any thread or runtime).
    pub fn handle(&self) -> &tokio::runtime::Handle {
        &self.handle
    }

    /// The asked and achieved speed.
    pub fn pace(&self) -> Arc<Pace> {
        self.pace.clone()
    }
}

impl Drop for PacedRuntime {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}

/// Holds virtual time back to `asked` times the wall clock, forever.
async fn pace_loop(pace: Arc<Pace>) {
    let speed = pace.asked;
    let tick = TICK.mul_f64(speed);
    let mut anchor_wall = std::time::Instant::now();
    let mut anchor_virtual = tokio::time::Instant::now();
    let mut window = std::collections::VecDeque::new();
    window.push_back((anchor_wall, anchor_virtual));
    loop {
        // Virtual time reaches the tick when every task of the run waits;
        // work in between costs no virtual time at all.
        tokio::time::sleep(tick).await;
        let due = anchor_wall + anchor_virtual.elapsed().div_f64(speed);
        let now = std::time::Instant::now();
        if due > now {
            // Off the runtime's thread: ready tasks go on meanwhile, and
            // tokio does not advance virtual time while a blocking task runs.
            let wait = due - now;
            let _ = tokio::task::spawn_blocking(move || std::thread::sleep(wait)).await;
        } else if now - due > MAX_CATCH_UP {
            anchor_wall = now;
            anchor_virtual = tokio::time::Instant::now();
        }
        let sample = (std::time::Instant::now(), tokio::time::Instant::now());
        window.push_back(sample);
        while window
            .front()
            .is_some_and(|(w, _)| sample.0.duration_since(*w) > WINDOW)
            && window.len() > 2
        {
            window.pop_front();
        }
        if let Some(&(w0, v0)) = window.front() {
            let wall = sample.0.duration_since(w0).as_secs_f64();
            if wall > 0.0 {
                pace.record(sample.1.duration_since(v0).as_secs_f64() / wall);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block_on<T: Send + 'static>(
        rt: &PacedRuntime,
        fut: impl std::future::Future<Output = T> + Send + 'static,
    ) -> T {
        let (tx, rx) = std::sync::mpsc::channel();
        rt.handle().spawn(async move {
            let _ = tx.send(fut.await);
        });
        match rx.recv_timeout(Duration::from_secs(30)) {
            Ok(v) => v,
            Err(e) => panic!("the paced task did not finish: {e}"),
        }
    }

    #[test]
    fn a_paced_wait_takes_its_physical_time_over_the_speed_in_wall_time() {
        let rt = PacedRuntime::start(100.0).unwrap_or_else(|e| panic!("{e}"));
        let wall = std::time::Instant::now();
        let virt = block_on(&rt, async {
            let clock = crate::Clock::virtual_time();
            clock.sleep(Duration::from_secs(50)).await;
            clock.now_s()
        });
        let wall = wall.elapsed().as_secs_f64();
        assert_eq!(virt, 50.0, "physical time is the waits' exactly");
        // 50 s at 100x is 0.5 s of wall time: never less.
        assert!(wall >= 0.49, "ran ahead of the pace: {wall} s");
    }

    #[test]
    fn host_work_costs_no_physical_time_and_shows_as_falling_behind() {
        let rt = PacedRuntime::start(1000.0).unwrap_or_else(|e| panic!("{e}"));
        let pace = rt.pace();
        let (virt, behind) = block_on(&rt, async move {
            let clock = crate::Clock::virtual_time();
            let mut behind = false;
            for _ in 0..20 {
                // 50 ms of host work per 1 s physical wait: the host can
                // do at most about 20x, far below the asked 1000x.
                std::thread::sleep(Duration::from_millis(50));
                clock.sleep(Duration::from_secs(1)).await;
                behind |= pace.is_behind();
            }
            (clock.now_s(), behind)
        });
        assert_eq!(virt, 20.0, "host load became rig time");
        assert!(behind, "achieved {} of 1000x", rt.pace().achieved());
    }

    #[test]
    fn a_bad_speed_is_refused() {
        for s in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(matches!(PacedRuntime::start(s), Err(PaceError::Speed(_))));
        }
    }
}
