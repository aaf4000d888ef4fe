//! One writer per run directory. Whoever captures into a run or resumes it
//! holds an exclusive advisory lock (`flock`) on the run's folder for as
//! long as it writes. A second writer, in this process or another, is
//! refused at once instead of interleaving its journal lines and states
//! with the first's. The kernel drops the lock when its holder exits, killed
//! or not, so a crashed run is never left locked.

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
        let dir = File::open(root).map_err(|error| StoreError::Io {
            path: root.to_path_buf(),
            op: "open directory",
            error,
        })?;
        #[cfg(unix)]
        {
            use std::os::fd::AsRawFd;
            // SAFETY: flock on a descriptor this function owns; the lock
            // lives as long as the descriptor.
            let rc = unsafe { libc::flock(dir.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
            if rc != 0 {
                let error = std::io::Error::last_os_error();
                return Err(if error.kind() == std::io::ErrorKind::WouldBlock {
                    StoreError::Busy(root.display().to_string())
                } else {
                    StoreError::Io {
                        path: root.to_path_buf(),
                        op: "lock",
                        error,
                    }
                });
            }
        }
        Ok(WriterLock { _dir: dir })
    }

    /// Whether a writer holds the lock of `root` now. A folder that cannot
    /// be opened has no writer.
    pub fn is_held(root: &Path) -> bool {
        matches!(WriterLock::acquire(root), Err(StoreError::Busy(_)))
    }
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
}
