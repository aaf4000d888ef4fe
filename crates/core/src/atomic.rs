//! Whole-or-nothing file writes, for every file rigd writes: the bytes go
//! to a temporary file beside the target, are synced, then renamed over it,
//! so a failure or a crash never leaves a half-written file.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// A whole-or-nothing write that failed: which file, which step, and the
/// system's error.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {op}: {error}")]
pub struct WriteError {
    /// The file that failed: the temporary one for the writing steps.
    pub path: PathBuf,
    /// The step: `create`, `write`, `fsync`, `rename`.
    pub op: &'static str,
    /// The system's error (`StorageFull` when the disk is full).
    pub error: std::io::Error,
}

impl From<WriteError> for std::io::Error {
    fn from(e: WriteError) -> std::io::Error {
        std::io::Error::new(e.error.kind(), e.to_string())
    }
}

/// Writes `path` with what `fill` puts into the buffered temporary file
/// (which can also seek, for formats such as zip).
pub fn write_with(
    path: &Path,
    fill: impl FnOnce(&mut BufWriter<&File>) -> std::io::Result<()>,
) -> Result<(), WriteError> {
    write_through_temporary(path, true, fill)
}

/// Writes `bytes` to `path` whole or not at all, like [`write`], but
/// without the fsync: for a file that another synced record vouches for
/// (a frame, whose journal line carries its SHA-256) or that can be made
/// again (a cache). A crash may lose it; it never leaves half of it.
pub fn write_unsynced(path: &Path, bytes: &[u8]) -> Result<(), WriteError> {
    write_through_temporary(path, false, |out| out.write_all(bytes))
}

fn write_through_temporary(
    path: &Path,
    sync: bool,
    fill: impl FnOnce(&mut BufWriter<&File>) -> std::io::Result<()>,
) -> Result<(), WriteError> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let dir = parent_dir(path);
    let fail = |path: &Path, op: &'static str| {
        let path = path.to_path_buf();
        move |error| WriteError { path, op, error }
    };
    let name = path.file_name().ok_or_else(|| WriteError {
        path: path.to_path_buf(),
        op: "name",
        error: std::io::Error::new(std::io::ErrorKind::InvalidInput, "path has no file name"),
    })?;
    let tmp = dir.join(format!(
        ".{}.tmp.{}.{}",
        name.to_string_lossy(),
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let result = (|| {
        let file = File::create(&tmp).map_err(fail(&tmp, "create"))?;
        let mut out = BufWriter::new(&file);
        fill(&mut out).map_err(fail(&tmp, "write"))?;
        out.flush().map_err(fail(&tmp, "write"))?;
        drop(out);
        if sync {
            file.sync_all().map_err(fail(&tmp, "fsync"))?;
        }
        std::fs::rename(&tmp, path).map_err(fail(path, "rename"))
    })();
    if result.is_err() {
        // Best effort: the error that matters is the one returned.
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Writes `bytes` to `path`.
pub fn write(path: &Path, bytes: &[u8]) -> Result<(), WriteError> {
    write_with(path, |out| out.write_all(bytes))
}

/// Makes the renames in `path`'s folder durable (the file's own data is
/// synced by [`write_with`]); worth it for records a crash must not lose.
pub fn sync_parent(path: &Path) -> Result<(), WriteError> {
    let dir = parent_dir(path);
    File::open(&dir)
        .and_then(|d| d.sync_all())
        .map_err(|error| WriteError {
            path: dir,
            op: "fsync directory",
            error,
        })
}

/// The folder a path is in; `.` for a bare file name.
fn parent_dir(path: &Path) -> PathBuf {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_leaves_no_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.bin");
        write(&path, b"abc").unwrap();
        write(&path, b"defg").unwrap();
        sync_parent(&path).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"defg");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        let bad = dir.path().join("no-such-dir").join("y.bin");
        let e = write(&bad, b"abc").err().map(|e| (e.op, e.error.kind()));
        assert_eq!(e, Some(("create", std::io::ErrorKind::NotFound)));
        // A failing fill leaves neither the target nor a temporary file.
        let failed = dir.path().join("z.bin");
        assert!(write_with(&failed, |_| Err(std::io::Error::other("boom"))).is_err());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        write_unsynced(&path, b"hi").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"hi");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
