//! Bounded reads, for every file rigd reads because someone named it (a
//! profile, plan, scene or its images, a peers or configuration file, a
//! token file) and every file the daemon serves: only a regular file is
//! read, and only up to a size limit, so a device (`/dev/zero`), a FIFO
//! or a huge file can neither hang the caller nor fill its memory. The
//! errors name the file and never quote its content. Hand-written text is
//! read past a byte order mark ([`strip_bom`]).

use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};

/// Largest configuration-like text file read: profiles, scenes, peers
/// files, the daemon's configuration and token files.
pub const TEXT_LIMIT: u64 = 4 << 20;
/// Largest plan file read (an explicit list of tens of thousands of pairs
/// fits in a few MiB).
pub const PLAN_LIMIT: u64 = 64 << 20;
/// Largest image a scene names (a heightfield or albedo PNG).
pub const IMAGE_LIMIT: u64 = 256 << 20;

/// A bounded read that failed: the file, and why.
#[derive(Debug, thiserror::Error)]
#[error("{}: {reason}", path.display())]
pub struct ReadError {
    /// The file asked for.
    pub path: PathBuf,
    /// Why it was not read.
    pub reason: ReadFailure,
}

/// Why a bounded read failed. The messages never quote the file's content.
#[derive(Debug, thiserror::Error)]
pub enum ReadFailure {
    /// The system refused to open or read it (missing, no permission, …).
    #[error("cannot read: {0}")]
    Io(std::io::Error),
    /// It is not a regular file: a directory, a device, a FIFO or a socket.
    #[error("not a regular file (a {0}); expected a file")]
    NotRegular(&'static str),
    /// It holds more than the limit.
    #[error("larger than {limit} bytes; refused")]
    TooLarge {
        /// The limit, bytes.
        limit: u64,
    },
    /// [`read_text`]: it is not UTF-8 text.
    #[error("not UTF-8 text")]
    NotText,
}

impl ReadError {
    /// The I/O error's kind when the read failed in the system (a missing
    /// file is `NotFound`); None for the other failures.
    pub fn io_kind(&self) -> Option<std::io::ErrorKind> {
        match &self.reason {
            ReadFailure::Io(e) => Some(e.kind()),
            _ => None,
        }
    }
}

/// An I/O error with the whole message; a file that is there but cannot
/// be used is `InvalidData`.
impl From<ReadError> for std::io::Error {
    fn from(e: ReadError) -> std::io::Error {
        let kind = match &e.reason {
            ReadFailure::Io(io) => io.kind(),
            // The file is there but unusable: bad data, not a failing system.
            ReadFailure::NotRegular(_) | ReadFailure::NotText | ReadFailure::TooLarge { .. } => {
                std::io::ErrorKind::InvalidData
            }
        };
        std::io::Error::new(kind, e.to_string())
    }
}

/// Reads all of `path`, a regular file of at most `limit` bytes.
///
/// The file is opened without blocking (a FIFO with no writer would
/// otherwise block the open) and checked on the open handle, so a file
/// swapped for a device after a check is refused too.
pub fn read_bounded(path: &Path, limit: u64) -> Result<Vec<u8>, ReadError> {
    let fail = |reason| ReadError {
        path: path.to_path_buf(),
        reason,
    };
    let file = open_nonblocking(path).map_err(|e| fail(ReadFailure::Io(e)))?;
    let meta = file.metadata().map_err(|e| fail(ReadFailure::Io(e)))?;
    if !meta.is_file() {
        return Err(fail(ReadFailure::NotRegular(kind_of(&meta.file_type()))));
    }
    if meta.len() > limit {
        return Err(fail(ReadFailure::TooLarge { limit }));
    }
    // The size can change while reading (and /proc files report 0): one
    // byte past the limit is what tells.
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    file.take(limit.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(|e| fail(ReadFailure::Io(e)))?;
    if bytes.len() as u64 > limit {
        return Err(fail(ReadFailure::TooLarge { limit }));
    }
    Ok(bytes)
}

/// [`read_bounded`] for UTF-8 text.
pub fn read_text(path: &Path, limit: u64) -> Result<String, ReadError> {
    let bytes = read_bounded(path, limit)?;
    String::from_utf8(bytes).map_err(|_| ReadError {
        path: path.to_path_buf(),
        reason: ReadFailure::NotText,
    })
}

#[cfg(unix)]
fn open_nonblocking(path: &Path) -> std::io::Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)
}

#[cfg(not(unix))]
fn open_nonblocking(path: &Path) -> std::io::Result<File> {
    File::open(path)
}

fn kind_of(t: &std::fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return "FIFO";
        }
        if t.is_char_device() {
            return "character device";
        }
        if t.is_block_device() {
            return "block device";
        }
        if t.is_socket() {
            return "socket";
        }
    }
    if t.is_dir() {
        "directory"
    } else {
        "special file"
    }
}

/// `text` without a leading UTF-8 byte order mark (U+FEFF). Some editors
/// (Notepad among them) start every file they save with one, and neither
/// TOML nor JSON allows it, so each loader of a hand-written file passes
/// its text through here first.
pub fn strip_bom(text: &str) -> &str {
    text.strip_prefix('\u{feff}').unwrap_or(text)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    #[test]
    fn only_a_leading_byte_order_mark_goes() {
        assert_eq!(strip_bom("\u{feff}a = 1"), "a = 1");
        assert_eq!(strip_bom("a = 1"), "a = 1");
        assert_eq!(strip_bom("a = \"\u{feff}\""), "a = \"\u{feff}\"");
        assert_eq!(strip_bom(""), "");
    }

    #[test]
    fn a_regular_file_within_the_limit_is_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.toml");
        std::fs::write(&path, "name = \"x\"\n").unwrap();
        assert_eq!(read_text(&path, 64).unwrap(), "name = \"x\"\n");
        assert_eq!(read_bounded(&path, 11).unwrap().len(), 11);
    }

    #[test]
    fn devices_fifos_directories_and_big_files_are_refused_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("fifo");
        let made = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap();
        assert!(made.success());
        let big = dir.path().join("big");
        std::fs::write(&big, vec![b'a'; 100]).unwrap();
        let started = Instant::now();
        for (path, expect) in [
            (
                Path::new("/dev/zero"),
                "not a regular file (a character device)",
            ),
            (fifo.as_path(), "not a regular file (a FIFO)"),
            (dir.path(), "not a regular file (a directory)"),
            (big.as_path(), "larger than 99 bytes"),
        ] {
            let e = read_bounded(path, 99).unwrap_err();
            let text = e.to_string();
            assert!(text.contains(expect), "{text}");
            assert!(text.starts_with(&path.display().to_string()), "{text}");
        }
        // /proc files say they are empty: the limit still holds.
        let e = read_bounded(Path::new("/proc/self/maps"), 10).unwrap_err();
        assert!(
            matches!(e.reason, ReadFailure::TooLarge { limit: 10 }),
            "{e}"
        );
        assert!(started.elapsed() < Duration::from_secs(2));
        let missing = read_bounded(&dir.path().join("none"), 10).unwrap_err();
        assert_eq!(missing.io_kind(), Some(std::io::ErrorKind::NotFound));
        std::fs::write(&big, [0xff, 0xfe, b'a']).unwrap();
        let e = read_text(&big, 99).unwrap_err().to_string();
        assert!(e.ends_with("not UTF-8 text"), "{e}");
    }
}
