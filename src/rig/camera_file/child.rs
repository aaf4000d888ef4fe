//! Camera files decoded in a child process: rigd itself, run as `rigd
//! internal decode-frame`, reads the file on its stdin under an
//! address-space limit and writes the image back ([`super::wire`]). The
//! decoders allocate what a file claims before they check the claim, and a
//! failed allocation aborts the process that made it: here that is the
//! child, and the parent gets an error naming what happened (the signal,
//! the exit status, the deadline, garbage). A hung child is killed at its
//! deadline.
//!
//! [`BatchDecoder`] keeps one child for many files (the property test of
//! damaged files sends it hundreds of thousands); a child that dies is
//! started again for the next file.

use std::ffi::OsString;
use std::io::{self, BufReader, BufWriter, Read, Write};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, ExitStatus, Stdio};
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use super::wire::{self, WireError};
use super::{decoders, CameraFileError, CameraImage};

/// The environment variable naming the rigd binary that decodes, for a
/// process that is not rigd itself (tests, benches, tools linking the
/// library); rigd uses its own binary.
pub const DECODER_ENV: &str = "RIGD_DECODER";

/// The address space a decoder child may use by default: a 100-megapixel
/// raw file's samples and the decoders' copies of them fit many times.
pub const DEFAULT_MEMORY: u64 = 4 << 30;

/// How long a decoder child may take by default; a 60-megapixel lossless
/// raw file decodes in well under a second.
pub const DEFAULT_DEADLINE: Duration = Duration::from_secs(60);

/// The largest file a child reads (as [`rigd_core::read::IMAGE_LIMIT`]).
const MAX_FILE: u64 = rigd_core::read::IMAGE_LIMIT;

/// The pipes' capacity to and from a child: Linux's default most.
const PIPE_SIZE: libc::c_int = 1 << 20;

/// How much of a child's stderr is kept for the error message.
const STDERR_KEPT: usize = 4096;

/// How a decoder child is started and bounded.
#[derive(Debug, Clone)]
pub struct Decoder {
    program: PathBuf,
    args: Vec<OsString>,
    memory: u64,
    deadline: Duration,
}

/// The rigd binary the library finds: [`DECODER_ENV`]; else this process,
/// when it is rigd; else a `rigd` beside this program or one folder up
/// (cargo puts test and bench binaries in `target/*/deps/`, rigd in
/// `target/*/`).
fn rigd_program() -> Result<PathBuf, String> {
    static PROGRAM: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    PROGRAM
        .get_or_init(|| {
            if let Some(p) = std::env::var_os(DECODER_ENV).filter(|p| !p.is_empty()) {
                return Ok(PathBuf::from(p));
            }
            let exe = std::env::current_exe()
                .map_err(|e| format!("cannot find this program's own binary: {e}"))?;
            if exe.file_name().is_some_and(|n| n == "rigd") {
                // The running binary even if its file was replaced since
                // (an upgrade): the child is the same rigd as the parent.
                let own = Path::new("/proc/self/exe");
                return Ok(if own.exists() { own.to_path_buf() } else { exe });
            }
            let dir = exe.parent();
            let found = [dir, dir.and_then(Path::parent)]
                .into_iter()
                .flatten()
                .map(|d| d.join("rigd"))
                .find(|p| p.is_file());
            found.ok_or_else(|| {
                format!(
                    "{} is not rigd and no rigd binary is beside it: set {DECODER_ENV} \
                         to the rigd binary that decodes camera files",
                    exe.display()
                )
            })
        })
        .clone()
}

impl Decoder {
    /// The rigd binary as the decoder, with the default limits.
    pub fn rigd() -> Result<Decoder, CameraFileError> {
        let program = rigd_program().map_err(CameraFileError::NoDecoder)?;
        Ok(Decoder::command(
            program,
            [OsString::from("internal"), OsString::from("decode-frame")],
        ))
    }

    /// `program` with `args` as the decoder (tests stand in children that
    /// misbehave); the limits are appended as `--memory BYTES`, and
    /// `--batch` for a [`BatchDecoder`].
    pub fn command(program: impl Into<PathBuf>, args: impl IntoIterator<Item = OsString>) -> Self {
        Decoder {
            program: program.into(),
            args: args.into_iter().collect(),
            memory: DEFAULT_MEMORY,
            deadline: DEFAULT_DEADLINE,
        }
    }

    /// The same decoder with an address-space limit of `bytes`.
    pub fn with_memory(mut self, bytes: u64) -> Self {
        self.memory = bytes;
        self
    }

    /// The same decoder with a deadline of `deadline` a file.
    pub fn with_deadline(mut self, deadline: Duration) -> Self {
        self.deadline = deadline;
        self
    }

