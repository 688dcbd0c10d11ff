#!/usr/bin/env bash
# One repeatable measurement of a GPU, for a session that is lent one for a few minutes.
#
#   scripts/gpu-check.sh --prepare        here (no GPU needed): release binaries, a small
#                                         trained avatar and the Vulkan loader, staged in
#                                         target/gpu-check/ (about 20 MB) to carry
#   scripts/gpu-check.sh [--out DIR]      on the lent machine: builds nothing, runs what
#                                         --prepare staged (under 8 minutes on an H200)
#   scripts/gpu-check.sh --short [--out DIR]
#                                         on lavapipe, in the test command: the test
#                                         build's binaries, the shared tiny run
#                                         ($DRAPE_TEST_RUN), tiny sizes, so the script
#                                         cannot rot
#
# Each mode runs `engine-bench sort`, `splat`, `composite` and `avatar` (512x512 and
# 1920x1080; frames in flight 1, 2, 3 with the device memory the avatar takes) and a
# short `drape train --preset paper --profile` (--short: the tiny run's config), then writes DIR/gpu-check.json (every
# benchmark's own JSON, the device and the commit) and DIR/gpu-check.md (one table per
# benchmark) through scripts/gpu-check-report.py. DIR defaults to $OUT (the device tool's
# folder that comes back), else target/gpu-check/out.
#
# On the lent machine, from the repository root, with target/gpu-check carried:
#   scripts/gpu-check.sh
# (it unpacks the carried Vulkan loader when the machine has none and points the loader at
# NVIDIA's driver when no driver is found).
set -euo pipefail
cd "$(dirname "$0")/.."

mode=full
out="${OUT:-}"
while (($#)); do
    case "$1" in
        --prepare) mode=prepare ;;
        --short) mode=short ;;
        --out)
            out="${2:?--out needs a directory}"
            shift
            ;;
        -h | --help)
            sed -n '2,26p' "$0" | sed 's/^# \{0,1\}//'
            exit 0
            ;;
        *)
            echo "gpu-check: unknown argument '$1' (see --help)" >&2
            exit 2
            ;;
    esac
    shift
done

stage=target/gpu-check

