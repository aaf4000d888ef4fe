//! Progress on the terminal: the run reporter of `rigd run` (a bar on a
//! terminal, plain log lines otherwise), the progress lines of long
//! processing, and durations as people read them.

use std::io::IsTerminal;
use std::time::{Duration, Instant};

use rigd::engine::{EventKind, RunEvent};
use tokio::sync::broadcast::Receiver;
use tokio::task::JoinHandle;

/// How `rigd run` shows its progress.
#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Progress {
    /// A bar on a terminal, log lines otherwise.
    Auto,
    /// A progress bar.
    Bar,
    /// A log line every 5 % or 30 s, and every state change.
    Log,
    /// Nothing but the summary.
    None,
}

/// Seconds as `1h02m03s`.
pub fn hms(s: f64) -> String {
    let s = s.max(0.0).round() as u64;
    if s >= 3600 {
        format!("{}h{:02}m{:02}s", s / 3600, (s % 3600) / 60, s % 60)
    } else if s >= 60 {
        format!("{}m{:02}s", s / 60, s % 60)
    } else {
        format!("{s}s")
    }
}

/// Progress of a long processing step on stderr, as `rigd run` shows its
/// own: a bar on a terminal; otherwise a plain line at every 5 % and at
/// least every 30 s, so a log never gets carriage returns.
pub fn progress_line(what: &'static str) -> impl Fn(usize, usize) + Sync {
    let bar = std::io::stderr().is_terminal().then(|| {
        let bar = indicatif::ProgressBar::new(0);
        bar.set_style(
            indicatif::ProgressStyle::with_template(&format!(
                "{what}: {{bar:40.cyan/blue}} {{pos}}/{{len}}  wall {{elapsed_precise}} eta {{eta}}"
            ))
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar
    });
    let logged = std::sync::Mutex::new((u64::MAX, Instant::now()));
    let started = Instant::now();
    move |done: usize, total: usize| {
        if let Some(bar) = &bar {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
            if done == total {
                bar.finish();
            }
            return;
        }
        let pct = done as u64 * 100 / (total as u64).max(1);
        let mut last = rigd_core::sync::lock(&logged);
        if pct / 5 != last.0 / 5 || last.1.elapsed() > Duration::from_secs(30) || done == total {
            if (pct, done == total) == (last.0, true) {
                return;
            }
            let elapsed = started.elapsed().as_secs_f64();
            let eta = if done > 0 {
                format!(
                    ", eta {}",
                    hms(elapsed / done as f64 * (total - done.min(total)) as f64)
                )
            } else {
                String::new()
            };
            eprintln!(
                "{what}: {done}/{total} ({pct}%), wall {}{eta}",
                hms(elapsed)
            );
            *last = (pct, Instant::now());
        }
    }
}

/// Reports a run's events on stderr until the engine drops its sender:
/// frames against `frames_total` (starting at `frames_done`), with the
/// physical time left until `end_estimate` (physical seconds).
pub fn report_run(
    mut events: Receiver<RunEvent>,
    progress: Progress,
    frames_total: usize,
    frames_done: usize,
    end_estimate: f64,
) -> JoinHandle<()> {
    let mode = match progress {
        Progress::Auto if std::io::stderr().is_terminal() => Progress::Bar,
        Progress::Auto => Progress::Log,
        m => m,
    };
    let bar = (mode == Progress::Bar).then(|| {
        let bar = indicatif::ProgressBar::new(frames_total as u64);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{bar:40.cyan/blue} {pos}/{len} frames  {msg}  wall {elapsed_precise} eta {eta}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar.set_position(frames_done as u64);
        bar
    });
    tokio::spawn(async move {
        let mut last_log = Instant::now();
        let mut last_pct = u64::MAX;
        loop {
            let ev = match events.recv().await {
                Ok(ev) => ev,
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => continue,
                Err(_) => break,
            };
            match &ev.kind {
                EventKind::Step {
                    frames_done,
                    frames_total,
                    ..
                } => {
                    let eta = hms(end_estimate - ev.t_s);
                    let msg = format!("physical {} (eta {eta})", hms(ev.t_s));
                    if let Some(bar) = &bar {
                        bar.set_position(*frames_done as u64);
                        bar.set_message(msg);
                    } else if mode == Progress::Log {
                        let pct = *frames_done as u64 * 100 / (*frames_total as u64).max(1);
                        if pct / 5 != last_pct / 5 || last_log.elapsed() > Duration::from_secs(30) {
                            eprintln!(
                                "progress: {frames_done}/{frames_total} frames ({pct}%), {msg}"
                            );
                            last_pct = pct;
                            last_log = Instant::now();
                        }
                    }
                }
                EventKind::State { to, reason, .. } => {
                    let line = match reason {
                        Some(r) => format!("state: {to} ({r})"),
                        None => format!("state: {to}"),
                    };
                    match &bar {
                        Some(bar) => bar.println(line),
                        None if mode != Progress::None => eprintln!("{line}"),
                        None => {}
                    }
                }
                EventKind::Retry {
                    device,
                    reason,
                    attempt,
                } => {
                    let line = format!("retry {attempt} on {device}: {reason}");
                    match &bar {
                        Some(bar) => bar.println(line),
                        None if mode != Progress::None => eprintln!("{line}"),
                        None => {}
                    }
                }
                EventKind::Refused { .. } => {}
            }
        }
        if let Some(bar) = bar {
            bar.finish_and_clear();
        }
    })
}
