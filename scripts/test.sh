#!/usr/bin/env bash
# The project's one test command: what a newcomer runs, and what CI runs.
# It installs what the tests need, then checks formatting and lints, and runs
# every test of the workspace (unit, integration, property tests, doc tests).
set -euo pipefail
cd "$(dirname "$0")/.."

# System packages: the dashboard's browser test (tests/browser.rs) drives
# Debian's headless Chromium through chromedriver.
if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
    echo "== installing chromium and chromium-driver (for tests/browser.rs)"
    if [ "$(id -u)" -eq 0 ]; then
        SUDO=""
    elif command -v sudo >/dev/null; then
        SUDO="sudo"
    else
        echo "error: chromium and chromedriver are missing and this is not root (no sudo):" >&2
        echo "       install the Debian packages chromium and chromium-driver" >&2
        exit 1
    fi
    $SUDO apt-get update
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium chromium-driver
fi

if ! command -v cargo >/dev/null; then
    echo "error: cargo not found; install Rust from https://rustup.rs" >&2
    exit 1
fi

echo "== cargo fmt --check"
cargo fmt --all -- --check
echo "== cargo clippy"
cargo clippy --workspace --all-targets --locked -- -D warnings
# The hardware path builds without the simulator (no rigd-sim in the build).
echo "== cargo clippy --no-default-features (rigd without the simulator)"
cargo clippy -p rigd --no-default-features --lib --bins --locked -- -D warnings
echo "== cargo test"
log="$(mktemp)"
trap 'rm -f "$log"' EXIT
cargo test --workspace --locked 2>&1 | tee "$log"
# One closing line for the whole suite (cargo ends with the doc tests' own count).
awk '/^test result:/ { for (i = 1; i <= NF; i++) { if ($(i+1) ~ /^passed/) p += $i; if ($(i+1) ~ /^failed/) f += $i } }
     END { printf "tests: %d passed, %d failed\n", p, f }' "$log"
