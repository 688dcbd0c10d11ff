#!/usr/bin/env bash
# The PyTorch (CPU) reference the tests compare the neural ops against: a virtual
# environment at target/torch-venv with pinned torch, numpy and pytorch-msssim. The
# torch package from PyPI brings its CUDA libraries (about 5 GB; the venv is ~7 GB);
# it runs on the CPU. Made once (about 2 minutes) and reused: a stamp file records
# what was installed, and a rerun with the same stamp does nothing.
# Prints the environment's python as its last line on stdout:
#   PY=$(scripts/torch-env.sh | tail -1)
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
venv="$root/target/torch-venv"
py="$venv/bin/python"
requirements="torch==2.9.1 numpy==2.1.3 pytorch-msssim==1.0.0"
stamp="$venv/.drape-stamp"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$requirements" ] && [ -x "$py" ]; then
    echo "torch-env: ready at $py" >&2
    echo "$py"
    exit 0
fi
echo "torch-env: installing $requirements into $venv (once; about 5 GB to download)" >&2
start=$SECONDS
rm -rf "$venv"
python3 -m venv "$venv"
# No cache: the wheels would double the disk used, and the venv itself is the cache.
"$py" -m pip install -q --disable-pip-version-check --no-cache-dir $requirements >&2
"$py" -c "import torch, numpy, pytorch_msssim" >&2
echo "$requirements" > "$stamp"
echo "torch-env: installed in $((SECONDS - start)) s ($(du -sh "$venv" | cut -f1))" >&2
echo "torch-env: ready at $py" >&2
echo "$py"
