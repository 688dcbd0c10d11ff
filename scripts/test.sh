#!/usr/bin/env bash
# The whole test suite, as CI runs it (the steps as they print):
#  1. formatting (rustfmt, every crate);
#  2. rebuild the SPIR-V with rust-gpu and fail, naming the module, if any byte
#     differs from what is committed;
#  3. the shader builder's own test (a changed kernel source fails the check);
#  4. lints (clippy -D warnings on the workspace's targets, run by the test build itself;
#     clippy.toml keeps file writes to drape-io), then every workspace test on lavapipe
#     with validation layers on (any validation message fails the test that caused it);
#  5. the engine's GPU tests again with DRAPE_FORCE_STAGING=1: uploads, readbacks and
#     buffer poisoning through staging copies, the path a discrete GPU takes (lavapipe
#     maps every buffer otherwise).
# A test that needs a device feature reports "SKIPPED: ..." without it; on lavapipe
# DRAPE_EXPECT_FEATURES turns such a skip into a failure (CI's device lost a feature).
set -euo pipefail
cd "$(dirname "$0")/.."

# Each step's wall time, printed when the next starts and at the end.
started=$SECONDS
step_started=$SECONDS
step() {
    if [ -n "${step_name:-}" ]; then
        echo "== took $((SECONDS - step_started)) s: $step_name"
    fi
    step_name="$1"
    step_started=$SECONDS
    [ -z "$1" ] || echo "== $1"
}

step "0/5 set-up (Vulkan, lavapipe, validation layers, the shader toolchain, numpy)"
scripts/setup.sh --shaders
# A real client of the NumPy files the project writes (pickled annots.npy, .npz).
if ! python3 -c "import numpy" 2>/dev/null; then
    echo "setup: installing numpy for Python 3"
    python3 -m pip install -q numpy
fi
# The independent reference for the neural ops: PyTorch (CPU) in target/torch-venv. Its
# first install (mostly download) runs while steps 1 to 3 do; step 4 waits for it.
mkdir -p target
torch_log=target/torch-env.log
scripts/torch-env.sh >"$torch_log.out" 2>"$torch_log" &
torch_pid=$!
# numpy 1.x (pickles as it writes them) and kubernetes-validate: target/clients-venv.
clients_log=target/clients-env.log
scripts/clients-env.sh >"$clients_log.out" 2>"$clients_log" &
clients_pid=$!
export DRAPE_DEVICE="${DRAPE_DEVICE:-llvmpipe}"
# Incremental caches would be written once per test binary and never reused on a
# clean clone: disk CI does not have to spare.
export CARGO_INCREMENTAL=0
if [ "$DRAPE_DEVICE" = llvmpipe ]; then
    export DRAPE_EXPECT_FEATURES="${DRAPE_EXPECT_FEATURES:-float-atomics,timestamps,subgroup-raster,subgroup-gemm}"
fi