    /// The most samples a child can have held: two bytes each in its
    /// address space.
    fn max_samples(&self) -> u64 {
        self.memory / 2
    }

    fn spawn(&self, batch: bool, size: Option<usize>) -> Result<Child, CameraFileError> {
        let mut cmd = Command::new(&self.program);
        cmd.args(&self.args)
            .arg("--memory")
            .arg(self.memory.to_string());
        if batch {
            cmd.arg("--batch");
        }
        if let Some(size) = size {
            // The child reads the file into a buffer of that size at once.
            cmd.arg("--size").arg(size.to_string());
        }
        // Its own process group: a deadline kills whatever it started too.
        // Its messages are a line for the parent's error, not a backtrace.
        cmd.env("RUST_BACKTRACE", "0")
            .process_group(0)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .inspect(|child| {
                // A frame is megabytes: wide pipes cross it in fewer steps.
                use std::os::fd::AsRawFd;
                let fds = [
                    child.stdin.as_ref().map(|p| p.as_raw_fd()),
                    child.stdout.as_ref().map(|p| p.as_raw_fd()),
                ];
                for fd in fds.into_iter().flatten() {
                    // SAFETY: fcntl(2) on a pipe this process holds open;
                    // a refusal (over the system's pipe-max-size) leaves
                    // the pipe as it was.
                    unsafe {
                        libc::fcntl(fd, libc::F_SETPIPE_SZ, PIPE_SIZE);
                    }
                }
            })
            .map_err(|e| {
                CameraFileError::NoDecoder(format!("cannot start {}: {e}", self.program.display()))
            })
    }

    /// Decodes `bytes` in a child of its own.
    pub fn decode(&self, bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
        let mut child = self.spawn(false, Some(bytes.len()))?;
        let pid = child.id();
        let (Some(mut stdin), Some(stdout), Some(stderr)) =
            (child.stdin.take(), child.stdout.take(), child.stderr.take())
        else {
            kill(pid);
            let _ = child.wait();
            return Err(CameraFileError::NoDecoder("the child has no pipes".into()));
        };
        let (record, timed_out, status, stderr) = std::thread::scope(|s| {
            // A child that stops reading (it died, or hangs) ends the
            // write with an error; what it answered says the rest.
            s.spawn(move || {
                let _ = stdin.write_all(bytes);
            });
            let errors = s.spawn(move || tail_of(stderr));
            let (disarm, armed) = mpsc::channel::<()>();
            let deadline = self.deadline;
            let watchdog = s.spawn(move || {
                let expired = armed.recv_timeout(deadline) == Err(RecvTimeoutError::Timeout);
                if expired {
                    kill(pid);
                }
                expired
            });
            let mut out = BufReader::with_capacity(1 << 20, stdout);
            let mut record = wire::read_record(&mut out, self.max_samples());
            if record.is_ok() {
                let mut more = [0u8; 1];
                if !matches!(out.read(&mut more), Ok(0)) {
                    record = Err(WireError::Garbage("more bytes after its answer".into()));
                }
            }
            if record.is_err() {
                // Not reaped yet, so the pid is still this child's.
                kill(pid);
            }
            drop(out);
            // Reaping waits for the watchdog, so it can never kill a
            // process that took the pid over.
            wait_exited(pid);
            let _ = disarm.send(());
            let timed_out = watchdog.join().unwrap_or(false);
            let status = child.wait();
            let stderr = errors.join().unwrap_or_default();
            (record, timed_out, status, stderr)
        });
        self.answer(record, timed_out, status, &stderr)
    }

    /// What a child's answer means: its record when it exited cleanly,
    /// else what happened to it.
    fn answer(
        &self,
        record: Result<Result<CameraImage, CameraFileError>, WireError>,
        timed_out: bool,
        status: io::Result<ExitStatus>,
        stderr: &str,
    ) -> Result<CameraImage, CameraFileError> {
        if timed_out {
            return Err(CameraFileError::Crashed(format!(
                "did not answer within {} s and was killed",
                self.deadline.as_secs_f64()
            )));
        }
        // rigd killed a child that answered garbage: the garbage is the news.
        if let Err(e @ WireError::Garbage(_)) = &record {
            return Err(CameraFileError::Crashed(e.to_string()));
        }
        let status = status.map_err(|e| CameraFileError::Crashed(format!("was lost: {e}")))?;
        if !status.success() {
            return Err(CameraFileError::Crashed(self.ended(status, stderr)));
        }
        record.map_err(|e| CameraFileError::Crashed(e.to_string()))?
    }

