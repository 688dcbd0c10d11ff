#!/usr/bin/env bash
# The whole test suite, as CI runs it:
#  1. rebuild the SPIR-V with rust-gpu and fail, naming the module, if any byte
#     differs from what is committed;
#  2. the shader builder's own test (a changed kernel source fails the check);
#  3. every workspace test on lavapipe with validation layers on (any validation
#     message fails the test that caused it);
#  4. the engine's GPU tests again with DRAPE_FORCE_STAGING=1: uploads, readbacks and
#     buffer poisoning through staging copies, the path a discrete GPU takes (lavapipe
#     maps every buffer otherwise).
# A test that needs a device feature reports "SKIPPED: ..." without it; on lavapipe
# DRAPE_EXPECT_FEATURES turns such a skip into a failure (CI's device lost a feature).
set -euo pipefail
cd "$(dirname "$0")/.."

scripts/setup.sh --shaders
# A real client of the NumPy files the project writes (pickled annots.npy, .npz).
if ! python3 -c "import numpy" 2>/dev/null; then
    echo "setup: installing numpy for Python 3"
    python3 -m pip install -q numpy
fi
# The independent reference for the neural ops: PyTorch (CPU) in target/torch-venv.
DRAPE_TORCH_PYTHON="$(scripts/torch-env.sh | tail -1)"
export DRAPE_TORCH_PYTHON
export DRAPE_DEVICE="${DRAPE_DEVICE:-llvmpipe}"
# Incremental caches would be written once per test binary and never reused on a
# clean clone: disk CI does not have to spare.
export CARGO_INCREMENTAL=0
if [ "$DRAPE_DEVICE" = llvmpipe ]; then
    export DRAPE_EXPECT_FEATURES="${DRAPE_EXPECT_FEATURES:-float-atomics,timestamps,subgroup-raster}"
fi

echo "== 1/4 SPIR-V freshness (rust-gpu rebuild; the first build of the backend takes minutes)"
(cd tools/shader-builder && cargo run --release --locked --quiet -- --check)

echo "== 2/4 shader builder tests"
(cd tools/shader-builder && cargo test --release --locked)

echo "== 3/4 workspace tests on $DRAPE_DEVICE with validation"
cargo test --workspace --locked

echo "== 4/4 the engine's GPU tests through staging buffers (DRAPE_FORCE_STAGING=1)"
# --workspace, not -p: the same feature unification as step 3, so this reuses its
# build instead of compiling every dependency a second time. The filters pick the
# modules of the two GPU test binaries (engine: tests/tests/engine, trainer:
# trainer/tests/trainer) that move buffers between host and device.
DRAPE_FORCE_STAGING=1 cargo test --workspace --locked --test engine --test trainer -- \
    runtime:: scan:: sort:: splat_gpu:: splat_robustness:: splat_gradients:: nn:: ssim:: sizes:: \
    composite:: skinning::
