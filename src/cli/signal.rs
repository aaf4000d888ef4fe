//! Ctrl-C and SIGTERM during `rigd run` (the engine finishes the frame in
//! flight and stops, leaving the run resumable) and during processing on
//! Slurm (the jobs are cancelled).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use rigd::engine::command::Command;
use tokio::sync::mpsc::Sender;
use tokio::task::JoinHandle;

/// Whether a signal detached the run.
pub struct Interrupt {
    fired: Arc<AtomicBool>,
    listener: JoinHandle<()>,
}

impl Interrupt {
    /// A signal arrived and the engine was told to detach.
    pub fn fired(&self) -> bool {
        self.fired.load(Ordering::SeqCst)
    }

    /// The run is over: later signals end the process as usual.
    pub fn stop_listening(&self) {
        self.listener.abort();
    }
}

/// Listens for SIGINT and SIGTERM; the first one detaches the engine.
pub fn detach_on_signal(commands: Sender<Command>) -> Interrupt {
    let fired = Arc::new(AtomicBool::new(false));
    let flag = fired.clone();
    let listener = tokio::spawn(async move {
        rigd::server::wait_for_signal().await;
        flag.store(true, Ordering::SeqCst);
        eprintln!("interrupted: finishing the frame in flight, then stopping (resumable)");
        let _ = commands.send(Command::Detach).await;
    });
    Interrupt { fired, listener }
}

/// A flag that the first SIGINT or SIGTERM sets, for work that runs
/// outside a runtime (processing on Slurm checks it between two looks at
/// the queue).
pub fn flag_on_signal() -> Arc<AtomicBool> {
    let fired = Arc::new(AtomicBool::new(false));
    let flag = fired.clone();
    let listening = std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || {
            let Ok(runtime) = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
            else {
                return;
            };
            runtime.block_on(rigd::server::wait_for_signal());
            flag.store(true, Ordering::SeqCst);
            eprintln!("interrupted: cancelling the Slurm jobs");
        });
    if let Err(e) = listening {
        tracing::warn!("cannot listen for signals: {e}");
    }
    fired
}