if [ "$mode" = prepare ]; then
    # What travels: stripped release binaries, a small avatar trained here with the quick
    # preset on lavapipe (its speed on a GPU is what is measured, not its quality), its
    # data, and Debian's Vulkan loader.
    cargo build --release --locked -p drape -p engine-bench
    rm -rf "$stage"
    mkdir -p "$stage/bin" "$stage/gl"
    # Stripped and gzipped: the repository and this folder travel within 64 MiB.
    for b in drape engine-bench; do
        cp "target/release/$b" "$stage/bin/"
        strip "$stage/bin/$b"
        gzip -9 "$stage/bin/$b"
    done
    target/release/drape synth --out "$stage/synth" --size 256 --frames 8 --cameras 3 >/dev/null
    DRAPE_DEVICE="${DRAPE_DEVICE:-llvmpipe}" target/release/drape train --data "$stage/synth" \
        --out "$stage/run" --preset quick --steps "${GPU_CHECK_STEPS:-300}" >/dev/null
    # Only the files rendering reads: checkpoints and previews stay behind.
    rm -f "$stage"/run/*.ply "$stage"/run/checkpoint.npz
    (cd "$stage/gl" && apt-get download libvulkan1 >/dev/null)
    git rev-parse --short HEAD >"$stage/commit"
    du -sh "$stage"
    echo "gpu-check: staged in $stage; on the lent machine run scripts/gpu-check.sh with carry [\"$stage\"]"
    exit 0
fi

if [ "$mode" = short ]; then
    bin=target/debug
    run="${DRAPE_TEST_RUN:?--short reads the shared tiny run: set DRAPE_TEST_RUN (scripts/test.sh does)}"
    data="$(dirname "$run")/synth"
    export DRAPE_DEVICE="${DRAPE_DEVICE:-llvmpipe}"
    sizes=64x64,96x64
    sort_n=4096
    splat=(--sizes 64x64 --counts 1000 --runs 10 --warmup 1)
    composite=(--sizes 64x64 --body 500 --cloth 200 --scene 300 --runs 1 --warmup 1)
    avatar=(--runs 1 --warmup 1 --train-steps 2 --train-warmup 1 --fit-steps 2 --flight-frames 4)
    # The paper preset's sizes are minutes a step on lavapipe: the tiny run's config.
    train=(--preset quick --config tests/fixtures/tiny-run.toml --steps 3)
    commit="$(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
else
    run="$stage/run"
    data="$stage/synth"
    [ -f "$stage/bin/engine-bench.gz" ] || {
        echo "gpu-check: $stage/bin/engine-bench.gz is missing: run scripts/gpu-check.sh --prepare here and carry $stage" >&2
        exit 1
    }
    bin="$(mktemp -d)"
    for b in drape engine-bench; do
        gzip -dc "$stage/bin/$b.gz" >"$bin/$b"
        chmod +x "$bin/$b"
    done
    # (grep without -q reads all its input: no SIGPIPE for ldconfig under pipefail.)
    if ! ldconfig -p | grep libvulkan.so.1 >/dev/null; then
        for f in "$stage"/gl/*.deb; do dpkg -x "$f" /; done
        ldconfig
    fi
    nvidia_icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
    if [ -z "${VK_DRIVER_FILES:-}" ] && [ -f "$nvidia_icd" ]; then
        export VK_DRIVER_FILES="$nvidia_icd"
    fi
    sizes=512x512,1920x1080
    sort_n=1000000
    splat=(--sizes 512x512,1920x1080 --counts 100000,1000000)
    composite=(--sizes 512x512,1920x1080)
    avatar=(--train-steps 20)
    train=(--preset paper --steps 200)
    commit="$(cat "$stage/commit" 2>/dev/null || git rev-parse --short HEAD)"
    # run.json names its data by the absolute path it had where --prepare trained it; the
    # library path (frames in flight) reads it from there: point it at this checkout's.
    python3 - "$run/run.json" "$(cd "$data" && pwd)" <<'PY'
import json, sys
path, data = sys.argv[1], sys.argv[2]
info = json.load(open(path))
info["data"] = data
json.dump(info, open(path, "w"), indent=2)
PY
fi
[ -n "$out" ] || out="$stage/out"
mkdir -p "$out"
results="$out/results"
rm -rf "$results"
mkdir -p "$results"

started=$SECONDS
bench() {
    local name="$1"
    shift
    echo "gpu-check: $name ($((SECONDS - started)) s)" >&2
    "$bin/engine-bench" "$@" --json >"$results/$name.json"
}
bench sort sort --n "$sort_n" --runs 10
bench splat splat "${splat[@]}"
bench composite composite "${composite[@]}"
bench avatar avatar "$run" --data "$data" --sizes "$sizes" --in-flight 1,2,3 "${avatar[@]}"

echo "gpu-check: drape train ${train[*]} --profile ($((SECONDS - started)) s)" >&2
train_out="$(mktemp -d)/run"
"$bin/drape" train --data "$data" --out "$train_out" "${train[@]}" --profile >"$results/train.log" 2>&1 || {
    cat "$results/train.log" >&2
    echo "gpu-check: drape train failed (its log above)" >&2
    exit 1
}
cp "$train_out/profile.json" "$results/train-profile.json"
cp "$train_out/profile.txt" "$results/train-profile.txt"
printf '%s\n' "${train[@]}" >"$results/train-args.txt"
rm -rf "$(dirname "$train_out")"

python3 scripts/gpu-check-report.py "$results" --commit "$commit" --mode "$mode" \
    --json "$out/gpu-check.json" --markdown "$out/gpu-check.md"
rm -rf "$results"
echo "gpu-check: wrote $out/gpu-check.json and $out/gpu-check.md in $((SECONDS - started)) s" >&2
