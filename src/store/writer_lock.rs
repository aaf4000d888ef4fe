//! One writer per run directory, and one processor per run. Whoever
//! captures into a run or resumes it holds an exclusive advisory lock
//! (`flock`) on the run's folder for as long as it writes; whoever
//! processes it (a `rigd process` command, a process job, the registration
//! during a capture) holds one on its `processed/` folder. A second writer
//! or processor, in this process or another, is refused at once instead of
//! interleaving its files with the first's. The kernel drops a lock when
//! its holder exits, killed or not, so a crashed run is never left locked.

use std::fs::File;
use std::path::Path;

use super::StoreError;

/// A run directory's writer lock, held until dropped.
#[derive(Debug)]
pub struct WriterLock {
    _dir: File,
}

impl WriterLock {
    /// Takes the lock of the run directory `root`; [`StoreError::Busy`]
    /// when another writer holds it.
    pub fn acquire(root: &Path) -> Result<WriterLock, StoreError> {
        match lock_folder(root)? {
            Some(dir) => Ok(WriterLock { _dir: dir }),
            None => Err(StoreError::Busy(root.display().to_string())),
        }
    }

    /// Whether a writer holds the lock of `root` now. A folder that cannot
    /// be opened has no writer.
    pub fn is_held(root: &Path) -> bool {
        matches!(WriterLock::acquire(root), Err(StoreError::Busy(_)))
    }
}

/// A run's processing lock (on `RUN/processed/`), held until dropped.
/// Slurm's array tasks write parts into the folder under their
/// coordinator's lock and take none themselves.
#[derive(Debug)]
pub struct ProcessingLock {
    _dir: File,
}

impl ProcessingLock {
    /// Takes the processing lock of the run at `root`, making its
    /// `processed/` folder if there is none; [`StoreError::ProcessingBusy`]
    /// when another processor holds it. A folder with neither a run nor a
    /// `processed/` folder (an imported dataset has only that) is
    /// [`StoreError::NoRun`], and nothing is made there.
    pub fn acquire(root: &Path) -> Result<ProcessingLock, StoreError> {
        let dir = super::processed::processed_dir(root);
        if !dir.is_dir() && !root.join(super::RUN_FILE).is_file() {
            return Err(StoreError::NoRun(root.display().to_string()));
        }
        match std::fs::create_dir(&dir) {
            Err(e) if e.kind() != std::io::ErrorKind::AlreadyExists => {
                return Err(StoreError::Io {
                    path: dir,
                    op: "create directory",
                    error: e,
                })
            }
            _ => {}
        }
        match lock_folder(&dir)? {
            Some(dir) => Ok(ProcessingLock { _dir: dir }),
            None => Err(StoreError::ProcessingBusy(root.display().to_string())),
        }
    }
}

/// An exclusive lock on the folder `dir`, or None when another holder has
/// it.
fn lock_folder(dir: &Path) -> Result<Option<File>, StoreError> {
    let io = |op, error| StoreError::Io {
        path: dir.to_path_buf(),
        op,
        error,
    };
    let file = File::open(dir).map_err(|e| io("open directory", e))?;
    #[cfg(unix)]
    {
        use std::os::fd::AsRawFd;
        // SAFETY: flock on a descriptor this function owns; the lock
        // lives as long as the descriptor. (`File::try_lock` does the same
        // from Rust 1.89, above this crate's minimum.)
        let rc = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if rc != 0 {
            let error = std::io::Error::last_os_error();
            if error.kind() == std::io::ErrorKind::WouldBlock {
                return Ok(None);
            }
            return Err(io("lock", error));
        }
    }
    Ok(Some(file))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_writer_is_refused_until_the_first_lets_go() {
        let dir = tempfile::tempdir().expect("tempdir");
        assert!(!WriterLock::is_held(dir.path()));
        let first = WriterLock::acquire(dir.path()).expect("the first writer");
        assert!(matches!(
            WriterLock::acquire(dir.path()),
            Err(StoreError::Busy(_))
        ));
        assert!(WriterLock::is_held(dir.path()));
        drop(first);
        assert!(!WriterLock::is_held(dir.path()));
        assert!(WriterLock::acquire(dir.path()).is_ok());
    }

    #[test]
    fn a_second_processor_is_refused_and_the_writer_is_not_in_its_way() {
        let dir = tempfile::tempdir().expect("tempdir");
        assert!(matches!(
            ProcessingLock::acquire(dir.path()),
            Err(StoreError::NoRun(_))
        ));
        assert!(!dir.path().join("processed").exists(), "nothing made");
        std::fs::write(dir.path().join(super::super::RUN_FILE), "{}").expect("run.json");
        let _writer = WriterLock::acquire(dir.path()).expect("the capture");
        let first = ProcessingLock::acquire(dir.path()).expect("the first processor");
        assert!(dir.path().join("processed").is_dir());
        assert!(matches!(
            ProcessingLock::acquire(dir.path()),
            Err(StoreError::ProcessingBusy(_))
        ));
        drop(first);
        assert!(ProcessingLock::acquire(dir.path()).is_ok());
    }
}
