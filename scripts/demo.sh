#!/usr/bin/env bash
# The main job on the embedded default data. Until training lands: generate the
# synthetic sequence (NeuMan and ZJU-MoCap layouts) into target/demo-data, and check
# the GPU stack (a 1M-pair sort on the GPU, lavapipe without one, against the CPU).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
cargo build --release --locked --quiet -p drape
./target/release/drape synth --out target/demo-data "$@"
./target/release/drape demo
