//! Ctrl-C and SIGTERM during `rigd run`: the engine finishes the frame in
//! flight and stops, leaving the run resumable.

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
