#!/usr/bin/env bash
# Fuzzes every loader (fuzz/fuzz_targets, libFuzzer through cargo-fuzz, nightly) for a
# given time each, one target after another, and prints a table: executions, corpus
# growth, and findings (crash files under fuzz/artifacts/<target>/).
#
#   scripts/fuzz.sh [SECONDS_PER_TARGET (default 120)] [TARGET...]
#
# Findings go to fuzz/artifacts/<target>/; once fixed, copy each into
# fuzz/regressions/<target>/ so that `cargo test` (trainer/tests/trainer/fuzz_corpus.rs)
# replays it forever. New corpus entries land in fuzz/corpus/<target>/; minimise them
# (cargo fuzz cmin TARGET) before committing. Not part of the test command.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${1:-120}"
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    targets=(ply obj npy npz pickle colmap camera_json config_toml checkpoint image motion smpl)
fi
command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz --locked
rustup toolchain list | grep -q '^nightly' || rustup toolchain install nightly --profile minimal
cd fuzz
cargo +nightly fuzz build -O
mkdir -p logs
printf '%-12s %8s %12s %10s %8s %s\n' target seconds executions exec/s corpus findings
for t in "${targets[@]}"; do
    mkdir -p "corpus/$t" "artifacts/$t"
    before=$(find "artifacts/$t" -type f | wc -l)
    # -rss_limit_mb / -malloc_limit_mb: an allocation beyond 2 GiB is a finding (the
    # loaders check sizes before allocating), as is a run past 10 s on one input.
    cargo +nightly fuzz run -O "$t" "corpus/$t" -- \
        -max_total_time="$seconds" -rss_limit_mb=4096 -malloc_limit_mb=2048 -timeout=10 \
        -max_len=65536 -print_final_stats=1 >"logs/$t.log" 2>&1 || true
    runs=$(grep -oE 'stat::number_of_executed_units: *[0-9]+' "logs/$t.log" | grep -oE '[0-9]+$' || echo 0)
    per=$(( runs / (seconds > 0 ? seconds : 1) ))
    after=$(find "artifacts/$t" -type f | wc -l)
    printf '%-12s %8s %12s %10s %8s %s\n' "$t" "$seconds" "$runs" "$per" "$(find "corpus/$t" -type f | wc -l)" "$((after - before)) new (fuzz/artifacts/$t)"
done