    /// How a child that did not exit cleanly ended, in words.
    fn ended(&self, status: ExitStatus, stderr: &str) -> String {
        use std::os::unix::process::ExitStatusExt;
        // The allocation that failed, else the first thing it said.
        let lines = || stderr.lines().map(str::trim).filter(|l| !l.is_empty());
        let said = lines()
            .find(|l| l.starts_with("memory allocation of"))
            .or_else(|| lines().next())
            .map(|l| format!(": {l}"))
            .unwrap_or_default();
        match (status.signal(), status.code()) {
            (Some(sig), _) => {
                let why = if sig == libc::SIGABRT {
                    format!(
                        " (it aborted: an allocation over its {} MiB address-space limit does)",
                        self.memory >> 20
                    )
                } else {
                    String::new()
                };
                format!(
                    "was killed by signal {sig} ({}){why}{said}",
                    signal_name(sig)
                )
            }
            (None, Some(code)) => format!("exited with status {code}{said}"),
            (None, None) => format!("ended as {status}{said}"),
        }
    }

    /// A child kept for many files.
    pub fn batch(&self) -> BatchDecoder {
        BatchDecoder {
            decoder: self.clone(),
            running: None,
            started: 0,
        }
    }
}

/// The usual name of a signal.
fn signal_name(sig: i32) -> &'static str {
    match sig {
        libc::SIGABRT => "SIGABRT",
        libc::SIGKILL => "SIGKILL",
        libc::SIGSEGV => "SIGSEGV",
        libc::SIGBUS => "SIGBUS",
        libc::SIGILL => "SIGILL",
        libc::SIGFPE => "SIGFPE",
        libc::SIGTERM => "SIGTERM",
        libc::SIGPIPE => "SIGPIPE",
        _ => "a signal",
    }
}

/// Sends SIGKILL to a child that has not been reaped, and to its process
/// group (whatever it started).
fn kill(pid: u32) {
    if let Ok(pid) = libc::pid_t::try_from(pid) {
        // SAFETY: kill(2) takes plain integers; the caller holds the
        // child unreaped, so its pid (and the group named by it) is still
        // its own.
        unsafe {
            libc::kill(-pid, libc::SIGKILL);
            libc::kill(pid, libc::SIGKILL);
        }
    }
}

/// Waits until child `pid` has ended, leaving it to be reaped.
fn wait_exited(pid: u32) {
    loop {
        // SAFETY: waitid(2) writes into the zeroed siginfo it is given.
        let rc = unsafe {
            let mut info: libc::siginfo_t = std::mem::zeroed();
            libc::waitid(
                libc::P_PID,
                pid as libc::id_t,
                &mut info,
                libc::WEXITED | libc::WNOWAIT,
            )
        };
        if rc == 0 || io::Error::last_os_error().kind() != io::ErrorKind::Interrupted {
            return;
        }
    }
}

/// The last [`STDERR_KEPT`] bytes a stream says, read to its end.
fn tail_of(mut stream: impl Read) -> String {
    let mut kept: Vec<u8> = Vec::new();
    let mut buf = [0u8; 4096];
    while let Ok(n) = stream.read(&mut buf) {
        if n == 0 {
            break;
        }
        kept.extend_from_slice(&buf[..n]);
        if kept.len() > 2 * STDERR_KEPT {
            kept.drain(..kept.len() - STDERR_KEPT);
        }
    }
    let start = kept.len().saturating_sub(STDERR_KEPT);
    String::from_utf8_lossy(&kept[start..]).into_owned()
}

/// One decoder child kept running for many files; see [`Decoder::batch`].
pub struct BatchDecoder {
    decoder: Decoder,
    running: Option<Running>,
    started: usize,
}

struct Running {
    child: Child,
    stdin: BufWriter<ChildStdin>,
    stdout: BufReader<ChildStdout>,
    stderr: Arc<Mutex<String>>,
    errors: std::thread::JoinHandle<()>,
}

impl BatchDecoder {
    /// How many children were started so far (one more after each that
    /// died).
    pub fn children_started(&self) -> usize {
        self.started
    }

    fn start(&mut self) -> Result<&mut Running, CameraFileError> {
        if self.running.is_none() {
            let mut child = self.decoder.spawn(true, None)?;
            let (Some(stdin), Some(stdout), Some(stderr)) =
                (child.stdin.take(), child.stdout.take(), child.stderr.take())
            else {
                kill(child.id());
                let _ = child.wait();
                return Err(CameraFileError::NoDecoder("the child has no pipes".into()));
            };
            let said = Arc::new(Mutex::new(String::new()));
            let into = Arc::clone(&said);
            let errors = std::thread::spawn(move || {
                let text = tail_of(stderr);
                *rigd_core::sync::lock(&into) = text;
            });
            self.started += 1;
            self.running = Some(Running {
                child,
                stdin: BufWriter::with_capacity(1 << 20, stdin),
                stdout: BufReader::with_capacity(1 << 20, stdout),
                stderr: said,
                errors,
            });
        }
        self.running
            .as_mut()
            .ok_or_else(|| CameraFileError::NoDecoder("the child did not start".into()))
    }

