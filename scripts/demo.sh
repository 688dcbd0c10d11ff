#!/usr/bin/env bash
# The main job on the embedded default data. For now: sort a million random keys on
# the GPU (lavapipe without a GPU) and check them against the CPU.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
cargo run --release --locked --quiet -p drape -- demo "$@"
