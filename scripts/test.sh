#!/usr/bin/env bash
# The project's one test command: what a newcomer runs, and what CI runs.
# It installs what the tests need, then checks formatting and lints, and runs
# every test of the workspace (unit, integration, property tests, doc tests).
set -euo pipefail
cd "$(dirname "$0")/.."

# Wall time by phase, printed at the end: where the minutes go.
phase_name="set-up: system packages, Python venv"
phase_start=$SECONDS
phase_times=""
end_phase() {
    phase_times+="$(printf '%6d s  %s' $((SECONDS - phase_start)) "$phase_name")"$'\n'
}
phase() {
    end_phase
    phase_name="$1"
    phase_start=$SECONDS
    echo "== $1"
}

# Debian packages, installed as root or through sudo.
apt_install() {
    if [ "$(id -u)" -eq 0 ]; then
        SUDO=""
    elif command -v sudo >/dev/null; then
        SUDO="sudo"
    else
        echo "error: this is not root (no sudo): install the Debian packages $*" >&2
        exit 1
    fi
    $SUDO apt-get update
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends "$@"
}

# System packages: the dashboard's browser test (tests/browser.rs) drives
# Debian's headless Chromium through chromedriver.
if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
    echo "== installing chromium and chromium-driver (for tests/browser.rs)"
    apt_install chromium chromium-driver
fi

# Processing on Slurm (tests/it/slurm.rs) starts a one-node cluster of
# Debian's slurm-wlm (slurmctld, slurmd, sbatch, squeue, sacct, scancel) and
# munge, all on 127.0.0.1 in a temporary folder, and stops it afterwards.
if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null \
    || ! command -v sbatch >/dev/null || ! command -v munged >/dev/null; then
    echo "== installing slurm-wlm and munge (for tests/it/slurm.rs)"
    apt_install slurm-wlm munge
fi

# GenICam cameras (tests/it/genicam.rs): rigd links Debian's Aravis 0.8
# (libaravis-dev; its pkg-config file also asks for libusb-1.0's) with the
# cargo feature `genicam`, and the tests run Aravis's fake GigE Vision camera
# (arv-fake-gv-camera-0.8, in aravis-tools) on 127.0.0.1.
if ! command -v arv-fake-gv-camera-0.8 >/dev/null || ! pkg-config --exists aravis-0.8 2>/dev/null; then
    echo "== installing aravis-tools and libaravis-dev (for tests/it/genicam.rs)"
    apt_install aravis-tools libaravis-dev libusb-1.0-0-dev pkg-config
fi

# Cameras through libgphoto2 (tests/it/gphoto2_transport.rs): rigd links
# Debian's libgphoto2 with the cargo feature `gphoto2`, whose bindings are
# generated at build time by bindgen (libclang-dev).
if ! pkg-config --exists libgphoto2 2>/dev/null || ! ls /usr/lib/llvm-*/lib/libclang*.so >/dev/null 2>&1; then
    echo "== installing libgphoto2-dev and libclang-dev (for tests/it/gphoto2_transport.rs)"
    apt_install libgphoto2-dev libclang-dev pkg-config
fi

# Camera files (tests/it/camera_files.rs): every DNG a simulated PTP run
# stores is opened by LibRaw's sample programs (raw-identify,
# unprocessed_raw), a raw decoder independent of the one rigd uses.
if ! command -v raw-identify >/dev/null || ! command -v unprocessed_raw >/dev/null; then
    echo "== installing libraw-bin (for tests/it/camera_files.rs)"
    apt_install libraw-bin
fi

# PTP/IP cameras (tests/it/gphoto2_peer.rs): the `gphoto2` tool, through
# libgphoto2's own ptp2 driver, lists and captures from rigd's simulated
# camera served over PTP/IP by `rigd sim serve`.
if ! command -v gphoto2 >/dev/null; then
    echo "== installing gphoto2 (for tests/it/gphoto2_peer.rs)"
    apt_install gphoto2
fi

# The Python the tests run, from a venv of their own (target/ is not
# committed), with the exact packages of tests/support/requirements.txt:
# pymodbus for tests/support/relay_module.py (a relay module),
# Schemathesis for tests/support/api_contract.py (the API contract), httpx
# and pytest for the Python client (clients/python). It is made again only
# when missing, broken, or made from another requirements file.
venv=target/test-venv
requirements=tests/support/requirements.txt
wanted="$(sha256sum "$requirements" | cut -d' ' -f1)"
if [ "$(cat "$venv/requirements.sha256" 2>/dev/null)" != "$wanted" ] \
    || ! "$venv/bin/python" -c "import pymodbus, schemathesis, httpx, pytest" 2>/dev/null; then
    echo "== creating $venv from $requirements"
    # Debian's python3 leaves venv's pip bootstrap (ensurepip) to python3-venv;
    # pyenv's CPython has it built in.
    if ! python3 -c 'import ensurepip, venv' 2>/dev/null; then
        apt_install python3 python3-venv
    fi
    python3 -m venv --clear "$venv"
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$requirements"
    echo "$wanted" > "$venv/requirements.sha256"
fi
export RIGD_TEST_PYTHON="$PWD/$venv/bin/python"

if ! command -v cargo >/dev/null; then
    echo "error: cargo not found; install Rust from https://rustup.rs" >&2
    exit 1