    /// Decodes `bytes` in the kept child (started first if none runs).
    pub fn decode(&mut self, bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
        let deadline = self.decoder.deadline;
        let max_samples = self.decoder.max_samples();
        let running = self.start()?;
        let pid = running.child.id();
        let (record, timed_out) = std::thread::scope(|s| {
            let (disarm, armed) = mpsc::channel::<()>();
            let watchdog = s.spawn(move || {
                let expired = armed.recv_timeout(deadline) == Err(RecvTimeoutError::Timeout);
                if expired {
                    kill(pid);
                }
                expired
            });
            let record = match wire::write_request(&mut running.stdin, bytes) {
                Ok(()) => wire::read_record(&mut running.stdout, max_samples),
                Err(e) => Err(WireError::Io(e)),
            };
            let _ = disarm.send(());
            (record, watchdog.join().unwrap_or(false))
        });
        match record {
            Ok(answer) if !timed_out => answer,
            record => {
                // The child is of no more use: end it and say why.
                let Some(mut running) = self.running.take() else {
                    return Err(CameraFileError::Crashed("was lost".into()));
                };
                kill(pid);
                let status = running.child.wait();
                let _ = running.errors.join();
                let stderr = rigd_core::sync::lock(&running.stderr).clone();
                self.decoder.answer(record, timed_out, status, &stderr)
            }
        }
    }
}

impl Drop for BatchDecoder {
    fn drop(&mut self) {
        if let Some(mut running) = self.running.take() {
            // End of input ends the child's loop.
            drop(running.stdin);
            let _ = running.child.wait();
            let _ = running.errors.join();
        }
    }
}

/// Kept decoder children for many files decoded by several threads (a
/// processing step reading a hardware run's frames): a thread takes an
/// idle child, or starts one, and gives it back after its file. The
/// children end with the pool.
pub struct DecoderPool {
    decoder: Decoder,
    idle: Mutex<Vec<BatchDecoder>>,
}

impl DecoderPool {
    /// A pool of children of `decoder`.
    pub fn new(decoder: Decoder) -> Self {
        DecoderPool {
            decoder,
            idle: Mutex::new(Vec::new()),
        }
    }

    /// Decodes `bytes` in an idle child of the pool, or a new one.
    pub fn decode(&self, bytes: &[u8]) -> Result<CameraImage, CameraFileError> {
        let kept = rigd_core::sync::lock(&self.idle).pop();
        let mut child = kept.unwrap_or_else(|| self.decoder.batch());
        let result = child.decode(bytes);
        rigd_core::sync::lock(&self.idle).push(child);
        result
    }
}

/// Sets this process's address-space limit to `bytes` (lower only).
fn limit_memory(bytes: u64) -> io::Result<()> {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit/setrlimit read and write the struct they are given.
    if unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut lim) } != 0 {
        return Err(io::Error::last_os_error());
    }
    let limit = bytes.min(lim.rlim_max);
    let lowered = libc::rlimit {
        rlim_cur: limit,
        rlim_max: limit,
    };
    if unsafe { libc::setrlimit(libc::RLIMIT_AS, &lowered) } != 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

/// The child's side (`rigd internal decode-frame`): lowers its address
/// space to `memory` bytes, then decodes the file on stdin and writes the
/// record to stdout; with `batch`, file after file (each prefixed by its
/// length) until stdin ends. `size`, when given, is the file's length.
pub fn serve(memory: u64, batch: bool, size: Option<u64>) -> io::Result<()> {
    limit_memory(memory)?;
    let mut input = io::stdin().lock();
    let mut out = BufWriter::with_capacity(1 << 20, io::stdout().lock());
    if batch {
        while let Some(bytes) = wire::read_request(&mut input, MAX_FILE)? {
            wire::write_record(&mut out, &decoders::decode(&bytes))?;
        }
        return Ok(());
    }
    let mut bytes = Vec::with_capacity(size.unwrap_or(0).min(MAX_FILE + 1) as usize);
    input.take(MAX_FILE + 1).read_to_end(&mut bytes)?;
    let result = if bytes.len() as u64 > MAX_FILE {
        Err(CameraFileError::Corrupt {
            format: "camera".into(),
            message: format!("the file is larger than {} MiB", MAX_FILE >> 20),
        })
    } else {
        decoders::decode(&bytes)
    };
    wire::write_record(&mut out, &result)
}
