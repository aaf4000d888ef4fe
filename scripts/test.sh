#!/usr/bin/env bash
# The project's one test command: what a newcomer runs, and what CI runs.
# It installs what the tests need, then checks formatting and lints, and runs
# every test of the workspace (unit, integration, property tests, doc tests).
set -euo pipefail
cd "$(dirname "$0")/.."

# System packages: none yet. The dashboard's browser test will add Debian's
# chromium and chromium-driver here (apt-get install -y chromium chromium-driver).

if ! command -v cargo >/dev/null; then
    echo "error: cargo not found; install Rust from https://rustup.rs" >&2
    exit 1
fi

echo "== cargo fmt --check"
cargo fmt --all -- --check
echo "== cargo clippy"
cargo clippy --workspace --all-targets --locked -- -D warnings
echo "== cargo test"
cargo test --workspace --locked