fi

# A build cache outside the clone, where this machine lets us keep one
# (/var/cache/rigd, as root or when writable): a later clone then builds
# only its own crates, not the dependencies again. A fresh machine has no
# cache and builds everything: slower, the same tests. A CARGO_TARGET_DIR
# the caller sets wins; a cache grown past 40 GiB (every clone path adds
# its own crates) is emptied first. The tests' scratch folders live in it
# too (target/tmp), so two runs of this script at once need two caches.
build_cache=/var/cache/rigd/target
if [ -z "${CARGO_TARGET_DIR:-}" ] && mkdir -p "$build_cache" 2>/dev/null && [ -w "$build_cache" ]; then
    if [ "$(du -sk "$build_cache" | cut -f1)" -gt $((40 * 1024 * 1024)) ]; then
        echo "== emptying the build cache $build_cache (over 40 GiB)"
        rm -rf "$build_cache"
        mkdir -p "$build_cache"
    fi
    export CARGO_TARGET_DIR="$build_cache"
    echo "== building in $build_cache"
fi

# The compiler's incremental state is keyed by the sources' path: a clone at
# a new path recompiles rigd's crates in full (about 7 minutes on two cores).
# As root, the clone is bind-mounted at one fixed path and built there, so
# the next clone recompiles only what changed. Without the right to mount
# (or while another live run holds that path) it is built where it is. A
# mount left by a run that was killed is taken over: the pid file tells a
# live run's mount from a dead one's.
stable_src=/var/cache/rigd/src
mounted=""
if [ "${CARGO_TARGET_DIR:-}" = "$build_cache" ] && [ "$(id -u)" -eq 0 ] \
    && [ "$PWD" != "$stable_src" ] && mkdir -p "$stable_src"; then
    holder="$(cat "$stable_src.pid" 2>/dev/null || true)"
    if mountpoint -q "$stable_src" && ! { [ -n "$holder" ] && kill -0 "$holder" 2>/dev/null; }; then
        umount --lazy "$stable_src" || true
    fi
    if ! mountpoint -q "$stable_src" && mount --bind "$PWD" "$stable_src" 2>/dev/null; then
        echo "$$" > "$stable_src.pid"
        mounted="$stable_src"
        cd "$stable_src"
        echo "== building this clone as $stable_src (a bind mount, removed at exit)"
    fi
fi
log=""
cleanup() {
    if [ -n "$log" ]; then
        rm -f "$log"
    fi
    if [ -n "$mounted" ]; then
        cd /
        umount --lazy "$mounted" || true
        rm -f "$mounted.pid"
    fi
}
trap cleanup EXIT

# Disk space: a build and the tests' scratch folders need about 15 GiB. On a
# full disk the tests do not fail fast: disk full pauses a run, and a test
# that waits for the run to complete waits out its whole time limit. So a
# short disk is named here, before anything is built; an old build cache is
# emptied first when that makes the room.
free_gib() { df -Pk "$1" | awk 'NR == 2 { print int($4 / 1048576) }'; }
need_gib=15
scratch="${CARGO_TARGET_DIR:-target}"
mkdir -p "$scratch"
if [ "$(free_gib "$scratch")" -lt "$need_gib" ] && [ -n "${CARGO_TARGET_DIR:-}" ] \
    && [ "$CARGO_TARGET_DIR" = "$build_cache" ]; then
    echo "== emptying the build cache $build_cache (the disk has less than $need_gib GiB free)"
    rm -rf "$build_cache"
    mkdir -p "$build_cache"
fi
for dir in "$scratch" "${TMPDIR:-/tmp}"; do
    if [ "$(free_gib "$dir")" -lt "$need_gib" ]; then
        echo "error: $(free_gib "$dir") GiB free on the disk of $dir; the build and the tests need $need_gib GiB" >&2
        df -h "$dir" >&2
        exit 1
    fi
done

phase "cargo fmt --check"
cargo fmt --all -- --check
phase "cargo clippy --features genicam,gphoto2"
cargo clippy --workspace --all-targets --locked --features genicam,gphoto2 -- -D warnings
# The hardware path builds without the simulator (no rigd-sim in the build),
# and without Aravis or libgphoto2 (no `genicam`, no `gphoto2` feature).
phase "cargo clippy --no-default-features (rigd without the simulator, Aravis or libgphoto2)"
cargo clippy -p rigd --no-default-features --lib --bins --locked -- -D warnings
phase "cargo test --features genicam,gphoto2 --no-run (build the tests)"
cargo test --workspace --locked --features genicam,gphoto2 --no-run
phase "cargo test --features genicam,gphoto2 (run the tests)"
log="$(mktemp)"
cargo test --workspace --locked --features genicam,gphoto2 2>&1 | tee "$log"
# One closing line for the whole suite (cargo ends with the doc tests' own count).
awk '/^test result:/ { for (i = 1; i <= NF; i++) { if ($(i+1) ~ /^passed/) p += $i; if ($(i+1) ~ /^failed/) f += $i } }
     END { printf "tests: %d passed, %d failed\n", p, f }' "$log"
end_phase
printf '== wall time by phase\n%s%6d s  in all\n' "$phase_times" "$SECONDS"
