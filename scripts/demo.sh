#!/usr/bin/env bash
# The main job on the embedded default data: generate the synthetic sequence (NeuMan
# and ZJU-MoCap layouts) into target/demo-data, train the avatar on it with the quick
# preset (docs/results.md has its speed per device), and print the held-out metrics. The run
# directory target/demo-run holds the held-out sheets and tables (eval/; `drape eval`,
# `drape animate` and `drape edit` open the run again),
# a novel pose (novel_pose.png), the log, the metrics and a posed PLY.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
cargo build --release --locked --quiet -p drape
# Data that lacks NeuMan's sparse/images.txt or the HUGS SAM masks drape synth writes is made again.
if [ ! -f target/demo-data/neuman/sparse/images.txt ] || [ ! -d target/demo-data/neuman/4d_humans/sam_segmentations ]; then
    rm -rf target/demo-data
    ./target/release/drape synth --out target/demo-data
fi
rm -rf target/demo-run
./target/release/drape train --data target/demo-data --out target/demo-run --preset quick "$@"
