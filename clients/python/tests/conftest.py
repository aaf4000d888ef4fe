"""Fixtures: rigd daemons of our own (temporary data directory, a free port on
127.0.0.1), started from ``$RIGD`` or ``rigd`` on PATH, always stopped."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator, List, Optional

import httpx
import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))  # the package, without installing it

from rigd_client import Client, RigdError  # noqa: E402

#: A fast simulated rig: a 4-image run takes well under a second of wall time.
SIM_SPEED = "5000"
#: The fault the fault daemon injects into every new run: the 2nd transfer disconnects.
FAULT = "camera:transfer:2:disconnect"
#: The first run of a fresh daemon takes long on a busy machine (see README).
FIRST_RUN_TIMEOUT = 90.0


def rigd_binary() -> str:
    """``$RIGD``, else ``rigd`` on PATH; fails (never skips) without one."""
    env = os.environ.get("RIGD")
    if env:
        if not (os.path.isfile(env) and os.access(env, os.X_OK)):
            pytest.fail(f"RIGD={env} is not an executable file", pytrace=False)
        return env
    found = shutil.which("rigd")
    if not found:
        pytest.fail("no rigd binary: set RIGD=/path/to/rigd or put rigd on PATH", pytrace=False)
    return found


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Daemon:
    """One ``rigd serve --sim`` process."""

    def __init__(self, data: Path, extra: Optional[List[str]] = None, port: Optional[int] = None) -> None:
        self.binary = rigd_binary()
        self.data = data
        self.extra = list(extra or [])
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = data.parent / f"{data.name}.log"
        self.proc: Optional[subprocess.Popen] = None

    def start(self, timeout: float = 30.0) -> "Daemon":
        cmd = [self.binary, "serve", "--sim", "--listen", f"127.0.0.1:{self.port}", "--data", str(self.data),
               "--sim-speed", SIM_SPEED, *self.extra]
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                pytest.fail(f"rigd exited with {self.proc.returncode}: {self.log.read_text()}", pytrace=False)
            try:
                if httpx.get(self.url + "/api/v1/health", timeout=1.0).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.05)
        self.stop()
        pytest.fail(f"rigd did not answer /health within {timeout:g} s: {self.log.read_text()}", pytrace=False)
        raise AssertionError("unreachable")

    @property
    def token(self) -> str:
        return (self.data / "token").read_text().strip()

    def client(self, **kw) -> Client:
        kw.setdefault("data_dir", self.data)
        return Client(self.url, **kw)

    def stop(self, grace: float = 5.0) -> None:
        """SIGTERM (the daemon pauses its run and exits), SIGKILL after ``grace`` s.

        The grace is short on purpose: a daemon still solving its built-in plans
        takes 10-15 s to exit on SIGTERM (README, "Known issues"), and these
        data directories are thrown away.
        """
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(grace)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)


def _daemon(tmp: Path, name: str, extra: Optional[List[str]] = None) -> Iterator[Daemon]:
    d = Daemon(tmp / name, extra)
    try:
        yield d.start()
    finally:
        d.stop()


@pytest.fixture(scope="session")
def fault_daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    """A daemon whose every new run pauses at its 2nd frame transfer.

    It drives the small VirTex rig (one camera, three lamps): a second Bonn
    daemon solving its plans beside the main one slows both for a minute.
    """
    yield from _daemon(tmp_path_factory.mktemp("fault"), "data",
                       ["--profile", "virtex-photometric-stereo", "--sim-fault", FAULT])


@pytest.fixture(scope="session")
def daemon(tmp_path_factory: pytest.TempPathFactory, fault_daemon: Daemon) -> Iterator[Daemon]:
    """The main daemon: the simulated Bonn rig, a trade-off report in its data
    directory, and the fault daemon as its peer ``faulty``."""
    tmp = tmp_path_factory.mktemp("main")
    data = tmp / "data"
    (data / "tradeoff").mkdir(parents=True)
    # A report `rigd tradeoff` made for this rig: computing one takes minutes.
    shutil.copy(HERE / "data" / "tradeoff.json", data / "tradeoff" / "tradeoff.json")
    peers = tmp / "peers.toml"
    peers.write_text(f'[[peer]]\nname = "faulty"\nurl = "{fault_daemon.url}"\n'
                     f'token_file = "{fault_daemon.data / "token"}"\n')
    yield from _daemon(tmp, "data", ["--peers", str(peers)])


@pytest.fixture(scope="session")
def client(daemon: Daemon) -> Iterator[Client]:
    with daemon.client() as c:
        yield c


@pytest.fixture(scope="session")
def fault_client(fault_daemon: Daemon) -> Iterator[Client]:
    with fault_daemon.client() as c:
        yield c


def tiny_plan(name: str = "tiny") -> dict:
    """Two directions, all paired with all: 4 images."""
    return {"name": name, "directions": [{"theta_deg": 0, "phi_deg": 0}, {"theta_deg": 45, "phi_deg": 90}]}


def long_plan(name: str = "long") -> dict:
    """16 directions, 256 images: a few wall seconds at the test speed, to pause and abort."""
    return {"name": name, "directions": [{"theta_deg": t, "phi_deg": p} for t in (0, 20, 40, 60) for p in (0, 90, 180, 270)]}


def settle(c: Client, timeout: float = 30.0) -> None:
    """Ends whatever run is active (aborting it) so the next test starts on a free rig."""
    deadline = time.monotonic() + timeout
    while True:
        page = c.runs()
        if page.active is None:
            return
        view = c.run(page.active)
        if view["state"] not in ("completed", "failed", "aborted"):
            try:
                c.abort(page.active)
            except RigdError:
                pass  # it ended by itself meanwhile (409), or is ending: the loop looks again
        if time.monotonic() > deadline:
            raise AssertionError(f"run {page.active} would not end: {view}")
        time.sleep(0.1)


def run_example(name: str, *args: str, timeout: float = 120.0, env: Optional[dict] = None) -> subprocess.CompletedProcess:
    """Runs examples/NAME with this interpreter, bounded."""
    return subprocess.run(
        [sys.executable, str(ROOT / "examples" / name), *args],
        capture_output=True, text=True, timeout=timeout, env={**os.environ, **(env or {})},
    )