step "1/5 formatting: rustfmt --check (the lints run with the test build, step 4)"
# The pinned toolchain (rust-toolchain.toml) brings rustfmt and clippy. The kernels and
# the shader builder are formatted with the same rustfmt.
cargo fmt --all --check
(cd shaders-rs/kernels && cargo fmt --check)
rustfmt --edition 2021 --check tools/shader-builder/src/main.rs tools/shader-builder/tests/*.rs
(cd fuzz && cargo fmt --check)

step "2/5 SPIR-V freshness (rust-gpu rebuild; the first build of the backend takes minutes)"
# rust-gpu's backend (rustc_codegen_spirv and the SPIRV-Tools C++ it links: about 15
# minutes on 2 cores) and `core` / spirv-std for the SPIR-V target are built once per
# machine into a cache outside the clone (about 3 GB; DRAPE_SHADER_CACHE moves it), as
# cargo-gpu caches the backend, and reused by later clones. What this clone's source
# makes (the builder, drape-shared, the kernels) is compiled again every run: their
# fingerprints are removed first, so that no file time (a copy that kept old ones, at a
# path used before) can make an earlier build look fresh. One run at a time holds the
# cache (steps 2 and 3 share its outputs).
shader_cache="${DRAPE_SHADER_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/drape/shader-builder}"
mkdir -p "$shader_cache"
shader_cache="$(cd "$shader_cache" && pwd)"
exec 9>"$shader_cache/.lock"
flock 9
(cd "$shader_cache" && find . -type d -name fingerprint \( -path '*/build/shader-builder/*' \
    -o -path '*/build/drape-shared/*' -o -path '*/build/drape-kernels/*' \) -prune -exec rm -rf {} +)
(cd tools/shader-builder && CARGO_TARGET_DIR="$shader_cache" cargo run --release --locked --quiet -- --check)

step "3/5 shader builder tests"
(cd tools/shader-builder && CARGO_TARGET_DIR="$shader_cache" cargo test --release --locked)
exec 9>&-

if ! wait "$torch_pid"; then
    cat "$torch_log" >&2
    echo "test: the PyTorch reference environment could not be installed (log above)" >&2
    exit 1
fi
cat "$torch_log" >&2
DRAPE_TORCH_PYTHON="$(tail -1 "$torch_log.out")"
export DRAPE_TORCH_PYTHON
if ! wait "$clients_pid"; then
    cat "$clients_log" >&2
    echo "test: the numpy 1.x / kubernetes-validate environment could not be installed (log above)" >&2
    exit 1
fi
DRAPE_CLIENTS_PYTHON="$(tail -1 "$clients_log.out")"
export DRAPE_CLIENTS_PYTHON
# The cluster manifest (scripts/cluster/), validated offline against Kubernetes' schemas.
scripts/cluster/check-k8s-manifest.sh "$DRAPE_CLIENTS_PYTHON"

step "4/5 lints and workspace tests on $DRAPE_DEVICE with validation"
# Clippy (-D warnings) runs as the test build compiles each workspace crate: clippy-driver
# as the workspace's rustc wrapper is what `cargo clippy` runs, here with code generation,
# so the lints cost no separate check of the workspace (a `cargo clippy` step took 6
# minutes on 2 cores). The price: clippy-driver compiles with MIR optimisations off and
# without the MIR passes that check raw-pointer dereferences for null and alignment at
# run time (std's own checks, slice::from_raw_parts's included, stay), so the workspace's
# tests run without those two checks. Exported for every cargo call below, whose builds
# must match this one's (another wrapper would rebuild the workspace). Clippy covers the
# workspace only: the kernels build for SPIR-V on the builder's nightly, without clippy.
RUSTC_WORKSPACE_WRAPPER="$(rustup which clippy-driver)"
export RUSTC_WORKSPACE_WRAPPER
export CLIPPY_ARGS="-D__CLIPPY_HACKERY__warnings__CLIPPY_HACKERY__"
# Build first, every target under the test profile with the tests' feature resolution, so
# that `cargo test` below finds it all built: the shared run is trained with this build's
# drape binary, and the C ABI tests link libdrape.so from it (`cargo test` builds rlibs
# only; a separate `cargo build` would compile every dependency again).
cargo build --workspace --all-targets --profile test --locked
# The one small trained run the tests share (tests/fixtures/tiny-run.toml on a 32-px
# synthetic sequence), trained once here for the embedding, C ABI, viewer and
# engine-bench tests.
test_run=target/test-run
rm -rf "$test_run"
target/debug/drape synth --out "$test_run/synth" --size 32 --frames 4 --cameras 2 >/dev/null
target/debug/drape train --data "$test_run/synth" --out "$test_run/run" --config tests/fixtures/tiny-run.toml >/dev/null
DRAPE_TEST_RUN="$PWD/$test_run/run"
export DRAPE_TEST_RUN
cargo test --workspace --locked
# The script a lent GPU runs (scripts/gpu-check.sh), on lavapipe at tiny sizes with this
# build's binaries and the shared run, so that it cannot rot between GPU sessions.
if ! scripts/gpu-check.sh --short --out target/gpu-check-short >target/gpu-check-short.log 2>&1; then
    cat target/gpu-check-short.log >&2
    echo "test: scripts/gpu-check.sh --short failed (its log above)" >&2
    exit 1
fi
tail -1 target/gpu-check-short.log

step "5/5 the engine's GPU tests through staging buffers (DRAPE_FORCE_STAGING=1)"
# The filters pick the modules of the two GPU test binaries (engine: tests/tests/engine,
# trainer: trainer/tests/trainer) that move buffers between host and device.
# The two binaries step 4 built, run directly: `cargo test --test engine --test trainer`
# would resolve features for those targets alone and recompile the trainer (45 s).
binaries=$(cargo test --workspace --locked --no-run --message-format=json 2>target/no-run.log | python3 -c '
import json, os, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["kind"] == ["test"] and m["target"]["name"] in ("engine", "trainer"):
        print(os.path.dirname(m["manifest_path"]) + "\t" + m["executable"])
') || { cat target/no-run.log >&2; echo "test: cargo test --no-run failed (its log above)" >&2; exit 1; }
[ "$(echo "$binaries" | wc -l)" = 2 ] || { echo "test: expected the engine and trainer test binaries, got: $binaries" >&2; exit 1; }
# A transfer goes through one staging buffer whatever its size, so the tests whose
# subject is size (millions of keys, the 100k-row GEMMs, the densest tiles) ran in step 4
# and are skipped here: through staging they would add minutes and test nothing more.
heavy="sort_len_4m sort_len_16m scan_len_4m scan_len_16m mlp_gpu_matches_cpu_reference
    twenty_million_intersections sixty_thousand_splats hundred_thousand_gaussians
    forty_thousand_splats image_of_2048_by_2048 through_a_dense_walk"
skips=()
for name in $heavy; do skips+=(--skip "$name"); done
while IFS=$'\t' read -r dir exe; do
    (cd "$dir" && DRAPE_FORCE_STAGING=1 "$exe" \
        runtime:: scan:: sort:: splat_gpu:: splat_robustness:: splat_gradients:: nn:: ssim:: sizes:: \
        composite:: skinning:: "${skips[@]}")
done <<<"$binaries"
step ""
echo "== all steps passed in $((SECONDS - started)) s"
